"""Gradients of the multi-order PSF (torch_bridge.phase_orders.OrderSet) against central finite differences of the
same forward, and its forward against rwwarp.psf's multi-order path (tests/rwwarp/test_phase_orders.py's lens)."""
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

import rwwarp  # noqa: E402
from rwwarp.trace import COLUMNS  # noqa: E402
from torch_bridge.phase_orders import OrderSet  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "rwwarp"))
from test_phase_orders import WL, bfl, make  # noqa: E402

SIZE = 32


@pytest.fixture(scope="module")
def orders():
    return OrderSet(make((0, 1, 2), sensor=bfl()), 0.0, WL, SIZE, method="focal")


def test_forward_matches_rwwarp_psf(orders):
    p = orders.psf(torch.tensor(orders.table)).detach().numpy()[0]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref = rwwarp.psf(make((0, 1, 2), sensor=bfl()), 0.0, WL, size=SIZE, method="focal",
                         focal_precision="double").data
    # the same arithmetic (torch holds the sums): measured 1.8e-16 of the peak
    assert np.abs(p - ref).max() < 1e-12 * ref.max()


@pytest.mark.parametrize("entry", [(2, COLUMNS.phase0), (1, COLUMNS.curvature)], ids=["A1", "plate-curvature"])
def test_gradient_against_finite_differences(orders, entry):
    rng = np.random.default_rng(3)
    W = torch.tensor(rng.random((1, SIZE, SIZE)))
    base = torch.tensor(orders.table, requires_grad=True)
    loss = (orders.psf(base) * W).sum()
    loss.backward()
    g = float(base.grad[entry])
    h = {COLUMNS.phase0: 1e-4, COLUMNS.curvature: 1e-7}[entry[1]]

    def f(step):
        t = torch.tensor(orders.table)
        t[entry] += step
        with torch.no_grad():
            return float((orders.psf(t) * W).sum())
    fd = (f(h) - f(-h)) / (2 * h)
    # measured relative difference 6.4e-8 (A1, h = 1e-4) and 2.5e-8 (curvature, h = 1e-7): FD truncation and
    # rounding; tolerance 3e-7
    assert g == pytest.approx(fd, rel=3e-7), (g, fd)


def test_hybrid_lens_sums_the_orders_and_differentiates_them():
    """HybridLens with a multi-order phase surface: psf and psf_map sum the kept orders (rwwarp.psf's multi-order
    PSF, the same arithmetic: tolerance 1e-12 of the peak as OrderSet's test), the map's sources equal psf of each
    (checkpointed tiles of one source), and d(loss)/dA_1 through the module equals central differences of its own
    forward on kept plans (``replan=False``: the gradient is the one at fixed discrete decisions; re-planned at
    +-h the plans move and the difference quotient is 19 % off). Measured 2.1e-8 relative at h = 1e-4; tolerance
    3e-7 (OrderSet's)."""
    import torch_bridge as tb
    lens = make((0, 1, 2), sensor=bfl())
    m = tb.HybridLens(lens, learn={"phase": [(2, 0)]}, method="focal", replan=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref = rwwarp.psf(lens, 0.0, WL, size=SIZE, method="focal", focal_precision="double").data
        one_order = rwwarp.psf(make(None, sensor=bfl()), 0.0, WL, size=SIZE, method="focal",
                               focal_precision="double").data
    p = m.psf(0.0, WL, SIZE)
    assert np.abs(p.detach().numpy() - ref).max() < 1e-12 * ref.max()
    assert np.abs(one_order - ref).max() > 0.05 * ref.max()      # the other orders matter here (0.185 in rwwarp's test)
    pm = m.psf_map([0.0, 0.3], [WL], SIZE)
    assert pm.shape == (2, 1, SIZE, SIZE)
    # the map's checkpointed tiles run their forward without a tape (the trace's other kernels): measured 9.0e-17
    # of the peak against psf; tolerance 1e-15
    for k, f in enumerate((0.0, 0.3)):
        one = m.psf(f, WL, SIZE).detach().numpy()
        assert np.abs(pm[k, 0].detach().numpy() - one).max() < 1e-15 * one.max()
    W = torch.tensor(np.random.default_rng(5).random((2, 1, SIZE, SIZE)))
    (pm * W).sum().backward()
    g = float(m.phase.grad[0])
    h = 1e-4

    def f(step):
        with torch.no_grad():
            m.phase[0] += step
            v = float((m.psf_map([0.0, 0.3], [WL], SIZE) * W).sum())
            m.phase[0] -= step
        return v
    fd = (f(h) - f(-h)) / (2 * h)
    assert g != 0.0 and g == pytest.approx(fd, rel=3e-7), (g, fd)


def test_hybrid_lens_orders_refuse_what_they_cannot_do():
    import torch_bridge as tb
    m = tb.HybridLens(make((0, 1, 2), sensor=bfl()), method="focal")
    with pytest.raises(ValueError, match="spatial_tile"):
        m.psf(0.0, WL, SIZE, spatial_tile=8)
    with pytest.raises(ValueError, match="tile=1"):
        m.psf_map([0.0], [WL], SIZE, tile=2)
    with pytest.raises(ValueError, match="order_tol"):
        tb.HybridLens(make((0, 1, 2), sensor=bfl()), order_tol=1.5)
    with pytest.raises(ValueError, match="wave step"):
        tb.HybridLens(make((0, 1, 2), sensor=bfl()), method="two-step").psf(0.0, WL, SIZE)
    with pytest.raises(ValueError, match="no phase surface with diffraction_orders"):
        tb.HybridLens(make(None, sensor=bfl())).order_set(0.0, WL, SIZE)


def test_live_provider_sums_the_orders_and_the_cached_one_says_it_does_not():
    """LiveProvider (the design loop with a learning lens) computes each node's kept orders (HybridLens.order_set at
    the node's common centre): its PSFs equal HybridLens.psf at the same centres (the same arithmetic; the
    provider's two checkpointed chunks run their forward without a tape: tolerance 1e-15 of the peak as the
    map's), and its gradient equals the one through psf (1e-12 relative). CachedProvider (frozen refractive part)
    keeps the design order only and warns."""
    import torch_bridge as tb
    from torch_bridge import design as dz
    from torch_bridge.live import common_centres
    m = tb.HybridLens(make((0, 1, 2), sensor=bfl()), learn={"phase": [(2, 0)]}, method="focal")
    pitch = make().sensor.pixel_pitch
    prov = dz.LiveProvider(m, [(0.0, 0.0), (0.0, 0.3)], SIZE, pitch, wavelength_ref_um=WL, tile=1)
    out = prov.psfs([WL])
    assert out.shape == (2, 1, SIZE, SIZE)
    W = torch.tensor(np.random.default_rng(2).random((2, 1, SIZE, SIZE)))
    (out * W).sum().backward()
    g = float(m.phase.grad[0])
    m.phase.grad = None
    cen = common_centres(m, [(0.0, 0.0), (0.0, 0.3)], WL)
    ref = torch.stack([m.psf((0.0, f), WL, SIZE, center_mm=tuple(c)) for f, c in zip((0.0, 0.3), cen)])[:, None]
    assert (out - ref).abs().max() < 1e-15 * ref.max()
    (ref * W).sum().backward()
    assert g != 0.0 and g == pytest.approx(float(m.phase.grad[0]), rel=1e-12)
    with pytest.warns(UserWarning, match="design order only"):
        dz.CachedProvider(m, [0.0], SIZE, pitch)
