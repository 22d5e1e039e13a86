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
    """One rank: the sharded map gathered on rank 0 (saved to ``out/gathered.npz``), the same map
    streamed to shards in ``out/shards``; then rank 1 raises while rank 0 waits in a collective (it
    would wait forever without the launcher stopping it)."""
    import torch.distributed as dist
    m = D.psf_map(doe_lens(), FIELDS, WLS, DEPTHS, size=SIZE, progress=True)
    D.psf_map(doe_lens(), FIELDS, WLS, DEPTHS, size=SIZE, out=Path(out) / "shards")
    if m is not None:
        np.savez(Path(out) / "gathered.npz", data=np.stack([x.data for x in m]),
                 centers=np.stack([x.centers_mm for x in m]), unit_ranks=[u["rank"] for u in m[0].info["units"]],
                 unit_costs=[u["cost"] for u in m[0].info["units"]], psfs=sum(r["psfs"] for r in m[0].info["ranks"]))
    dist.barrier()
    if dist.get_rank() == 1:
        raise ValueError("lens file broken on rank 1")
    dist.barrier()


def test_sharded_map_on_two_ranks_equals_the_single_process_map_and_a_failing_rank_ends_the_run(tmp_path):
    # one launch for both checks (starting 2 processes costs ~10 s here)
    pytest.importorskip("torch")
    t = time.perf_counter()
    with pytest.raises(D.DistributedError, match="lens file broken on rank 1") as e:
        D.launch(_map_worker, 2, str(tmp_path))
    # the failing rank's own error; the launcher stopped rank 0 (waiting in a barrier) at once: no
    # collective timeout (30 min) involved
    assert e.value.rank == 1
    assert time.perf_counter() - t < 120
    g = np.load(tmp_path / "gathered.npz")
    streamed = D.load_map(tmp_path / "shards")
    for k, d in enumerate(DEPTHS):
        ref = rw.psf_map(doe_lens(), FIELDS, WLS, size=SIZE, object_distance_mm=d)
        # same batches and plans on each rank as in one process: measured bit for bit (max error 0.0);
        # 1e-12 of the PSF values (peak ~1e-2) is the bound
        assert np.max(np.abs(g["data"][k] - ref.data)) <= 1e-12
        assert np.max(np.abs(streamed[k].data - ref.data)) <= 1e-12
        assert np.array_equal(g["centers"][k], ref.centers_mm)
    # both ranks worked; every unit has a positive cost (planned flops of an ASM batch, the source count of a focal one)
    assert set(g["unit_ranks"].tolist()) == {0, 1}
    assert np.all(g["unit_costs"] > 0) and int(g["psfs"]) == 8


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
    code = (f"import sys; sys.path.insert(0, {str(Path(__file__).parent)!r})\n"
            "from rwwarp import distributed as D\n"
            "from test_map import doe_lens\n"
            "D.psf_map(doe_lens(), [0.0], [0.45], size=8)\n"
            "assert 'torch' not in sys.modules, 'torch was imported'\n")
    env = {k: v for k, v in os.environ.items() if k not in ("WORLD_SIZE", "RANK", "LOCAL_RANK")}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env,
                       check=False)
    assert r.returncode == 0, r.stderr[-2000:]


def test_one_process_passes_focal_precision_and_tolerance_on_as_rw_psf_map():
    # the distributed map takes rw.psf_map's arguments from the same place (rwwarp.map_run): a non-default
    # focal_precision reaches the focal propagation (it used to run "auto", single on the CPU, whatever the caller)
    lens = doe_lens()
    kw = dict(size=SIZE, method="focal")   # "auto" plans these sources ASM
    single = rw.psf_map(lens, FIELDS, WLS, focal_precision="single", **kw)
    double = rw.psf_map(lens, FIELDS, WLS, focal_precision="double", **kw)
    assert any(p["method"] == "focal" for b in double.info["batches"] for p in b["plans"])
    # the argument matters here: single against double precision products differ (measured 1.5e-7 of the peak),
    # so a map that ignored it would fail the equality below
    assert not np.array_equal(single.data, double.data)
    m = D.psf_map(lens, FIELDS, WLS, focal_precision="double", **kw)
    assert np.array_equal(m.data, double.data) and np.array_equal(m.centers_mm, double.centers_mm)
    # the same argument checks (same messages) and the same over-tolerance warning as rw.psf_map
    with pytest.raises(ValueError, match="focal_precision must be"):
        D.psf_map(lens, FIELDS, WLS, size=SIZE, focal_precision="half")
    from rwwarp.wave.model_error import ModelErrorWarning
    with pytest.warns(ModelErrorWarning) as ref_w:
        rw.psf_map(lens, [0.8], [0.45], size=SIZE, method="focal", tolerance=1e-9)
    with pytest.warns(ModelErrorWarning) as got_w:
        D.psf_map(lens, [0.8], [0.45], size=SIZE, method="focal", tolerance=1e-9)
    assert [str(w.message) for w in got_w] == [str(w.message) for w in ref_w]


def test_one_process_plans_as_rw_psf_map_where_auto_picks_the_pixel_method():
    # pixels 16 um wide on the A489 (about 5 Airy radii): rw.psf_map's "auto" takes the pixel method
    # (rwwarp.wave.pixel_scale); the distributed map plans with the same RayWave options (it used to leave out
    # allow_pixel and model_tolerance, so "auto" planned another method there) and computes a pixel source alone
    lens = rw.load_lens("a489_doe")
    ref = rw.psf_map(lens, [0.0], [0.55], size=15, pixel_mm=0.016)
    assert ref.info["batches"][0]["plan"]["method"] == "pixel"
    m = D.psf_map(lens, [0.0], [0.55], size=15, pixel_mm=0.016)
    assert np.array_equal(m.data, ref.data)
    # method="pixel" is taken as rw.psf_map takes it (it was refused)
    m = D.psf_map(lens, [0.0], [0.55], size=15, pixel_mm=0.016, method="pixel")
    assert np.array_equal(m.data, ref.data)


def test_one_process_traces_each_sources_pilot_once(monkeypatch):
    # the units are planned once (to cost and assign them) and those plans are run: every source's pilot is traced
    # once. Counted at the one place every pilot trace goes through (pilot_from_tracer: trace_pilot's and a
    # planners' own through pilot_or_trace), per source; the map planned each unit again before (every source
    # traced twice)
    import rwwarp.wave.pilot as P
    traced = {}
    real = P.pilot_from_tracer

    def counting(tr, src, plane, wls, pupil_wls, dtype):
        for f, w in zip(src["fields"], wls):
            key = (float(np.ravel(f)[-1]), float(w))
            traced[key] = traced.get(key, 0) + 1
        return real(tr, src, plane, wls, pupil_wls, dtype)
    monkeypatch.setattr(P, "pilot_from_tracer", counting)
    fields, wls = [0.0, 0.5, 0.8], [0.45, 0.65]
    m = D.psf_map(doe_lens(), fields, wls, size=SIZE, batch=2)
    assert traced == {(f, w): 1 for f in fields for w in wls}
    assert len(m.info["units"]) == 3   # 2 sources a unit (batch=2): each unit was planned again, alone, before
    traced.clear()
    ref = rw.psf_map(doe_lens(), fields, wls, size=SIZE, batch=2)
    assert traced == {(f, w): 1 for f in fields for w in wls}   # what rw.psf_map does
    assert np.array_equal(m.data, ref.data) and np.array_equal(m.centers_mm, ref.centers_mm)
