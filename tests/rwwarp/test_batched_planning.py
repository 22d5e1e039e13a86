"""Planning steps made for many sources at once (issue 25). The focal planner's quadratic-transfer fit
(rwwarp.wave.plan.fit_quadratic_transfers):
checked against an independent least-squares reference written here (numpy.linalg.lstsq on the design matrix
[1, u], the fit the planner made per source and axis before issue 25), with masked points, the fallbacks to the
Taylor values and the degenerate cases; and the property the batched planner relies on: a source's fit is the
same bits alone and among other sources with any padding between its points."""
import numpy as np
import pytest

from rwwarp.wave.plan import fit_quadratic_transfer, fit_quadratic_transfers

# measured: the closed form against lstsq over 200 random batches (3..3000 points, 20 % masked, c1 in -50..-1,
# a small quadratic term), worst 5.3e-15 relative (c1 to itself, c0 to the largest |t|); 10x that
REL = 5e-14


def _lstsq(u, t):
    """Reference: the line t = c0 + c1 u through the points by numpy's least squares (SVD)."""
    (c0, c1), *_ = np.linalg.lstsq(np.stack([np.ones_like(u), u], 1), t, rcond=None)
    return c0, c1


def _beams(rng, S, P):
    """S random beams of P points: frequency offsets u (cycles/mm, a 0.1 NA spread at 0.5 um), slopes t of a
    focusing transfer (c1 < 0) with a small quadratic departure, and a mask dropping ~20 % of the points."""
    k = 1.0 / 5e-4
    u = rng.normal(0.0, 0.1 * k, (S, P)) * rng.uniform(0.01, 1.0)
    c1 = -rng.uniform(1.0, 50.0, S)
    t = rng.normal(0.0, 0.3, S)[:, None] + c1[:, None] * u + 1e-4 * rng.normal(size=(S, P)) * u ** 2 / k
    ok = rng.uniform(size=(S, P)) < 0.8
    return u, t, ok


def test_fit_is_the_least_squares_line_with_masked_points():
    rng = np.random.default_rng(7)
    worst = 0.0
    for P in (3, 5, 40, 961, 2900):
        u, t, ok = _beams(rng, 6, P)
        ok[:, :3] = True                       # at least 3 points a source
        t_in, u_in, ok_in = t.copy(), u.copy(), ok.copy()
        gf, qf = fit_quadratic_transfers(u, t, ok, np.zeros(6), -np.ones(6))
        assert np.array_equal(u, u_in) and np.array_equal(t, t_in) and np.array_equal(ok, ok_in)   # not mutated
        for s in range(6):
            c0, c1 = _lstsq(u[s, ok[s]], t[s, ok[s]])
            assert c1 < 0
            worst = max(worst, abs(gf[s] - c0) / np.max(np.abs(t[s, ok[s]])), abs(qf[s] - c1) / abs(c1))
    assert worst < REL, worst


def test_one_source_wrapper_on_an_exact_beam_matches_lstsq():
    """fit_quadratic_transfer (lists over orders, one source) on straight rays converging at 14 deg through NA 0.1,
    two 'orders' of rays: each axis is lstsq's line through -grad w = (L - x) / z."""
    from test_focal import converging_beam
    lam, z, k, fc, f, x, L = converging_beam(3000)
    g0, q0 = np.array([0.1, 0.2]), np.array([-1.0, -1.0])
    gf, qf = fit_quadratic_transfer([f[:1000], f[1000:]], [L[:1000], L[1000:]], [x[:1000], x[1000:]], fc, g0, q0, z)
    for ax in range(2):
        c0, c1 = _lstsq(f[:, ax] - fc[ax], (x[:, ax] - L[:, ax]) / z)
        assert abs(gf[ax] - c0) < REL * np.max(np.abs((x[:, ax] - L[:, ax]) / z))
        assert abs(qf[ax] - c1) < REL * abs(c1)


def test_fallbacks_keep_the_taylor_values():
    rng = np.random.default_rng(3)
    P = 50
    u, t, ok = _beams(rng, 8, P)
    ok[:] = True
    ok[0, 2:] = False                        # 2 points: too few
    ok[1, :] = False                         # no points
    u[2] = 0.125                             # no spread in u
    t[3] = 0.2 + 3.0 * u[3]                  # c1 > 0: would not focus
    t[4, 7] = np.nan                         # a non-finite slope among the points
    u[5, 9] = np.inf                         # a non-finite frequency among the points
    t[6] = 0.25                              # c1 = 0 exactly (flat slope; 0.25 sums exactly)
    u[7, 11], t[7, 11] = np.nan, np.inf      # ... but masked out: the fit of the others
    ok[7, 11] = False
    g0, q0 = rng.normal(size=8), -rng.uniform(1, 2, 8)
    gf, qf = fit_quadratic_transfers(u, t, ok, g0, q0)
    assert np.all(np.isfinite(gf)) and np.all(np.isfinite(qf))
    for s in range(7):
        assert gf[s] == g0[s] and qf[s] == q0[s], s
    c0, c1 = _lstsq(u[7, ok[7]], t[7, ok[7]])
    assert abs(gf[7] - c0) < REL * np.max(np.abs(t[7, ok[7]])) and abs(qf[7] - c1) < REL * abs(c1)
    # exactly 3 points on a line with c1 < 0: the line itself
    gf, qf = fit_quadratic_transfers(np.array([[-1.0, 0.5, 2.0]]), np.array([[2.5, -2.0, -6.5]]),
                                     np.ones((1, 3), bool), np.zeros(1), -np.ones(1))
    assert gf[0] == pytest.approx(-0.5, abs=1e-15) and qf[0] == pytest.approx(-3.0, rel=1e-15)


@pytest.mark.parametrize("S", [4, 20])
def test_a_source_gives_the_same_bits_alone_and_padded_in_a_batch(S):
    """The batched planner pads each source's points (copies, NaN of rays that do not land) and sources of other
    lengths beside it: the sums are added in order with -0.0 for padding, so the fit does not change by a bit
    (few sources: each row's running sum; FIT_WIDE or more: one reduction down the points)."""
    rng = np.random.default_rng(11)
    u, t, ok = _beams(rng, S, 700)
    alone = [fit_quadratic_transfers(u[s:s + 1, ok[s]], t[s:s + 1, ok[s]], np.ones((1, ok[s].sum()), bool),
                                     np.zeros(1), -np.ones(1)) for s in range(S)]
    up, tp = u.copy(), t.copy()
    up[~ok], tp[~ok] = np.nan, np.inf                               # garbage where masked
    wide = np.zeros((S, 1000), bool)
    wide[:, :700] = ok
    U = np.concatenate([up, np.full((S, 300), 7.0)], axis=1)       # trailing padding
    Tt = np.concatenate([tp, np.full((S, 300), -3.0)], axis=1)
    gf, qf = fit_quadratic_transfers(U, Tt, wide, np.zeros(S), -np.ones(S))
    for s in range(S):
        assert gf[s] == alone[s][0][0] and qf[s] == alone[s][1][0]
    # np.sum's pairwise rounding would depend on the layout: check the sums really differ somewhere, so this
    # test can fail (the order of additions matters at 1e-16 for these values)
    assert any(np.sum(u[s, ok[s]]) != np.sum(np.where(ok[s], u[s], 0.0)[::-1]) for s in range(S))


def test_bad_shapes_are_refused():
    with pytest.raises(ValueError, match="fit_quadratic_transfers"):
        fit_quadratic_transfers(np.zeros((2, 5)), np.zeros((2, 4)), np.ones((2, 5), bool), np.zeros(2), np.zeros(2))
    with pytest.raises(ValueError, match="fit_quadratic_transfers"):
        fit_quadratic_transfers(np.zeros((2, 5)), np.zeros((2, 5)), np.ones((2, 5), bool), np.zeros(3), np.zeros(3))




def test_gauss_legendre_bound_with_its_constant_kept_is_the_formula():
    """gauss_legendre_exp_error keeps the node count's part of log(bound) (lru_cache, issue 25: the planner asks it
    a few times a source): the same bits as the remainder formula written out here, in its order of additions, for
    node counts 1..40 and phases 1e-6..1e3 rad (0 mismatches in 20000 draws when it was written)."""
    from scipy import special
    from rwwarp.analytic import gauss_legendre_exp_error

    def formula(n, omega):
        if omega == 0.0:
            return 0.0
        log_e = ((2 * n + 1) * np.log(2.0) + 4 * special.gammaln(n + 1) - np.log(2 * n + 1)
                 - 3 * special.gammaln(2 * n + 1) + 2 * n * np.log(omega))
        return float(np.exp(log_e) / 2.0)
    rng = np.random.default_rng(9)
    for _ in range(2000):
        n, w = int(rng.integers(1, 41)), float(10.0 ** rng.uniform(-6, 3))
        assert gauss_legendre_exp_error(n, w) == formula(n, w)
        assert gauss_legendre_exp_error(n, -w) == formula(n, w)
    assert gauss_legendre_exp_error(5, 0.0) == 0.0


def test_blank_doe_adds_no_frequency_without_evaluating_its_gradient(monkeypatch):
    """doe_max_frequency returns zeros for a blank relief (a489_doe: every coefficient zero) without reading the
    points: the values the gradient path gives (run here by hiding the blank check), bit for bit; a relief with a
    phase still reads its points and gives a positive frequency."""
    import rwwarp as rw
    import rwwarp.doe as doe_mod
    from rwwarp.lens import Surface
    from rwwarp.wave.doe_sampling import doe_max_frequency
    lens = rw.load_lens("a489_doe")
    p = lens.wave_plane_index()
    rng = np.random.default_rng(1)
    pts = [rng.uniform(-1.0, 1.0, (50, 2)) for _ in range(3)]
    wls = [0.45, 0.55, 0.65]

    class Unread(list):
        def __getitem__(self, k):
            raise AssertionError("a blank relief's points were read")
    fast, feat = doe_max_frequency(lens, p, Unread(pts), wls)
    with monkeypatch.context() as m:
        m.setattr(doe_mod, "is_flat_profile", lambda profile: False)
        slow, feat_slow = doe_max_frequency(lens, p, pts, wls)
    assert np.array_equal(fast, slow) and np.all(fast == 0.0) and feat is None and feat_slow is None
    surfs = [Surface(**{k: getattr(s, k) for k in s.__dataclass_fields__}) for s in lens.surfaces]
    surfs[p].profile = {"kind": "even_poly", "norm_radius": 1.5, "coefficients": [-100.0, 0.0, 0.0, 0.0]}
    f, _ = doe_max_frequency(lens.replace(surfaces=surfs), p, pts, wls)
    assert np.all(f > 0.0)
