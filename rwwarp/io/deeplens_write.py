"""Writer of DeepLens lens files (GeoLens / HybridLens JSON, the paper's own format) from a
:class:`rwwarp.lens.Lens`; the inverse of :mod:`rwwarp.io.deeplens`. Lengths in mm, wavelengths in um.

Mapping:

================ =====================================================================================
rwwarp           DeepLens
================ =====================================================================================
standard         ``Spheric`` (``roc``, ``c``), ``Aspheric`` when it has ``conic``, ``a2`` or aspheric
                 terms (``k``, ``ai`` = [r^2, r^4, ...] with ``use_ai2`` true), ``Plane`` when flat
thin_lens        ``ThinLens`` (``f``; only in air)
phase            a flat standard surface with a ``phase``: ``Phase`` (``param_model`` ``binary2``, ``norm_radii``,
                 ``order2 .. order12``; a fresnel phase as its one-term equivalent); curved ones are refused
aperture         ``Aperture`` (``r``, ``is_square``); the stop must be the first aperture, and a stop on a
                 refracting surface gets an ``Aperture`` at its vertex (DeepLens has no stop flag)
doe              the ``DOE`` block at its ``d``: square only. Unquantised (``levels`` None): the older
                 ``"type": "DOE"`` block (``binary2`` with ``order2..order10`` on the half-diagonal, at most
                 5 terms; ``fresnel`` with ``f0``), which DeepLens does not quantise. Quantised: the newer
                 ``Binary2`` (``alpha2..alpha20`` in rad / mm^2i / pi) or ``Fresnel`` with ``fab_step``
                 = levels
layout           ``d`` (vertex z) and ``d_next`` on every surface, ``d_sensor``
sensor           ``sensor_res``, ``sensor_size`` [w, h] (mm), ``r_sensor`` (half diagonal)
system           ``enpd`` when the lens has an ``entrance_pupil_diameter``; ``info`` = name; ``foclen``
                 and ``fnum`` (informative, read by DeepLens, ignored by rwwarp)
================ =====================================================================================

Not in the format (a ``UserWarning`` says so): the object distance (DeepLens: infinity), the
wavelengths (DeepLens's RGB), a model glass's exact dispersion (DeepLens defines ``"nd/vd"`` at its
own lines); a warning names each material DeepLens's lookup would read back differently. Refused
(:class:`~rwwarp.errors.LensError` naming the surface): circular DOEs, pixel-map, Zernike and cubic
DOE profiles, odd ``poly`` terms, odd aspheric terms, obscurations, mirrors, thin lenses in glass, more than
5 (unquantised) or 10 (quantised) DOE terms.
"""
from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

from ..errors import LensError

__all__ = ["deeplens_dict", "write_deeplens"]


def _even_poly(s, i, lens):
    """(norm_radius, coefficients) of a DOE as even powers of r / norm_radius, or raise."""
    from .zemax_write import _binary2
    return _binary2(s, i, lens)  # even_poly, fresnel (one term), even-only poly; refuses the rest


def deeplens_dict(lens) -> dict:
    """The DeepLens JSON dictionary of ``lens`` (see the module docstring; raises
    :class:`~rwwarp.errors.LensError` for what DeepLens cannot hold)."""
    from .. import materials, paraxial
    if not math.isinf(lens.object_distance):
        warnings.warn(f"a DeepLens file has no object distance: the object at {lens.object_distance} mm reads back "
                      "at infinity", UserWarning, stacklevel=3)
    warnings.warn("a DeepLens file has no wavelengths: it reads back with DeepLens's RGB set (0.486, 0.587, "
                  "0.656 um)", UserWarning, stacklevel=3)
    z = lens.vertex_z
    zs = lens.sensor_z
    stop = lens.stop_index
    first_ap = next((i for i, s in enumerate(lens.surfaces) if s.type == "aperture"), None)
    surfs, doe_block = [], None
    for i, s in enumerate(lens.surfaces):
        where = dict(file=lens.source, surface=i)
        if s.obscuration:
            raise LensError("DeepLens surfaces have no obscuration", keyword="obscuration", **where)
        if s.type == "standard" and any(getattr(s, "odd_aspheric", None) or []):
            raise LensError("a DeepLens Aspheric surface has even terms only (no odd_aspheric)",
                            keyword="odd_aspheric", **where)
        if s.type == "standard" and s.mirror:
            raise LensError("a DeepLens GeoLens has no mirrors (refracting surfaces only)", keyword="mirror", **where)
        if s.type == "standard" and s.phase is not None and (s.radius is not None or s.conic or s.a2
                                                               or any(s.aspheric)):
            raise LensError("a diffractive phase on a curved or aspheric surface has no DeepLens form (its Phase "
                            "surface is flat); keep the native JSON or write a .zmx (BINARY_2)", keyword="phase",
                            **where)
        base = {"d": float(z[i])}
        if s.semi_diameter is not None:
            base["r"] = float(s.semi_diameter)
        if s.shape == "square":
            base["is_square"] = True
        if i == stop and s.type != "aperture":
            if first_ap is not None and first_ap < i:
                raise LensError("the stop follows an aperture surface: DeepLens makes the first aperture the stop",
                                keyword="stop", **where)
            surfs.append({"type": "Aperture", "d": float(z[i])})  # the stop plane at the vertex
        if s.type == "aperture":
            if i != stop and first_ap == i:
                raise LensError("the first aperture is not the stop: DeepLens makes the first aperture the stop",
                                keyword="stop", **where)
            surfs.append({"type": "Aperture", **base})
        elif s.type == "thin_lens":
            if s.material.lower() != "air":
                raise LensError("a DeepLens ThinLens sits in air", keyword="material", **where)
            surfs.append({"type": "ThinLens", "f": float(s.focal_length), **base})
        elif s.type == "standard" and s.phase is not None:
            from ..phase_surface import phase_profile
            rn, coeffs = phase_profile(s)
            if len(coeffs) > 6:
                raise LensError(f"a DeepLens Phase surface holds 6 terms (order2 .. order12), the phase has "
                                f"{len(coeffs)}", keyword="phase", **where)
            entry = {"type": "Phase", "param_model": "binary2", "norm_radii": rn,
                     "mat2": _material(s.material, i, lens, materials), **base}
            entry.update({f"order{2 * (k + 1)}": float(c) for k, c in enumerate(coeffs)})
            if s.diffraction_order != 1:
                entry["diffraction_order"] = int(s.diffraction_order)
            surfs.append(entry)
        elif s.type == "standard":
            mat = _material(s.material, i, lens, materials)
            asph = [float(a) for a in s.aspheric]
            while asph and asph[-1] == 0.0:
                asph.pop()
            if s.radius is None and not asph and not s.a2 and not s.conic:
                surfs.append({"type": "Plane", "mat2": mat, **base})
            elif asph or s.a2 or s.conic:
                surfs.append({"type": "Aspheric", "roc": float(s.radius or 0.0), "c": s.curvature,
                              "k": float(s.conic), "ai": [float(s.a2)] + asph, "use_ai2": True, "mat2": mat,
                              **base})
            else:
                surfs.append({"type": "Spheric", "roc": float(s.radius), "c": s.curvature, "mat2": mat, **base})
        elif s.type == "doe":
            doe_block = _doe_block(s, i, lens, float(z[i]))
        else:
            raise LensError(f"surface type {s.type!r} has no DeepLens form", keyword="type", **where)
    ds = [d["d"] for d in surfs] + [zs]
    for k, d in enumerate(surfs):
        d["d_next"] = ds[k + 1] - d["d"]
    nx, ny = lens.sensor.resolution
    w, h = nx * lens.sensor.pixel_pitch, ny * lens.sensor.pixel_pitch
    wl = 0.5876 if any(abs(w0 - 0.5876) < 0.01 for w0 in lens.wavelengths_um) else \
        lens.wavelengths_um[len(lens.wavelengths_um) // 2]
    out = {"info": lens.name or "", "foclen": lens.efl(wl), "fnum": paraxial.f_number(lens, wl),
           "r_sensor": 0.5 * math.hypot(w, h), "d_sensor": zs, "sensor_res": [nx, ny], "sensor_size": [w, h]}
    if lens.entrance_pupil_diameter is not None:
        out["enpd"] = float(lens.entrance_pupil_diameter)
    out["surfaces"] = surfs
    if doe_block is not None:
        out["DOE"] = doe_block
    return out


def _material(name, i, lens, materials):
    """The ``mat2`` text for a material, warning when DeepLens's lookup would read back another one."""
    from .deeplens import _material as read_material
    from .zemax_write import _check_dispersion
    if name.lower() == "air":
        return "air"
    m = materials.get_material(name)
    if m.formula == "Model" or "@" in name:
        text = name.split("@", 1)[0] if "/" in name else f"{m.nd!r}/{m.vd!r}"
    else:
        text = name.split(":", 1)[-1]

    def err(msg, surf=None, key=None, cls=LensError):
        return cls(msg, file=lens.source, surface=i, keyword="material")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        back = read_material({"mat2": text}, i, None, err, materials)
    _check_dispersion(name, back, i, lens, "DeepLens")
    return text


def _doe_block(s, i, lens, z):
    where = dict(file=lens.source, surface=i)
    if s.shape != "square" or s.semi_diameter is None:
        raise LensError("DeepLens DOEs are square: give the DOE a square aperture (semi_diameter = half side)",
                        keyword="shape", **where)
    half = float(s.semi_diameter)
    half_diag = half * math.sqrt(2.0)
    kind = (s.profile or {}).get("kind")
    common = {"d": z, "size": 2 * half, "wvln0": float(s.design_wavelength_um), "mat": s.material}
    if kind == "fresnel":
        f0 = float(s.profile["focal_length"])
        if s.levels is None:
            return {"type": "DOE", "param_model": "fresnel", "l": 2 * half, "d": z, "f0": f0,
                    "fresnel_wvln": float(s.design_wavelength_um), "wvln0": float(s.design_wavelength_um),
                    "mat": s.material}
        return {"type": "Fresnel", "f0": f0, "fab_step": int(s.levels), **common}
    levels = s.levels
    s_unq = s
    if levels is not None:  # _binary2 refuses quantised DOEs (Zemax); the quantisation goes in fab_step here
        import copy
        s_unq = copy.copy(s)
        s_unq.levels = None
    r0, coeffs = _even_poly(s_unq, i, lens)
    while coeffs and coeffs[-1] == 0.0 and len(coeffs) > 1:
        coeffs.pop()
    if levels is None:
        if len(coeffs) > 5:
            raise LensError(f"an unquantised DeepLens DOE (the older 'DOE' block) holds at most 5 terms (rho^2..rho^10), "
                            f"got {len(coeffs)}", keyword="profile", **where)
        # phase = sum a_k (r / r0)^2k = sum b_k (r / half_diag)^2k with b_k = a_k (half_diag / r0)^2k
        out = {"type": "DOE", "param_model": "binary2", "l": 2 * half, "d": z, "wvln0": float(s.design_wavelength_um),
               "mat": s.material}
        for k, a in enumerate(coeffs, start=1):
            out[f"order{2 * k}"] = a * (half_diag / r0) ** (2 * k)
        return out
    if len(coeffs) > 10:
        raise LensError(f"a DeepLens Binary2 DOE holds at most 10 terms, got {len(coeffs)}", keyword="profile", **where)
    out = {"type": "Binary2", "fab_step": int(levels), **common}
    for k in range(1, 11):
        a = coeffs[k - 1] if k <= len(coeffs) else 0.0
        out[f"alpha{2 * k}"] = a / (math.pi * r0 ** (2 * k))  # phase = pi sum alpha_2k r^2k, r in mm
    return out


def write_deeplens(lens, path) -> Path:
    """Write ``lens`` as a DeepLens JSON file at ``path``; returns the path."""
    p = Path(path)
    p.write_text(json.dumps(deeplens_dict(lens), indent=1) + "\n")
    return p
