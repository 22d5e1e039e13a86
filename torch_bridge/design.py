"""Optics side of end-to-end design: PSF nodes, differentiable PSF providers, and the two classical
comparison designs (paraxial achromatic DOE, RMS-spot optimisation with the ray model).

PSF providers (all return ``(n_nodes, n_channels, size, size)`` float64 tensors: the fraction of the
power entering the pupil per sensor pixel, rows along +y, for one wavelength per colour channel):

* :class:`LiveProvider` (in :mod:`torch_bridge.live`, re-exported here): ray-wave PSFs every call, so
  every learning quantity of the lens (curvatures, thicknesses, aspherics, DOE) gets gradients.
* :class:`CachedProvider`: the refractive part is frozen; the aberrated DOE-plane fields
  (:meth:`rwwarp.psf.RayWave.field_array`) are computed once per (depth, wavelength) for all nodes
  and kept, so a step only applies the DOE phase and propagates to the sensor (the paper's remark
  that this makes ray-wave PSFs as cheap as the paraxial model). Gradients reach the DOE only.
  With ``model="paraxial-wave"`` the fields are those of the paraxial equivalent system
  (:func:`rwwarp.psf.paraxial_equivalent`: an ideal thin lens at the DOE plane), which is how
  DOEs are designed when the refractive lens is idealised.
  With the module's ``method="two-step"`` the wave step (:mod:`rwwarp.wave.wave_step`) is applied to the
  geometric field once, when it is cached (it does not depend on the DOE behind it): docs/accuracy.md
  "In the design loop".

Ray model (:class:`RaySpot`, :func:`paraxial_efl`, :func:`paraxial_achromat`): in
:mod:`torch_bridge.ray_spot` (re-exported here).

Units: mm, um for wavelengths, degrees for fields, radians for DOE coefficients.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from torch_bridge.budget import cached_held_bytes, cached_step_bytes

from .functions import mixed_precision  # noqa: F401  (mixed_precision re-exported for train)
from .live import LiveProvider, _recentred, common_centres  # noqa: F401  (their home: live)
from .ray_spot import RaySpot, paraxial_achromat, paraxial_efl  # noqa: F401  (their home: ray_spot)
from .nodes import field_angles, node_positions_mm, paraxial_object_distance  # noqa: F401  (their home: nodes)
from .cached_focal import FocalEntries

__all__ = [
    "CachedProvider",
    "LiveProvider",
    "RaySpot",
    "common_centres",
    "field_angles",
    "node_positions_mm",
    "paraxial_achromat",
    "paraxial_efl",
    "paraxial_object_distance",
]


# ---------------------------------------------------------------------------------------------- providers
class CachedProvider(FocalEntries):
    """PSFs with a frozen refractive part: DOE-plane fields cached per (depth, wavelength).

    Parameters
    ----------
    module : HybridLens
        Holds the learning DOE (its ``doe`` values are used). Besides the DOE only the DOE-to-sensor
        distance (``thickness`` of the DOE when it is the last surface) may learn: the cached fields
        do not depend on it and the propagation differentiates it.
    fields_deg : list of (x, y)
        Node field angles (deg) of the real lens.
    size, pixel_mm : PSF patch size (pixels) and pixel pitch (mm).
    model : "ray-wave" | "paraxial-wave"
        Fields of the real lens, or of its paraxial equivalent (ideal thin lens at the DOE plane,
        made stigmatic for the object distance that gives the real lens's image shift).
    wavelength_ref_um : float
        Reference wavelength of the patch centres (um).
    doe_budget_cpmm : float
        Spatial frequency (cycles/mm) reserved for the DOE when a plan is made: the DOE-plane pitch
        is at most ``1 / (2 safety (f_field + f_DOE + budget))`` so the DOE can grow without replanning.
    min_feature_mm : float, optional
        Fabrication limit of the DOE (smallest feature, mm; see :meth:`HybridLens.limit_doe_feature`,
        which the training applies after every optics update). Plans are then made for any DOE
        within the limit: pitch at most half the feature, and at least ``1 / (levels feature)``
        cycles/mm (``1 / (2 feature)`` unquantised, times the wavelength's DOE scale) reserved for
        the DOE, so a DOE that grows up to the limit needs no replanning.
    cache_precision : "double" | "single"
        Storage of the cached DOE-plane fields: complex128, or complex64 (half the memory; each use is
        computed in complex128 from the stored values: the PSFs and gradients move by the fields' rounding,
        on the A489 + DOE (4 nodes, 2 wavelengths) PSFs by 2.6e-10 / 5.1e-10 of the peak and DOE gradients by
        1.3e-8 / 1.2e-10 (focal / ASM), far under the plans' 1e-4 sampling error; a focal entry's operators
        stay complex128, so it saves less there).
    cache_device : "device" | "host"
        Where the band-limited (ASM) entries' fields are kept: on the module's device, or (a CUDA module) in
        page-locked host memory, each node's field uploaded (asynchronously, on the current stream) when its
        propagation runs and again when its DOE modulation is recomputed in backward. A step then holds only the
        fields of the node being propagated, not every wavelength's entry: the a489_aberration gpu preset's nine
        entries are 9.5 GB, of which a step uses three, at the cost of ~6.4 GB of host-to-device copies a step.
        Focal entries stay on the device. On the CPU the two are the same.
    memory_budget_bytes : int, optional
        Peak bytes one entry's field build may use (default
        :func:`~torch_bridge.budget.default_memory_budget_bytes`: half the free memory of a CUDA
        device, 4 GiB on the CPU). The nodes of an entry are traced in batches of :meth:`build_batch`
        sources (rays without gradient buffers: the refractive part is frozen), so the peak does
        not grow with the node count; :attr:`build_log` records each entry's batches and estimates.

    **Plans.** Each entry gets its automatic plan (plus the DOE budget); the wavelengths of one depth
    share their patch centres. Each entry's plan, patch centres and
    the DOE frequency it was made for are recorded in :attr:`plans`; :meth:`check_sampling` replans
    entries whose DOE has outgrown them (Nyquist of field + DOE, two samples per quantisation step)
    and re-centres patches the DOE has moved; :meth:`load_plans` rebuilds entries from a record
    (exact resume: a RayWave is a deterministic function of the refractive lens, the sources, the
    plan and the centres). Patch centres are :func:`common_centres` (one per node for all wavelengths,
    so lateral colour stays in the RGB PSFs).
    """

    def __init__(self, module, fields_deg, size: int, pixel_mm: float, model: str = "ray-wave",
                 wavelength_ref_um: float = 0.55, doe_budget_cpmm: float = 0.0, memory_budget_bytes: int | None = None,
                 min_feature_mm: float | None = None, cache_precision: str = "double", cache_device: str = "device"):
        if model not in ("ray-wave", "paraxial-wave"):
            raise ValueError(f"model must be 'ray-wave' or 'paraxial-wave', got {model!r}")
        if memory_budget_bytes is not None and not memory_budget_bytes > 0:
            raise ValueError(f"memory_budget_bytes must be > 0 or None, got {memory_budget_bytes!r}")
        from .phase_orders import warn_design_order_only
        warn_design_order_only(module, "CachedProvider")
        if cache_precision not in ("double", "single"):
            raise ValueError(f"cache_precision must be 'double' or 'single', got {cache_precision!r}")
        #: dtype of the cached DOE-plane fields (they are propagated in complex128 whatever it is)
        self.cache_dtype = torch.complex128 if cache_precision == "double" else torch.complex64
        if cache_device not in ("device", "host"):
            raise ValueError(f"cache_device must be 'device' or 'host', got {cache_device!r}")
        #: the ASM entries' fields in page-locked host memory (a CUDA module with cache_device "host")
        self.cache_on_host = cache_device == "host" and module.thickness_base.device.type == "cuda"
        if min_feature_mm is not None and not min_feature_mm > 0:
            raise ValueError(f"min_feature_mm must be > 0 or None, got {min_feature_mm!r}")
        self.min_feature_mm = None if min_feature_mm is None else float(min_feature_mm)
        lens = module.to_lens()
        self.module, self.size, self.pixel_mm, self.model = module, int(size), float(pixel_mm), model
        self.real_fields = list(fields_deg)
        self.wl_ref = float(wavelength_ref_um)
        self.doe_budget = float(doe_budget_cpmm)
        self.plane = lens.doe_index
        self.learn_distance = self.plane == len(lens.surfaces) - 1 and \
            int(self.plane) in set(module.thickness_index.tolist())
        self._cache = {}
        self._focal = {}    # entry key -> (nodes [(RayWave, field, entering)], distance, geo): method "focal"
        self.plans = {}
        self.replans = 0
        self.replan_log = []
        self.memory_budget_bytes = None if memory_budget_bytes is None else int(memory_budget_bytes)
        self.build_log = []
        self.step_log = []
        self._chunks = {}   # entry key -> {chunk size: [(slice, RayWave)]}
        self._step_chunk = {}   # entry key -> the chunk size its steps use while it fits (step_chunk)

    # ------------------------------------------------------------------ geometry and plans
    def _geometry(self, depth_mm):
        """(HybridLens that makes the plans and samples the DOE, its node fields, the object distance
        to pass (mm or None)) for one depth. The paraxial-wave system is rebuilt from the current lens."""
        from torch_bridge.modules import HybridLens
        m = self.module
        if self.model == "ray-wave":
            return m, self.real_fields, depth_mm
        from rwwarp.psf import paraxial_equivalent
        lens = m.to_lens()
        eq, eq_fields = paraxial_equivalent(lens, self.real_fields, [self.wl_ref])
        d = lens.object_distance if depth_mm is None else float(depth_mm)
        eq = eq.replace(object_distance=paraxial_object_distance(lens, eq, d, self.wl_ref))
        geo = HybridLens(eq, plan=m.plan_policy, rays_per_sample=m.rays_per_sample, nyquist_safety=m.nyquist_safety,
                         amplitude=m.amplitude, gauss_nodes=m.gauss_nodes, use_reference=m.use_reference,
                         method=m.method, focal_patch_tol=m.focal_patch_tol, pixel_values=m.pixel_values)
        # on the module's device: the fields it traces are cached there, and the focal operator it plans
        # works in that device's array namespace (numpy on the CPU, CuPy on CUDA)
        geo = geo.to(m.thickness_base.device)
        return geo, eq_fields, None

    @staticmethod
    def _key(wavelength_um, depth_mm):
        return (round(float(wavelength_um), 9), None if depth_mm is None else float(depth_mm))

    def _doe_frequency(self, geo, origin, pitch, n_grid, wavelength_um):
        """(largest local DOE frequency (cycles/mm) over the windows at this wavelength, smallest
        quantisation step (mm) or inf), from the current DOE profile."""
        from rwwarp import doe as rdoe
        lens = geo.to_lens()
        s = lens.surfaces[lens.doe_index]
        prof = rdoe.profile_from_dict(s.profile)
        if not prof.is_continuous:
            return 0.0, math.inf
        g = np.linspace(0.0, (n_grid - 1) * pitch, 33)
        gmax = 0.0
        sd = s.semi_diameter
        for o in origin:
            x, y = np.meshgrid(o[0] + g, o[1] + g)
            if sd is not None:
                # only the clear aperture transmits (the tracer clips rays outside it): the profile's
                # continuation beyond it must not drive the sampling
                inside = (np.maximum(np.abs(x), np.abs(y)) <= sd) if s.shape == "square" else (x * x + y * y <= sd * sd)
                x, y = x[inside], y[inside]
                if x.size == 0:
                    continue
            gx, gy = prof.gradient(x, y, s.design_wavelength_um)
            gmax = max(gmax, float(np.max(np.hypot(gx, gy))))
        scale = rdoe.wavelength_scale(s.material, s.design_wavelength_um, wavelength_um)
        step = math.inf if (not s.levels or gmax == 0) else 2.0 * math.pi / gmax / int(s.levels)
        return scale * gmax / (2.0 * math.pi), step

    def _auto_plan(self, key, pilot=None):
        """The automatic plan of one entry (the DOE unquantised: rwwarp's auto plan cannot align a grid
        to the steps of a flat quantised DOE) refined by the DOE budget and the step rule. ``pilot``: the entry's
        (:meth:`_pilot`; the tracer reads no DOE levels: a DOE is a plane to it), None: traced here."""
        from rwwarp.wave.plan import Plan, nice_fft_length
        from rwwarp.psf import RayWave
        wavelength_um, depth_mm = key
        geo, fields, depth = self._geometry(depth_mm)
        lens_p = geo.to_lens()
        sd = lens_p.surfaces[lens_p.doe_index]
        if sd.levels:
            lens_p = lens_p.with_surface(lens_p.doe_index, levels=None)
        rw0 = RayWave(lens_p, fields, [float(wavelength_um)] * len(fields), self.size, self.pixel_mm,
                      device=geo.rw_device, plan=geo.plan_policy, amplitude=geo.amplitude, object_distance_mm=depth,
                      rays_per_sample=geo.rays_per_sample, use_reference=geo.use_reference,
                      gauss_nodes=geo.gauss_nodes, nyquist_safety=geo.nyquist_safety, pixel_values=geo.pixel_values,
                      pilot=pilot)
        pl = rw0.plan
        safety = geo.nyquist_safety
        budget = self._reserve_cpmm(sd, wavelength_um)
        pitch = 1.0 / (2.0 * safety * (1.0 / (2.0 * safety * pl.pitch_mm) + budget))
        _, step = self._doe_frequency(geo, rw0.origin, pl.pitch_mm, pl.n_grid, wavelength_um)
        if self.min_feature_mm is not None:
            step = min(step, self.min_feature_mm)
        pitch = min(pitch, 0.5 * step)
        ratio = pl.pitch_mm / pitch
        n_grid = math.ceil(pl.n_grid * ratio)
        return Plan(pitch, n_grid, nice_fft_length(max(2 * n_grid, math.ceil(pl.n_pad * ratio))),
                    math.ceil(pl.ray_grid * ratio), "explicit", False,
                    list(pl.reasons) + [f"DOE budget {budget:g} cycles/mm reserved"])

    def _reserve_cpmm(self, doe_surface, wavelength_um: float) -> float:
        """Spatial frequency (cycles/mm) an entry's plan reserves for the DOE at ``wavelength_um`` (um): the
        ``doe_budget_cpmm``, or with a fabrication limit at least what a DOE at the limit reaches (``1 /
        (levels min_feature)``, ``1 / (2 min_feature)`` unquantised, times the wavelength's DOE scale)."""
        budget = self.doe_budget
        if self.min_feature_mm is not None:
            from rwwarp import doe as rdoe
            sd = doe_surface
            f_lim = 1.0 / ((int(sd.levels) if sd.levels else 2) * self.min_feature_mm)
            budget = max(budget, f_lim * rdoe.wavelength_scale(sd.material, sd.design_wavelength_um, wavelength_um))
        return budget

    @staticmethod
    def _unify(plans):
        """One plan covering several: the finest pitch, the widest window, padding and ray density."""
        from rwwarp.wave.plan import Plan, nice_fft_length
        pitch = min(p.pitch_mm for p in plans)
        n_grid = max(math.ceil(p.n_grid * p.pitch_mm / pitch) for p in plans)
        n_pad = nice_fft_length(max([2 * n_grid] + [math.ceil(p.n_pad * p.pitch_mm / pitch) for p in plans]))
        rays = max(math.ceil(p.ray_grid * p.pitch_mm / pitch) for p in plans)
        return Plan(pitch, n_grid, n_pad, rays, "explicit", False, ["shared by the wavelengths of one depth"])

    def _recorded_plan(self, key):
        from rwwarp.wave.plan import Plan
        rec = self.plans.get(key)
        if rec is None or rec.get("pitch_mm") is None:
            return None
        return Plan(rec["pitch_mm"], rec["n_grid"], rec["n_pad"], rec["ray_grid"], "explicit", False,
                    ["recorded plan"])

    def budget_bytes(self, strict: bool = True) -> int:
        """The memory budget (bytes) of one entry's field build: ``memory_budget_bytes`` less what the device
        holds for this process outside torch's allocator (:func:`~torch_bridge.budget.device_overhead_bytes`: the
        CUDA context, CuPy's and Warp's pools; 0 on the CPU; read now), or the device default
        (:func:`~torch_bridge.budget.default_memory_budget_bytes`, read now). When the overhead alone reaches
        the budget: ``strict`` raises :class:`~rwwarp.wave.plan.MemoryBudgetError` saying so (a field build), else
        0 (a training step then checkpoints every chunk rather than stopping a run)."""
        from rwwarp.wave.plan import MemoryBudgetError
        from torch_bridge.budget import default_memory_budget_bytes, device_overhead_bytes
        if self.memory_budget_bytes is not None:
            overhead = device_overhead_bytes(self.module.rw_device)
            if overhead >= self.memory_budget_bytes:
                if not strict:
                    return 0
                raise MemoryBudgetError(
                    f"the memory budget of {self.memory_budget_bytes / 1e9:.3g} GB (optics.memory_budget_gb) leaves "
                    f"nothing for the field builds: {overhead / 1e9:.3g} GB of {self.module.rw_device} is in use "
                    "outside torch's allocator (the CUDA context, Warp's and CuPy's pools; where the driver cannot "
                    "report this process's own use, other processes on the card count too). Raise the budget, or "
                    "free the card")
            return self.memory_budget_bytes - overhead
        return default_memory_budget_bytes(self.module.rw_device)

    def step_budget_bytes(self) -> int:
        """Bytes a training step's propagation graphs (every entry of one :meth:`psfs` call, held until the
        backward) may take: half of what the memory budget leaves beside the cached fields and the device's
        memory outside torch's allocator (:meth:`budget_bytes`; the other half is the network's activations and
        the allocator's slack); without a budget, half the device default
        (:func:`~torch_bridge.budget.default_memory_budget_bytes`: half the free memory, read now)."""
        if self.memory_budget_bytes is None:
            return self.budget_bytes() // 2
        return max(0, self.budget_bytes(strict=False) - self.cache_bytes()) // 2

    def build_batch(self, rw, budget_bytes: int | None = None) -> dict:
        """Sources per trace batch of a field build under the budget (bytes, default
        :meth:`budget_bytes`), from the library's own estimates: ``fixed`` = the planning pilot and
        maps (:meth:`HybridLens.bytes_fixed`) plus the entry's cached field (``nsrc n_grid^2``
        complex128), ``per_source`` = one source of a frozen build
        (:meth:`HybridLens.bytes_per_source` with ``record=False``; with a wave step, its arrays). The default
        budget is what the memory budget leaves beside the fields already cached (``held``; the device default
        reads the free memory, which leaves them out already). Returns a dict with ``batch``, ``per_source``,
        ``fixed``, ``budget``, ``held`` and ``peak`` (``fixed + batch per_source``, bytes); warns when even one
        source exceeds the budget (the build then runs one source at a time)."""
        import warnings
        from rwwarp.errors import SamplingWarning
        held = self.cache_bytes() if (budget_bytes is None and self.memory_budget_bytes is not None) else 0
        budget = self.budget_bytes() - held if budget_bytes is None else int(budget_bytes)
        m = self.module
        per = int(m.bytes_per_source(rw, record=False))
        if np.any(getattr(rw, "wave_step", 0.0)):
            # the wave step of a source (method "two-step"): its padded field, spectrum and transfer function
            # (complex128, FFT length rw.wave_step_pad) and the reference sphere's phase, its rotation and the
            # field without it (rwwarp.wave.wave_step.apply_wave_step: 8 + 16 + 16 bytes a wave-plane sample)
            # (the rim-resolved step: one padded field and its weight per node, rwwarp.wave.wave_step.step_nodes)
            from rwwarp.wave.wave_step import step_nodes
            k = step_nodes(rw)
            per += 3 * 16 * k * int(rw.wave_step_pad) ** 2 + (40 + 24 * (k - 1)) * rw.plan.n_grid ** 2
        fixed = int(m.bytes_fixed(rw)) + rw.nsrc * rw.plan.n_grid ** 2 * 16
        batch = int(max(1, min(rw.nsrc, (budget - fixed) // max(per, 1))))
        if fixed + per > budget:
            warnings.warn(f"field build: one source needs ~{(fixed + per) / 1e9:.3g} GB (ray grid "
                          f"{rw.plan.ray_grid}^2, DOE-plane grid {rw.plan.n_grid}^2, {rw.nsrc} cached fields) "
                          f"> memory budget {budget / 1e9:.3g} GB; tracing one source at a time", SamplingWarning,
                          stacklevel=3)
        return {"batch": batch, "per_source": per, "fixed": fixed, "budget": budget, "held": held,
                "peak": fixed + batch * per}

    def _entry_centres(self, key, centres, geo, fields, depth):
        """Patch centres (mm, (n_nodes, 2)) of entry ``key``: those given, else the recorded ones, else
        :func:`common_centres` at the reference wavelength."""
        rec = self.plans.get(key) or {}
        if centres is None and rec.get("centers") is not None:
            centres = rec["centers"]
        if centres is None:
            centres = common_centres(geo, fields, self.wl_ref, depth)
        return np.asarray(centres, dtype=np.float64).reshape(-1, 2)

    def _build(self, key, plan=None, centres=None):
        """Compute and cache the DOE-plane fields of one (wavelength, depth) entry: the nodes are traced
        in batches of :meth:`build_batch` sources (no gradient buffers), each batch a RayWave of its
        nodes with the entry's plan and patch centres (the field of a source does not depend on the
        others in its batch)."""
        wavelength_um, depth_mm = key
        geo, fields, depth = self._geometry(depth_mm)
        pilot = self._pilot(geo, fields, wavelength_um, depth)   # one trace for every plan of the entry
        if self._uses_focal(key, pilot):
            return self._build_focal(key, centres, pilot)
        if plan is None:
            plan = self._auto_plan(key, pilot)
        centres = self._entry_centres(key, centres, geo, fields, depth)
        kw = dict(object_distance_mm=depth, pixel_mm=self.pixel_mm, plan=plan, requires_grad=False)
        wl = float(wavelength_um)
        rw = geo.raywave(fields, [wl] * len(fields), self.size, center_mm=centres, pilot=pilot, **kw)
        est = self.build_batch(rw)
        b = est["batch"]
        dev = self.module.thickness_base.device
        n = rw.plan.n_grid
        if b >= rw.nsrc:
            # the wave step (method "two-step", where the plan has one) does not depend on the DOE behind it:
            # the field is cached after it (rwwarp.wave.wave_step)
            u = self._to_torch(rw.wave_stepped(rw.field_array()), dev, self.cache_dtype)
            if self.cache_on_host:   # one copy into page-locked memory (no pageable copy in between)
                u = torch.empty(u.shape, dtype=u.dtype, pin_memory=True).copy_(u)
            entering = torch.as_tensor(rw.entering, dtype=torch.float64, device=dev)
        else:
            u = torch.empty((rw.nsrc, n, n), dtype=self.cache_dtype,
                            **({"device": "cpu", "pin_memory": True} if self.cache_on_host else {"device": dev}))
            entering = torch.empty(rw.nsrc, dtype=torch.float64, device=dev)
            for k in range(0, rw.nsrc, b):
                sl = slice(k, min(k + b, rw.nsrc))
                sub = self._sub_raywave(key, rw, geo, sl, centres[sl], depth, pilot.subset(sl))
                u[sl] = self._to_torch(sub.wave_stepped(sub.field_array()), dev, self.cache_dtype)
                entering[sl] = torch.as_tensor(sub.entering, dtype=torch.float64, device=dev)
                del sub
        if str(rw.tracer.device).startswith("cuda"):
            from rwwarp.trace import release_warp_pool
            # the batches' ray buffers went back to Warp's memory pool; hand them to the driver (for
            # torch, CuPy and the next entries: the pool would otherwise keep up to the build budget)
            release_warp_pool(rw.tracer.device)
        self.build_log.append({"key": list(key), "nsrc": rw.nsrc, "batches": -(-rw.nsrc // b),
                               "ray_grid": rw.plan.ray_grid, "n_grid": n, "n_pad": rw.plan.n_pad, **est})
        dist = torch.full((rw.nsrc,), float(rw.z_sensor - rw.z_plane), dtype=torch.float64, device=dev)
        f_doe = (self.plans.get(key) or {}).get("f_doe_cpmm")
        if f_doe is None:
            f_doe = self._doe_frequency(geo, rw.origin, plan.pitch_mm, plan.n_grid, wavelength_um)[0]
        self._cache[key] = (rw, u, dist, entering, geo)
        # the method is recorded with the plan: "auto" decides from the DOE of the moment, and an entry built again
        # (a resumed run's load_plans, release) must take the path it took, not the one today's DOE would get
        self.plans[key] = {"method": "asm", "pitch_mm": plan.pitch_mm, "n_grid": plan.n_grid, "n_pad": plan.n_pad,
                           "ray_grid": plan.ray_grid, "centers": np.asarray(centres).tolist(),
                           "f_doe_cpmm": float(f_doe), "safety": float(geo.nyquist_safety)}
        return self._cache[key]

    @staticmethod
    def _to_torch(u, dev, dtype=torch.complex128) -> torch.Tensor:
        """A field from :meth:`RayWave.field_array` (numpy, or a CuPy view of a Warp array) as a tensor of
        ``dtype`` (complex128 or complex64) on ``dev`` that owns its memory."""
        if isinstance(u, np.ndarray):
            return torch.from_numpy(np.array(u, copy=True)).to(dev, dtype)
        t = torch.as_tensor(u, device=dev)
        return t.to(dtype) if t.dtype != dtype else t.clone()

    def _entry(self, wavelength_um: float, depth_mm):
        key = self._key(wavelength_um, depth_mm)
        e = self._cache.get(key) or self._focal.get(key)
        if e is None:
            e = self._build(key, self._recorded_plan(key))
        return e

    def prepare(self, wavelengths_um, depths_mm, progress: bool = False):
        """Compute and cache the DOE-plane fields for every (depth, wavelength) now; entries without a
        recorded plan get the plan shared by the wavelengths of their depth."""
        work = []
        for d in depths_mm:
            keys = [self._key(w, d) for w in wavelengths_um]
            todo = [k for k in keys if k not in self._cache and k not in self._focal]
            if not todo:
                continue
            fresh = [k for k in todo if self._recorded_plan(k) is None]
            centres = None
            if fresh:
                geo, fields, depth = self._geometry(d)
                centres = common_centres(geo, fields, self.wl_ref, depth)
            for k in todo:
                work.append((k, None, None if k not in fresh else centres))
        it = work
        if progress:
            from tqdm.auto import tqdm
            it = tqdm(work, desc="DOE-plane fields", unit="batch", leave=False)
        for k, plan, centres in it:
            self._build(k, plan or self._recorded_plan(k), centres)  # no record: the automatic plan

    def load_plans(self, plans: dict):
        """Use recorded plans (:attr:`plans` of an earlier run) for the entries built from now on."""
        self._cache.clear()
        self._focal.clear()
        self._chunks.clear()
        self._step_chunk.clear()
        self.plans = {k: dict(v) for k, v in plans.items()}

    def release(self):
        """Drop the cached fields, their RayWaves (with their focal operators) and the propagation chunks,
        and hand the freed device memory back (torch's cache, Warp's pool). The recorded :attr:`plans`
        stay: an entry needed again is rebuilt on the same plan and patch centres."""
        self._cache.clear()
        self._focal.clear()
        self._chunks.clear()
        self._step_chunk.clear()
        dev = str(self.module.rw_device)
        if dev.startswith("cuda"):
            import gc

            from rwwarp.trace import release_warp_pool
            gc.collect()
            torch.cuda.empty_cache()
            release_warp_pool(dev)

    def cache_bytes(self) -> int:
        """Device bytes held by the cached fields (host-kept ones, ``cache_device="host"``, are not counted) and,
        for focal entries, the nodes' focal operators once built (their factors are of the order of the field:
        :attr:`rwwarp.wave.focal.FocalPropagator.nbytes`)."""
        ops = sum(op.nbytes for nodes, _, _ in self._focal.values() for rw, _, _ in nodes
                  if (op := getattr(rw, "_focal_op", None)) is not None)
        dev = self.module.thickness_base.device
        return sum(e[1].numel() * e[1].element_size() for e in self._cache.values() if e[1].device == dev) + ops + \
            sum(u.numel() * u.element_size() for nodes, _, _ in self._focal.values() for _, u, _ in nodes)

    def check_sampling(self) -> int:
        """Replan the entries whose pitch no longer samples field + DOE (``2 pitch (f_field + f_DOE) <= 1``
        with ``f_field`` the field's own band the plan was made for, and two samples per quantisation
        step), and re-centre patches the DOE has moved by more than ``size / 8`` pixels (the sensor
        patches move, the cached field is kept: :meth:`rwwarp.psf.RayWave.recentre`). Returns the
        number of entries replanned or re-centred."""
        rebuilt = 0
        per_depth = {}   # the current geometry and patch centres, once per depth

        def current(depth_key):
            if depth_key not in per_depth:
                geo_now, fields_now, depth_now = self._geometry(depth_key)
                per_depth[depth_key] = (geo_now, common_centres(geo_now, fields_now, self.wl_ref, depth_now))
            return per_depth[depth_key]
        for key in list(self._cache):
            rw, _, _, _, geo = self._cache[key]
            rec = self.plans[key]
            pitch = rw.plan.pitch_mm
            f_doe, step = self._doe_frequency(geo if self.model == "ray-wave" else current(key[1])[0],
                                              rw.origin, pitch, rw.plan.n_grid, key[0])
            lens_k = geo.to_lens()
            reserve = self._reserve_cpmm(lens_k.surfaces[lens_k.doe_index], key[0])   # as _auto_plan reserved it
            f_field = max(1.0 / (2.0 * rec["safety"] * pitch) - reserve - rec["f_doe_cpmm"], 0.0)
            if 2.0 * pitch * (f_field + f_doe) > 1.0 or pitch > 0.5 * step:
                self.replan_log.append({"key": list(key), "reason": "sampling", "pitch_um": pitch * 1e3,
                                        "f_field_cpmm": f_field, "f_doe_cpmm": f_doe, "doe_step_um": step * 1e3})
                self._cache.pop(key)
                self._chunks.pop(key, None)
                self._step_chunk.pop(key, None)
                self.plans.pop(key, None)
                self._build(key)
                rebuilt += 1
                continue
            cen = current(key[1])[1]
            if np.max(np.abs(cen - rw.centers)) > self.size * self.pixel_mm / 8.0:
                # only the sensor patches move: the cached DOE-plane field stays valid (no rebuild)
                self.replan_log.append({"key": list(key), "reason": "re-centre",
                                        "shift_um": float(np.max(np.abs(cen - rw.centers))) * 1e3})
                # copies: the RayWaves themselves stay as HybridLens.raywave cached them (keyed by centres)
                moved = _recentred(rw, cen)
                self._cache[key] = (moved,) + tuple(self._cache[key][1:])
                chunks = self._chunks.get(key, {})
                for c, parts in chunks.items():
                    chunks[c] = [(sl, moved if sub is rw else _recentred(sub, moved.centers[sl])) for sl, sub in parts]
                self.plans[key]["centers"] = np.asarray(moved.centers).tolist()
                rebuilt += 1
        rebuilt += self._check_focal(current)
        self.replans += rebuilt
        return rebuilt

    def step_bytes_per_source(self, rw) -> int:
        """Estimated peak bytes one node adds to a training step (:func:`torch_bridge.budget.cached_step_bytes`)."""
        k = int(self.module.doe_base.numel()) if hasattr(self.module, "doe_base") else 8
        return cached_step_bytes(rw, k, self.cache_dtype != torch.complex128)

    def step_chunk(self, rw, budget_bytes: int | None = None, key=None) -> int:
        """Nodes per propagation chunk of a step under the budget (bytes, default :meth:`step_budget_bytes`):
        ``budget // step_bytes_per_source`` (at least 1, at most all nodes). With an entry ``key`` the entry keeps
        the chunk it had while that still fits and is more than half of what fits: on a GPU the budget is read
        from the device's memory each step and wanders, and each new chunk size is new RayWaves and new FFT
        shapes (VkFFT plans, compiled at ~0.2-0.7 s each: the a489_edof gpu step built 1-13 a step, session 24)."""
        budget = self.step_budget_bytes() if budget_bytes is None else int(budget_bytes)
        fits = int(max(1, min(rw.nsrc, budget // max(self.step_bytes_per_source(rw), 1))))
        if key is None:
            return fits
        kept = self._step_chunk.get(key)
        if kept is not None and kept <= fits < 2 * kept:
            return kept
        self._step_chunk[key] = fits
        return fits

    def _chunk_raywaves(self, key, rw, geo, chunk: int):
        """[(slice, RayWave of those nodes)] for propagation chunks of ``chunk`` nodes: RayWaves made
        with the entry's plan and patch centres (their windows equal the entry's, checked), cached
        per entry and chunk size (only their propagation arguments are used; one pilot trace of all nodes)."""
        if chunk >= rw.nsrc:
            return [(slice(0, rw.nsrc), rw)]
        store = self._chunks.setdefault(key, {})
        if chunk in store:
            return store[chunk]
        depth = key[1] if self.model == "ray-wave" else None
        out, pilot = [], self._pilot(geo, list(rw.fields), key[0], depth)
        for k0 in range(0, rw.nsrc, chunk):
            sl = slice(k0, min(k0 + chunk, rw.nsrc))
            out.append((sl, self._sub_raywave(key, rw, geo, sl, rw.centers[sl], depth, pilot.subset(sl))))
        store[chunk] = out
        return out

    def _sub_raywave(self, key, rw, geo, sl, centres, depth, pilot=None):
        """A RayWave of the nodes ``sl`` of entry ``key`` on the entry's plan (``rw.plan``, explicit) and windows
        (checked), for a build batch or a propagation chunk. With a wave step (method "two-step") the batch is
        planned ``"asm"`` on the entry's widened plan and given the entry's reduced distances
        (``rw.wave_step[sl]``, FFT length ``rw.wave_step_pad``): its own wave-step plan would follow its own
        nodes' edge widths, not the entry's. ``pilot``: the nodes' (:meth:`_pilot` subset) or None (traced)."""
        import warnings
        from rwwarp.errors import SamplingWarning
        from rwwarp.wave.plan import Plan
        pl = rw.plan
        plan = Plan(pl.pitch_mm, pl.n_grid, pl.n_pad, pl.ray_grid, "explicit", False, ["entry plan"])
        stepped = bool(np.any(getattr(rw, "wave_step", 0.0)))
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="ray density criterion", category=SamplingWarning)
            sub = geo.raywave(list(rw.fields[sl]), list(rw.wls[sl]), self.size, object_distance_mm=depth,
                              pixel_mm=self.pixel_mm, plan=plan, center_mm=centres, requires_grad=False,
                              method="asm" if stepped else None, pilot=pilot)
        if not np.allclose(sub.origin, rw.origin[sl], rtol=0, atol=1e-9):
            raise RuntimeError(f"nodes {sl.start}:{sl.stop} of entry {key}: their DOE-plane windows differ from the "
                               "entry's (internal error)")
        if stepped:
            from dataclasses import replace
            rim = getattr(rw, "wave_step_rim", None)
            sub.use_plan(replace(sub.batch_plan, wave_step=np.asarray(rw.wave_step, float)[sl].copy(),
                                 wave_step_pad=rw.wave_step_pad,
                                 wave_step_rim=None if rim is None else np.asarray(rim, float)[sl].copy()))
        return sub

    def held_bytes_per_source(self, rw) -> int:
        """Bytes one node's recorded propagation keeps until the step's backward
        (:func:`torch_bridge.budget.cached_held_bytes`)."""
        return cached_held_bytes(rw, self.learn_distance)

    def psfs(self, wavelengths_um, depth_mm=None, chunk: int | None = None, part: int | None = None) -> torch.Tensor:
        """(n_nodes, len(wavelengths_um), size, size): DOE phase applied to the cached fields and
        propagated to the sensor (gradients reach the DOE coefficients and a learning DOE-to-sensor
        distance).

        The DOE modulation ``u exp(i alpha phi0)`` of a node's cached field is a checkpoint of its own
        (:class:`~torch_bridge.functions.Recompute`: no phase, polynomial or modulated field is kept for the
        backward pass, which recomputes them), so a recorded node keeps only :meth:`held_bytes_per_source` until
        the backward pass and its propagation runs forward once. The nodes of a wavelength are propagated in
        chunks of ``chunk`` nodes (default :meth:`step_chunk` under the step's budget: the chunk bounds the
        propagation's transient memory, freed before the next chunk runs, so each chunk may use the whole
        budget); only when the graphs kept until the backward pass (every node of the call) exceed the budget
        is each chunk checkpointed as a whole (forward without graph, recomputed in backward), each wavelength
        then taking an equal share. :attr:`step_log` records the choice. ``part`` (with ``chunk``): only the
        ``part``-th chunk of nodes, (its nodes, ...) -- a rank's share in a distributed step, the same values the
        whole call gives those nodes."""
        if part is not None and chunk is None:
            raise ValueError("CachedProvider.psfs: part needs chunk (the share's size in nodes)")
        from torch_bridge.functions import Recompute, doe_scale, upload
        from torch_bridge.operator_function import operator_propagate
        from torch_bridge.tiles import run_tiles, wants_grad
        doe = self.module.value("doe")
        thick = self.module.value("thickness")[self.plane] if self.learn_distance else None
        budget = self.step_budget_bytes()
        # a learning distance's value on the host once per call (a read waits for the device), not once per chunk
        thick_host = None if thick is None else float(thick.detach())
        entries = [(w, self._key(w, depth_mm), self._entry(w, depth_mm)) for w in wavelengths_um]
        held = sum(self.held_bytes_per_source(e[0]) * e[0].nsrc for _, k, e in entries if k not in self._focal)
        whole = held <= budget     # the recorded graphs of the call fit: no chunk is checkpointed
        out = []
        for w, key, entry in entries:
            if key in self._focal:
                if part is not None:   # one plan a node: the share is a slice of the nodes
                    nodes, dist_f, geo_f = entry
                    entry = (nodes[part * chunk:(part + 1) * chunk], dist_f, geo_f)
                out.append(self._focal_psfs(key, entry, doe, thick, budget // max(1, len(wavelengths_um))))
                continue
            rw, u, dist, entering, geo = entry
            share = budget if whole else budget // max(1, len(wavelengths_um))
            c = self.step_chunk(rw, share, key) if chunk is None else max(1, int(chunk))
            parts = self._chunk_raywaves(key, rw, geo, c)
            if part is not None:
                parts = [parts[part]]
                entering = entering[parts[0][0]]
            tensors = [doe] if thick is None else [doe, thick]
            self.step_log.append({"key": list(key), "chunk": c, "chunks": len(parts),
                                  "bytes_per_source": self.step_bytes_per_source(rw),
                                  "held_bytes": held, "checkpointed": not whole and wants_grad(tensors)})
            del self.step_log[:-64]
            # the distance on the host: the cached entry's own (dist holds it on the device), or the learning one
            d_host = float(rw.z_sensor - rw.z_plane) if thick is None else thick_host

            def run(part_, doe_t, thick_t=None, record=True, dist=dist, u=u, geo=geo, d_host=d_host):
                sl, sub = part_

                def modulate(doe_m, record=True):
                    # the cached field (complex64 or complex128) times the DOE's transmission, in complex128
                    with torch.enable_grad() if record else torch.no_grad():
                        phi0 = geo.doe_phase(sub, {"doe": doe_m})
                        alpha = upload(doe_scale(sub), torch.float64, phi0.device)
                        # a host-kept field (cache_device "host") goes up now, asynchronously from page-locked memory
                        us = u[sl].to(phi0.device, non_blocking=True)
                        return us.to(torch.complex128) * torch.exp(1j * alpha[:, None, None] * phi0)
                with torch.enable_grad() if record else torch.no_grad():
                    d = dist[sl] if thick_t is None else thick_t.expand(sl.stop - sl.start)
                    f = Recompute.apply(modulate, doe_t) if record and wants_grad([doe_t]) else \
                        modulate(doe_t, record=False)
                    return operator_propagate(f, d, sub, d_host)
            # chunks recorded as they run, or (graphs over the budget) each a checkpoint (torch_bridge.tiles)
            power = run_tiles(parts, run, tensors, checkpoint=not whole)
            out.append(power / entering[:, None, None])
        return torch.stack(out, 1)
