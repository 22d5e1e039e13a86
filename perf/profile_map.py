"""Where a PSF map's time goes, cold (first call: FFT plans, transfer functions, builds) and warm.

    python perf/profile_map.py [cuda] [--grid 10] [--batch 6]
"""
import argparse
import cProfile
import pstats
import time
import os

os.environ.setdefault("RWWARP_PLAN_CACHE", "0")   # time the planned call, not rw.psf's default cache (perf/_common.py)

import numpy as np

import rwwarp as rw


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("device", nargs="?", default="cpu")
    ap.add_argument("--grid", type=int, default=10)
    ap.add_argument("--batch", type=int, default=6)
    ap.add_argument("--top", type=int, default=25)
    a = ap.parse_args()
    lens = rw.load_lens("a489_doe")
    u = np.linspace(-0.9, 0.9, a.grid) * 10.0
    fields = [(float(x), float(y)) for y in u for x in u]
    wls = [0.45, 0.55, 0.65]
    rw.psf(lens, 0.0, 0.55, device=a.device)  # kernel builds
    for label in ("cold", "warm"):
        pr = cProfile.Profile()
        t0 = time.perf_counter()
        pr.enable()
        rw.psf_map(lens, fields, wls, device=a.device, batch=a.batch)
        pr.disable()
        print(f"== {label}: {time.perf_counter() - t0:.2f} s for {len(fields) * len(wls)} PSFs")
        pstats.Stats(pr).sort_stats("tottime").print_stats(a.top)
        if label == "cold":
            pstats.Stats(pr).sort_stats("cumulative").print_stats(a.top)


if __name__ == "__main__":
    main()
