"""LiveProvider plans all the sources of a call that need a plan of their own at once, before its tile loop: one
HybridLens.raywaves_alone call (one pilot trace) a call, none when every plan is kept.

The reference is each source planned alone (HybridLens.raywaves_alone of that one source: HybridLens.raywave, the
single-source planner rwwarp.wave.batch_plan.plan_batch, its own pilot trace), the way the provider's chunk-by-chunk
planning gave each source its plan; a source's pilot rays do not depend on the others traced beside it
(rwwarp.wave.pilot.Pilot.subset), so the plans, PSFs and gradients are the same numbers bit for bit on the CPU."""
from __future__ import annotations

import numpy as np
import pytest
import torch

import rwwarp as rw
import rwwarp.wave.pilot as P
import torch_bridge as tb
from torch_bridge import design as dz
from _lenses import wrapping_doe_lens




def _module(lens):
    return tb.HybridLens(lens, learn={"curvature": "all", "doe": "all", "thickness": "all"}, method="focal",
                         rays_per_sample=0.5, focal_patch_tol=1e-3)


class _Counts:
    """Counts of pilot traces (rwwarp.wave.pilot.pilot_from_tracer: every planner's) and of raywaves_alone calls
    (with their numbers of sources)."""

    def __init__(self, monkeypatch):
        self.pilots, self.alone = 0, []
        trace = P.pilot_from_tracer

        def pilot(*a, **k):
            self.pilots += 1
            return trace(*a, **k)
        monkeypatch.setattr(P, "pilot_from_tracer", pilot)
        alone = tb.HybridLens.raywaves_alone

        def counted(m, fields, *a, **k):
            self.alone.append(len(fields))
            return alone(m, fields, *a, **k)
        monkeypatch.setattr(tb.HybridLens, "raywaves_alone", counted)

    def take(self):
        out = (self.pilots, list(self.alone))
        self.pilots, self.alone = 0, []
        return out


def _one_by_one(m):
    """``m.raywaves_alone`` replaced by a loop planning each source alone (the reference; an instance attribute)."""
    alone = type(m).raywaves_alone

    def per_source(fields, wls, size, *, centers_mm, **k):
        c = np.asarray(centers_mm, dtype=np.float64).reshape(len(fields), 2)
        return [alone(m, [f], [w], size, centers_mm=c[i:i + 1], **k)[0] for i, (f, w) in enumerate(zip(fields, wls))]
    m.raywaves_alone = per_source


def test_a_call_plans_its_sources_from_one_pilot_trace_and_none_when_all_are_kept(monkeypatch):
    """Cooke triplet (focal, no DOE), fields 0, 5, 0 deg (the third repeats the first) x 0.5 / 0.6 um, chunks of 2:
    the sources of a chunk keep their order across 3 chunks. First call: one joint plan a chunk of new sources (its
    pilot trace) for the first two chunks, the third chunk's sources take the plans just made for the same sources
    (reused, 2), and the four new ones are planned together: one raywaves_alone of 4 sources, one pilot trace.
    Next call (replan_every 3): every plan kept, no pilot trace. Two plans given up (rays marked as having left
    their windows, in two chunks): one raywaves_alone of those 2 (their repeats reuse them). replan_every 1 (no kept
    plans): every call plans all 6 sources in one raywaves_alone (one pilot trace), not one a chunk; the first call's
    third chunk too (its sources were planned focal in the first chunk)."""
    lens = rw.load_lens("cooke_triplet")
    m = tb.HybridLens(lens, learn={"curvature": [0]}, method="focal", rays_per_sample=0.5)
    pix = lens.sensor.pixel_pitch
    c = _Counts(monkeypatch)
    prov = dz.LiveProvider(m, [0.0, 5.0, 0.0], 12, pix, tile=2, replan_every=3)
    with torch.no_grad():
        a = prov.psfs([0.5, 0.6])
        assert c.take() == (2 + 1, [4])
        assert (prov.plans_made, prov.plans_reused) == (4, 2)
        assert torch.equal(a[0], a[2])
        b = prov.psfs([0.5, 0.6])
        assert c.take() == (0, [])
        assert (prov.plans_made, prov.plans_reused) == (4, 8)
        assert torch.equal(a, b)
        keys = list(prov._focal_rws)
        assert len(keys) == 4
        for key in (keys[1], keys[2]):      # (0 deg, 0.6 um): chunk 1 (and 3); (5 deg, 0.5 um): chunk 2
            prov._focal_rws[key][3] = True
        d = prov.psfs([0.5, 0.6])
        assert c.take() == (1, [2])
        assert (prov.plans_made, prov.plans_reused, prov.replans["window"]) == (6, 12, 2)
        assert torch.equal(d[0], d[2]) and torch.equal(d, a)   # the values did not change: the same plans
    every = dz.LiveProvider(m, [0.0, 5.0, 0.0], 12, pix, tile=2)
    with torch.no_grad():
        every.psfs([0.5, 0.6])
        # no kept plans: the third chunk's repeats are planned again (their sources were planned focal before)
        assert c.take() == (2 + 1, [6]) and every.plans_made == 6
        e = every.psfs([0.5, 0.6])
        assert c.take() == (1, [6]) and every.plans_made == 12
    assert torch.equal(e, a)


def test_plans_made_together_give_the_psfs_and_gradients_of_each_source_planned_alone():
    """A489 + wrapping DOE, 0 / 3 / 5 deg x 0.5 / 0.6 um (6 focal sources, different DOE orders and windows), chunks
    of 2 (3 chunks, checkpointed), curvatures, DOE and thicknesses learning, kept plans (replan_every 3). Against a
    provider whose raywaves_alone plans each source alone: the first call (new sources), then a call with 3 plans
    given up in 3 chunks (planned again together) after a curvature step. PSFs and gradients equal bit for bit
    (measured: equal), the counts alike."""
    lens = wrapping_doe_lens()
    fields, wls, pix = [0.0, 3.0, 5.0], [0.5, 0.6], lens.sensor.pixel_pitch
    g = torch.as_tensor(np.random.default_rng(5).standard_normal((3, 2, 12, 12)))
    runs = []
    for ref in (False, True):
        m = _module(lens)
        if ref:
            _one_by_one(m)
        prov = dz.LiveProvider(m, fields, 12, pix, tile=2, replan_every=3)
        out = []
        for call in range(2):
            if call == 1:
                with torch.no_grad():
                    m.curvature[0] *= 1.0 + 1e-5
                for key in [k for k in prov._focal_rws if k[1] == (0.5 if k[0][-1] != 3.0 else 0.6)]:
                    prov._focal_rws[key][3] = True    # 0 deg 0.5 um, 3 deg 0.6 um, 5 deg 0.5 um: one in each chunk
            for q in ("curvature", "doe", "thickness"):
                getattr(m, q).grad = None
            p = prov.psfs(wls)
            (p * g).sum().backward()
            out.append((p.detach().clone(), {q: getattr(m, q).grad.clone() for q in ("curvature", "doe", "thickness")}))
        runs.append((out, prov.plans_made, prov.plans_reused, dict(prov.replans)))
    (new, *counts_new), (old, *counts_old) = runs
    assert counts_new == counts_old == [6 + 3, 3, {"age": 0, "window": 3}]
    for (a, ga), (b, gb) in zip(new, old):
        assert torch.equal(a, b)
        for q in ga:
            assert torch.equal(ga[q], gb[q]), q
    # the step moved the PSFs (the check above compares numbers that change)
    assert float((new[1][0] - new[0][0]).abs().max()) > 1e-6 * float(new[0][0].abs().max())


def test_a_sources_pilot_rows_in_a_batch_are_its_own_trace():
    """rwwarp.wave.pilot.trace_pilot(own_pupils=True) of the 6 sources above in one batch: each source's rows (Pilot.subset)
    are the bits of a trace of that source alone (rays are independent)."""
    lens = wrapping_doe_lens()
    fields = [f for f in (0.0, 3.0, 5.0) for _ in (0.5, 0.6)]
    wls = [w for _ in range(3) for w in (0.5, 0.6)]
    batch = P.trace_pilot(lens, fields, wls, own_pupils=True)
    for k in range(len(fields)):
        one, sub = P.trace_pilot(lens, [fields[k]], [wls[k]], own_pupils=True), batch.subset([k])
        for name in ("pos_p", "pos_s", "dir_s", "opl_p", "ok", "valid_plane"):
            assert np.array_equal(getattr(sub, name), getattr(one, name)), (k, name)


def test_a_failed_planning_leaves_the_kept_plans_as_they_were(monkeypatch):
    """Planning that fails (here raywaves_alone raising) leaves no entry waiting for a plan: the provider's kept plans
    are those before the call, and the next call plans the source given up and gives the same PSFs."""
    lens = rw.load_lens("cooke_triplet")
    m = tb.HybridLens(lens, learn={"curvature": [0]}, method="focal", rays_per_sample=0.5)
    prov = dz.LiveProvider(m, [0.0, 5.0], 12, lens.sensor.pixel_pitch, tile=1, replan_every=3)
    with torch.no_grad():
        a = prov.psfs([0.55])
        before = {k: e[0] for k, e in prov._focal_rws.items()}
        next(iter(prov._focal_rws.values()))[3] = True

        def fail(*args, **kw):
            raise RuntimeError("planning failed")
        monkeypatch.setattr(tb.HybridLens, "raywaves_alone", fail)
        with pytest.raises(RuntimeError, match="planning failed"):
            prov.psfs([0.55])
        assert {k: e[0] for k, e in prov._focal_rws.items()} == before
        monkeypatch.undo()
        made = prov.plans_made
        b = prov.psfs([0.55])
        assert prov.plans_made == made + 1
    assert torch.equal(a, b)


def test_drift_rule_replans_of_several_chunks_share_one_pilot_trace(monkeypatch):
    """Rule "drift", 4 sources in chunks of 1, a curvature step past the tolerance: every plan is due, the spreading
    (replan_spread 2, none forced: the hard bound set far) makes 2 again this call, in one raywaves_alone of those 2 (one pilot trace), not one a chunk."""
    lens = rw.load_lens("cooke_triplet")
    m = tb.HybridLens(lens, learn={"curvature": [0]}, method="focal", rays_per_sample=0.5)
    fields = [(10.0, 0.0), (0.0, 10.0), (-10.0, 0.0), (0.0, -10.0)]
    prov = dz.LiveProvider(m, fields, 12, lens.sensor.pixel_pitch, tile=1, replan_every=8, replan_rule="drift",
                           replan_drift=1e-3, replan_drift_hard=1e6, replan_spread=2)
    c = _Counts(monkeypatch)
    with torch.no_grad():
        prov.psfs([0.55])
        c.take()
        m.curvature[0] *= 1.0 + 1e-3
        prov.psfs([0.55])
        assert c.take() == (1, [2])
        assert prov.replans["drift"] == 2 and prov.replans_deferred == 2 and prov.plans_made == 4 + 2
