"""The ray-wave model's own error (issue 27): its estimate (rwwarp.wave.model_error) against the error measured on an
independent wave-exact truth, and the wave step (rwwarp.wave.wave_step) that removes it.

The truth (a radially symmetric Gauss-Hankel angular spectrum, thin lens -> DOE -> sensor, and the geometric
"one-step" model on the same quadrature) is in ``_wave_truth.py`` beside this file, shared with
``perf/model_error_chart.py``; its docstring states the equations.
"""
import warnings

import numpy as np
import pytest

import rwwarp as rw
from rwwarp.wave import model_error as me
from rwwarp.wave.edge_wave import PupilPhase, edge_wave_error, fit_pupil_phase, radial_pupil_phase
from rwwarp.lens import Lens, Sensor, Surface

from _wave_truth import (F_MM, LAM_MM, analytic_inputs, measured_error, radial_truth, steep_band, steep_radii,
                         thin_lens_doe)
from _wave_truth import pixel_truth as _pixel_truth


# The main order's estimate (rwwarp.wave.edge_wave: the rim's edge waves on the pupil phase) has no fitted constant:
# every case is held out (the one choice made on truths, the traced amplitude's blend, was taken on steep rims: a 2.5,
# 10 mm, c rho^4, c = 10 .. 35). Measured estimate / error (before the traced rays of steep rims in brackets):
# 1.03 / 1.00 / 0.94 (a 2.5, rho^4 3 / 3 / 8 rad, 10 / 35 / 10 mm: the old law's calibration cases, not tested here;
# 0.97 / 0.99 / 0.95), 1.01 (0.99; a 2.5, rho^4 3 rad, 20 mm, N_F 152), 1.18 (1.17; defocus 2 rad, 45 mm, N_F 2045),
# 1.05 (1.06; a 1.5, rho^2 + rho^4, 35 mm, N_F 191), 1.02 (0.99; a 1.5, rho^6 3 rad, 35 mm, N_F 191). Below N_F ~ 50
# (the old law C S / N_F (1 + (S / S0)^2) read 2.27x / 4.33x / 0.81x there): 1.09 (0.92; a 1.5, 3 rho^4, 10 mm, N_F
# 20.5, S 12), 1.35 (0.90; a 1.0, 10 mm, N_F 9.1, S 12: the edge wave's ray shifts 0.21 of the radius, and the
# amplitude the traced ray brings is blended in), 1.00 (0.97; a 1.5, 4 rho^4, 14 mm, N_F 31.8, S 16).
HELD_OUT = [(2.5, 20.0, (0.0, 3.0)), (2.5, 45.0, (2.0, 0.0)), (1.5, 35.0, (-3.0, 3.0)), (1.5, 35.0, (0.0, 0.0, 3.0)),
            (1.5, 10.0, (0.0, 3.0)), (1.0, 10.0, (0.0, 3.0)), (1.5, 14.0, (0.0, 4.0))]


@pytest.mark.parametrize("a_mm,d2_mm,coeffs", HELD_OUT)
def test_estimate_is_within_a_factor_2_of_the_measured_model_error(a_mm, d2_mm, coeffs):
    err = measured_error(a_mm, d2_mm, coeffs)
    nf, slope = analytic_inputs(a_mm, d2_mm, coeffs)
    est, info = edge_wave_error(nf, radial_pupil_phase(coeffs))
    print(f"a {a_mm} d2 {d2_mm} {coeffs}: N_F {nf:.1f} S {slope:.0f} estimate {est:.3e} measured {err:.3e} "
          f"ratio {est / err:.2f} (the old scalar law {me.model_error(nf, slope) / err:.2f})")
    # the claim is a factor 2; measured 1.00 .. 1.35 over these cases (comment above)
    assert 0.5 <= est / err <= 2.0, (est, err)
    assert 0.8 <= est / err <= 1.45, (est, err)
    # a model error well above the truth's own uncertainty (the band: 3 % of the error, module docstring)
    assert err > 1e-4


# Steep rims (S 40 .. 300 rad; rwwarp.wave.edge_wave, "Steep rims"): the truth's band widened by the DOE's largest
# frequency 1.5 times over and rolled off (taper 0.3: a hard cut's end-point ringing is of the order of these weak,
# wide PSFs' errors), 4 nodes per oscillation, radii over the whole geometric spot (steep_band / steep_radii): the
# measured error moved by < 1 % against 2.5x the extra band, 5-6 nodes and half the radial step (a 2.5, 25 rho^4,
# 10 mm). Held out (the only choice made on truths, the amplitude's blend, was taken on a 2.5, 10 mm, rho^4 of
# 10 / 15 / 25 / 35 rad: 1.08 / 1.00 / 0.86 / 1.02). Measured estimate / error, now (before the traced rays):
# a 1.5, 20 mm, 25 rho^4 (N_F 54.5, S 100): 0.93 (0.39); a 1.0, 10 mm, 10 rho^4 (N_F 9.1, S 40, the ray shifted 0.7
# of the radius): 1.25 (1.03); a 1.5, 10 mm, 25 rho^4 (N_F 20.5, S 100): 0.76 (0.62); a 2.5, 10 mm, -50 rho^2 +
# 50 rho^4 (N_F 56.8, S 100): 0.71 (1.49); 25 rho^6 (S 150): 1.34 (2.01); a 1.5, 20 mm, 40 / 50 rho^4 (S 160 / 200):
# 1.02 / 1.02 (1.64 / 0.74, the latter beyond the old 180 rad sampling limit); a 2.5, 10 mm, 20 rho^8 (S 160): 1.26
# (12.5)
STEEP_HELD_OUT = [(1.5, 20.0, (0.0, 25.0)), (1.0, 10.0, (0.0, 10.0)), (1.5, 10.0, (0.0, 25.0)),
                  pytest.param(2.5, 10.0, (-50.0, 50.0), marks=pytest.mark.slow),
                  pytest.param(2.5, 10.0, (0.0, 0.0, 25.0), marks=pytest.mark.slow),
                  pytest.param(1.5, 20.0, (0.0, 50.0), marks=pytest.mark.slow),
                  pytest.param(2.5, 10.0, (0.0, 0.0, 0.0, 20.0), marks=pytest.mark.slow),
                  # S 300, the ray shifted 0.88 of the radius: 1.07 (before: beyond the sampling limit, the scalar law)
                  (1.5, 20.0, (0.0, 75.0))]


@pytest.mark.parametrize("a_mm,d2_mm,coeffs", STEEP_HELD_OUT)
def test_steep_rims_the_estimate_is_within_a_factor_2_of_the_measured_model_error(a_mm, d2_mm, coeffs):
    rho = steep_radii(a_mm, d2_mm, coeffs)
    err = measured_error(a_mm, d2_mm, coeffs, rho_mm=rho, band=steep_band(a_mm, d2_mm, coeffs, 1.5), taper=0.3, q=4.0)
    nf, slope = analytic_inputs(a_mm, d2_mm, coeffs)
    est, info = edge_wave_error(nf, radial_pupil_phase(coeffs))
    print(f"a {a_mm} d2 {d2_mm} {coeffs}: N_F {nf:.1f} S {slope:.0f} estimate {est:.3e} measured {err:.3e} "
          f"ratio {est / err:.2f}")
    assert slope >= 40
    # the claim is a factor 2; measured 0.71 .. 1.34 over these cases (comment above and beside)
    assert 0.5 <= est / err <= 2.0, (est, err)
    assert 0.6 <= est / err <= 1.6, (est, err)


def test_steep_rims_the_plans_estimate_is_within_a_factor_2_of_the_measured_error():
    # the whole chain on a steep rim (what --explain prints): rwwarp's pilot trace -> the fitted pupil phase, N_F ->
    # the traced edge waves, against the steep truth's measured error (a 1.5, 20 mm, 25 rho^4: N_F 54.5, the pilot's
    # rim slope 94 rad; measured 1.158e-1, estimate 1.078e-1, 0.93x; the same as on the analytic phase: the degree-6
    # fit holds the rho^4 phase exactly), and no note below the checked slope
    a_mm, d2_mm, coeffs = 1.5, 20.0, (0.0, 25.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        got = rw.plan_psf(thin_lens_doe(d2_mm, a_mm, coeffs), 0.0, 0.55, size=32, method="focal").model_error
    rho = steep_radii(a_mm, d2_mm, coeffs)
    err = measured_error(a_mm, d2_mm, coeffs, rho_mm=rho, band=steep_band(a_mm, d2_mm, coeffs, 1.5), taper=0.3, q=4.0)
    assert got["rim_slope_rad"] > 80 and "checked against a wave truth" not in got["note"]
    assert 0.5 <= got["estimate"] / err <= 2.0, (got["estimate"], err)


def test_the_edge_wave_estimate_vanishes_without_a_phase_and_ignores_a_tilt():
    # the derivation's premise, in the estimate: an unaberrated beam's rim diffraction is a phase at the focus
    # (measured 5.6e-6 at N_F 50: the rim's one-edge picture), and a tilt moves the PSF only
    nf = 50.0
    assert edge_wave_error(nf, radial_pupil_phase((0.0, 0.0)))[0] < 1e-4
    p4 = radial_pupil_phase((0.0, 3.0))
    tilted = PupilPhase(np.vstack([p4.powers, [[1, 0], [0, 1]]]), np.concatenate([p4.coeffs, [5.0, -3.0]]))
    e4, e4t = edge_wave_error(nf, p4)[0], edge_wave_error(nf, tilted)[0]
    # the tilt falls between the FFT grid's tilts (pi / 4 apart): measured 2 % apart
    assert e4t == pytest.approx(e4, rel=0.05) and e4 > 1e-2
    # small phase, large N_F: the edge wave's first order, E = 2 |dU| / |U| = S / (pi N_F) for a defocus on the
    # axis (U ~ 1, dU ~ -S / (2 pi N_F))
    assert edge_wave_error(2000.0, radial_pupil_phase((0.5,)))[0] == pytest.approx(1.0 / (np.pi * 2000.0), rel=0.05)
    # the fit of the pupil phase from gradients returns the phase (to rounding) from a grid inside the beam
    g = np.linspace(-0.95, 0.95, 15)
    u = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    u = u[np.hypot(*u.T) < 0.97]
    q = radial_pupil_phase((1.0, -2.0, 0.5))
    fit = fit_pupil_phase(u, np.stack(q.gradient(*u.T), 1))
    assert np.max(np.abs(fit.value(*u.T) - q.value(*u.T))) < 1e-9
    with pytest.raises(ValueError, match="Fresnel number"):
        edge_wave_error(0.0, q)
    with pytest.raises(ValueError, match="fit_pupil_phase"):
        fit_pupil_phase(u, np.full_like(u, np.nan))


def test_without_a_doe_the_geometric_field_focuses_exactly():
    # the derivation's premise: the extra Fresnel propagation is a phase at the focus; the residual is the
    # Fresnel approximation's (measured 2e-4 at N_F 57), far below the 4e-2 a 3 rad DOE makes there
    err = measured_error(2.5, 10.0, (0.0, 0.0))
    assert err < 1e-3
    assert me.model_error(*analytic_inputs(2.5, 10.0, (0.0, 0.0))) == 0.0


def test_formulas_follow_their_definitions_and_refuse_bad_input():
    assert me.reduced_distance_mm(30.0, 20.0) == pytest.approx(12.0)
    assert me.reduced_distance_mm(30.0, np.inf) == 30.0
    assert me.reduced_distance_mm(0.0, 20.0) == 0.0
    a, f, z1, lam_um = 2.5, 50.0, 40.0, 0.55
    r_w = a * (f - z1) / f
    assert me.fresnel_number(r_w, z1, f - z1, lam_um) == pytest.approx(a * a * (f - z1) / (lam_um * 1e-3 * f * z1))
    assert me.fresnel_number(r_w, 0.0, 10.0, lam_um) == np.inf
    with pytest.raises(ValueError, match="aperture_to_plane_mm"):
        me.reduced_distance_mm(-1.0, 10.0)
    with pytest.raises(ValueError, match="plane_to_focus_mm"):
        me.reduced_distance_mm(1.0, 0.0)
    with pytest.raises(ValueError, match="Fresnel number"):
        me.model_error(0.0, 1.0)


def test_the_planner_reads_the_scene_and_prints_the_estimate():
    lens = thin_lens_doe(10.0)
    pl = rw.plan_psf(lens, 0.0, 0.55, size=32, method="asm")
    nf, slope = analytic_inputs(2.5, 10.0, (0.0, 3.0))
    got = pl.model_error
    # the pilot's 31 x 31 rays: the rim ray at 0.97 of the radius reads rho dW/drho = 12 rho^4 -> 10.6..12
    assert got["fresnel_number"] == pytest.approx(nf, rel=0.03)
    assert got["rim_slope_rad"] == pytest.approx(slope, rel=0.1)
    assert got["aperture_to_plane_mm"] == pytest.approx(40.0)
    assert got["plane_to_focus_mm"] == pytest.approx(10.0, rel=1e-3)
    text = pl.explain()
    assert "model error" in text and "N_F" in text


@pytest.mark.parametrize("a_mm,d2_mm,coeffs", [HELD_OUT[0], HELD_OUT[2]])
def test_the_scene_estimate_is_within_a_factor_2_of_the_measured_error(a_mm, d2_mm, coeffs):
    # the whole chain: rwwarp's pilot trace -> N_F, rim slope -> estimate, against the truth's measured error
    # (measured estimate / error: 1.29 and 0.91)
    est = rw.plan_psf(thin_lens_doe(d2_mm, a_mm, coeffs), 0.0, 0.55, size=32, method="focal").model_error["estimate"]
    err = measured_error(a_mm, d2_mm, coeffs)
    assert 0.5 <= est / err <= 2.0, (est, err)


def test_the_wave_step_conserves_the_field_power_off_axis():
    # the ASM is unitary on the band; what leaves the widened window is the edge's light at the widest angles
    from rwwarp.psf import RayWave
    from rwwarp.trace import as_field_list
    from rwwarp.wave.wave_step import apply_wave_step
    r = RayWave(thin_lens_doe(10.0), as_field_list([0.3]), [0.55], 32, 0.5e-3, method="two-step")
    u = r.field_array()
    v = apply_wave_step(r, u)
    p0, p1 = float(np.sum(np.abs(u) ** 2)), float(np.sum(np.abs(v) ** 2))
    assert np.all(np.isfinite(v))
    assert abs(p1 / p0 - 1.0) < 2e-3, p1 / p0                  # measured 7.9e-4 lost
    assert np.max(np.abs(v - u)) > 0.1 * np.max(np.abs(u))    # the edge did change


def test_psf_warns_when_the_estimate_exceeds_the_tolerance():
    lens = thin_lens_doe(10.0)
    with pytest.warns(me.ModelErrorWarning, match=r"estimated at 0\.0\d+ .* above the tolerance 0\.001.*two-step"):
        rw.psf(lens, 0.0, 0.55, size=16, method="asm", tolerance=1e-3)
    with warnings.catch_warnings():
        warnings.simplefilter("error", me.ModelErrorWarning)
        rw.psf(lens, 0.0, 0.55, size=16, method="asm", tolerance=0.5)       # estimate 0.066 < 0.5: quiet
        p = rw.psf(lens, 0.0, 0.55, size=16, method="auto", tolerance=1e-3)   # auto takes the wave step
    assert p.plan["wave_step_mm"] == pytest.approx(8.0, rel=1e-3)
    assert any("wave step" in r and "tolerance" in r for r in p.plan["reasons"])
    with pytest.raises(ValueError, match="tolerance"):
        rw.psf(lens, 0.0, 0.55, size=16, tolerance=0.0)


@pytest.mark.parametrize("d2_mm,method", [(10.0, "asm"), (10.0, "focal"), (5.0, "focal")])
def test_wave_step_matches_the_two_step_truth(d2_mm, method):
    import rwwarp.wave.wave_step as ws
    lens = thin_lens_doe(d2_mm)
    rho = np.linspace(0.0, 0.04, 2001)
    truth, model = radial_truth(2.5, d2_mm, (0.0, 3.0), rho)
    one = rw.psf(lens, 0.0, 0.55, size=32, method=method)
    x, y = one.coords_mm()
    T, M = _pixel_truth(truth, rho, x, y, one.pixel_mm), _pixel_truth(model, rho, x, y, one.pixel_mm)
    peak = T.max()
    e_one_model, e_one = np.max(np.abs(one.data - M)) / peak, np.max(np.abs(one.data - T)) / peak
    # rwwarp's one-step PSF is the geometric model of the test (measured 3.3e-4 asm / 2.1e-4 focal at 10 mm, 2.0e-3
    # focal at 5 mm, 190 samples across the beam: its sampling) ...
    assert e_one_model < 3e-3
    # ... whose error against the truth is the model's (measured 4.2e-2 at 10 mm, 6.9e-2 at 5 mm)
    assert e_one > 2e-2
    two = rw.psf(lens, 0.0, 0.55, size=32, method="two-step") if method == "asm" else None
    if two is None:   # the wave step on the focal plan: forced through the planner's decision
        orig = ws.plan_wave_step
        try:
            ws.plan_wave_step = lambda r, tol, req, *rest, **kw: orig(r, tol, "two-step", *rest, **kw)
            # cache=None: the patched planner is not in the default cache's key (the same arguments as `one` above)
            two = rw.psf(lens, 0.0, 0.55, size=32, method="focal", cache=None)
        finally:
            ws.plan_wave_step = orig
        assert two.plan["method"] == "focal"
    assert two.plan["wave_step_mm"] == pytest.approx((F_MM - d2_mm) * d2_mm / F_MM, rel=1e-3)
    # measured (CPU): 7.5e-5 (asm, 10 mm), 7.5e-5 (focal, 10 mm), 1.2e-4 (focal, 5 mm); over the paraxial reduced
    # distance (no obliquity stretch, rwwarp.wave.wave_step): 1.8e-4 / 1.8e-4 / 2.4e-4
    e_two = np.max(np.abs(two.data - T)) / peak
    print(f"d2 {d2_mm} {method}: one-step vs model {e_one_model:.2e}, vs truth {e_one:.2e}; two-step vs truth {e_two:.2e}")
    assert e_two < 3e-4


def test_wave_step_meets_issue_27s_target_at_the_issues_error_level():
    # issue 27's scene at its own error level (perf/model_error_issue_level.py): thin lens f = 50 mm, a = 5 mm (NA
    # 0.0995), DOE 4 rho^4 5 mm before the sensor (N_F 101), 64 px of 0.5 um; method "auto" with the tolerance 1e-3
    # adds the wave step. The step propagates over the reduced distance stretched for the rim ray's obliquity
    # (rwwarp.wave.wave_step, "Obliquity": 4.5 mm x 1 / m_z^3 = 4.568 mm); over the paraxial 4.5 mm it left 1.12e-3
    # (the target's 1e-3 missed: the edge wave 1.5 NA^2 = 1.5 % short of the 9.0e-2 one-step error it removes).
    # Measured (CPU): one-step 9.0e-2, with the step 1.2e-4 (the radial truth's own step with d / m_z^3: 3.7e-5)
    lens = thin_lens_doe(5.0, 5.0, (0.0, 4.0))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        two = rw.psf(lens, 0.0, 0.55, size=64, method="auto", tolerance=1e-3)
    assert two.plan["wave_step_mm"] == pytest.approx(4.5, rel=1e-3)
    assert two.plan["model_error"]["estimate"] > 5e-2          # the one-step model's error, estimated (9.1e-2)
    x, y = two.coords_mm()
    rho = np.linspace(0.0, 1.5 * np.hypot(np.abs(x).max(), np.abs(y).max()) + two.pixel_mm, 1201)
    truth, _ = radial_truth(5.0, 5.0, (0.0, 4.0), rho)
    T = _pixel_truth(truth, rho, x, y, two.pixel_mm)
    e_two = float(np.max(np.abs(two.data - T)) / T.max())
    print(f"issue level, 5 mm: auto + tolerance 1e-3 vs truth {e_two:.2e}")
    assert e_two < 3e-4          # 2.5x the measured 1.2e-4; the paraxial distance's 1.12e-3 fails it


@pytest.mark.parametrize("name", ["cooke_triplet", "a489_doe"])
def test_the_stops_image_is_the_paraxial_exit_pupil(name):
    # without a DOE (the Cooke triplet) the stop's image in front of the wave plane is the exit pupil; the A489's
    # DOE has paraxial power only after the field is formed, so its exit pupil (through the DOE) differs and
    # the image through the refracting surfaces alone is checked against a lens without the DOE's power
    from rwwarp import io, paraxial
    lens = io.load_lens(name)
    plane = lens.wave_plane_index()
    if lens.surfaces[plane].type == "doe":
        lens = lens.with_surface(plane, profile={"kind": "even_poly", "norm_radius": 1.0, "coefficients": [0.0]})
    want = lens.vertex_z[plane] - paraxial.pupils(lens, 0.55).exit_z
    assert me.stop_to_plane_mm(lens, plane, 0.55) == pytest.approx(want, rel=1e-9)


@pytest.mark.filterwarnings("ignore::rwwarp.errors.PatchWarning")
def test_the_wave_step_respects_the_memory_budget():
    from rwwarp.wave.plan import MemoryBudgetError
    lens = thin_lens_doe(10.0)
    # the one-step plan of the method "two-step" takes (auto without a tolerance never adds the step)
    one = rw.plan_psf(lens, 0.0, 0.55, size=16, method="auto").estimate["memory_bytes"]
    two = rw.plan_psf(lens, 0.0, 0.55, size=16, method="two-step").estimate["memory_bytes"]
    assert two > one
    gb = 0.5 * (one + two) / 2 ** 30            # room for the one-step plan only
    with pytest.raises(MemoryBudgetError, match="wave step"):
        rw.psf(lens, 0.0, 0.55, size=16, method="two-step", memory_budget_gb=gb)
    with pytest.warns(me.ModelErrorWarning):     # auto leaves the step out, says why, and warns
        p = rw.psf(lens, 0.0, 0.55, size=16, method="auto", memory_budget_gb=gb, tolerance=1e-3)
    assert p.plan["wave_step_mm"] is None and any("left out" in r for r in p.plan["reasons"])


def _fft2(a):
    """2-D FFT of the 2-D truths on every core (scipy.fft's workers; numpy's is single-threaded)."""
    import scipy.fft
    return scipy.fft.fft2(a, workers=-1)


def _ifft2(a):
    import scipy.fft
    return scipy.fft.ifft2(a, workers=-1)


def _disc_2d(X, Y, xc, yc, r, h):
    """The disc of radius ``r`` centred at ``(xc, yc)`` on the grid, its rim samples weighted by the share of their
    cell inside it (24 x 24 sub-samples)."""
    R = np.hypot(X - xc, Y - yc)
    ap = (R < r).astype(float)
    rim = np.abs(R - r) < 1.5 * h
    o = (np.arange(24) + 0.5) / 24 - 0.5
    sub = np.hypot(X[rim][:, None, None] - xc + h * o[None, :, None], Y[rim][:, None, None] - yc + h * o[None, None, :]) < r
    ap[rim] = sub.mean((1, 2))
    return ap


def truth_2d(a_mm, d2_mm, coeffs, field_deg, px, py, pixel, h=3e-3, npad=2560, nodes=4, model=False):
    """Off-axis two-step truth on a 2-D grid (pitch ``h`` mm, ``npad`` samples, periodic): the thin lens's
    sphere converging to (0, F tan(field)) on the stop's disc (rim samples weighted by the disc's share of their
    cell), the exact angular spectrum (FFT) over z1, the radial DOE (centred on the axis), the exact angular
    spectrum over d2 evaluated at the pixels' Gauss nodes (px, py (M,) pixel centres, mm) by a matrix DFT (the
    periodic field's trigonometric interpolation). Returns the power per pixel over the power entering the stop.
    Its own error on axis, against :func:`radial_truth`: 7.4e-4 of the peak at h = 3 um, 5.2e-4 at 2 um (the
    sampled rim's aliasing). ``model=True``: ``(truth, model)``, the model the ray-wave model's geometric field
    on the DOE plane (the same sphere, cut by the stop's shadow there: the disc of radius ``a d2 / F`` centred on
    the chief ray, ``z1 tan(field)``; amplitude ``F / d2``: the tube's power kept), propagated the same way."""
    k = 2 * np.pi / LAM_MM
    z1, rb = F_MM - d2_mm, a_mm * d2_mm / F_MM
    x = (np.arange(npad) - npad // 2) * h
    X, Y = np.meshgrid(x, x, indexing="xy")
    R = np.hypot(X, Y)
    yT = F_MM * np.tan(np.radians(field_deg))
    u0 = _disc_2d(X, Y, 0.0, 0.0, a_mm, h) * np.exp(-1j * k * np.sqrt(X ** 2 + (Y - yT) ** 2 + F_MM ** 2))
    p_in = np.sum(np.abs(u0) ** 2) * h * h
    nu = np.fft.fftfreq(npad, h)
    NX, NY = np.meshgrid(nu, nu, indexing="xy")
    w = np.sqrt(np.maximum(1 / LAM_MM ** 2 - NX ** 2 - NY ** 2, 0.0))
    fields = [_ifft2(_fft2(u0) * np.exp(2j * np.pi * z1 * w))]
    del u0
    if model:
        fields.append(_disc_2d(X, Y, 0.0, yT * z1 / F_MM, rb, h) * (F_MM / d2_mm)
                      * np.exp(-1j * k * np.sqrt(X ** 2 + (Y - yT) ** 2 + d2_mm ** 2)))
    W = sum(c * (R / rb) ** (2 * (i + 1)) for i, c in enumerate(coeffs))
    t, wt = np.polynomial.legendre.leggauss(nodes)
    xs = (px[:, None] + 0.5 * pixel * t[None]).ravel()
    ys = (py[:, None] + 0.5 * pixel * t[None]).ravel()
    m = len(px)
    out = []
    tdoe, h2 = np.exp(1j * W), np.exp(2j * np.pi * d2_mm * w) / npad ** 2      # the same for both fields
    ey, ex = np.exp(2j * np.pi * np.outer(ys - x[0], nu)), np.exp(2j * np.pi * np.outer(xs - x[0], nu)).T
    for u1 in fields:
        S = _fft2(u1 * tdoe) * h2
        U = ey @ S @ ex
        P = np.einsum("injm,n,m->ij", (np.abs(U) ** 2).reshape(m, nodes, m, nodes), wt, wt) * (0.5 * pixel) ** 2
        out.append(P / p_in)
    return tuple(out) if model else out[0]


def test_off_axis_the_wave_step_and_the_estimate_against_a_2d_truth():
    # a = 1.5 mm, DOE 20 mm before the sensor (N_F 54.5), 0.2 deg: the beam sits 0.1 mm off the DOE's centre
    lens = thin_lens_doe(20.0, 1.5, (0.0, 3.0), pixel=4e-3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        one = rw.psf(lens, 0.2, 0.55, size=32, method="asm")
        two = rw.psf(lens, 0.2, 0.55, size=32, method="two-step")
    px, py = one.coords_mm()
    T = truth_2d(1.5, 20.0, (0.0, 3.0), 0.2, px, py, one.pixel_mm)
    peak = T.max()
    e_one, e_two = np.max(np.abs(one.data - T)) / peak, np.max(np.abs(two.data - T)) / peak
    # measured: one-step 6.5e-2; two-step 1.4e-3, of which the truth's own is ~7e-4 (its docstring)
    assert e_one > 2e-2
    assert e_two < 2.5e-3
    # the estimate (the edge waves on the fitted pupil phase): 6.7e-2, 1.03x the measured (the old scalar law on
    # the RMS rim slope, 12.4 rad: 7.1e-2, 1.09x)
    assert 0.5 <= one.plan["model_error"]["estimate"] / e_one <= 2.0


@pytest.mark.parametrize("field_deg", [pytest.param(0.3, marks=pytest.mark.slow), 0.5,
                                       pytest.param(0.7, marks=pytest.mark.slow)])
def test_off_axis_the_estimate_against_a_2d_truth(field_deg):
    # a = 1.5 mm, DOE 3 rho^4 20 mm before the sensor (N_F 54.5): at 0.3 / 0.5 / 0.7 deg the beam sits 0.26 / 0.44 /
    # 0.61 of its radius off the DOE's centre (the DOE's clear aperture widened to 2 beam radii: nothing clips it).
    # The model error measured on the 2-D truth against the 2-D geometric model (both numpy, truth_2d): 6.34e-2 /
    # 3.04e-2 / 3.56e-2. The estimate: 7.66e-2 / 3.05e-2 / 3.32e-2 (1.21x / 1.00x / 0.93x); the old scalar law on
    # the RMS rim slope read 1.29x / 4.0x / 5.6x (its 0.5 deg is the case it was known to miss)
    lens = thin_lens_doe(20.0, 1.5, (0.0, 3.0), pixel=4e-3, doe_share=2.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        got = rw.plan_psf(lens, field_deg, 0.55, size=32, method="asm").model_error
    assert got["fresnel_number"] == pytest.approx(54.5, rel=0.03)
    c = (np.arange(32) - 15.5) * 4e-3
    # 2048 samples (a 6.1 mm window around the 3 mm stop): the measured error moved by 1e-5 of itself against 2560
    T, M = truth_2d(1.5, 20.0, (0.0, 3.0), field_deg, c, c + F_MM * np.tan(np.radians(field_deg)), 4e-3, npad=2048,
                    model=True)
    err = float(np.max(np.abs(M - T)) / T.max())
    print(f"{field_deg} deg: measured {err:.3e}, estimate {got['estimate']:.3e} ({got['estimate'] / err:.2f}x), "
          f"old law {me.model_error(got['fresnel_number'], got['rim_slope_rad']) / err:.2f}x")
    # the claim: a factor 2 (measured 0.93 .. 1.21x, above)
    assert 0.5 <= got["estimate"] / err <= 2.0, (got["estimate"], err)


def truth_2d_on_grid(a_mm, d2_mm, coeffs, field_deg, half_mm, h=3e-3, npad=2048):
    """:func:`truth_2d`'s two fields (the same equations: the stop's disc, the exact angular spectrum over z1, the
    radial DOE, over d2), read on the grid's own samples (one inverse FFT, no pixel integration) within ``half_mm`` of
    the chief ray's landing point: ``(truth, model)`` irradiance (the same arbitrary unit)."""
    k = 2 * np.pi / LAM_MM
    z1, rb = F_MM - d2_mm, a_mm * d2_mm / F_MM
    x = (np.arange(npad) - npad // 2) * h
    X, Y = np.meshgrid(x, x, indexing="xy")
    yT = F_MM * np.tan(np.radians(field_deg))
    nu = np.fft.fftfreq(npad, h)
    NX, NY = np.meshgrid(nu, nu, indexing="xy")
    w = np.sqrt(np.maximum(1 / LAM_MM ** 2 - NX ** 2 - NY ** 2, 0.0))
    u0 = _disc_2d(X, Y, 0.0, 0.0, a_mm, h) * np.exp(-1j * k * np.sqrt(X ** 2 + (Y - yT) ** 2 + F_MM ** 2))
    fields = [_ifft2(_fft2(u0) * np.exp(2j * np.pi * z1 * w)),
              _disc_2d(X, Y, 0.0, yT * z1 / F_MM, rb, h) * (F_MM / d2_mm)
              * np.exp(-1j * k * np.sqrt(X ** 2 + (Y - yT) ** 2 + d2_mm ** 2))]
    del u0
    W = sum(c * (np.hypot(X, Y) / rb) ** (2 * (i + 1)) for i, c in enumerate(coeffs))
    rows = np.abs(x - yT) <= half_mm
    cols = np.abs(x) <= half_mm
    out = []
    tdoe, h2 = np.exp(1j * W), np.exp(2j * np.pi * d2_mm * w)       # the same for both fields
    for u1 in fields:
        U = _ifft2(_fft2(u1 * tdoe) * h2)
        out.append(np.abs(U[np.ix_(rows, cols)]) ** 2)
    return tuple(out)


@pytest.mark.parametrize("coeffs,h_mm,npad", [((0.0, 10.0), 3e-3, 2048), ((0.0, 25.0), 3e-3, 2048),
                                           pytest.param((0.0, 35.0), 2e-3, 3072, marks=pytest.mark.slow)])
def test_steep_rims_off_axis_the_estimate_against_a_2d_truth(coeffs, h_mm, npad):
    # a = 1.5 mm, DOE c rho^4 20 mm before the sensor (N_F 54.5), 0.5 deg: the beam 0.44 of its radius off the DOE's
    # centre, so its phase about its own centre has coma and astigmatism (the geometry of the A489's beams off axis),
    # and steep: the pilot's RMS rim slope 59 / 147 rad (10 / 25 rho^4). The model error measured on the 2-D truth
    # against the 2-D geometric model on the grid's 3 um samples over the whole spot: 4.27e-2 / 5.78e-2 (with
    # truth_2d's 4 um pixels 3.86e-2 / 5.60e-2; 5.60e-2 again at h = 2 um, 3072 samples). The estimate: 4.12e-2 /
    # 5.53e-2, 0.96x / 0.96x (1.07x / 0.99x of the pixel figures); before the traced rays 0.92x / the scalar law's
    # ~420x (the phase was beyond the old 180 rad sampling limit). 35 rho^4 (206 rad; the light reaches 166 cycles/mm,
    # the 3 um grid's Nyquist limit: 2 um, 3072 samples; 30 rho^4 moved by 7 % from 3 to 2 um): measured 6.85e-2, the
    # estimate 6.59e-2, 0.96x (before: the scalar law)
    lens = thin_lens_doe(20.0, 1.5, coeffs, pixel=4e-3, doe_share=2.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        got = rw.plan_psf(lens, 0.5, 0.55, size=32, method="asm").model_error
    assert got["rim_slope_rad"] > 40
    rb = 1.5 * 20.0 / F_MM
    spot = 1.3 * LAM_MM * 20.0 * 4 * coeffs[1] / (2 * np.pi * rb) + 0.03
    T, M = truth_2d_on_grid(1.5, 20.0, coeffs, 0.5, spot, h=h_mm, npad=npad)
    err = float(np.max(np.abs(M - T)) / T.max())
    print(f"{coeffs}: measured {err:.3e}, estimate {got['estimate']:.3e} ({got['estimate'] / err:.2f}x), "
          f"rim slope {got['rim_slope_rad']:.0f} rad")
    # the claim: a factor 2 (measured 0.96x, 0.96x, 0.96x)
    assert 0.5 <= got["estimate"] / err <= 2.0, (got["estimate"], err)


def test_a_perfect_singlet_reads_no_rim_slope():
    # a flat-convex singlet whose last surface is the hyperboloid (conic -n^2) that focuses a plane wave from the
    # glass perfectly: the wavefront after it is the sphere to the focus, so S ~ 0 (the field is formed on the
    # curved surface's vertex plane; reading the pilot points on the surface itself gave 1.37 rad here)
    n, R = 1.5, -25.0
    surfs = [Surface(type="aperture", semi_diameter=2.0, shape="circle", stop=True),
             Surface(type="standard", thickness=3.0, material="1.5/1e9", semi_diameter=3.0),
             Surface(type="standard", radius=R, conic=-n * n, thickness=abs(R) / (n - 1), semi_diameter=3.0)]
    lens = Lens(surfs, Sensor(2e-3, (2000, 2000)), wavelengths_um=[0.55])
    got = rw.plan_psf(lens, 0.0, 0.55, size=16, method="focal").model_error
    assert got["rim_slope_rad"] < 0.2, got
    assert got["estimate"] < 1e-4
