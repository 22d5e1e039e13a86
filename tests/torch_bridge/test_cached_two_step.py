"""The wave step (rwwarp.wave.wave_step, issue 27) in the design loop: CachedProvider with method "two-step" caches
the DOE-plane field after the step and applies the learning DOE behind it. Checked against the live
HybridLens path (trace + splat + WaveStep + DOE + propagation every call), against rwwarp.psf(method="two-step")
for a focal entry, its DOE gradient against finite differences, and the config's optics.propagation."""
import sys
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

import rwwarp as rw  # noqa: E402
import torch_bridge as tb  # noqa: E402
from rwwarp.wave.plan import Plan  # noqa: E402
from torch_bridge import design as dz  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))
from _gradcheck import directional_error  # noqa: E402
from test_wave_step import small_scene  # noqa: E402

pytestmark = [pytest.mark.filterwarnings("ignore::rwwarp.errors.PatchWarning"),   # 16 px patches: enough to compare
              # the entry plan given to the live path explicitly (its ray grid is the auto plan's)
              pytest.mark.filterwarnings("ignore:ray density criterion")]

FIELDS = [(0.0, 0.0), (0.0, 0.3)]


def _live(m, prov, key, method="two-step"):
    """The live HybridLens PSFs (n_nodes, size, size) of the CachedProvider entry ``key``: the same base plan and
    patch centres, traced, splatted, wave-stepped and propagated in one differentiable pass."""
    rec = prov.plans[key]
    plan = Plan(rec["pitch_mm"], rec["n_grid"], rec["n_pad"], rec["ray_grid"], "explicit", False, ["test"])
    r = m.raywave(FIELDS, [key[0]] * len(FIELDS), prov.size, pixel_mm=prov.pixel_mm, plan=plan,
                  center_mm=np.asarray(rec["centers"]), method=method)
    return r, m._psf_rw(r, m.values(), tables={})


@pytest.fixture(scope="module")
def asm_two_step():
    m = tb.HybridLens(small_scene(), method="two-step", learn={"doe": "all"})
    prov = dz.CachedProvider(m, FIELDS, 16, 0.006)
    with torch.no_grad():
        out = prov.psfs([0.55])
    return m, prov, out


def test_cached_two_step_equals_the_live_two_step_path(asm_two_step):
    m, prov, out = asm_two_step
    key = prov._key(0.55, None)
    assert key in prov._cache and not prov._focal      # the band-limited ASM entry
    entry = prov._cache[key][0]
    # d = z1 R / (z1 + R) = 40 * 10 / 50 mm, stretched for the rim rays' obliquity (rwwarp.wave.wave_step,
    # "Obliquity"): by at most 1.5 |m_t|^2 < 1e-3 here (|m_t| <= NA 0.02 + the 0.3 deg chief ray's 0.005)
    assert np.all(entry.wave_step == pytest.approx(8.0, rel=1e-3)) and np.all(entry.wave_step >= 8.0)
    with torch.no_grad():
        r, live = _live(m, prov, key)
        _, one = _live(m, prov, key, method="asm")
    assert r.plan.n_grid == entry.plan.n_grid and np.array_equal(r.origin, entry.origin)
    ref = live.numpy()
    got = out[:, 0].numpy()
    # the same operators on the same plan (the DOE after the cached step): measured 0; the tolerance allows for
    # another summation order
    assert np.max(np.abs(got - ref)) < 1e-12 * ref.max()
    # the step matters here (N_F ~ 9; measured 0.11 of the peak): the test cannot pass without it
    assert np.max(np.abs(got - one.numpy())) > 1e-2 * ref.max()


def test_cached_two_step_in_batches_and_chunks_equals_one_batch(asm_two_step):
    """Build batches of one node (a small memory budget) and propagation chunks of one node: each on the entry's
    widened plan with the entry's reduced distances (their own wave-step plans would differ)."""
    m, prov, out = asm_two_step
    small = dz.CachedProvider(m, FIELDS, 16, 0.006, memory_budget_bytes=2 ** 20)
    with pytest.warns(Warning, match="one source at a time"), torch.no_grad():
        got = small.psfs([0.55], chunk=1)
    assert small.build_log[-1]["batches"] == 2 and small.step_log[-1]["chunks"] == 2
    # one source's field does not depend on its batch: measured 0 (bit-identical); the tolerance allows for
    # another summation order
    assert torch.max(torch.abs(got - out)) <= 1e-14 * out.max()


def test_cached_two_step_resumes_from_its_recorded_plans(asm_two_step):
    """The record keeps the entry's plan before the step; a provider loading it plans the same step on it (a
    RayWave is a deterministic function of lens, sources, plan and centres) and gives the same PSFs."""
    m, prov, out = asm_two_step
    assert prov.check_sampling() == 0    # nothing changed: no replan
    again = dz.CachedProvider(m, FIELDS, 16, 0.006)
    again.load_plans(prov.plans)
    with torch.no_grad():
        got = again.psfs([0.55])
    key = prov._key(0.55, None)
    assert again._cache[key][0].plan.n_grid == prov._cache[key][0].plan.n_grid > prov.plans[key]["n_grid"]
    # measured 0 (bit-identical); the tolerance allows for another summation order
    assert torch.max(torch.abs(got - out)) <= 1e-14 * out.max()

def test_cached_two_step_doe_gradient_matches_finite_differences(asm_two_step):
    m, prov, _ = asm_two_step
    w = torch.from_numpy(np.random.default_rng(1).random((len(FIELDS), 1, 16, 16)))
    # 4-point central difference (O(h^4): measured 5.5e-7 / 6.8e-9 / 3.9e-11 / 9.7e-12 at h = 3e-3 / 1e-3 / 3e-4 /
    # 1e-4 rad); tolerance 10x the last
    assert directional_error(lambda: (prov.psfs([0.55]) * w).sum(), m.doe, 1e-4) < 1e-10


@pytest.fixture(scope="module")
def focal_two_step():
    """The DOE 30 mm before the sensor: rw.psf's two-step takes the focal method with a 12 mm wave step."""
    lens = small_scene(d2=30.0)
    ref = rw.psf(lens, 0.0, 0.55, size=16, method="two-step", focal_precision="double")
    assert ref.plan["method"] == "focal" and ref.plan["wave_step_mm"] == pytest.approx(12.0)
    m = tb.HybridLens(lens, method="two-step", learn={"doe": "all"})
    prov = dz.CachedProvider(m, [(0.0, 0.0)], 16, lens.sensor.pixel_pitch)
    prov.plans[prov._key(0.55, None)] = {"method": "focal", "centers": [list(ref.center_mm)]}
    return lens, ref, m, prov


def test_cached_two_step_focal_entry_equals_rwwarp_psf(focal_two_step):
    lens, ref, m, prov = focal_two_step
    with torch.no_grad():
        got = prov.psfs([0.55])[0, 0].numpy()
    assert prov._focal and not prov._cache
    (node, _, _), = prov._focal[prov._key(0.55, None)][0]
    assert node.plan.wave_step_mm == pytest.approx(12.0)
    # the same plan and operator (rw.psf plans the step on its focal plan, the provider on the node's): measured
    # 5.3e-16 of the peak
    assert np.max(np.abs(got - ref.data)) < 1e-11 * ref.data.max()
    one = rw.psf(lens, 0.0, 0.55, size=16, method="focal", focal_precision="double", center_mm=ref.center_mm).data
    assert np.max(np.abs(got - one)) > 1e-2 * ref.data.max()      # the step matters: measured 0.044 of the peak
    assert prov.check_sampling() == 0   # nothing changed: no replan (the node's fresh plan has its step too)


def test_cached_two_step_focal_doe_gradient_matches_finite_differences(focal_two_step):
    _, _, m, prov = focal_two_step
    w = torch.from_numpy(np.random.default_rng(4).random((1, 1, 16, 16)))
    # 4-point central difference: measured 1.5e-12 / 1.2e-11 / 4.9e-11 at h = 3e-3 / 1e-3 / 3e-4 rad (rounding
    # grows below 3e-3); tolerance 10x the first
    assert directional_error(lambda: (prov.psfs([0.55]) * w).sum(), m.doe, 3e-3) < 1.5e-11


def test_config_accepts_two_step_and_refuses_an_unknown_propagation():
    from test_train import tiny
    from torch_bridge.train import ConfigError, load_config
    cfg = load_config(tiny(**{"optics.propagation": "two-step"}))
    assert cfg["arms"][0]["config"]["optics"]["propagation"] == "two-step"
    assert load_config(tiny())["arms"][0]["config"]["optics"]["propagation"] == "auto"   # the default stays
    with pytest.raises(ConfigError, match=r"'optics.propagation'.*'two-step'.*'two_step'"):
        load_config(tiny(**{"optics.propagation": "two_step"}))


def test_live_provider_gives_sources_planned_focal_alone_their_wave_step(focal_two_step):
    """LiveProvider plans a source focal on its own once its joint plan came out focal: with method "two-step"
    that plan gets the wave step (equal to rw.psf's two-step PSF), and such a source is not packed (a packed tile
    has no wave step)."""
    lens, ref, m, _ = focal_two_step
    live = dz.LiveProvider(m, [(0.0, 0.0)], 16, lens.sensor.pixel_pitch, wavelength_ref_um=0.55)
    cen = np.asarray([ref.center_mm])
    r0, r1 = live._plan_sources([0, 1], [(0.0, 0.0)] * 2, [0.55] * 2, np.repeat(cen, 2, 0), None)
    assert r0.plan.method == "focal" and r0.plan.wave_step_mm == pytest.approx(12.0)
    with torch.no_grad():
        got = m._psf_rw(r0, m.values(), tables={})[0].numpy()
    # the same plan and operator: measured 5.3e-16 of the peak
    assert np.max(np.abs(got - ref.data)) < 1e-11 * ref.data.max()
    units = live._units([0, 1], {0: r0, 1: r1}, [], {})
    assert [k for k, _, _ in units] == ["rw", "rw"]
    # the same two sources without the step (method "focal") are packed: the check above can fail
    one = dz.LiveProvider(tb.HybridLens(lens, method="focal", learn={"doe": "all"}), [(0.0, 0.0)], 16,
                          lens.sensor.pixel_pitch)
    a, b = one._plan_sources([0, 1], [(0.0, 0.0)] * 2, [0.55] * 2, np.repeat(cen, 2, 0), None)
    assert a.plan.wave_step_mm is None and [k for k, _, _ in one._units([0, 1], {0: a, 1: b}, [], {})] == ["packed"]


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cached_two_step_on_cuda_equals_the_cpu(asm_two_step, focal_two_step):
    """The ASM and focal entries on CUDA (CuPy wave step on the Warp field's view, the cached field in torch's
    allocator): PSFs and DOE gradients against the CPU's (1e-10 of the peak / of the largest gradient: the
    splat's atomic float sums on the GPU add in another order, as in test_packed_live; not run here: no GPU
    was available when this was written)."""
    w = torch.from_numpy(np.random.default_rng(1).random((len(FIELDS), 1, 16, 16)))
    cases = ((asm_two_step[0], asm_two_step[1], FIELDS), (focal_two_step[2], focal_two_step[3], [(0.0, 0.0)]))
    for m, prov, fields in cases:
        mc = tb.HybridLens(m.to_lens(), method="two-step", learn={"doe": "all"}).to("cuda")
        pc = dz.CachedProvider(mc, fields, 16, prov.pixel_mm)
        pc.load_plans(prov.plans)
        res = []
        for mm, pp in ((m, prov), (mc, pc)):
            mm.zero_grad()
            out = pp.psfs([0.55])
            (out * w[:len(fields)].to(out.device)).sum().backward()
            res.append((out.detach().cpu(), mm.doe.grad.detach().cpu()))
        (a, ga), (b, gb) = res
        assert float((a - b).abs().max()) <= 1e-10 * float(a.max())
        assert float((ga - gb).abs().max()) <= 1e-10 * float(ga.abs().max())
        key = pc._key(0.55, None)
        e = pc._cache[key][0] if key in pc._cache else pc._focal[key][0][0][0]
        assert np.any(e.wave_step > 0)
