"""DOE phase profiles against hand formulas, quantisation, wavelength remap and height maps."""
import math

import numpy as np
import pytest

from rwwarp import doe
from rwwarp.errors import LensError, LensFileError
from rwwarp.lens import Surface

RNG = np.random.default_rng(1234)
X = RNG.uniform(-2.0, 2.0, 200)
Y = RNG.uniform(-2.0, 2.0, 200)


def test_even_poly_is_zemax_binary2():
    p = doe.profile_from_dict({"kind": "even_poly", "norm_radius": 2.0, "coefficients": [3.0, -2.0, 0.5]})
    rho2 = (X ** 2 + Y ** 2) / 4.0
    np.testing.assert_allclose(p.phase(X, Y), 3.0 * rho2 - 2.0 * rho2 ** 2 + 0.5 * rho2 ** 3, rtol=1e-13,
                               atol=1e-13)
    assert p.quadratic_coefficient() == pytest.approx(3.0 / 4.0)


def test_poly_odd_and_even_terms():
    p = doe.profile_from_dict({"kind": "poly", "norm_radius": 1.5, "coefficients": [1.0, -2.0, 3.0, 0.25]})
    rho = np.hypot(X, Y) / 1.5
    np.testing.assert_allclose(p.phase(X, Y), rho - 2 * rho ** 2 + 3 * rho ** 3 + 0.25 * rho ** 4, rtol=1e-13,
                               atol=1e-13)
    gx, gy = p.gradient(np.array([0.0]), np.array([0.0]))
    assert gx[0] == 0.0 and gy[0] == 0.0  # the cone's gradient is reported as 0 on the axis


def test_fresnel_focal_length():
    f, lam0 = 50.0, 0.55
    p = doe.profile_from_dict({"kind": "fresnel", "focal_length": f})
    ref = -math.pi * (X ** 2 + Y ** 2) / (lam0 * 1e-3 * f)
    np.testing.assert_allclose(p.phase(X, Y, lam0), ref, rtol=1e-14)
    # local grating: a ray through (x, y) is deflected by sin(theta) = lambda0 / (2 pi) dphi/dx = -x / f,
    # i.e. every ray crosses the axis f behind the DOE
    gx, gy = p.gradient(X, Y, lam0)
    np.testing.assert_allclose(gx * lam0 * 1e-3 / (2 * math.pi), -X / f, rtol=1e-14)
    np.testing.assert_allclose(gy * lam0 * 1e-3 / (2 * math.pi), -Y / f, rtol=1e-14)
    assert -math.pi / (lam0 * 1e-3 * p.quadratic_coefficient(lam0)) == pytest.approx(f, rel=1e-14)
    # the same lens as a Binary 2 term: a1 = -pi R^2 / (lambda0 f)
    R = 1.7
    ev = doe.EvenPolyProfile(R, [-math.pi * R ** 2 / (lam0 * 1e-3 * f)])
    np.testing.assert_allclose(ev.phase(X, Y), p.phase(X, Y, lam0), rtol=1e-13)
    # narrowest zone at the rim: 2 pi / |dphi/dr| = lambda0 f / r
    assert p.feature_size_mm(1.0, lam0) == pytest.approx(lam0 * 1e-3 * f / 1.0, rel=1e-12)
    assert p.feature_size_mm(1.0, lam0, levels=16) == pytest.approx(lam0 * 1e-3 * f / 16, rel=1e-12)
    surf = Surface(type="doe", semi_diameter=1.0, design_wavelength_um=lam0, material="fused_silica",
                   levels=8, profile=p.to_dict())
    assert doe.surface_feature_size_mm(surf) == pytest.approx(lam0 * 1e-3 * f / 8, rel=1e-12)
    assert not doe.surface_is_continuous(surf)
    assert p.feature_size_mm(1.0, lam0, shape="square") == pytest.approx(lam0 * 1e-3 * f / math.sqrt(2),
                                                                     rel=1e-12)


def test_zernike_noll_values():
    R = 2.0
    r, t = np.hypot(X, Y) / R, np.arctan2(Y, X)
    hand = {
        1: np.ones_like(r),
        2: 2 * r * np.cos(t),
        3: 2 * r * np.sin(t),
        4: math.sqrt(3) * (2 * r ** 2 - 1),
        5: math.sqrt(6) * r ** 2 * np.sin(2 * t),
        6: math.sqrt(6) * r ** 2 * np.cos(2 * t),
        7: math.sqrt(8) * (3 * r ** 3 - 2 * r) * np.sin(t),
        8: math.sqrt(8) * (3 * r ** 3 - 2 * r) * np.cos(t),
        9: math.sqrt(8) * r ** 3 * np.sin(3 * t),
        10: math.sqrt(8) * r ** 3 * np.cos(3 * t),
        11: math.sqrt(5) * (6 * r ** 4 - 6 * r ** 2 + 1),
        12: math.sqrt(10) * (4 * r ** 4 - 3 * r ** 2) * np.cos(2 * t),
        13: math.sqrt(10) * (4 * r ** 4 - 3 * r ** 2) * np.sin(2 * t),
        22: math.sqrt(7) * (20 * r ** 6 - 30 * r ** 4 + 12 * r ** 2 - 1),
        29: 4 * (35 * r ** 7 - 60 * r ** 5 + 30 * r ** 3 - 4 * r) * np.sin(t),
        37: 3 * (70 * r ** 8 - 140 * r ** 6 + 90 * r ** 4 - 20 * r ** 2 + 1),
    }
    for j, ref in hand.items():
        c = [0.0] * j
        c[j - 1] = 1.0
        p = doe.profile_from_dict({"kind": "zernike", "norm_radius": R, "coefficients": c})
        np.testing.assert_allclose(p.phase(X, Y), ref, rtol=1e-12, atol=1e-11, err_msg=f"Z{j}")


def test_zernike_orthonormal_on_unit_disk():
    # Noll normalisation: (1/pi) * integral over the unit disk of Z_j Z_k = delta_jk
    # (Gauss-Legendre in r, uniform in theta)
    nr, nt = 40, 64
    xr, wr = np.polynomial.legendre.leggauss(nr)
    r = 0.5 * (xr + 1.0)
    w = 0.5 * wr * r
    t = np.arange(nt) * 2 * math.pi / nt
    rr, tt = np.meshgrid(r, t, indexing="ij")
    ww = np.repeat(w[:, None], nt, axis=1) * (2 * math.pi / nt)
    J = 22
    Z = []
    for j in range(1, J + 1):
        c = [0.0] * j
        c[-1] = 1.0
        Z.append(doe.ZernikeProfile(1.0, c).phase(rr * np.cos(tt), rr * np.sin(tt)))
    G = np.array([[np.sum(a * b * ww) for b in Z] for a in Z]) / math.pi
    np.testing.assert_allclose(G, np.eye(J), atol=1e-10)


def test_cubic():
    p = doe.profile_from_dict({"kind": "cubic", "norm_radius": 1.5, "alpha": 20.0})
    np.testing.assert_allclose(p.phase(X, Y), 20.0 * ((X / 1.5) ** 3 + (Y / 1.5) ** 3), rtol=1e-13)
    # max |grad| over the square of half side 1 is at the corner: 3 alpha / R^3 * sqrt(2)
    assert p.feature_size_mm(1.0, shape="square") == pytest.approx(
        2 * math.pi / (3 * 20.0 / 1.5 ** 3 * math.sqrt(2)), rel=1e-12)


@pytest.mark.parametrize("d", [
    {"kind": "even_poly", "norm_radius": 1.3, "coefficients": [30.0, -4.0, 2.0, 0.5]},
    {"kind": "poly", "norm_radius": 1.3, "coefficients": [3.0, -4.0, 2.0, 0.5, -1.0]},
    {"kind": "fresnel", "focal_length": -80.0},
    {"kind": "zernike", "norm_radius": 1.7, "coefficients": list(np.linspace(-1, 1, 37))},
    {"kind": "cubic", "norm_radius": 1.1, "alpha": 7.0},
])
def test_gradient_matches_finite_differences(d):
    p = doe.profile_from_dict(d)
    x, y = X[np.hypot(X, Y) > 1e-3], Y[np.hypot(X, Y) > 1e-3]
    h = 1e-6
    gx, gy = p.gradient(x, y, 0.55)
    fx = (p.phase(x + h, y, 0.55) - p.phase(x - h, y, 0.55)) / (2 * h)
    fy = (p.phase(x, y + h, 0.55) - p.phase(x, y - h, 0.55)) / (2 * h)
    scale = max(np.max(np.abs(fx)), np.max(np.abs(fy)))
    np.testing.assert_allclose(gx, fx, atol=1e-7 * scale)
    np.testing.assert_allclose(gy, fy, atol=1e-7 * scale)
    assert p.is_continuous
    assert doe.profile_from_dict(p.to_dict()) == p


def test_pixel_map_sampling_and_orientation(tmp_path):
    data = np.arange(12, dtype=float).reshape(3, 4)  # 3 rows (y), 4 columns (x)
    pitch = 0.5
    p = doe.profile_from_dict({"kind": "pixel_map", "data": data.tolist(), "pitch": pitch})
    assert not p.is_continuous
    # pixel (row, col) centre at x = (col - 1.5) pitch, y = (1 - row) pitch
    for row in range(3):
        for col in range(4):
            x, y = (col - 1.5) * pitch, (1 - row) * pitch
            jitter = 0.49 * pitch
            for dx, dy in ((0, 0), (jitter, jitter), (-jitter, -jitter)):
                assert p.phase(np.array([x + dx]), np.array([y + dy]))[0] == data[row, col]
    # zero outside the map
    assert p.phase(np.array([2.1 * pitch, 0.0]), np.array([0.0, 1.6 * pitch])).tolist() == [0.0, 0.0]
    with pytest.raises(LensError, match="discontinuous phase: no gradient"):
        p.gradient(np.zeros(1), np.zeros(1))
    assert p.feature_size_mm(1.0) == pitch
    # file form, relative to the lens file's folder
    np.save(tmp_path / "map.npy", data)
    q = doe.profile_from_dict({"kind": "pixel_map", "file": "map.npy", "pitch": pitch}, base=tmp_path)
    np.testing.assert_array_equal(q.phase(X, Y), p.phase(X, Y))
    assert q.to_dict() == {"kind": "pixel_map", "file": "map.npy", "pitch": pitch}
    with pytest.raises(LensFileError, match="not found"):
        doe.profile_from_dict({"kind": "pixel_map", "file": "nope.npy", "pitch": pitch}, base=tmp_path)


@pytest.mark.parametrize("d, match", [
    ({"kind": "spiral"}, "unknown"),
    ({"norm_radius": 1.0}, "kind"),
    ({"kind": "even_poly", "norm_radius": 1.0, "coefficients": [], "order": 1}, "profile.order"),
    ({"kind": "even_poly", "coefficients": [1.0]}, "profile.norm_radius"),
    ({"kind": "even_poly", "norm_radius": -1.0, "coefficients": [1.0]}, "norm_radius must be > 0"),
    ({"kind": "zernike", "norm_radius": 1.0, "coefficients": [1.0, "a"]}, r"coefficients\[1\]"),
    ({"kind": "fresnel", "focal_length": 0.0}, "non-zero"),
    ({"kind": "pixel_map", "pitch": 0.1}, "exactly one"),
    ({"kind": "pixel_map", "pitch": 0.1, "data": [[1.0, 2.0], [3.0]]}, "rectangular"),
    ("even_poly", "object"),
])
def test_bad_profile_dicts(d, match):
    with pytest.raises(LensFileError, match=match):
        doe.profile_from_dict(d)


def test_quantize_levels():
    phi = np.linspace(-10.0, 10.0, 100001)
    for n in (2, 4, 16):
        q = doe.quantize(phi, n)
        levels = np.unique(q)
        np.testing.assert_allclose(levels, np.arange(n) * 2 * math.pi / n, atol=1e-15)
        # error against the wrapped phase (modulo 2 pi) at most half a step
        err = np.angle(np.exp(1j * (q - phi)))
        assert np.max(np.abs(err)) <= math.pi / n + 1e-12
    assert doe.quantize(np.array([2 * math.pi - 1e-9]), 8)[0] == 0.0
    w = doe.wrap_phase(phi)
    assert w.min() >= 0.0 and w.max() < 2 * math.pi


def _fused_silica_malitson(lam):
    l2 = lam * lam
    return math.sqrt(1 + 0.6961663 * l2 / (l2 - 0.0684043 ** 2) + 0.4079426 * l2 / (l2 - 0.1162414 ** 2)
                     + 0.8974794 * l2 / (l2 - 9.896161 ** 2))


def test_wavelength_scale_fused_silica():
    lam0 = 0.55
    assert doe.wavelength_scale("fused_silica", lam0, lam0) == pytest.approx(1.0, abs=1e-15)
    n0 = _fused_silica_malitson(lam0)
    for lam in (0.45, 0.65):
        ref = (_fused_silica_malitson(lam) - 1) / (n0 - 1) * lam0 / lam
        assert doe.wavelength_scale("fused_silica", lam0, lam) == pytest.approx(ref, rel=2e-5)
    s = doe.wavelength_scale("fused_silica", lam0, np.array([0.45, 0.55, 0.65]))
    assert s.shape == (3,) and s[0] > 1.0 > s[2]  # diffractive dispersion: shorter waves see more phase


def test_height_map_values(tmp_path):
    lam0 = 0.55
    n0 = _fused_silica_malitson(lam0)
    phi = np.array([0.0, math.pi, 2 * math.pi + math.pi / 2, -math.pi / 2])
    h = doe.height_map_um(phi, "fused_silica", lam0)
    full = lam0 / (n0 - 1)  # 2 pi of phase, um
    np.testing.assert_allclose(h, [0.0, full / 2, full / 4, 3 * full / 4], rtol=2e-5)

    surf = Surface(type="doe", semi_diameter=0.05, shape="circle", design_wavelength_um=lam0,
                   material="fused_silica", profile={"kind": "fresnel", "focal_length": 1.0})
    prof = doe.get_profile(surf)
    hm = doe.export_height_map(prof, surf, tmp_path / "out" / "doe", pitch_mm=0.001, levels=4)
    assert hm.npy_path.exists() and hm.png_path.exists() and hm.png_path.stat().st_size > 1000
    arr = np.load(hm.npy_path)
    assert arr.shape == (100, 100)
    np.testing.assert_array_equal(arr, hm.height_um)
    steps = np.unique(np.round(arr / (full / 4), 3))
    assert set(steps.tolist()) <= {0.0, 1.0, 2.0, 3.0} and len(steps) == 4
    t = (np.arange(100) - 49.5) * 0.001
    xx, yy = np.meshgrid(t, t[::-1])
    assert np.all(arr[xx ** 2 + yy ** 2 > 0.05 ** 2] == 0.0)
    # continuous export: heights of the wrapped phase
    hc = doe.export_height_map(prof, surf, tmp_path / "c", pitch_mm=0.001).height_um
    inside = xx ** 2 + yy ** 2 <= 0.05 ** 2
    ref = doe.height_map_um(prof.phase(xx, yy, lam0), "fused_silica", lam0)
    np.testing.assert_allclose(hc[inside], ref[inside], rtol=0, atol=1e-12)
    assert hc.max() < full * (1 + 1e-4)


def test_modulation_phase_at_design_wavelength_is_wrapped_phase():
    p = doe.FresnelProfile(20.0)
    m = doe.modulation_phase(p, X, Y, 0.55, 0.55, "fused_silica")
    np.testing.assert_allclose(np.exp(1j * m), np.exp(1j * p.phase(X, Y, 0.55)), atol=1e-9)
    assert m.min() >= 0 and m.max() < 2 * math.pi


@pytest.mark.parametrize("kind,coeffs", [("even_poly", [-20.0, 8.0, 3.0, -1.0]), ("poly", [1.5, -20.0, 4.0, 2.0])])
def test_radial_gradient_against_finite_differences(kind, coeffs):
    """rwwarp.doe.radial_gradient_over_r (through Profile.gradient) against central differences of
    Profile.phase (h = 1e-6 mm; measured 1.7e-10 relative, tolerance 1e-9). Torch: see
    test_profile_functions_in_torch_follow_the_hand_formulas."""
    from rwwarp.doe import profile_from_dict
    prof = profile_from_dict({"kind": kind, "norm_radius": 1.3, "coefficients": coeffs})
    rng = np.random.default_rng(7)
    x, y = rng.uniform(-1.2, 1.2, 50), rng.uniform(-1.2, 1.2, 50)
    gx, gy = prof.gradient(x, y)
    h = 1e-6
    fx = (prof.phase(x + h, y) - prof.phase(x - h, y)) / (2 * h)
    fy = (prof.phase(x, y + h) - prof.phase(x, y - h)) / (2 * h)
    scale = np.max(np.hypot(fx, fy))
    assert np.max(np.abs(gx - fx)) < 1e-9 * scale and np.max(np.abs(gy - fy)) < 1e-9 * scale


# ---------------------------------------------------------------- one implementation for every namespace
def test_rwwarp_doe_imports_no_torch_and_infers_the_namespace():
    """rwwarp.doe runs the shared phase code without torch (a fresh interpreter); the namespace of lists,
    numbers and numpy arrays is numpy (float64 results), of a torch tensor torch."""
    import subprocess
    import sys
    code = ("import sys, numpy as np\nfrom rwwarp import doe\n"
            "p = doe.profile_from_dict({'kind': 'zernike', 'norm_radius': 1.0,\n"
            "                           'coefficients': [0, 1, 2, 3]})\n"
            "doe.design_phase(p, np.zeros(3), np.ones(3), 0.55, 8)\n"
            "assert 'torch' not in sys.modules, 'torch was imported'\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False)
    assert r.returncode == 0, r.stderr[-2000:]
    assert doe.array_namespace([1.0], 2.0, np.ones(2)) is np
    w = doe.wrap_phase([-1.0, 7.0])
    assert w.dtype == np.float64 and w.tolist() == [2 * math.pi - 1.0, 7.0 - 2 * math.pi]
    assert float(doe.wrap_phase(-1.0)) == 2 * math.pi - 1.0      # scalars too
    torch = pytest.importorskip("torch")
    assert doe.array_namespace(np.ones(2), torch.ones(2)) is torch


@pytest.mark.parametrize("levels", [None, 2, 8])
@pytest.mark.parametrize("ns", ["numpy", "torch"])
def test_wrap_and_quantize_follow_the_equations(ns, levels):
    """rwwarp.doe.relief_phase (the forward of torch_bridge.QuantizeSTE too) on numpy arrays (float64) and
    torch tensors (float64 and float32) against the definition written with other arithmetic: ``np.mod`` for
    the wrap (circular distance: np.mod rounds a tiny negative phase up to 2 pi), the level index
    ``round(w L / 2 pi) mod L`` for the staircase, the value ``k 2 pi / L``."""
    phi = np.concatenate([RNG.uniform(-50.0, 50.0, 5000), [0.0, -1e-20, 2 * math.pi, -2 * math.pi]])
    w_ref = np.mod(phi, 2 * math.pi)
    # tolerances (wrap, level): float64 measured 0 and 0, allowed a few ulp of 50 rad and of 2 pi;
    # float32 measured 4.6e-6 (the input's rounding, ulp(50) = 3.8e-6) and 3.3e-7 (ulp(2 pi) = 4.8e-7)
    if ns == "numpy":
        cases = [(lambda a: a, np.float64, 1e-13, 4e-15)]
    else:
        torch = pytest.importorskip("torch")
        cases = [(lambda a, dt=dt: torch.tensor(a, dtype=dt), dt, tol, tol_q)
                 for dt, tol, tol_q in ((torch.float64, 1e-13, 4e-15), (torch.float32, 2e-5, 1e-6))]
    for make, dt, tol, tol_q in cases:
        got = doe.relief_phase(make(phi), levels)
        assert got.dtype == dt
        g = np.asarray(got, dtype=np.float64) if ns == "numpy" else got.double().numpy()
        assert g.min() >= 0.0 and g.max() < 2 * math.pi
        if levels is None:
            d = np.abs(g - w_ref)
            assert np.max(np.minimum(d, 2 * math.pi - d)) < tol
        else:
            step = 2 * math.pi / levels
            k = np.rint(w_ref / step) % levels
            near_tie = np.abs(np.mod(w_ref / step, 1.0) - 0.5) < 1e-4   # float32 may round either way there
            np.testing.assert_allclose(g[~near_tie], (k * step)[~near_tie], rtol=0, atol=tol_q)
            assert set(np.round(g / step).astype(int)) <= set(range(levels))
        assert g[-4] == 0.0 and g[-3] == 0.0 and g[-2] == 0.0 and g[-1] == 0.0   # 0, -0, +-2 pi: level 0


def _hand_profiles(R):
    """Hand formulas (numpy) of every smooth kind: {name: (profile dict, values, phi(x, y, values))}."""
    def zern(x, y, c):
        r, t = np.hypot(x, y) / R, np.arctan2(y, x)
        z = [np.ones_like(r), 2 * r * np.cos(t), 2 * r * np.sin(t), math.sqrt(3) * (2 * r ** 2 - 1),
             math.sqrt(6) * r ** 2 * np.sin(2 * t), math.sqrt(6) * r ** 2 * np.cos(2 * t),
             math.sqrt(8) * (3 * r ** 3 - 2 * r) * np.sin(t), math.sqrt(8) * (3 * r ** 3 - 2 * r) * np.cos(t),
             math.sqrt(8) * r ** 3 * np.sin(3 * t), math.sqrt(8) * r ** 3 * np.cos(3 * t),
             math.sqrt(5) * (6 * r ** 4 - 6 * r ** 2 + 1)]
        return sum(ci * zi for ci, zi in zip(c, z))
    return {
        "even_poly": ([3.0, -2.0, 0.5], lambda x, y, c: sum(
            a * ((x * x + y * y) / R ** 2) ** (i + 1) for i, a in enumerate(c))),
        "poly": ([1.0, -2.0, 3.0, 0.25], lambda x, y, c: sum(
            a * (np.hypot(x, y) / R) ** (k + 1) for k, a in enumerate(c))),
        "fresnel": ([-40.0], lambda x, y, c: -math.pi * (x * x + y * y) / (0.55e-3 * c[0])),
        "cubic": ([7.0], lambda x, y, c: c[0] * ((x / R) ** 3 + (y / R) ** 3)),
        "zernike": (list(np.linspace(-1.0, 1.0, 11)), zern),
    }


def _profile_dict(kind, R, vals):
    if kind == "cubic":
        return {"kind": "cubic", "norm_radius": R, "alpha": vals[0]}
    if kind == "fresnel":
        return {"kind": "fresnel", "focal_length": vals[0]}
    return {"kind": kind, "norm_radius": R, "coefficients": vals}


def _hand_gradient(hand, x, y, vals, h=1e-6):
    """Central differences (h mm) of a hand formula: (dphi/dx, dphi/dy)."""
    return ((hand(x + h, y, vals) - hand(x - h, y, vals)) / (2 * h),
            (hand(x, y + h, vals) - hand(x, y - h, vals)) / (2 * h))


@pytest.mark.parametrize("kind", ["even_poly", "poly", "fresnel", "cubic", "zernike"])
def test_profile_classes_follow_the_hand_formulas(kind):
    """The numpy profile classes (Profile.phase / gradient: rwwarp.doe.profile_phase / profile_gradient) against
    the hand formulas: the phase (measured <= 6.4e-16 of the largest |phi|) and the gradient against central
    differences of the hand formula (h = 1e-6 mm; measured <= 3.0e-10 of the largest)."""
    R = 1.3
    vals, hand = _hand_profiles(R)[kind]
    x, y = X[np.hypot(X, Y) > 1e-2], Y[np.hypot(X, Y) > 1e-2]   # away from the cone's apex (poly rho^1)
    prof = doe.profile_from_dict(_profile_dict(kind, R, vals))
    assert prof.values == vals
    ref = hand(x, y, vals)
    scale = np.max(np.abs(ref))
    np.testing.assert_allclose(prof.phase(x, y, 0.55), ref, rtol=0, atol=4e-15 * scale)
    fx, fy = _hand_gradient(hand, x, y, vals)
    gs = max(np.max(np.abs(fx)), np.max(np.abs(fy)))
    gx, gy = prof.gradient(x, y, 0.55)
    np.testing.assert_allclose(gx, fx, rtol=0, atol=2e-9 * gs)
    np.testing.assert_allclose(gy, fy, rtol=0, atol=2e-9 * gs)


@pytest.mark.parametrize("kind", ["even_poly", "poly", "fresnel", "cubic", "zernike", "pixel_map"])
def test_profile_with_values_writes_the_learnable_values_back(kind, tmp_path):
    """profile_with_values (HybridLens.to_lens) is the inverse of Profile.values: the profile rebuilt from the
    dictionary with new values has those values and the hand formula's phase with them (a pixel map written
    inline, its file dropped); the input dictionary is not changed."""
    R = 1.3
    if kind == "pixel_map":
        np.save(tmp_path / "m.npy", np.zeros((3, 4)))
        d = {"kind": "pixel_map", "pitch": 0.5, "file": str(tmp_path / "m.npy")}
        new = RNG.uniform(0.0, 6.0, (3, 4))
    else:
        vals, hand = _hand_profiles(R)[kind]
        d = _profile_dict(kind, R, [0.0] * len(vals) if kind not in ("fresnel",) else [10.0])
        new = vals
    before = dict(d)
    out = doe.profile_with_values(d, new)
    assert d == before
    prof = doe.profile_from_dict(out)
    np.testing.assert_array_equal(np.asarray(prof.values), np.asarray(new))
    if kind == "pixel_map":
        assert "file" not in out and prof.phase(np.array([-0.9]), np.array([0.6]))[0] == new[0, 0]
    else:
        np.testing.assert_allclose(prof.phase(X, Y, 0.55), hand(X, Y, new), rtol=0,
                                   atol=4e-15 * np.max(np.abs(hand(X, Y, new))))
    with pytest.raises(LensFileError, match="kind"):
        doe.profile_with_values({"kind": "spline"}, [1.0])


def test_profile_dispatch_names_the_kinds():
    """profile_phase / profile_gradient / profile_quadratic refuse a kind that is not smooth, naming the smooth
    kinds, and a missing or bad norm_radius, naming it (Fresnel needs none)."""
    for f in (doe.profile_phase, doe.profile_gradient, doe.profile_quadratic):
        args = (X, Y) if f is not doe.profile_quadratic else ()
        with pytest.raises(ValueError, match="even_poly.*pixel_map_phase"):
            f("pixel_map", [1.0], *args, norm_radius=1.0)
        for R in (None, 0.0, -1.0):
            with pytest.raises(ValueError, match="'zernike' DOE profile needs norm_radius"):
                f("zernike", [1.0], *args, norm_radius=R)
        f("fresnel", [50.0], *args)


@pytest.mark.parametrize("kind", ["even_poly", "poly", "fresnel", "cubic", "zernike"])
def test_profile_functions_in_torch_follow_the_hand_formulas(kind):
    """rwwarp.doe.profile_phase / profile_gradient on torch tensors, as the design loop calls them (learnable
    values; HybridLens.doe_phase, RaySpot's grating), against hand formulas in numpy: the phase; its gradient
    in the values (autograd) and in x, y (autograd) against central differences of the hand formula;
    profile_gradient against central differences of the hand formula, and its own derivatives in the values
    and in x (autograd: the ray model differentiates its grating) against central differences of it."""
    torch = pytest.importorskip("torch")
    R = 1.3
    vals, hand = _hand_profiles(R)[kind]
    x, y = X[np.hypot(X, Y) > 1e-2], Y[np.hypot(X, Y) > 1e-2]   # away from the cone's apex (poly rho^1)
    kw = {"norm_radius": None if kind == "fresnel" else R, "design_wavelength_um": 0.55}
    v = torch.tensor(vals, dtype=torch.float64, requires_grad=True)
    xt = torch.tensor(x, requires_grad=True)
    yt = torch.tensor(y, requires_grad=True)
    phi = doe.profile_phase(kind, v, xt, yt, **kw)               # the namespace from the tensors
    ref = hand(x, y, vals)
    scale = np.max(np.abs(ref))
    # measured <= 6.4e-16 relative to the largest |phi| (zernike)
    np.testing.assert_allclose(phi.detach().numpy(), ref, rtol=0, atol=4e-15 * scale)
    wgt = np.cos(np.arange(x.size))                               # a generic weighted sum of the samples
    (phi * torch.from_numpy(wgt)).sum().backward()
    # d/d values: central differences (h = 1e-6 relative) of the hand formula; measured <= 7.3e-9 relative
    # (zernike: cancellation in the weighted sum)
    for i in range(len(vals)):
        h = 1e-6 * max(1.0, abs(vals[i]))
        vp, vm = list(vals), list(vals)
        vp[i] += h
        vm[i] -= h
        fd = np.sum(wgt * (hand(x, y, vp) - hand(x, y, vm))) / (2 * h)
        assert v.grad[i].item() == pytest.approx(fd, rel=1e-7, abs=1e-7 * scale)
    # d/dx, d/dy: central differences (h = 1e-6 mm) of the hand formula; measured <= 2.6e-10 of the largest
    fx, fy = _hand_gradient(hand, x, y, vals)
    gs = max(np.max(np.abs(fx)), np.max(np.abs(fy)))
    np.testing.assert_allclose(xt.grad.numpy(), wgt * fx, rtol=0, atol=2e-9 * gs)
    np.testing.assert_allclose(yt.grad.numpy(), wgt * fy, rtol=0, atol=2e-9 * gs)
    # profile_gradient: the same hand differences (measured <= 3.0e-10 of the largest)
    v.grad = xt.grad = None
    gx, gy = doe.profile_gradient(kind, v, xt, yt, **kw)
    np.testing.assert_allclose(gx.detach().numpy(), fx, rtol=0, atol=2e-9 * gs)
    np.testing.assert_allclose(gy.detach().numpy(), fy, rtol=0, atol=2e-9 * gs)
    # its derivatives: autograd against central differences of profile_gradient itself (values: h = 1e-5
    # relative, x: h = 1e-6 mm; measured <= 3.5e-12 and 1.5e-11 of sum |weight * gradient|; tolerance 1e-10)
    w2 = np.sin(np.arange(x.size))

    def loss(vv, xx):
        gxy = doe.profile_gradient(kind, torch.tensor(vv, dtype=torch.float64), torch.from_numpy(xx),
                                   torch.from_numpy(y), **kw)
        return float(np.sum(gxy[0].numpy() * wgt + gxy[1].numpy() * w2))
    ((gx * torch.from_numpy(wgt)).sum() + (gy * torch.from_numpy(w2)).sum()).backward()
    lscale = np.sum(np.abs(wgt * fx) + np.abs(w2 * fy))
    for i in range(len(vals)):
        h = 1e-5 * max(1.0, abs(vals[i]))
        vp, vm = list(vals), list(vals)
        vp[i] += h
        vm[i] -= h
        assert v.grad[i].item() == pytest.approx((loss(vp, x) - loss(vm, x)) / (2 * h), abs=1e-10 * lscale)
    h = 1e-6
    for j in range(0, x.size, 37):                                  # a few samples: one loss each
        xp_, xm_ = x.copy(), x.copy()
        xp_[j] += h
        xm_[j] -= h
        assert xt.grad[j].item() == pytest.approx((loss(vals, xp_) - loss(vals, xm_)) / (2 * h),
                                                  abs=1e-10 * lscale)


def test_pixel_map_functions_in_torch_sample_and_scatter_by_hand():
    """pixel_map_indices / pixel_map_phase on torch tensors: each sample takes the value of the pixel whose
    square contains it (centres at x = (col - (nx-1)/2) p, y = ((ny-1)/2 - row) p), 0 outside; the
    gradient in the map counts the samples per pixel (np.add.at of the hand indices)."""
    torch = pytest.importorskip("torch")
    ny, nx, p = 5, 7, 0.3
    data = RNG.uniform(0.5, 6.0, (ny, nx))
    x, y = RNG.uniform(-1.4, 1.4, 3000), RNG.uniform(-1.0, 1.0, 3000)
    col_h = np.floor((x + nx * p / 2) / p).astype(int)             # pixel edges from -nx p / 2 to +nx p / 2
    row_h = np.floor((ny * p / 2 - y) / p).astype(int)
    inside_h = (col_h >= 0) & (col_h < nx) & (row_h >= 0) & (row_h < ny)
    assert 0 < inside_h.sum() < x.size                           # both inside and outside samples
    ref = np.where(inside_h, data[np.clip(row_h, 0, ny - 1), np.clip(col_h, 0, nx - 1)], 0.0)
    dt = torch.tensor(data, requires_grad=True)
    row, col, inside = doe.pixel_map_indices(p, (ny, nx), torch.from_numpy(x), torch.from_numpy(y), torch)
    phi = doe.pixel_map_phase(dt, row, col, inside, torch)
    np.testing.assert_array_equal(phi.detach().numpy(), ref)
    phi.sum().backward()
    counts = np.zeros((ny, nx))
    np.add.at(counts, (row_h[inside_h], col_h[inside_h]), 1.0)
    np.testing.assert_array_equal(dt.grad.numpy(), counts)
    prof = doe.profile_from_dict({"kind": "pixel_map", "pitch": p, "data": data.tolist()})
    np.testing.assert_array_equal(prof.phase(x, y), ref)


def test_zernike_quadratic_coefficient_by_hand():
    """The paraxial r^2 coefficient of a Zernike DOE from the hand formulas of the rotationally symmetric
    terms up to j = 37 (Z4 = sqrt(3) (2 rho^2 - 1), Z11 = sqrt(5) (6 rho^4 - 6 rho^2 + 1),
    Z22 = sqrt(7) (20 rho^6 - 30 rho^4 + 12 rho^2 - 1), Z37 = 3 (70 rho^8 - ... - 20 rho^2 + 1)): their
    rho^2 coefficients over R^2; the others (tilt, astigmatism, coma, ...) have no rotationally symmetric
    r^2 part. Relative tolerance: a few ulp of the sum."""
    R = 1.7
    c = list(np.linspace(-1.0, 1.0, 37))
    p = doe.ZernikeProfile(R, c)
    z = dict(enumerate(c, start=1))
    q_hand = (2 * math.sqrt(3) * z[4] - 6 * math.sqrt(5) * z[11] + 12 * math.sqrt(7) * z[22]
              - 20 * 3 * z[37]) / R ** 2
    assert p.quadratic_coefficient() == pytest.approx(q_hand, rel=1e-14)
