"""The wave step's own error (rwwarp.wave.wave_step: ``step_phase_rad``, ``step_error``): the beam's aberration
before the DOE, already carried to the plane by the rays, is transported again over the reduced distance ``d``,
a phase error ``pi lambda_m d |f|^2 = pi s^2 / (lambda_m d)``. Checked against an independent exact trace of a
plano-convex singlet written from Snell's law here (its spherical aberration sets ``f``), against zero for an
ideal thin lens, and in the planner's decisions: ``method="auto"`` refuses a step whose own error exceeds the
tolerance (keeping the one-step plan, saying why), ``method="two-step"`` warns.
"""
import math
import warnings

import numpy as np
import pytest

import rwwarp as rw
import rwwarp.wave.wave_step as ws
from rwwarp.lens import Lens, Sensor, Surface
from rwwarp.wave import model_error as me
from rwwarp.wave.raywave import RayWave

from _wave_truth import thin_lens_doe

N_GLASS = 1.5
#: the singlet: stop radius A, then 1 mm to a sphere of radius RC, glass T thick, flat back, G to the (flat) DOE,
#: Z2 on to the sensor near the paraxial focus (f = RC / (n - 1) = 30 mm)
A, RC, T, G, Z2 = 5.0, 15.0, 5.0, 10.0, 16.7


def singlet(a=A):
    surfs = [Surface(type="aperture", semi_diameter=a, shape="circle", stop=True, thickness=1.0),
             Surface(type="standard", radius=RC, thickness=T, material=f"{N_GLASS}/1e9", semi_diameter=1.2 * a),
             Surface(type="standard", radius=None, thickness=G, semi_diameter=1.2 * a),
             Surface(type="doe", semi_diameter=a, thickness=Z2, material="1.5/1e9",
                     profile={"kind": "even_poly", "coefficients": [0.0], "norm_radius": a})]
    return Lens(surfs, Sensor(0.5e-3, (4000, 4000)), wavelengths_um=[0.55])


def _refract(d, nrm, n1, n2):
    """Snell's law in vector form: unit direction ``d`` (N, 2), unit normal ``nrm`` against it."""
    cosi = -np.sum(d * nrm, axis=1)
    eta = n1 / n2
    k = 1.0 - eta ** 2 * (1.0 - cosi ** 2)
    return eta * d + (eta * cosi - np.sqrt(k))[:, None] * nrm


def trace_singlet(h):
    """Exact meridional trace (x, z) of rays parallel to the axis at heights ``h`` (mm) to the DOE plane: their
    positions there and directions (N, 2)."""
    z_front = 1.0
    zc = z_front + RC
    z = zc - np.sqrt(RC ** 2 - h ** 2)
    p = np.stack([h, z], 1)
    d = np.tile([0.0, 1.0], (len(h), 1))
    d = _refract(d, (p - [0.0, zc]) / RC, 1.0, N_GLASS)
    z_back = z_front + T
    p = p + ((z_back - p[:, 1]) / d[:, 1])[:, None] * d
    d = _refract(d, np.tile([0.0, -1.0], (len(h), 1)), N_GLASS, 1.0)
    z_doe = z_back + G
    p = p + ((z_doe - p[:, 1]) / d[:, 1])[:, None] * d
    return p, d


def test_the_steps_phase_against_an_independent_trace_of_a_singlet():
    lens = singlet()
    with pytest.warns(ws.WaveStepWarning):       # phi 0.43 rad > 0.1: two-step warns (checked below)
        r = RayWave(lens, [(0.0, 0.0)], [0.55], 32, 0.5e-3, method="two-step")
    assert r.n_after[0] == 1.0
    d = float(r.wave_step[0])
    tgt = np.asarray(r.target[0])               # the sphere's centre: the planner's focus of the beam (an input)
    h = np.linspace(0.0, A, 20001)
    p, m = trace_singlet(h)
    to_t = np.stack([tgt[0] - p[:, 0], tgt[2] - p[:, 1]], 1)
    to_t /= np.linalg.norm(to_t, axis=1, keepdims=True)
    phi = math.pi * d * (m[:, 0] - to_t[:, 0]) ** 2 / 0.55e-3       # pi lambda d |f|^2, f = (m - m_T) / lambda
    # the pilot's outermost point on the plane: the trace's rays inside it
    pos, ok = r.pilot.pos_p[0], r.pilot.ok[0]
    r_max = float(np.max(np.hypot(pos[ok, 0], pos[ok, 1])))
    want = float(np.max(phi[np.abs(p[:, 0]) <= r_max]))
    got = float(ws.step_phase_rad(r, r.wave_step)[0])
    print(f"phi: step_phase_rad {got:.6g}, trace {want:.6g} (d {d:.4g} mm, pilot radius {r_max:.4g} mm)")
    assert 0.3 < want < 1.0                      # the scene is in the regime that matters (0.43 rad measured)
    # the same rays traced twice (the pilot's 2-D grid has no ray exactly at the trace's maximum; measured 1.1e-4
    # relative: 0.430408 against 0.430362), so 1e-3
    assert got == pytest.approx(want, rel=1e-3)
    # and it is pi s^2 / (lambda d) of the shift the plan reports
    s = ws.double_transport_shift_mm(r, r.wave_step)
    assert got == pytest.approx(math.pi * s ** 2 / (0.55e-3 * d), rel=1e-9)
    assert ws.step_error(got) == pytest.approx(got ** 2 / ws.STEP_ERROR_DIV)


def test_an_ideal_thin_lens_leaves_the_step_no_error_of_its_own():
    # the calibrated scene (tests/rwwarp/test_model_error.py: the step within 2.9e-4 of the truth): the beam before
    # the DOE is the lens's perfect sphere, so f = 0 up to the pilot's rounding (measured 8e-29 rad)
    lens = thin_lens_doe(10.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error", ws.WaveStepWarning)
        p = rw.plan_psf(lens, 0.0, 0.55, size=16, method="two-step")
        q = rw.plan_psf(lens, 0.0, 0.55, size=16, method="auto", tolerance=1e-3)
    assert p.model_error["step_phase_rad"] < 1e-6
    assert q.wave_step_mm == pytest.approx(8.0, rel=1e-3)     # auto still takes the step there
    with pytest.raises(ValueError, match="phase error"):
        ws.step_error(float("nan"))


@pytest.mark.filterwarnings("ignore::rwwarp.errors.PatchWarning")
def test_auto_refuses_a_step_whose_own_error_exceeds_the_tolerance_and_two_step_warns():
    lens = singlet()
    kw = dict(size=16, pixel_mm=0.5e-3)
    # the singlet at 5 mm: the one-step estimate is far above 1e-2 (measured 6.1: its spherical aberration's rim
    # slope) and the step's own error phi^2 / 10 = 0.0185 (phi 0.43 rad) is above it too
    p = rw.plan_psf(lens, 0.0, 0.55, method="auto", tolerance=1e-2, **kw)
    assert p.model_error["estimate"] > 1e-2 and p.model_error["step_error"] > 1e-2
    assert p.wave_step_mm is None
    assert any("wave step refused" in r and "exceeds the tolerance" in r for r in p.reasons)
    with pytest.warns(me.ModelErrorWarning, match="wave step was refused"):
        rw.psf(lens, 0.0, 0.55, method="auto", tolerance=1e-2, **kw)
    # a looser tolerance, between the step's own error and the model's: the step is taken, quietly
    with warnings.catch_warnings():
        warnings.simplefilter("error", ws.WaveStepWarning)
        q = rw.plan_psf(lens, 0.0, 0.55, method="auto", tolerance=5e-2, **kw)
    assert q.wave_step_mm > 0
    assert any("phase error" in r and "own error" in r for r in q.reasons)
    # method two-step takes it regardless, and warns (phi 0.43 > 0.1 rad without a tolerance; 0.0185 > 1e-2 with)
    with pytest.warns(ws.WaveStepWarning, match="not a reference"):
        t = rw.plan_psf(lens, 0.0, 0.55, method="two-step", **kw)
    assert t.wave_step_mm > 0
    with pytest.warns(ws.WaveStepWarning, match="above the tolerance 0.01"):
        rw.plan_psf(lens, 0.0, 0.55, method="two-step", tolerance=1e-2, **kw)
    # a smaller stop: phi 0.018 rad, E_step 3.4e-5: the step is taken under auto at 1e-3 and two-step is quiet
    small = singlet(3.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error", ws.WaveStepWarning)
        assert rw.plan_psf(small, 0.0, 0.55, method="auto", tolerance=1e-3, **kw).wave_step_mm > 0
        rw.plan_psf(small, 0.0, 0.55, method="two-step", **kw)
