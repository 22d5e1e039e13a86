"""The Kirchhoff form's tile expansion (rwwarp.wave.pixel_kirchhoff) piece by piece, against independent references:
the exact distance (numpy), the non-uniform DFT written out, and the Rayleigh-Sommerfeld sum (test_pixel_scale)."""
import math

import numpy as np
import pytest

from rwwarp.wave import pixel_kirchhoff as pk
from rwwarp.wave.nufft import nufft_type1


def test_quadratic_and_cubic_monomials_are_the_distance_expansion():
    """``|X + D - p| = r + u.D + sum_a g_a b_a(D) + sum_i c_i m_i(D) + O(|D|^4 / r^3)`` with the 3 quadratic monomials
    (D_x^2, D_x D_y, D_y^2) and the 4 cubic ones (D_x^3, D_x^2 D_y, D_x D_y^2, D_y^3): the rest over |D|^4 / r^3 stays
    bounded (measured 0.13-0.17) as |D| halves twice, so every term through the cubic is right (a wrong quadratic or
    cubic coefficient leaves a rest of order |D|^2 / r or |D|^3 / r^2: its ratio would grow 4x or 2x a halving)."""
    rng = np.random.default_rng(3)
    P = np.stack([rng.uniform(-8, 8, 200), rng.uniform(-8, 8, 200), np.zeros(200)], -1)   # f/1.2 wide, 38 mm on
    X = np.array([3.0, -7.0, 38.0])
    d = X - P
    r = np.linalg.norm(d, axis=1)
    u = d / r[:, None]
    g, c = pk._coefficients(r, u, np), pk._cubic(r, u, np)
    ratios = []
    for a in (0.04, 0.02, 0.01):
        worst = 0.0
        for Dx, Dy in ((a, a), (a, -0.3 * a), (-0.7 * a, a)):
            exact = np.linalg.norm(X + np.array([Dx, Dy, 0.0]) - P, axis=1)
            quad = g[0] * Dx ** 2 + g[1] * Dx * Dy + g[2] * Dy ** 2
            cub = c[0] * Dx ** 3 + c[1] * Dx ** 2 * Dy + c[2] * Dx * Dy ** 2 + c[3] * Dy ** 3
            rest = exact - (r + u[:, 0] * Dx + u[:, 1] * Dy + quad + cub)
            worst = max(worst, float(np.max(np.abs(rest) / ((Dx * Dx + Dy * Dy) ** 2 / r ** 3))))
        ratios.append(worst)
    assert max(ratios) < 0.5 and ratios[-1] < 1.5 * ratios[0]


@pytest.mark.parametrize("spread", [2, 3, 4, 5])
def test_gridding_error_bounds_the_nufft_at_each_spread(spread):
    """gridding_error(s), the correction groups' NUFFT error per unit of their size (the spreads the planner picks,
    group_spreads), against the type-1 sum written out: measured max |error| / sum |c| 2.5e-3, 3.1e-4, 3.2e-5, 3.7e-6 at
    2..5 (0.14-0.24 of the bound; at a focused spot's peak |U| ~ sum |c|): the bound holds and is not loose by 20x."""
    rng = np.random.default_rng(5)
    J, n = 400, 32
    tx, ty = rng.uniform(-math.pi, math.pi, J), rng.uniform(-math.pi, math.pi, J)
    c = rng.normal(size=J) + 1j * rng.normal(size=J)
    m = np.arange(-n // 2, n // 2)
    ref = np.exp(1j * (m[:, None, None] * ty[None, None] + m[None, :, None] * tx[None, None])) @ c
    err = np.max(np.abs(nufft_type1(tx, ty, c, n, spread=spread) - ref)) / np.sum(np.abs(c))
    assert 0.05 * pk.gridding_error(spread) < err < pk.gridding_error(spread)


def test_group_spreads_meet_the_nufft_error_and_are_the_narrowest():
    """Each group at the narrowest spread whose error (2 size gridding_error) is within KIRCHHOFF_NUFFT_ERROR."""
    sizes = pk.group_sizes(0.042, 1.4e-4, 9e-4)
    sp = pk.group_spreads(0.042, 1.4e-4, 9e-4)
    for g, s in sp.items():
        assert 2 * sizes[g] * pk.gridding_error(s) <= pk.KIRCHHOFF_NUFFT_ERROR
        assert s == pk.MIN_SPREAD or 2 * sizes[g] * pk.gridding_error(s - 1) > pk.KIRCHHOFF_NUFFT_ERROR
    assert sp["lin"] >= sp["quad"] >= sp["cub"]


def _estimate_line(pl, what="kirchhoff form: error ~"):
    return [r for r in pl.reasons if r.startswith(what)][0]


def test_tiles_are_as_large_as_the_expansion_estimate_allows(monkeypatch):
    """The A489 on axis, 16 um, 5 px, 300 rays across (plans only): KIRCHHOFF_EPS alone would allow 4 tiles of 56 (eps
    0.054 rad), whose expansion estimate (the cubic phase 0.0052 rad at their corners: 2 eps cubic 5.6e-4) is over
    KIRCHHOFF_EXPANSION_MAX: the planner takes 9 tiles of 38 (eps 0.025, expansion 9.2e-5) instead."""
    import rwwarp as rw
    import rwwarp.wave.pixel_scale as ps
    from rwwarp.io import load_lens
    monkeypatch.setattr(ps, "FIELD_FORM", "kirchhoff")
    lens = load_lens("a489_doe")
    kw = dict(size=5, pixel_mm=0.016, method="pixel", rays_per_sample=0.5)
    f = rw.plan_psf(lens, 0.0, 0.55, **kw).pixel_field
    exp = pk.kirchhoff_error_estimate(f["eps"], f["cubic"], 300, amp=f["amp"])["expansion"]
    cap = pk.KIRCHHOFF_EXPANSION_MAX
    assert exp <= cap and f["eps"] <= pk.KIRCHHOFF_EPS
    monkeypatch.setattr(pk, "KIRCHHOFF_EXPANSION_MAX", 1.0)     # the quadratic rest's cap alone
    g = rw.plan_psf(lens, 0.0, 0.55, **kw).pixel_field
    assert g["near"] < f["near"] and g["tile"] > f["tile"]
    assert pk.kirchhoff_error_estimate(g["eps"], g["cubic"], 300, amp=g["amp"])["expansion"] > cap


def test_ef50_at_10_deg_plans_within_the_issue_budget():
    """Issue 27 item 5's budget for the DeepLens EF50 f/1.8 at 10 deg, its own 15.3 um pixel, 64 px (plans only):
    <= 20 GFLOP and 1 GiB, the error estimate within the 1e-3 tolerance: auto takes the pixel method in the Kirchhoff
    form (4 tiles of 242 over the coma spot; 12 of 148 and 39.5 GFLOP before; measured against the full computation:
    docs/propagation.md)."""
    import rwwarp as rw
    from rwwarp.io import load_lens
    path = __import__("pathlib").Path(__file__).resolve().parents[1] / "data/third_party/files/DeepLens"
    path = path / "camera__ef50mm_f1.8.json"
    if not path.exists():
        pytest.skip("DeepLens lens files not present")
    pl = rw.plan_psf(load_lens(str(path)), 10.0, 0.55, size=64)
    assert pl.method == "pixel" and pl.pixel_field["form"] == "kirchhoff"
    assert pl.estimate["flops"] <= 2e10 and pl.estimate["memory_bytes"] <= 2 ** 30
    est = float(_estimate_line(pl, "pixel method: error ~").split("~")[1].split()[0])
    assert est <= 1e-3
