"""The PSFs behind the figures of merit (:mod:`rwwarp.metrics`): their sampling and the shared argument checks.

* :func:`default_sampling_mm`: the PSF pitch that resolves the intensity, ``lambda / (4 NA)`` below the Nyquist
  rate, from the image-space NA of traced rays (:func:`image_space_na`, :func:`_image_space_rays`);
* :func:`patch_size_for`: a patch wide enough for the spot plus a diffraction margin;
* ``_psfs``: the PSF map of the requested model that every wave figure starts from, ``_patch_check`` its
  patch-power warning; argument checks of PSF arrays, fields, wavelengths and weights.

Units and conventions: :mod:`rwwarp.metrics`.
"""
from __future__ import annotations

import math
import warnings

import numpy as np

from ..errors import LensError, SamplingWarning


MODELS = ("ray-wave", "ray", "paraxial-wave")


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


# ============================================================================== lens helpers
def _image_space_rays(lens, fields, wavelength_um, u, v, object_distance_mm=None, device="cpu",
                      doe_bending: str = "full"):
    """Rays after the last surface (the DOE's first order applied as a local grating).

    Returns ``pos`` (S, N, 3) on the wave plane (mm), unit ``dir`` (S, N, 3), ``valid`` (S, N),
    ``weight`` (S, N), image index ``n``. ``doe_bending``: ``"full"`` (phase gradient; continuous
    profiles only), ``"paraxial"`` (the profile's quadratic term: discontinuous profiles) or
    ``"none"``."""
    from ..trace import Tracer
    from .. import doe
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
    from ..trace import pupil_grid
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
    from ..trace import Tracer, pupil_grid
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
    from ..trace import as_field_list
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
    from ..psf import psf_map
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
