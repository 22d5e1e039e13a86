"""Warm repeats of the 10 x 10 x 3 A489 + DOE map at 32 px (perf/bench_map.py's fields, wavelengths and size) in one
process of the tree on PYTHONPATH: one cold map, then ``--repeats`` warm maps, each timed (wall and process CPU),
host RSS peak, the planned rays and wave-plane samples. ``--tolerance``: psf_map's. For min-of-N timing on a machine shared with other jobs (run from the tree's root).

    PYTHONPATH=TREE python perf/tools/map_warm_repeats.py --batch 9 --repeats 2 --out x.json
"""
import argparse, json, os, resource, subprocess, sys, time, warnings

sys.path.insert(0, os.path.join(os.getcwd(), "perf"))
warnings.simplefilter("ignore")
import numpy as np
import rwwarp as rw
from bench_map import WLS, field_grid

ap = argparse.ArgumentParser()
ap.add_argument("--batch", type=int, default=9, help="0: psf_map's default")
ap.add_argument("--repeats", type=int, default=2)
ap.add_argument("--grid", type=int, default=10)
ap.add_argument("--tolerance", type=float, default=None,
                help="psf_map's tolerance (max |error| / peak the caller accepts); default None")
ap.add_argument("--out", required=True)
a = ap.parse_args()
lens = rw.load_lens("a489_doe")
fields, _ = field_grid(a.grid, lens)
batch = a.batch or None
t0 = time.perf_counter()
m = rw.psf_map(lens, fields, WLS, size=32, batch=batch, tolerance=a.tolerance)
cold = time.perf_counter() - t0
runs = []
for _ in range(a.repeats):
    w0, c0, l0 = time.perf_counter(), time.process_time(), os.getloadavg()[0]
    m = rw.psf_map(lens, fields, WLS, size=32, batch=batch, tolerance=a.tolerance)
    runs.append({"wall_s": time.perf_counter() - w0, "cpu_s": time.process_time() - c0, "load_start": l0,
                 "load_end": os.getloadavg()[0]})
commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
plans = [p if isinstance(p, dict) else p.to_dict() for b in m.info["batches"] for p in b["plans"]]
out = {"commit": commit, "batch": batch, "tolerance": a.tolerance,
       "wave_plane_samples": int(sum(p["n_grid"] ** 2 for p in plans)), "rays": int(sum(p["ray_grid"] ** 2 for p in plans)),
       "wave_steps": int(sum(1 for p in plans if p.get("wave_step_mm"))), "grid": [a.grid, a.grid], "size_px": 32, "n_psfs": a.grid * a.grid * 3,
       "n_batches": len(m.info["batches"]), "cold_s": cold, "warm": runs,
       "min_warm_s": min((r["wall_s"] for r in runs), default=None),
       "median_warm_s": float(np.median([r["wall_s"] for r in runs])) if runs else None,
       "max_rss_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
       "patch_power_mean": float(m.data.sum(axis=(2, 3)).mean())}
np.save(a.out[:-5] + ".npy", m.data)
json.dump(out, open(a.out, "w"), indent=1)
print(f"{commit} batch {batch}: cold {cold:.1f} s, warm " + " / ".join(f"{r['wall_s']:.1f}" for r in runs)
      + f" s, {out['rays'] / 1e6:.3g} M rays, {out['wave_plane_samples'] / 1e6:.4g} M samples, max RSS {out['max_rss_bytes'] / 2 ** 30:.2f} GiB")
