"""The DOE fabrication limit (optics.min_feature_um): the projection leaves a compliant DOE alone and
scales an over-fine one so that its smallest feature, measured independently on the DOE's own
gradient, equals the limit; the cached plans sample that limit; bad values are refused."""
import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

import rwwarp as rw
import torch_bridge as tb
from torch_bridge import design as dz
from torch_bridge.train import ConfigError, load_config


def _lens(coeffs, levels=16):
    lens = rw.load_lens("a489_doe")
    d = lens.doe_index
    return lens.with_surface(d, profile={**lens.surfaces[d].profile, "coefficients": list(coeffs)}, levels=levels)


def _smallest_step_mm(lens):
    """Independent check: narrowest quantisation step from the analytic radial derivative of the
    even polynomial, sum 2 i a_i r^(2i-1) / R^(2i), on a fine radial grid over the aperture (a square
    of half side sd reaches r = sqrt(2) sd at its corners)."""
    s = lens.surfaces[lens.doe_index]
    R = s.profile["norm_radius"]
    r = np.linspace(0, s.semi_diameter * (math.sqrt(2) if s.shape == "square" else 1.0), 20001)
    g = sum(2 * (i + 1) * a * r ** (2 * i + 1) / R ** (2 * i + 2) for i, a in enumerate(s.profile["coefficients"]))
    return 2 * math.pi / np.max(np.abs(g)) / s.levels


def test_projection_scales_to_the_limit_and_leaves_compliant_doe():
    m = tb.HybridLens(_lens([-400.0, 120.0, 30.0, -10.0]), learn={"doe": [0, 1]})
    before = _smallest_step_mm(m.to_lens())
    limit = 2.0 * before
    c = m.limit_doe_feature(limit)
    assert 0.45 < c < 0.55                        # the feature grows as 1 / scale
    after = _smallest_step_mm(m.to_lens())
    assert after == pytest.approx(limit, rel=1e-3)
    coeffs = m.value("doe").detach().numpy()
    np.testing.assert_allclose(coeffs, c * np.array([-400.0, 120.0, 30.0, -10.0]), rtol=1e-12)
    assert m.limit_doe_feature(0.5 * after) == 1.0   # compliant: untouched
    np.testing.assert_array_equal(m.value("doe").detach().numpy(), coeffs)
    with pytest.raises(ValueError, match="min_feature_mm"):
        m.limit_doe_feature(0.0)


def test_cached_plan_samples_the_feature_limit():
    lens = _lens([-20.0, 8.0, 3.0, -1.0])
    m = tb.HybridLens(lens, learn={"doe": "all"}, nyquist_safety=1.0, rays_per_sample=1.2)
    fields = dz.field_angles(lens, [(0.0, 0.0)], 0.55)
    feat = 0.006   # mm: 16 levels -> DOE frequency up to 10.4 cycles/mm at the design wavelength
    free = dz.CachedProvider(m, fields, 15, 0.003, wavelength_ref_um=0.55)
    lim = dz.CachedProvider(m, fields, 15, 0.003, wavelength_ref_um=0.55, min_feature_mm=feat)
    for p in (free, lim):
        p.prepare([0.55], [None])
    k = free._key(0.55, None)
    assert lim.plans[k]["pitch_mm"] <= 0.5 * feat + 1e-15
    assert lim.plans[k]["pitch_mm"] < free.plans[k]["pitch_mm"]
    with pytest.raises(ValueError, match="min_feature_mm"):
        dz.CachedProvider(m, fields, 15, 0.003, min_feature_mm=-1.0)


def test_min_feature_config_validated():
    with pytest.raises(ConfigError, match="min_feature_um"):
        load_config({"lens": {"file": "a489_doe"}, "optics": {"min_feature_um": 0}})
    cfg = load_config({"lens": {"file": "a489_doe"}, "optics": {"min_feature_um": 1.0}})
    assert cfg["arms"][0]["config"]["optics"]["min_feature_um"] == 1.0


def test_training_keeps_the_doe_within_the_limit(tmp_path):
    """A tiny end-to-end run with a binding limit: the optics updates are projected and the designed
    DOE's smallest step (measured independently from its coefficients) is at the limit, not below."""
    import json
    from test_train import tiny
    from torch_bridge.train import train
    # 2 joint steps, no fine-tune: every optics step is projected (measured: 2 projections in 2 steps, 4 in
    # 4 before; the smallest step 0.2000000002 mm either way) and the fine-tune phase freezes the optics,
    # so more steps add nothing to what is checked
    res = train(tiny(**{"optics.min_feature_um": 200.0, "train.joint_steps": 2, "train.finetune_steps": 0}),
                out_dir=tmp_path)
    r = json.loads((tmp_path / "e2e" / "result.json").read_text())
    assert r["feature_projections"] >= 1
    lens = rw.load_lens(tmp_path / "e2e" / "lens.json")
    step = _smallest_step_mm(lens)
    assert 0.2 * (1 - 1e-6) <= step < 0.3, step     # at the limit: projected, not flattened
    assert res is not None


def test_auto_takes_the_asm_for_a_learning_doe_under_a_feature_limit():
    """At F/2.2 the design loop's "auto" probe picks the focal path for the A489's nodes; with a fabrication
    limit and a learning DOE the cached provider takes the ASM instead (its plan covers every DOE within the
    limit), and a DOE grown to the limit then needs no rebuild (the focal plan would: new orders, finer pitch)."""
    lens = _lens([-20.0, 8.0, 3.0, -1.0])
    lens = lens.replace(entrance_pupil_diameter=lens.efl(0.55) / 2.2)          # the gpu preset's F/2.2
    m = tb.HybridLens(lens, learn={"doe": "all"}, nyquist_safety=1.5, rays_per_sample=1.2)
    fields = dz.field_angles(lens, [(0.0, 0.0)], 0.55)
    free = dz.CachedProvider(m, fields, 63, 0.003, wavelength_ref_um=0.55)
    lim = dz.CachedProvider(m, fields, 63, 0.003, wavelength_ref_um=0.55, min_feature_mm=0.001)
    k = free._key(0.55, None)
    assert free._uses_focal(k) and not lim._uses_focal(k)
    frozen = tb.HybridLens(lens, nyquist_safety=1.5, rays_per_sample=1.2)       # nothing learns: the probe decides
    assert dz.CachedProvider(frozen, fields, 63, 0.003, wavelength_ref_um=0.55, min_feature_mm=0.001)._uses_focal(k)


def test_asm_entry_is_not_rebuilt_when_the_doe_grows_to_the_feature_limit():
    lens = _lens([-20.0, 8.0, 3.0, -1.0])
    m = tb.HybridLens(lens, learn={"doe": "all"}, nyquist_safety=1.0, rays_per_sample=1.2)
    fields = dz.field_angles(lens, [(0.0, 0.0)], 0.55)
    feat = 0.006
    p = dz.CachedProvider(m, fields, 15, 0.003, wavelength_ref_um=0.55, min_feature_mm=feat)
    p.prepare([0.55], [None])
    k = p._key(0.55, None)
    plan = dict(p.plans[k])
    with torch.no_grad():
        m.doe.mul_(100.0)                          # far past the limit ...
    assert m.limit_doe_feature(feat) < 1.0          # ... projected back onto it, as training does
    assert _smallest_step_mm(m.to_lens()) == pytest.approx(feat, rel=1e-3)
    assert p.check_sampling() == 0 and p.plans[k]["pitch_mm"] == plan["pitch_mm"]


def test_a_rebuilt_entry_keeps_the_method_auto_chose_when_it_was_planned():
    """"auto" decides an entry's path from the DOE of the moment (F/8 here: the ASM for the blank DOE, the focal
    path once the DOE is strong). An entry built again from its record (a resumed run's load_plans) keeps the ASM
    and its plan: a resumed design took the focal path and ended 0.4 dB off the uninterrupted run (session 19)."""
    lens = _lens([0.0, 0.0, 0.0, 0.0])
    lens = lens.replace(entrance_pupil_diameter=lens.efl(0.55) / 8.0)
    m = tb.HybridLens(lens, learn={"doe": "all"}, nyquist_safety=1.0, rays_per_sample=1.2)
    fields = dz.field_angles(lens, [(0.0, 0.0)], 0.55)
    first = dz.CachedProvider(m, fields, 31, 0.003, wavelength_ref_um=0.55)
    first.prepare([0.45], [None])
    k = first._key(0.45, None)
    assert k in first._cache and first.plans[k]["method"] == "asm"
    with torch.no_grad():
        m.doe.copy_(torch.tensor([-20.0, 5.0, 10.0, 10.0], dtype=m.doe.dtype))
    assert dz.CachedProvider(m, fields, 31, 0.003, wavelength_ref_um=0.55)._uses_focal(k)   # a fresh choice: focal
    resumed = dz.CachedProvider(m, fields, 31, 0.003, wavelength_ref_um=0.55)
    resumed.load_plans(first.plans)
    resumed.prepare([0.45], [None])
    assert k in resumed._cache and k not in resumed._focal
    assert resumed.plans[k]["pitch_mm"] == first.plans[k]["pitch_mm"]
