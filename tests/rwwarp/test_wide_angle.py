"""Refractive PSFs at wide field angles against the independent truth (issue 27: <= 2e-4 of the peak).

The reference is :func:`rwwarp.ground_truth.rs_lens_psf`: its own trace on a polar pupil rule, ray-tube
amplitudes by finite differences, the exact Rayleigh-Sommerfeld kernel (and its z-derivative for the flux)
summed to every pixel node, no FFT, no sampled field (converged here to 1.5e-11 of the peak: 32 x 128 against
64 x 256 pupil nodes at 40 deg). The lens is a BK7 singlet (stop 0.25 mm, R 6 / -30 mm, f ~ 10 mm, F/20) whose
35 / 40 deg beams are aberrated spots 440 / 660 um wide (many Airy radii): the 16 px patch about the chief ray
lies inside the geometric spot, the case the focal planner's ray-landing rules are for
(:func:`rwwarp.wave.plan.plan_focal`, ``FOCAL_RAY_SPREAD`` and ``FOCAL_LIT_SHIFT_MARGIN``).
"""
import warnings

import numpy as np
import pytest

import rwwarp as rw
from rwwarp.ground_truth import rs_lens_psf
from rwwarp.lens import Lens, Sensor, Surface


def _singlet():
    surfs = [Surface(type="aperture", semi_diameter=0.25, shape="circle", stop=True, thickness=0.1),
             Surface(type="standard", radius=6.0, material="N-BK7", semi_diameter=2.0, thickness=1.0),
             Surface(type="standard", radius=-30.0, semi_diameter=2.5, thickness=9.0)]
    return Lens(surfs, Sensor(0.002, (4000, 4000)), wavelengths_um=[0.55])


@pytest.mark.parametrize("field,tol", [(35.0, 2e-4), (40.0, 1.2e-4)])
def test_singlet_wide_angle_focal_against_rs_truth(field, tol):
    """The focal path (16 px of 2 um, flux) against rs_lens_psf, max |error| / peak. Measured 1.1e-4 (35 deg)
    and 5.4e-5 (40 deg); before the ray-landing rules 6.9e-4 / 6.4e-4 (the wave-plane period too short for the
    rim's phase slope; at 40 deg also V's taper cut through the lit spot). Tolerance about twice, at most issue 27's
    target for refractive lenses (2e-4)."""
    lens = _singlet()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        p = rw.psf(lens, field, 0.55, size=16, method="focal")
    truth = rs_lens_psf(lens, field, 0.55, p.center_mm, 16, p.pixel_mm, radial_nodes=32, angular_nodes=128)
    err = float(np.abs(p.data - truth).max() / truth.max())
    assert err < tol, err
    reasons = " ".join(p.plan["reasons"])
    assert "ray landings" in reasons
    if field == 40.0:
        assert "rays land in the taper" in reasons
