"""Host work of a warm (repeated) PSF call (issue 25): what every call does again, checked against an independent
reference. ``Plan.to_dict`` (every result carries its plans as dicts) against the standard library's
``dataclasses.asdict``, on real plans of each method, and its dict is the caller's own (changing it changes no plan)."""
import dataclasses
import warnings

import numpy as np
import pytest

import rwwarp as rw
from rwwarp.wave.plan import Plan

from test_map import doe_lens


@pytest.fixture(autouse=True)
def _default_cache_on(monkeypatch):
    """These tests are about the default cache: the perf scripts other tests import set RWWARP_PLAN_CACHE=0 in this
    worker's environment (perf/_common.py: they time the planned call), which would turn it off here."""
    monkeypatch.delenv("RWWARP_PLAN_CACHE", raising=False)


def _asdict_reference(plan):
    """The dict ``Plan.to_dict`` gave before (the standard library's recursion, ``reasons`` as a list)."""
    d = dataclasses.asdict(plan)
    d["reasons"] = list(d["reasons"])
    return d


def _same_tree(a, b):
    """Equal values and equal container types at every level (a tuple stays a tuple, a list a list)."""
    assert type(a) is type(b), (type(a), type(b))
    if isinstance(a, dict):
        assert list(a) == list(b)
        for k in a:
            _same_tree(a[k], b[k])
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b)
        for x, y in zip(a, b):
            _same_tree(x, y)
    elif isinstance(a, np.ndarray):
        assert np.array_equal(a, b) and a.dtype == b.dtype
    else:
        assert a == b or (a != a and b != b), (a, b)


def _plans():
    warnings.simplefilter("ignore")
    lens = doe_lens()
    out = [rw.plan_psf(lens, 0.0, 0.55, size=16, method=m) for m in ("asm", "focal")]
    out.append(rw.plan_psf(lens, 0.3, 0.55, size=16, method="focal", tolerance=1e-3))   # model error, reasons
    out.append(rw.plan_psf(rw.load_lens("cooke_triplet"), 14.0, 0.55, size=8, rays_per_sample=0.1))
    return out


def test_to_dict_is_what_asdict_gives():
    plans = _plans()
    assert any(p.model_error for p in plans) and any(p.estimate for p in plans)   # nested dicts are exercised
    for p in plans:
        _same_tree(p.to_dict(), _asdict_reference(p))
    # nested containers of every kind, an array and a dataclass inside a dict field
    @dataclasses.dataclass
    class Inner:
        a: float
        b: list

    p = Plan(0.01, 8, 16, 5, reasons=("x", "y"), estimate={"memory_bytes": 10, "flops": 2.5,
                                                            "parts": [1, (2, 3.0), {"k": None}],
                                                            "arr": np.arange(3.0), "inner": Inner(1.0, [2])})
    _same_tree(p.to_dict(), _asdict_reference(p))


def test_to_dict_is_a_copy():
    """Changing the returned dict (a nested list, a nested dict, an array in place) leaves the plan as it was."""
    p = Plan(0.01, 8, 16, 5, reasons=("x",), estimate={"flops": 1.0, "parts": [1, 2], "arr": np.zeros(2)},
             model_error={"estimate": 1e-3})
    before = _asdict_reference(p)
    d = p.to_dict()
    d["reasons"].append("z")
    d["estimate"]["parts"].append(3)
    d["estimate"]["arr"][0] = 5.0
    d["model_error"]["estimate"] = 1.0
    _same_tree(_asdict_reference(p), before)


# ------------------------------------------------------------------------------------------ the default cache
# rw.psf's default cache="auto": the process-wide PlanCache (rwwarp.wave.plan_cache.default_cache). Small thin-lens +
# DOE system of test_map, 16 px, the ASM (its kernels take almost nothing: the launches are the host's cost).
KW = dict(size=16, method="asm")


@pytest.fixture(autouse=True)
def fresh_default():
    """Every test starts from a new built-in default cache and leaves the setting it found."""
    from rwwarp.wave.plan_cache import set_default_cache
    old = set_default_cache("auto")
    yield
    set_default_cache(old)


def test_default_warm_call_is_a_hit_with_few_launches():
    """The second and third plain ``rw.psf`` calls (no cache argument) are hits: the uncached call's bits, and 6 Warp
    launches (the PSF's own: generate, trace through every surface (the CPU's fused kernel), power sums, tube areas,
    splat, finalize) against the uncached call's 11 (the pilot trace and planning). Before the default cache a
    plain call planned every time (no ``info["cache"]``, 11 launches)."""
    from test_map import warp_launches
    lens = doe_lens()
    n_off, ref = warp_launches(lambda: rw.psf(lens, 0.3, 0.55, cache=None, **KW))
    n_off2, _ = warp_launches(lambda: rw.psf(lens, 0.3, 0.55, cache=None, **KW))
    assert n_off == n_off2 and "cache" not in ref.info
    runs = [warp_launches(lambda: rw.psf(lens, 0.3, 0.55, **KW)) for _ in range(3)]
    assert [p.info["cache"] for _, p in runs] == ["miss", "hit", "hit"]
    for _, p in runs:
        assert np.array_equal(p.data, ref.data) and p.center_mm == ref.center_mm
        assert p.plan == ref.plan
    assert runs[0][0] == n_off
    assert runs[1][0] == runs[2][0] <= 6 < n_off, (runs[1][0], n_off)


def change_in_place(lens, change):
    """Apply ``change`` in place to the thin-lens + DOE system of ``test_map.doe_lens`` (None: nothing):
    "focal_length" (x 1.02), "doe_coefficient" (+4 rad), "sensor_pitch" (x 1.1), "thickness" (0.05 mm moved from
    the DOE's gap to the lens's)."""
    if change == "focal_length":
        lens.surfaces[1].focal_length *= 1.02
    elif change == "doe_coefficient":
        lens.surfaces[2].profile["coefficients"][0] += 4.0
    elif change == "sensor_pitch":
        lens.sensor.pixel_pitch *= 1.1
    elif change == "thickness":
        lens.surfaces[1].thickness += 0.05
        lens.surfaces[2].thickness -= 0.05
    elif change is not None:
        raise ValueError(f"unknown change {change!r}")
    return lens


def _changed(change):
    """A new thin-lens + DOE system with ``change`` applied (None: as built)."""
    return change_in_place(doe_lens(), change)


@pytest.mark.parametrize("change", ["focal_length", "doe_coefficient", "sensor_pitch", "thickness"])
def test_default_cache_follows_an_in_place_change_of_the_lens(change):
    """The lens changed in place after a cached call: the next plain call is a miss and gives what an uncached call of
    a new lens object built with the change gives (bit for bit), not the earlier PSF."""
    lens = _changed(None)
    first = rw.psf(lens, 0.0, 0.55, **KW)
    assert rw.psf(lens, 0.0, 0.55, **KW).info["cache"] == "hit"
    change_in_place(lens, change)   # the same change made in place on the cached lens object
    again = rw.psf(lens, 0.0, 0.55, **KW)
    fresh = rw.psf(_changed(change), 0.0, 0.55, cache=None, **KW)
    assert again.info["cache"] == "miss"
    assert np.array_equal(again.data, fresh.data) and again.center_mm == fresh.center_mm
    assert not np.array_equal(again.data, first.data)   # the change moves the PSF: the check can fail


@pytest.mark.parametrize("kw", [{"field_deg": 0.2}, {"wavelength_um": 0.5}, {"size": 12}, {"dtype": "float32"},
                                {"pixel_values": "intensity"}, {"method": "focal"}, {"rays_per_sample": 1.5}])
def test_default_cache_other_arguments_are_misses(kw):
    """Another field, wavelength, size or option after a cached call: a miss that gives the uncached call of a new
    lens object, not the earlier entry."""
    lens = doe_lens()
    rw.psf(lens, 0.0, 0.55, **KW)
    args = dict(KW, **kw)
    fd, wl = args.pop("field_deg", 0.0), args.pop("wavelength_um", 0.55)
    p = rw.psf(lens, fd, wl, **args)
    fresh = rw.psf(doe_lens(), fd, wl, cache=None, **args)
    assert p.info["cache"] == "miss"
    assert np.array_equal(p.data, fresh.data)


def test_default_cache_can_be_turned_off(monkeypatch):
    """cache=None / False on the call, set_default_cache(None) and RWWARP_PLAN_CACHE=0: nothing kept, no
    ``info["cache"]``, the same bits."""
    from rwwarp.wave import plan_cache as pc
    lens = doe_lens()
    ref = rw.psf(lens, 0.0, 0.55, cache=None, **KW)
    p = rw.psf(lens, 0.0, 0.55, cache=False, **KW)
    assert "cache" not in p.info and np.array_equal(p.data, ref.data)
    monkeypatch.setenv("RWWARP_PLAN_CACHE", "0")
    assert pc.default_cache() is None
    for _ in range(2):
        p = rw.psf(lens, 0.0, 0.55, **KW)
        assert "cache" not in p.info and np.array_equal(p.data, ref.data)
    monkeypatch.delenv("RWWARP_PLAN_CACHE")
    assert pc.default_cache() is not None and len(pc.default_cache()) == 0
    built_in = pc.default_cache()
    assert pc.set_default_cache(None) is built_in
    assert pc.default_cache() is None
    p = rw.psf(lens, 0.0, 0.55, **KW)
    assert "cache" not in p.info and np.array_equal(p.data, ref.data)
    with pytest.raises(TypeError, match="cache"):
        rw.psf(lens, 0.0, 0.55, cache="yes", **KW)


def test_default_cache_bounds():
    """The default cache keeps at most 8 entries and 512 MiB (PlanCache.nbytes: focal operators, DOE factors, tracer
    tables and work arrays, the private lens copy's arrays); ten distinct calls leave the eight latest, the oldest
    evicted first."""
    from rwwarp.wave import plan_cache as pc
    cache = pc.default_cache()
    assert (cache.max_entries, cache.max_bytes, cache.shared) == (8, 512 * 2 ** 20, True)
    lens = doe_lens()
    wls = [0.45, 0.47, 0.5, 0.52, 0.55, 0.57, 0.6, 0.62, 0.65, 0.7]
    for w in wls:
        rw.psf(lens, 0.0, w, **KW)
        assert 0 < cache.nbytes() <= cache.max_bytes
    assert len(cache) == 8 and cache.evictions == 2
    assert rw.psf(lens, 0.0, 0.7, **KW).info["cache"] == "hit"
    assert rw.psf(lens, 0.0, 0.5, **KW).info["cache"] == "hit"
    assert rw.psf(lens, 0.0, 0.45, **KW).info["cache"] == "miss"   # evicted first


def test_busy_default_cache_runs_uncached():
    """Another thread running through the default cache (its lock held): a call does not wait, it runs uncached
    (``info["cache"] == "busy"``) and gives the same bits."""
    import threading
    from rwwarp.wave import plan_cache as pc
    lens = doe_lens()
    ref = rw.psf(lens, 0.0, 0.55, cache=None, **KW)
    cache = pc.default_cache()
    held, done = threading.Event(), threading.Event()

    def hold():
        with cache.lock:
            held.set()
            done.wait(60)
    t = threading.Thread(target=hold)
    t.start()
    try:
        held.wait(60)
        p = rw.psf(lens, 0.0, 0.55, **KW)
    finally:
        done.set()
        t.join()
    assert p.info["cache"] == "busy" and np.array_equal(p.data, ref.data)
    assert len(cache) == 0
    assert rw.psf(lens, 0.0, 0.55, **KW).info["cache"] == "miss"


def test_multi_order_lens_runs_uncached_by_default():
    """A lens with multi-order phase surfaces (not cacheable: rwwarp.phase_orders) runs through a plain call as with
    cache=None (``info["cache"] == "off"``), the same bits; an explicit cache is still refused."""
    from test_phase_orders import make
    lens = make(orders=(0, 1))
    kw = dict(size=16)
    ref = rw.psf(lens, 0.0, 0.55, cache=None, **kw)
    p = rw.psf(lens, 0.0, 0.55, **kw)
    assert p.info["cache"] == "off" and np.array_equal(p.data, ref.data)
    with pytest.raises(ValueError, match="cache"):
        rw.psf(lens, 0.0, 0.55, cache=rw.PlanCache(), **kw)


def test_kept_lens_arrays_are_counted():
    """An entry holds a private copy of the lens: its arrays (here a 400 x 400 pixel-map DOE, 1.28 MB) are in the
    entry's bytes (PlanCache.nbytes, what max_bytes bounds), counted once; lens_bytes sums the lens's arrays."""
    from rwwarp.wave import plan_cache as pc
    lens = doe_lens()
    data = np.random.default_rng(2).uniform(0.0, 0.5, (400, 400))
    lens.surfaces[2].profile = {"kind": "pixel_map", "pitch": 0.0025, "data": data}
    assert pc.lens_bytes(lens) == data.nbytes
    assert pc.lens_bytes(doe_lens()) == 0
    cache = rw.PlanCache()
    rw.psf(lens, 0.0, 0.55, cache=cache, **KW)
    (batches, held, _), = cache._entries.values()
    assert held == pc.held_bytes(batches) == cache.nbytes()
    kept_lens = batches[0][1].members[0].lens
    assert kept_lens is not lens and pc.lens_bytes(kept_lens) == data.nbytes   # the private copy
    without = held - data.nbytes
    assert without > 0   # the operators and tracer tables besides
    small = rw.PlanCache(max_bytes=held - 1)   # the lens's bytes make the entry too large for this bound
    p = rw.psf(lens, 0.0, 0.55, cache=small, **KW)
    assert p.info["cache"] == "miss" and len(small) == 0
