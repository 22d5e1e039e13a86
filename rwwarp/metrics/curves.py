"""Ray-based curves (:mod:`rwwarp.metrics`): chromatic focal shift (the paraxial image distance per wavelength,
:func:`paraxial_image_distance`, :func:`chromatic_focal_shift`) and field curves (tangential / sagittal field
curvature and distortion from traced ray fans, :func:`field_curves`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import LensError
from .sampling import _image_space_rays


# ============================================================================== ray-based curves
@dataclass
class ChromaticFocalShift:
    """Paraxial focal shift ``shift_um`` (um; + away from the lens) of the image of the lens's object
    at each of ``wavelengths_um``, relative to ``reference_um``."""

    wavelengths_um: np.ndarray
    shift_um: np.ndarray
    reference_um: float

    def __repr__(self):
        from ..results import focal_shift_repr
        return focal_shift_repr(self)

    def plot(self, path=None, ax=None):
        """A picture (rwwarp.results); returns the Axes, or the Figure saved to ``path`` (PNG)."""
        from ..results import plot_focal_shift
        return plot_focal_shift(self, path=path, ax=ax)


def paraxial_image_distance(lens, wavelength_um: float, object_distance_mm=None) -> float:
    """Paraxial image distance behind the last surface (mm) of an axial object at the lens's object
    distance (or ``object_distance_mm``, mm from the first vertex; inf allowed), at ``wavelength_um``."""
    from ..paraxial import ynu_trace
    od = lens.object_distance if object_distance_mm is None else float(object_distance_mm)
    y0, nu0 = (1.0, 0.0) if math.isinf(od) else (od, 1.0)  # ray from the axial object point, slope 1
    y, nu = ynu_trace(lens, wavelength_um, y0, nu0)
    if nu[-1] == 0:
        raise LensError("the image is at infinity (afocal)", file=lens.source)
    return float(-y[-1] * lens.indices(wavelength_um)[-1] / nu[-1])


def chromatic_focal_shift(lens, wavelengths_um=None, reference_um=None, n: int = 41) -> ChromaticFocalShift:
    """Chromatic focal shift (paraxial, as Zemax plots it): image distance at each wavelength minus that
    at ``reference_um`` (um; default the lens's middle wavelength). ``wavelengths_um`` default: ``n``
    points over the lens's wavelength range (um). DOE power (proportional to lambda) is included."""
    wl = sorted(float(w) for w in lens.wavelengths_um)
    if wavelengths_um is None:
        lo, hi = wl[0], wl[-1]
        if hi - lo < 1e-6:
            lo, hi = 0.9 * lo, 1.1 * hi
        wavelengths_um = np.linspace(lo, hi, int(n))
    w = np.atleast_1d(np.asarray(wavelengths_um, dtype=float))
    if np.any((w < 0.2) | (w > 20.0)):
        raise ValueError("wavelengths_um outside 0.2..20 um (wavelengths are in micrometres)")
    ref = float(reference_um) if reference_um is not None else lens.wavelengths_um[len(lens.wavelengths_um) // 2]
    d0 = paraxial_image_distance(lens, ref)
    return ChromaticFocalShift(w, np.array([1e3 * (paraxial_image_distance(lens, x) - d0) for x in w]), ref)


@dataclass
class FieldCurves:
    """Field curvature and distortion against field (real rays, as Zemax plots them).

    ``tangential_mm`` / ``sagittal_mm``: axial position of the tangential / sagittal focus of rays
    about the chief ray, relative to the sensor plane (mm, + away from the lens). ``real_height_mm``:
    chief-ray image height; ``paraxial_height_mm``: paraxial image height at the sensor;
    ``distortion_percent = 100 (real - paraxial) / paraxial`` (0 on axis)."""

    fields_deg: np.ndarray
    tangential_mm: np.ndarray
    sagittal_mm: np.ndarray
    real_height_mm: np.ndarray
    paraxial_height_mm: np.ndarray
    distortion_percent: np.ndarray
    wavelength_um: float

    def __repr__(self):
        from ..results import field_curves_repr
        return field_curves_repr(self)

    def plot(self, path=None, ax=None):
        """A picture (rwwarp.results); returns the Axes, or the Figure saved to ``path`` (PNG)."""
        from ..results import plot_field_curves
        return plot_field_curves(self, path=path, ax=ax)


def field_curves(lens, fields_deg=None, wavelength_um=None, eps: float = 1e-3, device: str = "cpu") -> FieldCurves:
    """Field curvature (tangential and sagittal focus vs field) and F-tan(theta) distortion, for y
    fields ``fields_deg`` (deg; default 21 from 0 to the largest of ``lens.fields_deg``, else 10 deg)
    at ``wavelength_um`` (um; default the lens's middle wavelength).

    Foci from pairs of rays at pupil offsets ``+-eps`` (normalised pupil units) about the chief ray,
    in y (tangential) and x (sagittal): where their separation along that axis vanishes. The DOE's
    first order is applied as a local grating. Distortion compares the real chief ray's height on the
    sensor with the paraxial chief ray's (y-nu trace through the entrance-pupil centre)."""
    from ..paraxial import pupils, ynu_trace
    wl = float(wavelength_um) if wavelength_um is not None else lens.wavelengths_um[len(lens.wavelengths_um) // 2]
    if fields_deg is None:
        fmax = 10.0
        if lens.fields_deg:
            fmax = max(abs(float(f)) if np.ndim(f) == 0 else math.hypot(*map(float, f)) for f in lens.fields_deg)
        fields_deg = np.linspace(0.0, fmax if fmax > 0 else 10.0, 21)
    fl = np.atleast_1d(np.asarray(fields_deg, dtype=float))
    if fl.ndim != 1 or np.any(np.abs(fl) >= 89):
        raise ValueError(f"fields_deg must be a 1-D array of y field angles within +-89 deg, got {fields_deg!r}")
    if not (0 < eps < 0.5):
        raise ValueError(f"eps must be in (0, 0.5) (normalised pupil units), got {eps}")
    u = np.array([0.0, 0.0, 0.0, -eps, eps])
    v = np.array([0.0, -eps, eps, 0.0, 0.0])
    pos, d, ok, _, _ = _image_space_rays(lens, list(fl), wl, u, v, device=device)
    if not ok.all():
        bad = fl[~ok.all(1)]
        raise LensError(f"rays about the chief ray are vignetted at field(s) {list(bad)} deg", file=lens.source)
    zs = lens.sensor_z

    def cross(a, b, axis):
        # z where the rays a, b have equal coordinate `axis`: x_a + (z - z_a) m_a = x_b + (z - z_b) m_b
        ma, mb = d[:, a, axis] / d[:, a, 2], d[:, b, axis] / d[:, b, 2]
        xa = pos[:, a, axis] - pos[:, a, 2] * ma
        xb = pos[:, b, axis] - pos[:, b, 2] * mb
        with np.errstate(divide="ignore", invalid="ignore"):
            return -(xa - xb) / (ma - mb) - zs

    tan = cross(1, 2, 1)
    sag = cross(3, 4, 0)
    t = (zs - pos[:, 0, 2]) / d[:, 0, 2]
    real = pos[:, 0, 1] + t * d[:, 0, 1]
    pp = pupils(lens, wl)
    parax = np.zeros_like(fl)
    n_img = lens.indices(wl)[-1]
    for k, f in enumerate(fl):
        tt = math.tan(math.radians(f))
        y, nu = ynu_trace(lens, wl, -pp.entrance_z * tt, tt)
        parax[k] = y[-1] + lens.surfaces[-1].thickness * nu[-1] / n_img
    with np.errstate(divide="ignore", invalid="ignore"):
        dist = np.where(parax != 0, 100.0 * (real - parax) / np.where(parax != 0, parax, 1.0), 0.0)
    return FieldCurves(fl, tan, sag, real, parax, dist, wl)
