"""Closed-form diffraction PSFs of an aberration-free converging wave (Fraunhofer / focal plane).

Independent references for the ray-wave code: numpy/scipy only, no propagation. The pupil is
filled uniformly by a converging wave focused at distance ``focal_mm``; the total power entering
the pupil is 1, and every function returns either an intensity per unit area (1/mm^2) or the
fraction of that unit power landing in a sensor pixel (dimensionless).

Units: lengths in mm, wavelengths in micrometres (converted once to mm inside each function).
Sensor coordinates are measured from the geometric focus (the optical axis).

Formulas (lambda f written ``lf``, all in mm):

* square aperture of side ``a``:
  ``I(x, y) = a^2/lf^2 * sinc^2(a x/lf) * sinc^2(a y/lf)``, ``sinc(t) = sin(pi t)/(pi t)``;
  zeros at multiples of ``lf/a``; the 1-D pixel integral is closed-form through the sine
  integral: ``int_0^t sinc^2 = (Si(2 pi t) - pi t sinc^2(t)) / pi``.
* circular aperture of diameter ``D`` (Airy): ``v = pi D r/lf``,
  ``I(r) = pi D^2/(4 lf^2) * (2 J1(v)/v)^2``; zeros at ``j_{1,n}/pi * lf/D``
  (1.2197, 2.2331, 3.2383, ...); encircled energy ``1 - J0(v)^2 - J1(v)^2``.
"""

import functools

import numpy as np
from scipy import special

__all__ = [
    "square_aperture_psf",
    "square_aperture_pixel_psf",
    "square_aperture_window_energy",
    "circular_aperture_psf",
    "circular_aperture_pixel_psf",
    "airy_zeros",
    "encircled_energy",
    "gauss_legendre_exp_error",
]


def _lambda_f_mm2(focal_mm, wavelength_um):
    """lambda * f in mm^2 (wavelength converted from um)."""
    if not focal_mm > 0 or not wavelength_um > 0:
        raise ValueError(f"focal_mm and wavelength_um must be positive, got {focal_mm}, {wavelength_um}")
    return float(wavelength_um) * 1e-3 * float(focal_mm)


def square_aperture_psf(x_mm, y_mm, side_mm, focal_mm, wavelength_um):
    """Focal-plane intensity of a uniformly filled square aperture, unit power.

    Args:
        x_mm, y_mm: sensor coordinates from the focus, mm (broadcast against each other).
        side_mm: full side ``a`` of the square aperture, mm (edges parallel to x and y).
        focal_mm: distance from the pupil to the focus, mm.
        wavelength_um: wavelength, um.

    Returns:
        Intensity per unit area, 1/mm^2 (multiply by 1e-6 for 1/um^2); its integral over the
        plane is 1. Peak ``a^2/(lambda f)^2`` at the origin.
    """
    lf = _lambda_f_mm2(focal_mm, wavelength_um)
    a = float(side_mm)
    x = np.asarray(x_mm, dtype=np.float64)
    y = np.asarray(y_mm, dtype=np.float64)
    return (a * a / (lf * lf)) * np.sinc(a * x / lf) ** 2 * np.sinc(a * y / lf) ** 2


def _sinc2_cumulative(t):
    """int_0^t sinc^2(s) ds (odd in t, tends to 1/2 as t -> +inf), sinc(s) = sin(pi s)/(pi s)."""
    t = np.asarray(t, dtype=np.float64)
    si, _ = special.sici(2.0 * np.pi * t)
    return (si - np.pi * t * np.sinc(t) ** 2) / np.pi


def square_aperture_pixel_psf(centers_x_mm, centers_y_mm, pixel_mm, side_mm, focal_mm, wavelength_um):
    """Fraction of the unit power landing in each square pixel, square aperture, exact.

    The intensity is separable, and the 1-D integral of ``sinc^2`` over a pixel is closed-form
    via the sine integral (``scipy.special.sici``), so the result is exact to rounding
    (about 1e-15 absolute per pixel).

    Args:
        centers_x_mm: 1-D array (Px,) of pixel-centre x coordinates, mm.
        centers_y_mm: 1-D array (Py,) of pixel-centre y coordinates, mm.
        pixel_mm: pixel pitch (square pixels, 100% fill), mm.
        side_mm, focal_mm, wavelength_um: as in :func:`square_aperture_psf`.

    Returns:
        Array (Py, Px): fraction of the entering power in each pixel (dimensionless).
    """
    lf = _lambda_f_mm2(focal_mm, wavelength_um)
    scale = float(side_mm) / lf
    half = 0.5 * float(pixel_mm)
    cx = np.asarray(centers_x_mm, dtype=np.float64).ravel()
    cy = np.asarray(centers_y_mm, dtype=np.float64).ravel()
    fx = _sinc2_cumulative((cx + half) * scale) - _sinc2_cumulative((cx - half) * scale)
    fy = _sinc2_cumulative((cy + half) * scale) - _sinc2_cumulative((cy - half) * scale)
    return fy[:, None] * fx[None, :]


def square_aperture_window_energy(x0_mm, x1_mm, y0_mm, y1_mm, side_mm, focal_mm, wavelength_um):
    """Fraction of the unit power falling in the rectangle [x0, x1] x [y0, y1] (mm), square aperture.

    Exact (sine integral). Returns a float in [0, 1].
    """
    lf = _lambda_f_mm2(focal_mm, wavelength_um)
    scale = float(side_mm) / lf
    fx = _sinc2_cumulative(x1_mm * scale) - _sinc2_cumulative(x0_mm * scale)
    fy = _sinc2_cumulative(y1_mm * scale) - _sinc2_cumulative(y0_mm * scale)
    return float(fx * fy)


def circular_aperture_psf(r_mm, diameter_mm, focal_mm, wavelength_um):
    """Airy pattern: focal-plane intensity of a uniformly filled circular aperture, unit power.

    Args:
        r_mm: radial distance from the focus, mm (any shape).
        diameter_mm: aperture diameter ``D``, mm.
        focal_mm: distance from the pupil to the focus, mm.
        wavelength_um: wavelength, um.

    Returns:
        Intensity per unit area, 1/mm^2; integral over the plane 1; peak ``pi D^2/(4 lambda^2 f^2)``.
    """
    lf = _lambda_f_mm2(focal_mm, wavelength_um)
    d = float(diameter_mm)
    v = np.pi * d * np.abs(np.asarray(r_mm, dtype=np.float64)) / lf
    peak = np.pi * d * d / (4.0 * lf * lf)
    vs = np.where(v == 0.0, 1.0, v)
    amp = np.where(v == 0.0, 1.0, 2.0 * special.j1(vs) / vs)
    return peak * amp * amp


def airy_zeros(n):
    """First ``n`` zeros of the Airy pattern in units of lambda*f/D: j_{1,k}/pi (1.2197, 2.2331, ...).

    Multiply by ``wavelength_mm * focal_mm / diameter_mm`` for radii in mm.
    """
    return special.jn_zeros(1, int(n)) / np.pi


def encircled_energy(r_mm, diameter_mm, focal_mm, wavelength_um):
    """Fraction of the unit power inside radius ``r_mm`` (mm) of the Airy pattern: 1 - J0(v)^2 - J1(v)^2.

    ``v = pi D r/(lambda f)``; 0.8378 at the first dark ring, 0.9100 at the second.
    """
    lf = _lambda_f_mm2(focal_mm, wavelength_um)
    v = np.pi * float(diameter_mm) * np.abs(np.asarray(r_mm, dtype=np.float64)) / lf
    return 1.0 - special.j0(v) ** 2 - special.j1(v) ** 2


def gauss_legendre_exp_error(nodes, omega):
    """Bound on the relative error of n-point Gauss-Legendre for int_{-1}^{1} exp(i omega t) dt.

    Uses the classical remainder ``2^(2n+1) (n!)^4 / ((2n+1) ((2n)!)^3) * max|f^(2n)|`` with
    ``max|f^(2n)| = omega^(2n)``, divided by the integral's scale 2. For an interval over which
    a phase changes by ``Phi`` rad, ``omega = Phi/2``. Sharp to leading order (n = 2:
    ``3.7e-3 omega^4``).
    """
    n = int(nodes)
    omega = abs(float(omega))
    if omega == 0.0:
        return 0.0
    # the node count's part of log(bound) once per count, added as before: the same bits
    log_e = _gauss_legendre_log_constant(n) + 2 * n * np.log(omega)
    return float(np.exp(log_e) / 2.0)


@functools.lru_cache(maxsize=64)
def _gauss_legendre_log_constant(n: int):
    """``log(2^(2n+1) (n!)^4 / ((2n+1) ((2n)!)^3))`` of :func:`gauss_legendre_exp_error`, summed in its order."""
    return ((2 * n + 1) * np.log(2.0) + 4 * special.gammaln(n + 1) - np.log(2 * n + 1)
            - 3 * special.gammaln(2 * n + 1))


def circular_aperture_pixel_psf(centers_x_mm, centers_y_mm, pixel_mm, diameter_mm, focal_mm,
                                wavelength_um, nodes=12):
    """Fraction of the unit power landing in each square pixel, circular aperture (Airy).

    Each pixel is integrated with an ``nodes x nodes`` Gauss-Legendre rule. The Airy intensity
    is an entire function whose spectrum (the OTF) is cut off at ``D/(lambda f)`` cycles/mm, so
    the per-pixel relative error is bounded by :func:`gauss_legendre_exp_error` with
    ``omega = pi * pixel * D/(lambda f)`` (twice, once per axis). With the default 12 nodes the
    bound is 1e-19 for pixels of ``lambda f/D`` (omega = pi, i.e. rounding), 2e-12 at
    ``2 lambda f/D`` and 4e-5 at ``4 lambda f/D``; measured against 40 nodes the errors relative
    to the peak pixel are < 1e-15, 2e-14 and 5e-8 (the OTF is small near its cut-off).

    Args:
        centers_x_mm: 1-D array (Px,) of pixel-centre x coordinates, mm.
        centers_y_mm: 1-D array (Py,) of pixel-centre y coordinates, mm.
        pixel_mm: pixel pitch (square pixels, 100% fill), mm.
        diameter_mm, focal_mm, wavelength_um: as in :func:`circular_aperture_psf`.
        nodes: Gauss-Legendre nodes per axis per pixel.

    Returns:
        Array (Py, Px): fraction of the entering power in each pixel.
    """
    t, w = np.polynomial.legendre.leggauss(int(nodes))
    half = 0.5 * float(pixel_mm)
    cx = np.asarray(centers_x_mm, dtype=np.float64).ravel()
    cy = np.asarray(centers_y_mm, dtype=np.float64).ravel()
    out = np.empty((cy.size, cx.size))
    xs = cx[:, None] + half * t[None, :]  # (Px, n)
    wxy = (half * w)[:, None] * (half * w)[None, :]  # (n_y, n_x)
    rows_per_block = max(1, 2_000_000 // max(1, cx.size * t.size * t.size))
    for i0 in range(0, cy.size, rows_per_block):
        ys = cy[i0:i0 + rows_per_block, None] + half * t[None, :]  # (b, n)
        r = np.hypot(ys[:, None, :, None], xs[None, :, None, :])  # (b, Px, n_y, n_x)
        inten = circular_aperture_psf(r, diameter_mm, focal_mm, wavelength_um)
        out[i0:i0 + rows_per_block] = np.einsum("bpij,ij->bp", inten, wxy)
    return out
