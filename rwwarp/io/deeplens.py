"""Reader of DeepLens lens files (GeoLens and HybridLens JSON) into a :class:`rwwarp.lens.Lens`.

Units: DeepLens files are in mm and um, as rwwarp.

Layout. Surface positions come from ``d_next`` (distance to the next surface; the last surface's
``d_next`` is the distance to the sensor) when every surface has it, else from the older absolute
``d`` (vertex z of each surface) with ``d_sensor`` for the sensor. Keys written in parentheses, such as
``"(d)"``, ``"(c)"``, ``"(sensor_size)"``, are derived values and are ignored; so are DeepLens outputs
(``foclen``, ``fnum``, ``r_last``, ``mat1``, ``idx``, ...).

Surfaces (``r`` is the semi-diameter in mm, ``mat2`` the material after the surface):

================ =====================================================================================
DeepLens         rwwarp
================ =====================================================================================
Aperture, Stop   ``aperture`` (``is_square`` -> square); the first one is the stop
Spheric          ``standard``: curvature from ``roc`` (radius of curvature, 0 = flat) or ``c`` (1/mm)
Aspheric         ``standard`` with ``k`` (conic) and ``ai``: ``use_ai2`` true or absent (the legacy
                 layout) means ``ai[0]`` is the r^2 term (``Surface.a2``) and ``ai[1:]`` r^4, r^6, ...;
                 ``use_ai2`` false means ``ai`` starts at r^4.
Plane            flat ``standard`` into ``mat2``
ThinLens         ``thin_lens`` of focal length ``f`` (``foclen`` in newer files)
Phase            a flat ``standard`` surface into ``mat2`` carrying a diffractive ``phase`` traced in order
                 ``diffraction_order`` (default 1; :mod:`rwwarp.phase_surface`): ``param_model`` ``binary2``
                 (``order2 .. order12`` on (r / R)^2 .. (r / R)^12, R = ``norm_radii``, default ``r``) ->
                 ``even_poly``; ``fresnel`` (``f0`` at 0.55 um) -> ``fresnel``. DeepLens bends the ray by
                 renormalising ``(d_x + lambda/2pi dphi/dx, d_y + ..., d_z)`` after refracting at the plane, and
                 adds the wrapped phase to the path; rwwarp solves the grating equation in the medium after
                 (they agree to first order in the bending) and adds the unwrapped phase (the same
                 ``exp(i k OPL)`` at every wavelength's own traced path)
================ =====================================================================================

The HybridLens ``DOE`` block becomes a ``doe`` surface inserted at its absolute ``d``; its aperture
is a square of side ``l`` (old layout), ``size``, or ``res * fab_ps``. Phase models (``type`` of the
block, or ``param_model`` of the older ``"type": "DOE"`` block):

* ``binary2`` (old): ``order2..order8`` on (r/R)^2 .. (r/R)^8 with R the half-diagonal -> ``even_poly``;
* ``Binary2`` (new): ``pi (alpha2 r^2 + alpha4 r^4 + ...)``, r in mm -> ``even_poly`` (R = half-diagonal);
* ``fresnel``/``Fresnel``: ``f0`` (mm) at ``fresnel_wvln``/``wvln0`` -> ``fresnel``;
* ``zernike``/``Zernike``: 37 ``z_coeff`` -> Noll ``zernike`` (DeepLens's Z2/Z3 are sin/cos, Noll's
  cos/sin: they are swapped here; R = half-diagonal (old) or half side (new); DeepLens masks the new
  model outside the unit circle and writes Z29/Z30 with a constant "-4" for "-4 rho": rwwarp
  evaluates the true Noll polynomials everywhere);
* ``cubic`` (old): ``a3 (x^3 + y^3)``, x in mm -> ``cubic``; ``poly1d`` with zero odd terms -> ``even_poly``;
* ``pixel2d``/``Pixel2D``: ``doe_path``/``phase_map_path`` to a ``.npy`` -> ``pixel_map`` (torch ``.pth``
  files must be converted: ``numpy.save(p, torch.load(f).numpy())``).

The new DeepLens DOE quantises its phase to ``fab_step`` levels (default 16): ``levels`` is set to
that; the old ``"DOE"`` block does not quantise. Substrate ``mat`` (default fused_silica), design
wavelength ``wvln0`` (default 0.55 um).

Sensor: ``sensor_res`` (default 2000 x 2000) and ``sensor_size`` or the half-diagonal ``r_sensor``
(square pixels). The object is at infinity and the wavelengths are DeepLens's RGB set
(0.486, 0.587, 0.656 um); neither is stored in a DeepLens file. ``enpd`` sets the entrance pupil.

The newer inline layout, where the DOE (``{"type": "DOE", "param_model": ..., "d_next": ...}``) and the
sensor (a last ``{"type": "Sensor", "l": side_mm, "res": [nx, ny]}``) are entries of ``surfaces``, is read
the same way (the sensor entry ends the ``d_next`` chain and gives the sensor's size and resolution).

Errors name the file, the surface (its index in the DeepLens ``surfaces`` list, or ``DOE``) and the key.
"""
from __future__ import annotations

import math

from ..errors import LensError, LensFileError

DEFAULT_WAVELENGTHS_UM = [0.486, 0.587, 0.656]
_SURFACE_TYPES = ("Aperture", "Stop", "Spheric", "Aspheric", "Plane", "ThinLens", "Phase")


def _derived(key: str) -> bool:
    return key.startswith("(") and key.endswith(")")


def lens_from_deeplens(d: dict, source=None, strict: bool = True):
    """Build a :class:`~rwwarp.lens.Lens` from a parsed DeepLens GeoLens/HybridLens JSON dictionary.

    ``source`` is the file it came from (for messages, and to resolve a pixel map's relative path).
    Raises :class:`~rwwarp.errors.LensFileError` for unknown surface types and bad or missing keys,
    :class:`~rwwarp.errors.GlassError` for unknown materials, :class:`~rwwarp.errors.GeometryError`
    for crossing surfaces (with ``strict=False``, what :func:`rwwarp.load_lens` passes by default, a
    :class:`~rwwarp.errors.GeometryWarning` instead); nothing is half-built.
    """
    from .. import materials
    from ..lens import Lens, Sensor, Surface

    src = None if source is None else str(source)

    def err(msg, surf=None, key=None, cls=LensFileError):
        return cls(msg, file=src, surface=surf, keyword=key)

    if not isinstance(d, dict):
        raise err(f"not a lens file: expected a JSON object, got {type(d).__name__}")
    d = {k: v for k, v in d.items() if not _derived(k)}
    surfs = d.get("surfaces")
    if not isinstance(surfs, list) or not surfs:
        raise err("not a rwwarp-lens/1 or DeepLens file: no 'format' and no 'surfaces' list", key="surfaces")

    def num(sd, key, i, *, default=None, positive=False):
        if key not in sd or sd[key] is None:
            if default is not None:
                return default
            raise err(f"missing {key!r}", i, key)
        v = sd[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise err(f"{key!r} must be a finite number, got {v!r}", i, key)
        if positive and not v > 0:
            raise err(f"{key!r} must be > 0, got {v}", i, key)
        return float(v)

    # ---------------------------------------------------------------- positions
    clean = []
    for i, sd in enumerate(surfs):
        if not isinstance(sd, dict):
            raise err(f"surface entry must be an object, got {type(sd).__name__}", i)
        clean.append({k: v for k, v in sd.items() if not _derived(k)})
    # the newer inline layout: the DOE and the sensor are entries of 'surfaces' ({"type": "DOE", ...} with
    # its d_next, and a last {"type": "Sensor", "l": side, "res": [nx, ny]} whose position ends the chain)
    inline_sensor = None
    if clean and clean[-1].get("type") == "Sensor":
        inline_sensor = clean.pop()
    for i, sd in enumerate(clean):
        if sd.get("type") == "Sensor":
            raise err("a 'Sensor' entry must be the last of 'surfaces'", i, "type")
    relative = all("d_next" in sd for sd in clean)
    if relative:
        z, zc = [], 0.0
        for i, sd in enumerate(clean):
            z.append(zc)
            zc += num(sd, "d_next", i)
        z_sensor = zc
    else:
        if not all("d" in sd for sd in clean):
            if any("d_next" in sd for sd in clean):
                i, key = next(i for i, sd in enumerate(clean) if "d_next" not in sd), "d_next"
            else:
                i, key = next(i for i, sd in enumerate(clean) if "d" not in sd), "d"
            raise err("surface positions need 'd_next' on every surface or the absolute 'd' on every surface",
                      i, key)
        z = [num(sd, "d", i) for i, sd in enumerate(clean)]
        if "d_sensor" not in d:
            raise err("the absolute 'd' layout needs 'd_sensor' (sensor z, mm)", key="d_sensor")
        z_sensor = num(d, "d_sensor", None)

    # ---------------------------------------------------------------- surfaces
    items = []  # (z, Surface, label)
    stop_done = False
    inline_doe = None
    for i, sd in enumerate(clean):
        typ = sd.get("type")
        if typ == "DOE":
            if inline_doe is not None or d.get("DOE") is not None:
                raise err("at most one DOE (inline in 'surfaces' or the 'DOE' block)", i, "type")
            inline_doe = (i, dict({k: v for k, v in sd.items() if k not in ("idx", "d_next", "type")},
                                  type=sd.get("param_model", "pixel2d"), d=z[i]))
            continue
        if typ not in _SURFACE_TYPES:
            raise err(f"unknown or unsupported DeepLens surface type {typ!r} "
                      f"(supported: {', '.join(_SURFACE_TYPES)})", i, "type")
        for key, neutral in (("pos_xy", [0.0, 0.0]), ("vec_local", [0.0, 0.0, 1.0]), ("origin", None)):
            v = sd.get(key)
            if v is not None and (neutral is None or not isinstance(v, list)
                                  or any(isinstance(a, bool) or not isinstance(a, (int, float)) for a in v)
                                  or [float(a) for a in v] != neutral):
                raise err(f"decentred or tilted surfaces are not supported ({key} = {v!r:.80})", i, key)
        semi = num(sd, "r", i, positive=True) if sd.get("r") is not None else None
        shape = "square" if sd.get("is_square") and semi is not None else "circle"  # no r: no aperture, no shape
        if typ in ("Aperture", "Stop"):
            s = Surface(type="aperture", semi_diameter=semi, shape=shape, stop=not stop_done)
            stop_done = True
        elif typ == "ThinLens":
            fkey = "foclen" if "f" not in sd and "foclen" in sd else "f"  # newer DeepLens writes 'foclen'
            s = Surface(type="thin_lens", focal_length=num(sd, fkey, i), semi_diameter=semi, shape=shape)
        else:
            material = _material(sd, i, src, err, materials)
            if typ == "Plane":
                s = Surface(type="standard", radius=None, material=material, semi_diameter=semi, shape=shape)
            elif typ == "Phase":
                s = _phase_surface(sd, i, semi, shape, material, num, err, Surface)
            else:
                if sd.get("roc") not in (None, 0, 0.0):
                    radius = num(sd, "roc", i)
                elif "c" in sd:
                    c = num(sd, "c", i)
                    radius = None if c == 0 else 1.0 / c
                elif sd.get("roc") in (0, 0.0):
                    radius = None
                else:
                    raise err("missing curvature: give 'roc' (mm) or 'c' (1/mm)", i, "roc")
                conic, asph, a2 = 0.0, [], 0.0
                if typ == "Aspheric":
                    conic = num(sd, "k", i, default=0.0)
                    ai = sd.get("ai") or []
                    if not isinstance(ai, list):
                        raise err(f"'ai' must be a list of numbers, got {ai!r}", i, "ai")
                    try:
                        ai = [float(a) for a in ai]
                    except (TypeError, ValueError):
                        raise err(f"'ai' must be a list of numbers, got {ai!r}", i, "ai") from None
                    if sd.get("use_ai2", True) and ai:
                        a2, ai = ai[0], ai[1:]  # the r^2 term (Surface.a2)
                    while ai and ai[-1] == 0.0:
                        ai.pop()
                    asph = ai
                s = Surface(type="standard", radius=radius, conic=conic, aspheric=asph, material=material,
                            semi_diameter=semi, shape=shape, a2=a2)
        items.append((z[i], s, i))

    # ---------------------------------------------------------------- DOE (HybridLens)
    if d.get("DOE") is not None or inline_doe is not None:
        if inline_doe is not None:
            def err_inline(msg, surf=None, key=None, cls=LensFileError, _i=inline_doe[0]):
                return err(f"inline DOE: {msg}", _i, key, cls)
            doe_surface, z_doe = _doe(inline_doe[1], err_inline)
        else:
            doe_surface, z_doe = _doe(d["DOE"], err)
        pos = len(items)
        while pos > 0 and items[pos - 1][0] > z_doe:
            pos -= 1
        items.insert(pos, (z_doe, doe_surface, "DOE"))

    # thicknesses from positions
    surfaces = []
    labels = []
    for k, (zk, s, label) in enumerate(items):
        z_next = items[k + 1][0] if k + 1 < len(items) else z_sensor
        s.thickness = float(z_next - zk)
        surfaces.append(s)
        labels.append(label)
    # a first surface not at z = 0 only shifts the origin (rwwarp puts the first vertex at z = 0)

    # ---------------------------------------------------------------- sensor and system
    if inline_sensor is not None:
        if d.get("sensor_res") is None and inline_sensor.get("res") is not None:
            d = dict(d, sensor_res=inline_sensor["res"])
        if d.get("sensor_size") is None and d.get("r_sensor") is None and inline_sensor.get("l") is not None:
            d = dict(d, sensor_size=inline_sensor["l"])
    res = d.get("sensor_res", [2000, 2000])
    try:
        res = [_int(v) for v in (res if isinstance(res, (list, tuple)) else [res, res])]
    except (TypeError, ValueError, OverflowError):
        raise err(f"'sensor_res' must be two integers, got {res!r}", key="sensor_res") from None
    if len(res) != 2 or min(res) < 1:
        raise err(f"'sensor_res' must be two positive integers, got {res!r}", key="sensor_res")
    if d.get("sensor_size") is not None:
        size = d["sensor_size"]
        size = size if isinstance(size, (list, tuple)) else [size, size]
        try:
            pitch = num({"sensor_size": size[0]}, "sensor_size", None, positive=True) / res[0]
        except (TypeError, ValueError, IndexError, KeyError):
            raise err(f"'sensor_size' must be [w, h] in mm, got {size!r}", key="sensor_size") from None
    elif d.get("r_sensor") is not None:
        pitch = 2.0 * num(d, "r_sensor", None, positive=True) / math.hypot(res[0], res[1])
    else:
        raise err("no sensor size: give 'sensor_size' [w, h] (mm) or the half-diagonal 'r_sensor' (mm)",
                  key="r_sensor")
    epd = None if d.get("enpd") is None else num(d, "enpd", None, positive=True)
    if not isinstance(d.get("info", ""), (str, type(None))):
        raise err(f"'info' must be a string, got {type(d['info']).__name__}", key="info")
    try:
        lens = Lens(surfaces=surfaces, sensor=Sensor(pixel_pitch=pitch, resolution=tuple(res)),
                    object_distance=math.inf, wavelengths_um=list(DEFAULT_WAVELENGTHS_UM),
                    name=str(d.get("info", "") or ""),
                    entrance_pupil_diameter=None if epd is None else float(epd), source=src,
                    surface_labels=list(labels), allow_crossing=not strict)
    except LensError as e:
        from .zemax import _core
        surf = e.surface if not isinstance(e.surface, int) else labels[e.surface]
        raise type(e)(_core(e), file=src, surface=surf, keyword=e.keyword) from None
    return lens


def _int(v) -> int:
    """An integral JSON number (refuses bools, strings, fractions, inf and NaN with ValueError)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v != int(v):
        raise ValueError(v)
    return int(v)


#: DeepLens defines a "nd/Vd" material as a Cauchy glass through nd at 587.6 nm and Vd from 486.1 / 656.3 nm
DEEPLENS_MODEL_LINES_UM = (0.5876, 0.4861, 0.6563)


def _phase_surface(sd, i, semi, shape, material, num, err, Surface):
    """A DeepLens ``Phase`` entry (a flat diffractive surface) as a flat standard surface with a ``phase``."""
    model = sd.get("param_model", "binary2")
    order = sd.get("diffraction_order", 1)
    if isinstance(order, bool) or not isinstance(order, (int, float)) or order != int(order):
        raise err(f"'diffraction_order' must be an integer, got {order!r}", i, "diffraction_order")
    if model == "binary2":
        rn = sd.get("norm_radii")
        rn = semi if rn is None else num(sd, "norm_radii", i, positive=True)
        if rn is None:
            raise err("a binary2 Phase surface needs 'norm_radii' or 'r' (mm)", i, "norm_radii")
        coeffs = [num(sd, f"order{2 * k}", i, default=0.0) for k in range(1, 7)]
        while coeffs and coeffs[-1] == 0.0:
            coeffs.pop()
        phase = {"kind": "even_poly", "norm_radius": rn, "coefficients": coeffs}
        return Surface(type="standard", radius=None, material=material, semi_diameter=semi, shape=shape,
                       phase=phase, diffraction_order=int(order))
    if model == "fresnel":
        return Surface(type="standard", radius=None, material=material, semi_diameter=semi, shape=shape,
                       phase={"kind": "fresnel", "focal_length": num(sd, "f0", i)}, design_wavelength_um=0.55,
                       diffraction_order=int(order))
    raise err(f"Phase param_model {model!r} is not supported (binary2 and fresnel are)", i, "param_model")


def _material(sd, i, src, err, materials):
    """rwwarp material name for a DeepLens ``mat2``, resolved as DeepLens resolves it: its own catalogue
    entries (``DEEPLENS:<name>``, :mod:`rwwarp.materials`), then the makers' tables, then ``"nd/Vd"`` as a
    model glass at DeepLens's defining lines; a legacy name without data gets its successor, with a
    :class:`~rwwarp.materials.GlassSubstitutionWarning`."""
    name = sd.get("mat2", "air")
    if not isinstance(name, str) or not name:
        raise err(f"'mat2' must be a material name, got {name!r}", i, "mat2")
    key = name.strip().lower()
    if key in ("air", "vacuum", "occluder"):
        return "air"
    if "/" in key:
        parts = key.split("/")
        try:
            nd, vd = float(parts[0]), float(parts[1])
        except (ValueError, IndexError):
            raise err(f"'mat2' {name!r} is not 'nd/Vd'", i, "mat2") from None
        out = f"{nd!r}/{vd!r}@" + ",".join(repr(v) for v in DEEPLENS_MODEL_LINES_UM)
        try:
            materials.get_material(out)
        except LensError as e:
            from .zemax import _core
            raise type(e)(_core(e), file=src, surface=i, keyword="mat2") from None
        return out
    try:
        return materials.get_material(f"DEEPLENS:{key}").name
    except LensError:
        pass
    try:
        out, note = materials.resolve_glass(name)
    except LensError as e:
        from .zemax import _core
        raise type(e)(f"{_core(e)} (DeepLens material names are looked up in DeepLens's own table, then the "
                      "rwwarp glass tables)", file=src, surface=i, keyword="mat2") from None
    if note is not None:
        import warnings
        warnings.warn(f"{src}: surface {i} mat2: {note}", materials.GlassSubstitutionWarning, stacklevel=3)
    return out


def _doe(dd, err):
    """(doe Surface, z) from a DeepLens DOE block."""
    from ..lens import Surface

    if not isinstance(dd, dict):
        raise err(f"'DOE' must be an object, got {type(dd).__name__}", "DOE")
    dd = {k: v for k, v in dd.items() if not _derived(k)}
    typ = str(dd.get("type", ""))
    old = typ == "DOE"
    model = str(dd.get("param_model", "")).lower() if old else typ.lower()

    def num(key, default=None, positive=False):
        if dd.get(key) is None:
            if default is not None:
                return default
            raise err(f"missing {key!r}", "DOE", key)
        v = dd[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise err(f"{key!r} must be a finite number, got {v!r}", "DOE", key)
        if positive and not v > 0:
            raise err(f"{key!r} must be > 0, got {v}", "DOE", key)
        return float(v)

    z = num("d")
    res = dd.get("res", [2000, 2000])
    try:
        res = [_int(v) for v in (res if isinstance(res, (list, tuple)) else [res, res])]
        levels = None if old else _int(dd.get("fab_step", 16))
    except (TypeError, ValueError, OverflowError):
        raise err(f"'res' and 'fab_step' must be integers, got {res!r}, {dd.get('fab_step')!r}", "DOE",
                  "res") from None
    if len(res) != 2 or min(res) < 1:
        raise err(f"'res' must be two positive integers, got {res!r}", "DOE", "res")
    fab_ps = num("fab_ps", default=0.001, positive=True)
    if dd.get("l") is not None:
        w = h = num("l", positive=True)
    elif dd.get("size") is not None:
        size = dd["size"] if isinstance(dd["size"], (list, tuple)) else [dd["size"], dd["size"]]
        if len(size) != 2:
            raise err(f"'size' must be a number or [w, h] in mm, got {size!r:.80}", "DOE", "size")
        for v in size:
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or not v > 0:
                raise err(f"'size' entries must be finite numbers > 0 (mm), got {v!r:.80}", "DOE", "size")
        w, h = float(size[0]), float(size[1])
    else:
        w, h = res[0] * fab_ps, res[1] * fab_ps
    if abs(w - h) > 1e-9 * max(w, h):
        raise err(f"rectangular DOEs are not supported ({w} x {h} mm)", "DOE", "size")
    half = 0.5 * w
    half_diag = half * math.sqrt(2.0)
    pitch = w / res[0]
    wvln0 = num("wvln0", default=0.55, positive=True)
    mat = dd.get("mat", "fused_silica")
    if not isinstance(mat, str):
        raise err(f"'mat' must be a material name, got {mat!r:.80}", "DOE", "mat")

    if model == "binary2":
        if old:
            coeffs = [num(f"order{2 * i}", default=0.0) for i in range(1, 5)]
            if dd.get("order10") is not None:
                coeffs.append(num("order10"))
        else:
            keys = [f"alpha{2 * i}" for i in range(1, 11)]
            if not any(k in dd for k in keys):
                raise err("Binary2 DOE without alpha2.. coefficients (DeepLens would initialise it randomly)",
                          "DOE", "alpha2")
            coeffs = [math.pi * num(k, default=0.0) * half_diag ** (2 * i)
                      for i, k in enumerate(keys, start=1)]
        while coeffs and coeffs[-1] == 0.0 and len(coeffs) > 1:
            coeffs.pop()
        profile = {"kind": "even_poly", "norm_radius": half_diag, "coefficients": coeffs}
    elif model == "fresnel":
        f0 = num("f0")
        if old and dd.get("fresnel_wvln") is not None:
            fw = num("fresnel_wvln", positive=True)
            if abs(fw - wvln0) > 1e-12:
                raise err(f"fresnel_wvln {fw} um differs from the DOE design wavelength {wvln0} um", "DOE",
                          "fresnel_wvln")
        profile = {"kind": "fresnel", "focal_length": f0}
    elif model == "zernike":
        zc = dd.get("z_coeff")
        if not isinstance(zc, list) or not zc:
            raise err("Zernike DOE without 'z_coeff' (DeepLens would initialise it randomly)",
                      "DOE", "z_coeff")
        try:
            zc = [float(v) for v in zc]
        except (TypeError, ValueError):
            raise err("'z_coeff' must be a list of numbers", "DOE", "z_coeff") from None
        if len(zc) >= 3:
            zc[1], zc[2] = zc[2], zc[1]  # DeepLens Z2 = 2 rho sin, Z3 = 2 rho cos; Noll the other way round
        profile = {"kind": "zernike", "norm_radius": half_diag if old else half, "coefficients": zc}
    elif model == "cubic" and old:
        profile = {"kind": "cubic", "norm_radius": half, "alpha": num("a3") * half ** 3}
    elif model == "poly1d" and old:
        odd = [num(f"order{k}", default=0.0) for k in (3, 5, 7)]
        if any(odd):
            raise err("poly1d odd terms (x^3 + y^3, ...) are separable, not radial: no rwwarp profile", "DOE",
                      "order3")
        profile = {"kind": "even_poly", "norm_radius": half_diag,
                   "coefficients": [num(f"order{k}", default=0.0) for k in (2, 4, 6)]}
    elif model == "pixel2d":
        key = "doe_path" if old else "phase_map_path"
        p = dd.get(key)
        if not p:
            raise err(f"Pixel2D DOE without a phase map file ({key!r}); DeepLens would start from random "
                      "values", "DOE", key)
        if not str(p).lower().endswith(".npy"):
            raise err(f"phase map {p!r} is not a .npy file; convert a torch file with "
                      "numpy.save(path, torch.load(file).numpy())", "DOE", key)
        profile = {"kind": "pixel_map", "file": str(p), "pitch": pitch}
    else:
        raise err(f"unsupported DeepLens DOE model {model or typ!r}", "DOE", "param_model" if old else "type")

    s = Surface(type="doe", semi_diameter=half, shape="square", design_wavelength_um=wvln0,
                material=str(mat), levels=levels, profile=profile)
    return s, z
