"""Pixel values through torch (issue 27 item 3): the autograd Functions give the z-flux by default and
``|U|^2`` by name, equal to rwwarp's, with gradients that pass gradcheck (finite differences) on tiny
sizes. The independent references of the flux itself are in tests/rwwarp/test_flux.py."""
from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

torch = pytest.importorskip("torch")

import rwwarp as rw
import torch_bridge as tb
from rwwarp.lens import Lens, Sensor, Surface
from rwwarp.wave.plan import Plan
from rwwarp.psf import RayWave
from torch_bridge.functions import FocalPropagate
from torch_bridge.operator_function import operator_propagate


def _thin_lens():
    """A 0.5 mm square-aperture f = 20 mm thin lens with a DOE 1 mm behind it (tiny sampling)."""
    prof = {"kind": "even_poly", "norm_radius": 0.25, "coefficients": [-3.0, 1.0]}
    surfs = [Surface(type="aperture", semi_diameter=0.25, shape="square", stop=True),
             Surface(type="thin_lens", focal_length=20.0, semi_diameter=1.0, shape="square", thickness=1.0),
             Surface(type="doe", semi_diameter=1.0, shape="square", thickness=19.0, profile=prof)]
    return Lens(surfs, Sensor(0.01, (4000, 4000)), wavelengths_um=[0.55])


@pytest.fixture(scope="module", params=["flux", "intensity"])
def small_rw(request):
    """Two off-axis sources at 20 deg and 25 deg (the obliquity matters) on a tiny explicit plan."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return RayWave(_thin_lens(), [(0.0123, 20.0), (25.0, -0.013)], [0.55, 0.55], 6, 0.01,
                       plan=Plan(0.0291, 20, 40, 19), requires_grad=True, pixel_values=request.param)


def test_propagate_flux_gradcheck(small_rw):
    """The ASM's propagation (the generic operator path over AsmOperator) in both conventions: field, DOE phase
    and distance pass gradcheck."""
    rw_ = small_rw
    torch.manual_seed(0)
    n = rw_.plan.n_grid
    field = torch.randn(rw_.nsrc, n, n, dtype=torch.complex128, requires_grad=True)
    phi0 = (2 * math.pi * torch.rand(rw_.nsrc, n, n, dtype=torch.float64)).requires_grad_()
    dist = torch.full((rw_.nsrc,), rw_.z_sensor - rw_.z_plane, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda f, p, d: operator_propagate(f, d, rw_, phi0=p), (field, phi0, dist),
                                    eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=True)


def test_propagate_pixel_values_by_name_against_rwwarp(small_rw):
    """The ASM's torch path equals rwwarp's SensorPropagator of the same geometry and pixel values; flux and intensity
    differ by the obliquity (the sources are 20-25 deg off axis)."""
    from rwwarp.wave.propagate import SensorPropagator
    rw_ = small_rw
    torch.manual_seed(1)
    n = rw_.plan.n_grid
    field = torch.randn(rw_.nsrc, n, n, dtype=torch.complex128)
    got = operator_propagate(field, None, rw_).numpy()
    ref = np.asarray(SensorPropagator("cpu", rw_.sensor_geometry()).forward(field.numpy()).get())
    assert np.max(np.abs(got - ref)) < 1e-13 * np.abs(ref).max()
    other = "intensity" if rw_.pixel_values == "flux" else "flux"
    alt = np.asarray(SensorPropagator("cpu", rw_.sensor_geometry().with_(pixel_values=other))
                     .forward(field.numpy()).get())
    assert np.linalg.norm(alt - ref) > 1e-3 * np.linalg.norm(ref)


@pytest.fixture(scope="module")
def focal_rw():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return RayWave(_thin_lens(), [(0.0, 15.0)], [0.55], 6, 0.01, method="focal", rays_per_sample=0.5,
                       nyquist_safety=1.0)


def test_focal_propagate_flux_gradients(focal_rw):
    """FocalPropagate with the flux (the RayWave's default): its field and distance gradients against
    finite differences; its forward equals :meth:`RayWave.focal_intensity` (double)."""
    r = focal_rw
    assert r.pixel_values == "flux" and r.plan.method == "focal"
    n = r.plan.n_grid
    torch.manual_seed(2)
    field = torch.randn(1, n, n, dtype=torch.complex128, requires_grad=True)
    dist = torch.full((1,), r.z_sensor - r.z_plane, dtype=torch.float64, requires_grad=True)
    fac = r.doe_orders_factor()          # FocalPropagate takes the field with the DOE's orders applied
    fac = 1.0 if fac is None else torch.from_numpy(fac)
    out = FocalPropagate.apply(field.detach() * fac, dist, r).detach().numpy()
    ref = r.focal_intensity(field.detach().numpy(), precision="double")
    assert np.max(np.abs(out - ref)) < 1e-13 * np.abs(ref).max()
    # FocalPropagate frees its saved fields after one backward (gradcheck calls it twice): a directional
    # 4-point difference instead (measured 5.9e-11, 2.0e-10, 1.7e-10 for Re, Im and z; tolerance 2e-9)
    from _gradcheck import directional_error
    w = torch.from_numpy(np.random.default_rng(3).random((1, 6, 6)))
    re, im = field.detach().real.clone().requires_grad_(), field.detach().imag.clone().requires_grad_()
    loss = lambda: (FocalPropagate.apply(torch.complex(re, im), dist, r) * w).sum()
    errs = [directional_error(loss, re, 1e-3), directional_error(loss, im, 1e-3, seed=1),
            directional_error(loss, dist, 1e-4)]
    assert max(errs) < 2e-9, errs


@pytest.mark.parametrize("pixel_values", ["flux", "intensity"])
def test_hybridlens_psf_equals_rwwarp_psf_by_name(pixel_values):
    """HybridLens(pixel_values=...) gives rw.psf(pixel_values=...) on the same patch (both methods' own
    operators; measured ~1e-13 relative), and the two conventions differ at 20 deg."""
    lens = _thin_lens()
    for method in ("asm", "focal"):
        ref = rw.psf(lens, (0.0, 20.0), 0.55, size=8, method=method, focal_precision="double",
                     pixel_values=pixel_values)
        m = tb.HybridLens(lens, method=method, pixel_values=pixel_values)
        with torch.no_grad():
            got = m.psf((0.0, 20.0), 0.55, 8, center_mm=ref.center_mm).numpy()
        assert np.max(np.abs(got - ref.data)) < 1e-9 * ref.data.max(), method


def test_hybridlens_rejects_unknown_pixel_values():
    with pytest.raises(ValueError, match="pixel_values"):
        tb.HybridLens(_thin_lens(), pixel_values="power")


def _obscured_singlet():
    """An aspheric BK7 singlet behind a 0.3 mm circular stop whose central rectangular obscuration (half widths
    0.28 x 0.1 mm) leaves strips about a pupil cell wide at the rim: rays there have no valid neighbour on
    one side or the other along x, so their tube has no area (kernels/splat.py, tube_area_kernel)."""
    prof = {"kind": "even_poly", "norm_radius": 0.3, "coefficients": [-2.0, 1.0, 0.5]}
    surfs = [Surface(type="aperture", semi_diameter=0.3, shape="circle", stop=True, thickness=0.2,
                     obscuration={"shape": "rectangle", "half_x": 0.28, "half_y": 0.1}),
             Surface(type="standard", radius=12.0, conic=-0.8, aspheric=[1e-4, 2e-6], material="N-BK7",
                     semi_diameter=1.0, thickness=1.0),
             Surface(type="standard", radius=-40.0, semi_diameter=1.0, thickness=0.5),
             Surface(type="doe", semi_diameter=0.6, shape="square", thickness=17.5, profile=prof)]
    return Lens(surfs, Sensor(0.004, (1000, 1000)), wavelengths_um=[0.55])


def test_flux_curvature_gradients_with_lone_rays_are_finite_and_match_differences():
    """Valid rays whose ray tube has no area (no valid neighbour along u or v) deposit nothing; the splat's
    adjoint of their amplitude sqrt(q A) and of its division by the box area was 0/0 = NaN, which with
    pixel_values "flux" (amplitude / sqrt(cos theta), theta from the ray direction) flowed through the
    tracer's refraction adjoints into the curvature gradients (the cooke_hybrid gpu preset's NaN). Now the
    curvature gradients of a HybridLens PSF loss are finite and equal 4-point central differences."""
    from _gradcheck import directional_error
    m = tb.HybridLens(_obscured_singlet(), learn={"curvature": "all"}, method="asm", pixel_values="flux",
                      plan=Plan(0.0082, 75, 150, 72), replan=False)
    fld = (0.0123, 0.3)   # off axis and asymmetric: no ray-box edge sits on a cell boundary
    r = m.raywave([fld], [0.55], 8)
    _, rays = r.field()
    side = r.plan.ray_grid
    v = np.pad(rays.valid.numpy().reshape(side, side).astype(bool), 1)
    inner = v[1:-1, 1:-1]
    lone = inner & ~((v[1:-1, 2:] | v[1:-1, :-2]) & (v[2:, 1:-1] | v[:-2, 1:-1]))
    assert lone.sum() >= 10, "the scene must have valid rays with no valid neighbour along u or v"
    w = torch.from_numpy(np.random.default_rng(0).random((8, 8)))
    loss = lambda: (m.psf(fld, 0.55, 8) * w).sum()
    m.zero_grad()
    loss().backward()
    assert torch.isfinite(m.curvature.grad).all(), m.curvature.grad
    # two random directions span both curvatures; measured at h = 1e-5 1/mm: 2.0e-10 and 1.15e-9 (seeds 2, 3:
    # 2.4e-10, 1.7e-10; at 1e-4 up to 5.9e-9, truncation; at 1e-6 up to 1.6e-8, rounding): 1e-8 is 9x the worst
    errs = [directional_error(loss, m.curvature, 1e-5, seed=s) for s in (0, 1)]
    assert max(errs) < 1e-8, errs
