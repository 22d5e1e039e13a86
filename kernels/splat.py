"""Rays to a complex field on the DOE plane (Warp): atomic inverse-bilinear splatting.

Grid of one source: ``N x N`` samples, sample (row j, col i) at ``(x0 + i*pitch, y0 + j*pitch)``
(mm), flattened ``index = (source * N + j) * N + i``.

Each valid ray i (position p, direction d, optical path OPL, power q) adds, with bilinear weights
b to its four neighbouring samples:

    S += b * cos(theta) * exp(1j * psi),   psi = k * (OPL - OPL_ref(p))      (k = 2 pi / lambda, 1/mm)
    B += b,   Bc += b * cos(theta),   Q += b * q

with the reference sphere ``OPL_ref(p) = OPL_c + n (|T - p_c| - |T - p|)`` converging to the point T
(factoring it out keeps psi small, so the bilinear splat of the phasor is accurate and fits float32).
``theta`` is the ray angle to the DOE normal (z).

:func:`finalize_kernel` turns the sums into the field handed to the wave propagation:

    energy: U = S / Bc * sqrt(Q) / pitch      (irradiance follows ray density, power = traced power)
    paper:  U = S                             (unit ray amplitude; a global scale is applied on the host)

multiplied by the reference sphere and divided by the carrier of the chief ray,
``exp(1j * (k (OPL_ref(p) - OPL_c) - 2 pi f_c . (p - p_c)))``, ``f_c`` in cycles/mm, so the result is
the physical field with the chief ray's tilt removed (baseband).
"""
import functools

import warp as wp


@functools.cache
def make_splat_kernels(scalar):
    """Splat kernels for ray scalar type ``scalar`` (fields are always accumulated in float64)."""
    vec3 = wp.types.vector(3, scalar)
    f64 = wp.float64

    @wp.func
    def ref_opl(p: wp.vec3d, ctr: wp.vec3d, tpt: wp.vec3d, n: f64, oplc: f64):
        return oplc + n * (wp.length(tpt - ctr) - wp.length(tpt - p))

    @wp.kernel(module="unique")
    def splat_kernel(
        pos: wp.array(dtype=vec3),
        dir: wp.array(dtype=vec3),
        opl: wp.array(dtype=scalar),
        valid: wp.array(dtype=wp.int32),
        weight: wp.array(dtype=scalar),
        origin: wp.array(dtype=wp.vec2d),     # (n_src,) window origin, mm
        pitch: wp.array(dtype=f64),           # (n_src,) sample pitch, mm
        chief: wp.array(dtype=wp.vec3d),      # (n_src,) chief ray point on the plane, mm
        target: wp.array(dtype=wp.vec3d),     # (n_src,) reference sphere centre T, mm
        index: wp.array(dtype=f64),           # (n_src,) refractive index of the medium
        opl_chief: wp.array(dtype=f64),       # (n_src,) chief ray OPL at the plane, mm
        wavenumber: wp.array(dtype=f64),      # (n_src,) 2 pi / lambda, 1/mm
        use_reference: int,
        n_grid: int,
        n_pupil: int,
        # outputs
        s_re_out: wp.array(dtype=f64),
        s_im_out: wp.array(dtype=f64),
        b_out: wp.array(dtype=f64),
        bc_out: wp.array(dtype=f64),
        q_out: wp.array(dtype=f64),
        dropped_out: wp.array(dtype=wp.int32),
    ):
        i = wp.tid()
        if valid[i] == 0:
            return
        s = i // n_pupil
        pr = pos[i]
        p = wp.vec3d(f64(pr[0]), f64(pr[1]), f64(pr[2]))
        dr = dir[i]
        o = origin[s]
        h = pitch[s]
        fx = (p[0] - o[0]) / h
        fy = (p[1] - o[1]) / h
        ix = int(wp.floor(fx))
        iy = int(wp.floor(fy))
        if ix < 0 or iy < 0 or ix >= n_grid - 1 or iy >= n_grid - 1:
            wp.atomic_add(dropped_out, s, 1)
            return
        ax = fx - f64(ix)
        ay = fy - f64(iy)
        ref = f64(0.0)
        if use_reference == 1:
            ref = ref_opl(p, chief[s], target[s], index[s], opl_chief[s])
        psi = wavenumber[s] * (f64(opl[i]) - ref)
        cos_t = wp.abs(f64(dr[2]))
        pre = cos_t * wp.cos(psi)
        pim = cos_t * wp.sin(psi)
        q = f64(weight[i])
        base = (s * n_grid + iy) * n_grid + ix
        for c in range(4):
            cx = c % 2
            cy = c // 2
            bx = ax
            if cx == 0:
                bx = f64(1.0) - ax
            by = ay
            if cy == 0:
                by = f64(1.0) - ay
            b = bx * by
            k = base + cy * n_grid + cx
            wp.atomic_add(s_re_out, k, b * pre)
            wp.atomic_add(s_im_out, k, b * pim)
            wp.atomic_add(b_out, k, b)
            wp.atomic_add(bc_out, k, b * cos_t)
            wp.atomic_add(q_out, k, b * q)

    @wp.kernel(module="unique")
    def finalize_kernel(
        s_re: wp.array(dtype=f64),
        s_im: wp.array(dtype=f64),
        b: wp.array(dtype=f64),
        bc: wp.array(dtype=f64),
        q: wp.array(dtype=f64),
        origin: wp.array(dtype=wp.vec2d),
        pitch: wp.array(dtype=f64),
        chief: wp.array(dtype=wp.vec3d),
        target: wp.array(dtype=wp.vec3d),
        index: wp.array(dtype=f64),
        wavenumber: wp.array(dtype=f64),
        carrier: wp.array(dtype=wp.vec2d),    # (n_src,) chief-ray spatial frequency, cycles/mm
        use_reference: int,
        energy: int,
        n_grid: int,
        # outputs
        field_out: wp.array(dtype=wp.vec2d),  # (re, im)
    ):
        k = wp.tid()
        per = n_grid * n_grid
        s = k // per
        rem = k - s * per
        j = rem // n_grid
        i = rem - j * n_grid
        h = pitch[s]
        o = origin[s]
        re = s_re[k]
        im = s_im[k]
        if energy == 1:
            amp = f64(0.0)
            if bc[k] > f64(1.0e-12):
                amp = wp.sqrt(wp.max(q[k], f64(0.0))) / (bc[k] * h)
            re = re * amp
            im = im * amp
        c = chief[s]
        p = wp.vec3d(o[0] + f64(i) * h, o[1] + f64(j) * h, c[2])
        ph = f64(0.0)
        if use_reference == 1:
            ph = wavenumber[s] * index[s] * (wp.length(target[s] - c) - wp.length(target[s] - p))
        fc = carrier[s]
        ph = ph - f64(6.283185307179586) * (fc[0] * (p[0] - c[0]) + fc[1] * (p[1] - c[1]))
        cph = wp.cos(ph)
        sph = wp.sin(ph)
        field_out[k] = wp.vec2d(re * cph - im * sph, re * sph + im * cph)

    class K:
        pass

    K.splat_kernel = splat_kernel
    K.finalize_kernel = finalize_kernel
    return K
