"""Planning time of the A489 + DOE map (``rw.load_lens("a489_doe")``, ``--grid`` x ``--grid`` fields over +-9 deg x
0.45 / 0.55 / 0.65 um, ``--size`` px of the sensor's pixel, as psf_map's defaults):
:func:`rwwarp.wave.packed.source_plans` as :func:`rwwarp.psf_map` calls it (the pilot trace, every source's
plan, warm: kernels built, the model-error memo filled), ms per source (least process CPU time and least wall
time of ``--runs`` calls), and with ``--profile`` a cProfile of one call (by tottime and cumtime). ``--map-runs
N``: the warm map's PSF/s (least of N calls). ``--save PATH``: the map's PSFs (``rw.psf_map``, same options,
``--precision``) to an .npy, ``--transfer PATH``: every plan's fitted quadratic transfer (g, q), to compare
trees.

    PYTHONPATH=. python perf/tools/time_map_plan.py [--grid 10] [--runs 5] [--profile] [--save /tmp/map.npy]
"""
import argparse
import cProfile
import pstats
import time
import warnings

import numpy as np

import rwwarp as rw
from rwwarp.map_run import map_args
from rwwarp.wave.packed import source_plans


def setup(grid, size=64):
    """(lens, fields (list of (x, y) deg), wavelengths um, MapArgs) of the map."""
    lens = rw.load_lens("a489_doe")
    u = np.linspace(-0.9, 0.9, grid) * 10.0
    fields = [(float(x), float(y)) for y in u for x in u]
    wls = [0.45, 0.55, 0.65]
    return lens, fields, wls, map_args(lens, fields, wls, size=size)


def _timed(fn):
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--grid", type=int, default=10)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--profile", action="store_true")
    ap.add_argument("--top", type=int, default=30)
    ap.add_argument("--save", default=None)
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--precision", default="auto", help="psf_map's focal_precision for --save (auto: single on CPU)")
    ap.add_argument("--transfer", default=None, help="save every plan's fitted (g, q) (S, 2, 2) to this .npy")
    ap.add_argument("--map-runs", type=int, default=0, help="also time this many warm psf_map calls (PSF/s)")
    a = ap.parse_args()
    warnings.simplefilter("ignore")
    lens, fields, wls, ma = setup(a.grid, a.size)
    F = [f for f in fields for _ in wls]
    W = [w for _ in fields for w in wls]
    n = len(F)

    def plan():
        return source_plans(lens, F, W, a.size, ma.pixel, **ma.opts)
    plan()   # kernel builds, memo
    if a.save:
        m = rw.psf_map(lens, fields, wls, size=a.size, device="cpu", focal_precision=a.precision)
        np.save(a.save, np.asarray(m.data))
        print("saved", a.save, np.asarray(m.data).shape)
    if a.transfer:
        tq = [np.stack(p.focal["transfer"])[:, 0] for p in plan()]
        np.save(a.transfer, np.array(tq))
        print("saved", a.transfer)
    wall, cpu = [], []
    for _ in range(a.runs):
        t0, c0 = time.perf_counter(), time.process_time()
        plan()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    print(f"planning {n} sources: process CPU {min(cpu) / n * 1e3:.3f} ms/source (median "
          f"{sorted(cpu)[len(cpu) // 2] / n * 1e3:.3f}), wall {min(wall) / n * 1e3:.3f} ms/source", flush=True)
    if a.map_runs:
        rw.psf_map(lens, fields, wls, size=a.size, device="cpu")   # warm: FFT plans, operators
        best = min(_timed(lambda: rw.psf_map(lens, fields, wls, size=a.size, device="cpu")) for _ in range(a.map_runs))
        print(f"warm psf_map {a.grid}x{a.grid}x{len(wls)} at {a.size} px: {best:.2f} s (least of {a.map_runs}), "
              f"{n / best:.1f} PSF/s", flush=True)
    if a.profile:
        pr = cProfile.Profile()
        pr.enable()
        plan()
        pr.disable()
        st = pstats.Stats(pr)
        st.sort_stats("tottime").print_stats(a.top)
        st.sort_stats("cumulative").print_stats(a.top)


if __name__ == "__main__":
    main()
