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
"""
from __future__ import annotations

import argparse
import ctypes
import gc
import os
import threading
import time

import numpy as np
import torch
from _common import device_name, save

import rwwarp as rw
import torch_bridge as tb


def sync_fn(device):
    if device.startswith("cuda"):
        import warp as wp

        def s():
            wp.synchronize_device(device if ":" in device else "cuda:0")
            torch.cuda.synchronize()
            try:
                import cupy
                cupy.cuda.runtime.deviceSynchronize()
            except ImportError:
                pass
        return s
    return lambda: None


class PeakMemory:
    """Peak memory above the starting point while the block runs: host RSS (CPU) or device memory
    in use (CUDA), sampled every millisecond."""

    def __init__(self, device):
        self.device = device

    def _now(self):
        if self.device.startswith("cuda"):
            free, total = torch.cuda.mem_get_info()
            return total - free
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")

    def __enter__(self):
        gc.collect()
        if self.device.startswith("cuda"):
            # caching allocators (torch, CuPy, Warp's mempool) give their free blocks back first, so
            # "in use above start" sees this block's allocations
            torch.cuda.synchronize()
            torch.cuda.empty_cache()
            try:
                import cupy
                cupy.get_default_memory_pool().free_all_blocks()
            except ImportError:
                pass
        try:
            ctypes.CDLL("libc.so.6").malloc_trim(0)
        except OSError:
            pass
        self.base = self.peak = self._now()
        self._stop = False

        def run():
            while not self._stop:
                self.peak = max(self.peak, self._now())
                time.sleep(0.001)
        self._t = threading.Thread(target=run, daemon=True)
        self._t.start()
        return self

    def __exit__(self, *exc):
        self._stop = True
        self._t.join()
        self.peak = max(self.peak, self._now())

    @property
    def bytes(self):
        return int(self.peak - self.base)


def make_module(device, rays_per_sample):
    lens = rw.load_lens("a489_doe")
    hl = tb.HybridLens(lens, learn={"doe": "all", "curvature": [1], "conic": [1], "thickness": [3]},
                       rays_per_sample=rays_per_sample)
    return hl.to("cpu" if device == "cpu" else torch.device(device if ":" in device else "cuda:0"))


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
        s()
        t0 = time.perf_counter()
        out = fn()
        s()
        t1 = time.perf_counter()
        (out * weights).sum().backward()
        s()
        fwd.append(t1 - t0)
        bwd.append(time.perf_counter() - t1)
        del out
    hl.zero_grad()
    with PeakMemory(device) as pm:
        out = fn()
        (out * weights).sum().backward()
        s()
        del out
    return {"first_call_s": first, "forward_s": float(np.median(fwd)), "backward_s": float(np.median(bwd)),
            "forward_backward_s": float(np.median(np.add(fwd, bwd))), "peak_bytes": pm.bytes}


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
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--field", type=float, default=7.0, help="field of the single PSF, deg")
    ap.add_argument("--grid", type=int, default=2, help="map of grid x grid fields over 0..9 deg (x and y)")
    ap.add_argument("--wavelengths", type=float, nargs="+", default=[0.45, 0.55, 0.65])
    ap.add_argument("--tiles", type=int, nargs="+", default=[1, 4, 0])
    ap.add_argument("--budget-mb", type=float, default=None, help="also run the map under this memory budget")
    ap.add_argument("--rays-per-sample", type=float, default=1.0, help="the library's default is 1.0")
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()
    device = a.device
    if device.startswith("cuda"):
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
    hl = make_module(device, a.rays_per_sample)
    tdev = hl.thickness_base.device
    res = {"benchmark": "bridge", "lens": "a489_doe, object at 10 m", "device": device,
           "device_name": device_name(device), "size_px": a.size, "rays_per_sample": a.rays_per_sample,
           "learn": "doe (4 coefficients), curvature + conic of surface 1, thickness to the sensor",
           "memory": "host RSS above start (cpu) / device memory in use above start (cuda), sampled every ms"}
    # ---- one PSF
    w1 = torch.rand(a.size, a.size, dtype=torch.float64, device=tdev)
    rwv = hl.raywave([(0.0, a.field)], [0.55], a.size)
    res["psf"] = {"field_deg": a.field, "wavelength_um": 0.55, "plan": rwv.plan.to_dict(),
                  "rays": rwv.plan.ray_grid ** 2,
                  **run_case(hl, lambda: hl.psf((0.0, a.field), 0.55, a.size), w1, device, a.repeat)}
    print(f"psf: fwd {res['psf']['forward_s']:.3f} s, bwd {res['psf']['backward_s']:.3f} s, "
          f"peak {res['psf']['peak_bytes'] / 2**20:.0f} MiB")
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
              f"bwd {r['backward_s']:.2f} s, peak {r['peak_bytes'] / 2**20:.0f} MiB")
    name = "bench_bridge_gpu" if device.startswith("cuda") else "bench_bridge_cpu"
    path = save(name, res)
    chart(res, path.with_suffix(".png"))
    print(path)


def chart(res, png):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    runs = res["map"]["runs"]
    labels = [f"tile {r['tile']}" if "tile" in r else f"budget {r['budget'] / 2**20:.0f} MiB" for r in runs]
    fig = Figure(figsize=(9, 3.6), dpi=120)
    FigureCanvasAgg(fig)
    ax1, ax2 = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    x = np.arange(len(runs))
    ax1.bar(x - 0.2, [r["forward_s"] for r in runs], 0.4, label="forward")
    ax1.bar(x + 0.2, [r["backward_s"] for r in runs], 0.4, label="backward")
    ax1.set_xticks(x, labels, fontsize=8)
    ax1.set_ylabel("s")
    ax1.legend(fontsize=8)
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
