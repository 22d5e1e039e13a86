"""Paraxial (first-order) optics by y-nu ray tracing: EFL, BFL, pupils, conjugates.

Reduced slopes ``nu = n * u``; refraction ``nu' = nu - y * P`` with surface power
``P = (n' - n) * c`` (standard), ``1/f`` (thin lens), ``-lambda * a1 / (pi R^2)`` for a DOE
(a1 the rho^2 phase coefficient in radians: first diffraction order, power proportional to lambda),
plus ``-m lambda A_1 / (pi R^2)`` for a standard surface's phase in order m (:mod:`rwwarp.phase_surface`);
transfer ``y' = y + t * nu' / n'``. Lengths in mm, wavelengths in um.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import GeometryError


def surface_powers(lens, wavelength_um: float) -> np.ndarray:
    """Optical power of each surface at ``wavelength_um`` (um), 1/mm."""
    n = signed_indices(lens, wavelength_um)
    n_before = np.concatenate([[object_index(lens, wavelength_um)], n[:-1]])
    out = np.zeros(len(lens.surfaces))
    for i, s in enumerate(lens.surfaces):
        if s.type == "standard":
            out[i] = (n[i] - n_before[i]) * s.paraxial_curvature  # c + 2 a2 (r^2 asphere term)
            if s.phase is not None:
                from .phase_surface import phase_power
                out[i] += phase_power(s, wavelength_um)
        elif s.type == "thin_lens":
            out[i] = 1.0 / s.focal_length
        elif s.type == "doe":
            out[i] = doe_power(s, wavelength_um)
    return out


def doe_power(surface, wavelength_um: float) -> float:
    """Paraxial power (1/mm) of a DOE surface from the quadratic term of its phase at ``wavelength_um``."""
    from . import doe
    prof = doe.profile_from_dict(surface.profile)
    a2 = prof.quadratic_coefficient(surface.design_wavelength_um)  # phase = a2 * r^2 (rad/mm^2)
    return diffractive_power(a2, wavelength_um)


def diffractive_power(a2, wavelength_um: float):
    """Paraxial power (1/mm) ``P = -lambda a2 / pi`` of a DOE whose phase is ``a2 r^2`` near the axis (``a2`` in
    rad/mm^2: a number, or a torch tensor in ``torch_bridge``'s differentiable EFL; ``wavelength_um`` in um).
    The first diffraction order of the zone structure (grating equation): ``d(nu) = (lambda / 2 pi) d(phi0)/dr
    = lambda a2 r / pi``, proportional to the wavelength (Zemax Binary 2 convention); the substrate's remap
    ``(n(l)-1)/(n0-1) l0/l`` only changes the diffraction efficiency."""
    lam_mm = wavelength_um * 1e-3
    return -lam_mm * a2 / np.pi


def object_index(lens, wavelength_um) -> float:
    """Refractive index of object space (the medium before the first surface): air, 1.0, at any
    wavelength (um)."""
    return 1.0


def signed_indices(lens, wavelength_um) -> np.ndarray:
    """Index after each surface with the sign of the travel direction (negative after an odd number of
    mirrors), the usual paraxial convention that makes a mirror a surface of power -2 n c."""
    return lens.indices(wavelength_um) * lens.directions()


def ynu_steps(powers, thicknesses, indices, y0, nu0):
    """The paraxial y-nu trace (its one home): at surface ``i`` the reduced slope changes by refraction,
    ``nu -= y P_i`` (power 1/mm), then the ray moves on, ``y += t_i nu / n_i`` (thickness mm, index after
    the surface, signed by the travel direction). Elementwise arithmetic only, so the entries may be
    floats or torch scalars (differentiable: ``torch_bridge`` traces its learning lens with it).
    Returns three lists: the height at each surface (mm), the reduced slope arriving at it and the one
    leaving it."""
    ys, nus_in, nus = [], [], []
    y, nu = y0, nu0
    for P, t, n in zip(powers, thicknesses, indices):
        nus_in.append(nu)
        nu = nu - y * P
        ys.append(y)
        nus.append(nu)
        y = y + t * nu / n
    return ys, nus_in, nus


def ynu_trace(lens, wavelength_um: float, y0: float, nu0: float):
    """Trace a paraxial ray starting at the first vertex with height ``y0`` (mm) and reduced slope ``nu0``.

    Returns ``(y, nu)``: heights at each surface (mm) and reduced slopes after each surface.
    """
    ys, _, nus = ynu_steps(surface_powers(lens, wavelength_um), [s.thickness for s in lens.surfaces],
                           signed_indices(lens, wavelength_um), y0, nu0)
    return np.array(ys, dtype=np.float64), np.array(nus, dtype=np.float64)


def _checked(lens, wavelength_um) -> float:
    from . import checks
    checks.check_lens(lens)
    return checks.check_wavelength(wavelength_um, lens)


def _finite(v, what, lens) -> float:
    if not np.isfinite(v):
        raise GeometryError(f"the paraxial {what} is not finite ({v}); the lens data overflow float64",
                            file=lens.source)
    return float(v)


def efl(lens, wavelength_um: float = 0.5876) -> float:
    """Effective focal length in air, ``1 / phi`` (mm), at ``wavelength_um`` (um): the inverse of the
    system power, whatever the image-space medium (OpticStudio's "Effective Focal Length (in air)"). Where
    the image space is not air, :func:`efl_image_space` gives ``n' / phi``, the distance from the rear
    principal plane to the focus (optiland's ``f2``, OpticStudio's "(in image space)"); in air they are equal."""
    wavelength_um = _checked(lens, wavelength_um)
    _, nu = ynu_trace(lens, wavelength_um, 1.0, 0.0)
    if nu[-1] == 0:
        raise GeometryError("afocal system: the effective focal length is infinite", file=lens.source)
    return _finite(-1.0 / nu[-1], "effective focal length", lens)


def efl_image_space(lens, wavelength_um: float = 0.5876) -> float:
    """Effective focal length in image space, ``n' / phi`` (mm), at ``wavelength_um`` (um), n' the refractive
    index of the image-space medium: the rear principal plane to focus distance. Equals :func:`efl` (``1 /
    phi``, "in air") when the image space is air; differs by n' otherwise (an immersion or a cover medium)."""
    f = efl(lens, wavelength_um)
    n = abs(float(signed_indices(lens, float(wavelength_um))[-1]))
    return _finite(n * f, "image-space effective focal length", lens)


def bfl(lens, wavelength_um: float = 0.5876) -> float:
    """Back focal length (paraxial focus behind the last surface vertex), mm."""
    wavelength_um = _checked(lens, wavelength_um)
    y, nu = ynu_trace(lens, wavelength_um, 1.0, 0.0)
    n = signed_indices(lens, wavelength_um)[-1]
    if nu[-1] == 0:
        raise GeometryError("afocal system: the back focal length is infinite", file=lens.source)
    return _finite(-y[-1] * n / nu[-1], "back focal length", lens)


@dataclass
class Pupils:
    """Paraxial pupils: positions (z, mm, from the first vertex) and radii (mm)."""

    entrance_z: float
    entrance_radius: float
    exit_z: float
    exit_radius: float
    stop_semi_diameter: float


def stop_semi_diameter(lens, wavelength_um: float) -> float:
    """Semi-diameter of the stop (mm): its own, or derived from ``entrance_pupil_diameter``."""
    i = lens.stop_index
    if lens.entrance_pupil_diameter is not None:
        ya, _ = ynu_trace(lens, wavelength_um, 1.0, 0.0)
        return float(0.5 * lens.entrance_pupil_diameter * abs(ya[i]))
    sd = lens.surfaces[i].semi_diameter
    if sd is None:
        raise GeometryError("the stop has no semi_diameter and the lens no entrance_pupil_diameter: the "
                            "aperture is undefined", file=lens.source, surface=lens.surface_label(i), keyword="semi_diameter")
    return float(sd)


def pupils(lens, wavelength_um: float = 0.5876) -> Pupils:
    """Paraxial entrance and exit pupils at ``wavelength_um`` (um)."""
    wavelength_um = _checked(lens, wavelength_um)
    i = lens.stop_index
    ya, nua = ynu_trace(lens, wavelength_um, 1.0, 0.0)
    yb, nub = ynu_trace(lens, wavelength_um, 0.0, 1.0)
    if ya[i] == 0:
        raise GeometryError("the stop is at a focus: no entrance pupil", file=lens.source, surface=lens.surface_label(i))
    sd = stop_semi_diameter(lens, wavelength_um)
    ep_z = float(yb[i] / ya[i])
    ep_r = float(sd / abs(ya[i]))
    # chief ray through the EP centre with unit slope: y0 = -ep_z at the first vertex
    yc, nuc = ynu_trace(lens, wavelength_um, -ep_z, 1.0)
    ym, num = ynu_trace(lens, wavelength_um, ep_r, 0.0)
    n_img = signed_indices(lens, wavelength_um)[-1]
    z_last = lens.vertex_z[-1]
    if nuc[-1] == 0:
        xp_z, xp_r = np.inf, np.inf
    else:
        dz = -yc[-1] * n_img / nuc[-1]
        xp_z = float(z_last + dz)
        xp_r = float(abs(ym[-1] + dz * num[-1] / n_img))
    return Pupils(ep_z, ep_r, xp_z, xp_r, sd)


def f_number(lens, wavelength_um: float = 0.5876) -> float:
    """Paraxial F/# = EFL / entrance pupil diameter (object at infinity)."""
    wavelength_um = _checked(lens, wavelength_um)
    return efl(lens, wavelength_um) / (2.0 * pupils(lens, wavelength_um).entrance_radius)


def thin_lens_conjugates(lens, wavelength_um: float, index: int, object_distance=None):
    """Object-side 1/u (1/mm, 0 = infinity) and image-side distance v (mm) seen by thin lens ``index``.

    u is the distance of the (possibly virtual) paraxial object in front of the lens, for
    ``object_distance`` (mm from the first vertex; default the lens's own); v its paraxial image
    distance behind it: ``math.inf`` when the object sits at the lens's front focal plane (a
    collimator: the image is at infinity).
    """
    wavelength_um = _checked(lens, wavelength_um)
    from . import checks
    index = checks.check_int(index, "index", lo=0, hi=len(lens.surfaces) - 1)
    if lens.surfaces[index].type != "thin_lens":
        raise checks.ArgumentError(f"index={index}: surface {index} is a {lens.surfaces[index].type!r} "
                                   "surface, not a thin_lens")
    n = signed_indices(lens, wavelength_um)
    n1 = 1.0 if index == 0 else n[index - 1]
    n2 = n[index]
    s = lens.surfaces[index]
    od = lens.object_distance if object_distance is None else float(object_distance)
    if np.isinf(od):
        y, nu = ynu_trace(lens, wavelength_um, 1.0, 0.0)
    else:
        y, nu = ynu_trace(lens, wavelength_um, od, 1.0)
    # reduced slope arriving at the lens (before its own refraction)
    nu_in = nu[index] + y[index] / s.focal_length
    if y[index] == 0:
        raise GeometryError("the object is imaged onto the thin lens (its conjugates are undefined)",
                            file=lens.source, surface=lens.surface_label(index))
    uinv = 0.0 if abs(nu_in) < 1e-300 else nu_in / (n1 * y[index])
    denom = 1.0 / s.focal_length - n1 * uinv
    if abs(denom) <= 1e-12 * abs(1.0 / s.focal_length):
        return float(uinv), math.inf  # object at the front focal plane: image at infinity
    return float(uinv), float(n2 / denom)
