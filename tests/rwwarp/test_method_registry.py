"""Propagation methods as registered operators (rwwarp.wave.methods, issue 25 item 1).

* the registry: names, a clear error for an unknown name, a toy method registered here (one class, no other
  file touched) planned and run by RayWave, rw.psf and rw.psf_map;
* ``direct`` (brute-force Rayleigh-Sommerfeld, no FFT): its forward and adjoint are adjoint
  (<A x, y> = <x, A^H y>), its distance derivative is the finite difference of its forward, and its PSFs agree
  with those of the ASM and the focal method, which share none of its code;
* the ASM's operator (the registry's wrapper of PointPropagator) passes the same adjoint and distance-derivative
  tests;
* WaveField: the field object of a RayWave.
"""
import warnings

import numpy as np
import pytest

import rwwarp as rw
from rwwarp.lens import Lens, Sensor, Surface
from rwwarp.wave import methods
from rwwarp.wave.raywave import RayWave


def _singlet():
    """A BK7 singlet (f ~ 10 mm) at F/50 behind its stop: a small beam (wave-plane grids of 18-60 samples)."""
    surfs = [Surface(type="aperture", semi_diameter=0.1, shape="circle", stop=True, thickness=0.1),
             Surface(type="standard", radius=6.0, material="N-BK7", semi_diameter=2.0, thickness=1.0),
             Surface(type="standard", radius=-30.0, semi_diameter=2.5, thickness=9.0)]
    return Lens(surfs, Sensor(0.002, (4000, 4000)), wavelengths_um=[0.55])


def _psf(lens, method, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return rw.psf(lens, 10.0, 0.55, size=16, method=method, **kw)


# ------------------------------------------------------------------------------------------ registry
def test_names_list_the_built_in_methods():
    assert set(methods.names()) >= {"asm", "focal", "pixel", "direct"}
    for name in ("asm", "focal", "pixel", "direct"):
        assert methods.get(name).name == name
    # the planner's choices are not methods
    assert "auto" not in methods.names() and "two-step" not in methods.names()
    assert set(methods.choices(differentiable=True)) == {"auto", "two-step", "asm", "focal"}


def test_unknown_method_errors_naming_the_registered_ones():
    with pytest.raises(ValueError, match=r"unknown propagation method 'nope'.*'asm'.*'focal'.*'pixel'.*'direct'"):
        methods.get("nope")
    with pytest.raises(Exception, match=r"method='nope'.*'direct'"):
        rw.psf(_singlet(), 0.0, 0.55, size=8, method="nope")
    with pytest.raises(ValueError, match=r"RayWave: method must be one of .*got 'nope'"):
        RayWave(_singlet(), [(0.0, 0.0)], [0.55], 8, 0.002, method="nope")
    with pytest.raises(TypeError, match="not a Propagation subclass"):
        methods.register(int)


class _WavePlanePower(methods.Propagation):
    """A toy method defined only here: the wave-plane window's power ``sum |u|^2 h^2`` put on the patch's centre
    pixel (a test of the wiring, not physics). Planned on the ASM's windows."""

    name = "toy-plane-power"

    def plan(self, ctx):
        from dataclasses import replace
        from rwwarp.wave.methods.asm import plan_window
        p = plan_window(ctx)
        p.plan = replace(p.plan, method=self.name)
        return p

    def estimate(self, plan, n_sources, size, gauss_nodes):
        return {"memory_bytes": int(n_sources * plan.n_grid ** 2 * 64), "flops": float(plan.n_grid ** 2)}

    def pixels(self, rw_, field, precision="double", to_host=True):
        out = np.zeros((rw_.nsrc, rw_.size, rw_.size))
        out[:, rw_.size // 2, rw_.size // 2] = np.sum(np.abs(np.asarray(field)) ** 2, axis=(1, 2)) * rw_.plan.pitch_mm ** 2
        return out


def test_a_method_registered_here_is_planned_and_run_without_other_changes():
    """The "<= 3 files" target: a method is one class registered by name; RayWave, rw.psf and rw.psf_map take
    it (planning, cost, explain, packing and run go through the registry)."""
    methods.register(_WavePlanePower)
    try:
        lens = _singlet()
        r = RayWave(lens, [(0.0, 10.0)], [0.55], 16, 0.002, method="toy-plane-power")
        assert r.plan.method == "toy-plane-power" and r.propagation().name == "toy-plane-power"
        assert "toy-plane-power" in r.plan.explain()
        u = r.field_array()
        want = np.sum(np.abs(u[0]) ** 2) * r.plan.pitch_mm ** 2 / r.entering[0]
        out = r.run()["data"]
        # the same trace twice: the same bits (the CPU splat is deterministic)
        assert out[0, 8, 8] == want and np.count_nonzero(out) == 1
        # the flux field's power on the plane is the traced fraction of the entering power (test_flux: 5e-5 there)
        assert 0.5 < want < 1.0
        p = _psf(lens, "toy-plane-power")
        assert p.plan["method"] == "toy-plane-power" and p.data[8, 8] == pytest.approx(want, rel=1e-12)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            m = rw.psf_map(lens, [0.0, 10.0], [0.55], size=16, method="toy-plane-power")
        assert m.data[1, 0, 8, 8] == pytest.approx(want, rel=1e-12)
    finally:
        methods.unregister("toy-plane-power")
    with pytest.raises(ValueError, match="unknown propagation method"):
        methods.get("toy-plane-power")


# ------------------------------------------------------------------------------------------ direct
def _inner(a, b):
    return complex(np.vdot(np.asarray(a).ravel(), np.asarray(b).ravel()))


@pytest.mark.parametrize("name", ["direct", "asm"])
def test_operator_forward_and_adjoint_are_adjoint(name):
    """<A x, y> = <x, A^H y> for random x (wave plane) and y (nodes): both sides in float64, the sums over
    ~1e5 products; measured relative difference 1.1e-15 (direct) / 7.5e-16 (asm); tolerance 1e-14."""
    r = RayWave(_singlet(), [(0.0, 10.0)], [0.55], 6, 0.002, method=name)
    op = methods.get(name).operator(r)
    n, m = r.plan.n_grid, 6 * r.gauss_nodes
    rng = np.random.default_rng(1)
    x = rng.normal(size=(1, n, n)) + 1j * rng.normal(size=(1, n, n))
    y = rng.normal(size=(1, m, m)) + 1j * rng.normal(size=(1, m, m))
    lhs, rhs = _inner(y, op.forward(x)), _inner(op.adjoint(y), x)
    assert abs(lhs - rhs) < 1e-14 * abs(lhs)


@pytest.mark.parametrize("name", ["direct", "asm"])
def test_operator_distance_derivative_is_the_finite_difference(name):
    """d forward / dz (direct: the kernel's exact derivative; asm: the transfer function's, 2 pi i w H, at fixed band
    limits) against a central difference over +-0.1 nm (k h = 1.1e-3 rad: its error ~ (k h)^2 / 6 = 2e-7 of the
    value); measured 2.2e-7 (direct) and 2.2e-7 (asm; 2.1e-5 at h = 1e-6, 2.1e-3 at 1e-5: the h^2 law) of the
    largest value; tolerance 1e-6."""
    r = RayWave(_singlet(), [(0.0, 10.0)], [0.55], 6, 0.002, method=name)
    u = r.field_array()
    z, h = float(r.z_sensor - r.z_plane), 1e-7
    d = methods.get(name)
    fd = (d.operator(r, z + h).forward(u) - d.operator(r, z - h).forward(u)) / (2 * h)
    got = d.operator(r).distance_derivative(u)
    assert np.max(np.abs(got - fd)) < 1e-6 * np.max(np.abs(got))


def test_direct_agrees_with_the_asm_and_the_focal_method():
    """The singlet 10 deg off axis, 16 px of 2 um. On the planned grids (nyquist_safety 2: 18 samples across the
    window) the three PSFs differ by up to 0.8 % of the peak (measured: direct - asm 5.1e-3, direct - focal
    7.1e-3, asm - focal 7.7e-3): tolerance 1.5e-2. At nyquist_safety 8 (60 samples) direct and focal, which share
    no code past the field, meet to 7.2e-4 of the peak: tolerance 1.5e-3."""
    lens = _singlet()
    ref = _psf(lens, "asm")
    focal = _psf(lens, "focal", center_mm=ref.center_mm)
    direct = _psf(lens, "direct", center_mm=ref.center_mm)
    assert direct.plan["method"] == "direct"
    pk = ref.data.max()
    assert np.max(np.abs(direct.data - ref.data)) < 1.5e-2 * pk
    assert np.max(np.abs(direct.data - focal.data)) < 1.5e-2 * pk
    fine = {m: _psf(lens, m, center_mm=ref.center_mm, nyquist_safety=8.0) for m in ("focal", "direct")}
    assert np.max(np.abs(fine["direct"].data - fine["focal"].data)) < 1.5e-3 * pk
    assert np.all(np.isfinite(direct.data)) and direct.data.min() >= 0


# ------------------------------------------------------------------------------------------ field object
def test_wave_field_carries_the_raywave_field():
    r = RayWave(_singlet(), [(0.0, 10.0)], [0.55], 8, 0.002, method="asm")
    u = r.field_array()
    f = r.wave_field(u)
    assert f.samples is u and f.n_sources == 1 and f.n_grid == r.plan.n_grid
    np.testing.assert_array_equal(f.origin_mm, r.origin)
    assert f.wavelength_mm[0] == pytest.approx(0.55e-3 / r.n_after[0], rel=1e-15)
    np.testing.assert_array_equal(f.carrier_cpmm, r.carrier)
    np.testing.assert_array_equal(f.target_mm, r.target)
    x, y = f.coordinates()
    assert x.shape == (1, f.n_grid) and x[0, 1] - x[0, 0] == pytest.approx(r.plan.pitch_mm)
    with pytest.raises(ValueError, match=r"samples must be \(S, N, N\)"):
        f.with_samples(u[0])
    with pytest.raises(ValueError, match="origin_mm"):
        type(f)(u, np.zeros((2, 2)), 1e-3, np.ones(1), np.zeros((1, 2)))


def test_direct_sum_of_a_wave_field_meets_the_rayleigh_sommerfeld_integral_at_a_focus():
    """A Gaussian-apodised spherical wave converging to (0, 0, f), ``exp(-r^2 / w^2) exp(-i k R)``, handed in as a
    WaveField with an arbitrary carrier removed: at the focus its phase cancels the kernel's, and the
    Rayleigh-Sommerfeld integral is the 1-D ``f int exp(-r^2 / w^2) (1 - i k R) r / R^3 dr`` (scipy quad, written
    here from the kernel's equation). Measured relative difference 9e-15 (the grid's sum of a smooth integrand
    converges spectrally; the real part, the kernel's 1 / R^3 term, is 8e-6 of the whole); tolerance 1e-13."""
    from scipy.integrate import quad
    from rwwarp.wave.field import WaveField
    from rwwarp.wave.methods.direct import DirectOperator
    lam, f, w = 0.5e-3, 10.0, 0.1
    k = 2 * np.pi / lam
    h, n = 2e-3, 601                    # +-0.6 mm = 6 w: the window cuts exp(-36)
    g = (np.arange(n) - (n - 1) / 2) * h
    X, Y = np.meshgrid(g, g)
    R = np.sqrt(X ** 2 + Y ** 2 + f ** 2)
    car = np.array([[30.0, -20.0]])
    u = np.exp(-(X ** 2 + Y ** 2) / w ** 2 - 1j * k * R - 2j * np.pi * (car[0, 0] * X + car[0, 1] * Y))
    wave = WaveField(u[None], np.array([[g[0], g[0]]]), h, np.array([lam]), car)
    got = DirectOperator(wave, np.zeros((1, 1)), np.zeros((1, 1)), f).forward(wave)[0, 0, 0]
    re = quad(lambda r: f * np.exp(-r * r / w ** 2) * r / np.hypot(r, f) ** 3, 0, 8 * w, epsabs=0, epsrel=1e-13)[0]
    im = quad(lambda r: -f * k * np.exp(-r * r / w ** 2) * r / np.hypot(r, f) ** 2, 0, 8 * w, epsabs=0, epsrel=1e-13)[0]
    want = re + 1j * im
    assert abs(got - want) < 1e-13 * abs(want)
