"""The CPU map's execution (issue 25, deliverable 5): a packed batch's splat split over CPU threads by whole
sources (the same bits as one thread), the batches of a map sharing their work arrays (allocations bounded by
the largest batch, not summed over batches), and the default batch's planned bytes on the CPU
(:data:`rwwarp.map_run.CPU_BATCH_BYTES`). Small thin-lens + DOE system of test_map."""
import numpy as np
import pytest

wp = pytest.importorskip("warp")

import rwwarp as rw
from rwwarp.map_run import CPU_BATCH_BYTES, batch_budget, map_args, plan_units
from rwwarp.wave.packed import PackedRayWave, packed_bytes, source_plans
from rwwarp.wave.splat import source_groups

from test_map import WLS, doe_lens


def test_source_groups_cover_every_source_once_in_balanced_ranges():
    """Contiguous ranges, one per thread, covering 0..n_src once, each summed work within the largest single
    source's work of an even share; None with fewer sources than threads."""
    rng = np.random.default_rng(5)
    for n_src, threads in ((2, 2), (9, 2), (30, 4), (7, 3)):
        w = rng.uniform(0.2, 3.0, n_src)
        g = source_groups(w, n_src, threads)
        assert len(g) == threads and g[0][0] == 0 and g[-1][1] == n_src
        assert all(lo < hi for lo, hi in g) and all(g[k][1] == g[k + 1][0] for k in range(threads - 1))
        share = w.sum() / threads
        assert all(abs(w[lo:hi].sum() - share) <= w.max() + 1e-12 for lo, hi in g)
    assert source_groups(np.ones(1), 1, 2) is None


def test_cpu_threads_splat_whole_sources_the_same_bits_as_one_thread():
    """A packed batch of 6 sources (over the 65,536 rays a CPU launch is split from): its field with the tracer's
    2 threads, each taking whole sources into one set of sums, equals the field of one thread bit for bit (each
    sample adds its rays in the same order); the splat ran as 2 launches."""
    lens = doe_lens()
    fields = [(0.0, 0.0), (0.0, 0.3), (0.0, 0.6)]
    members = source_plans(lens, [f for f in fields for _ in WLS], [w for _ in fields for w in WLS], 32,
                           lens.sensor.pixel_pitch, "cpu", method="focal")
    packed = PackedRayWave(members)
    assert packed.nsrc * int(packed._ray_grids.max()) ** 2 >= 2 * 32768
    packed.tracer.threads = 2
    counts = {}
    orig = wp.launch

    def counted(kernel, *a, **k):
        counts[kernel.key] = counts.get(kernel.key, 0) + 1
        return orig(kernel, *a, **k)
    wp.launch = counted
    try:
        two = packed.field_array().copy()
    finally:
        wp.launch = orig
    assert sum(n for key, n in counts.items() if "splat_forward_kernel" in key) == 2
    packed.tracer.threads = 1
    one = packed.field_array().copy()
    assert np.array_equal(two, one)


def _run_bytes(call):
    """Bytes of the Warp arrays ``wp.zeros`` / ``wp.empty`` make while ``call()`` runs its batches
    (``PackedRayWave.run``: the trace, splat and field; the planning's pilot trace is not counted)."""
    made, inside = [0], [False]
    oz, oe, orun = wp.zeros, wp.empty, PackedRayWave.run

    def counted(f):
        def g(*a, **k):
            r = f(*a, **k)
            if inside[0]:
                made[0] += r.capacity
            return r
        return g

    def run(self, *a, **k):
        inside[0] = True
        try:
            return orun(self, *a, **k)
        finally:
            inside[0] = False
    wp.zeros, wp.empty, PackedRayWave.run = counted(oz), counted(oe), run
    try:
        call()
    finally:
        wp.zeros, wp.empty, PackedRayWave.run = oz, oe, orun
    return made[0]


def test_map_batches_share_their_work_arrays():
    """A map of 8 sources in batches of 1 allocates its rays, splat sums and field once (the largest batch's),
    not once a batch: measured 1.01x the bytes of its largest source's batch alone (each batch allocating its own,
    as before: 5.4x); bound 1.5x. The PSFs equal those of one batch of all 8 (measured 0: the same sums)."""
    lens = doe_lens()
    fields = [0.0, 0.3, 0.6, 0.9]
    kw = dict(size=16, device="cpu")
    m = rw.psf_map(lens, fields, WLS, batch=1, **kw)   # kernels built
    every = _run_bytes(lambda: rw.psf_map(lens, fields, WLS, batch=1, **kw))
    largest = max(_run_bytes(lambda: rw.psf_map(lens, [fields[i]], [WLS[j]], batch=1, **kw))
                  for i in range(len(fields)) for j in range(len(WLS)))
    assert len(m.info["batches"]) == len(fields) * len(WLS)
    assert every <= 1.5 * largest, (every, largest)
    together = rw.psf_map(lens, fields, WLS, batch=len(fields) * len(WLS), **kw)
    assert np.max(np.abs(together.data - m.data) / m.data.max(axis=(2, 3), keepdims=True)) <= 1e-12


def test_cpu_default_batches_stay_within_cpu_batch_bytes():
    """Without ``batch`` the CPU's packed batches plan at most CPU_BATCH_BYTES (a member over it runs alone), and
    within a smaller memory budget when one is given; an explicit ``batch`` keeps the budget alone."""
    assert batch_budget("cpu", None, 2 ** 40) == CPU_BATCH_BYTES
    assert batch_budget("cpu", None, 2 ** 20) == 2 ** 20
    assert batch_budget("cpu", 9, 2 ** 40) == 2 ** 40
    assert batch_budget("cuda", None, 2 ** 40) == 2 ** 40
    lens = rw.load_lens("a489_doe")
    fields = [(0.0, 0.0), (0.0, 4.0), (4.0, 4.0), (0.0, 9.0)]
    a = map_args(lens, fields, [0.45, 0.55, 0.65], size=32, device="cpu")
    units = plan_units(lens, a, [(i, j) for i in range(len(fields)) for j in range(3)])
    assert sum(len(c) for c, _, _ in units) == 12
    for _, _, members in units:
        if len(members) > 1:
            assert packed_bytes(members, 32) <= CPU_BATCH_BYTES
