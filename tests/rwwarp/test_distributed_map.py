"""Sharded PSF maps (rwwarp.distributed, issue 14): 2 gloo processes started through torch's launcher
give the single-process rw.psf_map (gathered on rank 0, and streamed to .npz shards); with one process
the helper runs without torch; a rank that raises ends the run with its own error, no hang."""
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from test_map import doe_lens  # the small thin-lens + DOE system whose fields need different plans

import rwwarp as rw
from rwwarp import distributed as D

FIELDS = [0.0, 0.8]
WLS = [0.45, 0.65]
DEPTHS = [None, 400.0]
SIZE = 16


def _map_worker(out):
    """One rank: the sharded map gathered on rank 0, then the same map streamed to shards in ``out``."""
    m = D.psf_map(doe_lens(), FIELDS, WLS, DEPTHS, size=SIZE, progress=True)
    D.psf_map(doe_lens(), FIELDS, WLS, DEPTHS, size=SIZE, out=out)
    if m is None:
        return None
    return [x.data for x in m], [x.centers_mm for x in m], m[0].info["units"], m[0].info["ranks"]


def _failing_worker():
    """Rank 1 raises while rank 0 waits in a collective (it would wait forever without the launcher)."""
    dist = D.init_group("cpu", timeout_s=600)
    if dist.get_rank() == 1:
        raise ValueError("lens file broken on rank 1")
    dist.barrier()
    return 0


def test_sharded_map_on_two_ranks_equals_the_single_process_map(tmp_path):
    pytest.importorskip("torch")
    res = D.launch(_map_worker, 2, str(tmp_path / "shards"))
    assert res[1] is None
    data, centers, units, ranks = res[0]
    streamed = D.load_map(tmp_path / "shards")
    for k, d in enumerate(DEPTHS):
        ref = rw.psf_map(doe_lens(), FIELDS, WLS, size=SIZE, object_distance_mm=d)
        # same batches and plans on each rank as in one process: measured bit for bit (max error 0.0);
        # 1e-12 of the PSF values (peak ~1e-2) is the bound
        assert np.max(np.abs(data[k] - ref.data)) <= 1e-12
        assert np.max(np.abs(streamed[k].data - ref.data)) <= 1e-12
        assert np.array_equal(centers[k], ref.centers_mm)
    # both ranks worked; every unit's cost is the planner's estimate (flops > 0)
    assert {u["rank"] for u in units} == {0, 1}
    assert all(u["cost"] > 0 for u in units) and sum(r["psfs"] for r in ranks) == 8


def test_balance_is_by_estimated_work_not_by_count():
    # one expensive unit and three cheap ones: the expensive one gets a rank to itself
    assert D.assign([10.0, 1.0, 1.0, 1.0], 2) == [[0], [1, 2, 3]]
    assert D.assign([1.0, 1.0, 1.0, 1.0], 2) == [[0, 2], [1, 3]]


def test_one_process_equals_rw_psf_map_and_needs_no_torch():
    # N = 1 (no launcher environment): the same batches in this process, bit for bit
    m = D.psf_map(doe_lens(), FIELDS, WLS, size=SIZE)
    ref = rw.psf_map(doe_lens(), FIELDS, WLS, size=SIZE)
    assert np.array_equal(m.data, ref.data) and m.info["world_size"] == 1
    # ... and without importing torch (a fresh interpreter: this one may hold torch from other tests)
    code = ("import sys; sys.path.insert(0, %r)\n"
            "from rwwarp import distributed as D\n"
            "from test_map import doe_lens\n"
            "D.psf_map(doe_lens(), [0.0], [0.45], size=8)\n"
            "assert 'torch' not in sys.modules, 'torch was imported'\n") % str(Path(__file__).parent)
    env = {k: v for k, v in os.environ.items() if k not in ("WORLD_SIZE", "RANK", "LOCAL_RANK")}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env)
    assert r.returncode == 0, r.stderr[-2000:]


def test_a_failing_rank_ends_the_run_with_its_error():
    pytest.importorskip("torch")
    t = time.perf_counter()
    with pytest.raises(D.DistributedError, match="lens file broken on rank 1") as e:
        D.launch(_failing_worker, 2)
    assert e.value.rank == 1
    # the launcher stops rank 0 (waiting in a barrier) at once: no collective timeout (600 s) involved
    assert time.perf_counter() - t < 60
