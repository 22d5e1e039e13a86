"""Coherent ray tracing kernels (Warp): ray generation, one surface per launch, sensor plane.

Rays are structure-of-arrays, index ``i = source * n_pupil + pupil_sample``:
``pos`` (vec3, mm), ``dir`` (unit vec3), ``opl`` (optical path length, mm), ``valid`` (int32 0/1),
``wl`` (int32 index into the per-wavelength index tables). Light travels +z.

Surface parameters live in one float array per surface (so ``wp.Tape`` accumulates gradients for
them, and torch builds the table as one tensor); its columns are the ``P_*`` constants below. Kernel code
never indexes them: ``load_surface`` reads a row once into the ``Surface`` struct and the geometry uses
its named fields (``sf.c``, ``sf.asph``, ``sf.sd``, ...). The kernels read a surface's row from ``R`` copies
(``params_rows``, ray ``i`` reads copy ``i & (R - 1)``): while recording, ``replicate_kernel`` makes the
copies on the tape, so the adjoint's atomic additions into a parameter spread over ``R`` addresses
instead of all rays contending for one (on an H100 the trace adjoint of the Cooke hybrid's design step
took 1.7 s of its 2.2 s of device time with a single copy), and its own adjoint sums the copies back
(per thread over a group of rows, then one atomic addition per group). Without a tape ``R = 1``. Geometry of a standard surface, local
coordinates q = pos - (0, 0, z_vertex), r2 = qx^2 + qy^2:

    sag(r2) = c r2 / (1 + sqrt(1 - (1 + k) c^2 r2)) + a2 r2 + sum_i a_i r2^(i+2)     (a_0 is the r^4 term)
    dsag/dr2 = c / (2 sqrt(1 - (1 + k) c^2 r2)) + a2 + sum_i (i+2) a_i r2^(i+1)

Intersection: the stable root of the base sphere c|q + t d|^2 - 2(q_z + t d_z) = 0,
``t = F / (B + sign(B) sqrt(B^2 - c F))`` with ``B = d_z - c q.d``, ``F = c|q|^2 - 2 q_z`` (no special
case for c = 0), then ``NEWTON_STEPS`` Newton steps on ``g(t) = q_z + t d_z - sag(r2(t))`` in
``intersect_kernel`` (launched off the tape), and one more, differentiable, in ``surface_kernel``.
Refraction: vector Snell's law with mu = n_in/n_out; total internal reflection, a missed surface,
an unconverged Newton or a hit outside the clear aperture make the ray invalid. Invalid rays keep
finite values (position and direction of their last valid state): no NaN leaves a kernel.

OPL accumulates ``n_in * t`` (t signed: a ray started on a virtual entrance-pupil plane behind
the first vertex travels back in object space).

The ideal thin lens (kind THIN) maps direction tangents ``t' = (n_in t - p P) / n_out`` (P the power
1/f) and adds the path that makes every ray from an object point reach its image point with equal
optical path (a perfect spherical wave behind it; a plane wave when the object sits at its front
focal plane). The object-side conjugate distance ``u`` and image-side ``v`` (mm, 1/u = 0 for an
object at infinity, v = 0 for an image at infinity) come from the host; a negative u (a converging input, the
virtual object behind the lens) or v (a diverging output, the virtual image in front) flips the sign of that
side's path difference.

A phase surface (kind PHASE, ``phase_surface_kernel``) is a refracting surface of any sag above that
also carries a diffractive phase ``phi(x, y) = sum_i A_i rho^(2 i)``, ``rho = r / R`` (radians; Zemax
``BINARY_2``), of which one diffraction order ``m`` is traced. At the intersection (the same Newton
root as a refracting surface) the local grating equation bends the ray:

    n' d'_t = n d_t + (m lambda / 2 pi) grad_t(phi),    n' d'_N = sqrt(n'^2 - |n' d'_t|^2)

(``_t``: the components in the tangent plane, ``N`` the unit normal oriented along the ray, ``grad_t`` the
tangential part of ``(dphi/dx, dphi/dy, 0)``, lambda the ray's vacuum wavelength in mm), and the optical
path gains ``m lambda phi / (2 pi)``, so the eikonal keeps the phase (the rays stay normal to the wavefront
and the coherent sum sees ``exp(i m phi)``). ``m lambda / 2 pi`` is Zemax's wavelength scaling: in order m
the zones of a relief of any depth add the phase ``m phi`` at every wavelength (only the efficiency
depends on it). An evanescent order (``|n' d'_t| >= n'``) makes the ray invalid.
"""
import functools

import warp as wp

# parameter layout of one surface
P_Z = 0           # vertex z, mm
P_C = 1           # curvature, 1/mm
P_K = 2           # conic
P_A0 = 3          # aspheric r^4 .. r^20 -> indices 3..11
N_ASPH = 9
P_SD = 12         # semi-diameter, mm (<= 0: unlimited)
P_SQUARE = 13     # 1: square aperture, 0: circle
P_POWER = 14      # thin lens power 1/f, 1/mm
P_UINV = 15       # thin lens: 1/u, u = object distance in front of the lens (mm); 0 = infinity
P_V = 16          # thin lens: image distance behind the lens, mm; 0 = image at infinity
P_A2 = 17         # r^2 coefficient of the even asphere, 1/mm
P_OB_KIND = 18    # central obscuration: 0 none, 1 circle (radius P_OB_X), 2 rectangle (half sides P_OB_X, P_OB_Y)
P_OB_X = 19
P_OB_Y = 20
P_ODD_ON = 21     # 1: the surface has power-series terms in r (Zemax ODDASPHE), coefficients below
P_ODD0 = 22       # b_1 .. b_8: sag += sum_i b_i r^i (r^1 .. r^8), mm^(1-i)
N_ODD = 8
P_PH_M = 30       # phase surface (KIND_PHASE): diffraction order m traced
P_PH_R = 31       # its normalisation radius R, mm
P_PH0 = 32        # A_1 .. A_8: phi = sum_i A_i (r / R)^(2 i), radians (Zemax BINARY_2 per unit order)
N_PHASE = 8
N_PARAMS = 40

KIND_REFRACT = 0
KIND_THIN = 1
KIND_PLANE = 2     # aperture / DOE plane / sensor: intersect and clip, no bending
KIND_REFLECT = 3   # mirror: intersect like KIND_REFRACT, then reflect (the medium is unchanged)
KIND_PHASE = 4     # refracting surface carrying a diffractive phase, one order traced (phase_surface_kernel)

NEWTON_STEPS = 8

#: The one tolerance at a clear-aperture edge: a pupil sample or a ray counts as inside a circle of
#: radius R while r^2 <= R^2 (1 + EDGE_RTOL) (a square: |x| <= R (1 + EDGE_RTOL)). Grid points that lie
#: on the pupil circle exactly (0.6, 0.8) carry r^2 = 1 + 2e-16 after rounding; without a tolerance they
#: are lost. float32 kernels use EDGE_RTOL_F32 (a few float32 roundings). The host's pupil grids
#: (:func:`rwwarp.pupil.pupil_grid`) use :func:`edge_rtol` too.
EDGE_RTOL = 1.0e-9
EDGE_RTOL_F32 = 1.0e-6


def edge_rtol(scalar=wp.float64) -> float:
    """The aperture-edge tolerance for kernels of ``scalar`` type (see :data:`EDGE_RTOL`)."""
    return EDGE_RTOL if scalar == wp.float64 else EDGE_RTOL_F32


@functools.cache
def make_trace_kernels(scalar):
    """Build the tracing kernels for ``scalar`` = ``wp.float64`` (default) or ``wp.float32``.

    Returns a namespace with ``vec3``, ``generate_kernel``, ``surface_kernel``.
    """
    vec3 = wp.types.vector(3, scalar)
    tol = 1.0e-10 if scalar == wp.float64 else 1.0e-4
    conv = 1.0e-15 if scalar == wp.float64 else 1.0e-7   # Newton: relative step below which t has converged
    edge = edge_rtol(scalar)
    asph_t = wp.types.vector(length=N_ASPH, dtype=scalar)
    odd_t = wp.types.vector(length=N_ODD, dtype=scalar)

    @wp.struct
    class Surface:
        """One surface's parameters by name (lengths mm; the table's columns ``P_*`` are only the storage)."""
        z: scalar          # vertex z
        c: scalar          # curvature, 1/mm
        k: scalar          # conic
        a2: scalar         # r^2 coefficient of the even asphere, 1/mm
        asph: asph_t       # r^4 .. r^20 coefficients
        odd_on: scalar     # 1: the power series in r below applies (ODDASPHE)
        odd: odd_t         # b_1 .. b_8 of sum_i b_i r^i
        sd: scalar         # semi-diameter (<= 0: unlimited)
        square: scalar     # 1: square aperture
        ob_kind: scalar    # central obscuration: 0 none, 1 circle, 2 rectangle
        ob_x: scalar       # its radius or half width
        ob_y: scalar       # its half height (rectangle)
        power: scalar      # thin lens power 1/f, 1/mm
        uinv: scalar       # thin lens 1/u (0: object at infinity)
        v: scalar          # thin lens image distance (0: at infinity)

    @wp.func
    def load_surface(row: wp.array(dtype=scalar)):
        # the one place that knows the table's layout; each column is read once (its adjoint adds once)
        sf = Surface()
        sf.z = row[P_Z]
        sf.c = row[P_C]
        sf.k = row[P_K]
        sf.a2 = row[P_A2]
        sf.asph = asph_t(row[P_A0], row[P_A0 + 1], row[P_A0 + 2], row[P_A0 + 3], row[P_A0 + 4], row[P_A0 + 5],
                         row[P_A0 + 6], row[P_A0 + 7], row[P_A0 + 8])
        sf.odd_on = row[P_ODD_ON]
        if sf.odd_on > scalar(0.5):
            sf.odd = odd_t(row[P_ODD0], row[P_ODD0 + 1], row[P_ODD0 + 2], row[P_ODD0 + 3], row[P_ODD0 + 4],
                           row[P_ODD0 + 5], row[P_ODD0 + 6], row[P_ODD0 + 7])
        sf.sd = row[P_SD]
        sf.square = row[P_SQUARE]
        sf.ob_kind = row[P_OB_KIND]
        sf.ob_x = row[P_OB_X]
        sf.ob_y = row[P_OB_Y]
        sf.power = row[P_POWER]
        sf.uinv = row[P_UINV]
        sf.v = row[P_V]
        return sf

    @wp.func
    def sag_and_slope(r2: scalar, sf: Surface):
        # returns (sag, dsag/dr2, ok)
        c = sf.c
        k = sf.k
        arg = scalar(1.0) - (scalar(1.0) + k) * c * c * r2
        ok = 1
        if arg < scalar(0.0):
            ok = 0
            arg = scalar(0.0)
        q = wp.sqrt(arg)
        s = c * r2 / (scalar(1.0) + q)
        ds = scalar(0.0)
        if q > scalar(0.0):
            ds = c / (scalar(2.0) * q)
        elif c != scalar(0.0):
            ok = 0
        a2 = sf.a2
        s = s + a2 * r2
        ds = ds + a2
        if sf.odd_on > scalar(0.5):
            # sum_i b_i r^i (i = 1..8): d(r^i)/d(r2) = i r^(i-2) / 2; the r^1 term is a cone at the axis
            # (its slope is taken as 0 there). Inside this branch only, so r = sqrt(r2) never enters the
            # adjoint of an ordinary surface (its derivative is infinite at r = 0).
            r = wp.sqrt(r2)
            p = scalar(1.0)  # r^(i-1) for the term of power i = 1 + loop index
            q = scalar(1.0)  # r^(i-2), from i = 2
            for j in range(N_ODD):
                b = sf.odd[j]
                s = s + b * p * r
                if j == 0:
                    if r > scalar(0.0):
                        ds = ds + scalar(0.5) * b / r
                else:
                    ds = ds + scalar(0.5) * scalar(j + 1) * b * q
                    q = q * r
                p = p * r
        rp = r2
        for i in range(N_ASPH):
            a = sf.asph[i]
            ds = ds + scalar(i + 2) * a * rp
            rp = rp * r2
            s = s + a * rp
        return s, ds, ok

    @wp.func
    def outside_aperture(x: scalar, y: scalar, sf: Surface):
        sd = sf.sd
        out = 0
        if sd > scalar(0.0):
            if sf.square > scalar(0.5):
                lim = sd * (scalar(1.0) + scalar(edge))
                if wp.abs(x) > lim or wp.abs(y) > lim:
                    out = 1
            else:
                if x * x + y * y > sd * sd * (scalar(1.0) + scalar(edge)):
                    out = 1
        kind = sf.ob_kind
        if kind > scalar(0.5):
            # an obscuration blocks rays strictly inside it (its edge, within the same tolerance, passes)
            ox = sf.ob_x
            if kind < scalar(1.5):
                if x * x + y * y < ox * ox * (scalar(1.0) - scalar(edge)):
                    out = 1
            else:
                lim = scalar(1.0) - scalar(edge)
                if wp.abs(x) < ox * lim and wp.abs(y) < sf.ob_y * lim:
                    out = 1
        return out

    @wp.kernel(module="unique")
    def generate_kernel(
        pupil_u: wp.array(dtype=scalar),        # (n_pupil,) normalised pupil x in [-1, 1]
        pupil_v: wp.array(dtype=scalar),        # (n_pupil,) normalised pupil y
        src_pos: wp.array(dtype=vec3),          # (n_src,) source point (finite) - unused at infinity
        src_dir: wp.array(dtype=vec3),          # (n_src,) propagation direction (infinity)
        src_finite: wp.array(dtype=wp.int32),   # (n_src,) 1: point source at src_pos
        aim: wp.array(dtype=vec3),              # (n_src,) pupil centre the grid is laid around (on the EP plane)
        half_x: wp.array(dtype=scalar),         # (n_src,) pupil half width, mm
        half_y: wp.array(dtype=scalar),         # (n_src,) pupil half height, mm
        src_wl: wp.array(dtype=wp.int32),       # (n_src,) wavelength index
        n_obj: wp.array(dtype=scalar),          # (n_wl,) object-space index
        cell: scalar,                           # area of one pupil cell in normalised (u, v) units
        circle: int,                            # 1: samples outside the unit circle start invalid;
                                                # 2 (with grid_n): each cell weighted by the fraction of it
                                                #    in the unit circle (frac), valid where that is > 0
        frac: wp.array(dtype=wp.vec3d),         # (grid_n^2,) with circle 2: (fraction, du, dv) of each cell
                                                #    (rwwarp.pupil.disc_cells): the ray starts at the centroid
        relative: int,                          # 1: OPL relative to the chief ray (point sources)
        grid_n: int,                            # > 0: pupil is the full grid_n x grid_n cell-centre grid,
                                                #      computed here (pupil_u / pupil_v unused);
                                                # < 0: each source's own grid, grid_src[s] x grid_src[s], and
                                                #      cell area cell_src[s] (a packed batch of sources with
                                                #      their own plans, rwwarp.wave.packed.PackedRayWave)
        n_pupil: int,                           # ray slots per source (with grid_n < 0, >= every grid_src^2;
                                                #      the slots past a source's own grid are padding: invalid,
                                                #      zero weight, at the pupil centre)
        grid_src: wp.array(dtype=wp.int32),     # (n_src,) with grid_n < 0, else unused ((1,))
        cell_src: wp.array(dtype=scalar),       # (n_src,) with grid_n < 0, else unused ((1,))
        frac_stride: int,                       # frac of source s, cell j at s * frac_stride + j (0: one table)
        offset: int,                            # first ray of this launch (CPU threads generate ray ranges; else 0)
        # outputs
        pos_out: wp.array(dtype=vec3),
        dir_out: wp.array(dtype=vec3),
        opl_out: wp.array(dtype=scalar),
        valid_out: wp.array(dtype=wp.int32),
        wl_out: wp.array(dtype=wp.int32),
        weight_out: wp.array(dtype=scalar),     # power of the ray for unit source radiance (mm^2 or sr)
    ):
        i = wp.tid() + offset
        s = i // n_pupil
        j = i - s * n_pupil
        c = aim[s]
        pu = scalar(0.0)
        pv = scalar(0.0)
        g = grid_n
        cl = cell
        if grid_n < 0:
            g = grid_src[s]
            cl = cell_src[s]
            if j >= g * g:
                # padding past this source's own grid: no ray
                pos_out[i] = vec3(c[0], c[1], c[2])
                dir_out[i] = vec3(scalar(0.0), scalar(0.0), scalar(1.0))
                opl_out[i] = scalar(0.0)
                valid_out[i] = 0
                weight_out[i] = scalar(0.0)
                wl_out[i] = src_wl[s]
                return
        if g > 0:
            row = j // g
            col = j - row * g
            pu = scalar(-1.0) + (scalar(2.0) * scalar(col) + scalar(1.0)) / scalar(g)
            pv = scalar(-1.0) + (scalar(2.0) * scalar(row) + scalar(1.0)) / scalar(g)
        else:
            pu = pupil_u[j]
            pv = pupil_v[j]
        fj = s * frac_stride + j
        if circle == 2:
            cell_j = frac[fj]
            pu = pu + scalar(cell_j[1])
            pv = pv + scalar(cell_j[2])
        p = vec3(c[0] + half_x[s] * pu, c[1] + half_y[s] * pv, c[2])
        w = src_wl[s]
        n0 = n_obj[w]
        area = cl * half_x[s] * half_y[s]  # pupil area of this sample, mm^2
        if src_finite[s] == 1:
            dvec = p - src_pos[s]
            dist = wp.length(dvec)
            d = dvec / dist
            # path from the source point; weight = solid angle of the pupil cell (cos / rho^2).
            # relative: minus the chief ray's |c - S|, formed stably as (p - c).(p + c - 2 S) / (|p-S| + |c-S|)
            # so float32 keeps the phase of a distant source (|S| ~ 1e4 mm) to ~1e-7 mm
            if relative == 1:
                sc = src_pos[s]
                opl_out[i] = n0 * wp.dot(p - c, p + c - scalar(2.0) * sc) / (dist + wp.length(c - sc))
            else:
                opl_out[i] = n0 * dist
            weight_out[i] = area * d[2] / (dist * dist)
        else:
            d = src_dir[s]
            # plane wave: zero path on the plane through the pupil centre normal to d
            opl_out[i] = n0 * wp.dot(p - c, d)
            weight_out[i] = area * d[2]
        pos_out[i] = p
        dir_out[i] = d
        valid_out[i] = 1
        if circle == 1:
            if pu * pu + pv * pv > scalar(1.0) + scalar(edge):
                valid_out[i] = 0
                weight_out[i] = scalar(0.0)
        if circle == 2:
            f = scalar(frac[fj][0])
            weight_out[i] = weight_out[i] * f
            if f <= scalar(0.0):
                valid_out[i] = 0
        wl_out[i] = w

    @wp.func
    def stable_start(q: vec3, d: vec3, sf: Surface):
        # root of the base sphere nearest the vertex plane (no special case for c = 0); the r^2 term is
        # part of the vertex curvature c + 2 a2
        c = sf.c + scalar(2.0) * sf.a2
        bq = d[2] - c * wp.dot(q, d)
        fq = c * wp.dot(q, q) - scalar(2.0) * q[2]
        disc = bq * bq - c * fq
        t = -q[2] / d[2]
        if disc >= scalar(0.0):
            root = wp.sqrt(disc)
            if bq >= scalar(0.0):
                t = fq / (bq + root)
            else:
                t = fq / (bq - root)
        return t

    @wp.func
    def newton_step(q: vec3, d: vec3, t: scalar, sf: Surface):
        x = q + t * d
        r2 = x[0] * x[0] + x[1] * x[1]
        sg, ds, sok = sag_and_slope(r2, sf)
        g = x[2] - sg
        dg = d[2] - ds * scalar(2.0) * (x[0] * d[0] + x[1] * d[1])
        tn = t
        if dg != scalar(0.0):
            tn = t - g / dg
        return tn

    @wp.func
    def converged_root(q: vec3, d: vec3, sf: Surface):
        # the ray parameter t of the intersection of q + t d (lens frame, vertex at z = 0) with the surface:
        # Newton from stable_start until a step moves t by <= conv (1 + |t|), at most NEWTON_STEPS steps (a
        # conic's start is its exact root: one step); the surface kernel's own step from it restores full precision
        t = stable_start(q, d, sf)
        for it in range(NEWTON_STEPS):
            tn = newton_step(q, d, t, sf)
            done = wp.abs(tn - t) <= scalar(conv) * (scalar(1.0) + wp.abs(tn))
            t = tn
            if done:
                break
        return t

    @wp.kernel(module="unique")
    def intersect_kernel(
        pos: wp.array(dtype=vec3),
        dir: wp.array(dtype=vec3),
        valid: wp.array(dtype=wp.int32),
        params_rows: wp.array2d(dtype=scalar),  # (R, N_PARAMS) copies of this surface's row, R = rmask + 1
        rmask: int,
        # outputs
        t_out: wp.array(dtype=scalar),
    ):
        """Converged ray parameter t of the intersection (launched outside the tape: the surface kernel
        then takes one differentiable Newton step from it, which gives the exact implicit derivative)."""
        i = wp.tid()
        t_out[i] = scalar(0.0)
        if valid[i] == 0:
            return
        sf = load_surface(params_rows[i & rmask])
        p0 = pos[i]
        t_out[i] = converged_root(vec3(p0[0], p0[1], p0[2] - sf.z), dir[i], sf)

    @wp.func
    def ray_in(i: int, sf: Surface, pos: wp.array(dtype=vec3), dir: wp.array(dtype=vec3),
               valid: wp.array(dtype=wp.int32), wl: wp.array(dtype=wp.int32), n_in: wp.array(dtype=scalar),
               n_out: wp.array(dtype=scalar)):
        # what surface_kernel and phase_surface_kernel read of ray i: (p0, d, ok, w, n1, n2, q), q the position in
        # the surface's vertex frame (z - sf.z), n1 / n2 the indices before / after at its wavelength w
        p0 = pos[i]
        d = dir[i]
        ok = valid[i]
        w = wl[i]
        n1 = n_in[w]
        n2 = n_out[w]
        q = vec3(p0[0], p0[1], p0[2] - sf.z)
        return p0, d, ok, w, n1, n2, q

    @wp.func
    def hit_and_normal(q: vec3, d: vec3, t0: scalar, sf: Surface):
        # one Newton step from the converged root t0 (intersect_kernel): exact value, exact (implicit) derivative,
        # and a short adjoint (the iterations themselves are not on the tape); then the ray is lost where the sag
        # is undefined, the root is off the surface or outside the aperture. Returns (t, x, nrm, cos i, ok): the
        # point x, the unit normal nrm turned to the ray's side (cos i = d.nrm >= 0)
        t = newton_step(q, d, t0, sf)
        x = q + t * d
        r2 = x[0] * x[0] + x[1] * x[1]
        sg, ds, sok = sag_and_slope(r2, sf)
        g = x[2] - sg
        ok = 1
        nrm = vec3(scalar(0.0), scalar(0.0), scalar(1.0))
        cosi = scalar(0.0)
        if sok == 0 or wp.abs(g) > scalar(tol) or outside_aperture(x[0], x[1], sf) == 1:
            ok = 0
        else:
            nrm = wp.normalize(vec3(-scalar(2.0) * x[0] * ds, -scalar(2.0) * x[1] * ds, scalar(1.0)))
            cosi = wp.dot(d, nrm)
            if cosi < scalar(0.0):
                nrm = -nrm
                cosi = -cosi
        return t, x, nrm, cosi, ok

    @wp.func
    def ray_out(i: int, ok: int, p0: vec3, d: vec3, q: vec3, t: scalar, zv: scalar, newd: vec3, n1: scalar,
                extra: scalar, opl: wp.array(dtype=scalar), pos_out: wp.array(dtype=vec3),
                dir_out: wp.array(dtype=vec3), opl_out: wp.array(dtype=scalar), valid_out: wp.array(dtype=wp.int32)):
        # ray i after the surface: at q + t d (back in the lens frame, z + zv), direction newd, optical path
        # opl[i] + n1 t + extra (extra: a thin lens's or a phase's own path); a lost ray (ok = 0) keeps its input
        if ok == 1:
            pos_out[i] = vec3(q[0] + t * d[0], q[1] + t * d[1], q[2] + t * d[2] + zv)
            dir_out[i] = newd
            opl_out[i] = opl[i] + n1 * t + extra
            valid_out[i] = 1
        else:
            pos_out[i] = p0
            dir_out[i] = d
            opl_out[i] = opl[i]
            valid_out[i] = 0

    @wp.func
    def surface_step(kind: int, q: vec3, d: vec3, t0: scalar, sf: Surface, n1: scalar, n2: scalar, ok_in: int):
        # one surface's step for a ray at q (lens frame, vertex at z = 0) along d, from the converged root t0
        # (curved surfaces): (t, the direction after, the surface's own path (a thin lens's), ok); the ray is
        # lost (ok = 0) outside the aperture, on a miss or at total internal reflection; ok_in = 0: nothing to do
        ok = ok_in
        t = scalar(0.0)
        newd = d
        extra = scalar(0.0)
        if ok == 1:
            if kind == KIND_REFRACT or kind == KIND_REFLECT:
                t, x, nrm, cosi, ok = hit_and_normal(q, d, t0, sf)
                if ok == 1:
                    if kind == KIND_REFLECT:
                        newd = wp.normalize(d - scalar(2.0) * cosi * nrm)
                    else:
                        mu = n1 / n2
                        kk = scalar(1.0) - mu * mu * (scalar(1.0) - cosi * cosi)
                        if kk <= scalar(0.0):
                            ok = 0  # total internal reflection
                        else:
                            newd = wp.normalize(mu * d + (wp.sqrt(kk) - mu * cosi) * nrm)
            else:
                # plane at the vertex: aperture, DOE plane, sensor, thin lens
                t = -q[2] / d[2]
                x = q + t * d
                if outside_aperture(x[0], x[1], sf) == 1:
                    ok = 0
                elif kind == KIND_THIN:
                    pw = sf.power
                    tx = (n1 * d[0] / d[2] - x[0] * pw) / n2
                    ty = (n1 * d[1] / d[2] - x[1] * pw) / n2
                    newd = wp.normalize(vec3(tx, ty, scalar(1.0)))
                    # ideal-lens path: equal optical path from the object point to its image point
                    ctr = vec3(scalar(0.0), scalar(0.0), x[2])
                    uinv = sf.uinv
                    inrel = scalar(0.0)
                    if uinv == scalar(0.0):
                        inrel = n1 * wp.dot(x - ctr, d)
                    else:
                        # u < 0: a virtual object behind the lens (a converging input): the path to x falls with
                        # the distance to it, so the difference takes the sign of u
                        src = x - d * (scalar(1.0) / (uinv * d[2]))
                        su = scalar(1.0)
                        if uinv < scalar(0.0):
                            su = scalar(-1.0)
                        inrel = su * n1 * (wp.length(x - src) - wp.length(ctr - src))
                    vdist = sf.v
                    if vdist == scalar(0.0):
                        # image at infinity (object at the front focal plane): a plane wave leaves, equal
                        # path up to the plane through the centre normal to the (common) direction
                        extra = -inrel + n2 * wp.dot(x - ctr, newd)
                    else:
                        # v < 0: a virtual image in front of the lens (a diverging output): the sign of v again
                        img = x + newd * (vdist / newd[2])
                        sv = scalar(1.0)
                        if vdist < scalar(0.0):
                            sv = scalar(-1.0)
                        extra = -inrel - sv * n2 * (wp.length(img - x) - wp.length(img - ctr))
        return t, newd, extra, ok

    @wp.kernel(module="unique")
    def surface_kernel(
        pos: wp.array(dtype=vec3),
        dir: wp.array(dtype=vec3),
        opl: wp.array(dtype=scalar),
        valid: wp.array(dtype=wp.int32),
        wl: wp.array(dtype=wp.int32),
        params_rows: wp.array2d(dtype=scalar),  # (R, N_PARAMS) copies of this surface's row (replicate_kernel)
        rmask: int,                             # R - 1, R a power of two: ray i reads row i & rmask
        n_in: wp.array(dtype=scalar),       # (n_wl,) index before the surface
        n_out: wp.array(dtype=scalar),      # (n_wl,) index after the surface
        kind: int,
        t_start: wp.array(dtype=scalar),    # converged intersection parameter (refracting surfaces)
        # outputs
        pos_out: wp.array(dtype=vec3),
        dir_out: wp.array(dtype=vec3),
        opl_out: wp.array(dtype=scalar),
        valid_out: wp.array(dtype=wp.int32),
    ):
        i = wp.tid()
        sf = load_surface(params_rows[i & rmask])
        p0, d, ok, w, n1, n2, q = ray_in(i, sf, pos, dir, valid, wl, n_in, n_out)
        t0 = scalar(0.0)
        if kind == KIND_REFRACT or kind == KIND_REFLECT:
            t0 = t_start[i]   # only a curved surface's t_start has a slot a ray (else a (1,) placeholder)
        t, newd, extra, ok = surface_step(kind, q, d, t0, sf, n1, n2, ok)
        ray_out(i, ok, p0, d, q, t, sf.z, newd, n1, extra, opl, pos_out, dir_out, opl_out, valid_out)

    @wp.func
    def phase_and_gradient(row: wp.array(dtype=scalar), x: scalar, y: scalar):
        # phi = sum_i A_i u^i, u = r^2 / R^2 (Horner), and grad phi = (2 / R^2) dphi/du (x, y)
        rn = row[P_PH_R]
        inv = scalar(1.0) / (rn * rn)
        u = (x * x + y * y) * inv
        ph = scalar(0.0)
        dp = scalar(0.0)
        for jj in range(N_PHASE):
            j = N_PHASE - 1 - jj
            a = row[P_PH0 + j]
            ph = (ph + a) * u
            dp = dp * u + scalar(j + 1) * a
        g = scalar(2.0) * inv * dp
        return ph, g * x, g * y

    @wp.kernel(module="unique")
    def phase_surface_kernel(
        pos: wp.array(dtype=vec3),
        dir: wp.array(dtype=vec3),
        opl: wp.array(dtype=scalar),
        valid: wp.array(dtype=wp.int32),
        wl: wp.array(dtype=wp.int32),
        params_rows: wp.array2d(dtype=scalar),  # (R, N_PARAMS) copies of this surface's row
        rmask: int,
        n_in: wp.array(dtype=scalar),       # (n_wl,) index before the surface
        n_out: wp.array(dtype=scalar),      # (n_wl,) index after the surface
        lam_bar: wp.array(dtype=scalar),    # (n_wl,) vacuum wavelength / (2 pi), mm (formed on the host in float64)
        t_start: wp.array(dtype=scalar),    # converged intersection parameter (intersect_kernel)
        # outputs
        pos_out: wp.array(dtype=vec3),
        dir_out: wp.array(dtype=vec3),
        opl_out: wp.array(dtype=scalar),
        valid_out: wp.array(dtype=wp.int32),
    ):
        """A refracting surface with a diffractive phase, order ``m = row[P_PH_M]`` (module docstring)."""
        i = wp.tid()
        row = params_rows[i & rmask]
        sf = load_surface(row)
        p0, d, ok, w, n1, n2, q = ray_in(i, sf, pos, dir, valid, wl, n_in, n_out)
        t = scalar(0.0)
        newd = d
        extra = scalar(0.0)
        if ok == 1:
            t, x, nrm, cosi, ok = hit_and_normal(q, d, t_start[i], sf)
            if ok == 1:
                ph, gx, gy = phase_and_gradient(row, x[0], x[1])
                scale = row[P_PH_M] * lam_bar[w]
                gv = vec3(scale * gx, scale * gy, scalar(0.0))
                tang = n1 * (d - cosi * nrm) + gv - wp.dot(gv, nrm) * nrm
                kk = n2 * n2 - wp.dot(tang, tang)
                if kk <= scalar(0.0):
                    ok = 0  # evanescent order (or total internal reflection)
                else:
                    newd = wp.normalize(tang + wp.sqrt(kk) * nrm)
                    extra = scale * ph
        ray_out(i, ok, p0, d, q, t, sf.z, newd, n1, extra, opl, pos_out, dir_out, opl_out, valid_out)

    @wp.kernel(module="unique")
    def replicate_kernel(params: wp.array(dtype=scalar), rows_per_thread: int, out: wp.array2d(dtype=scalar)):
        """``out[r, j] = params[j]`` for every row r. Launched over ``(N_PARAMS, R / rows_per_thread)``: thread
        (j, g) reads ``params[j]`` once and writes rows ``g rows_per_thread ..``, so the adjoint sums those
        rows' gradients in the thread and adds them to ``params``' gradient with one atomic addition (R /
        rows_per_thread of them per parameter). One thread looping over all 1024 rows took 0.46 ms a
        surface on an H100, a quarter of the design step's device time."""
        j, g = wp.tid()
        v = params[j]
        for r in range(rows_per_thread):
            out[g * rows_per_thread + r, j] = v

    @wp.kernel(module="unique")
    def replicate_rows_kernel(src: wp.array2d(dtype=scalar), rows_per_thread: int, out: wp.array2d(dtype=scalar)):
        """``out[g rows_per_thread + r, j] = src[g, j]``: the second level of the deterministic replication
        (``params`` -> G rows by ``replicate_kernel`` -> R rows here). Thread (j, g) alone adds into
        ``src``'s gradient at (g, j), after summing its rows in order, so no addition contends."""
        j, g = wp.tid()
        v = src[g, j]
        for r in range(rows_per_thread):
            out[g * rows_per_thread + r, j] = v

    class K:
        pass

    K.vec3 = vec3
    K.Surface = Surface
    K.replicate_kernel = replicate_kernel
    K.replicate_rows_kernel = replicate_rows_kernel
    K.scalar = scalar
    K.generate_kernel = generate_kernel
    K.surface_kernel = surface_kernel
    K.intersect_kernel = intersect_kernel
    K.phase_surface_kernel = phase_surface_kernel
    # the device functions the CPU's fused trace (rwwarp.kernels.trace_steps) calls, as these kernels do
    K.load_surface = load_surface
    K.converged_root = converged_root
    K.surface_step = surface_step
    return K


@functools.cache
def make_analysis_kernels(scalar):
    """Reductions for spot analysis, differentiable under ``wp.Tape``.

    ``moments_kernel`` writes per ray the terms of count, sum x, sum y, sum x^2 + y^2 of valid rays at
    the current plane (mm; summed per source by :func:`rwwarp.wave.reduce.source_sums`), about the middle ray
    of the source's pupil grid (a shift that keeps the
    variance well conditioned when the image height is large compared with the spot). ``rms_kernel`` turns them into the RMS radius about the centroid (mm):
    ``sqrt(<x^2 + y^2> - <x>^2 - <y>^2)``. ``slope_efl_kernel``: ``-h / tan(u')`` of ray 0.
    """
    vec3 = wp.types.vector(3, scalar)

    vec4 = wp.types.vector(4, scalar)

    @wp.kernel(module="unique")
    def moments_kernel(pos: wp.array(dtype=vec3), valid: wp.array(dtype=wp.int32), n_pupil: int,
                       # outputs
                       terms_out: wp.array(dtype=vec4)):
        # per ray (1, x, y, x^2 + y^2) if valid, else 0; summed per source by rwwarp.wave.reduce.source_sums
        # (a fixed tree: deterministic, no atomics)
        i = wp.tid()
        t = vec4()
        if valid[i] == 1:
            s = i // n_pupil
            p = pos[i] - pos[s * n_pupil + n_pupil // 2]
            t = vec4(scalar(1.0), p[0], p[1], p[0] * p[0] + p[1] * p[1])
        terms_out[i] = t

    @wp.kernel(module="unique")
    def rms_kernel(moments: wp.array(dtype=vec4, ndim=2),
                   # outputs
                   rms_out: wp.array(dtype=scalar)):
        s = wp.tid()
        m = moments[s, 0]
        n = m[0]
        if n > scalar(0.0):
            mx = m[1] / n
            my = m[2] / n
            var = m[3] / n - mx * mx - my * my
            rms_out[s] = wp.sqrt(wp.max(var, scalar(1.0e-30)))

    @wp.kernel(module="unique")
    def slope_efl_kernel(dir: wp.array(dtype=vec3), height: scalar,
                         # outputs
                         efl_out: wp.array(dtype=scalar)):
        d = dir[0]
        efl_out[0] = -height * d[2] / d[1]

    class K:
        pass

    K.moments_kernel = moments_kernel
    K.rms_kernel = rms_kernel
    K.slope_efl_kernel = slope_efl_kernel
    return K
