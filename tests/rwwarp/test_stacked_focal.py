"""The focal members of a packed batch propagated as stacked operators (rwwarp.wave.focal_packed.run_focal_members,
the default on CUDA) against each member's own focal operator (RayWave.focal_intensity: an FFT where the stack
uses a matrix DFT, its own DOE transmission, its own pixel sums): two implementations of the same sums, so they
agree to the float64 rounding of the longer sums (measured 2.2e-16..4.8e-16 of the peak on
these cases). The physics of the per-member path is tested against truths elsewhere
(test_focal.py, test_psf.py)."""
import numpy as np
import pytest

import rwwarp as rw
from rwwarp.wave.packed import PackedRayWave, source_plans
from test_focal import _cooke_with_doe   # the Cooke triplet with a flat even-polynomial DOE 5 mm before the sensor

# double precision: rounding of sums of ~1e3-1e5 terms in another order, 8x the largest measured (4.8e-16)
TOL = 4e-15


def _both(lens, fields, wls, precision="double", **kw):
    ms = source_plans(lens, fields, wls, 16, lens.sensor.pixel_pitch, method="focal", **kw)
    stacked = PackedRayWave(ms, stacked=True)
    assert stacked._runs_stacked()
    alone = PackedRayWave(ms, stacked=False)
    assert not alone._runs_stacked()
    return stacked.run(precision)["data"], alone.run(precision)["data"], stacked


def _rel(a, b):
    return float(np.max(np.abs(a - b)) / np.max(b))


@pytest.mark.parametrize("pixel_values", ["flux", "intensity"])
def test_a489_blank_doe_map_stacked_equals_each_member_alone(pixel_values):
    lens = rw.load_lens("a489_doe")
    a, b, _ = _both(lens, [(0.0, 0.0), (3.0, 7.0), (0.0, 10.0)], [0.45, 0.55, 0.65], pixel_values=pixel_values)
    assert a.shape == (3, 16, 16)
    assert _rel(a, b) < TOL


def test_doe_orders_series_single_and_exact_zones_in_one_stack():
    """A wrapped DOE at its design wavelength (order 1 only), off it (several orders: one Horner series with the
    chief ray's wrap zone exact) and a weak DOE off design (one remapped order), members of one stack."""
    lens = _cooke_with_doe(-6000.0, 0.0)
    a, b, p = _both(lens, [(0.0, 0.0), (0.0, 3.0), (0.0, 0.0)], [0.55, 0.5876, 0.47])
    kinds = [len(m.focal["orders"][0]) for m in p.members]
    assert max(kinds) > 1 and min(kinds) == 1            # both branches of the factor ran
    assert any(m.focal.get("central_zone") and m.focal["central_zone"][0] is not None for m in p.members)
    assert _rel(a, b) < TOL
    weak = _cooke_with_doe(-1000.0, 50.0)
    a, b, _ = _both(weak, [(0.0, 0.0), (0.0, 2.0)], [0.5876, 0.5876])
    assert _rel(a, b) < TOL


def test_kept_operators_give_the_same_values_again():
    lens = rw.load_lens("a489_doe")
    ms = source_plans(lens, [(0.0, 0.0), (0.0, 10.0)], [0.55, 0.65], 16, lens.sensor.pixel_pitch, method="focal")
    p = PackedRayWave(ms, stacked=True, hold=True)
    first = p.run("double", keep_operators=True)["data"]
    assert p._stacked_ops
    again = p.run("double", keep_operators=True)["data"]
    assert np.array_equal(first, again)
    p.run("double")
    assert not hasattr(p, "_stacked_ops")                 # a run that keeps nothing drops them


def test_stacked_only_where_it_applies():
    lens = rw.load_lens("a489_doe")
    one = source_plans(lens, [(0.0, 0.0)], [0.55], 16, lens.sensor.pixel_pitch, method="focal")
    assert not PackedRayWave(one, stacked=True)._runs_stacked()          # a lone member runs its own operator
    asm = source_plans(lens, [(0.0, 0.0), (0.0, 5.0)], [0.55, 0.55], 16, lens.sensor.pixel_pitch, method="asm")
    assert not PackedRayWave(asm, stacked=True)._runs_stacked()          # not focal
    assert not PackedRayWave(asm).stacked                                # the CPU's default


@pytest.mark.gpu
def test_cuda_map_stacks_its_focal_members_and_matches_each_alone():
    """On CUDA a map's focal members stack by default; their PSFs are each member's own (deterministic splat,
    double precision) to the same rounding as on the CPU, and a cached second call (kept operators) repeats them."""
    from test_cuda_cpu import _cuda_or_skip
    _cuda_or_skip()
    lens = _cooke_with_doe(-6000.0, 0.0)
    ms = source_plans(lens, [(0.0, 0.0), (0.0, 3.0), (0.0, 0.0)], [0.55, 0.5876, 0.47], 32, lens.sensor.pixel_pitch,
                      method="focal", device="cuda", deterministic=True)
    p = PackedRayWave(ms)
    assert p.stacked and p._runs_stacked()
    a = p.run("double")["data"]
    b = PackedRayWave(ms, stacked=False).run("double")["data"]
    assert _rel(a, b) < TOL
    fields = [0.0, 5.0, 10.0]
    m1 = rw.psf_map(rw.load_lens("a489_doe"), fields, [0.45, 0.65], size=32, device="cuda", deterministic=True,
                    focal_precision="double")
    assert {q["method"] for b in m1.info["batches"] for q in b["plans"]} == {"focal"}    # auto: fewer flops
    cache = rw.PlanCache()
    for _ in range(2):
        m2 = rw.psf_map(rw.load_lens("a489_doe"), fields, [0.45, 0.65], size=32, device="cuda", deterministic=True,
                        focal_precision="double", cache=cache)
        assert np.array_equal(m1.data, m2.data)


def test_a_group_over_the_byte_bound_runs_in_parts():
    """run_focal_members splits a group whose stacked operators would exceed max_bytes: with a bound below two
    members' stack every member runs alone (the same values to the rounding); the estimate of a stack's bytes bounds
    what the operator built for it holds."""
    from rwwarp.wave.focal_packed import (PackedFocalPropagator, _chunks, _shape, focal_groups, run_focal_members,
                                          stacked_bytes)
    lens = rw.load_lens("a489_doe")
    ms = source_plans(lens, [(0.0, 0.0), (0.0, 5.0), (0.0, 10.0)], [0.55, 0.55, 0.65], 16, lens.sensor.pixel_pitch,
                      method="focal")
    p = PackedRayWave(ms, stacked=True)
    u = p.field_array()
    whole = np.concatenate(run_focal_members(ms, u, "double"))
    shapes = [_shape(m) for m in ms]
    one = min(stacked_bytes(s, 1) for s in shapes)
    assert _chunks([0, 1, 2], shapes, one) == [[0], [1], [2]] and _chunks([0, 1, 2], shapes, 2 ** 40) == [[0, 1, 2]]
    alone = np.concatenate(run_focal_members(ms, u, "double", max_bytes=one))
    assert _rel(alone, whole) < TOL
    g = max(focal_groups(ms), key=len)
    pad = tuple(max(shapes[k][i] for k in g) for i in range(4))
    op = PackedFocalPropagator.from_members([ms[k] for k in g], float(ms[0].z_sensor - ms[0].z_plane))
    assert op.nbytes <= stacked_bytes(pad, len(g))
