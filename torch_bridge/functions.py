"""torch.autograd Functions around the stages of the ray-wave model.

Each Function wraps one stage of :class:`rwwarp.psf.RayWave` (one batch of point sources with a
fixed sampling plan) and runs in float64 unless said otherwise:

* :class:`TraceSplat`: surface-parameter table -> complex field on the DOE-plane windows
  (Warp coherent trace + splat, recorded on a ``wp.Tape``; backward replays the tape).
* the propagation to the sensor of every method, the ASM's included (band-limited ASM: its registered operator
  :class:`rwwarp.wave.methods.asm.AsmOperator`, the DOE phase applied as ``exp(1j alpha phi0)`` in torch), by the
  generic operator Functions of :mod:`torch_bridge.operator_function`
  (:func:`~torch_bridge.operator_function.operator_propagate`).
* :class:`FocalPropagate`: field on a focal plan's wave-plane grid (+ distance) -> power per sensor
  pixel (:class:`rwwarp.wave.focal.FocalPropagator`: the converging wave handled analytically; backward is
  the operator's adjoint and its exact distance derivative), by the generic operator Functions of
  :mod:`torch_bridge.operator_function`.
* :class:`MixedPrecision`: float64 forward -> float32, float32 gradient -> float64 (the paper's
  mixed precision: the optics in double, the network in single).
* :class:`QuantizeSTE`: DOE phase wrapped to [0, 2 pi) and quantised to N levels with a
  straight-through gradient.

Units: lengths in mm, wavelengths in um, phases in radians, powers as in :mod:`rwwarp.wave.propagate`
(field units^2 mm^2 per pixel; :func:`raywave_psf` divides by the entering power).

Gradient convention for complex tensors (torch's, and :mod:`rwwarp.wave.propagate`'s): for a real loss L
of a complex tensor z the gradient is ``dL/dRe z + 1j dL/dIm z``. Warp ``vec2d`` fields hold
``(Re, Im)``, so the incoming torch gradient maps to the Warp adjoint component-wise, without a
conjugation (checked with ``torch.autograd.gradcheck``).

**Discrete decisions are frozen.** A RayWave's ``__init__`` fixes the sampling plan (pitch, window,
FFT size, ray count), the sensor patch, the chief-ray carrier, the reference sphere centre and the
entrance pupil used to launch rays; the ray validity pattern (apertures, TIR) is re-evaluated on
every call but not differentiated (a ray crossing an aperture edge is a jump). The Functions
differentiate the smooth part for that plan; finite differences agree only when they reuse the
same RayWave. The box splat is piecewise linear in the ray positions: where a ray box edge sits
exactly on a sample-cell edge (symmetric layouts) the gradient is one of the one-sided ones.

**Devices.** On CPU, Warp arrays, torch tensors and PoCL buffers all live in host memory: the
field leaves Warp as a zero-copy torch view (``wp.to_torch``) and enters the OpenCL queue as a
host buffer (PoCL's buffers are host memory). On CUDA the same code hands device memory across
without copies: Warp -> torch by ``wp.to_torch``, torch -> CuPy by ``cupy.from_dlpack`` (the wave
backend wraps it in place), CuPy -> torch by ``torch.from_dlpack``, torch gradients -> Warp by
``wp.from_torch``; Warp launches run on torch's current stream
(``wp.ScopedStream(wp.stream_from_torch())``) and CuPy on an ``ExternalStream`` of the same
handle. Measured on an H100 (perf/results/bench_bridge_cuda_check.json): one forward + backward
of a 2-PSF map moves at most 36 kB per host <-> device copy (parameter tables, plan constants,
parameter gradients) while one DOE-plane field is 7.9 MB.
"""
from __future__ import annotations

import atexit
import contextlib
import sys
import weakref

import numpy as np
import torch
from rwwarp.doe import relief_phase, zone_relief_phase
from rwwarp.trace import COLUMNS as COL

__all__ = [
    "FocalPropagate",
    "MixedPrecision",
    "QuantizeSTE",
    "TraceSplat",
    "distance_from_table",
    "doe_orders_factor",
    "doe_scale",
    "focal_doe_factor",
    "focal_propagate",
    "load_table",
    "mixed_precision",
    "quantize_ste",
    "raywave_psf",
    "trace_splat",
    "bridge_state",
]


# ---------------------------------------------------------------------------------------------- helpers
_STATE = weakref.WeakKeyDictionary()


def bridge_state(obj) -> dict:
    """torch_bridge's own cache for a rwwarp object (a RayWave or a Tracer): the parameter table it was
    built with, the DOE sampling geometry, paraxial constants, wavelength scales. Kept here, keyed weakly
    by the object (freed with it), instead of as attributes set on rwwarp's objects."""
    st = _STATE.get(obj)
    if st is None:
        st = _STATE[obj] = {}
    return st


def _is_cuda(rw) -> bool:
    return str(rw.tracer.device).startswith("cuda")


class TorchAllocator:
    """Device memory from torch's caching allocator for Warp (:func:`warp.ScopedAllocator`) and CuPy
    (:func:`cupy.cuda.using_allocator`) on CUDA device ``index``: inside a bridge call all three libraries
    draw on one pool, so ``torch.cuda.max_memory_allocated`` is the step's whole peak and no library keeps
    a cache of its own beside torch's. Blocks belong to the stream current when allocated (the bridge runs
    everything on torch's current stream)."""

    def __init__(self, index: int):
        self.index = int(index)
        self.stream = None   # the CUDA stream handle (int) blocks are allocated on; set by the bridge's calls

    # Warp's Allocator protocol (bytes)
    def allocate(self, size_in_bytes: int) -> int:
        stream = self.stream if self.stream is not None else torch.cuda.current_stream(self.index).cuda_stream
        return int(torch.cuda.caching_allocator_alloc(max(int(size_in_bytes), 1), self.index, stream))

    def deallocate(self, ptr: int, size_in_bytes: int, _finalizing=sys.is_finalizing,
                   _delete=torch.cuda.caching_allocator_delete) -> None:
        # (the functions are bound at definition: arrays may be collected at interpreter exit, after the
        # modules' globals are gone; the driver frees the memory then)
        if _finalizing():
            return
        _delete(int(ptr))

    @property
    def cupy_malloc(self):
        """CuPy's allocator function (size -> MemoryPointer) over the same pool."""
        if getattr(self, "_cupy", None) is None:
            import cupy as cp
            self._cupy = cp.cuda.memory.PythonFunctionAllocator(
                lambda size, device_id: self.allocate(size), lambda ptr, device_id: self.deallocate(ptr, 0))
        return self._cupy.malloc


_ALLOCATORS: dict = {}


def _release_at_exit() -> None:
    """At exit, before the interpreter's teardown: rwwarp's backends release their caches
    (:func:`rwwarp.wave.backend.release_all`: CuPy arrays drawn from torch's pool through :class:`TorchAllocator`
    among them), then torch waits for its devices and empties its cache. Without it a design command on one H200
    ended with SIGSEGV after its work (``perf/tools/exit_probe.py``)."""
    from rwwarp.wave.backend import release_all
    release_all()
    if _ALLOCATORS and torch.cuda.is_initialized():
        torch.cuda.synchronize()
        torch.cuda.empty_cache()


atexit.register(_release_at_exit)


@contextlib.contextmanager
def _streams(rw):
    """Run Warp (and CuPy) on torch's current CUDA stream, drawing memory from torch's caching allocator
    (:class:`TorchAllocator`); a no-op on CPU."""
    if not _is_cuda(rw):
        yield
        return
    import warp as wp
    dev = wp.get_device(rw.tracer.device)
    tstream = torch.cuda.current_stream(torch.device(str(dev)))
    alloc = _ALLOCATORS.get(dev.ordinal)
    if alloc is None:
        alloc = _ALLOCATORS[dev.ordinal] = TorchAllocator(dev.ordinal)
    alloc.stream = tstream.cuda_stream   # looked up once per call, not per allocation
    with wp.ScopedStream(wp.stream_from_torch(tstream)), wp.ScopedAllocator(dev, alloc):
        try:
            import cupy as cp
        except ImportError:
            yield
            return
        with cp.cuda.ExternalStream(tstream.cuda_stream), cp.cuda.using_allocator(alloc.cupy_malloc):
            yield


def load_table(rw, table, table_host=None) -> np.ndarray:
    """Copy a parameter table ((n_surfaces + 1, N_PARAMS) float64, last row = sensor; layout
    ``rwwarp.trace.COLUMNS``) into ``rw``'s tracer (its Warp arrays, in place) and move the
    reference point of the DOE-plane grid to the plane's current vertex z. Returns the numpy table.
    A float64 tensor on the tracer's device with ``table_host`` (its values on the host) is copied device
    to device (``RayWave.load_params(device_table=)``): no host round trip of the parameters."""
    # the field grid lies on the DOE plane: its z follows the plane (see TraceSplat.backward)
    if torch.is_tensor(table) and table_host is not None and table.dtype == torch.float64 \
            and rw.tracer.np_dtype == np.float64 and str(table.device) == _torch_device_of(rw):
        import warp as wp
        return rw.load_params(table_host, device_table=wp.from_torch(table.detach().contiguous()))
    if table_host is not None:
        return rw.load_params(table_host)
    tab = table.detach().to("cpu", torch.float64).numpy() if torch.is_tensor(table) else np.asarray(table, np.float64)
    return rw.load_params(tab)


def _torch_device_of(rw) -> str:
    """The torch device string of ``rw``'s tracer ("cpu" or "cuda:N")."""
    d = str(rw.tracer.device)
    return "cuda:0" if d == "cuda" else d


def distance_from_table(rw, table):
    """DOE-plane-to-sensor distance (mm) from a parameter table tensor, (n_sources,)."""
    d = table[-1, COL.z] - table[rw.plane, COL.z]
    return d.expand(rw.nsrc)


def doe_scale(rw):
    """Per-source DOE wavelength remap ``(n(lambda)-1)/(n0-1) lambda0/lambda`` (numpy (S,)), or None."""
    s = rw.lens.surfaces[rw.plane]
    if s.type != "doe":
        return None
    st = bridge_state(rw)
    cached = st.get("doe_scale")
    if cached is None:
        from rwwarp import doe
        cached = np.array([doe.wavelength_scale(s.material, s.design_wavelength_um, w) for w in rw.wls])
        st["doe_scale"] = cached
    return cached


def _field_to_torch(field_wp, shape):
    import warp as wp
    t = wp.to_torch(field_wp)  # (N, 2) float64, zero-copy view of the Warp array
    return torch.view_as_complex(t).reshape(shape)


def _window_steps(rw, device, dtype=torch.float64):
    """``(n, g)``: the side of ``rw``'s field windows and the sample offsets from each window's origin (mm) on
    ``device``, (1, n) for one plan, (S, n) for a packed batch (:class:`rwwarp.wave.packed.PackedRayWave`: each
    source at its own pitch, in slots of the largest window; samples past a member's own window carry no
    field)."""
    lay = rw._layout()
    n = int(lay["n_stride"])
    if lay["ray_grids"] is None:
        return n, (torch.arange(n, dtype=dtype, device=device) * rw.plan.pitch_mm)[None, :]
    h = _on_device(rw, "packed_pitches", np.asarray(lay["pitches"], dtype=np.float64), device).to(dtype)
    return n, torch.arange(n, dtype=dtype, device=device)[None, :] * h[:, None]


def _grid_points(rw, device, dtype=torch.float64):
    """DOE-plane sample coordinates x (S, 1, n), y (S, n, 1) in mm, computed on ``device``."""
    _, g = _window_steps(rw, device, dtype)
    o = _on_device(rw, "origin_on", np.asarray(rw.origin, dtype=np.float64), device).to(dtype)
    return (o[:, 0, None, None] + g[:, None, :]), (o[:, 1, None, None] + g[:, :, None])


def upload(host, dtype=torch.float64, device=None) -> torch.Tensor:
    """Host data (a numpy array or a list) as a tensor of ``dtype`` on ``device`` without waiting for the
    device: copied with ``non_blocking=True``, which from pageable memory stages the bytes at once and does not
    drain the device's queue (a blocking upload waits for every queued kernel first: the host and the device
    then take turns instead of overlapping)."""
    a = np.asarray(host)
    if not a.flags.writeable:
        a = a.copy()      # a plan's read-only array (rwwarp.wave.batch_plan): torch shares no read-only memory
    t = torch.as_tensor(a, dtype=dtype)
    if device is None or torch.device(device).type == "cpu":
        return t
    return t.to(device, non_blocking=True)


def _on_device(rw, name: str, host: np.ndarray, device) -> torch.Tensor:
    """``host`` (a small float64 array of ``rw``'s constants) on ``device``, uploaded once per value: kept in
    ``bridge_state(rw)`` under ``name`` with its bytes (an upload from pageable memory waits for the
    device)."""
    st = bridge_state(rw)
    key = (str(device), host.tobytes())
    hit = st.get(name)
    if hit is None or hit[0] != key:
        hit = st[name] = (key, upload(host, torch.float64, device))
    return hit[1]


def _reference_z_factor(rw, device):
    """``+-k n (T_z - c_z) / |T - p|`` on the grid (S, n, n), on ``device``: d(phase of the field)/d(plane z)
    through the grid's z (the reference sphere put back at the grid points, see kernels/splat.py; the
    sign is the splat's: + for a sphere converging to T, - diverging)."""
    sign = np.where(rw.target[:, 2] >= rw.z_plane, 1.0, -1.0)
    # per source: window origin x, y; target T x, y; T_z - c_z; k n (signed), in one upload
    c = _on_device(rw, "reference_z_consts", np.column_stack(
        [rw.origin[:, 0], rw.origin[:, 1], rw.target[:, 0], rw.target[:, 1], rw.target[:, 2] - rw.chief_plane[:, 2],
         2.0 * np.pi / rw.lam_mm * rw.n_after * sign]).astype(np.float64), device)
    _, g = _window_steps(rw, device)
    x = c[:, 0, None, None] + g[:, None, :]
    y = c[:, 1, None, None] + g[:, :, None]
    dz = c[:, 4, None, None]
    dist = torch.sqrt((c[:, 2, None, None] - x) ** 2 + (c[:, 3, None, None] - y) ** 2 + dz ** 2)
    return c[:, 5, None, None] * dz / dist


# ---------------------------------------------------------------------------------------------- trace + splat
def trace_splat_forward(rw, table, record: bool, table_host=None):
    """Run ``rw.field()`` for the parameter ``table``; returns ``(field tensor (S, n, n) complex128,
    field Warp array, tape or None)``. Without ``record`` no tape and no gradient buffers are kept.
    ``table_host``: the same table as a numpy array, when the caller has it (no device-to-host copy,
    which would wait for the device)."""
    import warp as wp
    tr = rw.tracer
    n = int(rw._layout()["n_stride"])   # a packed batch: the slots of its largest window
    shape = (rw.nsrc, n, n)
    with _streams(rw):
        load_table(rw, table, table_host)
        if record:
            if not tr.requires_grad:
                raise ValueError("the RayWave was built without requires_grad=True: no gradients can be recorded")
            tape = wp.Tape()
            with tape:
                field_wp, _ = rw.field()
        else:
            tape = None
            with tr.without_gradients():
                field_wp, _ = rw.field()
    return _field_to_torch(field_wp, shape), field_wp, tape


class TraceSplat(torch.autograd.Function):
    """Surface parameters -> complex field on the DOE-plane windows of a RayWave.

    ``TraceSplat.apply(table, rw, table_host)``: ``table`` a float64 tensor (n_surfaces + 1, N_PARAMS) (last row
    the sensor; columns ``rwwarp.trace.COLUMNS``: vertex z in mm, curvature in 1/mm, conic,
    aspheric coefficients in mm^(1-2i), ...), ``rw`` a :class:`rwwarp.psf.RayWave` built with
    ``requires_grad=True``. Returns the complex128 field (S, n, n) on the windows, carrier and
    reference removed as in :meth:`RayWave.field` (energy convention: ``sum |u|^2 pitch^2`` is the
    traced power). ``table_host``: the same values as a numpy array, or None (then copied from
    ``table``, a copy that waits for the device).

    Forward copies the table into the tracer's Warp arrays and records ``rw.field()`` on a
    ``wp.Tape``; backward hands the incoming gradient to the field array, replays the tape, clones the
    parameter gradients and zeroes the tape. The grid's z follows the DOE plane's vertex z; its
    contribution to d/d(plane z) (the reference sphere put back on the grid) is added analytically.
    """

    @staticmethod
    def forward(ctx, table, rw, table_host=None):
        record = bool(ctx.needs_input_grad[0])
        u, field_wp, tape = trace_splat_forward(rw, table, record, table_host)
        ctx.rw, ctx.tape, ctx.field_wp, ctx.table_host = rw, tape, field_wp, table_host
        ctx.table_device = table.device
        ctx.save_for_backward(u, table.detach())
        return u

    @staticmethod
    def backward(ctx, grad_field):
        import warp as wp
        rw, tape, field_wp = ctx.rw, ctx.tape, ctx.field_wp
        if tape is None:
            return None, None, None
        u, table = ctx.saved_tensors
        g = grad_field.to(torch.complex128).contiguous()
        g_real = torch.view_as_real(g).reshape(-1, 2)
        with _streams(rw):
            # the adjoint kernels read the parameter arrays: restore this call's values (another forward
            # on the same RayWave may have loaded different ones since)
            load_table(rw, table, ctx.table_host)
            if getattr(ctx, "replayed", False):
                tape.zero()   # a second backward of this graph (retain_graph): every gradient from zero again
            g_wp = wp.from_torch(g_real.detach(), dtype=wp.vec2d)  # zero-copy view (CPU or CUDA)
            tape.backward(grads={field_wp: g_wp})
            # the parameter gradients stay on the device: zero-copy views of Warp's arrays, copied (to
            # float64) before they are zeroed
            grads = _take_param_grads(rw.tracer)
            ctx.replayed = True
        grads = grads.to(ctx.table_device)
        if rw.use_reference:
            fac = _reference_z_factor(rw, u.device)
            dz = -(torch.imag(torch.conj(g) * u) * fac).sum()
            grads[rw.plane, COL.z] = grads[rw.plane, COL.z] + dz.to(grads.device)
        ctx.table_host = None
        return grads, None, None


def _take_param_grads(tracer):
    """The gradients of ``tracer``'s parameter arrays as a float64 tensor (n_surfaces + 1, N_PARAMS) on its device,
    and those arrays' gradients zeroed: they are the tracer's own, read by every later call, while the tape's other
    gradient arrays belong to this call's rays and die with its graph (a replay zeroes them first: TraceSplat).
    One copy and one zeroing for a tracer whose rows are views of one array (``params_block``), not one a
    surface (issue 25: on a GPU each is a launch)."""
    import warp as wp
    block = getattr(tracer, "params_block", None)
    if block is not None:
        grads = wp.to_torch(block.grad).to(torch.float64, copy=True)
        block.grad.zero_()
        return grads
    grads = torch.stack([wp.to_torch(p.grad).to(torch.float64, copy=True) for p in tracer.params])
    for p in tracer.params:
        p.grad.zero_()
    return grads


def trace_splat(table, rw, table_host=None):
    """:class:`TraceSplat` where a gradient is wanted (grad mode on and ``table`` requiring grad),
    else a plain forward with no tape and no gradient buffers (``torch.no_grad()`` is honoured: a
    Function's ``needs_input_grad`` is not). ``table_host``: see :class:`TraceSplat`."""
    if torch.is_grad_enabled() and table.requires_grad:
        return TraceSplat.apply(table, rw, table_host)
    return trace_splat_forward(rw, table, record=False, table_host=table_host)[0]


def power_sums(rw, device):
    """``(entering, traced)`` power per source of ``rw``'s last :meth:`~rwwarp.psf.RayWave.field` call as
    float64 tensors (S,) on ``device`` (unit source radiance), copied on the device from
    :meth:`~rwwarp.psf.RayWave.power_sums_array`: no host round trip, so the device queue is not drained."""
    import warp as wp
    t = wp.to_torch(rw.power_sums_array()).reshape(rw.nsrc, 4)[:, :2]
    t = t.to(device=device, dtype=torch.float64, copy=True)
    return t[:, 0], t[:, 1]


def paper_amplitude(u, rw):
    """The paper's amplitude convention on a traced field (S, n, n): one differentiable scale per source
    so that the field carries the traced power (:func:`rwwarp.wave.splat.paper_rescale`, in torch; with
    ``rw.pixel_values == "flux"`` its z-flux through the plane; a packed tile: each member's own pitch)."""
    from rwwarp.wave.splat import paper_rescale_layout
    return paper_rescale_layout(rw, u, power_sums(rw, u.device)[1], torch)


# ---------------------------------------------------------------------------------------------- propagation
def spatial_tiles(size: int, tile_px: int | None):
    """Tiles ``(r0, r1, c0, c1)`` of a ``size`` x ``size`` sensor patch, ``tile_px`` pixels a side (the
    last ones ragged); ``[None]`` (one untiled call) when ``tile_px`` is None or covers the patch."""
    if tile_px is None or int(tile_px) >= size:
        return [None]
    t = max(1, int(tile_px))
    return [(r, min(r + t, size), c, min(c + t, size)) for r in range(0, size, t) for c in range(0, size, t)]


def _torch_release():
    """Give torch's cached CUDA blocks back to the driver (a release hook of the rwwarp backend)."""
    torch.cuda.synchronize()
    torch.cuda.empty_cache()


def backend_for(device: str):
    """rwwarp's backend for ``device``; on CUDA it gets a release hook that empties torch's caching
    allocator when a propagation allocation fails, so torch's cached blocks and rwwarp's buffers
    share the GPU instead of one allocator starving the other."""
    from rwwarp.wave import backend as bk
    be = bk.get_backend(device)
    if be.kind == "cuda":
        be.add_release_hook(_torch_release)
    return be


# ---------------------------------------------------------------------------------------------- focal propagation
def _xp_of(t):
    """(array module, zero-copy view) of a tensor: numpy on the CPU, CuPy (DLPack) on CUDA."""
    t = t.detach().contiguous()
    if t.is_cuda:
        import cupy
        return cupy, cupy.from_dlpack(t)
    return np, t.numpy()


def _from_xp(a, device):
    if isinstance(a, np.ndarray):
        return torch.from_numpy(a).to(device)
    return torch.from_dlpack(a)


class FocalPropagate:
    """Wave-plane field -> power per sensor pixel by the focal propagation of a RayWave planned with
    ``method="focal"`` (:class:`rwwarp.wave.focal.FocalPropagator`): the generic operator path
    (:func:`torch_bridge.operator_function.operator_propagate`: :class:`~torch_bridge.operator_function.OperatorApply`
    of ``rw.focal_operator(distance)``, then :class:`~torch_bridge.operator_function.NodePixels`).

    ``FocalPropagate.apply(field, distance, rw, distance_host=None)``: ``field`` complex128 (S, n, n) on the focal
    plan's wave-plane grid, carrier removed and any DOE orders already applied (``sum_m c_m exp(i m phi0)``,
    :func:`doe_orders_factor`); ``distance`` the wave-plane-to-sensor distance, float64 (S,) (mm; all
    entries equal: one lens). Returns float64 (S, size, size), the pixel values ``rw.pixel_values`` names integrated
    over each pixel: the z-flux ``Re(conj(U) U_w)`` (``"flux"``, :meth:`~rwwarp.wave.focal.FocalPropagator.forward_pair`)
    or ``|U|^2`` (``"intensity"``).

    Backward: the operator's adjoint for ``field`` (exact conjugate transpose) and, for ``distance``,
    its exact derivative :meth:`~rwwarp.wave.focal.FocalPropagator.distance_derivative` at the fixed plan
    (grids, band mask, carrier): finite differences on the same RayWave agree to rounding.
    """

    @staticmethod
    def apply(field, distance, rw, distance_host=None):
        from .operator_function import operator_propagate
        return operator_propagate(field, distance, rw, distance_host, method="focal")


def doe_orders_factor(phi0, orders):
    """``sum_m c_m exp(1j m phi0)`` per source (S, n, n) complex128 from the unwrapped DOE phase ``phi0``
    (rad, float64 (S, n, n)) and the orders a focal plan kept (``rw.focal["orders"]``: per source a list
    of ``(m, c_m)``); differentiable in ``phi0`` (:func:`rwwarp.wave.focal.doe_order_series` in torch)."""
    from rwwarp.wave.focal import doe_order_series
    return doe_order_series(phi0, orders, None, torch)


def focal_doe_factor(rw, phi0):
    """The DOE's transmission on a focal plan's wave-plane grid, (S, n, n) complex128, or None when the wave
    plane is no DOE. ``phi0``: the unwrapped DOE phase (rad, (S, n, n)), differentiable. With a DOE
    profile in the plan: the kept diffraction orders (:func:`doe_orders_factor`). A DOE that was flat when
    planned (no orders were planned, e.g. a blank DOE about to learn): ``exp(1j alpha phi0)``, the
    continuous transmission, exact at the planned (zero) phase with its exact derivative ``1j alpha``
    (``alpha``: the wavelength remap, :func:`doe_scale`); the design loop replans once it grows."""
    if phi0 is None:
        return None
    if rw.focal["profile"] is not None:
        # the kept orders, the chief ray's wrap zone exact: the same function as rwwarp's, in torch
        from rwwarp.wave.focal import doe_order_series
        return doe_order_series(phi0, rw.focal["orders"], rw.focal.get("central_zone"), torch)
    alpha = upload(doe_scale(rw), torch.float64, phi0.device)
    # the blank relief's zone 0, remapped to the wavelength (rwwarp.doe.zone_relief_phase)
    return torch.exp(1j * zone_relief_phase(phi0, 0.0, alpha[:, None, None]))


def focal_propagate(field, distance, rw, distance_host=None):
    """:class:`FocalPropagate` (a plain forward when no gradient is wanted). ``distance_host``: the
    distance's value (mm, a float) when the caller has it on the host, so the operator's set-up does not
    wait for the device to read it."""
    return FocalPropagate.apply(field, distance, rw, distance_host)


# ---------------------------------------------------------------------------------------------- checkpointing
class Recompute(torch.autograd.Function):
    """Checkpoint of one tile of sources: ``Recompute.apply(run, *tensors)`` with ``run(*tensors, record=...)``
    returning the tile's output. Forward without tape or graph, backward recomputes under a fresh tape
    (the template of warp's examples/optim/example_fluid_checkpoint.py), so a tile's tape lives
    only while its own gradient is formed."""

    @staticmethod
    def forward(ctx, run, *tensors):
        ctx.run = run
        ctx.save_for_backward(*tensors)
        return run(*tensors, record=False)

    @staticmethod
    def backward(ctx, grad_out):
        ts = [t.detach().requires_grad_(t.requires_grad) for t in ctx.saved_tensors]
        with torch.enable_grad():
            out = ctx.run(*ts, record=True)
        need = [t for t in ts if t.requires_grad]
        got = torch.autograd.grad(out, need, grad_out, allow_unused=True)
        it = iter(got)
        grads = [next(it) if t.requires_grad else None for t in ts]
        ctx.run = None
        return (None, *grads)


# ---------------------------------------------------------------------------------------------- precision, quantisation
class MixedPrecision(torch.autograd.Function):
    """float64 -> float32 on the way forward, the float32 gradient -> float64 on the way back.

    The paper's mixed precision: optics in double, the network in single precision. Complex input
    maps complex128 -> complex64.
    """

    @staticmethod
    def forward(ctx, x):
        ctx.dtype = x.dtype
        return x.to(torch.complex64 if x.is_complex() else torch.float32)

    @staticmethod
    def backward(ctx, g):
        return g.to(ctx.dtype)


def mixed_precision(x):
    """:class:`MixedPrecision` applied to ``x`` (float64 -> float32)."""
    return MixedPrecision.apply(x)


class QuantizeSTE(torch.autograd.Function):
    """DOE relief phase: ``phi`` (rad) wrapped to [0, 2 pi) and quantised to ``levels`` levels
    (``k 2 pi / levels``, the top level folding to 0), with a straight-through gradient (identity).
    ``levels=None``: wrap only (its derivative is 1 a.e.). The forward is :func:`rwwarp.doe.relief_phase`
    in torch (the one implementation numpy uses too); this class adds only the backward."""

    @staticmethod
    def forward(ctx, phi, levels):
        return relief_phase(phi, levels, torch)

    @staticmethod
    def backward(ctx, g):
        return g, None


def quantize_ste(phi, levels=None):
    """:class:`QuantizeSTE` applied to ``phi`` (rad)."""
    return QuantizeSTE.apply(phi, levels)


# ---------------------------------------------------------------------------------------------- chained
def raywave_psf(rw, table, phi0=None, distance=None):
    """The ray-wave PSFs of a RayWave batch as a differentiable tensor (S, size, size): fraction of
    the entering power per sensor pixel (as :func:`rwwarp.psf`).

    ``table``: float64 parameter table (n_surfaces + 1, N_PARAMS); ``phi0``: DOE phase on the windows
    (rad, (S, n, n)) or None for no DOE; ``distance``: DOE-to-sensor distance (mm, (S,)), default from
    the table (so the last thickness learns). Paper amplitude convention: the global field scale is
    formed in torch (differentiable).
    """
    u = trace_splat(table, rw)
    if rw.amplitude != "energy":
        u = paper_amplitude(u, rw)
    if distance is None:
        distance = distance_from_table(rw, table)
    from .operator_function import operator_propagate
    power = operator_propagate(u, distance, rw, phi0=phi0)
    return power / power_sums(rw, power.device)[0][:, None, None]
