"""The wave step (:mod:`rwwarp.wave.wave_step`, issue 27) as a torch autograd Function: the geometric wave-plane field's
edge diffracted over the planned reduced distance before the DOE, ``U = S_T P_d[U_geo / S_T]``, and its
adjoint (the map is linear in the field: ``S_T P_d^H[g / S_T]``, the band-limited ASM's conjugate transfer
function on the same grid). The distance is the plan's (held, like the band limits, while the lens learns).
numpy views on the CPU, CuPy (DLPack) on CUDA. Lengths in mm.
"""
from __future__ import annotations

import numpy as np
import torch


def _xp_view(t):
    t = t.detach().contiguous()
    if t.is_cuda:
        import cupy
        return cupy, cupy.from_dlpack(t)
    return np, t.numpy()


def _back(a, device):
    if isinstance(a, np.ndarray):
        return torch.from_numpy(np.ascontiguousarray(a)).to(device)
    return torch.from_dlpack(a)


class WaveStep(torch.autograd.Function):
    """``WaveStep.apply(field, rw)``: ``field`` complex128 (S, n, n) on the RayWave's windows (baseband, as
    :func:`torch_bridge.functions.trace_splat` gives it) -> the field after the wave step of ``rw``'s plan
    (``rw.wave_step``, mm per source). Gradient in torch's convention (``dL/dRe + 1j dL/dIm``)."""

    @staticmethod
    def forward(ctx, field, rw):
        from rwwarp.wave.wave_step import apply_wave_step
        xp, u = _xp_view(field.to(torch.complex128))
        ctx.rw, ctx.device = rw, field.device
        return _back(apply_wave_step(rw, u, xp), field.device)

    @staticmethod
    def backward(ctx, grad_out):
        from rwwarp.wave.wave_step import apply_wave_step_adjoint
        xp, g = _xp_view(grad_out.to(torch.complex128))
        return _back(apply_wave_step_adjoint(ctx.rw, g, xp), ctx.device), None


def wave_step(field, rw):
    """``field`` after ``rw``'s planned wave step (:class:`WaveStep`), or ``field`` itself where the plan has
    none."""
    if not np.any(getattr(rw, "wave_step", 0.0)):
        return field
    return WaveStep.apply(field, rw)


def add_wave_step(rw, memory_budget_bytes=None):
    """Give a :class:`rwwarp.psf.RayWave` planned without the wave step (a source planned on its own with
    ``method="focal"``: the design loop's per-source focal plans, :class:`torch_bridge.design.CachedProvider`,
    :class:`torch_bridge.live.LiveProvider`) the step ``method="two-step"`` would have planned for it: the same
    :func:`rwwarp.wave.wave_step.plan_wave_step` call (model error, reduced distances, refined pitch, widened
    window), as a new plan the batch runs from then on (:meth:`rwwarp.psf.RayWave.use_plan`). A batch that has its
    step already (``rw.plan.wave_step_mm`` set) is left as it is, so a kept RayWave is never widened twice.
    ``memory_budget_bytes``: a step whose plan exceeds it is refused (:class:`rwwarp.wave.plan.MemoryBudgetError`),
    as under ``"two-step"``. Returns ``rw``."""
    if rw.plan.wave_step_mm is not None:
        return rw
    from rwwarp.wave.wave_step import plan_wave_step
    rw.use_plan(plan_wave_step(rw.batch_plan, None, "two-step", memory_budget_bytes))
    return rw
