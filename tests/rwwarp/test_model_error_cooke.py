"""The ray-wave model's own error on the Cooke hybrid of the paper's Cooke experiment against a wave-exact truth
(issue 27).

The truth (``_cooke_truth.py`` beside this file: the geometric field on the stop's plane cut by the hard disc, then
the exact angular spectrum and the WPM through the last element to the DOE plane, 32 mm behind the stop; numpy, no
rwwarp code; its docstring states the equations) and its one-step model (the geometric field traced to the DOE plane)
share the DOE and the exact angular spectrum to the sensor. ``perf/model_error_cooke.py`` runs the cases (0 and 5
deg, their checks; ``perf/results/model_error_cooke.json``).

The reduced case here: the experiment's lens file (``torch_bridge/configs/lenses/cooke_hybrid.json``) stopped down to
a 3 mm entrance pupil (the stop's radius 1.14 mm; the file's F/4 needs ~6000^2 samples and ~700 WPM slices), on the
axis (there the physical iris and rwwarp's entrance-pupil disc cut the same rays), 0.55 um, the DOE's quadratic term
that focuses on the sensor (-678 rho^2 rad, rho = r / 4 mm), the grid's pitch 2 um (the base runs' 1.5 um: the beam's
NA at the DOE is 0.03, the 2 um grid's band reaches 0.14) and a 0.2 mm margin (0.3 mm there): 50 s on 2 shared CPU cores
(the truth ~40 s of it; one module-scope fixture). The truth is not converged in its pitch on the axis (2.1 / 2.5 /
3.1e-3 at 2 / 1.5 / 1 um) nor in its WPM slice at 5 deg (docs/accuracy.md, "The Cooke's own beams against a truth"):
no off-axis case here.
"""
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

import rwwarp as rw

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _cooke_truth import LENS_FILE, Cooke, measured_error, truth_and_model  # noqa: E402

EPD = 3.0


def _rw_lens(coeffs):
    """The experiment's lens file with a 3 mm entrance pupil and the truth's DOE (rad on its 4 mm radius)."""
    lens = rw.load_lens(str(LENS_FILE))
    lens.entrance_pupil_diameter = EPD
    lens.surfaces[-1].profile = {"kind": "even_poly", "norm_radius": 4.0, "coefficients": list(coeffs)}
    return lens


@pytest.fixture(scope="module")
def reduced():
    lens = Cooke(epd_mm=EPD)
    T, M, info = truth_and_model(lens, 0.0, h=2.0e-3, dz=1e-3, margin=0.2, patch_pitch=0.5e-3)
    return lens, T, M, info


def test_the_truth_keeps_the_power_through_the_last_element(reduced):
    # the angular spectrum is unitary on its band and the WPM's slices keep |U|^2 but for the sub-slice phase;
    # measured (base sampling, perf/results/model_error_cooke.json): DOE plane / stop 1.00020 (the truth), 0.99967 (the
    # geometric model: its rim samples' share of the cell). A lost or doubled slice, a wrong medium in a zone or a
    # window moved by the wrong number of samples moves these by > 1e-2
    _, _, _, info = reduced
    assert info["power_doe_truth"] / info["power_iris"] == pytest.approx(1.0, abs=2e-3)
    assert info["power_doe_model"] / info["power_iris"] == pytest.approx(1.0, abs=2e-3)


def test_the_estimate_against_the_truth_on_the_axis(reduced):
    # measured: the model's own error 2.10e-3 of the truth's peak at this sampling (2.47e-3 at the base runs' 1.5 um
    # pitch and 0.3 mm margin, 3.09e-3 at 1 um: the truth is not converged in its pitch; the smooth-pupil control is
    # 1.0e-3); the planner's estimate (what --explain prints) 1.807e-3: 0.86x (0.73x / 0.58x). Held out (nothing tuned
    # on the Cooke); the claim is the factor 2, asserted at this sampling; the bounds on the error hold the 2 and 1.5 um
    # figures with ~1.2x room (this test's sampling is what it computes)
    lens, T, M, _ = reduced
    err = measured_error(T, M)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est = rw.plan_psf(_rw_lens(lens.coeffs), 0.0, 0.55, size=32, pixel_mm=1e-3, method="focal").model_error
    assert 1.5e-3 < err < 3.0e-3, err
    assert 0.5 <= est["estimate"] / err <= 2.0, (est["estimate"], err)


def test_rwwarps_psfs_against_the_truth_on_the_axis(reduced):
    # rwwarp's one-step PSF (method "auto": focal) and its wave path (tolerance 1e-3: the estimate 1.8e-3 exceeds it,
    # the wave step runs over 13.7 mm) on 32 px of 1 um, |U|^2 per pixel, against the truth's pixels (3 x 3
    # Gauss-Legendre nodes a pixel, over the entering power pi (EPD / 2)^2). Measured at the base sampling (1.5 um,
    # perf/results/model_error_cooke.json): the one-step PSF 2.39e-3 of the truth's largest pixel (the numpy one-step
    # model's pixels 1.4e-4 from it: two independent one-step models agree), the wave path 1.15e-3 (0.48x); at this
    # test's 2 um: 1.94e-3 and 1.46e-3 (0.75x). The truth's own floor at this level is ~1e-3 (the smooth-pupil
    # control 1.0e-3 on the axis), so the wave path's gain is measured only roughly. Bounds: the models' agreement
    # 4e-4 (~3x the base figure), the wave path 2.2e-3 (1.5x this sampling's), and below 0.9x the one-step error
    lens, _, _, info = reduced
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        one = rw.psf(_rw_lens(lens.coeffs), 0.0, 0.55, size=32, pixel_mm=1e-3, method="auto", pixel_values="intensity")
        two = rw.psf(_rw_lens(lens.coeffs), 0.0, 0.55, size=32, pixel_mm=1e-3, method="auto", pixel_values="intensity",
                     tolerance=1e-3)
    assert two.plan["wave_step_mm"] > 0 and not one.plan.get("wave_step_mm")
    px, py = one.coords_mm()
    T, M = info["sensor"](py, px, 1e-3, 3)
    scale = 1e-6 / (np.pi * (0.5 * EPD) ** 2)
    T, M = T * scale, M * scale
    e_one = float(np.max(np.abs(one.data.T - T)) / T.max())
    e_two = float(np.max(np.abs(two.data.T - T)) / T.max())
    e_models = float(np.max(np.abs(one.data.T - M)) / M.max())
    assert e_models < 4e-4, e_models
    assert e_two < 2.2e-3, (e_one, e_two)
    assert e_two < 0.9 * e_one, (e_one, e_two)
