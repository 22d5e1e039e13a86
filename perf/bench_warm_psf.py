"""Warm ``rw.psf`` time (a repeated call: wall and process CPU time) on small problems, planned every call and through a ``rw.PlanCache`` where
the rwwarp imported has one, with the Warp launches, allocations and device reads of a call (issue 25).

Imports the ``rwwarp`` on ``PYTHONPATH`` (so two trees can be compared in alternating runs):

    PYTHONPATH=OLD_TREE python perf/bench_warm_psf.py --json /tmp/old.json
    PYTHONPATH=. python perf/bench_warm_psf.py --json /tmp/new.json
    python perf/bench_warm_psf.py --merge perf/results/warm_psf_cpu.json /tmp/old_*.json -- /tmp/new_*.json

Small problems (``rays_per_sample`` 0.1, 8 px) keep the kernels short, so the host work shows.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

CONFIGS = [("a489_doe", 0.0, 8, 0.1), ("a489_doe", 10.0, 8, 0.1), ("ac254_100_a", 0.0, 8, 0.1),
           ("cooke_triplet", 0.0, 8, 0.1), ("a489_doe", 0.0, 64, 1.0), ("thin_doe_asm", 0.0, 16, 1.0)]


def thin_doe_lens(rw):
    """tests/rwwarp/test_map.py's small system (aperture 1 mm, ideal f = 50 mm lens, even-polynomial DOE 10 mm before
    the sensor): its 16 px ASM plan (20^2 samples, FFT 40^2, 17^2 rays) leaves the kernels nearly nothing, so its
    time is the host's (launches, uploads, Python)."""
    from rwwarp.lens import Lens, Sensor, Surface
    doe = {"kind": "even_poly", "norm_radius": 0.5, "coefficients": [20.0, -5.0]}
    surfs = [Surface(type="aperture", semi_diameter=0.5, shape="circle", stop=True),
             Surface(type="thin_lens", focal_length=50.0, semi_diameter=1.0, thickness=40.0),
             Surface(type="doe", semi_diameter=1.0, shape="square", thickness=10.0, profile=doe)]
    return Lens(surfs, Sensor(0.55e-3 * 50.0 / 3, (1000, 1000)), wavelengths_um=[0.55])


def counts(call):
    """Warp launches, allocations (empty / zeros) and device reads (``array.numpy``) of ``call()``."""
    import warp as wp
    n = {"launch": 0, "alloc": 0, "numpy": 0}
    saved = {k: getattr(wp, k) for k in ("launch", "empty", "zeros")}

    def wrap(name, key):
        orig = saved[name]

        def f(*a, **k):
            n[key] += 1
            return orig(*a, **k)
        return f
    wp.launch, wp.empty, wp.zeros = wrap("launch", "launch"), wrap("empty", "alloc"), wrap("zeros", "alloc")
    num = wp.array.numpy

    def numpy(a):
        n["numpy"] += 1
        return num(a)
    wp.array.numpy = numpy
    try:
        call()
    finally:
        wp.launch, wp.empty, wp.zeros = saved["launch"], saved["empty"], saved["zeros"]
        wp.array.numpy = num
    return n


def bench(reps):
    import rwwarp as rw
    warnings.simplefilter("ignore")
    rows = []
    for name, field, size, rps in CONFIGS:
        lens = thin_doe_lens(rw) if name == "thin_doe_asm" else rw.load_lens(name)
        method = "asm" if name == "thin_doe_asm" else "auto"
        modes = [("uncached", {"cache": None})]   # (rw.psf's default caches since session 25)
        if hasattr(rw, "PlanCache"):
            modes.append(("cached", {"cache": rw.PlanCache()}))
        for mode, extra in modes:
            kw = dict(size=size, rays_per_sample=rps, method=method, **extra)
            for _ in range(3):
                rw.psf(lens, field, 0.55, **kw)
            n = max(5, reps if size <= 16 else reps // 4)
            t, cpu = [], []
            for _ in range(n):
                t0, c0 = time.perf_counter(), time.process_time()
                rw.psf(lens, field, 0.55, **kw)
                t.append(time.perf_counter() - t0)
                cpu.append(time.process_time() - c0)
            c = counts(lambda: rw.psf(lens, field, 0.55, **kw))
            rows.append({"lens": name, "field_deg": field, "size": size, "rays_per_sample": rps, "mode": mode,
                         "median_ms": 1e3 * float(np.median(t)), "min_ms": 1e3 * float(np.min(t)),
                         "cpu_median_ms": 1e3 * float(np.median(cpu)), "cpu_min_ms": 1e3 * float(np.min(cpu)),
                         "reps": n, **c})
            r = rows[-1]
            print(f"{name:14s} {field:5.1f} deg {size:3d} px rps {rps:g} {mode:8s}: median {r['median_ms']:8.3f} ms, "
                  f"min {r['min_ms']:8.3f} ms, process CPU median {r['cpu_median_ms']:8.3f} ms; {c}", flush=True)
    return {"rwwarp": str(Path(rw.__file__).resolve().parent), "rows": rows}


def merge(out, old, new):
    """Paired table: per config and mode, the medians of the alternating runs of each tree."""
    def load(paths):
        acc = {}
        for p in paths:
            for r in json.loads(Path(p).read_text())["rows"]:
                acc.setdefault((r["lens"], r["field_deg"], r["size"], r["rays_per_sample"], r["mode"]), []).append(r)
        return acc
    o, nw = load(old), load(new)
    table = []
    for key, rs in nw.items():
        base = o.get(key[:4] + ("uncached",), [])
        table.append({"lens": key[0], "field_deg": key[1], "size": key[2], "rays_per_sample": key[3], "mode": key[4],
                      "new_median_ms": [r["median_ms"] for r in rs], "new_min_ms": [r["min_ms"] for r in rs],
                      "before_uncached_median_ms": [r["median_ms"] for r in base],
                      "before_uncached_min_ms": [r["min_ms"] for r in base],
                      "new_cpu_median_ms": [r.get("cpu_median_ms") for r in rs],
                      "before_uncached_cpu_median_ms": [r.get("cpu_median_ms") for r in base],
                      "launches": rs[0]["launch"], "before_launches": base[0]["launch"] if base else None,
                      "allocations": rs[0]["alloc"], "before_allocations": base[0]["alloc"] if base else None,
                      "device_reads": rs[0]["numpy"], "before_device_reads": base[0]["numpy"] if base else None})
        t = table[-1]
        print(f"{key[0]:14s} {key[1]:5.1f} deg {key[2]:3d} px {key[4]:8s}: min of medians new "
              f"{min(t['new_median_ms']):8.3f} ms vs before {min(t['before_uncached_median_ms'] or [np.nan]):8.3f} ms; "
              f"process CPU {min(t['new_cpu_median_ms']):8.3f} vs {min(t['before_uncached_cpu_median_ms'] or [np.nan]):8.3f} ms; "
              f"launches {t['launches']} vs {t['before_launches']}")
    Path(out).write_text(json.dumps({"old": list(old), "new": list(new), "table": table}, indent=1) + "\n")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--reps", type=int, default=20)
    ap.add_argument("--json", default=None)
    ap.add_argument("--merge", nargs="+", default=None, help="OUT OLD.json ... -- NEW.json ...")
    a, rest = ap.parse_known_args(argv)
    if a.merge:
        files = a.merge + rest
        cut = files.index("--")
        return merge(files[0], files[1:cut], files[cut + 1:])
    res = bench(a.reps)
    if a.json:
        Path(a.json).write_text(json.dumps(res, indent=1) + "\n")


if __name__ == "__main__":
    sys.exit(main())
