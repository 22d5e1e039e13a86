"""Image simulation from PSF maps, differentiable end to end (torch).

* :func:`blend_weights` / :func:`spatially_varying_blur`: a spatially varying blur from a grid of
  PSFs. The image is split into overlapping patches around the PSF grid nodes with a raised-cosine
  partition of unity (``cos^2`` windows, C1-smooth, summing to exactly 1), each weighted patch is
  convolved with its node's PSF by FFT, and the results are overlap-added. This is the "scatter"
  model: every scene point spreads its light with the PSF blended from its neighbouring nodes,
  so a point source on a node reproduces that node's PSF exactly and the total energy is
  ``sum(image) * sum(psf)`` (light that leaves the frame is lost unless ``boundary`` pads it).
* :func:`channel_psfs` / :func:`render_rgb`: RGB with several wavelengths per colour channel (one
  drawn at random per call, as in the paper's training, or a weighted mean).
* :func:`sensor_noise`: Gaussian read noise plus Poisson shot noise through its Gaussian
  approximation ``N(x, x / photons)`` (reparameterised, so differentiable in ``x``).
* :func:`psf_grid`: the PSF grid of a :class:`~torch_bridge.HybridLens` for an image on the sensor
  (fields from the paraxial focal length, objects at any depth), rows flipped to image order.

Conventions: images are ``(..., C, H, W)`` tensors, row 0 at the top (+y on the sensor), pixel
values in any linear unit. A PSF kernel ``(kh, kw)`` has its centre at ``(kh // 2, kw // 2)`` (the
centre pixel of :func:`rwwarp.psf` patches) and is applied as a convolution (not a correlation),
so a point source reproduces the kernel as stored. PSF grid nodes sit at the centres of a
``gy x gx`` partition of the image: ``y_r = (r + 0.5) H / gy - 0.5`` (pixels), likewise x.
"""
from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from .functions import upload

__all__ = [
    "blend_weights",
    "channel_psfs",
    "node_positions",
    "psf_grid",
    "render_rgb",
    "sensor_noise",
    "spatially_varying_blur",
]


def node_positions(n_nodes: int, length: int) -> np.ndarray:
    """Pixel coordinates of ``n_nodes`` PSF nodes along an axis of ``length`` pixels (cell centres)."""
    return (np.arange(n_nodes) + 0.5) * length / n_nodes - 0.5


def blend_weights(n_nodes: int, length: int, dtype=torch.float64, device=None) -> torch.Tensor:
    """Raised-cosine partition of unity, (n_nodes, length): ``w_r(y) = cos^2(pi/2 (y - y_r) / L)`` for
    ``|y - y_r| < L`` (L the node spacing), held at 1 beyond the first and last node. Columns sum to 1."""
    y = torch.arange(length, dtype=dtype, device=device)
    if n_nodes == 1:
        return torch.ones(1, length, dtype=dtype, device=device)
    pos = upload(node_positions(n_nodes, length), dtype, device)
    spacing = float(length) / n_nodes
    d = (y[None, :] - pos[:, None]) / spacing
    w = torch.where(d.abs() < 1.0, torch.cos(0.5 * math.pi * d) ** 2, torch.zeros_like(d))
    w[0] = torch.where(y <= pos[0], torch.ones_like(y), w[0])
    w[-1] = torch.where(y >= pos[-1], torch.ones_like(y), w[-1])
    return w


def _extended_weights(n_nodes: int, length: int, dtype, device, offset: int, extended: int) -> torch.Tensor:
    """:func:`blend_weights` over ``length`` px, continued by the outer nodes' weights to ``extended`` px with
    the frame starting at ``offset`` px."""
    w = blend_weights(n_nodes, length, dtype, device)
    if offset or extended != length:
        w = F.pad(w[None], (offset, extended - length - offset), mode="replicate")[0]
    return w


def _supports(w: torch.Tensor):
    """Per node, the [start, stop) pixel range where its weight is non-zero."""
    nz = (w > 0).cpu().numpy()
    out = []
    for row in nz:
        idx = np.nonzero(row)[0]
        out.append((int(idx[0]), int(idx[-1]) + 1))
    return out


def _fast_len(n: int) -> int:
    from rwwarp.wave.propagate import next_fft_size
    return next_fft_size(n)


def spatially_varying_blur(image: torch.Tensor, psfs: torch.Tensor, *, boundary: str = "zero",
                           per_image: bool = False) -> torch.Tensor:
    """Blur ``image`` (..., C, H, W) with a grid of PSFs ``psfs`` (gy, gx, [C,] kh, kw).

    Patch-wise FFT convolution with raised-cosine blending between neighbouring nodes (see the
    module docstring). ``boundary``: ``"zero"`` (the scene is dark outside the frame; energy that
    spills out is lost), ``"reflect"`` or ``"replicate"`` (the scene continues beyond the frame by
    the PSF half size). ``per_image``: ``image`` is a batch (B, C, H, W) and ``psfs`` (B, [C,] kh, kw) one
    kernel for each image, blurred over the whole frame (a one-node grid each) in one batched FFT
    convolution: the values of a call per image. Returns a tensor of the image's shape (dtype of the
    promotion of both), differentiable in the image and the PSFs. Pixel units throughout.
    """
    if per_image:
        if image.ndim != 4 or psfs.ndim not in (3, 4) or psfs.shape[0] != image.shape[0]:
            raise ValueError(f"per_image: image must be (B, C, H, W) and psfs (B, [C,] kh, kw) with the same B, got "
                             f"{tuple(image.shape)} and {tuple(psfs.shape)}")
        psfs = (psfs if psfs.ndim == 4 else psfs.unsqueeze(1))[None, None]     # (1, 1, B, pc, kh, kw)
        gy, gx, _, pc, kh, kw = psfs.shape
    else:
        if psfs.ndim == 4:
            psfs = psfs.unsqueeze(2)
        if psfs.ndim != 5:
            raise ValueError(f"psfs must be (gy, gx, [C,] kh, kw), got shape {tuple(psfs.shape)}")
        gy, gx, pc, kh, kw = psfs.shape
    if image.ndim < 3:
        raise ValueError(f"image must be (..., C, H, W), got shape {tuple(image.shape)}")
    C, H, W = image.shape[-3:]
    if pc not in (1, C):
        raise ValueError(f"psfs have {pc} channels, the image {C}")
    dtype = torch.promote_types(image.dtype, psfs.dtype)
    image = image.to(dtype)
    psfs = psfs.to(dtype)
    # padding of the scene beyond the frame
    py0, px0 = kh // 2, kw // 2
    py1, px1 = kh - 1 - py0, kw - 1 - px0
    if boundary == "zero":
        ext, oy, ox = image, 0, 0
    elif boundary in ("reflect", "replicate"):
        lead = image.shape[:-3]
        flat = image.reshape((-1, C, H, W))
        ext = F.pad(flat, (px1, px0, py1, py0), mode=boundary).reshape(lead + (C, H + kh - 1, W + kw - 1))
        oy, ox = py1, px1
    else:
        raise ValueError(f"boundary must be 'zero', 'reflect' or 'replicate', got {boundary!r}")
    He, We = ext.shape[-2:]
    # node positions refer to the frame; the extension continues the outer nodes' weights
    # the weights' supports are read on the host from a CPU copy of the same weights (a read of device data
    # would wait for the device's queue to drain)
    sy, sx = _supports(_extended_weights(gy, H, dtype, "cpu", oy, He)), _supports(_extended_weights(gx, W, dtype, "cpu", ox, We))
    wy = _extended_weights(gy, H, dtype, image.device, oy, He)
    wx = _extended_weights(gx, W, dtype, image.device, ox, We)
    ph = max(b - a for a, b in sy)
    pw = max(b - a for a, b in sx)
    fy, fx = _fast_len(ph + kh - 1), _fast_len(pw + kw - 1)
    lead = ext.shape[:-3]
    # patches: (gy, gx, ..., C, ph, pw), the image zero-extended so every patch has the same size
    padded = F.pad(ext, (0, pw, 0, ph))
    wy_p = F.pad(wy, (0, ph))
    wx_p = F.pad(wx, (0, pw))
    rows = []
    for r, (ya, _) in enumerate(sy):
        cols = []
        for c, (xa, _) in enumerate(sx):
            w = wy_p[r, ya:ya + ph, None] * wx_p[c, None, xa:xa + pw]
            cols.append(padded[..., ya:ya + ph, xa:xa + pw] * w)
        rows.append(torch.stack(cols, 0))
    patches = torch.stack(rows, 0)                                     # (gy, gx, ..., C, ph, pw)
    kern = psfs if per_image else psfs.reshape((gy, gx) + (1,) * len(lead) + (pc, kh, kw))
    spec = torch.fft.rfft2(patches, s=(fy, fx)) * torch.fft.rfft2(kern, s=(fy, fx))
    conv = torch.fft.irfft2(spec, s=(fy, fx))[..., :ph + kh - 1, :pw + kw - 1]
    # overlap-add into the 'full' canvas, then crop the frame
    canvas = torch.zeros(lead + (C, He + kh - 1 + ph, We + kw - 1 + pw), dtype=dtype, device=image.device)
    for r, (ya, _) in enumerate(sy):
        for c, (xa, _) in enumerate(sx):
            canvas[..., ya:ya + ph + kh - 1, xa:xa + pw + kw - 1] = \
                canvas[..., ya:ya + ph + kh - 1, xa:xa + pw + kw - 1] + conv[r, c]
    # full-convolution index of frame pixel (y, x) is (y + oy + kh // 2, x + ox + kw // 2)
    y0, x0 = oy + py0, ox + px0
    return canvas[..., y0:y0 + H, x0:x0 + W]


def channel_psfs(psfs: torch.Tensor, channels, mode: str = "mean", weights=None, generator=None) -> torch.Tensor:
    """Per-colour-channel PSFs from a grid over wavelengths.

    ``psfs``: (gy, gx, n_wavelengths, kh, kw); ``channels``: for each output channel, a list of
    wavelength indices (e.g. ``[[0, 1], [2, 3], [4, 5]]`` for RGB). ``mode="mean"``: the mean over the
    channel's wavelengths (``weights``: optional matching lists of spectral weights, normalised
    per channel); ``mode="random"``: one wavelength drawn per channel per call (``generator``: a
    ``torch.Generator``), as in the paper's training. Returns (gy, gx, n_channels, kh, kw).
    """
    out = []
    for ci, idx in enumerate(channels):
        idx = [int(i) for i in idx]
        if mode == "random":
            k = int(torch.randint(len(idx), (1,), generator=generator).item())
            out.append(psfs[:, :, idx[k]])
        elif mode == "mean":
            w = torch.ones(len(idx), dtype=psfs.dtype, device=psfs.device) if weights is None else \
                upload(weights[ci], psfs.dtype, psfs.device)
            w = w / w.sum()
            out.append(torch.tensordot(psfs[:, :, idx], w, dims=([2], [0])))
        else:
            raise ValueError(f"mode must be 'mean' or 'random', got {mode!r}")
    return torch.stack(out, 2)


def render_rgb(image: torch.Tensor, psfs: torch.Tensor, channels, *, mode: str = "mean", weights=None,
               generator=None, boundary: str = "zero") -> torch.Tensor:
    """Blur an RGB (or any multi-channel) image (..., C, H, W) with the per-channel PSFs built by
    :func:`channel_psfs` from ``psfs`` (gy, gx, n_wavelengths, kh, kw)."""
    per_channel = channel_psfs(psfs, channels, mode=mode, weights=weights, generator=generator)
    return spatially_varying_blur(image, per_channel, boundary=boundary)


def sensor_noise(image: torch.Tensor, *, read_std: float = 0.0, photons: float | None = None,
                 generator=None) -> torch.Tensor:
    """Add sensor noise, differentiably.

    ``photons``: photo-electrons collected at signal 1 (full well): shot noise of variance
    ``max(x, 0) / photons`` (the Gaussian approximation of Poisson statistics, reparameterised as
    ``x + sqrt(max(x, 0) / photons) * n1``); ``read_std``: standard deviation of the Gaussian read
    noise in signal units (``+ read_std * n2``). ``n1, n2 ~ N(0, 1)`` from ``generator``.
    """
    out = image
    if photons is not None:
        n1 = torch.randn(image.shape, generator=generator, dtype=image.dtype, device=image.device)
        # the square root's gradient is infinite at 0: a floor of one hundredth of a photon
        var = torch.clamp(image, min=0.0) / float(photons)
        out = out + torch.sqrt(var + 1e-2 / float(photons) ** 2) * n1
    if read_std:
        n2 = torch.randn(image.shape, generator=generator, dtype=image.dtype, device=image.device)
        out = out + float(read_std) * n2
    return out


def psf_grid(lens_module, image_hw, grid, wavelengths_um, size: int, *, pixel_mm=None, object_distance_mm=None,
             center_px=None, **psf_map_kw) -> torch.Tensor:
    """PSF grid (gy, gx, n_wavelengths, size, size) of a :class:`~torch_bridge.HybridLens` for an image
    of ``image_hw = (H, W)`` sensor pixels, with gradients.

    Node (r, c) sits at the image pixel of :func:`node_positions`; its sensor position (mm) is
    ``x = (col + 0.5 - W/2) p``, ``y = (H/2 - row - 0.5) p`` about ``center_px`` (default the optical
    axis), ``p = pixel_mm`` (default the sensor pitch), and its field angle follows from the paraxial
    focal length ``tan(theta) = h / efl`` at the first wavelength. PSF rows are flipped to image order
    (row 0 at +y). Distortion is not modelled by the patch convolution (each PSF is used about its
    centre pixel). ``object_distance_mm`` sets the object depth (EDoF work); ``psf_map_kw`` goes to
    :meth:`HybridLens.psf_map` (``tile``, ``memory_budget_bytes``, ...).
    """
    H, W = (int(v) for v in image_hw)
    gy, gx = (int(grid), int(grid)) if np.ndim(grid) == 0 else (int(grid[0]), int(grid[1]))
    lens = lens_module.to_lens()
    p = float(pixel_mm or lens.sensor.pixel_pitch)
    efl = lens.efl(float(wavelengths_um[0]))
    ry, rx = node_positions(gy, H), node_positions(gx, W)
    cy, cx = (H / 2.0, W / 2.0) if center_px is None else (float(center_px[0]), float(center_px[1]))
    fields = []
    for r in ry:
        for c in rx:
            x_mm = (c + 0.5 - cx) * p
            y_mm = (cy - r - 0.5) * p
            fields.append((math.degrees(math.atan(x_mm / efl)), math.degrees(math.atan(y_mm / efl))))
    m = lens_module.psf_map(fields, wavelengths_um, size, object_distance_mm=object_distance_mm, pixel_mm=p,
                            **psf_map_kw)
    return m.reshape(gy, gx, len(wavelengths_um), size, size).flip(-2)
