"""torch bridge: forward + backward time and peak memory of one PSF and of a PSF map (A489 + DOE).

The loss is ``sum(psf * w)`` with fixed random weights; its gradient reaches the DOE coefficients,
the aspheric surface's curvature and conic and the DOE-to-sensor thickness. Reported per case:
forward time, backward time (median of ``--repeat`` after one warm-up, bracketed by device
synchronisation), the first call (kernel builds) apart, and the peak memory above the starting
point: host RSS sampled every millisecond on CPU, device memory in use (``cudaMemGetInfo``: Warp,
CuPy and torch pools together) sampled likewise on CUDA. The map runs with several tile sizes
(checkpointed tiles: peak memory should not grow with the map) and with a memory budget.

    python perf/bench_bridge.py [--device cuda] [--grid 2] [--wavelengths 0.45 0.55 0.65] [--tiles 1 4 0]

``--tiles 0`` means one tile for the whole map. Results: perf/results/bench_bridge_{cpu,gpu}.json + .png.

**Tile study** (``--study``): a 10 x 10 fields x 3 wavelengths map (300 PSFs) with forward + backward
at tiles of 1, 4, 16 and 100 fields (3, 12, 48, 300 sources; 100 fields = the whole map in one tile,
nothing checkpointed), and once more under a memory budget (``--budget-mb``, default room for 16
sources by the library's estimate: :meth:`HybridLens.bytes_per_source`, :meth:`~HybridLens.bytes_fixed`,
a quarter for the transfer-function cache), with the peak memory of each. On CUDA three peaks are recorded:
device memory in use (``cudaMemGetInfo``, everything on the GPU), the sampled sum of what torch's,
CuPy's and Warp's allocators hold (``torch.cuda.memory_allocated + cupy pool used_bytes +
wp.get_mempool_used_mem_current``) and ``torch.cuda.max_memory_allocated``, each above the starting
point; on CPU the process RSS above start. The lens can be stopped down (``--stop-scale``: stop
semi-diameter times this; smaller windows and fewer rays) so that the one-tile case fits and the CPU
run takes minutes; the JSON says which. ``--deeplens`` adds DeepLens 2.5.6's ``HybridLens.psf`` with
backward (its DOE coefficients, the asphere's curvature and conic learning) at 1M and 16.7M rays on
the full A489 lens of perf/bench_psf.py (perf/_deeplens.py), next to our on-axis PSF with backward on the same lens.
Sections land in the JSON of the device (merged with the sections already there).

    # the GPU run (one PSF, DeepLens with backward, the tile study; a few minutes on an H100):
    python perf/bench_bridge.py --device cuda --study --deeplens --no-map
    # the CPU run (a few minutes on 2 cores; stopped down, small patches):
    python perf/bench_bridge.py --device cpu --study --no-psf --no-map --stop-scale 0.25 --size 32 --warmup 1
"""
from __future__ import annotations

import argparse
import contextlib
import ctypes
import gc
import os
import threading
import time

import numpy as np
import torch
from _common import device_name, save, sync_fn

import rwwarp as rw
import torch_bridge as tb


def _allocators_in_use(device):
    """Bytes held by torch's, CuPy's and Warp's device allocators together (CUDA)."""
    total = torch.cuda.memory_allocated()
    try:
        import cupy
        total += cupy.get_default_memory_pool().used_bytes()
    except ImportError:
        pass
    try:
        import warp as wp
        total += wp.get_mempool_used_mem_current(device if ":" in device else "cuda:0")
    except (RuntimeError, ValueError, AttributeError):  # no mempool on this device / Warp version
        return total
    return total


class PeakMemory:
    """Peak memory above the starting point while the block runs: host RSS (CPU) or device memory
    in use (CUDA), sampled every millisecond. On CUDA also the sampled peak of what torch's, CuPy's
    and Warp's allocators hold (``allocator_bytes``) and ``torch.cuda.max_memory_allocated`` above its
    starting point (``torch_bytes``)."""

    def __init__(self, device):
        self.device = device
        self.cuda = device.startswith("cuda")

    def _now(self):
        if self.cuda:
            free, total = torch.cuda.mem_get_info()
            return total - free
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")

    def __enter__(self):
        gc.collect()
        if self.cuda:
            # caching allocators (torch, CuPy, Warp's mempool) give their free blocks back first, so
            # "in use above start" sees this block's allocations
            torch.cuda.synchronize()
            torch.cuda.empty_cache()
            try:
                import cupy
                cupy.get_default_memory_pool().free_all_blocks()
            except ImportError:
                pass
            torch.cuda.reset_peak_memory_stats()
            self.torch_base = torch.cuda.memory_allocated()
            self.alloc_base = self.alloc_peak = _allocators_in_use(self.device)
        try:
            ctypes.CDLL("libc.so.6").malloc_trim(0)
        except OSError:
            pass
        self.base = self.peak = self._now()
        self._stop = False

        def run():
            while not self._stop:
                self.peak = max(self.peak, self._now())
                if self.cuda:
                    self.alloc_peak = max(self.alloc_peak, _allocators_in_use(self.device))
                time.sleep(0.001)
        self._t = threading.Thread(target=run, daemon=True)
        self._t.start()
        return self

    def __exit__(self, *exc):
        self._stop = True
        self._t.join()
        self.peak = max(self.peak, self._now())
        if self.cuda:
            self.alloc_peak = max(self.alloc_peak, _allocators_in_use(self.device))
            self.torch_peak = torch.cuda.max_memory_allocated()

    @property
    def bytes(self):
        return int(self.peak - self.base)

    def report(self):
        """Peaks as a dict (bytes above the starting point)."""
        out = {"peak_bytes": self.bytes}
        if self.cuda:
            out["allocator_peak_bytes"] = int(self.alloc_peak - self.alloc_base)
            out["torch_max_allocated_bytes"] = int(self.torch_peak - self.torch_base)
        return out


def a489(stop_scale=1.0):
    """The A489 + DOE lens; ``stop_scale`` < 1 stops it down (stop semi-diameter times the scale)."""
    lens = rw.load_lens("a489_doe")
    if stop_scale != 1.0:
        stop = next(i for i, s in enumerate(lens.surfaces) if s.stop)
        lens.surfaces[stop].semi_diameter *= float(stop_scale)
        lens.validate()
    return lens


def make_module(device, rays_per_sample, stop_scale=1.0):
    lens = a489(stop_scale)
    hl = tb.HybridLens(lens, learn={"doe": "all", "curvature": [1], "conic": [1], "thickness": [3]},
                       rays_per_sample=rays_per_sample)
    return hl.to("cpu" if device == "cpu" else torch.device(device if ":" in device else "cuda:0"))


def _timed_step(fn, weights, sync):
    """One forward ``fn()`` and the backward of ``sum(out * weights)``, each bracketed by ``sync()``:
    (forward s, backward s)."""
    sync()
    t0 = time.perf_counter()
    out = fn()
    sync()
    t1 = time.perf_counter()
    (out * weights).sum().backward()
    sync()
    return t1 - t0, time.perf_counter() - t1


def run_case(hl, fn, weights, device, repeat):
    """First call, then median forward / backward times and the peak memory of one forward + backward."""
    s = sync_fn(device)
    t0 = time.perf_counter()
    out = fn()
    (out * weights).sum().backward()
    s()
    first = time.perf_counter() - t0
    del out
    fwd, bwd = [], []
    for _ in range(repeat):
        hl.zero_grad()
        tf, tb_ = _timed_step(fn, weights, s)
        fwd.append(tf)
        bwd.append(tb_)
    pm = _peak_run(hl, fn, weights, device, s)
    return {"first_call_s": first, "forward_s": float(np.median(fwd)), "backward_s": float(np.median(bwd)),
            "forward_backward_s": float(np.median(np.add(fwd, bwd))), **pm.report()}


def _peak_run(hl, fn, weights, device, s):
    """One forward + backward under :class:`PeakMemory` (gradients zeroed first); returns the monitor."""
    hl.zero_grad()
    with PeakMemory(device) as pm:
        out = fn()
        (out * weights).sum().backward()
        s()
        del out
    return pm


def run_timed_peak(hl, fn, weights, device, repeat, warmup):
    """Cheaper protocol for the tile study: an optional warm-up call (``first_call_s``), ``repeat``
    timed forward + backward runs, the last of them under :class:`PeakMemory` (on CPU the sampling
    thread costs little; on CUDA a separate peak run follows, so timings exclude refilling the pools
    that the peak measurement empties)."""
    s = sync_fn(device)
    res = {}
    if warmup:
        t0 = time.perf_counter()
        out = fn()
        (out * weights).sum().backward()
        s()
        res["first_call_s"] = time.perf_counter() - t0
        del out
    fwd, bwd = [], []
    cuda = device.startswith("cuda")
    for k in range(repeat):
        hl.zero_grad()
        last = k == repeat - 1 and not cuda
        pm = PeakMemory(device) if last else contextlib.nullcontext()
        with pm:
            tf, tb_ = _timed_step(fn, weights, s)
        fwd.append(tf)
        bwd.append(tb_)
    if cuda:
        pm = _peak_run(hl, fn, weights, device, s)
    res.update({"forward_s": float(np.median(fwd)), "backward_s": float(np.median(bwd)),
                "forward_backward_s": float(np.median(np.add(fwd, bwd))), "timed_runs": repeat, **pm.report()})
    return res


def run_study(device, a):
    """The 10 x 10 fields x 3 wavelengths map with backward at several tile sizes and under a budget."""
    from rwwarp.wave import backend as bk
    hl = make_module(device, a.rays_per_sample, a.stop_scale)
    tdev = hl.thickness_base.device
    g = np.linspace(0.0, 9.0, a.study_grid) if a.study_grid > 1 else np.array([5.0])
    fields = [(float(x) / np.sqrt(2), float(y) / np.sqrt(2)) for y in g for x in g]
    wls = list(a.wavelengths)
    n_src = len(fields) * len(wls)
    gen = torch.Generator().manual_seed(1)
    w = torch.rand(len(fields), len(wls), a.size, a.size, dtype=torch.float64, generator=gen).to(tdev)
    full = hl.raywave([f for f in fields for _ in wls], wls * len(fields), a.size)
    per_src = hl.bytes_per_source(full)
    fixed = hl.bytes_fixed(full)
    # default: room for 16 sources by the library's estimate (a quarter of a budget goes to the cache)
    budget = int(a.budget_mb * 2**20) if a.budget_mb else int((16 * per_src + fixed) * 4 / 3) + 1
    res = {"what": f"{len(fields)} fields ({a.study_grid} x {a.study_grid} over 0..9 deg) x {len(wls)} wavelengths, "
                   "forward + backward of sum(map * w), tiles checkpointed (recomputed in backward) when the map "
                   "has more than one tile; tile 100 fields = the whole map in one tile, no checkpointing. "
                   "planning_peak: the peak of making the map's plan alone (a pilot trace of every source, "
                   "not tiled), part of every run's peak",
           "lens": f"a489_doe, stop semi-diameter x {a.stop_scale}" + (" (stopped down)" if a.stop_scale != 1 else ""),
           "size_px": a.size, "rays_per_sample": a.rays_per_sample, "fields": len(fields), "wavelengths_um": wls,
           "sources": n_src, "plan": full.plan.to_dict(), "rays_per_source": full.plan.ray_grid ** 2,
           "estimated_bytes_per_source": per_src, "estimated_fixed_bytes": fixed,
           "transfer_cache_max_bytes": bk.get_backend(hl.rw_device).cache.max_bytes,
           "memory": ("cuda: peak_bytes = device memory in use above start (cudaMemGetInfo), allocator_peak_bytes = "
                      "torch + CuPy pool + Warp mempool in use above start, sampled every ms; "
                      "torch_max_allocated_bytes = torch.cuda.max_memory_allocated above start"
                      if device.startswith("cuda") else "cpu: process RSS above start, sampled every ms"),
           "runs": []}
    del full
    print(f"study: {n_src} sources, plan n_grid {res['plan']['n_grid']} n_pad {res['plan']['n_pad']} "
          f"rays {res['rays_per_source']}, estimated {per_src / 2**20:.0f} MiB/source")
    cases = [("tile_fields", t) for t in a.tile_fields] + [("budget_bytes", budget)]
    t0 = time.perf_counter()
    for t in sorted({min(t, len(fields)) for t in a.tile_fields} | {1}):
        # kernel builds and FFT plans of every batch size that follows (one and two tiles' worth)
        m = hl.psf_map(fields[:min(2 * t, len(fields))], wls, a.size, tile=t * len(wls))
        (m * w[:m.shape[0]]).sum().backward()
        del m
        if a.warmup:
            break
    res["warmup_s"] = time.perf_counter() - t0
    # the part that does not tile: the map's plan, made from a pilot trace of every source
    with PeakMemory(device) as pm:
        full = hl.raywave([f for f in fields for _ in wls], wls * len(fields), a.size)
        del full
    res["planning_peak"] = pm.report()
    print(f"  planning the whole map (pilot trace of {n_src} sources): peak {pm.bytes / 2**20:.0f} MiB", flush=True)
    for kind, val in cases:
        if kind == "tile_fields":
            kw = {"tile": min(val, len(fields)) * len(wls)}
        else:
            kw = {"memory_budget_bytes": val}
        def fn(kw=kw):
            return hl.psf_map(fields, wls, a.size, **kw)
        try:
            r = {kind: val, **run_timed_peak(hl, fn, w, device, a.study_repeat, warmup=bool(a.warmup))}
        except (RuntimeError, MemoryError) as e:  # e.g. out of memory for the one-tile case: report it, go on
            hl.zero_grad()
            gc.collect()
            if device.startswith("cuda"):
                torch.cuda.empty_cache()
            res["runs"].append({kind: val, "error": f"{type(e).__name__}: {str(e)[:300]}"})
            print(f"  {kind}={val}: failed: {type(e).__name__}: {str(e)[:200]}", flush=True)
            continue
        if kind == "tile_fields":
            r["tile_sources"] = kw["tile"]
            r["checkpointed"] = kw["tile"] < n_src
        else:
            r["tile_sources"] = max(1, int((val - val // 4 - fixed) // per_src))
            r["checkpointed"] = r["tile_sources"] < n_src
            r["under_budget"] = bool(max(r["peak_bytes"], r.get("allocator_peak_bytes", 0)) < val)
        res["runs"].append(r)
        extra = "" if kind == "tile_fields" else f" (budget {val / 2**20:.0f} MiB, under: {r['under_budget']})"
        print(f"  {kind}={val if kind == 'tile_fields' else str(val) + ' (tile ' + str(r['tile_sources']) + ' sources)'}: fwd {r['forward_s']:.2f} s, "
              f"bwd {r['backward_s']:.2f} s, peak {r['peak_bytes'] / 2**20:.0f} MiB"
              + (f", allocators {r['allocator_peak_bytes'] / 2**20:.0f} MiB" if "allocator_peak_bytes" in r else "")
              + extra, flush=True)
    return res


def run_deeplens(device, a):
    """DeepLens 2.5.6 ``HybridLens.psf`` with backward on the A489 (perf/_deeplens.py's DeepLens lens of
    ours, as perf/bench_psf.py), and our on-axis PSF with backward on the same (full) lens."""
    res = {"lens": "a489_doe (flat DOE), full aperture, object at 10 m, on axis, 0.55 um, 64 px"}
    # ours first (DeepLens changes torch's default dtype)
    hl = make_module(device, a.rays_per_sample)
    w = torch.rand(64, 64, dtype=torch.float64, generator=torch.Generator().manual_seed(2)).to(hl.thickness_base.device)
    r = run_case(hl, lambda: hl.psf((0.0, 0.0), 0.55, 64), w, device, a.repeat)
    r["rays"] = hl.raywave([(0.0, 0.0)], [0.55], 64).plan.ray_grid ** 2
    res["rwwarp"] = r
    print(f"rwwarp on-axis psf: fwd {r['forward_s'] * 1e3:.1f} ms, bwd {r['backward_s'] * 1e3:.1f} ms, "
          f"peak {r['peak_bytes'] / 2**30:.2f} GiB", flush=True)
    hl = None  # free ours before DeepLens runs
    keep = torch.get_default_dtype()
    try:
        from _deeplens import a489_hybridlens  # perf/_deeplens.py: the lens of perf/bench_psf.py
        try:
            tdev = "cuda" if device.startswith("cuda") else "cpu"
            lens = a489_hybridlens(tdev)  # sets torch's default dtype to float64
            learn = []
            for k in ("alpha2", "alpha4", "alpha6", "alpha8", "alpha10"):
                if hasattr(lens.doe, k):
                    t = torch.zeros(1, device=tdev, dtype=torch.float64, requires_grad=True)
                    setattr(lens.doe, k, t)
                    learn.append(t)
            asph = lens.geolens.surfaces[1]
            for k in ("c", "k"):
                t = getattr(asph, k).detach().clone().requires_grad_(True)
                setattr(asph, k, t)
                learn.append(t)
            res["deeplens_learn"] = "DOE alpha2..alpha10, curvature and conic of the asphere"
            for spp in a.deeplens_spp:
                wd = None

                def fn(spp=spp):
                    return lens.psf(points=[0.0, 0.0, -10000.0], ks=64, wvln=0.55, spp=spp)

                s = sync_fn(device)
                fwd, bwd = [], []
                for k in range(a.repeat + 1):
                    for t in learn:
                        t.grad = None
                    s()
                    t0 = time.perf_counter()
                    p = fn()
                    s()
                    t1 = time.perf_counter()
                    if wd is None:
                        wd = torch.rand(p.shape, dtype=p.dtype, generator=torch.Generator().manual_seed(3)).to(p.device)
                    (p * wd).sum().backward()
                    s()
                    if k:  # the first call apart
                        fwd.append(t1 - t0)
                        bwd.append(time.perf_counter() - t1)
                    else:
                        first = time.perf_counter() - t0
                    del p
                for t in learn:
                    t.grad = None
                with PeakMemory(device) as pm:
                    p = fn()
                    (p * wd).sum().backward()
                    s()
                    del p
                r = {"rays": spp, "first_call_s": first, "forward_s": float(np.median(fwd)),
                     "backward_s": float(np.median(bwd)), "forward_backward_s": float(np.median(np.add(fwd, bwd))),
                     "grads_finite": bool(all(t.grad is not None and torch.isfinite(t.grad).all() for t in learn)),
                     **pm.report()}
                res[f"deeplens_{spp}"] = r
                print(f"deeplens {spp} rays: fwd {r['forward_s'] * 1e3:.1f} ms, bwd {r['backward_s'] * 1e3:.1f} ms, "
                      f"peak {r['peak_bytes'] / 2**30:.2f} GiB", flush=True)
        finally:
            torch.set_default_dtype(keep)
    except Exception as e:  # noqa: BLE001 - report, don't hide (import errors, DeepLens's own failures)
        import traceback
        traceback.print_exc()
        res["deeplens_error"] = f"{type(e).__name__}: {e}"
        print("deeplens failed:", res["deeplens_error"])
    return res


def save_sections(name, sections, device):
    """Merge ``sections`` into perf/results/<name>.json (other sections kept; each section carries the
    commit and date of its run)."""
    import datetime
    import json

    from _common import RESULTS, git_commit
    path = __import__("pathlib").Path(os.environ.get("RWWARP_RESULTS", RESULTS)) / f"{name}.json"
    old = {}
    if path.exists():
        try:
            old = json.loads(path.read_text())
        except ValueError:
            old = {}
    if old.get("device_name") not in (None, device_name(device)):
        old = {}  # another machine: start afresh
    stamp = {"commit": git_commit(), "date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")}
    for k, v in sections.items():
        old[k] = {**v, **stamp} if isinstance(v, dict) and k not in ("memory",) else v
    return save(name, old)


CHECK_FIELDS = [(0.0, 0.0), (0.0, 7.0)]


def check_loss(hl, size=32):
    """The loss of the CPU / CUDA comparison and its gradients: sum(map * w), fixed weights."""
    dev = hl.thickness_base.device
    w = torch.rand(len(CHECK_FIELDS), 1, size, size, dtype=torch.float64,
                   generator=torch.Generator().manual_seed(0)).to(dev)
    hl.zero_grad()
    loss = (hl.psf_map(CHECK_FIELDS, [0.55], size) * w).sum()
    loss.backward()
    return float(loss.detach()), {n: p.grad.detach().cpu().tolist() for n, p in hl.named_parameters() if p.numel()}


def write_reference(path, rays_per_sample):
    """CPU loss and gradients for :func:`check_against`."""
    import json
    hl = make_module("cpu", rays_per_sample)
    loss, grads = check_loss(hl)
    path = os.path.abspath(path)
    with open(path, "w") as f:
        json.dump({"device": "cpu", "device_name": device_name("cpu"), "loss": loss, "grads": grads,
                   "rays_per_sample": rays_per_sample}, f, indent=1)
    print(f"wrote {path}")


def check_against(path, device):
    """Same loss and gradients on ``device`` (CUDA) as the CPU reference, and the host <-> device
    transfers of one forward + backward (CUPTI through torch.profiler: every memcpy of the process,
    Warp's and CuPy's included) against the size of one DOE-plane field."""
    import json
    import tempfile
    with open(path) as f:
        ref = json.load(f)
    hl = make_module(device, ref["rays_per_sample"])
    check_loss(hl)  # warm-up: kernel builds, plans
    loss, grads = check_loss(hl)
    rel = {"loss": abs(loss - ref["loss"]) / abs(ref["loss"])}
    for n, g in grads.items():
        a, b = np.array(g), np.array(ref["grads"][n])
        rel[n] = float(np.max(np.abs(a - b)) / np.max(np.abs(b)))
    from torch.profiler import ProfilerActivity, profile
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        check_loss(hl)
        torch.cuda.synchronize()
    trace = os.path.join(tempfile.mkdtemp(), "trace.json")
    prof.export_chrome_trace(trace)
    with open(trace) as f:
        events = json.load(f)
    events = events["traceEvents"] if isinstance(events, dict) else events
    copies = {"HtoD": [], "DtoH": [], "DtoD": []}
    for e in events:
        name = str(e.get("name", ""))
        if e.get("cat") in ("gpu_memcpy", "Memcpy") or name.startswith("Memcpy"):
            b = int((e.get("args") or {}).get("bytes", 0))
            for k, sizes in copies.items():
                if k in name:
                    sizes.append(b)
    rwv = hl.raywave(CHECK_FIELDS, [0.55, 0.55], 32)
    field_bytes = rwv.plan.n_grid ** 2 * 16
    out = {"benchmark": "bridge_cuda_check", "device": device, "device_name": device_name(device),
           "reference": ref["device_name"], "relative_difference": rel,
           "transfers": {k: {"count": len(v), "bytes": int(sum(v)), "largest": int(max(v) if v else 0)}
                         for k, v in copies.items()},
           "one_field_bytes": field_bytes}
    print(json.dumps(out, indent=1))
    save("bench_bridge_cuda_check", out)


def profile_psf(device, rays_per_sample, size, field):
    """torch.profiler tables (device kernels incl. Warp's and CuPy's, host ops) of one PSF forward and
    backward, after a warm-up."""
    from torch.profiler import ProfilerActivity, profile, record_function
    hl = make_module(device, rays_per_sample)
    w = torch.rand(size, size, dtype=torch.float64).to(hl.thickness_base.device)
    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.startswith("cuda") else [])
    for k in range(2):
        with profile(activities=acts) as prof:
            with record_function("forward"):
                p = hl.psf((0.0, field), 0.55, size)
            with record_function("backward"):
                (p * w).sum().backward()
            if device.startswith("cuda"):
                torch.cuda.synchronize()
    key = "self_cuda_time_total" if device.startswith("cuda") else "self_cpu_time_total"
    print(prof.key_averages().table(sort_by=key, row_limit=25))
    print(prof.key_averages().table(sort_by="cpu_time_total", row_limit=25))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--reference", default=None, help="write the CPU loss/gradient reference to this file and stop")
    ap.add_argument("--check", default=None, help="compare --device against this reference file and stop")
    ap.add_argument("--profile", action="store_true", help="print the top kernels / ops of one PSF's backward")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--size", type=int, default=64, help="PSF size in pixels (1 um pixels)")
    ap.add_argument("--field", type=float, default=7.0, help="field of the single PSF, deg")
    ap.add_argument("--grid", type=int, default=2, help="map of grid x grid fields over 0..9 deg (x and y)")
    ap.add_argument("--wavelengths", type=float, nargs="+", default=[0.45, 0.55, 0.65])
    ap.add_argument("--tiles", type=int, nargs="+", default=[1, 4, 0])
    ap.add_argument("--budget-mb", type=float, default=None,
                    help="map: also run under this memory budget; study: the budget (default room for 16 sources)")
    ap.add_argument("--rays-per-sample", type=float, default=1.0, help="the library's default is 1.0")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--no-psf", action="store_true", help="skip the single-PSF section")
    ap.add_argument("--no-map", action="store_true", help="skip the --grid map section")
    ap.add_argument("--study", action="store_true", help="the 10x10 x 3-wavelength tile study (see the docstring)")
    ap.add_argument("--study-grid", type=int, default=10)
    ap.add_argument("--tile-fields", type=int, nargs="+", default=[1, 4, 16, 100])
    ap.add_argument("--stop-scale", type=float, default=None,
                    help="tile study: stop semi-diameter x this (default 0.5 on CUDA, 0.25 on CPU)")
    ap.add_argument("--study-repeat", type=int, default=None, help="timed runs per tile case (default 1; CUDA adds a separate peak run)")
    ap.add_argument("--warmup", type=int, default=None,
                    help="tile study: 1 = an untimed first call per case (default on CUDA), 0 = only one small "
                         "warm-up map before all cases (default on CPU, where a first call costs a whole run)")
    ap.add_argument("--deeplens", action="store_true", help="DeepLens 2.5.6 psf with backward (and ours) on the A489")
    ap.add_argument("--deeplens-spp", type=int, nargs="+", default=[1_000_000, 16_777_216])
    a = ap.parse_args()
    device = a.device
    cuda = device.startswith("cuda")
    if a.stop_scale is None:
        a.stop_scale = 0.5 if cuda else 0.25
    if a.study_repeat is None:
        a.study_repeat = 1
    if a.warmup is None:
        a.warmup = 1 if cuda else 0
    if cuda:
        import warp as wp
        wp.init()
        wp.set_mempool_release_threshold(device if ":" in device else "cuda:0", 0)  # measurable peaks
    if a.reference:
        return write_reference(a.reference, a.rays_per_sample)
    if a.check:
        return check_against(a.check, device)
    if a.profile:
        return profile_psf(device, a.rays_per_sample, a.size, a.field)
    torch.manual_seed(0)
    name = "bench_bridge_gpu" if cuda else "bench_bridge_cpu"
    res = {}
    path = None
    if not (a.no_psf and a.no_map):
        hl = make_module(device, a.rays_per_sample)
        tdev = hl.thickness_base.device
        res.update({"benchmark": "bridge", "lens": "a489_doe, object at 10 m", "device": device,
                    "device_name": device_name(device), "size_px": a.size, "rays_per_sample": a.rays_per_sample,
                    "learn": "doe (4 coefficients), curvature + conic of surface 1, thickness to the sensor",
                    "memory": "host RSS above start (cpu) / device memory in use above start (cuda), sampled every ms"})
    if not a.no_psf:
        # ---- one PSF
        w1 = torch.rand(a.size, a.size, dtype=torch.float64, device=tdev)
        rwv = hl.raywave([(0.0, a.field)], [0.55], a.size)
        res["psf"] = {"field_deg": a.field, "wavelength_um": 0.55, "plan": rwv.plan.to_dict(),
                      "rays": rwv.plan.ray_grid ** 2,
                      **run_case(hl, lambda: hl.psf((0.0, a.field), 0.55, a.size), w1, device, a.repeat)}
        print(f"psf: fwd {res['psf']['forward_s']:.3f} s, bwd {res['psf']['backward_s']:.3f} s, "
              f"peak {res['psf']['peak_bytes'] / 2**20:.0f} MiB", flush=True)
    if not a.no_map:
        # ---- map
        g = np.linspace(0.0, 9.0, a.grid) if a.grid > 1 else np.array([5.0])
        fields = [(float(x) / np.sqrt(2), float(y) / np.sqrt(2)) for y in g for x in g]
        n_src = len(fields) * len(a.wavelengths)
        wm = torch.rand(len(fields), len(a.wavelengths), a.size, a.size, dtype=torch.float64, device=tdev)
        res["map"] = {"fields_deg": fields, "wavelengths_um": a.wavelengths, "sources": n_src, "runs": []}
        full = hl.raywave([f for f in fields for _ in a.wavelengths], a.wavelengths * len(fields), a.size)
        res["map"]["plan"] = full.plan.to_dict()
        res["map"]["estimated_bytes_per_source"] = hl.bytes_per_source(full)
        cases = [("tile", t if t > 0 else n_src) for t in a.tiles]
        if a.budget_mb:
            cases.append(("budget", int(a.budget_mb * 2**20)))
        for kind, val in cases:
            kw = {"tile": val} if kind == "tile" else {"memory_budget_bytes": val}
            r = run_case(hl, lambda kw=kw: hl.psf_map(fields, a.wavelengths, a.size, **kw), wm, device,
                         max(1, a.repeat - 2))
            r.update({kind: val})
            res["map"]["runs"].append(r)
            print(f"map {len(fields)}x{len(a.wavelengths)} {kind}={val}: fwd {r['forward_s']:.2f} s, "
                  f"bwd {r['backward_s']:.2f} s, peak {r['peak_bytes'] / 2**20:.0f} MiB", flush=True)
    if not (a.no_psf and a.no_map):
        del hl
        path = save_sections(name, res, device)  # each section is saved as soon as it is done
    if a.deeplens:
        res = {"device_name": device_name(device), "deeplens_backward": run_deeplens(device, a)}
        path = save_sections(name, res, device)
    if a.study:
        res = {"device_name": device_name(device), "tile_study": run_study(device, a)}
        path = save_sections(name, res, device)
    import json
    if path is None:
        print("nothing to run (--no-psf --no-map without --study or --deeplens)")
        return
    full_res = json.loads(path.read_text())
    if "map" in full_res and "psf" in full_res and not a.no_map:
        chart(full_res, path.with_suffix(".png"))
    if a.study:
        chart_study(full_res, path.with_name(path.stem + "_tiles.png"))
    print(path)


def _time_bars(ax, runs, labels, fontsize):
    """Forward / backward wall time (s) bars of ``runs`` on ``ax``; returns the bar positions."""
    x = np.arange(len(runs))
    ax.bar(x - 0.2, [r["forward_s"] for r in runs], 0.4, label="forward")
    ax.bar(x + 0.2, [r["backward_s"] for r in runs], 0.4, label="backward")
    ax.set_xticks(x, labels, fontsize=fontsize)
    ax.set_ylabel("s")
    ax.legend(fontsize=8)
    return x


def chart_study(res, png):
    """Bars: forward / backward time and peak memory per tile size of the tile study."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    st = res["tile_study"]
    runs = [r for r in st["runs"] if "error" not in r]
    labels = [f"tile {r['tile_fields']} field{'s' if r['tile_fields'] > 1 else ''}" if "tile_fields" in r else
              f"budget\n{r['budget_bytes'] / 2**20:.0f} MiB" for r in runs]
    fig = Figure(figsize=(10, 3.8), dpi=120)
    FigureCanvasAgg(fig)
    ax1, ax2 = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    x = _time_bars(ax1, runs, labels, 7)
    ax1.set_title(f"{st['sources']} PSFs ({st['size_px']} px), {res['device_name'][:30]}", fontsize=8)
    ax2.bar(x, [r["peak_bytes"] / 2**20 for r in runs], label="peak above start")
    for r, xi in zip(runs, x):
        if "budget_bytes" in r:
            ax2.hlines(r["budget_bytes"] / 2**20, xi - 0.4, xi + 0.4, colors="r", label="budget")
    ax2.set_xticks(x, labels, fontsize=7)
    ax2.set_ylabel("MiB")
    ax2.legend(fontsize=7)
    ax2.set_title(st["lens"], fontsize=8)
    fig.tight_layout()
    fig.savefig(png)


def chart(res, png):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    runs = res["map"]["runs"]
    labels = [f"tile {r['tile']}" if "tile" in r else f"budget {r['budget'] / 2**20:.0f} MiB" for r in runs]
    fig = Figure(figsize=(9, 3.6), dpi=120)
    FigureCanvasAgg(fig)
    ax1, ax2 = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    x = _time_bars(ax1, runs, labels, 8)
    ax1.set_title(f"map {res['map']['sources']} PSFs, {res['device_name'][:30]}", fontsize=8)
    ax2.bar(x, [r["peak_bytes"] / 2**20 for r in runs])
    ax2.set_xticks(x, labels, fontsize=8)
    ax2.set_ylabel("peak memory above start (MiB)")
    ax2.set_title(f"one PSF: {res['psf']['forward_backward_s']:.2f} s fwd+bwd, "
                  f"{res['psf']['peak_bytes'] / 2**20:.0f} MiB", fontsize=8)
    fig.tight_layout()
    fig.savefig(png)


if __name__ == "__main__":
    main()
