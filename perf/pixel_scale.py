"""Large pixels (issue 27 item 5): plans of ``method="pixel"`` against the full computation's, and its accuracy.

Plans (pilot traces only, seconds): the DeepLens camera lenses of ``tests/data/third_party`` at a 15.3 um pixel
(the EF50's own), 64 px, 0.55 um, on axis and at 10 deg: the full computation's plan (the fewer-flops one of
focal and ASM, what ``method="auto"`` ran before) and the pixel method's, memory and flops, with the pixel
method's error estimate and what ``"auto"`` now picks at the default tolerance (1e-3).

Accuracy (``--accuracy``): the pixel method against the full computation (the focal method at a 9x finer
pixel, box-summed 9 x 9) where the latter fits this machine: patches of 5 px, so the focal plan stays under
~300 GFLOP.

    python perf/pixel_scale.py [--accuracy] [--out perf/results/pixel_scale_cpu.json]

Lengths in mm (pixels printed in um), memory in GiB (2^30 bytes), work in GFLOP.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path
import os

os.environ.setdefault("RWWARP_PLAN_CACHE", "0")   # time the planned call, not rw.psf's default cache (perf/_common.py)

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
LENSES = ["camera__ef50mm_f1.8", "camera__ef35mm_f2.0", "camera__ef85mm_f1.8", "camera__rf50mm_f1.8",
          "camera__rf24mm_f1.8", "camera__yongnuo_50mm_f1.8"]     # camera__rf35mm_f1.8.json is empty
DEEPLENS = ROOT / "tests/data/third_party/files/DeepLens"


def _err_estimate(plan) -> float:
    line = [r for r in plan.reasons if r.startswith("pixel method: error ~") or "(pixel method: error ~" in r][0]
    return float(line.split("error ~")[1].split()[0])


def plan_rows(pixel_mm=0.0153, size=64, fields=(0.0, 10.0), wl=0.55) -> list:
    import rwwarp as rw
    from rwwarp.io import load_lens
    rows = []
    for name in LENSES:
        lens = load_lens(str(DEEPLENS / f"{name}.json"))
        for fld in fields:
            full = [rw.plan_psf(lens, fld, wl, size=size, pixel_mm=pixel_mm, method=m) for m in ("focal", "asm")]
            full = min(full, key=lambda p: p.estimate["flops"])
            pix = rw.plan_psf(lens, fld, wl, size=size, pixel_mm=pixel_mm, method="pixel")
            auto = rw.plan_psf(lens, fld, wl, size=size, pixel_mm=pixel_mm)
            row = {"lens": name, "field_deg": fld, "pixel_um": pixel_mm * 1e3, "size": size,
                   "full_method": full.method, "full_gib": full.estimate["memory_bytes"] / 2 ** 30,
                   "full_gflop": full.estimate["flops"] / 1e9, "pixel_gib": pix.estimate["memory_bytes"] / 2 ** 30,
                   "pixel_gflop": pix.estimate["flops"] / 1e9, "pixel_rays": pix.ray_grid,
                   "pixel_grid": pix.n_sensor, "pixel_error_estimate": _err_estimate(pix),
                   "auto_picks": auto.method}
            rows.append(row)
            print(f"| {name.replace('camera__', '')} | {fld:g} | {full.method} {row['full_gib']:.3g} GiB, "
                  f"{row['full_gflop']:.4g} GFLOP | {row['pixel_gib']:.3g} GiB, {row['pixel_gflop']:.3g} GFLOP | "
                  f"{row['pixel_error_estimate']:.2g} | {row['auto_picks']} |", flush=True)
    return rows


ACCURACY = (("camera__ef50mm_f1.8", 0.0, 0.0153, 5), ("camera__ef35mm_f2.0", 0.0, 0.0153, 5),
            ("camera__ef35mm_f2.0", 2.0, 0.0153, 5), ("camera__rf50mm_f1.8", 0.0, 0.0153, 5),
            ("camera__rf50mm_f1.8", 2.0, 0.0153, 5))


def accuracy_rows(cases=ACCURACY, k=9, max_gflop=400.0) -> list:
    import rwwarp as rw
    from rwwarp.io import load_lens
    rows = []
    for name, fld, p, size in cases:
        lens = load_lens(str(DEEPLENS / f"{name}.json") if name.startswith("camera") else name)
        t0 = time.perf_counter()
        a = rw.psf(lens, fld, 0.55, size=size, pixel_mm=p, method="pixel")
        ta = time.perf_counter() - t0
        pl = rw.plan_psf(lens, fld, 0.55, size=size * k, pixel_mm=p / k, method="focal", center_mm=a.center_mm)
        if pl.estimate["flops"] > max_gflop * 1e9:
            print(f"{name} {fld:g} deg: the full computation plans {pl.estimate['flops'] / 1e9:.4g} GFLOP: skipped")
            continue
        t0 = time.perf_counter()
        b = rw.psf(lens, fld, 0.55, size=size * k, pixel_mm=p / k, method="focal", center_mm=a.center_mm,
                   memory_budget_gb=8)
        tb = time.perf_counter() - t0
        B = b.data.reshape(size, k, size, k).sum(axis=(1, 3))
        err = float(np.max(np.abs(a.data - B)) / B.max())
        from rwwarp.wave.plan import Plan
        row = {"lens": name, "field_deg": fld, "pixel_um": p * 1e3, "size": size, "error": err,
               "estimate": _err_estimate(Plan(**{**a.plan, "reasons": tuple(a.plan["reasons"])})),
               "pixel_s": ta, "full_s": tb, "full_gflop": pl.estimate["flops"] / 1e9}
        rows.append(row)
        print(f"{name} {fld:g} deg, {p * 1e3:g} um, {size} px: error {err:.3g} of the peak (estimate "
              f"{row['estimate']:.2g}); pixel {ta:.2f} s, full (x{k} finer, focal) {tb:.1f} s", flush=True)
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--accuracy", action="store_true")
    ap.add_argument("--out", default=None, help="JSON file for the rows")
    a = ap.parse_args()
    warnings.simplefilter("ignore")
    print("| lens | field (deg) | full computation (plan) | pixel method (plan) | pixel error estimate | auto picks |")
    print("|---|---|---|---|---|---|")
    out = {"plans": plan_rows()}
    if a.accuracy:
        out["accuracy"] = accuracy_rows()
    if a.out:
        Path(a.out).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
