"""Many sources planned at once (issue 25, :func:`rwwarp.wave.plan_sources.plan_sources`): every plan is the one the
independent per-source planner (:func:`rwwarp.wave.batch_plan.plan_batch`, one source at a time from its own rows
of the same pilot) gives that source alone -- every :class:`BatchPlan` field equal, arrays bit for bit, the same
reasons, method choice and model-error estimate -- and the PSFs of :func:`rwwarp.psf_map` are the same bits as
those of the per-source plans. The model-error memo is emptied before each planner runs, so each computes its own
estimates (neither reads the other's)."""
import dataclasses
import math
import warnings

import numpy as np
import pytest

import rwwarp as rw
from rwwarp.lens import Surface
from rwwarp.wave import model_error
from rwwarp.wave.batch_plan import plan_batch
from rwwarp.wave.pilot import trace_pilot
from rwwarp.wave.plan_sources import plan_sources

from test_map import doe_lens


def _diff(a, b, path="plan"):
    """The differences between ``a`` and ``b``, exactly: arrays of the same dtype, shape and bits (NaN equal
    to NaN), floats equal, dataclasses / dicts / sequences member by member (dict keys in order), other objects
    by their attributes; the lens must be the same object."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        a2, b2 = np.asarray(a), np.asarray(b)
        if a2.dtype != b2.dtype or a2.shape != b2.shape:
            return [f"{path}: {a2.dtype}{a2.shape} vs {b2.dtype}{b2.shape}"]
        same = np.array_equal(a2, b2, equal_nan=a2.dtype.kind in "fc")
        return [] if same else [f"{path}: values differ"]
    if type(a) is not type(b):
        return [f"{path}: type {type(a).__name__} vs {type(b).__name__}"]
    if dataclasses.is_dataclass(a):
        out = []
        for f in dataclasses.fields(a):
            if f.name == "lens":
                out += [] if a.lens is b.lens else [f"{path}.lens: another object"]
            else:
                out += _diff(getattr(a, f.name), getattr(b, f.name), f"{path}.{f.name}")
        return out
    if isinstance(a, dict):
        if list(a) != list(b):
            return [f"{path}: keys {list(a)} vs {list(b)}"]
        return [d for k in a for d in _diff(a[k], b[k], f"{path}[{k!r}]")]
    if isinstance(a, (list, tuple)):
        if len(a) != len(b):
            return [f"{path}: length {len(a)} vs {len(b)}"]
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in _diff(x, y, f"{path}[{i}]")]
    if isinstance(a, float):
        return [] if (a == b or (math.isnan(a) and math.isnan(b))) else [f"{path}: {a!r} vs {b!r}"]
    if isinstance(a, (int, str, bool, complex, type(None), np.generic)):
        return [] if a == b else [f"{path}: {a!r} vs {b!r}"]
    if hasattr(a, "__dict__"):
        return _diff(vars(a), vars(b), f"{path}<{type(a).__name__}>")
    return [] if a == b else [f"{path}: {a!r} vs {b!r}"]


def _alone(lens, fields, wls, size, pixel, centers=None, **kw):
    """The reference: each source planned alone by plan_batch from its own rows of one pilot trace (pupils at
    their own wavelengths), the memo emptied first."""
    model_error._MEMO.clear()
    pilot = trace_pilot(lens, fields, wls, kw.get("device", "cpu"), kw.get("dtype", "float64"), None,
                        own_pupils=True, use_reference=kw.get("use_reference", True))
    out = []
    for k in range(len(fields)):
        kk = dict(kw) if centers is None else dict(kw, center_mm=centers[k:k + 1])
        out.append(plan_batch(lens, [fields[k]], [wls[k]], size, pixel, own_pupils=True, pilot=pilot.subset([k]),
                              **kk))
    return out


def _check(lens, fields, wls, size, pixel, centers=None, **kw):
    """plan_sources against the per-source reference, field by field; returns the plans."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")     # a two-step plan's WaveStepWarning, alike in both
        ref = _alone(lens, fields, wls, size, pixel, centers, **kw)
        model_error._MEMO.clear()
        if centers is None:
            got = plan_sources(lens, fields, wls, size, pixel, **kw)
        else:
            got = plan_sources(lens, fields, wls, size, pixel, center_mm=centers, per_source_centers=True, **kw)
    assert len(got) == len(ref)
    for k, (a, b) in enumerate(zip(ref, got)):
        d = _diff(a, b)
        assert not d, f"source {k} ({fields[k]} deg, {wls[k]} um): {d[:4]}"
    return got


def _grid(fields, wls):
    return [f for f in fields for _ in wls], [w for _ in fields for w in wls]


def _cooke_with_doe(a1, levels=None):
    """The Cooke triplet with an even-polynomial DOE (``a1 rho^2`` rad, rho = r / 15 mm, design 0.55 um) 5 mm
    before the sensor: a1 = -30000 wraps several zones inside the beam (test_focal)."""
    lens = rw.load_lens("cooke_triplet")
    surfs = [Surface(**{k: getattr(s, k) for k in s.__dataclass_fields__}) for s in lens.surfaces]
    surfs[-1].thickness = lens.surfaces[-1].thickness - 5.0
    surfs.append(Surface(type="doe", semi_diameter=15.0, shape="circle", thickness=5.0, design_wavelength_um=0.55,
                         material="fused_silica", levels=levels,
                         profile={"kind": "even_poly", "norm_radius": 15.0, "coefficients": [float(a1), 0.0]}))
    return lens.replace(surfaces=surfs)


def test_a489_map_plans_are_the_per_source_plans():
    """The A489+DOE map's options (method auto, pixel allowed, the CPU's memory budget), 0..10 deg x 3
    wavelengths, 64 px of 2 um."""
    from rwwarp.map_run import map_args
    lens = rw.load_lens("a489_doe")
    fields, wls = _grid([float(f) for f in np.linspace(0.0, 10.0, 6)], [0.45, 0.55, 0.65])
    opts = map_args(lens, fields, [0.55], size=64, pixel_mm=0.002).opts
    got = _check(lens, fields, wls, 64, 0.002, **opts)
    assert {p.method for p in got} == {"focal"}
    # each source's estimate is its own (a batch's notes once ran on into the next sources')
    assert len({p.model_errors[0].estimate for p in got}) == len(got)


@pytest.mark.parametrize("method,tol", [("focal", None), ("focal", 1e-4), ("auto", 1e-5), ("two-step", None),
                                        ("asm", None)])
def test_a489_methods_and_tolerances(method, tol):
    """method focal / auto / two-step / asm, with and without a model tolerance (the wave step planned where the
    estimate exceeds it), 32 px."""
    lens = rw.load_lens("a489_doe")
    fields, wls = _grid([0.0, 4.0, 10.0], [0.45, 0.65])
    got = _check(lens, fields, wls, 32, 0.002, method=method, model_tolerance=tol, allow_pixel=method == "auto")
    if method == "two-step":
        assert all(np.any(p.wave_step) for p in got)     # the step is planned: its branch is compared too
    if method == "auto":   # the estimate is over the tolerance: the step is planned or refused, with a reason
        assert all(np.any(p.wave_step) or any("wave step" in r for r in p.plan.reasons) for p in got)


def test_cooke_off_axis_per_source_centres():
    """The Cooke triplet off axis (x and y fields), method auto and focal, each source's patch centre given."""
    lens = rw.load_lens("cooke_triplet")
    fields = [0.0, 14.0, (3.0, 12.0), 10.0]
    wls = [0.55, 0.45, 0.65, 0.55]
    centers = np.array([[0.0, 0.0], [0.0, 4.1], [1.0, 3.4], [0.01, 2.9]])
    _check(lens, fields, wls, 32, lens.sensor.pixel_pitch, centers=centers, method="focal", model_tolerance=1e-3)
    _check(lens, fields, wls, 32, lens.sensor.pixel_pitch, method="auto", allow_pixel=True)


@pytest.mark.parametrize("levels", [None, 8])
def test_wrapped_and_quantised_doe(levels):
    """A DOE whose relief wraps inside the beam (several diffraction orders, the chief ray's zone), smooth and
    with 8 levels (the quantised orders), off its design wavelength."""
    lens = _cooke_with_doe(-30000.0, levels)
    got = _check(lens, [0.0, 3.0], [0.5876, 0.55], 32, lens.sensor.pixel_pitch, method="auto", allow_pixel=True,
                 model_tolerance=1e-3)
    # off the design wavelength (0.5876 um) the beam carries several orders: the multi-order branch is compared
    assert got[0].method == "focal" and len(got[0].focal["orders"][0]) > 1


def test_square_pupil_thin_lens_doe():
    """A square DOE aperture behind an ideal thin lens (test_map's): straight pupil edges, method auto and focal."""
    lens = doe_lens()
    fields, wls = [0.0, 0.3, 0.6], [0.45, 0.55, 0.65]
    _check(lens, fields, wls, 16, lens.sensor.pixel_pitch, method="auto")
    _check(lens, fields, wls, 16, lens.sensor.pixel_pitch, method="focal", model_tolerance=1e-4)


def test_pixel_method_chosen_alike():
    """A doublet with 50 um pixels (many Airy radii): method auto chooses the pixel method, for every source alike;
    with a tolerance the wave step is weighed against it too."""
    lens = rw.load_lens("ac254_100_a")
    fields, wls = [0.0, 1.0, 2.0], [0.55, 0.45, 0.65]
    got = _check(lens, fields, wls, 16, 0.05, method="auto", allow_pixel=True)
    assert {p.method for p in got} == {"pixel"}
    _check(lens, fields, wls, 16, 0.05, method="auto", allow_pixel=True, model_tolerance=1e-2)


def test_estimates_go_through_the_shared_memo():
    """plan_sources keeps each source's estimate under the key the per-source planner reads (and reads it): a
    plan_batch after it finds every estimate in the memo."""
    lens = rw.load_lens("a489_doe")
    fields, wls = [0.0, 5.0], [0.55, 0.65]
    model_error._MEMO.clear()
    plan_sources(lens, fields, wls, 32, 0.002, method="focal")
    n = len(model_error._MEMO)
    assert n == 2
    _alone_keep = trace_pilot(lens, fields, wls, own_pupils=True)
    for k in range(2):
        plan_batch(lens, [fields[k]], [wls[k]], 32, 0.002, method="focal", own_pupils=True,
                   pilot=_alone_keep.subset([k]))
    assert len(model_error._MEMO) == n      # hits: no new entry


def test_bad_input():
    lens = rw.load_lens("a489_doe")
    with pytest.raises(ValueError, match="one wavelength per field"):
        plan_sources(lens, [0.0, 1.0], [0.55], 16, 0.002)
    with pytest.raises(ValueError):
        plan_sources(lens, [0.0, 1.0], [0.55, 0.55], 16, 0.002, center_mm=[[0.0, 0.0]], per_source_centers=True)
    with pytest.raises(TypeError, match="pilot"):
        plan_sources(lens, [0.0], [0.55], 16, 0.002, pilot="not a pilot")
    pilot = trace_pilot(lens, [0.0], [0.55], own_pupils=True)
    with pytest.raises(ValueError, match="wavelengths"):
        plan_sources(lens, [0.0], [0.65], 16, 0.002, pilot=pilot)


def test_psf_map_bits_as_the_per_source_plans(monkeypatch):
    """rw.psf_map's PSFs with the plans of plan_sources are the same bits as with each source planned alone by
    plan_batch (the map's planning before issue 25, patched in), A489+DOE, 2 fields x 2 wavelengths, 16 px.
    Each run plans afresh (the memo emptied): the estimates, reasons and method choices come from each planner."""
    import rwwarp.map_run as mr
    from rwwarp.wave.raywave import RayWave
    lens = rw.load_lens("a489_doe")
    fields, wls = [0.0, 2.0], [0.45, 0.65]
    model_error._MEMO.clear()
    new = rw.psf_map(lens, fields, wls, size=16, pixel_mm=0.002)
    calls = []

    def alone(lens, fields, wls, size, pixel, center_mm=None, **kw):
        calls.append(len(fields))
        ref = _alone(lens, fields, wls, size, pixel, None, **dict(kw, center_mm=center_mm))
        return [RayWave.from_plan(bp) for bp in ref]
    monkeypatch.setattr(mr, "source_plans", alone)
    old = rw.psf_map(lens, fields, wls, size=16, pixel_mm=0.002)
    assert calls == [4]         # the map planned through the per-source reference
    assert new.data.shape == old.data.shape == (2, 2, 16, 16)
    assert np.array_equal(new.data, old.data)
    assert not _diff([b["plans"] for b in new.info["batches"]], [b["plans"] for b in old.info["batches"]])


def test_a_batch_estimates_each_source_on_its_own(monkeypatch):
    """A batch's model-error estimates are each source's own (its notes did run on into the next sources'): a plan
    of two sources (pupils at their own wavelengths) has the estimate each has alone, notes included; the first
    source (10 deg, 0.45 um, rim slope 62 rad) has a note, the second (on axis) none. The checked slope range is
    set to 35 rad here (its value before the steep-rim truths) so that the first source carries a note."""
    monkeypatch.setattr(model_error, "CHECKED_SLOPE_RAD", 35.0)
    monkeypatch.setattr(model_error, "CHECKED_OFF_AXIS_SLOPE_RAD", 35.0)
    lens = rw.load_lens("a489_doe")
    model_error._MEMO.clear()
    both = plan_batch(lens, [10.0, 0.0], [0.45, 0.55], 32, 0.002, method="focal", own_pupils=True)
    alone = _alone(lens, [10.0, 0.0], [0.45, 0.55], 32, 0.002, method="focal")
    assert both.model_errors[0].note and not both.model_errors[1].note
    for k in range(2):
        assert not _diff(both.model_errors[k], alone[k].model_errors[0]), k


def test_orders_partly_evanescent():
    """A strong DOE (-8e4 rad at the 15 mm norm radius) at 0.45 um, 5 deg: two of its kept orders land only in
    part (the rest evanescent), the focal plan's branch for them compared too."""
    lens = _cooke_with_doe(-8e4)
    got = _check(lens, [0.0, 5.0], [0.5876, 0.45], 32, lens.sensor.pixel_pitch, method="focal", focal_patch_tol=1e-9)
    assert len(got[1].focal["orders"][0]) == 1 and got[1].focal["lost_power"][0] > 0.1


def test_focal_plans_without_doe_at_once_and_alone(monkeypatch):
    """Without a DOE on the wave plane the focal plans of all sources are made at once
    (rwwarp.wave.focal_sources); a source whose beam misses its given patch (its main order's landing box far from
    it) is left to the per-source planner (which keeps its main order: a dark patch). Both kinds in one call,
    compared with the per-source reference field by field; the spy checks which sources went which way (3 at once,
    1 alone)."""
    from rwwarp.wave import focal_sources
    taken = []
    orig = focal_sources.focal_plans_one_order

    def spy(*a, **kw):
        out = orig(*a, **kw)
        taken.append(sorted(out))
        return out
    monkeypatch.setattr(focal_sources, "focal_plans_one_order", spy)
    lens = rw.load_lens("cooke_triplet")
    fields, wls = [0.0, 14.0, (3.0, 12.0), 10.0], [0.55, 0.45, 0.65, 0.55]
    # the chief rays land at (0, 0), (0, 12.42), (2.61, 10.59), (0, 8.78) mm: patches there, but source 3's 3 mm
    # beside its beam, which misses it
    centers = np.array([[0.0, 0.0], [0.0, 12.4], [2.6, 10.6], [3.0, 8.78]])
    got = _check(lens, fields, wls, 32, lens.sensor.pixel_pitch, centers=centers, method="focal")
    assert taken == [[0, 1, 2]]
    assert got[3].focal["lost_power"][0] == 0.0 and got[3].method == "focal"
    taken.clear()
    _check(lens, fields, wls, 32, lens.sensor.pixel_pitch, method="auto", allow_pixel=True)
    assert taken == [[0, 1, 2, 3]]


@pytest.mark.parametrize("method", ["focal", "auto", "two-step"])
def test_skipping_the_model_error_estimate_changes_nothing_else(method):
    """``estimate_model_error=False`` (the design loop's default): the plans are those with the estimate except the
    estimate itself and its reason (compared bit for bit with those two fields put back), in plan_sources and
    plan_batch alike; where a decision reads it ("two-step"; "auto" with a tolerance) it is made anyway."""
    lens = _cooke_with_doe(-30000.0)
    fields, wls = _grid([0.0, 10.0], [0.5, 0.6])
    for tol in ((None, 1e-2) if method == "auto" else (None,)):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model_error._MEMO.clear()
            full = plan_sources(lens, fields, wls, 24, 0.004, method=method, model_tolerance=tol)
            model_error._MEMO.clear()
            lean = plan_sources(lens, fields, wls, 24, 0.004, method=method, model_tolerance=tol,
                                estimate_model_error=False)
            one = plan_batch(lens, [fields[1]], [wls[1]], 24, 0.004, method=method, model_tolerance=tol,
                             own_pupils=True, estimate_model_error=False)
        needed = method == "two-step" or tol is not None
        for k, (a, b) in enumerate(zip(full, lean)):
            assert a.model_errors and a.plan.model_error is not None
            if needed:
                assert not _diff(a, b), (method, tol, k)
                continue
            assert b.model_errors == () and b.plan.model_error is None
            put_back = b.evolved(model_errors=a.model_errors, plan=b.plan.evolved(model_error=a.plan.model_error,
                                                                                 reasons=a.plan.reasons))
            assert not _diff(a, put_back), (method, tol, k, _diff(a, put_back)[:3])
            assert len(a.plan.reasons) == len(b.plan.reasons) + 1
        assert (one.model_errors == ()) is not needed


# ------------------------------------------------------- the focal plans of a DOE's orders, many sources at once
def _a489_with_doe(a1, levels=None):
    """The A489+DOE lens with its (blank) DOE given the relief ``a1 rho^2`` rad (rho = r / 1.5 mm, design 0.55 um):
    a1 = -100 wraps ~16 zones inside the aperture, so off the design wavelength a beam carries several orders
    (and where it crosses no wrap, one exact term of non-integer index)."""
    lens = rw.load_lens("a489_doe")
    p = lens.wave_plane_index()
    surfs = [Surface(**{k: getattr(s, k) for k in s.__dataclass_fields__}) for s in lens.surfaces]
    surfs[p].profile = {"kind": "even_poly", "norm_radius": 1.5, "coefficients": [float(a1), 0.0, 0.0, 0.0]}
    surfs[p].levels = levels
    return lens.replace(surfaces=surfs)


def _focal_paths(monkeypatch):
    """Spies: the sources each rwwarp.wave.focal_sources.focal_plans_orders call planned at once (a list a call),
    and the sources the per-source planner (rwwarp.wave.plan.plan_focal, one call a source) planned."""
    import rwwarp.wave.plan as plan_mod
    from rwwarp.wave import focal_sources
    at_once, alone = [], []
    orig, orig_pf = focal_sources.focal_plans_orders, plan_mod.plan_focal

    def spy(*a, **kw):
        out = orig(*a, **kw)
        at_once.append(sorted(out))
        return out

    def spy_pf(*a, **kw):
        alone.append(len(a[0]))
        return orig_pf(*a, **kw)
    monkeypatch.setattr(focal_sources, "focal_plans_orders", spy)
    monkeypatch.setattr(plan_mod, "plan_focal", spy_pf)
    return at_once, alone


@pytest.mark.parametrize("levels", [None, 8])
def test_a489_doe_orders_planned_at_once(monkeypatch, levels):
    """The A489 map's options with a DOE that wraps inside the beam (smooth and 8 levels), 0..10 deg x 0.45 / 0.55
    / 0.65 um, 32 px of 2 um: every source's focal plan is made at once (rwwarp.wave.focal_sources) and is the
    per-source planner's, bit for bit; plan_sources calls the per-source planner for none of them (it runs once a
    source, for the reference alone). The sources carry different numbers of orders (one exact term on axis, up
    to 18 off the design wavelength), several of them kept."""
    from rwwarp.map_run import map_args
    lens = _a489_with_doe(-100.0, levels)
    fields, wls = _grid([0.0, 2.0, 5.0, 10.0], [0.45, 0.55, 0.65])
    opts = map_args(lens, fields, [0.55], size=32, pixel_mm=0.002).opts
    at_once, alone = _focal_paths(monkeypatch)
    got = _check(lens, fields, wls, 32, 0.002, **opts)
    assert at_once == [list(range(len(fields)))]
    assert len(alone) == len(fields)        # the reference's calls (one a source, each of one source) alone
    kept = [len(p.focal["orders"][0]) for p in got]
    assert min(kept) == 1 and max(kept) > 2, kept


def test_doe_orders_partly_evanescent_at_once_and_a_missed_patch_alone(monkeypatch):
    """A strong DOE (-8e4 rad at the 15 mm norm radius, test_orders_partly_evanescent): the sources at 5 deg, 0.45
    and 0.65 um have orders that land only in part (the rest evanescent: their landing rays' boxes, bands and fit
    taken), planned at once with the others (17 kept orders on axis at 0.5876 / 0.45 um, one at the design
    wavelength); then the same sources with each patch where the first call centred it but the design-wavelength
    source's 3 mm beside it, which its one order misses: that source is left to the per-source planner (which keeps
    its main order: a dark patch). Every plan the per-source planner's, bit for bit."""
    lens = _cooke_with_doe(-8e4)
    fields, wls = [0.0, 5.0, 2.0, 5.0, 0.0], [0.5876, 0.45, 0.55, 0.65, 0.45]
    at_once, alone = _focal_paths(monkeypatch)
    got = _check(lens, fields, wls, 32, lens.sensor.pixel_pitch, method="focal", focal_patch_tol=1e-9)
    assert at_once == [[0, 1, 2, 3, 4]] and len(alone) == len(fields)
    assert [len(p.focal["orders"][0]) for p in got] == [17, 1, 1, 1, 17]
    assert got[1].focal["lost_power"][0] > 0.1 and got[3].focal["lost_power"][0] > 0.05
    centers = np.concatenate([p.centers for p in got])
    centers[2, 0] += 3.0
    at_once.clear()
    alone.clear()
    got = _check(lens, fields, wls, 32, lens.sensor.pixel_pitch, centers=centers, method="focal",
                 focal_patch_tol=1e-9)
    assert at_once == [[0, 1, 3, 4]] and len(alone) == len(fields) + 1
    assert got[2].focal["lost_power"][0] == 0.0 and got[2].focal["orders"][0] == [(1, 1 + 0j)]


def test_doe_orders_landing_in_part_kept_at_once(monkeypatch):
    """The strong DOE at 5 deg, 0.45 um, its patch given 8 mm below the axis, where orders 5 and 6 land with the
    rays of theirs that are not evanescent (their main order misses it): the orders kept land only in part, and
    the fit, the landings under the quadratic transfer, the displacement and the box are taken over their landing
    rays, at once with a source on axis (17 orders); bit for bit the per-source planner's."""
    lens = _cooke_with_doe(-8e4)
    at_once, alone = _focal_paths(monkeypatch)
    got = _check(lens, [5.0, 0.0], [0.45, 0.5876], 32, lens.sensor.pixel_pitch, centers=np.array([[0.0, -8.0],
                 [0.0, 0.0]]), method="focal", focal_patch_tol=1e-9)
    assert at_once == [[0, 1]] and len(alone) == 2
    assert [m for m, _ in got[0].focal["orders"][0]] == [5, 6] and len(got[1].focal["orders"][0]) == 17


@pytest.mark.parametrize("pad_ratio,chunk", [(math.inf, 1 << 30), (2.0, 1)])
def test_doe_orders_padded_and_chunked(monkeypatch, pad_ratio, chunk):
    """Sources with different numbers of live orders (17 off the design wavelength, 1 at it: the Cooke triplet's
    wrapping DOE) planned in one chunk, the fewer orders padded (``ORDERS_PAD_RATIO`` unbounded), or one source a
    chunk (``ORDERS_CHUNK_ELEMENTS`` = 1): the plans are the per-source planner's either way, bit for bit."""
    from rwwarp.wave import focal_sources
    monkeypatch.setattr(focal_sources, "ORDERS_PAD_RATIO", pad_ratio)
    monkeypatch.setattr(focal_sources, "ORDERS_CHUNK_ELEMENTS", chunk)
    chunks = []
    orig = focal_sources._orders_chunk

    def spy(sel, infos, *a, **kw):
        chunks.append([len(infos[k].live_m) for k in sel])
        return orig(sel, infos, *a, **kw)
    monkeypatch.setattr(focal_sources, "_orders_chunk", spy)
    at_once, alone = _focal_paths(monkeypatch)
    lens = _cooke_with_doe(-30000.0)
    fields, wls = _grid([0.0, 2.0, 4.0], [0.55, 0.5876, 0.5])
    got = _check(lens, fields, wls, 32, lens.sensor.pixel_pitch, method="focal")
    assert at_once == [list(range(len(fields)))] and len(alone) == len(fields)
    if chunk == 1:
        assert len(chunks) == len(fields) and all(len(c) == 1 for c in chunks)
    else:
        assert len(chunks) == 1 and sorted(set(chunks[0])) == [1, 17]    # padded: 1 live order among 17
    kept = {len(p.focal["orders"][0]) for p in got}
    assert 1 in kept and len(kept) > 1


def test_doe_orders_vignetted_sources_at_once(monkeypatch):
    """Sources of different ray counts (the Cooke triplet at 18 deg vignettes 60 of its 750 pilot rays) with a
    DOE (-6000 rad at the 15 mm norm radius; on axis 17 orders kept at ``focal_patch_tol`` 1e-12), planned at once:
    each source's rays padded with copies of one of its own, the plans the per-source planner's, bit for bit."""
    lens = _cooke_with_doe(-6000.0)
    fields, wls = [0.0, 18.0, 17.0, 18.0], [0.5876, 0.5876, 0.55, 0.45]
    assert len(set(trace_pilot(lens, fields, wls, own_pupils=True).ok.sum(1).tolist())) > 1   # ragged
    at_once, alone = _focal_paths(monkeypatch)
    got = _check(lens, fields, wls, 32, lens.sensor.pixel_pitch, method="focal", focal_patch_tol=1e-12)
    assert at_once == [[0, 1, 2, 3]] and len(alone) == len(fields)
    assert len(got[0].focal["orders"][0]) == 17
