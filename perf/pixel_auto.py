"""``method="auto"`` and the pixel method on the DeepLens camera lenses at their own pixel (issue 27 item 5).

Two modes, each case (lens x field) in its own process (peak RSS, memory isolation):

* ``--mode errors``: the Kirchhoff form of ``method="pixel"`` (``FIELD_FORM="kirchhoff"``) on a small patch
  (``--sub`` px, every tile Kirchhoff) against the full computation on the same pixels (the focal method at 9x finer
  pixels, box-summed, the same centre): the measured error beside the planner's estimate
  (:func:`rwwarp.wave.pixel_kirchhoff.kirchhoff_error_estimate`), to validate it;
* ``--mode table``: ``rw.psf(..., size=64)`` with ``method="auto"`` at the lens's own pixel: the method and form auto
  chose, planned GFLOP / GiB, wall and CPU time, peak RSS; with ``--ref`` the central ``--sub`` px against the full
  computation there (the 64 px full computation is 1.5-33 TFLOP / 2-27 GiB: not run on this CPU).

    python perf/pixel_auto.py --mode errors [--lenses ef85mm_f1.8,...] [--fields 0,10] [--sub 9]
    python perf/pixel_auto.py --mode table --ref [--json perf/results/pixel_auto_cpu.json]

Prints one JSON line a case; lengths in mm (um where named), 0.55 um.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path
import os

os.environ.setdefault("RWWARP_PLAN_CACHE", "0")   # time the planned call, not rw.psf's default cache (perf/_common.py)

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DEEPLENS = ROOT / "tests/data/third_party/files/DeepLens"
LENSES = ("ef50mm_f1.8", "ef35mm_f2.0", "ef85mm_f1.8", "rf50mm_f1.8", "ef100mm_f2.8", "ef40mm_f2.8", "sigma70mm_f2.8")


def _lens(name):
    from rwwarp.io import load_lens
    return load_lens(str(DEEPLENS / f"camera__{name}.json"))


def _reference(lens, field, p, sub, center, budget_gb=10.0):
    """The full computation on ``sub`` px of ``p`` mm centred at ``center``: focal at 9x finer pixels, box-summed; where
    its plan is over ``budget_gb`` (the 10 deg cases: the wave-plane grid follows the beam's footprint, 6-13 GiB), the
    central 5 px at 3x finer pixels (the box sum of a 9x or 15x finer pixel moved the result by 1.6e-10: the focal
    method integrates each fine pixel with Gauss-Legendre nodes). Returns ``(reference, sub, k)``."""
    import rwwarp as rw
    from rwwarp.wave.plan import MemoryBudgetError
    for s, k in ((sub, 9), (min(sub, 5), 3)):
        try:
            fine = rw.psf(lens, field, 0.55, size=s * k, pixel_mm=p / k, method="focal", center_mm=center,
                          memory_budget_gb=budget_gb)     # not half the memory available at the time: others share it
        except MemoryBudgetError:
            continue
        return fine.data.reshape(s, k, s, k).sum(axis=(1, 3)), s, k
    raise MemoryBudgetError(f"the full computation over {budget_gb} GiB even on 5 px at 3x finer pixels")


def _estimate(plan, what="kirchhoff form: error ~"):
    """The error estimate in the plan's reason that starts with ``what`` ("kirchhoff form: error ~", "debye form: error
    ~", or "pixel method: error ~": the form that runs), None where there is none."""
    for r in plan["reasons"] if isinstance(plan, dict) else plan.reasons:
        if r.startswith(what):
            return float(r[len(what):].split()[0])
    return None


def _one(a):
    import resource
    import warnings
    warnings.simplefilter("ignore")
    import rwwarp as rw
    import rwwarp.wave.pixel_scale as ps
    lens = _lens(a.lens)
    p = float(lens.sensor.pixel_pitch)
    rec = {"lens": a.lens, "field_deg": a.field, "pixel_um": p * 1e3}
    if a.mode == "errors":
        ps.FIELD_FORM = "kirchhoff"
        pl = rw.plan_psf(lens, a.field, 0.55, size=a.sub, method="pixel")
        t = time.time()
        psf = rw.psf(lens, a.field, 0.55, size=a.sub, method="pixel")
        rec.update(size=a.sub, form=pl.pixel_field["form"], wall_s=time.time() - t, rays=pl.ray_grid,
                   estimate=_estimate(pl))
        ref, sub, k = _reference(lens, a.field, p, a.sub, psf.center_mm)
        d = (a.sub - sub) // 2
        rec.update(ref_px=sub, ref_fine=k, measured=float(np.max(np.abs(psf.data[d:d + sub, d:d + sub] - ref)) / ref.max()))
    else:
        pl = rw.plan_psf(lens, a.field, 0.55, size=64)
        t, c = time.time(), time.process_time()
        psf = rw.psf(lens, a.field, 0.55, size=64)
        rec.update(size=64, method=pl.method, form=(pl.pixel_field or {}).get("form"), wall_s=time.time() - t,
                   cpu_s=time.process_time() - c, planned_gflop=pl.estimate["flops"] / 1e9,
                   planned_gib=pl.estimate["memory_bytes"] / 2 ** 30, estimate=_estimate(pl),
                   estimate_debye=_estimate(pl, "debye form: error ~"),
                   estimate_chosen=_estimate(pl, "pixel method: error ~") if pl.method == "pixel" else None,
                   peak_rss_gib=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20,
                   pixel_field={k: v for k, v in (pl.pixel_field or {}).items() if k != "region"},
                   choice=[r for r in pl.reasons if r.startswith("method auto")])
        if a.ref:
            from rwwarp.wave.plan import MemoryBudgetError
            try:
                ref, sub, k = _reference(lens, a.field, p, a.sub, psf.center_mm, a.ref_budget_gb)
                lo = 64 // 2 - sub // 2
                rec.update(ref_px=sub, ref_fine=k,
                           measured=float(np.max(np.abs(psf.data[lo:lo + sub, lo:lo + sub] - ref)) / ref.max()))
            except MemoryBudgetError as e:
                rec.update(measured=None, reference=str(e)[:200])
    print(json.dumps(rec), flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--mode", choices=("errors", "table"), default="table")
    ap.add_argument("--lenses", default=",".join(LENSES))
    ap.add_argument("--fields", default="0,10")
    ap.add_argument("--sub", type=int, default=9)
    ap.add_argument("--ref", action="store_true")
    ap.add_argument("--ref-budget-gb", type=float, default=10.0, help="the full computation's memory budget")
    ap.add_argument("--json", help="write the records here (with the commit and the machine)")
    ap.add_argument("--lens", help=argparse.SUPPRESS)
    ap.add_argument("--field", type=float, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.lens:
        return _one(a)
    recs = []
    for name in a.lenses.split(","):
        for f in a.fields.split(","):
            cmd = [sys.executable, __file__, "--mode", a.mode, "--lens", name, "--field", f, "--sub", str(a.sub),
                   "--ref-budget-gb", str(a.ref_budget_gb)]
            out = subprocess.run(cmd + (["--ref"] if a.ref else []), capture_output=True, text=True)
            line = [s for s in out.stdout.splitlines() if s.startswith("{")]
            rec = json.loads(line[-1]) if line else {"lens": name, "field_deg": float(f), "failed": out.stderr[-800:]}
            print(json.dumps(rec), flush=True)
            recs.append(rec)
    if a.json:
        import platform
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
        cpu = platform.processor() or platform.machine()
        try:
            cpu = [s.split(":", 1)[1].strip() for s in open("/proc/cpuinfo") if s.startswith("model name")][0]
        except (OSError, IndexError):
            pass
        Path(a.json).write_text(json.dumps({"commit": commit, "machine": f"{cpu}, {__import__('os').cpu_count()} "
                                            "cores (shared)", "wavelength_um": 0.55, "records": recs}, indent=1))


if __name__ == "__main__":
    main()
