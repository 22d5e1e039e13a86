"""The sensor side of a ray-wave plan: image-space indices, patch centres snapped to the sensor's pixels, pixel
centres, and the Gauss-Legendre nodes per pixel that integrate |U|^2 over a pixel (used by
:class:`rwwarp.wave.raywave.RayWave`). Lengths in mm, wavelengths in mm where named ``lam_mm``."""
from __future__ import annotations

import numpy as np

from ..lens import snap_to_pixel as _snap_center

__all__ = ["auto_gauss_nodes", "n_img_all", "pixel_centres", "snap_centers"]


def n_img_all(lens, wls):
    """Refractive index of the image space at each wavelength."""
    return np.array([lens.indices(w)[-1] for w in wls])


def auto_gauss_nodes(dir_s, ok, n_img, lam_mm, pixel, tol=1e-7):
    """Fewest Gauss-Legendre nodes (3..16) per axis integrating |U|^2 over a pixel to ``tol``.

    |U|^2 at the sensor holds spatial frequencies up to 2 n NA / lambda (NA: the largest direction-sine
    spread of the beam about its mean); across a pixel the phase of that component changes by
    ``Phi = 2 pi pixel 2 n NA / lambda``, and the node count follows the Gauss-Legendre error bound for
    ``exp(i Phi t / 2)`` on [-1, 1].
    """
    from ..analytic import gauss_legendre_exp_error
    worst = 0.0
    for k in range(dir_s.shape[0]):
        d = dir_s[k, ok[k], :2]
        if len(d) == 0:
            continue
        na = float(np.max(np.abs(d - d.mean(0))))
        worst = max(worst, 2.0 * np.pi * pixel * 2.0 * n_img[k] * na / lam_mm[k])
    for g in range(3, 17):
        if gauss_legendre_exp_error(g, worst / 2.0) < tol:
            return g
    return 16


def snap_centers(center_mm, pixel, resolution, nsrc):
    """(nsrc, 2) patch centres: ``center_mm`` ((x, y) mm, one pair or one per source) snapped to the
    sensor's pixel centres."""
    c = np.asarray(center_mm, dtype=float).reshape(-1, 2)
    return np.broadcast_to(np.stack([_snap_center(c[:, 0], pixel, resolution[0]),
                                     _snap_center(c[:, 1], pixel, resolution[1])], 1), (nsrc, 2)).copy()


def pixel_centres(centers, size, pixel):
    """Pixel-centre coordinates (mm) of each source's ``size``-pixel patch about ``centers`` ((nsrc, 2) mm):
    ``(x (nsrc, size), y (nsrc, size))``."""
    off = (np.arange(size) - size // 2) * pixel
    return centers[:, 0:1] + off[None, :], centers[:, 1:2] + off[None, :]


def gauss_nodes_xy(rw):
    """The Gauss-Legendre nodes of a batch's pixels, ``(x (S, size g), y (S, size g))`` mm: pixel by pixel, the
    ``g = rw.gauss_nodes`` nodes of each (the node order of :func:`rwwarp.wave.focal.pixel_power`)."""
    from .propagate_setup import gauss_legendre
    px, py = rw.pixel_centres()
    t, _ = gauss_legendre(rw.gauss_nodes)
    off = 0.5 * rw.pixel * t
    nx = (px[:, :, None] + off[None, None, :]).reshape(rw.nsrc, -1)
    ny = (py[:, :, None] + off[None, None, :]).reshape(rw.nsrc, -1)
    return nx, ny
