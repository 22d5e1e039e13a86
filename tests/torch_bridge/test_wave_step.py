"""The wave step (rwwarp.wave.wave_step, issue 27) in torch: gradients through it and the DOE behind it against
central finite differences of the same float64 pipeline, and the HybridLens path against rwwarp.psf."""
import numpy as np
import pytest

torch = pytest.importorskip("torch")

from rwwarp.lens import Lens, Sensor, Surface
from rwwarp.psf import RayWave
from rwwarp.trace import as_field_list
from torch_bridge.operator_function import operator_propagate
from torch_bridge.wave_step import WaveStep, wave_step


def small_scene(d2=10.0, a=1.0, f=50.0, coefficients=(0.0, 3.0), semi_mm=None):
    """Round stop a (mm), ideal thin lens f, a radial DOE d2 before the sensor at the focus (N_F ~ 9); the DOE's
    clear radius ``semi_mm`` (None: 1.5 beam radii)."""
    rb = a * d2 / f
    surfs = [Surface(type="aperture", semi_diameter=a, shape="circle", stop=True),
             Surface(type="thin_lens", focal_length=f, semi_diameter=1.2 * a, thickness=f - d2),
             Surface(type="doe", semi_diameter=1.5 * rb if semi_mm is None else semi_mm, thickness=d2,
                     material="1.5/1e9",
                     profile={"kind": "even_poly", "coefficients": list(coefficients), "norm_radius": rb})]
    return Lens(surfs, Sensor(0.006, (1000, 1000)), wavelengths_um=[0.55])


@pytest.fixture(scope="module")
def rw_two_step():
    rw = RayWave(small_scene(), as_field_list([0.0]), [0.55], 16, 0.006, method="two-step")
    # the reduced distance z1 R / (z1 + R) = 40 * 10 / 50 mm, stretched for the rim ray's obliquity 1 / m_z^3 on
    # the axis (rwwarp.wave.wave_step, "Obliquity"), m_z = f / sqrt(a^2 + f^2) (measured: 2.7e-8 relative, the pilot rim extrapolated)
    assert rw.plan.method == "asm" and rw.wave_step[0] == pytest.approx(8.0 * (1 + (1.0 / 50.0) ** 2) ** 1.5, rel=1e-6)
    from rwwarp.wave.wave_step import step_nodes
    assert step_nodes(rw) == 1         # on the axis the rim's distance is one number: the isotropic step
    return rw


@pytest.fixture(scope="module")
def rw_two_step_off_axis():
    # 10 deg, stop 2 mm (NA 0.04), a quadratic DOE of clear radius 9 mm (the beam lands 7.05 mm off its axis): the
    # rim's stretch varies around the rim (8.10 .. 8.44 mm), so the step is rim-resolved (rwwarp.wave.wave_step,
    # "Rim-resolved step"): two propagation rows, the transfer interpolated between two distances
    rw = RayWave(small_scene(a=2.0, coefficients=(2.0, 0.0), semi_mm=9.0), as_field_list([10.0]), [0.55], 16, 0.006,
                 method="two-step")
    from rwwarp.wave.wave_step import step_nodes
    assert int(rw.wave_step_rim[0, 3]) == 2 and step_nodes(rw) == 2
    return rw


@pytest.fixture(params=["on_axis", "rim_resolved"])
def stepped(request, rw_two_step, rw_two_step_off_axis):
    return rw_two_step if request.param == "on_axis" else rw_two_step_off_axis


def test_gradients_through_the_wave_step_and_the_doe_match_finite_differences(stepped):
    rw = stepped
    rng = np.random.default_rng(3)
    u0 = torch.from_numpy(rw.field_array().copy())
    phi_np, _ = rw.doe_phase()
    phi0 = torch.from_numpy(phi_np.copy())
    wts = torch.from_numpy(rng.uniform(0.5, 1.5, (1, rw.size, rw.size)))

    def loss(u, p):
        return (wts * operator_propagate(WaveStep.apply(u, rw), None, rw, phi0=p)).sum()

    u = u0.clone().requires_grad_(True)
    p = phi0.clone().requires_grad_(True)
    L = loss(u, p)
    gu, gp = torch.autograd.grad(L, (u, p))
    n = u0.shape[-1]
    yy, xx = np.meshgrid(np.linspace(-1, 1, n), np.linspace(-1, 1, n), indexing="ij")
    dp = torch.from_numpy((0.3 * xx + 0.2 * yy * yy - 0.1 * xx * yy)[None])            # a smooth phase change (rad)
    du = torch.from_numpy((rng.normal(size=(1, n, n)) + 1j * rng.normal(size=(1, n, n))) * 0.01 * np.abs(u0.numpy()).max())
    with torch.no_grad():
        for eps, (a, b), (da, db), g, d in ((1e-4, (u0, phi0), (0 * du, dp), gp, dp),
                                            (1e-4, (u0, phi0), (du, 0 * dp), gu, du)):
            fd = (loss(a + eps * da, b + eps * db) - loss(a - eps * da, b - eps * db)) / (2 * eps)
            an = torch.real(torch.sum(torch.conj(g) * d)) if g.is_complex() else torch.sum(g * d)
            # float64 pipeline, central differences (O(eps^2)): measured 4.2e-10 (phase), 2.3e-9 (field) on the
            # axis; rim-resolved (10 deg): 1.8e-10 (phase), 1.0e-9 (field)
            print(f"{rw.fields[0]}: analytic {float(an):.12e} fd {float(fd):.12e} rel {abs(float(an) / float(fd) - 1):.2e}")
            assert float(an) == pytest.approx(float(fd), rel=2e-8)


def test_wave_step_is_linear_with_its_adjoint(stepped):
    # <A u, g> = <u, A^H g> for the wave step's forward and backward (torch convention); rim-resolved too
    rw = stepped
    rng = np.random.default_rng(0)
    n = rw.plan.n_grid
    u = torch.from_numpy(rng.normal(size=(1, n, n)) + 1j * rng.normal(size=(1, n, n))).requires_grad_(True)
    g = torch.from_numpy(rng.normal(size=(1, n, n)) + 1j * rng.normal(size=(1, n, n)))
    y = WaveStep.apply(u, rw)
    (gu,) = torch.autograd.grad(y, u, grad_outputs=g)
    lhs = torch.sum(torch.conj(g) * y.detach())
    rhs = torch.sum(torch.conj(gu) * u.detach())
    assert complex(lhs) == pytest.approx(complex(rhs), rel=1e-10)


def test_a_plan_without_the_step_leaves_the_field_alone():
    rw = RayWave(small_scene(), as_field_list([0.0]), [0.55], 16, 0.006, method="asm")
    u = torch.ones(1, rw.plan.n_grid, rw.plan.n_grid, dtype=torch.complex128)
    assert wave_step(u, rw) is u


@pytest.mark.filterwarnings("ignore::rwwarp.errors.PatchWarning")   # 16 px keep 87-90 %: enough to compare
def test_hybrid_lens_two_step_equals_rwwarp_psf_and_differs_from_one_step():
    import rwwarp as rw
    import torch_bridge as tb
    lens = small_scene()
    ref = rw.psf(lens, 0.0, 0.55, size=16, method="two-step").data
    one = rw.psf(lens, 0.0, 0.55, size=16, method="asm").data
    hl = tb.HybridLens(lens, method="two-step", learn={"doe": "all"})
    p = hl.psf(0.0, 0.55, 16).detach().numpy()
    # the same plan and arithmetic: measured ~1e-15 of the peak
    assert np.max(np.abs(p - ref)) < 1e-9 * ref.max()
    # the step matters here (N_F ~ 9: estimate 0.27): the test cannot pass without it
    assert np.max(np.abs(p - one)) > 1e-2 * ref.max()


@pytest.mark.filterwarnings("ignore::rwwarp.errors.PatchWarning")
def test_hybrid_lens_gradients_through_the_two_step_path_match_finite_differences():
    import torch_bridge as tb
    hl = tb.HybridLens(small_scene(), method="two-step", replan=False, learn={"doe": "all", "focal_length": "all"})
    w = torch.from_numpy(np.random.default_rng(2).random((16, 16)))

    def loss():
        return (hl.psf(0.0, 0.55, 16) * w).sum()

    rw0 = hl.raywave([0.0], [0.55], 16)
    assert rw0.wave_step[0] > 0     # the planned path has the step
    hl.zero_grad()
    loss().backward()
    for name, k, h in (("doe", 1, 1e-3), ("focal_length", 0, 1e-3)):
        p = getattr(hl, name)
        g = p.grad.reshape(-1)[k].item()
        x0 = p.data.reshape(-1)[k].item()
        vals = {}
        with torch.no_grad():
            for m in (-2, -1, 1, 2):
                p.data.view(-1)[k] = x0 + m * h
                vals[m] = loss().item()
            p.data.view(-1)[k] = x0
        fd = (8.0 * (vals[1] - vals[-1]) - (vals[2] - vals[-2])) / (12.0 * h)   # O(h^4) central difference
        assert g == pytest.approx(fd, rel=1e-7), (name, g, fd)   # measured 8e-9 (doe), 7e-9 (focal_length)
