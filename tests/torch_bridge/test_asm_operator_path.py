"""The ASM through the generic operator path (issue 25 item 1):
:func:`torch_bridge.operator_function.operator_propagate` over :class:`rwwarp.wave.methods.asm.AsmOperator` (PointPropagator; the DOE phase applied in torch as
``exp(1j alpha phi0)``) against an independent reference written here from rwwarp's other ASM implementation,
:class:`rwwarp.wave.propagate.SensorPropagator` (its own node reduction and adjoint kernels, the DOE phase applied
inside its pad kernel, its distance gradient a band reduction): the PSF, and the gradients of the DOE phase, of every
lens parameter (curvatures, thin-lens power, vertex z) and of the learning sensor distance, chained by hand through
the traced field's TraceSplat. That reference is what the former ASM autograd Function (``Propagate``) computed.
Both conventions (flux, intensity), with and without a DOE, untiled and in spatial tiles; plus the pieces the
ASM's operator adds (``forward_pair`` / ``adjoint_pair`` against the flux, the phase-free distance derivative against
central differences)."""
from __future__ import annotations

import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from rwwarp.psf import RayWave
from rwwarp.trace import COLUMNS as COL
from rwwarp.wave.methods import get as get_method
from rwwarp.wave.plan import Plan
from rwwarp.wave.propagate import SensorPropagator
from torch_bridge.functions import doe_scale, trace_splat
from torch_bridge.operator_function import operator_propagate

sys.path.insert(0, str(Path(__file__).parent))
from test_functions import singlet_doe  # noqa: E402  (the aspheric singlet with a DOE behind it)


@pytest.fixture(scope="module", params=["intensity", "flux"])
def rw_(request):
    """Two off-axis sources of the singlet on a small explicit plan (8 x 8 pixels of 4 um)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return RayWave(singlet_doe(), [(0.0123, 1.3), (0.021, -1.1)], [0.55, 0.45], 8, 0.004,
                       plan=Plan(0.004, 40, 96, 37), requires_grad=True, pixel_values=request.param)


def _new(rw, with_doe, tile):
    """The operator path: PSF (unnormalised pixel values), table gradient, DOE-phase gradient of sum(w * psf)."""
    table = torch.from_numpy(rw.tracer.params_np.copy()).requires_grad_()
    phi0 = torch.from_numpy(rw.doe_phase()[0].copy()).requires_grad_() if with_doe else None
    u = trace_splat(table, rw)
    d = (table[-1, COL.z] - table[rw.plane, COL.z]).expand(rw.nsrc)
    p = operator_propagate(u, d, rw, phi0=phi0, tile_px=tile)
    (p * _weights(p.shape)).sum().backward()
    return p.detach().numpy(), table.grad.numpy().copy(), None if phi0 is None else phi0.grad.numpy().copy()


def _reference(rw, with_doe):
    """The same from SensorPropagator: forward, ``distance_adjoint`` (field, DOE phase, distance gradients), the
    field gradient taken back through TraceSplat by autograd, the distance's by the chain rule of
    ``d = z_sensor - z_plane``."""
    table = torch.from_numpy(rw.tracer.params_np.copy()).requires_grad_()
    u = trace_splat(table, rw)
    f = u.detach().numpy()
    phi0 = rw.doe_phase()[0].copy() if with_doe else None
    op = SensorPropagator("cpu", rw.sensor_geometry(doe_scale(rw) if with_doe else None))
    psf = np.asarray(op.forward(f, phi0).get())
    w = _weights(psf.shape).numpy()
    gf, gp, gd = op.distance_adjoint(w, f, phi0)
    u.backward(torch.from_numpy(np.asarray(gf.get())))
    g = table.grad.numpy().copy()
    g[-1, COL.z] += gd.sum()
    g[rw.plane, COL.z] -= gd.sum()
    return psf, g, None if gp is None else np.asarray(gp.get())


def _weights(shape):
    return torch.from_numpy(np.random.default_rng(3).random(tuple(shape)))


def _rel(a, b):
    return float(np.max(np.abs(a - b)) / np.max(np.abs(b)))


@pytest.mark.parametrize("with_doe", [False, True])
@pytest.mark.parametrize("tile", [None, 3])
def test_psf_and_gradients_equal_the_sensor_propagator_reference(rw_, with_doe, tile):
    """Measured (intensity and flux, with and without a DOE, untiled and in ragged 3 px tiles; CPU), relative to the
    reference's largest value: PSF <= 3.7e-16, DOE-phase gradient <= 2.3e-15, sensor-z gradient (the learning
    distance) <= 3.7e-15 of itself, the curvature / conic / asphere / power entries <= 4.1e-16 of the largest table
    entry, the surfaces' vertex z (the thicknesses) <= 1.3e-13 of the largest entry (<= 1.2e-11 of their own, ~100x
    smaller, values): those entries are ill-conditioned in the trace's backward (a vertex z moves the traced phase,
    ``k n`` ~ 1e4 /mm times sums that cancel to ~1e-2 of their terms), so the field gradients' own rounding (they
    agree to ~6e-16) reaches them amplified; the former ASM Function untiled against itself in tiles differed
    there by as much (7.8e-10 of the plane z's own value on test_functions' thin lens). Tolerances ~10x those:
    4e-15, 2e-14, 4e-14, 4e-15, 1e-12."""
    got, ref = _new(rw_, with_doe, tile), _reference(rw_, with_doe)
    assert got[0].shape == (2, 8, 8)
    assert _rel(got[0], ref[0]) < 4e-15
    if with_doe:
        assert _rel(got[2], ref[2]) < 2e-14
    ga, gb = got[1], ref[1]
    top = np.max(np.abs(gb))
    sz = (ga.shape[0] - 1, COL.z)
    assert abs(ga[sz] - gb[sz]) < 4e-14 * abs(gb[sz])
    not_z = np.ones_like(gb, dtype=bool)
    not_z[:, COL.z] = False
    assert np.max(np.abs(ga - gb)[not_z]) < 4e-15 * top
    assert np.max(np.abs(ga - gb)[:-1, COL.z]) < 1e-12 * top
    # the curvatures, the plane's z and the sensor distance carry gradients here (the checks are not vacuous)
    assert np.min(np.abs(gb[1:3, COL.curvature])) > 1e-2 * top and abs(gb[sz]) > 1e-3 * top
    assert abs(gb[rw_.plane, COL.z]) > 1e-3 * top


def test_pair_is_the_flux_and_its_adjoint():
    """AsmOperator.forward_pair's ``Re(conj(U) U_w)`` integrated equals SensorPropagator's flux pixels (measured
    2.2e-16 of the peak; tolerance 2e-15), and ``<A_pair x, (y, y_w)> = <x, adjoint_pair(y, y_w)>`` (measured 3.2e-16;
    tolerance 3e-15)."""
    from rwwarp.wave.focal import pixel_flux
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = RayWave(singlet_doe(), [(0.0, 8.0)], [0.55], 6, 0.004, plan=Plan(0.004, 40, 96, 37), pixel_values="flux")
    op = get_method("asm").operator(r, doe=False)
    f = r.field_array()
    u, uw = op.forward_pair(f)
    ref = np.asarray(SensorPropagator("cpu", r.sensor_geometry()).forward(f).get())
    assert _rel(pixel_flux(u, uw, r.gauss_nodes, r.pixel, r.size), ref) < 2e-15
    rng = np.random.default_rng(2)
    x = rng.normal(size=f.shape) + 1j * rng.normal(size=f.shape)
    y, yw = (rng.normal(size=u.shape) + 1j * rng.normal(size=u.shape) for _ in range(2))
    a, aw = op.forward_pair(x)
    lhs = np.vdot(y, a) + np.vdot(yw, aw)
    rhs = np.vdot(op.adjoint_pair(y, yw), x)
    assert abs(lhs - rhs) < 3e-15 * abs(lhs)


def test_phase_free_distance_derivative_is_the_finite_difference():
    """``distance_derivative_phase_free`` (and its pair) against central differences of ``exp(-2 pi i z / lambda)
    forward`` over +-1 nm: measured 2.9e-8 of the largest value (3.2e-7 at 0.1 nm: rounding / h; 1.9e-7 at 10 nm: the
    h^2 term); tolerance 3e-7. And it is the exact
    derivative minus ``(2 pi i / lambda) forward`` (measured 9e-14 of the largest: the exact one's rounding, which
    is ~100x larger here); tolerance 1e-12."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = RayWave(singlet_doe(), [(0.0, 8.0)], [0.55], 6, 0.004, plan=Plan(0.004, 40, 96, 37), pixel_values="flux")
    m = get_method("asm")
    f = r.field_array()
    z, h = float(r.z_sensor - r.z_plane), 1e-6
    k = 2 * np.pi / (0.55e-3 / r.n_after[0])          # rad/mm in the medium after the plane

    def reduced(zz):
        a, b = m.operator(r, zz, doe=False).forward_pair(f)
        ph = np.exp(-1j * k * (zz - z))       # the constant phase's change, taken out
        return ph * a, ph * b
    op = m.operator(r, doe=False)
    got = op.distance_derivative_pair_phase_free(f)
    for g, p, q in zip(got, reduced(z + h), reduced(z - h)):
        fd = (p - q) / (2 * h)
        assert np.max(np.abs(g - fd)) < 3e-7 * np.max(np.abs(g))
    single = op.distance_derivative_phase_free(f)
    exact = op.distance_derivative(f) - 1j * k * op.forward(f)
    assert np.max(np.abs(single - got[0])) < 1e-14 * np.max(np.abs(single))
    assert np.max(np.abs(single - exact)) < 1e-12 * np.max(np.abs(single))
