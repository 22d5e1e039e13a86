"""The DOE transmission as kept diffraction orders (rwwarp.wave.focal.doe_order_series), written once for
numpy, CuPy and torch: against the wrapped transmission exp(1j alpha wrap(phi0)) it expands, and the
same in numpy and torch."""
import numpy as np
import pytest

from rwwarp.wave.focal import doe_order_coefficients, doe_order_series


def _case(alpha=0.93, M=64):
    x = np.linspace(-1.0, 1.0, 401)
    phi0 = (-30.0 * x * x)[None, None, :] * np.ones((1, 3, 1))   # 4.8 zones, a smooth unwrapped phase
    ms = np.arange(-M, M + 1)
    c = doe_order_coefficients(alpha, None, ms)
    return phi0, [list(zip(ms.tolist(), c.tolist()))], alpha


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


def test_numpy_and_torch_agree():
    torch = pytest.importorskip("torch")
    phi0, orders, alpha = _case(M=8)
    a = doe_order_series(phi0, orders, [(-1, alpha)])
    b = doe_order_series(torch.from_numpy(phi0), orders, [(-1, alpha)], torch).numpy()
    np.testing.assert_allclose(b, a, rtol=0, atol=2e-15)   # measured 2.5e-16 (exp in two libraries)
