"""The plan cache of repeated PSF calls (issue 25, :class:`rwwarp.PlanCache`): a hit gives the bits of the uncached
call (same plans, launches and order of sums on the CPU), any change of the lens's numbers, in place included, is a
miss that gives the uncached result of the changed lens, and the bounds (entries, bytes) hold. Small thin-lens + DOE
system of test_map (16 px: a few ms a PSF)."""
import copy

import numpy as np
import pytest

import rwwarp as rw
from rwwarp.wave.plan_cache import lens_fingerprint

from test_map import doe_lens, warp_launches
from test_warm_host import change_in_place


@pytest.fixture(autouse=True)
def _no_default_cache():
    """These tests compare a given cache against the uncached calls: the process-wide default cache (rw.psf's
    ``cache="auto"``) is off while they run (tests/rwwarp/test_warm_host.py tests it)."""
    from rwwarp.wave.plan_cache import set_default_cache
    old = set_default_cache(None)
    yield
    set_default_cache(old)


def _same(a, b):
    """Bit equality of two PSF maps' data, centres, traced fractions and plans."""
    assert np.array_equal(a.data, b.data)
    assert np.array_equal(a.centers_mm, b.centers_mm)
    assert np.array_equal(np.asarray(a.info["valid_fraction"]), np.asarray(b.info["valid_fraction"]))
    assert [bt["plans"] for bt in a.info["batches"]] == [bt["plans"] for bt in b.info["batches"]]


@pytest.mark.parametrize("method", ["asm", "focal"])
def test_hit_gives_the_bits_of_the_uncached_call(method):
    """psf_map over 2 fields x 2 wavelengths (one batch of 4 sources, each on its own plan) and psf: the first cached
    call (a miss) and the next two (hits) equal the uncached call bit for bit, and a hit traces no pilot (fewer Warp
    launches: counted by wrapping ``warp.launch``)."""
    lens = doe_lens()
    fields, wls = [0.0, 0.3], [0.45, 0.65]
    ref = rw.psf_map(lens, fields, wls, size=16, method=method)
    cache = rw.PlanCache()
    runs, launches = [], []
    for _ in range(3):
        n, r = warp_launches(lambda: rw.psf_map(lens, fields, wls, size=16, method=method, cache=cache))
        runs.append(r)
        launches.append(n)
    assert [r.info["cache"] for r in runs] == ["miss", "hit", "hit"]
    for r in runs:
        _same(r, ref)
    assert launches[1] == launches[2] < launches[0], launches
    assert (cache.hits, cache.misses, len(cache)) == (2, 1, 1)
    # a single PSF through the same cache: its own entry, the bits of rw.psf
    p0 = rw.psf(lens, 0.3, 0.65, size=16, method=method)
    for expect in ("miss", "hit"):
        p = rw.psf(lens, 0.3, 0.65, size=16, method=method, cache=cache)
        assert p.info["cache"] == expect
        assert np.array_equal(p.data, p0.data) and p.center_mm == p0.center_mm
    assert len(cache) == 2


def test_changed_arguments_are_misses():
    """Another size, wavelength, field or precision is another entry (each result that of its uncached call)."""
    lens = doe_lens()
    cache = rw.PlanCache()
    base = dict(size=16, method="asm")
    for kw in ({}, {"size": 12}, {"wavelength_um": 0.5}, {"field_deg": 0.2}, {"dtype": "float32"}):
        args = dict(base, **kw)
        fd, wl = args.pop("field_deg", 0.0), args.pop("wavelength_um", 0.55)
        p = rw.psf(lens, fd, wl, cache=cache, **args)
        assert p.info["cache"] == "miss", kw
        assert np.array_equal(p.data, rw.psf(lens, fd, wl, **args).data), kw
    assert len(cache) == 5


@pytest.mark.parametrize("change", ["radius", "doe_coefficient", "sensor_pitch", "thickness", "pixel_map_data"])
def test_an_in_place_change_of_the_lens_is_a_miss(change):
    """Changing the lens object in place (a surface's focal length or thickness, a DOE coefficient in its profile's
    list, the sensor's pixel pitch, one pixel of a pixel-map DOE's inline array) makes the next cached
    call plan again and give what the uncached call of the changed lens gives; the earlier entry stays valid for
    the earlier values (a lens built with them again hits it)."""
    lens = doe_lens()
    original = copy.deepcopy(lens)
    cache = rw.PlanCache()
    kw = dict(size=16, method="asm")
    if change == "pixel_map_data":
        rng = np.random.default_rng(1)
        lens.surfaces[2].profile = {"kind": "pixel_map", "pitch": 0.02, "data": rng.uniform(0.0, 0.5, (60, 60))}
        original = copy.deepcopy(lens)
    first = rw.psf(lens, 0.0, 0.55, cache=cache, **kw)
    if change == "pixel_map_data":
        lens.surfaces[2].profile["data"][30, 30] += 1.0   # in place, in the numpy array
    else:
        change_in_place(lens, "focal_length" if change == "radius" else change)
    again = rw.psf(lens, 0.0, 0.55, cache=cache, **kw)
    fresh = rw.psf(lens, 0.0, 0.55, **kw)
    assert again.info["cache"] == "miss"
    assert np.array_equal(again.data, fresh.data)
    assert not np.array_equal(again.data, first.data)   # the change moves the PSF (the check can fail)
    back = rw.psf(original, 0.0, 0.55, cache=cache, **kw)   # the earlier values, another object: a hit
    assert back.info["cache"] == "hit"
    assert np.array_equal(back.data, first.data)


def test_kept_entry_is_not_reached_by_a_later_change():
    """An entry is planned on a private copy of the lens: changing the caller's lens after the call does not change
    what a hit of the earlier values computes (here the DOE coefficients, read again by every run of the DOE phase)."""
    lens = doe_lens()
    twin = copy.deepcopy(lens)
    cache = rw.PlanCache()
    kw = dict(size=16, method="asm")
    first = rw.psf(lens, 0.0, 0.55, cache=cache, **kw)
    lens.surfaces[2].profile["coefficients"][0] = 30.0
    hit = rw.psf(twin, 0.0, 0.55, cache=cache, **kw)
    assert hit.info["cache"] == "hit"
    assert np.array_equal(hit.data, first.data)


def test_fingerprint_follows_every_number_and_the_glass_data():
    """lens_fingerprint: equal lenses (built twice) agree; any numeric field, an element of a profile array changed in
    place, and a material's dispersion data (another glass under the surface) change it."""
    a, b = doe_lens(), doe_lens()
    assert lens_fingerprint(a) == lens_fingerprint(b)
    b.surfaces[0].semi_diameter = 0.5000000001
    assert lens_fingerprint(a) != lens_fingerprint(b)
    c = doe_lens()   # a pixel-map DOE's inline data, changed in place by one ulp in one pixel
    c.surfaces[2].profile = {"kind": "pixel_map", "pitch": 0.01, "data": np.zeros((8, 8))}
    f0 = lens_fingerprint(c)
    c.surfaces[2].profile["data"][3, 4] = np.nextafter(0.0, 1.0)
    assert lens_fingerprint(c) != f0
    d = doe_lens()
    d.surfaces[2].material = "N-BK7"
    assert lens_fingerprint(d) != lens_fingerprint(a)


def test_bounds_hold():
    """max_entries: the least recently used entry goes first (its next call is a miss, the others hit); max_bytes:
    the held bytes stay under it, and an entry over it on its own is not kept (every call a miss, the same bits)."""
    lens = doe_lens()
    kw = dict(size=16, method="focal")
    cache = rw.PlanCache(max_entries=2)
    for w in (0.45, 0.55, 0.65):
        rw.psf(lens, 0.0, w, cache=cache, **kw)
    assert len(cache) == 2 and cache.evictions == 1
    assert rw.psf(lens, 0.0, 0.65, cache=cache, **kw).info["cache"] == "hit"
    assert rw.psf(lens, 0.0, 0.45, cache=cache, **kw).info["cache"] == "miss"   # evicted first
    one = cache.nbytes() / len(cache)
    assert one > 0   # the focal operators are counted
    small = rw.PlanCache(max_bytes=int(1.5 * one))
    for w in (0.45, 0.55, 0.65):
        rw.psf(lens, 0.0, w, cache=small, **kw)
        assert small.nbytes() <= small.max_bytes
    assert len(small) == 1
    none = rw.PlanCache(max_bytes=0)
    ref = rw.psf(lens, 0.0, 0.55, **kw)
    for _ in range(2):
        p = rw.psf(lens, 0.0, 0.55, cache=none, **kw)
        assert p.info["cache"] == "miss" and np.array_equal(p.data, ref.data)
    assert len(none) == 0 and none.nbytes() == 0
    cache.clear()
    assert len(cache) == 0 and cache.nbytes() == 0


def test_bad_cache_arguments():
    with pytest.raises(TypeError, match="cache"):
        rw.psf(doe_lens(), 0.0, 0.55, size=16, cache={})
    with pytest.raises(ValueError, match="max_entries"):
        rw.PlanCache(max_entries=0)
    with pytest.raises(ValueError, match="max_bytes"):
        rw.PlanCache(max_bytes=-1)


def test_hit_bits_with_a_curved_last_surface():
    """The Cooke triplet (a curved last surface: the rays are carried on to its vertex plane, Tracer.to_plane, whose
    arrays a kept batch also reuses) at a coarse sampling: two hits equal the uncached call bit for bit."""
    lens = rw.load_lens("cooke_triplet")
    kw = dict(size=8, rays_per_sample=0.1)
    ref = rw.psf(lens, 14.0, 0.55, **kw)
    cache = rw.PlanCache()
    for expect in ("miss", "hit", "hit"):
        p = rw.psf(lens, 14.0, 0.55, cache=cache, **kw)
        assert p.info["cache"] == expect
        assert np.array_equal(p.data, ref.data)


@pytest.mark.parametrize("kw", [{"deterministic": True}, {"amplitude": "paper"}, {"pixel_values": "intensity"},
                                {"dtype": "float32"}])
def test_hit_bits_on_the_other_paths(kw):
    """The fixed-point splat (deterministic), the paper amplitude convention, intensity pixels and float32 rays: a
    hit's PSF is the uncached call's, bit for bit."""
    lens = doe_lens()
    ref = rw.psf(lens, 0.3, 0.45, size=16, method="focal", **kw)
    cache = rw.PlanCache()
    for expect in ("miss", "hit"):
        p = rw.psf(lens, 0.3, 0.45, size=16, method="focal", cache=cache, **kw)
        assert p.info["cache"] == expect
        assert np.array_equal(p.data, ref.data)


def test_results_do_not_alias_the_kept_arrays():
    """A kept batch reuses its work arrays (rays, splat sums, field) on every hit: what an earlier call returned (PSF
    data, traced fraction, dropped-ray count) stays as it was after later hits of another field's entry and of its
    own."""
    lens = doe_lens()
    cache = rw.PlanCache()
    a = rw.psf(lens, 0.0, 0.55, size=16, method="focal", cache=cache)
    a_data, a_vf = a.data.copy(), float(a.info["valid_fraction"])
    for f in (0.3, 0.0, 0.3, 0.0):
        rw.psf(lens, f, 0.55, size=16, method="focal", cache=cache)
    assert np.array_equal(a.data, a_data) and float(a.info["valid_fraction"]) == a_vf


def test_an_implicit_budget_is_checked_on_every_hit(monkeypatch):
    """Without ``memory_budget_gb`` a call plans under half the available memory of the moment; a kept entry whose
    batches no longer fit it is dropped and the call plans again, refusing as the uncached call does."""
    from rwwarp.wave import plan as plan_mod
    from rwwarp.wave.plan import MemoryBudgetError
    lens = doe_lens()
    cache = rw.PlanCache()
    rw.psf(lens, 0.0, 0.55, size=16, method="asm", cache=cache)
    assert rw.psf(lens, 0.0, 0.55, size=16, method="asm", cache=cache).info["cache"] == "hit"
    monkeypatch.setattr(plan_mod, "default_memory_budget_bytes", lambda device="cpu": 1024)
    with pytest.raises(MemoryBudgetError):
        rw.psf(lens, 0.0, 0.55, size=16, method="asm")
    with pytest.raises(MemoryBudgetError):
        rw.psf(lens, 0.0, 0.55, size=16, method="asm", cache=cache)
    assert len(cache) == 0


@pytest.mark.gpu
@pytest.mark.parametrize("name,field,method", [("a489_doe", 0.0, "asm"), ("a489_doe", 10.0, "focal"),
                                               ("cooke_triplet", 14.0, "focal")])
def test_cuda_hit_gives_the_bits_of_the_uncached_call(name, field, method):
    """On CUDA (not run on the CPU-only machine this was written on): a hit (the kept batch's pooled Warp arrays, its DOE
    phase uploaded once, its CuPy focal operators and DOE factor) equals the uncached call to within what two uncached
    calls differ by (nothing, when the device's sums are deterministic: the deterministic splat; exactly equal then),
    and a changed sensor pitch is a miss that gives its own uncached call."""
    try:
        import cupy
        if cupy.cuda.runtime.getDeviceCount() < 1:
            raise RuntimeError
    except Exception:
        pytest.skip("no CUDA device")
    lens = rw.load_lens(name)
    kw = dict(size=32, method=method, device="cuda", deterministic=True)
    ref = rw.psf(lens, field, 0.55, **kw).data
    noise = float(np.max(np.abs(rw.psf(lens, field, 0.55, **kw).data - ref)))   # run to run, uncached
    cache = rw.PlanCache()
    for expect in ("miss", "hit", "hit"):
        p = rw.psf(lens, field, 0.55, cache=cache, **kw)
        assert p.info["cache"] == expect
        assert float(np.max(np.abs(p.data - ref))) <= 2.0 * noise, (expect, noise)
    lens.sensor.pixel_pitch *= 1.05
    p = rw.psf(lens, field, 0.55, cache=cache, **kw)
    assert p.info["cache"] == "miss"
    assert float(np.max(np.abs(p.data - rw.psf(lens, field, 0.55, **kw).data))) <= 2.0 * noise
    assert float(np.max(np.abs(p.data[:ref.shape[0], :ref.shape[1]] - ref))) > 2.0 * noise   # the change shows


def test_held_bytes_makes_no_tracer():
    """Counting what a kept batch holds reads the members' tracers only where they exist: members planned with
    their tracer made on first use (rwwarp.wave.packed.source_plans) are not given one by the count."""
    from rwwarp.wave.packed import PackedRayWave, source_plans
    from rwwarp.wave.plan_cache import held_bytes
    lens = rw.load_lens("a489_doe")
    ms = source_plans(lens, [0.0, 5.0], [0.55, 0.55], 16, lens.sensor.pixel_pitch, method="focal")
    assert all(m.tracer_made() is None for m in ms)
    packed = PackedRayWave(ms, hold=True)
    n = held_bytes([(None, packed)])
    assert n >= packed.tracer.params_np.nbytes > 0
    assert all(m.tracer_made() is None for m in ms)
