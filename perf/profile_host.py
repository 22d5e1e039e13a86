"""Where a warm ``rw.psf`` call's host time goes, by phase (issue 25): pilot trace, planning, tracer set-up,
the field's launches (trace, splat, reductions), the propagation (operator build, DOE factor, products),
host <-> device copies, and the rest; with the number of Warp launches, allocations and device reads.

Each phase is the time of a function named in ``PHASES`` (wrapped with a timer; on CUDA every wrapped call
ends with a synchronisation, so a phase holds its own device work too) less the nested phases', reported
per enclosing phase (``trace launches < plan: ...`` is the pilot trace), so the phases add up to the call. Run on a small problem (``--size 8
--rays-per-sample 0.1``: kernels of microseconds) the phases are the host overhead a GPU call pays.

    python perf/profile_host.py [--device cpu] [--lens a489_doe] [--field 0] [--size 8] [--rays-per-sample 0.1]
        [--method auto] [--reps 30] [--cache] [--json perf/results/host_phases_cpu.json]

``--cache``: the calls go through one :class:`rwwarp.PlanCache` (the first call fills it; the measured ones hit).
"""
from __future__ import annotations

import argparse
import functools
import json
import sys
import time
import warnings
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import rwwarp as rw  # noqa: E402

#: phase name -> (module path, attribute path) of the functions whose inclusive time it is
PHASES = {
    "plan: pilot trace and per-source plans (source_plans)": ("rwwarp.psf", "source_plans"),
    "plan: RayWave set-up (planning on the host)": ("rwwarp.wave.raywave", "RayWave.__init__"),
    "plan: PackedRayWave set-up": ("rwwarp.wave.packed", "PackedRayWave.__init__"),
    "batch run (PackedRayWave.run rest)": ("rwwarp.wave.packed", "PackedRayWave.run"),
    "tracer set-up (Tracer.__init__)": ("rwwarp.trace", "Tracer.__init__"),
    "trace launches (Tracer._run)": ("rwwarp.trace", "Tracer._run"),
    "field: splat, tube areas, reductions (RayWave.field rest)": ("rwwarp.wave.raywave", "RayWave.field"),
    "field: host view / copy of the field": ("rwwarp.wave.raywave", "RayWave.field_array"),
    "power sums read (device -> host)": ("rwwarp.wave.raywave", "RayWave._power_sums"),
    "propagation: focal operator build": ("rwwarp.wave.raywave", "RayWave.focal_operator"),
    "propagation: DOE order factor (host phase + upload)": ("rwwarp.wave.raywave", "RayWave.doe_orders_factor"),
    "propagation: focal products and pixels": ("rwwarp.wave.focal", "focal_pixels"),
    "propagation: ASM (SensorPropagator)": ("rwwarp.wave.raywave", "RayWave.intensity"),
    "propagation: DOE phase on the windows (ASM)": ("rwwarp.wave.raywave", "RayWave.doe_phase"),
    "cache: fingerprint and look-up": ("rwwarp.wave.plan_cache", "PlanCache.lookup"),
}


def _resolve(mod, path):
    import importlib
    try:
        obj = importlib.import_module(mod)
    except ImportError:
        return None, None, None
    parts = path.split(".")
    for p in parts[:-1]:
        obj = getattr(obj, p, None)
        if obj is None:
            return None, None, None
    return obj, parts[-1], getattr(obj, parts[-1], None)


class PhaseTimer:
    """Wraps the ``PHASES`` functions: inclusive and exclusive (nested phases subtracted) times per phase."""

    def __init__(self, device):
        self.device = device
        self.incl = defaultdict(float)
        self.excl = defaultdict(float)
        self.calls = defaultdict(int)
        self.stack = []
        self.undo = []
        self.on = False

    def sync(self):
        if self.device.startswith("cuda"):
            import warp as wp
            wp.synchronize()
            try:
                import cupy
                cupy.cuda.Device().synchronize()
            except ImportError:
                pass

    def install(self):
        for name, (mod, path) in PHASES.items():
            owner, attr, fn = _resolve(mod, path)
            if fn is None:
                continue
            timer = self

            def wrapped(*a, _fn=fn, _name=name, **k):
                if not timer.on:
                    return _fn(*a, **k)
                parent = timer.stack[-1][0] if timer.stack else None
                key = _name if parent is None or parent == _name else f"{_name} < {parent}"
                timer.stack.append([_name, 0.0])
                t0 = time.perf_counter()
                try:
                    return _fn(*a, **k)
                finally:
                    timer.sync()
                    dt = time.perf_counter() - t0
                    inner = timer.stack.pop()[1]
                    timer.incl[key] += dt
                    timer.excl[key] += dt - inner
                    timer.calls[key] += 1
                    if timer.stack:
                        timer.stack[-1][1] += dt
            functools.update_wrapper(wrapped, fn)
            setattr(owner, attr, wrapped)
            self.undo.append((owner, attr, fn))

    def remove(self):
        for owner, attr, fn in reversed(self.undo):
            setattr(owner, attr, fn)
        self.undo = []


class Counters:
    """Counts Warp launches, Warp allocations (empty / zeros / array) and device -> host reads (``.numpy()``)."""

    def __init__(self):
        import warp as wp
        self.wp = wp
        self.n = defaultdict(int)
        self.saved = {}

    def __enter__(self):
        wp = self.wp
        for name in ("launch", "empty", "zeros", "copy"):
            orig = getattr(wp, name)
            self.saved[name] = orig

            def counted(*a, _orig=orig, _name=name, **k):
                self.n[_name] += 1
                return _orig(*a, **k)
            setattr(wp, name, counted)
        from warp._src import context as wctx   # the kernel's own run on the CPU (a launch's host part excluded)
        inv = wctx.invoke
        self.saved["invoke"] = inv
        self.kernel_s = 0.0

        def invoke(*a, _orig=inv, **k):
            t0 = time.perf_counter()
            try:
                return _orig(*a, **k)
            finally:
                self.kernel_s += time.perf_counter() - t0
        wctx.invoke = invoke
        arr = wp.array
        self.saved["array.numpy"] = arr.numpy

        def numpy(a, _orig=arr.numpy):
            self.n["numpy (device read)"] += 1
            return _orig(a)
        arr.numpy = numpy
        return self

    def __exit__(self, *exc):
        for name, orig in self.saved.items():
            if name == "array.numpy":
                self.wp.array.numpy = orig
            elif name == "invoke":
                from warp._src import context as wctx
                wctx.invoke = orig
            else:
                setattr(self.wp, name, orig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--lens", default="a489_doe")
    ap.add_argument("--field", type=float, default=0.0)
    ap.add_argument("--wl", type=float, default=0.55)
    ap.add_argument("--size", type=int, default=8)
    ap.add_argument("--rays-per-sample", type=float, default=0.1)
    ap.add_argument("--method", default="auto")
    ap.add_argument("--reps", type=int, default=30)
    ap.add_argument("--cache", action="store_true", help="call through one rwwarp.PlanCache")
    ap.add_argument("--json", default=None, help="write the figures here")
    a = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    lens = rw.load_lens(a.lens)
    kw = dict(size=a.size, rays_per_sample=a.rays_per_sample, device=a.device, method=a.method)
    if a.cache:
        kw["cache"] = rw.PlanCache(max_entries=4)
    timer = PhaseTimer(a.device)
    for _ in range(3):
        rw.psf(lens, a.field, a.wl, **kw)
    timer.sync()
    # wall time without the wrappers first
    wall = []
    for _ in range(a.reps):
        t0 = time.perf_counter()
        rw.psf(lens, a.field, a.wl, **kw)
        timer.sync()
        wall.append(time.perf_counter() - t0)
    kern = []
    for _ in range(max(3, a.reps // 3)):
        with Counters() as cnt:
            rw.psf(lens, a.field, a.wl, **kw)
        kern.append(cnt.kernel_s)
    kernel_ms = 1e3 * float(np.median(kern))
    timer.install()
    timer.on = True
    tot = []
    try:
        for _ in range(a.reps):
            t0 = time.perf_counter()
            p = rw.psf(lens, a.field, a.wl, **kw)
            timer.sync()
            tot.append(time.perf_counter() - t0)
    finally:
        timer.on = False
        timer.remove()
    total_ms = 1e3 * sum(tot) / a.reps
    phases = {k: 1e3 * v / a.reps for k, v in sorted(timer.excl.items(), key=lambda kv: -kv[1])}
    rest = total_ms - sum(phases.values())
    from _common import git_commit
    commit = git_commit()   # $RWWARP_COMMIT on a copied tree
    pl = p.plan or {}
    print(f"{a.lens} {a.field:g} deg {a.wl:g} um, {a.size} px, rays_per_sample {a.rays_per_sample}, device "
          f"{a.device}, cache {a.cache}: plan {pl.get('method')} grid {pl.get('n_grid')}^2, rays {pl.get('ray_grid')}^2")
    print(f"warm rw.psf: median {1e3 * np.median(wall):.3f} ms, min {1e3 * np.min(wall):.3f} ms over {a.reps} "
          f"(unwrapped); with the phase timers {total_ms:.3f} ms a call")
    print(f"per call: {dict(cnt.n)}; Warp kernels' own run (CPU: invoke, median) {kernel_ms:.3f} ms")
    for k, v in phases.items():
        print(f"  {v:8.3f} ms  {k}  ({timer.calls[k] // a.reps} call(s))")
    print(f"  {rest:8.3f} ms  rest of psf / psf_map (argument checks, batching, results, warnings)")
    if a.json:
        out = {"commit": commit, "lens": a.lens, "field_deg": a.field, "wavelength_um": a.wl, "size": a.size,
               "rays_per_sample": a.rays_per_sample, "method": a.method, "device": a.device, "cache": a.cache, "reps": a.reps,
               "plan": {k: pl.get(k) for k in ("method", "n_grid", "ray_grid", "n_pad", "n_sensor", "n_sensor_fft")},
               "warm_median_ms": 1e3 * float(np.median(wall)), "warm_min_ms": 1e3 * float(np.min(wall)),
               "timed_total_ms": total_ms, "counts_per_call": dict(cnt.n), "warp_kernels_ms": kernel_ms,
               "phases_ms": dict(phases, **{"rest of psf / psf_map": rest}),
               "phase_calls_per_call": {k: timer.calls[k] / a.reps for k in phases}}
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        Path(a.json).write_text(json.dumps(out, indent=1) + "\n")
        print(f"wrote {a.json}")


if __name__ == "__main__":
    main()
