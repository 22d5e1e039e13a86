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


def power_source_sums(valid, weight, n_src: int, n: int, scalar, device: str, work=None):
    """Per-source ``(launched power, valid power, 0, 0)`` of traced rays (``valid``: int32 per ray, ``weight``: the
    rays' weights of ``scalar``; ``n_src`` sources of ``n`` ray slots each, source-major): a Warp array (n_src, 1)
    of float64 vec4, the bits that the ``power_sums_kernel`` terms (:mod:`rwwarp.kernels.splat`) summed by
    :func:`source_sums` without gradients give. On the CPU one launch
    (:func:`rwwarp.kernels.reduce.make_power_tree_kernel`: the terms formed and summed through the same tree, in the
    same order); elsewhere the terms kernel and the tree's passes. ``work``: as :func:`source_sums` (the terms
    under "power_terms")."""
    from ..kernels.splat import make_splat_kernels
    n_src, n = int(n_src), int(n)
    if n_src < 1 or n < 1:
        raise ValueError(f"power_source_sums: n_src and n must be >= 1, got {n_src}, {n}")
    K = make_splat_kernels(scalar)
    widths = []   # the widths of source_sums' passes, down to 1
    w = n
    while True:
        w = -(-w // WIDE)
        widths.append(w)
        if w == 1:
            break
    if str(device) != "cpu" or len(widths) > 3:
        terms = wp.empty(n_src * n, dtype=K.vec4d, device=device) if work is None else \
            work("power_terms", n_src * n, K.vec4d)
        wp.launch(K.power_sums_kernel, dim=n_src * n, inputs=[valid, weight], outputs=[terms], device=device,
                  record_tape=False)
        return source_sums(terms, n_src, wp.float64, device, work=work)
    from ..kernels.reduce import make_power_tree_kernel
    levels = len(widths)
    widths += [1, 1]
    out = wp.empty((n_src, 1), dtype=K.vec4d, device=device) if work is None else \
        work(("source_sums", 1), (n_src, 1), K.vec4d)
    wp.launch(make_power_tree_kernel(scalar), dim=n_src,
              inputs=[valid, weight, n, levels, widths[0], widths[1], WIDE], outputs=[out], device=device,
              record_tape=False)
    return out
