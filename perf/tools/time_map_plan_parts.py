"""Where the planning of the A489 + DOE map goes, without cProfile's per-call overhead: the wall time of chosen
planning steps (wrapped with a timer, nested steps counted in their callers too), ms per source, least of ``--runs``
warm calls of :func:`rwwarp.wave.packed.source_plans` (``perf/tools/time_map_plan.py``'s setup).

    PYTHONPATH=. python perf/tools/time_map_plan_parts.py [--grid 10] [--runs 5]
"""
import argparse
import importlib
import sys
import time
import warnings
from collections import defaultdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

PARTS = [  # (module, attribute, where it is looked up from by the planner: modules that imported it by name)
    ("rwwarp.wave.pilot", "pilot_or_trace", ["rwwarp.wave.plan_sources"]),
    ("rwwarp.wave.batch_plan", "pilot_arrays", ["rwwarp.wave.plan_sources"]),
    ("rwwarp.wave.batch_plan", "_ray_focus", ["rwwarp.wave.plan_sources"]),
    ("rwwarp.wave.focal_sources", "focal_plans_one_order", []),
    ("rwwarp.wave.focal_sources", "focal_plans_orders", []),
    ("rwwarp.wave.focal_sources", "_orders_chunk", []),
    ("rwwarp.wave.plan", "focal_plan_from", ["rwwarp.wave.focal_sources"]),
    ("rwwarp.wave.plan_sources", "_gauss_nodes_one", []),
    ("rwwarp.wave.pixel_scale", "plan_pixel", []),
    ("rwwarp.wave.plan_sources", "BatchPlan", []),
    ("rwwarp.wave.plan_sources", "estimate_cost", []),
    ("rwwarp.wave.model_error", "estimate_sources", []),
    ("rwwarp.wave.pixel_scale", "consider_pixel", ["rwwarp.wave.methods.pixel"]),
    ("rwwarp.wave.wave_step", "plan_wave_step", []),
    ("rwwarp.wave.methods.asm", "plan_window", []),
]


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--grid", type=int, default=10)
    ap.add_argument("--runs", type=int, default=5)
    a = ap.parse_args()
    warnings.simplefilter("ignore")
    from time_map_plan import setup
    from rwwarp.wave.packed import source_plans
    lens, fields, wls, ma = setup(a.grid)
    F = [f for f in fields for _ in wls]
    W = [w for _ in fields for w in wls]
    n = len(F)
    acc = defaultdict(float)

    def wrap(name, fn):
        def timed(*args, **kw):
            t0 = time.perf_counter()
            try:
                return fn(*args, **kw)
            finally:
                acc[name] += time.perf_counter() - t0
        return timed

    for mod, attr, users in PARTS:
        m = importlib.import_module(mod)
        if not hasattr(m, attr):
            continue
        w = wrap(attr, getattr(m, attr))
        setattr(m, attr, w)
        for u in users:
            um = importlib.import_module(u)
            if hasattr(um, attr):
                setattr(um, attr, w)
    source_plans(lens, F, W, 64, ma.pixel, **ma.opts)
    best = None
    for _ in range(a.runs):
        acc.clear()
        t0 = time.perf_counter()
        source_plans(lens, F, W, 64, ma.pixel, **ma.opts)
        total = time.perf_counter() - t0
        if best is None or total < best[0]:
            best = (total, dict(acc))
    total, parts = best
    print(f"{n} sources: planning {total / n * 1e3:.3f} ms/source (fastest of {a.runs})")
    for k, v in sorted(parts.items(), key=lambda kv: -kv[1]):
        print(f"  {k:24s} {v / n * 1e3:.4f} ms/source")


if __name__ == "__main__":
    main()
