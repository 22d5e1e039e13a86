"""Focal propagation against the band-limited ASM: time, peak memory and error against independent truth.

    .venv/bin/python perf/bench_focal.py [--quick] [--out perf/results/focal_cpu.json]

* Cases (64 px PSFs, each in a fresh process so the peak RSS is the whole process's): the bundled Cooke
  triplet on axis and at 14 deg, the AC254-100-A doublet (25 mm EPD), the A489 + DOE.
  Warm time is the second call in the process.
* Error: relative L2 against ``rwwarp.ground_truth.rs_lens_psf`` (traced rays, exact RS kernel, direct sum)
  on a smaller patch (``--truth-size``, default 24 px: the truth's cost grows with patch^2 x pupil nodes).
* The README's 3 x 3 Cooke map (fields 0/7/14 x 3 wavelengths, 64 px).
* Cost against EPD (2, 5, 10, 20 mm) on the Cooke triplet for both paths: the focal path measured, the ASM
  path measured where its plan fits in 2 GiB and otherwise its planned memory and work (the planner's
  estimate, which the memory budget uses); plotted to ``perf/results/focal_cost_vs_epd.png``.
"""
import argparse
import json
import os
import subprocess
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)

CASE = r'''
import json, resource, sys, time
import numpy as np
import rwwarp as rw
name, field, wl, size, method, epd = sys.argv[1], float(sys.argv[2]), float(sys.argv[3]), int(sys.argv[4]), sys.argv[5], sys.argv[6]
lens = rw.load_lens(name)
if epd != "none":
    lens.entrance_pupil_diameter = float(epd)
t = time.perf_counter(); p = rw.psf(lens, field, wl, size=size, method=method, memory_budget_gb=20); cold = time.perf_counter() - t
t = time.perf_counter(); p = rw.psf(lens, field, wl, size=size, method=method, memory_budget_gb=20); warm = time.perf_counter() - t
print(json.dumps({"cold_s": cold, "warm_s": warm, "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                  "plan": {k: p.plan[k] for k in ("method", "pitch_mm", "n_grid", "n_pad", "ray_grid", "n_sensor", "n_sensor_fft", "estimate")},
                  "sum": float(p.data.sum())}))
'''


def run_case(name, field, wl, size, method, epd=None):
    out = subprocess.run([sys.executable, "-c", CASE, name, str(field), str(wl), str(size), method,
                          "none" if epd is None else str(epd)], capture_output=True, text=True, cwd=ROOT)
    if out.returncode != 0:
        return {"error": out.stderr.strip().splitlines()[-1] if out.stderr else f"exit {out.returncode}"}
    return json.loads(out.stdout.strip().splitlines()[-1])


def truth_error(name, field, wl, size, **kw):
    import rwwarp as rw
    from rwwarp.ground_truth import rs_lens_psf
    lens = rw.load_lens(name)
    p = rw.psf(lens, field, wl, size=size, **kw)
    t = time.perf_counter()
    g = rs_lens_psf(lens, field, wl, p.center_mm, size, p.pixel_mm, radial_nodes=32, angular_nodes=128)
    return {"rel_l2": float(np.linalg.norm(p.data - g) / np.linalg.norm(g)), "truth_s": time.perf_counter() - t,
            "size": size}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="skip the truth errors and the EPD sweep's ASM runs")
    ap.add_argument("--truth-size", type=int, default=24)
    ap.add_argument("--out", default=os.path.join(HERE, "results", "focal_cpu.json"))
    a = ap.parse_args()
    commit = __import__("_common").git_commit()   # $RWWARP_COMMIT on a copied tree
    res = {"commit": commit, "machine": f"{os.cpu_count()} CPU cores (Warp CPU + PoCL)", "cases": {}, "epd": []}
    cases = [("cooke_triplet", 0.0, 0.5876), ("cooke_triplet", 14.0, 0.5876), ("ac254_100_a", 0.0, 0.5876),
             ("a489_doe", 0.0, 0.55)]
    for name, field, wl in cases:
        key = f"{name}@{field:g}deg"
        r = run_case(name, field, wl, 64, "focal")
        if not a.quick and name != "a489_doe":
            r["truth"] = truth_error(name, field, wl, a.truth_size)
        res["cases"][key] = r
        print(key, json.dumps(r)[:300], flush=True)
    # the README's 3 x 3 map
    mapcode = ("import time, resource, rwwarp as rw; L = rw.load_lens('cooke_triplet'); "
               "rw.psf_map(L, fields=[0, 7, 14], wavelengths_um=[0.45, 0.55, 0.65], size=64); "
               "t = time.perf_counter(); rw.psf_map(L, fields=[0, 7, 14], wavelengths_um=[0.45, 0.55, 0.65], size=64); "
               "print(time.perf_counter() - t, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)")
    out = subprocess.run([sys.executable, "-c", mapcode], capture_output=True, text=True, cwd=ROOT)
    t_map, rss_map = (float(v) for v in out.stdout.split()[-2:])
    res["cooke_map_3x3"] = {"warm_s": t_map, "rss_mb": rss_map}
    print("3x3 map", res["cooke_map_3x3"], flush=True)
    # cost against EPD
    import rwwarp as rw
    from rwwarp.psf import RayWave
    for epd in (2.0, 5.0, 10.0, 20.0):
        row = {"epd_mm": epd}
        lens = rw.load_lens("cooke_triplet")
        lens.entrance_pupil_diameter = epd
        for method in ("focal", "asm"):
            rwm = RayWave(lens, [0.0], [0.5876], 64, lens.sensor.pixel_pitch, method=method)
            est = rwm.plan.estimate
            row[method] = {"planned_gib": est["memory_bytes"] / 2 ** 30, "planned_gflop": est["flops"] / 1e9,
                           "n_grid": rwm.plan.n_grid}
            if method == "focal" or (not a.quick and est["memory_bytes"] < 2 * 2 ** 30):
                m = run_case("cooke_triplet", 0.0, 0.5876, 64, method, epd)
                row[method].update({k: m.get(k) for k in ("warm_s", "rss_mb")})
        res["epd"].append(row)
        print("epd", json.dumps(row), flush=True)
    os.makedirs(os.path.dirname(a.out), exist_ok=True)
    with open(a.out, "w") as fh:
        json.dump(res, fh, indent=1)
    plot(res, os.path.join(HERE, "results", "focal_cost_vs_epd.png"))


def plot(res, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    epd = [r["epd_mm"] for r in res["epd"]]
    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    for method, c in (("focal", "C0"), ("asm", "C3")):
        ax[0].loglog(epd, [r[method]["planned_gib"] for r in res["epd"]], "o-", color=c, label=f"{method} (planned)")
        ax[1].loglog(epd, [r[method]["planned_gflop"] for r in res["epd"]], "o-", color=c, label=f"{method} (planned)")
        meas = [(r["epd_mm"], r[method].get("warm_s")) for r in res["epd"] if r[method].get("warm_s")]
        if meas:
            ax[1].loglog(*zip(*[(e, t * 10) for e, t in meas]), "x--", color=c, label=f"{method}: measured s x 10")
    ax[0].set(xlabel="entrance pupil diameter (mm)", ylabel="peak memory of the plan (GiB)",
              title="Cooke triplet, 64 px PSF on axis")
    ax[1].set(xlabel="entrance pupil diameter (mm)", ylabel="work (GFLOP) / measured time (s x 10)",
              title=f"2-core CPU, commit {res['commit']}")
    for a_ in ax:
        a_.grid(True, which="both", alpha=0.3)
        a_.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    main()
