"""The DOE as the wave stage samples it (host side, numpy): its relief phase on each source's wave-plane
window (:func:`doe_phase_grid`), the largest local frequency it adds at the pilot rays' points
(:func:`doe_max_frequency`, for the sampling plan), and the wrap zones the traced beam crosses
(:func:`one_branch`, :func:`chief_zone`, for the focal method's diffraction orders). Lengths in mm, phases
in rad, frequencies in cycles/mm, wavelengths in um."""
from __future__ import annotations

import math

import numpy as np

from ..doe import is_flat_profile as _is_flat_profile
from .doe_phase import wrap_zone

__all__ = ["branch_of_range", "chief_zone", "doe_max_frequency", "doe_phase_grid", "doe_pixel_origin", "lens_dir",
           "one_branch"]


def lens_dir(lens):
    """The folder of the lens file (relative DOE data files are read from it), or None."""
    from pathlib import Path
    return None if lens.source is None else Path(lens.source).parent


def one_branch(phi, tol=1e-9):
    """``k`` when every phase in ``phi`` (rad, a DOE's unwrapped phase at the traced beam's points) lies in
    one branch ``[2 pi k, 2 pi (k + 1)]`` of the wrap (ends included: a phase at a branch end, such as an
    even polynomial's 0 on the axis, is a set of measure zero), else None."""
    phi = np.asarray(phi, dtype=np.float64)
    if phi.size == 0 or not np.all(np.isfinite(phi)):
        return None
    return branch_of_range(phi.min(), phi.max(), tol)


def branch_of_range(phi_min, phi_max, tol=1e-9):
    """:func:`one_branch` of finite phases (rad) whose least is ``phi_min`` and greatest ``phi_max``: ``k`` when
    both lie in one branch ``[2 pi k, 2 pi (k + 1)]`` (within ``tol``), else None. Also used by
    :mod:`rwwarp.wave.focal_sources` (every source's range at once)."""
    k = math.floor(float(phi_min) / (2 * math.pi) + tol)
    lo, hi = 2 * math.pi * k, 2 * math.pi * (k + 1)
    if phi_min >= lo - tol and phi_max <= hi + tol:
        return k
    return None


def chief_zone(phi, xy, chief_xy):
    """The wrap zone ``k = floor(phi0 / 2 pi)`` (:func:`~rwwarp.wave.doe_phase.wrap_zone`) the chief ray
    crosses, from the pilot rays' phases ``phi`` (rad) at their wave-plane points ``xy`` (N, 2): the zone of the
    pilot point nearest the chief ray whose phase is not on a zone boundary (an even polynomial is 0, a
    boundary, exactly on the axis)."""
    phi = np.asarray(phi, dtype=np.float64)
    order = np.argsort(np.sum((np.asarray(xy) - np.asarray(chief_xy)[None, :]) ** 2, axis=1))
    for j in order:
        q = phi[j] / (2 * math.pi)
        if np.isfinite(q) and abs(q - round(q)) > 1e-9:
            return int(wrap_zone(phi[j], np))
    return int(wrap_zone(phi[order[0]], np))


def doe_phase_grid(lens, plane, origin, pitch, n):
    """phi0 (rad) of the DOE sampled on each source's grid, (S, n, n), or None."""
    s = lens.surfaces[plane]
    if s.type != "doe" or _is_flat_profile(s.profile):
        return None
    from .. import doe
    prof = doe.profile_from_dict(s.profile, base=lens_dir(lens))
    g = np.arange(n) * pitch
    out = np.empty((origin.shape[0], n, n))
    for k in range(origin.shape[0]):
        x, y = np.meshgrid(origin[k, 0] + g, origin[k, 1] + g, indexing="xy")
        # the physical relief: phi0 wrapped to [0, 2 pi) (and quantised), then remapped per wavelength
        ph = doe.design_phase(prof, x, y, s.design_wavelength_um, s.levels)
        # no mask at the DOE's edge: the tracer already clipped rays there, and samples straddling the
        # edge (partly covered) need the phase the profile has at the edge, not 0
        out[k] = ph
    return out


def doe_max_frequency(lens, plane, xy, wavelengths):
    """Largest local spatial frequency (cycles/mm) the DOE adds at the points ``xy`` (per source: ``xy[k]`` (N_k, 2)
    mm, read only where the relief has a phase) at ``wavelengths`` (um, per source); and the DOE's feature size (mm)
    where its relief has steps, else None. Returns ``(f_max (S,), feature)``."""
    s = lens.surfaces[plane]
    if s.type != "doe":
        return np.zeros(len(wavelengths)), None
    from .. import doe
    prof = doe.profile_from_dict(s.profile, base=lens_dir(lens))
    feat = None
    if doe.surface_has_steps(s, lens.source):  # (a quantised flat phase has none: issue 11 defect 6)
        feat = doe.surface_feature_size_mm(s, lens.source)
        return np.zeros(len(wavelengths)), feat
    if doe.is_flat_profile(s.profile):   # a blank relief (no phase) adds no frequency: the zeros its gradient gives
        return np.zeros(len(wavelengths)), feat
    out = np.zeros(len(wavelengths))
    scales = {}   # the phase scale once a wavelength (a map's sources share a few; the same value each call)
    for k, w in enumerate(wavelengths):
        gx, gy = prof.gradient(xy[k][:, 0], xy[k][:, 1], s.design_wavelength_um)
        sc = scales.get(w)
        if sc is None:
            sc = scales[w] = doe.wavelength_scale(s.material, s.design_wavelength_um, w)
        out[k] = sc * np.max(np.hypot(gx, gy)) / (2 * np.pi) if len(gx) else 0.0
    return out, feat


def doe_pixel_origin(lens, plane: int, origin, pitch_mm: float) -> np.ndarray:
    """Window origins ((S, 2) mm) shifted so that, for a pixel-map DOE on surface ``plane``, sample cells of
    ``pitch_mm`` (which divides the DOE pitch) tile the DOE pixels exactly (no cell straddles a phase step);
    ``origin`` itself (a new array) for any other surface."""
    origin = np.array(origin, dtype=np.float64)
    s = lens.surfaces[plane]
    if s.type != "doe" or s.profile.get("kind") != "pixel_map":
        return origin
    from .. import doe
    prof = doe.profile_from_dict(s.profile, base=lens_dir(lens))
    rows, cols = prof.data.shape
    h = pitch_mm
    for axis, count in ((0, cols), (1, rows)):
        first = -0.5 * count * prof.pitch + 0.5 * h  # centre of the first sample cell inside the map
        origin[:, axis] = first + np.round((origin[:, axis] - first) / h) * h
    return origin
