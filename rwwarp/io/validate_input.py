"""Validation of lens input at load time: the bytes of a file, its text and JSON structure, and
every value of a built :class:`~rwwarp.lens.Lens`.

The contract (project issue 12): whatever the bytes, :func:`rwwarp.load_lens` raises a
:class:`~rwwarp.errors.LensError` (or a subclass) naming the file, or returns a lens whose numbers
are finite, within the ranges below, and whose paraxial rays trace to finite numbers. Nothing is
half-built and nothing only fails later as NaN.

Limits (lengths in mm, wavelengths in um):

* files: regular files only (no directories, FIFOs, devices), at most :data:`MAX_FILE_BYTES` read;
  text in UTF-8 (optional BOM) or UTF-16 with a BOM; JSON nested at most :data:`MAX_JSON_DEPTH` deep;
* lengths (thickness, semi-diameter, radius, focal length, pupil, norm radius) at most
  :data:`MAX_LENGTH_MM` in magnitude; radii and focal lengths at least :data:`MIN_RADIUS_MM`;
* conic at most :data:`MAX_CONIC` in magnitude; the sag of every surface finite over its aperture;
* object distance > 0 and at most :data:`MAX_LENGTH_MM` * 1e6, or infinite;
* wavelengths and DOE design wavelengths in 0.2-20 um; at most :data:`MAX_WAVELENGTHS`;
* sensor: pixel pitch in [1e-6, 10] mm, resolution 1..:data:`MAX_RESOLUTION` per axis;
* DOE: ``levels`` 2..:data:`MAX_LEVELS`; at most :data:`MAX_TERMS` phase terms; the local zone
  period ``2 pi / |grad phi0|`` over the aperture at least the design wavelength (steeper phases
  diffract into evanescent orders and no sampling plan can resolve them); pixel maps at most
  :data:`MAX_PIXELS` pixels of at least 1e-5 mm;
* fields: at most :data:`MAX_FIELDS`, each a number or an (x, y) pair, |angle| < 90 deg;
* at most :data:`MAX_SURFACES` surfaces.
"""
from __future__ import annotations

import math
import numbers
import os
import stat
from pathlib import Path

from ..errors import GeometryError, LensError, LensFileError

MAX_FILE_BYTES = 16 * 2 ** 20
MAX_JSON_DEPTH = 64
MAX_LENGTH_MM = 1e6
MIN_RADIUS_MM = 1e-6
MAX_CONIC = 1e6
MAX_RESOLUTION = 100_000
MAX_LEVELS = 4096
MAX_TERMS = 240
MAX_WAVELENGTHS = 100
MAX_FIELDS = 10_000
MAX_SURFACES = 1000
MAX_PIXELS = 10 ** 8
WAVELENGTH_RANGE_UM = (0.2, 20.0)


# ------------------------------------------------------------------------------------------ bytes
def read_lens_bytes(path, max_bytes: int = MAX_FILE_BYTES) -> bytes:
    """The bytes of the lens file ``path``; refuses non-regular files and files over ``max_bytes``.

    Raises :class:`LensFileError` naming the file (never OSError)."""
    name = str(path)
    try:
        st = os.stat(path)
    except (OSError, ValueError) as e:  # ENAMETOOLONG, ELOOP, EACCES, NUL in the path...
        raise LensFileError(f"cannot read file ({_why(e)})", file=_short(name)) from None
    if stat.S_ISDIR(st.st_mode):
        raise LensFileError("is a directory, not a lens file", file=_short(name))
    if not stat.S_ISREG(st.st_mode):
        raise LensFileError("not a regular file (a FIFO, socket or device); lens files must be regular files",
                            file=_short(name))
    if st.st_size > max_bytes:
        raise LensFileError(f"file is {st.st_size} bytes; lens files are limited to {max_bytes} bytes",
                            file=_short(name))
    try:
        with open(path, "rb") as fh:
            raw = fh.read(max_bytes + 1)
    except (OSError, ValueError) as e:
        raise LensFileError(f"cannot read file ({_why(e)})", file=_short(name)) from None
    if len(raw) > max_bytes:
        raise LensFileError(f"file grew past {max_bytes} bytes while reading", file=_short(name))
    return raw


def _why(e) -> str:
    return getattr(e, "strerror", None) or str(e) or type(e).__name__


def _short(name: str, limit: int = 300) -> str:
    return name if len(name) <= limit else name[:limit // 2] + "..." + name[-limit // 2:]


def decode_json_text(raw: bytes, path) -> str:
    """Text of a JSON lens file: UTF-8 (optional BOM) or UTF-16/32 with a BOM; else LensFileError."""
    try:
        if raw.startswith(b"\xef\xbb\xbf"):
            return raw[3:].decode("utf-8")
        if raw.startswith((b"\xff\xfe\x00\x00", b"\x00\x00\xfe\xff")):
            return raw.decode("utf-32")
        if raw.startswith((b"\xff\xfe", b"\xfe\xff")):
            return raw.decode("utf-16")
        return raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise LensFileError(f"cannot decode the file as {e.encoding} text at byte {e.start}: {e.reason} "
                            "(lens JSON files are UTF-8, or UTF-16 with a byte-order mark)", file=str(path)) from None


def json_depth_ok(text: str, limit: int = MAX_JSON_DEPTH) -> int | None:
    """Position of the first bracket nested deeper than ``limit`` (strings skipped), or None."""
    depth, in_str, esc = 0, False, False
    for i, ch in enumerate(text):
        if in_str:
            if esc:
                esc = False
            elif ch == "\\":
                esc = True
            elif ch == '"':
                in_str = False
        elif ch == '"':
            in_str = True
        elif ch in "[{":
            depth += 1
            if depth > limit:
                return i
        elif ch in "]}":
            depth -= 1
    return None


def parse_json(raw: bytes, path):
    """Parse a JSON lens file's bytes; every failure is a :class:`LensFileError` naming the file."""
    import json

    text = decode_json_text(raw, path)
    pos = json_depth_ok(text)
    if pos is not None:
        line = text.count("\n", 0, pos) + 1
        raise LensFileError(f"JSON nested more than {MAX_JSON_DEPTH} levels deep (line {line})", file=str(path))
    try:  # integer literals past float range become inf, refused by name where a number belongs
        return json.loads(text, parse_int=lambda t: int(t) if len(t) <= 300 else float(t))
    except json.JSONDecodeError as e:
        raise LensFileError(f"malformed JSON at line {e.lineno} column {e.colno}: {e.msg}", file=str(path)) from None
    except (ValueError, RecursionError) as e:  # over-long integer literals, pathological input
        raise LensFileError(f"malformed JSON: {e}", file=str(path)) from None


# ------------------------------------------------------------------------------------------ values
def is_real(v) -> bool:
    """A real number (int, float, numpy scalar) but not a bool."""
    return isinstance(v, numbers.Real) and not isinstance(v, bool)


def _fail(msg, lens, surface=None, keyword=None, cls=LensError):
    return cls(msg, file=lens.source, surface=surface, keyword=keyword)


def _real(v, what, lens, surface=None, keyword=None, *, lo=None, hi=None, positive=False, allow_inf=False,
          nonzero=False):
    if not is_real(v):
        raise _fail(f"{what} must be a number, got {type(v).__name__} {_brief(v)}", lens, surface, keyword)
    try:
        x = float(v)
    except OverflowError:
        raise _fail(f"{what} = {_brief(v, 30)} overflows float64", lens, surface, keyword) from None
    if math.isnan(x) or (math.isinf(x) and not allow_inf):
        raise _fail(f"{what} must be finite, got {x}", lens, surface, keyword)
    if positive and not x > 0:
        raise _fail(f"{what} must be > 0, got {x}", lens, surface, keyword)
    if nonzero and x == 0:
        raise _fail(f"{what} must be non-zero", lens, surface, keyword)
    if lo is not None and math.isfinite(x) and x < lo:
        raise _fail(f"{what} = {x:.6g} is below {lo:g}", lens, surface, keyword)
    if hi is not None and math.isfinite(x) and x > hi:
        raise _fail(f"{what} = {x:.6g} is above {hi:g}", lens, surface, keyword)
    return x


def _brief(v, n=60) -> str:
    s = repr(v)
    return s if len(s) <= n else s[:n] + "..."


def _int(v, what, lens, surface=None, keyword=None, *, lo, hi):
    if isinstance(v, bool) or not (isinstance(v, numbers.Integral) or (is_real(v) and math.isfinite(v)
                                                                        and float(v).is_integer())):
        raise _fail(f"{what} must be an integer, got {_brief(v)}", lens, surface, keyword)
    x = int(v)
    if not lo <= x <= hi:
        raise _fail(f"{what} = {x} is outside {lo}..{hi}", lens, surface, keyword)
    return x


def check_wavelength_value(w, what, lens, surface=None, keyword=None):
    lo, hi = WAVELENGTH_RANGE_UM
    x = _real(w, what, lens, surface, keyword)
    if not lo <= x <= hi:
        raise _fail(f"{what}={x:g} is outside {lo:g}-{hi:g} um; wavelengths are in micrometres", lens, surface,
                    keyword)
    return x


def check_lens_values(lens) -> None:
    """Types and ranges of every input value of ``lens`` (see the module docstring); raises LensError
    (naming the file, the surface and the keyword as rwwarp attribute names)."""
    L = MAX_LENGTH_MM
    if not isinstance(lens.surfaces, (list, tuple)):
        raise _fail(f"surfaces must be a list, got {type(lens.surfaces).__name__}", lens, keyword="surfaces")
    if len(lens.surfaces) > MAX_SURFACES:
        raise _fail(f"{len(lens.surfaces)} surfaces; at most {MAX_SURFACES} are supported", lens,
                    keyword="surfaces")
    if not isinstance(lens.name, str):
        raise _fail(f"name must be a string, got {type(lens.name).__name__}", lens, keyword="name")
    _real(lens.object_distance, "object_distance", lens, keyword="object_distance", positive=True,
          allow_inf=True, hi=L * 1e6)
    wls = lens.wavelengths_um
    if not isinstance(wls, (list, tuple)) or not wls:
        raise _fail(f"wavelengths_um must be a non-empty list, got {_brief(wls)}", lens, keyword="wavelengths_um")
    if len(wls) > MAX_WAVELENGTHS:
        raise _fail(f"{len(wls)} wavelengths; at most {MAX_WAVELENGTHS}", lens, keyword="wavelengths_um")
    for w in wls:
        check_wavelength_value(w, "wavelength_um", lens, keyword="wavelengths_um")
    if lens.entrance_pupil_diameter is not None:
        _real(lens.entrance_pupil_diameter, "entrance_pupil_diameter", lens, keyword="entrance_pupil_diameter",
              positive=True, hi=L)
    check_fields_value(lens.fields_deg, lens)
    sen = lens.sensor
    _real(sen.pixel_pitch, "sensor pixel_pitch (mm)", lens, keyword="pixel_pitch", lo=1e-6, hi=10.0)
    res = sen.resolution
    if not isinstance(res, (list, tuple)) or len(res) != 2:
        raise _fail(f"sensor resolution must be two integers, got {_brief(res)}", lens, keyword="resolution")
    for v in res:
        _int(v, "sensor resolution", lens, keyword="resolution", lo=1, hi=MAX_RESOLUTION)
    for i, s in enumerate(lens.surfaces):
        _check_surface(s, i, lens)


def check_fields_value(fields, lens):
    if fields is None:
        return
    if not isinstance(fields, (list, tuple)):
        raise _fail(f"fields_deg must be a list of angles (deg), got {_brief(fields)}", lens, keyword="fields_deg")
    if len(fields) > MAX_FIELDS:
        raise _fail(f"{len(fields)} fields; at most {MAX_FIELDS}", lens, keyword="fields_deg")
    for k, f in enumerate(fields):
        vals = f if isinstance(f, (list, tuple)) else [f]
        if len(vals) not in (1, 2) or (isinstance(f, (list, tuple)) and len(vals) != 2):
            raise _fail(f"fields_deg[{k}] must be a number or an [x, y] pair, got {_brief(f)}", lens,
                        keyword="fields_deg")
        for v in vals:
            _real(v, f"fields_deg[{k}]", lens, keyword="fields_deg", lo=-89.999, hi=89.999)


def _check_surface(s, i, lens):
    L = MAX_LENGTH_MM
    for key in ("type", "material", "shape"):
        v = getattr(s, key)
        if not isinstance(v, str):
            raise _fail(f"{key} must be a string, got {type(v).__name__} {_brief(v)}", lens, i, key)
    if not isinstance(s.stop, bool):
        raise _fail(f"stop must be true or false, got {_brief(s.stop)}", lens, i, "stop")
    _real(s.thickness, "thickness (mm)", lens, i, "thickness", lo=-L, hi=L)
    if s.semi_diameter is not None:
        _real(s.semi_diameter, "semi_diameter (mm)", lens, i, "semi_diameter", positive=True, hi=L)
    if s.type in ("standard",):
        if s.radius is not None:
            r = _real(s.radius, "radius (mm)", lens, i, "radius", lo=-L * 1e6, hi=L * 1e6)
            if r != 0 and abs(r) < MIN_RADIUS_MM:
                raise _fail(f"radius {r:.3g} mm is smaller in magnitude than {MIN_RADIUS_MM:g} mm", lens, i, "radius")
        _real(s.conic, "conic", lens, i, "conic", lo=-MAX_CONIC, hi=MAX_CONIC)
        if getattr(s, "a2", None) is not None:  # r^2 asphere term, 1/mm: bounded like a curvature
            _real(s.a2, "a2 (1/mm)", lens, i, "a2", lo=-1.0 / MIN_RADIUS_MM, hi=1.0 / MIN_RADIUS_MM)
        if not isinstance(s.aspheric, (list, tuple)):
            raise _fail(f"aspheric must be a list of numbers, got {_brief(s.aspheric)}", lens, i, "aspheric")
        for k, a in enumerate(s.aspheric):
            _real(a, f"aspheric[{k}]", lens, i, "aspheric")
        if s.semi_diameter is not None:
            _check_sag(s, i, lens)
    if s.type == "thin_lens":
        if s.focal_length is None:
            raise _fail("thin_lens needs a finite non-zero focal_length", lens, i, "focal_length")
        f = _real(s.focal_length, "focal_length (mm)", lens, i, "focal_length", nonzero=True, lo=-L * 1e6,
                  hi=L * 1e6)
        if abs(f) < MIN_RADIUS_MM:
            raise _fail(f"focal_length {f:.3g} mm is smaller in magnitude than {MIN_RADIUS_MM:g} mm", lens, i,
                        "focal_length")
    if s.type == "doe":
        check_wavelength_value(s.design_wavelength_um, "design_wavelength_um", lens, i, "design_wavelength_um")
        if s.levels is not None:
            _int(s.levels, "levels", lens, i, "levels", lo=2, hi=MAX_LEVELS)
        _check_profile_values(s, i, lens)


def _check_sag(s, i, lens):
    """The sag must be finite up to the semi-diameter (corner of a square aperture)."""
    import numpy as np

    h = float(s.semi_diameter) * (math.sqrt(2.0) if s.shape == "square" else 1.0)
    c, k = s.curvature, float(s.conic)
    if c != 0 and (1.0 + k) * c * c * h * h > 1.0:
        rmax = 1.0 / (abs(c) * math.sqrt(1.0 + k))
        raise _fail(f"semi_diameter {s.semi_diameter:.6g} mm reaches past the edge of the surface (a radius "
                    f"{s.radius:.6g} mm, conic {k:.6g} surface ends at height {rmax:.6g} mm)", lens, i,
                    "semi_diameter", cls=GeometryError)
    with np.errstate(all="ignore"):
        z = s.sag(np.linspace(0.0, h, 17))
    if not np.all(np.isfinite(z)) or float(np.max(np.abs(z))) > MAX_LENGTH_MM:
        raise _fail(f"the sag overflows within the semi_diameter {s.semi_diameter:.6g} mm (check radius, conic "
                    "and aspheric coefficients; aspheric coefficients are per mm^4, mm^6, ...)", lens, i,
                    "aspheric" if s.aspheric else "radius", cls=GeometryError)


def _check_profile_values(s, i, lens):
    p = s.profile
    if not isinstance(p, dict):
        raise _fail(f"profile must be an object with a 'kind', got {_brief(p)}", lens, i, "profile")
    for key in ("norm_radius", "focal_length", "pitch"):
        if key in p and is_real(p[key]):
            x = _real(p[key], f"profile.{key} (mm)", lens, i, "profile", hi=MAX_LENGTH_MM * (1e6 if key ==
                                                                                             "focal_length" else 1))
            if abs(x) < (1e-5 if key == "pitch" else MIN_RADIUS_MM) and x != 0:
                raise _fail(f"profile.{key} = {x:.3g} mm is too small", lens, i, "profile")
    coeffs = p.get("coefficients")
    if isinstance(coeffs, (list, tuple)) and len(coeffs) > MAX_TERMS:
        raise _fail(f"profile has {len(coeffs)} coefficients; at most {MAX_TERMS}", lens, i, "profile")
    data = p.get("data")
    if isinstance(data, (list, tuple)):
        n = len(data) * (len(data[0]) if data and isinstance(data[0], (list, tuple)) else 1)
        if n > MAX_PIXELS:
            raise _fail(f"pixel map of {n} pixels; at most {MAX_PIXELS}", lens, i, "profile")


def check_doe_steepness(s, i, lens, prof) -> None:
    """Refuse a smooth DOE phase whose local zone period ``2 pi / |grad phi0|`` falls below the design
    wavelength anywhere on the aperture (the first order would be evanescent; no plan can sample it)."""
    import numpy as np

    h = s.semi_diameter
    ext = getattr(lens, "surface_extents", None)
    if h is None and ext is not None and i < len(ext) and ext[i] is not None and ext[i] > 0:
        h = float(ext[i])  # a .zmx DIAM: not an aperture, but the height the file gives the surface
    if not prof.is_continuous or h is None:
        if not prof.is_continuous:
            data = prof.data if getattr(prof, "_data", None) is not None else None
            if data is not None and data.size > MAX_PIXELS:
                raise _fail(f"pixel map of {data.size} pixels; at most {MAX_PIXELS}", lens, i, "profile")
            pitch = getattr(prof, "pitch", None)
            lam_mm = float(s.design_wavelength_um) * 1e-3
            if pitch is not None and pitch < 0.5 * lam_mm:
                raise _fail(f"pixel map pitch {pitch * 1e3:.3g} um is below half the design wavelength "
                            f"({s.design_wavelength_um:g} um): sub-wavelength pixels cannot be simulated by the "
                            "scalar model and no sampling plan can resolve them", lens, i, "profile")
        return
    h = float(h)
    with np.errstate(all="ignore"):
        gmax = float(prof.max_gradient(h, s.design_wavelength_um, s.shape))
    lam_mm = float(s.design_wavelength_um) * 1e-3
    if not math.isfinite(gmax):
        raise _fail("the DOE phase gradient overflows over the aperture (coefficients too large)", lens, i,
                    "profile")
    if gmax > 2.0 * math.pi / lam_mm:
        period_um = 2.0 * math.pi / gmax * 1e3
        raise _fail(f"the DOE phase is too steep: its narrowest 2 pi zone is {period_um:.3g} um, below the "
                    f"design wavelength {s.design_wavelength_um:g} um (the first order would be evanescent "
                    f"and no sampling plan can resolve it; max |grad phi0| = {gmax:.4g} rad/mm)", lens, i, "profile")


def check_paraxial_finite(lens) -> None:
    """Paraxial marginal and chief rays stay finite at every lens wavelength; else GeometryError."""
    import numpy as np

    from .. import paraxial

    for w in lens.wavelengths_um:
        with np.errstate(all="ignore"):
            ya, nua = paraxial.ynu_trace(lens, w, 1.0, 0.0)
            yb, nub = paraxial.ynu_trace(lens, w, 0.0, 1.0)
        for arr in (ya, nua, yb, nub):
            bad = np.flatnonzero(~np.isfinite(arr) | (np.abs(arr) > 1e150))
            if bad.size:
                raise GeometryError(f"the paraxial ray trace overflows at {w:g} um (magnitudes too large for "
                                    "float64)", file=lens.source, surface=int(bad[0]))


def check_object_at_pupil(lens) -> None:
    """A finite object must not sit on the paraxial entrance pupil: from a point there the pupil subtends
    180 degrees and no ray can be aimed through it (an object distance of 1e-300 mm in front of a stop at
    the first vertex). Refused, naming ``object_distance``, when the pupil's half-angle seen from the object
    exceeds 89.99 degrees (|object to pupil| < 1.75e-4 pupil radii)."""
    import math

    from .. import paraxial

    d = lens.object_distance
    if not math.isfinite(d):
        return
    w = lens.primary_wavelength_um or lens.wavelengths_um[0]
    try:
        pp = paraxial.pupils(lens, w)
    except LensError:
        return  # no pupil defined: reported where it is needed
    dist = d + pp.entrance_z
    if math.isfinite(pp.entrance_radius) and abs(dist) < math.tan(math.radians(0.01)) * pp.entrance_radius:
        raise GeometryError(f"object_distance = {d:g} mm puts the object {dist:.3g} mm from the entrance pupil "
                            f"(radius {pp.entrance_radius:.4g} mm, {pp.entrance_z:.4g} mm behind the first "
                            "vertex): seen from the object the pupil subtends 180 degrees and no ray can be aimed "
                            "through it; give a larger object distance (or inf)", file=lens.source,
                            keyword="object_distance")


def check_loaded(lens) -> None:
    """Checks that need the built lens as a whole (run by :func:`rwwarp.load_lens`)."""
    check_paraxial_finite(lens)
    check_object_at_pupil(lens)


def check_path_string(path) -> None:
    """A lens path must be a str or os.PathLike without NUL bytes."""
    if not isinstance(path, (str, os.PathLike)):
        raise LensFileError(f"a lens is named by a path or a bundled name, got {type(path).__name__}")
    if "\x00" in os.fspath(path) if isinstance(os.fspath(path), str) else b"\x00" in os.fspath(path):
        raise LensFileError("path contains a NUL byte", file=repr(os.fspath(path))[:300])


__all__ = ["read_lens_bytes", "decode_json_text", "parse_json", "check_lens_values", "check_doe_steepness",
           "check_paraxial_finite", "check_loaded", "check_path_string", "is_real"]
