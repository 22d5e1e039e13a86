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
    # F/4 at 10 deg, 0.45 um: the beam's aberration before the DOE diffracts over d with a phase pi |d| |m - m_T|^2 /
    # lambda of 0.75 rad (the wave step's own phase error there, rwwarp.wave.wave_step.step_phase_rad on the two-step
    # plan: 0.747 rad); on axis ~1e-3 rad (no note). The edge waves take that aberration as applied at the plane (on
    # this beam that leaves the truth's error in the estimate's picture: 0.131 against 0.142, --rim-check; its 2.9x was
    # the rim's shape, test_the_f4_beam_at_10_deg_and_045um_against_its_stored_truth)
    off, on = _plan_error(1.0, 10.0, 0.45, "two-step"), _plan_error(1.0, 0.0, 0.45, "two-step")
    assert "diffracts again over d (phase up to 0.75 rad)" in off["note"]
    # the step itself propagates over d stretched by its rim rays' obliquity (rwwarp.wave.wave_step.rim_obliquity,
    # a mean of (1 / m_z)(1 + (n.m_t)^2 / m_z^2) around the rim), so its own phase is the note's 0.747 rad times a
    # factor between 1 and the steepest rim ray's 1 / m_z^3: at F/4 and 10 deg tan(theta) <= tan(10 deg) + 1 / 8 =
    # 0.301, 1 / m_z^3 <= 1.139, bound 1.145 (measured 0.787 rad, 1.054x)
    assert 0.747 <= off["step_phase_rad"] <= 0.747 * 1.145
    assert "diffracts again" not in on["note"] and on["step_phase_rad"] < 0.1


def _stored_row(name: str, w_um: float, field_deg: float, a_mm: float = 1.0) -> dict:
    """The stored truth's row of ``perf/results/<name>.json`` (``perf/model_error_a489.py``: ``_a489_truth.py``'s wave
    through the real lens, numpy, no rwwarp code) at the wavelength, field and stop radius, with its provenance."""
    import json
    from pathlib import Path
    d = json.loads((Path(__file__).resolve().parents[2] / "perf" / "results" / f"{name}.json").read_text())
    row = next(r for r in d["rows"] if (r["wavelength_um"], r["field_deg"], r["stop_radius_mm"]) == (w_um, field_deg, a_mm))
    # provenance: the truth's commit, its sampling (1 um grid, 1 um WPM slices) and the machine that ran it
    assert row["commit"] and d["device"] and row["pitch_mm"] == 1e-3 and row["slice_mm"] == 1e-3
    return row


def test_the_f4_beam_at_10_deg_and_045um_against_its_stored_truth():
    # F/4, 10 deg, 0.45 um (every order of the wrapped relief; N_F 140.6, the plan's rim slope 34 rad): the truth's
    # measured error 0.131 of its peak (perf/results/model_error_a489_wavelengths.json, commit 0ceabf5: 72 CPU s,
    # refined: its change 1.5e-2 of its peak, 0.147; the asphere's zone traced: 0.151), with the DOE's main order alone
    # 0.142 (..._main_order.json). The estimate on a circle of radius beam_r (half the footprint's smaller extent) read
    # 0.384, 2.93x / 2.71x; the beam's footprint there is not that circle (the pupil's rim imaged: 0.977-1.030 of beam_r)
    # and the edge waves summed on the imaged rim read 0.171: 1.30x / 1.20x (the estimate's own picture, the
    # footprint's amplitude diffracted over d by a 2-D FFT with the traced phase, reads 0.131 against the main-order
    # truth's 0.142 on the real footprint and 0.326 on the circle: perf/model_error_a489.py --rim-check). Held out:
    # nothing set on it. The claim is the factor 2
    row = _stored_row("model_error_a489_wavelengths", 0.45, 10.0)
    main = _stored_row("model_error_a489_wavelengths_main_order", 0.45, 10.0)
    me = _plan_error(1.0, 10.0, 0.45, "focal")
    assert 0.5 <= me["estimate"] / row["measured"] <= 2.0, (me["estimate"], row["measured"])
    assert 0.5 <= me["estimate"] / row["measured_front_geometric"] <= 2.0
    assert 0.5 <= me["main_estimate"] / main["measured"] <= 2.0, (me["main_estimate"], main["measured"])


def test_the_estimates_rim_is_the_stops_rim_traced_by_the_truth():
    # the rim the estimate sums its edge waves on (rwwarp's pilot rays' pupil-to-plane map, a polynomial evaluated on
    # the pupil's rim) against the stop's rim traced to the DOE plane by the truth's own ray trace (_a489_truth.py's
    # A489.trace: numpy, no rwwarp code): F/4 at 10 deg, 0.45 um. Measured: radii 0.9772-1.0301 of beam_r (truth) and
    # 0.9773-1.0302 (estimate), 5.6e-5 apart at most (the bound 2e-4: the map's degree-4 fit over the pilot's 31 x 31
    # grid); the circle the estimate took before is 1 (2.3e-2 off at the most)
    from rwwarp.wave import model_error as mod
    from rwwarp.wave.edge_wave import rim_radius
    got = {}
    orig = mod._rim_harmonics

    def spy(uv, xy, xc, beam_r):
        got.update(xc=np.asarray(xc, float), beam_r=beam_r, rim=orig(uv, xy, xc, beam_r))
        return got["rim"]
    mod._rim_harmonics = spy
    try:
        mod._MEMO.clear()
        _plan_error(1.0, 10.0, 0.45, "focal")
    finally:
        mod._rim_harmonics = orig
        mod._MEMO.clear()
    lens = A489(a_mm=1.0, coeffs=COEFFS, lam_mm=0.45e-3)
    t = np.linspace(0.0, 2 * np.pi, 180, endpoint=False)
    xt, yt, _ = lens.trace(np.cos(t), np.sin(t), np.radians(10.0), lens.zD)
    # the truth's field lies along +x, rwwarp's along +y: rwwarp's (x, y) = the truth's (y, x)
    u = (np.stack([yt, xt], 1) - got["xc"]) / got["beam_r"]
    rho_truth = np.hypot(u[:, 0], u[:, 1])
    rho_est = rim_radius(got["rim"], np.arctan2(u[:, 1], u[:, 0]))
    assert np.max(np.abs(rho_est - rho_truth)) < 2e-4, np.max(np.abs(rho_est - rho_truth))
    assert np.max(np.abs(rho_truth - 1.0)) > 1e-2          # the footprint is not the circle
