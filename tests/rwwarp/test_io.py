"""Lens files: native JSON round trips, Zemax .zmx and DeepLens JSON readers, and their error messages."""
import copy
import json
import math
from pathlib import Path

import numpy as np
import pytest

import rwwarp.lens as lensmod
from rwwarp import doe
from rwwarp.errors import GeometryError, GeometryWarning, GlassError, LensError, LensFileError
from rwwarp.io.deeplens import lens_from_deeplens
from rwwarp.io.zemax import read_zmx
from rwwarp.io import load_lens
from rwwarp.lens import Lens

BUNDLED = Path(lensmod.__file__).parent / "lenses"
BUNDLED_JSON = sorted(p.name for p in BUNDLED.glob("*.json"))


# ------------------------------------------------------------------------------------------ native
def test_bundled_lenses_present():
    assert {"cooke_triplet.json", "a489_doe.json", "thin_lens_doe.json"} <= set(BUNDLED_JSON)
    assert (BUNDLED / "cooke_triplet.zmx").exists()


@pytest.mark.parametrize("name", BUNDLED_JSON)
def test_native_round_trip_is_exact(name):
    lens = load_lens(BUNDLED / name)
    d1 = lens.to_dict()
    d2 = Lens.from_dict(json.loads(json.dumps(d1))).to_dict()
    assert d1 == d2
    # the bundled files are stored in canonical form (exactly what to_dict writes)
    assert json.loads((BUNDLED / name).read_text()) == d1


def test_bundled_by_name():
    assert load_lens("cooke_triplet").source == str(BUNDLED / "cooke_triplet.json")
    assert load_lens("cooke_triplet.zmx").source == str(BUNDLED / "cooke_triplet.zmx")


def test_cooke_triplet_paraxial_data():
    # Zemax tutorial Cooke triplet at the d line: EFL 50.021351 mm, BFL 42.436440 mm (Zemax's values for this file)
    lens = load_lens("cooke_triplet")
    assert lens.stop_index == 3 and lens.entrance_pupil_diameter == 10.0
    assert lens.efl(0.5875618) == pytest.approx(50.021351, abs=1e-6)
    assert lens.bfl(0.5875618) == pytest.approx(42.436440, abs=1e-6)


def test_a489_positions():
    lens = load_lens("a489_doe")
    np.testing.assert_allclose(lens.vertex_z, [0.0, 0.1, 7.6, 8.3098], atol=1e-12)
    assert lens.sensor_z == pytest.approx(11.257, abs=1e-12)
    assert lens.doe_index == 3 and lens.stop_index == 0 and lens.object_distance == 10000.0
    s = lens.surfaces[1]
    assert (s.radius, s.conic, s.material) == (4.7531, -1.2051, "H-K51")
    assert s.aspheric == [5.33e-4, 1.12e-5, -3.75e-7, -7.63e-9, 1.36e-10]
    assert lens.sensor.half_size == pytest.approx((1.5, 1.5))


def test_thin_lens_doe_focus():
    lens = load_lens("thin_lens_doe")
    assert lens.efl(0.55) == pytest.approx(100.0, rel=1e-14)
    assert lens.sensor_z == 100.0 and lens.surfaces[0].shape == "square"


# ------------------------------------------------------------------------------------------ Zemax
def _cooke_text():
    raw = (BUNDLED / "cooke_triplet.zmx").read_bytes()
    assert raw[:2] == b"\xff\xfe" and b"\r\x00\n\x00" in raw  # UTF-16 LE, BOM, CRLF
    return raw.decode("utf-16")


def _write(tmp_path, text, name="lens.zmx", encoding="ascii"):
    p = tmp_path / name
    p.write_bytes(text.encode(encoding) if encoding != "utf-16" else b"\xff\xfe" + text.encode("utf-16-le"))
    return p


def test_zmx_utf16_and_ascii_identical(tmp_path):
    text = _cooke_text()
    a = read_zmx(BUNDLED / "cooke_triplet.zmx")
    b = read_zmx(_write(tmp_path, text.replace("\r\n", "\n")))
    assert a.to_dict() == b.to_dict()
    native = load_lens("cooke_triplet")
    assert a.surfaces == native.surfaces
    assert a.wavelengths_um == native.wavelengths_um
    assert a.fields_deg == native.fields_deg == [0.0, 14.0, 20.0]
    assert a.entrance_pupil_diameter == 10.0 and math.isinf(a.object_distance)


ZMX_HEAD = """VERS 190513 80 123457 L123457
MODE SEQ
NAME test lens
UNIT {unit} X W X CM MR CPMM
{aperture}
FTYP 0 0 2 2 0 0 0
XFLN 0 1 0 0 0 0 0 0 0 0 0 0
YFLN 0 2 0 0 0 0 0 0 0 0 0 0
WAVM 1 0.5 1
WAVM 2 0.6 1
WAVM 3 0.55 1
PWAV 2
SURF 0
  TYPE STANDARD
  CURV 0.0
  DISZ {obj}
"""


def _zmx(surfaces, unit="MM", aperture="ENPD 4", obj="INFINITY"):
    text = ZMX_HEAD.format(unit=unit, aperture=aperture, obj=obj)
    for k, body in enumerate(surfaces, start=1):
        text += f"SURF {k}\n" + "".join(f"  {line}\n" for line in body)
    text += f"SURF {len(surfaces) + 1}\n  TYPE STANDARD\n  CURV 0.0\n  DISZ 0\n"
    return text


def test_zmx_surface_types(tmp_path):
    text = _zmx([
        ["STOP", "TYPE STANDARD", "CURV 0", "DISZ 1", 'DIAM 2.5 1 0 0 1 ""'],
        ["TYPE EVENASPH", "CURV 0.05", "DISZ 3", "GLAS ___BLANK 1 0 1.5 60 0 0 0 0 0 0", "CONI -0.5",
         "PARM 1 0", "PARM 2 1e-4", "PARM 3 -2e-6", "PARM 4 0", 'DIAM 3 0 0 0 1 ""'],
        ["TYPE STANDARD", "CURV -0.02", "DISZ 2", "CLAP 0 3.2 0"],
        ["TYPE PARAXIAL", "CURV 0", "DISZ 1", "PARM 1 80", "PARM 2 0"],
        ["TYPE BINARY_2", "CURV 0", "DISZ 40", "PARM 0 2", "XDAT 1 3 0 0", "XDAT 2 2.5 0 0",
         "XDAT 3 -100 0 0", "XDAT 4 5 0 0", "XDAT 5 1 0 0", "SQAP 2.5 2.5 0 0 0"],
    ])
    lens = read_zmx(_write(tmp_path, text))
    s = lens.surfaces
    assert [x.type for x in s] == ["standard", "standard", "standard", "thin_lens", "doe"]
    # a DIAM, fixed or automatic, does not clip (OpticStudio and optiland clip only at CLAP / SQAP / FLAP);
    # the stop keeps its fixed DIAM (2.5), but floats under ENPD
    assert s[0].stop and s[0].semi_diameter == 2.5 and s[0].radius is None
    assert lens.surface_extents[:2] == [2.5, 3.0]  # kept for the crossing check only
    assert s[1].radius == pytest.approx(20.0) and s[1].conic == -0.5 and s[1].aspheric == [1e-4, -2e-6]
    assert s[1].material == "1.5/60.0" and s[1].semi_diameter is None  # automatic DIAM is ignored
    assert s[2].semi_diameter == 3.2 and s[2].material == "air"
    assert s[3].focal_length == 80.0
    assert s[4].shape == "square" and s[4].semi_diameter == 2.5 and s[4].design_wavelength_um == 0.6
    assert s[4].profile == {"kind": "even_poly", "norm_radius": 2.5, "coefficients": [-200.0, 10.0, 2.0]}
    assert [x.thickness for x in s] == [1.0, 3.0, 2.0, 1.0, 40.0]
    assert lens.wavelengths_um == [0.5, 0.6] and lens.fields_deg == [0.0, [1.0, 2.0]]
    assert lens.name == "test lens" and lens.entrance_pupil_diameter == 4.0


def test_zmx_units_object_distance_and_fnum(tmp_path):
    # a single thin lens in cm, object at 50 cm, F/4 -> EPD = EFL / 4
    text = _zmx([["STOP", "TYPE PARAXIAL", "CURV 0", "DISZ 12", "PARM 1 10"]], unit="CM", aperture="FNUM 4 0",
                obj="50")
    lens = read_zmx(_write(tmp_path, text))
    assert lens.object_distance == 500.0
    assert lens.surfaces[0].focal_length == 100.0 and lens.surfaces[0].thickness == 120.0
    assert lens.entrance_pupil_diameter == pytest.approx(25.0, rel=1e-12)


def test_zmx_binary2_between_media_splits(tmp_path):
    text = _zmx([
        ["STOP", "TYPE STANDARD", "CURV 0.02", "DISZ 3", "GLAS N-BK7 0 0 1.5168 64.17"],
        ["TYPE BINARY_2", "CURV 0", "DISZ 50", "XDAT 1 1 0 0", "XDAT 2 5 0 0", "XDAT 3 -50 0 0"],
    ])
    lens = read_zmx(_write(tmp_path, text))
    s = lens.surfaces
    assert [x.type for x in s] == ["standard", "standard", "doe"]
    assert s[1].radius is None and s[1].material == "air" and s[1].thickness == 0.0
    assert s[2].thickness == 50.0


@pytest.mark.parametrize("body, cls, surf, key, match", [
    ([["STOP", "TYPE TOROIDAL", "CURV 0.01", "DISZ 5"]], LensFileError, "SURF 1", "TYPE", "TOROIDAL"),
    # unknown glass with Zemax's nd 0 / Vd 0 placeholders: no model glass can stand in (issue 11)
    ([["STOP", "CURV 0.01", "DISZ 5", "GLAS NOSUCHGLASS 0 0 0 0"]], GlassError, "SURF 1", "GLAS",
     "NOSUCHGLASS"),
    ([["STOP", "CURV 0.05", "DISZ 5", "GLAS N-BK7", 'DIAM 8 1 0 0 1 ""'],
      ["CURV -0.05", "DISZ -4.5", 'DIAM 8 1 0 0 1 ""'], ["CURV 0", "DISZ 30"]],
     GeometryError, "SURF 2", "DISZ", "cross"),
    # (EVENASPH PARM 1, the r^2 term, is supported since issue 11: Surface.a2)
    ([["STOP", "CURV", "DISZ 5"]], LensFileError, "SURF 1", "CURV", "missing value"),
    ([["STOP", "CURV abc", "DISZ 5"]], LensFileError, "SURF 1", "CURV", "bad number"),
    # a curved BINARY_2 is a phase surface since issue 27 (rwwarp.phase_surface); its order must be an integer
    ([["STOP", "TYPE BINARY_2", "CURV 0.01", "DISZ 5", "PARM 0 1.5"]], LensFileError, "SURF 1", "PARM 0",
     "integer"),
    ([["STOP", "CURV 0", "DISZ 5", "SQAP 1 2 0"]], LensFileError, "SURF 1", "SQAP", "rectangular"),
])
def test_zmx_errors_name_file_surface_keyword(tmp_path, body, cls, surf, key, match):
    p = _write(tmp_path, _zmx(body))
    with pytest.raises(cls, match=match) as ei:
        read_zmx(p)
    msg = str(ei.value)
    assert str(p) in msg and f"surface {surf}" in msg and f"keyword {key!r}" in msg
    assert ei.value.surface == surf and ei.value.keyword == key


def test_zmx_error_utf16(tmp_path):
    text = _cooke_text().replace("GLAS F2 0 0 1.62004 36.37", "GLAS UNOBTAINIUM 0 0 0 0")
    p = _write(tmp_path, text, encoding="utf-16")
    with pytest.raises(GlassError, match="UNOBTAINIUM") as ei:
        load_lens(p)
    assert ei.value.surface == "SURF 3" and ei.value.keyword == "GLAS"


def test_zmx_needs_image_and_object(tmp_path):
    with pytest.raises(LensFileError, match="SURF block"):
        read_zmx(_write(tmp_path, "MODE SEQ\nSURF 0\n  DISZ INFINITY\nSURF 1\n  DISZ 0\n"))


# ------------------------------------------------------------------------------------------ native errors
def _native():
    return json.loads((BUNDLED / "a489_doe.json").read_text())


def _save(tmp_path, d, name="lens.json"):
    p = tmp_path / name
    p.write_text(json.dumps(d) if not isinstance(d, str) else d)
    return p


def test_native_malformed_json(tmp_path):
    p = _save(tmp_path, '{"format": "rwwarp-lens/1", "surfaces": [\n {"type": "standard",,}]}')
    with pytest.raises(LensFileError, match="malformed JSON at line 2") as ei:
        load_lens(p)
    assert str(p) in str(ei.value)


def test_native_unknown_key(tmp_path):
    d = _native()
    d["surfaces"][2]["curvature"] = 0.1
    p = _save(tmp_path, d)
    with pytest.raises(LensFileError, match="unknown key") as ei:
        load_lens(p)
    assert ei.value.surface == 2 and ei.value.keyword == "curvature" and str(p) in str(ei.value)


def test_native_unknown_profile_key(tmp_path):
    d = _native()
    d["surfaces"][3]["profile"]["order"] = 1
    p = _save(tmp_path, d)
    with pytest.raises(LensFileError, match="profile.order") as ei:
        load_lens(p)
    assert ei.value.surface == 3 and ei.value.keyword == "profile" and str(p) in str(ei.value)


def test_native_unknown_glass(tmp_path):
    d = _native()
    d["surfaces"][1]["material"] = "NOSUCHGLASS"
    with pytest.raises(GlassError) as ei:
        load_lens(_save(tmp_path, d))
    assert ei.value.surface == 1 and ei.value.keyword == "material"


def test_native_negative_thickness_crossing(tmp_path):
    """Crossing surfaces load with a GeometryWarning naming them and the gap (as OpticStudio, optiland and
    DeepLens load such files); strict=True refuses them with a GeometryError (issue 28)."""
    d = _native()
    d["surfaces"][1]["thickness"] = -1.0
    p = _save(tmp_path, d)
    with pytest.raises(GeometryError, match="cross") as ei:
        load_lens(p, strict=True)
    assert ei.value.surface == 1 and ei.value.keyword == "thickness" and str(p) in str(ei.value)
    with pytest.warns(GeometryWarning, match=r"surfaces 1 and 2 cross at height .* \(gap -"):
        lens = load_lens(p)
    assert lens.surfaces[1].thickness == -1.0


def test_native_pixel_map_relative_to_lens_file(tmp_path):
    d = json.loads((BUNDLED / "thin_lens_doe.json").read_text())
    d["surfaces"][2]["profile"] = {"kind": "pixel_map", "file": "maps/phase.npy", "pitch": 0.01}
    (tmp_path / "maps").mkdir()
    np.save(tmp_path / "maps" / "phase.npy", np.zeros((1000, 1000)))
    lens = load_lens(_save(tmp_path, d))
    assert lens.to_dict()["surfaces"][2]["profile"]["file"] == "maps/phase.npy"
    assert not doe.surface_is_continuous(lens.surfaces[2], lens.source)
    (tmp_path / "maps" / "phase.npy").unlink()
    with pytest.raises(LensFileError, match="not found") as ei:
        load_lens(tmp_path / "lens.json")
    assert ei.value.surface == 2 and ei.value.keyword == "profile"


# ------------------------------------------------------------------------------------------ DeepLens
DL_RELATIVE = {
    "info": "test hybrid lens",
    "foclen": 7.77, "fnum": 3.9, "r_sensor": 1.5 * math.sqrt(2), "(d_sensor)": 11.257,
    "(sensor_size)": [3.0, 3.0], "sensor_res": [3000, 3000],
    "surfaces": [
        {"idx": 1, "type": "Aperture", "r": 1.0, "(d)": 0.0, "mat2": "air", "is_square": False,
         "diffraction": False, "d_next": 0.1},
        {"idx": 2, "type": "Aspheric", "r": 6.35, "(c)": 0.2104, "roc": 4.7531, "d": 0.1, "k": -1.2051,
         "ai": [0.0, 5.33e-4, 1.12e-05, -3.75e-07, -7.63e-09, 1.36e-10], "mat2": "H-K51", "(ai2)": 0.0,
         "(ai4)": 5.33e-4, "d_next": 7.5},
        {"idx": 3, "type": "Spheric", "r": 6.35, "(c)": -0.0639, "roc": -15.65, "(d)": 7.6, "mat2": "air",
         "d_next": 3.657},
    ],
    "DOE": {"type": "DOE", "(size)": 3.0, "d": 8.3098, "res": [3000, 3000], "fab_ps": 0.001,
            "is_square": True, "param_model": "binary2", "doe_path": None, "order2": -40.0, "order4": 3.0,
            "order6": 0.0, "order8": 0.0},
}


def _absolute(dl):
    d = copy.deepcopy(dl)
    z = 0.0
    for s in d["surfaces"]:
        s.pop("(d)", None)
        s["d"] = z
        z += s.pop("d_next")
    d["d_sensor"] = z
    d["(d_sensor)"] = 999.0  # derived keys are ignored even when wrong
    return d


def test_deeplens_relative_and_absolute_layouts(tmp_path):
    a = load_lens(_save(tmp_path, DL_RELATIVE, "rel.json"))
    b = load_lens(_save(tmp_path, _absolute(DL_RELATIVE), "abs.json"))
    native = load_lens("a489_doe")
    for lens in (a, b):
        assert [s.type for s in lens.surfaces] == ["aperture", "standard", "standard", "doe"]
        np.testing.assert_allclose(lens.vertex_z, native.vertex_z, atol=1e-12)
        assert lens.sensor_z == pytest.approx(11.257, abs=1e-12)
        s = lens.surfaces[1]
        assert (s.radius, s.conic, s.material, s.semi_diameter) == (4.7531, -1.2051, "H-K51", 6.35)
        assert s.aspheric == native.surfaces[1].aspheric  # the legacy r^2 entry (0) is dropped
        assert lens.surfaces[0].stop and lens.surfaces[0].semi_diameter == 1.0
        dsurf = lens.surfaces[3]
        assert dsurf.shape == "square" and dsurf.semi_diameter == pytest.approx(1.5)
        assert dsurf.levels is None and dsurf.material == "fused_silica"
        assert lens.sensor.pixel_pitch == pytest.approx(0.001, rel=1e-12)
        assert lens.sensor.resolution == (3000, 3000) and lens.name == "test hybrid lens"
        # DeepLens binary2: phase = order2 (r/R)^2 + order4 (r/R)^4 with R the DOE's half-diagonal
        R = 1.5 * math.sqrt(2)
        prof = doe.get_profile(dsurf)
        x, y = np.array([0.3, -1.2, 1.4]), np.array([0.1, 0.7, -1.4])
        rho2 = (x ** 2 + y ** 2) / R ** 2
        np.testing.assert_allclose(prof.phase(x, y), -40.0 * rho2 + 3.0 * rho2 ** 2, rtol=1e-13)
    assert a.to_dict() == b.to_dict()


def test_deeplens_new_doe_models(tmp_path):
    base = {"r_sensor": 2.0, "sensor_res": [100, 100],
            "surfaces": [{"type": "Stop", "r": 2.0, "mat2": "occluder", "d_next": 1.0},
                         {"type": "ThinLens", "f": 50.0, "r": 2.0, "(d)": 1.0, "mat2": "air", "d_next": 50.0},
                         {"type": "Plane", "r": 3.0, "mat2": "N-BK7", "d_next": 1.0, "is_square": True},
                         {"type": "Plane", "r": 3.0, "mat2": "air", "d_next": 2.0}]}
    x, y = np.array([0.2, -0.9]), np.array([0.4, 0.3])
    d = copy.deepcopy(base)
    d["DOE"] = {"type": "Binary2", "d": 1.5, "res": [2000, 2000], "fab_ps": 0.001, "wvln0": 0.6,
                "alpha2": -20.0, "alpha4": 1.5, "fab_step": 8}
    lens = lens_from_deeplens(d, source=None)
    assert [s.type for s in lens.surfaces] == ["aperture", "thin_lens", "doe", "standard", "standard"]
    np.testing.assert_allclose(lens.vertex_z, [0.0, 1.0, 1.5, 51.0, 52.0])
    s = lens.surfaces[2]
    assert s.levels == 8 and s.design_wavelength_um == 0.6 and s.semi_diameter == pytest.approx(1.0)
    r2 = x ** 2 + y ** 2
    ref = math.pi * (-20.0 * r2 + 1.5 * r2 ** 2)
    np.testing.assert_allclose(doe.get_profile(s).phase(x, y), ref, rtol=1e-12)
    assert lens.surfaces[3].shape == "square" and lens.surfaces[3].material == "N-BK7"

    d["DOE"] = {"type": "Fresnel", "d": 1.5, "res": 2000, "fab_ps": 0.001, "f0": 40.0}
    s = lens_from_deeplens(d).surfaces[2]
    assert s.profile == {"kind": "fresnel", "focal_length": 40.0} and s.levels == 16

    z = [0.0] * 37
    z[1] = 1.0  # DeepLens Z2 = 2 rho sin(theta), which is Noll Z3
    d["DOE"] = {"type": "Zernike", "d": 1.5, "res": [2000, 2000], "fab_ps": 0.001, "z_coeff": z}
    s = lens_from_deeplens(d).surfaces[2]
    np.testing.assert_allclose(doe.get_profile(s).phase(x, y), 2 * y / 1.0, rtol=1e-13)

    np.save(tmp_path / "pmap.npy", np.ones((20, 20)))
    d["DOE"] = {"type": "Pixel2D", "d": 1.5, "res": [20, 20], "fab_ps": 0.05, "phase_map_path": "pmap.npy"}
    lens = lens_from_deeplens(d, source=str(tmp_path / "lens.json"))
    s = lens.surfaces[2]
    assert s.profile == {"kind": "pixel_map", "file": "pmap.npy", "pitch": 0.05}
    assert doe.get_profile(s, lens.source).phase(x / 2, y).tolist() == [1.0, 1.0]  # inside the 1 mm map


@pytest.mark.parametrize("change, cls, surf, key, match", [
    (lambda d: d["surfaces"][2].update(type="Cylindric"), LensFileError, 2, "type", "Cylindric"),
    (lambda d: d["surfaces"][1].update(mat2="unobtainium"), GlassError, 1, "mat2", "unobtainium"),
    (lambda d: d["surfaces"][1].pop("d_next"), LensFileError, 1, "d_next", "d_next"),
    (lambda d: d["DOE"].update(param_model="nurbs"), LensFileError, "DOE", "param_model", "nurbs"),
])
def test_deeplens_errors(tmp_path, change, cls, surf, key, match):
    d = copy.deepcopy(DL_RELATIVE)
    change(d)
    p = _save(tmp_path, d)
    with pytest.raises(cls, match=match) as ei:
        load_lens(p)
    assert ei.value.surface == surf and ei.value.keyword == key and str(p) in str(ei.value)


def test_deeplens_crossing_warns_or_strict_refuses(tmp_path):
    d = copy.deepcopy(DL_RELATIVE)
    d.pop("DOE")
    d["surfaces"][1].update(d_next=0.5)  # a biconvex lens 0.5 mm thick at the centre: its rims cross
    p = _save(tmp_path, d)
    with pytest.raises(GeometryError, match="cross") as ei:
        load_lens(p, strict=True)
    assert ei.value.surface == 1 and ei.value.keyword == "thickness" and str(p) in str(ei.value)
    with pytest.warns(GeometryWarning, match=r"surfaces 1 and 2 cross"):
        load_lens(p)


def test_zmx_cut_short_after_a_bad_value_names_it(tmp_path):
    """A file that ends after a malformed value names the value and its line, not the missing surfaces."""
    p = _write(tmp_path, "MODE SEQ\nENPD 4\nSURF 0\n  DISZ INFINITY\nSURF 1\n  STOP\n  CURV abc\n")
    with pytest.raises(LensFileError, match=r"bad number 'abc' for CURV \(line 7\)") as ei:
        read_zmx(p)
    assert ei.value.surface == "SURF 1" and ei.value.keyword == "CURV"


def test_zmx_floa_stop_without_diam_names_the_stop(tmp_path):
    p = _write(tmp_path, _zmx([["CURV 0.02", "DISZ 3", "GLAS N-BK7"], ["CURV 0", "DISZ 2"],
                               ["STOP", "CURV 0", "DISZ 50"]], aperture="FLOA"))
    with pytest.raises(LensFileError, match="FLOA") as ei:
        read_zmx(p)
    assert ei.value.surface == "SURF 3" and ei.value.keyword == "DIAM" and "surface SURF 3" in str(ei.value)


def test_object_at_the_entrance_pupil_names_object_distance(tmp_path):
    d = _native()
    d["object_distance"] = 1e-300  # the stop is the first surface: the object sits on the pupil
    p = _save(tmp_path, d)
    with pytest.raises(GeometryError, match="object_distance = 1e-300 mm") as ei:
        load_lens(p)
    assert ei.value.keyword == "object_distance" and str(p) in str(ei.value)


def test_deeplens_use_ai2_false():
    d = copy.deepcopy(DL_RELATIVE)
    d["surfaces"][1]["ai"] = [5.33e-4, 1.12e-05]
    d["surfaces"][1]["use_ai2"] = False
    assert lens_from_deeplens(d).surfaces[1].aspheric == [5.33e-4, 1.12e-05]


def test_not_a_lens_file(tmp_path):
    with pytest.raises(LensError, match="surfaces"):
        load_lens(_save(tmp_path, {"hello": 1}))
