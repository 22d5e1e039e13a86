"""Image-reconstruction network: NAFNet (Chen, Chu, Zhang, Sun, "Simple Baselines for Image
Restoration", ECCV 2022), written here so that nothing is downloaded.

A U-Net of NAFBlocks. Each NAFBlock is

    x + beta  * Conv1x1(SCA(SimpleGate(DWConv3x3(Conv1x1(LN(x))))))        (spatial mixing)
    y + gamma * Conv1x1(SimpleGate(Conv1x1(LN(y))))                          (channel FFN)

with ``SimpleGate(a, b) = a * b`` (the channels split in two halves), simplified channel attention
``SCA(x) = x * Conv1x1(AvgPool(x))`` and ``beta``, ``gamma`` initialised to zero (every block starts
as the identity). The encoder halves the resolution with a 2x2 stride-2 convolution and doubles the
width at each level; the decoder upsamples with a 1x1 convolution and ``PixelShuffle(2)`` and adds
the skip connection; the output is added to the input image (global residual).

Images are ``(B, C, H, W)`` float tensors (any linear unit, ~[0, 1]); H and W need not be multiples
of ``2 ** levels`` (they are padded by reflection and cropped back).

Presets (:data:`PRESETS`): ``"tiny"`` (trains on a CPU in minutes), ``"small"``, ``"paper"`` (the
NAFNet-width32 deblurring configuration of the NAFNet repository, GoPro:
encoder blocks [1, 1, 1, 28], 1 middle block, decoder blocks [1, 1, 1, 1]).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["PRESETS", "LayerNorm2d", "NAFBlock", "NAFNet", "build_network"]

PRESETS = {
    "tiny": {"width": 8, "enc_blocks": [1, 1], "middle_blocks": 1, "dec_blocks": [1, 1]},
    "small": {"width": 16, "enc_blocks": [1, 1, 1], "middle_blocks": 1, "dec_blocks": [1, 1, 1]},
    "paper": {"width": 32, "enc_blocks": [1, 1, 1, 28], "middle_blocks": 1, "dec_blocks": [1, 1, 1, 1]},
}


class _LayerNorm2dFunction(torch.autograd.Function):
    """``w y + b`` with ``y = (x - mean_c x) / sqrt(var_c x + eps)`` over the channel axis of (B, C, H, W), with
    its backward written out: on a GPU each operation is a kernel launch, and the step is bound by its launches
    (issue 25), so the forward takes 6 operations (one ``var_mean`` reduction) instead of autograd's 10, and the
    backward 10 instead of ~30.

    Backward (per pixel, sums over the C channels, ``g`` the output's gradient, ``r = 1/sqrt(var + eps)``):
    ``dL/dx = r (w g - mean(w g) - y mean(w g y))`` (the derivative of the normalisation: ``dy_i/dx_j =
    r (delta_ij - 1/C - y_i y_j / C)``), ``dL/dw = sum_{b,h,w} g y``, ``dL/db = sum_{b,h,w} g``. First order only
    (the design loop takes no second derivatives): a second backward through it raises."""

    @staticmethod
    def forward(ctx, x, weight, bias, eps):
        var, mu = torch.var_mean(x, 1, correction=0, keepdim=True)
        r = torch.rsqrt(var + eps)
        y = (x - mu) * r
        ctx.save_for_backward(y, r, weight)
        return torch.addcmul(bias[None, :, None, None], weight[None, :, None, None], y)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g):
        y, r, weight = ctx.saved_tensors
        gw = g * weight[None, :, None, None]
        dx = r * torch.addcmul(gw - gw.mean(1, keepdim=True), y, (gw * y).mean(1, keepdim=True), value=-1.0)
        dw = (g * y).sum((0, 2, 3)) if ctx.needs_input_grad[1] else None
        db = g.sum((0, 2, 3)) if ctx.needs_input_grad[2] else None
        return dx, dw, db, None


class LayerNorm2d(nn.Module):
    """Layer normalisation over the channel axis of a (B, C, H, W) tensor, per pixel (dimensionless):
    ``weight * (x - mean) / sqrt(var + eps) + bias``, mean and (biased) variance over the C channels, by
    :class:`_LayerNorm2dFunction` (its gradient written out: fewer operations, each a GPU launch)."""

    def __init__(self, channels: int, eps: float = 1e-6):
        super().__init__()
        self.weight = nn.Parameter(torch.ones(channels))
        self.bias = nn.Parameter(torch.zeros(channels))
        self.eps = eps

    def forward(self, x):
        if x.ndim != 4 or x.shape[1] != self.weight.shape[0]:
            raise ValueError(f"LayerNorm2d({self.weight.shape[0]}): expected (B, {self.weight.shape[0]}, H, W), got "
                             f"{tuple(x.shape)}")
        return _LayerNorm2dFunction.apply(x, self.weight, self.bias, float(self.eps))


class SimpleGate(nn.Module):
    """Split the channels in two halves and multiply them."""

    def forward(self, x):
        a, b = x.chunk(2, dim=1)
        return a * b


class NAFBlock(nn.Module):
    """One NAFNet block on ``channels`` channels (see the module docstring)."""

    def __init__(self, channels: int, dw_expand: int = 2, ffn_expand: int = 2, dropout: float = 0.0):
        super().__init__()
        dw = channels * dw_expand
        self.conv1 = nn.Conv2d(channels, dw, 1)
        self.conv2 = nn.Conv2d(dw, dw, 3, padding=1, groups=dw)
        self.conv3 = nn.Conv2d(dw // 2, channels, 1)
        self.sca = nn.Sequential(nn.AdaptiveAvgPool2d(1), nn.Conv2d(dw // 2, dw // 2, 1))
        self.sg = SimpleGate()
        ffn = channels * ffn_expand
        self.conv4 = nn.Conv2d(channels, ffn, 1)
        self.conv5 = nn.Conv2d(ffn // 2, channels, 1)
        self.norm1 = LayerNorm2d(channels)
        self.norm2 = LayerNorm2d(channels)
        self.drop1 = nn.Dropout(dropout) if dropout > 0 else nn.Identity()
        self.drop2 = nn.Dropout(dropout) if dropout > 0 else nn.Identity()
        self.beta = nn.Parameter(torch.zeros(1, channels, 1, 1))
        self.gamma = nn.Parameter(torch.zeros(1, channels, 1, 1))

    def forward(self, inp):
        x = self.conv2(self.conv1(self.norm1(inp)))
        x = self.sg(x)
        x = x * self.sca(x)
        x = self.drop1(self.conv3(x))
        # inp + x beta and y + x gamma, each one fused operation (one launch, not two)
        y = torch.addcmul(inp, x, self.beta)
        x = self.conv5(self.sg(self.conv4(self.norm2(y))))
        return torch.addcmul(y, self.drop2(x), self.gamma)


class NAFNet(nn.Module):
    """NAFNet U-Net.

    Parameters
    ----------
    in_channels : int
        Image channels (3 for RGB); the output has the same number.
    width : int
        Channels of the first level (doubled at each encoder level).
    enc_blocks, dec_blocks : list of int
        NAFBlocks per encoder / decoder level (same length: the number of levels).
    middle_blocks : int
        NAFBlocks at the bottom of the U.
    zero_init : bool
        Zero the last convolution so that the untrained network is the identity (the global
        residual passes the input through): short trainings start from "no reconstruction" instead
        of from random noise added to the image. The NAFNet paper initialises it randomly.
    """

    def __init__(self, in_channels: int = 3, width: int = 16, enc_blocks=(1, 1, 1), middle_blocks: int = 1,
                 dec_blocks=(1, 1, 1), dropout: float = 0.0, zero_init: bool = True):
        super().__init__()
        enc_blocks, dec_blocks = list(enc_blocks), list(dec_blocks)
        if len(enc_blocks) != len(dec_blocks):
            raise ValueError(f"enc_blocks and dec_blocks need the same length, got {enc_blocks} and {dec_blocks}")
        if width < 1 or any(b < 0 for b in enc_blocks + dec_blocks) or middle_blocks < 0:
            raise ValueError("width must be >= 1 and block counts >= 0")
        self.intro = nn.Conv2d(in_channels, width, 3, padding=1)
        self.ending = nn.Conv2d(width, in_channels, 3, padding=1)
        if zero_init:
            nn.init.zeros_(self.ending.weight)
            nn.init.zeros_(self.ending.bias)
        self.encoders, self.downs = nn.ModuleList(), nn.ModuleList()
        self.decoders, self.ups = nn.ModuleList(), nn.ModuleList()
        ch = width
        for n in enc_blocks:
            self.encoders.append(nn.Sequential(*[NAFBlock(ch, dropout=dropout) for _ in range(n)]))
            self.downs.append(nn.Conv2d(ch, 2 * ch, 2, stride=2))
            ch *= 2
        self.middle = nn.Sequential(*[NAFBlock(ch, dropout=dropout) for _ in range(middle_blocks)])
        for n in dec_blocks:
            self.ups.append(nn.Sequential(nn.Conv2d(ch, 2 * ch, 1, bias=False), nn.PixelShuffle(2)))
            ch //= 2
            self.decoders.append(nn.Sequential(*[NAFBlock(ch, dropout=dropout) for _ in range(n)]))
        self.multiple = 2 ** len(enc_blocks)

    def forward(self, inp):
        """Restore ``inp`` (B, C, H, W); returns the same shape."""
        H, W = inp.shape[-2:]
        ph = (-H) % self.multiple
        pw = (-W) % self.multiple
        x0 = F.pad(inp, (0, pw, 0, ph), mode="reflect") if (ph or pw) else inp
        x = self.intro(x0)
        skips = []
        for enc, down in zip(self.encoders, self.downs):
            x = enc(x)
            skips.append(x)
            x = down(x)
        x = self.middle(x)
        for dec, up, skip in zip(self.decoders, self.ups, reversed(skips)):
            x = dec(up(x) + skip)
        x = self.ending(x) + x0
        return x[..., :H, :W]


def build_network(preset: str | None = "tiny", in_channels: int = 3, **overrides) -> NAFNet:
    """A NAFNet from a preset name (:data:`PRESETS`) with any of ``width``, ``enc_blocks``,
    ``middle_blocks``, ``dec_blocks``, ``dropout``, ``zero_init`` overridden."""
    if preset is None:
        cfg = dict(PRESETS["tiny"])
    else:
        if preset not in PRESETS:
            raise ValueError(f"unknown network preset {preset!r} (choose from {sorted(PRESETS)})")
        cfg = dict(PRESETS[preset])
    cfg.update({k: v for k, v in overrides.items() if v is not None})
    return NAFNet(in_channels=in_channels, **cfg)
