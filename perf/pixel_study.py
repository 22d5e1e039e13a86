"""Which knob the error of ``method="pixel"`` follows (issue 27 item 5): a study against the full computation.

For one case (lens, field, pixel, patch) the pixel method's max |difference| over the peak against the full
computation (the focal method at a ``k`` x finer pixel, box-summed ``k x k``, as ``perf/pixel_scale.py``), with
one knob changed at a time on either side:

* the reference: ``focal_precision="double"``, ``k = 15`` (the box sum's own convergence), ``nyquist_safety=3``
  (its wave-plane sampling), ``rays_per_sample=2``, a larger patch (``size + 2``, ``size + 4``: its window);
* the pixel method: ``rays_per_sample=2`` (rays across), ``GRID_MARGIN`` (the Nyquist rate's safety factor),
  ``NUFFT_SPREAD`` (the gridding kernel's width), ``TILE`` (tile size), ``RAY_SAFETY``.

Each row prints the error against the reference and the change of the changed side against its base (how far
that knob moves it), and the time.

    python perf/pixel_study.py [--lens camera__ef35mm_f2.0] [--field 0] [--pixel-um 15.3] [--size 5] [--form debye]
    python perf/pixel_study.py --lens cooke_triplet --field 14 --pixel-um 10 --size 9

``--form``: the pixel method's sensor-field form (``rwwarp.wave.pixel_scale.FIELD_FORM``: "debye", the form the
study in docs/propagation.md "What the error follows" is of; "kirchhoff"; "auto"). Lengths in mm (um where named),
times in s on this machine.
"""
from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path
import os

os.environ.setdefault("RWWARP_PLAN_CACHE", "0")   # time the planned call, not rw.psf's default cache (perf/_common.py)

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
DEEPLENS = ROOT / "tests/data/third_party/files/DeepLens"


def _lens(name):
    from rwwarp.io import load_lens
    return load_lens(str(DEEPLENS / f"{name}.json") if name.startswith("camera") else name)


def _pix(name, fld, p, size, center=None, **kw):
    """The pixel method with module constants (upper-case keys) set for the call."""
    import rwwarp as rw
    import rwwarp.wave.pixel_scale as ps
    consts = {k: kw.pop(k) for k in list(kw) if k.isupper()}
    old = {k: getattr(ps, k) for k in consts}
    for k, v in consts.items():
        setattr(ps, k, v)
    try:
        t = time.perf_counter()
        a = rw.psf(_lens(name), fld, 0.55, size=size, pixel_mm=p, method="pixel", center_mm=center, **kw)
        return a, time.perf_counter() - t
    finally:
        for k, v in old.items():
            setattr(ps, k, v)


def _full(name, fld, p, size, center, k=9, **kw):
    import rwwarp as rw
    t = time.perf_counter()
    b = rw.psf(_lens(name), fld, 0.55, size=size * k, pixel_mm=p / k, method="focal", center_mm=center,
               memory_budget_gb=8, **kw)
    return b.data.reshape(size, k, size, k).sum(axis=(1, 3)), time.perf_counter() - t


def _err(a, b):
    return float(np.max(np.abs(a - b)) / b.max())


def study(name, fld, p, size):
    a0, ta = _pix(name, fld, p, size)
    c = a0.center_mm
    A0 = a0.data
    B0, tb = _full(name, fld, p, size, c)
    print(f"{name} {fld:g} deg, {p * 1e3:g} um, {size} px: pixel rays {a0.plan['ray_grid']}, grid "
          f"{a0.plan['n_sensor']}^2")
    print("| side | knob | error vs reference | change of that side | time (s) |\n|---|---|---|---|---|")
    print(f"| both | base | {_err(A0, B0):.3g} | - | {ta:.1f} / {tb:.1f} |", flush=True)
    for lab, kw in (("focal_precision double", {"focal_precision": "double"}), ("k = 15", {"k": 15}),
                    ("nyquist_safety 3", {"nyquist_safety": 3.0}), ("rays_per_sample 2", {"rays_per_sample": 2.0})):
        B, t = _full(name, fld, p, size, c, **kw)
        print(f"| reference | {lab} | {_err(A0, B):.3g} | {_err(B, B0):.3g} | {t:.1f} |", flush=True)
    for extra in (2, 4):
        s = size + extra
        B, t = _full(name, fld, p, s, c)
        a, t2 = _pix(name, fld, p, s, c)
        d = extra // 2
        print(f"| both | patch {s} px (centre {size} px) | {_err(a.data[d:-d, d:-d], B[d:-d, d:-d]):.3g} | ref "
              f"{_err(B[d:-d, d:-d], B0):.3g}, pixel {_err(a.data[d:-d, d:-d], A0):.3g} | {t2:.1f} / {t:.1f} |",
              flush=True)
    for lab, kw in (("rays_per_sample 2", {"rays_per_sample": 2.0}), ("GRID_MARGIN 1.6", {"GRID_MARGIN": 1.6}),
                    ("NUFFT_SPREAD 8", {"NUFFT_SPREAD": 8}), ("TILE 128", {"TILE": 128}),
                    ("RAY_SAFETY 2", {"RAY_SAFETY": 2.0})):
        a, t = _pix(name, fld, p, size, c, **kw)
        print(f"| pixel | {lab} | {_err(a.data, B0):.3g} | {_err(a.data, A0):.3g} | {t:.1f} |", flush=True)
    print("(pixel - reference) / peak x 1e4:")
    print(np.round((A0 - B0) / B0.max() * 1e4, 1))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lens", default="camera__ef35mm_f2.0")
    ap.add_argument("--field", type=float, default=0.0)
    ap.add_argument("--pixel-um", type=float, default=15.3)
    ap.add_argument("--size", type=int, default=5)
    ap.add_argument("--form", default="debye", choices=("debye", "kirchhoff", "auto"))
    a = ap.parse_args()
    warnings.simplefilter("ignore")
    import rwwarp.wave.pixel_scale as ps
    ps.FIELD_FORM = a.form
    study(a.lens, a.field, a.pixel_um * 1e-3, a.size)


if __name__ == "__main__":
    main()
