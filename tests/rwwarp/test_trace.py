"""Coherent ray tracer against published lens data (Zemax tutorial Cooke triplet), finite
differences, and physical edge cases (missed surfaces, TIR, vignetting)."""
import math

import numpy as np
import pytest
import warp as wp

from rwwarp.lens import Lens, Surface, Sensor
from rwwarp.trace import Tracer, pupil_grid
from rwwarp.metrics.analysis import spot_rms, spot_rms_tape, efl_tape
from rwwarp.kernels import trace as ktrace
from rwwarp import paraxial

D, F, C = 0.5875618, 0.4861327, 0.6562725
COOKE = [(22.01359, 3.25896, "N-SK16"), (-435.76044, 6.00755, "air"), (-22.21328, 0.99997, "F2"),
         (20.29192, 4.75041, "air"), (79.68360, 2.95208, "N-SK16"), (-18.39533, 42.20778, "air")]


def cooke(r1=COOKE[0][0]):
    rows = [(r1,) + COOKE[0][1:]] + COOKE[1:]
    surfs = [Surface(radius=r, thickness=t, material=m, stop=(i == 3)) for i, (r, t, m) in enumerate(rows)]
    return Lens(surfs, Sensor(0.005, (4000, 4000)), entrance_pupil_diameter=10.0, wavelengths_um=[D])


def test_cooke_paraxial_data():
    lens = cooke()
    assert lens.efl(D) == pytest.approx(50.021351, abs=1e-6)
    assert lens.efl(F) == pytest.approx(49.986597, abs=1e-6)
    assert lens.efl(C) == pytest.approx(50.070949, abs=1e-6)
    assert lens.bfl(D) == pytest.approx(42.436440, abs=1e-6)
    p = paraxial.pupils(lens, D)
    assert p.entrance_radius == pytest.approx(5.0, rel=1e-12)
    assert paraxial.f_number(lens, D) == pytest.approx(50.021351 / 10.0, abs=1e-6)


@pytest.mark.parametrize("field,expected_um", [(0.0, 4.8284), (14.0, 15.2153), (20.0, 10.3441)])
def test_cooke_rms_spot_zemax(field, expected_um):
    # 401 x 401 square grid over the paraxial entrance pupil, no ray aiming, image plane fixed. All 20 grid
    # points on the pupil circle are traced (one edge tolerance, kernels.trace.EDGE_RTOL); dropping or
    # keeping them moves the RMS by up to 1.5e-4 relative, and Zemax's edge convention is not documented:
    # measured 4.82917 / 15.21638 / 10.34350, i.e. 1.6e-4 / 7.1e-5 / 5.8e-5 relative to Zemax
    lens = cooke()
    assert spot_rms(lens, field, D, grid=401) == pytest.approx(expected_um, rel=2.5e-4)


def test_efl_gradient_tape_matches_reference_and_finite_difference():
    lens = cooke()
    tr = Tracer(lens, [D], requires_grad=True)
    tape = wp.Tape()
    with tape:
        efl = efl_tape(tr)
    tape.backward(grads={efl: wp.ones(1, dtype=wp.float64)})
    defl_dc = tr.params[0].grad.numpy()[ktrace.P_C]
    r1 = COOKE[0][0]
    defl_dr = defl_dc * (-1.0 / r1 ** 2)
    h = 1e-4
    fd = (cooke(r1 + h).efl(D) - cooke(r1 - h).efl(D)) / (2 * h)
    assert efl.numpy()[0] == pytest.approx(lens.efl(D), rel=1e-9)
    assert defl_dr == pytest.approx(2.393785, abs=1e-6)
    assert defl_dr == pytest.approx(fd, rel=1e-6)


def test_rms_spot_gradient_matches_central_difference():
    lens = cooke()
    tr = Tracer(lens, [D], requires_grad=True)
    tape = wp.Tape()
    with tape:
        rms = spot_rms_tape(tr, [14.0], grid=61)
    tape.backward(grads={rms: wp.ones(1, dtype=wp.float64)})
    g = tr.params[2].grad.numpy()[ktrace.P_C]  # d rms / d curvature of surface 3 (index 2)
    base = tr.params_np.copy()
    h = 1e-8  # the spot size varies fast with curvature: larger steps carry O(h^2) truncation error
    vals = []
    for sgn in (1, -1):
        p = base.copy()
        p[2, ktrace.P_C] += sgn * h
        t2 = Tracer(lens, [D])
        t2.set_params(p)
        vals.append(spot_rms_tape(t2, [14.0], grid=61).numpy()[0])
    fd = (vals[0] - vals[1]) / (2 * h)
    assert g == pytest.approx(fd, rel=1e-6)


def test_missed_tir_and_clipped_rays_are_invalid_and_finite():
    # a strongly curved glass surface hit from inside the glass at steep angles -> TIR;
    # a small semi-diameter clips; a tiny sphere is missed entirely by outer rays
    surfs = [Surface(type="aperture", semi_diameter=4.0, thickness=1.0),
             Surface(radius=None, thickness=5.0, material="N-SK16", semi_diameter=10),
             Surface(radius=-4.5, thickness=10.0, material="air", semi_diameter=4.4)]
    lens = Lens(surfs, Sensor(0.01, (100, 100)))
    tr = Tracer(lens, [D])
    rays = tr.trace(0.0, grid=41)
    r = rays.numpy()
    assert np.all(np.isfinite(r["pos"])) and np.all(np.isfinite(r["dir"])) and np.all(np.isfinite(r["opl"]))
    n_valid = rays.count_valid()[0]
    assert 0 < n_valid < rays.n_pupil
    # rays that survive are inside the clear aperture of the last surface
    # check the TIR criterion analytically: sin(incidence) at the sphere > 1/n for the outer rays
    n = lens.indices(D)[1]
    h_tir = 4.5 / n  # height where incidence angle on the -4.5 mm sphere reaches the critical angle
    u, v, _ = pupil_grid(41, "circle")
    h = 4.0 * np.hypot(u, v)
    ok = r["valid"][0]
    assert not np.any(ok & (h > h_tir + 1e-9))
    assert np.all(ok[h < h_tir - 0.05])


def test_float32_build_same_source():
    lens = cooke()
    a = spot_rms(lens, 14.0, D, grid=101)
    b = spot_rms(lens, 14.0, D, grid=101, dtype="float32")
    assert b == pytest.approx(a, rel=1e-3)


def test_ray_aiming_puts_chief_ray_on_stop_centre():
    lens = cooke()
    tr = Tracer(lens, [D])
    src = tr.sources([20.0], ray_aiming=True)
    rays = tr._run(src, np.zeros(1), np.zeros(1), 1.0, upto=lens.stop_index + 1)
    assert np.allclose(rays.pos.numpy()[0, :2], 0.0, atol=1e-9)
    # without aiming it misses the centre (pupil aberration of the front group)
    src0 = tr.sources([20.0])
    r0 = tr._run(src0, np.zeros(1), np.zeros(1), 1.0, upto=lens.stop_index + 1)
    assert abs(r0.pos.numpy()[0, 1]) > 1e-4


def test_thin_lens_is_stigmatic_with_equal_optical_path():
    # ideal thin lens, object at 300 mm: all rays meet at the paraxial image with equal OPL
    f = 100.0
    u = 300.0
    v = 1.0 / (1.0 / f - 1.0 / u)
    surfs = [Surface(type="thin_lens", focal_length=f, semi_diameter=10.0, thickness=v, stop=True)]
    lens = Lens(surfs, Sensor(0.001, (100, 100)), object_distance=u)
    tr = Tracer(lens, [0.55])
    # put the source off axis by a field angle, rays to the image plane
    rays = tr.trace(3.0, grid=21).numpy()
    ok = rays["valid"][0]
    xy = rays["pos"][0, ok, :2]
    assert np.ptp(xy[:, 0]) < 1e-12 and np.ptp(xy[:, 1]) < 1e-12
    assert np.ptp(rays["opl"][0, ok]) < 1e-10
    # image height = -m * object height, m = v/u
    assert xy[0, 1] == pytest.approx(-(v / u) * (-math.tan(math.radians(3.0)) * u), rel=1e-12)


def test_grad_replicas_must_be_a_power_of_two():
    lens = cooke()
    for bad in (0, 3, 12):
        with pytest.raises(ValueError, match="grad_replicas"):
            Tracer(lens, [0.55], requires_grad=True, grad_replicas=bad)
    assert Tracer(lens, [0.55], requires_grad=True, grad_replicas=8).grad_replicas == 8
