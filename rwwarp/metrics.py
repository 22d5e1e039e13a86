"""Figures of merit: MTF, through-focus MTF, Strehl ratio, encircled / ensquared energy, and the
ray-based curves (chromatic focal shift, field curvature, distortion).

Units: lengths in mm unless a name says otherwise (``_um``), spatial frequencies in line pairs per
mm (lp/mm = cycles/mm), wavelengths in um, field angles in degrees.

The wave figures (MTF, Strehl, encircled and ensquared energy) are computed from the PSFs that
:func:`rwwarp.psf_map` returns, for any of its three models (``"ray-wave"``, ``"ray"``,
``"paraxial-wave"``; Strehl needs a wave model). Conventions:

* A PSF patch holds the power per sensor pixel, i.e. the intensity *box-integrated* over each pixel.
  Its discrete Fourier transform is therefore the optical transfer function (OTF) times the pixel's
  own transfer function ``sinc(fx p) sinc(fy p)``; the *optical* MTF divides that out (exact for a PSF
  sampled above the Nyquist rate of the intensity, ``p < lambda / (4 NA)``, which the default
  sampling pitch :func:`default_sampling_mm` guarantees). ``include_pixel=True`` multiplies the
  optical MTF by the sensor pixel's MTF ``|sinc(f p_sensor)|`` (``sinc(x) = sin(pi x) / (pi x)``).
* Tangential frequencies point along the field direction on the sensor (y for a y field and on
  axis), sagittal frequencies perpendicular to it (x for a y field), as Zemax plots them.
* Polychromatic figures weight each wavelength's PSF normalised to unit power; the OTFs are summed
  with their phases in sensor coordinates, so lateral colour lowers the polychromatic MTF.
* Encircled / ensquared energy is the fraction of the power reaching the sensor (all of it, not just
  the patch) inside a circle / square about the PSF centroid (or the chief ray).
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np

from .errors import LensError, PatchWarning, SamplingWarning

__all__ = ["MTF", "ThroughFocusMTF", "Strehl", "EnergyCurve", "FieldCurves", "ChromaticFocalShift",
           "mtf", "through_focus_mtf", "strehl", "encircled_energy", "ensquared_energy",
           "chromatic_focal_shift", "field_curves", "otf_from_psf", "encircled_energy_from_psf",
           "ensquared_energy_from_psf", "peak_intensity_from_psf", "pixel_mtf", "default_sampling_mm",
           "image_space_na", "diffraction_mtf_circular", "mtf_from_psf_map", "energy_from_psf_map",
           "ideal_peak_intensity", "paraxial_image_distance", "strehl_from_psf_map", "patch_size_for"]

MODELS = ("ray-wave", "ray", "paraxial-wave")


# ============================================================================== analytic helpers
def diffraction_mtf_circular(frequencies_lp_mm, cutoff_lp_mm):
    """Diffraction-limited MTF of an aberration-free, uniformly filled circular pupil,
    ``(2/pi) (acos v - v sqrt(1 - v^2))`` with ``v = f / cutoff`` (0 beyond the cutoff).

    ``frequencies_lp_mm``: lp/mm; ``cutoff_lp_mm``: ``2 NA / lambda`` = ``1 / (lambda F#)`` in lp/mm."""
    v = np.clip(np.abs(np.asarray(frequencies_lp_mm, dtype=float)) / float(cutoff_lp_mm), 0.0, 1.0)
    return (2.0 / np.pi) * (np.arccos(v) - v * np.sqrt(1.0 - v * v))


def pixel_mtf(frequencies_lp_mm, pixel_mm):
    """MTF of a square pixel of pitch ``pixel_mm`` (mm, 100 % fill) along one axis: ``|sinc(f p)|``."""
    return np.abs(np.sinc(np.asarray(frequencies_lp_mm, dtype=float) * float(pixel_mm)))


# ============================================================================== PSF-array cores
def _check_psf_array(data, name="data"):
    a = np.asarray(data, dtype=np.float64)
    if a.ndim != 2 or a.shape[0] != a.shape[1] or a.shape[0] < 2:
        raise ValueError(f"{name} must be a square 2-D PSF patch, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} has non-finite values")
    return a


def _check_positive(value, name):
    v = float(value)
    if not (v > 0) or not math.isfinite(v):
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    return v


def _patch_coords(n, pixel_mm, center_mm=(0.0, 0.0)):
    off = (np.arange(n) - n // 2) * pixel_mm
    return center_mm[0] + off, center_mm[1] + off


def otf_from_psf(data, pixel_mm, frequencies_lp_mm, direction=(0.0, 1.0), center_mm=(0.0, 0.0),
                 pixel_integrated: bool = True, normalize: bool = True):
    """Complex OTF of a PSF patch along one direction, by a direct Fourier sum over its samples.

    ``data``: (n, n) patch, rows = y (up), columns = x, sample ``[n//2, n//2]`` at ``center_mm``
    ((x, y) mm); ``pixel_mm``: sample pitch (mm); ``frequencies_lp_mm``: 1-D frequencies (lp/mm);
    ``direction``: the (x, y) direction of the frequency vector (normalised here).
    ``pixel_integrated``: the samples are box integrals over pixels (rwwarp PSFs), so the box's
    ``sinc(fx p) sinc(fy p)`` is divided out; ``False`` for point samples. ``normalize``: divide by the
    patch's power (OTF(0) = 1). The phase is referred to the sensor origin (``center_mm`` matters), so
    OTFs of several patches add coherently. Returns complex128 of the frequencies' shape.
    """
    a = _check_psf_array(data)
    p = _check_positive(pixel_mm, "pixel_mm")
    f = np.atleast_1d(np.asarray(frequencies_lp_mm, dtype=np.float64))
    d = np.asarray(direction, dtype=np.float64)
    if d.shape != (2,) or not np.hypot(*d) > 0:
        raise ValueError(f"direction must be a non-zero (x, y) pair, got {direction!r}")
    d = d / np.hypot(*d)
    x, y = _patch_coords(a.shape[0], p, center_mm)
    fx, fy = f * d[0], f * d[1]
    # separable sum: sum_y e^{-2 pi i fy y} sum_x a[y, x] e^{-2 pi i fx x}
    ex = np.exp(-2j * np.pi * np.outer(fx, x))  # (nf, n)
    ey = np.exp(-2j * np.pi * np.outer(fy, y))
    otf = np.einsum("fx,yx,fy->f", ex, a, ey)
    if pixel_integrated:
        otf = otf / (np.sinc(fx * p) * np.sinc(fy * p))
    if normalize:
        s = a.sum()
        if not s > 0:
            raise ValueError("the PSF patch holds no power")
        otf = otf / s
    return otf.reshape(np.shape(frequencies_lp_mm)) if np.ndim(frequencies_lp_mm) else otf[0]


def _subpixel_inside(n, pixel_mm, center_rel_mm, inside, sub=16):
    """Fraction of each pixel's area inside a region (``inside(dx, dy) -> bool``), by sub x sub
    sub-samples per pixel; dx, dy relative to ``center_rel_mm`` (mm, relative to the patch centre)."""
    off = (np.arange(n) - n // 2) * pixel_mm
    s = ((np.arange(sub) + 0.5) / sub - 0.5) * pixel_mm
    xs = (off[:, None] + s[None, :]).ravel() - center_rel_mm[0]  # (n*sub,)
    ys = (off[:, None] + s[None, :]).ravel() - center_rel_mm[1]
    m = inside(xs[None, :], ys[:, None]).astype(np.float64)  # (n*sub rows=y, n*sub cols=x)
    return m.reshape(n, sub, n, sub).mean(axis=(1, 3))


def _centroid_rel(a, pixel_mm):
    off = (np.arange(a.shape[0]) - a.shape[0] // 2) * pixel_mm
    s = a.sum()
    return float((a.sum(0) * off).sum() / s), float((a.sum(1) * off).sum() / s)


def encircled_energy_from_psf(data, pixel_mm, radii_mm, total=None, center_rel_mm=None, sub: int = 16):
    """Encircled energy of a PSF patch: power inside circles of ``radii_mm`` (mm) / ``total``.

    Each pixel's power is taken as uniform over the pixel (sub x sub sub-samples decide the covered
    fraction). ``total``: the normalising power (default the patch sum); ``center_rel_mm``: circle
    centre (x, y) relative to the patch centre (mm), default the patch centroid. Returns the
    fractions, shape of ``radii_mm``."""
    a = _check_psf_array(data)
    p = _check_positive(pixel_mm, "pixel_mm")
    r = np.atleast_1d(np.asarray(radii_mm, dtype=float))
    if np.any(r < 0):
        raise ValueError("radii_mm must be >= 0")
    c = _centroid_rel(a, p) if center_rel_mm is None else tuple(float(v) for v in center_rel_mm)
    tot = a.sum() if total is None else _check_positive(total, "total")
    out = np.array([(a * _subpixel_inside(a.shape[0], p, c, lambda x, y, R=R: x * x + y * y <= R * R, sub)).sum()
                    for R in r]) / tot
    return out.reshape(np.shape(radii_mm)) if np.ndim(radii_mm) else float(out[0])


def ensquared_energy_from_psf(data, pixel_mm, half_widths_mm, total=None, center_rel_mm=None, sub: int = 16):
    """Ensquared energy of a PSF patch: power inside axis-aligned squares of half width
    ``half_widths_mm`` (mm) / ``total`` (default the patch sum); centre as in
    :func:`encircled_energy_from_psf`. Returns the fractions, shape of ``half_widths_mm``."""
    a = _check_psf_array(data)
    p = _check_positive(pixel_mm, "pixel_mm")
    h = np.atleast_1d(np.asarray(half_widths_mm, dtype=float))
    if np.any(h < 0):
        raise ValueError("half_widths_mm must be >= 0")
    c = _centroid_rel(a, p) if center_rel_mm is None else tuple(float(v) for v in center_rel_mm)
    tot = a.sum() if total is None else _check_positive(total, "total")
    out = np.array([(a * _subpixel_inside(a.shape[0], p, c,
                                          lambda x, y, H=H: (np.abs(x) <= H) & (np.abs(y) <= H), sub)).sum()
                    for H in h]) / tot
    return out.reshape(np.shape(half_widths_mm)) if np.ndim(half_widths_mm) else float(out[0])


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


# ============================================================================== lens helpers
def _image_space_rays(lens, fields, wavelength_um, u, v, object_distance_mm=None, device="cpu",
                      doe_bending: str = "full"):
    """Rays after the last surface (the DOE's first order applied as a local grating).

    Returns ``pos`` (S, N, 3) on the wave plane (mm), unit ``dir`` (S, N, 3), ``valid`` (S, N),
    ``weight`` (S, N), image index ``n``. ``doe_bending``: ``"full"`` (phase gradient; continuous
    profiles only), ``"paraxial"`` (the profile's quadratic term: discontinuous profiles) or
    ``"none"``."""
    from .trace import Tracer
    from . import doe
    plane = lens.wave_plane_index()
    tr = Tracer(lens, [wavelength_um], device=device)
    src = tr.sources(fields, 0, object_distance=object_distance_mm)
    rays = tr._run(src, np.asarray(u, float), np.asarray(v, float), 1.0, upto=plane + 1)
    S, N = len(fields), len(u)
    pos = rays.pos.numpy().reshape(S, N, 3)
    dr = rays.dir.numpy().reshape(S, N, 3)
    valid = rays.valid.numpy().reshape(S, N).astype(bool)
    weight = rays.weight.numpy().reshape(S, N)
    n_pl = float(lens.indices(wavelength_um)[plane])
    s = lens.surfaces[plane]
    if s.type == "doe" and doe_bending != "none":
        prof = doe.profile_from_dict(s.profile, base=None if lens.source is None else
                                     __import__("pathlib").Path(lens.source).parent)
        continuous = prof.is_continuous and not s.levels
        lam = wavelength_um * 1e-3
        for k in range(S):
            if continuous and doe_bending == "full":
                gx, gy = prof.gradient(pos[k, :, 0], pos[k, :, 1], s.design_wavelength_um)
            else:
                a2 = prof.quadratic_coefficient(s.design_wavelength_um)
                gx, gy = 2 * a2 * pos[k, :, 0], 2 * a2 * pos[k, :, 1]
            tx = n_pl * dr[k, :, 0] + lam * gx / (2 * np.pi)
            ty = n_pl * dr[k, :, 1] + lam * gy / (2 * np.pi)
            tz2 = n_pl ** 2 - tx ** 2 - ty ** 2
            valid[k] &= tz2 > 0
            d = np.stack([tx, ty, np.sqrt(np.maximum(tz2, 1e-30))], -1)
            dr[k] = d / np.linalg.norm(d, axis=1, keepdims=True)
    return pos, dr, valid, weight, n_pl


def image_space_na(lens, field_deg=0.0, wavelength_um: float = 0.55, grid: int = 33, device: str = "cpu") -> float:
    """Image-space numerical aperture ``n sin(theta)`` of the converging beam (half the spread of its
    direction sines about their mean, largest over x and y) for one field, from a ray trace."""
    from .trace import pupil_grid
    shape = lens.surfaces[lens.stop_index].shape
    u, v, _ = pupil_grid(grid, shape, layout="edges")
    _, d, ok, _, n = _image_space_rays(lens, [field_deg], wavelength_um, u, v, device=device)
    d = d[0, ok[0], :2]
    if len(d) < 3:
        raise LensError("no rays reach the image space for this field", file=lens.source, field=field_deg)
    return float(n * 0.5 * np.max(d.max(0) - d.min(0)))


def default_sampling_mm(lens, fields, wavelengths_um, device="cpu") -> float:
    """Default PSF sampling pitch for the wave figures, mm: ``lambda_min / (5 NA)`` (the intensity's
    band limit ``2 NA / lambda`` sampled 2.5x above its Nyquist rate), NA the largest over the fields,
    and never coarser than the lens's sensor pixel."""
    na = max(image_space_na(lens, f, min(wavelengths_um), device=device) for f in fields)
    return min(float(lens.sensor.pixel_pitch), min(wavelengths_um) * 1e-3 / (5.0 * max(na, 1e-6)))


def patch_size_for(lens, fields, wavelengths_um, pixel_mm, cap: int = 256, device: str = "cpu") -> int:
    """PSF patch size (samples of ``pixel_mm`` mm, a multiple of 8 in 32..``cap``) that holds every
    (field, wavelength) PSF: twice the farthest ray of a 31 x 31 pupil grid from the chief ray, plus
    10 Airy radii of diffraction (an aberration-free PSF keeps ~98.5 % of its power), plus 10 %."""
    from .trace import Tracer, pupil_grid
    shape = lens.surfaces[lens.stop_index].shape
    u, v, _ = pupil_grid(31, shape, layout="edges")
    u, v = np.concatenate([[0.0], u]), np.concatenate([[0.0], v])
    need = 0.0  # half width of the patch, mm
    for w in wavelengths_um:
        r = Tracer(lens, [w], device=device).trace(list(fields), pupil=(u, v, 1.0)).numpy()
        for k, f in enumerate(fields):
            ok = r["valid"][k]
            if ok.sum() < 2:
                continue
            ref = r["pos"][k, 0, :2] if ok[0] else r["pos"][k, ok, :2].mean(0)
            geo = float(np.max(np.hypot(*(r["pos"][k, ok, :2] - ref).T)))
            airy = 0.61 * w * 1e-3 / max(image_space_na(lens, f, w, device=device), 1e-6)
            need = max(need, geo + 10.0 * airy)
    n = int(math.ceil(1.1 * 2.0 * need / pixel_mm))
    return int(min(max(32, 8 * math.ceil(n / 8)), cap))


def _as_wavelengths(wavelength_um, weights):
    wls = [float(w) for w in np.atleast_1d(np.asarray(wavelength_um, dtype=float))]
    if not wls:
        raise ValueError("wavelength_um must hold at least one wavelength (um)")
    for w in wls:
        if not (0.2 <= w <= 20.0):
            raise ValueError(f"wavelength_um {w} outside 0.2..20 um (wavelengths are in micrometres)")
    if weights is None:
        wt = np.ones(len(wls))
    else:
        wt = np.asarray(weights, dtype=float).ravel()
        if wt.shape != (len(wls),) or np.any(wt < 0) or not wt.sum() > 0 or not np.all(np.isfinite(wt)):
            raise ValueError(f"weights must be {len(wls)} non-negative numbers (one per wavelength), not all 0; "
                             f"got {weights!r}")
    return wls, wt / wt.sum()


def _as_fields(field_deg):
    from .trace import as_field_list
    fields = as_field_list(field_deg)
    if not fields:
        raise ValueError("field_deg must hold at least one field (deg)")
    scalar = np.ndim(field_deg) == 0 or isinstance(field_deg, tuple)
    return fields, scalar


def _check_model(model):
    if model not in MODELS:
        raise ValueError(f"model must be one of {MODELS}, got {model!r}")


def _field_direction_on_sensor(f):
    """Unit (x, y) of the tangential direction for a field (deg): along the field vector, y on axis."""
    fx, fy = (0.0, float(f)) if np.ndim(f) == 0 else (float(f[0]), float(f[1]))
    r = math.hypot(fx, fy)
    return (0.0, 1.0) if r == 0 else (fx / r, fy / r)


def _psfs(lens, fields, wls, model, size, pixel_mm, device, psf_kwargs):
    from .psf import psf_map
    if isinstance(size, str):
        if size != "auto":
            raise ValueError(f"size must be a number of samples or 'auto', got {size!r}")
        size = patch_size_for(lens, fields, wls, pixel_mm, 256, device)
    if int(size) < 8:
        raise ValueError(f"size must be >= 8 pixels, got {size}")
    return psf_map(lens, fields, wls, model=model, size=int(size), pixel_mm=pixel_mm, device=device, **psf_kwargs)


def _patch_check(m, what):
    """Fraction of each PSF's power (that reaches the sensor) inside its patch; warn when < 0.98."""
    vf = np.asarray(m.info.get("valid_fraction"), dtype=float).reshape(m.data.shape[:2])
    inside = m.data.sum(axis=(2, 3)) / np.maximum(vf, 1e-300)
    if np.any(inside < 0.98):
        i, j = np.unravel_index(int(np.argmin(inside)), inside.shape)
        warnings.warn(f"{what}: the PSF patch keeps only {inside[i, j]:.3f} of the power for field "
                      f"{m.fields_deg[i]} deg at {m.wavelengths_um[j]} um; pass a larger size (pixels) so the "
                      "figure is not biased", SamplingWarning, stacklevel=3)
    return inside, vf


# ============================================================================== MTF
@dataclass
class MTF:
    """MTF curves: ``tangential`` and ``sagittal`` of shape (n_fields, n_frequencies) (or
    (n_frequencies,) for a single field given as a number), at ``frequencies_lp_mm`` (lp/mm).
    ``cutoff_lp_mm``: the diffraction cutoff ``2 NA / lambda`` of the shortest wavelength.
    ``info``: sampling pitch (mm), patch size, the power fraction inside each patch."""

    frequencies_lp_mm: np.ndarray
    tangential: np.ndarray
    sagittal: np.ndarray
    fields_deg: list
    wavelengths_um: list
    weights: np.ndarray
    model: str
    include_pixel: bool
    cutoff_lp_mm: float
    info: dict = field(default_factory=dict)


def _poly_mtf(m, weights, freqs, include_pixel, sensor_pixel, normalize="patch"):
    nf = len(m.fields_deg)
    vf = np.asarray(m.info.get("valid_fraction"), dtype=float).reshape(m.data.shape[:2])
    tan = np.zeros((nf, len(freqs)))
    sag = np.zeros((nf, len(freqs)))
    for i in range(nf):
        t = _field_direction_on_sensor(m.fields_deg[i])
        s = (t[1], -t[0])
        ot = np.zeros(len(freqs), complex)
        os_ = np.zeros(len(freqs), complex)
        for j, w in enumerate(weights):
            if w == 0:
                continue
            c = tuple(m.centers_mm[i, j])
            # "sensor": the patch's power over all the power reaching the sensor (tails cut by the patch
            # then lower only the lowest frequencies instead of offsetting the whole curve)
            sc = m.data[i, j].sum() / vf[i, j] if normalize == "sensor" else 1.0
            ot += w * sc * otf_from_psf(m.data[i, j], m.pixel_mm, freqs, t, c)
            os_ += w * sc * otf_from_psf(m.data[i, j], m.pixel_mm, freqs, s, c)
        tan[i], sag[i] = np.abs(ot), np.abs(os_)
    if include_pixel:
        pm = pixel_mtf(freqs, sensor_pixel)
        tan, sag = tan * pm, sag * pm
    return tan, sag


def mtf_from_psf_map(m, frequencies_lp_mm, weights=None, include_pixel: bool = False, sensor_pixel_mm=None,
                     normalize: str = "patch"):
    """Tangential and sagittal MTF, each (n_fields, n_frequencies), of a :class:`rwwarp.PSFMap` ``m``
    (polychromatic over its wavelengths with ``weights``, default equal); frequencies in lp/mm.
    ``include_pixel`` multiplies by ``|sinc(f sensor_pixel_mm)|``. See :func:`mtf`."""
    if normalize not in ("patch", "sensor"):
        raise ValueError(f"normalize must be 'patch' or 'sensor', got {normalize!r}")
    _, wt = _as_wavelengths(m.wavelengths_um, weights)
    freqs = np.atleast_1d(np.asarray(frequencies_lp_mm, dtype=float))
    if include_pixel and sensor_pixel_mm is None:
        raise ValueError("include_pixel needs sensor_pixel_mm (mm)")
    return _poly_mtf(m, wt, freqs, include_pixel, sensor_pixel_mm, normalize)


def mtf(lens, field_deg=0.0, wavelength_um=0.55, weights=None, frequencies_lp_mm=None, model: str = "ray-wave",
        include_pixel: bool = False, size="auto", pixel_mm=None, device: str = "cpu", normalize: str = "patch",
        **psf_kwargs) -> MTF:
    """Diffraction MTF (tangential and sagittal) from the PSF, for one or several fields.

    Parameters
    ----------
    lens : Lens
    field_deg : float, (x, y) or list of them
        Field angles, degrees (batched like :func:`rwwarp.psf_map`).
    wavelength_um : float or list
        Wavelength(s), um; several give the polychromatic MTF with ``weights`` (default equal).
    frequencies_lp_mm : array, optional
        Frequencies, lp/mm; default 51 points from 0 to the diffraction cutoff ``2 NA / lambda_min``.
    model : "ray-wave" | "ray" | "paraxial-wave"
    include_pixel : bool
        Multiply by the sensor pixel's MTF ``|sinc(f p)|`` (p = ``lens.sensor.pixel_pitch``).
    size : int or "auto"
        PSF patch size in samples; the patch must hold the PSF (a :class:`SamplingWarning` says when
        less than 98 % of the power is inside). ``"auto"``: :func:`patch_size_for` (at most 256).
    pixel_mm : float, optional
        PSF sampling pitch, mm; default :func:`default_sampling_mm` (finer than the sensor pixel).
    normalize : "patch" | "sensor"
        Divide the OTF by the power inside the patch (MTF(0) = 1, as Zemax's FFT MTF) or by all the power
        reaching the sensor (MTF(0) = the fraction inside the patch; PSF tails cut by a small patch then
        bias only the lowest frequencies: an F/10 Airy pattern on 256 x 2 um samples is within 3.2e-4 of
        the diffraction formula above f = 0 with "sensor" (the F/10 beam's own non-paraxial pupil
        apodisation; 6.8e-5 at F/40 on 256 x 10 um samples), 8e-3 with "patch").
    psf_kwargs
        Passed to :func:`rwwarp.psf_map` (``plan``, ``object_distance_mm``, ...).
    """
    _check_model(model)
    if normalize not in ("patch", "sensor"):
        raise ValueError(f"normalize must be 'patch' or 'sensor', got {normalize!r}")
    fields, scalar = _as_fields(field_deg)
    wls, wt = _as_wavelengths(wavelength_um, weights)
    na = max(image_space_na(lens, f, min(wls), device=device) for f in fields)
    cutoff = 2.0 * na / (min(wls) * 1e-3)
    if frequencies_lp_mm is None:
        freqs = np.linspace(0.0, cutoff, 51)
    else:
        freqs = np.atleast_1d(np.asarray(frequencies_lp_mm, dtype=float))
        if freqs.ndim != 1 or np.any(freqs < 0) or not np.all(np.isfinite(freqs)):
            raise ValueError(f"frequencies_lp_mm must be a 1-D array of non-negative lp/mm, got {frequencies_lp_mm!r}")
    pixel = _check_positive(pixel_mm, "pixel_mm") if pixel_mm is not None else \
        min(float(lens.sensor.pixel_pitch), min(wls) * 1e-3 / (5.0 * max(na, 1e-6)))
    if np.max(freqs, initial=0.0) * pixel >= 0.5:
        warnings.warn(f"frequencies up to {np.max(freqs):.4g} lp/mm reach the Nyquist limit of the PSF "
                      f"sampling ({0.5 / pixel:.4g} lp/mm); pass a smaller pixel_mm", SamplingWarning, stacklevel=2)
    m = _psfs(lens, fields, wls, model, size, pixel, device, psf_kwargs)
    inside, _ = _patch_check(m, "mtf")
    tan, sag = _poly_mtf(m, wt, freqs, include_pixel, lens.sensor.pixel_pitch, normalize)
    if scalar:
        tan, sag = tan[0], sag[0]
    return MTF(freqs, tan, sag, fields, wls, wt, model, include_pixel, cutoff,
               {"pixel_mm": pixel, "size": int(m.data.shape[-1]), "power_in_patch": inside, "psf_map": m})


@dataclass
class ThroughFocusMTF:
    """Through-focus MTF: ``tangential`` / ``sagittal`` of shape (n_fields, n_focus, n_frequencies)
    (the field axis dropped for a single field given as a number) at sensor shifts ``focus_mm`` (mm,
    + away from the lens) and ``frequencies_lp_mm``."""

    focus_mm: np.ndarray
    frequencies_lp_mm: np.ndarray
    tangential: np.ndarray
    sagittal: np.ndarray
    fields_deg: list
    wavelengths_um: list
    model: str
    info: dict = field(default_factory=dict)


def through_focus_mtf(lens, field_deg=0.0, wavelength_um=0.55, weights=None, frequencies_lp_mm=None,
                      focus_mm=None, model: str = "ray-wave", include_pixel: bool = False, size: int = 128,
                      pixel_mm=None, device: str = "cpu", progress: bool = False, normalize: str = "patch",
                      **psf_kwargs) -> ThroughFocusMTF:
    """MTF at chosen frequencies as the sensor moves through focus.

    ``focus_mm``: sensor shifts (mm, + away from the lens); default 21 shifts over +- 4 lambda F#^2
    (about +- 2 depths of focus, ``F# = 1 / (2 NA)``). ``frequencies_lp_mm``: default a quarter and
    a half of the diffraction cutoff. Other arguments as :func:`mtf`; ``progress`` shows a bar.
    """
    _check_model(model)
    fields, scalar = _as_fields(field_deg)
    wls, wt = _as_wavelengths(wavelength_um, weights)
    na = max(image_space_na(lens, f, min(wls), device=device) for f in fields)
    cutoff = 2.0 * na / (min(wls) * 1e-3)
    if frequencies_lp_mm is None:
        frequencies_lp_mm = [0.25 * cutoff, 0.5 * cutoff]
    if focus_mm is None:
        fno = 1.0 / (2.0 * max(na, 1e-6))
        dof = 4.0 * float(np.mean(wls)) * 1e-3 * fno * fno
        focus_mm = np.linspace(-dof, dof, 21)
    focus = np.atleast_1d(np.asarray(focus_mm, dtype=float))
    t_last = lens.surfaces[-1].thickness
    if np.any(t_last + focus <= 0):
        raise ValueError(f"focus_mm moves the sensor onto or in front of the last surface (its distance is {t_last} mm)")
    it = focus
    if progress:
        from tqdm.auto import tqdm
        it = tqdm(focus, desc="through focus", unit="plane")
    tan, sag, inside = [], [], []
    for dz in it:
        moved = lens.with_surface(len(lens.surfaces) - 1, thickness=t_last + float(dz))
        with warnings.catch_warnings(record=True) as rec:
            warnings.simplefilter("always")
            r = mtf(moved, fields, wls, wt, frequencies_lp_mm, model, include_pixel, size, pixel_mm, device,
                    normalize, **psf_kwargs)
        for w in rec:  # patch and sampling warnings are summed up once below
            if not issubclass(w.category, (SamplingWarning, PatchWarning)):
                warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
        tan.append(r.tangential)
        sag.append(r.sagittal)
        inside.append(r.info["power_in_patch"])
    tan, sag = np.stack(tan, 1), np.stack(sag, 1)  # (n_fields, n_focus, n_freq)
    inside = np.stack(inside, 0)
    if np.any(inside < 0.98):
        warnings.warn(f"through_focus_mtf: some defocused PSFs keep only {inside.min():.3f} of their power in the "
                      "patch; pass a larger size", SamplingWarning, stacklevel=2)
    if scalar:
        tan, sag = tan[0], sag[0]
    return ThroughFocusMTF(focus, r.frequencies_lp_mm, tan, sag, fields, wls, model,
                           {"power_in_patch": inside, "pixel_mm": r.info["pixel_mm"]})


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
                from .psf import paraxial_equivalent
                eq, eqf = paraxial_equivalent(lens, [f], [w], object_distance_mm)
                ideal[i, j] = vf[i, j] * ideal_peak_intensity(eq, eqf[0], w, pt, grid, device, per="passing")
            else:
                ideal[i, j] = vf[i, j] * ideal_peak_intensity(lens, f, w, pt, grid, device, object_distance_mm,
                                                              per="passing")
            peak[i, j] = pk
            ratio[i, j] = pk / ideal[i, j]
    return ratio, peak, ideal


# ============================================================================== encircled / ensquared energy
@dataclass
class EnergyCurve:
    """Encircled (``kind="encircled"``, ``size_um`` = radius) or ensquared (``"ensquared"``, ``size_um``
    = half width) energy: ``fraction`` of the power reaching the sensor, shape (n_fields, n_sizes)
    (field axis dropped for a single field given as a number)."""

    size_um: np.ndarray
    fraction: np.ndarray
    kind: str
    fields_deg: list
    wavelengths_um: list
    model: str
    info: dict = field(default_factory=dict)


def _energy(kind, lens, field_deg, wavelength_um, weights, sizes_um, model, reference, size, pixel_mm, device,
            psf_kwargs):
    _check_model(model)
    if reference not in ("centroid", "chief"):
        raise ValueError(f"reference must be 'centroid' or 'chief', got {reference!r}")
    fields, scalar = _as_fields(field_deg)
    wls, wt = _as_wavelengths(wavelength_um, weights)
    pixel = _check_positive(pixel_mm, "pixel_mm") if pixel_mm is not None else \
        (float(lens.sensor.pixel_pitch) if model == "ray" else default_sampling_mm(lens, fields, wls, device))
    if sizes_um is not None:
        chk = np.atleast_1d(np.asarray(sizes_um, dtype=float))
        if chk.ndim != 1 or np.any(chk < 0) or not np.all(np.isfinite(chk)):
            raise ValueError(f"{'radii_um' if kind == 'encircled' else 'half_widths_um'} must be a 1-D array of "
                             f"non-negative um, got {sizes_um!r}")
    m = _psfs(lens, fields, wls, model, size, pixel, device, psf_kwargs)
    _patch_check(m, kind + "_energy")
    if sizes_um is None:
        sizes_um = np.linspace(0.0, 0.5 * m.data.shape[-1] * pixel * 1e3, 41)
    sz = np.atleast_1d(np.asarray(sizes_um, dtype=float))
    out = energy_from_psf_map(m, sz, kind, wt, reference)
    if scalar:
        out = out[0]
    return EnergyCurve(sz, out, kind, fields, wls, model, {"pixel_mm": pixel, "psf_map": m})


def energy_from_psf_map(m, sizes_um, kind: str = "encircled", weights=None, reference: str = "centroid"):
    """Encircled (``sizes_um`` = radii) or ensquared (half widths) energy, (n_fields, n_sizes), of a
    :class:`rwwarp.PSFMap`, as fractions of the power reaching the sensor; polychromatic with
    ``weights``; about the centroid or the chief ray (``reference``). See :func:`encircled_energy`."""
    if kind not in ("encircled", "ensquared"):
        raise ValueError(f"kind must be 'encircled' or 'ensquared', got {kind!r}")
    if reference not in ("centroid", "chief"):
        raise ValueError(f"reference must be 'centroid' or 'chief', got {reference!r}")
    fields, wls = m.fields_deg, m.wavelengths_um
    _, wt = _as_wavelengths(wls, weights)
    vf = np.asarray(m.info["valid_fraction"], float).reshape(len(fields), len(wls))
    sz = np.atleast_1d(np.asarray(sizes_um, dtype=float))
    if sz.ndim != 1 or np.any(sz < 0):
        raise ValueError(f"{'radii_um' if kind == 'encircled' else 'half_widths_um'} must be a 1-D array of "
                         f"non-negative um, got {sizes_um!r}")
    out = np.zeros((len(fields), len(sz)))
    fn = encircled_energy_from_psf if kind == "encircled" else ensquared_energy_from_psf
    for i in range(len(fields)):
        # polychromatic: each wavelength's PSF normalised to the power reaching the sensor, on a common grid
        ref = m.centers_mm[i, int(np.argmax(wt))]
        acc = np.zeros(m.data.shape[2:])
        for j in range(len(wls)):
            if wt[j] == 0:
                continue
            shift = np.round((m.centers_mm[i, j] - ref) / m.pixel_mm).astype(int)
            acc += wt[j] * _shift_patch(m.data[i, j] / vf[i, j], shift[0], shift[1])
        if reference == "centroid":
            c = None
        else:  # chief ray of the primary (heaviest) wavelength: the patch centre is where it lands
            c = (0.0, 0.0)
        out[i] = fn(acc, m.pixel_mm, sz * 1e-3, total=1.0, center_rel_mm=c)
    return out


def _shift_patch(a, sx, sy):
    """Shift a patch by whole samples (sx along x, sy along y), zero filled."""
    out = np.zeros_like(a)
    n = a.shape[0]
    ys, yd = (slice(0, n - sy), slice(sy, n)) if sy >= 0 else (slice(-sy, n), slice(0, n + sy))
    xs, xd = (slice(0, n - sx), slice(sx, n)) if sx >= 0 else (slice(-sx, n), slice(0, n + sx))
    out[yd, xd] = a[ys, xs]
    return out


def encircled_energy(lens, field_deg=0.0, wavelength_um=0.55, weights=None, radii_um=None, model: str = "ray-wave",
                     reference: str = "centroid", size="auto", pixel_mm=None, device: str = "cpu",
                     **psf_kwargs) -> EnergyCurve:
    """Encircled energy: fraction of the power reaching the sensor inside circles of ``radii_um`` (um,
    default 41 radii up to half the patch) about the PSF centroid (``reference="centroid"``) or the
    chief ray (``"chief"``). Polychromatic with ``weights``; batched over fields. ``pixel_mm``: PSF
    sampling pitch (mm), default :func:`default_sampling_mm` (the sensor pixel for ``model="ray"``);
    ``size``: samples per side or ``"auto"`` (:func:`patch_size_for`)."""
    return _energy("encircled", lens, field_deg, wavelength_um, weights, radii_um, model, reference, size,
                   pixel_mm, device, psf_kwargs)


def ensquared_energy(lens, field_deg=0.0, wavelength_um=0.55, weights=None, half_widths_um=None,
                     model: str = "ray-wave", reference: str = "centroid", size="auto", pixel_mm=None,
                     device: str = "cpu", **psf_kwargs) -> EnergyCurve:
    """Ensquared energy: fraction of the power reaching the sensor inside axis-aligned squares of half
    width ``half_widths_um`` (um); otherwise as :func:`encircled_energy`."""
    return _energy("ensquared", lens, field_deg, wavelength_um, weights, half_widths_um, model, reference, size,
                   pixel_mm, device, psf_kwargs)


# ============================================================================== ray-based curves
@dataclass
class ChromaticFocalShift:
    """Paraxial focal shift ``shift_um`` (um; + away from the lens) of the image of the lens's object
    at each of ``wavelengths_um``, relative to ``reference_um``."""

    wavelengths_um: np.ndarray
    shift_um: np.ndarray
    reference_um: float


def paraxial_image_distance(lens, wavelength_um: float, object_distance_mm=None) -> float:
    """Paraxial image distance behind the last surface (mm) of an axial object at the lens's object
    distance (or ``object_distance_mm``, mm from the first vertex; inf allowed), at ``wavelength_um``."""
    from .paraxial import ynu_trace
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


def field_curves(lens, fields_deg=None, wavelength_um=None, eps: float = 1e-3, device: str = "cpu") -> FieldCurves:
    """Field curvature (tangential and sagittal focus vs field) and F-tan(theta) distortion, for y
    fields ``fields_deg`` (deg; default 21 from 0 to the largest of ``lens.fields_deg``, else 10 deg)
    at ``wavelength_um`` (um; default the lens's middle wavelength).

    Foci from pairs of rays at pupil offsets ``+-eps`` (normalised pupil units) about the chief ray,
    in y (tangential) and x (sagittal): where their separation along that axis vanishes. The DOE's
    first order is applied as a local grating. Distortion compares the real chief ray's height on the
    sensor with the paraxial chief ray's (y-nu trace through the entrance-pupil centre)."""
    from .paraxial import pupils, ynu_trace
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
