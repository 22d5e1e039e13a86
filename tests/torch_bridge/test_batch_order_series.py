"""rwwarp.wave.focal.batch_order_series, the one batched DOE transmission of packed focal members (rwwarp's stacked
runs with numpy / CuPy, torch_bridge's packed tiles with torch): against the series written out term by term
from its definition, ``t = sum_m c_m exp(1j m phi0)`` with the chief-ray zone replaced by the exact
``exp(1j alpha (phi0 - 2 pi k_c))`` where ``floor(phi0 / 2 pi) == k_c``; the torch path against the numpy path;
and torch's gradient through phi0 against central finite differences of the numpy path."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from rwwarp.wave.focal import batch_order_series, doe_order_coefficients, doe_order_series, order_tables

TWO_PI = 2.0 * np.pi


def _batch():
    """Six members on one 40 x 40 phase (rad) spanning ~0.3 .. 22 rad (zones 0 .. 3), in an order that mixes the
    two kinds (so the rows come back permuted): integer series with and without gaps (missing orders: zero
    coefficients), each with a chief-ray zone; one remapped order (a relief that does not wrap); a blank DOE
    as the one order (alpha, 1); several non-integer orders (no Horner: a sum of terms)."""
    n = 40
    y, x = np.mgrid[0:n, 0:n] / (n - 1)
    base = 0.3 + 21.7 * (x ** 2 + 0.8 * y ** 2) / 1.8
    S = 6
    phi0 = np.stack([base * (1.0 + 0.03 * k) + 0.1 * np.sin(3 * x + k) for k in range(S)])
    ints = np.arange(-2, 5)
    c09 = doe_order_coefficients(0.9, None, ints)
    c8 = doe_order_coefficients(1.07, 8, ints)
    orders = [
        [(0.97, 1.0 + 0j)],                                         # one remapped order (c = 1 here)
        [(int(m), complex(c)) for m, c in zip(ints, c09)],          # -2 .. 4, continuous relief off design
        [(0.8, 0.3 - 0.1j), (1.3, 0.9 + 0.2j), (2.1, -0.05j)],      # several orders, not integers
        [(-1, complex(c8[1])), (1, complex(c8[3])), (3, complex(c8[5]))],   # a series with gaps (8 levels)
        [(1.04, 1.0)],                                              # a blank DOE: exp(1j alpha phi0)
        [(0, 0.2 + 0.1j), (1, 0.95 - 0.05j)],                       # two integer orders
    ]
    zones = [None, (2, 0.9), (1, 1.3), (3, 1.07), None, (0, 1.0)]
    return phi0, orders, zones


def _reference(phi0, orders, zones):
    """The definition, term by term per member (no Horner, no batching), and the zone by ``floor``."""
    out = np.zeros(phi0.shape, complex)
    for k, (ol, z) in enumerate(zip(orders, zones)):
        p = phi0[k]
        out[k] = sum(complex(c) * np.exp(1j * float(m) * p) for m, c in ol)
        if z is not None:
            inside = np.floor(p / TWO_PI) == z[0]
            assert inside.any() and not inside.all()         # the zone is exercised, and so is the series
            out[k][inside] = np.exp(1j * z[1] * (p[inside] - TWO_PI * z[0]))
    return out


def test_batched_series_equals_its_definition_and_each_member_alone():
    """numpy: against the term-by-term definition, measured 6.8e-16 (the Horner recursion's rounding over up to 7
    orders); tolerance 4e-15. Against rwwarp.wave.focal.doe_order_series per member (its own orders only, not
    the union), measured 5.0e-16; tolerance 3e-15. Inputs are not changed."""
    phi0, orders, zones = _batch()
    keep = phi0.copy()
    tables = order_tables(orders, zones)
    assert len(tables.series) == 3 and len(tables.terms) == 3 and tables.order is not None
    got = batch_order_series(phi0, tables, np)
    assert np.array_equal(phi0, keep)
    ref = _reference(phi0, orders, zones)
    assert np.abs(got - ref).max() <= 4e-15
    alone = doe_order_series(phi0, orders, zones, np)
    assert np.abs(got - alone).max() <= 3e-15


def test_torch_path_equals_numpy_and_its_gradient_the_finite_differences():
    """torch (CPU) against numpy on the same tables: values measured 6.7e-16 (the complex products round
    differently), tolerance 4e-15. Gradient of ``L = sum Re(conj(w) t(phi0))`` through phi0 (torch autograd)
    against central differences of the numpy path (step 1e-5 rad, each sample's own: the factor is
    elementwise), away from the zone edges the step would cross: measured 9.2e-11 of the largest (truncation
    ~h^2 m^3 / 6 and rounding 1e-16 / h; 4.9e-9 at 1e-4, 1.3e-9 at 1e-6); tolerance 5e-10. And against the
    derivative written from the definition, ``sum 1j m c_m exp(1j m phi0)`` (``1j alpha exp(...)`` in the
    zone): measured 6.8e-16 of the largest; tolerance 5e-15."""
    phi0, orders, zones = _batch()
    tables = order_tables(orders, zones)
    ref = batch_order_series(phi0, tables, np)
    p = torch.tensor(phi0, requires_grad=True)
    got = batch_order_series(p, tables, torch)
    assert got.dtype == torch.complex128
    assert np.abs(got.detach().numpy() - ref).max() <= 4e-15
    rng = np.random.default_rng(0)
    w = rng.standard_normal(phi0.shape) + 1j * rng.standard_normal(phi0.shape)
    (g,) = torch.autograd.grad((got * torch.as_tensor(w).conj()).real.sum(), p)
    h = 1e-5
    fd = ((np.conj(w) * (batch_order_series(phi0 + h, tables, np) - batch_order_series(phi0 - h, tables, np))).real
          / (2 * h))
    away = np.floor((phi0 + h) / TWO_PI) == np.floor((phi0 - h) / TWO_PI)
    assert away.mean() > 0.99
    g = g.numpy()
    assert np.abs(g - fd)[away].max() <= 5e-10 * np.abs(g).max()
    d = np.zeros(phi0.shape, complex)
    for k, (ol, z) in enumerate(zip(orders, zones)):
        q = phi0[k]
        d[k] = sum(1j * float(m) * complex(c) * np.exp(1j * float(m) * q) for m, c in ol)
        if z is not None:
            inside = np.floor(q / TWO_PI) == z[0]
            d[k][inside] = 1j * z[1] * np.exp(1j * z[1] * (q[inside] - TWO_PI * z[0]))
    assert np.abs(g - (np.conj(w) * d).real).max() <= 5e-15 * np.abs(g).max()


def test_bad_batch_is_named():
    phi0, orders, zones = _batch()
    tables = order_tables(orders, zones)
    with pytest.raises(ValueError, match="phi0 has 5 members, the order tables 6"):
        batch_order_series(phi0[:5], tables, np)
    with pytest.raises(ValueError, match="5 central zones for 6 members"):
        order_tables(orders, zones[:5])


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_on_cuda_torch_and_cupy_equal_numpy():
    """torch on CUDA (tables moved beside phi0 by the default put) and CuPy against numpy: the GPU's exp and
    floor round differently from the CPU's, tolerance 1e-13 (not run here: no GPU was available when this was
    written)."""
    phi0, orders, zones = _batch()
    tables = order_tables(orders, zones)
    ref = batch_order_series(phi0, tables, np)
    got = batch_order_series(torch.tensor(phi0, device="cuda"), tables, torch)
    assert np.abs(got.cpu().numpy() - ref).max() <= 1e-13
    cp = pytest.importorskip("cupy")
    got = batch_order_series(cp.asarray(phi0), tables, cp)
    assert np.abs(cp.asnumpy(got) - ref).max() <= 1e-13
