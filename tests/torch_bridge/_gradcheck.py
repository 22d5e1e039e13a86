"""A directional finite-difference check of autograd gradients (shared by the bridge tests)."""
import numpy as np
import torch


def directional_error(loss, param, h: float, seed: int = 0) -> float:
    """Relative error of ``grad(loss) . v`` against the 4-point central difference of ``loss`` along a
    random unit direction ``v`` of ``param`` (a leaf tensor; step ``h`` in its units; truncation
    O(h^4)). ``loss`` is a closure returning a scalar tensor; ``param.grad`` is left as computed."""
    v = torch.from_numpy(np.random.default_rng(seed).normal(size=tuple(param.shape))).to(param)
    v /= torch.linalg.vector_norm(v)
    param.grad = None
    loss().backward()
    g = float((param.grad * v).sum())
    vals = {}
    x0 = param.detach().clone()
    with torch.no_grad():
        for m in (-2, -1, 1, 2):
            param.copy_(x0 + m * h * v)
            vals[m] = float(loss())
        param.copy_(x0)
    fd = (8.0 * (vals[1] - vals[-1]) - (vals[2] - vals[-2])) / (12.0 * h)
    return abs(g - fd) / abs(fd)


def central_difference(loss, p, i, h: float) -> float:
    """``(loss(p_i + h) - loss(p_i - h)) / 2h`` for entry ``i`` of the leaf tensor ``p`` (changed in place under
    ``no_grad`` and restored); ``loss`` a closure returning a scalar tensor."""
    with torch.no_grad():
        p[i] += h
        lp = loss().item()
        p[i] -= 2 * h
        lm = loss().item()
        p[i] += h
    return (lp - lm) / (2 * h)
