"""Many point sources, each planned on its own, in one call (:func:`plan_sources`): the plans
:func:`rwwarp.wave.batch_plan.plan_batch` gives each source alone (its entrance pupil at its own wavelength,
``own_pupils``), made from one pilot trace of all of them with every per-call, per-lens and per-wavelength
quantity computed once and the pilot-derived per-source arrays (chief rays, footprints, carriers, patch
centres, reference-sphere centres, DOE frequencies, ...) computed for all sources at once.

Every plan is the one ``plan_batch`` makes for that source alone, field by field and bit for bit (the same
arithmetic on the same values, row by row: tests/rwwarp/test_plan_sources.py); ``plan_batch`` stays the
independent reference and what a single :class:`~rwwarp.wave.raywave.RayWave` plans with. Used by
:func:`rwwarp.wave.packed.source_plans` (:func:`rwwarp.psf_map`) and the design loop's per-source plans
(:meth:`torch_bridge.HybridLens.raywaves_alone`). Lengths in mm, wavelengths in um.
"""
from __future__ import annotations

import numpy as np

from ..lens import snap_to_pixel as _snap_center
from ..trace import Tracer, as_field_list
from .batch_plan import (AUTO_PAIR, BatchPlan, _choose_auto, _ray_focus, check_plan_args, planned_method,
                         check_sensor_behind_plane, pilot_arrays)
from .doe_sampling import doe_pixel_origin
from .methods import PlanContext, names
from .methods import get as get_method
from .pilot import Pilot, PILOT_GRID, own_pupil_sources, pilot_or_trace
from .sensor_grid import snap_centers as _snap_centers

__all__ = ["plan_sources"]


def _pilot_row(pilot: Pilot, k: int) -> Pilot:
    """Source ``k`` of ``pilot`` as :meth:`Pilot.subset` ``([k])`` gives it (the same values), its arrays read-only
    views of the batch's (no copy, no re-validation: the batch's were checked)."""
    p = object.__new__(Pilot)
    set_ = object.__setattr__
    for name in ("pos_p", "pos_s", "dir_s", "opl_p", "ok", "valid_plane"):
        set_(p, name, getattr(pilot, name)[k:k + 1])
    for name in ("fields", "wls", "pupil_wls"):
        set_(p, name, (getattr(pilot, name)[k],))
    for name in ("object_distance_mm", "relative_opl", "dtype", "plane"):
        set_(p, name, getattr(pilot, name))
    return p


def _frozen(a: np.ndarray) -> np.ndarray:
    """``a`` set read-only (in place; an array made here) and returned."""
    a.flags.writeable = False
    return a


def _gauss_nodes_one(d, n_img: float, lam_mm: float, pixel: float, tol: float = 1e-7) -> int:
    """:func:`rwwarp.wave.sensor_grid.auto_gauss_nodes` of one source (``d``: its valid pilot rays' direction
    cosines (N, 2)): the same arithmetic."""
    from ..analytic import gauss_legendre_exp_error
    worst = 0.0
    if len(d):
        na = float(np.max(np.abs(d - d.mean(0))))
        worst = max(worst, 2.0 * np.pi * pixel * 2.0 * n_img * na / lam_mm)
    for g in range(3, 17):
        if gauss_legendre_exp_error(g, worst / 2.0) < tol:
            return g
    return 16


def plan_sources(lens, fields, wls, size, pixel, device="cpu", plan="auto", dtype="float64", amplitude="energy",
                 object_distance_mm=None, rays_per_sample=1.0, center_mm=None, use_reference=True, gauss_nodes=None,
                 nyquist_safety=2.0, method="asm", memory_budget_bytes=None, focal_patch_tol=1e-5,
                 deterministic: bool = False, pixel_values: str = "flux", model_tolerance: float | None = None,
                 auto_rule: str = "device", allow_pixel: bool = False, pilot: Pilot | None = None,
                 per_source_centers: bool = False, estimate_model_error: bool = True) -> list:
    """One :class:`~rwwarp.wave.batch_plan.BatchPlan` per source ``(fields[k], wls[k])`` (deg, um), each the plan
    :func:`~rwwarp.wave.batch_plan.plan_batch` gives that source alone with ``own_pupils=True`` (and the pilot
    rows of that source): ``size`` px of ``pixel`` mm; the other arguments as ``plan_batch`` takes them, the
    same for every source. ``center_mm``: None (each patch where its chief ray's main order lands), one ``(x,
    y)`` pair (mm) for every source, or, with ``per_source_centers``, one pair per source ((S, 2) mm). ``pilot``:
    the sources' pilot (:func:`rwwarp.wave.pilot.trace_pilot` with ``own_pupils=True``, checked), else traced
    here in one set of launches. ``estimate_model_error``: as ``plan_batch`` (False: skipped where no decision reads
    it). Returns the plans in source order.

    Where a source cannot be planned (vignetted, over the memory budget, ...) the error is the one
    ``plan_batch`` raises for it; with several such sources, the pilot's checks (vignetting) of every source come
    before the other checks of the first."""
    requested, method0, pixel_values, deterministic = check_plan_args(method, auto_rule, pixel_values, deterministic)
    fields = as_field_list(fields)
    wls = [float(w) for w in wls]
    nsrc = len(fields)
    if nsrc != len(wls) or nsrc == 0:
        raise ValueError(f"plan_sources: {nsrc} fields and {len(wls)} wavelengths; give one wavelength per field "
                         "(at least one source)")
    if per_source_centers:
        cen_in = np.asarray(center_mm, dtype=np.float64).reshape(nsrc, 2)
        centers_req = [cen_in[k:k + 1] for k in range(nsrc)]
    else:
        centers_req = [center_mm] * nsrc

    plane = lens.wave_plane_index()
    uniq = sorted(set(wls))
    # ---- the sources, each entrance pupil at its own wavelength (one paraxial pupil a wavelength), and the
    # pilot of all of them in one trace: the bits of trace_pilot(own_pupils=True)
    tr = Tracer(lens, uniq, device=device, dtype=dtype)
    src_all = own_pupil_sources(tr, fields, wls, uniq, object_distance_mm)
    src_all["relative_opl"] = bool(use_reference)
    pilot = pilot_or_trace(pilot, tr, src_all, plane, fields, wls, wls, use_reference, dtype, "plan_sources")
    # per wavelength: the index behind the plane and the image space's (lens.indices once a wavelength)
    idx = {w: lens.indices(w) for w in uniq}
    n_after = np.array([idx[w][plane] for w in wls])
    n_img = np.array([idx[w][-1] for w in wls])
    z_plane = lens.vertex_z[plane]
    z_sensor = lens.sensor_z
    check_sensor_behind_plane(lens, plane)
    lam_mm = np.array(wls) * 1e-3

    # ---- every source's pilot-derived arrays at once (row k: what plan_batch computes for source k alone)
    pa = pilot_arrays(lens, plane, pilot, fields, wls, n_after, lam_mm, z_plane)
    pos_p, pos_s, dir_s, opl_p, ok = pa["pos_p"], pa["pos_s"], pa["dir_s"], pa["opl_p"], pa["ok"]
    curved_plane, chief_plane0, chief_sensor, chief_dir = pa["curved"], pa["chief_plane"], pa["chief_sensor"], pa["chief_dir"]
    carrier0, fmax, lo0, hi0, f_doe, feature = pa["carrier"], pa["fmax"], pa["lo"], pa["hi"], pa["f_doe"], pa["feature"]
    widths = np.max(hi0 - lo0, axis=1)
    res = lens.sensor.resolution
    if center_mm is None:
        centers0 = np.stack([_snap_center(chief_sensor[:, 0], pixel, res[0]),
                             _snap_center(chief_sensor[:, 1], pixel, res[1])], axis=1)
    else:
        centers0 = np.concatenate([_snap_centers(c, pixel, res, 1) for c in centers_req])
    out_width = size * pixel
    opl_chief = opl_p[:, 0].copy()
    chief_ok = pilot.valid_plane[:, 0].copy()
    chief_plane1 = np.where(chief_ok[:, None], pos_p[:, 0], chief_plane0)
    target = _ray_focus(pos_p, dir_s, ok, chief_plane1)

    # ---- per call: the method choice, the pupil's shape, the methods planned beside
    method0 = planned_method(method0, plan, lens, plane)
    square_pupil = src_all["shape"] != "circle"
    late = [get_method(requested)] if requested in names() and get_method(requested).planned_beside else \
        [get_method(m) for m in names() if get_method(m).planned_beside] if requested == "auto" and allow_pixel else []
    if late and requested != "auto" and not (isinstance(plan, str) and plan == "auto"):
        raise ValueError(f"method={requested!r} plans its own sampling: use plan='auto'")
    may_beside = bool(late) and isinstance(plan, str) and plan == "auto"
    from .plan import estimate_cost, check_budget

    def budget_check(pl, alt=""):
        check_budget(pl.estimate, int(memory_budget_bytes), f"a ray-wave batch of 1 source(s) "
                     f"({pl.method}: {pl.ray_grid}^2 rays, wave-plane grid {pl.n_grid}^2)",
                     "size (patch pixels), the field angle and aperture (beam footprint), rays_per_sample, "
                     "nyquist_safety" + (", the padded FFT n_pad" if get_method(pl.method).fft_padded else "") + alt)

    shared = {}   # the methods' per-call constants (the DOE profile, its scale per wavelength), PlanContext.shared
    # the focal plans, every source's at once where its rays allow: a wave plane without a DOE (one order) or
    # with one (its diffraction orders)
    focal_fast = {}
    if method0 in ("focal", "compare") and isinstance(plan, str):
        from ..doe import is_flat_profile
        s_pl = lens.surfaces[plane]
        if not (s_pl.type == "doe" and not is_flat_profile(s_pl.profile)):
            from .focal_sources import focal_plans_one_order
            focal_fast = focal_plans_one_order(
                pos_p, dir_s, ok, chief_plane0, chief_dir, n_after, lam_mm, z_sensor - z_plane,
                None if center_mm is None else centers0, widths, size, pixel, res, lo0, hi0, rays_per_sample,
                nyquist_safety, square_pupil, sampling_tol=model_tolerance)
        else:
            from .focal_sources import focal_plans_orders
            focal_fast = focal_plans_orders(
                lens, plane, pos_p, dir_s, ok, chief_plane0, chief_dir, n_after, lam_mm, wls, z_sensor - z_plane,
                None if center_mm is None else centers0, widths, size, pixel, res, lo0, hi0, rays_per_sample,
                nyquist_safety, square_pupil, focal_patch_tol, shared, sampling_tol=model_tolerance)
    # the sources' launch arrays, one row each (wavelength index 0: each plan's tracer is of its own wavelength)
    wl0 = np.zeros(1, dtype=np.int32)
    shape, od = src_all["shape"], src_all["object_distance"]
    plans, beside = [], []
    # the per-source arrays the plans keep, read-only once: each plan's rows are read-only views of them, which a
    # BatchPlan keeps as they are (it copies a writeable array), the same values
    launch = {key: _frozen(np.array(src_all[key])) for key in ("pos", "dir", "finite", "aim", "half_x", "half_y")}
    for a in (wl0, n_after, lam_mm, chief_plane1, chief_sensor, opl_chief, chief_ok, target, carrier0, centers0, lo0,
              hi0):
        _frozen(a)
    from .plan import gauss_tol
    g_tol = gauss_tol(model_tolerance)   # the pixel integration's error bound (1e-7 unless a tolerance relaxes it)
    for k in range(nsrc):
        sl = slice(k, k + 1)
        src = {"pos": launch["pos"][sl], "dir": launch["dir"][sl], "finite": launch["finite"][sl],
               "aim": launch["aim"][sl], "half_x": launch["half_x"][sl], "half_y": launch["half_y"][sl],
               "wl": wl0, "shape": shape, "fields": [fields[k]], "object_distance": od,
               "relative_opl": bool(use_reference)}   # the keys in Tracer.sources' order
        width = float(widths[k])
        method = method0
        carrier, centers, lo, hi = carrier0[sl], centers0[sl], lo0[sl], hi0[sl]
        ctx = PlanContext(lens=lens, plane=plane, plan=plan, pos_p=pos_p[sl], dir_s=dir_s[sl], ok=ok[sl],
                          chief_plane=chief_plane0[sl], chief_dir=chief_dir[sl], n_after=n_after[sl],
                          lam_mm=lam_mm[sl], wls=[wls[k]], distance_mm=z_sensor - z_plane,
                          center_mm=centers_req[k], size=size, pixel=pixel, width=width, pilot_cell=width / 31.0,
                          lo=lo, hi=hi, fmax=fmax[sl], f_doe=f_doe[sl], feature=feature, out_width=out_width,
                          carrier=carrier, centers=centers, rays_per_sample=rays_per_sample,
                          nyquist_safety=nyquist_safety, patch_tol=focal_patch_tol, straight_edges=square_pupil,
                          shared=shared, sampling_tol=model_tolerance)
        planned = {m: focal_fast[k] if m == "focal" and k in focal_fast else get_method(m).plan(ctx)
                   for m in (AUTO_PAIR if method == "compare" else (method,))}
        main = planned["asm" if method == "compare" else method]
        pl, carrier, centers, lo, hi, focal = main.plan, main.carrier, main.centers, main.lo, main.hi, main.geo
        gn = gauss_nodes
        more = ()
        if gn is None:
            gn = _gauss_nodes_one(dir_s[k, ok[k], :2], n_img[k], lam_mm[k], pixel, tol=g_tol)
            more = (f"pixel integration: {gn} x {gn} Gauss-Legendre nodes per pixel "
                    f"(intensity band of the beam's NA across a {pixel * 1e3:.4g} um pixel)",)
        # the reasons and the estimate in one copy (estimate_cost reads neither)
        pl = pl.evolved(reasons=pl.reasons + more, estimate=estimate_cost(pl, 1, size, gn))
        if method == "compare":
            pl, chosen_focal = _choose_auto(pl, planned["focal"], 1, size, gn, auto_rule, device,
                                            memory_budget_bytes)
            if chosen_focal:
                f = planned["focal"]
                focal, carrier, centers = f.geo, f.carrier, f.centers
        if memory_budget_bytes is not None and not may_beside:
            budget_check(pl)
        n = pl.n_grid
        mid = 0.5 * (lo + hi)
        origin = lo.copy() if pl.kind == "paper" else mid - 0.5 * (n - 1) * pl.pitch_mm
        origin = doe_pixel_origin(lens, plane, origin, pl.pitch_mm)
        rim = amplitude == "energy" and src["shape"] == "circle" and get_method(pl.method).rim_weighted
        bp = BatchPlan(lens=lens, fields=[fields[k]], wls=[wls[k]], size=size, pixel=pixel, device=device,
                       dtype=dtype, amplitude=amplitude, use_reference=use_reference, gauss_nodes=gn,
                       pixel_values=pixel_values, deterministic=deterministic, own_pupils=True,
                       pilot=_pilot_row(pilot, k), src=src, plane=plane, curved_plane=curved_plane,
                       square_pupil=square_pupil, nsrc=1, n_after=n_after[sl], lam_mm=lam_mm[sl], z_plane=z_plane,
                       z_sensor=z_sensor, plan=pl, method=pl.method, focal=focal, chief_plane=chief_plane1[sl],
                       chief_sensor=chief_sensor[sl], carrier=carrier, centers=centers, lo=lo, hi=hi, origin=origin,
                       opl_chief=opl_chief[sl], chief_ok=chief_ok[sl], target=target[sl],
                       pupil=(None, None, (2.0 / pl.ray_grid) ** 2), rim=rim)
        plans.append(bp)
        beside.append({"pos_s": pos_s[sl], "dir_s": dir_s[sl], "ok": ok[sl], "carrier": carrier0[sl],
                       "centers": centers0[sl], "beam_width_mm": float(np.min(hi - lo)),
                       "rays_per_sample": rays_per_sample})

    # ---- the methods planned beside (pixel), with every source's model error against its chief patch in one call
    from .model_error import estimate_sources
    chosen_late = [None] * nsrc
    key_states = {}   # each source's memo-key digest after its pilot rows, hashed once for both calls
    if may_beside:
        from ..doe import is_flat_profile
        s_pl = lens.surfaces[plane]
        # consider_pixel reads the model error only where the lens has no DOE (or a blank one)
        ests = [None] * nsrc if s_pl.type == "doe" and not is_flat_profile(s_pl.profile) else \
            estimate_sources(lens, plane, pilot, [b["centers"] for b in beside], target, wls, n_after, lam_mm,
                             z_plane, z_sensor, key_states=key_states)
        for k in range(nsrc):
            bp = plans[k]
            pilot_s = dict(beside[k], model_error=None if ests[k] is None else [ests[k]])
            for m in late:
                bp, switched = m.consider(bp, requested == m.name, pilot_s, model_tolerance, memory_budget_bytes)
                if switched:
                    chosen_late[k] = m.name
                    break
            if chosen_late[k] is None and memory_budget_bytes is not None:
                budget_check(bp.plan, bp.pixel_alternative)
            plans[k] = bp
    # ---- the model error of every source's plan in one call, then each one's wave step
    from . import wave_step as _ws
    skip = not estimate_model_error and not _ws.model_error_needed(requested, model_tolerance)
    ests = None if skip else estimate_sources(lens, plane, pilot, [bp.centers for bp in plans], target, wls,
                                              n_after, lam_mm, z_plane, z_sensor, key_states=key_states)
    out = []
    for k, bp in enumerate(plans):
        req = chosen_late[k] if chosen_late[k] is not None else requested
        out.append(_ws.plan_wave_step(bp, model_tolerance, req, memory_budget_bytes, estimate=[] if skip else [ests[k]]))
    return out
