"""The pilot trace as an object (rwwarp.wave.pilot): one trace of a batch gives every source the rays a trace of
it alone gives (rays are independent), the object is read-only, a RayWave planned from a source's subset is the
RayWave of that source alone, and rwwarp.psf_map traces one pilot per system."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import rwwarp as rw
from rwwarp.trace import Tracer
from rwwarp.wave import pilot as pilot_mod
from rwwarp.wave.pilot import PILOT_GRID, Pilot, trace_pilot
from rwwarp.wave.raywave import RayWave

ARRAYS = ("pos_p", "pos_s", "dir_s", "opl_p", "ok", "valid_plane")
FIELDS = [0.0, 3.0, (2.0, 5.0), 3.0]
WLS = [0.5, 0.6, 0.55, 0.45]


@pytest.fixture(scope="module")
def lens():
    return rw.load_lens("a489_doe")


def _same(a: Pilot, b: Pilot):
    for name in ARRAYS:
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape, name
        assert np.array_equal(x, y), name   # bit for bit: the same independent rays


@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_batch_pilot_is_each_source_traced_alone(lens, dtype):
    """A batch of four sources at four wavelengths (own pupils) traced once equals, bit for bit, each source
    traced alone; the subset keeps what the pilot was traced for."""
    batch = trace_pilot(lens, FIELDS, WLS, dtype=dtype, own_pupils=True)
    assert len(batch) == 4 and batch.dtype == dtype
    assert batch.pos_p.shape[1] == batch.opl_p.shape[1] > PILOT_GRID ** 2 // 2   # chief + the grid in the disc
    for k in range(4):
        alone = trace_pilot(lens, [FIELDS[k]], [WLS[k]], dtype=dtype, own_pupils=True)
        sub = batch.subset([k])
        _same(sub, alone)
        assert (sub.fields, sub.wls, sub.pupil_wls) == (alone.fields, alone.wls, alone.pupil_wls)
    # a reordered subset is the same rows reordered
    _same(batch.subset([2, 0]), trace_pilot(lens, [FIELDS[2], FIELDS[0]], [WLS[2], WLS[0]], dtype=dtype,
                                            own_pupils=True))


def test_pilot_comparison_sees_the_pupil_wavelength():
    """The comparison above can fail: without own pupils every pupil is laid at the batch's shortest wavelength,
    so off axis the 0.6 um source's rays differ from its trace alone (the Cooke triplet's paraxial entrance
    pupil moves 0.033 mm between 0.45 and 0.6 um: a beam from 10 deg shifts by ~6 um), and the pilot says at
    which wavelength each pupil was laid."""
    cooke = rw.load_lens("cooke_triplet")
    batch = trace_pilot(cooke, [10.0, 10.0], [0.45, 0.6])
    assert batch.pupil_wls == (0.45, 0.45)
    alone = trace_pilot(cooke, [10.0], [0.6])
    assert np.max(np.abs(batch.subset([1]).pos_p - alone.pos_p)) > 1e-3
    _same(batch.subset([0]), trace_pilot(cooke, [10.0], [0.45]))
    _same(trace_pilot(cooke, [10.0, 10.0], [0.45, 0.6], own_pupils=True).subset([1]), alone)


def test_pilot_rays_obey_the_geometry(lens):
    """Independent checks of what the pilot holds: the on-axis chief ray of this rotationally symmetric lens
    stays on the axis (x = y = 0 on the plane and the sensor), every direction is a unit vector (to 1e-15,
    float64 rounding), the flat DOE plane's points lie at its vertex z, and a ray that reaches the sensor has
    reached the plane."""
    p = trace_pilot(lens, [0.0, 5.0], [0.55, 0.55])
    plane = lens.wave_plane_index()
    assert p.plane == plane
    assert np.all(p.ok[:, 0]) and np.array_equal(p.pos_p[0, 0, :2], [0.0, 0.0])
    assert np.array_equal(p.pos_s[0, 0, :2], [0.0, 0.0])
    assert np.max(np.abs(np.linalg.norm(p.dir_s[p.ok], axis=-1) - 1.0)) < 1e-15
    assert np.all(p.pos_p[p.valid_plane][:, 2] == lens.vertex_z[plane])
    assert not np.any(p.ok & ~p.valid_plane)
    assert p.object_distance_mm == lens.object_distance and p.relative_opl


def test_pilot_is_read_only(lens):
    """Writing into a pilot's arrays or fields raises; a pilot owns copies of the arrays it is made from."""
    p = trace_pilot(lens, [0.0, 3.0], [0.5, 0.6], own_pupils=True)
    for name in ARRAYS:
        with pytest.raises(ValueError, match="read-only"):
            getattr(p, name)[...] = 0
        with pytest.raises(ValueError, match="read-only"):
            getattr(p.subset([1]), name).flat[0] = 0
    with pytest.raises(dataclasses.FrozenInstanceError):
        p.pos_p = np.zeros_like(p.pos_p)
    mine = np.array(p.pos_s)
    q = dataclasses.replace(p, pos_s=mine)
    mine[...] = 0.0
    assert np.array_equal(q.pos_s, p.pos_s) and not q.pos_s.flags.writeable
    with pytest.raises(ValueError, match="pos_s has shape"):
        dataclasses.replace(p, pos_s=p.pos_s[:1])
    with pytest.raises(IndexError):
        p.subset([2])


@pytest.mark.parametrize("method", ["asm", "focal"])
def test_raywave_from_a_subset_is_the_source_planned_alone(lens, method):
    """Each source's RayWave planned from its subset of one batch pilot has the plan, chief rays and PSF of the
    RayWave of that source alone (which traces its own pilot): equal plans, the same PSF bits (the same rays
    on the same plan; measured 0.0), and the pilot is left as it was."""
    batch = trace_pilot(lens, FIELDS[:3], WLS[:3], own_pupils=True)
    before = {name: np.array(getattr(batch, name)) for name in ARRAYS}
    for k in range(3):
        kw = dict(rays_per_sample=0.5, method=method, focal_patch_tol=1e-3, own_pupils=True)
        alone = RayWave(lens, [FIELDS[k]], [WLS[k]], 12, lens.sensor.pixel_pitch, **kw)
        sub = RayWave(lens, [FIELDS[k]], [WLS[k]], 12, lens.sensor.pixel_pitch, pilot=batch.subset([k]), **kw)
        assert sub.plan == alone.plan
        for attr in ("chief_plane", "chief_sensor", "carrier", "centers", "origin", "opl_chief", "target"):
            assert np.array_equal(getattr(sub, attr), getattr(alone, attr)), attr
        assert np.array_equal(sub.run("double")["data"], alone.run("double")["data"])
    for name in ARRAYS:
        assert np.array_equal(getattr(batch, name), before[name])


def test_raywave_refuses_a_pilot_of_other_sources(lens):
    """A pilot traced for other sources or settings is refused, naming what differs; the old dict is refused
    with the way to a Pilot."""
    p = trace_pilot(lens, [0.0, 3.0], [0.5, 0.6], own_pupils=True)
    px = lens.sensor.pixel_pitch
    with pytest.raises(ValueError, match=r"fields \(deg\)"):
        RayWave(lens, [5.0], [0.5], 12, px, own_pupils=True, pilot=p.subset([0]))
    with pytest.raises(ValueError, match=r"wavelengths \(um\)"):
        RayWave(lens, [0.0], [0.6], 12, px, own_pupils=True, pilot=p.subset([0]))
    with pytest.raises(ValueError, match="use_reference"):
        RayWave(lens, [0.0], [0.5], 12, px, own_pupils=True, use_reference=False, pilot=p.subset([0]))
    with pytest.raises(ValueError, match="number of sources"):
        RayWave(lens, [0.0], [0.5], 12, px, own_pupils=True, pilot=p)
    # a batch's pupils without own_pupils: the 0.6 um source's pupil was laid at 0.5 um
    shared = trace_pilot(lens, [0.0, 3.0], [0.5, 0.6])
    with pytest.raises(ValueError, match="entrance-pupil wavelengths"):
        RayWave(lens, [3.0], [0.6], 12, px, pilot=shared.subset([1]))
    with pytest.raises(TypeError, match="trace_pilot"):
        RayWave(lens, [0.0], [0.5], 12, px, pilot={name: getattr(p, name)[:1] for name in ARRAYS})


def _count_pilots(monkeypatch):
    """Count the pilot traces (Tracer._run with a kept surface and an explicit pupil: the pilot's signature;
    the field traces generate their grid on the device) and the pilot traces (every one goes through
    rwwarp.wave.pilot.pilot_from_tracer: trace_pilot's and the planners' own, pilot_or_trace)."""
    calls = {"launch_sets": [], "trace_pilot": 0}
    run, tp = Tracer._run, pilot_mod.pilot_from_tracer

    def counted_run(self, src, u, v, cell=1.0, upto=None, keep=False, **kw):
        if keep and keep is not True and kw.get("grid_n", 0) == 0 and kw.get("grids") is None:
            calls["launch_sets"].append(len(src["wl"]))
        return run(self, src, u, v, cell, upto, keep, **kw)

    def counted_tp(*a, **k):
        calls["trace_pilot"] += 1
        return tp(*a, **k)
    monkeypatch.setattr(Tracer, "_run", counted_run)
    monkeypatch.setattr(pilot_mod, "pilot_from_tracer", counted_tp)
    return calls


@pytest.mark.parametrize("model, systems", [("ray-wave", 1), ("paraxial-wave", 2)])
def test_psf_map_traces_one_pilot_per_system(lens, monkeypatch, model, systems):
    """A 6-source map (3 fields x 2 wavelengths) traces one pilot per system for all its sources: ray-wave one
    of 6 sources, paraxial-wave one of 3 per wavelength (its equivalent system differs per wavelength)."""
    calls = _count_pilots(monkeypatch)
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")   # the 12 px patches cut these PSFs (PatchWarning): not the point here
        rw.psf_map(lens, [0.0, 3.0, 6.0], [0.5, 0.6], model=model, size=12, rays_per_sample=0.5)
    assert calls["trace_pilot"] == systems
    assert calls["launch_sets"] == [6 // systems] * systems
