"""Writer of Zemax OpticStudio sequential lens files (``.zmx``) from a :class:`rwwarp.lens.Lens`.

Units: ``UNIT MM`` (rwwarp's mm), wavelengths in um, field angles in degrees. Numbers are written
with Python's shortest round-trip ``repr``, so :func:`rwwarp.load_lens` reads back the same floats.

Mapping (the inverse of :mod:`rwwarp.io.zemax`):

============== =====================================================================================
rwwarp         .zmx
============== =====================================================================================
object         ``SURF 0``, ``DISZ`` = object distance (``INFINITY``)
standard       ``STANDARD`` (``CURV`` = 1/radius, ``CONI``), or ``EVENASPH`` when it has aspheric terms
               (``PARM 1`` = the r^2 term ``a2``, ``PARM 2..8`` = r^4 .. r^16; r^18 and r^20 terms have
               no EVENASPH slot: refused)
               ``ODDASPHE`` (``PARM 1..8`` = r^1 .. r^8) when it has ``odd_aspheric`` terms (the r^2
               and r^4..r^8 even terms fold in)
phase          a standard surface with a ``phase`` (:mod:`rwwarp.phase_surface`): ``BINARY_2`` with its sag
               as ``EVENASPH`` (``CURV``, ``CONI``, ``PARM 1`` = a2, ``PARM 2..8`` = r^4 .. r^16),
               ``PARM 0`` = its diffraction order, ``XDAT 1..`` its phase terms (a ``fresnel`` phase as its
               one-term ``even_poly`` equivalent, R = 1 mm); odd aspheric terms are refused
thin_lens      ``PARAXIAL``, ``PARM 1`` = focal length
aperture       flat ``STANDARD`` that keeps the medium (``GLAS`` of the medium it sits in)
doe            flat ``BINARY_2`` that keeps the medium: ``PARM 0`` = 1 (diffraction order),
               ``XDAT 1`` = number of terms, ``XDAT 2`` = normalisation radius (mm),
               ``XDAT 3..`` = a1.. (radians on rho^2, rho^4, ...). ``even_poly`` profiles directly,
               ``fresnel`` as its exact one-term equivalent, ``poly`` when it has only even powers.
               Pixel maps, Zernike, cubic, odd ``poly`` terms and quantised (``levels``) DOEs have
               no BINARY_2 form and are refused (:class:`~rwwarp.errors.LensError` naming the surface).
semi_diameter  ``DIAM sd 1`` (fixed) plus a hard aperture ``CLAP 0 sd`` (circle) or ``SQAP sd sd``
               (square): rwwarp clips rays at every semi-diameter, Zemax only at surface apertures
               (not on the stop of a lens with an ``entrance_pupil_diameter``: that stop floats)
mirror         ``GLAS MIRROR`` on a reflecting standard surface (the medium is unchanged)
material       ``GLAS NAME`` (the catalogue name; fused silica as ``F_SILICA``), a model glass
               ``"nd/vd"`` as ``GLAS ___BLANK 1 0 nd vd``; the catalogues used go in ``GCAT``
obscuration    ``OBSC 0 r`` (circle) or ``SQOB hx hy`` (rectangle), centred
stop           ``STOP`` on :attr:`Lens.stop_index`
aperture size  ``ENPD``: the lens's ``entrance_pupil_diameter``, or the paraxial entrance pupil
               of the stop at the primary wavelength (the stop keeps its hard aperture, so it still
               clips, as in rwwarp); a square stop's pupil is circumscribed (x sqrt 2) and cut to the
               square by the stop's ``SQAP``
wavelengths    ``WAVM k wl 1``; ``PWAV`` = the DOE's design wavelength (must be one of them), else the
               middle wavelength
fields         ``FTYP 0`` (angles) with ``XFLN`` / ``YFLN``; a lens without fields gets one at 0 deg
sensor         not part of a .zmx (a comment line records it; :func:`rwwarp.load_lens` uses the
               default sensor)
============== =====================================================================================

What reads back differently (optically the same): a DOE's substrate becomes ``fused_silica`` and its
design wavelength the primary wavelength (a warning says so when they differ); an ``aperture`` surface
comes back as a flat ``standard`` one; the stop's hard aperture under ``ENPD`` comes back as a
floating stop plane followed by the clipping surface (the reader's model of Zemax's floating stop);
a lens whose aperture was set by its stop's size reads back with that ``entrance_pupil_diameter``; a
square pupil reads back as its circumscribed circle cut by the square aperture (the same rays reach
the sensor; a PSF's normalisation to the entering power changes by the area ratio 2 / pi).
"""
from __future__ import annotations

import math
import warnings
from pathlib import Path

from ..errors import LensError

__all__ = ["write_zmx", "zmx_text"]

_ZEMAX_NAMES = {"fused_silica": "F_SILICA"}


def _num(v) -> str:
    """Shortest round-trip text of a float (``repr``), integers without a trailing ``.0``."""
    v = float(v)
    if not math.isfinite(v):
        raise ValueError(f"non-finite value {v}")
    return repr(v)


def _glass(name: str, surface: int, lens):
    """(GLAS line tokens, catalogue or None) for a material name."""
    from .. import materials
    if name.lower() == "air":
        return None, None
    try:
        m = materials.get_material(name)
    except LensError as e:
        raise LensError(f"material {name!r} is unknown: {e}", file=lens.source, surface=surface,
                        keyword="material") from None
    if m.formula == "Model" or "@" in name:
        nd, vd = m.nd, m.vd
        if "/" in name and "@" not in name:
            try:
                nd, vd = (float(t) for t in name.split("/"))
            except ValueError:
                pass
        _check_dispersion(name, f"{float(nd)!r}/{float(vd)!r}", surface, lens, ".zmx")
        return f"___BLANK 1 0 {_num(nd)} {_num(vd)} 0 0 0 0 0 0", None
    plain = name.split(":", 1)[-1]
    plain = _ZEMAX_NAMES.get(plain.lower(), plain)
    nd = m.catalog_nd if m.catalog_nd is not None else m.nd
    vd = m.catalog_vd if m.catalog_vd is not None else m.vd
    ok_nv = bool(nd and vd and math.isfinite(vd))
    nd_w, vd_w = (round(nd, 6), round(vd, 4)) if ok_nv else (None, None)
    back = plain
    try:
        materials.get_material(plain)
    except LensError:  # the reader substitutes (a model glass through the nd / vd written on the line)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                back = materials.resolve_glass(plain, nd_w, vd_w)[0]
        except LensError:
            warnings.warn(f"surface {surface}: the material {name!r} is written as {plain!r}, which no glass table "
                          "knows: the file will not read back", UserWarning, stacklevel=3)
    _check_dispersion(name, back, surface, lens, ".zmx")
    if any(c.isspace() for c in plain):
        raise LensError(f"material name {name!r} has spaces: a .zmx GLAS entry cannot hold it", file=lens.source,
                        surface=surface, keyword="material")
    extra = f" 0 0 {_num(nd_w)} {_num(vd_w)} 0 0 0 0 0 0" if ok_nv else ""
    return plain + extra, m.catalog


def _check_dispersion(original: str, read_back: str, surface: int, lens, fmt: str):
    """Warn when the material a file will read back as differs from the lens's own (indices at the
    lens's wavelengths and 0.4-0.8 um)."""
    from .. import materials
    try:
        a, b = materials.get_material(original), materials.get_material(read_back)
    except LensError:
        return
    if a == b:
        return
    wls = sorted(set([float(w) for w in lens.wavelengths_um] + [0.45, 0.5876, 0.65]))
    dn = max(abs(float(a.n(w)) - float(b.n(w))) for w in wls)
    if dn > 1e-12:
        warnings.warn(f"surface {surface}: the material {original!r} has no exact {fmt} name; it reads back as "
                      f"{read_back!r} (index differs by up to {dn:.2g})", UserWarning, stacklevel=4)


def _binary2(s, i, lens):
    """(norm_radius, [a1, a2, ...]) of a DOE surface's profile as Zemax BINARY_2 terms, or raise."""
    prof = s.profile or {}
    kind = prof.get("kind")
    where = dict(file=lens.source, surface=i, keyword="profile")
    if s.levels is not None:
        raise LensError(f"the DOE is quantised to {s.levels} levels: a Zemax BINARY_2 surface holds only a "
                        "continuous phase; export the unquantised design (levels None) or keep the native JSON",
                        file=lens.source, surface=i, keyword="levels")
    if kind == "even_poly":
        return float(prof["norm_radius"]), [float(c) for c in prof["coefficients"]]
    if kind == "fresnel":
        # -pi r^2 / (lambda0 f) = a1 rho^2 with rho = r / R0
        r0 = float(s.semi_diameter) if s.semi_diameter else 1.0
        f = float(prof["focal_length"])
        return r0, [-math.pi * r0 * r0 / (s.design_wavelength_um * 1e-3 * f)]
    if kind == "poly":
        c = [float(v) for v in prof["coefficients"]]  # c_k on rho^k, k = 1, 2, ...
        odd = [k + 1 for k, v in enumerate(c) if (k + 1) % 2 == 1 and v != 0.0]
        if odd:
            raise LensError(f"the 'poly' DOE profile has odd powers rho^{odd} that a Zemax BINARY_2 surface cannot "
                            "hold (it takes even powers only)", **where)
        return float(prof["norm_radius"]), [c[k] for k in range(1, len(c), 2)]
    if kind == "pixel_map":
        raise LensError("a pixel-map DOE has no Zemax BINARY_2 form (it is not a polynomial phase); keep the native "
                        "JSON, or write the phase as a Zemax Grid Phase surface by hand", **where)
    raise LensError(f"a {kind!r} DOE profile has no Zemax BINARY_2 form (only even_poly, fresnel and even "
                    "'poly' profiles are exported)", **where)


def _phase_lines(s, i, lens) -> list:
    """The ``BINARY_2`` lines of a standard surface carrying a phase (sag, order, phase terms), or raise."""
    from ..phase_surface import phase_profile
    if s.odd_aspheric and any(s.odd_aspheric):
        raise LensError("a phase surface with odd aspheric terms has no .zmx form (BINARY_2 takes the even asphere "
                        "sag)", file=lens.source, surface=i, keyword="odd_aspheric")
    if s.mirror:
        raise LensError("a BINARY_2 mirror is not written", file=lens.source, surface=i, keyword="mirror")
    asph = [float(a) for a in s.aspheric]
    while asph and asph[-1] == 0.0:
        asph.pop()
    if len(asph) > 7:
        raise LensError(f"aspheric terms beyond r^16 ({len(asph)} terms) have no BINARY_2 slot in a .zmx",
                        file=lens.source, surface=i, keyword="aspheric")
    r0, coeffs = phase_profile(s)
    lines = ["TYPE BINARY_2", f"CURV {_num(s.curvature)} 0 0 0 0 \"\""]
    if s.conic:
        lines.append(f"CONI {_num(s.conic)}")
    lines.append(f"PARM 0 {int(s.diffraction_order)}")
    lines.append(f"PARM 1 {_num(s.a2)}")
    lines += [f"PARM {k + 2} {_num(a)}" for k, a in enumerate(asph)]
    lines.append(f"XDAT 1 {len(coeffs)} 0 0 0 0 0 \"\"")
    lines.append(f"XDAT 2 {_num(r0)} 0 0 0 0 0 \"\"")
    lines += [f"XDAT {k + 3} {_num(c)} 0 0 0 0 0 \"\"" for k, c in enumerate(coeffs)]
    return lines


def zmx_text(lens) -> str:
    """The .zmx file of ``lens`` as text (see the module docstring for the mapping; raises
    :class:`~rwwarp.errors.LensError` naming the surface for what a .zmx cannot hold)."""
    from .. import paraxial
    wls = [float(w) for w in lens.wavelengths_um]
    doe_i = lens.doe_index
    primary = len(wls) // 2
    if doe_i is not None:
        s = lens.surfaces[doe_i]
        match = [k for k, w in enumerate(wls) if abs(w - s.design_wavelength_um) <= 1e-12]
        if match:
            primary = match[0]
        else:
            warnings.warn(f"the DOE's design wavelength {s.design_wavelength_um} um is not among the lens's "
                          f"wavelengths {wls}: a .zmx reads back with the primary wavelength {wls[primary]} um as "
                          "the design wavelength (its blaze)", UserWarning, stacklevel=3)
        if s.material.lower() not in ("fused_silica", "f_silica", "silica", "fusedsilica", "fused silica",
                                      "fused_silica", "sio2"):
            warnings.warn(f"the DOE's substrate {s.material!r} is not kept by a .zmx (it reads back as fused "
                          "silica, which sets the per-wavelength blaze remap)", UserWarning, stacklevel=3)
    if lens.entrance_pupil_diameter is not None:
        enpd = float(lens.entrance_pupil_diameter)
    else:
        enpd = 2.0 * paraxial.pupils(lens, wls[primary]).entrance_radius
    stop_s = lens.surfaces[lens.stop_index]
    if stop_s.shape == "square":
        # a Zemax entrance pupil is a circle: circumscribe the square pupil, the stop's SQAP cuts the square
        enpd *= math.sqrt(2.0)
        if stop_s.semi_diameter is None:
            warnings.warn("the square pupil of a stop without a semi-diameter cannot be written to a .zmx (its "
                          "pupil is a circle); the square's circumscribed circle is used", UserWarning, stacklevel=3)

    # surfaces first (they name the catalogues)
    blocks, cats = [], []
    medium = "air"
    stop = lens.stop_index
    for i, s in enumerate(lens.surfaces):
        lines = []
        if i == stop:
            lines.append("STOP")
        if s.type == "standard" and s.phase is not None:
            lines += _phase_lines(s, i, lens)
            medium = s.material
        elif s.type == "standard":
            asph = [float(a) for a in s.aspheric]
            while asph and asph[-1] == 0.0:
                asph.pop()
            odd = [float(b) for b in getattr(s, "odd_aspheric", None) or []]
            while odd and odd[-1] == 0.0:
                odd.pop()
            if odd:
                # ODDASPHE: PARM 1..8 on r^1..r^8; the r^2 term and r^4..r^8 even terms fold in
                if len(asph) > 3:
                    raise LensError("a surface with odd aspheric terms and even terms beyond r^8 has no .zmx form "
                                    "(ODDASPHE stops at r^8)", file=lens.source, surface=i, keyword="aspheric")
                odd = odd + [0.0] * (8 - len(odd))
                odd[1] += float(s.a2)
                for k, a in enumerate(asph):
                    odd[3 + 2 * k] += a
            elif len(asph) > 7:
                raise LensError(f"aspheric terms beyond r^16 ({len(asph)} terms) have no EVENASPH slot in a .zmx",
                                file=lens.source, surface=i, keyword="aspheric")
            even = bool(asph) or bool(s.a2)
            lines.append("TYPE ODDASPHE" if odd else "TYPE EVENASPH" if even else "TYPE STANDARD")
            lines.append(f"CURV {_num(s.curvature)} 0 0 0 0 \"\"")
            if s.conic:
                lines.append(f"CONI {_num(s.conic)}")
            if odd:
                lines += [f"PARM {k + 1} {_num(b)}" for k, b in enumerate(odd)]
            elif even:
                lines.append(f"PARM 1 {_num(s.a2)}")
                lines += [f"PARM {k + 2} {_num(a)}" for k, a in enumerate(asph)]
            if not s.mirror:  # a mirror keeps the medium (its material is the medium in front of it)
                medium = s.material
        elif s.type == "thin_lens":
            lines += ["TYPE PARAXIAL", "CURV 0.0 0 0 0 0 \"\"", f"PARM 1 {_num(s.focal_length)}", "PARM 2 0"]
            medium = s.material
        elif s.type == "aperture":
            lines += ["TYPE STANDARD", "CURV 0.0 0 0 0 0 \"\""]
        elif s.type == "doe":
            r0, coeffs = _binary2(s, i, lens)
            lines += ["TYPE BINARY_2", "CURV 0.0 0 0 0 0 \"\"", "PARM 0 1"]
            lines += [f"PARM {k} 0" for k in range(1, 9)]
            lines.append(f"XDAT 1 {len(coeffs)} 0 0 0 0 0 \"\"")
            lines.append(f"XDAT 2 {_num(r0)} 0 0 0 0 0 \"\"")
            lines += [f"XDAT {k + 3} {_num(c)} 0 0 0 0 0 \"\"" for k, c in enumerate(coeffs)]
        else:
            raise LensError(f"surface type {s.type!r} has no .zmx form", file=lens.source, surface=i, keyword="type")
        lines.append(f"DISZ {_num(s.thickness)}")
        glas, cat = ("MIRROR", None) if s.type == "standard" and s.mirror else _glass(medium, i, lens)
        if glas:
            lines.append(f"GLAS {glas}")
            if cat and cat not in cats:
                cats.append(cat)
        if s.semi_diameter is not None:
            sd = _num(s.semi_diameter)
            lines.append(f"DIAM {sd} 1 0 0 1 \"\"")
            # under an entrance_pupil_diameter the rwwarp stop floats (does not clip): no hard aperture
            if not (i == stop and lens.entrance_pupil_diameter is not None):
                lines.append(f"CLAP 0 {sd} 0" if s.shape == "circle" else f"SQAP {sd} {sd} 0 0 0")
        else:
            lines.append("DIAM 0 0 0 0 1 \"\"")
        ob = s.obscuration
        if ob:
            if ob.get("shape") == "circle":
                lines.append(f"OBSC 0 {_num(ob['radius'])} 0 0 0")
            elif ob.get("shape") == "rectangle":
                lines.append(f"SQOB {_num(ob['half_x'])} {_num(ob['half_y'])} 0 0 0")
            else:
                raise LensError(f"obscuration {ob!r} has no .zmx form", file=lens.source, surface=i,
                                keyword="obscuration")
        blocks.append(lines)

    fields = lens.fields_deg if lens.fields_deg else [0.0]
    fx = [0.0 if isinstance(f, (int, float)) else float(f[0]) for f in fields]
    fy = [float(f) if isinstance(f, (int, float)) else float(f[1]) for f in fields]
    out = ["VERS 190513 80 123457 L123457", "MODE SEQ"]
    if lens.name:
        out.append("NAME " + " ".join(str(lens.name).split()))
    out += ["PFIL 0 0 0", "UNIT MM X W X CM MR CPMM", f"ENPD {_num(enpd)}", "ENVD 2.0E+1 1 0", "GFAC 0 0"]
    if cats:
        out.append("GCAT " + " ".join(cats))
    out += ["RAIM 0 0 1 1 0 0 0 0 0", "PUSH 0 0 0 0 0 0", "SDMA 0 1 0",
            f"FTYP 0 0 {len(fields)} {len(wls)} 0 0 0",
            "XFLN " + " ".join(_num(v) for v in fx), "YFLN " + " ".join(_num(v) for v in fy),
            "FWGN " + " ".join("1" for _ in fields)]
    out += [f"WAVM {k + 1} {_num(w)} 1" for k, w in enumerate(wls)]
    out.append(f"PWAV {primary + 1}")
    sx, sy = lens.sensor.resolution
    out.append(f"! rwwarp sensor: pixel pitch {_num(lens.sensor.pixel_pitch)} mm, {sx} x {sy} pixels "
               "(not part of the .zmx format)")
    od = lens.object_distance
    out += ["SURF 0", "  TYPE STANDARD", "  CURV 0.0 0 0 0 0 \"\"",
            "  DISZ " + ("INFINITY" if math.isinf(od) else _num(od)), "  DIAM 0 0 0 0 1 \"\""]
    for k, lines in enumerate(blocks):
        out.append(f"SURF {k + 1}")
        out += ["  " + ln for ln in lines]
    out += [f"SURF {len(blocks) + 1}", "  TYPE STANDARD", "  CURV 0.0 0 0 0 0 \"\"", "  DISZ 0",
            "  DIAM 0 0 0 0 1 \"\""]
    return "\n".join(out) + "\n"


def write_zmx(lens, path, encoding: str = "utf-8") -> Path:
    """Write ``lens`` as a sequential Zemax ``.zmx`` file at ``path``; ``encoding`` ``"utf-8"``
    (plain text) or ``"utf-16"`` (with BOM, as OpticStudio writes it). Returns the path."""
    if encoding.lower().replace("-", "") not in ("utf8", "utf16"):
        raise ValueError(f"encoding must be 'utf-8' or 'utf-16', got {encoding!r}")
    text = zmx_text(lens)
    p = Path(path)
    if encoding.lower().replace("-", "") == "utf16":
        p.write_bytes(text.replace("\n", "\r\n").encode("utf-16"))
    else:
        p.write_text(text)
    return p
