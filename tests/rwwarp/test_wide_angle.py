"""Refractive PSFs at wide field angles against the independent truth (issue 27: <= 2e-4 of the peak).

The reference is :func:`rwwarp.ground_truth.rs_lens_psf`: its own trace on a polar pupil rule, ray-tube
amplitudes by finite differences, the exact Rayleigh-Sommerfeld kernel (and its z-derivative for the flux)
summed to every pixel node, no FFT, no sampled field (converged here to 1.5e-11 of the peak: 32 x 128 against
64 x 256 pupil nodes at 40 deg). The lens is a BK7 singlet (stop 0.25 mm, R 6 / -30 mm, f ~ 10 mm, F/20) whose
35 / 40 deg beams are aberrated spots 440 / 660 um wide (many Airy radii): the 16 px patch about the chief ray
lies inside the geometric spot, the case the focal planner's ray-landing rules are for
(:func:`rwwarp.wave.plan.plan_focal`, ``FOCAL_RAY_SPREAD`` and ``FOCAL_LIT_SHIFT_MARGIN``).
"""
import re
import warnings

import numpy as np
import pytest

import rwwarp as rw
from rwwarp.ground_truth import rs_lens_psf
from rwwarp.lens import Lens, Sensor, Surface

from _mirror import mirrored_patch_truth  # noqa: E402


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


def _cooke_defocused(mm=5.0):
    """The bundled Cooke triplet (EPD 10 mm, F/5) with its sensor ``mm`` behind focus: the issue's wide-angle study's
    defocused case, a ~1 mm geometric spot about a 16 px patch of 5 um (~47 waves of defocus over the pupil)."""
    from dataclasses import replace
    lens = rw.load_lens("cooke_triplet")
    last = replace(lens.surfaces[-1], thickness=lens.surfaces[-1].thickness + mm)
    return replace(lens, surfaces=[*lens.surfaces[:-1], last])


@pytest.mark.slow
def test_cooke_defocused_capped_plan_states_its_error():
    """A beam defocused by 5 mm asks for a ray-landing period of a 9,600^2 wave-plane grid; the plan caps it at
    FOCAL_RAY_MAX_GRID (2048: 2258^2 samples) and must say what that costs. Against rs_lens_psf (128 x 256 pupil
    nodes; 256 x 256 agreed to 1e-9 of the peak, and the sequence 4097^2 / 8193^2 grids gave 1.4e-3 / 2.5e-4, so the
    error is the cap's, not the truth's) the PSF errs by 7.7e-3 of the peak; the plan's estimate (the rules' 2e-4
    grown by the capped period ratio to the power FOCAL_RAY_CAP_POWER) must be within 2x of it, and a
    SamplingWarning must carry it; with ``tolerance=1e-3`` the cap gives way and the PSF meets it. (Radial nodes of 384 and more put the outermost node within rs_lens_psf's
    finite-difference step of the rim: the truth's own failure there, not a convergence check.)"""
    lens = _cooke_defocused()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        p = rw.psf(lens, 0.0, 0.532, size=16)
    truth = mirrored_patch_truth(
        lambda c, n: rs_lens_psf(lens, 0.0, 0.532, c, n, p.pixel_mm, radial_nodes=128, angular_nodes=256,
                                 pixel_nodes=6), p.center_mm, 16, p.pixel_mm)
    err = float(np.abs(p.data - truth).max() / truth.max())
    sampling = [w for w in caught if issubclass(w.category, rw.SamplingWarning) and "capped" in str(w.message)]
    assert len(sampling) == 1, [str(w.message) for w in caught]
    est = float(re.search(r"sampling error is ~([0-9.e+-]+) of the peak", str(sampling[0].message)).group(1))
    assert 0.5 < est / err < 2.0, (est, err)
    assert 3e-3 < err < 2e-2, err   # the capped plan's error is real: the warning is not a false alarm
    # with a tolerance the cap gives way (to 5042^2 samples here): measured 8.4e-4 <= 1e-3, and no capped warning
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        q = rw.psf(lens, 0.0, 0.532, size=16, tolerance=1e-3, method="focal")
    assert not [w for w in caught if "capped" in str(w.message)], [str(w.message) for w in caught]
    assert q.plan["n_grid"] > p.plan["n_grid"]
    assert float(np.abs(q.data - truth).max() / truth.max()) < 1e-3
