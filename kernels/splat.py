"""Rays to a complex field on the DOE plane (Warp): atomic inverse-bilinear splatting.

Grid of one source: ``N x N`` samples, sample (row j, col i) at ``(x0 + i*pitch, y0 + j*pitch)``
(mm), flattened ``index = (source * N + j) * N + i``.

Each valid ray i (position p, direction d, optical path OPL, power q, ray-tube footprint area A on
the plane) adds, with bilinear weights b to its four neighbouring samples:

    energy: S += o * sqrt(q * A) * exp(1j * psi) / A_box   (o: overlap area of the ray's tube box,
            an axis-aligned box of area A, with the sample's cell; a conservative "box" splat that is
            exact when the tubes tile the plane, so aperture edges get their exact covered fraction)
    paper:  S += b * cos(theta) * exp(1j * psi)      (unit amplitude and the obliquity factor, with
            bilinear weights b: the paper's inverse bilinear interpolation)
    psi = k * (OPL - OPL_ref(p)),  k = 2 pi / lambda (1/mm)

In the energy convention ``U = S / pitch^2`` is the area average of a field whose irradiance is the
ray-tube irradiance q / A: it follows ray density, partly covered edge samples get the covered
fraction of the amplitude, and the field power ``sum |U|^2 pitch^2`` equals the traced power.
``energy == 2`` (pixel_values "flux", :mod:`rwwarp.wave.propagate`) makes ``U`` the scalar field whose z-flux
through the plane is that irradiance: each ray's amplitude is divided by ``sqrt(cos theta)`` (``|U|^2 =
q / (A cos theta)``, so ``Re(conj(U) dU/dz / (i k)) = cos theta |U|^2 = q / A`` for the ray's local plane wave).
A valid ray whose tube has no area (no valid neighbour along u or along v: :func:`tube_area_kernel` gives it
``A = 0`` and a point box) or no power deposits nothing and leaves before ``sqrt(q A)`` and the division by its
box area, whose adjoints at 0 are 0/0 = NaN even for a zero incoming gradient.

with the reference sphere ``OPL_ref(p) = OPL_c + n (|T - p_c| - |T - p|)`` converging to the point T
(``index`` negative: diverging from T)
(factoring it out keeps psi small, so the bilinear splat of the phasor is accurate and fits float32).
``theta`` is the ray angle to the DOE normal (z).

:func:`finalize_kernel` turns the sums into the field handed to the wave propagation
(energy: ``U = S / pitch^2``; paper: ``U = S``, a global scale is applied on the host),
multiplied by the reference sphere and divided by the carrier of the chief ray,
``exp(1j * (k (OPL_ref(p) - OPL_c) - 2 pi f_c . (p - p_c)))``, ``f_c`` in cycles/mm, so the result is
the physical field with the chief ray's tilt removed (baseband).

Float64 atomic additions on a GPU add in the order threads arrive, so the last bits of a sample's sum
change from run to run. The deterministic splat (``fixed``) adds fixed-point integers instead (see
:data:`FIXED_ONE`): a first launch (``fixed == 2``) writes each ray's amplitude, summed per source by the
fixed tree of :mod:`rwwarp.kernels.reduce` into the bound; the second (``fixed == 1``) adds the
contributions as int64 in units of ``bound / FIXED_ONE``; :func:`fixed_to_float_kernel` converts back.
Under a tape the float splat (``fixed == 0``) is recorded beside it for the adjoint, which only reads the
samples' gradients and is deterministic either way. The tube areas read the neighbours' positions, so their
adjoint adds into a position from several threads; in deterministic mode :func:`stencil_kernel` first copies
each ray's position into the slots of the rays that read it, and the tube-area kernel reads only its own
slots.
"""
import functools

import warp as wp


#: The deterministic splat's fixed point: a source's sums are integers in units of ``bound / FIXED_ONE``,
#: ``bound`` the sum of its rays' amplitudes, which no sample's sum can exceed (each ray deposits at most
#: its amplitude in all), so no int64 sum overflows (2^61 < 2^63). Resolution: ``bound`` x 4.3e-19 (each
#: contribution rounded to it). Against the float splat's field, measured: 2.3e-13 relative with 401^2 rays
#: (Cooke triplet, focal plan), 1e-11 with 5824^2 rays. Integer additions commute: the sums do not depend
#: on the order the GPU's threads arrive in.
FIXED_ONE = wp.constant(wp.float64(2.0 ** 61))


@functools.cache
def make_splat_kernels(scalar):
    """Splat kernels for ray scalar type ``scalar`` (fields are always accumulated in float64)."""
    vec3 = wp.types.vector(3, scalar)
    f64 = wp.float64
    vec4d = wp.types.vector(4, f64)

    @wp.func
    def sinc_half(a: f64):
        # sin(a / 2) / (a / 2): the mean of exp(1j g x) over an interval of length L, a = g L
        if wp.abs(a) < f64(1.0e-4):
            return f64(1.0) - a * a / f64(24.0)
        return wp.sin(f64(0.5) * a) / (f64(0.5) * a)

    @wp.func
    def ref_opl(p: wp.vec3d, ctr: wp.vec3d, tpt: wp.vec3d, n: f64, oplc: f64):
        return oplc + n * (wp.length(tpt - ctr) - wp.length(tpt - p))

    @wp.func
    def cell_offset(cells: wp.array(dtype=wp.vec3d), rim: int, j: int, n_side: int):
        # offset of pupil cell j's ray from the cell centre, in cells (0 without rim weighting); j indexes
        # cells (the source's table offset included)
        if rim == 0:
            return wp.vec2d()
        g = cells[j]
        h = f64(2.0) / f64(n_side)
        return wp.vec2d(g[1] / h, g[2] / h)

    @wp.kernel(module="unique")
    def stencil_kernel(
        pos: wp.array(dtype=vec3),
        n_side: int,                          # > 0: every source's grid; < 0: side_src[s] (packed batch)
        side_src: wp.array(dtype=wp.int32),   # (n_src,) each source's grid side with n_side < 0, else (1,)
        n_pupil: int,                         # ray slots per source with n_side < 0 (padding past side^2)
        # outputs
        nbr_out: wp.array2d(dtype=vec3),      # (n, 5): +u, -u, +v, -v neighbour and own position of each ray
    ):
        # ray j hands its position to the rays that read it (deterministic mode): each thread reads only its
        # own position and writes slots no other thread writes, so the adjoint adds without atomics contending
        j = wp.tid()
        side = n_side
        per = n_side * n_side
        if n_side < 0:
            per = n_pupil
            side = side_src[j // per]
        jj = j - (j // per) * per
        if jj >= side * side:
            return
        r = jj // side
        c = jj - r * side
        p = pos[j]
        nbr_out[j, 4] = p
        if c > 0:
            nbr_out[j - 1, 0] = p
        if c + 1 < side:
            nbr_out[j + 1, 1] = p
        if r > 0:
            nbr_out[j - side, 2] = p
        if r + 1 < side:
            nbr_out[j + side, 3] = p

    @wp.func
    def tube_pos(pos: wp.array(dtype=vec3), nbr: wp.array2d(dtype=vec3), stencil: int, i: int, k: int, off: int):
        # position of ray i + off: from the stencil's slot k (deterministic mode) or read directly
        if stencil == 1:
            return wp.vec3d(nbr[i, k])
        return wp.vec3d(pos[i + off])

    @wp.kernel(module="unique")
    def tube_area_kernel(
        pos: wp.array(dtype=vec3),
        valid: wp.array(dtype=wp.int32),
        n_side: int,                          # pupil grid is n_side x n_side per source (row-major); < 0:
                                              # each source's own side_src[s] in n_pupil slots (packed batch)
        cells: wp.array(dtype=wp.vec3d),      # with rim: (fraction, du, dv) per pupil cell (rays at centroids)
        rim: int,
        stencil: int,                         # 1: neighbours' positions from nbr (stencil_kernel), deterministic
        nbr: wp.array2d(dtype=vec3),          # (n, 5) with stencil, else (1, 5)
        side_src: wp.array(dtype=wp.int32),   # (n_src,) with n_side < 0, else (1,)
        n_pupil: int,                         # ray slots per source with n_side < 0 (padding invalid)
        cell_stride: int,                     # cells of source s start at s * cell_stride (0: one table)
        # outputs
        area_out: wp.array(dtype=f64),        # footprint area of each ray's pupil cell on the plane, mm^2
        half_out: wp.array(dtype=wp.vec2d),   # half sizes (x, y) of the tube's box, mm
    ):
        i = wp.tid()
        per = n_side * n_side
        if n_side < 0:
            per = n_pupil
        s = i // per
        j = i - s * per
        area_out[i] = f64(0.0)
        half_out[i] = wp.vec2d()
        if valid[i] == 0:
            return
        side = n_side
        if n_side < 0:
            side = side_src[s]
        r = j // side
        c = j - r * side
        cb = s * cell_stride
        # central differences where both neighbours are valid, one-sided otherwise: plane steps du, dv and
        # the pupil steps pu, pv they span (in cells: (1, 0) and (0, 1) on the regular grid; rim rays start
        # at their part-cell's centroid, so there the steps are the actual ones)
        du = wp.vec3d()
        pu = wp.vec2d()
        nu = 0
        if c + 1 < side and valid[i + 1] == 1:
            du = du + tube_pos(pos, nbr, stencil, i, 0, 1) - tube_pos(pos, nbr, stencil, i, 4, 0)
            pu = pu + wp.vec2d(f64(1.0), f64(0.0)) + cell_offset(cells, rim, cb + j + 1, side)
            pu = pu - cell_offset(cells, rim, cb + j, side)
            nu = nu + 1
        if c > 0 and valid[i - 1] == 1:
            du = du + tube_pos(pos, nbr, stencil, i, 4, 0) - tube_pos(pos, nbr, stencil, i, 1, -1)
            pu = pu + wp.vec2d(f64(1.0), f64(0.0)) + cell_offset(cells, rim, cb + j, side)
            pu = pu - cell_offset(cells, rim, cb + j - 1, side)
            nu = nu + 1
        dv = wp.vec3d()
        pv = wp.vec2d()
        nv = 0
        if r + 1 < side and valid[i + side] == 1:
            dv = dv + tube_pos(pos, nbr, stencil, i, 2, side) - tube_pos(pos, nbr, stencil, i, 4, 0)
            pv = pv + wp.vec2d(f64(0.0), f64(1.0)) + cell_offset(cells, rim, cb + j + side, side)
            pv = pv - cell_offset(cells, rim, cb + j, side)
            nv = nv + 1
        if r > 0 and valid[i - side] == 1:
            dv = dv + tube_pos(pos, nbr, stencil, i, 4, 0) - tube_pos(pos, nbr, stencil, i, 3, -side)
            pv = pv + wp.vec2d(f64(0.0), f64(1.0)) + cell_offset(cells, rim, cb + j, side)
            pv = pv - cell_offset(cells, rim, cb + j - side, side)
            nv = nv + 1
        if nu > 0 and nv > 0:
            du = du / f64(nu)
            dv = dv / f64(nv)
            pu = pu / f64(nu)
            pv = pv / f64(nv)
            # Jacobian J = X P^-1 (X = [du dv] on the plane, P = [pu pv] in the pupil, in cells): the plane
            # area of one pupil cell is |det X| / |det P|, and J's columns are the images of a cell's sides
            det_p = pu[0] * pv[1] - pv[0] * pu[1]
            a = wp.abs(du[0] * dv[1] - du[1] * dv[0]) / wp.max(wp.abs(det_p), f64(1.0e-300))
            area_out[i] = a
            if a > f64(0.0):
                # axis-aligned box of the same area, aspect from the Jacobian's diagonal (a degenerate Jacobian,
                # a = 0, keeps the point box written above: the square root's adjoint at 0 is 0/0 = NaN)
                j1x = (du[0] * pv[1] - dv[0] * pu[1]) / det_p
                j2y = (dv[1] * pu[0] - du[1] * pv[0]) / det_p
                wx = wp.max(wp.abs(j1x), f64(1.0e-300))
                wy = wp.max(wp.abs(j2y), f64(1.0e-300))
                sc = wp.sqrt(a / (wx * wy))
                half_out[i] = wp.vec2d(f64(0.5) * wx * sc, f64(0.5) * wy * sc)

    @wp.kernel(module="unique")
    def splat_kernel(
        pos: wp.array(dtype=vec3),
        dir: wp.array(dtype=vec3),
        opl: wp.array(dtype=scalar),
        valid: wp.array(dtype=wp.int32),
        weight: wp.array(dtype=scalar),
        area: wp.array(dtype=f64),            # ray-tube footprint area, mm^2 (energy convention)
        half: wp.array(dtype=wp.vec2d),       # ray-tube box half sizes, mm (energy convention)
        origin: wp.array(dtype=wp.vec2d),     # (n_src,) window origin, mm
        pitch: wp.array(dtype=f64),           # (n_src,) sample pitch, mm
        chief: wp.array(dtype=wp.vec3d),      # (n_src,) chief ray point on the plane, mm
        target: wp.array(dtype=wp.vec3d),     # (n_src,) reference sphere centre T, mm
        index: wp.array(dtype=f64),           # (n_src,) refractive index of the medium
        opl_chief: wp.array(dtype=f64),       # (n_src,) chief ray OPL at the plane, mm
        wavenumber: wp.array(dtype=f64),      # (n_src,) 2 pi / lambda, 1/mm
        use_reference: int,
        energy: int,                          # 0: paper, 1: energy, 2: energy, the flux-normalised field
        n_grid: int,                          # > 0: every window n_grid^2; < 0: windows of grid_src[s]^2 in
                                              # slots of -n_grid x -n_grid (packed batch)
        n_pupil: int,
        frac: wp.array(dtype=wp.vec3d),       # (n_pupil,) (fraction in the aperture, du, dv) per cell, or (1,)
        rim: int,                             # 1: the fraction applies (energy convention; the weight carries it)
        grid_src: wp.array(dtype=wp.int32),   # (n_src,) each window's side with n_grid < 0, else (1,)
        frac_stride: int,                     # frac of source s, cell j at s * frac_stride + j (0: one table)
        offset: int,                          # first ray of this launch (CPU threads splat ray ranges)
        fixed: int,                           # 0: float sums; 1: fixed-point sums (deterministic); 2: bounds only
        bound: wp.array2d(dtype=vec4d),       # (n_src, 1): per source the sum of the rays' amplitudes (fixed == 1)
        # outputs
        s_re_out: wp.array(dtype=f64),
        s_im_out: wp.array(dtype=f64),
        dropped_out: wp.array(dtype=wp.int32),
        acc_re_out: wp.array(dtype=wp.int64),  # fixed-point sums (fixed == 1), FIXED_ONE / bound per unit
        acc_im_out: wp.array(dtype=wp.int64),
        amp_out: wp.array(dtype=vec4d),       # per ray (amplitude, 0, 0, 0) (fixed == 2)
    ):
        i = wp.tid() + offset
        if valid[i] == 0:
            if fixed == 2:
                amp_out[i] = vec4d()
            return
        s = i // n_pupil
        ng = n_grid                           # this source's window side
        stride = n_grid                       # the slot's side
        if n_grid < 0:
            stride = -n_grid
            ng = grid_src[s]
        unit = f64(1.0)
        if fixed == 1:
            unit = FIXED_ONE / wp.max(bound[s, 0][0], f64(1.0e-300))
        pr = pos[i]
        p = wp.vec3d(f64(pr[0]), f64(pr[1]), f64(pr[2]))
        o = origin[s]
        h = pitch[s]
        ref = f64(0.0)
        if use_reference == 1:
            ref = ref_opl(p, chief[s], target[s], index[s], opl_chief[s])
        psi = wavenumber[s] * (f64(opl[i]) - ref)
        if energy >= 1:
            # conservative box deposit: overlap of the tube's box with the sample cells (up to 3 x 3), with
            # the ray's local phase slope across its tube (first-order splat): the phase at x in the box is
            # psi + g.(x - p), g = k n (d_xy - u_T), u_T the unit vector to T (the gradient of the OPL on the
            # plane is n d_xy, that of the reference sphere n u_T). Each overlap rectangle gets the exact
            # integral of exp(1j (psi + g.(x - p))): its area times exp(1j g.(centre - p)) times sinc per axis.
            hb = half[i]
            f = f64(1.0)
            if rim == 1:
                # a rim cell the aperture covers in part (fraction f, already in the weight; the ray starts
                # at the part's centroid): the tube's irradiance on f of its area, a box of f A about the ray
                f = frac[s * frac_stride + i - s * n_pupil][0]
                hb = hb * wp.sqrt(f)
            amp2 = f64(weight[i]) * area[i]
            # every sample cell the tube's box overlaps (a tube may span many cells: no power is lost)
            cx0 = int(wp.floor((p[0] - hb[0] - o[0]) / h + f64(0.5)))
            cy0 = int(wp.floor((p[1] - hb[1] - o[1]) / h + f64(0.5)))
            cx1 = int(wp.floor((p[0] + hb[0] - o[0]) / h + f64(0.5)))
            cy1 = int(wp.floor((p[1] + hb[1] - o[1]) / h + f64(0.5)))
            if fixed != 2:
                if cx0 < 0 or cy0 < 0 or cx1 >= ng or cy1 >= ng:
                    wp.atomic_add(dropped_out, s, 1)
                    return
                if amp2 == f64(0.0):
                    # nothing to deposit: a zero-area tube (a valid ray with no valid neighbour along u or v, e.g.
                    # a lone rim ray; tube_area_kernel gives it area 0 and a point box) or zero power. Leave before
                    # the square root and the division by the box area: in the forward they give 0 and 0/0 that no
                    # cell reads (a point overlaps no cell), but their adjoints are 0/0 = NaN even with a zero
                    # incoming gradient, and that NaN reached area, half and (energy == 2) dir, so the tracer's
                    # refraction adjoints carried it to the surface parameters
                    return
            amp = wp.sqrt(amp2)
            if energy == 2:
                # the field whose z-flux is the tube's irradiance: amplitude / sqrt(cos theta) (theta: the ray's
                # angle to the plane's normal, in the medium after it)
                dc = dir[i]
                dn = wp.sqrt(f64(dc[0]) * f64(dc[0]) + f64(dc[1]) * f64(dc[1]) + f64(dc[2]) * f64(dc[2]))
                amp = amp / wp.sqrt(wp.max(wp.abs(f64(dc[2])) / dn, f64(1.0e-12)))
            if rim == 1:
                amp = amp * wp.sqrt(f)
            if fixed == 2:
                amp_out[i] = vec4d(amp, f64(0.0), f64(0.0), f64(0.0))
                return
            gx = f64(0.0)
            gy = f64(0.0)
            if use_reference == 1:
                dr = dir[i]
                ut = wp.normalize(target[s] - p)
                # index[s] carries the sphere's sign (+ converging to T, - diverging from it)
                gx = wavenumber[s] * (wp.abs(index[s]) * f64(dr[0]) - index[s] * ut[0])
                gy = wavenumber[s] * (wp.abs(index[s]) * f64(dr[1]) - index[s] * ut[1])
            pre = amp / (f64(4.0) * hb[0] * hb[1])
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
                        if fixed == 1:
                            wp.atomic_add(acc_re_out, k, wp.int64(wp.round(w * wp.cos(ph) * unit)))
                            wp.atomic_add(acc_im_out, k, wp.int64(wp.round(w * wp.sin(ph) * unit)))
                        else:
                            wp.atomic_add(s_re_out, k, w * wp.cos(ph))
                            wp.atomic_add(s_im_out, k, w * wp.sin(ph))
            return
        # paper convention: unit amplitude with obliquity, inverse bilinear interpolation
        fx = (p[0] - o[0]) / h
        fy = (p[1] - o[1]) / h
        ix = int(wp.floor(fx))
        iy = int(wp.floor(fy))
        if ix < 0 or iy < 0 or ix >= ng - 1 or iy >= ng - 1:
            wp.atomic_add(dropped_out, s, 1)
            return
        ax = fx - f64(ix)
        ay = fy - f64(iy)
        amp = wp.abs(f64(dir[i][2]))
        if fixed == 2:
            amp_out[i] = vec4d(amp, f64(0.0), f64(0.0), f64(0.0))
            return
        pre = amp * wp.cos(psi)
        pim = amp * wp.sin(psi)
        base = (s * stride + iy) * stride + ix
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
            k = base + cy * stride + cx
            if fixed == 1:
                wp.atomic_add(acc_re_out, k, wp.int64(wp.round(b * pre * unit)))
                wp.atomic_add(acc_im_out, k, wp.int64(wp.round(b * pim * unit)))
            else:
                wp.atomic_add(s_re_out, k, b * pre)
                wp.atomic_add(s_im_out, k, b * pim)

    @wp.kernel(module="unique")
    def finalize_kernel(
        s_re: wp.array(dtype=f64),
        s_im: wp.array(dtype=f64),
        origin: wp.array(dtype=wp.vec2d),
        pitch: wp.array(dtype=f64),
        chief: wp.array(dtype=wp.vec3d),
        target: wp.array(dtype=wp.vec3d),
        index: wp.array(dtype=f64),
        wavenumber: wp.array(dtype=f64),
        carrier: wp.array(dtype=wp.vec2d),    # (n_src,) chief-ray spatial frequency, cycles/mm
        use_reference: int,
        energy: int,
        n_grid: int,                          # > 0: every window n_grid^2; < 0: windows of grid_src[s]^2 in
                                              # slots of -n_grid x -n_grid (packed batch; the rest is zero)
        grid_src: wp.array(dtype=wp.int32),   # (n_src,) with n_grid < 0, else (1,)
        skip_zero: int,                       # 1: a sample whose sums are both 0 is written 0 without its phase
                                              # (the same value; forward only: no adjoint reads it)
        offset: int,                          # first sample of this launch (CPU threads finalize ranges)
        # outputs
        field_out: wp.array(dtype=wp.vec2d),  # (re, im)
    ):
        k = wp.tid() + offset
        stride = n_grid
        if n_grid < 0:
            stride = -n_grid
        per = stride * stride
        s = k // per
        rem = k - s * per
        j = rem // stride
        i = rem - j * stride
        if n_grid < 0:
            if i >= grid_src[s] or j >= grid_src[s]:
                field_out[k] = wp.vec2d()   # outside this source's own window
                return
        h = pitch[s]
        o = origin[s]
        re = s_re[k]
        im = s_im[k]
        if skip_zero == 1:
            if re == f64(0.0) and im == f64(0.0):
                field_out[k] = wp.vec2d()   # no ray reached it: 0 times the phase factor
                return
        if energy >= 1:
            re = re / (h * h)
            im = im / (h * h)
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

    @wp.kernel(module="unique")
    def fixed_to_float_kernel(
        acc_re: wp.array(dtype=wp.int64),
        acc_im: wp.array(dtype=wp.int64),
        bound: wp.array2d(dtype=vec4d),
        per_source: int,                      # samples per source (n_grid^2)
        # outputs
        s_re_out: wp.array(dtype=f64),
        s_im_out: wp.array(dtype=f64),
    ):
        # the fixed-point sums of the deterministic splat back to float64 (off the tape: the float splat
        # recorded beside it carries the adjoint)
        k = wp.tid()
        unit = FIXED_ONE / wp.max(bound[k // per_source, 0][0], f64(1.0e-300))
        s_re_out[k] = f64(acc_re[k]) / unit
        s_im_out[k] = f64(acc_im[k]) / unit

    @wp.kernel(module="unique")
    def power_sums_kernel(
        valid: wp.array(dtype=wp.int32),
        weight: wp.array(dtype=scalar),
        # outputs
        terms_out: wp.array(dtype=vec4d),   # per ray: (launched power, power if valid, 0, 0)
    ):
        # summed per source by rwwarp.wave.reduce.source_sums (a fixed tree: deterministic, no atomics)
        i = wp.tid()
        q = f64(weight[i])
        v = f64(0.0)
        if valid[i] == 1:
            v = q
        terms_out[i] = vec4d(q, v, f64(0.0), f64(0.0))

    class K:
        pass

    K.splat_kernel = splat_kernel
    K.fixed_to_float_kernel = fixed_to_float_kernel
    K.vec4d = vec4d
    K.tube_area_kernel = tube_area_kernel
    K.stencil_kernel = stencil_kernel
    K.power_sums_kernel = power_sums_kernel
    K.finalize_kernel = finalize_kernel
    return K
