"""The pixel method at the issue's size (issue 27 item 5): DeepLens camera lenses at their own pixel (15.3 um), 64 px.

For one lens and field: the plan of each sensor-field form ("debye", "kirchhoff": ``rwwarp.wave.pixel_scale.FIELD_FORM``,
"kirchhoff" on the tiles near the spot as ``KIRCHHOFF_NEAR``; "kirchhoff-all": on every tile)
with its estimate (GiB, GFLOP, the NUFFTs' share), the run's wall and CPU time and peak RSS, and the accuracy where the
full computation can be run: on the central ``--sub`` pixels (the focal method at 9x finer pixels, box-summed, the
same centre), and the two forms' difference by distance from the centre (where the Kirchhoff form is needed).

    python perf/pixel_64.py [--lens camera__ef35mm_f2.0] [--field 0] [--size 64] [--sub 9] [--forms debye,kirchhoff,...]

Each form runs in its own process (peak RSS per form). Lengths in mm (um where named); results printed as JSON lines
and the arrays saved under ``--out`` (default /tmp/pixel_64).
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


def _one(a):
    """One form in this process: plan, run, save; prints a JSON line."""
    import resource
    import rwwarp as rw
    import rwwarp.wave.pixel_scale as ps
    from rwwarp.io import load_lens
    lens = load_lens(str(DEEPLENS / f"{a.lens}.json"))
    ps.FIELD_FORM = a.form.split("-")[0]
    ps.KIRCHHOFF_NEAR = a.form != "kirchhoff-all"       # "kirchhoff-all": the Kirchhoff form on every tile
    pl = rw.plan_psf(lens, a.field, 0.55, size=a.size, pixel_mm=a.pixel_um * 1e-3, method="pixel")
    t, c = time.time(), time.process_time()
    psf = rw.psf(lens, a.field, 0.55, size=a.size, pixel_mm=a.pixel_um * 1e-3, method="pixel")
    rec = {"lens": a.lens, "field": a.field, "size": a.size, "form": a.form, "wall_s": time.time() - t,
           "cpu_s": time.process_time() - c, "peak_rss_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20,
           "estimate_gib": pl.estimate["memory_bytes"] / 2 ** 30, "estimate_gflop": pl.estimate["flops"] / 1e9,
           "nufft_gflop": pl.estimate["nufft_flops"] / 1e9, "pixel_field": pl.pixel_field}
    out = Path(a.out)
    np.save(out / f"{a.lens}_{a.field:g}_{a.form}_{a.size}.npy", psf.data)
    np.save(out / f"{a.lens}_{a.field:g}_center.npy", np.asarray(psf.center_mm))
    print(json.dumps(rec), flush=True)


def _reference(a):
    """The full computation on the central ``a.sub`` pixels (focal, 9x finer, box-summed), the same centre."""
    import rwwarp as rw
    from rwwarp.io import load_lens
    lens = load_lens(str(DEEPLENS / f"{a.lens}.json"))
    c = tuple(np.load(Path(a.out) / f"{a.lens}_{a.field:g}_center.npy"))
    p = a.pixel_um * 1e-3
    t = time.process_time()
    fine = rw.psf(lens, a.field, 0.55, size=a.sub * 9, pixel_mm=p / 9, method="focal", center_mm=c)
    print(json.dumps({"reference": "focal", "sub": a.sub, "cpu_s": time.process_time() - t}), flush=True)
    return fine.data.reshape(a.sub, 9, a.sub, 9).sum(axis=(1, 3))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--lens", default="camera__ef35mm_f2.0")
    ap.add_argument("--field", type=float, default=0.0)
    ap.add_argument("--pixel-um", type=float, default=15.3)
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--sub", type=int, default=9)
    ap.add_argument("--forms", default="debye,kirchhoff,kirchhoff-all")
    ap.add_argument("--out", default="/tmp/pixel_64")
    ap.add_argument("--reuse", action="store_true", help="keep a form's saved result (its run not repeated)")
    ap.add_argument("--form", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    Path(a.out).mkdir(parents=True, exist_ok=True)
    if a.form:
        return _one(a)
    forms = a.forms.split(",")
    for f in forms:
        if a.reuse and (Path(a.out) / f"{a.lens}_{a.field:g}_{f}_{a.size}.npy").exists():
            continue
        subprocess.run([sys.executable, __file__, "--lens", a.lens, "--field", str(a.field), "--pixel-um",
                        str(a.pixel_um), "--size", str(a.size), "--out", a.out, "--form", f], check=True)
    data = {f: np.load(Path(a.out) / f"{a.lens}_{a.field:g}_{f}_{a.size}.npy") for f in forms}
    ref = _reference(a)
    lo = a.size // 2 - a.sub // 2          # the 64 px patch's pixel j is centred at (j - size // 2) p
    for f, d in data.items():
        sub = d[lo:lo + a.sub, lo:lo + a.sub]
        print(json.dumps({"form": f, "central_px": a.sub, "max_abs_diff_over_peak": float(np.max(np.abs(sub - ref)) / ref.max())}))
    j = np.arange(a.size) - a.size // 2
    ring = np.maximum(np.abs(j)[:, None], np.abs(j)[None, :])
    last = forms[-1]                      # the others against the last form, by ring (px from the centre, Chebyshev)
    for f in forms[:-1]:
        d = np.abs(data[f] - data[last]) / data[last].max()
        print(json.dumps({"against": last, "form": f, "max": float(d.max()),
                          "by_ring_px": {int(r): float(d[ring == r].max()) for r in range(0, a.size // 2 + 1, 2)}}))


if __name__ == "__main__":
    main()
