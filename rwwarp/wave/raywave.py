"""The ray-wave model of one batch of point sources, in stages (:class:`RayWave`).

Every discrete decision (chief rays, the sampling plan, windows, patches, wave step) is in its plan, a read-only
:class:`rwwarp.wave.batch_plan.BatchPlan` (:func:`rwwarp.wave.batch_plan.plan_batch`, which its ``__init__`` calls;
:meth:`RayWave.from_plan` runs an existing one); a RayWave holds the plan (``rw.batch_plan``, its names read through:
``rw.plan``, ``rw.origin``, ``rw.centers``, ...) and the per-call state (tracer, splatter, power sums, focal operator,
memoised DOE arrays). Its stages run the differentiable part: trace to the wave plane and splat into a complex
field (Warp, :mod:`rwwarp.kernels.splat`), apply the DOE, propagate to the sensor and integrate over the
pixels (:mod:`rwwarp.wave.propagate` or :mod:`rwwarp.wave.focal`). :func:`rwwarp.psf.psf` and
:func:`rwwarp.psf.psf_map` are the public calls around it; :mod:`torch_bridge` differentiates its stages.
Lengths in mm, wavelengths in um.
"""
from __future__ import annotations

import numpy as np

from .batch_plan import AUTO_PAIR, PLAN_FIELDS, BatchPlan, plan_batch  # noqa: F401  (AUTO_PAIR: its home batch_plan)
from .doe_sampling import doe_phase_grid
from .methods import check_method, gauss_nodes_xy
from .methods import get as get_method
from .splat import paper_rescale_layout
from ..device_upload import upload_packed
from ..trace import Tracer

from .focal import FOCAL_MAX_ORDER  # noqa: F401  (its home: focal; read by rwwarp.wave.methods.focal)
from .sensor_grid import pixel_centres as _pixel_centres
from .pilot import Pilot
from .pilot import own_pupil_sources  # noqa: F401  (its home: rwwarp.wave.pilot; public here before)


class _TracerOnUse:
    """A RayWave's tracer made on first use (:meth:`RayWave.from_plan` ``tracer_on_use``): ``Tracer(*args, **kw)``."""

    def __init__(self, args, kw):
        self.args, self.kw, self.tracer = args, kw, None

    def get(self) -> Tracer:
        if self.tracer is None:
            self.tracer = Tracer(*self.args, **self.kw)
        return self.tracer


# ---------------------------------------------------------------------------------------------- ray-wave
class RayWave:
    """The ray-wave model for one batch of point sources, in stages.

    ``__init__`` plans (:func:`rwwarp.wave.batch_plan.plan_batch`: pilot trace, chief rays, sampling plan, windows,
    sensor patches; kept read-only as :attr:`batch_plan`, whose names this object reads through) and makes the
    tracer; :meth:`from_plan` runs a plan without planning again; :meth:`field` runs the differentiable part on the Warp device (trace to the DOE
    plane, ray-tube areas, splat, reference sphere and carrier) and returns the complex field;
    :meth:`doe_phase` samples phi0 on the windows; :meth:`intensity` propagates to the sensor and
    integrates over pixels (OpenCL); :meth:`run` chains them and normalises by the entering power.
    Lengths in mm, wavelengths in um.

    ``focal_patch_tol`` (focal method): a DOE order other than the main one is computed only if the
    share of the source's power it puts on the patch (estimated from its pilot rays' landing box) is at
    least this (default 1e-5). Strongly defocused orders off the design wavelength spread a few percent
    of the power over millimetres; keeping them makes the sensor-side box, and with it the wave-plane
    grid, as wide as their spread. A larger value (1e-3) leaves them out; their power is reported in the
    plan's reasons.

    ``deterministic``: the same inputs give the same bits on every run on a GPU too. The splat adds
    fixed-point integers (:mod:`rwwarp.kernels.splat`, resolution ~1e-12 of a sample) and the tracer
    gives every ray its own copy of each surface's parameters when recording
    (:class:`~rwwarp.trace.Tracer` ``deterministic``: 2 x 8 x N_PARAMS = 640 bytes a ray and surface more). On the
    CPU the results are deterministic either way (Warp's CPU kernels run in order; CPU threads sum privately).

    ``pixel_values``: what a pixel records, ``"flux"`` (default, the power through it) or ``"intensity"``
    (``|U|^2`` over it, the earlier convention); docs/propagation.md "Pixel values".

    ``pilot``: the sources' :class:`rwwarp.wave.pilot.Pilot` (:func:`rwwarp.wave.pilot.trace_pilot` of these
    sources, or a :meth:`~rwwarp.wave.pilot.Pilot.subset` of a batch's traced with ``own_pupils``), read and never
    changed; checked to be of these fields, wavelengths, pupils, object distance, ``use_reference`` and ``dtype``
    (``ValueError`` naming what differs); it must come from the same lens values. None (default): traced here.

    ``auto_rule`` (``method="auto"``): how the two planned propagations are chosen. ``"flops"``: the plan of fewer
    flops; ``"device"`` (default): the same, on every device (the rule for a device, should one need another);
    ``"small-asm"``: the band-limited ASM while its plan is under 1 GiB and 20 GFLOP, else the plan of fewer flops
    (the rule GPUs had while launches bound both paths; :func:`rwwarp.wave.batch_plan._choose_auto` says why it
    changed).

    ``estimate_model_error``: False skips the model-error estimate (:mod:`rwwarp.wave.model_error`) where no decision
    reads it (``method`` neither ``"two-step"`` nor ``"auto"`` with a ``model_tolerance``): the plan records none. A
    design loop that re-plans every step spends most of its planning there (the Cooke hybrid's 48 sources with
    the estimates' memo missed: 57 % of the planning's CPU time).

    ``allow_pixel``: ``method="auto"`` may choose ``"pixel"`` (pixels many Airy radii wide,
    :mod:`rwwarp.wave.pixel_scale`; no wave-plane field, so nothing to differentiate): on for the public calls
    (:func:`rwwarp.psf`, :func:`rwwarp.psf_map`, :func:`rwwarp.plan_psf`), off by default so that a differentiable
    caller's "auto" never gets it. ``method="pixel"`` asks for it either way.
    """

    def __init__(self, lens, fields, wls, size, pixel, device="cpu", plan="auto", dtype="float64",
                 amplitude="energy", object_distance_mm=None, rays_per_sample=1.0, center_mm=None,
                 use_reference=True, gauss_nodes=None, nyquist_safety=2.0, requires_grad=False, method="asm",
                 memory_budget_bytes=None, focal_patch_tol=1e-5, deterministic: bool = False,
                 own_pupils: bool = False, pilot: Pilot | None = None, pixel_values: str = "flux",
                 model_tolerance: float | None = None, auto_rule: str = "device", allow_pixel: bool = False,
                 estimate_model_error: bool = True):
        if auto_rule not in ("device", "small-asm", "flops"):
            raise ValueError(f"auto_rule must be 'device', 'small-asm' or 'flops', got {auto_rule!r}")
        check_method(method, "RayWave")
        tr = Tracer(lens, sorted(set(wls)), device=device, dtype=dtype, requires_grad=requires_grad,
                    deterministic=bool(deterministic))
        bp = plan_batch(lens, fields, wls, size, pixel, device, plan, dtype, amplitude, object_distance_mm,
                        rays_per_sample, center_mm, use_reference, gauss_nodes, nyquist_safety, method,
                        memory_budget_bytes, focal_patch_tol, deterministic, own_pupils, pilot, pixel_values,
                        model_tolerance, auto_rule, allow_pixel, tracer=tr, estimate_model_error=estimate_model_error)
        self._start(bp, tr, device)

    def _start(self, batch_plan: BatchPlan, tracer: Tracer, device: str, deterministic: bool | None = None):
        """The per-call state: ``batch_plan`` (its names, :data:`rwwarp.wave.batch_plan.PLAN_FIELDS`, read
        through), ``tracer``, the device (as given), determinism (default the plan's)."""
        #: the :class:`rwwarp.wave.batch_plan.BatchPlan` this RayWave runs (read-only; a new plan replaces it)
        self.batch_plan = batch_plan
        self._tracer = tracer
        self.device = device
        self.deterministic = batch_plan.deterministic if deterministic is None else bool(deterministic)

    @classmethod
    def from_plan(cls, batch_plan: BatchPlan, device: str | None = None, requires_grad: bool = False,
                  deterministic: bool | None = None, tracer_on_use: bool = False) -> "RayWave":
        """A RayWave that runs ``batch_plan`` (:func:`rwwarp.wave.batch_plan.plan_batch`, or another RayWave's
        :attr:`batch_plan`) without planning again: its own tracer of the plan's lens (``requires_grad``: with
        gradient buffers) on ``device`` (default the plan's) in the plan's precision; ``deterministic`` default
        the plan's. The same inputs give the same bits as the RayWave the plan came from. ``tracer_on_use``: the
        tracer is made when first used (:attr:`tracer`; shared by shallow copies), from the lens as it is then: a
        plan computed only inside a :class:`~rwwarp.wave.packed.PackedRayWave` (which has its own) never makes it."""
        if not isinstance(batch_plan, BatchPlan):
            raise TypeError(f"RayWave.from_plan: batch_plan must be a rwwarp.wave.batch_plan.BatchPlan, got "
                            f"{type(batch_plan).__name__}")
        device = batch_plan.device if device is None else device
        det = batch_plan.deterministic if deterministic is None else bool(deterministic)
        args = (batch_plan.lens, sorted(set(batch_plan.wls)))
        kw = dict(device=device, dtype=batch_plan.dtype, requires_grad=requires_grad, deterministic=det)
        tr = _TracerOnUse(args, kw) if tracer_on_use else Tracer(*args, **kw)
        rw = cls.__new__(cls)
        rw._start(batch_plan, tr, device, det)
        return rw

    @property
    def tracer(self) -> Tracer:
        """This batch's :class:`rwwarp.trace.Tracer` (its device arrays: surface parameters, index tables)."""
        t = self._tracer
        return t.get() if isinstance(t, _TracerOnUse) else t

    def tracer_made(self) -> Tracer | None:
        """The tracer if it exists, None where it is made on first use (:meth:`from_plan` ``tracer_on_use``) and
        nothing used it yet: what reads what is held (:func:`rwwarp.wave.plan_cache.held_bytes`) without making it."""
        t = self._tracer
        return t.tracer if isinstance(t, _TracerOnUse) else t

    def use_plan(self, batch_plan: BatchPlan) -> None:
        """Run ``batch_plan`` from now on (a new plan of the same sources and lens: :meth:`recentre`,
        :func:`rwwarp.wave.wave_step.plan_wave_step`); what was derived from the old one (the focal operator)
        is made again on next use (memoised DOE phases are keyed by the windows)."""
        if not isinstance(batch_plan, BatchPlan) or batch_plan.nsrc != self.batch_plan.nsrc:
            raise ValueError("RayWave.use_plan: a BatchPlan of the same number of sources is needed")
        self.batch_plan = batch_plan
        self._focal_op = None

    def field(self):
        """Trace to the DOE plane, splat, apply the reference sphere and carrier.

        Returns ``(field, rays)``: a Warp ``vec2d`` array (n_sources * n * n) of the complex field on
        the windows (carrier removed), and the traced rays. Record inside a ``wp.Tape`` (with
        ``requires_grad=True``) to differentiate w.r.t. ``self.tracer.params``.
        """
        tr, src, pl, plane, nsrc = self.tracer, self.src, self.plan, self.plane, self.nsrc
        import warp as wp
        from .reduce import power_source_sums
        u, v, cell = self.pupil
        # rim cells weighted by the part of them the pupil disc covers (energy convention)
        rim = self.rim
        lay = self._layout()
        npup = lay["slots"]
        rays = tr._run(src, u, v, cell, upto=plane + 1, grid_n=pl.ray_grid, rim=rim, grids=lay["ray_grids"])
        if self.curved_plane:
            rays = tr.to_plane(rays, self.z_plane, plane)
        # per source (entering, valid) power: a fixed summation tree, the same bits on every run (on the CPU the terms
        # formed and summed in one launch; elsewhere the terms kernel and the tree's passes), read when asked
        self._sums_dev, self._sums = power_source_sums(rays.valid, rays.weight, nsrc, npup, tr.scalar, tr.device,
                                                       work=tr.work_array if tr.pool is not None else None), None
        chief_plane, opl_p = self.chief_plane.copy(), self.opl_chief.copy()
        if not self.chief_ok.all():
            valid = rays.valid.numpy().reshape(nsrc, npup).astype(bool)
            # vignetted chief ray: the valid ray nearest the footprint centre is the reference
            all_opl = rays.opl.numpy().reshape(nsrc, npup)
            all_pos = rays.pos.numpy().reshape(nsrc, npup, 3)
            for k in np.where(~self.chief_ok)[0]:
                d2 = np.sum((all_pos[k, :, :2] - chief_plane[k, :2]) ** 2, axis=1) + np.where(valid[k], 0, np.inf)
                j = int(np.argmin(d2))
                chief_plane[k] = all_pos[k, j]
                opl_p[k] = all_opl[k, j]
        #: the chief point and path the splat referenced (the vignetted chief's substitute where needed): the
        #: constant phase it removed (rwwarp.phase_orders.absolute_node_fields)
        self._splat_reference = (chief_plane, opl_p)
        n = lay["n_stride"]
        sp = self.splatter
        held = getattr(self, "_memo", None) is not None   # a kept batch: its small uploads by content (LRU)
        # 2: pixel_values "flux", the field whose z-flux is the tube irradiance (amplitude / sqrt(cos), splat.py)
        energy = (2 if self.pixel_values == "flux" else 1) if self.amplitude == "energy" else 0
        rim_args = self._rim_args(rim)
        if lay["ray_grids"] is None:
            area, half = sp.tube_areas(rays, pl.ray_grid, rim_args, bool(energy))
            grid_src, frac_stride, n_arg = sp.grid_placeholder(), 0, n
        else:   # a packed batch: each source's own pupil grid and window in slots of the largest
            ray_src, grid_src = upload_packed([(lay["ray_grids"], np.int32, wp.int32),
                                               (lay["grids"], np.int32, wp.int32)], tr.device, cache=held)
            frac_stride = npup if rim else 0
            area, half = sp.tube_areas(rays, -1, rim_args, bool(energy), packed=(ray_src, npup, frac_stride))
            n_arg = -n
        # per-source constants in one upload
        origin, pitch, chief, target, index, opl_c, k_wave, carrier = upload_packed(
            [(self.origin, np.float64, wp.vec2d), (lay["pitches"], np.float64, wp.float64),
             (chief_plane, np.float64, wp.vec3d), (self.target, np.float64, wp.vec3d),
             # the reference-sphere index carries the sign: + converging to T, - diverging from T
             (self.n_after * np.where(self.target[:, 2] >= self.z_plane, 1.0, -1.0), np.float64, wp.float64),
             (opl_p, np.float64, wp.float64), (2.0 * np.pi / self.lam_mm, np.float64, wp.float64),
             (self.carrier, np.float64, wp.vec2d)], tr.device, cache=held)
        geo = [origin, pitch, chief, target, index]
        splat_in = [rays.pos, rays.dir, rays.opl, rays.valid, rays.weight, area, half] + geo + \
                   [opl_c, k_wave, int(self.use_reference), energy, n_arg, npup, *rim_args, grid_src, frac_stride]
        # CPU threads take whole sources where there are enough (each source's cost: its window's samples)
        s_re, s_im, self.dropped = sp.sums(splat_in, nsrc, n,
                                           source_work=np.asarray(lay["grids"], dtype=np.float64) ** 2)
        field = sp.finalize([s_re, s_im] + geo + [k_wave, carrier, int(self.use_reference), energy, n_arg, grid_src],
                            nsrc * n * n)
        return field, rays

    def _layout(self) -> dict:
        """How this batch's rays and windows are laid out: ``ray_grids`` (None: every source on the plan's pupil
        grid), ``slots`` (ray slots per source), ``grids`` and ``n_stride`` (window sides and the side of each
        source's slot of the field), ``pitches`` (mm, per source)."""
        pl = self.plan
        return {"ray_grids": None, "slots": pl.ray_grid ** 2, "grids": np.full(self.nsrc, pl.n_grid),
                "n_stride": pl.n_grid, "pitches": np.full(self.nsrc, pl.pitch_mm)}

    @property
    def splatter(self):
        """The :class:`rwwarp.wave.splat.Splatter` of this batch's tracer (made on first use)."""
        sp = getattr(self, "_splatter", None)
        if sp is None:
            from .splat import Splatter
            sp = self._splatter = Splatter(self.tracer, self.deterministic)
        return sp

    def _rim_args(self, rim: bool):
        """The ``(cells, rim)`` inputs of the tube-area and splat kernels: this plan's pupil cells
        (:func:`rwwarp.pupil.disc_cells`) when the rim is weighted, else a placeholder."""
        tr = self.tracer
        return (tr.rim_cells(self.plan.ray_grid), 1) if rim else (tr.no_rim_cells(), 0)

    def power_sums_array(self):
        """Per-source power sums of the last :meth:`field` call as the device array itself (a Warp array
        of ``(n_sources, 1)`` vec4 float64: entering power, traced power, then two unused slots; unit source
        radiance), with no host copy: a caller on the device reads it without synchronising. A new array
        each :meth:`field` call (on a batch kept by a :class:`~rwwarp.wave.plan_cache.PlanCache`: the same one)."""
        return self._sums_dev

    def _power_sums(self):
        if self._sums is None:
            self._sums = self._sums_dev.numpy().reshape(-1, 4)[:, :2]
        return self._sums

    @property
    def entering(self):
        """Power entering the pupil per source (unit source radiance), from the last :meth:`field` call."""
        return self._power_sums()[:, 0]

    @property
    def traced_power(self):
        """Power of the rays that reach the wave plane per source, from the last :meth:`field` call."""
        return self._power_sums()[:, 1]

    @property
    def valid_fraction(self):
        """``traced_power / entering`` per source."""
        s = self._power_sums()
        return s[:, 1] / s[:, 0]

    def field_array(self):
        """:meth:`field` as a complex128 array (n_sources, n, n), paper convention rescaled: numpy on the
        CPU, a zero-copy CuPy view of the Warp array on CUDA (the field never visits the host)."""
        field, rays = self.field()
        lay = self._layout()
        n = lay["n_stride"]
        if self.tracer.device.startswith("cuda"):
            import cupy
            u_field = cupy.asarray(field).view(cupy.complex128).reshape(self.nsrc, n, n)
        else:
            u_field = field.numpy().view(np.complex128).reshape(self.nsrc, n, n)
        if self.amplitude != "energy":
            xp = np if isinstance(u_field, np.ndarray) else __import__("cupy")
            u_field = paper_rescale_layout(self, u_field, xp.asarray(self.traced_power), xp)
        return u_field

    def _memoised(self, name, make, *key):
        """``make()``, kept for the next call with the same ``key`` when this RayWave is held for repeated runs
        (:class:`rwwarp.wave.plan_cache.PlanCache`: its lens is a private copy; the windows are in the key)."""
        memo = getattr(self, "_memo", None)
        if memo is None:
            return make()
        key = (self.origin.tobytes(), self.plan.pitch_mm, self.plan.n_grid) + key
        hit = memo.get(name)
        if hit is None or hit[0] != key:
            hit = memo[name] = (key, make())
        return hit[1]

    def doe_phase(self):
        """phi0 (rad) on each window, (n_sources, n, n), and the per-source wavelength scale; or (None, None)."""
        return self._memoised("doe_phase", self._doe_phase)

    def _doe_phase(self):
        phi0 = doe_phase_grid(self.lens, self.plane, self.origin, self.plan.pitch_mm, self.plan.n_grid)
        if phi0 is None:
            return None, None
        from .. import doe
        s = self.lens.surfaces[self.plane]
        scale = np.array([doe.wavelength_scale(s.material, s.design_wavelength_um, w) for w in self.wls])
        return phi0, scale

    def release_operators(self):
        """Drop the cached focal operator (:meth:`focal_operator`; its factors take tens of MB on a
        large grid); the next use builds it again. Plans, windows and patches are kept."""
        self._focal_op = None

    def snapped_centres(self, center_mm) -> np.ndarray:
        """The patch centres ((nsrc, 2) mm) this batch would have for ``center_mm`` ((x, y) mm, one pair or
        one per source): snapped to the sensor's pixel centres as in the constructor. Changes nothing; a
        plan made for other centres (equal after snapping) computes the same patches."""
        return self.batch_plan.snapped_centres(center_mm)

    def recentre(self, center_mm):
        """Move the sensor patches to new centres ((x, y) mm, one pair or one per source; snapped to
        the sensor's pixel centres as in the constructor). Only the output positions change: the
        DOE-plane windows, the traced field and the plan do not depend on them, so a field computed
        before stays valid (the propagation evaluates any sensor positions). A focal plan's sensor-side
        grid (patch plus the remainder's displacement and margins) moves with its patch, by the same
        whole number of pixels, and its operator is built again on next use. This RayWave runs the new plan
        (:meth:`rwwarp.wave.batch_plan.BatchPlan.recentred`); the old plan is not changed."""
        focal_op = getattr(self, "_focal_op", None)
        self.use_plan(self.batch_plan.recentred(center_mm))
        if self.focal is None:
            self._focal_op = focal_op   # no sensor-side grid: the operator (if any) is the same

    def load_params(self, table, device_table=None):
        """Load a surface parameter table ((n_surfaces + 1, N_PARAMS) float64, last row the sensor, layout
        :data:`rwwarp.trace.COLUMNS`; lengths mm) into the tracer's device arrays, in place, and move the
        z of the wave-plane grid's reference point to the plane's vertex in it (the grid lies on the
        plane). Returns the table as a float64 array. Plans, windows and patch centres are unchanged.
        ``device_table``: the same values already on the tracer's device (a Warp array of the table's shape
        and the tracer's scalar type, e.g. a zero-copy view of a torch tensor): its rows are copied device to
        device and ``table`` (host) only moves the reference point."""
        import warp as wp
        from ..kernels import trace as ktrace
        tab = np.asarray(table, dtype=np.float64)
        tr = self.tracer
        if tab.shape != (len(tr.params), ktrace.N_PARAMS):
            raise ValueError(f"parameter table must be {(len(tr.params), ktrace.N_PARAMS)}, got {tab.shape}")
        if not np.all(np.isfinite(tab)):
            raise ValueError("parameter table has non-finite entries")
        tr.own_params()   # a tracer without gradients reads shared views of a cached upload: never written
        if device_table is not None:
            if tuple(device_table.shape) != tab.shape or device_table.dtype != tr.scalar:
                raise ValueError(f"device_table must be {tab.shape} of {tr.scalar.__name__}, got "
                                 f"{tuple(device_table.shape)} of {getattr(device_table.dtype, '__name__', device_table.dtype)}")
            block = getattr(tr, "params_block", None)
            if block is not None:       # a tracer with gradients: its rows are views of one array, one copy
                wp.copy(block, device_table)
            else:
                for k, arr in enumerate(tr.params):
                    wp.copy(arr, device_table[k])
        elif getattr(tr, "params_block", None) is not None:
            tr.params_block.assign(np.ascontiguousarray(tab, dtype=tr.np_dtype))
        else:
            for row, arr in zip(tab, tr.params):
                arr.assign(np.ascontiguousarray(row, dtype=tr.np_dtype))
        tr.params_np = tab.copy()
        # the plane's vertex moves the windows' reference point: a new plan (the windows, patches and
        # operators are unchanged)
        self.batch_plan = self.batch_plan.with_plane_z(tab[self.plane, ktrace.P_Z])
        return tab

    def pixel_centres(self):
        """Sensor pixel centres (x (S, size), y (S, size)) of each patch, mm."""
        return _pixel_centres(self.centers, self.size, self.pixel)

    def sensor_geometry(self, doe_scale=None):
        """The :class:`rwwarp.wave.propagate.SensorGeometry` of this batch's band-limited propagation: its
        windows (pitch, origins), wavelengths in the medium after the plane (um), plane-to-sensor
        distance (mm), the patches' pixel centres, FFT size and carrier; ``doe_scale`` (per-source DOE
        wavelength remap) when a DOE phase goes with the field."""
        from .propagate import SensorGeometry
        px, py = self.pixel_centres()
        return SensorGeometry(self.plan.pitch_mm, self.origin, np.array(self.wls) / self.n_after,
                              np.full(self.nsrc, float(self.z_sensor - self.z_plane)), px, py, self.pixel,
                              gauss_nodes=self.gauss_nodes, doe_scale=doe_scale, carrier_cpmm=self.carrier,
                              pad_to=self.plan.n_pad, pixel_values=self.pixel_values)

    def intensity(self, u_field, phi0=None, scale=None, to_host: bool = True):
        """Power per sensor pixel (S, size, size) for a DOE-plane field (complex, (S, n, n)), by the
        band-limited ASM (:class:`rwwarp.wave.propagate.SensorPropagator`). ``to_host=False``: the backend's
        array as it is (a CuPy array on CUDA: no copy, no wait; :mod:`rwwarp.wave.graph_replay`)."""
        from . import backend as bk
        from .propagate import SensorPropagator
        be = bk.get_backend(self.device)
        u_field = self.wave_stepped(u_field)
        if isinstance(u_field, np.ndarray) and hasattr(be, "wrap_host"):
            # PoCL: the OpenCL buffers use the numpy memory (zero-copy host pointers)
            u_field = be.wrap_host(u_field)
            phi0 = None if phi0 is None else be.wrap_host(phi0)
        elif isinstance(phi0, np.ndarray) and getattr(self, "_memo", None) is not None:
            # a kept batch (PlanCache) on a GPU: its DOE phase (memoised on the host) is uploaded once
            host = phi0
            phi0 = self._memoised("doe_phase_device", lambda: be.to_device(host), id(host))
        power = SensorPropagator(be, self.sensor_geometry(scale)).forward(u_field, phi0)
        return be.to_host(power) if to_host else power

    def wave_stepped(self, u_field):
        """``u_field`` after the planned wave step (:func:`rwwarp.wave.wave_step.apply_wave_step`), or as it is."""
        if not np.any(getattr(self, "wave_step", 0.0)):
            return u_field
        from .wave_step import apply_wave_step
        return apply_wave_step(self, u_field, np if isinstance(u_field, np.ndarray) else __import__("cupy"))

    def focal_operator(self, distance_mm=None, precision="double"):
        """The planned :class:`rwwarp.wave.focal.FocalPropagator` of this batch (``method="focal"``), built once per
        wave-plane-to-sensor distance (mm; default the lens's) and ``precision`` of its first step ("double"
        for gradients; the forward PSFs of :meth:`run`: single on the CPU, double on CUDA): a learning sensor
        distance rebuilds it on the same grids."""
        z = float(self.z_sensor - self.z_plane) if distance_mm is None else float(distance_mm)
        op = getattr(self, "_focal_op", None)
        if op is None or op.z != z or op.precision != precision:
            from .focal import FocalPropagator
            xp = np
            if str(self.device).startswith("cuda"):   # (no tracer made for it: a packed member never traces)
                import cupy as xp   # (FocalPropagator sizes CuPy's cuFFT plan cache in the thread of each FFT)
            nx, ny = gauss_nodes_xy(self)
            pl = self.plan
            self._focal_op = FocalPropagator(self.origin, pl.pitch_mm, pl.n_grid, self.lam_mm / self.n_after,
                                             z, self.carrier,
                                             self.focal["sensor_origin"], pl.sensor_pitch_mm, pl.n_sensor,
                                             pl.n_sensor_fft, nx, ny, xp=xp,
                                             transfer=self.focal.get("transfer"),
                                             taper_guard_mm=self.focal.get("taper_guard_mm"), precision=precision)
        return self._focal_op

    def doe_orders_factor(self, xp=np):
        """``sum_m c_m exp(1j m phi0)`` on each window (S, n, n) for the DOE orders the focal plan kept
        (:func:`rwwarp.wave.focal.doe_order_series`, the chief ray's wrap zone exact), in the array namespace
        ``xp`` (the focal operator's: CuPy on CUDA); None without a DOE, for a blank DOE, or with only
        the zeroth order and c_0 = 1."""
        return self._memoised("doe_orders_factor", lambda: self._doe_orders_factor(xp), xp.__name__)

    def _doe_orders_factor(self, xp):
        from .focal import doe_order_series
        geo, prof = self.focal, self.focal["profile"]
        if prof is None:
            return None
        s = self.lens.surfaces[self.plane]
        g = np.arange(self.plan.n_grid) * self.plan.pitch_mm
        phi0 = np.empty((self.nsrc, self.plan.n_grid, self.plan.n_grid))
        for k in range(self.nsrc):
            x, y = np.meshgrid(self.origin[k, 0] + g, self.origin[k, 1] + g, indexing="xy")
            phi0[k] = prof.phase(x, y, s.design_wavelength_um)   # unwrapped: each order is smooth
        return doe_order_series(xp.asarray(phi0), geo["orders"], geo.get("central_zone"), xp)

    def focal_intensity(self, u_field, precision="single", to_host: bool = True):
        """Power per sensor pixel (S, size, size) by the focal propagation (``method="focal"``; ``precision`` of
        its matrix products, :class:`rwwarp.wave.focal.FocalPropagator`; :attr:`pixel_values` as the ASM's).
        ``to_host=False``: the operator's array as it is (CuPy on CUDA)."""
        from .focal import focal_pixels
        op = self.focal_operator(precision=precision)
        u_field = self.wave_stepped(u_field)
        fac = self.doe_orders_factor(op.xp)
        if fac is not None:
            u_field = u_field * fac
        power, _ = focal_pixels(op, u_field, self.pixel_values, self.gauss_nodes, self.pixel, self.size)
        return power if (op.xp is np or not to_host) else op.xp.asnumpy(power)

    def run(self, focal_precision: str = "auto") -> dict:
        """The whole model: PSFs as fractions of the entering power per pixel (``focal_precision``: the focal
        method's matrix products, "auto" = single on the CPU, double on CUDA; see :func:`rwwarp.psf`)."""
        if focal_precision == "auto":
            focal_precision = "double" if self.tracer.device.startswith("cuda") else "single"
        m = get_method(self.plan.method)
        data = m.pixels(self, self.field_array() if m.forms_field else None, focal_precision) / self.entering[:, None, None]
        if not np.all(np.isfinite(data)):
            raise FloatingPointError("non-finite PSF values (please report this lens and field)")
        return {"data": data, "centers": self.centers, "plan": self.plan.to_dict(),
                "valid_fraction": self.valid_fraction, "dropped_rays": self.dropped.numpy()}

    def wave_field(self, samples=None):
        """This batch's wave-plane field as a :class:`rwwarp.wave.field.WaveField` (samples of
        :meth:`field_array`, traced now when ``samples`` is None; windows, pitch, medium wavelengths, carrier,
        reference wave, DOE phase)."""
        from .field import raywave_field
        return raywave_field(self, samples)

    def propagation(self):
        """The registered propagation method of this batch's plan (:func:`rwwarp.wave.methods.get`)."""
        return get_method(self.plan.method)


def _plan_name(name):
    def get(self):
        return getattr(self.batch_plan, name)
    get.__name__ = name
    get.__doc__ = f"``batch_plan.{name}`` (:class:`rwwarp.wave.batch_plan.BatchPlan`; read-only: a new plan changes it)"
    return property(get)


for _name in PLAN_FIELDS:
    if _name not in ("device", "deterministic"):    # the per-call executor's own (a plan may run elsewhere)
        setattr(RayWave, _name, _plan_name(_name))
del _name


#: The keyword options of :class:`RayWave` that :func:`rwwarp.psf_map` (and its distributed form) hand to
#: every batch unchanged, under the same names (with ``memory_budget_bytes`` from their budget).
RAYWAVE_OPTIONS = ("device", "plan", "dtype", "amplitude", "rays_per_sample", "center_mm", "use_reference",
                   "gauss_nodes", "nyquist_safety", "method", "focal_patch_tol", "deterministic", "pixel_values")
