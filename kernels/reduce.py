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

On the CPU (issue 25: one launch a stage, not one a pass) ``power_tree_kernel`` forms a RayWave's per-ray power
terms ``(weight, weight if valid else 0, 0, 0)`` and sums them per source through the same tree of ``WIDE`` runs,
every level of it in one thread a source: the same additions in the same order as ``power_sums_kernel``
(:mod:`rwwarp.kernels.splat`) followed by the ``sum_wide_kernel`` passes, so the same bits, in one launch instead
of one plus one a level (a CPU launch runs its threads one after the other, so nothing runs in parallel that did
before).
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


@functools.cache
def make_power_tree_kernel(scalar):
    """``power_tree_kernel`` (module docstring) for ray weights of ``scalar`` (float32 or float64): launched with
    ``dim=n_src``; ``n`` the rays a source (source-major slots), ``levels`` (1 to 3) and ``w1``, ``w2`` the widths
    of the first two levels of the ``WIDE`` tree :func:`rwwarp.wave.reduce.source_sums` would pass through;
    writes each source's ``(launched power, valid power, 0, 0)`` into ``sums_out[s, 0]`` (float64)."""
    vec4d = wp.types.vector(4, wp.float64)
    f64 = wp.float64

    @wp.func
    def run_sum(valid: wp.array(dtype=wp.int32), weight: wp.array(dtype=scalar), base: int, lo: int, hi: int):
        # one run of the first level: 0 + term[lo] + ... + term[hi - 1], as sum_wide_kernel adds the stored terms
        acc = vec4d()
        for k in range(lo, hi):
            q = f64(weight[base + k])
            v = f64(0.0)
            if valid[base + k] == 1:
                v = q
            acc = acc + vec4d(q, v, f64(0.0), f64(0.0))
        return acc

    @wp.kernel(module="unique")
    def power_tree_kernel(valid: wp.array(dtype=wp.int32), weight: wp.array(dtype=scalar), n: int, levels: int,
                          w1: int, w2: int, width: int,
                          # outputs
                          sums_out: wp.array(dtype=vec4d, ndim=2)):
        s = wp.tid()
        base = s * n
        if levels == 1:
            sums_out[s, 0] = run_sum(valid, weight, base, 0, n)
        elif levels == 2:
            acc2 = vec4d()
            for b in range(w1):
                acc2 = acc2 + run_sum(valid, weight, base, b * width, wp.min(b * width + width, n))
            sums_out[s, 0] = acc2
        else:
            acc3 = vec4d()
            for c in range(w2):
                acc2 = vec4d()
                for b in range(c * width, wp.min(c * width + width, w1)):
                    acc2 = acc2 + run_sum(valid, weight, base, b * width, wp.min(b * width + width, n))
                acc3 = acc3 + acc2
            sums_out[s, 0] = acc3

    return power_tree_kernel
