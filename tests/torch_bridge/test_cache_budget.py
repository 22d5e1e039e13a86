"""CachedProvider field builds under a memory budget: split into batches of nodes, the cached
DOE-plane fields and the PSFs equal those of a one-batch build, the library's own peak estimate
stays within the budget, and the frozen build keeps no ray gradients."""
import numpy as np
import pytest

torch = pytest.importorskip("torch")

import rwwarp as rw
import torch_bridge as tb
from torch_bridge import design as dz
from torch_bridge.train import ConfigError, load_config


def _setup():
    lens = rw.load_lens("a489_doe")
    d = lens.doe_index
    lens = lens.with_surface(d, profile={**lens.surfaces[d].profile, "coefficients": [-20.0, 8.0, 3.0, -1.0]})
    m = tb.HybridLens(lens, learn={"doe": "all"}, nyquist_safety=1.0, rays_per_sample=1.2)
    pos = dz.node_positions_mm("grid", 1.0, (2, 2), region="quadrant")       # 4 nodes, sensor mm
    return m, dz.field_angles(lens, pos, 0.55)


def test_batched_cache_build_equals_one_batch_and_respects_budget():
    m, fields = _setup()
    wls = [0.47, 0.63]
    one = dz.CachedProvider(m, fields, 21, 0.003, wavelength_ref_um=0.55, memory_budget_bytes=10 ** 12)
    one.prepare(wls, [None])
    assert [e["batches"] for e in one.build_log] == [1, 1]
    # the frozen refractive part: no gradient buffers on the rays
    assert all(not e[0].tracer.requires_grad for e in one._cache.values())
    # a budget that holds the fixed part and two of the four sources of the larger entry (bytes)
    est = max(one.build_log, key=lambda e: e["per_source"])
    budget = est["fixed"] + 2 * est["per_source"] + est["per_source"] // 2
    split = dz.CachedProvider(m, fields, 21, 0.003, wavelength_ref_um=0.55, memory_budget_bytes=budget)
    split.load_plans(one.plans)                       # the same plans and centres
    split.prepare(wls, [None])
    for e in split.build_log:
        assert e["budget"] + e["held"] == budget       # the fields cached before count against the budget
        assert e["peak"] + e["held"] <= budget        # the library's own estimate of the build's peak
        assert e["fixed"] + e["batch"] * e["per_source"] == e["peak"]
    assert max(e["batches"] for e in split.build_log) >= 2
    for w in wls:
        k = one._key(w, None)
        u1, u2 = one._cache[k][1].numpy(), split._cache[k][1].numpy()
        assert u1.shape == u2.shape
        np.testing.assert_allclose(u2, u1, rtol=0, atol=1e-12 * np.abs(u1).max())
        np.testing.assert_allclose(split._cache[k][3].numpy(), one._cache[k][3].numpy(), rtol=1e-12, atol=0)
    p1 = one.psfs(wls).detach().numpy()
    p2 = split.psfs(wls).detach().numpy()
    np.testing.assert_allclose(p2, p1, rtol=0, atol=1e-12 * p1.max())
    # the DOE gradient through the batched cache (design wavelength, weighted PSFs, random direction)
    # against a 4-point central difference. With the current focal planner the difference does not follow
    # the O(h^4) truncation: 4.9e-11, 1.4e-10, 4.9e-11, 1.7e-11 at h = 0.005, 0.01, 0.02, 0.04 rad (one
    # batch) and 2.35e-10 at 0.01 (split build): the finite difference's own floor (2.2e-11 with the
    # previous planner). Tolerance 5e-10, about twice the largest; a wrong gradient term is off by > 1e-4
    from _gradcheck import directional_error
    w = torch.from_numpy(np.random.default_rng(4).random((len(fields), 1, 21, 21)))
    assert directional_error(lambda: (split.psfs([0.55]) * w).sum(), m.doe, 0.01) < 5e-10


def test_budget_too_small_warns_and_traces_one_source_at_a_time():
    m, fields = _setup()
    prov = dz.CachedProvider(m, fields[:2], 21, 0.003, wavelength_ref_um=0.55, memory_budget_bytes=1)
    with pytest.warns(rw.errors.SamplingWarning, match="memory budget"):
        prov.prepare([0.55], [None])
    assert prov.build_log[0]["batch"] == 1 and prov.build_log[0]["batches"] == 2


def test_memory_budget_validated():
    m, fields = _setup()
    with pytest.raises(ValueError, match="cache_device"):
        dz.CachedProvider(m, fields, 21, 0.003, cache_device="gpu")
    # on the CPU the host is the device: the fields stay where they are and count against the budget
    assert not dz.CachedProvider(m, fields, 21, 0.003, cache_device="host").cache_on_host
    with pytest.raises(ConfigError, match="cache_device"):
        load_config({"lens": {"file": "a489_doe"}, "optics": {"cache_device": "gpu"}})
    with pytest.raises(ValueError, match="memory_budget_bytes"):
        dz.CachedProvider(m, fields, 21, 0.003, memory_budget_bytes=0)
    base = {"lens": {"file": "a489_doe"}, "optics": {"memory_budget_gb": -1}}
    with pytest.raises(ConfigError, match="memory_budget_gb"):
        load_config(base)
    assert tb.modules.default_memory_budget_bytes("cpu") == 4 * 2 ** 30


def test_step_chunks_equal_one_chunk_values_and_gradients():
    """A step propagated in chunks of nodes, recorded or checkpointed, gives the one-chunk PSFs and gradients
    (DOE coefficients and the learning DOE-to-sensor distance), and the default chunk follows the budget
    (bytes) through the library's own per-node estimates."""
    lens = rw.load_lens("a489_doe")
    d = lens.doe_index
    lens = lens.with_surface(d, profile={**lens.surfaces[d].profile, "coefficients": [-20.0, 8.0, 3.0, -1.0]})
    m = tb.HybridLens(lens, learn={"doe": "all", "thickness": [d]}, nyquist_safety=1.0, rays_per_sample=1.2)
    fields = dz.field_angles(lens, dz.node_positions_mm("grid", 1.0, (2, 2), region="quadrant"), 0.55)
    prov = dz.CachedProvider(m, fields, 21, 0.003, wavelength_ref_um=0.55, memory_budget_bytes=10 ** 12)
    assert prov.learn_distance
    wls = [0.47, 0.63]
    prov.prepare(wls, [None])
    w = torch.linspace(0.5, 1.5, 21, dtype=torch.float64)[None, None, :, None]   # a non-uniform loss weight

    def run(chunk):
        m.zero_grad()
        p = prov.psfs(wls, chunk=chunk)
        (p * w).sum().backward()
        return p.detach().numpy(), m.doe.grad.numpy().copy(), m.thickness.grad.numpy().copy()
    p1, g1, t1 = run(None)
    assert prov.step_log[-1]["chunks"] == 1
    # chunks of 3 nodes: 4 nodes make a chunk of 3 and a remainder chunk of 1, so this one case holds both
    # a multi-node checkpointed chunk and a single-node one (a chunk of 1, checked alone before, is the
    # remainder's path; the chunk count -(-4 // c) is checked for c = 3)
    for c in (3,):
        pc, gc, tc = run(c)
        assert prov.step_log[-1]["chunks"] == -(-4 // c)
        np.testing.assert_allclose(pc, p1, rtol=0, atol=1e-13 * p1.max())
        np.testing.assert_allclose(gc, g1, rtol=1e-10, atol=1e-12 * np.abs(g1).max())
        np.testing.assert_allclose(tc, t1, rtol=1e-10, atol=1e-12 * np.abs(t1).max())
    assert np.abs(g1).max() > 0 and np.abs(t1).max() > 0
    # the default chunk: a step's propagation gets half of what the budget leaves beside the cached fields.
    # A budget of 2.5 nodes' estimate: 2 nodes, 2 chunks, recorded as they run (what a recorded node keeps
    # until backward is far below the budget)
    e = prov._entry(0.63, None)[0]
    per = prov.step_bytes_per_source(e)
    prov.memory_budget_bytes = prov.cache_bytes() + 2 * int(2.5 * per)
    prov.psfs([0.63])
    assert prov.step_log[-1]["chunk"] == 2 and prov.step_log[-1]["chunks"] == 2
    assert not prov.step_log[-1]["checkpointed"]
    # two wavelengths of a call (the entry twice): a chunk's transient memory is freed before the next chunk
    # runs, so each wavelength's chunks still take the whole budget
    prov.psfs([0.63, 0.63])
    assert [r["chunk"] for r in prov.step_log[-2:]] == [2, 2]
    # a budget below what the recorded nodes keep until backward (4 nodes x two wavelengths): every chunk is
    # checkpointed, each wavelength gets half the budget, and values and gradients stay those of one chunk
    held = prov.held_bytes_per_source(e)
    assert held >= 16 * e.plan.n_grid ** 2        # a learning distance keeps the modulated field
    prov.memory_budget_bytes = prov.cache_bytes() + 2 * (7 * held)
    m.zero_grad()
    p = prov.psfs(wls)
    (p * w).sum().backward()
    assert [r["checkpointed"] for r in prov.step_log[-2:]] == [True, True]
    assert all(r["chunk"] == 1 for r in prov.step_log[-2:])
    np.testing.assert_allclose(p.detach().numpy(), p1, rtol=0, atol=1e-13 * p1.max())
    np.testing.assert_allclose(m.doe.grad.numpy(), g1, rtol=1e-10, atol=1e-12 * np.abs(g1).max())
    np.testing.assert_allclose(m.thickness.grad.numpy(), t1, rtol=1e-10, atol=1e-12 * np.abs(t1).max())


def test_recentre_keeps_the_cached_field_and_matches_an_independent_psf():
    """When the DOE moves the patches, check_sampling re-centres them without a rebuild, and the
    re-centred PSFs equal the full ray-wave PSF (its own trace, plan and propagation) at the new
    centres."""
    lens = rw.load_lens("a489_doe")
    d = lens.doe_index
    lens = lens.with_surface(d, profile={**lens.surfaces[d].profile, "coefficients": [-2.0, 0.0, 0.0, 0.0]})
    m = tb.HybridLens(lens, learn={"doe": "all"}, nyquist_safety=2.0, rays_per_sample=1.2)
    fields = dz.field_angles(lens, [(1.2, 1.2)], 0.55)
    prov = dz.CachedProvider(m, fields, 21, 0.003, wavelength_ref_um=0.55, doe_budget_cpmm=40)
    prov.prepare([0.55], [None])
    u_before = prov._cache[prov._key(0.55, None)][1]
    rw_before = prov._cache[prov._key(0.55, None)][0]
    c_before = rw_before.centers.copy()
    with torch.no_grad():
        m.doe.copy_(torch.tensor([-60.0, 0.0, 0.0, 0.0], dtype=torch.float64))   # added power: the patch moves
    assert prov.check_sampling() == 1
    assert [e["reason"] for e in prov.replan_log] == ["re-centre"] and prov.replan_log[0]["shift_um"] > 21 * 3 / 8
    assert prov._cache[prov._key(0.55, None)][1] is u_before        # kept, not rebuilt
    np.testing.assert_array_equal(rw_before.centers, c_before)       # the module's cached RayWave untouched
    cen = prov._cache[prov._key(0.55, None)][0].centers[0]
    with torch.no_grad():
        got = prov.psfs([0.55])[0, 0].numpy()
        ref = m.psf(fields[0], 0.55, 21, pixel_mm=0.003, center_mm=cen).numpy()
        fresh = dz.CachedProvider(m, fields, 21, 0.003, wavelength_ref_um=0.55, doe_budget_cpmm=40)
        fresh.load_plans(prov.plans)                                  # rebuilt at the recorded new centres
        fresh.prepare([0.55], [None])
        rebuilt = fresh.psfs([0.55])[0, 0].numpy()
    np.testing.assert_array_equal(got, rebuilt)
    err = np.linalg.norm(got - ref) / np.linalg.norm(ref)
    assert err < 2e-3, err                                            # measured 5.4e-4 (sampling error)
    # the patch holds the PSF: its centroid is near the patch centre (not cut at an edge)
    yy, xx = np.mgrid[-10:11, -10:11]
    assert abs((got * xx).sum() / got.sum()) < 3 and abs((got * yy).sum() / got.sum()) < 3


def test_budget_leaves_aside_what_the_device_holds_outside_torch(monkeypatch):
    """A budget of the device's used memory: the build's and the step's shares leave aside what the card holds
    outside torch's allocator (context, CuPy / Warp pools; on an H100 the a489_aberration field builds went 0.52 GB
    over 24 GB without this). The CUDA reading is total - free - torch's reserve, checked on made-up readings."""
    from torch_bridge import budget as bud
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda d=None: (60 * 10 ** 9, 80 * 10 ** 9))
    monkeypatch.setattr(torch.cuda, "memory_reserved", lambda d=None: 15 * 10 ** 9)
    assert bud.device_overhead_bytes("cuda:0") == 5 * 10 ** 9          # 80 - 60 - 15 GB
    monkeypatch.setattr(torch.cuda, "memory_reserved", lambda d=None: 25 * 10 ** 9)
    assert bud.device_overhead_bytes("cuda:0") == 0                    # never negative
    assert bud.device_overhead_bytes("cpu") == 0
    m, fields = _setup()
    p = dz.CachedProvider(m, fields, 21, 0.003, wavelength_ref_um=0.55, memory_budget_bytes=24 * 10 ** 9)
    monkeypatch.setattr(bud, "device_overhead_bytes", lambda dev: 10 ** 9)
    assert p.budget_bytes() == 23 * 10 ** 9
    monkeypatch.setattr(p, "cache_bytes", lambda: 9 * 10 ** 9)
    assert p.step_budget_bytes() == 7 * 10 ** 9                        # (24 - 1 - 9) / 2 GB


def test_a_recorded_step_keeps_only_the_node_fields_until_backward():
    """What a step's recorded graph keeps for the backward pass, measured with torch's saved-tensor hooks (the
    distinct storages saved by every op and custom Function, bytes): the DOE modulation is recomputed in
    backward, so a node keeps its node fields only, the library's estimate ``held_bytes_per_source`` (no
    DOE-plane array: without the recomputed modulation the phase polynomial's intermediates, the transmission
    and the modulated field, each ``n_grid^2`` samples, were kept: 50 MB against 7.3 MB here). Gradients equal those of the
    chunks checkpointed whole (the path taken when the kept graphs exceed the budget)."""
    m, fields = _setup()
    prov = dz.CachedProvider(m, fields, 21, 0.003, wavelength_ref_um=0.55, memory_budget_bytes=10 ** 12)
    wls = [0.47, 0.63]
    prov.prepare(wls, [None])
    seen = {}

    def pack(t):
        s = t.untyped_storage()
        seen[s.data_ptr()] = s.nbytes()
        return t
    m.zero_grad()
    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        p = prov.psfs(wls)
    p.sum().backward()
    g_rec = m.doe.grad.clone()
    kept = sum(seen.values())
    entries = [prov._entry(w, None)[0] for w in wls]
    held = sum(prov.held_bytes_per_source(e) * e.nsrc for e in entries)
    grid = max(e.plan.n_grid for e in entries) ** 2 * 8       # one real DOE-plane array of the larger entry
    assert not any(r["checkpointed"] for r in prov.step_log[-2:])
    assert held <= kept <= held + 2 * grid, (kept, held, grid)
    prov.memory_budget_bytes = prov.cache_bytes() + held      # below what the two wavelengths keep: checkpoints
    m.zero_grad()
    prov.psfs(wls).sum().backward()
    assert all(r["checkpointed"] for r in prov.step_log[-2:])
    np.testing.assert_allclose(m.doe.grad.numpy(), g_rec.numpy(), rtol=1e-10, atol=1e-12 * g_rec.abs().max().item())


def test_other_processes_on_the_card_do_not_eat_the_budget(monkeypatch):
    """Session 24, on an H200: a profiling run on the same GPU (~31 GB) made a design run's device-wide overhead
    exceed its 28 GB budget, and its first field build was refused "over the memory budget of 0 GiB". The overhead
    is now this process's own figure from the driver (NVML), less torch's reserve; other processes' entries do
    not count. Checked with a made-up NVML answering for this pid and another one."""
    import os
    import sys
    import types
    from torch_bridge import budget as bud
    from rwwarp.wave.plan import MemoryBudgetError

    class Proc:
        def __init__(self, pid, used):
            self.pid, self.usedGpuMemory = pid, used

    listed = [Proc(os.getpid() + 1, 31 * 10 ** 9), Proc(os.getpid(), 17 * 10 ** 9)]
    fake = types.SimpleNamespace(nvmlInit=lambda: None, nvmlDeviceGetHandleByUUID=lambda u: ("handle", u),
                                 nvmlDeviceGetComputeRunningProcesses=lambda h: listed)
    monkeypatch.setitem(sys.modules, "pynvml", fake)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "get_device_properties",
                        lambda d: types.SimpleNamespace(uuid="1234-abcd"))
    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda d=None: (80 * 10 ** 9, 141 * 10 ** 9))   # 61 GB used
    monkeypatch.setattr(torch.cuda, "memory_reserved", lambda d=None: 15 * 10 ** 9)
    assert bud.process_device_bytes("cuda:0") == 17 * 10 ** 9
    assert bud.device_overhead_bytes("cuda:0") == 2 * 10 ** 9        # 17 GB own - 15 GB reserved; not 61 - 15
    assert bud.memory_gb("cuda:0") == 17.0                             # a step's figure: this process's, not 61 GB
    # not listed (another PID namespace) or no figure: the device-wide reading, as before
    assert bud.own_process_bytes([Proc(os.getpid() + 1, 5)], os.getpid()) is None
    assert bud.own_process_bytes([Proc(os.getpid(), None)], os.getpid()) is None
    assert bud.overhead_from(141, 80, 15, None) == 46
    # an overhead that reaches the budget: a field build is refused with a message that says why; a step's share
    # is 0 (it checkpoints every chunk) rather than stopping a run
    m, fields = _setup()
    p = dz.CachedProvider(m, fields, 21, 0.003, wavelength_ref_um=0.55, memory_budget_bytes=24 * 10 ** 9)
    monkeypatch.setattr(bud, "device_overhead_bytes", lambda dev: 30 * 10 ** 9)
    with pytest.raises(MemoryBudgetError, match="in use outside torch's allocator"):
        p.budget_bytes()
    assert p.step_budget_bytes() == 0


def test_a_wandering_step_budget_keeps_each_entrys_chunk():
    """On a GPU the step's budget is read from the device each step and wanders (its overhead: Warp's and CuPy's
    pools, cuFFT work areas); each new chunk size is new RayWaves and new FFT shapes, and on CUDA each new shape a
    VkFFT compile (~0.2-0.7 s: the a489_edof gpu step built 1-13 plans a step on an H200, session 24). An entry
    keeps its chunk while it still fits and is more than half of what fits; it shrinks at once when it no longer
    fits. Checked on the a489 entries with made-up budgets, in units of the library's per-node step estimate, and
    on two steps whose budgets differ by 20 %: one set of chunk RayWaves, the same PSFs."""
    m, fields = _setup()
    prov = dz.CachedProvider(m, fields, 21, 0.003, wavelength_ref_um=0.55, memory_budget_bytes=10 ** 12)
    prov.prepare([0.55], [None])
    rw_e = prov._entry(0.55, None)[0]
    per = prov.step_bytes_per_source(rw_e)
    assert rw_e.nsrc == 4
    key = ("k",)
    seq = [prov.step_chunk(rw_e, int(b * per), key) for b in (2.5, 3.9, 2.0, 1.4, 1.9, 4.0, 2.2)]
    # 2 (fits 2); 3 fits: kept 2 (3 < 4); 2 kept; 1 fits: shrinks to 1; 1 fits: kept; 4 fits (>= 2 x 1): 4; 2 fits: 2
    assert seq == [2, 2, 2, 1, 1, 4, 2], seq
    assert [prov.step_chunk(rw_e, int(b * per)) for b in (2.5, 3.9)] == [2, 3]     # without a key: what fits
    budgets = iter([int(2.5 * per), int(3.0 * per)])
    prov.step_budget_bytes = lambda: next(budgets)
    a = prov.psfs([0.55]).detach().clone()
    b = prov.psfs([0.55]).detach().clone()
    key55 = prov._key(0.55, None)
    assert list(prov._chunks[key55]) == [2]      # the second step (3 nodes fit) reused the chunk of 2
    np.testing.assert_array_equal(a.numpy(), b.numpy())
