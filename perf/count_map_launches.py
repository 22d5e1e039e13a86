"""Warp launches of a warm 30-source ``rw.psf_map`` (issue 25's target: <= 60), by kernel name and batch.

The map: ``a489_doe`` (A489 + its DOE), fields 0..10 deg (10, evenly spaced) x 0.45 / 0.55 / 0.65 um, 32 px,
CPU, ``method="auto"``, everything else psf_map's defaults; called twice through one :class:`rwwarp.PlanCache`,
the second call's launches counted (``warp.launch`` wrapped; every thread).

    python perf/count_map_launches.py [--save PSFS.npz] [--compare PSFS.npz] [--json OUT.json] [--time N]
        [--max-bytes B] [--machine WORDS]

``--save``: the second call's PSFs (``data``, shape (10, 3, 32, 32)) to an .npz; ``--compare``: the largest
difference from such a file (relative to each PSF's peak); ``--time N``: N further warm calls timed (wall and
process CPU s each); ``--max-bytes``: the cache's bound.
"""
from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import rwwarp as rw  # noqa: E402

FIELDS = [float(f) for f in np.linspace(0.0, 10.0, 10)]
WLS = [0.45, 0.55, 0.65]
SIZE = 32


def count_launches(call):
    """``(counts, result)``: ``Counter`` of kernel names of the ``warp.launch`` calls ``call()`` makes, and its
    result."""
    import warp as wp
    orig, counts, lock = wp.launch, Counter(), threading.Lock()

    def counted(kernel, *a, **k):
        with lock:
            counts[getattr(kernel, "key", str(kernel))] += 1
        return orig(kernel, *a, **k)
    wp.launch = counted
    try:
        out = call()
    finally:
        wp.launch = orig
    return counts, out


def the_map(cache, **kw):
    """The issue's map through ``cache`` (a :class:`rwwarp.PlanCache`)."""
    lens = rw.load_lens("a489_doe")
    return rw.psf_map(lens, FIELDS, WLS, size=SIZE, cache=cache, **kw)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--save")
    p.add_argument("--compare")
    p.add_argument("--json")
    p.add_argument("--time", type=int, default=0)
    p.add_argument("--max-bytes", type=int, help="the PlanCache's max_bytes (default its own, 1 GiB)")
    p.add_argument("--machine", default="2-core CPU", help="the machine, in words, for --json")
    args = p.parse_args(argv)
    import warnings
    warnings.simplefilter("ignore")
    cache = rw.PlanCache() if args.max_bytes is None else rw.PlanCache(max_bytes=args.max_bytes)
    t0 = time.perf_counter()
    first = the_map(cache)
    t_first = time.perf_counter() - t0
    t0 = time.perf_counter()
    counts, m = count_launches(lambda: the_map(cache))
    t_second = time.perf_counter() - t0
    n = sum(counts.values())
    print(f"first call {t_first:.2f} s, second call {t_second:.2f} s ({m.info.get('cache')})")
    print(f"batches: {len(m.info['batches'])} sizes {[len(b['pairs']) for b in m.info['batches']]}")
    print(f"Warp launches of the second call: {n}")
    for name, c in counts.most_common():
        print(f"  {c:5d}  {name}")
    assert np.array_equal(first.data, m.data), "first and second call differ"
    if args.save:
        np.savez(args.save, data=m.data)
    if args.compare:
        ref = np.load(args.compare)["data"]
        peak = np.abs(ref).max(axis=(-2, -1), keepdims=True)
        d = np.abs(m.data - ref) / peak
        print(f"vs {args.compare}: bit-identical {np.array_equal(m.data, ref)}, max |diff| / peak {d.max():.3e}")
    times, cpu = [], []
    for _ in range(args.time):
        t0, c0 = time.perf_counter(), time.process_time()
        the_map(cache)
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    if times:
        print(f"warm calls: wall {[round(t, 3) for t in times]} cpu {[round(t, 3) for t in cpu]}")
    if args.json:
        import subprocess
        root = Path(rw.__file__).resolve().parents[1]
        commit = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"], capture_output=True,
                                text=True).stdout.strip()
        Path(args.json).write_text(json.dumps({
            "commit": commit, "machine": args.machine, "lens": "a489_doe", "fields_deg": FIELDS,
            "wavelengths_um": WLS, "size_px": SIZE, "device": "cpu", "cache": m.info.get("cache"),
            "launches_second_call": n, "by_kernel": dict(counts),
            "batches": [len(b["pairs"]) for b in m.info["batches"]], "warm_wall_s": times, "warm_cpu_s": cpu},
            indent=1))


if __name__ == "__main__":
    main()
