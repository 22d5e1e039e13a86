"""Fixtures of the Warp kernel tests (``tests/kernels``).

``device``: every test runs on Warp's CPU device, and again on ``cuda:0`` when Warp sees a CUDA device
(skipped otherwise), so the CUDA build of each kernel is checked against the same numpy references.
"""
import numpy as np
import pytest

wp = pytest.importorskip("warp")


def _cuda_count() -> int:
    from rwwarp.trace import init_warp

    init_warp()
    try:
        return wp.get_cuda_device_count()
    except RuntimeError:  # a Warp build without CUDA support
        return 0


@pytest.fixture(scope="session", params=["cpu", "cuda:0"])
def device(request):
    """Warp device string: ``"cpu"`` always, ``"cuda:0"`` when present."""
    if request.param.startswith("cuda") and _cuda_count() == 0:
        pytest.skip("Warp sees no CUDA device")
    from rwwarp.trace import init_warp

    init_warp()
    return request.param


@pytest.fixture
def rng():
    """A fixed-seed generator per test (results do not depend on the order tests run in)."""
    return np.random.default_rng(20261123)
