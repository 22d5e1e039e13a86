"""Ray-wave PSFs against analytic diffraction, energy conservation and stability cases."""

import numpy as np
import pytest

import rwwarp as rw
from rwwarp.lens import Lens, Surface, Sensor
from rwwarp import analytic
from rwwarp.wave.plan import Plan
from rwwarp.errors import SamplingWarning, LensError

from _mirror import mirrored_truth


def thin_lens(side_mm=2.0, f=100.0, shape="square", pixel=None, doe=None, levels=None):
    pixel = pixel or 0.55e-3 * f / side_mm / 4
    surfs = [Surface(type="aperture", semi_diameter=side_mm / 2, shape=shape, stop=True),
             Surface(type="thin_lens", focal_length=f, semi_diameter=side_mm, shape="square",
                     thickness=0.0 if doe else f)]
    if doe:
        surfs.append(Surface(type="doe", semi_diameter=side_mm, shape="square", thickness=f, profile=doe,
                             levels=levels))
    return Lens(surfs, Sensor(pixel, (1000, 1000)), wavelengths_um=[0.55])


def rel_l2(a, b):
    return np.linalg.norm(a - b) / np.linalg.norm(b)


def test_square_aperture_matches_pixel_integrated_sinc2():
    lens = thin_lens(2.0, shape="square")
    p = rw.psf(lens, 0.0, 0.55, size=64)
    x, y = p.coords_mm()
    ref = analytic.square_aperture_pixel_psf(x, y, lens.sensor.pixel_pitch, 2.0, 100.0, 0.55)
    assert rel_l2(p.data, ref) < 1e-3
    # normalisation: fraction of entering power in the patch equals the analytic window energy
    h = lens.sensor.pixel_pitch / 2
    e = analytic.square_aperture_window_energy(x[0] - h, x[-1] + h, y[0] - h, y[-1] + h, 2.0, 100.0, 0.55)
    assert p.data.sum() == pytest.approx(e, abs=2e-3)


def test_circular_aperture_matches_airy():
    lens = thin_lens(2.0, shape="circle")
    p = rw.psf(lens, 0.0, 0.55, size=64)
    x, y = p.coords_mm()
    ref = analytic.circular_aperture_pixel_psf(x, y, lens.sensor.pixel_pitch, 2.0, 100.0, 0.55)
    assert rel_l2(p.data, ref) < 8e-4  # measured 3.8e-4 (CPU, PoCL)


def test_paper_and_energy_conventions_agree_for_uniform_rays():
    lens = thin_lens(2.0)
    a = rw.psf(lens, 0.0, 0.55, size=32, amplitude="energy").data
    b = rw.psf(lens, 0.0, 0.55, size=32, amplitude="paper").data
    assert rel_l2(b, a) < 6e-3  # paper mode smears aperture edges over a sample (bilinear splat); measured 3.1e-3


def test_energy_large_patch_collects_almost_all_power():
    lens = thin_lens(2.0, pixel=0.55e-3 * 100 / 2 / 2)
    p = rw.psf(lens, 0.0, 0.55, size=256)
    assert 0.99 <= p.data.sum() <= 1.0 + 1e-6


def test_half_vignetted_field_is_finite_and_normalised():
    # an aperture behind the lens clips part of the off-axis beam
    surfs = [Surface(type="aperture", semi_diameter=1.0, shape="circle", stop=True),
             Surface(type="thin_lens", focal_length=100.0, semi_diameter=2.0, thickness=5.0),
             Surface(type="aperture", semi_diameter=0.9, shape="circle", thickness=95.0)]
    lens = Lens(surfs, Sensor(0.0068, (3000, 3000)), wavelengths_um=[0.55])
    p = rw.psf(lens, 1.0, 0.55, size=48)
    assert np.all(np.isfinite(p.data))
    vf = p.info["valid_fraction"]
    # the beam (radius 0.95 mm at the second aperture, centred 5 tan(1 deg) = 0.0873 mm off the axis) keeps the
    # overlap of two discs with the 0.9 mm aperture: 0.88219 of its power; measured 0.88292 (the ray grid)
    d, r1, r2 = 5.0 * np.tan(np.radians(1.0)), 0.95, 0.9
    overlap = (r1 * r1 * np.arccos((d * d + r1 * r1 - r2 * r2) / (2 * d * r1))
               + r2 * r2 * np.arccos((d * d + r2 * r2 - r1 * r1) / (2 * d * r2))
               - 0.5 * np.sqrt((-d + r1 + r2) * (d + r1 - r2) * (d - r1 + r2) * (d + r1 + r2)))
    assert abs(vf - overlap / (np.pi * r1 * r1)) < 2e-3
    assert p.data.sum() <= vf + 1e-6


def test_undersampled_explicit_plan_warns_naming_the_criterion():
    lens = thin_lens(2.0)
    with pytest.warns(SamplingWarning, match="Nyquist"):
        rw.psf(lens, 0.0, 0.55, size=16, plan=Plan(0.05, 50, 128, 200))


def test_float32_trace_needs_the_reference_phase():
    # object at 10 m: absolute OPL ~ 1e4 mm ~ 2e7 waves; float32 cannot hold the phase without a reference
    surfs = [Surface(type="aperture", semi_diameter=1.0, shape="square", stop=True),
             Surface(type="thin_lens", focal_length=100.0, semi_diameter=2.0, shape="square",
                     thickness=1.0 / (1.0 / 100.0 - 1.0 / 10000.0))]
    lens = Lens(surfs, Sensor(0.0069, (1000, 1000)), object_distance=10000.0, wavelengths_um=[0.55])
    ref = rw.psf(lens, 0.0, 0.55, size=32).data
    good = rw.psf(lens, 0.0, 0.55, size=32, dtype="float32").data
    bad = rw.psf(lens, 0.0, 0.55, size=32, dtype="float32", use_reference=False).data
    # measured: 0.055 with the reference (float32 ray positions and tube areas), 0.99 without
    assert rel_l2(good, ref) < 0.07
    assert rel_l2(bad, ref) > 0.5


def test_ray_model_refuses_discontinuous_doe_and_ray_wave_handles_it():
    rng = np.random.default_rng(0)
    pm = {"kind": "pixel_map", "pitch": 0.1, "data": (rng.integers(0, 16, (24, 24)) * 2 * np.pi / 16).tolist()}
    lens = thin_lens(2.0, doe=pm)
    with pytest.raises(LensError, match="discontinuous"):
        rw.psf(lens, 0.0, 0.55, model="ray", size=16)
    p = rw.psf(lens, 0.0, 0.55, size=32)
    assert np.all(np.isfinite(p.data)) and 0 < p.data.sum() <= 1.0


def test_fresnel_zone_doe_focal_length_scales_with_wavelength():
    # DOE phase -pi r^2/(lambda0 f0) with lambda0 = 0.55 um, f0 = 100 mm (no refractive power): paraxial
    # focal length f0 * lambda0 / lambda (substrate dispersion switched off with a model glass of vd huge)
    surfs = [Surface(type="aperture", semi_diameter=1.0, shape="circle", stop=True),
             Surface(type="doe", semi_diameter=1.0, shape="circle", thickness=100.0,
                     profile={"kind": "fresnel", "focal_length": 100.0}, material="1.5/1e9")]
    lens = Lens(surfs, Sensor(0.005, (1000, 1000)), wavelengths_um=[0.55])
    for wl in (0.45, 0.55, 0.65):
        assert lens.efl(wl) == pytest.approx(100.0 * 0.55 / wl, rel=1e-6)


# tolerances ~2x the measured distances to the RS summation: a 1.3e-5, b 1.8e-4, c 4.0e-4
@pytest.mark.parametrize("kind,tol", [("a", 3e-5), ("b", 4e-4), pytest.param("c", 1e-3, marks=pytest.mark.slow)])
def test_validation_doe_cases_against_rayleigh_sommerfeld(kind, tol):
    # the paper's accuracy study: thin lens + DOE vs a direct RS summation (independent of the ASM code)
    from rwwarp.validate import _case_lens
    from rwwarp.ground_truth import rs_thin_lens_psf
    side, pixel = 2.0, 0.55e-3 * 100 / 2.0 / 3
    lens, dist, phase = _case_lens(kind, side, 100.0, 1000.0, pixel, 0.02)
    p = rw.psf(lens, 0.0, 0.55, size=16, nyquist_safety=3.0)
    x, y = p.coords_mm()
    # the scenes are even in x and y (square aperture, rotationally symmetric DOE or its symmetric pixel map, all
    # centred): the truth on one quadrant of pixels, mirrored (tests/rwwarp/_mirror.py), equals the one summed
    # on every pixel to 2.3e-16 (measured on a, b, c) at a quarter of the cost
    gt = mirrored_truth(lambda qx, qy: rs_thin_lens_psf(100.0, "square", side / 2, 0.55, dist, qx, qy, pixel,
                                                        doe_phase=phase), x, y)
    assert rel_l2(p.data, gt) < tol


def test_sixteen_level_quantisation_efficiency_is_sinc2():
    # a Fresnel-zone DOE alone (f0 = 100 mm) focusing a plane wave: quantising it to 16 levels moves
    # 1 - sinc^2(1/16) of the focused power to other orders (scalar diffraction efficiency)
    def fz(levels):
        s = [Surface(type="aperture", semi_diameter=1.0, shape="circle", stop=True),
             Surface(type="doe", semi_diameter=1.0, shape="circle", thickness=100.0,
                     profile={"kind": "fresnel", "focal_length": 100.0}, material="1.5/1e9", levels=levels)]
        return Lens(s, Sensor(0.0055, (4000, 4000)), wavelengths_um=[0.55])
    a = rw.psf(fz(None), 0.0, 0.55, size=32).data
    b = rw.psf(fz(16), 0.0, 0.55, size=32).data
    core = slice(12, 20)  # the focal spot (first Airy zero at 4 px)
    assert b[core, core].sum() / a[core, core].sum() == pytest.approx(np.sinc(1 / 16) ** 2, abs=2e-3)


def test_deterministic_psf_matches_the_default_and_bad_flags_are_refused():
    """rw.psf(deterministic=True): the fixed-point splat's PSF against the default float splat's, Cooke triplet
    at 14 deg (focal path in double precision, 16 px): measured 2.3e-15 relative on the CPU; tolerance 1e-13.
    (With the CPU's default single-precision focal products the two differ by 6.6e-11: their rounding.) A
    non-boolean flag is refused by name."""
    import rwwarp as rw
    lens = rw.load_lens("cooke_triplet")
    a = rw.psf(lens, 14.0, 0.55, size=16, focal_precision="double").data
    b = rw.psf(lens, 14.0, 0.55, size=16, deterministic=True, focal_precision="double").data
    assert np.linalg.norm(a - b) <= 1e-13 * np.linalg.norm(a)
    with pytest.raises(TypeError, match="deterministic"):
        rw.psf(lens, 0.0, 0.55, size=8, deterministic="yes")
