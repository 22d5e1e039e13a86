"""Deterministic per-source sums (Warp): a fixed tree of 16-wide partial sums instead of atomics.

Per-ray quantities of ``n_src`` sources laid out source-major, ``value[s * n + i]``, are summed per source
by repeated passes; each pass replaces every run of ``WIDTH`` consecutive entries of a source by its sum
(the last run may be shorter):

    level 0: (n_src, n) -> (n_src, ceil(n / 16)) -> ... -> (n_src, 1)

Every thread adds its 16 entries in index order, so the result does not depend on thread scheduling:
run to run and device to device the same inputs give the same bits (the float64 atomics this replaces
add in the order the GPU's threads happen to arrive, and contend on one address per source). The
16-term loop has a compile-time bound, which Warp unrolls, so the sums are differentiable under
``wp.Tape`` (the adjoint of a pass hands each entry its run's gradient).

Without gradients, ``sum_wide_kernel`` adds a run-time number of entries per thread (a dynamic loop,
not differentiable): the same fixed order, in fewer passes (``WIDE`` entries each: three passes for a
million rays instead of five).

Values are ``wp.vec4`` of the ray scalar type (up to four quantities summed in one tree). Host code:
:func:`rwwarp.wave.reduce.source_sums`.
"""
import functools

import warp as wp

WIDTH = 16
#: entries per thread of a pass without gradients (``sum_wide_kernel``)
WIDE = 256


@functools.cache
def make_reduce_kernels(scalar):
    """The pass kernels ``sum16_kernel`` (differentiable) and ``sum_wide_kernel`` for vec4 values of ``scalar``
    (float32 or float64)."""
    vec4 = wp.types.vector(4, scalar)

    @wp.kernel(module="unique")
    def sum16_kernel(values: wp.array(dtype=vec4, ndim=2),
                     # outputs
                     sums_out: wp.array(dtype=vec4, ndim=2)):
        s, b = wp.tid()
        n = values.shape[1]
        acc = vec4()
        for j in range(16):
            k = b * 16 + j
            if k < n:
                acc = acc + values[s, k]
        sums_out[s, b] = acc

    @wp.kernel(module="unique")
    def sum_wide_kernel(values: wp.array(dtype=vec4, ndim=2), width: int,
                        # outputs
                        sums_out: wp.array(dtype=vec4, ndim=2)):
        s, b = wp.tid()
        n = values.shape[1]
        acc = vec4()
        for k in range(b * width, wp.min(b * width + width, n)):
            acc = acc + values[s, k]
        sums_out[s, b] = acc

    class K:
        pass

    K.sum16_kernel = sum16_kernel
    K.sum_wide_kernel = sum_wide_kernel
    K.vec4 = vec4
    return K
