"""The model-error estimate on the A489 + DOE's own beams against a wave-exact truth through the real lens (issue 27).

The truth (``_a489_truth.py`` beside this file: the stop's disc propagated as a wave through the asphere, the glass
and the rear surface, written from the equations, no rwwarp code; its docstring states them) and the one-step model
(the geometric field traced to the DOE plane) share the DOE and the exact angular spectrum to the sensor; their
difference is the model's own error. ``perf/model_error_a489.py`` runs the full cases (F/4, F/8; 0, 5, 10 deg).
The reduced case here: the stop radius 0.5 mm (F/8), on axis, 0.55 um, the DOE 600 rho^2 + 200 rho^4 rad (rho = r /
1.5 mm), the grid's pitch 1.5 um, the WPM's slice 1 um.
"""
import warnings

import numpy as np
import pytest

import rwwarp as rw

from _a489_truth import A489, measured_error, truth_and_model

COEFFS = (600.0, 200.0)


def _plan_error(a_mm: float, field_deg: float, w_um: float, method: str) -> dict:
    """The planner's model-error record (what --explain prints) of the bundled A489 + DOE stopped down to an
    ``a_mm`` stop radius (mm) with the tests' DOE (``COEFFS`` over a 1.5 mm normalisation radius), 64 px."""
    lens = rw.load_lens("a489_doe")
    lens.surfaces[0].semi_diameter = a_mm
    lens.surfaces[3].profile = {"kind": "even_poly", "norm_radius": 1.5, "coefficients": list(COEFFS)}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return rw.plan_psf(lens, field_deg, w_um, size=64, method=method).model_error


@pytest.fixture(scope="module")
def reduced():
    lens = A489(a_mm=0.5, coeffs=COEFFS)
    T, M, info = truth_and_model(lens, 0.0, h=1.5e-3, dz=1e-3, front="wave")
    return lens, T, M, info


def test_the_truth_keeps_the_power_through_the_lens(reduced):
    # the angular spectrum is unitary on the band and the WPM's slices keep |U|^2 but for the sub-slice phase:
    # measured: DOE plane / stop 0.99893 (the rear window's crop took 1.0e-3: the edge's widest-angle light), the
    # geometric model 0.99827 (its rim samples' share of the cell); a lost or doubled slice, a wrong transfer
    # function's sign in the glass, or a window moved by the wrong number of samples moves these by > 1e-2
    _, _, _, info = reduced
    assert info["power_doe_truth"] / info["power_stop"] == pytest.approx(1.0, abs=3e-3)
    assert info["power_doe_model"] / info["power_stop"] == pytest.approx(1.0, abs=3e-3)
    assert info["crop_loss"] < 3e-3
    assert info["doe_clipped"] == 0.0


def test_without_an_edge_the_truth_is_geometric_optics():
    # the stop's amplitude a cos^2 over its whole radius (no edge to diffract): the wave through the real asphere,
    # glass and rear surface against the traced geometric field, both with the DOE, on the spot: measured 7.8e-3 of
    # the peak (the smooth pupil's own diffraction included), against 0.54 with the hard stop. A wrong surface sag,
    # index, refraction or a lateral offset between the planes' windows shows here as a difference of order 1
    lens = A489(a_mm=0.5, coeffs=COEFFS)
    T, M, _ = truth_and_model(lens, 0.0, h=1.5e-3, dz=1e-3, front="wave", soft=1.0)
    assert measured_error(T, M) < 1.6e-2


def test_the_estimate_against_the_truth_on_the_reduced_case(reduced):
    # the hard stop: measured 0.537 of the peak (N_F 30.4, the plan's rim slope 18.9 rad); the truth moved by 5.7e-3
    # of its peak with its pitch and slice halved (perf/model_error_a489.py). The planner's estimate (what --explain
    # prints) reads 0.539: 1.00x. Held out (nothing tuned on it); the claim is a factor 2, the bound below 1.25x
    _, T, M, _ = reduced
    err = measured_error(T, M)
    est = _plan_error(0.5, 0.0, 0.55, "focal")["estimate"]
    assert 0.4 < err < 0.7
    assert 0.5 <= est / err <= 2.0, (est, err)
    assert 0.8 <= est / err <= 1.25, (est, err)


@pytest.mark.slow
def test_the_front_zone_carries_about_one_percent_of_the_error(reduced):
    # the asphere's sag zone (stop -> 0.13 mm) traced geometrically instead of the WPM: the edge's diffraction over
    # it is ~1 % of the reduced distance (0.1 mm of air and <= 0.03 mm of glass at the stop's scale, against ~15 mm);
    # measured 0.5329 against 0.5366 (0.7 %)
    lens, T, M, _ = reduced
    Tg, Mg, _ = truth_and_model(lens, 0.0, h=1.5e-3, dz=1e-3, front="geometric")
    e, eg = measured_error(T, M), measured_error(Tg, Mg)
    assert abs(eg / e - 1) < 0.02
    assert np.isfinite(Tg).all()


@pytest.mark.parametrize("w_um", [0.45, 0.65])
def test_the_estimate_with_the_wrapped_reliefs_orders_at_other_wavelengths(w_um):
    # F/8 on axis at 0.45 / 0.65 um: the truth takes the glass's index there and the DOE as its wrapped relief
    # s wrap(phi0) (s = 1.237 / 0.840: every order, sinc^2(m - s) of the light in order m; _a489_truth.py). Held out:
    # no constant of the estimate was set on these (nor on any A489 case). Measured: the error with every order 0.224 /
    # 0.734 of the truth's peak, with the main order alone (exp(i phi0)) 0.121 / 0.167: the other orders' light on the
    # patch changes it by 1.9x / 4.4x. The estimate sums every order that lights the patch coherently (each order's
    # rim edge wave turned by its own slope's Fresnel phase, the error over the peak of all of them): 0.201 / 0.756,
    # 0.90x / 1.03x; the estimate before (the main order's error over its own peak plus an on-axis orders term) read
    # 0.527 / 0.167, 2.35x / 0.23x. The truth moved by 8.3e-3 / 9.4e-3 of its peak with its pitch and slice halved
    # (the measured error by 1.1 % / 0.5 %; the smooth-pupil control 2.1e-2 / 3.0e-2: perf/model_error_a489.py
    # --wavelengths-f8). The claim is the factor 2, asserted first; the bound 0.8-1.25 (the reduced case's above) holds
    # the measured 0.90 / 1.03 with twice their distance from 1 and the truth's 1 % on top
    lens = A489(a_mm=0.5, coeffs=COEFFS, lam_mm=w_um * 1e-3)
    T, M, _ = truth_and_model(lens, 0.0, h=1.5e-3, dz=1e-3, front="wave")
    err = measured_error(T, M)
    lens.doe_scale = 1.0                                   # the main order alone: a diagnostic
    T1, M1, _ = truth_and_model(lens, 0.0, h=1.5e-3, dz=1e-3, front="wave")
    err_main = measured_error(T1, M1)
    me = _plan_error(0.5, 0.0, w_um, "focal")
    # the other orders matter in the truth (measured 1.9x / 4.4x)
    assert err / err_main > 1.5, (err, err_main)
    assert 0.5 <= me["estimate"] / err <= 2.0, (me, err)
    assert 0.8 <= me["estimate"] / err <= 1.25, (me, err)
    # the main order's own part against the main-order truth: measured 1.03x / 1.00x
    assert 0.8 <= me["main_estimate"] / err_main <= 1.25, (me, err_main)
    assert me["estimate"] == pytest.approx(me["main_estimate"] + me["orders_estimate"])


def test_the_note_names_the_beams_own_aberration_where_it_diffracts_again():
    # F/4 at 10 deg (0.45 um: the estimate 2.9x the measured error, the one A489 case outside the factor 2): the beam's
    # aberration before the DOE diffracts over d with a phase pi |d| |m - m_T|^2 / lambda of 0.75 rad (the wave step's
    # own phase error there, rwwarp.wave.wave_step.step_phase_rad on the two-step plan: 0.747 rad); on axis ~1e-3 rad
    # (no note). The edge waves take that aberration as applied at the plane
    off, on = _plan_error(1.0, 10.0, 0.45, "two-step"), _plan_error(1.0, 0.0, 0.45, "two-step")
    assert "diffracts again over d (phase up to 0.75 rad)" in off["note"]
    assert off["step_phase_rad"] == pytest.approx(0.75, abs=0.01)
    assert "diffracts again" not in on["note"] and on["step_phase_rad"] < 0.1
