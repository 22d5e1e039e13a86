"""The CPU's trace through several surfaces in one launch (issue 25: one launch a stage for a batch of sources,
not one a surface).

``trace_steps_kernel`` carries each ray through ``n_steps`` surfaces of the kinds ``surface_kernel`` handles
without a phase (:data:`~rwwarp.kernels.trace.KIND_REFRACT`, ``KIND_REFLECT``, ``KIND_THIN``, ``KIND_PLANE``):
for each, the converged intersection of ``intersect_kernel`` (curved surfaces) and then ``surface_kernel``'s
step from it, through the same device functions (``converged_root``, ``surface_step``) with the ray's state in
registers in place of the arrays between the launches (the same operations in the same order: the same bits; tests/kernels/
test_trace_steps.py); a ray once lost reads no further surface (the per-surface launches leave it as it is). Forward only (no adjoint: :meth:`rwwarp.trace.Tracer._trace_range` takes it only for a
tracer without gradients, on the CPU, where a launch's threads run one after the other, so it keeps every
ray's arithmetic and drops the launches and the intermediate states' memory traffic).

Per step ``s``: ``rows[s]`` the surface's parameter row (the table of :mod:`rwwarp.kernels.trace`), ``kinds[s]``,
``n_in[s, w]`` / ``n_out[s, w]`` the indices before / after it at wavelength index ``w``. Lengths in mm.
"""
import functools

import warp as wp

from .trace import KIND_REFLECT, KIND_REFRACT, make_trace_kernels


@functools.cache
def make_trace_steps_kernel(scalar):
    """``trace_steps_kernel`` (module docstring) for rays of ``scalar`` (float32 or float64)."""
    K = make_trace_kernels(scalar)
    vec3 = K.vec3
    load_surface, converged_root, surface_step = K.load_surface, K.converged_root, K.surface_step

    @wp.kernel(module="unique", enable_backward=False)
    def trace_steps_kernel(
        pos: wp.array(dtype=vec3),
        dir: wp.array(dtype=vec3),
        opl: wp.array(dtype=scalar),
        valid: wp.array(dtype=wp.int32),
        wl: wp.array(dtype=wp.int32),
        rows: wp.array2d(dtype=scalar),     # (n_steps, N_PARAMS) each step's surface row
        kinds: wp.array(dtype=wp.int32),    # (n_steps,) surface kind (no KIND_PHASE)
        n_in: wp.array2d(dtype=scalar),     # (n_steps, n_wl) index before each surface
        n_out: wp.array2d(dtype=scalar),    # (n_steps, n_wl) index after each surface
        n_steps: int,
        # outputs: the state after the last step
        pos_out: wp.array(dtype=vec3),
        dir_out: wp.array(dtype=vec3),
        opl_out: wp.array(dtype=scalar),
        valid_out: wp.array(dtype=wp.int32),
    ):
        i = wp.tid()
        p0 = pos[i]
        d = dir[i]
        o = opl[i]
        ok = valid[i]
        w = wl[i]
        for s in range(n_steps):
            if ok != 1:
                break   # a lost (or padding) ray keeps its state through every later surface: nothing to read
            kind = kinds[s]
            sf = load_surface(rows[s])
            q = vec3(p0[0], p0[1], p0[2] - sf.z)
            # intersect_kernel: the converged root (0 for an invalid ray; not read then)
            t_start = scalar(0.0)
            if ok == 1 and (kind == KIND_REFRACT or kind == KIND_REFLECT):
                t_start = converged_root(q, d, sf)
            # surface_kernel
            n1 = n_in[s, w]
            n2 = n_out[s, w]
            t, newd, extra, ok = surface_step(kind, q, d, t_start, sf, n1, n2, ok)
            # ray_out: a lost ray keeps its input state
            if ok == 1:
                p0 = vec3(q[0] + t * d[0], q[1] + t * d[1], q[2] + t * d[2] + sf.z)
                d = newd
                o = o + n1 * t + extra
        pos_out[i] = p0
        dir_out[i] = d
        opl_out[i] = o
        v = 0
        if ok == 1:
            v = 1
        valid_out[i] = v

    return trace_steps_kernel
