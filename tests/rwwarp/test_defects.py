"""Regression tests for the physics defects of issue 11, each against physics: an analytic PSF or
conjugate, energy conservation, or an independent trace.
"""
import math

import numpy as np
import pytest

import rwwarp as rw
from rwwarp import analytic, paraxial
from rwwarp.errors import LensError
from rwwarp.lens import Lens, Sensor, Surface


def rel_l2(a, b):
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


def _blank_doe(thickness, sd=1.0, shape="square", levels=None):
    return Surface(type="doe", semi_diameter=sd, shape=shape, thickness=thickness, levels=levels,
                   profile={"kind": "even_poly", "norm_radius": sd, "coefficients": [0.0, 0.0]})


# ------------------------------------------------------------------ defect 1: paraxial-wave object distance
def test_paraxial_wave_uses_object_distance_analytic_conjugate():
    """Ideal f = 100 mm lens, 2 mm square aperture, object at 300 mm: the image lies at 150 mm
    (1/v = 1/f - 1/u), where the sensor is. The paraxial-wave PSF must be the focused sinc^2 of a
    2 mm square at 150 mm (closed form, pixel-integrated); before the fix the model put the object at
    infinity (image at 100 mm, 50 mm of defocus: relative L2 error 0.997)."""
    lens = Lens([Surface(type="aperture", semi_diameter=1.0, shape="square"),
                 Surface(type="thin_lens", focal_length=100.0), _blank_doe(150.0)],
                Sensor(0.002, (2000, 2000)), math.inf, [0.55])
    p = rw.psf(lens, 0.0, 0.55, model="paraxial-wave", size=32, object_distance_mm=300.0)
    x, y = p.coords_mm()
    ref = analytic.square_aperture_pixel_psf(x, y, p.pixel_mm, 2.0, 150.0, 0.55)
    # measured 1.06e-3 (the ray-wave model of the same lens at 300 mm: the same to 1e-8; the residual is
    # the sampling of the energy splat on the aperture edge plus the Fresnel/Fraunhofer difference)
    assert rel_l2(p.data, ref) < 2e-3
    # the lens's own object distance is used when none is passed
    p2 = rw.psf(lens.replace(object_distance=300.0), 0.0, 0.55, model="paraxial-wave", size=32)
    assert rel_l2(p2.data, ref) < 2e-3


def test_paraxial_wave_field_at_finite_object_lands_at_analytic_image_height():
    """Object at 300 mm, field 2 deg (object height 300 tan 2deg below the axis, pupil at the lens): the
    image at 150 mm has height 150 tan(2 deg) = 5.238115 mm (magnification -1/2). Measured centroid
    5.238101 mm (1.4e-5 mm off: the sinc^2 tails cut by the 32-pixel patch); bound 5e-5 mm."""
    lens = Lens([Surface(type="aperture", semi_diameter=1.0, shape="square"),
                 Surface(type="thin_lens", focal_length=100.0), _blank_doe(150.0)],
                Sensor(0.002, (20000, 20000)), 300.0, [0.55])
    p = rw.psf(lens, 2.0, 0.55, model="paraxial-wave", size=32)
    _, y = p.coords_mm()
    cy = float((p.data.sum(1) * y).sum() / p.data.sum())
    assert abs(cy - 150.0 * math.tan(math.radians(2.0))) < 5e-5


# ------------------------------------------------------------------ defect 9: pupil-edge rays
def test_pupil_edge_rays_are_kept_on_a_401_grid():
    """The 401 x 401 'edges' grid holds exactly the integer points i^2 + j^2 <= 200^2 (125629 of them,
    20 on the circle itself: (0, 200), (120, 160), (56, 192), ...). Every one enters the Cooke triplet
    (no vignetting on axis, floating stop): the host grid and the kernel share one edge tolerance.
    Before the fix the kernel dropped the 4 whose u^2 + v^2 rounds to 1 + 2e-16."""
    from rwwarp.trace import Tracer, pupil_grid
    i = np.arange(-200, 201)
    exact = int(np.sum(i[:, None] ** 2 + i[None, :] ** 2 <= 200 ** 2))
    assert exact == 125629
    u, v, _ = pupil_grid(401, "circle", layout="edges")
    assert len(u) == exact
    lens = rw.load_lens("cooke_triplet")
    rays = Tracer(lens, [0.5876]).trace([0.0], grid=401, layout="edges").numpy()
    assert int(rays["valid"].sum()) == exact
    # the same tolerance at a surface's clear aperture: a stop whose semi-diameter is exactly the
    # marginal ray height on axis (a thin-lens system: the paraxial marginal ray is exact there)
    thin = Lens([Surface(type="aperture", semi_diameter=2.0, stop=True),
                 Surface(type="thin_lens", focal_length=50.0, thickness=10.0),
                 Surface(type="aperture", semi_diameter=2.0 * 40.0 / 50.0, thickness=40.0)],
                Sensor(0.004, (1000, 1000)), math.inf, [0.55])
    rays = Tracer(thin, [0.55]).trace([0.0], grid=401, layout="edges").numpy()
    assert int(rays["valid"].sum()) == exact


# ------------------------------------------------------------------ defect 4: ray aiming
def _chief_at_stop(lens, fields, aim):
    from rwwarp.trace import Tracer
    tr = Tracer(lens, [0.5876])
    return tr.trace(fields, pupil=(np.zeros(1), np.zeros(1), 1.0), ray_aiming=aim,
                    upto=lens.stop_index + 1).numpy()


def test_ray_aiming_hits_the_stop_centre_and_default_is_paraxial_pupil():
    """Default (documented, Zemax's): no aiming, the chief ray of the Cooke triplet at 20 deg misses the
    real stop centre by its pupil aberration, 0.2259 mm (0.0682 mm at 14 deg). Aimed: it hits the stop
    centre; measured 5.6e-16 mm (rounding), bound 1e-10 mm (the Newton stop is 1e-12 mm)."""
    lens = rw.load_lens("cooke_triplet")
    free = _chief_at_stop(lens, [14.0, 20.0], False)["pos"][:, 0, :2]
    assert free[1, 1] == pytest.approx(0.225895, abs=1e-5)
    aimed = _chief_at_stop(lens, [14.0, 20.0], True)
    assert aimed["valid"].all()
    assert np.max(np.abs(aimed["pos"][:, 0, :2])) < 1e-10


def test_ray_aiming_ignores_clear_apertures():
    """A clear aperture (4 mm on the first surface) that the 20 deg chief ray passes outside (it meets
    that surface 4.51 mm off axis): aiming must still find the chief ray (vignetted, as Zemax aims),
    the same pupil position as for the lens without the aperture (an independent run), to 1e-12 mm;
    before the fix it raised GeometryError."""
    from rwwarp.trace import Tracer
    lens = rw.load_lens("cooke_triplet")
    clipped = lens.with_surface(0, semi_diameter=4.0)
    a_free = Tracer(lens, [0.5876]).sources([20.0], ray_aiming=True)["aim"]
    a_clip = Tracer(clipped, [0.5876]).sources([20.0], ray_aiming=True)["aim"]
    assert np.max(np.abs(a_free - a_clip)) < 1e-12
    assert not _chief_at_stop(clipped, [20.0], True)["valid"].any()  # the chief ray itself is vignetted


# ------------------------------------------------------------------ defect 5: no ray reaches the image
def test_fully_vignetted_field_raises_in_spot_rms_and_ray_model():
    """A489 + DOE at 60 deg: every ray misses a lens surface (the 6.35 mm clear apertures). spot_rms
    returned NaN and the ray model an all-zero PSF centred at (nan, nan); both now raise the ray-wave
    model's error, naming the field."""
    lens = rw.load_lens("a489_doe")
    with pytest.raises(LensError, match="no ray") as e1:
        rw.spot_rms(lens, 60.0, 0.55)
    with pytest.raises(LensError, match="no rays reach the sensor") as e2:
        rw.psf(lens, 60.0, 0.55, model="ray", size=8)
    assert "60" in str(e1.value) and "field 60" in str(e2.value)
    # a field that is not vignetted keeps its power: the ray PSF's patch plus what falls outside it is
    # the traced fraction (energy conservation of the binning)
    p = rw.psf(lens, 5.0, 0.55, model="ray", size=256)
    assert 0.0 < p.data.sum() <= p.info["valid_fraction"] + 1e-12


# ------------------------------------------------------------------ defect 6: blank DOE with levels
@pytest.mark.parametrize("model", ["ray-wave", "paraxial-wave", "ray"])
def test_blank_doe_with_levels_is_a_plain_window(model):
    """Quantising a flat phase leaves it flat: a blank DOE with 16 levels (DeepLens's default
    fabrication step; the paper's baseline arm) must act as no DOE. Before the fix the plan took its
    'feature size' (inf) and raised OverflowError. Ideal f = 100 mm lens, 2 mm square: the ray-wave and
    paraxial-wave PSFs equal the closed-form pixel-integrated sinc^2 (measured 1.06e-3, as without
    levels); the ray model (geometric, a perfect focus on a pixel corner) keeps all the power within
    the 2 x 2 pixels around the focus."""
    lens = Lens([Surface(type="aperture", semi_diameter=1.0, shape="square"),
                 Surface(type="thin_lens", focal_length=100.0), _blank_doe(100.0, levels=16)],
                Sensor(0.002, (2000, 2000)), math.inf, [0.55])
    p = rw.psf(lens, 0.0, 0.55, model=model, size=32)
    if model == "ray":
        c = p.data.shape[0] // 2
        assert p.data[c - 1:c + 1, c - 1:c + 1].sum() == pytest.approx(1.0, abs=1e-12)
        return
    x, y = p.coords_mm()
    ref = analytic.square_aperture_pixel_psf(x, y, p.pixel_mm, 2.0, 100.0, 0.55)
    assert rel_l2(p.data, ref) < 1.2e-3  # measured 5.4e-4 (ray-wave and paraxial-wave alike)


# ------------------------------------------------------------------ defect 7: stop apertures in Zemax files
def _cooke_zmx_text():
    from importlib import resources
    from rwwarp.io.zemax import _decode
    raw = (resources.files("rwwarp") / "lenses" / "cooke_triplet.zmx").read_bytes()
    return _decode(raw).replace("\r\n", "\n")


def _write(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return p


def _rms_um(xy):
    return 1e3 * float(np.sqrt(np.mean(np.sum((xy - xy.mean(0)) ** 2, axis=1))))


def test_clap_on_the_stop_clips_under_enpd(tmp_path):
    """Cooke triplet (ENPD 10: the stop floats; paraxially its beam is 3.80 mm high there) with a hard
    CLAP of 3.5 mm on the stop. Reference: the file without the CLAP traced to the stop and on to the
    image, and the rays farther than 3.5 mm from the axis on the stop removed by hand (numpy). Before the
    fix the CLAP was dropped: 4.829 / 15.218 um at 0 / 14 deg (201 grid) instead of the clipped 5.242 /
    13.342 um; the fixed reader agrees with the hand-clipped reference to rounding, bound 1e-9."""
    from rwwarp.trace import Tracer, pupil_grid
    text = _cooke_zmx_text().replace("SURF 4\n  STOP\n", "SURF 4\n  STOP\n  CLAP 0 3.5 0 0 0\n")
    clipped = rw.load_lens(_write(tmp_path, "clap.zmx", text))
    ref = rw.load_lens(_write(tmp_path, "plain.zmx", _cooke_zmx_text()))
    tr = Tracer(ref, [0.5876])
    u, v, cell = pupil_grid(201, "circle", layout="edges")
    for field in (0.0, 14.0):
        src = tr.sources([field])
        rays = tr._run(src, u, v, cell, keep=(ref.stop_index,))
        at_stop = rays.kept[ref.stop_index][0].numpy()
        r = rays.numpy()
        inside = r["valid"][0] & (np.hypot(at_stop[:, 0], at_stop[:, 1]) <= 3.5)
        want = _rms_um(r["pos"][0, inside, :2])
        got = rw.spot_rms(clipped, field, 0.5876, grid=201)
        free = rw.spot_rms(ref, field, 0.5876, grid=201)
        assert 0 < inside.sum() < r["valid"][0].sum()
        assert got == pytest.approx(want, rel=1e-9)
        assert abs(free - want) > 1e-3 * want  # the aperture matters
    assert clipped.entrance_pupil_diameter == 10.0


def test_floa_stop_sets_the_pupil_and_does_not_clip(tmp_path):
    """FLOA (float by stop size) with the stop's DIAM at 3.8045565 mm: the entrance pupil is the paraxial
    image of the stop, 10 mm across (the ENPD file's, analytic y-nu conjugate), and Zemax does not clip
    real rays at the stop: the spots equal those of the ENPD file (which floats the stop) to 1e-12
    (measured 0). Before the fix the real rays were clipped at the paraxial semi-diameter (pupil
    aberration): spots off by +0.92 / -0.40 / -0.23 % at 0 / 14 / 20 deg."""
    ref = rw.load_lens(_write(tmp_path, "plain.zmx", _cooke_zmx_text()))
    sd = paraxial.stop_semi_diameter(ref, 0.5875618)  # at the primary wavelength (PWAV 2)
    text = _cooke_zmx_text().replace("ENPD 1.0E+1\n", "FLOA\n").replace(
        "SURF 4\n  STOP\n  TYPE STANDARD\n  CURV 0.04928069891858434 0 0 0 0 \"\"\n  HIDE 0 0 0 0 0 0 0 0 0 0\n"
        "  MIRR 2 0\n  DISZ 4.75041\n  DIAM 0 0 0 0 1 \"\"\n",
        "SURF 4\n  STOP\n  TYPE STANDARD\n  CURV 0.04928069891858434 0 0 0 0 \"\"\n  HIDE 0 0 0 0 0 0 0 0 0 0\n"
        f"  MIRR 2 0\n  DISZ 4.75041\n  DIAM {sd!r} 1 0 0 1 \"\"\n")
    assert "FLOA" in text and repr(sd) in text
    floa = rw.load_lens(_write(tmp_path, "floa.zmx", text))
    assert floa.entrance_pupil_diameter == pytest.approx(10.0, rel=1e-13)
    for field in (0.0, 14.0, 20.0):
        assert rw.spot_rms(floa, field, 0.5876, grid=201) == pytest.approx(
            rw.spot_rms(ref, field, 0.5876, grid=201), rel=1e-12)


# ------------------------------------------------------------------ defect 8: PARAXIAL at any conjugate
_HEAD = """VERS 190513 80 123457 L123457
MODE SEQ
NAME collimator and camera
UNIT MM X W X CM MR CPMM
ENPD 4
FTYP 0 0 1 1 0 0 0
WAVM 1 0.55 1
PWAV 1
SURF 0
  TYPE STANDARD
  DISZ {obj}
"""


def _zmx(tmp_path, surfaces, obj="50", name="lens.zmx"):
    text = _HEAD.format(obj=obj)
    for k, body in enumerate(surfaces, start=1):
        text += f"SURF {k}\n" + "".join(f"  {line}\n" for line in body)
    text += f"SURF {len(surfaces) + 1}\n  TYPE STANDARD\n  CURV 0.0\n  DISZ 0\n"
    return _write(tmp_path, name, text)


def test_paraxial_collimator_with_object_at_its_front_focal_plane(tmp_path):
    """Object 50 mm in front of a PARAXIAL f = 50 mm collimator (its front focal plane: image at
    infinity), a PARAXIAL f = 100 mm camera 20 mm behind it, sensor at its focal plane. Analytic: perfect
    imaging with magnification -f2/f1 = -2 (object height -50 tan(theta) -> image 100 tan(theta)), and
    on axis the Airy pattern of the 4 mm collimated beam at f = 100 mm. Before the fix: GeometryError
    'image at infinity is not supported'. Measured: RMS spot 0 um (rounding, < 1e-9); image height
    error < 1e-9 mm; ray-wave PSF against the pixel-integrated Airy 3.1e-4 relative L2 (bound 1e-3: the
    energy splat at the pupil edge, as in the ideal-lens validation)."""
    path = _zmx(tmp_path, [["STOP", "TYPE PARAXIAL", "CURV 0", "DISZ 20", "PARM 1 50"],
                           ["TYPE PARAXIAL", "CURV 0", "DISZ 100", "PARM 1 100"]])
    lens = rw.load_lens(path)
    assert lens.object_distance == 50.0
    assert math.isinf(paraxial.thin_lens_conjugates(lens, 0.55, 0)[1])
    for field in (0.0, 1.0):
        assert rw.spot_rms(lens, field, 0.55, grid=101) < 1e-9
        xy = rw.spot_diagram(lens, field, 0.55, grid=11)[0]
        assert np.max(np.abs(xy[:, 1] - 100.0 * math.tan(math.radians(field)))) < 1e-9
    p = rw.psf(lens, 0.0, 0.55, size=32)
    x, y = p.coords_mm()
    ref = analytic.circular_aperture_pixel_psf(x, y, p.pixel_mm, 4.0, 100.0, 0.55)
    assert rel_l2(p.data, ref) < 6e-4  # measured 3.1e-4


def test_thin_lens_follows_an_object_distance_override():
    """The ideal lens's path correction depends on its conjugates: tracing a thin lens (f = 100 mm, object
    at infinity in the file, aperture 80 mm: NA 0.26) with object_distance=300 must give a perfect
    spherical wave converging to 150 mm (analytic conjugate): equal optical path from the source to the
    image point for every ray (measured spread 1.7e-13 mm; bound 1e-10 mm). Before the fix the
    conjugates of the lens's own object distance were used (path spread 5.7e-4 mm, one wave)."""
    from rwwarp.trace import Tracer
    lens = Lens([Surface(type="aperture", semi_diameter=40.0, stop=True),
                 Surface(type="thin_lens", focal_length=100.0, thickness=150.0)],
                Sensor(0.002, (2000, 2000)), math.inf, [0.55])
    r = Tracer(lens, [0.55]).trace([0.0], grid=21, object_distance=300.0).numpy()
    ok = r["valid"][0]
    pos, d, opl = r["pos"][0, ok], r["dir"][0, ok], r["opl"][0, ok]
    img = np.array([0.0, 0.0, 150.0])
    t = (img[2] - pos[:, 2]) / d[:, 2]
    hit = pos + t[:, None] * d
    assert np.max(np.abs(hit[:, :2])) < 1e-9  # all rays meet at the analytic image point
    total = opl + t
    assert np.ptp(total) < 1e-10


def test_errors_use_the_files_surface_numbers(tmp_path):
    """A Zemax stop placed at the focus of a PARAXIAL lens (SURF 2; rwwarp's surface 1) has no entrance
    pupil: the error must say SURF 2, the file's numbering, never the internal index."""
    path = _zmx(tmp_path, [["TYPE PARAXIAL", "CURV 0", "DISZ 50", "PARM 1 50"],
                           ["STOP", "TYPE STANDARD", "CURV 0", "DISZ 10"]], obj="INFINITY")
    lens = rw.load_lens(path)
    with pytest.raises(LensError) as e:
        paraxial.pupils(lens, 0.55)
    assert "SURF 2" in str(e.value) and "surface 1" not in str(e.value)
