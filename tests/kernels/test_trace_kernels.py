"""The ray-tracing kernels of ``kernels/trace.py`` against numpy written from the equations.

Each reference is written independently of the kernel's formulation:

* intersection: the root of ``g(t) = q_z + t d_z - sag(r(t))`` by bracketing (scipy's brentq), with the
  sag written in r (not r^2) -- the kernel starts from the base sphere and runs Newton on r^2;
* surface normal: the gradient of ``z - sag(r)`` with ``dsag/dr`` differentiated term by term in r;
* refraction: Snell's law in its tangential form (the component of ``n d`` along the surface is kept,
  ``d'_t = (n1/n2) d_t``, ``d' = d'_t + sqrt(1 - |d'_t|^2) N``), the kernel uses the ``mu d + (...) N`` form;
* OPL: ``opl + n1 * |hit - start|``;
* the thin lens by what an ideal lens must do: every ray of a collimated beam meets its image point, with
  the same optical path (Fermat).
"""
import numpy as np
import pytest
from scipy.optimize import brentq

wp = pytest.importorskip("warp")

from rwwarp.kernels import trace as kt

F64 = wp.float64


def _params(z=0.0, c=0.0, k=0.0, asph=(), sd=0.0, square=False, power=0.0, uinv=0.0, v=0.0, a2=0.0,
            ob=None, odd=()):
    p = np.zeros(kt.N_PARAMS)
    p[kt.P_Z], p[kt.P_C], p[kt.P_K], p[kt.P_A2] = z, c, k, a2
    p[kt.P_A0:kt.P_A0 + len(asph)] = asph
    p[kt.P_SD], p[kt.P_SQUARE] = sd, float(square)
    p[kt.P_POWER], p[kt.P_UINV], p[kt.P_V] = power, uinv, v
    if ob is not None:
        p[kt.P_OB_KIND], p[kt.P_OB_X], p[kt.P_OB_Y] = ob
    if odd:
        p[kt.P_ODD_ON] = 1.0
        p[kt.P_ODD0:kt.P_ODD0 + len(odd)] = odd
    return p


def _sag_np(r, c, k, asph=(), a2=0.0, odd=()):
    """sag(r) and dsag/dr, written in r."""
    root = np.sqrt(1.0 - (1.0 + k) * c * c * r * r)
    s = c * r * r / (1.0 + root) + a2 * r * r
    ds = c * r / root + 2.0 * a2 * r
    for i, a in enumerate(asph):          # a_i multiplies r^(2 i + 4)
        s = s + a * r ** (2 * i + 4)
        ds = ds + (2 * i + 4) * a * r ** (2 * i + 3)
    for i, b in enumerate(odd):           # b_i multiplies r^(i + 1)
        s = s + b * r ** (i + 1)
        ds = ds + (i + 1) * b * r ** i
    return s, ds


def _refract_np(p0, d, opl, surf, n1, n2, reflect=False):
    """Hit point, new direction and OPL of each ray on a surface (numpy, from the equations)."""
    z0 = surf["z"]
    hits, dirs, opls = [], [], []
    for p, di, o in zip(p0, d, opl):
        q = p - np.array([0.0, 0.0, z0])

        def g(t, q=q, di=di):
            x = q + t * di
            return x[2] - _sag_np(np.hypot(x[0], x[1]), surf["c"], surf["k"], surf["asph"], surf["a2"],
                                  surf["odd"])[0]
        t = brentq(g, 0.0, 40.0, xtol=1e-15, rtol=1e-15, maxiter=500)
        x = q + t * di
        r = np.hypot(x[0], x[1])
        _, dsdr = _sag_np(r, surf["c"], surf["k"], surf["asph"], surf["a2"], surf["odd"])
        grad = np.array([-dsdr * x[0] / r, -dsdr * x[1] / r, 1.0]) if r > 0 else np.array([0.0, 0.0, 1.0])
        nrm = grad / np.linalg.norm(grad)
        if di @ nrm < 0:
            nrm = -nrm
        if reflect:
            dn = di - 2.0 * (di @ nrm) * nrm
        else:
            dt = (n1 / n2) * (di - (di @ nrm) * nrm)            # tangential part of n d is conserved
            dn = dt + np.sqrt(1.0 - dt @ dt) * nrm
        hits.append(x + np.array([0.0, 0.0, z0]))
        dirs.append(dn)
        opls.append(o + n1 * np.linalg.norm(x - q))
    return np.array(hits), np.array(dirs), np.array(opls)


def _run_surface(device, pos, d, opl, params, n1, n2, kind, scalar=F64):
    K = kt.make_trace_kernels(scalar)
    dt = np.float64 if scalar == F64 else np.float32
    n = len(pos)
    a_pos = wp.array(pos.astype(dt), dtype=K.vec3, device=device)
    a_dir = wp.array(d.astype(dt), dtype=K.vec3, device=device)
    a_opl = wp.array(opl.astype(dt), dtype=scalar, device=device)
    a_valid = wp.ones(n, dtype=wp.int32, device=device)
    a_wl = wp.zeros(n, dtype=wp.int32, device=device)
    # four copies of the row: ray i reads copy i & 3 (the layout a recording Tracer uses)
    a_par = wp.array(np.tile(params.astype(dt), (4, 1)), dtype=scalar, device=device)
    a_n1 = wp.array(np.array([n1], dt), dtype=scalar, device=device)
    a_n2 = wp.array(np.array([n2], dt), dtype=scalar, device=device)
    t = wp.zeros(n, dtype=scalar, device=device)
    if kind in (kt.KIND_REFRACT, kt.KIND_REFLECT):
        wp.launch(K.intersect_kernel, dim=n, inputs=[a_pos, a_dir, a_valid, a_par, 3], outputs=[t], device=device)
    out = [wp.zeros(n, dtype=K.vec3, device=device), wp.zeros(n, dtype=K.vec3, device=device),
           wp.zeros(n, dtype=scalar, device=device), wp.zeros(n, dtype=wp.int32, device=device)]
    wp.launch(K.surface_kernel, dim=n, inputs=[a_pos, a_dir, a_opl, a_valid, a_wl, a_par, 3, a_n1, a_n2, kind, t],
              outputs=out, device=device)
    return [o.numpy().astype(np.float64) if o.dtype != wp.int32 else o.numpy() for o in out]


def _rays(rng, n, z0=-5.0, h=6.0, max_tan=0.15):
    """Rays from the plane z0, heights within h, directions up to max_tan off the axis."""
    xy = rng.uniform(-h, h, (n, 2)) / np.sqrt(2.0)
    pos = np.column_stack([xy, np.full(n, z0)])
    tan = rng.uniform(-max_tan, max_tan, (n, 2))
    d = np.column_stack([tan, np.ones(n)])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return pos, d, rng.uniform(0.0, 3.0, n)


SURFACES = {
    "sphere": dict(z=2.0, c=1 / 25.0, k=0.0, asph=(), a2=0.0, odd=()),
    "concave": dict(z=2.0, c=-1 / 30.0, k=0.0, asph=(), a2=0.0, odd=()),
    "asphere": dict(z=1.5, c=1 / 22.0, k=-0.8, asph=(2e-5, -3e-7, 1e-9), a2=1e-3, odd=()),
    "odd": dict(z=1.0, c=1 / 40.0, k=0.5, asph=(1e-5,), a2=0.0, odd=(0.0, 2e-3, -4e-5)),
    "flat": dict(z=0.5, c=0.0, k=0.0, asph=(), a2=0.0, odd=()),
}


@pytest.mark.parametrize("name", list(SURFACES))
def test_refraction_matches_snell(device, rng, name):
    """Hit point, refracted direction and OPL of 200 random rays on a sphere, an even/odd asphere and a plane:
    measured worst errors on the CPU 1.8e-15 mm (hit), 3.3e-16 (direction), 3.6e-15 mm (OPL); tolerance
    5e-14, about 10x (room for the CUDA build's fused multiply-adds)."""
    tol = 5e-14
    s = SURFACES[name]
    pos, d, opl = _rays(rng, 200)
    par = _params(z=s["z"], c=s["c"], k=s["k"], asph=s["asph"], a2=s["a2"], odd=s["odd"])
    n1, n2 = 1.0, 1.5168
    p_k, d_k, o_k, v_k = _run_surface(device, pos, d, opl, par, n1, n2, kt.KIND_REFRACT)
    p_r, d_r, o_r = _refract_np(pos, d, opl, s, n1, n2)
    assert v_k.all()
    np.testing.assert_allclose(p_k, p_r, rtol=0, atol=tol)
    np.testing.assert_allclose(d_k, d_r, rtol=0, atol=tol)
    np.testing.assert_allclose(o_k, o_r, rtol=0, atol=tol)


def test_refraction_float32(device, rng):
    """The float32 build of the same kernels against the float64 numpy reference (fed the float32-rounded
    rays): measured worst errors 3.0e-7 mm (hit), 8.9e-8 (direction), 8.8e-7 mm (OPL); tolerances 10x."""
    s = SURFACES["asphere"]
    pos, d, opl = _rays(rng, 100)
    par = _params(z=s["z"], c=s["c"], k=s["k"], asph=s["asph"], a2=s["a2"])
    p_k, d_k, o_k, v_k = _run_surface(device, pos, d, opl, par, 1.0, 1.6, kt.KIND_REFRACT, scalar=wp.float32)
    p_r, d_r, o_r = _refract_np(pos.astype(np.float32).astype(float), d.astype(np.float32).astype(float),
                                opl.astype(np.float32).astype(float), s, 1.0, 1.6)
    assert v_k.all()
    np.testing.assert_allclose(p_k, p_r, rtol=0, atol=3e-6)
    np.testing.assert_allclose(d_k, d_r, rtol=0, atol=1e-6)
    np.testing.assert_allclose(o_k, o_r, rtol=0, atol=9e-6)


def test_mirror_reflects(device, rng):
    """KIND_REFLECT: d' = d - 2 (d.N) N at the numpy hit point; measured 1.8e-15 mm (hit), 6.7e-16
    (direction), 3.6e-15 mm (OPL); tolerance 5e-14 as above."""
    s = SURFACES["concave"]
    pos, d, opl = _rays(rng, 100)
    par = _params(z=s["z"], c=s["c"])
    p_k, d_k, o_k, v_k = _run_surface(device, pos, d, opl, par, 1.0, 1.0, kt.KIND_REFLECT)
    p_r, d_r, o_r = _refract_np(pos, d, opl, s, 1.0, 1.0, reflect=True)
    assert v_k.all() and (d_k[:, 2] < 0).all()
    np.testing.assert_allclose(p_k, p_r, rtol=0, atol=5e-14)
    np.testing.assert_allclose(d_k, d_r, rtol=0, atol=5e-14)
    np.testing.assert_allclose(o_k, o_r, rtol=0, atol=5e-14)


def test_total_internal_reflection_invalidates(device):
    """Glass (1.7) to air through a plane: a ray past the critical angle (36.0 deg) is invalid and keeps its
    state; one below it refracts to sin i' = 1.7 sin i."""
    ang = np.radians([30.0, 40.0])
    d = np.column_stack([np.sin(ang), np.zeros(2), np.cos(ang)])
    pos = np.zeros((2, 3))
    opl = np.array([1.0, 2.0])
    p_k, d_k, o_k, v_k = _run_surface(device, pos, d, opl, _params(z=1.0), 1.7, 1.0, kt.KIND_REFRACT)
    assert v_k.tolist() == [1, 0]
    assert abs(d_k[0, 0] - 1.7 * np.sin(ang[0])) < 1e-14
    np.testing.assert_array_equal(p_k[1], pos[1])
    np.testing.assert_array_equal(d_k[1], d[1])
    assert o_k[1] == opl[1]


@pytest.mark.parametrize("shape", ["circle", "square", "obscured"])
def test_aperture_clips(device, rng, shape):
    """Rays landing outside the clear aperture (or inside an obscuration) on a plane are invalid; the
    rest land at the plane with OPL + n * path."""
    n = 400
    pos = np.column_stack([rng.uniform(-5, 5, (n, 2)), np.zeros(n)])
    d = np.tile([0.0, 0.0, 1.0], (n, 1))
    opl = np.zeros(n)
    if shape == "circle":
        par, inside = _params(z=2.0, sd=3.0), np.hypot(pos[:, 0], pos[:, 1]) <= 3.0
    elif shape == "square":
        par, inside = _params(z=2.0, sd=3.0, square=True), (np.abs(pos[:, :2]) <= 3.0).all(1)
    else:
        r = np.hypot(pos[:, 0], pos[:, 1])
        par, inside = _params(z=2.0, sd=4.0, ob=(1.0, 1.5, 0.0)), (r <= 4.0) & (r >= 1.5)
    p_k, _, o_k, v_k = _run_surface(device, pos, d, opl, par, 1.33, 1.33, kt.KIND_PLANE)
    np.testing.assert_array_equal(v_k.astype(bool), inside)
    np.testing.assert_allclose(o_k[inside], 1.33 * 2.0, rtol=0, atol=1e-14)
    np.testing.assert_allclose(p_k[inside, 2], 2.0, rtol=0, atol=1e-14)


def test_thin_lens_is_ideal(device):
    """An ideal lens (f = 50 mm, object at infinity): a collimated beam at 3 deg meets one point on the
    focal plane, at height f tan(3 deg), and every ray reaches it with the same optical path (Fermat).
    Measured: 1.3e-15 mm (landing height error), 2.1e-14 mm (spread of the path); tolerances 2e-14, 2e-13."""
    f, n = 50.0, 41
    ang = np.radians(3.0)
    y = np.linspace(-6.0, 6.0, n)
    pos = np.column_stack([np.zeros(n), y, np.full(n, -1.0)])
    d = np.tile([0.0, np.sin(ang), np.cos(ang)], (n, 1))
    opl = (pos - pos[n // 2]) @ d[0]             # zero on the wavefront through the middle ray
    par = _params(z=0.0, power=1.0 / f, uinv=0.0, v=f)
    p_k, d_k, o_k, v_k = _run_surface(device, pos, d, opl, par, 1.0, 1.0, kt.KIND_THIN)
    assert v_k.all()
    t = (f - p_k[:, 2]) / d_k[:, 2]              # to the focal plane z = f
    land = p_k + t[:, None] * d_k
    np.testing.assert_allclose(land[:, 1], f * np.tan(ang), rtol=0, atol=2e-14)
    total = o_k + t                              # n = 1 after the lens
    assert np.ptp(total) < 2e-13


def test_generate_rays(device):
    """Ray generation on a cell-centre pupil grid: positions, directions, OPL (plane wave: zero on the plane
    through the pupil centre normal to d; point source: path relative to the chief ray) and ray weights
    (pupil cell area times cos, divided by distance^2 for a point source), written out in numpy."""
    K = kt.make_trace_kernels(F64)
    g, n0 = 6, 1.2
    nsrc, npup = 2, g * g
    aim = np.array([[0.1, -0.2, 0.0], [0.3, 0.4, 0.0]])
    half = np.array([[2.0, 1.5], [1.0, 1.0]])
    tilt = np.radians(5.0)
    src_dir = np.array([[0.0, np.sin(tilt), np.cos(tilt)], [0.0, 0.0, 1.0]])
    src_pos = np.array([[0.0, 0.0, 0.0], [1.0, -2.0, -80.0]])
    finite = np.array([0, 1], np.int32)
    cell = (2.0 / g) ** 2
    arr = lambda a, dt=F64: wp.array(a, dtype=dt, device=device)
    n = nsrc * npup
    outs = [wp.zeros(n, dtype=K.vec3, device=device), wp.zeros(n, dtype=K.vec3, device=device),
            wp.zeros(n, dtype=F64, device=device), wp.zeros(n, dtype=wp.int32, device=device),
            wp.zeros(n, dtype=wp.int32, device=device), wp.zeros(n, dtype=F64, device=device)]
    wp.launch(K.generate_kernel, dim=n,
              inputs=[arr(np.zeros(1)), arr(np.zeros(1)), arr(src_pos, K.vec3), arr(src_dir, K.vec3),
                      arr(finite, wp.int32), arr(aim, K.vec3), arr(half[:, 0]), arr(half[:, 1]),
                      arr(np.array([0, 0], np.int32), wp.int32), arr(np.array([n0])), cell, 1,
                      arr(np.array([[1.0, 0.0, 0.0]]), wp.vec3d), 1, g,
                      npup, arr(np.zeros(1, np.int32), wp.int32), arr(np.zeros(1)), 0, 0],
              outputs=outs, device=device)
    pos, d, opl, valid, wl, weight = [o.numpy() for o in outs]
    u = -1.0 + (2.0 * np.arange(g) + 1.0) / g
    pu, pv = np.meshgrid(u, u)                   # row-major: row = v, column = u
    inside = (pu ** 2 + pv ** 2 <= 1.0).ravel()
    for s in range(nsrc):
        sl = slice(s * npup, (s + 1) * npup)
        p = np.column_stack([aim[s, 0] + half[s, 0] * pu.ravel(), aim[s, 1] + half[s, 1] * pv.ravel(),
                             np.full(npup, aim[s, 2])])
        area = cell * half[s, 0] * half[s, 1]
        if finite[s]:
            v = p - src_pos[s]
            dist = np.linalg.norm(v, axis=1)
            dd = v / dist[:, None]
            o_ref = n0 * (dist - np.linalg.norm(aim[s] - src_pos[s]))
            w_ref = area * dd[:, 2] / dist ** 2
        else:
            dd = np.tile(src_dir[s], (npup, 1))
            o_ref = n0 * (p - aim[s]) @ src_dir[s]
            w_ref = np.full(npup, area * src_dir[s, 2])
        np.testing.assert_allclose(pos[sl], p, rtol=0, atol=1e-14)
        np.testing.assert_allclose(d[sl], dd, rtol=0, atol=1e-15)
        np.testing.assert_allclose(opl[sl], o_ref, rtol=0, atol=1e-13)
        np.testing.assert_array_equal(valid[sl].astype(bool), inside)
        np.testing.assert_allclose(weight[sl], np.where(inside, w_ref, 0.0), rtol=1e-14, atol=0)
    assert (wl == 0).all()


def test_spot_moments_and_rms(device, rng):
    """moments_kernel + rms_kernel: the RMS radius about the centroid of the valid rays of each source
    (numpy: std of x and y over the valid rays, spot 10 um wide 5 mm off the axis); measured relative error
    1.9e-15 on the CPU, tolerance 2e-14."""
    K = kt.make_analysis_kernels(F64)
    T = kt.make_trace_kernels(F64)
    nsrc, npup = 3, 257
    pos = np.column_stack([rng.normal(5.0, 0.01, (nsrc * npup, 2)), np.zeros(nsrc * npup)])
    valid = (rng.random(nsrc * npup) < 0.8).astype(np.int32)
    valid[np.arange(nsrc) * npup + npup // 2] = 1
    from rwwarp.wave.reduce import source_sums
    terms = wp.zeros(nsrc * npup, dtype=wp.types.vector(4, F64), device=device)
    rms = wp.zeros(nsrc, dtype=F64, device=device)
    wp.launch(K.moments_kernel, dim=nsrc * npup,
              inputs=[wp.array(pos, dtype=T.vec3, device=device), wp.array(valid, dtype=wp.int32, device=device),
                      npup], outputs=[terms], device=device)
    mom = source_sums(terms, nsrc, F64, device)
    wp.launch(K.rms_kernel, dim=nsrc, inputs=[mom], outputs=[rms], device=device)
    mom = mom.numpy().reshape(nsrc, 4)
    for s in range(nsrc):
        sl = slice(s * npup, (s + 1) * npup)
        p = pos[sl][valid[sl] == 1, :2]
        ref = np.sqrt(p[:, 0].var() + p[:, 1].var())
        assert abs(rms.numpy()[s] / ref - 1.0) < 2e-14
        assert mom[s, 0] == valid[sl].sum()


@pytest.mark.parametrize("u", [150.0, 50.0, 30.0], ids=["finite", "collimator", "virtual-image"])
def test_thin_lens_finite_conjugates(device, u):
    """Object point 150 mm in front of an f = 50 mm ideal lens: every ray meets the image point at
    v = 1 / (1/f - 1/u) = 75 mm, height -y_s v / u, with equal total optical path. At u = f the rays leave
    parallel (image at infinity, v = 0 in the kernel) and their path is equal up to the plane through the
    lens centre normal to them. Measured on the CPU: landing 8.9e-16 mm, path spread 5.7e-14 mm (finite);
    directions 1.4e-17, path spread 7.1e-15 mm (collimator). Tolerances 1e-14 (landing, directions), 2e-13."""
    f, n, ys = 50.0, 33, 1.5
    src = np.array([0.0, ys, -u])
    xy = np.column_stack([np.zeros(n), np.linspace(-5.0, 5.0, n)])
    target = np.column_stack([xy, np.zeros(n)])
    d = target - src
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    pos = np.tile(src, (n, 1))
    v = 0.0 if u == f else 1.0 / (1.0 / f - 1.0 / u)
    par = _params(z=0.0, power=1.0 / f, uinv=1.0 / u, v=v)
    p_k, d_k, o_k, v_k = _run_surface(device, pos, d, np.zeros(n), par, 1.0, 1.0, kt.KIND_THIN)
    assert v_k.all()
    if v:
        t = v / d_k[:, 2]
        land = p_k + t[:, None] * d_k
        np.testing.assert_allclose(land[:, 1], -ys * v / u, rtol=0, atol=1e-14)
        assert np.ptp(o_k + t) < 2e-13
    else:
        np.testing.assert_allclose(d_k, np.tile(d_k[n // 2], (n, 1)), rtol=0, atol=1e-14)
        assert np.ptp(o_k - p_k @ d_k[n // 2]) < 2e-13


def test_thin_lens_virtual_object(device):
    """A converging input (virtual object 100 mm behind an f = 50 mm ideal lens, height 1.5 mm): rays on a sphere
    of radius 110 mm about the virtual point (equal path there), aimed at it. They must meet the image point at
    v = 1 / (1/f - 1/u) = 33.3 mm (u = -100), height -y_s v / u, with equal total optical path (the path to the
    lens falls with the distance to the virtual object: the kernel used to add it, a path error of about r^2 / |u|,
    0.25 mm at r = 5 mm). Tolerances as the finite case (1e-14 landing, 2e-13 path). The "virtual-image" case of
    test_thin_lens_finite_conjugates (u = 30 mm < f: image 75 mm in front) failed likewise."""
    f, n, ys, u = 50.0, 33, 1.5, -100.0
    vpt = np.array([0.0, ys, -u])
    xy = np.column_stack([np.zeros(n), np.linspace(-5.0, 5.0, n)])
    target = np.column_stack([xy, np.zeros(n)])
    d = vpt - target
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    pos = vpt - 110.0 * d
    v = 1.0 / (1.0 / f - 1.0 / u)
    par = _params(z=0.0, power=1.0 / f, uinv=1.0 / u, v=v)
    p_k, d_k, o_k, v_k = _run_surface(device, pos, d, np.zeros(n), par, 1.0, 1.0, kt.KIND_THIN)
    assert v_k.all()
    t = v / d_k[:, 2]
    land = p_k + t[:, None] * d_k
    np.testing.assert_allclose(land[:, 1], -ys * v / u, rtol=0, atol=1e-14)
    assert np.ptp(o_k + t) < 2e-13


def test_slope_efl(device):
    """slope_efl_kernel: EFL = -h / tan(u') from ray 0 (h its entrance height, u' its exit angle)."""
    K = kt.make_analysis_kernels(F64)
    T = kt.make_trace_kernels(F64)
    d = np.array([[0.0, -0.02, 1.0]]) / np.hypot(0.02, 1.0)
    out = wp.zeros(1, dtype=F64, device=device)
    wp.launch(K.slope_efl_kernel, dim=1, inputs=[wp.array(d, dtype=T.vec3, device=device), 1.0], outputs=[out],
              device=device)
    assert abs(out.numpy()[0] - 50.0) < 1e-12


@pytest.mark.parametrize("replicas,per", [(1, 1), (8, 4), (512, 512)], ids=["one", "groups", "per-ray"])
def test_parameter_gradient_through_replicated_rows(device, rng, replicas, per):
    """The adjoint through ``replicate_kernel`` and the replicated rows the surface kernel reads: d(sum of
    OPL and exit directions' x) / d(curvature, conic, r^4 term) of 300 rays refracted at an asphere, against
    central differences of the numpy refraction of this file (step 1e-4 relative). Measured 3.9e-11 (curvature),
    3.4e-9 (conic), 2.2e-9 (r^4) relative, the same for 1 and 8 copies (the differences' own truncation and
    rounding: 8.6e-8 for the conic at step 1e-6); tolerance 1e-8, 3x the largest. With 8 copies the replicate
    kernel runs two groups of 4 rows, so its adjoint's per-thread sum and its atomic addition are both used.
    512 copies, one thread each parameter: the deterministic layout (a copy per ray, summed in order)."""
    s = dict(SURFACES["asphere"])
    pos, d, opl = _rays(rng, 300)
    n1, n2 = 1.0, 1.5168
    K = kt.make_trace_kernels(F64)
    n = len(pos)

    def objective_np(c, k, a4):
        q = dict(s, c=c, k=k, asph=(a4,) + tuple(s["asph"][1:]))
        p_r, d_r, o_r = _refract_np(pos, d, opl, q, n1, n2)
        return float(o_r.sum() + d_r[:, 0].sum())
    par = wp.array(_params(z=s["z"], c=s["c"], k=s["k"], asph=s["asph"], a2=s["a2"]), dtype=F64, device=device,
                   requires_grad=True)
    rows = wp.zeros((replicas, kt.N_PARAMS), dtype=F64, device=device, requires_grad=True)
    a_pos = wp.array(pos, dtype=K.vec3, device=device, requires_grad=True)
    a_dir = wp.array(d, dtype=K.vec3, device=device, requires_grad=True)
    a_opl = wp.array(opl, dtype=F64, device=device, requires_grad=True)
    a_valid = wp.ones(n, dtype=wp.int32, device=device)
    a_wl = wp.zeros(n, dtype=wp.int32, device=device)
    a_n1 = wp.array(np.array([n1]), dtype=F64, device=device)
    a_n2 = wp.array(np.array([n2]), dtype=F64, device=device)
    t = wp.zeros(n, dtype=F64, device=device)
    out = [wp.zeros(n, dtype=K.vec3, device=device, requires_grad=True),
           wp.zeros(n, dtype=K.vec3, device=device, requires_grad=True),
           wp.zeros(n, dtype=F64, device=device, requires_grad=True), wp.zeros(n, dtype=wp.int32, device=device)]
    tape = wp.Tape()
    with tape:
        wp.launch(K.replicate_kernel, dim=(kt.N_PARAMS, replicas // per), inputs=[par, per], outputs=[rows],
                  device=device)
        wp.launch(K.intersect_kernel, dim=n, inputs=[a_pos, a_dir, a_valid, rows, replicas - 1], outputs=[t],
                  device=device, record_tape=False)
        wp.launch(K.surface_kernel, dim=n, inputs=[a_pos, a_dir, a_opl, a_valid, a_wl, rows, replicas - 1, a_n1, a_n2,
                                                   kt.KIND_REFRACT, t], outputs=out, device=device)
    seed_dir = np.zeros((n, 3))
    seed_dir[:, 0] = 1.0
    tape.backward(grads={out[2]: wp.ones(n, dtype=F64, device=device),
                         out[1]: wp.array(seed_dir, dtype=K.vec3, device=device)})
    g = par.grad.numpy()
    x0 = (s["c"], s["k"], s["asph"][0])
    for j, idx in enumerate((kt.P_C, kt.P_K, kt.P_A0)):
        h = 1e-4 * abs(x0[j])
        up, dn = list(x0), list(x0)
        up[j] += h
        dn[j] -= h
        fd = (objective_np(*up) - objective_np(*dn)) / (2 * h)
        assert abs(g[idx] - fd) <= 1e-8 * max(abs(fd), 1e-12), (idx, g[idx], fd)


def test_deterministic_parameter_gradients_are_the_same_bits_every_run(device):
    """Tracer(deterministic=True) with gradients: a copy of each surface's row per ray, summed in order, so the
    curvature and conic gradients of a Cooke triplet trace (4000 rays, 3 fields) are bit-equal over three
    runs (on a GPU the default replicas add atomically in arrival order), and equal the default tracer's to
    rounding (measured on the CPU: 8.0e-16 of the largest; tolerance 1e-12)."""
    import rwwarp as rw
    from rwwarp.trace import Tracer
    lens = rw.load_lens("cooke_triplet")

    def grads(det):
        tr = Tracer(lens, [0.55], device=device, requires_grad=True, deterministic=det)
        src = tr.sources([0.0, 7.0, 14.0], [0, 0, 0])
        tape = wp.Tape()
        with tape:
            rays = tr._run(src, None, None, grid_n=37)
        n = rays.opl.shape[0]
        tape.backward(grads={rays.opl: wp.ones(n, dtype=rays.opl.dtype, device=device)})
        g = np.stack([p.grad.numpy().copy() for p in tr.params])
        tape.zero()
        return g
    first = grads(True)
    for _ in range(2):
        assert np.array_equal(grads(True), first)
    ref = grads(False)
    assert np.max(np.abs(first - ref)) <= 1e-12 * np.max(np.abs(ref))
