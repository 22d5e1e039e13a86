"""A propagation method defined and registered only here is differentiable through torch_bridge (issue 25 item 1:
"files touched to add a propagation method <= 3"): its module (here: this file), no other file changed.

The toy method ``toy-fresnel`` is the Fresnel (paraxial) diffraction integral summed directly from the wave-plane
samples to the pixels' Gauss nodes, written below from its equation (it shares no code with rwwarp's methods):

    U(X, Y) = exp(i k z) / (i lambda z) h^2 sum_{x, y} u(x, y) t(x, y) exp(i k ((X - x)^2 + (Y - y)^2) / (2 z)),

``t`` the carrier put back, ``k = 2 pi / lambda`` in the medium; separable, so two matrix products per source.
Its operator has ``forward``, ``adjoint`` and the exact ``distance_derivative``; with ``torch_path = "operator"``
:class:`torch_bridge.HybridLens` differentiates it through the generic Functions of
:mod:`torch_bridge.operator_function`. Checked: the gradients against central finite differences (the field,
the lens's curvature and the sensor distance), the torch path against rwwarp's own ``rw.psf`` of the method, the
toy against the Rayleigh-Sommerfeld sum on axis (where the paraxial kernel holds), the generic Functions on the
ASM's operator against rwwarp's :class:`~rwwarp.wave.propagate.SensorPropagator`, and the errors for what an
operator lacks.
"""
from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np
import pytest

torch = pytest.importorskip("torch")

import rwwarp as rw
import torch_bridge as tb
from rwwarp.lens import Lens, Sensor, Surface
from rwwarp.wave import methods
from _gradcheck import central_difference as _fd  # noqa: E402
from rwwarp.wave.methods.asm import plan_window
from rwwarp.wave.raywave import RayWave
from torch_bridge.operator_function import OperatorApply, operator_propagate


class _FresnelOperator:
    """The Fresnel sum (module docstring) of a RayWave batch over ``z`` mm, numpy, float64."""

    def __init__(self, r, z):
        self.z = float(z)
        n, h = r.plan.n_grid, r.plan.pitch_mm
        nx, ny = methods.gauss_nodes_xy(r)
        self.k = 2 * np.pi * r.n_after / r.lam_mm                                    # (S,) rad/mm
        lam = r.lam_mm / r.n_after
        xs = r.origin[:, 0, None] + h * np.arange(n)                                  # (S, n)
        ys = r.origin[:, 1, None] + h * np.arange(n)
        self.t = np.exp(2j * np.pi * (r.carrier[:, 0, None, None] * xs[:, None, :]
                                      + r.carrier[:, 1, None, None] * ys[:, :, None]))
        self.dx2 = (nx[:, :, None] - xs[:, None, :]) ** 2                            # (S, Mx, n)
        self.dy2 = (ny[:, :, None] - ys[:, None, :]) ** 2                            # (S, My, n)
        k, z = self.k[:, None, None], self.z
        self.kx, self.ky = np.exp(1j * k * self.dx2 / (2 * z)), np.exp(1j * k * self.dy2 / (2 * z))
        self.c = (np.exp(1j * self.k * z) / (1j * lam * z) * h * h)[:, None, None]

    def forward(self, field):
        return self.c * (self.ky @ (np.asarray(field) * self.t) @ np.swapaxes(self.kx, 1, 2))

    def adjoint(self, grad):
        g = np.conj(self.c) * np.asarray(grad)
        return np.conj(self.t) * (np.swapaxes(np.conj(self.ky), 1, 2) @ g @ np.conj(self.kx))

    def distance_derivative(self, field):
        k, z = self.k[:, None, None], self.z
        f = np.asarray(field) * self.t
        dkx, dky = -1j * k * self.dx2 / (2 * z * z) * self.kx, -1j * k * self.dy2 / (2 * z * z) * self.ky
        return ((1j * k - 1.0 / z) * self.forward(field)
                + self.c * (dky @ f @ np.swapaxes(self.kx, 1, 2) + self.ky @ f @ np.swapaxes(dkx, 1, 2)))


class _ToyFresnel(methods.Propagation):
    """The toy method: planned on the ASM's windows; its field takes the DOE before the operator, which the bridge
    then applies in torch (``doe_in_propagator = False``); intensities only (no ``forward_pair``)."""

    name = "toy-fresnel"
    torch_path = "operator"
    doe_in_propagator = False

    def plan(self, ctx):
        p = plan_window(ctx)
        p.plan = replace(p.plan, method=self.name)
        return p

    def estimate(self, plan, n_sources, size, gauss_nodes):
        m, n = int(size) * int(gauss_nodes), plan.n_grid
        return {"memory_bytes": int(n_sources * (n * n + 2 * m * n + m * m) * 16), "flops": 16.0 * m * n * (n + m)}

    def operator(self, r, distance_mm=None, precision="double"):
        return _FresnelOperator(r, float(r.z_sensor - r.z_plane) if distance_mm is None else distance_mm)

    def pixels(self, r, field, precision="double", to_host=True):
        from rwwarp.wave.focal import pixel_power
        if r.pixel_values != "intensity":
            raise ValueError("toy-fresnel: pixel_values='intensity' only")
        field = r.wave_stepped(np.asarray(field))
        phi0, scale = r.doe_phase()
        if phi0 is not None:
            field = field * np.exp(1j * np.asarray(scale)[:, None, None] * phi0)
        return pixel_power(self.operator(r).forward(field), r.gauss_nodes, r.pixel, r.size)


@pytest.fixture()
def toy():
    methods.register(_ToyFresnel)
    yield _ToyFresnel.name
    methods.unregister(_ToyFresnel.name)


def _singlet():
    """A BK7 singlet (f ~ 10 mm) at F/50 behind its stop (as tests/rwwarp/test_method_registry.py): grids of
    18-60 samples."""
    surfs = [Surface(type="aperture", semi_diameter=0.1, shape="circle", stop=True, thickness=0.1),
             Surface(type="standard", radius=6.0, material="N-BK7", semi_diameter=2.0, thickness=1.0),
             Surface(type="standard", radius=-30.0, semi_diameter=2.5, thickness=9.0)]
    return Lens(surfs, Sensor(0.002, (4000, 4000)), wavelengths_um=[0.55])




def test_the_toy_operator_is_linear_adjoint_and_its_distance_derivative_is_the_difference(toy):
    """The toy's own operator (what the generic Functions rely on): <A x, y> = <x, A^H y> (measured 7.3e-16 relative;
    tolerance 1e-14) and d forward / dz against a central difference over +-0.1 nm (truncation ~ (k h)^2 / 6 =
    2e-7 of the value; measured 2.1e-7 of the largest value; tolerance 1e-6)."""
    r = RayWave(_singlet(), [(0.0, 10.0)], [0.55], 6, 0.002, method=toy, pixel_values="intensity")
    op = methods.get(toy).operator(r)
    n, m = r.plan.n_grid, 6 * r.gauss_nodes
    rng = np.random.default_rng(1)
    x = rng.normal(size=(1, n, n)) + 1j * rng.normal(size=(1, n, n))
    y = rng.normal(size=(1, m, m)) + 1j * rng.normal(size=(1, m, m))
    lhs, rhs = np.vdot(y, op.forward(x)), np.vdot(op.adjoint(y), x)
    assert abs(lhs - rhs) < 1e-14 * abs(lhs)
    u, z, h = r.field_array(), op.z, 1e-7
    fd = (_FresnelOperator(r, z + h).forward(u) - _FresnelOperator(r, z - h).forward(u)) / (2 * h)
    got = op.distance_derivative(u)
    assert np.max(np.abs(got - fd)) < 1e-6 * np.max(np.abs(got))


def test_generic_functions_field_and_distance_gradients_match_finite_differences(toy):
    """OperatorApply + NodePixels (operator_propagate) on the toy: a weighted sum of the pixel powers of a random
    field, differentiated along random directions of Re u, Im u and the distance, against the 4-point central
    difference. The loss is quadratic in the field: that difference is exact up to rounding, measured 2.1e-12 /
    4.1e-12 (tolerance 1e-10). In z the loss is nearly stationary (a focus), so the difference's rounding
    ~ eps L / (h dL/dz) meets its h^4 truncation: measured 3.2e-6, 2.6e-8, 5.5e-10, 4.4e-9 at h = 1e-3, 3e-4, 1e-4,
    1e-5 mm; at h = 1e-4 tolerance 5e-9."""
    from _gradcheck import directional_error
    r = RayWave(_singlet(), [(0.0, 10.0), (0.0, 0.0)], [0.55, 0.55], 6, 0.002, method=toy,
                pixel_values="intensity")
    n = r.plan.n_grid
    rng = np.random.default_rng(2)
    re = torch.from_numpy(rng.normal(size=(2, n, n))).requires_grad_()
    im = torch.from_numpy(rng.normal(size=(2, n, n))).requires_grad_()
    d = torch.tensor(float(r.z_sensor - r.z_plane), dtype=torch.float64, requires_grad=True)
    w = torch.from_numpy(rng.random((2, 6, 6)))

    def loss():
        return (operator_propagate(torch.complex(re, im), d.expand(2), r) * w).sum()
    errs = [directional_error(loss, re, 1e-3), directional_error(loss, im, 1e-3, seed=1)]
    assert max(errs) < 1e-10, errs
    err = directional_error(loss, d, 1e-4)
    assert err < 5e-9, err
    assert d.grad is not None and torch.isfinite(d.grad) and float(d.grad) != 0.0


def test_hybridlens_differentiates_the_toy_method(toy):
    """HybridLens(method=toy): its PSF is rwwarp's own rw.psf of the toy (the same operator: measured 2e-16 of the
    peak; tolerance 1e-12), and its gradients in a curvature (through the trace, the field's adjoint) and the
    sensor distance (the operator's distance derivative) match central differences on the frozen plan. Measured:
    curvature 1.9e-6 at h = 1e-7 mm^-1 (2.9e-5 at 1e-8, 9.5e-6 at 1e-9: the box splat's kinks; the ASM path
    on the same lens measures the same, 2.1e-6 / 3.6e-5 / 5.8e-5), tolerance 1e-5; distance 4.6e-12 at h = 1e-6 mm
    (2e-9 at 1e-5), tolerance 1e-9."""
    lens = _singlet()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref = rw.psf(lens, (0.0, 5.0), 0.55, size=8, method=toy, pixel_values="intensity")
    m = tb.HybridLens(lens, learn={"curvature": [1], "thickness": [2]}, replan=False, method=toy,
                      pixel_values="intensity")
    g = torch.as_tensor(np.random.default_rng(1).standard_normal((8, 8)))

    def psf():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return m.psf((0.0, 5.0), 0.55, 8, center_mm=ref.center_mm)

    def loss():
        return (psf() * g).sum()
    with torch.no_grad():
        got = psf().numpy()
    assert np.max(np.abs(got - ref.data)) < 1e-12 * ref.data.max()
    loss().backward()
    assert m.raywave([(0.0, 5.0)], [0.55], 8).plan.method == toy
    for p, h, tol in ((m.curvature, 1e-7, 1e-5), (m.thickness, 1e-6, 1e-9)):
        fd = _fd(loss, p, 0, h)
        assert abs(p.grad[0].item() - fd) < tol * abs(fd), (p.grad, fd)


def test_the_toy_meets_the_rayleigh_sommerfeld_sum_on_axis(toy):
    """On axis at F/50 the beam is 0.2 mm wide 9 mm from the sensor: the Fresnel kernel's phase error
    k r^4 / (8 z^3) is ~2e-4 rad over it and its obliquity ~1 - 1e-4, so the toy's PSF meets that of ``direct`` (the
    Rayleigh-Sommerfeld sum over the same samples, rwwarp's code) to 1.1e-4 of the peak (measured, at
    nyquist_safety 2, 4 and 8 alike); tolerance 3e-4. (Both sums differ from the ASM's by the same 1.3e-2 ->
    5.9e-3 as the sampling refines: the plain sums' error at the aperture's edge, as in test_method_registry.)"""
    lens = _singlet()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref = rw.psf(lens, 0.0, 0.55, size=16, method="direct", pixel_values="intensity")
        got = rw.psf(lens, 0.0, 0.55, size=16, method=toy, pixel_values="intensity", center_mm=ref.center_mm)
    assert np.max(np.abs(got.data - ref.data)) < 3e-4 * ref.data.max()


def test_generic_functions_on_the_asm_operator_equal_the_sensor_propagator():
    """The generic Functions over the ASM's registered operator (AsmOperator: PointPropagator; the distance
    gradient its fused band reduction without the constant phase's term) against rwwarp's other ASM implementation
    (SensorPropagator: forward, and ``distance_adjoint`` for the field and distance gradients) on the same field,
    intensities: PSF measured 2.1e-16 of the peak, field gradient 5.0e-16 of the largest, distance gradient 1.5e-15
    (with the exact derivative, the constant phase's term included, it was 7.5e-13: that term, 2 pi / lambda times
    the others, cancels only to rounding); tolerances 2e-15 / 5e-15 / 1.5e-14."""
    from rwwarp.wave.propagate import SensorPropagator
    r = RayWave(_singlet(), [(0.0, 10.0)], [0.55], 6, 0.002, method="asm", pixel_values="intensity")
    u0 = r.field_array()
    w = np.random.default_rng(4).random((1, 6, 6))
    u = torch.from_numpy(u0.copy()).requires_grad_()
    d = torch.full((1,), float(r.z_sensor - r.z_plane), dtype=torch.float64, requires_grad=True)
    p = operator_propagate(u, d, r)
    (p * torch.from_numpy(w)).sum().backward()
    op = SensorPropagator("cpu", r.sensor_geometry())
    ref = np.asarray(op.forward(u0).get())
    gf, _, gd = op.distance_adjoint(w, u0)
    gf = np.asarray(gf.get())
    assert p.shape == (1, 6, 6)
    e = (np.max(np.abs(p.detach().numpy() - ref)) / ref.max(), np.max(np.abs(u.grad.numpy() - gf)) / np.max(np.abs(gf)),
         abs(float(d.grad[0]) - gd[0]) / abs(gd[0]))
    assert e[0] < 2e-15 and e[1] < 5e-15 and e[2] < 1.5e-14, e


class _NoDistance:
    """An operator without a distance derivative (the ASM's before issue 25's change)."""

    def __init__(self, op):
        self.op = op

    def forward(self, f):
        return self.op.forward(f)

    def adjoint(self, g):
        return self.op.adjoint(g)

    def distance_derivative(self, f):
        raise NotImplementedError("not formed")


def test_what_an_operator_lacks_is_named(toy):
    """A distance needing a gradient through an operator without a distance derivative: an error naming the
    method at backward (NotImplementedError raised there) or at forward (no such method); without a distance
    gradient it runs. pixel_values 'flux' without forward_pair: an error naming the method."""
    r = RayWave(_singlet(), [(0.0, 10.0)], [0.55], 6, 0.002, method=toy, pixel_values="intensity")
    u = torch.from_numpy(r.field_array()).requires_grad_()
    d = torch.full((1,), float(r.z_sensor - r.z_plane), dtype=torch.float64, requires_grad=True)
    op = _NoDistance(methods.get(toy).operator(r))
    out = OperatorApply.apply(u, d, op, False, None, "no-dz")
    with pytest.raises(NotImplementedError, match=r"'no-dz': the distance needs a gradient.*not formed"):
        out.abs().sum().backward()

    class _Bare:
        forward, adjoint = op.forward, op.adjoint
    with pytest.raises(NotImplementedError, match=r"'bare'.*no distance_derivative"):
        OperatorApply.apply(u, d, _Bare(), False, None, "bare")
    v = OperatorApply.apply(u, d.detach(), op, False, None, "no-dz")
    v.abs().sum().backward()
    assert u.grad is not None and torch.all(torch.isfinite(u.grad))
    rf = RayWave(_singlet(), [(0.0, 10.0)], [0.55], 6, 0.002, method=toy, pixel_values="flux")
    with pytest.raises(ValueError, match=r"'toy-fresnel': pixel_values='flux' needs its operator's forward_pair"):
        operator_propagate(torch.from_numpy(rf.field_array()), None, rf)
