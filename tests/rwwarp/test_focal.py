"""Focal propagation (rwwarp.wave.focal) and the planner that sizes it: checked against independent truth.

References, none of which shares code with the propagation:
* ``rs_lens_psf``: traced rays, ray-tube amplitudes, exact Rayleigh-Sommerfeld kernel summed directly
  to the sensor pixels, on a polar pupil rule (converged to ~1e-11: 32x128 and 48x256 nodes agree to
  4e-12 on the Cooke triplet on axis and 6e-12 at 14 deg);
* ``rs_thin_lens_psf``: the thin lens + DOE ground truth (exact aperture quadrature);
* numpy: the Fourier series of a DOE's transmission by FFT.
Tolerances are about twice the measured error (the figures are in each test).
"""
import math

import numpy as np
import pytest

import rwwarp as rw
from rwwarp.wave.focal import doe_order_coefficients
from rwwarp.ground_truth import rs_lens_psf, rs_thin_lens_psf
from rwwarp.lens import Lens, Surface
from rwwarp.wave.plan import MemoryBudgetError
from rwwarp.psf import RayWave

from _mirror import mirrored_patch_truth, mirrored_truth


def _rel(a, b):
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


def _rs_truth(lens, field, wavelength_um, p, **kw):
    """``rs_lens_psf`` on the patch of the PSF ``p``. On axis (the lenses here are rotationally symmetric, a DOE
    even in r) the PSF is even in x and y: the truth on one quadrant of the patch, mirrored
    (tests/rwwarp/_mirror.py; equal to the sum on the whole patch to 4e-13 relative on the Cooke triplet,
    measured: the trace's rounding), a quarter of the summation; off axis on the whole patch."""
    def on(center, n):
        return rs_lens_psf(lens, field, wavelength_um, center, n, p.pixel_mm, **kw)
    n = p.data.shape[0]
    if field == 0.0:
        return mirrored_patch_truth(on, p.center_mm, n, p.pixel_mm)
    return on(p.center_mm, n)


# ------------------------------------------------------------------------------------- DOE orders
@pytest.mark.parametrize("alpha,levels", [(1.0, None), (0.83, None), (1.21, None), (1.0, 8), (0.9, 16)])
def test_order_coefficients_match_fft_of_transmission(alpha, levels):
    """c_m against the FFT of t(phi) = exp(1j alpha q(phi)) sampled on a fine phi grid (numpy)."""
    n = 2 ** 16
    phi = (np.arange(n) + 0.5) * (2 * np.pi / n)
    if levels is None:
        q = phi
    else:
        step = 2 * np.pi / levels
        q = np.mod(np.rint(phi / step), levels) * step
    t = np.exp(1j * alpha * q)
    m = np.arange(-6, 7)
    ref = np.array([np.mean(t * np.exp(-1j * mm * phi)) for mm in m])
    got = doe_order_coefficients(alpha, levels, m)
    assert np.max(np.abs(got - ref)) < 1e-4   # midpoint sampling of the jumps: measured 2e-5
    if alpha == 1.0 and levels is None:
        assert abs(got[m == 1][0] - 1.0) < 1e-14
    if alpha == 1.0 and levels:
        assert abs(abs(got[m == 1][0]) ** 2 - np.sinc(1 / levels) ** 2) < 1e-14


# ------------------------------------------------------------------------------------- against truth
def _thin_lens_doe(focal, dist, half, coeffs, norm):
    surfs = [Surface(type="aperture", semi_diameter=half, shape="square", stop=True),
             Surface(type="thin_lens", focal_length=focal, semi_diameter=half, shape="square"),
             Surface(type="doe", semi_diameter=half, shape="square", design_wavelength_um=0.55,
                     material="fused_silica", profile={"kind": "even_poly", "norm_radius": norm,
                                                       "coefficients": list(coeffs)})]
    surfs[-1].thickness = dist
    return Lens(surfs, rw.Sensor(0.002, (4000, 4000)), math.inf, [0.55], name="thin lens + DOE")


@pytest.mark.slow
@pytest.mark.parametrize("coeffs,tol", [([-40.0, 6.0], 7e-5), ([-60.0, 10.0], 5e-5)])
def test_thin_lens_even_poly_doe_20mm_before_sensor(coeffs, tol):
    """A thin lens (f = 21 mm) with a modest even-polynomial DOE 20 mm before the sensor behind a square
    aperture, at the design wavelength (continuous relief: only order 1). Truth: rs_thin_lens_psf with the
    same phi0. Measured 1.5e-5 and, for a stronger DOE, 2.4e-5 (focal, default plan, 16 px). The square
    aperture's 1 / r diffraction tails need a longer wave-plane period and a wider sensor-side margin than a
    round one's (FOCAL_EDGE_SPREAD, FOCAL_EDGE_MARGIN_B): with the round pupil's rules 3.7e-4 and 3.8e-4; the
    band-limited ASM reference path gives 4.0e-4 on the first case. Tolerance about twice.
    The first case's error moves with the exact grid (its sampling phase against the square edges): over
    nyquist_safety 1.9 / 2.0 / 2.1 it measured 7.4e-6 / 1.5e-5 / 3.6e-5 with session 12's plan rules and 2.8e-6 /
    3.3e-5 / 2.3e-5 with the wide-spot rules (rwwarp.wave.plan FOCAL_RAY_SPREAD, FOCAL_LIT_SHIFT_MARGIN: this spot's
    rays land in the taper, so its margin and grid grew slightly): 7e-5 is twice the largest of them. At cbce674
    the two cases measured 3.3e-5 and 4.0e-5.
    The truth is evaluated on one quadrant of pixels and mirrored: the scene (on-axis plane wave, square aperture
    and rotationally symmetric DOE centred on the axis) is even in x and in y, and the patch's pixel centres are
    symmetric about the axis (tests/rwwarp/_mirror.py asserts it); the mirrored truth equals the one summed on all
    256 pixels to 2e-14 (measured on both cases) at a quarter of the cost."""
    norm, half = 1.0, 1.0
    lens = _thin_lens_doe(21.0, 20.0, half, coeffs, norm)
    p = rw.psf(lens, 0.0, 0.55, size=16, method="focal")
    assert p.plan["method"] == "focal"
    x, y = p.coords_mm()

    def phi0(xx, yy):
        r2 = (xx * xx + yy * yy) / norm ** 2
        return coeffs[0] * r2 + coeffs[1] * r2 * r2
    # 4 x 4 sensor nodes a pixel: within 2e-8 of the peak of 5 x 5 (measured on the second case), 40 % less time
    truth = mirrored_truth(lambda qx, qy: rs_thin_lens_psf(21.0, "square", half, 0.55, 20.0, qx, qy, p.pixel_mm,
                                                           doe_phase=phi0, gauss_nodes_sensor=4), x, y)
    assert _rel(p.data, truth) < tol


@pytest.mark.slow
@pytest.mark.parametrize("field,tol", [(0.0, 1.2e-4), (14.0, 8e-5)])
def test_cooke_triplet_against_rs_truth(field, tol):
    """The bundled Cooke triplet (no DOE: the wave plane is the curved last surface's vertex plane).
    Measured with the default plan (size 16): 5.9e-5 on axis, 4.1e-5 at 14 deg (9.2e-5 / 1.84e-4 before the
    quadratic transfer was fitted and V tapered, 1.6e-4 / 2.5e-4 before the rim cells were weighted; the
    ASM path took 149-412 s and was 15 % / 156 % off). Tolerance about twice that."""
    lens = rw.load_lens("cooke_triplet")
    p = rw.psf(lens, field, 0.5876, size=16)
    assert p.plan["method"] == "focal"
    truth = _rs_truth(lens, field, 0.5876, p, radial_nodes=32, angular_nodes=128)
    assert _rel(p.data, truth) < tol


@pytest.mark.slow
def test_achromatic_doublet_against_rs_truth():
    """AC254-100-A at 25 mm EPD on axis (the case that exhausted Warp's allocator before). Measured 3.0e-5
    (1.41e-4 before the taper and fitted transfer, 1.9e-4 before the rim cells were weighted; truth converged
    to 2e-11); tolerance about twice."""
    lens = rw.load_lens("ac254_100_a")
    p = rw.psf(lens, 0.0, 0.5876, size=16)
    truth = _rs_truth(lens, 0.0, 0.5876, p, radial_nodes=32, angular_nodes=128)
    err = _rel(p.data, truth)
    assert err < DOUBLET_TOL, err


DOUBLET_TOL = 6e-5


def test_truth_rejects_doe_lenses():
    lens = rw.load_lens("a489_doe")
    lens.surfaces[lens.doe_index].profile = {"kind": "even_poly", "norm_radius": 1.0, "coefficients": [1.0]}
    with pytest.raises(rw.LensError):
        rs_lens_psf(lens, 0.0, 0.55, (0.0, 0.0), 4, 0.001)


# ------------------------------------------------------------------------------------- cost follows the patch
def test_focal_sampling_follows_the_patch_not_the_beam():
    """The wave-plane grid of the focal plan grows with the patch; the ASM's with the beam (planning only:
    nothing is traced beyond the pilot)."""
    lens = rw.load_lens("cooke_triplet")
    f32 = RayWave(lens, [0.0], [0.5876], 32, 0.005, method="focal")
    f64 = RayWave(lens, [0.0], [0.5876], 64, 0.005, method="focal")
    asm = RayWave(lens, [0.0], [0.5876], 64, 0.005, method="asm")
    assert f64.plan.n_grid < asm.plan.n_grid / 5          # measured 616 against 6275
    assert f64.plan.estimate["memory_bytes"] < 2 ** 30      # the 1 GB figure, planned
    assert asm.plan.estimate["memory_bytes"] > 4 * 2 ** 30  # the 11 GB case is recognised before it runs
    assert f32.plan.n_grid < f64.plan.n_grid


def test_memory_budget_refuses_with_the_knobs():
    lens = rw.load_lens("cooke_triplet")
    with pytest.raises(MemoryBudgetError) as e:
        rw.psf(lens, 0.0, 0.5876, size=64, method="asm", memory_budget_gb=1.0)
    msg = str(e.value)
    assert "GiB" in msg and "memory_budget_gb" in msg and "size" in msg and "rays_per_sample" in msg


def test_psf_map_splits_batches_under_a_budget():
    """A budget that holds one source splits a batch of two; the PSFs equal those of one-source batches
    (same plans) to 1e-12."""
    lens = rw.load_lens("a489_doe")
    kw = dict(fields=[0.0, 5.0], wavelengths_um=[0.55], size=16)
    whole = rw.psf_map(lens, **kw, method="focal", batch=2)
    assert len(whole.info["batches"]) == 1
    single = rw.psf_map(lens, **kw, method="focal", batch=1)
    one = RayWave(lens, [5.0], [0.55], 16, lens.sensor.pixel_pitch, method="focal")
    budget = 1.3 * one.plan.estimate["memory_bytes"] / 2 ** 30
    split = rw.psf_map(lens, **kw, method="focal", batch=2, memory_budget_gb=budget)
    assert len(split.info["batches"]) == 2
    np.testing.assert_allclose(split.data, single.data, rtol=0, atol=1e-12)
    # a shared plan (finest pitch, widest box) gives the same PSFs within the method's error
    assert _rel(whole.data, single.data) < 1e-3


def test_plan_is_immutable_and_not_mutated_by_calls():
    lens = rw.load_lens("a489_doe")
    p0 = rw.psf(lens, 0.0, 0.55, size=8, method="focal")
    plan = rw.Plan(**p0.plan)
    before = plan.to_dict()
    for _ in range(3):
        rw.psf(lens, 0.0, 0.55, size=8, plan=plan)
    assert plan.to_dict() == before
    with pytest.raises(Exception):
        plan.pitch_mm = 1.0


def test_splat_conserves_power_for_wide_ray_tubes():
    """rays_per_sample 0.25 (tubes four samples wide): the field holds the traced power (was 36 %).
    The remaining deficit is the box-filtered rim, ~h / (3 R): measured 0.5 %."""
    lens = rw.load_lens("a489_doe")
    for rps in (1.0, 0.25):
        r = RayWave(lens, [0.0], [0.55], 16, lens.sensor.pixel_pitch, rays_per_sample=rps, method="focal")
        u = r.field_array()
        power = float(np.sum(np.abs(u) ** 2) * r.plan.pitch_mm ** 2)
        assert abs(power / r.traced_power[0] - 1.0) < 0.01, (rps, power / r.traced_power[0])
        assert int(r.dropped.numpy()[0]) == 0
    m = rw.psf_map(lens, [0.0], [0.55], size=16, rays_per_sample=0.25)
    assert list(m.info["dropped_rays"]) == [0]     # reported per PSF, not discarded


def test_quantised_doe_orders_that_spread_over_the_field_are_left_out():
    """A 16-level Fresnel-zone DOE alone: its orders -15 and 17 spread over ~30 mm; the focal plan leaves
    them out (power reported) instead of sampling 30 mm at 0.4 um (263 GiB before). The focused power
    ratio stays the scalar efficiency sinc^2(1/16) (measured 0.98619 against 0.98721; 0.98757 with whole
    rim cells)."""
    def fz(levels):
        s = [Surface(type="aperture", semi_diameter=1.0, shape="circle", stop=True),
             Surface(type="doe", semi_diameter=1.0, shape="circle", thickness=100.0,
                     profile={"kind": "fresnel", "focal_length": 100.0}, material="1.5/1e9", levels=levels)]
        return Lens(s, rw.Sensor(0.0055, (4000, 4000)), wavelengths_um=[0.55])
    a = rw.psf(fz(None), 0.0, 0.55, size=32, method="focal")
    b = rw.psf(fz(16), 0.0, 0.55, size=32, method="focal")
    assert b.plan["n_grid"] < 200 and "[1]" in b.plan["reasons"][1]
    core = slice(12, 20)
    assert b.data[core, core].sum() / a.data[core, core].sum() == pytest.approx(np.sinc(1 / 16) ** 2, abs=2e-3)


@pytest.mark.slow
def test_a489_auto_takes_the_cheaper_plan_and_both_paths_match_truth():
    """The A489 (F/2.2, blank DOE as a plane). Method auto runs the plan of fewer flops (on every device):
    the focal path here. Against rs_lens_psf on
    axis (16 px): ASM 4.9e-5, tolerance 1e-4; focal 2.9e-5 (6.4e-5 before the taper and fitted transfer,
    8.0e-4 with whole rim cells), tolerance 6e-5."""
    lens = rw.load_lens("a489_doe")
    p = rw.psf(lens, 0.0, 0.55, size=16)
    a = rw.psf(lens, 0.0, 0.55, size=16, method="asm", center_mm=p.center_mm)
    f = rw.psf(lens, 0.0, 0.55, size=16, method="focal", center_mm=p.center_mm)
    assert f.plan["estimate"]["flops"] < a.plan["estimate"]["flops"]
    assert p.plan["method"] == "focal"
    truth = _rs_truth(lens, 0.0, 0.55, p, radial_nodes=32, angular_nodes=128)
    assert _rel(a.data, truth) < 1e-4
    assert _rel(f.data, truth) < 6e-5


@pytest.mark.slow
def test_a489_off_axis_focal_against_truth():
    """The A489 at 10 deg (an aberrated beam, 10 % of its power outside a 64 px patch): the focal path
    measures 1.13e-4 against rs_lens_psf (16 px; max / peak 1.48e-4): the main order's ray-landing extent sets
    the wave-plane period (FOCAL_RAY_SPREAD; 5.8e-4 with the spread rules alone, 1.4e-3 before the fitted
    transfer and taper, the ASM 6.2e-4). Tolerance about twice; max / peak at issue 27's target for refractive
    lenses, 2e-4 (1.35x the measured)."""
    lens = rw.load_lens("a489_doe")
    f = rw.psf(lens, 10.0, 0.55, size=16, method="focal")
    truth = rs_lens_psf(lens, 10.0, 0.55, f.center_mm, 16, f.pixel_mm, radial_nodes=32, angular_nodes=128)
    assert _rel(f.data, truth) < 2.5e-4
    assert float(np.abs(f.data - truth).max() / truth.max()) < 2e-4


@pytest.mark.parametrize("fitted", [False, True])
def test_focal_operator_adjoint_is_the_conjugate_transpose(fitted):
    """<A x, y> = <x, A^H y> for random complex x, y (the operator's adjoint, used for gradients), with the
    Taylor quadratic transfer and with a fitted one plus the sensor-side taper."""
    from rwwarp.wave.focal import FocalPropagator
    rng = np.random.default_rng(1)
    S, n, ns, nf, m = 2, 24, 20, 32, 9
    extra = {"transfer": ([[0.0, 0.0], [0.0, -0.0155]], [[-6.0e-4, -6.1e-4], [-5.9e-4, -6.2e-4]]),
             "taper_guard_mm": 0.005} if fitted else {}
    op = FocalPropagator(origin_mm=[[-0.5, -0.5], [-0.4, -0.6]], pitch_mm=0.04, n_grid=n,
                         wavelength_mm=[5.5e-4, 6.0e-4], distance_mm=20.0,
                         carrier_cpmm=[[0.0, 0.0], [0.0, 25.0]], sensor_origin_mm=[[-0.02, -0.02], [-0.01, 0.28]],
                         sensor_pitch_mm=0.002, n_sensor=ns, n_fft=nf,
                         nodes_x_mm=rng.uniform(-0.01, 0.01, (S, m)), nodes_y_mm=rng.uniform(-0.01, 0.01, (S, m)),
                         **extra)
    x = rng.normal(size=(S, n, n)) + 1j * rng.normal(size=(S, n, n))
    y = rng.normal(size=(S, m, m)) + 1j * rng.normal(size=(S, m, m))
    lhs = np.vdot(op.forward(x), y)
    rhs = np.vdot(x, op.adjoint(y))
    assert abs(lhs - rhs) <= 1e-12 * abs(lhs)


def test_sensor_taper_is_one_inside_zero_at_the_ends_and_smooth():
    """The taper against its definition: 1 on [lo, hi], 0 at the grid's ends, 1/2 halfway (symmetry of
    s(t) = e(t) / (e(t) + e(1 - t))), and monotone in between."""
    from rwwarp.wave.focal import sensor_taper
    p = np.linspace(-1.0, 1.0, 401)[None]
    w = sensor_taper(p, np.array([-0.2]), np.array([0.4]))[0]
    inside = (p[0] >= -0.2) & (p[0] <= 0.4)
    assert np.all(w[inside] == 1.0) and w[0] == 0.0 and w[-1] == 0.0
    assert w[np.argmin(abs(p[0] - 0.7))] == pytest.approx(0.5, abs=1e-12)
    assert np.all(np.diff(w[p[0] > 0.4]) <= 0) and np.all(np.diff(w[p[0] < -0.2]) >= 0)


def converging_beam(n, seed=0):
    """An exact beam for the transfer fits: ``n`` straight rays converging at 14 deg through NA 0.1 (0.5876 um,
    z = 42 mm), spatial frequencies ``f`` (cycles/mm) uniform over the pupil disc, start points ``x`` uniform over
    8 x 8 mm, landing points ``L = x + z f / w``. Returns (lam, z, k, fc, f, x, L)."""
    lam, z = 5.876e-4, 42.0
    k = 1.0 / lam
    rng = np.random.default_rng(seed)
    fc = np.array([0.0, np.sin(np.deg2rad(14.0)) * k])
    r = 0.1 * k * np.sqrt(rng.uniform(0, 1, n))
    a = rng.uniform(0, 2 * np.pi, n)
    f = fc + np.stack([r * np.cos(a), r * np.sin(a)], 1)
    w = np.sqrt(k * k - np.sum(f * f, 1))
    x = rng.uniform(-4, 4, (n, 2))
    return lam, z, k, fc, f, x, x + z * f / w[:, None]


def test_fitted_transfer_narrows_the_remainder_off_axis():
    """fit_quadratic_transfer on an exact beam (straight rays converging at 14 deg through NA 0.1): the
    largest remainder displacement z |grad w - g - q (f - f_c)| falls below the Taylor expansion's
    (computed here from w(f) = sqrt(k^2 - |f|^2) directly)."""
    from rwwarp.wave.plan import fit_quadratic_transfer
    from rwwarp.wave.focal import transfer_curvature
    lam, z, k, fc, f, x, L = converging_beam(4000)
    _, g, q = transfer_curvature(fc[None], np.array([k]))
    gf, qf = fit_quadratic_transfer([f], [L], [x], fc, g[0], q[0], z)

    def worst(gg, qq):
        return np.max(np.abs(L - (x - z * (gg + (f - fc) * qq))))
    assert worst(gf, qf) < 0.7 * worst(g[0], q[0])
    assert np.all(qf < 0)


def _cooke_with_doe(a1, a2):
    """The Cooke triplet with a flat even-polynomial DOE (``a1 rho^2 + a2 rho^4`` rad, rho = r / 15 mm, design
    0.55 um, fused silica) 5 mm before the sensor."""
    from rwwarp.lens import Surface
    lens = rw.load_lens("cooke_triplet")
    surfs = [Surface(**{k: getattr(s, k) for k in s.__dataclass_fields__}) for s in lens.surfaces]
    surfs[-1].thickness = lens.surfaces[-1].thickness - 5.0
    surfs.append(Surface(type="doe", semi_diameter=15.0, shape="circle", thickness=5.0, design_wavelength_um=0.55,
                         material="fused_silica", profile={"kind": "even_poly", "norm_radius": 15.0,
                                                           "coefficients": [float(a1), float(a2)]}))
    return lens.replace(surfaces=surfs)


@pytest.mark.slow
def test_weak_doe_off_its_design_wavelength_against_rs_truth():
    """A weak even-polynomial DOE 5 mm before the Cooke triplet's sensor (its relief does not wrap inside
    the 1 mm beam) at 0.5876 um (alpha = 0.933). The integer-order series sum_m c_m exp(i m phi0) over
    m = -8..8 converges slowly next to the wrap (Gibbs) and was 1.9e-2 off; the exact single term
    exp(i alpha (phi0 - 2 pi k)) gives 7.1e-5 (1.39e-4 before the taper and fitted transfer, 2.0e-4 before
    the rim cells were weighted; the band-limited ASM: 4.1e-5). Truth: rs_lens_psf with the DOE phase (include_doe). Tolerance about twice
    the measured."""
    lens = _cooke_with_doe(-1000.0, 50.0)
    p = rw.psf(lens, 0.0, 0.5876, size=16, method="focal")
    orders = p.plan["reasons"] if isinstance(p.plan, dict) else []
    assert any("0.933" in str(r) for r in orders)
    truth = _rs_truth(lens, 0.0, 0.5876, p, radial_nodes=32, angular_nodes=128, include_doe=True)
    assert _rel(p.data, truth) < 1.5e-4


@pytest.mark.slow
def test_wrapped_doe_off_design_wavelength_against_the_converged_asm():
    """Cooke triplet + even-polynomial DOE (a1 = -30000 rad at a 15 mm norm radius, several zones in the
    1 mm beam) 5 mm before the sensor, at 0.5876 um (alpha = 0.933: several diffraction orders). Reference:
    the band-limited ASM at half its default pitch (converged: halving again changes it by 2.9e-4). The
    focal method was 1.43e-2 off with the integer-order series everywhere (the series converges slowly near
    the axis, where phi0 touches the wrap boundary 0 without crossing it); with the chief ray's zone exact,
    2.87e-3. Tolerance 6e-3 (about twice): the rest is the order series at the real zone edges (open,
    docs/accuracy.md)."""
    import warnings
    from rwwarp.wave.plan import Plan, nice_fft_length
    lens = _cooke_with_doe(-30000.0, 0.0)
    fo = rw.psf(lens, 0.0, 0.5876, size=32, method="focal")
    c = tuple(fo.center_mm)
    a = rw.psf(lens, 0.0, 0.5876, size=32, method="asm", center_mm=c).plan
    fine = Plan(a["pitch_mm"] / 2, a["n_grid"] * 2, nice_fft_length(a["n_pad"] * 2), a["ray_grid"] * 2, "explicit",
                False, [])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref = rw.psf(lens, 0.0, 0.5876, size=32, method="asm", center_mm=c, plan=fine)
    assert _rel(fo.data, ref.data) < 6e-3


@pytest.mark.parametrize("name,file,tol", [("cooke_triplet", "cooke_triplet_14deg_64px", 4.5e-5),
                                           ("cooke_triplet", "cooke_triplet_0deg_64px", 5.5e-5),
                                           ("ac254_100_a", "ac254_100_a_0deg_64px", 5.5e-5)])
def test_64px_psfs_against_stored_truth(name, file, tol):
    """The issue's figure cases at 64 px against rs_lens_psf computed once (~15-20 min each on one core, so
    stored in tests/data/truth with their parameters; at 14 deg 128 x 512 pupil nodes, 2.6e-12 from 96 x 384;
    the others 96 x 384). Measured 2.37e-5 (14 deg), 2.9e-5 (on axis), 2.55e-5 (AC254); tolerance about
    twice. The stored truths are ``|U|^2`` (before issue 27): the PSFs here are asked for by that name."""
    from pathlib import Path
    d = np.load(Path(__file__).resolve().parents[1] / "data" / "truth" / f"{file}.npz")
    lens = rw.load_lens(name)
    p = rw.psf(lens, float(d["field_deg"]), float(d["wavelength_um"]), size=64, center_mm=tuple(d["center_mm"]),
               pixel_values="intensity")
    assert p.plan["method"] == "focal" and p.pixel_mm == pytest.approx(float(d["pixel_mm"]))
    assert _rel(p.data, d["psf"]) < tol
