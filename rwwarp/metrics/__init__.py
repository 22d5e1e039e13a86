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

Where each figure lives: the MTF and through-focus MTF here; :mod:`rwwarp.metrics.energy` (encircled / ensquared
energy), :mod:`rwwarp.metrics.strehl` (Strehl ratio, ideal peak), :mod:`rwwarp.metrics.curves` (chromatic focal
shift, field curves), :mod:`rwwarp.metrics.sampling` (PSF sampling and patch size, image-space NA). Every public
name is importable from this module.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np

from ..errors import PatchWarning, SamplingWarning
from .curves import (
    ChromaticFocalShift, FieldCurves, chromatic_focal_shift, field_curves, paraxial_image_distance,
)
from .energy import (
    EnergyCurve, encircled_energy, encircled_energy_from_psf, energy_from_psf_map, ensquared_energy,
    ensquared_energy_from_psf,
)
from .sampling import MODELS, _image_space_rays  # noqa: F401  (here before the split; still imported)
from .sampling import (
    default_sampling_mm, image_space_na, patch_size_for, _as_fields,
    _as_wavelengths, _check_model, _check_positive, _check_psf_array, _field_direction_on_sensor,
    _patch_check, _patch_coords, _psfs,
)
from .strehl import Strehl, ideal_peak_intensity, peak_intensity_from_psf, strehl, strehl_from_psf_map

__all__ = ["MTF", "ThroughFocusMTF", "Strehl", "EnergyCurve", "FieldCurves", "ChromaticFocalShift",
           "mtf", "through_focus_mtf", "strehl", "encircled_energy", "ensquared_energy",
           "chromatic_focal_shift", "field_curves", "otf_from_psf", "encircled_energy_from_psf",
           "ensquared_energy_from_psf", "peak_intensity_from_psf", "pixel_mtf", "default_sampling_mm",
           "image_space_na", "diffraction_mtf_circular", "mtf_from_psf_map", "energy_from_psf_map",
           "ideal_peak_intensity", "paraxial_image_distance", "strehl_from_psf_map", "patch_size_for", "tail_otf",
           "BestFocus", "best_focus"]


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

    def __repr__(self):
        from ..results import mtf_repr
        return mtf_repr(self)

    def plot(self, path=None, ax=None):
        """A picture (rwwarp.results); returns the Axes, or the Figure saved to ``path`` (PNG)."""
        from ..results import plot_mtf
        return plot_mtf(self, path=path, ax=ax)


def tail_otf(frequencies_lp_mm, half_width_mm, n_angles: int = 2048):
    """Transfer function of the power a square patch cuts off, modelled as a diffraction tail.

    The far tail of the PSF of a pupil with a hard edge falls as ``r^-3`` (the Airy pattern's, averaged
    over its rings; aberrations change its strength, not the power law); this is the OTF (real, 1 at f = 0)
    of a rotationally symmetric density ``r^-3`` outside the square ``|x|, |y| <= half_width_mm`` (mm)
    at spatial frequencies ``frequencies_lp_mm`` (lp/mm; only ``|f|`` matters). In polar coordinates
    ``T(f) = C sum_theta int_{r0(theta)}^inf cos(k r) r^-2 dr``, ``k = 2 pi f |sin theta|``, with
    ``int_{r0}^inf cos(k r) / r^2 dr = cos(k r0) / r0 - k (pi/2 - Si(k r0))``; ``n_angles`` angles."""
    from scipy.special import sici
    f = np.abs(np.atleast_1d(np.asarray(frequencies_lp_mm, dtype=np.float64)))
    th = (np.arange(int(n_angles)) + 0.5) * (2.0 * np.pi / int(n_angles))
    r0 = float(half_width_mm) / np.maximum(np.abs(np.cos(th)), np.abs(np.sin(th)))
    k = 2.0 * np.pi * f[:, None] * np.abs(np.sin(th))[None, :]
    si, _ = sici(k * r0)
    g = np.cos(k * r0) / r0 - k * (0.5 * np.pi - si)
    return g.mean(axis=1) / np.mean(1.0 / r0)


NORMALIZE = ("tail", "sensor", "patch")


def _poly_mtf(m, weights, freqs, include_pixel, sensor_pixel, normalize="tail"):
    nf = len(m.fields_deg)
    vfi = m.info.get("valid_fraction") if isinstance(m.info, dict) else None
    if vfi is None:  # without the power reaching the sensor only the patch can normalise
        normalize = "patch"
    else:
        vf = np.asarray(vfi, dtype=float).reshape(m.data.shape[:2])
    n, p = m.data.shape[-1], float(m.pixel_mm)
    tail = tail_otf(freqs, 0.5 * n * p) if normalize == "tail" else None
    # the patch's geometric centre (samples at (i - n // 2) p, each a box of p): where the tail is centred
    g_off = ((n - 1) / 2.0 - n // 2) * p
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
            # "tail": as "sensor", the power cut by the patch added back as an r^-3 diffraction tail
            # (tail_otf) about the patch centre, so MTF(0) = 1 and the cut does not ripple the low frequencies
            sp = m.data[i, j].sum()
            sc = sp / vf[i, j] if normalize in ("sensor", "tail") and vf[i, j] > 0 else 1.0
            ot += w * sc * otf_from_psf(m.data[i, j], m.pixel_mm, freqs, t, c)
            os_ += w * sc * otf_from_psf(m.data[i, j], m.pixel_mm, freqs, s, c)
            if tail is not None and vf[i, j] > 0 and sp > 0:
                cut = max(vf[i, j] - sp, 0.0) / vf[i, j]  # fraction of the sensor's power outside the patch
                cg = np.array(c, float) + g_off
                for acc, dd in ((ot, t), (os_, s)):
                    acc += w * cut * tail * np.exp(-2j * np.pi * freqs * (dd[0] * cg[0] + dd[1] * cg[1]))
        tan[i], sag[i] = np.abs(ot), np.abs(os_)
    if include_pixel:
        pm = pixel_mtf(freqs, sensor_pixel)
        tan, sag = tan * pm, sag * pm
    return tan, sag


def mtf_from_psf_map(m, frequencies_lp_mm, weights=None, include_pixel: bool = False, sensor_pixel_mm=None,
                     normalize: str = "tail"):
    """Tangential and sagittal MTF, each (n_fields, n_frequencies), of a :class:`rwwarp.PSFMap` ``m``
    (polychromatic over its wavelengths with ``weights``, default equal); frequencies in lp/mm.
    ``include_pixel`` multiplies by ``|sinc(f sensor_pixel_mm)|``. See :func:`mtf`."""
    if normalize not in NORMALIZE:
        raise ValueError(f"normalize must be one of {NORMALIZE}, got {normalize!r}")
    _, wt = _as_wavelengths(m.wavelengths_um, weights)
    freqs = np.atleast_1d(np.asarray(frequencies_lp_mm, dtype=float))
    if include_pixel and sensor_pixel_mm is None:
        raise ValueError("include_pixel needs sensor_pixel_mm (mm)")
    return _poly_mtf(m, wt, freqs, include_pixel, sensor_pixel_mm, normalize)


def mtf(lens, field_deg=0.0, wavelength_um=0.55, weights=None, frequencies_lp_mm=None, model: str = "ray-wave",
        include_pixel: bool = False, size="auto", pixel_mm=None, device: str = "cpu", normalize: str = "tail",
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
    normalize : "tail" | "sensor" | "patch"
        ``"tail"`` (default): divide the OTF by all the power reaching the sensor and add back the power the
        patch cuts off as an ``r^-3`` diffraction tail about the patch centre (:func:`tail_otf`), so MTF(0) = 1
        and the cut neither offsets nor ripples the curve: an ideal F/10 lens (f = 5 mm, 0.55 um) with every
        default (152 x 1 um samples, 98.6 % of the power inside) is within 4.2e-4 of the diffraction formula
        (1.4e-2 with "patch", 1.4e-3 above f = 0 with "sensor"; 3e-4 of it is the F/10 beam's own non-paraxial
        pupil apodisation, the rest the PSF plan's sampling). ``"sensor"``: the same without the tail
        (MTF(0) = the fraction inside the patch). ``"patch"``: divide by the power inside the patch (MTF(0) = 1,
        but a patch that cuts 1 % of the power lowers every frequency by about 1 %). With the ``"ray"`` model
        the cut power is geometric (rays outside the patch), not a diffraction tail: the tail then only
        approximates it; a :class:`SamplingWarning` says when a patch keeps < 98 % of the power.
    psf_kwargs
        Passed to :func:`rwwarp.psf_map` (``plan``, ``object_distance_mm``, ...). ``rays_per_sample`` defaults to
        1.5 here (1.0 for a PSF): the MTF is read to 1e-4 where a PSF's peak is not, and the ray density is what
        the default plan's sampling error follows (the ideal F/10 lens: 5.5e-4 from the formula at 1.0, 4.2e-4
        at 1.5, 3.9e-4 at 3.0; the Cooke triplet's two-field MTF takes 1.5 -> ~2 s on 2 cores).
    """
    _check_model(model)
    if model == "ray-wave":
        psf_kwargs.setdefault("rays_per_sample", 1.5)
    if normalize not in NORMALIZE:
        raise ValueError(f"normalize must be one of {NORMALIZE}, got {normalize!r}")
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

    def __repr__(self):
        from ..results import through_focus_repr
        return through_focus_repr(self)

    def plot(self, path=None, ax=None):
        """A picture (rwwarp.results); returns the Axes, or the Figure saved to ``path`` (PNG)."""
        from ..results import plot_through_focus
        return plot_through_focus(self, path=path, ax=ax)


def through_focus_mtf(lens, field_deg=0.0, wavelength_um=0.55, weights=None, frequencies_lp_mm=None,
                      focus_mm=None, model: str = "ray-wave", include_pixel: bool = False, size: int = 128,
                      pixel_mm=None, device: str = "cpu", progress: bool = False, normalize: str = "tail",
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


@dataclass
class BestFocus:
    """Best focus of one field: ``focus_mm`` (sensor shift, mm, + away from the lens) where the mean of the
    tangential and sagittal MTF at ``frequency_lp_mm`` (the first frequency of the scan) peaks (a parabola through the best scanned plane and its
    two neighbours); ``scan``: the :class:`ThroughFocusMTF` of every plane scanned (sorted by focus),
    ``merit``: that mean per plane, ``step_mm``: the plane spacing, ``interior``: the peak has at least one
    scanned plane on each side (``False`` only where ``max_planes`` stopped the extension)."""

    focus_mm: float
    frequency_lp_mm: float
    scan: ThroughFocusMTF
    merit: np.ndarray
    step_mm: float
    interior: bool


def best_focus(lens, field_deg=0.0, wavelength_um=0.55, frequency_lp_mm=None, focus_mm=None, model: str = "ray-wave",
               weights=None, size: int = 128, pixel_mm=None, device: str = "cpu", max_planes: int = 41,
               **psf_kwargs) -> BestFocus:
    """Best focus (sensor shift, mm) of one field (deg) at ``wavelength_um`` (um; a list: polychromatic with
    ``weights``): the peak of the mean tangential / sagittal MTF at ``frequency_lp_mm`` (lp/mm; default a
    quarter of the diffraction cutoff; a list: the first is the merit, the others are scanned along for the
    plots) through focus.

    ``focus_mm``: the first scan (equally spaced sensor shifts, mm; default 9 over +- 4 lambda F#^2). While the
    best plane is the first or the last one scanned, the scan is extended past that end at the same step
    (half the first scan's planes at a time, at most ``max_planes`` in all), so the peak lies inside the
    scan with a plane on each side; a parabola through the best plane and its two neighbours then places it
    between planes. Other arguments as :func:`through_focus_mtf` (one field)."""
    fields, _ = _as_fields(field_deg)
    if len(fields) != 1:
        raise ValueError("best_focus takes one field")
    wls, wt = _as_wavelengths(wavelength_um, weights)
    if frequency_lp_mm is None:
        na = image_space_na(lens, fields[0], min(wls), device=device)
        frequency_lp_mm = 0.25 * 2.0 * na / (min(wls) * 1e-3)
    freqs = [float(f) for f in np.atleast_1d(frequency_lp_mm)]
    if focus_mm is None:
        na = image_space_na(lens, fields[0], min(wls), device=device)
        dof = 4.0 * float(np.mean(wls)) * 1e-3 / (2.0 * max(na, 1e-6)) ** 2
        focus_mm = np.linspace(-dof, dof, 9)
    z = np.sort(np.atleast_1d(np.asarray(focus_mm, dtype=float)))
    if len(z) < 3 or not np.allclose(np.diff(z), z[1] - z[0], rtol=1e-6, atol=1e-12) or not z[1] > z[0]:
        raise ValueError(f"focus_mm must be >= 3 equally spaced sensor shifts (mm), got {focus_mm!r}")
    h = float(z[1] - z[0])
    t_last = lens.surfaces[-1].thickness
    chunk = max(len(z) // 2, 2)
    kw = dict(frequencies_lp_mm=freqs, model=model, size=size, pixel_mm=pixel_mm, device=device,
              **psf_kwargs)
    planes, tan, sag = [], [], []

    def scan(zs):
        zs = zs[t_last + zs > 0]  # never onto or in front of the last surface
        if len(zs) == 0:
            return False
        r = through_focus_mtf(lens, fields[0], wls, wt, focus_mm=zs, **kw)
        planes.extend(r.focus_mm)
        tan.extend(r.tangential)
        sag.extend(r.sagittal)
        scan.last = r
        return True

    scan(z)
    while True:
        order = np.argsort(planes)
        zz = np.asarray(planes)[order]
        merit = 0.5 * (np.asarray(tan) + np.asarray(sag))[order, 0]
        i = int(np.argmax(merit))
        interior = 0 < i < len(zz) - 1
        if interior or len(zz) >= max_planes:
            break
        if i == 0:
            grown = scan(zz[0] - h * np.arange(chunk, 0, -1))
        else:
            grown = scan(zz[-1] + h * np.arange(1, chunk + 1))
        if not grown:
            break
    best = float(zz[i])
    if interior:
        a, b, c = merit[i - 1], merit[i], merit[i + 1]
        den = a - 2.0 * b + c
        if den < 0:  # concave: the vertex lies within half a step of the best plane
            best += h * float(np.clip(0.5 * (a - c) / den, -0.5, 0.5))
    else:
        warnings.warn(f"best_focus: the MTF still rises at the end of {len(zz)} planes ({zz[0] * 1e3:+.1f} .. "
                      f"{zz[-1] * 1e3:+.1f} um); pass a wider focus_mm or a larger max_planes", UserWarning,
                      stacklevel=2)
    tf = ThroughFocusMTF(zz, np.array(freqs), np.asarray(tan)[order], np.asarray(sag)[order], fields, wls, model,
                         {"pixel_mm": scan.last.info["pixel_mm"]})
    return BestFocus(best, freqs[0], tf, merit, h, interior)
