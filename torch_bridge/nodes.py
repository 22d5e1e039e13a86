"""The PSF nodes of a design: their sensor positions (mm) on a grid or the diagonal, the field angles that image
there, and the paraxial-wave model's object distance for a depth. :mod:`torch_bridge.design` re-exports them."""
from __future__ import annotations

import math

import numpy as np

__all__ = ["field_angles", "node_positions_mm", "paraxial_object_distance"]


def node_positions_mm(layout: str, half_size_mm, grid=(2, 2), fractions=(0.0, 0.5, 0.9), region: str = "quadrant"):
    """Sensor positions (x, y) in mm of the PSF nodes.

    ``layout="grid"``: ``gy x gx`` cell centres of the region (``region="full"``: the rectangle
    ``[-hx, hx] x [-hy, hy]``; ``"quadrant"``: ``[0, hx] x [0, hy]``), row-major from the top row
    (+y) down, as :func:`torch_bridge.imaging.node_positions` orders image rows.
    ``layout="diagonal"``: points on the diagonal towards (+hx, +hy) at the given ``fractions`` of the
    corner distance (rotationally symmetric lenses: the field dependence along one azimuth).
    """
    hx, hy = (float(half_size_mm), float(half_size_mm)) if np.ndim(half_size_mm) == 0 else \
        (float(half_size_mm[0]), float(half_size_mm[1]))
    if layout == "diagonal":
        return [(f * hx, f * hy) for f in fractions]
    if layout != "grid":
        raise ValueError(f"node layout must be 'grid' or 'diagonal', got {layout!r}")
    gy, gx = (int(grid), int(grid)) if np.ndim(grid) == 0 else (int(grid[0]), int(grid[1]))
    if region == "full":
        x0, x1, y0, y1 = -hx, hx, -hy, hy
    elif region == "quadrant":
        x0, x1, y0, y1 = 0.0, hx, 0.0, hy
    else:
        raise ValueError(f"region must be 'full' or 'quadrant', got {region!r}")
    out = []
    for r in range(gy):
        y = y1 - (r + 0.5) * (y1 - y0) / gy
        for c in range(gx):
            out.append((x0 + (c + 0.5) * (x1 - x0) / gx, y))
    return out


def field_angles(lens, positions_mm, wavelength_um: float = 0.55):
    """Field angles (x, y) in degrees whose paraxial image lands at the sensor positions (mm):
    ``tan(theta) = h / EFL`` (distortion is not inverted)."""
    f = lens.efl(wavelength_um)
    return [(math.degrees(math.atan(x / f)), math.degrees(math.atan(y / f))) for x, y in positions_mm]


def paraxial_object_distance(lens, eq_lens, object_distance_mm: float, wavelength_um: float) -> float:
    """Object distance (mm) in front of the paraxial-equivalent thin lens that puts its image where
    the real lens images an object at ``object_distance_mm`` (from the first vertex) -- so the
    paraxial-wave model sees the same defocus as the ray-wave model at each depth."""
    from rwwarp import paraxial
    if not math.isfinite(object_distance_mm):
        return math.inf
    plane = lens.wave_plane_index()
    slope = 1e-3
    ys, nus = paraxial.ynu_trace(lens, wavelength_um, object_distance_mm * slope, slope)
    n_pl = lens.indices(wavelength_um)[plane]
    v = -ys[plane] * n_pl / nus[plane - 1]  # image distance behind the DOE plane
    f_eq = next(s.focal_length for s in eq_lens.surfaces if s.type == "thin_lens")
    inv = 1.0 / f_eq - 1.0 / v
    return math.inf if abs(inv) < 1e-15 else 1.0 / inv
