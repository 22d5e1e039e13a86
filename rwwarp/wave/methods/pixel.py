"""``pixel``: pixels many Airy radii wide (:mod:`rwwarp.wave.pixel_scale`): the sensor field as the rays' plane
waves (Debye) or the Kirchhoff sum of the rays' wave-plane samples (:mod:`rwwarp.wave.pixel_kirchhoff`), the pixel
box applied analytically; no wave-plane field on a grid. Planned beside the window plan the ASM makes
(:func:`rwwarp.wave.pixel_scale.consider_pixel`, called by the planner where ``"pixel"`` is asked for or
``"auto"`` may choose it)."""
from __future__ import annotations

from .registry import Propagation, register


@register
class Pixel(Propagation):
    """The pixel-scale method (:func:`rwwarp.wave.pixel_scale.pixel_psf`): its own ray trace, no wave-plane field,
    nothing to differentiate or pack; a lens with a DOE that is not blank is refused."""

    name = "pixel"
    forms_field = False
    packable = False
    planned_beside = True

    def plan(self, ctx):
        # the window plan it is compared with and planned beside (consider_pixel switches the batch to it)
        from .asm import plan_window
        return plan_window(ctx)

    def consider(self, rw, explicit, pilot, tolerance, memory_budget_bytes):
        from ..pixel_scale import consider_pixel
        return consider_pixel(rw, explicit, pilot["pos_s"], pilot["dir_s"], pilot["ok"], pilot["carrier"],
                              pilot["centers"], pilot["beam_width_mm"], pilot["rays_per_sample"], tolerance,
                              memory_budget_bytes, model=pilot.get("model_error"))

    def estimate(self, plan, n_sources, size, gauss_nodes):
        from ..pixel_scale import pixel_cost
        return pixel_cost(plan, n_sources, size)

    def explain_grids(self, plan):
        f = plan.pixel_field
        if not f:
            return (f"sensor grid {plan.n_sensor}^2 at {plan.sensor_pitch_mm * 1e3:.4g} um, "
                    f"FFT {plan.n_sensor_fft}^2, ")
        from ..pixel_scale import NUFFT_OVERSAMPLE
        kir = f["form"] == "kirchhoff" and f.get("origins")
        return (f"sensor grid {plan.n_sensor}^2 at {plan.sensor_pitch_mm * 1e3:.4g} um, {f['form']} sensor field in "
                + (f"{f['near']} tiles of {f['tile']}^2" if kir else f"{f['tiles']} x {f['tiles']} tiles of {f['tile']}^2")
                + (" (near the spot, Debye elsewhere)" if f.get("reach_mm") is not None else "")
                + f", {f['vectors']} NUFFT(s) a tile (FFT "
                f"{NUFFT_OVERSAMPLE * f['tile']}^2), ")

    def pixels(self, rw, field, precision="double", to_host=True):
        from ..pixel_scale import pixel_psf
        return pixel_psf(rw)
