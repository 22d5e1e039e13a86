"""HybridLens.psf_map plans every source from one pilot trace (HybridLens.raywaves_alone) and computes the focal
sources of a tile together (torch_bridge.packed.PackedTile, cut by torch_bridge.packed.pack_units, the cutter
LiveProvider uses too).

The reference is each source computed alone by HybridLens.psf: its own plan (HybridLens.raywave: the single-source
planner rwwarp.wave.batch_plan.plan_batch and its own pilot trace) and its own path (HybridLens._psf_rw, whose
gradients tests/torch_bridge/test_focal_bridge.py checks against finite differences). A source's pilot rays do not
depend on the others traced beside it, so the plans are the same bits; the packed tile sums the same terms in
another order (one trace of all members, batched matrix products), so PSFs and gradients agree to rounding."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

import rwwarp.wave.pilot as P
import torch_bridge as tb
from _lenses import wrapping_doe_lens

FIELDS = [(0.0, 0.0), (0.0, 5.0), (3.0, 2.0)]
WLS = [0.5, 0.6]
SIZE = 12




def _module(lens, **kw):
    # the coarse plan (nyquist_safety 1): the orchestration is compared, not the sampling
    opts = dict(method="focal", rays_per_sample=0.5, focal_patch_tol=1e-3, nyquist_safety=1.0)
    opts.update(kw)
    return tb.HybridLens(lens, learn={"curvature": "all", "doe": "all", "thickness": "all"}, **opts)


def _grads(m):
    return {q: getattr(m, q).grad.detach().clone() for q in ("curvature", "doe", "thickness")}


def _diff(a, b, path="plan"):
    """Where ``a`` and ``b`` differ, exactly (arrays: dtype, shape and bits; dataclasses, dicts, sequences member by
    member; the lens and the pilot skipped: another object each, the pilot's rows compared apart; the flag
    ``own_pupils``, which names how a batch lays its pupils: a single source's is at its own wavelength either way,
    the batch's shortest)."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        a2, b2 = np.asarray(a), np.asarray(b)
        ok = a2.dtype == b2.dtype and a2.shape == b2.shape and np.array_equal(a2, b2, equal_nan=a2.dtype.kind in "fc")
        return [] if ok else [path]
    if isinstance(a, float) and isinstance(b, float):   # np.float64 or float (the single-source planner's kind)
        return [] if (a == b or (math.isnan(a) and math.isnan(b))) else [path]
    if type(a) is not type(b):
        return [f"{path}: type"]
    if dataclasses.is_dataclass(a):
        return [d for f in dataclasses.fields(a) if f.name not in ("lens", "pilot", "own_pupils")
                for d in _diff(getattr(a, f.name), getattr(b, f.name), f"{path}.{f.name}")]
    if isinstance(a, dict):
        return [f"{path}: keys"] if list(a) != list(b) else [d for k in a for d in _diff(a[k], b[k], f"{path}[{k!r}]")]
    if isinstance(a, (list, tuple)):
        return [f"{path}: length"] if len(a) != len(b) else \
            [d for i, (x, y) in enumerate(zip(a, b)) for d in _diff(x, y, f"{path}[{i}]")]
    if hasattr(a, "__dict__") and not isinstance(a, (int, str, bool)):
        return _diff(vars(a), vars(b), f"{path}<{type(a).__name__}>")
    return [] if a == b else [path]


def test_map_plans_are_each_sources_own_plan():
    """The plans psf_map uses (raywaves_alone without centres: one pilot trace) against HybridLens.raywave of each
    source alone (its own pilot trace, its own patch centre): every field of every plan the same bits, the
    pilot's rows too (a float may be a numpy float64 on one side: the values are compared)."""
    lens = wrapping_doe_lens()
    m = _module(lens)
    f = [x for x in FIELDS for _ in WLS]
    w = [y for _ in FIELDS for y in WLS]
    got = m.raywaves_alone(f, w, SIZE, centers_mm=None)
    for k, r in enumerate(got):
        ref = m.raywave([f[k]], [w[k]], SIZE)
        d = _diff(ref.batch_plan, r.batch_plan)
        assert not d, (k, d[:4])
        for name in ("pos_p", "pos_s", "dir_s", "opl_p", "ok", "valid_plane"):
            assert np.array_equal(getattr(ref.batch_plan.pilot, name), getattr(r.batch_plan.pilot, name)), name
    # the check compares plans that differ between sources (patches of their own: 5 centres for 6 sources, the
    # lateral colour moving some by a pixel)
    assert len({tuple(r.centers[0]) for r in got}) >= len(FIELDS)


@pytest.mark.parametrize("tile,budget,slot_waste,packs", [(None, None, None, [6]), (None, None, 1.5, [4, 2]),
                                                          (4, None, None, [4, 2]), (3, 100 * 2**20, None, [2, 3])],
                         ids=["one-tile", "slot-sets", "tiles-of-4", "budget"])
def test_map_equals_each_source_alone(tile, budget, slot_waste, packs, monkeypatch):
    """A489 + wrapping DOE, 3 fields x 2 wavelengths (6 focal sources, each on its own plan), curvatures, DOE and
    thicknesses learning: psf_map (one packed tile, slot_waste None; the default slot_waste 1.5: the sources by
    their ray grids and windows (48-103 rays a side, 102-220 samples), a packed tile of the 1st, 2nd, 4th and 6th sources and one of
    the 3rd and 5th, the rows put back in order); tiles of 4 sources, checkpointed: a packed tile of 4 and one
    of 2; tiles of 3 sources under a 100 MiB budget, checkpointed, each cut into packed tiles whose estimate fits
    the 74 MiB left for tiles: the first tile's sources estimated 17.6 MiB packed by two, 97 MiB by three (the 5 deg
    source at 0.5 um needs 32 MiB alone), so a packed tile of 2 and the third source alone; the second tile's 54
    MiB, one packed tile) against HybridLens.psf of each source, and the gradient of a weighted sum of the map
    against the sum of each source's. Measured on the CPU (the three cases): PSFs up to 8.0e-16 of each PSF's peak;
    gradients up to 1.6e-15 (curvature), 2.2e-14 (DOE) and 2.1e-13 (thickness: the wave plane's z gradient, a sum
    of terms 1e4 times its value that cancels, test_packed_live) of the largest; tolerances about 10x those: 1e-14
    (PSFs), 2e-13 (curvature, DOE), 2e-12 (thickness). The
    centres are those of each source alone."""
    lens = wrapping_doe_lens()
    weights = torch.as_tensor(np.random.default_rng(4).standard_normal((len(FIELDS), len(WLS), SIZE, SIZE)))
    import torch_bridge.packed as tp
    made = []

    class Counted(tp.PackedTile):
        def __init__(self, members, *a, **k):
            made.append(len(members))
            super().__init__(members, *a, **k)
    monkeypatch.setattr(tp, "PackedTile", Counted)
    m = _module(lens)
    out, centers = m.psf_map(FIELDS, WLS, SIZE, tile=tile, memory_budget_bytes=budget, return_centers=True,
                             slot_waste=slot_waste)
    assert made == packs
    (out * weights).sum().backward()
    got = _grads(m)
    ref = _module(lens)
    for i, f in enumerate(FIELDS):
        for j, w in enumerate(WLS):
            p, c = ref.psf(f, w, SIZE, return_centers=True)
            (p * weights[i, j]).sum().backward()
            peak = float(p.detach().abs().max())
            assert float((out[i, j].detach() - p.detach()).abs().max()) <= 1e-14 * peak, (f, w)
            assert np.array_equal(centers[i, j], c), (f, w)
    want = _grads(ref)
    for q, g in want.items():
        scale = float(g.abs().max())
        assert scale > 0, q
        assert float((got[q] - g).abs().max()) <= (2e-12 if q == "thickness" else 2e-13) * scale, q
    # the sources differ (the comparison is not of equal numbers)
    assert float((out[0, 0] - out[1, 0]).abs().max()) > 1e-3 * float(out[0, 0].abs().max())


class _Counts:
    """Counts of pilot traces (rwwarp.wave.pilot.pilot_from_tracer: every planner's) and of warp.launch calls."""

    def __init__(self, monkeypatch):
        import warp as wp
        self.pilots = self.launches = 0
        trace, launch = P.pilot_from_tracer, wp.launch

        def pilot(*a, **k):
            self.pilots += 1
            return trace(*a, **k)

        def counted(*a, **k):
            self.launches += 1
            return launch(*a, **k)
        monkeypatch.setattr(P, "pilot_from_tracer", pilot)
        monkeypatch.setattr(wp, "launch", counted)

    def take(self):
        out = (self.pilots, self.launches)
        self.pilots = self.launches = 0
        return out


def test_one_pilot_trace_a_map_and_launches_independent_of_the_sources(monkeypatch):
    """A psf_map call that plans (replan=True) traces one pilot for all its sources, however many; forward +
    backward of 1 x 2, 2 x 2 and 3 x 2 focal sources (one packed tile each: slot_waste None) make the same number
    of Warp launches (measured 36 each, planning included; one source at a time before the packing: 72, 144 and 216, 36 a
    source, with one pilot trace a source). With kept plans (replan=False) each source is planned alone
    (HybridLens.raywave's cache), once: one pilot trace a source on the first call, none on the next, whose
    launches are again those of one packed tile whatever the sources (measured 28 for 4 and 6 sources; before:
    128 and 184)."""
    lens = wrapping_doe_lens()
    count = _Counts(monkeypatch)
    m = _module(lens)
    launches = {}
    for n in (1, 2, 3):
        m.zero_grad()
        m.psf_map(FIELDS[:n], WLS, SIZE, slot_waste=None).sum().backward()
        pilots, launches[n] = count.take()
        assert pilots == 1, n
    assert launches[1] == launches[2] == launches[3], launches
    kept = _module(lens, replan=False)
    kept.psf_map(FIELDS, WLS, SIZE, slot_waste=None).sum().backward()
    assert count.take()[0] == len(FIELDS) * len(WLS)
    steady = {}
    for n in (2, 3):
        kept.zero_grad()
        kept.psf_map(FIELDS[:n], WLS, SIZE, slot_waste=None).sum().backward()
        pilots, steady[n] = count.take()
        assert pilots == 0, n
    assert steady[2] == steady[3] < launches[3], steady
    # the kept tile follows the values: after a curvature step the map equals each source on its kept plan
    # (HybridLens.psf: the same cached RayWave, computed alone), to 1e-14 of the peak (measured 8.0e-16 above)
    with torch.no_grad():
        prev = kept.psf_map(FIELDS, WLS, SIZE, slot_waste=None)
        kept.curvature[0] *= 1.0 + 1e-4
        out = kept.psf_map(FIELDS, WLS, SIZE, slot_waste=None)
        assert count.take()[0] == 0
        for i, f in enumerate(FIELDS):
            for j, w in enumerate(WLS):
                p = kept.psf(f, w, SIZE)
                assert float((out[i, j] - p).abs().max()) <= 1e-14 * float(p.abs().max()), (f, w)
    # the step moved the PSFs (the comparison above is not of the values before it)
    assert float((out - prev).abs().max()) > 1e-6 * float(prev.abs().max())


def test_sources_not_packable_run_alone_in_the_maps_order(monkeypatch):
    """Sources that cannot be packed (here the 0.5 um ones, declared so: in use a band-limited method or a wave
    step) run alone, the others in one packed tile; the tile's work is the alone ones first, so the rows are put
    back in the sources' order: against HybridLens.psf of each source, PSFs to 1e-14 of the peak (measured
    8.0e-16, test_map_equals_each_source_alone) and the same patch centres."""
    import torch_bridge.packed as tp
    real = tp.packable
    monkeypatch.setattr(tp, "packable", lambda r: real(r) and r.wls[0] != 0.5)
    lens = wrapping_doe_lens()
    made = []

    class Counted(tp.PackedTile):
        def __init__(self, members, *a, **k):
            made.append([r.wls[0] for r in members])
            super().__init__(members, *a, **k)
    monkeypatch.setattr(tp, "PackedTile", Counted)
    m = _module(lens)
    with torch.no_grad():
        out, centers = m.psf_map(FIELDS, WLS, SIZE, return_centers=True, slot_waste=None)
        assert made == [[0.6] * len(FIELDS)]
        for i, f in enumerate(FIELDS):
            for j, w in enumerate(WLS):
                p, c = m.psf(f, w, SIZE, return_centers=True)
                assert float((out[i, j] - p).abs().max()) <= 1e-14 * float(p.abs().max()), (f, w)
                assert np.array_equal(centers[i, j], c), (f, w)


def test_slot_sets_bound_the_padding():
    """torch_bridge.packed.slot_sets on random ray grids and windows: every set's packed work (each member in the
    slots of the set's largest ray grid and largest window, 232 bytes a ray and 64 a sample, written here from the
    definition) is at most ``waste`` times the members' own, every source in exactly one set, each set in source
    order; equal members make one set, and waste 1 keeps only equal sizes together."""
    from types import SimpleNamespace as NS

    from torch_bridge.packed import slot_sets
    work = lambda rg, n: rg * rg * 232 + n * n * 64
    rng = np.random.default_rng(7)
    for waste in (1.0, 1.25, 1.5, 3.0):
        rg, ng = rng.integers(40, 400, 30), rng.integers(100, 900, 30)
        members = [NS(plan=NS(ray_grid=int(a), n_grid=int(b))) for a, b in zip(rg, ng)]
        js = list(range(100, 130))
        sets = slot_sets(js, members, waste)
        assert sorted(j for s in sets for j in s) == js
        for s in sets:
            assert s == sorted(s)
            k = [j - 100 for j in s]
            padded = len(k) * work(int(rg[k].max()), int(ng[k].max()))
            assert padded <= waste * sum(work(int(rg[i]), int(ng[i])) for i in k)
        if waste == 3.0:
            assert len(sets) < 15   # the bound lets sizes share a set (the check above is not of singletons only)
    same = [NS(plan=NS(ray_grid=100, n_grid=300))] * 5
    assert slot_sets(list(range(5)), same, 1.0) == [list(range(5))]
    with pytest.raises(ValueError, match="waste"):
        slot_sets([0], same[:1], 0.5)


def test_live_provider_slot_sets_equal_its_per_source_path():
    """LiveProvider(slot_waste=1.5) cuts its chunk by the same torch_bridge.packed.pack_units as psf_map: the six
    sources above in 2 packed tiles (None: 1), the PSFs those of LiveProvider(pack=False), each source on its own
    path, to 1e-14 of each peak (measured 6.5e-16 both ways)."""
    from torch_bridge import design as dz
    lens = wrapping_doe_lens()
    pix = lens.sensor.pixel_pitch
    fields = FIELDS
    with torch.no_grad():
        ref = dz.LiveProvider(_module(lens), fields, SIZE, pix, pack=False).psfs(WLS)
        for sw, packs in ((1.5, 2), (None, 1)):
            prov = dz.LiveProvider(_module(lens), fields, SIZE, pix, slot_waste=sw)
            out = prov.psfs(WLS)
            assert prov.packs_made == packs, sw
            peak = ref.abs().amax((2, 3), keepdim=True)
            assert float(((out - ref).abs() / peak).max()) <= 1e-14, sw
    with pytest.raises(ValueError, match="slot_waste"):
        dz.LiveProvider(_module(lens), fields, SIZE, pix, slot_waste=0.5)


@pytest.mark.parametrize("opts", [dict(pixel_values="intensity"), dict(amplitude="paper"),
                                  dict(deterministic=True), dict(method="two-step")],
                         ids=["intensity", "paper", "deterministic", "two-step"])
def test_map_options_equal_each_source_alone(opts):
    """The module's options reach the packed tiles: pixel values |U|^2 ("intensity"), the paper's amplitude, the
    deterministic splat; psf_map (one packed tile, slot_waste None) against HybridLens.psf of each source,
    PSFs to 1e-14 of each peak (measured 7.9e-16, 6.7e-16, 5.8e-16). "two-step": every source planned ASM with
    a wave step (2.0-2.06 mm), none packable: each runs alone on the plan it has alone (measured equal, 0)."""
    import warnings
    lens = wrapping_doe_lens()
    m = _module(lens, **opts)
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")     # a two-step plan's WaveStepWarning, alike in both
        out = m.psf_map(FIELDS, WLS, SIZE, slot_waste=None)
        for i, f in enumerate(FIELDS):
            for j, w in enumerate(WLS):
                p = m.psf(f, w, SIZE)
                assert float((out[i, j] - p).abs().max()) <= 1e-14 * float(p.abs().max()), (f, w)
