"""Where a batch's beams go after the DOE, shared by the propagation methods' planners: the DOE orders each beam
carries and the carrier of the chief ray's main order (:func:`doe_orders`), and the patch centres where the chief
rays land after that order (:func:`main_order_centres`). The focal method sizes its plans from them; the ASM method
centres its default patch with them, so the patch does not move with the method ``"auto"`` picks."""
from __future__ import annotations

import numpy as np

from ...doe import is_flat_profile
from ...errors import LensError
from ...lens import snap_to_pixel
from ..doe_sampling import chief_zone, lens_dir, one_branch


def doe_orders(ctx):
    """The DOE orders a batch's beams carry (:class:`~rwwarp.wave.methods.registry.PlanContext`), per source:
    ``(prof, xy, freq, f_c, orders, doe_freq, central)``: the DOE's profile (None: none or blank), the valid pilot
    rays on the plane (mm) and their frequencies ``n d_xy / lambda`` (cycles/mm), the carrier ``f_c`` (S, 2) after the
    chief ray's main order (cycles/mm), the orders ``[(m, c_m)]`` (one smooth order ``alpha`` where the relief does
    not wrap inside the beam), the DOE's local frequencies at the rays and the chief ray's zone (or None)."""
    from ... import doe
    from ..focal import FOCAL_MAX_ORDER, doe_order_coefficients
    lens, plane, pos_p, dir_s, ok = ctx.lens, ctx.plane, ctx.pos_p, ctx.dir_s, ctx.ok
    chief_plane, n_after, lam_mm, wls = ctx.chief_plane, ctx.n_after, ctx.lam_mm, ctx.wls
    nsrc = len(n_after)
    s = lens.surfaces[plane]
    shared = ctx.shared if ctx.shared is not None else {}
    prof = shared.get("focal_profile", False)
    if prof is False:   # the DOE's profile (None: none or blank), once per call where the sources share it
        prof = None
        if s.type == "doe" and not is_flat_profile(s.profile):
            prof = doe.profile_from_dict(s.profile, base=lens_dir(lens))
        shared["focal_profile"] = prof
    scales = shared.setdefault("focal_alpha", {})   # the relief's phase scale per wavelength (um)
    orders, doe_freq, central = [], [], []
    xy = [pos_p[k, ok[k], :2] for k in range(nsrc)]
    freq = [n_after[k] * dir_s[k, ok[k], :2] / lam_mm[k] for k in range(nsrc)]
    f_c = n_after[:, None] * ctx.chief_dir[:, :2] / lam_mm[:, None]
    for k in range(nsrc):
        central.append(None)
        if prof is None:
            orders.append([(0, 1.0 + 0j)])
            doe_freq.append(None)
            continue
        alpha = scales.get(wls[k])
        if alpha is None:
            alpha = scales[wls[k]] = doe.wavelength_scale(s.material, s.design_wavelength_um, wls[k])
        gx, gy = prof.gradient(xy[k][:, 0], xy[k][:, 1], s.design_wavelength_um)
        doe_freq.append(np.stack([gx, gy], 1) / (2 * np.pi))
        cx, cy = prof.gradient(np.array([chief_plane[k, 0]]), np.array([chief_plane[k, 1]]), s.design_wavelength_um)
        branch = None if s.levels else one_branch(prof.phase(xy[k][:, 0], xy[k][:, 1], s.design_wavelength_um))
        if branch is not None:
            # the relief does not wrap inside the beam: the transmission is exactly exp(1j alpha (phi0 -
            # 2 pi k)), one smooth "order" of non-integer index alpha (its Fourier series over integer
            # orders would converge slowly next to the wrap: Gibbs)
            orders.append([(float(alpha), complex(np.exp(-2j * np.pi * alpha * branch)))])
            f_c[k] += alpha * np.array([cx[0], cy[0]]) / (2 * np.pi)
            continue
        ms = set(range(-FOCAL_MAX_ORDER, FOCAL_MAX_ORDER + 1))
        if s.levels:
            ms |= {1 + j * int(s.levels) for j in (-2, -1, 1, 2)}
        ms = np.array(sorted(ms))
        cm = doe_order_coefficients(alpha, s.levels, ms)
        orders.append(list(zip(ms.tolist(), cm.tolist())))
        if not s.levels:
            # the zone the chief ray crosses is computed exactly, exp(1j alpha (phi0 - 2 pi k_c)): the order
            # series converges slowly next to a wrap boundary the relief touches without crossing (an even
            # polynomial's 0 on the axis), where every order's light reaches the patch
            central[-1] = (chief_zone(prof.phase(xy[k][:, 0], xy[k][:, 1], s.design_wavelength_um),
                                       xy[k], chief_plane[k, :2]), float(alpha))
        m0 = int(ms[np.argmax(np.abs(cm))])
        f_c[k] += m0 * np.array([cx[0], cy[0]]) / (2 * np.pi)
    return prof, xy, freq, f_c, orders, doe_freq, central


def main_order_centres(ctx, f_c):
    """The patch centres ((S, 2) mm, snapped to pixels) where the chief rays land after their main DOE order:
    ``f_c`` (S, 2) cycles/mm the carriers of :func:`doe_orders`, straight from the chief points on the plane over
    the distance to the sensor (:func:`rwwarp.wave.plan.landing_points`). LensError where that order is evanescent."""
    from ..plan import landing_points
    inv_lam = ctx.n_after / ctx.lam_mm
    land = np.array([landing_points(ctx.chief_plane[k, :2], f_c[k], inv_lam[k], ctx.distance_mm)
                     for k in range(len(ctx.n_after))])
    if not np.all(np.isfinite(land)):
        raise LensError("the chief ray's main diffraction order is evanescent behind the DOE", file=ctx.lens.source)
    res = ctx.lens.sensor.resolution
    return np.stack([snap_to_pixel(land[:, 0], ctx.pixel, res[0]), snap_to_pixel(land[:, 1], ctx.pixel, res[1])], axis=1)
