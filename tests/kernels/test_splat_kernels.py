"""The ray-to-field kernels of ``kernels/splat.py`` against numpy written from the equations.

* energy convention: each ray deposits ``sqrt(q A) / A_box`` times the integral of its phasor
  ``exp(1j (psi + g.(x - p)))`` over the overlap of its tube's box with each sample cell; the numpy
  reference integrates the exponential in closed form, ``(exp(1j g b) - exp(1j g a)) / (1j g)`` per axis
  (the kernel uses the centre phase times a sinc);
* paper convention: bilinear weights times ``|d_z| exp(1j psi)``;
* finalize: ``U = S / h^2`` times the reference sphere ``exp(1j k n (|T - c| - |T - p|))`` and the
  conjugate chief-ray carrier ``exp(-2 pi 1j f_c.(p - c))``;
* energy conservation with traced rays: ``sum |U|^2 h^2`` equals the power of the valid rays.
"""
import numpy as np
import pytest

wp = pytest.importorskip("warp")

from rwwarp.kernels import splat as ks
from rwwarp.kernels import trace as kt

F64 = wp.float64
V3 = wp.types.vector(3, F64)


def _a(x, dtype, device):
    return wp.array(np.ascontiguousarray(x), dtype=dtype, device=device)


def _ph(device):
    """The (1,) int32 per-source grid placeholder of a launch that is not a packed batch."""
    return wp.zeros(1, dtype=wp.int32, device=device)


def _splat(device, rays, src, n_grid, energy, use_reference, fixed=False):
    """Launch splat_kernel + finalize_kernel; returns (S, U, dropped) as complex (n_src, N, N) arrays.
    ``fixed``: the deterministic splat's passes (amplitudes, their per-source sum as the bound, int64 sums,
    conversion back)."""
    K = ks.make_splat_kernels(F64)
    nsrc = len(src["pitch"])
    n = len(rays["pos"])
    npup = n // nsrc
    s_re = wp.zeros(nsrc * n_grid * n_grid, dtype=F64, device=device)
    s_im = wp.zeros_like(s_re)
    dropped = wp.zeros(nsrc, dtype=wp.int32, device=device)
    per_src = [_a(src["origin"], wp.vec2d, device), _a(src["pitch"], F64, device), _a(src["chief"], wp.vec3d, device),
               _a(src["target"], wp.vec3d, device), _a(src["index"], F64, device)]
    ins = [_a(rays["pos"], V3, device), _a(rays["dir"], V3, device), _a(rays["opl"], F64, device),
           _a(rays["valid"].astype(np.int32), wp.int32, device), _a(rays["weight"], F64, device),
           _a(rays["area"], F64, device), _a(rays["half"], wp.vec2d, device), *per_src,
           _a(src["opl_chief"], F64, device), _a(src["k"], F64, device), use_reference, energy,
           n_grid, npup, _a(np.array([[1.0, 0.0, 0.0]]), wp.vec3d, device), 0, _ph(device), 0, 0]
    nb = wp.zeros((1, 1), dtype=K.vec4d, device=device)
    na = wp.zeros(1, dtype=wp.int64, device=device)
    nv = wp.zeros(1, dtype=K.vec4d, device=device)
    if not fixed:
        wp.launch(K.splat_kernel, dim=n, inputs=ins + [0, nb], outputs=[s_re, s_im, dropped, na, na, nv],
                  device=device)
    else:
        from rwwarp.wave.reduce import source_sums
        amps = wp.zeros(n, dtype=K.vec4d, device=device)
        wp.launch(K.splat_kernel, dim=n, inputs=ins + [2, nb], outputs=[s_re, s_im, wp.zeros_like(dropped), na, na, amps],
                  device=device)
        bound = source_sums(amps, nsrc, F64, device)
        acc = [wp.zeros(nsrc * n_grid * n_grid, dtype=wp.int64, device=device) for _ in range(2)]
        wp.launch(K.splat_kernel, dim=n, inputs=ins + [1, bound], outputs=[s_re, s_im, dropped, *acc, nv], device=device)
        wp.launch(K.fixed_to_float_kernel, dim=nsrc * n_grid * n_grid, inputs=[*acc, bound, n_grid * n_grid],
                  outputs=[s_re, s_im], device=device)
    field = wp.zeros(nsrc * n_grid * n_grid, dtype=wp.vec2d, device=device)
    wp.launch(ks.make_splat_kernels(F64).finalize_kernel, dim=nsrc * n_grid * n_grid,
              inputs=[s_re, s_im, *per_src, _a(src["k"], F64, device), _a(src["carrier"], wp.vec2d, device),
                      use_reference, energy, n_grid, _ph(device), 0, 0],
              outputs=[field], device=device)
    S = (s_re.numpy() + 1j * s_im.numpy()).reshape(nsrc, n_grid, n_grid)
    f = field.numpy()
    return S, (f[:, 0] + 1j * f[:, 1]).reshape(nsrc, n_grid, n_grid), dropped.numpy()


def _interval(g, a, b):
    """Integral of exp(1j g x) over [a, b]."""
    if abs(g * (b - a)) < 1e-9:
        return (b - a) * np.exp(1j * g * 0.5 * (a + b))
    return (np.exp(1j * g * b) - np.exp(1j * g * a)) / (1j * g)


def _splat_np(rays, src, n_grid, energy, use_reference):
    nsrc = len(src["pitch"])
    npup = len(rays["pos"]) // nsrc
    S = np.zeros((nsrc, n_grid, n_grid), complex)
    for i, (p, d, opl, ok) in enumerate(zip(rays["pos"], rays["dir"], rays["opl"], rays["valid"])):
        if not ok:
            continue
        s = i // npup
        o, h, k, n = src["origin"][s], src["pitch"][s], src["k"][s], src["index"][s]
        T, c = src["target"][s], src["chief"][s]
        ref = src["opl_chief"][s] + n * (np.linalg.norm(T - c) - np.linalg.norm(T - p)) if use_reference else 0.0
        psi = k * (opl - ref)
        if energy:
            q, A, hb = rays["weight"][i], rays["area"][i], rays["half"][i]
            g = np.zeros(2)
            if use_reference:
                uT = (T - p) / np.linalg.norm(T - p)
                g = k * (abs(n) * d[:2] - n * uT[:2])
            pre = np.sqrt(q * A) / (4.0 * hb[0] * hb[1])
            for iy in range(n_grid):
                for ix in range(n_grid):
                    xc, yc = o[0] + ix * h, o[1] + iy * h
                    ax, bx = max(p[0] - hb[0], xc - h / 2), min(p[0] + hb[0], xc + h / 2)
                    ay, by = max(p[1] - hb[1], yc - h / 2), min(p[1] + hb[1], yc + h / 2)
                    if bx > ax and by > ay:
                        S[s, iy, ix] += pre * np.exp(1j * psi) * _interval(g[0], ax - p[0], bx - p[0]) \
                            * _interval(g[1], ay - p[1], by - p[1])
        else:
            fx, fy = (p[0] - o[0]) / h, (p[1] - o[1]) / h
            ix, iy = int(np.floor(fx)), int(np.floor(fy))
            ax, ay = fx - ix, fy - iy
            v = abs(d[2]) * np.exp(1j * psi)
            S[s, iy, ix] += (1 - ax) * (1 - ay) * v
            S[s, iy, ix + 1] += ax * (1 - ay) * v
            S[s, iy + 1, ix] += (1 - ax) * ay * v
            S[s, iy + 1, ix + 1] += ax * ay * v
    U = np.empty_like(S)
    for s in range(nsrc):
        o, h, c, T = src["origin"][s], src["pitch"][s], src["chief"][s], src["target"][s]
        x = o[0] + h * np.arange(n_grid)
        y = o[1] + h * np.arange(n_grid)
        X, Y = np.meshgrid(x, y)
        ph = np.zeros_like(X)
        if use_reference:
            dist = np.sqrt((T[0] - X) ** 2 + (T[1] - Y) ** 2 + (T[2] - c[2]) ** 2)
            ph = src["k"][s] * src["index"][s] * (np.linalg.norm(T - c) - dist)
        ph = ph - 2 * np.pi * (src["carrier"][s][0] * (X - c[0]) + src["carrier"][s][1] * (Y - c[1]))
        U[s] = (S[s] / h ** 2 if energy else S[s]) * np.exp(1j * ph)
    return S, U


def _random_case(rng, nsrc=2, npup=60, n_grid=16, h=0.01):
    """Rays near the middle of each source's window, boxes of about a cell, a converging reference sphere."""
    o = rng.uniform(-0.1, 0.1, (nsrc, 2))
    mid = o + 0.5 * (n_grid - 1) * h
    pos = np.concatenate([np.column_stack([mid[s] + rng.uniform(-4 * h, 4 * h, (npup, 2)), np.full(npup, 5.0)])
                          for s in range(nsrc)])
    d = np.column_stack([rng.uniform(-0.05, 0.05, (nsrc * npup, 2)), np.ones(nsrc * npup)])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    half = rng.uniform(0.3 * h, 1.2 * h, (nsrc * npup, 2))
    target = np.column_stack([mid + 0.01, np.full(nsrc, 25.0)])
    index, opl_chief = np.array([1.0, -1.5])[:nsrc], np.array([0.3, -0.2])[:nsrc]
    chief = np.column_stack([mid, np.full(nsrc, 5.0)])
    # OPL near the reference sphere's (psi = k (OPL - OPL_ref) of a few radians, as in use)
    s_of = np.repeat(np.arange(nsrc), npup)
    ref = opl_chief[s_of] + index[s_of] * (np.linalg.norm(target[s_of] - chief[s_of], axis=1)
                                           - np.linalg.norm(target[s_of] - pos, axis=1))
    rays = dict(pos=pos, dir=d, opl=ref + rng.uniform(0.0, 2e-4, nsrc * npup),
                valid=(rng.random(nsrc * npup) < 0.9), weight=rng.uniform(0.5, 2.0, nsrc * npup),
                area=4.0 * half[:, 0] * half[:, 1], half=half)
    src = dict(origin=o, pitch=np.full(nsrc, h), chief=chief, target=target, index=index, opl_chief=opl_chief,
               k=2 * np.pi / np.array([0.55e-3, 0.65e-3])[:nsrc],
               carrier=rng.uniform(-20, 20, (nsrc, 2)))
    return rays, src, n_grid


@pytest.mark.parametrize("fixed", [False, True], ids=["float", "fixed"])
@pytest.mark.parametrize("use_reference", [0, 1], ids=["plain", "reference"])
def test_energy_splat_matches_box_integral(device, rng, use_reference, fixed):
    """Energy convention, random rays, boxes and phases, a converging and a diverging (index < 0) reference
    sphere: the deposits S and the finalized field U against the closed-form box integrals; measured error on
    the CPU 1.5e-15 of the largest sample (S and U), the same with the deterministic fixed-point sums (whose
    resolution, the rays' summed amplitude / 2^61, is far below); tolerance 2e-14."""
    rays, src, n = _random_case(rng)
    S, U, dropped = _splat(device, rays, src, n, energy=1, use_reference=use_reference, fixed=fixed)
    S_np, U_np = _splat_np(rays, src, n, energy=1, use_reference=use_reference)
    assert (dropped == 0).all()
    assert np.abs(S - S_np).max() < 2e-14 * np.abs(S_np).max()
    assert np.abs(U - U_np).max() < 2e-14 * np.abs(U_np).max()


@pytest.mark.parametrize("fixed", [False, True], ids=["float", "fixed"])
def test_paper_splat_is_bilinear(device, rng, fixed):
    """Paper convention: bilinear weights times |d_z| exp(1j psi), then the reference sphere and carrier;
    measured error 1.2e-16 of the largest sample on the CPU (float sums), 1.8e-16 (fixed-point); tolerance
    2e-14."""
    rays, src, n = _random_case(rng)
    S, U, dropped = _splat(device, rays, src, n, energy=0, use_reference=1, fixed=fixed)
    S_np, U_np = _splat_np(rays, src, n, energy=0, use_reference=1)
    assert (dropped == 0).all()
    assert np.abs(S - S_np).max() < 2e-14 * np.abs(S_np).max()
    assert np.abs(U - U_np).max() < 2e-14 * np.abs(U_np).max()


def test_rays_off_the_window_are_dropped_and_counted(device, rng):
    """A ray whose box leaves the window deposits nothing and is counted in ``dropped`` of its source."""
    rays, src, n = _random_case(rng, nsrc=2, npup=3)
    rays["valid"][:] = True
    rays["pos"][1, 0] = src["origin"][0, 0] - 0.5 * src["pitch"][0]        # source 0: box sticks out left
    rays["pos"][5, 1] = src["origin"][1, 1] + (n - 0.6) * src["pitch"][1]  # source 1: out at the top
    S, _, dropped = _splat(device, rays, src, n, energy=1, use_reference=0)
    keep = np.ones(6, bool)
    keep[[1, 5]] = False
    rays["valid"] = keep
    S_np, _ = _splat_np(rays, src, n, energy=1, use_reference=0)
    assert dropped.tolist() == [1, 1]
    assert np.abs(S - S_np).max() < 2e-14 * np.abs(S_np).max()


@pytest.mark.parametrize("stencil", [0, 1], ids=["direct", "stencil"])
def test_tube_area_of_an_affine_map(device, rng, stencil):
    """tube_area_kernel: for positions that are an affine image of the pupil grid (some rays invalid, so
    one-sided differences too) every tube's area is |det J| (J the map's Jacobian per grid step) and its box
    has that area with the Jacobian diagonal's aspect; exact up to rounding (measured 1.6e-14 relative: the
    differences of positions ~1 mm apart by ~0.01 mm; tolerance 1e-13). ``stencil``: the neighbours'
    positions handed over by stencil_kernel first (deterministic mode), the same numbers."""
    K = ks.make_splat_kernels(F64)
    m, nsrc = 7, 2
    J = np.array([[0.012, 0.003], [-0.002, 0.009]])
    jj, ii = np.meshgrid(np.arange(m), np.arange(m), indexing="ij")
    grid = np.column_stack([ii.ravel(), jj.ravel()]).astype(float)          # (col, row), row-major
    pos = np.concatenate([np.column_stack([grid @ J.T + s, np.full(m * m, 3.0)]) for s in range(nsrc)])
    valid = (rng.random(nsrc * m * m) < 0.85).astype(np.int32)
    area = wp.zeros(nsrc * m * m, dtype=F64, device=device)
    half = wp.zeros(nsrc * m * m, dtype=wp.vec2d, device=device)
    a_pos = _a(pos, V3, device)
    nbr = wp.zeros((nsrc * m * m if stencil else 1, 5), dtype=V3, device=device)
    if stencil:
        wp.launch(K.stencil_kernel, dim=nsrc * m * m, inputs=[a_pos, m, _ph(device), 0], outputs=[nbr], device=device)
    wp.launch(K.tube_area_kernel, dim=nsrc * m * m, inputs=[a_pos, _a(valid, wp.int32, device), m,
                                                        _a(np.array([[1.0, 0.0, 0.0]]), wp.vec3d, device), 0,
                                                        stencil, nbr, _ph(device), 0, 0],
              outputs=[area, half], device=device)
    a, hb = area.numpy(), half.numpy()
    # a ray has a tube when it has a valid neighbour along the row and one along the column
    v = valid.reshape(nsrc, m, m).astype(bool)
    pad = np.pad(v, ((0, 0), (1, 1), (1, 1)))
    has_u = pad[:, 1:-1, 2:] | pad[:, 1:-1, :-2]
    has_v = pad[:, 2:, 1:-1] | pad[:, :-2, 1:-1]
    tube = (v & has_u & has_v).ravel()
    det = abs(np.linalg.det(J))
    np.testing.assert_allclose(a[tube], det, rtol=1e-13)
    assert (a[~tube] == 0).all()
    sc = np.sqrt(det / (abs(J[0, 0]) * abs(J[1, 1])))
    np.testing.assert_allclose(hb[tube], np.tile(0.5 * sc * np.array([abs(J[0, 0]), abs(J[1, 1])]),
                                                 (tube.sum(), 1)), rtol=1e-13)


@pytest.mark.parametrize("rays_per_cell,circle", [(1, 0), (2, 0), (1, 1)], ids=["1x1", "2x2", "1x1-circle"])
def test_energy_conservation_with_traced_rays(device, rays_per_cell, circle):
    """Generate a plane wave on a circular pupil (generate_kernel), tube areas (tube_area_kernel), splat and
    finalize: the field power sum |U|^2 h^2 equals the power of the valid rays (power_sums_kernel) and the
    numpy sum of their weights. The tubes tile the window here (grid pitch a multiple of the ray spacing,
    aligned: on a circular pupil one ray per cell), the case where the box splat is exact -- a partly covered
    edge cell otherwise keeps the square of its covered fraction of the power (2 x 2 rays per cell on the
    circle: -4.5 %). Measured relative errors on the CPU: field power 1.6e-15 (tolerance 2e-14); the tree
    power sums against numpy's sum 1.4e-14 (tolerance 1e-13)."""
    T = kt.make_trace_kernels(F64)
    K = ks.make_splat_kernels(F64)
    g, a = 24, 1.2                                    # pupil grid g x g over [-a, a]^2, mm
    step = 2 * a / g                                  # ray spacing
    h = step * rays_per_cell                          # sample pitch
    n_grid = int(round(2 * a / h)) + 4
    npup = g * g
    outs = [wp.zeros(npup, dtype=V3, device=device), wp.zeros(npup, dtype=V3, device=device),
            wp.zeros(npup, dtype=F64, device=device), wp.zeros(npup, dtype=wp.int32, device=device),
            wp.zeros(npup, dtype=wp.int32, device=device), wp.zeros(npup, dtype=F64, device=device)]
    one = lambda x, dt=F64: _a(np.array([x]), dt, device)
    wp.launch(T.generate_kernel, dim=npup,
              inputs=[_a(np.zeros(1), F64, device), _a(np.zeros(1), F64, device), one([0.0, 0, 0], V3),
                      one([0.0, 0, 1], V3), one(0, wp.int32), one([0.0, 0, 0], V3), one(a), one(a), one(0, wp.int32),
                      one(1.0), (2.0 / g) ** 2, circle, _a(np.array([[1.0, 0.0, 0.0]]), wp.vec3d, device), 1, g, npup,
                      _ph(device), _a(np.zeros(1), F64, device), 0, 0],
              outputs=outs, device=device)
    pos, d, opl, valid, _, weight = outs
    area = wp.zeros(npup, dtype=F64, device=device)
    half = wp.zeros(npup, dtype=wp.vec2d, device=device)
    no_rim = _a(np.array([[1.0, 0.0, 0.0]]), wp.vec3d, device)
    wp.launch(K.tube_area_kernel, dim=npup, inputs=[pos, valid, g, no_rim, 0, 0, wp.zeros((1, 5), dtype=V3, device=device),
                                                    _ph(device), 0, 0],
              outputs=[area, half], device=device)
    from rwwarp.wave.reduce import source_sums
    terms = wp.zeros(npup, dtype=wp.types.vector(4, F64), device=device)
    wp.launch(K.power_sums_kernel, dim=npup, inputs=[valid, weight], outputs=[terms], device=device)
    sums = source_sums(terms, 1, F64, device).numpy().reshape(1, 4)
    # sample centres on the centres of rays_per_cell x rays_per_cell blocks of rays
    o = -a - 2 * h + 0.5 * h
    rays = dict(pos=pos.numpy(), dir=d.numpy(), opl=opl.numpy(), valid=valid.numpy().astype(bool),
                weight=weight.numpy(), area=area.numpy(), half=half.numpy())
    src = dict(origin=np.array([[o, o]]), pitch=np.array([h]), chief=np.zeros((1, 3)),
               target=np.array([[0.0, 0.0, 100.0]]), index=np.array([1.0]), opl_chief=np.zeros(1),
               k=np.array([2 * np.pi / 0.55e-3]), carrier=np.zeros((1, 2)))
    _, U, dropped = _splat(device, rays, src, n_grid, energy=1, use_reference=0)
    power = float((np.abs(U) ** 2).sum() * h * h)
    traced = rays["weight"][rays["valid"]].sum()
    assert dropped[0] == 0 and rays["valid"].sum() > 0.7 * npup
    assert abs(sums[0, 1] / traced - 1) < 1e-13
    assert abs(sums[0, 0] / rays["weight"].sum() - 1) < 1e-13
    assert abs(power / traced - 1) < 2e-14


@pytest.mark.parametrize("amplitude", ["energy", "paper"])
def test_deterministic_splat_is_the_same_bits_every_run_and_agrees_with_the_float_splat(device, amplitude):
    """RayWave(deterministic=True): the fixed-point splat (kernels/splat.py, FIXED_ONE) gives the same field bits
    on every run (float64 atomics on a GPU add in arrival order) and the float splat's field to its resolution:
    Cooke triplet at 10 deg, focal plan (401^2 rays); measured on the CPU 2.3e-13 (energy) and 6.7e-14 (paper)
    relative (1e-11 with the 5824^2 rays of an ASM plan: the resolution is the bound, the sum of the rays'
    amplitudes, over 2^61); tolerance 1e-12. The dropped-ray count is the float splat's."""
    import rwwarp as rw
    from rwwarp.wave.raywave import RayWave
    lens = rw.load_lens("cooke_triplet")

    def field(det):
        r = RayWave(lens, [10.0], [0.55], 16, lens.sensor.pixel_pitch, method="focal", amplitude=amplitude,
                    device=device, deterministic=det)
        f, _ = r.field()
        return f.numpy().copy(), r.dropped.numpy().copy()
    first, dropped = field(True)
    assert np.array_equal(field(True)[0], first)
    ref, ref_dropped = field(False)
    assert np.linalg.norm(first - ref) <= 1e-12 * np.linalg.norm(ref)
    assert np.array_equal(dropped, ref_dropped)


@pytest.mark.parametrize("energy", [1, 2], ids=["intensity", "flux"])
def test_zero_area_tubes_have_finite_adjoints(device, rng, energy):
    """A valid ray whose tube has no area (a point box: no valid neighbour along u or v, or a degenerate
    Jacobian) deposits nothing, and the splat's and the tube areas' adjoints stay finite (their sqrt(q A) and
    division by the box area at 0 were 0/0 = NaN, with a zero incoming gradient too; with ``energy == 2`` the
    NaN reached the ray directions and the surface parameters, issue: flux NaN curvature gradients). The
    reference: the gradients with such a ray equal those with it marked invalid, and its own are zero."""
    K = ks.make_splat_kernels(F64)
    rays, src, n = _random_case(rng, nsrc=1, npup=20)
    rays["valid"][:] = True
    lone = [3, 11]
    rays["area"][lone] = 0.0
    rays["half"][lone] = 0.0
    g_re, g_im = rng.normal(size=n * n), rng.normal(size=n * n)

    def grads(valid):
        arr = {k: wp.array(np.ascontiguousarray(rays[k]), dtype=t, device=device, requires_grad=True)
               for k, t in (("pos", V3), ("dir", V3), ("opl", F64), ("weight", F64), ("area", F64), ("half", wp.vec2d))}
        s_re = wp.zeros(n * n, dtype=F64, device=device, requires_grad=True)
        s_im = wp.zeros(n * n, dtype=F64, device=device, requires_grad=True)
        per_src = [_a(src[k], t, device) for k, t in (("origin", wp.vec2d), ("pitch", F64), ("chief", wp.vec3d),
                                                      ("target", wp.vec3d), ("index", F64))]
        ins = [arr["pos"], arr["dir"], arr["opl"], _a(valid.astype(np.int32), wp.int32, device), arr["weight"],
               arr["area"], arr["half"], *per_src, _a(src["opl_chief"], F64, device), _a(src["k"], F64, device), 1,
               energy, n, len(valid), _a(np.array([[1.0, 0.0, 0.0]]), wp.vec3d, device), 0, _ph(device), 0, 0, 0,
               wp.zeros((1, 1), dtype=K.vec4d, device=device)]
        tape = wp.Tape()
        with tape:
            wp.launch(K.splat_kernel, dim=len(valid), inputs=ins,
                      outputs=[s_re, s_im, wp.zeros(1, dtype=wp.int32, device=device),
                               wp.zeros(1, dtype=wp.int64, device=device), wp.zeros(1, dtype=wp.int64, device=device),
                               wp.zeros(1, dtype=K.vec4d, device=device)], device=device)
        tape.backward(grads={s_re: _a(g_re, F64, device), s_im: _a(g_im, F64, device)})
        return s_re.numpy(), {k: a.grad.numpy() for k, a in arr.items()}

    s_with, with_lone = grads(rays["valid"])
    off = rays["valid"].copy()
    off[lone] = False
    s_without, without = grads(off)
    assert np.array_equal(s_with, s_without)   # the forward: a point box deposits nothing
    for k in with_lone:
        assert np.isfinite(with_lone[k]).all(), k
        assert np.array_equal(with_lone[k], without[k]), k
        assert not with_lone[k][lone].any(), k

    # tube areas with a degenerate (rank-1) Jacobian: area 0, a point box, and finite position gradients
    m = 5
    J = np.array([[0.01, 0.02], [0.005, 0.01]])      # det 0: the grid folds onto a line
    jj, ii = np.meshgrid(np.arange(m), np.arange(m), indexing="ij")
    pos = wp.array(np.column_stack([np.column_stack([ii.ravel(), jj.ravel()]) @ J.T, np.full(m * m, 3.0)]),
                   dtype=V3, device=device, requires_grad=True)
    area = wp.zeros(m * m, dtype=F64, device=device, requires_grad=True)
    half = wp.zeros(m * m, dtype=wp.vec2d, device=device, requires_grad=True)
    tape = wp.Tape()
    with tape:
        wp.launch(K.tube_area_kernel, dim=m * m,
                  inputs=[pos, _a(np.ones(m * m, np.int32), wp.int32, device), m,
                          _a(np.array([[1.0, 0.0, 0.0]]), wp.vec3d, device), 0, 0,
                          wp.zeros((1, 5), dtype=V3, device=device), _ph(device), 0, 0],
                  outputs=[area, half], device=device)
    assert not area.numpy().any() and not half.numpy().any()
    tape.backward(grads={area: _a(rng.normal(size=m * m), F64, device),
                         half: _a(rng.normal(size=(m * m, 2)), wp.vec2d, device)})
    assert np.isfinite(pos.grad.numpy()).all()
