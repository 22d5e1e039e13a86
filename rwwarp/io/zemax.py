"""Reader of Zemax OpticStudio sequential lens files (``.zmx``) into a :class:`rwwarp.lens.Lens`.

Units: the file's lens unit (``UNIT MM``, ``CM``, ``IN`` or ``METER``) is converted to mm;
wavelengths (``WAVM``/``WAVL``) are in um; field angles in degrees.

Supported:

* encodings: ASCII/UTF-8 (with or without BOM) and UTF-16 (LE/BE with BOM, as OpticStudio writes
  it), LF or CRLF line ends;
* surface types ``STANDARD`` (sphere/plane + conic), ``ODDASPHE`` (``PARM 1..8`` = the r^1..r^8 terms,
  ``Surface.odd_aspheric``), ``EVENASPH`` (conic + ``PARM 1`` = the r^2 term
  ``Surface.a2``, ``PARM 2..8`` = r^4..r^16), ``PARAXIAL`` (ideal thin lens, focal length
  ``PARM 1``) and ``BINARY_2`` (sag as ``EVENASPH``: ``CURV``, ``CONI``, ``PARM 1..8`` = r^2..r^16;
  diffraction order ``PARM 0``; phase ``XDAT 1`` = number of terms N, ``XDAT 2`` = normalisation
  radius, ``XDAT 3..N+2`` = A1..AN in radians on rho^2..rho^(2N), at most 8 terms on a phase surface).
  A flat, aspheric-free ``BINARY_2`` with no surface behind it but the image becomes the wave-plane DOE (surface type ``doe``, an ``even_poly`` profile with the terms times
  the order: the wave models keep all its orders); every other ``BINARY_2`` (curved, aspheric, in front
  of or between lenses, several) becomes a ``standard`` surface carrying a ``phase`` traced in its order
  (:mod:`rwwarp.phase_surface`). ``read_zmx(..., binary2="phase")`` makes every one a phase surface;
* per surface ``CURV``, ``DISZ`` (``INFINITY``), ``GLAS`` (a catalogue name, or a model glass
  ``GLAS ___BLANK 1 0 nd vd ...`` -> material ``"nd/vd"``), ``CONI``, ``PARM``, ``XDAT``, ``STOP``,
  ``DIAM``, ``CLAP`` (circular aperture; annular with a minimum radius), ``SQAP`` (square aperture),
  ``FLAP`` (floating aperture), ``OBSC`` / ``SQOB`` (circular / rectangular central obscurations);
* system data ``ENPD`` (entrance pupil diameter), ``FNUM`` (image-space F/#: EPD = EFL / F# at the
  primary wavelength), ``FLOA`` (float by stop size), ``WAVM``/``WAVL``, ``PWAV``, ``FTYP``,
  ``XFLN``/``YFLN`` (``XFLD``/``YFLD``), ``UNIT``, ``NAME``.

Mapping: SURF 0 is the object (its ``DISZ`` is the object distance); the last SURF is the image
plane and the thickness of the surface before it is the distance to the sensor; SURF k (0 < k < last)
becomes rwwarp surface k-1 (a BINARY_2 surface between two different media becomes two rwwarp
surfaces: a flat refracting ``standard`` surface and the DOE, at the same z).

Semi-diameters: OpticStudio (and optiland) do not clip rays at a ``DIAM`` semi-diameter, fixed (solve
flag 1) or automatic (flag 0), only at surface apertures. rwwarp clips at ``semi_diameter``, so it is
taken from ``CLAP``/``SQAP``/``FLAP`` apertures only; every ``DIAM`` is kept as
``Lens.surface_extents`` (the heights the crossing check looks at; nothing clips there). The stop keeps
a fixed ``DIAM`` as its ``semi_diameter`` (it floats under a system aperture, so that clips nothing
either). Surfaces that cross inside their ``DIAM`` heights raise a :class:`~rwwarp.errors.GeometryError`
with ``strict=True``, else (what :func:`rwwarp.load_lens` does by default) a
:class:`~rwwarp.errors.GeometryWarning` naming ``SURF j`` and ``SURF k``, the height and the gap, and the
lens is traced sequentially as OpticStudio traces it. Under ``FLOA`` the stop's ``DIAM`` sets the entrance pupil
(its paraxial image at the primary wavelength, stored as ``entrance_pupil_diameter``) and, as under
``ENPD`` and ``FNUM``, the stop floats: real rays are not clipped at its size. An explicit aperture
(``CLAP``/``SQAP``/``FLAP``) on the stop still clips: the stop becomes a floating aperture plane at
the surface's vertex, followed by the surface with its aperture (two rwwarp surfaces, one SURF).

Fields: ``FTYP`` field type 0 (angle) gives ``fields_deg`` (a number where x = 0, else [x, y]);
other field types (object/image heights) leave ``fields_deg`` None. The sensor is not part of a
.zmx file: the default :class:`~rwwarp.lens.Sensor` is used.

Errors: everything is checked before a :class:`Lens` is built (nothing half-loaded). Messages name
the file, the surface as its Zemax number (``SURF k``) and the keyword. Unsupported surface types,
multi-config-only features, annular/elliptical/rectangular apertures, BINARY_2 mirrors raise :class:`~rwwarp.errors.LensFileError`; unknown glasses
:class:`~rwwarp.errors.GlassError`; impossible geometry :class:`~rwwarp.errors.GeometryError`.
"""
from __future__ import annotations

import math
from pathlib import Path

from ..errors import GlassError, LensError, LensFileError

# keywords that belong to a SURF block (others are system data or ignored)
_SURF_KEYS = {"TYPE", "CURV", "DISZ", "GLAS", "CONI", "PARM", "XDAT", "STOP", "DIAM", "CLAP", "SQAP", "FLAP",
              "OBSC", "OBDC", "ELOB", "ELAP", "SQOB", "UDAP", "COMM", "HIDE", "MIRR", "SLAB", "POPS", "COAT",
              "MEMA", "PZUP", "PPAR", "MAZH", "SCBD", "ATTR", "FIMP", "IGNR", "VPAR", "VCON", "VDSZ"}
_UNITS = {"MM": 1.0, "CM": 10.0, "IN": 25.4, "METER": 1000.0, "M": 1000.0}
_SUPPORTED_TYPES = ("STANDARD", "EVENASPH", "ODDASPHE", "PARAXIAL", "BINARY_2")
# rwwarp keyword -> Zemax keyword, for errors raised while validating the built lens
_KEYWORD_MAP = {"thickness": "DISZ", "material": "GLAS", "semi_diameter": "DIAM", "focal_length": "PARM 1",
                "profile": "XDAT", "aspheric": "PARM", "type": "TYPE", "shape": "SQAP", "conic": "CONI",
                "radius": "CURV", "levels": "XDAT", "phase": "XDAT",
                "diffraction_order": "PARM 0"}


# ---------------------------------------------------------------------------------------------- text
def _decode(raw: bytes) -> str:
    """Decode a .zmx file: UTF-16 (BOM, or NUL bytes of an unmarked UTF-16 file), UTF-8, or Latin-1."""
    if raw.startswith(b"\xff\xfe") or raw.startswith(b"\xfe\xff"):
        return raw.decode("utf-16")
    if raw.startswith(b"\xef\xbb\xbf"):
        return raw[3:].decode("utf-8", errors="replace")
    head = raw[:400]
    if head.count(b"\x00") > len(head) // 4:
        even_nuls = head[0::2].count(b"\x00")
        return raw.decode("utf-16-be" if even_nuls > len(head) // 4 else "utf-16-le")
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        return raw.decode("latin-1")


class _Block:
    """One SURF block: lines as (keyword, tokens, line number)."""

    def __init__(self, number, line):
        self.number, self.line = number, line
        self.entries = []

    def get(self, key):
        for k, toks, ln in self.entries:
            if k == key:
                return toks, ln
        return None

    def all(self, key):
        return [(toks, ln) for k, toks, ln in self.entries if k == key]

    def has(self, key):
        return any(k == key for k, _, _ in self.entries)


class _Reader:
    def __init__(self, path):
        self.path = str(path)
        self.header = []  # (keyword, tokens, line)
        self.blocks = []

    # -------- errors
    def err(self, msg, surf=None, key=None, cls=LensFileError, line=None):
        where = f" (line {line})" if line is not None else ""
        return cls(msg + where, file=self.path, surface=None if surf is None else f"SURF {surf}", keyword=key)

    # -------- parsing
    def parse(self, text):
        cur = None
        for ln, raw in enumerate(text.splitlines(), start=1):
            line = raw.strip()
            if not line or line.startswith("!"):
                continue
            toks = line.split()
            key, rest = toks[0].upper(), toks[1:]
            if key == "SURF":
                try:
                    num = int(rest[0])
                except (IndexError, ValueError):
                    raise self.err(f"bad SURF line {line!r}", key="SURF", line=ln) from None
                if num != len(self.blocks):
                    raise self.err(f"surfaces must be numbered 0, 1, 2, ...; found SURF {num} after "
                                   f"{len(self.blocks)} surface(s)", surf=num, key="SURF", line=ln)
                from .validate_input import MAX_SURFACES
                if num > MAX_SURFACES + 1:
                    raise self.err(f"more than {MAX_SURFACES} lens surfaces", surf=num, key="SURF", line=ln)
                cur = _Block(num, ln)
                self.blocks.append(cur)
            elif cur is not None and key in _SURF_KEYS:
                cur.entries.append((key, rest, ln))
            else:
                self.header.append((key, rest, ln))
        if len(self.blocks) < 3:
            # a file cut short after a malformed value: name the value first (it is the likelier cause)
            self.check_numbers()
            raise self.err(f"a sequential .zmx needs an object, at least one lens surface and an image "
                           f"surface; found {len(self.blocks)} SURF block(s)")

    # keyword -> token positions that must be numbers (INFINITY allowed for DISZ), checked on a file
    # that ends too early, so that a malformed value is named with its line rather than the missing surfaces
    _NUMERIC = {"CURV": (0,), "DISZ": (0,), "CONI": (0,), "DIAM": (0,), "PARM": (0, 1), "XDAT": (0, 1),
                "ENPD": (0,), "FNUM": (0,), "WAVM": (0, 1), "PWAV": (0,)}

    def check_numbers(self):
        entries = [(None, k, t, ln) for k, t, ln in self.header] + \
            [(b.number, k, t, ln) for b in self.blocks for k, t, ln in b.entries]
        for surf, key, toks, ln in sorted(entries, key=lambda e: e[3]):
            for i in self._NUMERIC.get(key, ()):
                if i < len(toks) and not (key == "DISZ" and toks[i].upper() in ("INFINITY", "INF")):
                    self.num(toks, i, key if i == 0 else f"{key} {toks[0]}", surf=surf, key=key, line=ln)

    def hget(self, key):
        for k, toks, ln in self.header:
            if k == key:
                return toks, ln
        return None

    def hall(self, key):
        return [(toks, ln) for k, toks, ln in self.header if k == key]

    def num(self, toks, i, what, surf=None, key=None, line=None, allow_inf=False):
        try:
            tok = toks[i]
        except IndexError:
            raise self.err(f"missing value for {what}", surf=surf, key=key, line=line) from None
        if allow_inf and tok.upper() in ("INFINITY", "INF"):
            return math.inf
        try:
            v = float(tok)
        except ValueError:
            raise self.err(f"bad number {tok!r} for {what}", surf=surf, key=key, line=line) from None
        if not math.isfinite(v):
            raise self.err(f"non-finite value {tok!r} for {what}", surf=surf, key=key, line=line)
        return v


def read_zmx(path, strict: bool = True, binary2: str = "auto"):
    """Read a Zemax sequential ``.zmx`` file into a :class:`~rwwarp.lens.Lens` (lengths in mm).

    Surfaces that cross inside their ``DIAM`` heights raise a :class:`~rwwarp.errors.GeometryError`;
    with ``strict=False`` (what :func:`rwwarp.load_lens` passes by default) they load with a
    :class:`~rwwarp.errors.GeometryWarning` and are traced sequentially, as OpticStudio traces them.

    ``binary2``: ``"auto"`` (the module docstring's rule: a flat BINARY_2 behind everything is the wave-plane
    DOE, any other a phase surface) or ``"phase"`` (every BINARY_2 a phase surface traced in its order).

    See the module docstring for what is supported and how it maps. Raises
    :class:`~rwwarp.errors.LensFileError`, :class:`~rwwarp.errors.GlassError` or
    :class:`~rwwarp.errors.GeometryError` (all :class:`~rwwarp.errors.LensError`) naming the file, the
    Zemax surface (``SURF k``) and the keyword; no lens is returned half-built.
    """
    from ..lens import Lens, Sensor, Surface

    if binary2 not in ("auto", "phase"):
        raise ValueError(f"binary2 must be 'auto' or 'phase', got {binary2!r}")
    path = Path(path)
    rd = _Reader(path)
    from .validate_input import read_lens_bytes
    raw = read_lens_bytes(path)  # regular files only, size capped (LensFileError naming the file)
    try:
        text = _decode(raw)
    except UnicodeDecodeError as e:
        raise LensFileError(f"cannot decode the file as {e.encoding} text at byte {e.start}: {e.reason}",
                            file=str(path)) from None
    rd.parse(text)

    # ------------------------------------------------------------------ system data
    mode = rd.hget("MODE")
    if mode and mode[0] and mode[0][0].upper() != "SEQ":
        raise rd.err(f"only sequential files are supported (MODE {mode[0][0]})", key="MODE", line=mode[1])
    unit = rd.hget("UNIT")
    scale = 1.0
    if unit and unit[0]:
        u = unit[0][0].upper()
        if u not in _UNITS:
            raise rd.err(f"unsupported lens unit {unit[0][0]!r} (expected one of {sorted(_UNITS)})",
                         key="UNIT", line=unit[1])
        scale = _UNITS[u]
    name = ""
    nm = rd.hget("NAME")
    if nm:
        name = " ".join(nm[0])

    # wavelengths
    ftyp = rd.hget("FTYP")
    n_fields = n_waves = None
    field_type = 0
    if ftyp:
        field_type = int(rd.num(ftyp[0], 0, "field type", key="FTYP", line=ftyp[1]))
        if len(ftyp[0]) >= 4:
            n_fields = int(rd.num(ftyp[0], 2, "number of fields", key="FTYP", line=ftyp[1]))
            n_waves = int(rd.num(ftyp[0], 3, "number of wavelengths", key="FTYP", line=ftyp[1]))
    wavm = {}
    for toks, ln in rd.hall("WAVM"):
        idx = int(rd.num(toks, 0, "wavelength number", key="WAVM", line=ln))
        wavm[idx] = rd.num(toks, 1, "wavelength (um)", key="WAVM", line=ln)
    if wavm:
        idxs = sorted(wavm)
        if n_waves is not None:
            idxs = [i for i in idxs if i <= n_waves]
        wavelengths = [wavm[i] for i in idxs]
    elif rd.hget("WAVL"):
        toks, ln = rd.hget("WAVL")
        wavelengths = [rd.num(toks, i, "wavelength (um)", key="WAVL", line=ln) for i in range(len(toks))]
        if n_waves is not None:
            wavelengths = wavelengths[:n_waves]
    else:
        wavelengths = [0.55]
    if not wavelengths:
        raise rd.err("no wavelengths defined", key="WAVM")
    pw = rd.hget("PWAV")
    primary = 1
    if pw:
        primary = int(rd.num(pw[0], 0, "primary wavelength number", key="PWAV", line=pw[1]))
        if not 1 <= primary <= len(wavelengths):
            raise rd.err(f"primary wavelength {primary} not among the {len(wavelengths)} wavelengths",
                         key="PWAV", line=pw[1])
    primary_um = wavelengths[primary - 1]

    # fields
    fields_deg = None
    field_heights = None  # FTYP 1: object heights (lens units), turned into angles once the pupil is known
    if field_type in (0, 1):
        def _vals(*keys):
            for k in keys:
                got = rd.hget(k)
                if got:
                    return [rd.num(got[0], i, "field value", key=k, line=got[1]) for i in range(len(got[0]))]
            return None
        xs, ys = _vals("XFLN", "XFLD"), _vals("YFLN", "YFLD")
        if xs is not None or ys is not None:
            xs = xs or [0.0] * len(ys)
            ys = ys or [0.0] * len(xs)
            n = min(len(xs), len(ys))
            if n_fields is not None:
                n = min(n, n_fields)
            else:  # drop the (0, 0) padding after the first field
                while n > 1 and xs[n - 1] == 0 and ys[n - 1] == 0:
                    n -= 1
            fields_deg = [ys[i] if xs[i] == 0 else [xs[i], ys[i]] for i in range(n)]
            if field_type == 1:
                field_heights, fields_deg = [(xs[i] * scale, ys[i] * scale) for i in range(n)], None

    # Zemax's per-field vignetting factors shrink / shift each field's pupil; rwwarp traces the whole
    # paraxial pupil of every field (as with the factors at 0), and says so
    vig = [k for k in ("VDXN", "VDYN", "VCXN", "VCYN", "VANN")
           if any(_isnum(t) and float(t) != 0 for toks, _ in rd.hall(k) for t in toks)]
    if vig:
        import warnings
        warnings.warn(f"{path}: vignetting factors {', '.join(vig)} are ignored: every field traces the whole "
                      "paraxial entrance pupil", UserWarning, stacklevel=2)

    # system aperture
    epd = fnum = None
    floa = rd.hget("FLOA") is not None
    if rd.hget("ENPD") and not floa:
        toks, ln = rd.hget("ENPD")
        epd = rd.num(toks, 0, "entrance pupil diameter", key="ENPD", line=ln) * scale
    obna = None
    if rd.hget("OBNA") and not floa:
        toks, ln = rd.hget("OBNA")
        obna = rd.num(toks, 0, "object-space numerical aperture", key="OBNA", line=ln)
        if not 0 < obna < 1:
            raise rd.err(f"OBNA must be in (0, 1) (object space is air), got {obna}", key="OBNA", line=ln)
        epd = None
    for key in ("PFNO",):
        if rd.hget(key):
            raise rd.err(f"unsupported system aperture type {key} (use ENPD, FNUM or FLOA)", key=key,
                         line=rd.hget(key)[1])
    floa_sd = None  # the stop's DIAM under FLOA
    if rd.hget("FNUM"):
        toks, ln = rd.hget("FNUM")
        fnum = rd.num(toks, 0, "image-space F/#", key="FNUM", line=ln)
        if not fnum > 0:
            raise rd.err(f"FNUM must be > 0, got {fnum}", key="FNUM", line=ln)
        epd = None

    # the stop floats; its own size sets nothing
    pupil_set = epd is not None or fnum is not None or floa or obna is not None
    # ------------------------------------------------------------------ surfaces
    blocks = rd.blocks
    obj, img = blocks[0], blocks[-1]
    object_distance = math.inf
    got = obj.get("DISZ")
    if got:
        object_distance = rd.num(got[0], 0, "object distance", surf=0, key="DISZ",
                                 line=got[1], allow_inf=True)
        object_distance *= scale
    if obj.has("STOP") or img.has("STOP"):
        raise rd.err("the stop cannot be the object or image surface", surf=obj.number if obj.has("STOP")
                     else img.number, key="STOP")
    img_type = (img.get("TYPE") or (["STANDARD"], None))[0]
    if img.get("CURV") and rd.num(img.get("CURV")[0], 0, "curvature", surf=img.number, key="CURV") != 0:
        raise rd.err("a curved image surface is not supported (the sensor is a plane)", surf=img.number,
                     key="CURV")
    if img_type and img_type[0].upper() not in ("STANDARD",):
        raise rd.err(f"image surface type {img_type[0]} not supported", surf=img.number, key="TYPE")

    from .. import materials
    surfaces, zsurf = [], []  # rwwarp surfaces and their Zemax numbers
    extents = []  # per rwwarp surface: the DIAM height (for the crossing check only; DIAM does not clip)
    medium = "air"
    for bi, b in enumerate(blocks[1:-1]):
        k = b.number

        def num(key, i=0, what=None, default=None, allow_inf=False, b=b, k=k):
            got = b.get(key)
            if got is None:
                return default
            return rd.num(got[0], i, what or key, surf=k, key=key, line=got[1], allow_inf=allow_inf)

        typ = (b.get("TYPE") or (["STANDARD"], None))[0]
        typ = typ[0].upper() if typ else "STANDARD"
        if typ not in _SUPPORTED_TYPES:
            raise rd.err(f"unsupported surface type {typ} (supported: {', '.join(_SUPPORTED_TYPES)})", surf=k,
                         key="TYPE", line=b.get("TYPE")[1])
        curv = num("CURV", what="curvature", default=0.0) / scale
        thick = num("DISZ", what="thickness", default=0.0, allow_inf=True)
        if not math.isfinite(thick):
            raise rd.err("only the object surface may have an infinite thickness", surf=k, key="DISZ")
        thick *= scale
        conic = num("CONI", what="conic", default=0.0)
        parms = {}
        for toks, ln in b.all("PARM"):
            i = int(rd.num(toks, 0, "parameter number", surf=k, key="PARM", line=ln))
            parms[i] = rd.num(toks, 1, f"PARM {i}", surf=k, key=f"PARM {i}", line=ln)
        xdat = {}
        for toks, ln in b.all("XDAT"):
            i = int(rd.num(toks, 0, "extra data number", surf=k, key="XDAT", line=ln))
            xdat[i] = rd.num(toks, 1, f"XDAT {i}", surf=k, key=f"XDAT {i}", line=ln)

        # material after the surface
        material = "air"
        mirror = False
        glas = b.get("GLAS")
        if glas:
            toks, ln = glas
            if not toks:
                raise rd.err("missing glass name", surf=k, key="GLAS", line=ln)
            gname = toks[0]
            if gname.upper() == "MIRROR":
                if typ not in ("STANDARD", "EVENASPH", "ODDASPHE"):
                    raise rd.err(f"a {typ} mirror is not supported (STANDARD and aspheric mirrors are)", surf=k,
                                 key="GLAS", line=ln)
                mirror, material = True, medium  # light turns back in the same medium
            elif gname.upper() == "___BLANK":
                nd = rd.num(toks, 3, "model glass nd", surf=k, key="GLAS", line=ln)
                vd = rd.num(toks, 4, "model glass Vd", surf=k, key="GLAS", line=ln)
                material = f"{nd!r}/{vd!r}"
            elif gname.upper() != "AIR":
                material = gname
            if material != "air" and not mirror:
                file_nd = file_vd = None
                if gname.upper() != "___BLANK" and len(toks) >= 5 and _isnum(toks[3]) and _isnum(toks[4]):
                    file_nd, file_vd = float(toks[3]), float(toks[4])
                try:
                    material, note = materials.resolve_glass(material, file_nd, file_vd)
                except LensError as e:
                    # the lookup's own message names the glass once; Zemax's nd 0 / Vd 0 placeholders are no data
                    raise rd.err(f"{_core(e)} (and the file lists no usable nd / Vd for a model glass)", surf=k,
                                 key="GLAS", cls=GlassError, line=ln) from None
                if note is not None:
                    import warnings
                    warnings.warn(f"{path}: SURF {k} GLAS (line {ln}): {note}", materials.GlassSubstitutionWarning,
                                  stacklevel=2)

        # aperture
        sd, shape = None, "circle"
        diam = b.get("DIAM")
        is_stop = b.has("STOP")
        d_val = None
        if diam:
            d_val = rd.num(diam[0], 0, "semi-diameter", surf=k, key="DIAM", line=diam[1]) * scale
            if is_stop and floa:
                floa_sd = d_val  # float by stop size: the stop's size sets the pupil (it does not clip)
            # DIAM (fixed or automatic) does not clip in OpticStudio or optiland: only the stop keeps a fixed
            # one (or, under FLOA, any), recorded as its semi_diameter; the stop floats under ENPD / FNUM / FLOA
            # / OBNA, so that clips nothing either
            fixed = len(diam[0]) > 1 and diam[0][1] == "1"
            if d_val > 0 and is_stop and (fixed or floa or not pupil_set):
                sd = d_val
        for bad in ("ELOB", "ELAP", "UDAP", "OBDC"):
            if b.has(bad):
                raise rd.err(f"unsupported surface aperture {bad} (only CLAP, SQAP, FLAP, OBSC and SQOB)",
                             surf=k, key=bad, line=b.get(bad)[1])
        obscuration = None
        for key in ("OBSC", "SQOB"):
            got = b.get(key)
            if not got:
                continue
            if obscuration is not None:
                raise rd.err("one obscuration per surface", surf=k, key=key, line=got[1])
            v0 = rd.num(got[0], 0, "first size", surf=k, key=key, line=got[1]) * scale
            v1 = rd.num(got[0], 1, "second size", surf=k, key=key, line=got[1]) * scale
            decs = [float(t) for t in got[0][3:5] if _isnum(t)]
            if any(v != 0 for v in decs):
                raise rd.err("decentred obscurations are not supported", surf=k, key=key, line=got[1])
            if key == "OBSC":  # circular obscuration: min radius, max radius (blocks inside the max radius)
                if v0 != 0:
                    raise rd.err(f"annular obscurations are not supported (OBSC minimum radius {v0})", surf=k,
                                 key=key, line=got[1])
                obscuration = {"shape": "circle", "radius": v1}
            else:  # rectangular obscuration: x half width, y half width
                obscuration = {"shape": "rectangle", "half_x": v0, "half_y": v1}
        clap = b.get("CLAP")
        if clap:
            rmin = rd.num(clap[0], 0, "minimum radius", surf=k, key="CLAP", line=clap[1]) * scale
            rmax = rd.num(clap[0], 1, "maximum radius", surf=k, key="CLAP", line=clap[1]) * scale
            if rmin != 0:
                # an annular aperture: clear between rmin and rmax (a circular obscuration inside)
                if obscuration is not None:
                    raise rd.err("an annular CLAP and an obscuration on one surface", surf=k, key="CLAP",
                                 line=clap[1])
                obscuration = {"shape": "circle", "radius": rmin}
            sd = rmax
        sqap = b.get("SQAP")
        if sqap:
            hx = rd.num(sqap[0], 0, "x half width", surf=k, key="SQAP", line=sqap[1]) * scale
            hy = rd.num(sqap[0], 1, "y half width", surf=k, key="SQAP", line=sqap[1]) * scale
            if abs(hx - hy) > 1e-12 * max(abs(hx), abs(hy)):
                raise rd.err(f"rectangular apertures are not supported (SQAP {hx} x {hy}); only squares",
                             surf=k, key="SQAP", line=sqap[1])
            decs = [float(t) for t in sqap[0][3:] if _isnum(t)]
            if any(v != 0 for v in decs):
                raise rd.err("decentred apertures are not supported", surf=k, key="SQAP", line=sqap[1])
            sd, shape = hx, "square"
        flap = b.get("FLAP")
        if flap and not clap and not sqap:
            vals = [float(t) for t in flap[0] if _isnum(t)]
            rmax = vals[1] * scale if len(vals) > 1 and vals[1] > 0 else None
            if rmax is None and diam:
                rmax = rd.num(diam[0], 0, "semi-diameter", surf=k, key="DIAM", line=diam[1]) * scale
            if rmax:
                sd = rmax
        stop = is_stop
        hard = bool(clap or sqap or (flap and sd is not None))
        if stop and pupil_set and hard:
            # the system aperture (ENPD, FNUM, FLOA) sets the pupil and the stop floats, but an explicit
            # aperture on the stop still clips (as in Zemax): a floating stop plane at the vertex, then
            # the surface itself with its hard aperture (issue 11 defect 7)
            surfaces.append(Surface(type="aperture", thickness=0.0, semi_diameter=None, stop=True))
            zsurf.append(k)
            extents.append(d_val)
            stop = False

        if typ in ("STANDARD", "EVENASPH", "ODDASPHE"):
            asph, a2, odd = [], 0.0, []
            if typ == "ODDASPHE":  # PARM 1..8: the coefficients of r^1 .. r^8
                for i in sorted(parms):
                    if (i < 1 or i > 8) and parms[i] != 0:
                        raise rd.err(f"PARM {i} is not an ODDASPHE coefficient", surf=k, key=f"PARM {i}")
                odd = [parms.get(i, 0.0) * scale ** (1 - i) for i in range(1, 9)]
                while odd and odd[-1] == 0.0:
                    odd.pop()
            if typ == "EVENASPH":
                a2 = parms.get(1, 0.0) / scale  # the r^2 term (Surface.a2, 1/mm)
                for i in sorted(parms):
                    if i > 8 and parms[i] != 0:
                        raise rd.err(f"PARM {i} is not an EVENASPH coefficient", surf=k, key=f"PARM {i}")
                asph = [parms.get(i, 0.0) * scale ** (1 - 2 * i) for i in range(2, 9)]
                while asph and asph[-1] == 0.0:
                    asph.pop()
            radius = None if curv == 0 else 1.0 / curv
            surfaces.append(Surface(type="standard", thickness=thick, radius=radius, conic=conic, a2=a2,
                                    aspheric=asph, material=material, semi_diameter=sd, shape=shape,
                                    obscuration=obscuration, mirror=mirror, odd_aspheric=odd,
                                    stop=stop))
            zsurf.append(k)
            extents.append(d_val)
        elif typ == "PARAXIAL":
            if curv != 0:
                raise rd.err("a PARAXIAL surface must be flat (CURV 0)", surf=k, key="CURV")
            if 1 not in parms:
                raise rd.err("PARAXIAL surface needs its focal length in PARM 1", surf=k, key="PARM 1")
            f = parms[1] * scale
            if f == 0:
                raise rd.err("PARAXIAL focal length (PARM 1) must be non-zero", surf=k, key="PARM 1")
            surfaces.append(Surface(type="thin_lens", thickness=thick, focal_length=f, material=material,
                                    semi_diameter=sd, shape=shape, stop=stop, obscuration=obscuration))
            zsurf.append(k)
            extents.append(d_val)
        else:  # BINARY_2: an even asphere's sag (PARM 1..8) carrying the phase sum_i A_i rho^(2 i) in order PARM 0
            for i in sorted(parms):
                if i > 8 and parms[i] != 0:
                    raise rd.err(f"PARM {i} is not a BINARY_2 parameter", surf=k, key=f"PARM {i}")
            order = parms.get(0, 1.0)
            nterms = int(xdat.get(1, 0))
            if nterms < 0:
                raise rd.err(f"BINARY_2 number of terms XDAT 1 = {nterms} must be >= 0", surf=k, key="XDAT 1")
            from .validate_input import MAX_TERMS
            if nterms > MAX_TERMS or xdat.get(1, 0) != nterms:
                raise rd.err(f"BINARY_2 number of terms XDAT 1 = {xdat.get(1)} must be an integer 0..{MAX_TERMS}",
                             surf=k, key="XDAT 1")
            terms = [xdat.get(2 + i, 0.0) for i in range(1, nterms + 1)]
            rnorm = xdat.get(2, 0.0) * scale
            if nterms and not rnorm > 0:
                raise rd.err(f"BINARY_2 normalisation radius XDAT 2 = {rnorm} must be > 0",
                             surf=k, key="XDAT 2")
            a2 = parms.get(1, 0.0) / scale
            asph = [parms.get(i, 0.0) * scale ** (1 - 2 * i) for i in range(2, 9)]
            while asph and asph[-1] == 0.0:
                asph.pop()
            flat = curv == 0 and conic == 0 and a2 == 0 and not asph
            wave_plane = binary2 == "auto" and flat and bi == len(blocks) - 3
            if wave_plane:
                profile = {"kind": "even_poly", "norm_radius": rnorm if rnorm > 0 else 1.0,
                           "coefficients": [order * a for a in terms]}
                if material != medium:  # refraction at the flat DOE: a plane interface, then the phase
                    surfaces.append(Surface(type="standard", thickness=0.0, radius=None, material=material,
                                            semi_diameter=sd, shape=shape))
                    zsurf.append(k)
                    extents.append(d_val)
                surfaces.append(Surface(type="doe", thickness=thick, semi_diameter=sd, shape=shape,
                                        design_wavelength_um=primary_um, material="fused_silica", profile=profile,
                                        stop=stop, obscuration=obscuration))
            else:
                from ..phase_surface import MAX_PHASE_TERMS
                if order != int(order):
                    raise rd.err(f"BINARY_2 diffraction order PARM 0 = {order} must be an integer", surf=k,
                                 key="PARM 0")
                while terms and terms[-1] == 0.0:
                    terms.pop()
                if len(terms) > MAX_PHASE_TERMS:
                    raise rd.err(f"BINARY_2 with {len(terms)} phase terms: a phase surface (curved, or not the last "
                                 f"surface) carries at most {MAX_PHASE_TERMS}", surf=k, key="XDAT 1")
                phase = {"kind": "even_poly", "norm_radius": rnorm if rnorm > 0 else 1.0, "coefficients": terms}
                surfaces.append(Surface(type="standard", thickness=thick, radius=None if curv == 0 else 1.0 / curv,
                                        conic=conic, a2=a2, aspheric=asph, material=material, semi_diameter=sd,
                                        shape=shape, obscuration=obscuration, stop=stop, phase=phase,
                                        diffraction_order=int(order), design_wavelength_um=primary_um))
            zsurf.append(k)
            extents.append(d_val)
        medium = material

    # ------------------------------------------------ build (validation errors map back to SURF k)
    try:
        lens = Lens(surfaces=surfaces, sensor=Sensor(), object_distance=object_distance,
                    wavelengths_um=wavelengths, name=name, entrance_pupil_diameter=epd,
                    fields_deg=fields_deg, source=str(path), surface_labels=[f"SURF {k}" for k in zsurf],
                    primary_wavelength_um=primary_um, surface_extents=extents, allow_crossing=not strict)
        if fnum is not None:
            from ..paraxial import efl
            lens.entrance_pupil_diameter = abs(efl(lens, primary_um)) / fnum
            _revalidate(lens)
        elif obna is not None:
            # object-space NA: the marginal ray from the axial object point to the paraxial entrance pupil's
            # edge makes the angle asin(NA) (object space in air), as Zemax and optiland size it
            if not math.isfinite(object_distance):
                raise rd.err("OBNA needs a finite object distance (SURF 0 DISZ)", key="OBNA")
            lens.entrance_pupil_diameter = 2.0 * abs(object_distance + _ep_z(lens, primary_um)) * \
                math.tan(math.asin(obna))
            _revalidate(lens)
        elif floa:
            # float by stop size: the entrance pupil is the paraxial image of the stop at its DIAM size
            # (primary wavelength); the stop then floats like under ENPD: real rays are not clipped there
            stop_k = next((b.number for b in blocks if b.has("STOP")), None)
            if floa_sd is None or not floa_sd > 0:
                raise rd.err("FLOA (float by stop size) needs the stop's semi-diameter (DIAM)", surf=stop_k,
                             key="DIAM")
            from ..paraxial import ynu_trace
            ya, _ = ynu_trace(lens, primary_um, 1.0, 0.0)
            m = abs(ya[lens.stop_index])
            if m == 0:
                raise rd.err("FLOA: the stop is at a focus (no entrance pupil)", surf=stop_k, key="FLOA")
            lens.entrance_pupil_diameter = 2.0 * floa_sd / m
            _revalidate(lens)
        if field_heights is not None:
            # FTYP 1 (object heights): each field as the angle of its chief ray to the paraxial entrance
            # pupil centre, atan(h / (object distance + EP z)) (a rotationally symmetric lens images +-h alike)
            if not math.isfinite(object_distance):
                raise rd.err("FTYP 1 (object-height fields) needs a finite object distance (SURF 0 DISZ)",
                             key="FTYP")
            dist = object_distance + _ep_z(lens, primary_um)
            ang = [tuple(math.degrees(math.atan(v / dist)) for v in h) for h in field_heights]
            lens.fields_deg = [a[1] if a[0] == 0 else [a[0], a[1]] for a in ang]
    except LensError as e:
        if isinstance(e.surface, str):  # already a Zemax "SURF k" (raised by this reader)
            surf = e.surface
        elif isinstance(e.surface, int) and 0 <= e.surface < len(zsurf):
            surf = f"SURF {zsurf[e.surface]}"
        else:
            surf = None
        key = _KEYWORD_MAP.get(e.keyword, e.keyword)
        raise type(e)(_core(e), file=str(path), surface=surf, keyword=key) from None
    return lens


def _revalidate(lens) -> None:
    """Validate again after the pupil is set (its crossing warning was already given once)."""
    import warnings
    from ..errors import GeometryWarning
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", GeometryWarning)
        lens.validate()


def _ep_z(lens, wavelength_um) -> float:
    """Paraxial entrance-pupil position (mm from the first vertex): the stop imaged back through the
    surfaces before it (independent of the pupil's size)."""
    from ..paraxial import ynu_trace
    i = lens.stop_index
    ya, _ = ynu_trace(lens, wavelength_um, 1.0, 0.0)
    yb, _ = ynu_trace(lens, wavelength_um, 0.0, 1.0)
    if ya[i] == 0:
        raise LensError("the stop is at a focus: no entrance pupil", file=lens.source,
                        surface=lens.surface_label(i))
    return float(yb[i] / ya[i])


def _core(e: LensError) -> str:
    """The message of a LensError without its 'file ..., surface ...: ' prefix."""
    prefix = str(LensError("", file=e.file, surface=e.surface, keyword=e.keyword, field=e.field))
    s = str(e)
    return s[len(prefix):] if prefix and s.startswith(prefix) else s


def _isnum(tok: str) -> bool:
    try:
        float(tok)
        return True
    except ValueError:
        return False
