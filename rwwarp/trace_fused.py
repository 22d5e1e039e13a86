"""Host side of the CPU's trace through several surfaces in one launch (:mod:`rwwarp.kernels.trace_steps`, issue 25):
the tables its kernel reads, for :meth:`rwwarp.trace.Tracer._run`. Lengths in mm."""
from __future__ import annotations

import numpy as np
import warp as wp

from .kernels import trace as ktrace


def fused_tables(tracer, steps):
    """The tables of :mod:`rwwarp.kernels.trace_steps` for ``steps`` (:meth:`rwwarp.trace.Tracer._run`'s ``(kind,
    rows, rmask, n_in, n_out, t_buf)`` a surface): ``(rows, kinds, n_in, n_out)`` Warp arrays on ``tracer``'s
    device ((n_steps, N_PARAMS) surface rows, (n_steps,) kinds, (n_steps, n_wl) indices before and after each
    surface), or None where the fused kernel does not apply (no step, a phase surface, replicated gradient rows).
    From the tracer's :attr:`~rwwarp.trace.Tracer.pool` on a kept batch, written again each run (the values of the
    moment: a parameter changed in place is read)."""
    if not steps or any(k == ktrace.KIND_PHASE or rmask != 0 for k, _, rmask, _, _, _ in steps):
        return None
    sc = tracer.scalar
    tabs = (np.stack([r.numpy().reshape(-1) for _, r, _, _, _, _ in steps]),
            np.array([k for k, _, _, _, _, _ in steps], dtype=np.int32),
            np.stack([a.numpy().reshape(-1) for _, _, _, a, _, _ in steps]),
            np.stack([b.numpy().reshape(-1) for _, _, _, _, b, _ in steps]))
    dts = (sc, wp.int32, sc, sc)
    if tracer.pool is None:
        return tuple(wp.array(t, dtype=dt, device=tracer.device) for t, dt in zip(tabs, dts))
    out = []
    for tag, t, dt in zip(("rows", "kinds", "n_in", "n_out"), tabs, dts):
        a = tracer.work_array(("trace_steps", tag), t.shape, dt)
        a.numpy()[...] = t
        out.append(a)
    return tuple(out)


def step_kernels(tracer, steps, fused):
    """The Warp kernels :meth:`rwwarp.trace.Tracer._trace_range` launches for ``steps`` (``fused``: the tables of
    :func:`fused_tables`, or None), for :func:`rwwarp.trace.run_chunks` to load before its threads launch them."""
    if fused is not None:
        from .kernels.trace_steps import make_trace_steps_kernel
        return (make_trace_steps_kernel(tracer.scalar),)
    kinds = {k for k, *_ in steps}
    K = tracer.K
    curved = bool(kinds & {ktrace.KIND_REFRACT, ktrace.KIND_REFLECT, ktrace.KIND_PHASE})   # an intersect launch
    return tuple(k for k, use in ((K.intersect_kernel, curved), (K.phase_surface_kernel, ktrace.KIND_PHASE in kinds),
                                  (K.surface_kernel, bool(kinds - {ktrace.KIND_PHASE}))) if use)
