"""Bad and hostile input (issue 12): one regression test per class. Readers raise LensError naming the
file whatever the bytes; public functions name the argument and its range; nothing is mutated."""
import copy
import json
import math
import os
import time
from pathlib import Path

import numpy as np
import pytest

import rwwarp as rw
from rwwarp.errors import ArgumentError, GeometryError, LensError, LensFileError

LENSES = Path(rw.__file__).parent / "lenses"
A489 = json.loads((LENSES / "a489_doe.json").read_text())
ZMX = (LENSES / "cooke_triplet.zmx").read_bytes().decode("utf-16").replace("\r\n", "\n")


def _load_bytes(tmp_path, data, name="lens.json"):
    p = tmp_path / name
    p.write_bytes(data)
    return rw.load_lens(p), p


def _refused(tmp_path, data, name="lens.json", cls=LensError, match=None):
    p = tmp_path / name
    p.write_bytes(data if isinstance(data, bytes) else json.dumps(data).encode())
    with pytest.raises(cls, match=match) as ei:
        rw.load_lens(p)
    assert str(p) in str(ei.value)
    return ei.value


def _native(change):
    d = copy.deepcopy(A489)
    change(d)
    return d


# ---------------------------------------------------------------------------------------------- bytes
@pytest.mark.parametrize("data", [
    b"\xff\xfe{\x00 ",                      # odd-length UTF-16
    b"\xff\xfe\x00\xd8{\x00}\x00",          # lone surrogate in UTF-16
    b'{"name": "\xed\xa0\x80"}',             # surrogate in UTF-8
    b"\x80\x81\x82",                        # not UTF-8
    b"\x00" * 100,
    b"",
    b"[" * 100_000 + b"]" * 100_000,        # pathological nesting
    b'{"a": ' + b"9" * 5000 + b"}",         # integer literal past Python's digit limit
    b"NaN", b"Infinity", b'"x"', b"[]", b"null",
])
def test_json_bytes_refused_with_the_file_named(tmp_path, data):
    _refused(tmp_path, data, cls=LensFileError)


@pytest.mark.parametrize("data", [
    b"\xff\xfeS\x00U\x00R",                 # odd-length UTF-16 with a BOM
    b"S\x00U\x00R\x00F\x00 \x000\x00\n",    # unmarked UTF-16, odd length
    b"\xff\xfe\x00\xdcS\x00",               # lone low surrogate
    b"SURF 0\nSURF 1\n CURV nan\nSURF 2\n",
    b"SURF 0\nSURF 1\n CURV 1e308\n DISZ 1\nSURF 2\n",
])
def test_zmx_bytes_refused_with_the_file_named(tmp_path, data):
    _refused(tmp_path, data, name="lens.zmx")


def test_directories_fifos_devices_and_long_paths(tmp_path):
    with pytest.raises(LensFileError, match="directory"):
        rw.load_lens(tmp_path)
    (tmp_path / "d.zmx").mkdir()
    with pytest.raises(LensFileError, match="directory"):
        rw.load_lens(tmp_path / "d.zmx")
    fifo = tmp_path / "fifo.json"
    os.mkfifo(fifo)
    t = time.perf_counter()
    with pytest.raises(LensFileError, match="regular file"):
        rw.load_lens(fifo)
    assert time.perf_counter() - t < 5  # refused, not read (a FIFO with no writer blocks forever)
    for dev in ("/dev/zero", "/dev/null"):
        with pytest.raises(LensFileError, match="regular file"):
            rw.load_lens(dev)
    with pytest.raises(LensFileError):
        rw.load_lens("x" * 5000)
    with pytest.raises(LensFileError):
        rw.load_lens(str(tmp_path / ("y" * 300)) + ".json")
    with pytest.raises(LensFileError):
        rw.load_lens("a\x00b")
    with pytest.raises(LensFileError):
        rw.load_lens(12)


def test_byte_cap(tmp_path, monkeypatch):
    import rwwarp.io.validate_input as vi
    monkeypatch.setattr(vi, "MAX_FILE_BYTES", 1000)
    monkeypatch.setattr(vi.read_lens_bytes, "__defaults__", (1000,))
    p = tmp_path / "big.json"
    p.write_text(json.dumps(A489) + " " * 2000)
    with pytest.raises(LensFileError, match="limited to 1000 bytes"):
        rw.load_lens(p)


# ---------------------------------------------------------------------------------------------- types
@pytest.mark.parametrize("change, key", [
    (lambda d: d["surfaces"][1].update(radius=[4.0]), "radius"),
    (lambda d: d["surfaces"][1].update(radius={"r": 4}), "radius"),
    (lambda d: d["surfaces"][1].update(radius="4.7"), "radius"),
    (lambda d: d["surfaces"][1].update(thickness=True), "thickness"),
    (lambda d: d["surfaces"][1].update(material=["H-K51"]), "material"),
    (lambda d: d["surfaces"][1].update(material={"n": 1.5}), "material"),
    (lambda d: d["surfaces"][1].update(aspheric="abc"), "aspheric"),
    (lambda d: d["surfaces"][1].update(aspheric=[[1]]), "aspheric"),
    (lambda d: d["surfaces"][1].update(type=["standard"]), "type"),
    (lambda d: d["surfaces"][0].update(shape=None), "shape"),
    (lambda d: d["surfaces"][0].update(stop="no"), "stop"),
    (lambda d: d["surfaces"][3].update(levels=2.5), "levels"),
    (lambda d: d["surfaces"][3].update(levels="8"), "levels"),
    (lambda d: d["surfaces"][3]["profile"].update(coefficients=[[0.0]]), "profile"),
    (lambda d: d["surfaces"][3]["profile"].update(norm_radius=[1.5]), "profile"),
    (lambda d: d.update(wavelengths_um=0.55), "wavelengths_um"),
    (lambda d: d.update(wavelengths_um="0.55"), "wavelengths_um"),
    (lambda d: d.update(wavelengths_um=[]), "wavelengths_um"),
    (lambda d: d.update(name=["x"]), "name"),
    (lambda d: d.update(fields_deg={"a": 1}), "fields_deg"),
    (lambda d: d.update(fields_deg=[[1, 2, 3]]), "fields_deg"),
    (lambda d: d["sensor"].update(resolution=[2000]), "resolution"),
    (lambda d: d["sensor"].update(resolution="2000"), "resolution"),
    (lambda d: d["sensor"].update(pixel_pitch=None), "pixel_pitch"),
    (lambda d: d.update(surfaces={"0": {}}), "surfaces"),
])
def test_wrong_types_named(tmp_path, change, key):
    e = _refused(tmp_path, _native(change))
    assert key in str(e)


@pytest.mark.parametrize("text", ["NaN", "Infinity", "-Infinity", '"nan"', '"inf"', "1e999", "-1e999"])
@pytest.mark.parametrize("where", ["radius", "thickness", "conic", "semi_diameter"])
def test_nan_and_inf_in_numeric_fields(tmp_path, text, where):
    d = copy.deepcopy(A489)
    d["surfaces"][1][where] = "@@"
    raw = json.dumps(d).replace('"@@"', text).encode()
    e = _refused(tmp_path, raw)
    assert where in str(e)


# ---------------------------------------------------------------------------------------------- magnitudes
@pytest.mark.parametrize("change, key", [
    (lambda d: d["surfaces"][1].update(radius=1e-300), "radius"),
    (lambda d: d["surfaces"][1].update(radius=1e308), None),   # loads: flat in practice, finite numbers
    (lambda d: d["surfaces"][1].update(thickness=1e308), "thickness"),
    (lambda d: d["surfaces"][1].update(conic=1e300), "conic"),
    (lambda d: d["surfaces"][1].update(aspheric=[1e300]), "aspheric"),
    (lambda d: d["surfaces"][1].update(semi_diameter=1e-320), None),
    (lambda d: d["surfaces"][3]["profile"].update(norm_radius=1e-300), "profile"),
    (lambda d: d["surfaces"][3].update(levels=10 ** 12), "levels"),
    (lambda d: d["sensor"].update(resolution=[10 ** 9, 10 ** 9]), "resolution"),
    (lambda d: d["sensor"].update(pixel_pitch=1e-300), "pixel_pitch"),
    (lambda d: d.update(object_distance=1e-300), "object_distance"),  # the object on the pupil (issue 28)
    (lambda d: d.update(object_distance=-5.0), "object_distance"),
    (lambda d: d.update(wavelengths_um=[550]), "wavelength"),
    (lambda d: d["surfaces"][3]["profile"].update(coefficients=[0.0] * 100_000), "profile"),
])
def test_magnitudes_refused_or_finite(tmp_path, change, key):
    d = _native(change)
    p = tmp_path / "lens.json"
    p.write_text(json.dumps(d))
    try:
        lens = rw.load_lens(p)
    except LensError as e:
        assert str(p) in str(e)
        if key is not None:
            assert key in str(e)
        return
    assert key is None, f"should have been refused naming {key}"
    for w in lens.wavelengths_um:
        assert math.isfinite(lens.efl(w)) and math.isfinite(lens.bfl(w))


def test_steep_doe_refused_at_load(tmp_path):
    e = _refused(tmp_path, _native(lambda d: d["surfaces"][3]["profile"].update(coefficients=[1e9])))
    assert "too steep" in str(e) and "surface 3" in str(e)


HYBRID_ZMX = """MODE SEQ
UNIT MM
ENPD 4
WAVM 1 0.55 1
SURF 0
  DISZ INFINITY
SURF 1
  STOP
  TYPE PARAXIAL
  PARM 1 50
  DISZ 1
SURF 2
  TYPE BINARY_2
  XDAT 1 {n} 0 9 0 0
  XDAT 2 2.0 0 9 0 0
  XDAT 3 {a1} 0 9 0 0
  DIAM 2 1 0 0 1 ""
  DISZ 49
SURF 3
"""


def test_zmx_binary2_term_count_refused_fast(tmp_path):
    p = tmp_path / "ok.zmx"
    p.write_text(HYBRID_ZMX.format(n=1, a1=-10.0))
    assert rw.load_lens(p).doe_index == 1
    t = time.perf_counter()
    e = _refused(tmp_path, HYBRID_ZMX.format(n="1e8", a1=-10.0).encode(), name="lens.zmx")
    assert time.perf_counter() - t < 5 and "XDAT 1" in str(e)
    _refused(tmp_path, HYBRID_ZMX.format(n="1.5", a1=-10.0).encode(), name="lens.zmx", match="XDAT 1")
    e = _refused(tmp_path, HYBRID_ZMX.format(n=1, a1="1e12").encode(), name="lens.zmx", match="too steep")
    assert "SURF 2" in str(e)


def test_zmx_overflowing_curvature_and_units(tmp_path):
    lines = ZMX.splitlines()
    i = next(k for k, ln in enumerate(lines) if ln.strip().startswith("CURV") and k > 60)
    lines[i] = "  CURV 1e308 0 0 0 0"
    _refused(tmp_path, "\n".join(lines).encode(), name="lens.zmx")
    _refused(tmp_path, ZMX.replace("ENPD 1.0E+1", "ENPD 1e308").replace("UNIT MM", "UNIT METER").encode(),
             name="lens.zmx")


def test_deeplens_wrong_types(tmp_path):
    base = {"r_sensor": 2.0, "sensor_res": [100, 100],
            "surfaces": [{"type": "Stop", "r": 1.0, "d_next": 1.0},
                         {"type": "ThinLens", "f": 50.0, "r": 2.0, "d_next": 50.0}]}
    rw.load_lens(_save(tmp_path, base))
    for change in (lambda d: d["surfaces"][0].update(pos_xy={"x": 1}),
                   lambda d: d["surfaces"][0].update(pos_xy=5),
                   lambda d: d.update(sensor_res=[1e999, 2]),
                   lambda d: d.update(sensor_size=["a", "b"]),
                   lambda d: d.update(enpd="wide"),
                   lambda d: d.update(info=[1]),
                   lambda d: d["surfaces"][1].update(f=float("nan")),
                   lambda d: d.update(DOE={"type": "Fresnel", "d": 1.5, "res": 1e999, "f0": 40.0}),
                   lambda d: d.update(DOE={"type": "Fresnel", "d": 1.5, "size": "ab", "f0": 40.0}),
                   lambda d: d.update(DOE={"type": "Fresnel", "d": 1.5, "fab_step": 1e300, "f0": 40.0})):
        d = copy.deepcopy(base)
        change(d)
        p = _save(tmp_path, d)
        with pytest.raises(LensError) as ei:
            rw.load_lens(p)
        assert str(p) in str(ei.value)


def _save(tmp_path, d, name="dl.json"):
    p = tmp_path / name
    p.write_text(json.dumps(d, allow_nan=True))
    return p


# ---------------------------------------------------------------------------------------------- arguments
@pytest.fixture(scope="module")
def a489():
    return rw.load_lens("a489_doe")


def test_wavelength_in_nm_is_named(a489):
    for call in (lambda: a489.efl(550), lambda: a489.bfl(550), lambda: rw.spot_rms(a489, 0.0, 550, grid=11),
                 lambda: rw.psf(a489, 0.0, 550, model="ray", size=8)):
        with pytest.raises(ArgumentError, match=r"wavelength_um=550 is outside 0.2-20 um; wavelengths are in "
                                                r"micrometres"):
            call()
    with pytest.raises(ArgumentError, match="glass data of H-K51"):
        a489.efl(0.25)


@pytest.mark.parametrize("kwargs, name", [
    (dict(size=0), "size"), (dict(size=2.5), "size"), (dict(size=10 ** 9), "size"), (dict(size="64"), "size"),
    (dict(object_distance_mm=float("nan")), "object_distance_mm"),
    (dict(object_distance_mm=0.0), "object_distance_mm"), (dict(object_distance_mm=-1.0), "object_distance_mm"),
    (dict(nyquist_safety=0.0), "nyquist_safety"), (dict(nyquist_safety=float("inf")), "nyquist_safety"),
    (dict(rays_per_sample=-1), "rays_per_sample"), (dict(rays_per_sample=float("nan")), "rays_per_sample"),
    (dict(pixel_mm=-0.001), "pixel_mm"), (dict(pixel_mm=float("inf")), "pixel_mm"),
    (dict(center_mm=(float("nan"), 0.0)), "center_mm"), (dict(center_mm=(1.0, 2.0, 3.0)), "center_mm"),
    (dict(batch=0), "batch"), (dict(device="gpu"), "device"), (dict(device="cuda:99"), "device"),
    (dict(model="wave"), "model"), (dict(dtype="float16"), "dtype"), (dict(fields=[]), "fields"),
    (dict(fields=[0.0, float("nan")]), "fields[1]"), (dict(fields=[(1, 2, 3)]), "field_deg"),
    (dict(fields=[95.0]), "field_deg"), (dict(fields="0"), "fields"), (dict(wavelengths_um=[]), "wavelengths_um"),
    (dict(wavelengths_um=[0.55, -1]), "wavelengths_um[1]"), (dict(gauss_nodes=0), "gauss_nodes"),
])
def test_psf_map_arguments_named(a489, kwargs, name):
    args = dict(fields=[0.0], wavelengths_um=[0.55], model="ray", size=8)
    args.update(kwargs)
    with pytest.raises(ArgumentError) as ei:
        rw.psf_map(a489, **args)
    assert name in str(ei.value)


def test_spot_rms_arguments_and_vignetting(a489):
    for kwargs, name in ((dict(grid=0), "grid"), (dict(grid=2), "grid"), (dict(field_deg=float("inf")), "field_deg"),
                         (dict(reference="mean"), "reference"), (dict(device="tpu"), "device")):
        with pytest.raises(ArgumentError, match=name):
            rw.spot_rms(a489, **{"field_deg": 0.0, "wavelength_um": 0.55, "grid": 11, **kwargs})
    with pytest.raises(GeometryError, match=r"field_deg=60.0.*vignetted"):
        rw.spot_rms(a489, 60.0, 0.55, grid=11)
    v = rw.spot_rms(a489, [0.0, 5.0], 0.55, grid=11)
    assert v.shape == (2,) and np.all(np.isfinite(v))


def test_inputs_not_mutated(a489):
    before = copy.deepcopy(a489.to_dict())
    fields, wls = [0.0, (0.0, 2.0)], [0.55, 0.65]
    m = rw.psf_map(a489, fields, wls, model="ray", size=8)
    assert fields == [0.0, (0.0, 2.0)] and wls == [0.55, 0.65]
    assert a489.to_dict() == before
    assert np.all(np.isfinite(m.data)) and np.all(m.data.sum(axis=(2, 3)) <= 1 + 1e-9)


def test_pixel_map_files_and_pitch(tmp_path):
    def with_map(profile):
        return _native(lambda d: d["surfaces"][3].update(profile=profile))
    os.mkfifo(tmp_path / "fifo.npy")
    t = time.perf_counter()
    e = _refused(tmp_path, with_map({"kind": "pixel_map", "file": "fifo.npy", "pitch": 0.01}))
    assert time.perf_counter() - t < 5 and "fifo.npy" in str(e)
    (tmp_path / "dir.npy").mkdir()
    _refused(tmp_path, with_map({"kind": "pixel_map", "file": "dir.npy", "pitch": 0.01}))
    (tmp_path / "text.npy").write_text("not numpy")
    _refused(tmp_path, with_map({"kind": "pixel_map", "file": "text.npy", "pitch": 0.01}))
    e = _refused(tmp_path, with_map({"kind": "pixel_map", "data": [[0.0, 1.0], [1.0, 0.0]], "pitch": 1e-5}))
    assert "half the design wavelength" in str(e)


def test_integer_literals_past_float_range(tmp_path, a489):
    d = copy.deepcopy(A489)
    d["object_distance"] = "@@"  # past float range: infinity, a legal object distance
    lens, _ = _load_bytes(tmp_path, json.dumps(d).replace('"@@"', "1" + "0" * 400).encode())
    assert math.isinf(lens.object_distance)
    for key in ("entrance_pupil_diameter", "thickness"):
        d = copy.deepcopy(A489)
        (d if key == "entrance_pupil_diameter" else d["surfaces"][1])[key] = "@@"
        e = _refused(tmp_path, json.dumps(d).replace('"@@"', "1" + "0" * 400).encode())
        assert key in str(e) and "cannot interpret" not in str(e)
    d = copy.deepcopy(A489)
    d["sensor"]["resolution"] = ["@@", 10]
    e = _refused(tmp_path, json.dumps(d).replace('"@@"', "9" * 400).encode())
    assert "resolution" in str(e)
    for call, name in ((lambda: a489.efl(10 ** 400), "wavelength_um"), (lambda: rw.psf(a489, 0.0, 0.55, size=10 ** 400),
                                                                        "size"),
                       (lambda: rw.spot_rms(a489, 10 ** 400, 0.55, grid=5), "field_deg")):
        with pytest.raises(ArgumentError, match=name) as ei:
            call()
        assert len(str(ei.value)) < 300
