"""Issue 25's launch count: the 30-source A489 + DOE map (fields 0..10 deg x 0.45 / 0.55 / 0.65 um, 32 px, CPU)
called a second time through a :class:`rwwarp.PlanCache` makes a fixed set of Warp launches, one per stage and
batch, none per source or surface (target <= 60; 96 at the start of session 23: the entry was over the cache's
1 GiB, so the second call planned again, and 22 launches a batch); and its PSFs are those of every source
computed alone (``batch=1``)."""
from collections import Counter

import numpy as np
import pytest

wp = pytest.importorskip("warp")

import rwwarp as rw  # noqa: E402

FIELDS = [float(f) for f in np.linspace(0.0, 10.0, 10)]
WLS = [0.45, 0.55, 0.65]


def _map(cache=None, **kw):
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")   # the map's own warnings (model error, patch) are not under test here
        return rw.psf_map(rw.load_lens("a489_doe"), FIELDS, WLS, size=32, cache=cache, **kw)


@pytest.fixture
def two_threads(monkeypatch):
    """Tracers of 2 CPU threads whatever the machine (the launches a stage split over threads are counted), and
    the default memory budget of a machine with 8 GiB available (4 GiB; the batches are then cut by the CPU's
    batch bytes alone, not by what the machine has free at the moment)."""
    import rwwarp.trace as trace
    import rwwarp.wave.plan as plan
    monkeypatch.setattr(trace, "cpu_threads", lambda: 2)
    monkeypatch.setattr(plan, "default_memory_budget_bytes", lambda device="cpu": 4 * 2 ** 30)


def test_warm_a489_map_launches(two_threads):
    """The second call is a cache hit and makes 40 launches: 4 batches (the CPU's default batch bytes) x 10 =
    the ray generation of each thread's range, the trace through every surface (kernels/trace_steps.py) and the
    splat and finalize on each of the 2 threads, the tube areas, the power sums and their tree in one launch
    (power_tree_kernel). The count is deterministic, so it is asserted exactly, kernel by kernel."""
    cache = rw.PlanCache()
    first = _map(cache)
    counts = Counter()
    orig = wp.launch

    def counted(kernel, *a, **k):
        counts[kernel.key.split("__")[-1]] += 1
        return orig(kernel, *a, **k)
    wp.launch = counted
    try:
        second = _map(cache)
    finally:
        wp.launch = orig
    assert second.info["cache"] == "hit"
    assert len(second.info["batches"]) == 4
    assert dict(counts) == {"generate_kernel": 8, "trace_steps_kernel": 8, "tube_area_kernel": 4,
                            "splat_forward_kernel": 8, "finalize_kernel": 8, "power_tree_kernel": 4}, dict(counts)
    assert sum(counts.values()) == 40
    assert np.array_equal(first.data, second.data)


def test_map_psfs_equal_sources_alone(two_threads):
    """Every PSF of the map (4 packed batches, each source on its own plan) against the same source computed in
    a batch of its own (``batch=1``): equal bit for bit (a source's rays add into its own window in one thread's
    order in both; its power sums go through the same tree; its propagation is its own)."""
    packed = _map()
    alone = _map(batch=1)
    assert len(packed.info["batches"]) == 4 and len(alone.info["batches"]) == 30
    assert np.array_equal(packed.data, alone.data)
