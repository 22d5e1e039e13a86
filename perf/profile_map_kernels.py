"""Where a warm CPU ``rw.psf_map`` spends its time, by Warp kernel and by Python function (issue 25).

The map: ``a489_doe``, perf/bench_map.py's ``--grid`` x ``--grid`` fields x 0.45 / 0.55 / 0.65 um, ``--size`` px,
object at 10 m. One cold map, then one warm map under cProfile with ``warp.launch`` wrapped: each launch's wall
seconds summed by kernel name, over every thread (on 2 CPU threads the sum can exceed the wall time), and the
calls of ``wp.zeros`` / ``array.zero_``. Seconds of wall time.

    python perf/profile_map_kernels.py [--grid 5] [--size 32] [--batch 9] [--top 25] [--json OUT.json]
"""
from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import sys
import threading
import time
import warnings
from collections import defaultdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))
import rwwarp as rw  # noqa: E402
from bench_map import WLS, field_grid  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--grid", type=int, default=5)
    ap.add_argument("--size", type=int, default=32)
    ap.add_argument("--batch", type=int, default=9, help="0: psf_map's default")
    ap.add_argument("--top", type=int, default=25)
    ap.add_argument("--json")
    a = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    import warp as wp
    lens = rw.load_lens("a489_doe")
    fields, _ = field_grid(a.grid, lens)
    batch = a.batch or None
    rw.psf_map(lens, fields, WLS, size=a.size, batch=batch)   # cold: builds, plans
    secs, calls, lock = defaultdict(float), defaultdict(int), threading.Lock()
    orig_launch, orig_zeros, orig_zero_ = wp.launch, wp.zeros, wp.array.zero_

    def timed(name, fn):
        def f(*x, **k):
            t0 = time.perf_counter()
            try:
                return fn(*x, **k)
            finally:
                key = name(x, k)
                with lock:
                    secs[key] += time.perf_counter() - t0
                    calls[key] += 1
        return f
    wp.launch = timed(lambda x, k: getattr(x[0], "key", str(x[0])), orig_launch)
    wp.zeros = timed(lambda x, k: "wp.zeros", orig_zeros)
    wp.array.zero_ = timed(lambda x, k: "array.zero_", orig_zero_)
    pr = cProfile.Profile()
    t0 = time.perf_counter()
    pr.enable()
    rw.psf_map(lens, fields, WLS, size=a.size, batch=batch)
    pr.disable()
    wall = time.perf_counter() - t0
    wp.launch, wp.zeros, wp.array.zero_ = orig_launch, orig_zeros, orig_zero_
    print(f"== warm map {a.grid}x{a.grid}x{len(WLS)} at {a.size} px, batch {batch}: {wall:.2f} s wall")
    for k in sorted(secs, key=secs.get, reverse=True):
        print(f"  {k:40s} {secs[k]:8.3f} s  {calls[k]:5d} calls")
    pstats.Stats(pr).sort_stats("tottime").print_stats(a.top)
    if a.json:
        json.dump({"wall_s": wall, "grid": a.grid, "size_px": a.size, "batch": batch,
                   "kernels": {k: {"s": secs[k], "calls": calls[k]} for k in secs}}, open(a.json, "w"), indent=1)


if __name__ == "__main__":
    main()
