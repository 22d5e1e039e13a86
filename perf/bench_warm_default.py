"""Warm plain ``rw.psf`` calls (no ``cache`` argument: what a user's repeated call does) of one configuration, for
timing two trees in turn (issue 25). Imports the ``rwwarp`` on ``PYTHONPATH``; prints one JSON line: the median and
least wall time of the warm calls (ms; the first ``--warmup`` calls, which build kernels and fill any cache, are not
counted), the Warp launches of one more warm call, the tree imported.

    PYTHONPATH=TREE python perf/bench_warm_default.py a489_doe 0 8 0.1 --reps 40
    python perf/bench_warm_default.py cooke_triplet 14 64 1 --device cuda [--uncached]   # issue 25's sizes on a GPU

``LENS`` is a bundled lens name or ``thin_doe_asm`` (perf/bench_warm_psf.py's thin lens + DOE, 16 px ASM: kernels
nearly free, so its time is the host's). Lengths mm, field deg, wavelength 0.55 um.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("lens")
    ap.add_argument("field", type=float)
    ap.add_argument("size", type=int)
    ap.add_argument("rays_per_sample", type=float)
    ap.add_argument("--reps", type=int, default=20)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--uncached", action="store_true", help="pass cache=None (plan every call)")
    ap.add_argument("--device", default="cpu", help="rwwarp device (cpu, cuda, ...)")
    a = ap.parse_args(argv)
    import rwwarp as rw
    from bench_warm_psf import counts, thin_doe_lens
    warnings.simplefilter("ignore")
    lens = thin_doe_lens(rw) if a.lens == "thin_doe_asm" else rw.load_lens(a.lens)
    kw = dict(size=a.size, rays_per_sample=a.rays_per_sample, method="asm" if a.lens == "thin_doe_asm" else "auto",
              device=a.device)
    if a.uncached:
        kw["cache"] = None
    for _ in range(a.warmup):
        p = rw.psf(lens, a.field, 0.55, **kw)
    t = []
    for _ in range(a.reps):   # a call returns host arrays: the device's work is inside its time
        t0 = time.perf_counter()
        p = rw.psf(lens, a.field, 0.55, **kw)
        t.append(time.perf_counter() - t0)
    c = counts(lambda: rw.psf(lens, a.field, 0.55, **kw))
    print(json.dumps({"lens": a.lens, "field_deg": a.field, "size": a.size, "rays_per_sample": a.rays_per_sample,
                      "uncached": a.uncached, "median_ms": 1e3 * float(np.median(t)), "min_ms": 1e3 * float(np.min(t)),
                      "reps": a.reps, "device": a.device, "cache": p.info.get("cache"), "method": (p.plan or {}).get("method"), **c,
                      "rwwarp": str(Path(rw.__file__).resolve().parent)}), flush=True)


if __name__ == "__main__":
    sys.exit(main())
