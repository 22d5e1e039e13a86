"""Focal sources computed together (torch_bridge.packed, LiveProvider(pack=True)) against the same sources one
at a time (LiveProvider(pack=False): HybridLens._psf_rw per source, the reference path whose gradients
tests/torch_bridge/test_focal_bridge.py checks against finite differences), and the launch count of a step.

The packed tile traces all members in one launch set (slots of the largest member, padding invalid and
zero), forms the DOE transmission of all members in one Horner recursion over the union of their orders, and
propagates the members by batched matrix products (the FFT of step 2 as an equal matrix DFT, factors
zero-padded): per member the same sums in another order, so the results agree to rounding."""
from __future__ import annotations

import numpy as np
import pytest
import torch

import rwwarp as rw
import torch_bridge as tb
from rwwarp.wave.focal_packed import PackedFocalPropagator, focal_groups
from rwwarp.wave.packed import source_plans
from torch_bridge import design as dz
from _lenses import wrapping_doe_lens
from _op_count import OpCounter  # noqa: E402




def _run(lens, pack, learn, fields, wls, size=12, seed=3, device="cpu", amplitude="energy", nyquist_safety=2.0):
    m = tb.HybridLens(lens, learn=learn, method="focal", rays_per_sample=0.5, focal_patch_tol=1e-3,
                      amplitude=amplitude, nyquist_safety=nyquist_safety).to(device)
    prov = dz.LiveProvider(m, fields, size, lens.sensor.pixel_pitch, pack=pack)
    out = prov.psfs(wls)
    g = torch.as_tensor(np.random.default_rng(seed).standard_normal(tuple(out.shape)), device=out.device)
    (out * g).sum().backward()
    grads = {q: getattr(m, q).grad.detach().cpu().clone() for q in learn}
    return out.detach().cpu(), grads, prov


_REFERENCE = {}
ALL = {"curvature": "all", "doe": "all", "thickness": "all"}


def _reference(levels, coefficients=(-30.0,)):
    """The one-at-a-time run of :func:`_doe_lens` (``levels``, ``coefficients``) at 0 and 5 deg x 0.5 and
    0.6 um, everything learning: (PSFs, gradients). Computed once a module and shared by the tests that
    compare against the same sources (the 8-level case below and the tiled/checkpointed test): the same
    deterministic run, read only."""
    key = (levels, tuple(coefficients))
    if key not in _REFERENCE:
        a, ga, pa = _run(wrapping_doe_lens(levels, coefficients), False, ALL, [0.0, 5.0], [0.5, 0.6])
        assert pa.packs_made == 0
        _REFERENCE[key] = (a, ga)
    return _REFERENCE[key]


@pytest.mark.parametrize("levels,coefficients", [(None, (-30.0,)), (8, (-30.0,)), (None, (0.0,))],
                         ids=["continuous", "8-levels", "blank"])
def test_packed_psfs_and_gradients_equal_the_per_source_path(levels, coefficients):
    """A489 + wrapping DOE, 0 and 5 deg x 0.5 and 0.6 um (4 focal sources, each on its own plan: windows of
    201-459 samples, different DOE orders; "blank": a flat DOE about to learn, exp(1j alpha phi0)), curvatures,
    DOE coefficient and every thickness learning. PSFs: measured 8.4e-16 (continuous), 4.9e-16 (8 levels)
    and 6.6e-16 (blank) of each PSF's peak; gradients up to 2.5e-14 (curvature) and 2.1e-14 (DOE) of the
    largest; tolerance 1e-12. The thicknesses before the DOE move the wave plane,
    whose z gradient holds the reference-sphere term: a sum over the windows of terms up to 1.3e4 times the
    field's (the factor k n dz / r) that cancels to order 1, so the order of its sums shows, 7.2e-13 of the
    largest thickness gradient (the sensor distance alone: 1.1e-15); tolerance 5e-12 there."""
    lens = wrapping_doe_lens(levels, coefficients)
    learn = ALL
    a, ga = _reference(levels, coefficients)
    b, gb, pb = _run(lens, True, learn, [0.0, 5.0], [0.5, 0.6])
    assert pb.packs_made == 1
    peak = a.abs().amax((2, 3), keepdim=True)
    assert float(((a - b).abs() / peak).max()) <= 1e-12
    for q in learn:
        scale = float(ga[q].abs().max())
        assert scale > 0
        assert float((ga[q] - gb[q]).abs().max()) <= (5e-12 if q == "thickness" else 1e-12) * scale, q
    # the packed output is not the same numbers by construction: the sources differ from each other
    assert float((a[0, 0] - a[1, 0]).abs().max()) > 1e-3 * float(peak[0, 0])


def test_packed_paper_amplitude_equals_the_per_source_path():
    """The paper's amplitude convention (one power scale per member at its own pitch, in torch): A489 + DOE
    (8 levels), 4 sources, curvatures and DOE learning; measured 5.3e-16 of the peak (PSFs), 6.2e-15 and 0
    (gradients); tolerance 1e-12."""
    lens = wrapping_doe_lens(8)
    learn = {"curvature": "all", "doe": "all"}
    a, ga, _ = _run(lens, False, learn, [0.0, 5.0], [0.5, 0.6], amplitude="paper")
    b, gb, pb = _run(lens, True, learn, [0.0, 5.0], [0.5, 0.6], amplitude="paper")
    assert pb.packs_made == 1
    assert float(((a - b).abs() / a.abs().amax((2, 3), keepdim=True)).max()) <= 1e-12
    for q in learn:
        assert float((ga[q] - gb[q]).abs().max()) <= 1e-12 * float(ga[q].abs().max()), q


def test_packed_thin_lens_tiles_split_by_wavelength():
    """With an ideal thin lens (its table columns follow the tracer's first wavelength) members are packed per
    wavelength: 2 tiles for 2 fields x 2 wavelengths; PSFs (measured 1.0e-15 of the peak) and the DOE and
    distance gradients (3.6e-15, 5.3e-16 relative) as one at a time; tolerance 1e-12. On the coarse plan
    (nyquist_safety 1; the default plan measured 1.1e-15, 5.7e-16, 2.1e-15 in 1.75x the time): the packing, not
    the sampling, is what is compared."""
    import math

    from rwwarp.lens import Lens, Surface
    half = 1.0
    surfs = [Surface(type="aperture", semi_diameter=half, shape="square", stop=True),
             Surface(type="thin_lens", focal_length=21.0, semi_diameter=half, shape="square"),
             Surface(type="doe", semi_diameter=half, shape="square", design_wavelength_um=0.55,
                     material="fused_silica", profile={"kind": "even_poly", "norm_radius": 1.0,
                                                       "coefficients": [-40.0, 6.0]})]
    surfs[-1].thickness = 20.0
    lens = Lens(surfs, rw.Sensor(0.002, (4000, 4000)), math.inf, [0.55], name="thin lens + DOE")
    learn = {"doe": "all", "thickness": [2]}
    a, ga, _ = _run(lens, False, learn, [0.0, 1.0], [0.5, 0.6], size=10, nyquist_safety=1.0)
    b, gb, pb = _run(lens, True, learn, [0.0, 1.0], [0.5, 0.6], size=10, nyquist_safety=1.0)
    assert pb.packs_made == 2
    assert float(((a - b).abs() / a.abs().amax((2, 3), keepdim=True)).max()) <= 1e-12
    for q in learn:
        assert float((ga[q] - gb[q]).abs().max()) <= 1e-12 * float(ga[q].abs().max()), q


def test_packed_focal_operator_equals_each_members_operator():
    """PackedFocalPropagator of 4 Cooke triplet sources (on the coarse plan, nyquist_safety 1: wave-plane grids
    176-601, 9 and 10 Gauss nodes, 3 groups; the default plan's grids 349-1199 took 2.7x the time for the same
    property) against each member's own FocalPropagator: forward, adjoint and distance derivative on random
    fields, at the plans' distance and, moved there by ``at_distance``, at 0.97 and 1.02 times it; measured
    <= 1.3e-15 relative to each result's largest entry (both plans); tolerance 1e-12. Outputs past a member's
    nodes and adjoints past its grid are exactly zero."""
    lens = rw.load_lens("cooke_triplet")
    ms = source_plans(lens, [0.0, 0.0, 10.0, 10.0], [0.5, 0.6, 0.5, 0.6], 12, lens.sensor.pixel_pitch,
                      method="focal", rays_per_sample=0.5, nyquist_safety=1.0)
    assert len(focal_groups(ms)) > 1                    # the default waste splits these sizes
    z = float(ms[0].z_sensor - ms[0].z_plane)
    op = PackedFocalPropagator.from_members(ms, z)
    rng = np.random.default_rng(0)
    f = np.zeros((4, op.n, op.n), complex)
    for k, m in enumerate(ms):
        n = m.plan.n_grid
        f[k, :n, :n] = rng.standard_normal((n, n)) + 1j * rng.standard_normal((n, n))
    g = rng.standard_normal((4, op.m, op.m)) + 1j * rng.standard_normal((4, op.m, op.m))
    # the same operator moved to another distance (a learning thickness: PackedFocalPropagator.at_distance
    # shares the distance-free factors) against each member's own operator built at that distance
    first = op.forward(f)
    for zz, o in ((z, op), (0.97 * z, op.at_distance(0.97 * z)), (1.02 * z, op.at_distance(1.02 * z))):
        out, dd, adj = o.forward(f), o.distance_derivative(f), o.adjoint(g)
        for k, m in enumerate(ms):
            n, mm = m.plan.n_grid, m.size * m.gauss_nodes
            own = m.focal_operator(zz)
            for x, y in ((out[k, :mm, :mm], own.forward(f[k:k + 1, :n, :n])[0]),
                         (dd[k, :mm, :mm], own.distance_derivative(f[k:k + 1, :n, :n])[0]),
                         (adj[k, :n, :n], own.adjoint(g[k:k + 1, :mm, :mm])[0])):
                assert np.abs(x - y).max() <= 1e-12 * np.abs(y).max(), zz
            assert not np.any(out[k, mm:]) and not np.any(adj[k, n:]) and not np.any(adj[k, :, n:])
        # and the same numbers as an operator built at that distance from the start (measured: bit for bit)
        fresh = PackedFocalPropagator.from_members(ms, zz)
        assert np.array_equal(out, fresh.forward(f)) and np.array_equal(adj, fresh.adjoint(g))
    assert np.array_equal(op.forward(f), first)   # moving a copy leaves the operator as it was


def _count_launches(monkeypatch):
    import warp as wp
    count = [0]
    real = wp.launch

    def counting(*a, **k):
        count[0] += 1
        return real(*a, **k)
    monkeypatch.setattr(wp, "launch", counting)
    return count


def test_a_packed_step_makes_a_bounded_number_of_launches(monkeypatch):
    """One design step on kept plans (LiveProvider(replan_every=...): the steady state of the gpu preset) of the
    A489 + DOE (4 surfaces): forward + backward of 2, then 4 (and 6) focal sources. One at a time the Warp launches
    grow with the sources (measured 67 and 123: 28 a source); packed they do not (measured 39 and 39: the
    patch centres' ray trace, one trace of all members to the DOE plane with its parameter-row copies, tube
    areas, splat, finalize, power sums, and the adjoints of the recorded ones). Bound: 8 launches per surface
    (7 measured: trace, copies and their adjoints, the centres' trace) plus 12 for the stages (11 measured),
    independent of the number of sources."""
    lens = wrapping_doe_lens(None)
    count = _count_launches(monkeypatch)
    got, torch_ops = {}, {}
    for pack in (False, True):
        for fields in ([0.0], [0.0, 5.0]) + (([0.0, 2.5, 5.0],) if pack else ()):
            # the coarse plan (nyquist_safety 1): launches and torch ops are counted, not the sampling
            m = tb.HybridLens(lens, learn={"curvature": "all", "doe": "all"}, method="focal", rays_per_sample=0.5,
                              focal_patch_tol=1e-3, nyquist_safety=1.0)
            prov = dz.LiveProvider(m, fields, 12, lens.sensor.pixel_pitch, pack=pack, replan_every=100)
            prov.psfs([0.5, 0.6])                          # plans (not counted)
            count[0] = 0
            ops = OpCounter()
            with ops:
                prov.psfs([0.5, 0.6]).sum().backward()
            got[pack, len(fields)] = count[0]
            torch_ops[pack, len(fields)] = ops.n
    bound = 8 * len(lens.surfaces) + 12
    assert got[True, 1] == got[True, 2] <= bound
    assert got[False, 2] >= 2 * got[False, 1] - bound    # one at a time: per source
    assert got[True, 3] == got[True, 2]
    # nor do the torch operations (views included) of the packed step, once the members' kinds of DOE
    # transmission are the same (on axis one order, off axis a series: a batch each): 4 and 6 sources,
    # measured 571 and 571 (one at a time: 655 for 2 sources, 1281 for 4)
    assert torch_ops[True, 2] == torch_ops[True, 3] < torch_ops[False, 2]


def test_checkpointed_and_budget_split_tiles_equal_the_per_source_path():
    """The A489 + DOE (8 levels), 4 focal sources: in chunks of 2 (checkpointed: forward without tape, each chunk
    traced again under the tape in backward), and in one chunk under a budget that holds 2 packed members but
    not 3 (packed_recorded_bytes: each member at the largest member's rays and window), which splits it into
    tiles of at most 2; the same budget as ``record_budget_bytes`` beside a memory budget that holds everything
    (a training step's share of its budget) splits it alike. PSFs and gradients as one at a time: measured as the first test (<= 5e-16 of the peak,
    <= 4.4e-13 of the largest thickness gradient); tolerances as there."""
    from torch_bridge.packed import packed_recorded_bytes
    lens = wrapping_doe_lens(8)
    learn = ALL
    fields, wls = [0.0, 5.0], [0.5, 0.6]
    a, ga = _reference(8)                     # the one-at-a-time run of these sources (shared)
    m = tb.HybridLens(lens, learn=learn, method="focal", rays_per_sample=0.5, focal_patch_tol=1e-3)
    members = [m.raywave([f], [w], 12, pixel_mm=lens.sensor.pixel_pitch, method="focal") for f in fields for w in wls]
    budget = max(packed_recorded_bytes(m, [p, q]) for p in members for q in members) + 1
    assert packed_recorded_bytes(m, members[:3]) > budget
    for kw, tiles in (({"tile": 2}, 2), ({"memory_budget_bytes": budget}, None),
                      ({"memory_budget_bytes": 1000 * budget, "record_budget_bytes": budget}, None)):
        m = tb.HybridLens(lens, learn=learn, method="focal", rays_per_sample=0.5, focal_patch_tol=1e-3)
        prov = dz.LiveProvider(m, fields, 12, lens.sensor.pixel_pitch, **kw)
        out = prov.psfs(wls)
        g = torch.as_tensor(np.random.default_rng(3).standard_normal(tuple(out.shape)))
        (out * g).sum().backward()
        assert prov.packs_made >= 2 if tiles is None else prov.packs_made == tiles
        assert float(((a - out.detach()).abs() / a.abs().amax((2, 3), keepdim=True)).max()) <= 1e-12
        for q in learn:
            d = float((ga[q] - getattr(m, q).grad).abs().max())
            assert d <= (5e-12 if q == "thickness" else 1e-12) * float(ga[q].abs().max()), (kw, q)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_packed_on_cuda_equals_the_per_source_path_and_the_cpu():
    """The first test's continuous case on CUDA (Warp on torch's stream, CuPy views of the same memory, torch's
    allocator): packed against one at a time on the GPU (tolerances as on the CPU), and against the CPU's
    packed PSFs (1e-10 of the peak: the splat's atomic float sums on the GPU add in another order; not run
    here: no GPU was available when this was written)."""
    lens = wrapping_doe_lens(None)
    learn = {"curvature": "all", "doe": "all", "thickness": "all"}
    a, ga, _ = _run(lens, False, learn, [0.0, 5.0], [0.5, 0.6], device="cuda")
    b, gb, pb = _run(lens, True, learn, [0.0, 5.0], [0.5, 0.6], device="cuda")
    c, _, _ = _run(lens, True, learn, [0.0, 5.0], [0.5, 0.6])
    assert pb.packs_made == 1
    peak = a.abs().amax((2, 3), keepdim=True)
    assert float(((a - b).abs() / peak).max()) <= 1e-12
    assert float(((c - b).abs() / peak).max()) <= 1e-10
    for q in learn:
        scale = float(ga[q].abs().max())
        assert float((ga[q] - gb[q]).abs().max()) <= (5e-12 if q == "thickness" else 1e-12) * scale, q


def test_one_source_planned_again_rebuilds_its_tile_not_the_others_plans():
    """Cooke triplet, 0 and 10 deg, kept plans (replan_every=3): one packed tile. One source's plan given up
    (its rays marked as having left its window) is planned again alone: the other keeps its plan, the tile
    is built again from the new member set (no planning), and the next call reuses that tile as it is (same
    members: the same PSFs bit for bit)."""
    lens = rw.load_lens("cooke_triplet")
    m = tb.HybridLens(lens, learn={"curvature": [0]}, method="focal", rays_per_sample=0.5)
    prov = dz.LiveProvider(m, [0.0, 10.0], 12, lens.sensor.pixel_pitch, replan_every=3)
    with torch.no_grad():
        prov.psfs([0.55])
        assert (prov.plans_made, prov.plans_reused, prov.packs_made) == (2, 0, 1)
        first = next(iter(prov._focal_rws.values()))
        first[3] = True
        b = prov.psfs([0.55])
        assert (prov.plans_made, prov.plans_reused, prov.packs_made) == (3, 1, 2)
        assert prov.replans == {"age": 0, "window": 1}
        c = prov.psfs([0.55])
        assert (prov.plans_made, prov.plans_reused, prov.packs_made) == (3, 3, 2)
    assert torch.equal(b, c)


def test_sources_planned_together_equal_each_planned_alone():
    """HybridLens.raywaves_alone (one pilot trace for several sources, used by LiveProvider to plan sources again)
    against HybridLens.raywave of each source alone: the A489 + DOE at 0 / 5 deg x 0.5 / 0.6 um, each with its
    own patch centre. A source's pilot rays do not depend on the others, so the plans are equal and the PSFs
    the same numbers (measured 0.0; tolerance 1e-14 of the peak for the splat's summation order)."""
    lens = wrapping_doe_lens(None)
    m = tb.HybridLens(lens, learn={"curvature": "all"}, method="focal", rays_per_sample=0.5, focal_patch_tol=1e-3)
    fields, wls = [0.0, 0.0, 5.0, 5.0], [0.5, 0.6, 0.5, 0.6]
    cen = dz.common_centres(m, [0.0, 5.0], 0.55)
    cen = np.repeat(cen, 2, axis=0)
    together = m.raywaves_alone(fields, wls, 12, centers_mm=cen, pixel_mm=lens.sensor.pixel_pitch, method="focal")
    assert len(together) == 4
    for k, r in enumerate(together):
        alone = m.raywave([fields[k]], [wls[k]], 12, pixel_mm=lens.sensor.pixel_pitch, center_mm=cen[k:k + 1],
                          method="focal")
        assert r.plan == alone.plan
        a, b = alone.run("double")["data"], r.run("double")["data"]
        assert np.max(np.abs(a - b)) <= 1e-14 * np.max(a), k


def test_pack_groups_even_where_the_budget_allows():
    """live.pack_groups: the greedy cut's number of groups, near-equal lengths where each fits, else the greedy cut
    itself. ``fits`` as packed_recorded_bytes counts a tile: every member at the largest member's size."""
    from torch_bridge.live import pack_groups

    def rule(w, budget):
        return lambda g: len(g) * max(w[i] for i in g) <= budget
    w = [1.0] * 8
    assert pack_groups(list(range(8)), rule(w, 7)) == [[0, 1, 2, 3], [4, 5, 6, 7]]      # greedy: 7 + 1
    assert pack_groups(list(range(8)), rule(w, 8)) == [list(range(8))]
    assert pack_groups(list(range(7)), rule(w, 3)) == [[0, 1, 2], [3, 4], [5, 6]]        # greedy: 3 + 3 + 1
    w = [1.0] * 5 + [2.0]
    # greedy 5 + 1; the even cut 3 + 3 puts the large member with two others (3 x 2 > 5): greedy kept
    assert pack_groups(list(range(6)), rule(w, 5)) == [[0, 1, 2, 3, 4], [5]]
    assert pack_groups([], rule(w, 5)) == []
    assert pack_groups([4], rule(w, 0)) == [[4]]                                          # alone, whatever fits


def test_a_chunk_over_the_budget_splits_into_even_packed_tiles():
    """The A489 + DOE, 4 focal sources under a record budget that holds 3 packed members but not 4: two packed
    tiles of 2 (not 3 + 1, whose single source would run on its own path)."""
    from torch_bridge.packed import packed_recorded_bytes
    lens = wrapping_doe_lens(8)
    m = tb.HybridLens(lens, learn={"doe": "all"}, method="focal", rays_per_sample=0.5, focal_patch_tol=1e-3)
    members = [m.raywave([f], [w], 12, pixel_mm=lens.sensor.pixel_pitch, method="focal")
               for f in (0.0, 5.0) for w in (0.5, 0.6)]
    budget = max(packed_recorded_bytes(m, [members[i] for i in c]) for c in ((0, 1, 2), (1, 2, 3), (0, 1, 3), (0, 2, 3)))
    assert packed_recorded_bytes(m, members) > budget
    prov = dz.LiveProvider(m, [0.0, 5.0], 12, lens.sensor.pixel_pitch, record_budget_bytes=budget)
    units = prov._units([0, 1, 2, 3], dict(enumerate(members)), [], {})
    assert [(kind, rows) for kind, _, rows in units] == [("packed", [0, 1]), ("packed", [2, 3])]
