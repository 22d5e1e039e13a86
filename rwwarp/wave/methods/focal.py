"""``focal``: the reference wave handled analytically (:mod:`rwwarp.wave.focal`,
:class:`rwwarp.wave.focal.FocalPropagator`): its planning (the DOE orders the beam carries, the carrier and patch
centre after the main order, the wave-plane and sensor-side grids of :func:`rwwarp.wave.plan.plan_focal`), its
cost and its pixels. Lengths in mm."""
from __future__ import annotations

import math

import numpy as np

from ..sensor_grid import snap_centers
from .asm import wave_plane_cost
from .main_order import doe_orders, main_order_centres
from .registry import Planned, Propagation, register


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
