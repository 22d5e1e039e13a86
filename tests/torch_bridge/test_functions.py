"""autograd Functions of torch_bridge: gradcheck in float64 on tiny sizes, dtype round trips,
straight-through quantisation, and the chained PSF against rwwarp's own."""
import math
import warnings

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from rwwarp.kernels import trace as ktrace

import torch_bridge as tb
from rwwarp.lens import Lens, Sensor, Surface
from rwwarp.wave.plan import Plan
from rwwarp.psf import RayWave
from torch_bridge.functions import TraceSplat
from torch_bridge.operator_function import operator_propagate


def thin_lens_doe():
    """A 0.5 mm square-aperture f = 50 mm thin lens with a DOE 1 mm behind it (tiny sampling)."""
    prof = {"kind": "even_poly", "norm_radius": 0.25, "coefficients": [-3.0, 1.0]}
    surfs = [Surface(type="aperture", semi_diameter=0.25, shape="square", stop=True),
             Surface(type="thin_lens", focal_length=50.0, semi_diameter=1.0, shape="square", thickness=1.0),
             Surface(type="doe", semi_diameter=1.0, shape="square", thickness=49.0, profile=prof)]
    return Lens(surfs, Sensor(0.02, (1000, 1000)), wavelengths_um=[0.55])


def singlet_doe():
    """An aspheric BK7 singlet with a DOE 0.5 mm behind it."""
    prof = {"kind": "even_poly", "norm_radius": 0.3, "coefficients": [-2.0, 1.0, 0.5]}
    surfs = [Surface(type="aperture", semi_diameter=0.3, shape="circle", stop=True, thickness=0.2),
             Surface(type="standard", radius=12.0, conic=-0.8, aspheric=[1e-4, 2e-6], material="N-BK7",
                     semi_diameter=1.0, thickness=1.0),
             Surface(type="standard", radius=-40.0, semi_diameter=1.0, thickness=0.5),
             Surface(type="doe", semi_diameter=0.6, shape="square", thickness=17.5, profile=prof)]
    return Lens(surfs, Sensor(0.004, (1000, 1000)), wavelengths_um=[0.55])


@pytest.fixture(scope="module")
def small_rw():
    """Two off-axis sources (no symmetry: the box splat is piecewise linear, and a symmetric layout
    puts ray-box edges exactly on cell boundaries, where it has no derivative)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return RayWave(thin_lens_doe(), [(0.0123, 0.3), (0.021, -0.013)], [0.55, 0.55], 6, 0.02,
                       plan=Plan(0.0291, 20, 40, 19), requires_grad=True)


def test_trace_splat_gradcheck(small_rw):
    rw = small_rw
    base = torch.from_numpy(rw.tracer.params_np.copy())
    # entries and the scale of gradcheck's step (eps 1e-5) for each: the DOE-plane z moves the sampled
    # field fast (step 1e-7 mm), the thin lens z slowly, while the phase 2 pi OPL / lambda is formed from
    # ~50 mm paths with ~1e-11 rad of rounding per ray (step 1e-4 mm)
    entries = [(1, ktrace.P_POWER, 0.1), (2, ktrace.P_Z, 0.01), (1, ktrace.P_Z, 10.0)]

    def f(x):
        t = base.clone()
        for k, (i, j, scale) in enumerate(entries):
            t = t.index_put((torch.tensor(i), torch.tensor(j)), base[i, j] + scale * x[k])
        return TraceSplat.apply(t, rw)

    x = torch.zeros(len(entries), dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(f, (x,), eps=1e-5, atol=1e-4, rtol=1e-5, fast_mode=True)


def test_propagate_gradcheck(small_rw):
    """The ASM's propagation (the generic operator path: AsmOperator, the DOE as exp(1j alpha phi0) in torch):
    field, DOE phase and distance gradients against gradcheck's finite differences."""
    rw = small_rw
    torch.manual_seed(0)
    n = rw.plan.n_grid
    field = torch.randn(rw.nsrc, n, n, dtype=torch.complex128, requires_grad=True)
    phi0 = (2 * math.pi * torch.rand(rw.nsrc, n, n, dtype=torch.float64)).requires_grad_()
    dist = torch.full((rw.nsrc,), rw.z_sensor - rw.z_plane, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda f, p, d: operator_propagate(f, d, rw, phi0=p), (field, phi0, dist),
                                    eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=True)
    # no DOE, fixed distance
    assert torch.autograd.gradcheck(lambda f: operator_propagate(f, None, rw), (field,), eps=1e-6, atol=1e-6,
                                    rtol=1e-4, fast_mode=True)


def test_raywave_psf_equals_rwwarp(small_rw):
    rw = small_rw
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref = rw.run()["data"]
    phi0, _ = rw.doe_phase()
    table = torch.from_numpy(rw.tracer.params_np.copy())
    got = tb.raywave_psf(rw, table, torch.from_numpy(phi0)).numpy()
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-14 * ref.max())


def test_mixed_precision_round_trip():
    x = torch.randn(4, 5, dtype=torch.float64, requires_grad=True)
    y = tb.mixed_precision(x)
    assert y.dtype == torch.float32
    (y * torch.arange(5, dtype=torch.float32)).sum().backward()
    assert x.grad.dtype == torch.float64
    np.testing.assert_array_equal(x.grad.numpy(), np.tile(np.arange(5.0), (4, 1)))
    z = torch.randn(3, dtype=torch.complex128, requires_grad=True)
    assert tb.mixed_precision(z).dtype == torch.complex64
    # gradcheck on a float64 composition (float32 inside, so loose tolerances)
    assert torch.autograd.gradcheck(lambda a: tb.mixed_precision(a).double() * 3.0, (x,), eps=1e-3, atol=1e-3,
                                    rtol=1e-3)


@pytest.mark.parametrize("levels", [None, 4, 16])
def test_quantize_ste_matches_the_equations_and_passes_gradients(levels):
    """Forward (rwwarp.doe.relief_phase in torch, the code numpy runs too) against a reference written
    from the definition with other arithmetic: ``np.mod(phi, 2 pi)`` in [0, 2 pi) and, quantised, the
    level index ``k = round(w / (2 pi / L)) mod L`` (the top level folds to 0), value ``k 2 pi / L``.
    Backward: the identity (straight through)."""
    phi = torch.linspace(-20.0, 20.0, 1001, dtype=torch.float64, requires_grad=True)
    q = tb.quantize_ste(phi, levels)
    qn = q.detach().numpy()
    w_ref = np.mod(phi.detach().numpy(), 2 * math.pi)
    assert qn.min() >= 0.0 and qn.max() < 2 * math.pi
    if levels is None:
        # floor-based vs fmod-based wrap: the same angle (np.mod rounds a tiny negative phase up to
        # 2 pi itself, hence the circular distance); measured 0 here, tolerance a few ulp of 20 rad
        d = np.abs(qn - w_ref)
        assert np.max(np.minimum(d, 2 * math.pi - d)) < 1e-14
    else:
        step = 2 * math.pi / levels
        k = np.rint(w_ref / step)
        assert np.all(np.abs(w_ref / step - np.floor(w_ref / step) - 0.5) > 1e-9)  # no sample at a tie
        k_ref = np.where(k == levels, 0, k)
        # the values are the levels k 2 pi / L exactly (one multiplication), the right level each
        np.testing.assert_array_equal(qn, k_ref * step)
        assert set(np.unique(k_ref)) == set(range(levels))
    # fold to 0: just below 2 pi (to the top level when quantised), a tiny negative phase that rounds to 2 pi
    edge = tb.quantize_ste(torch.tensor([2 * math.pi - 1e-9, -1e-20, 2 * math.pi], dtype=torch.float64),
                           levels)
    assert edge[1].item() == 0.0 and edge[2].item() == 0.0
    assert edge[0].item() == (0.0 if levels else pytest.approx(2 * math.pi - 1e-9, abs=1e-15))
    # float32 stays float32
    assert tb.quantize_ste(phi.detach().float(), levels).dtype == torch.float32
    w = torch.randn(1001, dtype=torch.float64)
    (q * w).sum().backward()
    np.testing.assert_array_equal(phi.grad.numpy(), w.numpy())


def test_parameter_table_loads_device_to_device():
    """load_table with the table's host values beside the tensor copies the tensor's rows into the tracer
    device to device (RayWave.load_params(device_table=)): the tracer's rows equal the table bit for bit, and
    equal what the host path loads; a device table of the wrong shape is refused by name."""
    import warp as wp

    import rwwarp as rw
    from rwwarp.wave.raywave import RayWave
    from torch_bridge.functions import load_table
    lens = rw.load_lens("cooke_triplet")
    r = RayWave(lens, [0.0], [0.55], 8, lens.sensor.pixel_pitch, method="focal", requires_grad=True)
    base = r.tracer.params_np.copy()
    t = torch.as_tensor(base) * (1.0 + 1e-3 * torch.arange(base.size, dtype=torch.float64).reshape(base.shape))
    t[:, 12] = torch.as_tensor(base[:, 12])   # keep the semi-diameters (limits) as they are
    load_table(r, t, t.numpy())
    dev = np.stack([p.numpy() for p in r.tracer.params])
    assert np.array_equal(dev, t.numpy())
    load_table(r, torch.as_tensor(base))
    load_table(r, t)                          # the host path
    assert np.array_equal(np.stack([p.numpy() for p in r.tracer.params]), dev)
    with pytest.raises(ValueError, match="device_table"):
        r.load_params(t.numpy(), device_table=wp.from_torch(t[:-1].contiguous()))
