"""The DOE transmission as kept diffraction orders (rwwarp.wave.focal.doe_order_series, order_series_horner,
exact_zone), written once for numpy, CuPy and torch: against the wrapped transmission exp(1j alpha wrap(phi0))
it expands, against the direct sum of its orders written in the test, and (torch) its derivative in phi0
against the derivative of that sum written by hand."""
import math

import numpy as np
import pytest

from rwwarp.wave.focal import doe_order_coefficients, doe_order_series, exact_zone, order_series_horner


def _case(alpha=0.93, M=64):
    x = np.linspace(-1.0, 1.0, 401)
    phi0 = (-30.0 * x * x)[None, None, :] * np.ones((1, 3, 1))   # 4.8 zones, a smooth unwrapped phase
    ms = np.arange(-M, M + 1)
    c = doe_order_coefficients(alpha, None, ms)
    return phi0, [list(zip(ms.tolist(), c.tolist()))], alpha


def _direct(phi0, orders, zone=None):
    """``sum_m c_m exp(1j m phi0)`` term by term (numpy's complex exp), the zone ``(k_c, alpha)`` replaced by
    ``exp(1j alpha (phi0 - 2 pi k_c))`` where ``floor(phi0 / 2 pi) == k_c``; and the derivative in phi0."""
    s = sum(c * np.exp(1j * m * phi0) for m, c in orders)
    d = sum(1j * m * c * np.exp(1j * m * phi0) for m, c in orders)
    if zone is not None:
        kc, a = zone
        inside = np.floor(phi0 / (2 * math.pi)) == kc
        s = np.where(inside, np.exp(1j * a * (phi0 - 2 * math.pi * kc)), s)
        d = np.where(inside, 1j * a * np.exp(1j * a * (phi0 - 2 * math.pi * kc)), d)
    return s, d


def test_series_converges_to_the_wrapped_transmission_away_from_zone_edges():
    """Orders -64..64 at alpha = 0.93: away from the zone edges (|frac(phi0 / 2 pi) - 1/2| < 0.4) the series
    equals exp(1j alpha wrap(phi0)) to 7e-3 (measured 3.4e-3; the Gibbs tail decays like 1/(M d), d the
    distance to an edge in zones); in the chief ray's zone, given, it is exact (0)."""
    phi0, orders, alpha = _case()
    exact = np.exp(1j * alpha * np.mod(phi0, 2 * np.pi))
    s = doe_order_series(phi0, orders)
    t = phi0 / (2 * np.pi) - np.floor(phi0 / (2 * np.pi))
    away = np.abs(t - 0.5) < 0.4
    assert np.max(np.abs(s - exact)[away]) < 7e-3
    kc = int(np.floor(phi0[0, 0, 200] / (2 * np.pi)))              # the zone at the axis
    z = doe_order_series(phi0, orders, [(kc, alpha)])
    zone = np.floor(phi0 / (2 * np.pi)) == kc
    assert np.max(np.abs(z - np.exp(1j * alpha * (phi0 - 2 * np.pi * kc)))[zone]) == 0.0
    assert np.array_equal(z[~zone], s[~zone])


@pytest.mark.parametrize("ns", ["numpy", "torch"])
def test_series_is_the_direct_sum_of_its_orders(ns):
    """Integer orders -8..8 (Horner in exp(1j phi0)), a non-integer single order, and orders 2..5 (a positive
    lowest order), each with and without an exact zone, against the direct sum written in the test. Torch:
    the derivative in phi0 (autograd, a real loss) against the hand derivative. Measured 7.2e-15 (numpy and
    torch; sum |c_m| ~ 1) and 3.4e-14 for the derivative (sum |m c_m| = 5.6): tolerances 2e-14 and 1e-13."""
    phi0, orders, alpha = _case(M=8)
    phi0 = np.concatenate([phi0, phi0[:, ::-1] * 0.5, phi0 + 1.0])   # 3 sources
    orders = orders + [[(alpha, 0.8 - 0.1j)], [(m, complex(0.3 / m, 0.1 * m)) for m in range(2, 6)]]
    zones = [(-2, alpha), None, (-1, 1.1)]
    xp = np
    if ns == "torch":
        torch = pytest.importorskip("torch")
        xp = torch
    for zs in (None, zones):
        p = phi0 if xp is np else torch.tensor(phi0, requires_grad=True)
        got = doe_order_series(p, orders, zs, xp)
        w = np.cos(np.arange(phi0.size)).reshape(phi0.shape) + 1j * np.sin(0.3 * np.arange(phi0.size)).reshape(
            phi0.shape)
        for k in range(3):
            ref, dref = _direct(phi0[k], orders[k], None if zs is None else zs[k])
            g = got[k] if xp is np else got[k].detach().numpy()
            np.testing.assert_allclose(g, ref, rtol=0, atol=2e-14)
        if xp is not np:
            # d/dphi0 of Re(sum conj(w) t(phi0)): Re(conj(w) dt/dphi0), per sample
            torch.real(torch.sum(torch.conj(torch.from_numpy(w)) * got)).backward()
            dref = np.stack([_direct(phi0[k], orders[k], None if zs is None else zs[k])[1] for k in range(3)])
            np.testing.assert_allclose(p.grad.numpy(), np.real(np.conj(w) * dref), rtol=0, atol=1e-13)
    # the zone is used somewhere on each source that has one
    assert all(np.any(np.floor(phi0[k] / (2 * math.pi)) == zones[k][0]) for k in (0, 2))


@pytest.mark.parametrize("ns", ["numpy", "torch"])
def test_horner_and_exact_zone_take_a_coefficient_and_zone_per_member(ns):
    """The batched form torch_bridge's packed tiles use: coefficients (S, 1, 1) per order, lowest order
    negative, zones and remaps (S, 1, 1) per member (a member without a zone at 2^60), against the direct sum
    and the exact zone written in the test (measured 1.3e-14 = 1.0e-15 of the largest sum |c_m|; tolerance 1e-14
    of it)."""
    rng = np.random.default_rng(3)
    S, lo, hi = 3, -3, 4
    p = rng.uniform(-14.0, 3.0, (S, 5, 6))
    c = rng.normal(size=(S, hi - lo + 1)) + 1j * rng.normal(size=(S, hi - lo + 1))
    zone = np.array([-1.0, 2.0 ** 60, 0.0])[:, None, None]
    alpha = np.array([0.9, 0.0, 1.2])[:, None, None]
    ref = sum(c[:, j, None, None] * np.exp(1j * (lo + j) * p) for j in range(hi - lo + 1))
    inside = np.floor(p / (2 * math.pi)) == zone
    assert inside[0].any() and inside[2].any() and not inside[1].any()
    ref = np.where(inside, np.exp(1j * alpha * (p - 2 * math.pi * zone)), ref)
    if ns == "torch":
        torch = pytest.importorskip("torch")
        e = torch.exp(1j * torch.from_numpy(p))
        acc = order_series_horner(e, [torch.from_numpy(c[:, j, None, None]) for j in range(hi - lo + 1)], lo, torch)
        got = exact_zone(acc, torch.from_numpy(p), torch.from_numpy(zone), torch.from_numpy(alpha), torch).numpy()
    else:
        e = np.exp(1j * p)
        acc = order_series_horner(e, [c[:, j, None, None] for j in range(hi - lo + 1)], lo)
        got = exact_zone(acc, p, zone, alpha)
        assert not np.shares_memory(got, acc)                     # the input is not changed
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-14 * np.abs(c).sum(axis=1).max())
