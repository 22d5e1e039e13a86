"""The focal plans of many sources, each planned on its own, at once: what
:func:`rwwarp.wave.methods.focal.plan_focal_batch` (through :func:`rwwarp.wave.plan.plan_focal`) gives each source
alone, where the beam carries one order (no DOE on the wave plane, or a blank one: :func:`focal_plans_one_order`)
and where a DOE splits it into diffraction orders (:func:`focal_plans_orders`). Every source's orders' frequencies,
straight-ray landings, landing boxes, bands, the decisions which orders are kept, the landings under the fitted
quadratic transfer and the remainder's displacement are computed for all sources (in chunks) in one set of array
operations; only elementwise operations, maxima / minima over a source's rays and orders and sums of the two
components run across sources (the same values: each source's rays padded with copies of its own first ray, its
orders with copies of its first live order, which no decision, maximum or minimum sees); the least-squares fit of
the transfer runs for all sources at once too (:func:`rwwarp.wave.plan.fit_quadratic_transfers`, whose sums are
added in order, padding masked out: a source's fit is the same bits alone and in a batch); the chief ray's wrap
zone and the plan's grids and reasons stay per source, on that source's own values; an order some of whose rays
are evanescent is taken over the rays that land (masked), as the per-source planner takes it. The sources the
common case does not cover (a beam that misses its patch, an evanescent chief ray, a source without rays, a
pixel-map relief) are left to the per-source planner.
Used by :func:`rwwarp.wave.plan_sources.plan_sources`; tests/rwwarp/test_plan_sources.py compares every plan with
the per-source planner's, bit for bit. On the 2-core CPU of issue 25 the Cooke triplet's design step (48 sources,
17 live orders at two of its three wavelengths) plans its focal part in 0.64 ms a source instead of 1.78
(perf/time_plan_sources.py --case cooke: 3.1 -> 2.0 ms a source in all, warm memo). Lengths in mm, frequencies in
cycles/mm."""
from __future__ import annotations

import numpy as np

from ..lens import snap_to_pixel
from .methods.registry import Planned
from .plan import (FOCAL_EDGE_MARGIN_B, FOCAL_LIT_SHIFT_MARGIN, FOCAL_MARGIN_B, FOCAL_SHIFT_MARGIN,
                   FOCAL_TAPER_GUARD, fit_quadratic_transfers, focal_plan_from, lit_shift_margin)

__all__ = ["focal_plans_one_order", "focal_plans_orders"]

ORDERS_CHUNK_ELEMENTS = 1 << 16   # per (sources x orders x rays) array of one chunk: 512 KiB in float64 (in cache)
ORDERS_PAD_RATIO = 2.0            # a source joins a chunk whose sources carry up to this many times its live orders


class _Orders:
    """One source's diffraction orders as :func:`rwwarp.wave.plan.plan_focal` walks them: ``orders`` (every
    ``(m, c_m)``), the main order ``main_m``, the live ones (``|c_m|^2 >= order_tol``) with their ``p = |c_m|^2``,
    kept entries and whether each is the main one, and ``lost0``: the power of the others, summed in order."""
    __slots__ = ("orders", "main_m", "main_c", "live_m", "p", "entry", "is_main", "lost0")

    def __init__(self, orders, order_tol):
        from .plan import _order_index
        self.orders = orders
        self.main_m, self.main_c = max(orders, key=lambda mc: abs(mc[1]))
        self.live_m, self.p, self.entry, self.is_main = [], [], [], []
        lost = 0.0
        for m, c in orders:
            p = abs(c) ** 2
            if p < order_tol:
                lost += p
                continue
            self.live_m.append(m)
            self.p.append(p)
            self.entry.append((_order_index(m), complex(c)))
            self.is_main.append(m == self.main_m)
        self.lost0 = lost


def _rays(pos_p, dir_s, ok, n_after, lam_mm):
    """Every source's pilot rays on the wave plane, its valid ones first (in their order), then copies of its first
    valid one (seen by no maximum or minimum): ``counts`` (S,), ``inside`` (S, R) (a valid ray, not a copy),
    ``flat`` (S, R) the index of each into the valid rays of all sources one after another, ``xy`` (S, R, 2) mm
    and ``freq`` (S, R, 2) cycles/mm (``n d_xy / lambda``, as ``plan_focal_batch`` computes them)."""
    S, R = ok.shape
    counts = ok.sum(1)
    order = np.argsort(~ok, axis=1, kind="stable")
    rank = np.arange(R)[None, :]
    inside = rank < counts[:, None]
    idx = np.where(inside, order, order[:, :1])
    rows = np.arange(S)[:, None]
    xy = pos_p[rows, idx, :2]
    freq = n_after[:, None, None] * dir_s[rows, idx, :2] / lam_mm[:, None, None]
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    flat = np.minimum(start[:, None] + np.where(inside, rank, 0), max(int(counts.sum()) - 1, 0))   # no rays: any
    return counts, inside, flat, xy, freq


def focal_plans_one_order(pos_p, dir_s, ok, chief_plane, chief_dir, n_after, lam_mm, distance_mm, centers_given,
                          widths, size, pixel, resolution, lo, hi, rays_per_sample, nyquist_safety,
                          straight_edges, sampling_tol=None) -> dict:
    """Per source ``k`` of ``S``: the :class:`~rwwarp.wave.methods.registry.Planned` focal plan that
    ``plan_focal_batch`` makes for it alone (``ctx`` of that source's rows) where the wave plane has no DOE (or a
    blank one: the single order ``(0, 1)``) and the plan is the planner's own (``plan="auto"``). ``pos_p`` /
    ``dir_s`` (S, R, 3) pilot rays on the wave plane, ``ok`` (S, R), ``chief_plane`` (S, 3) mm, ``chief_dir``
    (S, 3), ``n_after`` / ``lam_mm`` (S,), ``distance_mm`` from the wave plane to the sensor, ``centers_given``:
    None (each patch where its chief ray lands) or (S, 2) mm patch centres already snapped; ``widths`` (S,) mm beam
    footprints; ``size`` px of ``pixel`` mm on a sensor of ``resolution`` pixels; ``lo`` / ``hi`` (S, 2) mm the
    footprint corners; the sampling knobs as ``plan_focal`` takes them. Returns ``{k: Planned}`` for the sources
    planned here: those whose landing box (of the rays that land) comes near the patch; the others (a beam that
    misses its patch or whose every ray is evanescent, an evanescent chief ray) are left to the per-source planner,
    which plans them (or raises their error) as before."""
    S = ok.shape[0]
    counts, _, _, xy, freq = _rays(pos_p, dir_s, ok, n_after, lam_mm)
    f_c = n_after[:, None] * chief_dir[:, :2] / lam_mm[:, None]
    one = _Orders([(0, 1.0 + 0j)], 1e-8)       # plan_focal_batch's order of a beam without a DOE
    # its frequencies: 0 * 0 + freq, the bits of plan_focal's freq + 0.0 (x + 0.0 = 0.0 + x, -0.0 included)
    return _plans(xy, freq, np.zeros_like(xy), counts, [one] * S, [None] * S, None, f_c, chief_plane, n_after,
                  lam_mm, distance_mm, centers_given, widths, size, pixel, resolution, lo, hi, rays_per_sample,
                  nyquist_safety, straight_edges, 0.0, sampling_tol)


def focal_plans_orders(lens, plane, pos_p, dir_s, ok, chief_plane, chief_dir, n_after, lam_mm, wls, distance_mm,
                       centers_given, widths, size, pixel, resolution, lo, hi, rays_per_sample, nyquist_safety,
                       straight_edges, patch_tol, shared=None, order_tol=1e-8, sampling_tol=None) -> dict:
    """Per source ``k`` of ``S``: the :class:`~rwwarp.wave.methods.registry.Planned` focal plan that
    ``plan_focal_batch`` makes for it alone where the wave plane (surface ``plane`` of ``lens``) is a DOE with a
    smooth relief (several diffraction orders, or one order of non-integer index where the relief does not wrap
    inside the beam), ``plan="auto"``. The arguments as :func:`focal_plans_one_order` takes them, and ``wls`` (S,)
    um, ``patch_tol`` (the focal planner's ``patch_tol``), ``shared`` (the per-call dict of
    :class:`~rwwarp.wave.methods.PlanContext`: the DOE profile and its phase scale per wavelength are read from and
    kept in it, as the per-source planner does). The DOE's gradient and phase at every source's pilot rays come
    from one evaluation (a smooth relief's are elementwise arithmetic: each point's value is the per-source
    call's), each wavelength's order coefficients once; then every source's orders at once, in chunks of sources
    of similar order counts (``ORDERS_CHUNK_ELEMENTS``, ``ORDERS_PAD_RATIO``): a source's orders padded with copies
    of its first live order and its rays with copies of its first ray, whose results no decision, maximum or
    minimum sees (an order some of whose rays are evanescent: over the rays that land). Returns ``{k: Planned}``
    for the sources planned here: those whose chief ray's main order lands and which keep at least one order; the
    others (and every source of a pixel-map relief, which has no gradient) are left to the per-source planner,
    which plans them (or raises their error) as before."""
    from .. import doe
    from ..doe import is_flat_profile
    from .doe_phase import SMOOTH_KINDS
    from .doe_sampling import branch_of_range, chief_zone, lens_dir
    from .focal import FOCAL_MAX_ORDER, doe_order_coefficients
    s = lens.surfaces[plane]
    shared = {} if shared is None else shared
    prof = shared.get("focal_profile", False)
    if prof is False:   # as plan_focal_batch reads it: once per call, kept for the per-source planner
        prof = None
        if s.type == "doe" and not is_flat_profile(s.profile):
            prof = doe.profile_from_dict(s.profile, base=lens_dir(lens))
        shared["focal_profile"] = prof
    if prof is None or getattr(prof, "kind", None) not in SMOOTH_KINDS:
        return {}
    S = ok.shape[0]
    counts, inside, flat, xy, freq = _rays(pos_p, dir_s, ok, n_after, lam_mm)
    if not counts.any():
        return {}
    dwl = s.design_wavelength_um
    # the relief's gradient (and phase) at every source's valid rays in one call, source after source
    xyv = xy[inside]
    start = flat[:, 0]
    gx, gy = prof.gradient(xyv[:, 0], xyv[:, 1], dwl)
    doe_f = (np.stack([gx, gy], 1) / (2 * np.pi))[flat]
    cx, cy = prof.gradient(chief_plane[:, 0].copy(), chief_plane[:, 1].copy(), dwl)
    phv = None if s.levels else prof.phase(xyv[:, 0], xyv[:, 1], dwl)
    if phv is not None:
        ph = phv[flat]
        ph_fin = np.isfinite(ph).all(axis=1)
        ph_min, ph_max = ph.min(axis=1), ph.max(axis=1)
    # each source's orders: per wavelength (the relief wraps inside the beam), or one exact term (it does not)
    scales = shared.setdefault("focal_alpha", {})
    series = {}
    infos, central, coef = [], [], np.zeros(S)
    for k in range(S):
        alpha = scales.get(wls[k])
        if alpha is None:
            alpha = scales[wls[k]] = doe.wavelength_scale(s.material, s.design_wavelength_um, wls[k])
        branch = None
        if phv is not None and counts[k] and ph_fin[k]:
            branch = branch_of_range(ph_min[k], ph_max[k])
        if branch is not None:
            infos.append(_Orders([(float(alpha), complex(np.exp(-2j * np.pi * alpha * branch)))], order_tol))
            central.append(None)
            coef[k] = alpha
            continue
        if wls[k] not in series:
            ms = set(range(-FOCAL_MAX_ORDER, FOCAL_MAX_ORDER + 1))
            if s.levels:
                ms |= {1 + j * int(s.levels) for j in (-2, -1, 1, 2)}
            ms = np.array(sorted(ms))
            cm = doe_order_coefficients(alpha, s.levels, ms)
            series[wls[k]] = (_Orders(list(zip(ms.tolist(), cm.tolist())), order_tol), int(ms[np.argmax(np.abs(cm))]))
        info, m0 = series[wls[k]]
        infos.append(info)
        coef[k] = m0
        central.append(None if s.levels or not counts[k] else
                       (chief_zone(phv[start[k]:start[k] + counts[k]], xy[k, :counts[k]], chief_plane[k, :2]),
                        float(alpha)))
    # the carrier after each source's main order (or its exact term)
    f_c = n_after[:, None] * chief_dir[:, :2] / lam_mm[:, None]
    f_c += coef[:, None] * np.stack([cx, cy], 1) / (2 * np.pi)
    return _plans(xy, freq, doe_f, counts, infos, central, prof, f_c, chief_plane, n_after, lam_mm, distance_mm,
                  centers_given, widths, size, pixel, resolution, lo, hi, rays_per_sample, nyquist_safety,
                  straight_edges, patch_tol, sampling_tol)


def _plans(xy, freq, doe_f, counts, infos, central, prof, f_c, chief_plane, n_after, lam_mm, distance_mm,
           centers_given, widths, size, pixel, resolution, lo, hi, rays_per_sample, nyquist_safety, straight_edges,
           patch_tol, sampling_tol=None) -> dict:
    """The plans of :func:`focal_plans_one_order` and :func:`focal_plans_orders` from every source's padded rays
    (:func:`_rays`; ``doe_f`` (S, R, 2) the DOE's frequency at them), orders (``infos``), chief zones
    (``central``), the profile ``prof`` and carriers ``f_c`` (S, 2): the patch centres, then every source's orders
    at once in chunks (:func:`_orders_chunk`), each plan's grids and reasons (:func:`focal_plan_from`)."""
    S, R = counts.shape[0], xy.shape[1]
    z = float(distance_mm)
    half_w = 0.5 * size * pixel
    mb = FOCAL_EDGE_MARGIN_B if straight_edges else FOCAL_MARGIN_B
    inv_lam = n_after / lam_mm
    inv2 = np.array([inv_lam[k] ** 2 for k in range(S)])          # as landing_points squares its scalar inv_lam
    go = (counts > 0) & np.array([len(i.live_m) > 0 for i in infos])
    if centers_given is None:   # where the chief ray's main order lands (evanescent: the per-source planner's error)
        cw2 = inv2 - np.sum(f_c * f_c, axis=-1)
        land = chief_plane[:, :2] + z * f_c / np.sqrt(np.where(cw2 > 0, cw2, np.nan))[:, None]
        go &= np.isfinite(land).all(axis=1)
        land = np.where(np.isfinite(land), land, 0.0)
        centers = np.stack([snap_to_pixel(land[:, 0], pixel, resolution[0]),
                            snap_to_pixel(land[:, 1], pixel, resolution[1])], axis=1)
    else:
        centers = np.array(centers_given, dtype=np.float64)   # a copy: set read-only below
    from .focal import transfer_curvature
    _, g, q = transfer_curvature(f_c, inv_lam)
    by_axis = [np.ascontiguousarray(np.moveaxis(a, -1, 0)) for a in (xy, freq, doe_f)]   # (2, S, R) each
    res = {}
    for sel in _order_chunks(np.flatnonzero(go), [len(i.live_m) for i in infos], R):
        res.update(_orders_chunk(sel, infos, *by_axis, counts, f_c, centers, inv2, g, q, z, half_w, mb,
                                 patch_tol, lit_shift_margin(sampling_tol)))
    out = {}
    for a in (f_c, centers):   # each plan keeps read-only views of its rows
        a.flags.writeable = False
    for k in sorted(res):
        keep, lost, band, shifts, g_fit, q_fit, lit, spread, spread_main, ray_spread, box = res[k]
        sl = slice(k, k + 1)
        pl, geo = focal_plan_from([box], [keep], lost, band, shifts, g_fit, q_fit, lit, spread, spread_main,
                                  ray_spread, z, half_w, mb, float(widths[k]), rays_per_sample, nyquist_safety,
                                  straight_edges, sampling_tol=sampling_tol)
        geo["profile"] = prof
        geo["central_zone"] = [central[k]]
        out[int(k)] = Planned(pl, f_c[sl], centers[sl], lo[sl], hi[sl], geo)
    return out


def _order_chunks(ks, n_live, R):
    """The sources ``ks`` in chunks: by decreasing live-order count, a chunk's sources carrying more than 1 /
    ``ORDERS_PAD_RATIO`` of its most orders, its arrays within ``ORDERS_CHUNK_ELEMENTS``."""
    ks = sorted(ks, key=lambda k: -n_live[k])
    out, cur = [], []
    for k in ks:
        if cur and (n_live[k] * ORDERS_PAD_RATIO <= n_live[cur[0]]
                    or (len(cur) + 1) * n_live[cur[0]] * R > ORDERS_CHUNK_ELEMENTS):
            out.append(np.array(sorted(cur)))
            cur = []
        cur.append(k)
    if cur:
        out.append(np.array(sorted(cur)))
    return out


def _orders_chunk(sel, infos, xy, freq, doe_f, counts, f_c, centers, inv2, g, q, z, half_w, mb, patch_tol,
                  lit_margin=FOCAL_LIT_SHIFT_MARGIN):
    """:func:`rwwarp.wave.plan.plan_focal`'s loop for the sources ``sel`` at once (``xy``, ``freq``, ``doe_f``: (2,
    S, R) by component, the other arrays' rows ``sel``; ``infos``: each source's :class:`_Orders`): ``{k: (kept
    orders, lost power (1,), band (1,), shifts (1,), g_fit (1, 2), q_fit (1, 2), lit (1,), spread, spread_main,
    ray_spread, (box_lo, box_hi))}`` for those which keep an order. Every value is the per-source loop's:
    elementwise arithmetic, maxima and minima over the same values (padding and rays that do not land masked out,
    or copies), sums and products of the two components (``a + b`` in either order), the same decisions, the fit
    of every source at once (:func:`rwwarp.wave.plan.fit_quadratic_transfers`: sums in the points' order, the
    padding masked out, the same bits as plan_focal's). The arrays are (n, M, R) per component (contiguous
    reductions over the rays). ``lit_margin``: a lit taper's sensor-side margin in displacements
    (:func:`rwwarp.wave.plan.lit_shift_margin` of the requested tolerance)."""
    n, R = len(sel), xy.shape[2]
    M = max(len(infos[k].live_m) for k in sel)
    ms = np.empty((n, M), dtype=doe_f.dtype)    # m * doe_freq in doe_freq's precision, as plan_focal multiplies it
    valid = np.zeros((n, M), dtype=bool)
    main = np.zeros((n, M), dtype=bool)
    P = np.zeros((n, M))
    for i, k in enumerate(sel):
        inf = infos[k]
        L = len(inf.live_m)
        ms[i, :L] = inf.live_m
        ms[i, L:] = inf.live_m[0]                 # padding: copies of the first live order, never read
        valid[i, :L] = True
        main[i, :L] = inf.is_main
        P[i, :L] = inf.p
    T, fc, r1 = centers[sel], f_c[sel], np.arange(n)
    X = [xy[a][sel][:, None, :] for a in range(2)]                                         # (n, 1, R)
    F = []
    for a in range(2):                          # freq + m * doe_freq (n, M, R), in place where it can be
        f = ms[:, :, None] * doe_f[a][sel][:, None, :]
        f += freq[a][sel][:, None, :]
        F.append(f)
    w = F[0] * F[0]
    w += F[1] * F[1]                            # the sum over the two components, a + b in either order
    np.subtract(inv2[sel][:, None, None], w, out=w)
    w[~(w > 0)] = np.nan                        # evanescent (or grazing) rays: NaN, as landing_points has them
    np.sqrt(w, out=w)
    Ls = []
    for a in range(2):                          # xy + z f / w
        L = z * F[a]
        L /= w
        L += X[a]
        Ls.append(L)
    LLO = np.stack([L.min(axis=2) for L in Ls], axis=-1)     # (n, M, 2)
    LHI = np.stack([L.max(axis=2) for L in Ls], axis=-1)
    # every ray of an order lands iff its landings' least and greatest are finite (NaN reaches both)
    full = np.isfinite(LLO).all(axis=2) & np.isfinite(LHI).all(axis=2)
    landed, okr = valid, None
    if (valid & ~full).any():
        # an order some of whose rays do not land (evanescent): its landing rays' box and band, as plan_focal's
        okr = np.isfinite(Ls[0]) & np.isfinite(Ls[1])          # (n, M, R) the rays that land
        landed = valid & okr.any(axis=2)
        LLO = np.stack([np.where(okr, L, np.inf).min(axis=2) for L in Ls], axis=-1)
        LHI = np.stack([np.where(okr, L, -np.inf).max(axis=2) for L in Ls], axis=-1)
        LLO[~landed] = 0.0                                      # no ray lands: never read
        LHI[~landed] = 0.0
        Fhi = [np.where(okr, f, -np.inf).max(axis=2) for f in F]
        Flo = [np.where(okr, f, np.inf).min(axis=2) for f in F]
    else:
        Fhi, Flo = [f.max(axis=2) for f in F], [f.min(axis=2) for f in F]
    # max |f - f_c| from the least and greatest f (a rounded difference is monotone in f: the same value)
    o_band = np.zeros((n, M))
    for a in range(2):
        o_band = np.maximum(o_band, np.maximum(np.abs(Fhi[a] - fc[:, a, None]), np.abs(Flo[a] - fc[:, a, None])))
    band = np.maximum(1e-9, np.max(np.where(landed, o_band, -np.inf), axis=1))
    margin = mb / band
    up = T + half_w + margin[:, None]
    dn = T - half_w - margin[:, None]
    miss = np.any(LLO > up[:, None], axis=2) | np.any(LHI < dn[:, None], axis=2)
    ext = LHI - LLO
    reach = np.prod(np.minimum(ext, (2 * (half_w + margin))[:, None, None]) + 1e-12, axis=2)
    area = np.prod(ext + 1e-12, axis=2)
    share = reach / area
    used = landed & ~miss & (main | ~(P * share < patch_tol))
    whole = used.any(axis=1)                    # nothing reaches the patch: the per-source planner's dark patch
    if not whole.any():
        return {}
    mu = (used & main).any(axis=1)              # the main order is kept
    jm = np.argmax(main, axis=1)
    mLLO, mLHI = LLO[r1, jm], LHI[r1, jm]
    ray_spread = np.where(mu, np.maximum(0.0, np.max(mLHI - mLLO, axis=1)), 0.0)
    # the kept orders alone from here: each source's first K, padded with copies of its first (masked out)
    nu = used.sum(axis=1)
    K = int(nu.max())
    ju = np.argsort(~used, axis=1, kind="stable")[:, :K]
    ju = np.where(np.arange(K)[None, :] < nu[:, None], ju, ju[:, :1])
    uk = np.arange(K)[None, :] < nu[:, None]                 # (n, K): a kept order, not padding
    mk = uk & main[r1[:, None], ju]                          # ... the main one
    FU = [F[a][r1[:, None], ju] for a in range(2)]           # (n, K, R)
    LU = [Ls[a][r1[:, None], ju] for a in range(2)]
    OKU = None if okr is None else okr[r1[:, None], ju]      # the kept orders' rays that land
    # the transfer fitted to every source's kept orders' rays (those that land) at once, each source's points in
    # plan_focal's order (order after order), the padding masked out: the same bits as plan_focal's fit
    pts = uk[:, :, None] & (np.arange(R)[None, None, :] < counts[sel][:, None, None])
    if OKU is not None:
        pts = pts & OKU
    pts = pts.reshape(n, K * R)
    g_fit, q_fit = np.empty((n, 2)), np.empty((n, 2))
    for a in range(2):
        u = (FU[a] - fc[:, a, None, None]).reshape(n, K * R)
        t = ((X[a] - LU[a]) / z).reshape(n, K * R)
        g_fit[:, a], q_fit[:, a] = fit_quadratic_transfers(u, t, pts, g[sel, a], q[sel, a])
    # landings under the quadratic transfer, the remainder's displacement, their boxes
    LG = [X[a] - z * (g_fit[:, a, None, None] + (FU[a] - fc[:, a, None, None]) * q_fit[:, a, None, None])
          for a in range(2)]
    if OKU is None:
        dev = np.maximum(np.max(np.abs(LU[0] - LG[0]), axis=2), np.max(np.abs(LU[1] - LG[1]), axis=2))
        LGlo = np.stack([L.min(axis=2) for L in LG], axis=-1)    # (n, K, 2)
        LGhi = np.stack([L.max(axis=2) for L in LG], axis=-1)
    else:                                       # over the rays that land alone
        dev = np.maximum(np.max(np.where(OKU, np.abs(LU[0] - LG[0]), 0.0), axis=2),
                         np.max(np.where(OKU, np.abs(LU[1] - LG[1]), 0.0), axis=2))
        LGlo = np.stack([np.where(OKU, L, np.inf).min(axis=2) for L in LG], axis=-1)
        LGhi = np.stack([np.where(OKU, L, -np.inf).max(axis=2) for L in LG], axis=-1)
    shifts = np.maximum(0.0, np.max(np.where(uk, dev, 0.0), axis=1))
    u3, m3 = uk[..., None], mk[..., None]
    lo_g = np.minimum(T - half_w, np.min(np.where(u3, LGlo, np.inf), axis=1))
    hi_g = np.maximum(T + half_w, np.max(np.where(u3, LGhi, -np.inf), axis=1))
    mlo = np.minimum(T - half_w, np.min(np.where(m3, LGlo, np.inf), axis=1))
    mhi = np.maximum(T + half_w, np.max(np.where(m3, LGhi, -np.inf), axis=1))
    guard = half_w + FOCAL_TAPER_GUARD * shifts + 3.0 / band
    lit = mu & (np.any(mLLO < T - guard[:, None], axis=1) | np.any(mLHI > T + guard[:, None], axis=1))
    margin_k = margin + np.where(lit, lit_margin, FOCAL_SHIFT_MARGIN) * shifts
    lo_s = np.minimum(lo_g, T - half_w - shifts[:, None]) - margin_k[:, None]
    hi_s = np.maximum(hi_g, T + half_w + shifts[:, None]) + margin_k[:, None]
    spread = np.maximum(0.0, np.max(hi_s - lo_s, axis=1))
    spread_main = np.maximum(0.0, np.max(mhi - mlo, axis=1) + 2.0 * margin_k)
    box_lo = T - half_w - shifts[:, None] - margin_k[:, None]
    box_hi = T + half_w + shifts[:, None] + margin_k[:, None]
    for a in (band, shifts, g_fit, q_fit, lit):   # each plan keeps read-only views of its rows
        a.flags.writeable = False
    out = {}
    for i in np.flatnonzero(whole):
        inf = infos[sel[i]]
        lost = inf.lost0
        for j in np.flatnonzero(valid[i] & ~used[i]):   # in order, as plan_focal adds them
            lost += inf.p[j]
        sl = slice(i, i + 1)
        out[int(sel[i])] = ([inf.entry[j] for j in np.flatnonzero(used[i])], np.array([lost]), band[sl],
                            shifts[sl], g_fit[sl], q_fit[sl], lit[sl], float(spread[i]), float(spread_main[i]),
                            float(ray_spread[i]), (box_lo[i], box_hi[i]))
    return out
