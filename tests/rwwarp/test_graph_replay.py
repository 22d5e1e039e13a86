"""A kept batch replayed as a CUDA graph (issue 25 item 2, :mod:`rwwarp.wave.graph_replay`).

On CUDA a cache hit replays the recorded trace, splat and propagation; the replayed kernels are the recorded ones
with the same arguments, so with ``deterministic=True`` (fixed-point splat sums) a replay must give the bits of the
uncached eager call, and a replay after a change of the lens must not happen (a miss: planned and run again). On the
CPU nothing is recorded and the call says why."""
import numpy as np
import pytest

import rwwarp as rw

from test_cuda_cpu import _cuda_or_skip


def test_cpu_hits_run_eagerly_and_say_why():
    """On the CPU a hit runs eagerly (no graphs) and ``info["replay"]`` names the reason; the bits are the
    uncached call's."""
    from test_map import doe_lens
    lens = doe_lens()
    ref = rw.psf(lens, 0.3, 0.55, size=16, method="focal")
    cache = rw.PlanCache()
    rw.psf(lens, 0.3, 0.55, size=16, method="focal", cache=cache)
    hit = rw.psf(lens, 0.3, 0.55, size=16, method="focal", cache=cache)
    assert hit.info["cache"] == "hit"
    assert hit.info["replay"] == "eager: device cpu (CUDA graphs only on CUDA devices)"   # rw.psf: one batch
    assert np.array_equal(hit.data, ref.data)
    off = rw.PlanCache(graphs=False)
    rw.psf(lens, 0.3, 0.55, size=16, method="focal", cache=off)
    assert rw.psf(lens, 0.3, 0.55, size=16, method="focal", cache=off).info["replay"] == "eager: graphs off"
    with pytest.raises(ValueError, match="graphs must be True or False"):
        rw.PlanCache(graphs="yes")


@pytest.mark.gpu
@pytest.mark.parametrize("name,fields,method", [("cooke_triplet", [0.0, 14.0], "focal"),
                                                ("a489_doe", [0.0, 10.0], "focal"),
                                                ("a489_doe", [0.0], "asm")])
def test_replay_gives_the_bits_of_the_eager_call(name, fields, method):
    """Two hits (the first records, both replay) equal the uncached eager map bit for bit (deterministic splat), and
    their info says what was replayed; a changed lens is a miss whose result is the changed lens's eager map."""
    _cuda_or_skip()
    lens = rw.load_lens(name)
    kw = dict(size=64, method=method, device="cuda", deterministic=True, focal_precision="double")
    ref = rw.psf_map(lens, fields, [0.55], **kw)
    cache = rw.PlanCache()
    first = rw.psf_map(lens, fields, [0.55], cache=cache, **kw)
    hits = [rw.psf_map(lens, fields, [0.55], cache=cache, **kw) for _ in range(2)]
    assert first.info["cache"] == "miss" and np.array_equal(first.data, ref.data)
    for h in hits:
        assert h.info["cache"] == "hit"
        assert set(h.info["replay"]) == {"graph: trace and splat"}, h.info["replay"]
        assert np.array_equal(h.data, ref.data), float(np.max(np.abs(h.data - ref.data)))
        assert np.array_equal(np.asarray(h.info["valid_fraction"]), np.asarray(ref.info["valid_fraction"]))
    # the lens changes: a miss, planned and run eagerly, equal to the changed lens's uncached map
    lens.surfaces[-1].thickness += 0.01
    changed = rw.psf_map(lens, fields, [0.55], cache=cache, **kw)
    assert changed.info["cache"] == "miss"
    assert np.array_equal(changed.data, rw.psf_map(lens, fields, [0.55], **kw).data)


def test_uploads_read_by_a_recording_are_held():
    """Every array upload_packed returns inside ``recording_uploads`` (a new upload or a cache hit) is appended to the
    holder's list, and nothing outside the block: the graph's inputs stay alive whatever the upload cache drops."""
    import numpy as np
    import warp as wp

    from rwwarp.device_upload import recording_uploads, upload_packed
    parts = [(np.arange(3.0), np.float64, wp.float64)]
    keep = []
    with recording_uploads(keep):
        a = upload_packed(parts, "cpu", cache=True)
        b = upload_packed(parts, "cpu", cache=True)          # a hit: the same views
    upload_packed([(np.arange(4.0), np.float64, wp.float64)], "cpu", cache=True)
    assert len(keep) == 2 and keep[0] is a[0] and keep[1] is b[0] and b[0] is a[0]
    assert np.array_equal(keep[0].numpy(), np.arange(3.0))


@pytest.mark.gpu
def test_auto_on_cuda_plans_the_fewer_flops_cached_or_not():
    """A489 + DOE on axis, 64 px: "auto" plans focal (fewer flops) on CUDA as on the CPU, uncached and with a
    graph-replaying cache, and gives the bits of the uncached ``method="focal"`` call (deterministic splat)."""
    _cuda_or_skip()
    lens = rw.load_lens("a489_doe")
    kw = dict(size=64, device="cuda", deterministic=True, focal_precision="double")
    ref = rw.psf(lens, 0.0, 0.55, method="focal", **kw)
    assert rw.psf(lens, 0.0, 0.55, **kw).plan["method"] == "focal"
    cache = rw.PlanCache()
    for _ in range(3):
        p = rw.psf(lens, 0.0, 0.55, cache=cache, **kw)
        assert p.plan["method"] == "focal"
        assert np.array_equal(p.data, ref.data), float(np.max(np.abs(p.data - ref.data)))
