"""perf/model_vs_wave_path.py (issue 27): its PSF measures, its rendering and its one-step vs wave-path
measurement, each against an independent reference.

* the RMS and 80 % encircled-energy radii of a pixel-integrated Gaussian against the Gaussian's own
  ``sqrt(2) sigma`` and ``sigma sqrt(-2 ln 0.2)``;
* the rendering against ``scipy.ndimage`` (a delta PSF returns the crop; a Gaussian PSF equals
  ``gaussian_filter`` with mirror edges, where the kernel holds all but ~1e-9 of the Gaussian);
* the script's one-step vs wave-path difference (and, with ``grid_check``, that it is the step's and not the
  wave path's grid's) on the calibrated thin-lens scene (``_wave_truth.thin_lens_doe``,
  DOE 20 mm before the sensor, where the independent Gauss-Hankel truth puts the one-step error at 5.0e-3 and the
  wave step within 2.4e-4 of it: docs/accuracy.md) against the model-error estimate, within the documented
  factor 2.
"""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "perf"))
import model_vs_wave_path as mvw   # noqa: E402

from _wave_truth import thin_lens_doe   # noqa: E402


def _pixel_gaussian(n, sigma_px, shift=(0.0, 0.0)):
    """A unit-power Gaussian (sigma in pixels) integrated over the pixels of an n x n patch (erf differences)."""
    from scipy.special import erf
    e = np.arange(n + 1) - n / 2.0 - 0.5   # pixel edges, centre pixel n // 2 at 0 (n odd)
    gx = np.diff(0.5 * erf((e - shift[0]) / (math.sqrt(2) * sigma_px)))
    gy = np.diff(0.5 * erf((e - shift[1]) / (math.sqrt(2) * sigma_px)))
    return np.outer(gy, gx)


def test_rms_and_ee80_radius_of_a_gaussian():
    pixel_mm, sigma = 2e-3, 4.0
    a = _pixel_gaussian(63, sigma, shift=(0.3, -0.7))
    s_um = sigma * pixel_mm * 1e3
    # RMS radius about the centroid: sqrt(2) sigma; the pixel-centre moments of box integrals add p^2 / 12 per
    # axis (the box's variance), so sqrt(2 sigma^2 + p^2 / 6) exactly up to the patch's truncation (~1e-50);
    # measured 1.9e-13 (the erf differences' rounding)
    want = math.sqrt(2 * s_um ** 2 + (pixel_mm * 1e3) ** 2 / 6)
    assert mvw.rms_radius_um(a, pixel_mm) == pytest.approx(want, rel=1e-11)
    # EE80: sigma sqrt(-2 ln 0.2) for the continuous Gaussian; the function spreads each pixel's power uniformly
    # (the box blur) and interpolates on 1/8 px: measured 0.55 % here (4 px sigma), so 1 %
    assert mvw.ee_radius_um(a, pixel_mm) == pytest.approx(s_um * math.sqrt(-2 * math.log(0.2)), rel=1e-2)


def test_render_against_scipy():
    from scipy.ndimage import gaussian_filter
    rng = np.random.default_rng(3)
    crops = rng.random((2, 3, 40, 40))
    delta = np.zeros((3, 15, 15))
    delta[:, 7, 7] = 2.0          # normalised to unit sum by render
    assert np.allclose(mvw.render(crops, delta), crops, atol=1e-12)
    # a sampled Gaussian kernel of sigma 1.5 px on 31 px (15 px = 10 sigma: truncation ~1e-22) against scipy's
    # Gaussian filter ('mirror' = numpy's 'reflect'); scipy truncates at 4 sigma by default: truncate=10
    x = np.arange(31) - 15
    g = np.exp(-0.5 * (x / 1.5) ** 2)
    k = np.outer(g, g)
    out = mvw.render(crops, np.stack([k] * 3))
    ref = np.clip(np.stack([gaussian_filter(crops[:, c], sigma=(0, 1.5, 1.5), mode="mirror", truncate=10.0)
                            for c in range(3)], 1), 0, 1)
    assert np.max(np.abs(out - ref)) < 1e-10   # FFT convolution's rounding, ~1e-15


def test_one_step_vs_wave_path_on_the_calibrated_scene():
    # A = 5 mm, DOE 3 rho^4, 20 mm before the sensor, 0.5 um pixels: the chart's scene (perf/model_error_chart.py),
    # whose independent truth gives the one-step error 5.0e-3 with the wave step 2.4e-4 from the truth; the
    # estimate 5.6e-3 was calibrated against it (within a factor 2 for held-out scenes)
    lens = thin_lens_doe(20.0, 5.0, (0.0, 3.0), pixel=0.5e-3)
    kw = dict(size=48, pixel_mm=0.5e-3, nyquist_safety=2.0, rays_per_sample=1.0, focal_patch_tol=1e-5,
              pixel_values="flux")
    row = mvw.one_psf(lens, (0.0, 0.0), 0.55, None, kw, grid_check=True)
    assert row["two_step_method"] == row["auto_method"]
    assert row["wave_step_mm"] > 0
    r = row["estimate"] / row["max_diff_over_peak"]
    assert 0.5 < r < 2.0, row
    # the truth's one-step error (5.0e-3) against the difference measured here (4.8e-3): equal up to the wave
    # step's own error against the truth, 2.4e-4, so 2x that
    assert abs(row["max_diff_over_peak"] - 5.0e-3) < 5.0e-4, row
    assert row["auto_tolerance_adds_step"] == (row["estimate"] > mvw.TOLERANCE)
    # the difference is the step's, not the wave path's finer grid: the one-step PSF on the wave path's plan moved
    # by 2.3e-7 (measured), so 1e-6
    assert row["grid_vs_one"] < 1e-6, row
    assert abs(row["grid_vs_two"] - row["max_diff_over_peak"]) < 1e-6, row
