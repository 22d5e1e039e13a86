"""The paraxial-wave comparison system (``model="paraxial-wave"``): the refractive part of a lens
replaced by an ideal thin lens at the wave plane (the DOE).

The equivalent keeps, for the object where it is (at infinity or at a finite distance):

* the paraxial image of the axial object point formed by the surfaces in front of the plane (so the
  defocus at the sensor is the real lens's paraxial defocus at that object distance);
* the paraxial footprint of the axial beam on the plane (its aperture);
* the paraxial image height of each field on the sensor side (equivalent field angles).

The thin lens's focal length is the distance behind the plane at which the refractive part images an
object at infinity (a property of the lens, independent of the object); a finite object is then put
at the distance in front of the thin lens that it images to the real lens's image point:
``1/u_eq = 1/f_eq - 1/v`` (paraxial, in the plane's medium as the real lens). Lengths in mm,
wavelengths in um.
"""
from __future__ import annotations

import math

import numpy as np

from .. import paraxial
from ..errors import LensError


def _field_pair(f):
    return (0.0, float(f)) if np.ndim(f) == 0 else (float(f[0]), float(f[1]))


def _image_distance_behind(lens, plane, wl, od):
    """Paraxial image distance (mm) behind surface ``plane`` of an axial object at ``od`` mm in front
    of the first vertex (inf allowed), formed by the surfaces before the plane."""
    if math.isinf(od):
        ys, nus = paraxial.ynu_trace(lens, wl, 1.0, 0.0)
    else:
        ys, nus = paraxial.ynu_trace(lens, wl, od, 1.0)  # slope 1 from the object point
    n_pl = lens.indices(wl)[plane]
    nu = nus[plane - 1]
    if nu == 0:
        raise LensError("paraxial-wave model: the refractive part images the object at infinity (afocal at "
                        "this object distance)", file=lens.source, surface=lens.surface_label(plane))
    return float(-ys[plane] * n_pl / nu)


def _image_height(lens, wl, od, tan_field):
    """Paraxial image height (mm) of the whole lens for a field of direction tangent ``tan_field``
    (chief ray through the entrance pupil centre), at the lens's paraxial image plane."""
    if math.isinf(od):
        return paraxial.efl(lens, wl) * tan_field
    pup = paraxial.pupils(lens, wl)
    n_img = lens.indices(wl)[-1]
    ya, nua = paraxial.ynu_trace(lens, wl, od, 1.0)
    if nua[-1] == 0:
        raise LensError("paraxial-wave model: the lens images the object at infinity", file=lens.source)
    dz = -ya[-1] * n_img / nua[-1]
    yc, nuc = paraxial.ynu_trace(lens, wl, -pup.entrance_z * tan_field, tan_field)
    return float(yc[-1] + dz * nuc[-1] / n_img)


def paraxial_equivalent(lens, fields, wls, object_distance_mm=None):
    """The paraxial-wave comparison system: the refractive part replaced by an ideal thin lens.

    ``object_distance_mm``: mm from the first vertex (inf allowed); None: the lens's own. Returns
    ``(lens, fields)``: the equivalent lens (its object distance set so the thin lens images the object
    where the refractive part's paraxial image lies) and equivalent field angles (same paraxial image
    height).
    """
    from ..lens import Lens, Surface
    plane = lens.wave_plane_index()
    if plane == 0:
        raise LensError("paraxial-wave model needs refracting surfaces before the DOE", file=lens.source)
    od = lens.object_distance if object_distance_mm is None else float(object_distance_mm)
    if not od > 0:
        raise LensError(f"object distance must be > 0 mm or inf, got {od}", file=lens.source)
    w0 = wls[0]
    f_eq = _image_distance_behind(lens, plane, w0, math.inf)
    v = f_eq if math.isinf(od) else _image_distance_behind(lens, plane, w0, od)
    inv_u = 1.0 / f_eq - 1.0 / v
    if math.isinf(od) or abs(inv_u) * abs(v) < 1e-15:
        od_eq = math.inf
    elif inv_u > 0:
        od_eq = 1.0 / inv_u
    else:
        # the real object images closer than the lens's focus (a virtual object for the thin lens):
        # the thin lens takes the image distance as its focal length, object at infinity
        f_eq, od_eq = v, math.inf
    pup = paraxial.pupils(lens, w0)
    if math.isinf(od):
        marg_y, _ = paraxial.ynu_trace(lens, w0, pup.entrance_radius, 0.0)
        half = abs(marg_y[plane])
    else:
        # marginal ray: from the axial object point to the edge of the entrance pupil
        ya, _ = paraxial.ynu_trace(lens, w0, od, 1.0)
        half = abs(ya[plane]) * pup.entrance_radius / abs(od + pup.entrance_z)
    s_doe = lens.surfaces[plane]
    surfs = [Surface(type="aperture", semi_diameter=half, shape=lens.surfaces[lens.stop_index].shape, stop=True),
             Surface(type="thin_lens", focal_length=f_eq, semi_diameter=None)]
    if s_doe.type == "doe":
        surfs.append(Surface(type="doe", semi_diameter=s_doe.semi_diameter, shape=s_doe.shape,
                             profile=s_doe.profile, design_wavelength_um=s_doe.design_wavelength_um,
                             material=s_doe.material, levels=s_doe.levels))
    surfs[-1].thickness = lens.sensor_z - lens.vertex_z[plane]
    eq = Lens(surfs, lens.sensor, od_eq, list(wls), name=f"paraxial equivalent of {lens.name}",
              source=lens.source)
    eq_fields = []
    for f in fields:
        fx, fy = _field_pair(f)
        # same paraxial image height h; the equivalent's chief ray passes the thin lens's centre undeviated,
        # so its image height v tan(theta_eq) (object at infinity: f_eq tan(theta_eq))
        tx = _image_height(lens, w0, od, math.tan(math.radians(fx))) / v
        ty = _image_height(lens, w0, od, math.tan(math.radians(fy))) / v
        eq_fields.append((math.degrees(math.atan(tx)), math.degrees(math.atan(ty))))
    return eq, eq_fields
