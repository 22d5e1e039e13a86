"""The focal propagation through torch: gradients against central finite differences on the same
(frozen) plans, and the torch paths against :func:`rwwarp.psf` with ``method="focal"``.

Finite differences are the independent reference of the gradients (the plan, sensor patch and ray
validity are frozen, so the loss is a smooth function of the parameters). Measured relative errors
with the steps below: curvature 2.1e-7 at h = 1e-9 (1.4e-4 at 1e-7, 3.2e-6 at 1e-8: the loss curves
strongly in the curvature, so the central difference converges as h^2), DOE coefficients 3e-10 at
h = 1e-5 (2e-6 at 1e-3), distance 6e-8 (Cooke, h = 1e-5) and 5e-11 (thin lens, h = 1e-6); tolerances
2e-6 (curvature) and 1e-6 (DOE, distance), 10x or more above the measured.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from _gradcheck import central_difference as _fd

import rwwarp as rw
import torch_bridge as tb
from rwwarp.lens import Lens, Surface
from torch_bridge import design as dz


def _thin_lens_doe(coeffs, dist=20.0, half=1.0):
    surfs = [Surface(type="aperture", semi_diameter=half, shape="square", stop=True),
             Surface(type="thin_lens", focal_length=21.0, semi_diameter=half, shape="square"),
             Surface(type="doe", semi_diameter=half, shape="square", design_wavelength_um=0.55,
                     material="fused_silica", profile={"kind": "even_poly", "norm_radius": 1.0,
                                                       "coefficients": list(coeffs)})]
    surfs[-1].thickness = dist
    return Lens(surfs, rw.Sensor(0.002, (4000, 4000)), math.inf, [0.55], name="thin lens + DOE")




def test_focal_gradients_match_finite_differences_refractive():
    """Cooke triplet (no DOE: the wave plane is the last, curved surface), 10 deg, focal path:
    d/d(curvature) and d/d(sensor distance)."""
    lens = rw.load_lens("cooke_triplet")
    last = len(lens.surfaces) - 1
    m = tb.HybridLens(lens, learn={"curvature": [0, 5], "thickness": [last]}, replan=False, method="focal",
                      rays_per_sample=0.5)
    g = torch.as_tensor(np.random.default_rng(1).standard_normal((12, 12)))

    def loss():
        return (m.psf((0, 10.0), 0.55, 12) * g).sum()
    loss().backward()
    assert m.raywave([(0, 10.0)], [0.55], 12).plan.method == "focal"
    for i in range(2):
        fd = _fd(loss, m.curvature, i, 1e-9)
        assert abs(m.curvature.grad[i].item() - fd) < 2e-6 * abs(fd)
    fd = _fd(loss, m.thickness, 0, 1e-5)
    assert abs(m.thickness.grad[0].item() - fd) < 1e-6 * abs(fd)


def test_focal_doe_gradients_through_orders_match_finite_differences():
    """Thin lens + even-poly DOE at 0.47 um (off its design wavelength: several diffraction orders reach
    the patch and are summed coherently): d/d(DOE coefficients) and d/d(DOE-to-sensor distance). The plan
    is coarse (nyquist_safety 1: a square pupil's default plan takes 4x the samples since its period and
    margin grew) -- the gradient is that of the planned model, whatever its sampling -- and keeps the orders
    that bring 1e-3 of the patch's power (focal_patch_tol, as test_packed_live.py: orders -1 .. 3, 5 of them;
    the default 1e-5 kept 15, -6 .. 8, in 10x the time). Measured relative errors: DOE 6.7e-10 / 2.5e-10,
    distance 5.5e-9 (15 orders: 4.0e-10 / 1.0e-10, 2.5e-9); tolerance 1e-6."""
    lens = _thin_lens_doe([-40.0, 6.0])
    m = tb.HybridLens(lens, learn={"doe": "all", "thickness": [2]}, replan=False, method="focal",
                      rays_per_sample=0.5, nyquist_safety=1.0, focal_patch_tol=1e-3)
    g = torch.as_tensor(np.random.default_rng(2).standard_normal((12, 12)))

    def loss():
        return (m.psf(0.0, 0.47, 12) * g).sum()
    loss().backward()
    r = m.raywave([0.0], [0.47], 12)
    assert len(r.focal["orders"][0]) > 1
    for i in range(2):
        fd = _fd(loss, m.doe, i, 1e-5)
        assert abs(m.doe.grad[i].item() - fd) < 1e-6 * abs(fd)
    fd = _fd(loss, m.thickness, 0, 1e-6)
    assert abs(m.thickness.grad[0].item() - fd) < 1e-6 * abs(fd)


def test_hybridlens_and_cached_provider_equal_rwwarp_focal_psf():
    """HybridLens.psf and CachedProvider.psfs (focal) give rw.psf(method="focal") on the same patch
    (the same operator; measured 6.4e-16 of the peak, 3.8e-16 on the default plan). On the coarse plan
    (nyquist_safety 1: wave-plane grid 1423, not the default's 2843, 17.5 -> 1.7 s): the property is that the three
    paths build and apply the same operator, whatever its sampling."""
    lens = _thin_lens_doe([-40.0, 6.0])
    ref = rw.psf(lens, (0.0, 1.0), 0.5, size=12, method="focal", focal_precision="double", nyquist_safety=1.0)
    m = tb.HybridLens(lens, learn={"doe": "all"}, method="focal", pixel_values="flux",   # rw.psf's default
                      nyquist_safety=1.0)
    with torch.no_grad():
        got = m.psf((0.0, 1.0), 0.5, 12).numpy()
    assert np.max(np.abs(got - ref.data)) < 1e-11 * ref.data.max()
    prov = dz.CachedProvider(m, [(0.0, 1.0)], 12, lens.sensor.pixel_pitch)
    prov.plans[prov._key(0.5, None)] = {"method": "focal", "centers": [list(ref.center_mm)]}
    with torch.no_grad():
        out = prov.psfs([0.5])[0, 0].numpy()
    assert np.max(np.abs(out - ref.data)) < 1e-11 * ref.data.max()
    assert prov.check_sampling() == 0   # nothing changed: no replan


@pytest.mark.parametrize("method", ["auto", "focal"])
def test_cached_provider_auto_takes_focal_where_the_asm_plan_is_large(method):
    """The F/4 Cooke hybrid 7 deg off axis: the ASM plan is over the auto limit, so "auto" propagates by
    the focal method (the cached entry is per node), and the DOE gradient of a weighted PSF along a random
    direction matches a 4-point central difference (measured 5.5e-10 at h = 0.01 rad; tolerance 5e-9)."""
    lens = rw.load_lens(str(__import__("pathlib").Path(tb.__file__).parent / "configs/lenses/cooke_hybrid.json"))
    d = len(lens.surfaces) - 1
    lens = lens.with_surface(d, profile={**lens.surfaces[d].profile, "coefficients": [-664.9, 0, 0, 0]},
                             thickness=19.9843)
    m = tb.HybridLens(lens, learn={"doe": "all"}, method=method, rays_per_sample=0.5)
    prov = dz.CachedProvider(m, [(0, 7.0)], 16, 0.004)
    out = prov.psfs([0.55])
    assert prov._focal and not prov._cache
    from _gradcheck import directional_error
    w = torch.from_numpy(np.random.default_rng(5).random((1, 1, 16, 16)))
    assert directional_error(lambda: (prov.psfs([0.55]) * w).sum(), m.doe, 0.01) < 5e-9


@pytest.mark.parametrize("preset", ["cpu", "cpu_long", "cpu_lens", "gpu"])
def test_cooke_hybrid_presets_are_at_the_papers_aperture(preset):
    """Every cooke_hybrid preset keeps the lens's own F/4 (EPD 11.75 mm, the file's) and plans the
    wave stage with the focal method where the ASM would sample the converging beam."""
    from torch_bridge.config import build_lens, load_config
    exp = load_config("cooke_hybrid", preset)
    for arm in exp["arms"]:
        lens = build_lens(arm["config"], exp["source"])
        assert lens.entrance_pupil_diameter == pytest.approx(11.75, abs=1e-12)
        assert arm["config"]["optics"]["propagation"] == "auto"


def test_hybridlens_refuses_a_psf_over_the_memory_budget_before_tracing():
    """HybridLens.psf / psf_map check the estimated peak of a recorded source against the budget (issue:
    hostile input, memory) and name the estimate and the knobs; within the budget they run."""
    from rwwarp.wave.plan import MemoryBudgetError
    lens = _thin_lens_doe([-40.0, 6.0])
    m = tb.HybridLens(lens, learn={"doe": "all"}, method="focal", rays_per_sample=0.5)
    with pytest.raises(MemoryBudgetError, match="rays_per_sample") as e:
        m.psf(0.0, 0.55, 12, memory_budget_bytes=2 ** 20)
    assert "GiB" in str(e.value)
    with pytest.raises(MemoryBudgetError):
        m.psf_map([0.0], [0.55], 12, memory_budget_bytes=2 ** 20)
    r = m.raywave([0.0], [0.55], 12)
    need = m.check_budget(r, 2 ** 40)
    assert torch.isfinite(m.psf(0.0, 0.55, 12, memory_budget_bytes=2 * need)).all()


def test_blank_doe_learns_through_the_focal_path_and_is_replanned_once_it_grows():
    """A blank (all-zero) learning DOE planned by the focal method: its gradient exists and matches central
    differences on the frozen plan (the transmission exp(1j alpha phi0) is exact at phi0 = 0, its
    derivative too; measured 1.8e-10 and 2.6e-12 relative at h = 1e-5 on the coarse plan, nyquist_safety 1, as
    the gradient test through orders: 3x faster than the default plan, which measured 2.7e-11 and 2.2e-10); once
    the DOE has grown, check_sampling replans the entry (its first-order focus moved the light)."""
    lens = _thin_lens_doe([0.0, 0.0])
    m = tb.HybridLens(lens, learn={"doe": "all"}, replan=False, method="focal", rays_per_sample=0.5,
                      nyquist_safety=1.0)
    g = torch.as_tensor(np.random.default_rng(3).standard_normal((12, 12)))

    def loss():
        return (m.psf(0.0, 0.47, 12) * g).sum()
    loss().backward()
    assert m.doe.grad is not None and (m.doe.grad != 0).all()
    for i in range(2):
        fd = _fd(loss, m.doe, i, 1e-5)
        assert abs(m.doe.grad[i].item() - fd) < 1e-6 * abs(fd)
    prov = dz.CachedProvider(m, [0.0], 12, lens.sensor.pixel_pitch)
    out = prov.psfs([0.47])
    out.pow(2).sum().backward()
    assert prov.check_sampling() == 0
    with torch.no_grad():
        m.doe[0] = -40.0
    assert prov.check_sampling() == 1
    assert prov.replan_log[-1]["reason"] == "sampling"


def test_live_provider_refuses_a_chunk_over_the_budget():
    """LiveProvider checks each chunk's estimated recorded peak before tracing it."""
    from rwwarp.wave.plan import MemoryBudgetError
    lens = _thin_lens_doe([-40.0, 6.0])
    m = tb.HybridLens(lens, learn={"doe": "all"}, method="focal", rays_per_sample=0.5)
    with pytest.raises(MemoryBudgetError, match="rays_per_sample"):
        dz.LiveProvider(m, [0.0], 12, lens.sensor.pixel_pitch, memory_budget_bytes=2 ** 20).psfs([0.55])
    out = dz.LiveProvider(m, [0.0], 12, lens.sensor.pixel_pitch).psfs([0.55])
    assert out.shape == (1, 1, 12, 12) and torch.isfinite(out).all()
