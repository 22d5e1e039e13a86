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
that focuses on the sensor (-678 rho^2 rad, rho = r / 4 mm). The truth is the guarded one (``band=120`` cycles/mm
on every free-space step, the window's margin 0.8 mm: ``_cooke_truth.truth_and_model``'s docstring; without the
guard the edge's wide-angle light wrapped round the periodic window and the error rose as the pitch fell), at a 3 um
pitch (Nyquist 167 cycles/mm, above the band): ~30 s of the truth on 2 shared CPU cores (one module-scope fixture).
Converged figures (perf/results/model_error_cooke.json, rows "guarded"; docs/accuracy.md, "The Cooke's own beams
against a truth"): on the axis the model's own error 3.39e-3 of the peak at pitches of 2 and 1.5 um (the truth moved
by 1e-6 of its peak), 3.43e-3 at this test's 3 um / 0.8 mm; no off-axis case here (its WPM slice is the costly part).
"""
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

import rwwarp as rw

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _cooke_truth import LENS_FILE, Cooke, measured_error, truth_and_model, window_guard  # noqa: E402

EPD = 3.0
SAMPLING = dict(h=3.0e-3, dz=1e-3, margin=0.8, band=120.0)     # the guarded truth, reduced (module docstring)


def _rw_lens(coeffs):
    """The experiment's lens file with a 3 mm entrance pupil and the truth's DOE (rad on its 4 mm radius)."""
    lens = rw.load_lens(str(LENS_FILE))
    lens.entrance_pupil_diameter = EPD
    lens.surfaces[-1].profile = {"kind": "even_poly", "norm_radius": 4.0, "coefficients": list(coeffs)}
    return lens


@pytest.fixture(scope="module")
def reduced():
    lens = Cooke(epd_mm=EPD)
    T, M, info = truth_and_model(lens, 0.0, patch_pitch=0.5e-3, **SAMPLING)
    return lens, T, M, info


def test_the_truth_keeps_the_power_through_the_last_element(reduced):
    # the angular spectrum is unitary on its band and the WPM's slices keep |U|^2 but for the sub-slice phase; the
    # band (120 cycles/mm) drops the edge's wide-angle light. Measured (perf/results/model_error_cooke.json,
    # "guarded"): DOE plane / iris 0.99919 / 0.99908 / 0.99940 (the truth at 2 / 1.5 / 3 um), 0.99952 / 0.99967 / 0.99927 (the
    # geometric model: its rim samples' share of the cell). A lost or doubled slice, a wrong medium in a zone or a
    # window moved by the wrong number of samples moves these by > 1e-2
    _, _, _, info = reduced
    assert info["power_doe_truth"] / info["power_iris"] == pytest.approx(1.0, abs=2e-3)
    assert info["power_doe_model"] / info["power_iris"] == pytest.approx(1.0, abs=2e-3)


def test_the_truths_window_is_guarded(reduced):
    # no plane wave of the band leaving the iris's rim (1.14 mm) re-enters the window within the DOE plane's beam
    # (0.64 mm) over the 31.6 mm to it: the guard of _cooke_truth.window_guard (0.01 mm at this sampling, 0.41 mm at
    # the 1 mm margin of the converged rows)
    lens, _, _, info = reduced
    window = info["grid_n"] * SAMPLING["h"]
    assert window_guard(SAMPLING["band"], lens.lam, lens.zD - lens.zI, window, lens.a, 0.64) > 0


def test_the_estimate_against_the_truth_on_the_axis(reduced):
    # measured: the model's own error 3.43e-3 of the truth's peak at this sampling (3.39e-3 converged: pitches 2 and
    # 1.5 um, bands 120 and 160 cycles/mm agree to 1e-6; band 90 reads 3.29e-3), the planner's estimate (what
    # --explain prints) 1.807e-3: 0.53x. Held out (nothing tuned on the Cooke); the claim is the factor 2; the bounds
    # on the error hold the converged figure and this sampling's with ~1.1x room
    lens, T, M, _ = reduced
    err = measured_error(T, M)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est = rw.plan_psf(_rw_lens(lens.coeffs), 0.0, 0.55, size=32, pixel_mm=1e-3, method="focal").model_error
    assert 3.0e-3 < err < 3.8e-3, err
    assert 0.5 <= est["estimate"] / err <= 2.0, (est["estimate"], err)


def test_rwwarps_psfs_against_the_truth_on_the_axis(reduced):
    # rwwarp's one-step PSF (method "auto": focal) and its wave path (tolerance 1e-3: the estimate 1.8e-3 exceeds it,
    # the wave step runs over 13.7 mm) on 32 px of 1 um, |U|^2 per pixel, against the truth's pixels (3 x 3
    # Gauss-Legendre nodes a pixel, over the entering power pi (EPD / 2)^2). Measured on the converged truth (2 and
    # 1.5 um, perf/results/model_error_cooke.json, "guarded"): the one-step PSF 3.33e-3 of the truth's largest pixel
    # (the numpy one-step model's pixels 1.7e-5 from it: two independent one-step models agree), the wave path
    # 2.09e-3 (0.63x: the wave step takes 37 % of the error away, not the 1e-3 it was asked for); at this test's
    # sampling (3 um): 3.37e-3, 2.13e-3 (0.63x), the models 1.4e-5. Bounds: the models' agreement 5e-5 (3x the
    # converged truth's 1.7e-5), the wave path 2.5e-3 (1.2x), below 0.75x the one-step error
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
    assert e_models < 5e-5, e_models
    assert e_two < 2.5e-3, (e_one, e_two)
    assert e_two < 0.75 * e_one, (e_one, e_two)
