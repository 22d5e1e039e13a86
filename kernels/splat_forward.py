"""The energy convention's float splat in separable form, forward only (Warp): what
:mod:`rwwarp.kernels.splat`'s ``splat_kernel`` adds with ``energy >= 1`` and ``fixed == 0``, with each ray's
deposits formed from per-column and per-row factors.

A ray's deposit into sample cell (ix, iy) is (``splat_kernel``'s box splat)

    w exp(1j ph),  w = ox oy pre sinc(gx ox / 2) sinc(gy oy / 2),  ph = psi + gx mx + gy my,

``ox`` / ``mx`` depending on the column alone and ``oy`` / ``my`` on the row alone, so it is the product

    pre exp(1j psi) * X(ix) * Y(iy),  X = ox sinc(gx ox / 2) exp(1j gx mx),  Y = oy sinc(gy oy / 2) exp(1j gy my):

three transcendentals a column and a row instead of four a cell (a tube box ``b`` cells across: ``6 b`` against
``4 b^2``). The same sums in exact arithmetic; in float64 each deposit differs by a few units of the last place
(the phase split into three factors). A box wider than :data:`MAX_CELLS` cells along an axis takes the per-cell
form. No adjoint: the host uses it off the tape (a tape records ``splat_kernel``).
"""
import functools

import warp as wp

#: Columns / rows of a ray's tube box kept as factors (a wider box is deposited cell by cell)
MAX_CELLS = 16


@functools.cache
def make_splat_forward_kernel(scalar):
    """The separable forward splat for ray scalar type ``scalar`` (sums in float64); its arguments are
    ``splat_kernel``'s up to ``frac_stride``, then ``offset`` (first ray of the launch) and the outputs
    ``s_re``, ``s_im``, ``dropped``."""
    vec3 = wp.types.vector(3, scalar)
    f64 = wp.float64
    vecm = wp.types.vector(MAX_CELLS, f64)
    intm = wp.types.vector(MAX_CELLS, wp.int32)

    @wp.func
    def sinc_half(a: f64):
        # sin(a / 2) / (a / 2), as splat_kernel's
        if wp.abs(a) < f64(1.0e-4):
            return f64(1.0) - a * a / f64(24.0)
        return wp.sin(f64(0.5) * a) / (f64(0.5) * a)

    @wp.kernel(enable_backward=False, module="unique")
    def splat_forward_kernel(
        pos: wp.array(dtype=vec3),
        dir: wp.array(dtype=vec3),
        opl: wp.array(dtype=scalar),
        valid: wp.array(dtype=wp.int32),
        weight: wp.array(dtype=scalar),
        area: wp.array(dtype=f64),
        half: wp.array(dtype=wp.vec2d),
        origin: wp.array(dtype=wp.vec2d),
        pitch: wp.array(dtype=f64),
        chief: wp.array(dtype=wp.vec3d),
        target: wp.array(dtype=wp.vec3d),
        index: wp.array(dtype=f64),
        opl_chief: wp.array(dtype=f64),
        wavenumber: wp.array(dtype=f64),
        use_reference: int,
        energy: int,                          # 1 or 2 (splat_kernel's energy conventions)
        n_grid: int,
        n_pupil: int,
        frac: wp.array(dtype=wp.vec3d),
        rim: int,
        grid_src: wp.array(dtype=wp.int32),
        frac_stride: int,
        offset: int,                          # first ray of this launch
        # outputs
        s_re_out: wp.array(dtype=f64),
        s_im_out: wp.array(dtype=f64),
        dropped_out: wp.array(dtype=wp.int32),
    ):
        i = wp.tid() + offset
        if valid[i] == 0:
            return
        s = i // n_pupil
        ng = n_grid
        stride = n_grid
        if n_grid < 0:
            stride = -n_grid
            ng = grid_src[s]
        pr = pos[i]
        p = wp.vec3d(f64(pr[0]), f64(pr[1]), f64(pr[2]))
        o = origin[s]
        h = pitch[s]
        ref = f64(0.0)
        if use_reference == 1:
            ctr = chief[s]
            tpt = target[s]
            ref = opl_chief[s] + index[s] * (wp.length(tpt - ctr) - wp.length(tpt - p))
        psi = wavenumber[s] * (f64(opl[i]) - ref)
        hb = half[i]
        f = f64(1.0)
        if rim == 1:
            f = frac[s * frac_stride + i - s * n_pupil][0]
            hb = hb * wp.sqrt(f)
        amp2 = f64(weight[i]) * area[i]
        cx0 = int(wp.floor((p[0] - hb[0] - o[0]) / h + f64(0.5)))
        cy0 = int(wp.floor((p[1] - hb[1] - o[1]) / h + f64(0.5)))
        cx1 = int(wp.floor((p[0] + hb[0] - o[0]) / h + f64(0.5)))
        cy1 = int(wp.floor((p[1] + hb[1] - o[1]) / h + f64(0.5)))
        if cx0 < 0 or cy0 < 0 or cx1 >= ng or cy1 >= ng:
            wp.atomic_add(dropped_out, s, 1)
            return
        if amp2 == f64(0.0):
            return
        amp = wp.sqrt(amp2)
        if energy == 2:
            dc = dir[i]
            dn = wp.sqrt(f64(dc[0]) * f64(dc[0]) + f64(dc[1]) * f64(dc[1]) + f64(dc[2]) * f64(dc[2]))
            amp = amp / wp.sqrt(wp.max(wp.abs(f64(dc[2])) / dn, f64(1.0e-12)))
        if rim == 1:
            amp = amp * wp.sqrt(f)
        gx = f64(0.0)
        gy = f64(0.0)
        if use_reference == 1:
            dr = dir[i]
            ut = wp.normalize(target[s] - p)
            gx = wavenumber[s] * (wp.abs(index[s]) * f64(dr[0]) - index[s] * ut[0])
            gy = wavenumber[s] * (wp.abs(index[s]) * f64(dr[1]) - index[s] * ut[1])
        pre = amp / (f64(4.0) * hb[0] * hb[1])
        ncx = cx1 - cx0 + 1
        ncy = cy1 - cy0 + 1
        if ncx > MAX_CELLS or ncy > MAX_CELLS:
            # a box of many cells: splat_kernel's per-cell deposit
            for iy in range(cy0, cy1 + 1):
                for ix in range(cx0, cx1 + 1):
                    xc = o[0] + f64(ix) * h
                    yc = o[1] + f64(iy) * h
                    ox = wp.min(p[0] + hb[0], xc + f64(0.5) * h) - wp.max(p[0] - hb[0], xc - f64(0.5) * h)
                    oy = wp.min(p[1] + hb[1], yc + f64(0.5) * h) - wp.max(p[1] - hb[1], yc - f64(0.5) * h)
                    if ox > f64(0.0) and oy > f64(0.0):
                        k = (s * stride + iy) * stride + ix
                        mx = wp.max(p[0] - hb[0], xc - f64(0.5) * h) + f64(0.5) * ox - p[0]
                        my = wp.max(p[1] - hb[1], yc - f64(0.5) * h) + f64(0.5) * oy - p[1]
                        ph = psi + gx * mx + gy * my
                        w = ox * oy * pre * sinc_half(gx * ox) * sinc_half(gy * oy)
                        wp.atomic_add(s_re_out, k, w * wp.cos(ph))
                        wp.atomic_add(s_im_out, k, w * wp.sin(ph))
            return
        # the columns' factors X (0 where the box does not overlap the column)
        xr = vecm()
        xi = vecm()
        xin = intm()
        for c in range(ncx):
            xc = o[0] + f64(cx0 + c) * h
            ox = wp.min(p[0] + hb[0], xc + f64(0.5) * h) - wp.max(p[0] - hb[0], xc - f64(0.5) * h)
            if ox > f64(0.0):
                mx = wp.max(p[0] - hb[0], xc - f64(0.5) * h) + f64(0.5) * ox - p[0]
                ax = ox * sinc_half(gx * ox)
                xr[c] = ax * wp.cos(gx * mx)
                xi[c] = ax * wp.sin(gx * mx)
                xin[c] = 1
        # the ray's factor pre exp(1j psi)
        pr_re = pre * wp.cos(psi)
        pr_im = pre * wp.sin(psi)
        for r in range(ncy):
            iy = cy0 + r
            yc = o[1] + f64(iy) * h
            oy = wp.min(p[1] + hb[1], yc + f64(0.5) * h) - wp.max(p[1] - hb[1], yc - f64(0.5) * h)
            if oy > f64(0.0):
                my = wp.max(p[1] - hb[1], yc - f64(0.5) * h) + f64(0.5) * oy - p[1]
                ay = oy * sinc_half(gy * oy)
                yr = ay * wp.cos(gy * my)
                yi = ay * wp.sin(gy * my)
                rr = pr_re * yr - pr_im * yi
                ri = pr_re * yi + pr_im * yr
                base = (s * stride + iy) * stride + cx0
                for c in range(ncx):
                    if xin[c] == 1:
                        wp.atomic_add(s_re_out, base + c, rr * xr[c] - ri * xi[c])
                        wp.atomic_add(s_im_out, base + c, rr * xi[c] + ri * xr[c])

    return splat_forward_kernel
