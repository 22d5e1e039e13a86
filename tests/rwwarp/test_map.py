"""PSF maps: per-source plans (each source on its own plan, whatever its batch), accuracy against the Rayleigh-Sommerfeld
ground truth (``rwwarp.ground_truth.rs_lens_psf``: traced rays summed directly to the pixels, no FFT and no
sampled field), equality with single-PSF calls on the same plan, and the backend's memory bookkeeping staying
bounded over many plan shapes (small thin-lens + DOE system)."""
import numpy as np
import pytest

import rwwarp as rw
from rwwarp.wave import backend as bk
from rwwarp import convergence as cv
from rwwarp.ground_truth import rs_lens_psf
from rwwarp.lens import Lens, Sensor, Surface
from rwwarp.psf import RayWave

from _mirror import mirrored_patch_truth

WLS = [0.45, 0.65]
SIZE = 32


def doe_lens(side_mm=1.0, f=50.0, doe_to_sensor_mm=10.0):
    """Aperture + ideal thin lens + an even-polynomial DOE 10 mm before the sensor: the DOE's local
    frequency grows with the footprint's distance from the axis, so fields need different pitches."""
    pixel_mm = 0.55e-3 * f / side_mm / 3
    doe = {"kind": "even_poly", "norm_radius": 0.5, "coefficients": [20.0, -5.0]}
    surfs = [Surface(type="aperture", semi_diameter=side_mm / 2, shape="circle", stop=True),
             Surface(type="thin_lens", focal_length=f, semi_diameter=side_mm, thickness=f - doe_to_sensor_mm),
             Surface(type="doe", semi_diameter=side_mm, shape="square", thickness=doe_to_sensor_mm, profile=doe)]
    return Lens(surfs, Sensor(pixel_mm, (1000, 1000)), wavelengths_um=[0.55])


def warp_launches(call):
    """``(n, result)``: the number of ``warp.launch`` calls ``call()`` makes (every thread) and its result."""
    import warp as wp
    orig, n = wp.launch, [0]

    def counted(*a, **k):
        n[0] += 1
        return orig(*a, **k)
    wp.launch = counted
    try:
        out = call()
    finally:
        wp.launch = orig
    return n[0], out


def own_plans(lens, fields, wls):
    """The plan each (field, wavelength) pair gets alone (rw.psf), by pair."""
    return {(i, j): RayWave(lens, [f], [w], SIZE, lens.sensor.pixel_pitch).plan
            for i, f in enumerate(fields) for j, w in enumerate(wls)}


# Distance of the map's on-axis PSFs to the RS ground truth, measured on the CPU (PoCL): 8.3e-3 at 0.45 um,
# 1.6e-2 at 0.65 um, those of the single-PSF calls (each source on its own plan; when a batch shared its finest
# member's plan the 0.45 um entry was 5.4e-3: a finer grid than the source's own; the ground truth itself
# converges to < 1e-5 at 24 x 96 pupil nodes). Tolerances 1.5x. Off-axis the DOE's relief wraps inside the
# footprint at these wavelengths, which the ground truth's smooth quadrature refuses: those entries are
# checked by equality with the single PSF.
MAP_TOL = {0.45: 1.25e-2, 0.65: 2.5e-2}


def test_map_sources_keep_their_own_plans_and_match_the_rs_ground_truth():
    lens = doe_lens()
    fields = [0.0, 0.8]
    m = rw.psf_map(lens, fields, WLS, size=SIZE)
    own = own_plans(lens, fields, WLS)
    batches = m.info["batches"]
    seen = set()
    for b in batches:
        assert len(b["plans"]) == len(b["pairs"])
        for pr, pl in zip(b["pairs"], b["plans"]):
            seen.add(tuple(pr))
            o = own[tuple(pr)]
            # each source on the plan it has alone, whatever its batch
            assert (pl["pitch_mm"], pl["n_grid"], pl["n_pad"], pl["ray_grid"]) == (o.pitch_mm, o.n_grid, o.n_pad,
                                                                                 o.ray_grid)
    assert seen == set(own)
    for j, w in enumerate(WLS):
        # on axis the scene (round stop, thin lens, even-polynomial DOE, all centred) is even in x and y: the truth
        # on one quadrant of the patch, mirrored (tests/rwwarp/_mirror.py), a quarter of the summation
        truth = mirrored_patch_truth(lambda c, n: rs_lens_psf(lens, 0.0, w, c, n, m.pixel_mm, radial_nodes=24,
                                                              angular_nodes=96, pixel_nodes=3, include_doe=True),
                                     m.centers_mm[0, j], SIZE, m.pixel_mm)
        assert cv.rel_l2(m.data[0, j], truth) <= MAP_TOL[w]
    for i, f in enumerate(fields):
        for j, w in enumerate(WLS):
            single = rw.psf(lens, f, w, size=SIZE)
            np.testing.assert_allclose(m.centers_mm[i, j], single.center_mm, rtol=0, atol=1e-12)
            # the same plan as alone: the same numbers (the splat's float sums on CPU threads may add in another
            # order: measured 1e-16 of the peak)
            assert np.abs(m.data[i, j] - single.data).max() <= 1e-12 * single.data.max()


@pytest.mark.parametrize("name,fields,wls,size", [
    ("cooke_triplet", [14.0, 0.0], [0.55, 0.65], 16),
    ("a489_doe", [0.0, 7.0], [0.45, 0.65], 16),
], ids=["cooke-14deg", "a489-doe"])
@pytest.mark.parametrize("deterministic", [False, True], ids=["float", "deterministic"])
def test_a_psf_does_not_depend_on_its_batch(name, fields, wls, size, deterministic):
    """Issue 25 item 5: a source's PSF is the same in a batch of 1, of 2 and of all its map's sources (each on
    its own plan; a packed batch only pads with zeros). Here the Cooke triplet runs the focal method, the
    A489 + DOE the ASM. When a batch shared its members' finest plan, batch 2 against batch 1 differed by
    1.4e-3 (Cooke) and 1.1e-3 (A489 + DOE) of the PSF's peak, float and deterministic alike. Measured now:
    0 and 3.6e-16 (the splat's float sums on CPU threads add in another order; deterministic: 0);
    tolerance 1e-12. On the coarse plan (nyquist_safety 1: the batching, not the sampling, is compared; both
    lenses' batches plan the focal method on the CPU now, measured 0 on both plans, 2-2.7x faster than the default
    plan)."""
    lens = rw.load_lens(name)
    kw = dict(size=size, deterministic=deterministic, nyquist_safety=1.0)
    ones = rw.psf_map(lens, fields, wls, batch=1, **kw)
    assert all(len(b["pairs"]) == 1 for b in ones.info["batches"])
    peak = ones.data.max(axis=(2, 3), keepdims=True)
    for batch in (2, None):
        m = rw.psf_map(lens, fields, wls, batch=batch, **kw)
        assert max(len(b["pairs"]) for b in m.info["batches"]) > 1   # packed batches ran
        assert np.max(np.abs(m.data - ones.data) / peak) <= 1e-12
        np.testing.assert_array_equal(m.centers_mm, ones.centers_mm)


def test_paper_amplitude_psf_does_not_depend_on_its_batch():
    """The same for the paper's amplitude convention (bilinear splat, one power scale per source at its own
    pitch), A489 + DOE, 2 fields x 2 wavelengths: batch 2 against batch 1 differed by 9.9e-4 of the peak with a
    shared plan; now 4.1e-16 (all four in one batch); tolerance 1e-12 as above."""
    lens = rw.load_lens("a489_doe")
    kw = dict(size=16, amplitude="paper")
    ones = rw.psf_map(lens, [0.0, 7.0], [0.45, 0.65], batch=1, **kw)
    for batch in (2, None):
        m = rw.psf_map(lens, [0.0, 7.0], [0.45, 0.65], batch=batch, **kw)
        assert max(len(b["pairs"]) for b in m.info["batches"]) > 1
        assert np.max(np.abs(m.data - ones.data) / ones.data.max(axis=(2, 3), keepdims=True)) <= 1e-12


def test_backend_memory_stays_bounded_over_a_map_and_results_do_not_depend_on_it():
    lens = doe_lens()
    fields = [0.0, 0.3, 0.6, 0.9]
    wls = [0.45, 0.55, 0.65]
    be = bk.get_backend("cpu")
    be.clear_caches()
    assert be.allocated_bytes() == 0
    # batch=1: one propagation per (field, wavelength), each with its own grid and FFT shapes
    m = rw.psf_map(lens, fields, wls, size=SIZE, batch=1)
    after_map = be.memory_report()
    pads = [b["plan"]["n_pad"] for b in m.info["batches"]]
    assert len(set(pads)) >= 4  # many shapes went through the backend
    # working set of the largest plan alone, on an emptied backend
    (i, j), = m.info["batches"][int(np.argmax(pads))]["pairs"]
    be.clear_caches()
    p = rw.psf(lens, fields[i], wls[j], size=SIZE)
    largest = be.memory_report()
    np.testing.assert_allclose(p.data, m.data[i, j], rtol=0, atol=1e-12 * p.data.max())
    # scratch arrays: one per tag, as big as the largest request, not one per shape
    assert after_map["workspace_bytes"] <= largest["workspace_bytes"]
    assert set(after_map["workspaces"]) == set(largest["workspaces"])
    # FFT plans and transfer functions are LRU caches with fixed bounds
    assert after_map["fft_plans"] <= be.max_fft_plans
    assert after_map["fft_plan_bytes"] <= be.max_fft_plan_bytes
    assert after_map["cache_bytes"] <= be.cache.max_bytes
    assert be.allocated_bytes() == largest["workspace_bytes"] + largest["cache_bytes"] + largest["fft_plan_bytes"]
    # every other map entry equals its PSF computed on an emptied backend
    for (i2, j2) in [(0, 0), (3, 2), (1, 1)]:
        be.clear_caches()
        q = rw.psf(lens, fields[i2], wls[j2], size=SIZE)
        np.testing.assert_allclose(q.data, m.data[i2, j2], rtol=0, atol=1e-12 * q.data.max())


def test_release_all_empties_every_backend_made_and_is_registered_at_exit():
    """``release_all`` (run at exit, before the interpreter's teardown) leaves no cached workspace, FFT plan or
    transfer function in any backend made; the caches refill on the next use and give the same PSF."""
    be = bk.get_backend("cpu")
    lens = doe_lens()
    p = rw.psf(lens, 0.2, 0.55, size=16)
    assert be in bk._MADE and be.allocated_bytes() > 0
    bk.release_all()
    assert be.allocated_bytes() == 0 and be.memory_report()["fft_plans"] == 0
    q = rw.psf(lens, 0.2, 0.55, size=16)
    np.testing.assert_array_equal(p.data, q.data)
    # run at exit: a process whose only backend records the calls prints them as it exits
    import subprocess
    import sys
    code = ("from rwwarp.wave import backend as b\n"
            "class Fake:\n"
            "    def synchronize(self): print('synchronized', flush=True)\n"
            "    def clear_caches(self): print('cleared', flush=True)\n"
            "b._MADE.append(Fake())\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and r.stdout.split() == ["synchronized", "cleared"], (r.stdout, r.stderr)


def test_workspace_views_share_one_buffer_per_tag():
    be = bk.get_backend("cpu")
    be.clear_caches()
    a = be.workspace("t_probe", (4, 8), np.complex128)
    b = be.workspace("t_probe", (2, 3), np.complex128)  # smaller: a view of the same buffer
    assert b.shape == (2, 3) and be.memory_report()["workspaces"]["t_probe:<c16"] == 4 * 8 * 16
    c = be.workspace("t_probe", (16, 16), np.complex128)  # larger: replaced
    assert c.shape == (16, 16) and be.memory_report()["workspaces"]["t_probe:<c16"] == 16 * 16 * 16
    be.workspace("t_probe", (4,), np.complex64)  # another dtype: its own buffer
    assert be.memory_report()["workspaces"]["t_probe:<c8"] == 4 * 8
    # views are usable device arrays: write through one, read the same memory back
    c.fill(1.0 + 2.0j)
    d = be.workspace("t_probe", (3, 5), np.complex128)
    np.testing.assert_array_equal(be.to_host(d), np.full((3, 5), 1.0 + 2.0j))
    del a
    be.clear_caches()
    assert be.allocated_bytes() == 0


@pytest.mark.parametrize("threads", [1, 2])
def test_parallel_cpu_trace_is_bitwise_the_serial_trace(threads):
    from rwwarp.trace import Tracer, pupil_grid
    lens = rw.load_lens("cooke_triplet")
    ref = Tracer(lens, [0.55, 0.45], device="cpu", threads=1).trace(
        [(0.0, 0.0), (0.0, 10.0), (3.0, 5.0)], grid=201, wavelength_index=[0, 1, 0]).numpy()
    tr = Tracer(lens, [0.55, 0.45], device="cpu", threads=threads + 1)
    got = tr.trace([(0.0, 0.0), (0.0, 10.0), (3.0, 5.0)], grid=201, wavelength_index=[0, 1, 0]).numpy()
    n_rays = got["valid"].size
    assert len(tr._chunks(n_rays)) == min(threads + 1, n_rays // 32768) > 1
    for k in ref:
        np.testing.assert_array_equal(got[k], ref[k])
    # an independent check of the traced geometry: the chief ray of the on-axis field stays on the axis
    u, v, _ = pupil_grid(201, "circle")
    centre = int(np.flatnonzero((u == 0) & (v == 0))[0])
    assert got["valid"][0, centre] and np.abs(got["pos"][0, centre, :2]).max() < 1e-12


def test_fft_plan_cache_is_an_lru_with_a_count_bound_and_stays_correct():
    be = bk.get_backend("cpu")
    be.clear_caches()
    keep = be.max_fft_plans
    be.max_fft_plans = 2
    try:
        rng = np.random.default_rng(1)
        built, dropped = be.fft_plans_built, be.fft_plans_dropped
        # sizes 8, 12, 16, 8, 8, 20 with two plans kept (least recently used dropped): 8 built, 12 built, 16 built
        # (drops 8), 8 built again (drops 12), 8 kept, 20 built (drops 16): five builds, three drops
        # 8 built again after its drop: the cache cycles, counted and warned once (a plan build is a VkFFT kernel
        # compile, ~0.2-0.7 s on CUDA: a working set over the bound would cost that at every use, unseen)
        from rwwarp.errors import PerformanceWarning
        rebuilt = be.fft_plans_rebuilt
        with pytest.warns(PerformanceWarning, match="FFT plans are cycling"):
            for n in (8, 12, 16, 8, 8, 20):
                x = rng.standard_normal((2, n, n)) + 1j * rng.standard_normal((2, n, n))
                d = be.to_device(x)
                be.fft2(d)
                np.testing.assert_allclose(be.to_host(d), np.fft.fft2(x), rtol=0, atol=1e-12 * n * n)
                assert be.memory_report()["fft_plans"] <= 2
        assert (be.fft_plans_built - built, be.fft_plans_dropped - dropped) == (5, 3)
        assert be.fft_plans_rebuilt - rebuilt == 1
        assert be.memory_report()["fft_plans_built"] == be.fft_plans_built
    finally:
        be.max_fft_plans = keep
        be.clear_caches()


def test_allocation_retries_after_release_hooks(cl_backend):
    """An out-of-memory allocation frees the backend's cache and calls the release hooks (torch_bridge
    registers torch's empty_cache) before one retry; other errors pass through untouched."""
    be = cl_backend
    calls = []
    be.cache.get(("test-oom", 1), lambda: be.empty((16,), np.complex128))
    view = be.workspace("test-oom", (4, 4), np.complex128)
    assert len(be.cache) >= 1 and be.memory_report()["workspaces"]

    def hook():
        calls.append("hook")

    be.add_release_hook(hook)
    be.add_release_hook(hook)  # registered once
    attempts = []

    def alloc():
        attempts.append(1)
        if len(attempts) == 1:
            raise MemoryError("out of memory")
        return "ok"

    try:
        assert be._allocate(alloc) == "ok"
        assert attempts == [1, 1] and calls == ["hook"] and len(be.cache) == 0
        assert not be.memory_report()["workspaces"]
        assert view.shape == (4, 4)  # a view still held keeps its buffer

        def bad():
            raise ValueError("not memory")

        with pytest.raises(ValueError):
            be._allocate(bad)
        assert calls == ["hook"]
    finally:
        be._release_hooks.remove(hook)


def test_map_launches_do_not_grow_with_its_sources():
    """The second ``psf_map`` call of a plan-stable map makes one set of Warp launches per batch, whatever the
    number of sources in it (issue 25: a 30-source A489 + DOE map at 32 px made 908 launches, 30 a source;
    packed per-source plans make 30 for the whole map). Counted by wrapping ``warp.launch`` (every thread).
    Here 2 and 6 sources of the small DOE system, 16 px: the counts must be equal (the launches are per
    surface and stage, not per source; measured 15 and 15) and stay at most 20 (one source a batch, as
    before the packing, would make 15 a source: 90 for the 6)."""
    lens = doe_lens()
    counts = {}
    for fields in ([(0.0, 0.0)], [(0.0, 0.0), (0.0, 0.2), (0.0, 0.4)]):
        rw.psf_map(lens, fields, WLS, size=16, device="cpu")   # first call: kernels built
        counts[len(fields) * len(WLS)], _ = warp_launches(lambda: rw.psf_map(lens, fields, WLS, size=16, device="cpu"))
    assert counts[2] == counts[6], counts
    assert 0 < counts[6] <= 20, counts


def test_pack_sources_is_the_greedy_packing_under_the_budget():
    """rwwarp.map_run.pack_sources (running maxima) against the greedy packing written from its definition with
    rwwarp.wave.packed.packed_bytes over each candidate batch: the same batches, each within the budget, on random
    plans of two methods."""
    from types import SimpleNamespace as NS

    from rwwarp.map_run import pack_sources
    from rwwarp.wave.packed import packed_bytes
    rng = np.random.default_rng(3)
    members = []
    for k in range(60):
        rg, n = int(rng.integers(50, 400)), int(rng.integers(100, 900))
        est = rg * rg * 232 + n * n * 64 + int(rng.integers(0, 5e7))
        members.append(NS(plan=NS(method=("focal", "asm")[k % 5 == 0], ray_grid=rg, n_grid=n,
                                  estimate={"memory_bytes": est}), rim=True))
    for budget, batch in ((2 ** 31, None), (2 ** 29, 7), (2 ** 33, None)):
        got = pack_sources(members, 32, batch, budget)
        order = sorted(range(60), key=lambda k: (members[k].plan.method, members[k].rim, -members[k].plan.ray_grid,
                                                 -members[k].plan.n_grid, k))
        want, cur = [], []
        for k in order:
            if cur and members[cur[0]].plan.method == members[k].plan.method and \
                    packed_bytes([members[i] for i in cur + [k]], 32) <= budget and (batch is None or len(cur) < batch):
                cur.append(k)
                continue
            if cur:
                want.append(cur)
            cur = [k]
        want.append(cur)
        assert got == want
        assert sorted(k for b in got for k in b) == list(range(60))
        assert all(len(b) == 1 or packed_bytes([members[k] for k in b], 32) <= budget for b in got)
