"""Sampling plans: how big, how fine and how many rays a ray-wave PSF needs (adaptive modelling).

A plan is chosen per batch of point sources from a cheap pilot trace (a coarse pupil grid):

* window: the beam footprint on the DOE plane plus a margin of ``margin_samples`` samples;
* pitch: Nyquist for the field after the DOE with the chief ray's carrier removed,
  ``pitch <= 1 / (2 * safety * (max |f_field - f_chief| + max |f_doe|))`` (cycles/mm), and at most half
  the DOE feature size for pixel-map DOEs (the paper's choice);
* padding: the band-limited ASM needs a period ``L >= window + sensor patch`` (shifted band limit),
  rounded up to a VkFFT-friendly length (2^a 3^b 5^c 7^d);
* rays: ``rays_per_sample`` rays per sample along each axis across the footprint.

``plan="paper"`` reproduces the paper's fixed grid: the whole DOE aperture at half the DOE
feature size (1 um features -> 0.5 um), padded 2x, output on the same grid.
Every choice is recorded with its reason in :attr:`Plan.reasons`.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field, asdict


from .errors import SamplingWarning


def nice_fft_length(n: int) -> int:
    """Smallest integer >= n whose prime factors are all in {2, 3, 5, 7} (fast for VkFFT)."""
    from .propagate import next_fft_size
    return next_fft_size(n)


@dataclass
class Plan:
    """Sampling of one batch: ``pitch_mm`` of the DOE-plane grid, ``n_grid`` samples per side,
    ``n_pad`` FFT length, ``ray_grid`` pupil samples across the diameter, ``reasons`` (text)."""

    pitch_mm: float
    n_grid: int
    n_pad: int
    ray_grid: int
    kind: str = "auto"
    output_on_grid: bool = False
    reasons: list = field(default_factory=list)

    def to_dict(self) -> dict:
        return asdict(self)

    def explain(self) -> str:
        """Human-readable summary of the plan and why."""
        head = (f"plan {self.kind}: pitch {self.pitch_mm * 1e3:.4g} um, grid {self.n_grid}^2, "
                f"FFT {self.n_pad}^2, pupil rays {self.ray_grid} across")
        return "\n".join([head] + [f"  - {r}" for r in self.reasons])


def check_explicit(plan: Plan, needed_pitch_mm: float, needed_pad: int, window_mm: float):
    """Warn (:class:`SamplingWarning`) where an explicit plan violates a sampling criterion."""
    if plan.pitch_mm > needed_pitch_mm * 1.0001:
        warnings.warn(f"Nyquist criterion violated: pitch {plan.pitch_mm * 1e3:.4g} um > "
                      f"{needed_pitch_mm * 1e3:.4g} um needed by the local wavefront slope and DOE features; "
                      f"the field will alias. Fix: pitch_mm <= {needed_pitch_mm:.4g} or plan='auto'",
                      SamplingWarning, stacklevel=3)
    if plan.n_pad < needed_pad:
        warnings.warn(f"band-limit (padding) criterion violated: FFT length {plan.n_pad} < {needed_pad} "
                      f"needed for the window plus the sensor patch; wrap-around will alias. "
                      f"Fix: n_pad >= {needed_pad} or plan='auto'", SamplingWarning, stacklevel=3)
    if plan.n_grid * plan.pitch_mm < window_mm * 0.999:
        warnings.warn(f"window criterion violated: grid {plan.n_grid} x {plan.pitch_mm * 1e3:.4g} um = "
                      f"{plan.n_grid * plan.pitch_mm:.4g} mm does not cover the beam footprint "
                      f"{window_mm:.4g} mm; rays outside are lost. Fix: n_grid >= "
                      f"{math.ceil(window_mm / plan.pitch_mm) + 2}", SamplingWarning, stacklevel=3)
    ray_pitch = window_mm / max(plan.ray_grid, 1)
    if ray_pitch > plan.pitch_mm * 1.0001:
        warnings.warn(f"ray density criterion violated: {plan.ray_grid} rays across a {window_mm:.4g} mm "
                      f"footprint leave samples without rays (ray spacing {ray_pitch * 1e3:.4g} um > pitch "
                      f"{plan.pitch_mm * 1e3:.4g} um). Fix: ray_grid >= {math.ceil(window_mm / plan.pitch_mm)}",
                      SamplingWarning, stacklevel=3)
