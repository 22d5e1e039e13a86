"""Deterministic per-source sums of per-ray values on the device (the tree of :mod:`rwwarp.kernels.reduce`).

Used where a sum over a source's rays feeds a result: the traced and valid power of each source
(:class:`rwwarp.wave.raywave.RayWave`) and the spot moments (:func:`rwwarp.metrics.analysis.spot_rms_tape`). The same
inputs give the same bits on every run and device (no atomics), and the sums differentiate under
``wp.Tape``.
"""
from __future__ import annotations

import warp as wp

from ..kernels.reduce import WIDE, WIDTH, make_reduce_kernels


def source_sums(values, n_src: int, scalar, device: str, requires_grad: bool = False, work=None):
    """Per-source sums of ``values`` (a Warp array of ``n_src * n`` vec4 of ``scalar``, source-major).

    Returns a Warp array (n_src, 1) of vec4 (the four sums of each source) on ``device``. With
    ``requires_grad`` the intermediate levels keep gradients (call inside a ``wp.Tape``; 16 entries a
    thread), else :data:`~rwwarp.kernels.reduce.WIDE` entries a thread. Either way a fixed order: the same
    bits on every run. ``work`` (without ``requires_grad``): ``work(tag, shape, dtype)`` gives the levels' arrays
    (:meth:`rwwarp.trace.Tracer.work_array`: a kept batch's pool), else they are new."""
    K = make_reduce_kernels(scalar)
    total = int(values.shape[0])
    if n_src <= 0 or total % n_src:
        raise ValueError(f"{total} values do not split into {n_src} sources")
    if total == 0:
        return wp.zeros((n_src, 1), dtype=K.vec4, device=device, requires_grad=requires_grad)
    level = values.reshape((n_src, total // n_src))
    while True:
        if requires_grad:
            width = -(-int(level.shape[1]) // WIDTH)
            out = wp.zeros((n_src, width), dtype=K.vec4, device=device, requires_grad=True)
            wp.launch(K.sum16_kernel, dim=(n_src, width), inputs=[level], outputs=[out], device=device)
        else:   # fewer, wider passes (every entry of out is written)
            width = -(-int(level.shape[1]) // WIDE)
            out = wp.empty((n_src, width), dtype=K.vec4, device=device) if work is None else \
                work(("source_sums", width), (n_src, width), K.vec4)
            wp.launch(K.sum_wide_kernel, dim=(n_src, width), inputs=[level, WIDE], outputs=[out], device=device,
                      record_tape=False)   # not differentiated: off any active tape
        level = out
        if width == 1:
            return level
