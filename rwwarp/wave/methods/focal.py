"""``focal``: the reference wave handled analytically (:mod:`rwwarp.wave.focal`,
:class:`rwwarp.wave.focal.FocalPropagator`): its planning (the DOE orders the beam carries, the carrier and patch
centre after the main order, the wave-plane and sensor-side grids of :func:`rwwarp.wave.plan.plan_focal`), its
cost and its pixels. Lengths in mm."""
from __future__ import annotations

import math

import numpy as np

from ...doe import is_flat_profile
from ...errors import LensError
from ...lens import snap_to_pixel
from ..doe_sampling import chief_zone, lens_dir, one_branch
from ..sensor_grid import snap_centers
from .asm import wave_plane_cost
from .registry import Planned, Propagation, register


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


def plan_focal_batch(ctx) -> Planned:
    """Plan the focal propagation of a batch (:class:`~rwwarp.wave.methods.registry.PlanContext`): DOE orders,
    carrier and patch centre after the main order, grids (:func:`rwwarp.wave.plan.plan_focal`); an explicit
    focal :class:`~rwwarp.wave.plan.Plan` keeps its grids, centred where the planner centres them."""
    from ..plan import Plan, plan_focal
    prof, xy, freq, f_c, orders, doe_freq, central = doe_orders(ctx)
    inv_lam = ctx.n_after / ctx.lam_mm
    dist, pixel, nsrc = ctx.distance_mm, ctx.pixel, len(ctx.n_after)
    if ctx.center_mm is None:
        centers = main_order_centres(ctx, f_c)
    else:
        centers = snap_centers(ctx.center_mm, pixel, ctx.lens.sensor.resolution, nsrc)
    pl, geo = plan_focal(xy, freq, doe_freq, orders, centers, f_c, inv_lam, dist, ctx.width, ctx.size, pixel,
                         ctx.rays_per_sample, ctx.nyquist_safety, patch_tol=ctx.patch_tol,
                         straight_edges=ctx.straight_edges, sampling_tol=ctx.sampling_tol)
    plan = ctx.plan
    if isinstance(plan, Plan):  # an explicit focal plan: its grids, centred where the planner centres them
        if plan.n_sensor is None or plan.sensor_pitch_mm is None or plan.n_sensor_fft is None:
            raise ValueError("an explicit Plan with method='focal' needs sensor_pitch_mm, n_sensor and n_sensor_fft")
        geo["sensor_origin"] = geo["sensor_center"] - 0.5 * (plan.n_sensor - 1) * plan.sensor_pitch_mm
        pl = plan
    geo["profile"] = prof
    geo["central_zone"] = central
    return Planned(pl, f_c, centers, ctx.lo, ctx.hi, geo)


@register
class Focal(Propagation):
    """The focal method: the field's reference wave and the DOE's diffraction orders handled analytically,
    two matrix products to a sensor-side grid, one FFT there and a matrix DFT to the nodes
    (:class:`rwwarp.wave.focal.FocalPropagator`). The DOE enters as the orders' factor the caller applies
    first (:meth:`RayWave.doe_orders_factor`); the circular pupil's rim cells are traced by their part."""

    name = "focal"
    torch_path = "focal"
    doe_in_propagator = False
    rim_weighted = True
    per_source_plans = True

    def plan(self, ctx):
        return plan_focal_batch(ctx)

    def estimate(self, plan, n_sources, size, gauss_nodes):
        S, m = int(n_sources), int(size) * int(gauss_nodes)
        mem, flops = wave_plane_cost(plan, S)
        ns, nf, n = plan.n_sensor, plan.n_sensor_fft, plan.n_grid
        mem += S * (2 * ns * n * 16 + n * ns * 16 + 3 * nf * nf * 16 + 2 * nf * m * 16 + nf * m * 16 + m * m * 16)
        flops += S * (8.0 * (n * n * ns + ns * ns * n) + 5.0 * nf * nf * math.log2(max(nf * nf, 2))
                      + 8.0 * (nf * nf * m + nf * m * m))
        return {"memory_bytes": int(mem), "flops": float(flops)}

    def explain_grids(self, plan):
        return (super().explain_grids(plan) + f"sensor grid {plan.n_sensor}^2 at {plan.sensor_pitch_mm * 1e3:.4g} um, "
                f"FFT {plan.n_sensor_fft}^2, ")

    def operator(self, rw, distance_mm=None, precision="double"):
        return rw.focal_operator(distance_mm, precision)

    def pixels(self, rw, field, precision="double", to_host=True):
        return rw.focal_intensity(field, precision, to_host=to_host)

    def wave_step_sizes(self, plan, rw, pitch, extra):
        # the focal rule (rwwarp.wave.plan.plan_focal): >= samples / 4 rays across; no padded FFT
        ray_grid = max(plan.ray_grid, int(math.ceil(float(np.max(rw.hi - rw.lo)) / pitch / 4.0)) + 1)
        return ray_grid, plan.n_pad
