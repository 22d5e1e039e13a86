"""Strehl ratio (:mod:`rwwarp.metrics`): the PSF's peak intensity (:func:`peak_intensity_from_psf`, the
pixel-integrated patch band-limited and upsampled to its peak) over the peak of the ideal wave that carries the
same power through the same pupil (:func:`ideal_peak_intensity`: traced pupil, amplitude and NA, no aberration).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import LensError
from .sampling import (
    default_sampling_mm, _as_fields, _as_wavelengths, _check_model, _check_positive, _check_psf_array,
    _image_space_rays, _patch_check, _psfs,
)


def peak_intensity_from_psf(data, pixel_mm, upsample: int = 4):
    """Peak point intensity (power / mm^2) of a pixel-integrated PSF patch and its position.

    The patch is treated as box integrals of a band-limited intensity sampled above its Nyquist rate:
    the box is divided out in the Fourier domain and the intensity is interpolated (zero padding) on
    a grid ``upsample`` times finer. Returns ``(peak, (dx, dy))``, the offset (mm) from the patch
    centre."""
    a = _check_psf_array(data)
    p = _check_positive(pixel_mm, "pixel_mm")
    if int(upsample) < 1:
        raise ValueError(f"upsample must be >= 1, got {upsample}")
    n, m = a.shape[0], int(upsample) * a.shape[0]
    F = np.fft.fftshift(np.fft.fft2(np.fft.ifftshift(a)))
    f = (np.arange(n) - n // 2) / (n * p)
    F = F / np.outer(np.sinc(f * p), np.sinc(f * p))
    if n % 2 == 0:  # the Nyquist row/column is shared by +-f: split it so the interpolant is real
        F[0, :] *= 0.5
        F[:, 0] *= 0.5
        G = np.zeros((n + 1, n + 1), dtype=complex)
        G[:n, :n] = F
        G[n, :] = G[0, :]
        G[:, n] = G[:, 0]
        G[n, n] = G[0, 0]
        F = G
    big = np.zeros((m, m), dtype=complex)
    k = F.shape[0]
    s0 = m // 2 - n // 2
    big[s0:s0 + k, s0:s0 + k] = F
    img = np.real(np.fft.fftshift(np.fft.ifft2(np.fft.ifftshift(big)))) * (m / n) ** 2 / (p * p)
    j = np.unravel_index(int(np.argmax(img)), img.shape)
    step = p / upsample
    return float(img[j]), ((j[1] - m // 2) * step, (j[0] - m // 2) * step)


# ============================================================================== Strehl
@dataclass
class Strehl:
    """Strehl ratios, shape (n_fields, n_wavelengths) (scalars dropped as given), with the PSFs' peak
    intensities and the ideal ones (fraction of entering power per mm^2)."""

    ratio: np.ndarray
    peak: np.ndarray
    ideal_peak: np.ndarray
    fields_deg: list
    wavelengths_um: list
    model: str
    info: dict = field(default_factory=dict)

    def __repr__(self):
        from ..results import strehl_repr
        return strehl_repr(self)

    def plot(self, path=None, ax=None):
        """A picture (rwwarp.results); returns the Axes, or the Figure saved to ``path`` (PNG)."""
        from ..results import plot_strehl
        return plot_strehl(self, path=path, ax=ax)


def ideal_peak_intensity(lens, field_deg, wavelength_um, image_point_mm, grid: int = 401, device: str = "cpu",
                         object_distance_mm=None, paraxial_doe: bool = False, per: str = "entering") -> float:
    """Peak intensity (fraction of the entering power per mm^2) of the aberration-free wave with the
    lens's pupil: the beam's amplitude on the wave plane (ray density; vignetting included) with a
    spherical phase converging exactly to ``image_point_mm`` ((x, y) on the sensor, mm).

    Rayleigh-Sommerfeld at the focus: ``U = (n / lambda) sum_i sqrt(w_i dA_i) cos(theta_i) / r_i`` over
    the rays of a ``grid`` x ``grid`` entrance-pupil grid (``w_i`` ray power, ``dA_i`` its cell's area on
    the wave plane from the grid's Jacobian), normalised by the entering power (``per="entering"``) or
    by the power that passes the lens (``per="passing"``: then independent of how the pupil edge is
    counted; multiply by a model's own passing fraction to compare with its PSF)."""
    if per not in ("entering", "passing"):
        raise ValueError(f"per must be 'entering' or 'passing', got {per!r}")
    plane = lens.wave_plane_index()
    shape = lens.surfaces[lens.stop_index].shape
    g = -1.0 + (2.0 * np.arange(grid) + 1.0) / grid
    uu, vv = np.meshgrid(g, g, indexing="xy")
    inside_pupil = np.ones_like(uu, bool) if shape == "square" else (uu * uu + vv * vv <= 1.0 + 1e-12)
    pos, d, ok, w, n = _image_space_rays(lens, [field_deg], wavelength_um, uu.ravel(), vv.ravel(),
                                         object_distance_mm, device,
                                         doe_bending="paraxial" if paraxial_doe else "full")
    pos, d, ok, w = pos[0], d[0], ok[0] & inside_pupil.ravel(), w[0]
    # to a common flat plane at the wave plane's vertex (a curved last surface has sag)
    z0 = float(lens.vertex_z[plane])
    t = (z0 - pos[:, 2]) / d[:, 2]
    p = pos + t[:, None] * d
    X = p[:, 0].reshape(grid, grid)
    Y = p[:, 1].reshape(grid, grid)
    with np.errstate(invalid="ignore"):
        xu, xv = np.gradient(X, axis=1), np.gradient(X, axis=0)
        yu, yv = np.gradient(Y, axis=1), np.gradient(Y, axis=0)
        jac = np.abs(xu * yv - xv * yu).ravel()  # wave-plane area per grid cell
    okj = ok & np.isfinite(jac)
    if okj.sum() < 3:
        raise LensError("no rays reach the wave plane for this field", file=lens.source, field=field_deg)
    if (ok & ~np.isfinite(jac)).any():
        jac = np.where(np.isfinite(jac), jac, np.median(jac[okj]))
        okj = ok
    entering = w[inside_pupil.ravel()].sum()
    zs = lens.sensor_z
    dx, dy, dz = image_point_mm[0] - p[:, 0], image_point_mm[1] - p[:, 1], zs - z0
    r = np.sqrt(dx * dx + dy * dy + dz * dz)
    lam = wavelength_um * 1e-3
    u0 = (n / lam) * np.sum(np.sqrt(w[okj] * jac[okj]) * (dz / r[okj]) / r[okj])
    return float(u0 * u0 / (entering if per == "entering" else np.sum(w[okj])))


def strehl(lens, field_deg=0.0, wavelength_um=0.55, model: str = "ray-wave", size="auto", pixel_mm=None,
           device: str = "cpu", grid: int = 401, **psf_kwargs) -> Strehl:
    """Strehl ratio: the PSF's peak intensity over that of the aberration-free wave with the same pupil.

    The PSF (``model`` "ray-wave" or "paraxial-wave"; the geometric "ray" PSF has no diffraction peak
    and is refused) is sampled at ``pixel_mm`` (default :func:`default_sampling_mm`) on ``size`` samples
    (``"auto"``: :func:`patch_size_for`);
    its point-intensity peak is recovered by :func:`peak_intensity_from_psf`. The ideal peak is
    :func:`ideal_peak_intensity` at the PSF's peak position (same amplitude over the pupil, vignetting
    included, spherical wave converging to that point; for the paraxial-wave model, of its paraxial
    equivalent system), carrying the fraction of the entering power that the PSF model lets through.
    Fields and wavelengths batch like :func:`rwwarp.psf_map`; returns :class:`Strehl`.
    """
    _check_model(model)
    if model == "ray":
        raise ValueError("model='ray' gives a geometric PSF without a diffraction peak: the Strehl ratio needs "
                         "model='ray-wave' or 'paraxial-wave'")
    fields, fscalar = _as_fields(field_deg)
    wls, _ = _as_wavelengths(wavelength_um, None)
    wscalar = np.ndim(wavelength_um) == 0
    pixel = _check_positive(pixel_mm, "pixel_mm") if pixel_mm is not None else \
        default_sampling_mm(lens, fields, wls, device)
    m = _psfs(lens, fields, wls, model, size, pixel, device, psf_kwargs)
    _patch_check(m, "strehl")
    ratio, peak, ideal = strehl_from_psf_map(lens, m, grid, device, psf_kwargs.get("object_distance_mm"))
    sl = (0 if fscalar else slice(None), 0 if wscalar else slice(None))
    return Strehl(ratio[sl], peak[sl], ideal[sl], fields, wls, model, {"pixel_mm": pixel, "psf_map": m})


def strehl_from_psf_map(lens, m, grid: int = 401, device: str = "cpu", object_distance_mm=None):
    """Strehl ratios ``(ratio, peak, ideal_peak)``, each (n_fields, n_wavelengths), of a wave-model
    :class:`rwwarp.PSFMap` ``m`` of ``lens`` (see :func:`strehl`; peaks in fraction of the entering power
    per mm^2). The map's samples must be finer than ``lambda / (4 NA)`` (see :func:`default_sampling_mm`)."""
    if m.model == "ray":
        raise ValueError("a 'ray' model PSF map has no diffraction peak: the Strehl ratio needs a wave model")
    nf, nw = m.data.shape[:2]
    # the ideal wave carries the power the model lets through (its own pupil-edge bookkeeping)
    vf = np.asarray(m.info["valid_fraction"], float).reshape(nf, nw)
    ratio, peak, ideal = np.zeros((nf, nw)), np.zeros((nf, nw)), np.zeros((nf, nw))
    for i, f in enumerate(m.fields_deg):
        for j, w in enumerate(m.wavelengths_um):
            pk, (dx, dy) = peak_intensity_from_psf(m.data[i, j], m.pixel_mm)
            pt = (m.centers_mm[i, j, 0] + dx, m.centers_mm[i, j, 1] + dy)
            if m.model == "paraxial-wave":
                from ..psf import paraxial_equivalent
                eq, eqf = paraxial_equivalent(lens, [f], [w], object_distance_mm)
                ideal[i, j] = vf[i, j] * ideal_peak_intensity(eq, eqf[0], w, pt, grid, device, per="passing")
            else:
                ideal[i, j] = vf[i, j] * ideal_peak_intensity(lens, f, w, pt, grid, device, object_distance_mm,
                                                              per="passing")
            peak[i, j] = pk
            ratio[i, j] = pk / ideal[i, j]
    return ratio, peak, ideal
