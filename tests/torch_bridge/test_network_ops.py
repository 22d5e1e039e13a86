"""The NAFNet's layer norm with its gradient written out (torch_bridge.network._LayerNorm2dFunction) and its fused
residual updates (``addcmul``) against the equations written out here, finite differences, and the number of
operations a network step dispatches (issue 25: on a GPU each is a kernel launch, and the design step is bound by
its launches)."""
from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from torch_bridge.network import LayerNorm2d, NAFBlock, build_network
from _op_count import OpCounter  # noqa: E402


def _ln_numpy(x, w, b, eps):
    """Layer norm over axis 1 of (B, C, H, W) in numpy float64, from its definition."""
    mu = x.mean(1, keepdims=True)
    var = ((x - mu) ** 2).mean(1, keepdims=True)
    return w[None, :, None, None] * (x - mu) / np.sqrt(var + eps) + b[None, :, None, None]


def test_layer_norm_2d_equals_its_definition_and_finite_differences():
    """Forward against numpy's float64 evaluation of the definition (measured 2.3e-16 of the largest output;
    tolerance 1e-14); the written-out backward against central finite differences (torch.autograd.gradcheck,
    float64, its default tolerances) in the input, weight and bias; a second derivative is refused (first order
    only), not silently wrong."""
    g = torch.Generator().manual_seed(0)
    x = torch.randn(2, 5, 3, 4, dtype=torch.float64, generator=g) * 3.0 + 1.0
    ln = LayerNorm2d(5, eps=1e-6).double()
    with torch.no_grad():
        ln.weight.copy_(torch.randn(5, dtype=torch.float64, generator=g))
        ln.bias.copy_(torch.randn(5, dtype=torch.float64, generator=g))
    ref = _ln_numpy(x.numpy(), ln.weight.detach().numpy(), ln.bias.detach().numpy(), 1e-6)
    got = ln(x).detach().numpy()
    assert np.abs(got - ref).max() <= 1e-14 * np.abs(ref).max()
    xs = x.clone().requires_grad_(True)
    w, b = ln.weight.detach().clone().requires_grad_(True), ln.bias.detach().clone().requires_grad_(True)
    from torch_bridge.network import _LayerNorm2dFunction as Fn
    assert torch.autograd.gradcheck(lambda a, c, d: Fn.apply(a, c, d, 1e-6), (xs, w, b))
    (gx,) = torch.autograd.grad(Fn.apply(xs, w, b, 1e-6).pow(2).sum(), xs, create_graph=True)
    with pytest.raises(RuntimeError):
        gx.sum().backward()
    with pytest.raises(ValueError, match="expected"):
        ln(torch.zeros(2, 4, 3, 3, dtype=torch.float64))


def _block_reference(blk, inp):
    """One NAFBlock written out from the equations of torch_bridge.network's docstring with its weights:
    ``y = x + beta Conv1x1(SCA(SimpleGate(DWConv3x3(Conv1x1(LN(x))))))``, ``y + gamma Conv1x1(SimpleGate(Conv1x1(
    LN(y))))``, the layer norm as mean / biased variance over the channels, in torch (autograd's own gradient)."""
    def ln(x, m):
        mu = x.mean(1, keepdim=True)
        var = ((x - mu) ** 2).mean(1, keepdim=True)
        return m.weight[None, :, None, None] * (x - mu) / torch.sqrt(var + m.eps) + m.bias[None, :, None, None]

    def conv(x, c):
        return F.conv2d(x, c.weight, c.bias, padding=c.padding, groups=c.groups)

    def gate(x):
        h = x.shape[1] // 2
        return x[:, :h] * x[:, h:]
    x = gate(conv(conv(ln(inp, blk.norm1), blk.conv1), blk.conv2))
    x = x * conv(x.mean((2, 3), keepdim=True), blk.sca[1])
    y = inp + conv(x, blk.conv3) * blk.beta
    x = conv(gate(conv(ln(y, blk.norm2), blk.conv4)), blk.conv5)
    return y + x * blk.gamma


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-14), (torch.float32, 2e-6)])
def test_nafblock_equals_the_written_out_block(dtype, tol):
    """A NAFBlock (8 channels, random weights, beta and gamma non-zero) against :func:`_block_reference`: output
    and every parameter's and the input's gradient. Measured (largest difference / largest value): float64
    5.6e-16 (output) and 1.1e-15 (gradients), tolerance 1e-14; float32 (the network's dtype: the fused variance
    and ``rsqrt`` round differently from mean-of-squares and ``sqrt``) 8.1e-8 and 2.9e-7, tolerance 2e-6."""
    torch.manual_seed(1)
    blk = NAFBlock(8).to(dtype)
    with torch.no_grad():
        for p in blk.parameters():
            p.add_(0.3 * torch.randn_like(p))
    x = torch.randn(2, 8, 6, 5, dtype=dtype)
    g = torch.randn(2, 8, 6, 5, dtype=dtype)
    out = []
    for fn in (blk, lambda t: _block_reference(blk, t)):
        xs = x.clone().requires_grad_(True)
        blk.zero_grad(set_to_none=True)
        y = fn(xs)
        (y * g).sum().backward()
        out.append((y.detach(), xs.grad, [p.grad.clone() for p in blk.parameters()]))
    (ya, xa, pa), (yb, xb, pb) = out
    assert float((ya - yb).abs().max()) <= tol * float(yb.abs().max())
    for a, b in zip([xa] + pa, [xb] + pb):
        assert float(b.abs().max()) > 0
        assert float((a - b).abs().max()) <= tol * float(b.abs().max())


def test_a_network_step_makes_a_bounded_number_of_operations():
    """Forward and backward of the ``small`` (7 NAFBlocks) and ``paper`` (36) networks on one 16 x 16 image: the
    aten operations (each a kernel launch on a GPU, views included here) a block adds. Measured 112.3 a block
    (830 and 4086 in all); with autograd's layer norm and separate multiply-adds 160.1 (1166 and 5810). Bound: 120
    a block and 900 for the small network."""
    counts = {}
    for preset in ("small", "paper"):
        net = build_network(preset, 3)
        x = torch.rand(1, 3, 16, 16)
        with OpCounter() as ops:
            net(x).sum().backward()
        counts[preset] = (ops.n, sum(isinstance(m, NAFBlock) for m in net.modules()))
    (n_s, b_s), (n_p, b_p) = counts["small"], counts["paper"]
    assert (b_s, b_p) == (7, 36)
    assert (n_p - n_s) / (b_p - b_s) <= 120
    assert n_s <= 900
