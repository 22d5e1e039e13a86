"""The callers of the pilot trace in torch_bridge trace it once per batch of sources (rwwarp.wave.pilot):
HybridLens.raywaves_alone one pilot for all its sources and one RayWave a source (no throwaway RayWave of all of
them), CachedProvider one pilot per entry build. The PSFs themselves are checked elsewhere
(test_packed_live.test_sources_planned_together_equal_each_planned_alone, test_cache_budget, test_focal_bridge)."""
from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

import rwwarp as rw
import torch_bridge as tb
from rwwarp.trace import Tracer
from rwwarp.wave import raywave as raywave_mod
from torch_bridge import design as dz


def _counters(monkeypatch):
    """Pilot launch sets (Tracer._run with a kept surface and an explicit pupil: the pilot's signature; the
    field traces generate their grid on the device), each with its number of sources, and RayWaves built."""
    seen = {"pilots": [], "raywaves": 0}
    run, init = Tracer._run, raywave_mod.RayWave._start   # every RayWave starts there (__init__, from_plan)

    def counted_run(self, src, u, v, cell=1.0, upto=None, keep=False, **kw):
        if keep and keep is not True and kw.get("grid_n", 0) == 0 and kw.get("grids") is None:
            seen["pilots"].append(len(src["wl"]))
        return run(self, src, u, v, cell, upto, keep, **kw)

    def counted_init(self, *a, **k):
        seen["raywaves"] += type(self) is raywave_mod.RayWave     # not a PackedRayWave of them
        return init(self, *a, **k)
    monkeypatch.setattr(Tracer, "_run", counted_run)
    monkeypatch.setattr(raywave_mod.RayWave, "_start", counted_init)
    return seen


def _lens():
    lens = rw.load_lens("a489_doe")
    d = lens.doe_index
    return lens.with_surface(d, profile={**lens.surfaces[d].profile, "coefficients": [-20.0, 8.0, 3.0, -1.0]})


def test_raywaves_alone_traces_one_pilot_and_builds_one_raywave_a_source(monkeypatch):
    """Four sources (2 fields x 2 wavelengths): one pilot launch set of 4 sources, 4 RayWaves (before: a fifth,
    the probe planning all four with the ASM only to give its pilot)."""
    lens = _lens()
    m = tb.HybridLens(lens, learn={"doe": "all"}, method="focal", rays_per_sample=0.5, focal_patch_tol=1e-3)
    seen = _counters(monkeypatch)
    rs = m.raywaves_alone([0.0, 0.0, 3.0, 3.0], [0.5, 0.6, 0.5, 0.6], 12, centers_mm=np.zeros((4, 2)),
                          pixel_mm=lens.sensor.pixel_pitch, method="focal")
    assert len(rs) == 4 and [list(r.wls) for r in rs] == [[0.5], [0.6], [0.5], [0.6]]
    assert seen == {"pilots": [4], "raywaves": 4}


@pytest.mark.parametrize("method, raywaves", [("asm", 2), ("focal", 4), ("auto", 3)])
def test_cached_provider_traces_one_pilot_an_entry(monkeypatch, method, raywaves):
    """An entry of 4 nodes at one wavelength traces one pilot of the 4 (before: one per RayWave it built: the
    "auto" probe, the auto plan and the entry's batch, or one a focal node), and builds the RayWaves it did
    (asm: the auto plan and the entry; focal: one a node; auto: the probe besides, which finds the ASM here)."""
    lens = _lens()
    m = tb.HybridLens(lens, learn={"doe": "all"}, nyquist_safety=1.0, rays_per_sample=1.0, method=method,
                      focal_patch_tol=1e-3)
    fields = dz.field_angles(lens, dz.node_positions_mm("grid", 1.0, (2, 2), region="quadrant"), 0.55)
    prov = dz.CachedProvider(m, fields, 15, 0.003, wavelength_ref_um=0.55, memory_budget_bytes=10 ** 12)
    seen = _counters(monkeypatch)
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")   # the ray-density criterion of these small plans: not the point here
        prov.prepare([0.63], [None])
    assert seen == {"pilots": [4], "raywaves": raywaves}
    assert bool(prov._focal) == (method == "focal")
