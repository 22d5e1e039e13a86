"""The plan of a batch (issue 25 item 1, :mod:`rwwarp.wave.batch_plan`): a :class:`BatchPlan` cannot be changed (a
frozen dataclass, read-only arrays and mappings), a RayWave built from another's plan (:meth:`RayWave.from_plan`)
gives its bits without planning again, running PSFs leaves the plan as it was, and a change (re-centring, a new
parameter table) is a new plan. The vectorised planning steps are checked against the per-source equations written
here. Small thin-lens + DOE system of test_map (16 px: a few ms a PSF)."""
import dataclasses

import numpy as np
import pytest

from rwwarp.wave.batch_plan import BatchPlan, FrozenDict, _chief_rays, _footprints, plan_batch
from rwwarp.wave.raywave import RayWave

from test_map import doe_lens, warp_launches

SIZE = 16


def _rw(method, **kw):
    lens = doe_lens()
    return RayWave(lens, [0.0, 0.3], [0.45, 0.65], SIZE, lens.sensor.pixel_pitch, method=method, **kw)


def _snapshot(bp):
    """Copies of every array of the plan (its own fields and its dicts' arrays) and its Plan."""
    out = {}
    for f in dataclasses.fields(bp):
        v = getattr(bp, f.name)
        if isinstance(v, np.ndarray):
            out[f.name] = v.copy()
        elif isinstance(v, dict):
            for k, a in v.items():
                if isinstance(a, np.ndarray):
                    out[f"{f.name}.{k}"] = a.copy()
    out["plan"] = bp.plan
    return out


def _unchanged(bp, snap):
    for key, a in snap.items():
        if key == "plan":
            assert bp.plan is a
            continue
        name, _, sub = key.partition(".")
        b = getattr(bp, name)[sub] if sub else getattr(bp, name)
        assert np.array_equal(a, b, equal_nan=True), key


@pytest.mark.parametrize("method", ["asm", "focal"])
def test_a_plan_refuses_changes(method):
    bp = _rw(method).batch_plan
    assert isinstance(bp, BatchPlan)
    with pytest.raises(dataclasses.FrozenInstanceError):
        bp.centers = np.zeros((2, 2))
    with pytest.raises(dataclasses.FrozenInstanceError):
        bp.plan = None
    arrays = [f.name for f in dataclasses.fields(bp) if isinstance(getattr(bp, f.name), np.ndarray)]
    assert {"origin", "centers", "carrier", "chief_plane", "target", "lo", "hi", "n_after"} <= set(arrays)
    for name in arrays:
        a = getattr(bp, name)
        assert not a.flags.writeable, name
        with pytest.raises(ValueError):
            a.reshape(-1)[0] = 1.0
    assert isinstance(bp.src, FrozenDict)
    with pytest.raises(TypeError):
        bp.src["shape"] = "square"
    with pytest.raises(ValueError):
        bp.src["pos"][0, 0] = 1.0
    if method == "focal":
        assert isinstance(bp.focal, FrozenDict)
        with pytest.raises(TypeError):
            bp.focal["sensor_origin"] = None
        with pytest.raises(ValueError):
            bp.focal["sensor_origin"][0, 0] = 1.0
        with pytest.raises(ValueError):
            bp.focal["transfer"][0][0, 0] = 1.0       # the fitted (g, q)
    with pytest.raises(ValueError):
        bp.pilot.pos_p[0, 0, 0] = 1.0
    # the RayWave reads the plan through and cannot write it
    r = _rw(method)
    with pytest.raises(AttributeError):
        r.origin = np.zeros((2, 2))
    assert r.origin is r.batch_plan.origin and r.plan is r.batch_plan.plan


@pytest.mark.parametrize("method", ["asm", "focal"])
def test_from_plan_gives_the_bits_without_planning(method):
    """RayWave.from_plan(rw.batch_plan) runs the same PSFs bit for bit as the RayWave planned at the same inputs, with
    fewer Warp launches (no pilot trace), and the plan is unchanged by the runs of both."""
    r = _rw(method)
    bp = r.batch_plan
    snap = _snapshot(bp)
    ref = r.run()
    n, again = warp_launches(lambda: RayWave.from_plan(bp).run())
    n_planned, planned = warp_launches(lambda: _rw(method).run())
    assert np.array_equal(again["data"], ref["data"]) and np.array_equal(planned["data"], ref["data"])
    assert np.array_equal(again["valid_fraction"], ref["valid_fraction"])
    assert again["plan"] == ref["plan"]
    assert n < n_planned   # the pilot trace's launches are not repeated
    _unchanged(bp, snap)
    assert r.batch_plan is bp


def test_plan_batch_alone_is_the_raywaves_plan():
    """plan_batch (its own tracer, no gradients) plans what RayWave plans at the same inputs."""
    lens = doe_lens()
    args = (lens, [0.0, 0.3], [0.45, 0.65], SIZE, lens.sensor.pixel_pitch)
    bp = plan_batch(*args, method="focal")
    r = RayWave(*args, method="focal", requires_grad=True)
    assert bp.plan == r.plan
    for name in ("origin", "centers", "carrier", "chief_plane", "target", "lo", "hi", "opl_chief", "wave_step"):
        assert np.array_equal(getattr(bp, name), getattr(r, name)), name
    assert np.array_equal(RayWave.from_plan(bp).run()["data"], r.run()["data"])


def test_a_change_is_a_new_plan():
    """recentre and load_params give the RayWave a new plan and leave the old one as it was; the re-centred
    patches move by whole pixels and a focal plan's sensor-side grid with them."""
    r = _rw("focal")
    bp = r.batch_plan
    snap = _snapshot(bp)
    px = r.pixel
    r.recentre(bp.centers + np.array([3 * px, -2 * px]))
    assert r.batch_plan is not bp
    _unchanged(bp, snap)
    assert np.allclose(r.centers - bp.centers, [3 * px, -2 * px], rtol=0, atol=1e-12)
    assert np.allclose(r.focal["sensor_origin"] - bp.focal["sensor_origin"], [3 * px, -2 * px], rtol=0, atol=1e-12)
    assert np.array_equal(r.origin, bp.origin)
    moved = r.batch_plan
    from rwwarp.kernels.trace import P_Z
    table = r.tracer.params_np.copy()
    table[r.plane, P_Z] += 0.01            # the wave plane 10 um further: its windows' reference point follows
    r.load_params(table)
    assert r.batch_plan is not moved
    assert np.array_equal(r.chief_plane[:, 2], np.full(2, table[r.plane, P_Z]))
    assert np.array_equal(r.chief_plane[:, :2], moved.chief_plane[:, :2])
    assert not np.array_equal(moved.chief_plane[:, 2], r.chief_plane[:, 2])
    _unchanged(bp, snap)


def test_vectorised_planning_steps_follow_the_equations():
    """The chief rays and footprints of the planning (all sources at once, with masks) against the per-source
    equations written out here: the pupil centre's ray where valid, else the valid rays' centroid (direction
    normalised); f = n d_xy / lambda - carrier, fmax = max |f|, lo / hi the valid points' min / max."""
    rng = np.random.default_rng(1)
    S, R = 4, 50
    pos_p = rng.normal(size=(S, R, 3))
    pos_s = rng.normal(size=(S, R, 3))
    d = rng.normal(size=(S, R, 3)) * [0.1, 0.1, 1.0] + [0, 0, 3.0]
    dir_s = d / np.linalg.norm(d, axis=2, keepdims=True)
    ok = rng.random((S, R)) > 0.3
    ok[1, 0] = False   # a vignetted chief ray
    ok[2, 0] = True
    n_after, lam_mm = np.array([1.0, 1.5, 1.0, 1.2]), np.array([0.45, 0.55, 0.65, 0.5]) * 1e-3
    cp, cs, cd = _chief_rays(pos_p, pos_s, dir_s, ok)
    carrier = n_after[:, None] * cd[:, :2] / lam_mm[:, None]
    fmax, lo, hi = _footprints(pos_p, dir_s, ok, n_after, lam_mm, carrier)
    for k in range(S):
        v = ok[k]
        if v[0]:
            want = pos_p[k, 0], pos_s[k, 0], dir_s[k, 0]
        else:
            m = dir_s[k, v].mean(0)
            want = pos_p[k, v].mean(0), pos_s[k, v].mean(0), m / np.linalg.norm(m)
        for got, w in zip((cp[k], cs[k], cd[k]), want):
            assert np.array_equal(got, w)
        f = n_after[k] * dir_s[k, v, :2] / lam_mm[k] - carrier[k]
        assert fmax[k] == np.max(np.abs(f))
        assert np.array_equal(lo[k], pos_p[k, v, :2].min(0)) and np.array_equal(hi[k], pos_p[k, v, :2].max(0))


def test_the_model_errors_orders_at_once_are_the_orders_one_by_one():
    """The model error's other orders (rwwarp.wave.model_error), all at once: whether each lights the patch and its
    rim slope are the values of the per-order functions bit for bit (an order with an evanescent ray included)."""
    from rwwarp.wave import model_error as me
    rng = np.random.default_rng(2)
    N, inv_lam, dist = 300, 2000.0, 20.0
    xy = rng.normal(size=(N, 2))
    f = rng.normal(size=(N, 2)) * 50.0
    grad = rng.normal(size=(N, 2)) * 30.0 + [400.0, 0.0]   # each order off by 4 mm a unit of m on the sensor
    xc = xy.mean(0)
    rr = np.linalg.norm(xy - xc, axis=1)
    rim = rr >= 0.9 * rr.max()
    dm = [-3.0, -0.01, 0.0, 1.0, 4.5]           # the last: |f| > n / lambda for some of its rays (evanescent)
    fm = me._order_frequencies(f, grad, dm)
    centre = np.array([0.3, -0.2])
    c2 = 1.0 - np.sum((fm / inv_lam) ** 2, axis=2)
    assert np.any(c2[-1] <= 0) and np.any(c2[-1] > 0) and np.all(c2[:-1] > 0)
    got = me._reaches_patch_orders(xy, fm, inv_lam, dist, centre, rr, rim)
    want = [me._reaches_patch(xy, f + d * grad, inv_lam, dist, centre, rr, rim) for d in dm]
    assert list(got) == want and any(want) and not all(want)
    f_sph = rng.normal(size=(N, 2))
    slopes = me._rim_slopes(xy, xc, rr, rim, 1.1, fm - f_sph)
    for s, d in zip(slopes, dm):
        assert s == me._rim_slope(xy, xc, rr, rim, 1.1, f + d * grad - f_sph)


def test_a_tracer_made_on_use_gives_the_same_bits(monkeypatch):
    """RayWave.from_plan(..., tracer_on_use=True) makes its Tracer only when it traces (counted by wrapping
    Tracer.__init__), one for it and its shallow copies, and gives the bits of the eager one."""
    import copy
    from rwwarp import trace
    r = _rw("focal")
    made = []
    init = trace.Tracer.__init__
    monkeypatch.setattr(trace.Tracer, "__init__", lambda self, *a, **k: (made.append(1), init(self, *a, **k))[1])
    lazy = RayWave.from_plan(r.batch_plan, tracer_on_use=True)
    twin = copy.copy(lazy)
    assert made == [] and lazy.centers is r.centers
    out = lazy.run()
    assert made == [1] and twin.tracer is lazy.tracer
    assert np.array_equal(out["data"], r.run()["data"])


def test_evolved_is_dataclasses_replace():
    """BatchPlan.evolved / Plan.evolved (one dict copy) give what dataclasses.replace gives: every field the same
    object or the same bits, a changed array copied read-only (the caller's stays writeable), dicts frozen; the old
    plan unchanged; an unknown field or an unregistered method refused by name."""
    bp = _rw("focal").batch_plan
    snap = _snapshot(bp)
    lo = np.asarray(bp.lo) - 0.25
    changes = dict(lo=lo, focal=dict(bp.focal), model_errors=[1, 2], method="asm")
    a, b = bp.evolved(**changes), dataclasses.replace(bp, **changes)
    for f in dataclasses.fields(BatchPlan):
        x, y = getattr(a, f.name), getattr(b, f.name)
        assert type(x) is type(y), f.name
        if isinstance(x, np.ndarray):
            assert np.array_equal(x, y) and not x.flags.writeable, f.name
        elif f.name != "focal":
            assert x is y or x == y, f.name
    assert isinstance(a.focal, FrozenDict) and list(a.focal) == list(b.focal)
    assert lo.flags.writeable and a.lo is not lo
    _unchanged(bp, snap)
    pl = bp.plan
    assert pl.evolved(reasons=["x"], n_grid=7) == dataclasses.replace(pl, reasons=["x"], n_grid=7)
    assert pl.with_reasons("y").reasons == pl.reasons + ("y",)
    with pytest.raises(TypeError, match="no_such"):
        bp.evolved(no_such=1)
    with pytest.raises(TypeError, match="no_such"):
        pl.evolved(no_such=1)
    with pytest.raises(ValueError, match="registered propagation method"):
        pl.evolved(method="nope")


def test_loading_parameters_leaves_other_tracers_of_the_lens_alone():
    """A tracer without gradients reads shared views of a cached upload; load_params writes the batch's own copy:
    a later tracer (and plan) of the same lens sees the lens's values, not the moved wave plane (a map planned after
    such a change had its pitches moved by 7e-5 relative: test_map's plans against own_plans)."""
    from rwwarp.kernels.trace import P_Z
    from rwwarp.trace import Tracer
    lens = doe_lens()
    before = Tracer(lens, [0.45, 0.65]).params_np.copy()   # the wavelengths of _rw: the same cached upload
    r = _rw("focal")
    table = r.tracer.params_np.copy()
    table[r.plane, P_Z] += 0.01
    r.load_params(table)
    assert np.array_equal(np.stack([a.numpy() for a in r.tracer.params]), table)
    fresh = Tracer(lens, [0.45, 0.65])
    assert np.array_equal(np.stack([a.numpy() for a in fresh.params]), before)
