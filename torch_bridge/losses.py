"""Losses and image-quality metrics for end-to-end design.

Training loss (the paper's): ``L = MSE(out, gt) + alpha * L_percep(out, gt)`` with alpha = 0.1.

Perceptual term (:class:`PerceptualLoss`), ``kind``:

* ``"vgg"``: the VGG loss of Johnson et al. 2016: mean squared difference of VGG16 activations at
  relu1_2, relu2_2 and relu3_3 (inputs normalised with the ImageNet mean and standard deviation),
  averaged over the three layers. The weights are **not downloaded**: give the path of
  torchvision's ImageNet VGG16 ``state_dict`` file (``vgg16-397923af.pth``; keys ``features.N.*``).
  Without a usable file the loss falls back to ``fallback`` and emits a :class:`UserWarning`
  saying so.
* ``"ssim"`` (the default fallback, weight-free): ``1 - SSIM(out, gt)`` with the standard 11x11
  Gaussian window (sigma 1.5), C1 = 0.01^2, C2 = 0.03^2, per channel, averaged. Like the VGG loss it
  rewards local structure (contrast, edges) rather than per-pixel agreement.
* ``"gradient"``: mean absolute difference of horizontal and vertical finite differences (edges).
* ``"none"``: no perceptual term.

Metrics (:func:`image_metrics`): PSNR and SSIM by scikit-image's definitions (scikit-image on the CPU, torch
on other devices: :func:`image_metrics_per_image`), on images clipped to [0, 1]
(``data_range=1``; SSIM with Gaussian weights, sigma 1.5, population covariance: Wang et al. 2004),
averaged over the batch; ``1 - LPIPS`` (VGG variant, Zhang et al. 2018) only when both the VGG16
backbone file and the LPIPS linear-layer file (``vgg.pth`` of the ``lpips`` package, v0.1) are
given, otherwise reported as NaN.

Images are (B, 3, H, W) tensors with values in [0, 1].
"""
from __future__ import annotations

import functools
import math
import warnings
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

__all__ = [
    "LPIPS",
    "PERCEPTUAL_KINDS",
    "PerceptualLoss",
    "ReconstructionLoss",
    "VGG16Features",
    "gradient_loss",
    "image_metrics",
    "image_metrics_per_image",
    "psnr",
    "psnr_tensor",
    "ssim_torch",
]

PERCEPTUAL_KINDS = ("vgg", "ssim", "gradient", "none")
_IMAGENET_MEAN = (0.485, 0.456, 0.406)
_IMAGENET_STD = (0.229, 0.224, 0.225)
# torchvision vgg16.features: (index of the conv, in channels, out channels); "M" = max pool
_VGG16_CFG = [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512]
# relu output indices in torchvision's numbering
RELU = {"relu1_2": 3, "relu2_2": 8, "relu3_3": 15, "relu4_3": 22, "relu5_3": 29}


class VGG16Features(nn.Module):
    """The convolutional part of VGG16 laid out as torchvision's ``vgg16().features`` (so its
    ``state_dict`` keys ``features.N.weight`` load directly). Frozen (no gradients to its weights).
    ``forward(x, layers)`` returns the activations at the named ReLUs (:data:`RELU`)."""

    def __init__(self):
        super().__init__()
        mods, c = [], 3
        for v in _VGG16_CFG:
            if v == "M":
                mods.append(nn.MaxPool2d(2, 2))
            else:
                mods += [nn.Conv2d(c, v, 3, padding=1), nn.ReLU(inplace=False)]
                c = v
        self.features = nn.Sequential(*mods)
        for p in self.parameters():
            p.requires_grad_(False)

    @classmethod
    def from_file(cls, path) -> VGG16Features:
        """Load torchvision's VGG16 ``state_dict`` (the whole model's or just ``features``)."""
        sd = torch.load(str(path), map_location="cpu", weights_only=True)
        if isinstance(sd, dict) and "state_dict" in sd:
            sd = sd["state_dict"]
        feats = {k[len("features."):]: v for k, v in sd.items() if k.startswith("features.")}
        if not feats:
            feats = {k: v for k, v in sd.items() if k.split(".")[0].isdigit()}
        if not feats:
            raise ValueError(f"{path}: no VGG16 'features.N.weight' keys found")
        net = cls()
        missing, _ = net.features.load_state_dict(feats, strict=False)
        if missing:
            raise ValueError(f"{path}: VGG16 weights missing {missing[:4]}...")
        return net.eval()

    def forward(self, x, layers=("relu1_2", "relu2_2", "relu3_3")):
        want = {RELU[n]: n for n in layers}
        last = max(want)
        out = {}
        for i, m in enumerate(self.features):
            x = m(x)
            if i in want:
                out[want[i]] = x
            if i >= last:
                break
        return [out[n] for n in layers]


def _gaussian_window(size: int = 11, sigma: float = 1.5, dtype=torch.float32, device=None):
    g = torch.exp(-0.5 * ((torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2) / sigma) ** 2)
    g = g / g.sum()
    return g[:, None] * g[None, :]


def ssim_torch(x: torch.Tensor, y: torch.Tensor, window: int = 11, sigma: float = 1.5, data_range: float = 1.0):
    """Differentiable mean SSIM of (B, C, H, W) images (Gaussian window, valid region only)."""
    C = x.shape[1]
    w = _gaussian_window(window, sigma, x.dtype, x.device).expand(C, 1, window, window)
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2

    def blur(t):
        return F.conv2d(t, w, groups=C)
    mx, my = blur(x), blur(y)
    sxx = blur(x * x) - mx * mx
    syy = blur(y * y) - my * my
    sxy = blur(x * y) - mx * my
    s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
    return s.mean()


def gradient_loss(x: torch.Tensor, y: torch.Tensor):
    """Mean absolute difference of the horizontal and vertical finite differences."""
    dx = (x[..., :, 1:] - x[..., :, :-1]) - (y[..., :, 1:] - y[..., :, :-1])
    dy = (x[..., 1:, :] - x[..., :-1, :]) - (y[..., 1:, :] - y[..., :-1, :])
    return 0.5 * (dx.abs().mean() + dy.abs().mean())


class PerceptualLoss(nn.Module):
    """Perceptual term (see the module docstring). ``kind`` "vgg" with ``vgg_weights`` (path) or a
    weight-free ``kind``; ``fallback`` is used (with a warning) when "vgg" has no usable weights.
    :attr:`active_kind` says which one runs."""

    def __init__(self, kind: str = "vgg", vgg_weights=None, fallback: str = "ssim"):
        super().__init__()
        if kind not in PERCEPTUAL_KINDS:
            raise ValueError(f"perceptual kind must be one of {PERCEPTUAL_KINDS}, got {kind!r}")
        if fallback not in ("ssim", "gradient", "none"):
            raise ValueError(f"fallback must be 'ssim', 'gradient' or 'none', got {fallback!r}")
        self.vgg = None
        self.active_kind = kind
        if kind == "vgg":
            reason = None
            if vgg_weights is None:
                reason = "no VGG16 weights file was given (loss.vgg_weights)"
            elif not Path(vgg_weights).is_file():
                reason = f"the VGG16 weights file {vgg_weights} does not exist"
            else:
                try:
                    self.vgg = VGG16Features.from_file(vgg_weights)
                except Exception as e:  # noqa: BLE001 - any unreadable file means: fall back
                    reason = f"the VGG16 weights file {vgg_weights} could not be read ({e})"
            if reason is not None:
                warnings.warn(f"perceptual loss: {reason}; using the weight-free '{fallback}' loss instead "
                              f"(pass torchvision's vgg16 state_dict path to use the VGG loss)", UserWarning,
                              stacklevel=2)
                self.active_kind = fallback
        mean = torch.tensor(_IMAGENET_MEAN).view(1, 3, 1, 1)
        std = torch.tensor(_IMAGENET_STD).view(1, 3, 1, 1)
        self.register_buffer("mean", mean, persistent=False)
        self.register_buffer("std", std, persistent=False)

    def forward(self, out, gt):
        k = self.active_kind
        if k == "vgg":
            fa = self.vgg((out - self.mean) / self.std)
            fb = self.vgg((gt - self.mean) / self.std)
            return sum(F.mse_loss(a, b) for a, b in zip(fa, fb)) / len(fa)
        if k == "ssim":
            return 1.0 - ssim_torch(out, gt)
        if k == "gradient":
            return gradient_loss(out, gt)
        return out.new_zeros(())


class ReconstructionLoss(nn.Module):
    """``MSE(out, gt) + alpha * perceptual(out, gt)``; :meth:`forward` returns ``(total, parts)`` with
    ``parts = {"mse": ..., "perceptual": ...}`` (floats).

    ``fallback_alpha``: the weight used instead of ``alpha`` when the VGG term was asked for but its
    weights are missing and the ``fallback`` term runs (None: ``alpha``). The paper's alpha = 0.1 is
    calibrated for the VGG term; the weight-free terms have another scale: on blurred 64 px crops
    ``1 - SSIM`` is ~0.1-0.2 while the MSE is ~1e-3 (images in [0, 1]), so at alpha = 0.1 the SSIM term
    is ~10x the MSE and a small network trained for a few hundred steps lowers the PSNR (measured on
    the A489 CPU preset). :attr:`alpha` is the weight in use.
    """

    def __init__(self, alpha: float = 0.1, perceptual: str = "vgg", vgg_weights=None, fallback: str = "ssim",
                 fallback_alpha: float | None = None):
        super().__init__()
        self.perceptual = PerceptualLoss(perceptual, vgg_weights, fallback)
        fell_back = perceptual == "vgg" and self.perceptual.active_kind != "vgg"
        self.alpha = float(fallback_alpha if (fell_back and fallback_alpha is not None) else alpha)

    def forward(self, out, gt, tensors: bool = False):
        """``(total, parts)``: the loss (0-d tensor with its graph) and ``parts`` (``mse``, ``perceptual``; floats, or
        with ``tensors`` detached 0-d tensors on the images' device: no host read, which waits for the device)."""
        mse = F.mse_loss(out, gt)
        if self.alpha and self.perceptual.active_kind != "none":
            per = self.perceptual(out, gt)
        else:
            per = out.new_zeros(())
        total = mse + self.alpha * per
        if tensors:
            return total, {"mse": mse.detach(), "perceptual": per.detach()}
        return total, {"mse": float(mse.detach()), "perceptual": float(per.detach())}


class LPIPS(nn.Module):
    """LPIPS distance, VGG variant (v0.1): unit-normalised VGG16 activations at relu1_2 .. relu5_3,
    squared differences weighted by the learned non-negative 1x1 layers, averaged over space and
    summed over layers. Needs torchvision's VGG16 file and the ``lpips`` package's ``vgg.pth``
    (keys ``lin{0..4}.model.1.weight``). Inputs in [0, 1]."""

    CHANNELS = (64, 128, 256, 512, 512)
    LAYERS = ("relu1_2", "relu2_2", "relu3_3", "relu4_3", "relu5_3")

    def __init__(self, vgg_weights, lpips_weights):
        super().__init__()
        self.vgg = VGG16Features.from_file(vgg_weights)
        sd = torch.load(str(lpips_weights), map_location="cpu", weights_only=True)
        self.lins = nn.ParameterList()
        for i, c in enumerate(self.CHANNELS):
            w = sd.get(f"lin{i}.model.1.weight", sd.get(f"lin{i}.weight"))
            if w is None or w.numel() != c:
                raise ValueError(f"{lpips_weights}: no LPIPS weights lin{i} with {c} channels")
            self.lins.append(nn.Parameter(w.reshape(1, c, 1, 1).float(), requires_grad=False))
        self.register_buffer("shift", torch.tensor([-.030, -.088, -.188]).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor([.458, .448, .450]).view(1, 3, 1, 1), persistent=False)

    @torch.no_grad()
    def forward(self, x, y):
        """LPIPS distance per image, (B,)."""
        fx = self.vgg(((2 * x - 1) - self.shift) / self.scale, self.LAYERS)
        fy = self.vgg(((2 * y - 1) - self.shift) / self.scale, self.LAYERS)
        d = 0.0
        for a, b, w in zip(fx, fy, self.lins):
            a = a / (a.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            b = b / (b.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            d = d + ((a - b) ** 2 * w).sum(1).mean((1, 2))
        return d


def psnr(out: torch.Tensor, gt: torch.Tensor) -> float:
    """Mean PSNR (dB) over the batch of images clipped to [0, 1] (torch, no scikit-image)."""
    return float(psnr_tensor(out, gt))


def psnr_tensor(out: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """:func:`psnr` as a 0-d tensor on the images' device (dB; no host read, which waits for the device)."""
    mse = ((out.clamp(0, 1) - gt) ** 2).flatten(1).mean(1)
    return (10.0 * torch.log10(1.0 / mse.clamp_min(1e-12))).mean()


def _metric_taps(sigma: float = 1.5, truncate: float = 3.5) -> np.ndarray:
    """The 1-D Gaussian taps of scikit-image's SSIM with ``gaussian_weights=True`` (scipy.ndimage's
    ``gaussian_filter`` kernel: radius ``int(truncate sigma + 0.5)``, ``exp(-x^2 / (2 sigma^2))`` normalised to
    sum 1; sigma in pixels), float64."""
    r = int(truncate * sigma + 0.5)
    x = np.arange(-r, r + 1)
    phi = np.exp(-0.5 / (sigma * sigma) * x ** 2)
    return phi / phi.sum()


@functools.lru_cache(maxsize=16)
def _metric_band(n: int, device: str) -> torch.Tensor:
    """(n - k + 1, n) float64 on ``device``: row i holds :func:`_metric_taps` (k of them) at columns i..i+k-1, the
    'valid' correlation along an axis of n px as a matrix product. Kept per size and device: made and uploaded once
    (an upload from pageable memory waits for the device)."""
    taps = _metric_taps()
    k = taps.size
    m = np.zeros((n - k + 1, n))
    for j in range(k):
        m[np.arange(n - k + 1), np.arange(n - k + 1) + j] = taps[j]
    return torch.as_tensor(m, dtype=torch.float64, device=device)


def image_metrics_per_image(out: torch.Tensor, gt: torch.Tensor, method: str = "auto", chunk: int = 16) -> tuple:
    """PSNR (dB) and SSIM of each of the (B, 3, H, W) images ``out`` against ``gt``, both clipped to [0, 1] (as
    float32, then float64): two (B,) float64 tensors on the images' device.

    The definitions are scikit-image's (``peak_signal_noise_ratio`` and ``structural_similarity`` with
    ``data_range=1, channel_axis=2, gaussian_weights=True, sigma=1.5, use_sample_covariance=False``). ``method``:
    ``"skimage"`` (those functions, image by image, on a host copy), ``"torch"`` (float64 on the images' device,
    no host read, so no wait for the device: PSNR ``10 log10(1 / MSE)`` over all pixels and channels, 100 dB where
    the images are equal; SSIM per channel the mean of the SSIM map (Wang et al. 2004, C1 = 0.01^2, C2 = 0.03^2)
    over the pixels at least the Gaussian window's radius (5 px) from the edges -- the region scikit-image keeps,
    which the border mode of its filter never reaches, so the filters here are 'valid' separable correlations,
    done as products with banded matrices -- then the channels averaged) or ``"auto"``: scikit-image on the CPU
    (its line-by-line filters are ~2.5x faster there than torch's), torch elsewhere. The two agree to the rounding
    of the sums (~1e-15, tests/torch_bridge/test_eval_batched.py). ``chunk``: images filtered at once by the torch
    method (memory: ~150 chunk C H W bytes)."""
    if out.shape != gt.shape or out.ndim != 4:
        raise ValueError(f"out and gt must be (B, C, H, W) of one shape, got {tuple(out.shape)}, {tuple(gt.shape)}")
    if method not in ("auto", "torch", "skimage"):
        raise ValueError(f"method must be 'auto', 'torch' or 'skimage', got {method!r}")
    taps = _metric_taps()
    if min(out.shape[-2:]) < taps.size:
        raise ValueError(f"images of {tuple(out.shape[-2:])} px are smaller than the SSIM window ({taps.size} px)")
    if method == "skimage" or (method == "auto" and out.device.type == "cpu"):
        from skimage.metrics import peak_signal_noise_ratio, structural_similarity
        a = out.detach().float().clamp(0, 1).cpu().numpy().transpose(0, 2, 3, 1).astype(np.float64)
        b = gt.detach().float().clamp(0, 1).cpu().numpy().transpose(0, 2, 3, 1).astype(np.float64)
        ps = [peak_signal_noise_ratio(b[i], a[i], data_range=1.0) for i in range(a.shape[0])]
        ss = [structural_similarity(b[i], a[i], data_range=1.0, channel_axis=2, gaussian_weights=True, sigma=1.5,
                                    use_sample_covariance=False) for i in range(a.shape[0])]
        ps = [p if math.isfinite(p) else 100.0 for p in ps]
        return (torch.tensor(ps, dtype=torch.float64).to(out.device),
                torch.tensor(ss, dtype=torch.float64).to(out.device))
    H, W = out.shape[-2:]
    my, mxt = _metric_band(H, str(out.device)), _metric_band(W, str(out.device)).T
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    ps, ss = [], []
    for i in range(0, out.shape[0], int(chunk)):
        a = out[i:i + chunk].detach().float().clamp(0, 1).double()
        b = gt[i:i + chunk].detach().float().clamp(0, 1).double()
        n = a.shape[0]
        mse = ((b - a) ** 2).reshape(n, -1).mean(1)
        p = 10.0 * torch.log10(1.0 / mse)
        ps.append(torch.where(torch.isfinite(p), p, torch.full_like(p, 100.0)))
        # the five filtered maps of every channel: x, y, x^2, y^2, xy (rows, then columns)
        f = torch.matmul(torch.matmul(my, torch.stack([a, b, a * a, b * b, a * b], 2)), mxt)
        ux, uy, uxx, uyy, uxy = f.unbind(2)
        vx, vy, vxy = uxx - ux * ux, uyy - uy * uy, uxy - ux * uy
        s = ((2 * ux * uy + c1) * (2 * vxy + c2)) / ((ux ** 2 + uy ** 2 + c1) * (vx + vy + c2))
        ss.append(s.mean((-2, -1)).mean(-1))
    return torch.cat(ps), torch.cat(ss)


def image_metrics(out: torch.Tensor, gt: torch.Tensor, lpips: LPIPS | None = None) -> dict:
    """PSNR (dB), SSIM and 1 - LPIPS of (B, 3, H, W) images in [0, 1], averaged over the batch (PSNR and SSIM
    by scikit-image's definitions, :func:`image_metrics_per_image`; ``one_minus_lpips`` is
    NaN without an :class:`LPIPS`)."""
    p, s = image_metrics_per_image(out, gt)
    res = {"psnr": float(np.mean(p.cpu().numpy())), "ssim": float(np.mean(s.cpu().numpy())),
           "one_minus_lpips": float("nan")}
    if lpips is not None:
        res["one_minus_lpips"] = float(1.0 - lpips(out.detach().float().clamp(0, 1).cpu(), gt.float().cpu()).mean())
    return res
