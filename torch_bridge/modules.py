"""torch modules: a hybrid refractive-diffractive lens whose PSFs carry gradients.

:class:`HybridLens` wraps a :class:`rwwarp.lens.Lens`. Its optical quantities are tensors (float64):

============ ====================== =========================================================
name         shape                  meaning (units)
============ ====================== =========================================================
curvature    (n_surfaces,)          vertex curvature 1/R of ``standard`` surfaces (1/mm)
thickness    (n_surfaces,)          axial distance to the next surface; the last one is the
                                    distance to the sensor (mm). Vertex z = cumulative sum.
conic        (n_surfaces,)          conic constant of ``standard`` surfaces
aspheric     (n_surfaces, 9)        r^4 .. r^20 coefficients (mm^-3 .. mm^-19)
doe          (n_coefficients,)      DOE profile coefficients (rad): ``even_poly``/``poly``/
                                    ``zernike`` coefficients, ``cubic`` [alpha],
                                    ``fresnel`` [focal_length (mm)]
doe          (ny, nx)               ``pixel_map`` DOE: the phase map (rad)
focal_length (n_surfaces,)          focal length of ideal ``thin_lens`` surfaces (mm; 0 for
                                    other surfaces)
phase        (n_surfaces, 8)        A_1 .. A_8 (rad at the normalisation radius) of phase surfaces
                                    (:mod:`torch_bridge.phase_params`; 0 on other surfaces)
============ ====================== =========================================================

A thin lens enters the trace through its power ``1/f`` and its conjugates (object-side ``1/u``,
image distance ``v``, which make its path length that of a perfect lens); both conjugates are
recomputed in torch from a paraxial y-nu trace of the current values (curvatures, thicknesses,
focal lengths, phase surfaces' A_1; indices at the tracer's first wavelength, DOE powers fixed), as
:func:`rwwarp.paraxial.thin_lens_conjugates`, so their gradients reach every earlier surface too.

Which entries learn is chosen per quantity and per entry with ``learn``: a dict from a name above
to ``"all"`` or a list of entries (surface indices; ``(surface, k)`` pairs for ``aspheric`` (k = 0 is r^4) and
``phase`` (k = 0 is A_1); coefficient indices or ``(row, col)`` pairs of a pixel map for ``doe``). Each quantity
``q`` is stored as a buffer ``q_base`` (all entries), a buffer ``q_index`` (flat indices of the learning entries)
and an ``nn.Parameter`` ``q`` holding just those entries, so optimisers never touch frozen entries and
``state_dict`` round-trips exactly. ``.to(device)`` moves all of
them; the rwwarp device follows (``"cpu"`` or ``"cuda:N"``).

**Sampling plans are not differentiated.** Every forward call makes the discrete decisions of the
ray-wave model (plan: DOE-plane pitch, window, FFT size, ray count; sensor patch position; chief
ray carrier; reference sphere; entrance pupil; ray validity) from the current lens values, then
differentiates the smooth part for that plan. ``replan=False`` (or :meth:`frozen_plans`) keeps
the first plan of each (fields, wavelengths, size) request, which makes the loss an exactly
differentiable function of the parameters between calls (needed for finite-difference checks,
and cheaper per step); replanning now and then is advisable when parameters move a lot.
"""
from __future__ import annotations

import contextlib
import copy
import warnings

import numpy as np
import torch
from rwwarp.trace import COLUMNS as COL
from rwwarp.trace import field_pairs
from torch import nn

from rwwarp import doe
from rwwarp.lens import MAX_ASPHERIC, Lens
from rwwarp.phase_orders import ORDER_TOL, multi_order_surfaces
from rwwarp.wave.methods import check_method, get as get_method

from .wave_step import wave_step
from . import budget as _budget
from . import phase_params as _ph
from .budget import default_memory_budget_bytes  # noqa: F401  (its home: budget)
from .functions import backend_for, bridge_state, focal_doe_factor, focal_propagate, paper_amplitude, trace_splat
from .lens_tables import LensTables
from .operator_function import operator_propagate
from .tiles import run_tiles

__all__ = ["QUANTITIES", "HybridLens"]

QUANTITIES = ("curvature", "thickness", "conic", "aspheric", "doe", "focal_length", "phase")


class HybridLens(LensTables, nn.Module):
    """A rwwarp lens as an ``nn.Module`` whose PSFs and PSF maps carry gradients to its parameters.

    Parameters
    ----------
    lens : rwwarp.lens.Lens
        The lens (copied). The ray-wave model needs the DOE (if any) behind every refracting surface.
    learn : dict, optional
        ``{quantity: "all" | [entries]}`` (see the module docstring); everything else is a buffer.
    plan : "auto" | "paper" | rwwarp.wave.plan.Plan
        Sampling plan policy of each forward call.
    rays_per_sample, nyquist_safety, amplitude, gauss_nodes, use_reference :
        As :func:`rwwarp.psf` (``amplitude`` "energy" or "paper").
    replan : bool
        True (default): a new plan per forward call; False: plans cached per request (see the
        module docstring).
    method : "auto" | "focal" | "asm" | "two-step"
        Wave propagation, as :func:`rwwarp.psf`: ``"focal"`` handles the wave converging to the patch
        analytically (cost follows the patch: the Cooke triplet at F/4), ``"asm"`` is the band-limited
        angular spectrum (pixel-map DOEs), ``"auto"`` the ASM while its plan is small, else focal;
        ``"two-step"``: auto's choice with the wave step before the DOE (:mod:`rwwarp.wave.wave_step`, issue 27).
    focal_patch_tol : float
        Focal method: least share of a source's power a DOE order other than the main one must put on
        the patch to be computed (:class:`rwwarp.psf.RayWave`; default 1e-5).
    estimate_model_error : bool
        Each plan's model-error estimate (:class:`rwwarp.wave.raywave.RayWave` ``estimate_model_error``): False
        skips it where nothing decides by it (``method`` other than ``"two-step"``; the PSFs are the same). The
        design configs' ``optics.model_error_estimate`` (default false: most of a re-planning step's planning time).
    order_tol : float
        A lens whose phase surfaces keep several ``diffraction_orders`` (:mod:`rwwarp.phase_orders`): order
        combinations of lower efficiency are skipped (default 1e-4). Its :meth:`psf` and :meth:`psf_map` sum the
        kept orders coherently (:class:`torch_bridge.phase_orders.OrderSet`, one plan per order and source, as
        :func:`rwwarp.psf`); the design loop's ``LiveProvider`` sums them too, ``CachedProvider`` follows the design order only.
    pixel_values : "flux" | "intensity"
        What a sensor pixel records, as :func:`rwwarp.psf`: ``"flux"`` (default) the power through it (the
        z-component of the Poynting vector, obliquity included), ``"intensity"`` ``|U|^2`` over it. The design
        configs default to "intensity" for now: with "flux" the curvature gradients of the cooke_hybrid gpu
        preset's live step came out NaN (the splat's adjoint at zero-area ray tubes, since fixed on the CPU and
        not yet rerun on a GPU: docs/propagation.md "Pixel values").
    deterministic : bool
        The same values give the same PSFs and gradients bit for bit on every run, on a GPU too
        (:class:`rwwarp.psf.RayWave` ``deterministic``: fixed-point splat, a parameter-row copy per ray
        while recording: 2 x 8 x N_PARAMS = 640 bytes a ray and surface more, counted by :meth:`bytes_per_source`). On the
        CPU the results are deterministic either way. torch's own operations follow
        ``torch.use_deterministic_algorithms``.

    Methods return tensors: :meth:`psf` (size, size), :meth:`psf_map` (n_fields, n_wavelengths,
    size, size), fractions of the entering power per sensor pixel; :meth:`to_lens` exports the
    current values as a :class:`~rwwarp.lens.Lens`.
    """

    def __init__(self, lens: Lens, learn: dict | None = None, *, plan="auto", rays_per_sample: float = 1.0,
                 nyquist_safety: float = 2.0, amplitude: str = "energy", gauss_nodes: int | None = None,
                 use_reference: bool = True, replan: bool = True, method: str = "auto",
                 focal_patch_tol: float = 1e-5, deterministic: bool = False, pixel_values: str = "flux",
                 order_tol: float = ORDER_TOL, estimate_model_error: bool = True):
        super().__init__()
        self.deterministic = bool(deterministic)
        if pixel_values not in ("flux", "intensity"):
            raise ValueError(f"pixel_values must be 'flux' or 'intensity', got {pixel_values!r}")
        self.pixel_values = pixel_values
        check_method(method, "HybridLens", differentiable=True)   # auto, two-step or a method torch_bridge differentiates
        self.method = method
        if not (np.isfinite(focal_patch_tol) and 0 <= focal_patch_tol <= 1):
            raise ValueError(f"focal_patch_tol must be in [0, 1], got {focal_patch_tol!r}")
        self.focal_patch_tol = float(focal_patch_tol)
        self.lens_template = copy.deepcopy(lens)
        self.plan_policy = plan
        self.rays_per_sample = float(rays_per_sample)
        self.nyquist_safety = float(nyquist_safety)
        self.amplitude = amplitude
        self.gauss_nodes = None if gauss_nodes is None else int(gauss_nodes)  # None: per scene, as rw.psf
        self.use_reference = bool(use_reference)
        self.replan = bool(replan)
        self._plans: dict = {}
        self._same_values = None   # see same_values()
        surfs = lens.surfaces
        ns = len(surfs)
        std = [s.type == "standard" for s in surfs]
        thin = [s.type == "thin_lens" for s in surfs]
        self._thin_surfaces = thin  # host copy: no device sync per call
        self.register_buffer("standard_mask", torch.tensor(std, dtype=torch.bool), persistent=False)
        self.register_buffer("thin_mask", torch.tensor(thin, dtype=torch.bool), persistent=False)
        self._phase_surfaces = _ph.phase_mask(lens)   # host copy, as _thin_surfaces
        self._multi_order = bool(multi_order_surfaces(lens))   # phase surfaces with diffraction_orders
        if not (np.isfinite(order_tol) and 0 <= order_tol < 1):
            raise ValueError(f"order_tol must be in [0, 1), got {order_tol!r}")
        self.order_tol = float(order_tol)
        self.estimate_model_error = bool(estimate_model_error)
        self.register_buffer("phase_mask", torch.tensor(self._phase_surfaces, dtype=torch.bool), persistent=False)
        curv = [s.curvature if s.type == "standard" else 0.0 for s in surfs]
        asph = np.zeros((ns, MAX_ASPHERIC))
        for i, s in enumerate(surfs):
            if s.type == "standard" and s.aspheric:
                asph[i, :len(s.aspheric)] = s.aspheric
        base = {"curvature": np.array(curv, dtype=np.float64),
                "thickness": np.array([s.thickness for s in surfs], dtype=np.float64),
                "conic": np.array([s.conic if s.type == "standard" else 0.0 for s in surfs], dtype=np.float64),
                "aspheric": asph,
                "doe": self._doe_base(lens),
                "focal_length": np.array([s.focal_length if s.type == "thin_lens" else 0.0 for s in surfs],
                                         dtype=np.float64), "phase": _ph.phase_base(lens)}
        learn = dict(learn or {})
        unknown = set(learn) - set(QUANTITIES)
        if unknown:
            raise ValueError(f"unknown quantities in learn: {sorted(unknown)} (choose from {QUANTITIES})")
        for q in QUANTITIES:
            b = torch.from_numpy(np.ascontiguousarray(base[q], dtype=np.float64))
            idx = (_ph.phase_indices(learn.get(q), b.shape, self._phase_surfaces) if q == "phase" else
                   self._flat_indices(q, learn.get(q), b.shape, thin if q == "focal_length" else std))
            self.register_buffer(f"{q}_base", b)
            self.register_buffer(f"{q}_index", idx)
            setattr(self, q, nn.Parameter(b.reshape(-1)[idx].clone()))

    # ------------------------------------------------------------------ parameters
    def _doe_base(self, lens):
        d = lens.doe_index
        self.doe_kind = None
        if d is None:
            return np.zeros(0)
        s = lens.surfaces[d]
        prof = doe.profile_from_dict(s.profile, base=None if lens.source is None else
                                     __import__("pathlib").Path(lens.source).parent)
        self.doe_kind = prof.kind
        if prof.kind == "pixel_map":
            self._pixel_pitch = prof.pitch
        return np.array(prof.values, dtype=np.float64)          # the layout rwwarp.doe.profile_phase takes

    def _flat_indices(self, q, spec, shape, std):
        """Flat indices of the learning entries of ``q``; ``std`` marks the surfaces that may learn it
        (``standard`` surfaces for curvature / conic / aspheric, ``thin_lens`` ones for focal_length)."""
        numel = int(np.prod(shape))
        if spec is None:
            return torch.zeros(0, dtype=torch.long)
        if isinstance(spec, str):
            if spec != "all":
                raise ValueError(f"learn[{q!r}] must be 'all' or a list, got {spec!r}")
            if q in ("curvature", "conic", "focal_length"):
                flat = [i for i in range(numel) if std[i]]
            elif q == "aspheric":
                flat = [i for i in range(numel) if std[i // MAX_ASPHERIC]]
            else:
                flat = list(range(numel))
        else:
            flat = []
            for e in spec:
                if isinstance(e, (tuple, list)):
                    if len(shape) != 2:
                        raise ValueError(f"learn[{q!r}]: entry {e!r} is a pair but {q} is 1-D")
                    r, c = int(e[0]), int(e[1])
                    if not (0 <= r < shape[0] and 0 <= c < shape[1]):
                        raise ValueError(f"learn[{q!r}]: entry {e!r} outside {tuple(shape)}")
                    flat.append(r * shape[1] + c)
                else:
                    i = int(e)
                    if len(shape) == 2 and q == "aspheric":
                        raise ValueError("learn['aspheric'] entries are (surface, k) pairs, k = 0 for r^4")
                    if not 0 <= i < numel:
                        raise ValueError(f"learn[{q!r}]: index {i} outside 0..{numel - 1}")
                    flat.append(i)
            if q in ("curvature", "conic", "aspheric", "focal_length"):
                kind = "thin_lens" if q == "focal_length" else "standard"
                for i in flat:
                    s = i // MAX_ASPHERIC if q == "aspheric" else i
                    if not std[s]:
                        raise ValueError(f"learn[{q!r}]: surface {s} is not a '{kind}' surface")
        return torch.tensor(sorted(set(flat)), dtype=torch.long)

    def value(self, q: str) -> torch.Tensor:
        """Current full tensor of quantity ``q`` (the learning entries from the parameter, the rest
        from the buffer); differentiable with respect to the parameter."""
        base = getattr(self, f"{q}_base")
        idx = getattr(self, f"{q}_index")
        if idx.numel() == 0:
            return base
        flat = base.reshape(-1).index_put((idx,), getattr(self, q).to(base.dtype))
        return flat.reshape(base.shape)

    def values(self) -> dict:
        """All quantities, ``{name: tensor}``."""
        return {q: self.value(q) for q in QUANTITIES}

    def check_finite(self) -> None:
        """Raise ``ValueError`` naming the quantity and the entries when a lens value is NaN or inf (a
        diverged optimiser step), before any ray is traced: otherwise it surfaces only as "no rays reach
        the sensor" or as a NaN PSF."""
        vals = {q: self.value(q).detach() for q in QUANTITIES}
        # one read of the device for all quantities (each read waits for the device's queue)
        if bool(torch.stack([torch.isfinite(v).all() for v in vals.values()]).all()):
            return
        for q, v in vals.items():
            bad = ~torch.isfinite(v)
            if bool(bad.any()):
                where = torch.nonzero(bad.reshape(-1)).reshape(-1)[:8].tolist()
                raise ValueError(f"HybridLens: {q} has non-finite values (NaN or inf) at flat entries {where}: the "
                                 "lens parameters diverged (lower the learning rate or clip the gradients)")

    @property
    def rw_device(self) -> str:
        """rwwarp device string of the module's tensors ("cpu" or "cuda:N")."""
        d = self.thickness_base.device
        return "cpu" if d.type == "cpu" else f"cuda:{d.index or 0}"

    # ------------------------------------------------------------------ export
    def to_lens(self) -> Lens:
        """The current values as a new :class:`~rwwarp.lens.Lens` (validated). A pixel-map DOE is
        written inline (``profile.data``); :meth:`save_lens` can write it to a .npy file."""
        # one read of the device for every quantity (each read waits for the device's queue)
        ts = [self.value(q).detach() for q in QUANTITIES]
        flat = torch.cat([t.reshape(-1).to(torch.float64) for t in ts]).cpu().numpy()
        cuts = np.cumsum([t.numel() for t in ts])[:-1]
        v = {q: part.reshape(tuple(t.shape)) for q, t, part in zip(QUANTITIES, ts, np.split(flat, cuts))}
        lens = copy.deepcopy(self.lens_template)
        for i, s in enumerate(lens.surfaces):
            s.thickness = float(v["thickness"][i])
            if s.type == "thin_lens":
                s.focal_length = float(v["focal_length"][i])
            if s.type == "standard":
                c = float(v["curvature"][i])
                s.radius = None if c == 0.0 else 1.0 / c
                s.conic = float(v["conic"][i])
                a = v["aspheric"][i]
                nz = np.nonzero(a)[0]
                keep = max(len(s.aspheric), int(nz[-1]) + 1 if nz.size else 0)
                s.aspheric = [float(x) for x in a[:keep]]
                if s.phase is not None:
                    s.phase = _ph.exported_phase(s, v["phase"][i])
        d = lens.doe_index
        if d is not None:
            s = lens.surfaces[d]
            s.profile = doe.profile_with_values(s.profile, v["doe"])
        lens.validate()
        return lens

    def save_lens(self, path) -> None:
        """Write the current lens as a native ``rwwarp-lens/1`` JSON file; a pixel-map DOE goes to
        ``<path stem>_doe.npy`` next to it, referenced by ``profile.file``."""
        from pathlib import Path
        path = Path(path)
        lens = self.to_lens()
        d = lens.doe_index
        if d is not None and self.doe_kind == "pixel_map":
            npy = path.with_name(path.stem + "_doe.npy")
            np.save(npy, self.value("doe").detach().cpu().numpy())
            p = dict(lens.surfaces[d].profile)
            p.pop("data", None)
            p["file"] = npy.name
            lens.surfaces[d].profile = p
        lens.save(path)

    # ------------------------------------------------------------------ plans
    @contextlib.contextmanager
    def frozen_plans(self):
        """Within the block, plans (RayWave objects) are cached per request and reused."""
        keep = self.replan
        self.replan = False
        try:
            yield self
        finally:
            self.replan = keep

    @contextlib.contextmanager
    def same_values(self):
        """Within the block the caller promises the values do not change (one provider call, which plans
        many sources): the finiteness check and the :meth:`to_lens` export that every :meth:`raywave`
        plan starts from are done once, not once per source (each reads the values on the host, a read
        that waits for the device). Nested blocks share the outer one's snapshot."""
        keep = self._same_values
        if keep is None:
            self._same_values = {}
        try:
            yield self
        finally:
            self._same_values = keep

    def _once(self, name: str, make):
        """``make()``, once per :meth:`same_values` block (every time outside one)."""
        snap = self._same_values
        if snap is None:
            return make()
        if name not in snap:
            snap[name] = make()
        return snap[name]

    def clear_plans(self):
        """Forget cached plans."""
        self._plans.clear()

    def raywave(self, fields, wavelengths_um, size, *, object_distance_mm=None, pixel_mm=None, center_mm=None,
                plan=None, requires_grad: bool = True, method: str | None = None, memory_budget_bytes=None, pilot=None):
        """The :class:`rwwarp.psf.RayWave` (plan and discrete decisions) for sources ``fields`` x
        ``wavelengths_um`` (paired element-wise), built from the current values (or cached, see
        ``replan``). ``requires_grad=False``: the tracer keeps no gradient buffers and ping-pongs two
        ray-state buffers (a frozen refractive part, e.g. :class:`~torch_bridge.design.CachedProvider`).
        ``method``: override of the module's propagation method; ``memory_budget_bytes``: the planner's estimate
        is checked against it before anything is traced (:class:`rwwarp.wave.plan.MemoryBudgetError`); ``pilot``:
        the sources' :class:`rwwarp.wave.pilot.Pilot` of the current lens (None: traced here; not in the cache key)."""
        from rwwarp.psf import RayWave
        self._once("finite", self.check_finite)
        fields = field_pairs(fields)
        wls = [float(w) for w in wavelengths_um]
        plan = self.plan_policy if plan is None else plan
        key = (tuple(fields), tuple(wls), int(size),
               object_distance_mm, pixel_mm, None if center_mm is None else tuple(np.ravel(center_mm)),
               plan if isinstance(plan, str) else (plan.pitch_mm, plan.n_grid, plan.n_pad, plan.ray_grid),
               self.rw_device, bool(requires_grad), method or self.method, self.deterministic, self.pixel_values)
        if not self.replan and key in self._plans:
            return self._plans[key]
        lens = self._once("lens", self.to_lens)
        pixel = float(pixel_mm or lens.sensor.pixel_pitch)
        rw = RayWave(lens, fields, wls, int(size), pixel, plan=plan, center_mm=center_mm,
                     requires_grad=bool(requires_grad), method=method or self.method, pilot=pilot,
                     memory_budget_bytes=memory_budget_bytes, **self._raywave_options(object_distance_mm))
        bridge_state(rw)["base_table"] = rw.tracer.params_np.copy()
        if not self.replan:
            self._plans[key] = rw
        return rw

    def _raywave_options(self, object_distance_mm) -> dict:
        """The :class:`rwwarp.psf.RayWave` options every plan of this module shares (``object_distance_mm`` in mm,
        None: the lens's). The small-ASM rule on every device: cached and kept focal plans are not yet restored
        exactly on resume (the DOE orders a focal plan keeps follow the DOE)."""
        return dict(device=self.rw_device, dtype="float64", amplitude=self.amplitude,
                    object_distance_mm=object_distance_mm, rays_per_sample=self.rays_per_sample,
                    use_reference=self.use_reference, gauss_nodes=self.gauss_nodes,
                    nyquist_safety=self.nyquist_safety, focal_patch_tol=self.focal_patch_tol,
                    deterministic=self.deterministic, pixel_values=self.pixel_values, auto_rule="small-asm",
                    estimate_model_error=self.estimate_model_error)

    def raywaves_alone(self, fields, wavelengths_um, size, *, centers_mm, object_distance_mm=None, pixel_mm=None,
                       method: str | None = None, requires_grad: bool = True) -> list:
        """One :class:`rwwarp.psf.RayWave` per source (``fields`` x ``wavelengths_um`` paired element-wise; deg,
        um), each with the plan :meth:`raywave` gives that source alone (``centers_mm`` (S, 2): its patch
        centre, mm; None: each patch where its chief ray's main order lands, as :meth:`raywave` without
        ``center_mm`` places it), from one pilot trace of all of them (:func:`rwwarp.wave.pilot.trace_pilot`: a
        source's pilot rays, its pupil at its own wavelength, do not depend on the others): one set of trace
        launches, no plan of them all. Without ``replan`` (kept plans) each is :meth:`raywave` of that source."""
        fields = field_pairs(fields)
        wls = [float(w) for w in wavelengths_um]
        centers = None if centers_mm is None else np.asarray(centers_mm, dtype=np.float64).reshape(len(fields), 2)
        if len(fields) < 2 or not self.replan:
            return [self.raywave([f], [w], size, object_distance_mm=object_distance_mm, pixel_mm=pixel_mm,
                                 center_mm=None if centers is None else centers[k:k + 1], method=method,
                                 requires_grad=requires_grad)
                    for k, (f, w) in enumerate(zip(fields, wls))]
        from rwwarp.psf import RayWave
        self._once("finite", self.check_finite)
        lens = self._once("lens", self.to_lens)
        pixel = float(pixel_mm or lens.sensor.pixel_pitch)
        opts = self._raywave_options(object_distance_mm)
        from rwwarp.trace import Tracer
        from rwwarp.wave.plan_sources import plan_sources
        # every source planned on its own from one pilot trace of all of them (each entrance pupil at its own
        # wavelength), the per-source arrays computed together: each plan is what plan_batch gives it alone
        plans = plan_sources(lens, fields, wls, int(size), pixel, plan=self.plan_policy, center_mm=centers,
                             per_source_centers=centers is not None, method=method or self.method, **opts)
        # one tracer a wavelength for the parameter tables (as each RayWave's own); a RayWave's is made when it
        # traces alone
        layers, out = {}, []
        for bp, w in zip(plans, wls):
            if w not in layers:
                layers[w] = Tracer(lens, [w], device=opts["device"], dtype=opts["dtype"]).params_np
            rw = RayWave.from_plan(bp, requires_grad=bool(requires_grad), tracer_on_use=True)
            bridge_state(rw)["base_table"] = layers[w].copy()
            out.append(rw)
        return out

    # ------------------------------------------------------------------ differentiable pieces
    # (param_table, host_table, doe_phase: torch_bridge.lens_tables.LensTables)
    def limit_doe_feature(self, min_feature_mm: float) -> float:
        """Project the DOE onto the fabrication limit: when its smallest feature over the aperture
        (:func:`rwwarp.doe.surface_feature_size_mm`: the narrowest 2 pi zone, divided by the number of
        levels for a quantised relief; mm) is below ``min_feature_mm``, scale the whole phase profile
        (buffer and learning entries) by ``feature / min_feature_mm`` so the smallest feature equals
        the limit (the phase gradient is linear in the coefficients of every supported kind).
        Returns the scale applied (1.0 when the DOE already complies or is flat).

        Supported kinds: ``even_poly``, ``poly``, ``zernike``, ``cubic``; others raise ValueError."""
        from rwwarp.doe import surface_feature_size_mm
        if not min_feature_mm > 0:
            raise ValueError(f"min_feature_mm must be > 0, got {min_feature_mm!r}")
        if self.doe_kind not in ("even_poly", "poly", "zernike", "cubic"):
            raise ValueError(f"limit_doe_feature: wave-plane DOE kind {self.doe_kind!r} is not linear in its values "
                             "(supported: even_poly, poly, zernike, cubic; phase surfaces are not limited)")
        lens = self.to_lens()
        feat = surface_feature_size_mm(lens.surfaces[lens.doe_index])
        if feat >= min_feature_mm:
            return 1.0
        c = feat / float(min_feature_mm) * (1.0 - 1e-9)
        with torch.no_grad():
            self.doe_base.mul_(c)
            if self.doe_index.numel():
                self.doe.mul_(c)
        return c

    def _psf_rw(self, rw, values, record: bool = True, spatial_tile=None, tables: dict | None = None):
        """PSFs (S, size, size) of one RayWave batch from the given values. ``record=False``: plain
        forward, no tape, no graph (used by the tiled checkpointing); also when no gradient is wanted.
        ``spatial_tile``: sensor pixels per side of the propagation's spatial tiles (None: untiled).
        ``tables``: the caller's cache of host tables for these values (:meth:`host_table`)."""
        from .functions import power_sums
        ctx = contextlib.nullcontext() if record else torch.no_grad()
        with ctx:
            table = self.param_table(rw, values)
            host = self.host_table(rw, table, tables)
            method = get_method(rw.plan.method)
            phi0 = self.doe_phase(rw, values) if method.torch_path == "operator" else None
            dist = (table[-1, COL.z] - table[rw.plane, COL.z]).expand(rw.nsrc)
            u = trace_splat(table, rw, host)
            if rw.amplitude != "energy":
                u = paper_amplitude(u, rw)
            u = wave_step(u, rw)   # the rim's diffraction before the DOE, where the plan has it (issue 27)
            d_host = float(host[-1, COL.z] - host[rw.plane, COL.z])
            if method.torch_path == "focal":
                fac = focal_doe_factor(rw, self.doe_phase(rw, values, wrap=False))
                if fac is not None:
                    u = u * fac
                power = focal_propagate(u, dist, rw, d_host)
            else:   # any method's operator, the ASM's included (torch_bridge.operator_function)
                power = operator_propagate(u, dist, rw, d_host, phi0=phi0,
                                           tile_px=spatial_tile if method.spatial_tiles else None)
            return power / power_sums(rw, power.device)[0][:, None, None]

    def _psf_packed(self, tile, values, record: bool = True, tables: dict | None = None):
        """PSFs (S, size, size) of a :class:`torch_bridge.packed.PackedTile` of focal sources from the given
        values, computed together (one trace + splat, batched DOE and propagation); per source the same as
        :meth:`_psf_rw` of it alone (:func:`torch_bridge.packed.packed_psfs`)."""
        from .packed import packed_psfs
        return packed_psfs(self, tile, values, record=record, tables=tables)

    def memory_budget(self, memory_budget_bytes=None) -> int:
        """``memory_budget_bytes``, or the device default: half the available memory
        (:func:`rwwarp.wave.plan.default_memory_budget_bytes`), bytes."""
        if memory_budget_bytes is not None:
            if not memory_budget_bytes > 0:
                raise ValueError(f"memory_budget_bytes must be > 0, got {memory_budget_bytes!r}")
            return int(memory_budget_bytes)
        from rwwarp.wave.plan import default_memory_budget_bytes as rw_default
        return int(rw_default(self.rw_device))

    def check_budget(self, rw, budget_bytes: int, spatial_tile=None, sources: int = 1) -> int:
        """Estimated peak bytes of ``sources`` recorded sources of ``rw`` (forward + backward: the trace with
        gradients, :meth:`bytes_per_source`, plus the output side of the propagation at ``spatial_tile``);
        raises :class:`rwwarp.wave.plan.MemoryBudgetError` naming the estimate and the knobs when it exceeds
        ``budget_bytes``, before anything is traced. Returns the estimate."""
        from rwwarp.wave.plan import check_budget
        est = self.recorded_bytes(rw, spatial_tile, sources)
        check_budget({"memory_bytes": est}, int(budget_bytes),
                     f"a differentiable ray-wave PSF ({sources} source(s), {rw.plan.method}: {rw.plan.ray_grid}^2 rays "
                     f"with gradients, wave-plane grid {rw.plan.n_grid}^2)",
                     "size (patch pixels), the field angle and aperture (beam footprint), rays_per_sample, "
                     "nyquist_safety; psf_map tiles sources (tile=) and checkpoints them")
        return est

    def recorded_bytes(self, rw, spatial_tile=None, sources: int = 1) -> int:
        """Estimated peak bytes of ``sources`` recorded sources of ``rw`` (forward + backward): the trace with
        gradients (:meth:`bytes_per_source`) plus the propagation's output side at ``spatial_tile``
        (:meth:`output_bytes_per_source`). The figure :meth:`check_budget` checks."""
        return sources * (self.bytes_per_source(rw) + self.output_bytes_per_source(rw, spatial_tile))

    def output_bytes_per_source(self, rw, tile_px=None) -> int:
        """:func:`torch_bridge.budget.output_bytes_per_source` (bytes)."""
        return _budget.output_bytes_per_source(rw, tile_px)

    def spatial_tile_for(self, rw, budget_bytes, sources: int = 1):
        """Pixels per side of the propagation's spatial tiles so that ``sources`` sources' output
        side (:meth:`output_bytes_per_source`) fits in an eighth of ``budget_bytes``; None when the
        whole patch fits (no tiling). At least 8 pixels."""
        share = int(budget_bytes) // 8
        if self.output_bytes_per_source(rw) * sources <= share:
            return None
        t = rw.size
        while t > 8 and self.output_bytes_per_source(rw, t) * sources > share:
            t = max(8, t // 2)
        return t

    # ------------------------------------------------------------------ public
    def psf(self, field_deg=0.0, wavelength_um: float = 0.55, size: int = 64, *, object_distance_mm=None,
            pixel_mm=None, center_mm=None, return_centers: bool = False, spatial_tile: int | None = None,
            memory_budget_bytes: int | None = None):
        """Differentiable PSF (size, size), float64: fraction of the entering power per sensor pixel
        (rows along +y, columns along +x, as :func:`rwwarp.psf`). ``field_deg`` (deg, y or (x, y)),
        ``wavelength_um`` (um), ``object_distance_mm`` (mm, default the lens's), ``pixel_mm`` (mm,
        default the sensor's). ``return_centers``: also the sensor (x, y) of the centre pixel (mm).
        ``spatial_tile``: propagate in tiles of that many sensor pixels a side (each recomputed in
        backward; same result), or chosen from ``memory_budget_bytes`` (:meth:`spatial_tile_for`). The source's
        estimated peak (:meth:`check_budget`) is checked against ``memory_budget_bytes`` (default: half the
        available memory of the device, :func:`rwwarp.wave.plan.default_memory_budget_bytes`) before tracing."""
        if self._multi_order:
            return self._psf_orders(field_deg, wavelength_um, size, object_distance_mm, pixel_mm, center_mm,
                                    return_centers, spatial_tile, memory_budget_bytes)
        rw = self.raywave([field_deg], [wavelength_um], size, object_distance_mm=object_distance_mm,
                          pixel_mm=pixel_mm, center_mm=center_mm)
        budget = self.memory_budget(memory_budget_bytes)
        if spatial_tile is None:
            spatial_tile = self.spatial_tile_for(rw, budget)
        self.check_budget(rw, budget, spatial_tile)
        out = self._psf_rw(rw, self.values(), spatial_tile=spatial_tile, tables={})[0]
        return (out, rw.centers[0].copy()) if return_centers else out

    def order_set(self, field_deg, wavelength_um: float, size: int, *, object_distance_mm=None, pixel_mm=None,
                  center_mm=None):
        """The :class:`~torch_bridge.phase_orders.OrderSet` of one source (deg, um, px; mm) of a lens with
        multi-order phase surfaces: one plan per kept order combination from the current values (cached per
        request without ``replan``, as :meth:`raywave`)."""
        from .phase_orders import OrderSet
        if not self._multi_order:
            raise ValueError("HybridLens.order_set: the lens has no phase surface with diffraction_orders")
        self._once("finite", self.check_finite)
        key = ("orders", tuple(field_pairs([field_deg])[0]), float(wavelength_um), int(size), object_distance_mm,
               pixel_mm, None if center_mm is None else tuple(np.ravel(center_mm)), self.rw_device, self.method,
               self.deterministic, self.pixel_values, self.order_tol)
        if not self.replan and key in self._plans:
            return self._plans[key]
        lens = self._once("lens", self.to_lens)
        opts = self._raywave_options(object_distance_mm)
        opts.update(method=self.method, center_mm=center_mm)
        if not isinstance(self.plan_policy, str):
            raise ValueError("HybridLens: a lens with multi-order phase surfaces plans each order itself (plan='auto' "
                             "or 'paper', not an explicit Plan)")
        opts["plan"] = self.plan_policy
        orders = OrderSet(lens, field_deg, float(wavelength_um), int(size), pixel_mm, order_tol=self.order_tol, **opts)
        bridge_state(orders.rws[0])["base_table"] = orders.table.copy()
        if not self.replan:
            self._plans[key] = orders
        return orders

    def _psf_orders(self, field_deg, wavelength_um, size, object_distance_mm, pixel_mm, center_mm, return_centers,
                    spatial_tile, memory_budget_bytes):
        """:meth:`psf` of a lens with multi-order phase surfaces: the kept orders summed coherently at the pixels'
        nodes (:meth:`order_set`); each order's plan is checked against the memory budget before it is traced."""
        if spatial_tile is not None:
            raise ValueError("HybridLens.psf: spatial_tile is not available for multi-order phase surfaces")
        orders = self.order_set(field_deg, wavelength_um, size, object_distance_mm=object_distance_mm,
                                pixel_mm=pixel_mm, center_mm=center_mm)
        out = self.order_psfs([orders], 1, memory_budget_bytes)[0]
        return (out, orders.rws[0].centers[0].copy()) if return_centers else out

    def order_psfs(self, sets, tile: int, memory_budget_bytes=None, checkpoint=None, progress=None) -> torch.Tensor:
        """PSFs (S, size, size) of the :meth:`order_set` s ``sets`` (one a source) from the current values, ``tile``
        sources a chunk (each a checkpoint when there are several, :func:`torch_bridge.tiles.run_tiles`:
        ``checkpoint``, ``progress``); every order's plan is checked against ``memory_budget_bytes`` (bytes; None:
        :meth:`memory_budget`'s default) before anything is traced."""
        budget = self.memory_budget(memory_budget_bytes)
        for o in sets:
            for rw in o.rws:
                self.check_budget(rw, budget)
        values = self.values()
        names = list(values)

        def run(ch, *ts, record=True):
            vals = dict(zip(names, ts))
            with contextlib.nullcontext() if record else torch.no_grad():
                return torch.cat([sets[k].psf(self.param_table(sets[k].rws[0], vals)) for k in ch], 0)
        n = len(sets)
        chunks = [list(range(k, min(k + int(tile), n))) for k in range(0, n, int(tile))]
        return run_tiles(chunks, run, [values[q] for q in names], checkpoint=checkpoint, progress=progress)

    def _psf_map_orders(self, fields, wls, size, object_distance_mm, pixel_mm, tile, memory_budget_bytes,
                        checkpoint, progress, return_centers, spatial_tile):
        """:meth:`psf_map` of a lens with multi-order phase surfaces: each source's orders on their own plans
        (:meth:`order_set`), one source a tile (each a checkpoint when there are several: peak memory one
        source's), every order's plan checked against the budget before anything is traced."""
        if spatial_tile is not None or (tile is not None and int(tile) != 1):
            raise ValueError("HybridLens.psf_map: multi-order phase surfaces run one source a tile (tile=1), without "
                             "spatial_tile")
        sets = [self.order_set(f, w, size, object_distance_mm=object_distance_mm, pixel_mm=pixel_mm)
                for f in fields for w in wls]
        out = self.order_psfs(sets, 1, memory_budget_bytes, checkpoint, "PSF sources" if progress else None)
        out = out.reshape(len(fields), len(wls), size, size)
        if return_centers:
            return out, np.stack([o.rws[0].centers[0] for o in sets]).reshape(len(fields), len(wls), 2)
        return out

    def psf_map(self, fields, wavelengths_um, size: int = 64, *, object_distance_mm=None, pixel_mm=None,
                tile: int | None = None, memory_budget_bytes: int | None = None, checkpoint: bool | None = None,
                progress: bool = False, return_centers: bool = False, spatial_tile: int | None = None,
                slot_waste: float | None = 1.5):
        """Differentiable PSF map (n_fields, n_wavelengths, size, size), float64.

        Every (field, wavelength) source is computed on its own plan, as :func:`rwwarp.psf` plans it alone
        (so a PSF does not depend on the map it is in, nor on the tiling); all the plans are made from one pilot
        trace of all the sources (:meth:`raywaves_alone`, each patch where its chief ray's main order lands).
        Sources are computed in tiles of ``tile`` (field, wavelength) pairs; in a tile the single-source focal
        plans are computed together in packed tiles (:class:`torch_bridge.packed.PackedTile`: one trace + splat
        launch set, the focal propagations as batched matrix products; per source the PSF and gradients of the
        source alone up to the order of floating-point sums), cut by :func:`torch_bridge.packed.pack_units` (as
        :class:`torch_bridge.live.LiveProvider`'s) so that each packed tile's recorded peak fits the budget
        below and that the padding of its members to the slots of its largest (ray grid, window) costs at most
        ``slot_waste`` times their own work (:func:`torch_bridge.packed.slot_sets`; None: no bound, one packed tile
        for all that fit the budget: fewest launches); the other sources (a band-limited method, a wave step) run
        one at a time. ``memory_budget_bytes``
        (bytes) caps the transfer-function cache at a quarter of the budget and chooses the tile from what
        is left after the map's fixed needs (:meth:`bytes_fixed`) and an estimate of the bytes one
        source needs (:meth:`bytes_per_source`: rays and their gradients for every traced surface,
        the DOE-plane grid, the padded FFT work space); what is left also bounds a packed tile's estimate
        (:func:`torch_bridge.packed.packed_recorded_bytes`; without a budget the device default,
        :meth:`memory_budget`). With ``checkpoint`` (default: on when the map has more than one tile) each tile runs
        without a tape on the way forward and is recomputed under a fresh tape in the backward pass,
        so peak memory is one tile's, independent of the map size.
        ``return_centers``: also the centre-pixel sensor positions (n_fields, n_wavelengths, 2), mm.
        ``spatial_tile``: the propagation of each tile evaluates the sensor patches in spatial tiles of
        that many pixels a side (:func:`torch_bridge.operator_function.operator_propagate`; same result, each recomputed
        in backward; the focal propagation has no spatial tiles); with a budget and no ``spatial_tile``, chosen by
        :meth:`spatial_tile_for` when a large patch's output side would not fit.
        """
        fields = field_pairs(fields)
        wls = [float(w) for w in wavelengths_um]
        if slot_waste is not None and not (np.isfinite(slot_waste) and slot_waste >= 1):
            raise ValueError(f"HybridLens.psf_map: slot_waste must be >= 1 or None, got {slot_waste!r}")
        if self._multi_order:
            return self._psf_map_orders(fields, wls, size, object_distance_mm, pixel_mm, tile, memory_budget_bytes,
                                        checkpoint, progress, return_centers, spatial_tile)
        pairs = [(i, j) for i in range(len(fields)) for j in range(len(wls))]
        # each source planned alone (its own pilot rows, window, pitch, rays and method), all from one pilot trace
        rws = self.raywaves_alone([fields[i] for i, _ in pairs], [wls[j] for _, j in pairs], size, centers_mm=None,
                                  object_distance_mm=object_distance_mm, pixel_mm=pixel_mm)
        full = max(rws, key=self.bytes_per_source)    # the largest source sizes the tiles and the budget check
        budget = self.memory_budget(memory_budget_bytes)
        pack_budget = budget   # bytes a packed tile's recorded peak may take
        if memory_budget_bytes is not None:
            # the budget holds the tiles, the transfer-function cache (capped at a quarter of it) and
            # what does not depend on the tile (the map's pilot trace, the output)
            need = self.bytes_per_source(full)
            avail = memory_budget_bytes - memory_budget_bytes // 4 - self.bytes_fixed(full)
            pack_budget = max(avail, 0)
            if tile is None:
                tile = max(1, int(avail // max(need, 1)))
                if need > avail:
                    warnings.warn(f"memory_budget_bytes = {memory_budget_bytes / 2**20:.0f} MiB leaves "
                                  f"{max(avail, 0) / 2**20:.0f} MiB for tiles (a quarter goes to the transfer-function "
                                  f"cache, {self.bytes_fixed(full) / 2**20:.0f} MiB to the map's pilot trace and "
                                  f"output), below the estimated need of one source ({need / 2**20:.0f} MiB): running "
                                  "one source per tile (fewer rays_per_sample or a smaller plan would fit)",
                                  RuntimeWarning, stacklevel=2)
        tile = len(pairs) if tile is None else max(1, min(int(tile), len(pairs)))
        if spatial_tile is None and memory_budget_bytes is not None:
            spatial_tile = self.spatial_tile_for(full, memory_budget_bytes, tile)
        # one source of the map's plan must fit the budget (checkpointed tiles keep one tile's graph at a time)
        self.check_budget(full, budget, spatial_tile)
        chunks = [list(range(k, min(k + tile, len(pairs)))) for k in range(0, len(pairs), tile)]
        values = self.values()
        names = list(values)
        centers = np.concatenate([rw.centers for rw in rws], 0)
        tables = {}   # host copies of the parameter table for these values (HybridLens.host_table)

        def work(ch):
            # a chunk's work, cut when the tile loop reaches it: its packed tiles and its sources alone, and the
            # order of their rows back to the sources' (None: in order)
            units = self._map_units(ch, rws, pack_budget, spatial_tile, slot_waste)
            flat = [j for _, _, row in units for j in row]
            return units, None if flat == ch else torch.as_tensor(np.argsort(flat))

        def run(chunk, *ts, record=True):
            units, perm = chunk
            vals = dict(zip(names, ts))
            out = torch.cat([self._psf_packed(u, vals, record=record, tables=tables) if kind == "packed" else
                             self._psf_rw(u, vals, record=record, spatial_tile=spatial_tile, tables=tables)
                             for kind, u, _ in units], 0)
            return out if perm is None else out[perm.to(out.device, non_blocking=True)]
        with self._cache_limit(memory_budget_bytes):   # the tiles, each a checkpoint (torch_bridge.tiles)
            out = run_tiles((work(ch) for ch in chunks), run, [values[q] for q in names], checkpoint=checkpoint,
                            progress="PSF tiles" if progress else None, total=len(chunks))
        out = out.reshape(len(fields), len(wls), size, size)
        if return_centers:
            return out, centers.reshape(len(fields), len(wls), 2)
        return out

    def _map_units(self, chunk, rws, budget_bytes, spatial_tile=None, slot_waste=None) -> list:
        """:meth:`psf_map`'s work for the sources ``chunk`` (indices into ``rws``, in order): ``[(kind, object,
        rows)]``, the sources that cannot be packed (:func:`torch_bridge.packed.packable`) alone (``"rw"``), then the
        others cut into packed tiles whose recorded peak fits ``budget_bytes`` (bytes) by
        :func:`torch_bridge.packed.pack_units` (``slot_waste``: its bound on the slots' padding). Without ``replan``
        (kept plans) a tile is kept with its members
        (in the plan cache, :meth:`clear_plans`) and built again only when one of them changes."""
        from .packed import PackedTile, pack_units, packable

        def tile_for(members):
            if self.replan:
                return PackedTile(members)
            key = ("packed", tuple(id(r) for r in members))
            hit = self._plans.get(key)
            if hit is None or any(a is not b for a, b in zip(hit[0], members)):
                hit = self._plans[key] = (list(members), PackedTile(members))
            return hit[1]
        alone = [("rw", rws[j], [j]) for j in chunk if not packable(rws[j])]
        return alone + pack_units(self, [j for j in chunk if packable(rws[j])], rws, budget_bytes,
                                  spatial_tile=spatial_tile, tile_for=tile_for, slot_waste=slot_waste)

    def bytes_per_source(self, rw, record: bool = True) -> int:
        """:func:`torch_bridge.budget.bytes_per_source` (bytes)."""
        return _budget.bytes_per_source(rw, record)

    def bytes_fixed(self, rw) -> int:
        """:func:`torch_bridge.budget.bytes_fixed` (bytes)."""
        return _budget.bytes_fixed(rw)

    @contextlib.contextmanager
    def _cache_limit(self, budget):
        if budget is None:
            yield
            return
        be = backend_for(self.rw_device)
        keep = be.cache.max_bytes
        be.cache.max_bytes = min(keep, int(budget) // 4)
        be.cache.clear()
        try:
            yield
        finally:
            be.cache.max_bytes = keep

    def _load_from_state_dict(self, state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys,
                              error_msgs):
        # state dicts written before focal_length / phase existed: keep the lens's own values, frozen
        for q in ("focal_length", "phase"):
            if f"{prefix}{q}_base" not in state_dict:
                for k in (f"{q}_base", f"{q}_index", q):
                    state_dict[prefix + k] = getattr(self, k).detach().clone()
        super()._load_from_state_dict(state_dict, prefix, local_metadata, strict, missing_keys, unexpected_keys,
                                      error_msgs)

    def forward(self, fields, wavelengths_um, size: int = 64, **kw):
        """Same as :meth:`psf_map`."""
        return self.psf_map(fields, wavelengths_um, size, **kw)
