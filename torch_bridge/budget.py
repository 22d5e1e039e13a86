"""Memory estimates of the torch side (bytes), used to tile, checkpoint and refuse work before it runs.

The per-source figures of a :class:`rwwarp.psf.RayWave` batch recorded for gradients
(:func:`bytes_per_source`), of the propagation's output side (:func:`output_bytes_per_source`), of what a
PSF map needs whatever its tiling (:func:`bytes_fixed`), and the default budget of a device
(:func:`default_memory_budget_bytes`). :class:`torch_bridge.HybridLens` and the design providers call
these; each docstring gives the measurement the estimate was checked against. What a design step measured
(:func:`memory_gb`, :func:`torch_gb`: GB in use) is read here too, and checked against the budget by
:func:`over_budget`.
"""
from __future__ import annotations

import torch
from rwwarp.trace import COLUMNS as _COL

__all__ = ["bytes_fixed", "bytes_per_source", "cached_held_bytes", "cached_step_bytes",
           "default_memory_budget_bytes", "device_overhead_bytes",
           "overhead_from", "own_process_bytes", "process_device_bytes", "focal_graph_bytes", "memory_gb",
           "output_bytes_per_source", "over_budget", "torch_gb"]


def focal_graph_bytes(rw) -> int:
    """Estimated bytes one focal node's autograd graph holds from its forward to its backward (a cached
    provider's node, :class:`torch_bridge.design.CachedProvider`): the DOE phase and its polynomial intermediates
    (8 real wave-plane arrays), the order series (one complex array per Horner step: the span of the kept orders
    plus the shift to the lowest, and the stack), the modulated field and the operator's saved input (complex),
    and its output nodes (4 complex arrays of ``(size G)^2``)."""
    n2 = rw.plan.n_grid ** 2
    orders = [int(round(float(m))) for m, _ in (rw.focal["orders"][0] if rw.focal["orders"] else [])]
    steps = (max(orders) - min(orders) + abs(min(orders)) + 2) if len(orders) > 1 else 1
    return int(n2 * (8 * 8 + 16 * (steps + 3)) + 16 * 4 * (rw.size * rw.gauss_nodes) ** 2)


def cached_step_bytes(rw, doe_terms: int, upcast: bool) -> int:
    """Estimated peak bytes one node of a cached provider's ASM entry adds to a training step (DOE phase applied
    to its cached field, propagated, and back): the DOE phase and its autograd intermediates (about ``2 k + 8``
    real arrays of the DOE-plane grid for a ``k = doe_terms``-term polynomial), the field and phase gradients (and,
    ``upcast``, the complex128 copy of a complex64 cache), the padded FFT work space (3 complex arrays of
    ``n_pad^2``) and the sensor nodes, times a safety factor of 2 (allocator slack, transient copies)."""
    n, n_pad = rw.plan.n_grid, rw.plan.n_pad
    per_sample = 8 * (2 * min(int(doe_terms), 16) + 8) + 16 * 2 + (16 if upcast else 0)
    nodes = (rw.size * rw.gauss_nodes) ** 2 * 16 * 3
    return 2 * int(n * n * per_sample + n_pad * n_pad * 16 * 3 + nodes)


def cached_held_bytes(rw, learn_distance: bool) -> int:
    """Bytes one node of a cached provider's ASM entry keeps from its recorded forward to the step's backward: its
    node fields (:class:`~torch_bridge.operator_function.NodePixels`, complex128 at the pixels' Gauss nodes; two with
    pixel_values "flux") and, with a learning DOE-to-sensor distance (``learn_distance``), its modulated DOE-plane
    field (complex128, ``n_grid^2``: the distance's gradient reads it). The DOE modulation is recomputed in backward
    (:meth:`torch_bridge.design.CachedProvider.psfs`) and the ASM operator keeps its geometry only."""
    nodes = (rw.size * rw.gauss_nodes) ** 2 * 16 * (2 if rw.pixel_values == "flux" else 1)
    return int(nodes + (16 * rw.plan.n_grid ** 2 if learn_distance else 0))


def over_budget(memory_gb: float, budget_gb, where: str) -> str | None:
    """A message when ``memory_gb`` (GB = 1e9 bytes, the memory in use a training step measured) exceeds
    ``budget_gb`` (GB; None or 0: no budget), else None. ``where`` names the run and step in the message. The design
    loop warns with it once per arm and records it in ``progress.json``: a provider whose plans grow (a focal entry
    rebuilt for new DOE orders went from 20 to 117 GB under a 24 GB budget on an H200) must not pass unseen. On a GPU ``memory_gb`` is this process's own figure where the driver reports it
    (:func:`memory_gb`); where it does not, the device's, so a process sharing the card (session 23: the GPU smoke
    beside a design run, 25.2 GB against 24 at the run's first step) trips it too: the message says so."""
    if not budget_gb or memory_gb is None or not memory_gb > float(budget_gb):
        return None
    return (f"{where}: {memory_gb:.3g} GB of memory in use, over the memory budget of {float(budget_gb):.3g} GB "
            "(optics.memory_budget_gb): the plans or caches grew past what the budget was set for, or, on a GPU "
            "whose driver does not report this process's own use, other processes share it (the figure is then the "
            "device's used memory: a smoke run beside this one counts)")


_NVML_READY: list = []   # [True] once this process has initialised NVML


def process_device_bytes(device) -> int | None:
    """Bytes the driver reports this process using on the CUDA device ``device`` (its context and every
    allocation: torch's, Warp's and CuPy's pools, cuFFT work areas), read now through NVML (``pynvml``, the
    ``nvidia-ml-py`` package). None where that cannot be read: no CUDA, no NVML, the driver does not list this
    process (a container in another PID namespace) or gives no figure for it. Other processes on the same card do
    not count, unlike ``torch.cuda.mem_get_info``'s device-wide figure."""
    import os
    dev = str(device)
    if not (dev.startswith("cuda") and torch.cuda.is_available()):
        return None
    try:
        import pynvml
        if not _NVML_READY:
            pynvml.nvmlInit()          # once a process (NVML counts its initialisations)
            _NVML_READY.append(True)
        uuid = str(torch.cuda.get_device_properties(torch.device(dev)).uuid)
        handle = pynvml.nvmlDeviceGetHandleByUUID(uuid if uuid.startswith("GPU-") else "GPU-" + uuid)
        procs = pynvml.nvmlDeviceGetComputeRunningProcesses(handle)
    except Exception:  # noqa: BLE001 (no NVML, or a driver that cannot answer: the caller falls back)
        return None
    return own_process_bytes(procs, os.getpid())


def own_process_bytes(processes, pid: int) -> int | None:
    """The bytes NVML's process list ``processes`` (entries with ``pid`` and ``usedGpuMemory``, bytes or None)
    gives the process ``pid``, summed over its entries; None where it is not listed or has no figure."""
    used = [p.usedGpuMemory for p in processes if int(p.pid) == int(pid) and p.usedGpuMemory is not None]
    return int(sum(used)) if used else None


def overhead_from(total: int, free: int, reserved: int, own: int | None) -> int:
    """Bytes (>= 0) a device holds outside torch's caching allocator on behalf of this process: ``own`` (this
    process's use as the driver reports it, :func:`process_device_bytes`) less torch's ``reserved`` bytes; where
    ``own`` is None, the device-wide figure ``total - free - reserved`` (which counts other processes too)."""
    if own is not None:
        return max(0, int(own) - int(reserved))
    return max(0, int(total) - int(free) - int(reserved))


def device_overhead_bytes(device) -> int:
    """Bytes (>= 0) the CUDA device ``device`` has in use for this process outside torch's caching allocator, read
    now: the CUDA context, CuPy's and Warp's own pools, cuFFT plans' work areas: memory a budget of the process's
    used memory (``optics.memory_budget_gb``, sampled per process by ``perf/smoke_presets.py``) has to leave aside.
    0 on the CPU. This process's own figure comes from the driver (:func:`process_device_bytes`); other processes
    on the card do not count (session 24: a profiling run sharing the GPU made a design run's device-wide
    overhead exceed its 28 GB budget, and its first field build was refused at a budget of 0). Where the driver
    cannot say, the device-wide figure is used (:func:`overhead_from`). Measured on an H100 at d2b756b: without
    any overhead the a489_aberration e2e_doe field builds, estimated at 23.8 GB with the cached fields, peaked at
    24.52 GB of device memory against 24."""
    dev = str(device)
    if dev.startswith("cuda") and torch.cuda.is_available():
        d = torch.device(dev)
        free, total = torch.cuda.mem_get_info(d)
        return overhead_from(total, free, torch.cuda.memory_reserved(d), process_device_bytes(dev))
    return 0


def default_memory_budget_bytes(device) -> int:
    """Default memory budget (bytes) of a frozen field build (:class:`~torch_bridge.design.CachedProvider`)
    on ``device`` (a torch device or Warp device string): half the free memory of a CUDA device
    (``torch.cuda.mem_get_info`` plus the blocks torch's allocator caches unused; what torch, Warp and
    CuPy hold in use is left out), 4 GiB on the CPU."""
    dev = str(device)
    if dev.startswith("cuda") and torch.cuda.is_available():
        d = torch.device(dev)
        free, _ = torch.cuda.mem_get_info(d)
        # blocks torch's caching allocator holds but does not use are free for the next allocation
        # (rwwarp's release hook hands them back when another allocator needs them)
        free += torch.cuda.memory_reserved(d) - torch.cuda.memory_allocated(d)
        return int(free) // 2
    return 4 * 2 ** 30


def output_bytes_per_source(rw, tile_px=None) -> int:
    """Estimated bytes of the propagation's output side for one source and a spatial tile of
    ``tile_px`` x ``tile_px`` sensor pixels (default the whole patch): the node field, its gradient
    and a GEMM temporary ((tile_px G)^2 complex each, G Gauss nodes per pixel axis), and the two
    matrix-DFT factors (tile_px G x band width, bounded by the padded FFT size), times 2."""
    m = (rw.size if tile_px is None else min(int(tile_px), rw.size)) * rw.gauss_nodes
    return 2 * 16 * (3 * m * m + 2 * m * 2 * rw.plan.n_pad)


def bytes_per_source(rw, record: bool = True) -> int:
    """Estimated peak bytes one source adds in a recorded forward + backward (CPU and CUDA): rays
    with gradients for each launch up to the DOE plane (pos, dir, opl, valid), tube boxes, the
    splat and field grids with gradients, the DOE phase, the padded FFT work space and the sensor
    nodes, times a safety factor of 2 for allocator slack and transient copies. Measured: on CPU a
    recorded trace + splat of 41k rays x 5 launches takes 25 MB per source, a whole tile with
    backward up to 48 MB (estimate 59 MB); on an H100 the A489 at 1.5 rays per sample takes
    1.1-1.5 GB per source (estimate 1.6 GB).

    ``record=False``: the bytes of one source of a frozen field build (``rw.field_array()`` of a
    RayWave made with ``requires_grad=False``, no tape, no propagation), the same factor 2: two
    ray states (ping-pong: pos, dir, opl, valid, 60 bytes a ray in float64), wavelength index,
    weight, the shared intersection parameter and the tube boxes (164 bytes a ray); the splat
    sums, the field and its copy into the cache (48 bytes a DOE-plane sample). Measured on CPU (A489
    F/4, 1425^2 rays, 1015^2 samples): 268 MB a source (RSS), estimate 765 MB. A ``deterministic``
    RayWave adds its per-ray parameter copies (2 x 8 x N_PARAMS = 640 bytes a ray and surface) and fixed-point sums."""
    pl = rw.plan
    rays = pl.ray_grid ** 2
    if not record:
        return 2 * int(rays * 164 + pl.n_grid ** 2 * 48)
    per_ray = 128 * (rw.plane + 2) + 96           # 5 arrays (+ grads) per launch; tube boxes, power terms
    per_sample = 16 * 2 * 2 + 16 * 4 + 8 * 6      # s_re/s_im (+grad), field (+grad, torch views), phi0 etc.
    per_pad = 16 * 3                              # padded FFT work space, band, transfer function
    nodes = (rw.size * rw.gauss_nodes) ** 2 * 16 * 3
    extra = 0
    if getattr(rw, "deterministic", False):
        # a parameter-row copy per ray (the count rounded up to a power of two) and surface, with its
        # gradient (2 x 8 x N_PARAMS bytes, 640); the fixed-point splat's int64 sums, the rays' amplitudes and the tube-area
        # stencil (5 positions a ray, with gradients)
        extra = (1 << max(rays - 1, 0).bit_length()) * 16 * _COL.n_params * (rw.plane + 2) + pl.n_grid ** 2 * 16 + rays * (32 + 240)
    return 2 * int(rays * per_ray + pl.n_grid ** 2 * per_sample + pl.n_pad ** 2 * per_pad + nodes + extra)

def bytes_fixed(rw) -> int:
    """Estimated peak bytes of a PSF map that do not depend on the tile size: the pilot trace that
    plans the whole map (31 x 31 + 1 rays per source, position, direction, path and validity kept
    at every surface, with gradient buffers: 128 bytes per ray and surface) and the map itself with
    its gradient and weights (x 2). ``rw``: the whole map's RayWave. Measured on CPU (A489 stopped
    down, 300 sources, 5 surfaces): about 160 MiB peak for the planning, estimate 176 MiB. This part
    grows with the map: the planning pilot is not tiled."""
    n_surf = len(rw.lens.surfaces) + 1
    pilot = rw.nsrc * (31 * 31 + 1) * n_surf * 128
    maps = rw.nsrc * rw.size ** 2 * 8 * 3
    return int(pilot + 2 * maps)


def memory_gb(device) -> float:
    """Memory in use (GB = 1e9 bytes) after a step: on CUDA this process's use of the device as the driver reports it
    (:func:`process_device_bytes`: torch, Warp and CuPy pools and the context all count, other processes on the card
    do not), or the whole device's used memory (total - free) where the driver cannot say; on the CPU the
    process's peak resident set size."""
    dev = torch.device(device)
    if dev.type == "cuda":
        own = process_device_bytes(str(dev) if dev.index is not None else f"cuda:{torch.cuda.current_device()}")
        if own is not None:
            return round(own / 1e9, 3)
        free, total = torch.cuda.mem_get_info(dev)
        return round((total - free) / 1e9, 3)
    import resource
    import sys
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss          # kB on Linux, bytes on macOS
    return round(rss * (1 if sys.platform == "darwin" else 1024) / 1e9, 3)


def torch_gb(device) -> dict:
    """``torch_gb`` and ``torch_peak_gb`` (GB = 1e9 bytes) of torch's CUDA allocator on ``device`` (memory allocated
    now, and the most allocated since the process started or its last peak reset); empty strings on the CPU."""
    dev = torch.device(device)
    if dev.type != "cuda":
        return {"torch_gb": "", "torch_peak_gb": ""}
    return {"torch_gb": round(torch.cuda.memory_allocated(dev) / 1e9, 3),
            "torch_peak_gb": round(torch.cuda.max_memory_allocated(dev) / 1e9, 3)}
