"""Host side of the coherent ray tracer: sources, pupil sampling, one Warp launch per surface.

Kernels are in :mod:`rwwarp.kernels.trace`. Lengths in mm, wavelengths in um, field angles in
degrees. Precision (``"float64"`` default, ``"float32"``) and device (``"cpu"``, ``"cuda:0"``) are
explicit arguments.

Typical use::

    tr = Tracer(lens, wavelengths_um=[0.5876], device="cpu")
    rays = tr.trace(fields_deg=[0.0, 14.0], grid=101)           # to the sensor plane
    xy, ok = rays.numpy()["pos"][..., :2], rays.numpy()["valid"]
"""
from __future__ import annotations

import concurrent.futures
import contextlib
import math
import os
import threading
from dataclasses import dataclass

import numpy as np
import warp as wp

from .wave.backend import get_backend, release_warp_pool  # noqa: F401  (release_warp_pool: public here too)
from .device_upload import upload_packed  # noqa: F401  (also read as rwwarp.trace.upload_packed)
from .errors import GeometryError, LensError
from .grad_block import GradBlock
from .kernels import trace as ktrace
from . import paraxial
from .trace_fused import fused_tables, step_kernels
from .fields import _field_pair, as_field_list, field_direction, field_label, field_pairs  # noqa: F401  (their home: rwwarp.fields)
from .pupil import device_disc_cells, disc_cell_fractions, disc_cells, pupil_grid  # noqa: F401  (re-exported)

wp.config.quiet = True
wp.config.log_level = wp.LOG_WARNING  # no per-module load messages (compile time is reported by perf/)
_WP_INIT = False


def init_warp():
    """Initialise Warp once (quietly)."""
    global _WP_INIT
    if not _WP_INIT:
        wp.init()
        _WP_INIT = True


#: surface kinds intersected by Newton iterations (``intersect_kernel``) before their surface kernel
_CURVED = (ktrace.KIND_REFRACT, ktrace.KIND_REFLECT, ktrace.KIND_PHASE)
#: fewest rays per CPU thread worth a parallel chunk (below it the launch overhead dominates)
PARALLEL_MIN_RAYS = 32768
@dataclass(frozen=True)
class SurfaceColumns:
    """Columns of the surface parameter table (:attr:`Tracer.params_np`, ``(n_surfaces + 1, n_params)``
    float64, last row the sensor; :meth:`rwwarp.psf.RayWave.load_params` takes it): the public names of
    the layout ``rwwarp.kernels.trace`` defines for the device. ``z`` vertex z (mm), ``curvature`` (1/mm),
    ``conic``, ``asph0`` the first of ``n_asph`` even aspheric terms (r^4 .. , mm^-3 ..), ``power`` thin
    lens power (1/mm), ``uinv`` thin lens 1 / object distance (1/mm, 0 at infinity), ``v`` thin lens image
    distance (mm, 0 at infinity); a phase surface's (:mod:`rwwarp.phase_surface`) diffraction order
    ``phase_order``, normalisation radius ``phase_norm`` (mm) and ``n_phase`` terms from ``phase0`` (rad)."""
    z: int = ktrace.P_Z
    curvature: int = ktrace.P_C
    conic: int = ktrace.P_K
    asph0: int = ktrace.P_A0
    n_asph: int = ktrace.N_ASPH
    power: int = ktrace.P_POWER
    uinv: int = ktrace.P_UINV
    v: int = ktrace.P_V
    phase_order: int = ktrace.P_PH_M
    phase_norm: int = ktrace.P_PH_R
    phase0: int = ktrace.P_PH0
    n_phase: int = ktrace.N_PHASE
    n_params: int = ktrace.N_PARAMS


#: The surface parameter table's columns (:class:`SurfaceColumns`)
COLUMNS = SurfaceColumns()

#: Copies of a surface's parameter row the rays read while recording (:class:`Tracer` ``grad_replicas``):
#: on a GPU the adjoint's float64 atomic additions of ~10^6 rays into one row serialise; over 1024 copies
#: each address takes ~10^3 of them. On the CPU (one thread) a few copies keep the path exercised.
GRAD_REPLICAS_GPU = 1024
GRAD_REPLICAS_CPU = 4
#: Rows of the replicated parameter table one thread of ``replicate_kernel`` writes (and whose gradients its
#: adjoint sums before one atomic addition)
REPLICATE_ROWS_PER_THREAD = 32
_POOL = None
_POOL_LOCK = threading.Lock()


def _pool(workers: int):
    """The module's thread pool for parallel CPU trace chunks (grown to ``workers``)."""
    global _POOL
    with _POOL_LOCK:
        if _POOL is None or _POOL._max_workers < workers:
            _POOL = concurrent.futures.ThreadPoolExecutor(max_workers=workers, thread_name_prefix="rwwarp-trace")
        return _POOL


def run_chunks(fn, chunks, outs, kernels=(), device="cpu"):
    """Call ``fn(chunk, out)`` for each ``(lo, hi)`` chunk (or None: everything) with its ``out``, in the module's
    thread pool when there are several (Warp's CPU kernels release the GIL). ``kernels`` (launched by ``fn``) are
    loaded on ``device`` first: two threads loading one module at their first launch can crash Warp (a cold map)."""
    if len(chunks) == 1:
        fn(chunks[0], outs[0])
        return
    for k in kernels:
        wp.load_module(k.module, device=device)   # ~3 us once loaded
    futures = [_pool(len(chunks)).submit(fn, c, o) for c, o in zip(chunks, outs)]
    for f in futures:
        f.result()


def cpu_threads() -> int:
    """CPU cores this process may run on (the default number of trace threads on the CPU)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def warp_scalar(dtype: str):
    """Warp scalar type for ``"float64"`` / ``"float32"``."""
    if dtype in ("float64", np.float64, "f8"):
        return wp.float64
    if dtype in ("float32", np.float32, "f4"):
        return wp.float32
    raise ValueError(f"dtype must be 'float64' or 'float32', got {dtype!r}")


def warp_device(device: str) -> str:
    """Warp device name for an rwwarp device string (``cpu``, ``cuda``, ``cuda:N``, ``opencl:P:D`` -> cpu)."""
    if device is None or device == "cpu" or device.startswith("opencl"):
        return "cpu"
    if device == "cuda":
        return "cuda:0"
    if device.startswith("cuda"):
        return device
    raise ValueError(f"unknown device {device!r}: use 'cpu', 'cuda', 'cuda:N' or 'opencl:P:D'")


def _with_release(device, alloc):
    """``alloc()`` (Warp arrays on ``device``); on CUDA, when Warp cannot allocate, the device's rwwarp
    backend frees its caches and calls its release hooks (torch's caching allocator, where
    torch_bridge registered it), then ``alloc()`` runs once more."""
    if not str(device).startswith("cuda"):
        return alloc()
    return get_backend(str(device))._allocate(alloc)


@dataclass
class Rays:
    """Rays on the device (structure of arrays), ``n_sources x n_pupil`` of them, source-major."""

    pos: wp.array
    dir: wp.array
    opl: wp.array
    valid: wp.array
    wl: wp.array
    weight: wp.array
    n_sources: int
    n_pupil: int

    def numpy(self) -> dict:
        """Host copies reshaped to ``(n_sources, n_pupil, ...)``."""
        s, p = self.n_sources, self.n_pupil
        return {"pos": self.pos.numpy().reshape(s, p, 3), "dir": self.dir.numpy().reshape(s, p, 3),
                "opl": self.opl.numpy().reshape(s, p), "valid": self.valid.numpy().reshape(s, p).astype(bool),
                "weight": self.weight.numpy().reshape(s, p)}

    def count_valid(self) -> np.ndarray:
        """Number of valid rays per source."""
        return self.valid.numpy().reshape(self.n_sources, self.n_pupil).sum(axis=1)


class Tracer:
    """Sequential coherent ray tracer for one lens (float64 by default), one launch per surface.

    Parameters
    ----------
    lens : Lens
    wavelengths_um : list of float
        Wavelengths (um) the refractive-index tables are built for; sources refer to them by index.
    device : str
        ``"cpu"`` or ``"cuda"``/``"cuda:N"``.
    dtype : str
        ``"float64"`` (default) or ``"float32"``.
    requires_grad : bool
        Allocate gradient buffers for surface parameters and rays (for ``wp.Tape``).
    threads : int, optional
        CPU only, without gradients: trace this many ray chunks in parallel (default: the cores this
        process may use, :func:`cpu_threads`). 1 traces in the calling thread.
    grad_replicas : int, optional
        With ``requires_grad``: copies of each surface's parameter row the rays read (a power of two;
        ray ``i`` reads copy ``i mod R``), so the adjoint's atomic additions into the parameters'
        gradients spread over ``R`` addresses (see ``rwwarp.kernels.trace``). Default
        :data:`GRAD_REPLICAS_GPU` on a GPU, :data:`GRAD_REPLICAS_CPU` on the CPU (one thread: no
        contention, the copies only cost their sum).
    deterministic : bool
        With ``requires_grad`` on a GPU: the parameter gradients come out the same bits on every run. Every
        ray gets its own copy of each surface's row (``R`` = the ray count rounded up to a power of two:
        ``2 x 8 x N_PARAMS = 640`` bytes a ray and traced surface, gradient included), made in two levels
        (512 rows, then the rest) whose adjoints sum in a fixed order. The CPU is deterministic either way.
    """

    def __init__(self, lens, wavelengths_um, device: str = "cpu", dtype: str = "float64",
                 requires_grad: bool = False, threads: int | None = None, grad_replicas: int | None = None,
                 deterministic: bool = False):
        init_warp()
        self.threads = cpu_threads() if threads is None else max(1, int(threads))
        self.lens = lens
        self.wavelengths_um = [float(w) for w in wavelengths_um]
        self.device = warp_device(device)
        self.scalar = warp_scalar(dtype)
        self.np_dtype = np.float64 if self.scalar == wp.float64 else np.float32
        self.K = ktrace.make_trace_kernels(self.scalar)
        self.requires_grad = requires_grad
        # True inside without_gradients() of a tracer built with requires_grad: its forward-only pass must give the
        # bits its recorded pass gives (a checkpointed tile is run both ways), so no forward-only kernel variant
        self.recordable_pass = False
        if grad_replicas is None:
            grad_replicas = GRAD_REPLICAS_CPU if self.device == "cpu" else GRAD_REPLICAS_GPU
        r = int(grad_replicas)
        if r < 1 or r & (r - 1):
            raise ValueError(f"Tracer: grad_replicas must be a power of two >= 1, got {grad_replicas!r}")
        self.grad_replicas = r
        self.deterministic = bool(deterministic)
        #: None, or a dict of work arrays reused by every forward-only launch sequence of this tracer (its traces,
        #: and the splat's and reductions' arrays of :meth:`rwwarp.wave.raywave.RayWave.field`): set on a batch kept
        #: for repeated runs (:class:`rwwarp.wave.plan_cache.PlanCache`), whose rays and sums are read before the
        #: next run, and shared by the batches of a CPU map (:func:`rwwarp.map_run._wave_map`), each batch's read before
        #: the next runs; the rays and arrays a run returns are then overwritten by the next
        self.pool = None
        wl0 = self.wavelengths_um[0]
        self.pupils = paraxial.pupils(lens, wl0)
        nw = len(self.wavelengths_um)
        idx = np.stack([lens.indices(w) for w in self.wavelengths_um], axis=1)  # (n_surf, n_wl)
        self.n_obj_np = np.ones(nw)
        self.index_np = idx
        self.params_np = self._surface_params()
        self.kinds = [self._kind(s) for s in lens.surfaces]
        self._upload()

    # -------------------------------------------------------------- setup
    def _kind(self, s):
        if s.type == "standard" and s.mirror:
            return ktrace.KIND_REFLECT
        if s.type == "standard" and s.phase is not None:
            return ktrace.KIND_PHASE
        return {"standard": ktrace.KIND_REFRACT, "thin_lens": ktrace.KIND_THIN}.get(s.type, ktrace.KIND_PLANE)

    def _surface_params(self, object_distance=None) -> np.ndarray:
        lens = self.lens
        z = lens.vertex_z
        out = np.zeros((len(lens.surfaces) + 1, ktrace.N_PARAMS))
        stop = lens.stop_index
        for i, s in enumerate(lens.surfaces):
            p = out[i]
            p[ktrace.P_Z] = z[i]
            p[ktrace.P_C] = s.curvature if s.type == "standard" else 0.0
            p[ktrace.P_K] = s.conic if s.type == "standard" else 0.0
            if s.type == "standard":
                p[ktrace.P_A0:ktrace.P_A0 + len(s.aspheric)] = s.aspheric
                p[ktrace.P_A2] = s.a2
                if any(s.odd_aspheric):
                    p[ktrace.P_ODD_ON] = 1.0
                    p[ktrace.P_ODD0:ktrace.P_ODD0 + len(s.odd_aspheric)] = s.odd_aspheric
                if s.phase is not None:
                    from .phase_surface import phase_columns
                    order, rnorm, coeffs = phase_columns(s)
                    p[ktrace.P_PH_M] = order
                    p[ktrace.P_PH_R] = rnorm
                    p[ktrace.P_PH0:ktrace.P_PH0 + len(coeffs)] = coeffs
            sd = s.semi_diameter
            if i == stop and lens.entrance_pupil_diameter is not None:
                sd = None  # floating stop: the entrance pupil sets the beam
            p[ktrace.P_SD] = -1.0 if sd is None else sd
            p[ktrace.P_SQUARE] = 1.0 if s.shape == "square" else 0.0
            ob = s.obscuration
            if ob is not None:
                circ = ob["shape"] == "circle"
                p[ktrace.P_OB_KIND] = 1.0 if circ else 2.0
                p[ktrace.P_OB_X] = ob["radius"] if circ else ob["half_x"]
                p[ktrace.P_OB_Y] = 0.0 if circ else ob["half_y"]
            if s.type == "thin_lens":
                uinv, v = paraxial.thin_lens_conjugates(lens, self.wavelengths_um[0], i, object_distance)
                p[ktrace.P_POWER] = 1.0 / s.focal_length
                p[ktrace.P_UINV] = uinv
                p[ktrace.P_V] = 0.0 if math.isinf(v) else v  # 0: image at infinity (see kernels.trace)
        out[-1, ktrace.P_Z] = lens.sensor_z
        out[-1, ktrace.P_SD] = -1.0
        return out

    def own_params(self):
        """Give this tracer parameter arrays of its own before they are written in place
        (:meth:`rwwarp.wave.raywave.RayWave.load_params`): without gradients they are read-only views of a cached
        upload (:func:`rwwarp.device_upload.upload_packed`) that every tracer of the same values shares, and a write
        there changed every later tracer of that lens (a test's moved wave plane changed another test's plans)."""
        if getattr(self, "_own_params", False) or self.requires_grad:
            return
        self.params = [wp.clone(a) for a in self.params]
        self._own_params = True

    def _upload(self):
        """Surface parameters and index tables to the device: one upload (read-only views) without
        gradients; with ``requires_grad`` one (n_surfaces + 1, N_PARAMS) array with its gradient,
        :attr:`params_block`, whose rows are :attr:`params` (views: the table is loaded, and its gradient read and
        zeroed, in one operation each instead of one a surface)."""
        dev, sc, g = self.device, self.scalar, self.requires_grad
        fdt = self.np_dtype
        tables = [(self.n_obj_np, fdt, sc)] + [(self.index_np[i], fdt, sc) for i in range(self.index_np.shape[0])]
        # vacuum wavelengths / (2 pi) in mm (the phase surfaces' grating equation and path; a literal 2 pi in a
        # kernel would be a float32 constant)
        tables.append((np.array(self.wavelengths_um, dtype=np.float64) * 1e-3 / (2.0 * math.pi), fdt, sc))
        if g:
            self.params_block = wp.array(np.ascontiguousarray(self.params_np, dtype=fdt), dtype=sc, device=dev,
                                         requires_grad=True)
            self.params = [self.params_block[k] for k in range(self.params_block.shape[0])]
            views = upload_packed(tables, dev, cache=True)
        else:
            self.params_block = None
            views = upload_packed([(p, fdt, sc) for p in self.params_np] + tables, dev, cache=True)
            self.params = views[:len(self.params_np)]
            views = views[len(self.params_np):]
        nw = len(self.wavelengths_um)
        self.n_obj = views[0]
        self.lam_bar = views[-1]
        self.n_tables = views[1:-1]
        self.n_before = [self.n_obj] + self.n_tables[:-1]
        self._n_wl = nw

    def set_params(self, params_np: np.ndarray):
        """Replace the per-surface parameter table (``(n_surfaces + 1, N_PARAMS)``, last row = sensor)."""
        self.params_np = np.array(params_np, dtype=np.float64)
        self._upload()

    # -------------------------------------------------------------- sources
    @contextlib.contextmanager
    def without_gradients(self):
        """Within the block the tracer traces as if built without ``requires_grad``: no gradient buffers, no
        parameter-row copies, ray states reused between surfaces (a pilot trace, a forward-only pass). The
        rays are the same as with gradients."""
        keep, keep_pass = self.requires_grad, self.recordable_pass
        self.requires_grad, self.recordable_pass = False, keep or keep_pass
        try:
            yield self
        finally:
            self.requires_grad, self.recordable_pass = keep, keep_pass

    def sources(self, fields_deg, wavelength_index=0, ray_aiming: bool = False, object_distance=None):
        """Per-source arrays for the generation kernel.

        ``fields_deg``: list of fields (number = y angle, or (x, y) pair), degrees.
        ``wavelength_index``: int or list (one per field). ``object_distance``: mm, default the lens's.
        Returns a dict of numpy arrays.

        ``ray_aiming=False`` is the default, deliberately, everywhere (tracer, spot analysis, all PSF
        models): as Zemax's default, each field's pupil grid is laid on the paraxial entrance pupil, so
        the chief ray passes the real stop off centre by the pupil aberration (Cooke triplet at 20 deg:
        0.226 mm) and the reference values of Zemax, optiland and ray-optics without aiming are
        reproduced. ``True`` moves each pupil centre so the real chief ray hits the stop centre (to
        1e-12 mm; clear apertures are ignored while aiming, as Zemax does).
        """
        fields = as_field_list(fields_deg)
        n = len(fields)
        wli = np.broadcast_to(np.asarray(wavelength_index, dtype=np.int32), (n,)).copy()
        if np.any(wli < 0) or np.any(wli >= self._n_wl):
            raise LensError(f"wavelength index out of range 0..{self._n_wl - 1}: {wli}")
        od = self.lens.object_distance if object_distance is None else float(object_distance)
        pup = self.pupils
        dirs = np.zeros((n, 3))
        pos = np.zeros((n, 3))
        finite = np.zeros(n, dtype=np.int32)
        aim = np.zeros((n, 3))
        aim[:, 2] = pup.entrance_z
        for k, f in enumerate(fields):
            fx, fy = _field_pair(f)
            if not (abs(fx) < 89.0 and abs(fy) < 89.0):
                raise LensError(f"field angle must be within +-89 deg, got {f}", field=f)
            d = field_direction((fx, fy))
            dirs[k] = d
            if math.isfinite(od):
                finite[k] = 1
                dist = pup.entrance_z + od
                pos[k] = [-math.tan(math.radians(fx)) * dist, -math.tan(math.radians(fy)) * dist, -od]
        shape = self.lens.surfaces[self.lens.stop_index].shape
        half = np.full(n, pup.entrance_radius)
        src = {"pos": pos, "dir": dirs, "finite": finite, "aim": aim, "half_x": half, "half_y": half.copy(),
               "wl": wli, "shape": shape, "fields": fields, "object_distance": od}
        if ray_aiming:
            self._aim_at_stop(src)
        return src

    def _params_for(self, object_distance):
        """The surface parameter views for sources at ``object_distance`` (mm, inf allowed): :attr:`params`
        unless the lens has thin lenses and the distance differs from the lens's own (an ideal lens's
        path correction depends on its conjugates); those rows are then rebuilt (cached)."""
        lens = self.lens
        od = lens.object_distance if object_distance is None else float(object_distance)
        if od == lens.object_distance or not any(s.type == "thin_lens" for s in lens.surfaces):
            return self.params
        if self.requires_grad:
            raise LensError(f"object distance {od} mm differs from the lens's ({lens.object_distance} mm) and "
                            "the lens has an ideal thin lens: with gradients, set the distance on the lens "
                            "(lens.replace(object_distance=...))", file=lens.source)
        cache = getattr(self, "_od_params", None)
        if cache is None or cache[0] is not self.params_np:
            cache = self._od_params = (self.params_np, {})
        if od not in cache[1]:
            table = np.array(self.params_np, dtype=np.float64)
            fresh = self._surface_params(od)
            for i, s in enumerate(lens.surfaces):
                if s.type == "thin_lens":
                    table[i, [ktrace.P_UINV, ktrace.P_V]] = fresh[i, [ktrace.P_UINV, ktrace.P_V]]
            cache[1][od] = upload_packed([(row, self.np_dtype, self.scalar) for row in table], self.device,
                                         cache=True)
        return cache[1][od]

    def _unclipped_params(self):
        """The surface parameter views with every clear aperture removed (for ray aiming)."""
        if getattr(self, "_noclip", None) is None or self._noclip[0] is not self.params_np:
            p = np.array(self.params_np, dtype=np.float64)
            p[:, ktrace.P_SD] = -1.0
            p[:, ktrace.P_OB_KIND] = 0.0  # nor obscurations (the chief ray of an obscured pupil is still aimed)
            views = upload_packed([(row, self.np_dtype, self.scalar) for row in p], self.device, cache=True)
            self._noclip = (self.params_np, views)
        return self._noclip[1]

    def _aim_at_stop(self, src, iterations: int = 20, tol_mm: float = 1e-12):
        """Move each source's pupil centre on the EP plane so its chief ray hits the stop centre.

        Newton iterations on the 2-D stop coordinates of the chief ray, traced with the clear apertures
        removed (as Zemax aims): the chief ray of a vignetted field is still defined, and an iterate
        that passes outside a surface's clear aperture is not a failure. Only a ray that misses a
        surface altogether (or total internal reflection) makes aiming fail, with the field named."""
        stop = self.lens.stop_index
        if stop == 0 and self.lens.surfaces[0].type != "standard":
            # the stop is the first (plane) surface: the paraxial EP is the stop itself
            return
        n = len(src["wl"])
        aim = src["aim"].copy()
        h = 1e-4 * max(self.pupils.entrance_radius, 1e-3)
        params = self._unclipped_params()
        for _ in range(iterations):
            trial = np.concatenate([aim, aim + [h, 0, 0], aim + [0, h, 0]])
            sub = {k: (np.concatenate([v, v, v]) if isinstance(v, np.ndarray) else v) for k, v in src.items()}
            sub["aim"] = trial
            rays = self._run(sub, np.zeros(1), np.zeros(1), 1.0, upto=stop + 1, params=params)
            xy = rays.pos.numpy()[:, :2].reshape(3, n, 2)
            ok = rays.valid.numpy().reshape(3, n)
            if not ok.all():
                bad = [src["fields"][k] for k in range(n) if not ok[:, k].all()]
                raise GeometryError("ray aiming failed: the chief ray misses a surface before the stop (or is "
                                    "totally reflected)", file=self.lens.source, surface=self.lens.surface_label(stop),
                                    field=bad[0])
            r0, rx, ry = xy[0], xy[1], xy[2]
            if np.max(np.abs(r0)) < tol_mm:
                break
            jac = np.stack([(rx - r0) / h, (ry - r0) / h], axis=2)  # (n, 2 stop coords, 2 aim coords)
            step = np.linalg.solve(jac, -r0[..., None])[..., 0]
            aim[:, :2] += step
        src["aim"] = aim

    # -------------------------------------------------------------- tracing
    def trace(self, fields_deg=0.0, grid: int = 101, wavelength_index=0, ray_aiming: bool = False,
              jitter: float = 0.0, layout: str = "centers", upto: int | None = None,
              object_distance=None, pupil=None) -> Rays:
        """Trace a pupil grid for each field to surface ``upto`` (exclusive; default: the sensor plane).

        ``grid``: pupil samples across the diameter; ``pupil``: optional explicit ``(u, v)`` arrays.
        ``pupil``: optional explicit ``(u, v, cell_area)`` in normalised pupil units.
        Returns :class:`Rays` after the last traced surface (at the sensor by default). Record on a
        ``wp.Tape`` around this call to differentiate (with ``requires_grad=True``).
        """
        src = self.sources(fields_deg, wavelength_index, ray_aiming, object_distance)
        if pupil is None:
            u, v, cell = pupil_grid(grid, src["shape"], jitter=jitter, layout=layout)
        else:
            u, v, cell = pupil
        return self._run(src, u, v, cell, upto=upto)

    def run(self, src, u, v, cell: float = 1.0, upto: int | None = None):
        """Trace the sources ``src`` (from :meth:`sources`) over explicit normalised pupil samples ``u``, ``v``
        (in [-1, 1]; ``cell``: the area of one sample's pupil cell in those units) up to surface ``upto``
        (exclusive; default the sensor). Returns the rays (positions in mm, directions, optical paths in mm,
        validity, power weights); recorded on a ``wp.Tape`` when the tracer was made with
        ``requires_grad=True``."""
        return self._run(src, u, v, cell, upto=upto)

    def rim_cells(self, grid_n: int):
        """:func:`disc_cells` of a ``grid_n`` pupil grid as a device array of ``wp.vec3d`` (made once per
        grid size and device, shared by the tracers of the process, up to :data:`rwwarp.pupil.RIM_CACHE_DEVICE_BYTES`;
        read-only)."""
        return device_disc_cells(grid_n, self.device)

    def _placeholders(self):   # the generate kernel's unused per-source grid and cell arrays ((1,) each)
        a = self.__dict__.get("_ph_grid")
        if a is None:
            a = self._ph_grid = (wp.zeros(1, dtype=wp.int32, device=self.device),
                                 wp.zeros(1, dtype=self.scalar, device=self.device))
        return a

    def no_rim_cells(self):
        """The placeholder ``(1,)`` cell array of a launch without rim weighting."""
        a = self.__dict__.get("_no_rim")
        if a is None:
            a = self._no_rim = wp.array(np.array([[1.0, 0.0, 0.0]]), dtype=wp.vec3d, device=self.device)
        return a

    def packed_rim_cells(self, grids, slots: int):
        """The rim cells (:meth:`rim_cells`) of a packed batch whose source ``k`` has its own ``grids[k]`` pupil
        grid in ``slots`` ray slots: one device array of ``len(grids) * slots`` ``wp.vec3d``, source ``k``'s table
        from ``k * slots`` (zeros past its own cells). Made once per grid list (cached on the tracer), on the device
        by one copy per source: no host table (150 sources of 401^2 slots are 0.58 GB) and no upload."""
        key = (tuple(int(g) for g in grids), int(slots))
        cache = self.__dict__.setdefault("_packed_rim", {})
        a = cache.get(key)
        if a is None:
            cache.clear()   # one packed batch at a time
            # zeros past each source's cells: one memset of the whole table, not one a source (on a GPU a launch
            # each), where any source has fewer cells than slots
            full = all(int(g) * int(g) >= key[1] for g in key[0])
            a = (wp.empty if full else wp.zeros)(len(key[0]) * key[1], dtype=wp.vec3d, device=self.device)
            for k, g in enumerate(key[0]):   # each source's cells
                wp.copy(a, self.rim_cells(g), dest_offset=k * key[1], src_offset=0, count=g * g)
            cache[key] = a
        return a

    def _run(self, src, u, v, cell=1.0, upto=None, keep=False, grid_n: int = 0, params=None, rim: bool = False,
             grids=None):
        """Generate and trace. ``grid_n > 0``: the pupil is the full ``grid_n x grid_n`` cell-centre grid,
        generated on the device (``u``, ``v`` ignored; no upload). ``keep=True``: also return
        ``rays.history`` (positions after each surface); ``keep`` (True or surface indices): ``rays.kept``,
        a dict surface index -> (pos, opl, valid) after that surface.

        The per-source inputs and the pupil go to the device in one upload. Without gradients
        (``requires_grad=False``) the rays ping-pong between two buffer sets (the tape needs every
        surface's state only when it records), and on the CPU the surfaces are traced for
        :attr:`threads` ray chunks in parallel (Warp's CPU launches release the GIL; every ray is
        independent, so the result is the same bit for bit). ``params``: per-surface parameter views to
        trace with instead of :attr:`params` (ray aiming traces without clear apertures). ``rim`` (with
        ``grid_n`` and a circular pupil): every cell the unit circle touches is traced, weighted by the
        fraction of it inside, its ray starting at the centroid of that part (:meth:`rim_cells`), instead of
        the cells whose centre is inside. ``grids`` (a packed batch, :class:`rwwarp.wave.packed.PackedRayWave`):
        each source's own pupil grid side (``grid_n`` and ``cell`` ignored): source ``k``'s cell-centre grid
        of ``grids[k]^2`` rays, cell area ``(2 / grids[k])^2``, fills the first of its ``max(grids)^2`` ray
        slots, the rest are padding (invalid, zero weight)."""
        dev, sc, K = self.device, self.scalar, self.K
        if params is None:
            params = self._params_for(src.get("object_distance"))
        nsrc = len(src["wl"])
        if grids is not None:
            grids = np.asarray(grids, dtype=np.int64).reshape(nsrc)
            grid_n = -1
            npup = int(grids.max()) ** 2
            cells = (2.0 / grids.astype(np.float64)) ** 2
        else:
            npup = grid_n * grid_n if grid_n > 0 else len(u)
        if grid_n != 0:
            u = v = np.zeros(1)
        n = nsrc * npup
        g = self.requires_grad
        fdt = self.np_dtype
        pu, pv, spos, sdir, sfin, saim, shx, shy, swl = upload_packed(
            [(u, fdt, sc), (v, fdt, sc), (src["pos"], fdt, K.vec3), (src["dir"], fdt, K.vec3),
             (src["finite"], np.int32, wp.int32), (src["aim"], fdt, K.vec3), (src["half_x"], fdt, sc),
             (src["half_y"], fdt, sc), (src["wl"], np.int32, wp.int32)], dev, cache=True)

        pooled = self.pool is not None and not g   # a kept batch's forward run: the same arrays every run
        made = [0]
        nsurf = len(self.lens.surfaces)
        last = nsurf + 1 if upto is None else upto
        # recording: every state's and parameter-row copy's gradient from one zeroed block (one memset, not one an
        # array; the deterministic mode's row sizes vary: their own arrays)
        n_rows = 0 if self.deterministic else last * self.grad_replicas * ktrace.N_PARAMS
        gb = GradBlock(dev, sc, (last + 1) * 7 * n + n_rows, lambda c: _with_release(
            dev, lambda: wp.zeros(c, dtype=sc, device=dev))) if g else None

        def new():
            if pooled:
                made[0] += 1
                tag = ("state", made[0])
                return (self.work_array(tag + (0,), n, K.vec3), self.work_array(tag + (1,), n, K.vec3),
                        self.work_array(tag + (2,), n, sc), self.work_array(tag + (3,), n, wp.int32))
            if gb is not None:
                pos, dr, opl, valid = _with_release(dev, lambda: (
                    wp.empty(n, dtype=K.vec3, device=dev), wp.empty(n, dtype=K.vec3, device=dev),
                    wp.empty(n, dtype=sc, device=dev), wp.empty(n, dtype=wp.int32, device=dev)))
                return gb.attach(pos), gb.attach(dr), gb.attach(opl), valid
            return _with_release(dev, lambda: (wp.empty(n, dtype=K.vec3, device=dev, requires_grad=g),
                                               wp.empty(n, dtype=K.vec3, device=dev, requires_grad=g),
                                               wp.empty(n, dtype=sc, device=dev, requires_grad=g),
                                               wp.empty(n, dtype=wp.int32, device=dev)))
        gen = new()
        if pooled:
            wl, weight = self.work_array("wl", n, wp.int32), self.work_array("weight", n, sc)
        else:
            wl = wp.empty(n, dtype=wp.int32, device=dev)
            weight = wp.empty(n, dtype=sc, device=dev)
        circle = int(src["shape"] == "circle")
        frac, stride = self.no_rim_cells(), 0
        if rim and circle and grid_n > 0:
            circle, frac = 2, self.rim_cells(grid_n)
        if grids is not None:
            if rim and circle:
                circle, frac, stride = 2, self.packed_rim_cells(grids, npup), npup
            g_src, c_src = upload_packed([(grids, np.int32, wp.int32), (cells, fdt, sc)], dev, cache=True)
        else:
            g_src, c_src = self._placeholders()
        inputs = [pu, pv, spos, sdir, sfin, saim, shx, shy, swl, self.n_obj, sc(cell), circle, frac,
                  int(src.get("relative_opl", False)), int(grid_n), npup, g_src, c_src, stride]

        def generate(c):   # rays of chunk c (None: all), each thread its own range before it traces them
            wp.launch(K.generate_kernel, dim=n if c is None else c[1] - c[0], inputs=inputs + [c[0] if c else 0],
                      outputs=list(gen) + [wl, weight], device=dev, record_tape=False)   # off the tape: no gradient
        kept = set(range(last)) if keep is True else set(keep or ())
        # a state is reused once the next surface has read it, unless the tape (every state) or ``keep`` reads it again
        outs, spare, prev, prev_kept = [], [], gen, False
        for i in range(last):
            out = new() if (g or i in kept or not spare) else spare.pop()
            if not (g or prev_kept):
                spare.append(prev)
            outs.append(out)
            prev, prev_kept = out, i in kept
        steps = []
        t_shared = t_dummy = None
        for i in range(last):
            kind = self.kinds[i] if i < nsurf else ktrace.KIND_PLANE
            n_in = self.n_before[i] if i < nsurf else self.n_tables[-1]
            n_out = self.n_tables[i] if i < nsurf else self.n_tables[-1]
            if kind in _CURVED:
                # converge the intersection off the tape; the surface kernel differentiates one step. A
                # buffer per surface when recording (the adjoint reads it again during tape.backward())
                if g:
                    t_buf = wp.empty(n, dtype=sc, device=dev)
                else:
                    if t_shared is None:
                        t_shared = self.work_array("t", n, sc) if pooled else wp.empty(n, dtype=sc, device=dev)
                    t_buf = t_shared
            else:
                if t_dummy is None:   # placeholder for non-refracting surfaces
                    t_dummy = self.work_array("t_dummy", 1, sc, zero=True) if pooled else \
                        wp.zeros(1, dtype=sc, device=dev)
                t_buf = t_dummy
            steps.append((kind, *self._param_rows((self.params if params is None else params)[i], n, gb), n_in,
                          n_out, t_buf))
        chunks = self._chunks(n)
        # the CPU without gradients and with no intermediate state read again: every surface in one launch a chunk
        fused = self._fused_steps(steps) if dev == "cpu" and not g and not kept else None
        run_chunks(lambda c, _: (generate(c), self._trace_range(steps, gen, outs, wl, c, fused)), chunks,
                   [None] * len(chunks), kernels=(K.generate_kernel, *step_kernels(self, steps, fused)), device=dev)
        pos, dr, opl, valid = outs[-1] if last else gen
        rays = Rays(pos, dr, opl, valid, wl, weight, nsrc, npup)
        if keep is True:
            rays.history = [o[0] for o in outs]
        if keep:
            rays.kept = {i: (outs[i][0], outs[i][2], outs[i][3]) for i in sorted(kept)}
        return rays

    def to_plane(self, rays, z_mm: float, surface_index: int):
        """Carry traced rays straight on (or back) to the plane ``z = z_mm`` in the medium behind surface
        ``surface_index``, adding ``n t`` to their OPL (one launch, recorded on an active ``wp.Tape``; the
        plane's position is not differentiated). Returns new :class:`Rays`."""
        K, dev, sc, g = self.K, self.device, self.scalar, self.requires_grad
        n = rays.pos.shape[0]
        pooled = self.pool is not None and not g   # a kept batch's forward run: the same arrays every run
        params = self.pool.get(("plane_row", float(z_mm))) if pooled else None
        if params is None:
            row = np.zeros(ktrace.N_PARAMS)
            row[ktrace.P_Z] = z_mm
            row[ktrace.P_SD] = -1.0
            params = wp.array(row.astype(self.np_dtype)[None], dtype=sc, device=dev)
            if pooled:
                self.pool[("plane_row", float(z_mm))] = params
        if pooled:
            out = (self.work_array(("to_plane", 0), n, K.vec3), self.work_array(("to_plane", 1), n, K.vec3),
                   self.work_array(("to_plane", 2), n, sc), self.work_array(("to_plane", 3), n, wp.int32))
            dummy = self.work_array("t_dummy", 1, sc, zero=True)
        else:
            out = _with_release(dev, lambda: (wp.empty(n, dtype=K.vec3, device=dev, requires_grad=g),
                                              wp.empty(n, dtype=K.vec3, device=dev, requires_grad=g),
                                              wp.empty(n, dtype=sc, device=dev, requires_grad=g),
                                              wp.empty(n, dtype=wp.int32, device=dev)))
            dummy = wp.zeros(1, dtype=sc, device=dev)
        idx = self.n_tables[surface_index]
        wp.launch(K.surface_kernel, dim=n, inputs=[rays.pos, rays.dir, rays.opl, rays.valid, rays.wl, params, 0, idx,
                                                   idx, ktrace.KIND_PLANE, dummy], outputs=list(out), device=dev)
        return Rays(out[0], out[1], out[2], out[3], rays.wl, rays.weight, rays.n_sources, rays.n_pupil)

    def _param_rows(self, p, n_rays: int = 0, grads=None):
        """``(rows, rmask)`` the kernels read a surface's parameters from: without gradients the row
        itself as a (1, N_PARAMS) view; with them :attr:`grad_replicas` copies made by
        ``replicate_kernel`` (recorded on an active tape, whose adjoint sums them back into ``p.grad``).
        :attr:`deterministic`: a copy for each of the ``n_rays`` rays (the next power of two), so no two rays
        add into one address, made in two levels whose adjoints sum in a fixed order. ``grads``: a
        :class:`rwwarp.grad_block.GradBlock` the copies' (zeroed) gradient comes from (not deterministic)."""
        if not self.requires_grad or not p.requires_grad:
            rows = getattr(p, "_rw_rows", None)   # the (1, N_PARAMS) view, made once per parameter array
            if rows is None:
                rows = p._rw_rows = p.reshape((1, ktrace.N_PARAMS))
            return rows, 0
        r = self.grad_replicas
        if self.deterministic:
            r = max(r, 1 << max(int(n_rays) - 1, 0).bit_length())
        # every row is written by the replicate kernels (the gradient buffer starts at zero all the same)
        if grads is not None and not self.deterministic:
            rows = grads.attach(wp.empty((r, ktrace.N_PARAMS), dtype=self.scalar, device=self.device))
        else:
            rows = wp.empty((r, ktrace.N_PARAMS), dtype=self.scalar, device=self.device, requires_grad=True)
        if self.deterministic:
            # two levels, each adjoint summing in order and adding where no other thread adds: params -> G rows
            # (one thread a parameter) -> R rows (thread (j, g) owns row g of the first level)
            grp = min(r, 512)
            mid = wp.empty((grp, ktrace.N_PARAMS), dtype=self.scalar, device=self.device, requires_grad=True)
            wp.launch(self.K.replicate_kernel, dim=(ktrace.N_PARAMS, 1), inputs=[p, grp], outputs=[mid],
                      device=self.device)
            wp.launch(self.K.replicate_rows_kernel, dim=(ktrace.N_PARAMS, grp), inputs=[mid, r // grp], outputs=[rows],
                      device=self.device)
            return rows, r - 1
        per = min(r, REPLICATE_ROWS_PER_THREAD)
        wp.launch(self.K.replicate_kernel, dim=(ktrace.N_PARAMS, r // per), inputs=[p, per], outputs=[rows],
                  device=self.device)
        return rows, r - 1

    def work_array(self, tag, shape, dtype, zero: bool = False):
        """A forward-only work array (no gradient): from :attr:`pool` when set, else a new ``wp.zeros`` /
        ``wp.empty`` on the tracer's device. In the pool a 1-D array (``shape`` an int) is kept under ``(tag,
        dtype)`` and handed out as its first ``shape`` elements, grown (made again) when a larger one is asked
        for, so the batches of a map share one array per tag (:func:`rwwarp.map_run._wave_map` on the CPU); other
        shapes under ``(tag, shape, dtype)``. Zeroed (again) when ``zero`` (a new CPU one is not zeroed otherwise)."""
        if self.pool is None:
            return (wp.zeros if zero else wp.empty)(shape, dtype=dtype, device=self.device)
        flat = isinstance(shape, (int, np.integer))
        key = (tag, dtype) if flat else (tag, shape, dtype)
        a = self.pool.get(key)
        if a is None or (flat and a.shape[0] < int(shape)):
            self.pool.pop(key, None)   # the smaller one goes before the larger is made
            new = wp.empty if self.device == "cpu" and not zero else wp.zeros   # a CPU one: written before read
            a = self.pool[key] = _with_release(self.device, lambda: new(shape, dtype=dtype, device=self.device))
            return a
        if flat and a.shape[0] != int(shape):
            a = a[:int(shape)]
        if zero:
            a.zero_()
        return a

    def _chunks(self, n: int):
        """Ray index ranges traced in parallel: one per thread on the CPU without a tape and with at least
        :data:`PARALLEL_MIN_RAYS` rays per chunk, else one."""
        t = self.threads
        if self.device != "cpu" or self.requires_grad or t <= 1 or n < 2 * PARALLEL_MIN_RAYS:
            return [None]
        t = min(t, n // PARALLEL_MIN_RAYS)
        b = np.linspace(0, n, t + 1).astype(np.int64)
        return [(int(b[k]), int(b[k + 1])) for k in range(t)]

    _fused_steps = fused_tables   # the tables of the fused trace (None: the per-surface launches)

    def _trace_range(self, steps, gen, outs, wl, rng, fused=None):
        """Launch the intersection and surface kernels of every step for rays ``rng = (lo, hi)`` (all if None); the
        arrays are 1-D views of the chunk, so the kernels see an independent batch. ``fused`` (:meth:`_fused_steps`'
        tables): every step in one launch of :func:`rwwarp.kernels.trace_steps.make_trace_steps_kernel` (the same
        bits), its state into the last step's arrays."""
        K, dev = self.K, self.device

        def cut(a):
            return a if rng is None else a[rng[0]:rng[1]]
        n = gen[0].shape[0] if rng is None else rng[1] - rng[0]
        state = tuple(cut(a) for a in gen)
        wlc = cut(wl)
        if fused is not None:
            wp.launch(step_kernels(self, steps, fused)[0], dim=n, inputs=[*state, wlc, *fused, len(steps)],
                      outputs=[cut(a) for a in outs[-1]], device=dev, record_tape=False)
            return
        for (kind, rows, rmask, n_in, n_out, t_buf), out in zip(steps, outs):
            nxt = tuple(cut(a) for a in out)
            tc = cut(t_buf) if kind in _CURVED else t_buf
            if kind in _CURVED:
                wp.launch(K.intersect_kernel, dim=n, inputs=[state[0], state[1], state[3], rows, rmask], outputs=[tc],
                          device=dev, record_tape=False)
            if kind == ktrace.KIND_PHASE:
                wp.launch(K.phase_surface_kernel, dim=n, inputs=[*state, wlc, rows, rmask, n_in, n_out, self.lam_bar,
                                                                 tc], outputs=list(nxt), device=dev)
            else:
                wp.launch(K.surface_kernel, dim=n, inputs=[*state, wlc, rows, rmask, n_in, n_out, kind, tc],
                          outputs=list(nxt), device=dev)
            state = nxt

