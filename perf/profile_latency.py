"""Where one PSF's latency goes on a device: stage timings (synchronised) and a cProfile by own time.

    python perf/profile_latency.py cuda [--lens a489_doe] [--field 0] [--reps 20]
"""
import argparse
import cProfile
import pstats
import time

import numpy as np

import rwwarp as rw
from rwwarp.psf import RayWave


def sync(device):
    if device.startswith("cuda"):
        import warp as wp
        wp.synchronize()
        try:
            import cupy
            cupy.cuda.Device().synchronize()
        except ImportError:
            pass


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("device", nargs="?", default="cpu")
    ap.add_argument("--lens", default="a489_doe")
    ap.add_argument("--field", type=float, default=0.0)
    ap.add_argument("--wl", type=float, default=0.55)
    ap.add_argument("--reps", type=int, default=20)
    a = ap.parse_args()
    lens = rw.load_lens(a.lens)
    for _ in range(3):
        rw.psf(lens, a.field, a.wl, device=a.device)
    sync(a.device)
    t = []
    for _ in range(a.reps):
        t0 = time.perf_counter()
        rw.psf(lens, a.field, a.wl, device=a.device)
        sync(a.device)
        t.append(time.perf_counter() - t0)
    print(f"rw.psf median {1e3 * np.median(t):.2f} ms, min {1e3 * np.min(t):.2f} ms over {a.reps}")
    # stages
    stages = {"init": [], "field": [], "intensity": []}
    for _ in range(a.reps):
        t0 = time.perf_counter()
        r = RayWave(lens, [(0.0, a.field)], [a.wl], 64, lens.sensor.pixel_pitch, device=a.device)
        sync(a.device)
        t1 = time.perf_counter()
        u = r.field_array()
        sync(a.device)
        t2 = time.perf_counter()
        phi0, scale = r.doe_phase()
        r.intensity(u, phi0, scale)
        sync(a.device)
        t3 = time.perf_counter()
        stages["init"].append(t1 - t0)
        stages["field"].append(t2 - t1)
        stages["intensity"].append(t3 - t2)
    print("stages (median ms): " + ", ".join(f"{k} {1e3 * np.median(v):.2f}" for k, v in stages.items()))
    pr = cProfile.Profile()
    pr.enable()
    for _ in range(5):
        rw.psf(lens, a.field, a.wl, device=a.device)
    sync(a.device)
    pr.disable()
    pstats.Stats(pr).sort_stats("tottime").print_stats(30)


if __name__ == "__main__":
    main()
