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
