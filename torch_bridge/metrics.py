"""Differentiable figures of merit on PSF tensors: MTF at chosen frequencies, Strehl ratio,
encircled energy (torch twins of :mod:`rwwarp.metrics`, same conventions).

Units: ``pixel_mm`` and positions in mm, frequencies in lp/mm, intensities in (fraction of power)
per mm^2. A PSF tensor is a (..., n, n) patch of box-integrated power per pixel (rows = y up,
columns = x), as :meth:`torch_bridge.HybridLens.psf` returns it; leading dimensions batch.

    import torch_bridge as tb
    from torch_bridge import metrics as tm
    psf = hl.psf(0.0, 0.55, size=128, pixel_mm=0.001)
    loss = -tm.mtf(psf, 0.001, [50.0, 100.0]).mean()          # maximise the MTF at 50 and 100 lp/mm
    s = tm.strehl(psf, 0.001, ideal_peak)                     # ideal_peak: rwwarp.metrics.ideal_peak_intensity
"""
from __future__ import annotations

import math

import numpy as np
import torch

__all__ = ["otf", "mtf", "peak_intensity", "strehl", "encircled_energy"]


def _check_psf(psf):
    if not torch.is_tensor(psf):
        raise TypeError(f"psf must be a torch tensor, got {type(psf).__name__}")
    if psf.dim() < 2 or psf.shape[-1] != psf.shape[-2] or psf.shape[-1] < 2:
        raise ValueError(f"psf must be (..., n, n) with n >= 2, got shape {tuple(psf.shape)}")
    return psf


def _positive(v, name):
    v = float(v)
    if not (v > 0) or not math.isfinite(v):
        raise ValueError(f"{name} must be a positive finite number, got {v!r}")
    return v


def otf(psf, pixel_mm, frequencies_lp_mm, direction=(0.0, 1.0), center_mm=(0.0, 0.0),
        pixel_integrated: bool = True, normalize: bool = True):
    """Complex OTF (..., n_frequencies) of PSF patches along ``direction`` ((x, y)), by a direct
    Fourier sum; ``pixel_integrated`` divides out the pixel box's sinc; ``normalize`` divides by
    each patch's power. ``center_mm``: sensor (x, y) of sample ``[n//2, n//2]`` (mm)."""
    psf = _check_psf(psf)
    p = _positive(pixel_mm, "pixel_mm")
    f = torch.as_tensor(np.atleast_1d(np.asarray(frequencies_lp_mm, dtype=np.float64)), device=psf.device)
    d = np.asarray(direction, dtype=np.float64)
    if d.shape != (2,) or not np.hypot(*d) > 0:
        raise ValueError(f"direction must be a non-zero (x, y) pair, got {direction!r}")
    d = d / np.hypot(*d)
    n = psf.shape[-1]
    off = (torch.arange(n, dtype=torch.float64, device=psf.device) - n // 2) * p
    x, y = center_mm[0] + off, center_mm[1] + off
    fx, fy = f * d[0], f * d[1]
    ex = torch.exp(-2j * math.pi * torch.outer(fx, x))  # (nf, n)
    ey = torch.exp(-2j * math.pi * torch.outer(fy, y))
    a = psf.to(torch.complex128)
    o = torch.einsum("fx,...yx,fy->...f", ex, a, ey)
    if pixel_integrated:
        o = o / (torch.sinc(fx * p) * torch.sinc(fy * p))
    if normalize:
        o = o / psf.sum(dim=(-2, -1)).unsqueeze(-1)
    return o


def mtf(psf, pixel_mm, frequencies_lp_mm, direction=(0.0, 1.0), pixel_integrated: bool = True, eps: float = 0.0):
    """MTF (..., n_frequencies) = |OTF| along ``direction`` (default y: tangential for y fields).
    ``eps`` (>= 0) smooths the modulus at zero (``sqrt(|OTF|^2 + eps^2)``) where gradients must exist."""
    o = otf(psf, pixel_mm, frequencies_lp_mm, direction, pixel_integrated=pixel_integrated)
    if eps:
        return torch.sqrt(o.real ** 2 + o.imag ** 2 + float(eps) ** 2)
    return torch.abs(o)


def peak_intensity(psf, pixel_mm, upsample: int = 4, temperature: float | None = None):
    """Peak point intensity (per mm^2) of pixel-integrated PSF patches (..., n, n): the pixel box
    divided out in the Fourier domain, the band-limited intensity interpolated ``upsample`` times
    finer, then the maximum (``temperature``: a smooth log-sum-exp maximum instead, in the units of
    the intensity). Matches :func:`rwwarp.metrics.peak_intensity_from_psf`."""
    psf = _check_psf(psf)
    p = _positive(pixel_mm, "pixel_mm")
    up = int(upsample)
    if up < 1:
        raise ValueError(f"upsample must be >= 1, got {upsample}")
    n = psf.shape[-1]
    m = up * n
    F = torch.fft.fftshift(torch.fft.fft2(torch.fft.ifftshift(psf.to(torch.float64), dim=(-2, -1))), dim=(-2, -1))
    f = (torch.arange(n, dtype=torch.float64, device=psf.device) - n // 2) / (n * p)
    s = torch.sinc(f * p)
    F = F / torch.outer(s, s)
    if n % 2 == 0:  # split the Nyquist row/column between +-f so the interpolant is real
        w = torch.ones(n, dtype=torch.float64, device=psf.device)
        w[0] = 0.5
        F = F * torch.outer(w, w)
        F = torch.cat([F, F[..., :1, :]], dim=-2)
        F = torch.cat([F, F[..., :, :1]], dim=-1)
    k = F.shape[-1]
    s0 = m // 2 - n // 2
    big = torch.nn.functional.pad(F, (s0, m - s0 - k, s0, m - s0 - k))
    img = torch.fft.fftshift(torch.fft.ifft2(torch.fft.ifftshift(big, dim=(-2, -1))), dim=(-2, -1)).real
    img = img * (m / n) ** 2 / (p * p)
    flat = img.reshape(*img.shape[:-2], -1)
    if temperature:
        t = float(temperature)
        return t * torch.logsumexp(flat / t, dim=-1)
    return flat.max(dim=-1).values


def strehl(psf, pixel_mm, ideal_peak, upsample: int = 4, temperature: float | None = None):
    """Strehl ratio: :func:`peak_intensity` over ``ideal_peak`` (per mm^2, e.g. from
    :func:`rwwarp.metrics.ideal_peak_intensity`, a constant for the pupil)."""
    return peak_intensity(psf, pixel_mm, upsample, temperature) / float(ideal_peak)


def encircled_energy(psf, pixel_mm, radius_mm, center_rel_mm=(0.0, 0.0), total=None, sub: int = 16):
    """Power inside a circle of ``radius_mm`` about ``center_rel_mm`` ((x, y) mm from the patch
    centre) over ``total`` (default each patch's sum); pixels uniform, covered fraction from
    ``sub`` x ``sub`` sub-samples. Differentiable in ``psf``."""
    psf = _check_psf(psf)
    p = _positive(pixel_mm, "pixel_mm")
    R = float(radius_mm)
    if R < 0:
        raise ValueError(f"radius_mm must be >= 0, got {radius_mm}")
    n = psf.shape[-1]
    off = (np.arange(n) - n // 2) * p
    s = ((np.arange(sub) + 0.5) / sub - 0.5) * p
    xs = (off[:, None] + s[None, :]).ravel() - center_rel_mm[0]
    ys = (off[:, None] + s[None, :]).ravel() - center_rel_mm[1]
    w = (xs[None, :] ** 2 + ys[:, None] ** 2 <= R * R).astype(np.float64).reshape(n, sub, n, sub).mean(axis=(1, 3))
    w = torch.as_tensor(w, dtype=psf.dtype, device=psf.device)
    tot = psf.sum(dim=(-2, -1)) if total is None else total
    return (psf * w).sum(dim=(-2, -1)) / tot
