"""Closed-form PSFs (rwwarp.analytic) and the direct Rayleigh-Sommerfeld ground truth (rwwarp.ground_truth).

Physics oracles only: textbook numbers, exact integrals, closed-form on-axis RS fields, and the
agreement of the RS ground truth with Fraunhofer at the level the non-paraxial effects allow.

Expected RS-vs-Fraunhofer level. The exact converging-wave RS field at z = f differs from the
Fraunhofer sinc^2 / Airy pattern through the pupil's sine-space mapping (s = p/R, not p/f), the
amplitude factor f/rho^2 and the obliquity z/rho: all relative O(<|p|^2>/f^2) ~ NA^2. For a
2 mm aperture at f = 100 mm (NA = 0.01) that is ~1e-4 relative L2 (measured: square 9.7e-5,
circle 7.4e-5), and it falls as NA^2 (1 mm aperture: 2.4e-5, 1.9e-5). The quadrature error of
the ground truth itself is < 1e-9, so these comparisons measure physics, not numerics.
"""

import math

import numpy as np
import pytest
from scipy import integrate

from rwwarp import analytic
from rwwarp import ground_truth as gt
from rwwarp.errors import LensError

from _mirror import mirrored_truth

F_MM = 100.0
WL_UM = 0.55
WL_MM = WL_UM * 1e-3


def rel_l2(a, b):
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


def centred(n, pitch_mm, offset_mm=0.0):
    return offset_mm + (np.arange(n) - 0.5 * (n - 1)) * pitch_mm


# ----------------------------------------------------------------------------- closed forms

def test_square_aperture_peak_and_zeros():
    peak_um2 = analytic.square_aperture_psf(0.0, 0.0, 10.0, F_MM, WL_UM) * 1e-6
    assert peak_um2 == pytest.approx(0.033058, abs=5e-7)
    assert peak_um2 == pytest.approx(10.0 ** 2 / (WL_MM * F_MM) ** 2 * 1e-6, rel=1e-14)
    zeros_mm = np.array([5.5, 11.0, 16.5]) * 1e-3
    for x, y in ((zeros_mm, 0.0), (0.0, zeros_mm), (zeros_mm, zeros_mm)):
        vals = analytic.square_aperture_psf(x, y, 10.0, F_MM, WL_UM)
        assert np.all(vals < 1e-25 * peak_um2 * 1e6)
    # between the zeros the side lobes are positive
    assert np.all(analytic.square_aperture_psf(np.array([8.25, 13.75]) * 1e-3, 0.0, 10.0, F_MM, WL_UM) > 0)


def test_circular_aperture_peak_zeros_and_encircled_energy():
    peak_um2 = analytic.circular_aperture_psf(0.0, 10.0, F_MM, WL_UM) * 1e-6
    assert peak_um2 == pytest.approx(0.025964, abs=5e-7)
    assert peak_um2 == pytest.approx(math.pi * 100.0 / (4 * (WL_MM * F_MM) ** 2) * 1e-6, rel=1e-14)
    np.testing.assert_allclose(analytic.airy_zeros(3), [1.2197, 2.2331, 3.2383], atol=5e-5)
    zeros_um = analytic.airy_zeros(3) * WL_MM * F_MM / 10.0 * 1e3
    np.testing.assert_allclose(zeros_um, [6.7082, 12.2822, 17.8107], atol=5e-5)
    at_zeros = analytic.circular_aperture_psf(zeros_um * 1e-3, 10.0, F_MM, WL_UM)
    assert np.all(at_zeros < 1e-20 * peak_um2 * 1e6)
    ee = analytic.encircled_energy(zeros_um * 1e-3, 10.0, F_MM, WL_UM)
    assert ee[0] == pytest.approx(0.8378, abs=1e-4)
    assert ee[1] == pytest.approx(0.9099, abs=1e-4)


def test_encircled_energy_is_integral_of_airy():
    # d EE / dr = 2 pi r I(r), and EE(inf) = 1 (unit power)
    r = np.linspace(1e-4, 0.05, 200)
    h = 1e-7
    deriv = (analytic.encircled_energy(r + h, 10.0, F_MM, WL_UM)
             - analytic.encircled_energy(r - h, 10.0, F_MM, WL_UM)) / (2 * h)
    ring = 2 * math.pi * r * analytic.circular_aperture_psf(r, 10.0, F_MM, WL_UM)
    np.testing.assert_allclose(deriv, ring, rtol=1e-6, atol=1e-6 * ring.max())
    assert analytic.encircled_energy(50.0, 10.0, F_MM, WL_UM) == pytest.approx(1.0, abs=2e-4)


def test_square_pixel_psf_matches_integral_of_closed_form():
    side, pixel = 2.0, 0.004
    cx, cy = centred(21, pixel, 0.003), centred(17, pixel, -0.011)
    pix = analytic.square_aperture_pixel_psf(cx, cy, pixel, side, F_MM, WL_UM)
    assert pix.shape == (17, 21)
    # brute force: 1-D integrals of sinc^2 (the PSF is separable), adaptive quadrature
    scale = side / (WL_MM * F_MM)

    def integral_1d(c):
        val, _ = integrate.quad(lambda x: scale * np.sinc(scale * x) ** 2, c - pixel / 2, c + pixel / 2,
                                epsabs=1e-15, epsrel=1e-13)
        return val
    ref = np.outer([integral_1d(c) for c in cy], [integral_1d(c) for c in cx])
    np.testing.assert_allclose(pix, ref, rtol=1e-11, atol=1e-15)
    # the window's total matches the exact window energy, and a huge window holds ~all the power
    window = analytic.square_aperture_window_energy(cx[0] - pixel / 2, cx[-1] + pixel / 2,
                                                    cy[0] - pixel / 2, cy[-1] + pixel / 2, side, F_MM, WL_UM)
    assert pix.sum() == pytest.approx(window, rel=1e-12)
    # +-L lobes: each axis misses 2 * int_L^inf sinc^2 ~ 1/(pi^2 L) (the sinc^2 tail)
    lobes = 1e3 / (WL_MM * F_MM / side)
    huge = analytic.square_aperture_window_energy(-1e3, 1e3, -1e3, 1e3, side, F_MM, WL_UM)
    assert huge == pytest.approx((1 - 1 / (math.pi ** 2 * lobes)) ** 2, abs=1e-10)


def test_circular_pixel_psf_quadrature_and_energy_bounds():
    diameter = 2.0
    lf_d = WL_MM * F_MM / diameter
    pixel = lf_d                                    # one lambda f/D per pixel
    c = centred(40, pixel)
    pix = analytic.circular_aperture_pixel_psf(c, c, pixel, diameter, F_MM, WL_UM)
    ref = analytic.circular_aperture_pixel_psf(c, c, pixel, diameter, F_MM, WL_UM, nodes=40)
    assert np.max(np.abs(pix - ref)) < 1e-13 * ref.max()
    # energy bounds: EE(inscribed circle) <= window total <= EE(circumscribed circle)
    half = 20 * pixel
    total = pix.sum()
    assert analytic.encircled_energy(half, diameter, F_MM, WL_UM) < total
    assert total < analytic.encircled_energy(half * math.sqrt(2), diameter, F_MM, WL_UM)


def test_gauss_legendre_error_bound_is_sharp():
    # n = 2: int exp(i w t) = 2 sin(w)/w against 2 cos(w/sqrt3); leading term 3.7e-3 w^4
    omega = 0.05
    actual = abs(2 * math.sin(omega) / omega - 2 * math.cos(omega / math.sqrt(3))) / 2
    bound = analytic.gauss_legendre_exp_error(2, omega)
    assert actual <= bound <= 1.01 * actual


# ----------------------------------------------------------------------------- aperture quadrature

@pytest.mark.parametrize("doe", [None, (np.zeros((7, 9)), 0.3), (np.zeros((64, 64)), 0.0317)])
def test_aperture_quadrature_integrates_disk_and_square_exactly(doe):
    h = 1.3
    q = gt.aperture_quadrature("circle", h, doe, gradient_rad_per_mm=(3.0, 5.0))
    assert q.weight_mm2.sum() == pytest.approx(math.pi * h * h, rel=1e-12)
    assert np.sum(q.weight_mm2 * q.x_mm ** 2) == pytest.approx(math.pi * h ** 4 / 4, rel=1e-12)
    assert np.sum(q.weight_mm2 * q.x_mm ** 2 * q.y_mm ** 2) == pytest.approx(math.pi * h ** 6 / 24, rel=1e-10)
    assert np.all(q.x_mm ** 2 + q.y_mm ** 2 <= h * h * (1 + 1e-12))
    q = gt.aperture_quadrature("square", h, doe, gradient_rad_per_mm=(3.0, 5.0))
    assert q.weight_mm2.sum() == pytest.approx(4 * h * h, rel=1e-13)
    assert np.sum(q.weight_mm2 * q.x_mm ** 2) == pytest.approx(4 * h ** 4 / 3, rel=1e-12)


def test_bad_input_raises_lens_error():
    c = centred(4, 0.002)
    with pytest.raises(LensError, match="aperture_shape"):
        gt.rs_thin_lens_psf(F_MM, "hexagon", 1.0, WL_UM, F_MM, c, c, 0.002)
    with pytest.raises(LensError, match="distance_mm"):
        gt.rs_thin_lens_psf(F_MM, "square", 1.0, WL_UM, -1.0, c, c, 0.002)
    with pytest.raises(LensError, match="doe_phase"):
        gt.rs_thin_lens_psf(F_MM, "square", 1.0, WL_UM, F_MM, c, c, 0.002, doe_phase=(np.zeros(5), 0.1))


# ----------------------------------------------------------------------------- RS ground truth

def test_rs_on_axis_field_matches_closed_form():
    # At x' = 0, z = f: rho = R, the phase vanishes and U(0) = A f int (1/R^3 - jk/R^2) d^2p.
    k = 2 * math.pi / WL_MM
    h = 1.0
    # circle: A f 2 pi/(2 pi) [ (1/f - 1/R_h) - jk/2 ln(1 + h^2/f^2) ]
    u_circ = gt.rs_thin_lens_field(F_MM, "circle", h, WL_UM, F_MM, 0.0, 0.0)
    exact = (F_MM / math.sqrt(math.pi * h * h)) * ((1 / F_MM - 1 / math.hypot(h, F_MM))
                                                    - 0.5j * k * math.log1p(h * h / F_MM ** 2))
    assert abs(u_circ - exact) < 1e-11 * abs(exact)
    # square: int f/R^3 = solid angle 4 atan(h^2/(f sqrt(2h^2+f^2))); int 1/R^2 by a 1-D quadrature
    u_sq = gt.rs_thin_lens_field(F_MM, "square", h, WL_UM, F_MM, 0.0, 0.0, quad_rtol=1e-12)
    u_sq_default = gt.rs_thin_lens_field(F_MM, "square", h, WL_UM, F_MM, 0.0, 0.0)   # quad_rtol 1e-9
    solid = 4 * math.atan(h * h / (F_MM * math.sqrt(2 * h * h + F_MM ** 2)))
    def strip(x):
        c = math.sqrt(x * x + F_MM ** 2)
        return 2 / c * math.atan(h / c)                 # int_{-h}^{h} dy/(x^2 + y^2 + f^2)
    inv_r2, _ = integrate.quad(strip, -h, h, epsabs=0, epsrel=1e-13)
    exact = (1 / (2 * h)) * (solid - 1j * k * F_MM * inv_r2) / (2 * math.pi)
    assert abs(u_sq - exact) < 1e-11 * abs(exact)
    assert abs(u_sq_default - exact) < 1e-9 * abs(exact)
    # peak intensity: a^2/(lambda f)^2 up to O(NA^2)
    assert abs(u_sq) ** 2 == pytest.approx((2 * h) ** 2 / (WL_MM * F_MM) ** 2, rel=2e-4)


def test_rs_defocused_on_axis_matches_radial_quadrature():
    # circle, sensor 2 mm beyond focus: U(0, z) = A z int_0^h (1/rho - jk)/rho^2 exp(jk(rho - R)) r dr
    k = 2 * math.pi / WL_MM
    h, z = 1.0, F_MM + 2.0

    def integrand(r, part):
        rho, big_r = math.hypot(r, z), math.hypot(r, F_MM)
        phase = k * ((z - F_MM) * (z + F_MM) / (rho + big_r))
        val = (1 / rho - 1j * k) / rho ** 2 * complex(math.cos(phase), math.sin(phase)) * r
        return val.real if part == 0 else val.imag
    re, _ = integrate.quad(integrand, 0, h, args=(0,), epsabs=0, epsrel=1e-13, limit=200)
    im, _ = integrate.quad(integrand, 0, h, args=(1,), epsabs=0, epsrel=1e-13, limit=200)
    exact = z / math.sqrt(math.pi * h * h) * complex(re, im)
    got = gt.rs_thin_lens_field(F_MM, "circle", h, WL_UM, z, 0.0, 0.0, quad_rtol=1e-12)
    assert abs(got - exact) < 1e-11 * abs(exact)
    got = gt.rs_thin_lens_field(F_MM, "circle", h, WL_UM, z, 0.0, 0.0)       # default quad_rtol 1e-9
    assert abs(got - exact) < 2e-9 * abs(exact)


@pytest.mark.parametrize("side, bound", [(2.0, 1.5e-4), (1.0, 4e-5)])
def test_rs_square_matches_fraunhofer(side, bound):
    c = centred(32, 0.002)
    psf = gt.rs_thin_lens_psf(F_MM, "square", side / 2, WL_UM, F_MM, c, c, 0.002)
    ref = analytic.square_aperture_pixel_psf(c, c, 0.002, side, F_MM, WL_UM)
    err = rel_l2(psf, ref)
    na2 = (side / 2 / F_MM) ** 2
    assert err < bound
    assert 0.8 * na2 < err < 1.2 * na2                 # the O(NA^2) physics: measured err / NA^2 = 0.97, 0.94


def test_rs_circle_matches_airy():
    c = centred(32, 0.002)
    errs = []
    for diameter in (2.0, 1.0):
        psf = gt.rs_thin_lens_psf(F_MM, "circle", diameter / 2, WL_UM, F_MM, c, c, 0.002)
        ref = analytic.circular_aperture_pixel_psf(c, c, 0.002, diameter, F_MM, WL_UM)
        errs.append(rel_l2(psf, ref))
    assert errs[0] < 1.2e-4 and errs[1] < 3e-5
    assert 3.8 < errs[0] / errs[1] < 4.2                # scales as NA^2 (measured 4.00)


def test_rs_tilted_wave_focuses_off_axis():
    # A linear-phase DOE (smooth callable path) of direction sine s moves the focus to f s/sqrt(1-s^2).
    # A converging sphere times a tilt is not a sphere about the new focus: the residual is coma,
    # W ~ k s h^3/(2 f^2) = 1.4e-4 rad here (it gives the PSF an antisymmetric part ~W/2 relative,
    # 8x more for a 2 mm aperture, as measured), on top of the O(NA^2) 2.5e-5.
    s, side = 0.002, 1.0
    k = 2 * math.pi / WL_MM
    shift = F_MM * s / math.sqrt(1 - s * s)
    cx, cy = centred(24, 0.0025, shift), centred(24, 0.0025)
    psf = gt.rs_thin_lens_psf(F_MM, "square", side / 2, WL_UM, F_MM, cx, cy, 0.0025,
                              doe_phase=lambda x, y: k * s * x)
    ref = analytic.square_aperture_pixel_psf(cx - shift, cy, 0.0025, side, F_MM, WL_UM)
    assert rel_l2(psf, ref) < 1.5e-4
    # a focus misplaced by 1% of a pixel would already show
    off = analytic.square_aperture_pixel_psf(cx - shift - 2.5e-5, cy, 0.0025, side, F_MM, WL_UM)
    assert rel_l2(psf, off) > 2 * rel_l2(psf, ref)


def test_rs_energy_in_large_window():
    # +-23 lobes of lambda f/a: the exact window energy is 0.9912; the RS PSF must hold >= 0.99
    side = 2.0
    lobe = WL_MM * F_MM / side
    c = centred(46, lobe)
    # 4 pi-rad cells: half the cost; the scene is even in x and y and c is symmetric: one quadrant of pixels,
    # mirrored (tests/rwwarp/_mirror.py), a quarter of the cost
    psf = mirrored_truth(lambda qx, qy: gt.rs_thin_lens_psf(F_MM, "square", side / 2, WL_UM, F_MM, qx, qy, lobe,
                                                            quad_rtol=1e-6, max_cell_phase_rad=4 * math.pi), c, c)
    window = analytic.square_aperture_window_energy(c[0] - lobe / 2, c[-1] + lobe / 2,
                                                    c[0] - lobe / 2, c[-1] + lobe / 2, side, F_MM, WL_UM)
    assert psf.sum() >= 0.99
    assert psf.sum() == pytest.approx(window, abs=1e-3)    # 3 sensor nodes per lobe-wide pixel
    assert psf.sum() <= 1.0


def test_rs_converges_under_refinement():
    c = centred(16, 0.003)
    kwargs = dict(doe_phase=(np.pi * (np.indices((20, 20)).sum(axis=0) % 4 == 0), 0.1))
    psf, err = gt.rs_thin_lens_psf(F_MM, "circle", 1.0, WL_UM, F_MM + 0.5, c, c, 0.003, tolerance=1e-8,
                                   gauss_nodes_sensor=2, **kwargs)
    assert err < 1e-8
    # the brief's rule (< 0.3 rad per cell) and the default (2 pi-rad cells, more nodes) agree
    fine = gt.rs_thin_lens_psf(F_MM, "square", 1.0, WL_UM, F_MM + 0.5, c, c, 0.003,
                               max_cell_phase_rad=0.3, gauss_nodes_sensor=2)
    default = gt.rs_thin_lens_psf(F_MM, "square", 1.0, WL_UM, F_MM + 0.5, c, c, 0.003, gauss_nodes_sensor=2)
    assert rel_l2(default, fine) < 1e-9


def test_constant_pi_pixel_map_changes_nothing():
    c = centred(24, 0.002)
    plain = gt.rs_thin_lens_psf(F_MM, "square", 1.0, WL_UM, F_MM, c, c, 0.002)
    flat = gt.rs_thin_lens_psf(F_MM, "square", 1.0, WL_UM, F_MM, c, c, 0.002,
                               doe_phase=(np.full((20, 20), np.pi), 0.1))
    assert rel_l2(flat, plain) < 1e-10


def test_checkerboard_pixel_map_matches_callable():
    # 0/pi checkerboard of 0.25 mm squares over a 2 mm square aperture: the pixel-map path and the
    # callable path (cells aligned with the squares so no Gauss rule straddles a step) agree
    pitch, h = 0.25, 1.0
    board = np.pi * (np.indices((8, 8)).sum(axis=0) % 2)

    def board_fn(x, y):                                 # map convention: row 0 at +y, column 0 at -x
        row = np.floor((h - y) / pitch).astype(int)
        col = np.floor((x + h) / pitch).astype(int)
        return np.pi * ((row + col) % 2)
    c = centred(24, 0.010)                               # +-120 um: sees the (+-1, +-1) orders at 110 um
    common = dict(gauss_nodes_sensor=2, quad_rtol=1e-12)
    by_map = gt.rs_thin_lens_psf(F_MM, "square", h, WL_UM, F_MM, c, c, 0.010, doe_phase=(board, pitch),
                                 **common)
    by_fn = gt.rs_thin_lens_psf(F_MM, "square", h, WL_UM, F_MM, c, c, 0.010, doe_phase=board_fn,
                                doe_gradient_rad_per_mm=0.0, aperture_cells=16, **common)
    assert rel_l2(by_fn, by_map) < 1e-11
    # and the checkerboard really diffracts: the zero order (on axis) is dark, the diagonal orders bright
    centre = by_map[11:13, 11:13].sum()
    assert centre < 1e-3 * by_map.max()


def test_pixel_map_convention_is_that_of_doe_profiles():
    # An asymmetric 16-level map given as a PixelMapProfile (rwwarp.doe) and its own phase(x, y)
    # through the callable path (cells aligned with the pixels) give the same PSF; the map flipped
    # upside down does not.
    from rwwarp.doe import PixelMapProfile
    rng = np.random.default_rng(7)
    data = rng.integers(0, 16, size=(4, 6)) * (2 * np.pi / 16)
    profile = PixelMapProfile(0.25, data=data)
    c = centred(12, 0.010)
    common = dict(gauss_nodes_sensor=2, quad_rtol=1e-12)
    by_map = gt.rs_thin_lens_psf(F_MM, "square", 0.5, WL_UM, F_MM, c, c, 0.010, doe_phase=profile, **common)
    by_fn = gt.rs_thin_lens_psf(F_MM, "square", 0.5, WL_UM, F_MM, c, c, 0.010, doe_phase=profile.phase,
                                doe_gradient_rad_per_mm=0.0, aperture_cells=4, **common)
    assert rel_l2(by_fn, by_map) < 1e-11
    flipped = gt.rs_thin_lens_psf(F_MM, "square", 0.5, WL_UM, F_MM, c, c, 0.010,
                                  doe_phase=(data[::-1], 0.25), **common)
    assert rel_l2(flipped, by_map) > 1e-2
