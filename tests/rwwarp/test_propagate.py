"""Band-limited angular spectrum propagation (rwwarp.wave.propagate) on OpenCL (PoCL by default).

Oracles: numpy.fft; an independent numpy implementation of the (shifted) BL-ASM written here
from Matsushima's papers; the analytic paraxial Gaussian beam; the exact angular-spectrum integral
of a tilted Gaussian (analytic spectrum, direct quadrature); analytic pixel integrals (erf);
Parseval; z then -z round trips; adjoint dot products and central finite differences.
"""

import numpy as np
import pytest
from scipy.special import erf

from rwwarp.wave import propagate as prop
from rwwarp.errors import SamplingWarning

# ----------------------------------------------------------------------------------------------
# independent references
# ----------------------------------------------------------------------------------------------


def _matsushima_limits(lam, z, x0s, sx):
    """Band limits of the shifted BL-ASM (Matsushima 2010, z > 0): offset x0s, half window sx."""
    u_plus = 1.0 / (lam * np.sqrt((z / (x0s + sx)) ** 2 + 1.0))
    u_minus = 1.0 / (lam * np.sqrt((z / (x0s - sx)) ** 2 + 1.0))
    if x0s > sx:
        return u_minus, u_plus
    if x0s < -sx:
        return -u_minus, -u_plus
    return -u_minus, u_plus


def ref_blasm(field, pitch, origin, lam_um, z, out_x, out_y, npad, carrier=(0.0, 0.0), phase=None, scale=1.0,
              d_dz=False):
    """numpy BL-ASM of one (N, N) field, evaluated at out_x (Mx,), out_y (My,) by an explicit
    inverse DFT sum over the whole padded spectrum (numpy fftfreq frequencies). ``d_dz``: the
    derivative of the output with respect to z instead (transfer function times
    ``2 pi i sqrt(1/lambda^2 - u^2 - v^2)``, band limits held fixed)."""
    u = np.asarray(field, dtype=complex)
    if phase is not None:
        u = u * np.exp(1j * scale * phase)
    ny, nx = u.shape
    padded = np.zeros((npad, npad), dtype=complex)
    padded[:ny, :nx] = u
    spectrum = np.fft.fft2(padded)
    f = np.fft.fftfreq(npad, d=pitch)
    lam = lam_um * 1e-3
    half = 0.5 * npad * pitch
    x0s = 0.5 * (out_x.min() + out_x.max()) - (origin[0] + 0.5 * (nx - 1) * pitch)
    y0s = 0.5 * (out_y.min() + out_y.max()) - (origin[1] + 0.5 * (ny - 1) * pitch)
    ulo, uhi = _matsushima_limits(lam, z, x0s, half)
    vlo, vhi = _matsushima_limits(lam, z, y0s, half)
    uu = f[None, :] + carrier[0]
    vv = f[:, None] + carrier[1]
    arg = 1.0 / lam**2 - uu**2 - vv**2
    keep = (uu >= ulo) & (uu <= uhi) & (vv >= vlo) & (vv <= vhi) & (arg > 0)
    h = np.where(keep, np.exp(2j * np.pi * z * np.sqrt(np.maximum(arg, 0.0))), 0.0)
    if d_dz:
        h = h * 2j * np.pi * np.sqrt(np.maximum(arg, 0.0))
    ex = (
        np.exp(2j * np.pi * np.outer(out_x - origin[0], f)) * np.exp(2j * np.pi * carrier[0] * out_x)[:, None]
    )
    ey = (
        np.exp(2j * np.pi * np.outer(out_y - origin[1], f)) * np.exp(2j * np.pi * carrier[1] * out_y)[:, None]
    )
    return ey @ (spectrum * h) @ ex.T / npad**2


def gaussian_paraxial(x, y, w0, lam_um, z, xc=0.0, yc=0.0):
    """Paraxial Gaussian beam exp(-r^2/w0^2) at z = 0, propagated by z (q-parameter form,
    including exp(i k z))."""
    lam = lam_um * 1e-3
    k = 2 * np.pi / lam
    q0 = -1j * np.pi * w0**2 / lam
    q = q0 + z
    r2 = (x[None, :] - xc) ** 2 + (y[:, None] - yc) ** 2
    return (q0 / q) * np.exp(1j * k * z) * np.exp(1j * k * r2 / (2 * q))


def gaussian_angular_spectrum(x, y, w0, lam_um, z, xc, yc, carrier, span=8.0, step=0.05):
    """Exact scalar propagation of exp(-|r - rc|^2/w0^2) exp(2 pi i c.r) by the angular-spectrum
    integral: analytic spectrum, trapezoidal quadrature over |u - c| < span sigma."""
    lam = lam_um * 1e-3
    sigma = 1.0 / (np.pi * w0 * np.sqrt(2.0))
    du = np.arange(-span * sigma, span * sigma + step / 2, step)
    u = carrier[0] + du
    v = carrier[1] + du
    spec = (
        np.pi
        * w0**2
        * np.exp(-(np.pi**2) * w0**2 * (du[:, None] ** 2 + du[None, :] ** 2))
        * np.exp(-2j * np.pi * (du[None, :] * xc + du[:, None] * yc))
    )
    w = np.sqrt(1.0 / lam**2 - u[None, :] ** 2 - v[:, None] ** 2)
    a = spec * np.exp(2j * np.pi * z * w) * step * step
    ex = np.exp(2j * np.pi * np.outer(x, u))
    ey = np.exp(2j * np.pi * np.outer(y, v))
    return ey @ a @ ex.T


def pixel_integral_gaussian_intensity(cx, cy, pitch, w, peak):
    """Integral of peak * exp(-2 r^2/w^2) over square pixels centred on cx (Px,), cy (Py,)."""
    s = w / np.sqrt(2.0)  # exp(-2 x^2 / w^2) = exp(-x^2 / s^2)

    def axis(c):
        return 0.5 * np.sqrt(np.pi) * s * (erf((c + pitch / 2) / s) - erf((c - pitch / 2) / s))

    return peak * np.outer(axis(cy), axis(cx))


@pytest.fixture(params=["opencl", pytest.param("cuda", marks=pytest.mark.gpu)])
def backend(request):
    """Both builds of the same kernels: OpenCL (PoCL by default) and CUDA (skipped without CuPy/GPU)."""
    if request.param == "cuda":
        return _cuda_backend()
    return request.getfixturevalue("cl_backend")


def field_at(backend, field, pitch, origin, lam, z, out_x, out_y, doe_phase=None, **kw):
    """The propagated field at the points out_x x out_y ((M,) or (B, M), mm): the node field of the production
    operator, :class:`SensorPropagator`, with one Gauss node per pixel (the node is the pixel centre; the pixel
    pitch then only scales the pixel power). ``kw``: the other :class:`SensorGeometry` fields."""
    geo = prop.SensorGeometry(pitch, origin, lam, z, out_x, out_y, 1.0, gauss_nodes=1, **kw)
    return prop.SensorPropagator(backend, geo).forward(field, doe_phase, return_nodes=True)[1]


def sensor_op(backend, pitch, origin, lam, z, cx, cy, pp, **kw):
    """The production operator for these sensor pixels (``kw``: the other :class:`SensorGeometry` fields)."""
    return prop.SensorPropagator(backend, prop.SensorGeometry(pitch, origin, lam, z, cx, cy, pp, **kw))


def rel_l2(a, b):
    return float(np.linalg.norm(np.ravel(a - b)) / np.linalg.norm(np.ravel(b)))


def _rand_complex(rng, shape):
    return rng.standard_normal(shape) + 1j * rng.standard_normal(shape)


# ----------------------------------------------------------------------------------------------
# FFT
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("shape", [(3, 24, 40), (1, 60, 60)])
def test_fft2_matches_numpy(backend, dtype, shape):
    rng = np.random.default_rng(1)
    x = _rand_complex(rng, shape).astype(dtype)
    tol = 1e-14 if dtype == np.complex128 else 2e-6
    dev = backend.to_device(x)
    backend.fft2(dev, inverse=False)
    ref = np.fft.fft2(x.astype(np.complex128), axes=(-2, -1))
    assert rel_l2(backend.to_host(dev), ref) < tol
    backend.fft2(dev, inverse=True)
    assert rel_l2(backend.to_host(dev), x) < tol
    dev = backend.to_device(x)
    backend.fft2(dev, inverse=True)
    assert rel_l2(backend.to_host(dev), np.fft.ifft2(x.astype(np.complex128), axes=(-2, -1))) < tol


def test_backend_arrays_and_selection(backend):
    from rwwarp.wave.backend import get_backend

    assert get_backend(backend.device) is backend  # memoised
    host = np.arange(12, dtype=np.complex64).reshape(3, 4) * (1 - 2j)
    assert np.array_equal(backend.to_host(backend.to_device(host)), host)
    z = backend.zeros((5, 7), np.float64)
    assert z.shape == (5, 7) and not np.any(backend.to_host(z))
    assert backend.empty((2, 3), np.complex128).dtype == np.complex128
    with pytest.raises(ValueError):
        get_backend("tpu:0")


def test_cuda_without_cupy_is_a_clear_error():
    try:
        import cupy  # noqa: F401

        pytest.skip("CuPy is installed")
    except ImportError:
        pass
    from rwwarp.wave.backend import get_backend

    with pytest.raises(RuntimeError, match="CuPy"):
        get_backend("cuda:0")


@pytest.mark.parametrize("flags", [(0, 0, 0, 0), (1, 1, 0, 0), (0, 0, 0, 1), (1, 0, 1, 1)])
def test_gemm_kernels_match_numpy(backend, dtype, flags):
    """Both complex GEMM kernels (GPU-tiled in its two tile shapes, CPU-vectorised) against numpy
    for op(A) op(B) with transposes/conjugates, odd sizes and a batch."""
    ta, ca, tb, cb = flags
    rng = np.random.default_rng(12)
    bsz, m, n, k = 2, 37, 45, 70
    a = _rand_complex(rng, (bsz, k, m) if ta else (bsz, m, k)).astype(dtype)
    b = _rand_complex(rng, (bsz, n, k) if tb else (bsz, k, n)).astype(dtype)
    op_a = np.swapaxes(a, 1, 2) if ta else a
    op_b = np.swapaxes(b, 1, 2) if tb else b
    ref = (np.conj(op_a) if ca else op_a).astype(np.complex128) @ (np.conj(op_b) if cb else op_b).astype(
        np.complex128
    )
    tol = 1e-13 if dtype == np.complex128 else 2e-6
    args = (
        backend.to_device(a),
        backend.to_device(b),
        m,
        n,
        k,
        a.shape[2],
        b.shape[2],
        n,
        a[0].size,
        b[0].size,
        m * n,
        ta,
        ca,
        tb,
        cb,
    )
    variants = [
        (
            "cgemm_batched_kernel",
            (-(-n // 32) * wg, -(-m // 32) * wg, bsz),
            (wg, wg, 1),
            ("GEMM_TS=32", f"GEMM_WG={wg}", f"GEMM_TK={tk}"),
        )
        for wg, tk in ((16, 32), (8, 16))
    ]
    if getattr(backend, "is_cpu", False):
        variants = variants[:1]  # CPUs use cgemm_cpu_kernel; one tiled build is enough there (compile time)
    if getattr(backend, "is_cpu", False) and not tb:
        variants.append(("cgemm_cpu_kernel", (-(-n // 4), -(-m // 8), bsz), (16, 1, 1), ()))
    for name, gsize, lsize, defines in variants:
        c = backend.empty((bsz, m, n), dtype)
        backend.launch("angular_spectrum.cl", name, dtype, gsize, lsize, *args, c, defines=defines)
        assert rel_l2(backend.to_host(c), ref) < tol, name
    if backend.vendor_gemm:   # CUDA: cuBLAS through strided_gemm, the path propagate_stages._gemm takes there
        c = backend.empty((bsz, m, n), dtype)
        backend.gemm(args[0], args[1], c, m, n, k, batch=bsz, lda=args[5], ldb=args[6], ldc=n, sa=args[8], sb=args[9],
                     sc=m * n, ta=ta, ca=ca, tb=tb, cb=cb)
        assert rel_l2(backend.to_host(c), ref) < tol, "vendor gemm"


@pytest.mark.parametrize("flags", [(0, 0, 0, 0), (1, 1, 0, 0), (0, 0, 1, 1), (1, 0, 1, 1)])
def test_strided_gemm_reads_the_kernel_layout(flags):
    """strided_gemm (the vendor-BLAS GEMM's argument mapping, run here with numpy) against a plain loop over
    the batch, with the layouts the OpenCL kernel takes: padded rows (ld > columns), a gap between batch
    matrices, a matrix shared over the batch (batch stride 0) and an output with padded rows; and a view
    that would reach past its buffer is refused."""
    from rwwarp.wave.blas import strided_gemm
    ta, ca, tb, cb = flags
    rng = np.random.default_rng(3)
    bsz, m, n, k = 3, 5, 7, 11
    ra, rb = (k, m) if ta else (m, k), (n, k) if tb else (k, n)
    lda, ldb, ldc = ra[1] + 2, rb[1] + 1, n + 3
    sa, sb, sc = ra[0] * lda + 4, 0, m * ldc
    a = _rand_complex(rng, (bsz * sa,))
    b = _rand_complex(rng, (rb[0] * ldb,))
    c = np.zeros(bsz * sc, complex)
    strided_gemm(np, a, b, c, m, n, k, batch=bsz, lda=lda, ldb=ldb, ldc=ldc, sa=sa, sb=sb, sc=sc, ta=ta, ca=ca,
                 tb=tb, cb=cb)
    mat_b = b.reshape(rb[0], ldb)[:, :rb[1]]
    mat_b = mat_b.T if tb else mat_b
    for i in range(bsz):
        mat_a = a[i * sa:i * sa + ra[0] * lda].reshape(ra[0], lda)[:, :ra[1]]
        mat_a = mat_a.T if ta else mat_a
        want = (np.conj(mat_a) if ca else mat_a) @ (np.conj(mat_b) if cb else mat_b)
        got = c[i * sc:(i + 1) * sc].reshape(m, ldc)[:, :n]
        assert np.max(np.abs(got - want)) < 1e-12 * np.max(np.abs(want))
        assert not np.any(c[i * sc:(i + 1) * sc].reshape(m, ldc)[:, n:])   # the padding is not written
    with pytest.raises(ValueError, match="does not fit"):
        strided_gemm(np, a[:(bsz - 1) * sa + (ra[0] - 1) * lda + ra[1] - 1], b, c, m, n, k, batch=bsz, lda=lda, ldb=ldb, ldc=ldc, sa=sa, sb=sb, sc=sc,
                     ta=ta, ca=ca, tb=tb, cb=cb)


def test_next_fft_size():
    assert [prop.next_fft_size(n) for n in (1, 11, 13, 64, 97, 121, 2000)] == [1, 12, 14, 64, 98, 125, 2000]


# ----------------------------------------------------------------------------------------------
# BL-ASM against the numpy reference
# ----------------------------------------------------------------------------------------------
B, N, NP, PITCH = 2, 32, 64, 0.004


def _random_case(seed=0):
    rng = np.random.default_rng(seed)
    return {
        "field": _rand_complex(rng, (B, N, N)),
        "origin": np.array([[-0.06, 0.01], [0.02, -0.03]]),
        "lam": np.array([0.55, 0.45]),
        "phase": rng.uniform(-3, 3, (N, N)),
        "scale": np.array([1.0, 1.2]),
        "carrier": np.array([[10.0, -5.0], [0.0, 20.0]]),
        "ox": np.linspace(-0.05, 0.07, 17)[None, :] + np.array([[0.0], [0.03]]),
        "oy": np.linspace(-0.04, 0.05, 13)[None, :] + np.array([[0.01], [-0.02]]),
    }


@pytest.mark.parametrize("z", [0.8, 3.0])
def test_point_field_matches_numpy_blasm(backend, z):
    """The field at arbitrary points (the sensor operator's node field): random field, DOE phase, carrier,
    per-batch wavelengths and off-grid, off-axis outputs; the band limit is active (z = 3 mm cuts most of
    the spectrum)."""
    c = _random_case()
    out = field_at(
        backend,
        c["field"],
        PITCH,
        c["origin"],
        c["lam"],
        z,
        c["ox"],
        c["oy"],
        doe_phase=c["phase"],
        doe_scale=c["scale"],
        carrier_cpmm=c["carrier"],
        pad_to=NP,
    )
    out = backend.to_host(out)
    assert out.shape == (B, 13, 17) and out.dtype == np.complex128
    for b in range(B):
        ref = ref_blasm(
            c["field"][b],
            PITCH,
            c["origin"][b],
            c["lam"][b],
            z,
            c["ox"][b],
            c["oy"][b],
            NP,
            c["carrier"][b],
            c["phase"],
            c["scale"][b],
        )
        assert np.abs(out[b] - ref).max() <= 1e-10 * np.abs(ref).max()


def test_propagate_grid_matches_numpy_blasm(backend):
    """Fixed-grid path (inverse FFT + crop) with a shifted output window and a carrier."""
    c = _random_case(1)
    z = 1.5
    out_origin = c["origin"] + np.array([[0.013, -0.021], [-0.05, 0.002]])
    out = backend.to_host(
        prop.propagate_grid(
            backend,
            c["field"],
            PITCH,
            c["origin"],
            c["lam"],
            z,
            out_origin_mm=out_origin,
            doe_phase=c["phase"],
            doe_scale=c["scale"],
            carrier_cpmm=c["carrier"],
            pad_to=NP,
        )
    )
    assert out.shape == (B, N, N)
    for b in range(B):
        xs = out_origin[b, 0] + PITCH * np.arange(N)
        ys = out_origin[b, 1] + PITCH * np.arange(N)
        ref = ref_blasm(
            c["field"][b],
            PITCH,
            c["origin"][b],
            c["lam"][b],
            z,
            xs,
            ys,
            NP,
            c["carrier"][b],
            c["phase"],
            c["scale"][b],
        )
        # propagate_grid keeps the carrier factored out
        ref = ref * np.exp(
            -2j * np.pi * (c["carrier"][b, 0] * xs[None, :] + c["carrier"][b, 1] * ys[:, None])
        )
        assert np.abs(out[b] - ref).max() <= 1e-10 * np.abs(ref).max()


# ----------------------------------------------------------------------------------------------
# physics
# ----------------------------------------------------------------------------------------------
G_N, G_PITCH, G_W0, G_LAM = 64, 0.01, 0.05, 0.5  # Gaussian beam: NA ~ lambda / (pi w0) = 3e-3


def _gaussian_input(n=G_N, pitch=G_PITCH, w0=G_W0):
    origin = np.array([-(n - 1) / 2 * pitch, -(n - 1) / 2 * pitch])
    x = origin[0] + pitch * np.arange(n)
    field = np.exp(-(x[None, :] ** 2 + x[:, None] ** 2) / w0**2)
    return field[None].astype(np.complex128), origin, x


def test_round_trip(backend):
    """The field at points (DFT output on the input grid) by z, then propagate_grid by -z: identity for
    a field whose spectrum lies inside the band."""
    rng = np.random.default_rng(3)
    field, origin, x = _gaussian_input(w0=0.04)
    field = (
        field * np.exp(1j * rng.uniform(-0.2, 0.2) * (x[None, :] / 0.1) ** 2) * (1 + 0.3j * x[:, None] / 0.1)
    )
    z = 5.0
    fwd = field_at(backend, field, G_PITCH, origin, G_LAM, z, x, x)
    back = backend.to_host(prop.propagate_grid(backend, fwd, G_PITCH, origin, G_LAM, -z))
    assert rel_l2(back, field) < 1e-11
    fwd2 = prop.propagate_grid(backend, field, G_PITCH, origin, G_LAM, -z)
    back2 = backend.to_host(field_at(backend, fwd2, G_PITCH, origin, G_LAM, z, x, x))
    assert rel_l2(back2, field) < 1e-11


def test_energy_conservation(backend):
    """Parseval: the power sum |U|^2 dA is conserved on the grid, on a different output pitch,
    and as the sum of sensor-pixel powers."""
    field, origin, _x = _gaussian_input()
    p_in = np.sum(np.abs(field) ** 2) * G_PITCH**2
    z = 20.0
    grid = backend.to_host(prop.propagate_grid(backend, field, G_PITCH, origin, G_LAM, z))
    assert abs(np.sum(np.abs(grid) ** 2) * G_PITCH**2 / p_in - 1) < 1e-12
    xo = np.arange(-0.3, 0.3, 0.0071)
    pts = backend.to_host(field_at(backend, field, G_PITCH, origin, G_LAM, z, xo, xo))
    assert abs(np.sum(np.abs(pts) ** 2) * 0.0071**2 / p_in - 1) < 1e-10
    centers = np.arange(-0.3, 0.3, 0.02) + 0.01
    inten = backend.to_host(
        sensor_op(backend, G_PITCH, origin, G_LAM, z, centers, centers, 0.02).forward(field)
    )
    assert abs(inten.sum() / p_in - 1) < 1e-8


def test_gaussian_beam_paraxial(backend):
    """Against the analytic paraxial Gaussian beam at z = 20 mm (z/zR = 1.3), off-grid outputs."""
    field, origin, _ = _gaussian_input()
    z = 20.0
    xo = np.linspace(-0.15, 0.2, 41)
    yo = np.linspace(-0.18, 0.12, 37)
    out = backend.to_host(field_at(backend, field, G_PITCH, origin, G_LAM, z, xo, yo))[0]
    ref = gaussian_paraxial(xo, yo, G_W0, G_LAM, z)
    assert rel_l2(out, ref) < 2e-5  # non-paraxial terms ~ k z (lambda f)^4 / 8


def test_tilted_gaussian_shifted_window(backend):
    """Off-axis beam (8 deg in x, -5 deg in y, far above the grid's Nyquist frequency) carried by
    carrier_cpmm; the output window follows the beam 2.8 mm off axis (shifted ASM). Checked against
    the exact angular-spectrum integral and the analytic beam walk-off."""
    field, origin, _ = _gaussian_input()
    lam = G_LAM * 1e-3
    carrier = np.array([np.sin(np.radians(8.0)), np.sin(np.radians(-5.0))]) / lam
    z = 20.0
    dirz = np.sqrt(1 - lam**2 * np.sum(carrier**2))
    walk = z * lam * carrier / dirz  # where the beam axis crosses the plane z
    xo = walk[0] + np.linspace(-0.2, 0.2, 33)
    yo = walk[1] + np.linspace(-0.2, 0.2, 29)
    out = backend.to_host(
        field_at(backend, field, G_PITCH, origin, G_LAM, z, xo, yo, carrier_cpmm=carrier)
    )[0]
    ref = gaussian_angular_spectrum(xo, yo, G_W0, G_LAM, z, 0.0, 0.0, carrier)
    assert rel_l2(out, ref) < 1e-9
    inten = np.abs(out) ** 2
    cx = np.sum(inten * xo[None, :]) / inten.sum()
    cy = np.sum(inten * yo[:, None]) / inten.sum()
    assert abs(cx - walk[0]) < 1e-3 * abs(walk[0]) and abs(cy - walk[1]) < 1e-3 * abs(walk[1])
    # without the shift the same beam would wrap around: the library says so
    with pytest.warns(SamplingWarning):
        field_at(backend, field, G_PITCH, origin, G_LAM, z, np.linspace(-0.2, walk[0], 9), yo, carrier_cpmm=carrier)


def test_sensor_intensity_box_integration(backend):
    """Pixel powers: against the analytic (erf) integral of the paraxial Gaussian intensity, and
    against direct 16-point Gauss-Legendre integration of |U|^2 per pixel (U: the field at those points)."""
    field, origin, _ = _gaussian_input()
    z = 20.0
    pp = 0.012
    cx = np.arange(-6, 7) * pp + 0.003
    cy = np.arange(-5, 6) * pp - 0.002
    inten = backend.to_host(
        sensor_op(backend, G_PITCH, origin, G_LAM, z, cx, cy, pp, gauss_nodes=3).forward(field)
    )[0]
    lam = G_LAM * 1e-3
    zr = np.pi * G_W0**2 / lam
    wz = G_W0 * np.sqrt(1 + (z / zr) ** 2)
    analytic = pixel_integral_gaussian_intensity(cx, cy, pp, wz, (G_W0 / wz) ** 2)
    assert rel_l2(inten, analytic) < 2e-5
    t, w = np.polynomial.legendre.leggauss(16)
    xs = (cx[:, None] + 0.5 * pp * t[None, :]).ravel()
    ys = (cy[:, None] + 0.5 * pp * t[None, :]).ravel()
    u = backend.to_host(field_at(backend, field, G_PITCH, origin, G_LAM, z, xs, ys))[0]
    direct = np.einsum("aibj,i,j->ab", (np.abs(u) ** 2).reshape(len(cy), 16, len(cx), 16), w, w) * pp * pp / 4
    assert rel_l2(inten, direct) < 1e-7


def test_complex64_close_to_complex128(backend):
    c = _random_case(2)
    args = (c["field"], PITCH, c["origin"], c["lam"], 0.8, c["ox"], c["oy"])
    kw = {"doe_phase": c["phase"], "doe_scale": c["scale"], "carrier_cpmm": c["carrier"], "pad_to": NP}
    u64 = field_at(backend, *args, dtype=np.complex64, **kw)
    assert u64.dtype == np.complex64
    u128 = field_at(backend, *args, dtype=np.complex128, **kw)
    assert rel_l2(backend.to_host(u64), backend.to_host(u128)) < 1e-4
    field, origin, _ = _gaussian_input()
    cx = np.arange(-8, 8) * 0.01
    i64 = sensor_op(backend, G_PITCH, origin, G_LAM, 20.0, cx, cx, 0.01, dtype=np.complex64).forward(field)
    i128 = sensor_op(backend, G_PITCH, origin, G_LAM, 20.0, cx, cx, 0.01).forward(field)
    assert i64.dtype == np.float32
    assert rel_l2(backend.to_host(i64), backend.to_host(i128)) < 1e-4


# ----------------------------------------------------------------------------------------------
# adjoints
# ----------------------------------------------------------------------------------------------
def _vdot(a, b):
    return np.vdot(np.ravel(a), np.ravel(b))


@pytest.mark.parametrize("phase_batched", [False, True])
def test_sensor_adjoint_is_the_adjoint_of_the_point_field(backend, phase_batched):
    """<A x', y> = <x', A^H y> for the linear map A: field -> U at the nodes (DOE phase, carrier, shift
    included). With one Gauss node per pixel (weight 2, area pp^2/4) the pixel power is I = pp^2 |U|^2, so
    L = sum W I has the node gradient y = dL/dRe U + 1j dL/dIm U = 2 pp^2 W U(x), and the operator's
    field gradient for (W, x) must be A^H y: checked against A applied to an independent field x'."""
    c = _random_case(4)
    rng = np.random.default_rng(5)
    phase = c["phase"] if not phase_batched else rng.uniform(-3, 3, (B, N, N))
    pp = 0.7
    op = sensor_op(backend, PITCH, c["origin"], c["lam"], 1.1, c["ox"], c["oy"], pp, gauss_nodes=1,
                   doe_scale=c["scale"], carrier_cpmm=c["carrier"], pad_to=NP)
    x = c["field"]
    x2 = _rand_complex(rng, x.shape)
    weight = rng.standard_normal((B, 13, 17))
    inten, u = op.forward(x, phase, return_nodes=True)
    u = backend.to_host(u)
    assert np.allclose(backend.to_host(inten), pp**2 * np.abs(u) ** 2, rtol=1e-14, atol=0)
    y = 2 * pp**2 * weight * u
    ahy, gphi = op.adjoint(weight, x, phase)
    ax2 = backend.to_host(op.forward(x2, phase, return_nodes=True)[1])
    lhs, rhs = _vdot(ax2, y), _vdot(x2, backend.to_host(ahy))
    assert abs(lhs - rhs) < 1e-12 * abs(lhs)
    assert backend.to_host(gphi).shape == np.shape(phase)


def test_propagate_grid_adjoint_dot_product(backend):
    c = _random_case(6)
    rng = np.random.default_rng(7)
    kw = {
        "doe_phase": c["phase"],
        "doe_scale": c["scale"],
        "carrier_cpmm": c["carrier"],
        "pad_to": NP,
        "out_origin_mm": c["origin"] + 0.03,
    }
    args = (PITCH, c["origin"], c["lam"], 2.0)
    x = c["field"]
    y = _rand_complex(rng, (B, N, N))
    ax = backend.to_host(prop.propagate_grid(backend, x, *args, **kw))
    ahy = backend.to_host(prop.propagate_grid_adjoint(backend, y, x, *args, **kw)[0])
    lhs, rhs = _vdot(ax, y), _vdot(x, ahy)
    assert abs(lhs - rhs) < 1e-12 * abs(lhs)


def _fd_check(loss, grad_field, grad_phase, field, phase, rng, eps=1e-6):
    """Directional central differences of loss(field, phase) against the analytic gradients
    (grad = dL/dRe + 1j dL/dIm for the field, dL/dphi for the phase)."""
    d_field = _rand_complex(rng, field.shape)
    d_phase = rng.standard_normal(phase.shape)
    fd = (loss(field + eps * d_field, phase) - loss(field - eps * d_field, phase)) / (2 * eps)
    an = np.real(_vdot(grad_field, d_field))  # Re sum conj(g) d = dRe.gRe + dIm.gIm
    assert abs(fd - an) < 1e-6 * max(abs(an), 1e-300)
    fd = (loss(field, phase + eps * d_phase) - loss(field, phase - eps * d_phase)) / (2 * eps)
    an = np.sum(grad_phase * d_phase)
    assert abs(fd - an) < 1e-6 * max(abs(an), 1e-300)


@pytest.mark.parametrize("phase_batched", [False, True])
def test_sensor_adjoint_finite_differences(backend, phase_batched):
    """L = sum W * I(field, phi) with a shared or per-batch DOE phase and a carrier, reusing the forward
    node field (a shared phase's gradient sums over the batch)."""
    rng = np.random.default_rng(9)
    n, b = 8, 2
    field = _rand_complex(rng, (b, n, n))
    phase = rng.uniform(-2, 2, (b, n, n) if phase_batched else (n, n))
    kw = {"doe_scale": np.array([1.0, 0.9]), "carrier_cpmm": np.array([3.0, -7.0]), "pad_to": 16, "gauss_nodes": 2}
    op = sensor_op(backend, 0.003, np.array([0.0, 0.0]), np.array([0.5, 0.6]), 0.3,
                   np.array([[0.002, 0.006, 0.01], [0.004, 0.008, 0.012]]), np.array([0.003, 0.007, 0.011, 0.015]),
                   0.004, **kw)
    weight = rng.standard_normal((b, 4, 3))

    def loss(f, p):
        return float(np.sum(weight * backend.to_host(op.forward(f, p))))

    _, nodes = op.forward(field, phase, return_nodes=True)
    gf, gp = op.adjoint(weight, field, phase, nodes=nodes)
    gf, gp = backend.to_host(gf), backend.to_host(gp)
    assert gp.shape == phase.shape
    _fd_check(loss, gf, gp, field, phase, rng)
    gf2, _ = op.adjoint(weight, field, phase)
    assert np.allclose(backend.to_host(gf2), gf, rtol=0, atol=1e-13 * np.abs(gf).max())


@pytest.mark.parametrize("z", [0.8, 3.0])
def test_sensor_intensity_distance_gradient(backend, z):
    """dL/dz of L = sum W * I (I the pixel-integrated intensity) from
    SensorPropagator.distance_adjoint against (a) an independent numpy derivative (ref_blasm with
    dH/dz = 2 pi i w H, Gauss-Legendre nodes summed here) and (b) 4-point central differences of the
    loss; its field / phase gradients equal SensorPropagator.adjoint's. z = 3 mm: band limit active."""
    c = _random_case(3)
    gauss = 3
    pp = 0.006
    cx = np.linspace(-0.04, 0.06, 6)[None, :] + np.array([[0.0], [0.02]])
    cy = np.linspace(-0.03, 0.04, 5)[None, :] + np.array([[0.01], [-0.01]])
    kw = {"doe_scale": c["scale"], "carrier_cpmm": c["carrier"], "pad_to": NP, "gauss_nodes": gauss}
    rng = np.random.default_rng(4)
    weight = rng.random((B, 5, 6))
    zs = np.array([z, 1.1 * z])
    args = (PITCH, c["origin"], c["lam"])
    sens = (cx, cy, pp)
    op = sensor_op(backend, *args, zs, *sens, **kw)
    gf, gp, gd = op.distance_adjoint(weight, c["field"], c["phase"])
    assert gd.shape == (B,) and gd.dtype == np.float64
    gf0, gp0 = op.adjoint(weight, c["field"], c["phase"])
    np.testing.assert_array_equal(backend.to_host(gf), backend.to_host(gf0))
    np.testing.assert_array_equal(backend.to_host(gp), backend.to_host(gp0))
    # (a) numpy: dI/dz = area sum w w 2 Re(conj(U) dU/dz) at the Gauss nodes
    t, wg = np.polynomial.legendre.leggauss(gauss)
    for b in range(B):
        nx = (cx[b][:, None] + 0.5 * pp * t[None, :]).ravel()
        ny = (cy[b][:, None] + 0.5 * pp * t[None, :]).ravel()
        ref = [ref_blasm(c["field"][b], PITCH, c["origin"][b], c["lam"][b], zs[b], nx, ny, NP, c["carrier"][b],
                         c["phase"], c["scale"][b], d_dz=d) for d in (False, True)]
        di = 2.0 * np.real(np.conj(ref[0]) * ref[1]).reshape(5, gauss, 6, gauss)
        di = 0.25 * pp * pp * np.einsum("yaxb,a,b->yx", di, wg, wg)
        expect = float(np.sum(weight[b] * di))
        assert abs(gd[b] - expect) <= 1e-9 * abs(expect), (b, gd[b], expect)
    # (b) central differences of the loss (step small enough that no band edge crosses a sample)
    def loss(zz):
        inten = backend.to_host(sensor_op(backend, *args, zz, *sens, **kw).forward(c["field"], c["phase"]))
        return np.sum(weight * inten, axis=(1, 2))

    h = 1e-5 * z
    fd = (8.0 * (loss(zs + h) - loss(zs - h)) - (loss(zs + 2 * h) - loss(zs - 2 * h))) / (12.0 * h)
    np.testing.assert_allclose(gd, fd, rtol=1e-6, atol=0)
    # only the distance
    none_f, none_p, gd2 = op.distance_adjoint(weight, c["field"], c["phase"], need_field=False)
    assert none_f is None and none_p is None
    np.testing.assert_array_equal(gd2, gd)


# ----------------------------------------------------------------------------------------------
# CUDA build of the same kernels (skipped without CuPy / GPU)
# ----------------------------------------------------------------------------------------------
def _cuda_backend():
    cupy = pytest.importorskip("cupy")
    try:
        if cupy.cuda.runtime.getDeviceCount() < 1:
            pytest.skip("no CUDA device")
    except RuntimeError:  # cupy.cuda.runtime.CUDARuntimeError: no driver / device
        pytest.skip("no CUDA device")
    from rwwarp.wave.backend import get_backend

    return get_backend("cuda")


@pytest.mark.gpu
def test_cuda_matches_opencl(cl_backend):
    cu = _cuda_backend()
    c = _random_case(10)
    args = (c["field"], PITCH, c["origin"], c["lam"], 0.8, c["ox"], c["oy"])
    kw = {"doe_phase": c["phase"], "doe_scale": c["scale"], "carrier_cpmm": c["carrier"], "pad_to": NP}
    ref = cl_backend.to_host(field_at(cl_backend, *args, **kw))
    got = cu.to_host(field_at(cu, *args, **kw))
    assert np.abs(got - ref).max() <= 1e-12 * np.abs(ref).max()
    weight = np.random.default_rng(11).standard_normal(ref.shape)
    field, phase = args[0], kw.pop("doe_phase")
    g_ref = [cl_backend.to_host(a) for a in sensor_op(cl_backend, *args[1:], 0.01, gauss_nodes=1, **kw).adjoint(
        weight, field, phase)]
    g_cu = [cu.to_host(a) for a in sensor_op(cu, *args[1:], 0.01, gauss_nodes=1, **kw).adjoint(weight, field, phase)]
    for a, r in zip(g_cu, g_ref):
        assert np.abs(a - r).max() <= 1e-11 * np.abs(r).max()
    field, origin, _ = _gaussian_input()
    cx = np.arange(-8, 8) * 0.01
    for dt in (np.complex128, np.complex64):
        i_ref = cl_backend.to_host(
            sensor_op(cl_backend, G_PITCH, origin, G_LAM, 20.0, cx, cx, 0.01, dtype=dt).forward(field)
        )
        i_cu = cu.to_host(
            sensor_op(cu, G_PITCH, origin, G_LAM, 20.0, cx, cx, 0.01, dtype=dt).forward(field)
        )
        assert rel_l2(i_cu, i_ref) < (1e-12 if dt == np.complex128 else 1e-5)
    grid_ref = cl_backend.to_host(prop.propagate_grid(cl_backend, field, G_PITCH, origin, G_LAM, 5.0))
    grid_cu = cu.to_host(prop.propagate_grid(cu, field, G_PITCH, origin, G_LAM, 5.0))
    assert rel_l2(grid_cu, grid_ref) < 1e-12


def test_x_fft_plans_shared_across_window_heights(cl_backend):
    """Windows a few rows apart share one x-FFT plan (row count on a coarse ladder, plans cost
    ~0.5 s each), and the shared plan's extra rows do not leak into the result: every window still
    conserves energy to 1e-8 (Parseval, as in test_energy_conservation)."""
    from rwwarp.wave.propagate_stages import _fft_rows

    be = cl_backend
    assert [_fft_rows(n) for n in (1, 7, 8, 9, 15, 16, 17)] == [1, 7, 8, 9, 15, 16, 18]
    assert all(n <= _fft_rows(n) <= 1.125 * n for n in range(1, 5000, 37))
    pitch, lam, z = 0.002, 0.55, 1.0
    before = {k for k in be._plans if k[2] == (-1,)}
    for ny in (121, 124, 127):  # all on the ladder step 128
        y = (np.arange(ny) - ny / 2) * pitch
        x = (np.arange(128) - 64) * pitch
        field = np.exp(-(y[:, None] ** 2 + x[None, :] ** 2) / 0.02**2).astype(np.complex128)
        p_in = np.sum(np.abs(field) ** 2) * pitch**2
        centers = np.arange(-0.08, 0.08, 0.01) + 0.005
        op = sensor_op(be, pitch, (x[0], y[0]), lam, z, centers, centers, 0.01, gauss_nodes=8)
        inten = be.to_host(op.forward(field))
        assert abs(inten.sum() / p_in - 1) < 1e-8, ny
    new = {k for k in be._plans if k[2] == (-1,)} - before
    assert len(new) == 1, new
