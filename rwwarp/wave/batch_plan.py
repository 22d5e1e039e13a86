"""The plan of one batch of point sources (:class:`BatchPlan`), made once from a pilot trace (:func:`plan_batch`)
and read, never changed, by the :class:`rwwarp.wave.raywave.RayWave` s that run it.

:func:`plan_batch` makes every discrete decision of the ray-wave model: the chief rays, the carrier and the beam's
footprint, each registered propagation method's plan (:mod:`rwwarp.wave.methods`; "auto" compares the band-limited
ASM's and the focal method's), the wave-plane windows (aligned to a pixel-map DOE's pixels), the reference-sphere
centres, the rim weighting, the pixel method planned beside (:mod:`rwwarp.wave.pixel_scale`), the model error and
the wave step (:mod:`rwwarp.wave.wave_step`). A :class:`BatchPlan` holds these decisions and their host arrays
(read-only); what changes them makes a new plan (:meth:`BatchPlan.recentred`, :meth:`BatchPlan.with_plane_z`,
:func:`rwwarp.wave.wave_step.plan_wave_step`, ``dataclasses.replace``). Lengths in mm, wavelengths in um.
"""
from __future__ import annotations

from dataclasses import dataclass, fields as _dc_fields, replace
from typing import Any

import numpy as np

from ..errors import LensError
from ..lens import snap_to_pixel as _snap_center
from ..trace import Tracer
from ..trace import field_label as _fmt_field
from .doe_sampling import doe_max_frequency, doe_pixel_origin
from .methods import PlanContext, check_method, names
from .methods import get as get_method
from .pilot import Pilot, batch_sources, pilot_or_trace
from .plan import Plan
from .sensor_grid import auto_gauss_nodes as _auto_gauss_nodes, n_img_all
from .sensor_grid import snap_centers as _snap_centers

#: the registered methods "auto" plans side by side and chooses between (the order they are planned in)
AUTO_PAIR = ("focal", "asm")


class FrozenDict(dict):
    """A dict that refuses changes (a :class:`BatchPlan`'s sources and method state); copy it
    (``dict(d, key=value)``) to change one. Pickles and copies as itself."""

    def _refuse(self, *args, **kwargs):
        raise TypeError("a BatchPlan's mappings are read-only: make a new plan (dataclasses.replace, "
                        "BatchPlan.recentred) with a changed copy (dict(d, key=value))")

    __setitem__ = __delitem__ = __ior__ = clear = pop = popitem = setdefault = update = _refuse

    def __reduce__(self):
        return (FrozenDict, (dict(self),))


def _read_only(value):
    """``value`` as a plan holds it: a writeable array copied and set read-only (an array already read-only is
    kept), a dict frozen with its arrays (and tuples of arrays) read-only, a list as a tuple; anything else as it
    is (lists inside a dict stay lists)."""
    if isinstance(value, np.ndarray):
        if value.flags.writeable:
            value = value.copy()
            value.flags.writeable = False
        return value
    if isinstance(value, dict) and not isinstance(value, FrozenDict):
        def member(v):   # an array, or a tuple of arrays (a focal plan's fitted transfer), made read-only
            if isinstance(v, tuple):
                return tuple(_read_only(a) if isinstance(a, np.ndarray) else a for a in v)
            return _read_only(v) if isinstance(v, np.ndarray) else v
        return FrozenDict({k: member(v) for k, v in value.items()})
    if isinstance(value, list):
        return tuple(value)
    return value


@dataclass(frozen=True, eq=False)
class BatchPlan:
    """Every decision of a batch of ``nsrc`` point sources and the host arrays it made them from (read-only):
    what :class:`rwwarp.wave.raywave.RayWave` runs. Made by :func:`plan_batch`; change one by a new plan
    (:meth:`recentred`, :meth:`with_plane_z`, ``dataclasses.replace``), never in place (a frozen dataclass;
    its arrays are read-only, its dicts :class:`FrozenDict`). ``lens`` is the lens planned on (held, not
    copied: a RayWave of this plan traces and samples it). Per source S: ``n_after`` index behind the wave plane,
    ``lam_mm`` vacuum wavelength (mm), ``chief_plane`` / ``chief_sensor`` (S, 3) mm, ``carrier`` (S, 2)
    cycles/mm, ``centers`` (S, 2) mm patch centres, ``lo`` / ``hi`` (S, 2) mm footprint corners, ``origin``
    (S, 2) mm window origins, ``opl_chief`` (S,) mm, ``chief_ok`` (S,), ``target`` (S, 3) mm reference-sphere
    centres, ``wave_step`` (S,) mm: the distances the wave step propagates over, the reduced distances stretched for the
    rim's obliquity (:func:`rwwarp.wave.wave_step.rim_obliquity`; zeros: none), ``wave_step_rim`` (S, RIM_COLS): their
    variation around the rim (:func:`rwwarp.wave.wave_step.rim_profile`; None: the isotropic step)."""

    lens: Any
    fields: tuple
    wls: tuple
    size: int
    pixel: float
    device: str                 # the device planned for ("auto"'s rule); a RayWave may run it on another
    dtype: str
    amplitude: str
    use_reference: bool
    gauss_nodes: int
    pixel_values: str
    deterministic: bool
    own_pupils: bool
    pilot: Pilot | None
    src: dict
    plane: int
    curved_plane: bool
    square_pupil: bool
    nsrc: int
    n_after: np.ndarray
    lam_mm: np.ndarray
    z_plane: float
    z_sensor: float
    plan: Plan
    method: str
    focal: dict | None
    chief_plane: np.ndarray
    chief_sensor: np.ndarray
    carrier: np.ndarray
    centers: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    origin: np.ndarray
    opl_chief: np.ndarray
    chief_ok: np.ndarray
    target: np.ndarray
    pupil: tuple
    rim: bool
    model_errors: tuple = ()
    wave_step: Any = None
    wave_step_pad: int | None = None
    wave_step_rim: Any = None
    pixel_alternative: str = ""

    def __post_init__(self):
        for name in PLAN_FIELDS:
            v = getattr(self, name)
            t = type(v)
            # what _read_only keeps as it is, skipped without a call (a new plan of a plan: most of its values)
            if v is None or t in _KEPT_TYPES or t is FrozenDict or (t is np.ndarray and not v.flags.writeable):
                continue
            ro = _read_only(v)
            if ro is not v:
                object.__setattr__(self, name, ro)

    def evolved(self, **changes) -> "BatchPlan":
        """``dataclasses.replace(self, **changes)`` without re-running every field through ``__init__`` and
        ``__post_init__``: the same plan (the changed values made read-only as ``__post_init__`` makes them; the
        others are already), made with one dict copy (the planners make several a source)."""
        bad = set(changes).difference(self.__dataclass_fields__)
        if bad:
            raise TypeError(f"BatchPlan.evolved: no field(s) {', '.join(sorted(bad))}")
        new = object.__new__(BatchPlan)
        d = new.__dict__
        d.update(self.__dict__)
        for name, v in changes.items():
            t = type(v)
            d[name] = v if (v is None or t in _KEPT_TYPES or t is FrozenDict
                            or (t is np.ndarray and not v.flags.writeable)) else _read_only(v)
        return new

    def snapped_centres(self, center_mm) -> np.ndarray:
        """The patch centres ((nsrc, 2) mm) of ``center_mm`` ((x, y) mm, one pair or one per source) snapped to
        the sensor's pixel centres as :func:`plan_batch` snaps them."""
        return _snap_centers(center_mm, self.pixel, self.lens.sensor.resolution, self.nsrc)

    def recentred(self, center_mm) -> "BatchPlan":
        """This plan with its sensor patches moved to ``center_mm`` ((x, y) mm, one pair or one per source;
        snapped to the pixel centres). Only the output positions change: the DOE-plane windows and the field do
        not depend on them. A focal plan's sensor-side grid moves with its patch by the same whole number of
        pixels."""
        new = self.snapped_centres(center_mm)
        focal = self.focal
        if focal is not None:
            d = new - self.centers
            focal = dict(focal, sensor_origin=np.asarray(focal["sensor_origin"]) + d,
                         sensor_center=np.asarray(focal["sensor_center"]) + d)
        return replace(self, centers=new, focal=focal)

    def with_plane_z(self, z_mm: float) -> "BatchPlan":
        """This plan with the z of its chief rays' points on the wave plane (the windows' reference point) at
        ``z_mm`` (mm: the plane's vertex in a new parameter table, :meth:`RayWave.load_params`)."""
        cp = np.array(self.chief_plane, dtype=np.float64)
        cp[:, 2] = z_mm
        return replace(self, chief_plane=cp)


#: the names a :class:`~rwwarp.wave.raywave.RayWave` reads through from its plan
PLAN_FIELDS = tuple(f.name for f in _dc_fields(BatchPlan))
#: value types :func:`_read_only` returns unchanged (immutable; a tuple's members are not looked into)
_KEPT_TYPES = (str, int, float, bool, tuple, Plan, Pilot)


def _is_curved(surface) -> bool:
    """True for a refracting surface with sag (curvature or aspheric terms): not a plane."""
    if surface.type != "standard":
        return False
    return bool(surface.curvature) or bool(getattr(surface, "a2", 0.0)) or any(float(a) for a in (surface.aspheric or []))


def planned_method(method: str, plan, lens, plane: int) -> str:
    """What the planners plan for ``method``: "auto" becomes "compare" (both plans from the same pilot; the
    cheaper one, by planned work, runs), "asm" under ``plan="paper"`` or for a pixel-map DOE on the wave plane
    (discontinuous: no smooth diffraction orders to factor), an explicit :class:`Plan`'s own method; any other
    method is kept."""
    if method != "auto":
        return method
    if isinstance(plan, Plan):
        return plan.method
    s_pl = lens.surfaces[plane]
    if (isinstance(plan, str) and plan == "paper") or (s_pl.type == "doe" and s_pl.profile.get("kind") == "pixel_map"):
        return "asm"
    return "compare"


def plan_batch(lens, fields, wls, size, pixel, device="cpu", plan="auto", dtype="float64", amplitude="energy",
               object_distance_mm=None, rays_per_sample=1.0, center_mm=None, use_reference=True, gauss_nodes=None,
               nyquist_safety=2.0, method="asm", memory_budget_bytes=None, focal_patch_tol=1e-5,
               deterministic: bool = False, own_pupils: bool = False, pilot: Pilot | None = None,
               pixel_values: str = "flux", model_tolerance: float | None = None, auto_rule: str = "device",
               allow_pixel: bool = False, tracer: Tracer | None = None, estimate_model_error: bool = True) -> BatchPlan:
    """The :class:`BatchPlan` of the sources ``fields`` (deg) x ``wls`` (um, one per field) with patches of
    ``size`` pixels of ``pixel`` mm: the arguments as :class:`rwwarp.wave.raywave.RayWave` takes them (which calls
    this). ``pilot`` (:func:`rwwarp.wave.pilot.trace_pilot` of these sources, or a subset): planned from it, else
    traced here. ``tracer``: a :class:`rwwarp.trace.Tracer` of ``lens`` at ``sorted(set(wls))`` to lay the
    sources with (and trace the pilot with when none is given); None: one is made here (without gradients).
    ``estimate_model_error=False``: the model-error estimate is skipped where no decision reads it
    (:func:`rwwarp.wave.wave_step.model_error_needed`; the plan then records none)."""
    if any(getattr(s, "diffraction_orders", None) is not None for s in lens.surfaces):
        import warnings
        warnings.warn("a RayWave traces each phase surface in its diffraction_order only: Surface.diffraction_orders "
                      "is summed by rwwarp.psf / rwwarp.psf_map (rwwarp.phase_orders)", UserWarning, stacklevel=3)
    requested, method, pixel_values, deterministic = check_plan_args(method, auto_rule, pixel_values, deterministic)

    plane = lens.wave_plane_index()
    uniq = sorted(set(wls))
    tr = tracer if tracer is not None else Tracer(lens, uniq, device=device, dtype=dtype)
    nsrc = len(fields)
    src, pupil_wls = batch_sources(tr, fields, wls, object_distance_mm, own_pupils)
    src["relative_opl"] = bool(use_reference)  # OPL from the chief ray's source sphere (float32-safe)
    n_after = np.array([lens.indices(w)[plane] for w in wls])
    z_plane = lens.vertex_z[plane]
    z_sensor = lens.sensor_z
    check_sensor_behind_plane(lens, plane)
    lam_mm = np.array(wls) * 1e-3

    # ---- pilot trace: chief ray + coarse grid, to the plane and on to the sensor (rwwarp.wave.pilot)
    pilot = pilot_or_trace(pilot, tr, src, plane, fields, wls, pupil_wls, use_reference, dtype, "RayWave")
    pa = pilot_arrays(lens, plane, pilot, fields, wls, n_after, lam_mm, z_plane)
    pos_p, pos_s, dir_s, opl_p, ok = pa["pos_p"], pa["pos_s"], pa["dir_s"], pa["opl_p"], pa["ok"]
    curved_plane, chief_plane, chief_sensor, chief_dir = pa["curved"], pa["chief_plane"], pa["chief_sensor"], pa["chief_dir"]
    carrier, fmax, lo, hi, f_doe, feature = pa["carrier"], pa["fmax"], pa["lo"], pa["hi"], pa["f_doe"], pa["feature"]
    width = float(np.max(hi - lo))
    pilot_cell = width / 31.0
    if center_mm is None:
        centers = np.stack([_snap_center(chief_sensor[:, 0], pixel, lens.sensor.resolution[0]),
                            _snap_center(chief_sensor[:, 1], pixel, lens.sensor.resolution[1])], axis=1)
    else:
        centers = _snap_centers(center_mm, pixel, lens.sensor.resolution, nsrc)
    out_width = size * pixel
    chief_carrier, chief_centers = carrier.copy(), centers.copy()
    method = planned_method(method, plan, lens, plane)
    # a square pupil (stop) bounds the beam with straight edges: their 1 / r diffraction tails alias more
    square_pupil = src["shape"] != "circle"
    # ---- plan: each registered method plans its part (rwwarp.wave.methods); "compare" plans both of auto's
    ctx = PlanContext(lens=lens, plane=plane, plan=plan, pos_p=pos_p, dir_s=dir_s, ok=ok, chief_plane=chief_plane,
                      chief_dir=chief_dir, n_after=n_after, lam_mm=lam_mm, wls=wls, distance_mm=z_sensor - z_plane,
                      center_mm=center_mm, size=size, pixel=pixel, width=width, pilot_cell=pilot_cell, lo=lo, hi=hi,
                      fmax=fmax, f_doe=f_doe, feature=feature, out_width=out_width, carrier=carrier, centers=centers,
                      rays_per_sample=rays_per_sample, nyquist_safety=nyquist_safety, patch_tol=focal_patch_tol,
                      straight_edges=square_pupil, sampling_tol=model_tolerance)
    planned = {m: get_method(m).plan(ctx) for m in (AUTO_PAIR if method == "compare" else (method,))}
    main = planned["asm" if method == "compare" else method]
    pl, carrier, centers, lo, hi, focal = main.plan, main.carrier, main.centers, main.lo, main.hi, main.geo

    if gauss_nodes is None:
        from .plan import gauss_tol
        gauss_nodes = _auto_gauss_nodes(dir_s, ok, n_img_all(lens, wls), lam_mm, pixel, tol=gauss_tol(model_tolerance))
        pl = pl.with_reasons(f"pixel integration: {gauss_nodes} x {gauss_nodes} Gauss-Legendre nodes per pixel "
                             f"(intensity band of the beam's NA across a {pixel * 1e3:.4g} um pixel)")
    from .plan import estimate_cost, check_budget
    pl = replace(pl, estimate=estimate_cost(pl, nsrc, size, gauss_nodes))
    if method == "compare":
        pl, chosen_focal = _choose_auto(pl, planned["focal"], nsrc, size, gauss_nodes, auto_rule, device,
                                        memory_budget_bytes)
        if chosen_focal:
            f = planned["focal"]
            focal, carrier, centers = f.geo, f.carrier, f.centers
    # methods planned beside the window plan at the end (pixel): the one asked for, or those "auto" may choose
    late = [get_method(requested)] if requested in names() and get_method(requested).planned_beside else \
        [get_method(m) for m in names() if get_method(m).planned_beside] if requested == "auto" and allow_pixel else []
    if late and requested != "auto" and not (isinstance(plan, str) and plan == "auto"):
        raise ValueError(f"method={requested!r} plans its own sampling: use plan='auto'")
    may_beside = bool(late) and isinstance(plan, str) and plan == "auto"
    budget_check = lambda pl, alt="": check_budget(pl.estimate, int(memory_budget_bytes), f"a ray-wave batch of {nsrc} source(s) "
                     f"({pl.method}: {pl.ray_grid}^2 rays, wave-plane grid {pl.n_grid}^2)",
                     "size (patch pixels), the field angle and aperture (beam footprint), rays_per_sample, "
                     "nyquist_safety" + (", the padded FFT n_pad" if get_method(pl.method).fft_padded else "") + alt)
    if memory_budget_bytes is not None and not may_beside:
        budget_check(pl)
    n = pl.n_grid
    mid = 0.5 * (lo + hi)
    origin = lo.copy() if pl.kind == "paper" else mid - 0.5 * (n - 1) * pl.pitch_mm
    origin = doe_pixel_origin(lens, plane, origin, pl.pitch_mm)
    # chief ray OPL on the plane (a per-source constant phase: not differentiated); the pilot's pupil
    # sample 0 is the chief ray (u = v = 0), traced alone before as the same independent ray
    opl_chief = opl_p[:, 0].copy()
    chief_ok = pilot.valid_plane[:, 0].copy()
    chief_plane = np.where(chief_ok[:, None], pos_p[:, 0], chief_plane)
    target = _ray_focus(pos_p, dir_s, ok, chief_plane)
    # rim weighting (focal plans, energy convention, circular pupil): every pupil cell the disc touches
    # is traced from the centroid of its part inside the disc, weighted by that part (the splat gives it
    # that part of the tube; tube areas from the actual pupil steps), so the aperture edge is not a
    # staircase of cells: the focal method's error followed that staircase (docs/accuracy.md). The
    # ASM keeps whole cells: its converged Airy reference moved from 2.0e-5 to 5.8e-5 with it
    rim = amplitude == "energy" and src["shape"] == "circle" and get_method(pl.method).rim_weighted
    bp = BatchPlan(lens=lens, fields=list(fields), wls=list(wls), size=size, pixel=pixel, device=device, dtype=dtype,
                   amplitude=amplitude, use_reference=use_reference, gauss_nodes=gauss_nodes,
                   pixel_values=pixel_values, deterministic=deterministic, own_pupils=bool(own_pupils), pilot=pilot,
                   src=src, plane=plane, curved_plane=curved_plane, square_pupil=square_pupil, nsrc=nsrc,
                   n_after=n_after, lam_mm=lam_mm, z_plane=z_plane, z_sensor=z_sensor, plan=pl, method=pl.method,
                   focal=focal, chief_plane=chief_plane, chief_sensor=chief_sensor, carrier=carrier, centers=centers,
                   lo=lo, hi=hi, origin=origin, opl_chief=opl_chief, chief_ok=chief_ok, target=target,
                   # full ray_grid x ray_grid cell-centre pupil grid, generated on the device (see Tracer._run)
                   pupil=(None, None, (2.0 / pl.ray_grid) ** 2), rim=rim)
    if may_beside:
        # e.g. pixels many Airy radii wide: rwwarp.wave.pixel_scale (the pixel box applied analytically)
        pilot_s = {"pos_s": pos_s, "dir_s": dir_s, "ok": ok, "carrier": chief_carrier, "centers": chief_centers,
                   "beam_width_mm": float(np.min(hi - lo)), "rays_per_sample": rays_per_sample}
        chosen = None
        for m in late:
            bp, switched = m.consider(bp, requested == m.name, pilot_s, model_tolerance, memory_budget_bytes)
            if switched:
                chosen = m.name
                break
        if chosen is not None:
            requested = chosen      # no wave step: requested is neither "auto" nor "two-step"
        elif memory_budget_bytes is not None:
            budget_check(bp.plan, bp.pixel_alternative)
    from . import wave_step as _ws
    skip = not estimate_model_error and not _ws.model_error_needed(requested, model_tolerance)
    return _ws.plan_wave_step(bp, model_tolerance, requested, memory_budget_bytes,   # model error; wave step
                              estimate=[] if skip else None)


def _choose_auto(pl, f, nsrc, size, gauss_nodes, auto_rule, device, memory_budget_bytes):
    """``method="auto"``: the ASM plan ``pl`` or the focal one (``f``, a :class:`Planned`), by ``auto_rule``
    and the memory budget; returns (the chosen plan with the reason, True when focal)."""
    from .plan import estimate_cost
    fpl = f.plan
    fpl = fpl.evolved(estimate=estimate_cost(fpl, nsrc, size, gauss_nodes), reasons=fpl.reasons + pl.reasons[-1:])
    small_first = auto_rule == "small-asm"
    rule = ("asm while its plan is under 1 GiB and 20 GFLOP" if small_first else
            "the plan of fewer flops")
    why = (f"method auto ({rule}): focal {fpl.estimate['flops'] / 1e9:.3g} GFLOP / {fpl.estimate['memory_bytes'] / 2 ** 30:.3g} "
           f"GiB against asm {pl.estimate['flops'] / 1e9:.3g} GFLOP / {pl.estimate['memory_bytes'] / 2 ** 30:.3g} GiB")
    # The plan of fewer flops runs on every device ("device", "flops"). On the CPU the arithmetic is the cost
    # (A489 map at 32 px: focal 0.4-1.3 GFLOP and 255-401^2 rays against asm 3.2-7.8 GFLOP and 533-790^2 rays a
    # source; at 64 px, 5 x 5 fields x 3 wavelengths: all focal, 2.0 GFLOP a source on average against 7.7 with
    # "small-asm"). On a GPU the ASM used to be kept while small, because launches bound both paths; since then
    # an uncached focal PSF is as fast (H100, c3f59eb, A489 at 0 / 10 deg, 64 px: focal 13.5 / 14.6 ms median
    # against the ASM's 15.7 / 15.7), a replayed one faster (2.2 / 1.9 against 3.9 / 4.0 ms), and a map's focal
    # members propagate as stacked operators (rwwarp.wave.focal_packed.run_focal_members). "small-asm" keeps the
    # old rule by name. Both meet the refractive truths alike (docs/accuracy.md).
    small_asm = small_first and pl.estimate["memory_bytes"] <= 2 ** 30 and pl.estimate["flops"] <= 2e10
    # a plan over the memory budget cannot run: the one that fits wins whatever its work
    fits = [memory_budget_bytes is None or e["memory_bytes"] <= memory_budget_bytes
            for e in (pl.estimate, fpl.estimate)]
    # an aberrated spot wider than the focal box's taper guard (the patch inside a geometric spot many Airy
    # radii wide): the ASM's plan (padding for the patch, whole rim cells) is not sized for it (a BK7 singlet
    # at 35 / 40 deg, 16 px: 1.5e-2 / 9.6e-2 off rs_lens_psf, still 1.5e-3 with 2 x the grid, rays and padding;
    # the focal path 1.1e-4 / 5.4e-5 of the peak), so the focal path runs wherever it fits
    aberrated = bool(np.any(f.geo.get("lit_taper", False)))
    if aberrated:
        why += "; the geometric spot outgrows the patch (rays land in the focal taper): focal"
    if fits == [False, True] or (fits != [True, False] and (aberrated or (not small_asm
                                 and fpl.estimate["flops"] <= pl.estimate["flops"]))):
        return fpl.with_reasons(why + " -> focal"), True
    return pl.with_reasons(why + " -> asm"), False


def check_sensor_behind_plane(lens, plane: int) -> None:
    """``LensError`` (naming the lens file and surface) unless the sensor lies behind the wave plane ``plane``: the
    wave models propagate forward from it (a mirror or a negative last thickness puts it before)."""
    z_sensor = lens.sensor_z
    if not z_sensor > lens.vertex_z[plane]:
        raise LensError(f"the wave models need the sensor behind the wave plane (surface {plane}); here it is "
                        f"{lens.vertex_z[plane] - z_sensor:.6g} mm before it (a mirror or a negative last "
                        "thickness): use model='ray' or the ray trace", file=lens.source, surface=plane)


def check_plan_args(method: str, auto_rule: str, pixel_values: str, deterministic) -> tuple:
    """The planners' argument checks (:func:`plan_batch`, :func:`rwwarp.wave.plan_sources.plan_sources`): ``auto_rule``
    and ``method`` known (``ValueError`` naming them), ``pixel_values`` resolved. Returns ``(requested, method,
    pixel_values, deterministic)``: the method asked for and the one planned ("two-step" plans as "auto",
    :mod:`rwwarp.wave.wave_step`)."""
    if auto_rule not in ("device", "small-asm", "flops"):
        raise ValueError(f"auto_rule must be 'device', 'small-asm' or 'flops', got {auto_rule!r}")
    check_method(method, "RayWave")
    from .propagate_setup import check_pixel_values
    return method, ("auto" if method == "two-step" else method), check_pixel_values(pixel_values, "RayWave"), \
        bool(deterministic)


def pilot_arrays(lens, plane, pilot, fields, wls, n_after, lam_mm, z_plane) -> dict:
    """What the planning reads from a pilot trace, for every source at once (row k: source k; lengths mm): the rays
    on the wave plane (``pos_p``, a curved last surface's carried straight on to its vertex plane, OPL included, so
    the field is formed on a true plane; ``curved``), at the sensor (``pos_s``, ``dir_s``), their paths ``opl_p``
    and validity ``ok``; the chief rays (``chief_plane``, ``chief_sensor``, ``chief_dir``: :func:`_chief_rays`), the
    carrier ``n d_xy / lambda`` of the chief ray (cycles/mm), the footprint (``fmax`` cycles/mm after the carrier,
    ``lo`` / ``hi`` mm: :func:`_footprints`) and the DOE's largest frequency and feature (``f_doe``, ``feature``:
    :func:`rwwarp.wave.doe_sampling.doe_max_frequency`). ``LensError`` naming the field where fewer than 3 rays reach
    the sensor. The one home of these steps for :func:`plan_batch` and :func:`rwwarp.wave.plan_sources.plan_sources`."""
    pos_p, pos_s, dir_s = pilot.pos_p, pilot.pos_s, pilot.dir_s
    opl_p = pilot.opl_p
    curved_plane = _is_curved(lens.surfaces[plane])
    if curved_plane:
        t = (z_plane - pos_p[..., 2]) / dir_s[..., 2]
        pos_p = pos_p + t[..., None] * dir_s
        opl_p = opl_p + n_after[:, None] * t
    ok = pilot.ok
    counts = ok.sum(1)
    for k in np.flatnonzero(counts < 3):
        raise LensError("no rays reach the sensor (the field is fully vignetted or misses a surface)",
                        file=lens.source, field=_fmt_field(fields[k]))
    chief_plane, chief_sensor, chief_dir = _chief_rays(pos_p, pos_s, dir_s, ok)
    carrier = n_after[:, None] * chief_dir[:, :2] / lam_mm[:, None]  # cycles/mm
    # local frequencies of the field relative to the carrier, and the footprint
    fmax, lo, hi = _footprints(pos_p, dir_s, ok, n_after, lam_mm, carrier)
    f_doe, feature = doe_max_frequency(lens, plane, _ValidRows(pos_p, ok), wls)
    return {"pos_p": pos_p, "pos_s": pos_s, "dir_s": dir_s, "opl_p": opl_p, "ok": ok, "curved": curved_plane,
            "chief_plane": chief_plane, "chief_sensor": chief_sensor, "chief_dir": chief_dir, "carrier": carrier,
            "fmax": fmax, "lo": lo, "hi": hi, "f_doe": f_doe, "feature": feature}


class _ValidRows:
    """``rows[k]``: source ``k``'s valid points on the plane, ``pos_p[k, ok[k], :2]`` (mm), made when read (a DOE
    without a phase reads none)."""
    __slots__ = ("pos_p", "ok")

    def __init__(self, pos_p, ok):
        self.pos_p, self.ok = pos_p, ok

    def __len__(self):
        return len(self.ok)

    def __getitem__(self, k):
        return self.pos_p[k, self.ok[k], :2]


def _chief_rays(pos_p, pos_s, dir_s, ok):
    """Chief rays ((S, 3) each: on the plane, at the sensor, direction): the pupil centre's ray (sample 0)
    where it is valid, else the centroid of the valid rays (the direction normalised)."""
    good = ok[:, 0]
    chief_plane = np.where(good[:, None], pos_p[:, 0], 0.0)
    chief_sensor = np.where(good[:, None], pos_s[:, 0], 0.0)
    chief_dir = np.where(good[:, None], dir_s[:, 0], 0.0)
    for k in np.flatnonzero(~good):   # a vignetted chief ray (rare): a subset's mean, as it always was
        chief_plane[k] = pos_p[k, ok[k]].mean(0)
        chief_sensor[k] = pos_s[k, ok[k]].mean(0)
        d = dir_s[k, ok[k]].mean(0)
        chief_dir[k] = d / np.linalg.norm(d)
    return chief_plane, chief_sensor, chief_dir


def _footprints(pos_p, dir_s, ok, n_after, lam_mm, carrier):
    """Per source: the largest local frequency of the field after the carrier (cycles/mm, (S,)) and the
    footprint's corners on the plane (``lo``, ``hi`` (S, 2) mm), over the valid pilot rays. Max / min only:
    the masked forms give the same values as the valid subsets."""
    f = (n_after[:, None, None] * dir_s[..., :2]) / lam_mm[:, None, None] - carrier[:, None, :]
    okm = ok[..., None]
    fmax = np.max(np.where(okm, np.abs(f), -np.inf), axis=(1, 2))
    xy = pos_p[..., :2]
    lo = np.min(np.where(okm, xy, np.inf), axis=1)
    hi = np.max(np.where(okm, xy, -np.inf), axis=1)
    return fmax, lo, hi


def _ray_focus(pos_p, dir_s, ok, chief_plane):
    """Reference-sphere centres ((S, 3) mm): where each source's rays converge (least-squares focus along z).

    Rays are straight behind the wave plane, x_i(t) = p_i + t m_i with slopes m_i = d_xy / d_z; the
    transverse variance is smallest at ``t* = -cov(p, m) / var(m)``. The centre is the chief ray's point
    at that depth (``chief_plane``: on the plane, the pupil centre's ray where it reaches the plane), so the residual
    phase splatted is only the aberration (not defocus). Collimated beams (var(m) ~ 0) get a centre 1 m along
    the chief ray (a nearly plane reference).
    """
    nsrc = ok.shape[0]
    out = np.zeros((nsrc, 3))
    for k in range(nsrc):
        p = pos_p[k, ok[k], :2]
        m = dir_s[k, ok[k], :2] / dir_s[k, ok[k], 2:3]
        pc, mc = p - p.mean(0), m - m.mean(0)
        var = float(np.sum(mc * mc))
        t = -float(np.sum(pc * mc)) / var if var > 1e-18 else np.inf
        if not np.isfinite(t) or abs(t) > 1e6:
            t = 1e6  # collimated: a nearly plane reference (residual curvature < 1e-2 rad over 1 mm)
        c0 = chief_plane[k]
        dc = dir_s[k, 0] if ok[k, 0] else dir_s[k, ok[k]].mean(0)
        out[k] = [c0[0] + t * dc[0] / dc[2], c0[1] + t * dc[1] / dc[2], c0[2] + t]
    return out
