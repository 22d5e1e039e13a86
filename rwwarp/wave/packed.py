"""Sources computed together, each on its own plan: :func:`source_plans` plans every (field, wavelength)
source alone from one pilot trace of all of them; :class:`PackedRayWave` traces and splats its members in one
set of launches, in arrays sized to the largest member (padding invalid, zero weight, zero field), and
propagates each member by its own plan; :func:`packed_bytes` is a batch's planned peak memory. A PSF is
therefore the same whatever the batch it is computed in (:func:`rwwarp.psf_map`)."""
from __future__ import annotations

import numpy as np

from .plan_sources import plan_sources
from .methods import get
from .batch_plan import BatchPlan
from .raywave import RayWave
from ..trace import Tracer

__all__ = ["PackedRayWave", "packed_bytes", "packed_plan", "source_plans"]


def source_plans(lens, fields, wls, size, pixel, device="cpu", plan="auto", dtype="float64", amplitude="energy",
                 object_distance_mm=None, rays_per_sample=1.0, center_mm=None, use_reference=True,
                 gauss_nodes=None, nyquist_safety=2.0, method="asm", memory_budget_bytes=None,
                 focal_patch_tol=1e-5, deterministic: bool = False, pixel_values: str = "flux",
                 model_tolerance: float | None = None, allow_pixel: bool = False, auto_rule: str = "device",
                 estimate_model_error: bool = True) -> list:
    """Every source planned on its own: one :class:`RayWave` per (field, wavelength) pair (fields in deg,
    wavelengths in um, ``size`` px of ``pixel`` mm), each with the plan, windows and patch it has alone
    (entrance pupil at its own wavelength), from one pilot trace of all of them
    (:func:`rwwarp.wave.plan_sources.plan_sources`: one set of launches, the per-source arrays computed for all
    sources at once; each plan is the one :func:`~rwwarp.wave.batch_plan.plan_batch` gives that source alone).
    Arguments as
    :class:`RayWave` (``allow_pixel``: "auto" may choose ``method="pixel"``, whose members :class:`PackedRayWave` does not take;
    ``auto_rule``: how "auto" chooses, :class:`RayWave`);
    :class:`PackedRayWave` computes them together."""
    plans = plan_sources(lens, fields, wls, size, pixel, device, plan, dtype, amplitude, object_distance_mm,
                         rays_per_sample, center_mm, use_reference, gauss_nodes, nyquist_safety, method,
                         memory_budget_bytes, focal_patch_tol, deterministic, pixel_values, model_tolerance,
                         auto_rule, allow_pixel, estimate_model_error=estimate_model_error)
    # each member's tracer is made when it traces alone (a member computed in a PackedRayWave never does)
    return [RayWave.from_plan(bp, tracer_on_use=True) for bp in plans]


def slot_bytes(ray_grid: int, n_grid: int) -> int:
    """Bytes one member's slot of a :class:`PackedRayWave` takes: its traced rays (232 bytes a ray) and its window
    (64 bytes a sample), the traced-ray and field parts of :func:`rwwarp.wave.plan.estimate_cost`."""
    return int(ray_grid) ** 2 * 232 + int(n_grid) ** 2 * 64


def packed_bytes(members, size: int) -> int:
    """Planned peak memory (bytes) of computing ``members`` (single-source :class:`RayWave` s, ``size`` px
    patches) as one :class:`PackedRayWave`: every source's rays and window in slots of the largest (the
    traced-ray and field parts of :func:`rwwarp.wave.plan.estimate_cost`), plus the largest member's propagation
    (the members propagate one after the other)."""
    rg = max(m.plan.ray_grid for m in members)
    n = max(m.plan.n_grid for m in members)
    prop = max(m.plan.estimate["memory_bytes"] - slot_bytes(m.plan.ray_grid, m.plan.n_grid) for m in members)
    return len(members) * slot_bytes(rg, n) + prop


def packed_plan(members) -> BatchPlan:
    """The :class:`~rwwarp.wave.batch_plan.BatchPlan` of a :class:`PackedRayWave` of single-source ``members``: their
    sources, per-source arrays and windows one after the other (each member keeps its own plan; this one's
    ``plan`` is the first member's, of which only the method is read; no wave step at the batch's level: each
    member's is applied with its propagation)."""
    m0 = members[0]
    uniq = sorted(set(m.wls[0] for m in members))
    src = dict(m0.src)
    for key in ("pos", "dir", "finite", "aim", "half_x", "half_y"):
        src[key] = np.concatenate([np.asarray(m.src[key]) for m in members])
    # each member's own launch (its entrance pupil as it was planned: a kept plan of earlier values keeps
    # its pupil, as it does alone), its wavelength index moved to this batch's tracer
    src["wl"] = np.array([uniq.index(m.wls[0]) for m in members], dtype=np.int32)
    src["fields"] = [f for m in members for f in m.src["fields"]]
    src["relative_opl"] = bool(m0.use_reference)
    cat = lambda name: np.concatenate([np.asarray(getattr(m, name)) for m in members])
    arrays = {name: cat(name) for name in ("n_after", "lam_mm", "origin", "chief_plane", "chief_sensor", "carrier",
                                           "centers", "target", "opl_chief", "chief_ok", "lo", "hi")}
    return BatchPlan(lens=m0.lens, fields=[m.fields[0] for m in members], wls=[m.wls[0] for m in members],
                     size=m0.size, pixel=m0.pixel, device=m0.device, dtype=m0.batch_plan.dtype,
                     amplitude=m0.amplitude, use_reference=m0.use_reference, gauss_nodes=m0.gauss_nodes,
                     pixel_values=m0.pixel_values, deterministic=m0.deterministic, own_pupils=True, pilot=None,
                     src=src, plane=m0.plane, curved_plane=m0.curved_plane, square_pupil=m0.square_pupil,
                     nsrc=len(members), z_plane=m0.z_plane, z_sensor=m0.z_sensor, plan=m0.plan, method=m0.method,
                     focal=None, pupil=(None, None, 1.0), rim=m0.rim, **arrays)


class PackedRayWave(RayWave):
    """Several sources computed together, each on its own plan (:func:`source_plans`): one trace, tube-area,
    splat and finalize launch for all of them, in arrays sized to the largest member (its pupil grid's rays
    and its window per source); a smaller member's extra ray slots are invalid with zero weight and its extra
    samples zero, so they contribute nothing, and its rays land, are splatted and dropped by its own window.
    Each member is then propagated by its own plan (:meth:`RayWave.focal_intensity` / :meth:`RayWave.intensity`
    on its window), or, where :attr:`stacked` (default on CUDA), the focal members' propagations as a few stacked
    operators (:func:`rwwarp.wave.focal_packed.run_focal_members`: the same sums in another order, 2.5e-16 of the
    peak in double precision on the CPU). A source's PSF is therefore what it is alone, whatever the batch (the
    float sums of the splat on CPU threads may add in another order: ~1e-16). ``members``: single-source :class:`RayWave` s of
    one lens, device, precision, amplitude convention and propagation method. Lengths in mm.
    ``requires_grad``: the batch's tracer keeps gradient buffers, so its :meth:`field` can be recorded on a
    ``wp.Tape`` and differentiated with respect to ``tracer.params`` (:mod:`torch_bridge`). ``hold``: the batch
    is kept for repeated runs (:class:`rwwarp.wave.plan_cache.PlanCache`): it and its members keep what their
    runs derive from the plan alone (DOE phases and factors on the windows, the small per-source uploads), so a
    kept batch must not be changed (its lens is the cache's private copy). ``stacked``: True / False, or None for
    the device's default (:meth:`_runs_stacked`)."""

    def __init__(self, members, requires_grad: bool = False, hold: bool = False, stacked: bool | None = None):
        if not members or any(m.nsrc != 1 for m in members):
            raise ValueError("PackedRayWave takes single-source RayWave members")
        for m in members:
            if not get(m.plan.method).packable:
                raise ValueError(f"PackedRayWave takes no method={m.plan.method!r} member (not packable, as pixel: "
                                 "no wave-plane field): run it on its own (RayWave.run)")
        m0 = members[0]
        for m in members:
            if (m.plan.method, m.rim, m.amplitude, m.use_reference, m.deterministic, m.device,
                    m.batch_plan.dtype, m.pixel_values) != (m0.plan.method, m0.rim, m0.amplitude, m0.use_reference,
                                                            m0.deterministic, m0.device, m0.batch_plan.dtype,
                                                            m0.pixel_values):
                raise ValueError("PackedRayWave members must share the method, rim weighting, amplitude, "
                                 "reference, determinism, device, precision and pixel values")
            if (m.src["shape"], m.src.get("object_distance"), m.plane, len(m.lens.surfaces)) != \
                    (m0.src["shape"], m0.src.get("object_distance"), m0.plane, len(m0.lens.surfaces)):
                raise ValueError("PackedRayWave members must be of one lens (pupil shape, object distance, wave "
                                 "plane and surfaces)")
        self.members = list(members)
        self.stacked = str(m0.device).startswith("cuda") if stacked is None else bool(stacked)
        lens = m0.lens
        wls = [m.wls[0] for m in members]
        uniq = sorted(set(wls))
        dtype = m0.batch_plan.dtype     # the members' tracers' (made, or made on use, in the plan's precision)
        tracer = Tracer(lens, uniq, device=m0.device, dtype=dtype, requires_grad=bool(requires_grad),
                        deterministic=m0.deterministic)
        self._start(packed_plan(members), tracer, m0.device, m0.deterministic)
        self._grids = np.array([m.plan.n_grid for m in members])
        self._ray_grids = np.array([m.plan.ray_grid for m in members])
        self._pitches = np.array([m.plan.pitch_mm for m in members])
        if hold:
            for m in [self] + self.members:
                m._memo = {}
            self.tracer.pool = {}   # its rays, splat sums and field: the same arrays every run

    def _layout(self) -> dict:
        return {"ray_grids": self._ray_grids, "slots": int(self._ray_grids.max()) ** 2, "grids": self._grids,
                "n_stride": int(self._grids.max()), "pitches": self._pitches}

    def _rim_args(self, rim: bool):
        tr = self.tracer
        if not rim:
            return tr.no_rim_cells(), 0
        return tr.packed_rim_cells(self._ray_grids, int(self._ray_grids.max()) ** 2), 1

    def plans(self) -> list:
        """Each member's plan (:class:`rwwarp.wave.plan.Plan`)."""
        return [m.plan for m in self.members]

    def run(self, focal_precision: str = "auto", keep_operators: bool = False) -> dict:
        """PSFs of every member as fractions of its entering power per pixel, each propagated by its own plan
        (``focal_precision`` as :meth:`RayWave.run`); ``plans``: the members' plans as dicts. ``keep_operators``:
        the members keep their focal operators for the next run (a kept batch), else they are dropped."""
        return self.result(self.device_psfs(focal_precision, keep_operators))

    def device_psfs(self, focal_precision: str = "auto", keep_operators: bool = False, to_host: bool = True,
                    u_all=None) -> list:
        """Each member's pixel powers (1, size, size), not yet normalised, in the order of :attr:`members`: trace,
        splat and every member's propagation queued. ``to_host=False``: left on the device (CuPy arrays on CUDA;
        nothing waits for the device, nothing is copied: what :mod:`rwwarp.wave.graph_replay` records).
        ``u_all``: the batch's field (:meth:`field_array`) when already formed (no trace, no splat)."""
        if focal_precision == "auto":
            focal_precision = "double" if self.tracer.device.startswith("cuda") else "single"
        if u_all is None:
            u_all = self.field_array()
        if self._runs_stacked():
            # every member's focal propagation as a few stacked operators (rwwarp.wave.focal_packed)
            from .focal_packed import run_focal_members
            keep = None
            if keep_operators:
                keep = self.__dict__.setdefault("_stacked_ops", {})
            else:
                self.__dict__.pop("_stacked_ops", None)
            data = run_focal_members(self.members, u_all, focal_precision, keep)
            if to_host and not isinstance(data[0], np.ndarray):
                import cupy
                host = cupy.asnumpy(cupy.concatenate(data))   # one copy for the batch
                data = [host[k:k + 1] for k in range(len(data))]
            return data
        data = []
        for k, m in enumerate(self.members):
            n = m.plan.n_grid
            u = u_all[k:k + 1, :n, :n]
            if not (isinstance(u, np.ndarray) and m.plan.method == "focal"):
                u = u.copy()   # (the CPU's focal step reads the view into its own single-precision copy)
            d = get(m.plan.method).pixels(m, u, focal_precision, to_host=to_host)
            if not keep_operators:
                m.release_operators()
            data.append(d)
        return data

    def _runs_stacked(self) -> bool:
        """The members propagate as stacked focal operators (:func:`rwwarp.wave.focal_packed.run_focal_members`):
        :attr:`stacked` (default: on CUDA, where a few batched launches replace each member's own; on the CPU the
        members' own FFTs do less arithmetic than the stacked matrix DFT and padding), two or more focal members,
        none with a wave step, their DOE (if any) a smooth profile."""
        ms = self.members
        if not self.stacked or len(ms) < 2 or ms[0].plan.method != "focal":
            return False
        if any(np.any(getattr(m, "wave_step", 0.0)) for m in ms):
            return False
        prof = ms[0].focal["profile"]
        return prof is None or (hasattr(prof, "kind") and hasattr(prof, "values"))

    def result(self, data) -> dict:
        """The result of :meth:`run` from the members' pixel powers (host arrays (1, size, size) each, or one
        (n_members, size, size) array): divided by each member's entering power (read now, from the last trace:
        on a GPU the host did not wait for the trace before it queued the propagations), checked finite."""
        entering = self.entering
        data = np.stack([np.asarray(d).reshape(self.size, self.size) / entering[k] for k, d in enumerate(data)])
        if not np.all(np.isfinite(data)):
            raise FloatingPointError("non-finite PSF values (please report this lens and field)")
        plans = [m.plan.to_dict() for m in self.members]
        return {"data": data, "centers": self.centers, "plan": plans[-1], "plans": plans,
                "valid_fraction": self.valid_fraction, "dropped_rays": self.dropped.numpy().copy()}
