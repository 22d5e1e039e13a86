"""The focal plans of many sources, each planned on its own, at once where the beam carries one order
(:func:`focal_plans_one_order`): what :func:`rwwarp.wave.methods.focal.plan_focal_batch` (through
:func:`rwwarp.wave.plan.plan_focal`) gives each source alone, with its per-ray arrays (landings, landing boxes, bands,
landings under the fitted quadratic transfer, the remainder's displacement) computed for all sources in one set
of array operations. Only elementwise operations and maxima / minima over a source's rays run across sources (the
same values: each source's rays padded with copies of its own first ray, which no maximum or minimum sees); the
least-squares fit of the transfer and the plan's grids and reasons stay per source, on that source's own rays.
Used by :func:`rwwarp.wave.plan_sources.plan_sources`; tests/rwwarp/test_plan_sources.py compares every plan with
the per-source planner's, bit for bit. Lengths in mm, frequencies in cycles/mm."""
from __future__ import annotations

import numpy as np

from ..lens import snap_to_pixel
from .methods.registry import Planned
from .plan import (FOCAL_EDGE_MARGIN_B, FOCAL_LIT_SHIFT_MARGIN, FOCAL_MARGIN_B, FOCAL_SHIFT_MARGIN,
                   FOCAL_TAPER_GUARD, fit_quadratic_transfer, focal_plan_from)

__all__ = ["focal_plans_one_order"]


def focal_plans_one_order(pos_p, dir_s, ok, chief_plane, chief_dir, n_after, lam_mm, distance_mm, centers_given,
                          widths, size, pixel, resolution, lo, hi, rays_per_sample, nyquist_safety,
                          straight_edges) -> dict:
    """Per source ``k`` of ``S``: the :class:`~rwwarp.wave.methods.registry.Planned` focal plan that
    ``plan_focal_batch`` makes for it alone (``ctx`` of that source's rows) where the wave plane has no DOE (or a
    blank one: the single order ``(0, 1)``) and the plan is the planner's own (``plan="auto"``). ``pos_p`` /
    ``dir_s`` (S, R, 3) pilot rays on the wave plane, ``ok`` (S, R), ``chief_plane`` (S, 3) mm, ``chief_dir``
    (S, 3), ``n_after`` / ``lam_mm`` (S,), ``distance_mm`` from the wave plane to the sensor, ``centers_given``:
    None (each patch where its chief ray lands) or (S, 2) mm patch centres already snapped; ``widths`` (S,) mm beam
    footprints; ``size`` px of ``pixel`` mm on a sensor of ``resolution`` pixels; ``lo`` / ``hi`` (S, 2) mm the
    footprint corners; the sampling knobs as ``plan_focal`` takes them. Returns ``{k: Planned}`` for the sources
    planned here: those whose every pilot ray lands and whose landing box comes near the patch; the others
    (an evanescent ray, a beam that misses its patch, an evanescent chief ray) are left to the per-source planner,
    which plans them (or raises their error) as before."""
    S, R = ok.shape
    z = float(distance_mm)
    half_w = 0.5 * size * pixel
    mb = FOCAL_EDGE_MARGIN_B if straight_edges else FOCAL_MARGIN_B
    inv_lam = n_after / lam_mm
    inv2 = np.array([inv_lam[k] ** 2 for k in range(S)])          # as landing_points squares its scalar inv_lam
    f_c = n_after[:, None] * chief_dir[:, :2] / lam_mm[:, None]
    # each source's valid rays first, in their order, then copies of its first valid ray (seen by no max / min)
    order = np.argsort(~ok, axis=1, kind="stable")
    counts = ok.sum(1)
    idx = np.where(np.arange(R)[None, :] < counts[:, None], order, order[:, :1])
    rows = np.arange(S)[:, None]
    xy = pos_p[rows, idx, :2]
    freq = n_after[:, None, None] * dir_s[rows, idx, :2] / lam_mm[:, None, None]
    F = freq + 0.0                                               # freq + the zero DOE frequency, as plan_focal adds it
    # straight-ray landings (landing_points, elementwise)
    w2 = inv2[:, None] - np.sum(F * F, axis=-1)
    Ls = xy + z * F / np.sqrt(np.where(w2 > 0, w2, np.nan))[..., None]
    full = np.isfinite(Ls).all(axis=2).all(axis=1)
    if centers_given is None:
        cw2 = inv2 - np.sum(f_c * f_c, axis=-1)
        land = chief_plane[:, :2] + z * f_c / np.sqrt(np.where(cw2 > 0, cw2, np.nan))[:, None]
        full &= np.isfinite(land).all(axis=1)
        land = np.where(np.isfinite(land), land, 0.0)
        centers = np.stack([snap_to_pixel(land[:, 0], pixel, resolution[0]),
                            snap_to_pixel(land[:, 1], pixel, resolution[1])], axis=1)
    else:
        centers = np.array(centers_given, dtype=np.float64)   # a copy: set read-only below
    LLO, LHI = Ls.min(axis=1), Ls.max(axis=1)
    band = np.maximum(1e-9, np.max(np.abs(F - f_c[:, None, :]), axis=(1, 2)))
    margin = mb / band
    miss = np.any(LLO > centers + half_w + margin[:, None], axis=1) | \
        np.any(LHI < centers - half_w - margin[:, None], axis=1)
    go = np.flatnonzero(full & ~miss)
    if not len(go):
        return {}
    from .focal import transfer_curvature
    _, g, q = transfer_curvature(f_c, inv_lam)
    g_fit, q_fit = g.copy(), q.copy()
    for k in go:
        n = counts[k]
        g_fit[k], q_fit[k] = fit_quadratic_transfer([F[k, :n]], [Ls[k, :n]], [xy[k, :n]], f_c[k], g[k], q[k], z)
    LG = xy - z * (g_fit[:, None, :] + (F - f_c[:, None, :]) * q_fit[:, None, :])   # under the quadratic transfer
    shifts = np.maximum(0.0, np.max(np.abs(Ls - LG), axis=(1, 2)))
    lo_g = np.minimum(centers - half_w, LG.min(axis=1))
    hi_g = np.maximum(centers + half_w, LG.max(axis=1))
    guard = half_w + FOCAL_TAPER_GUARD * shifts + 3.0 / band
    lit = np.any(LLO < centers - guard[:, None], axis=1) | np.any(LHI > centers + guard[:, None], axis=1)
    margin_k = margin + np.where(lit, FOCAL_LIT_SHIFT_MARGIN, FOCAL_SHIFT_MARGIN) * shifts
    lo_s = np.minimum(lo_g, centers - half_w - shifts[:, None]) - margin_k[:, None]
    hi_s = np.maximum(hi_g, centers + half_w + shifts[:, None]) + margin_k[:, None]
    spread = np.maximum(0.0, np.max(hi_s - lo_s, axis=1))
    spread_main = np.maximum(0.0, np.max(hi_g - lo_g, axis=1) + 2.0 * margin_k)
    ray_spread = np.maximum(0.0, np.max(LHI - LLO, axis=1))
    box_lo = centers - half_w - shifts[:, None] - margin_k[:, None]
    box_hi = centers + half_w + shifts[:, None] + margin_k[:, None]
    out = {}
    for a in (band, shifts, g_fit, q_fit, lit, f_c, centers):   # each plan keeps read-only views of its rows
        a.flags.writeable = False
    for k in go:
        sl = slice(k, k + 1)
        pl, geo = focal_plan_from([(box_lo[k], box_hi[k])], [[(0, 1 + 0j)]], np.zeros(1), band[sl],
                                  shifts[sl], g_fit[sl], q_fit[sl], lit[sl],
                                  float(spread[k]), float(spread_main[k]), float(ray_spread[k]), z, half_w, mb,
                                  float(widths[k]), rays_per_sample, nyquist_safety, straight_edges)
        geo["profile"] = None
        geo["central_zone"] = [None]
        out[int(k)] = Planned(pl, f_c[sl], centers[sl], lo[sl], hi[sl], geo)
    return out
