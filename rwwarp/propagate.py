"""Free-space wave propagation: band-limited angular spectrum method, evaluated anywhere.

Method. The field (optionally times a DOE phase) is zero-padded to (npy, npx), Fourier
transformed (pyvkfft), multiplied by the angular-spectrum transfer function
``H = exp(2 pi i z sqrt(1/lambda^2 - u^2 - v^2))`` (evanescent waves dropped) inside the band limit of
Matsushima & Shimobaba (2009), in its shifted form (Matsushima 2010) when the output window is
off the input window, and brought back either

* at arbitrary output coordinates (:func:`propagate`, :func:`sensor_intensity`): a separable
  matrix DFT ``U = Ey C Ex^T`` over the band (two tiled complex GEMM launches), which is the exact
  trigonometric interpolation of the band-limited result, so the output pitch is free of the
  input pitch; or
* on the input grid, possibly shifted (:func:`propagate_grid`): inverse FFT and crop, the
  classic fixed-grid method.

All device work runs in the OpenCL C kernels of ``kernels/opencl/propagate.cl`` (also built for
CUDA, see :mod:`rwwarp.backend`); this module only computes per-batch parameters on the host and
queues launches. Nothing returns to the host within a call.

Conventions
-----------
* Units: lengths in mm, wavelengths in um (converted to mm here), spatial frequencies in cycles/mm,
  phases in radians.
* **Pixel-centre convention.** Sample (row j, column i) of batch element b sits at
  ``x = origin_mm[b, 0] + i * pitch_mm[b]``, ``y = origin_mm[b, 1] + j * pitch_mm[b]``: the origin
  is the centre of sample (0, 0), rows run along +y, columns along +x. Output and sensor
  coordinates are absolute in the same frame.
* **Field normalisation.** ``sum |u|^2 * pitch^2`` is the power; sensor intensities are
  ``|U|^2`` integrated over each pixel (field units^2 * mm^2), i.e. power per pixel.
* **Carrier.** With ``carrier_cpmm = (fx0, fy0)`` the field handed in is the true field times
  ``exp(-2 pi i (fx0 x + fy0 y))``; the transfer function is evaluated at the true frequencies.
  :func:`propagate` returns the true field (carrier restored) at the requested points;
  :func:`propagate_grid` returns the output with the same carrier still factored out (a coarse
  grid cannot hold it). Intensities do not depend on it.
* **Shift / band limit.** The representable offsets between a source point and an output point
  are the window ``[s - Lp/2, s + Lp/2]`` per axis, ``Lp = n_pad * pitch`` and ``s`` the offset of the
  output window centre from the input window centre; a plane wave of true frequency u reaches
  offset ``z u / sqrt(1/lambda^2 - u^2)``, and it is kept iff that offset lies in the window
  (Matsushima's 1-D limits on each axis; 2009 for s = 0, 2010 otherwise). The result is exact
  (alias-free) when ``input width + output width <= Lp`` per axis; otherwise a
  :class:`~rwwarp.errors.SamplingWarning` names the padding needed.
* **Gradients.** For a real loss L of a complex array U the gradient is ``dL/dRe U + 1j dL/dIm U``
  (torch's convention, twice the conjugate Wirtinger derivative). The adjoint functions map the
  gradient of the output to the gradients of ``field`` (complex) and ``doe_phase`` (real).
* Precision: complex128 by default; complex64 halves memory and is about 1e-5 relative (phases
  are formed in double on devices that have it).
"""

from __future__ import annotations

import warnings

import numpy as np

from .backend import Backend, complex_dtype, get_backend, real_dtype
from .errors import SamplingWarning

__all__ = [
    "band_limits",
    "gauss_legendre",
    "next_fft_size",
    "propagate",
    "propagate_adjoint",
    "propagate_grid",
    "propagate_grid_adjoint",
    "sensor_intensity",
    "sensor_intensity_adjoint",
    "sensor_intensity_distance_adjoint",
    "sensor_window_center",
]

_SRC = "propagate.cl"

# Per-batch parameter row, mirrored from kernels/opencl/propagate.cl (P_* macros).
_P_LAMBDA, _P_Z, _P_ZFRAC, _P_LPX, _P_LPY, _P_X0, _P_Y0, _P_XS, _P_YS = range(9)
_P_CX, _P_CY, _P_ULO, _P_UHI, _P_VLO, _P_VHI, _P_QX0, _P_QY0, _P_KXB, _P_KYB = range(9, 19)
_P_DOE_SCALE = 19
_NPAR = 20
# Columns the transfer function depends on (cache key).
_H_COLS = [c for c in range(_NPAR) if c not in (_P_X0, _P_Y0, _P_DOE_SCALE)]

_LOCAL = (32, 8, 1)
_GEMM_TS = 32
_CPU_GEMM_ROWS = 8
_KX_ROUND = 64


def _round_up(n, m):
    return -(-int(n) // int(m)) * int(m)


def next_fft_size(n: int) -> int:
    """Smallest integer >= n whose prime factors are all in {2, 3, 5, 7} (VkFFT's fast radices)."""
    n = max(int(n), 1)
    while True:
        m = n
        for p in (2, 3, 5, 7):
            while m % p == 0:
                m //= p
        if m == 1:
            return n
        n += 1


def gauss_legendre(order: int):
    """Gauss-Legendre nodes ``t`` and weights ``w`` on [-1, 1] (numpy float64 arrays of ``order``)."""
    t, w = np.polynomial.legendre.leggauss(int(order))
    return t, w


def band_limits(wavelength_mm, distance_mm, window_mm, shift_mm):
    """Matsushima's band limit on one axis (true spatial frequency, cycles/mm).

    A plane wave of frequency u reaches the lateral offset ``z u / sqrt(1/lambda^2 - u^2)``
    (stationary phase); it is kept iff that offset lies in ``[shift - window/2, shift + window/2]``,
    ``window`` being the padded window width ``n_pad * pitch`` (mm). For ``shift = 0`` this is
    ``|u| <= 1 / (lambda sqrt((2 z / window)^2 + 1))`` (Matsushima & Shimobaba 2009); otherwise the
    shifted limits of Matsushima (2010). Arrays broadcast; returns ``(u_lo, u_hi)``
    (``u_lo > u_hi`` when nothing reaches the window).
    """
    lam = np.asarray(wavelength_mm, dtype=np.float64)
    z = np.asarray(distance_mm, dtype=np.float64)
    s_lo = np.asarray(shift_mm, dtype=np.float64) - 0.5 * np.asarray(window_mm, dtype=np.float64)
    s_hi = s_lo + np.asarray(window_mm, dtype=np.float64)
    lam, z, s_lo, s_hi = np.broadcast_arrays(lam, z, s_lo, s_hi)
    with np.errstate(divide="ignore", invalid="ignore"):
        g_lo = np.sign(z) * s_lo / (lam * np.sqrt(z * z + s_lo * s_lo))
        g_hi = np.sign(z) * s_hi / (lam * np.sqrt(z * z + s_hi * s_hi))
    lo = np.minimum(g_lo, g_hi)
    hi = np.maximum(g_lo, g_hi)
    at0 = z == 0  # no propagation: everything stays at offset 0
    inside = (s_lo <= 0) & (s_hi >= 0)
    lo = np.where(at0, np.where(inside, -1.0 / lam, 1.0), lo)
    hi = np.where(at0, np.where(inside, 1.0 / lam, -1.0), hi)
    return lo, hi


# ---------------------------------------------------------------------------------------------
# host-side setup
# ---------------------------------------------------------------------------------------------
class _Setup:
    """Everything a launch sequence needs: sizes, dtype, per-batch parameters (host and device)."""

    __slots__ = (
        "backend",
        "batch",
        "dtype",
        "field",
        "has_phase",
        "kx_max",
        "ky_max",
        "npx",
        "npy",
        "nx",
        "ny",
        "params",
        "params_dev",
        "phase",
        "phase_batched",
        "phase_shape",
        "rdtype",
    )


def _per_batch(value, batch, name, tail=()):
    arr = np.asarray(value, dtype=np.float64)
    try:
        return np.ascontiguousarray(np.broadcast_to(arr, (batch,) + tuple(tail)))
    except ValueError:
        raise ValueError(
            f"{name}: shape {arr.shape} does not broadcast to {(batch,) + tuple(tail)}"
        ) from None


def _resolve_dtype(field, dtype):
    if dtype is not None:
        return complex_dtype(dtype)
    fdt = getattr(field, "dtype", None)
    if fdt is not None and np.dtype(fdt).kind == "c":
        return complex_dtype(fdt)
    return np.dtype(np.complex128)


def _pad_shape(pad_to, ny, nx):
    if pad_to is None:
        return next_fft_size(2 * ny), next_fft_size(2 * nx)
    if np.ndim(pad_to) == 0:
        npy = npx = int(pad_to)
    else:
        npy, npx = (int(v) for v in pad_to)
    if npy < ny or npx < nx:
        raise ValueError(f"pad_to {(npy, npx)} is smaller than the field {(ny, nx)}")
    return npy, npx


def _setup(
    backend,
    field,
    pitch_mm,
    origin_mm,
    wavelength_um,
    distance_mm,
    *,
    doe_phase,
    doe_scale,
    carrier_cpmm,
    pad_to,
    dtype,
    shift_mm=None,
    out_center_mm=None,
):
    """Per-batch parameters. The output window is given either by its centre (DFT path; shift =
    centre - input centre) or by the shift directly (grid path)."""
    be = get_backend(backend) if not isinstance(backend, Backend) else backend
    st = _Setup()
    st.backend = be
    st.dtype = _resolve_dtype(field, dtype)
    st.rdtype = real_dtype(st.dtype)
    fdev = be.to_device(field, st.dtype)
    if fdev.ndim == 2:
        fdev = fdev.reshape((1,) + tuple(fdev.shape))
    if fdev.ndim != 3:
        raise ValueError(f"field must be (B, Ny, Nx) or (Ny, Nx), got shape {tuple(fdev.shape)}")
    st.field = fdev
    batch, ny, nx = (int(s) for s in fdev.shape)
    st.batch, st.ny, st.nx = batch, ny, nx
    st.npy, st.npx = _pad_shape(pad_to, ny, nx)

    pitch = _per_batch(pitch_mm, batch, "pitch_mm")
    if np.any(pitch <= 0):
        raise ValueError("pitch_mm must be positive")
    origin = _per_batch(origin_mm, batch, "origin_mm", (2,))
    lam = _per_batch(wavelength_um, batch, "wavelength_um") * 1e-3
    if np.any(lam <= 0):
        raise ValueError("wavelength_um must be positive")
    z = _per_batch(distance_mm, batch, "distance_mm")
    carrier = (
        np.zeros((batch, 2))
        if carrier_cpmm is None
        else _per_batch(carrier_cpmm, batch, "carrier_cpmm", (2,))
    )

    n = np.array([nx, ny], dtype=np.float64)
    npad = np.array([st.npx, st.npy], dtype=np.float64)
    lp = pitch[:, None] * npad[None, :]  # (B, 2)
    in_center = origin + 0.5 * (n[None, :] - 1.0) * pitch[:, None]
    if shift_mm is not None:
        shift = _per_batch(shift_mm, batch, "shift", (2,))
    else:
        shift = out_center_mm - in_center

    lo, hi = band_limits(lam[:, None], z[:, None], lp, shift)  # (B, 2) each
    qmin = -(npad // 2)
    qmax = (npad - 1) // 2
    with np.errstate(invalid="ignore", over="ignore"):
        q_lo = np.where(np.isfinite(lo), np.ceil((lo - carrier) * lp) - 1.0, qmin)
        q_hi = np.where(np.isfinite(hi), np.floor((hi - carrier) * lp) + 1.0, qmax)
    q_lo = np.clip(q_lo, qmin, qmax + 1)
    q_hi = np.clip(q_hi, qmin - 1, qmax)
    kb = np.maximum(q_hi - q_lo + 1.0, 0.0)

    params = np.zeros((batch, _NPAR), dtype=np.float64)
    params[:, _P_LAMBDA] = lam
    params[:, _P_Z] = z
    zl = z / lam
    params[:, _P_ZFRAC] = zl - np.rint(zl)
    params[:, _P_LPX], params[:, _P_LPY] = lp[:, 0], lp[:, 1]
    params[:, _P_X0], params[:, _P_Y0] = origin[:, 0], origin[:, 1]
    params[:, _P_XS], params[:, _P_YS] = shift[:, 0], shift[:, 1]
    params[:, _P_CX], params[:, _P_CY] = carrier[:, 0], carrier[:, 1]
    params[:, _P_ULO], params[:, _P_UHI] = lo[:, 0], hi[:, 0]
    params[:, _P_VLO], params[:, _P_VHI] = lo[:, 1], hi[:, 1]
    params[:, _P_QX0], params[:, _P_QY0] = q_lo[:, 0], q_lo[:, 1]
    params[:, _P_KXB], params[:, _P_KYB] = kb[:, 0], kb[:, 1]
    # band width rounded up (zero columns beyond each element's band are harmless) so that few
    # distinct y-FFT plans of shape (B, npy, kx_max) are ever built
    st.kx_max = min(st.npx, _round_up(max(int(kb[:, 0].max()), 1), _KX_ROUND))
    st.ky_max = max(int(kb[:, 1].max()), 1)

    # DOE phase
    st.has_phase = doe_phase is not None
    st.phase_batched = False
    st.phase_shape = None
    if st.has_phase:
        ph = be.to_device(doe_phase, st.rdtype)
        st.phase_shape = tuple(ph.shape)
        if ph.ndim == 3 and tuple(ph.shape) == (batch, ny, nx):
            st.phase_batched = True
        elif tuple(ph.shape[-2:]) != (ny, nx) or (ph.ndim == 3 and ph.shape[0] != 1) or ph.ndim not in (2, 3):
            raise ValueError(
                f"doe_phase shape {tuple(ph.shape)} must be ({ny}, {nx}) or ({batch}, {ny}, {nx})"
            )
        st.phase = ph
        scale = np.ones(batch) if doe_scale is None else _per_batch(doe_scale, batch, "doe_scale")
        params[:, _P_DOE_SCALE] = scale
    else:
        st.phase = be.workspace("dummy_phase", (1,), st.rdtype)
        params[:, _P_DOE_SCALE] = 0.0
    st.params = params
    st.params_dev = be.to_device(params.astype(be.phase_dtype))
    return st


def _check_window(st, extent_x, extent_y, what):
    """Warn when input width + output width exceeds the padded window (aliasing)."""
    pitch = st.params[:, _P_LPX] / st.npx
    for axis, ext, n, npad in (("x", extent_x, st.nx, st.npx), ("y", extent_y, st.ny, st.npy)):
        need = n * pitch + np.asarray(ext)
        have = npad * pitch
        if np.any(need > have * (1 + 1e-12)):
            need_n = int(np.max(np.ceil(need / pitch - 1e-9)))
            warnings.warn(
                f"{what}: input width + output width along {axis} ({float(np.max(need)):.6g} mm) exceeds the "
                f"padded window ({float(np.min(have)):.6g} mm = {npad} samples); the result aliases. "
                f"Use pad_to >= {next_fft_size(need_n)} along {axis} or a smaller output window.",
                SamplingWarning,
                stacklevel=3,
            )


# ---------------------------------------------------------------------------------------------
# launch helpers
# ---------------------------------------------------------------------------------------------
def _launch(st, name, gsize, *args, local=_LOCAL, defines=()):
    st.backend.launch(_SRC, name, st.dtype, gsize, local, *args, defines=defines)


def _gemm(st, a, b, c, m, n, k, *, lda, ldb, ldc, sa, sb, sc, ta=0, ca=0, tb=0, cb=0):
    """c[b] = op(a[b]) @ op(b[b]) over the batch: the explicitly vectorised kernel on CPU OpenCL
    devices, the local-memory tiled one on GPUs (same arguments, see propagate.cl). GPU tiles:
    32 x 32 outputs per work-group, 2 x 2 per work-item (k-step 32) when the problem has few
    tiles, 4 x 4 per work-item (k-step 16) when it fills the device several times over
    (measured on an H100: 1.3-1.5x faster there, slower on small problems)."""
    args = (a, b, m, n, k, lda, ldb, ldc, sa, sb, sc, ta, ca, tb, cb, c)
    be = st.backend
    if getattr(be, "is_cpu", False) and not tb:
        _launch(
            st, "cgemm_cpu_kernel", (-(-n // 4), -(-m // _CPU_GEMM_ROWS), st.batch), *args, local=(16, 1, 1)
        )
        return
    tiles = -(-n // _GEMM_TS) * -(-m // _GEMM_TS) * st.batch
    wg, tk = (8, 16) if tiles >= 4 * getattr(be, "compute_units", 1) else (16, 32)
    _launch(
        st,
        "cgemm_batched_kernel",
        (-(-n // _GEMM_TS) * wg, -(-m // _GEMM_TS) * wg, st.batch),
        *args,
        local=(wg, wg, 1),
        defines=(f"GEMM_TS={_GEMM_TS}", f"GEMM_WG={wg}", f"GEMM_TK={tk}"),
    )


def _transfer(st, scale):
    """Transfer function on the band grid (B, ky_max, kx_max), cached per parameters."""
    key = (
        "transfer",
        st.dtype.str,
        st.npx,
        st.npy,
        st.kx_max,
        st.ky_max,
        float(scale),
        st.params[:, _H_COLS].tobytes(),
    )

    def make():
        h = st.backend.empty((st.batch, st.ky_max, st.kx_max), st.dtype)
        _launch(
            st,
            "band_transfer_kernel",
            (st.kx_max, st.ky_max, st.batch),
            st.params_dev,
            st.kx_max,
            st.ky_max,
            st.batch,
            scale,
            h,
        )
        return h

    return st.backend.cache.get(key, make)


def _pad_fft(st, src, has_phase):
    """padded = FFT(zero-pad(src * exp(i s phi))) in the 'padded' workspace."""
    be = st.backend
    padded = be.workspace("padded", (st.batch, st.npy, st.npx), st.dtype)
    _launch(
        st,
        "pad_modulate_kernel",
        (st.npx, st.npy, st.batch),
        src,
        st.phase,
        st.params_dev,
        st.nx,
        st.ny,
        st.npx,
        st.npy,
        st.batch,
        int(has_phase),
        int(st.phase_batched),
        padded,
    )
    be.fft2(padded, inverse=False)
    return padded


def _fft_rows(count: int) -> int:
    """``count`` rounded up on a coarse ladder (a multiple of 2^(floor(log2 count) - 3), so at most
    12.5% more): the row count of x-FFT plans, so that batches whose windows differ by a few rows
    share one plan (a VkFFT plan costs ~0.5 s to build, on PoCL and on CUDA alike)."""
    count = max(int(count), 1)
    step = 1 << max(count.bit_length() - 4, 0)
    return _round_up(count, step)


def _rows_workspace(st):
    """The 'rows' scratch: ``(fft_view, rows)``, both views of one buffer: ``rows`` (B, ny, npx) for
    the kernels and ``fft_view`` (R, npx), R = :func:`_fft_rows` (B ny) >= B ny, for the x-FFT (rows
    past B ny hold garbage that no kernel reads; the transform is row by row)."""
    be = st.backend
    fft_view = be.workspace("rows", (_fft_rows(st.batch * st.ny), st.npx), st.dtype)
    rows = be.workspace("rows", (st.batch, st.ny, st.npx), st.dtype)  # the same buffer's start
    return fft_view, rows


def _band_spectrum(st):
    """C = H * FFT(padded field) on the band (B, ky_max, kx_max), H carrying 1/(npx npy).

    Pruned 2-D FFT: the x-FFT runs over the ny non-zero rows only, the y-FFT over the kx_max band
    columns only (the zero padding along y is inserted between the two)."""
    be = st.backend
    rows_fft, rows = _rows_workspace(st)
    _launch(
        st,
        "pad_modulate_kernel",
        (st.npx, st.ny, st.batch),
        st.field,
        st.phase,
        st.params_dev,
        st.nx,
        st.ny,
        st.npx,
        st.ny,
        st.batch,
        int(st.has_phase),
        int(st.phase_batched),
        rows,
    )
    be.fft1(rows_fft, axis=-1)
    cols = be.workspace("cols", (st.batch, st.npy, st.kx_max), st.dtype)
    _launch(
        st,
        "column_gather_kernel",
        (st.kx_max, st.npy, st.batch),
        rows,
        st.params_dev,
        st.ny,
        st.npx,
        st.npy,
        st.kx_max,
        st.batch,
        cols,
    )
    be.fft1(cols, axis=-2)
    h = _transfer(st, 1.0 / (st.npx * st.npy))
    band = be.workspace("band", (st.batch, st.ky_max, st.kx_max), st.dtype)
    _launch(
        st,
        "band_gather_kernel",
        (st.kx_max, st.ky_max, st.batch),
        cols,
        h,
        st.params_dev,
        st.npy,
        st.kx_max,
        st.ky_max,
        st.batch,
        band,
    )
    return band, h


def _upload_coords(st, xs, ys):
    """Output coordinates (B, M) to the device, before any launch of the call (uploads block)."""
    be = st.backend
    return (
        be.to_device(np.ascontiguousarray(xs, dtype=be.phase_dtype)),
        be.to_device(np.ascontiguousarray(ys, dtype=be.phase_dtype)),
    )


def _dft_factors(st, coords, adjoint=False):
    """Matrix-DFT factors for the device coordinates ``coords = (xs (B, Mx), ys (B, My))``:
    Ey (B, My, ky_max) and Ex^T (B, kx_max, Mx) for the forward product, or Ex (B, Mx, kx_max) for
    the adjoint one (so that the right-hand GEMM operand is never transposed)."""
    be = st.backend
    xs_dev, ys_dev = coords
    mx, my = int(xs_dev.shape[1]), int(ys_dev.shape[1])
    ey = be.workspace("ey", (st.batch, my, st.ky_max), st.dtype)
    _launch(
        st,
        "dft_matrix_kernel",
        (st.ky_max, my, st.batch),
        ys_dev,
        st.params_dev,
        my,
        st.ky_max,
        st.batch,
        1,
        0,
        ey,
    )
    if adjoint:
        ex = be.workspace("ex", (st.batch, mx, st.kx_max), st.dtype)
        _launch(
            st,
            "dft_matrix_kernel",
            (st.kx_max, mx, st.batch),
            xs_dev,
            st.params_dev,
            mx,
            st.kx_max,
            st.batch,
            0,
            0,
            ex,
        )
    else:
        ex = be.workspace("ext", (st.batch, st.kx_max, mx), st.dtype)
        _launch(
            st,
            "dft_matrix_kernel",
            (mx, st.kx_max, st.batch),
            xs_dev,
            st.params_dev,
            mx,
            st.kx_max,
            st.batch,
            0,
            1,
            ex,
        )
    return ex, ey


def _band_to_points(st, band, ext, ey, out):
    """out (B, My, Mx) = Ey @ band @ Ex^T, contracting the cheaper axis first."""
    kx, ky = st.kx_max, st.ky_max
    my, mx = ey.shape[1], ext.shape[2]
    be = st.backend
    if ky * kx * mx + my * ky * mx <= my * ky * kx + my * kx * mx:
        tmp = be.workspace("gemm_tmp", (st.batch, ky, mx), st.dtype)
        _gemm(st, band, ext, tmp, ky, mx, kx, lda=kx, ldb=mx, ldc=mx, sa=ky * kx, sb=kx * mx, sc=ky * mx)
        _gemm(st, ey, tmp, out, my, mx, ky, lda=ky, ldb=mx, ldc=mx, sa=my * ky, sb=ky * mx, sc=my * mx)
    else:
        tmp = be.workspace("gemm_tmp", (st.batch, my, kx), st.dtype)
        _gemm(st, ey, band, tmp, my, kx, ky, lda=ky, ldb=kx, ldc=kx, sa=my * ky, sb=ky * kx, sc=my * kx)
        _gemm(st, tmp, ext, out, my, mx, kx, lda=kx, ldb=mx, ldc=mx, sa=my * kx, sb=kx * mx, sc=my * mx)
    return out


def _points_to_band(st, grad, ex, ey, out):
    """Adjoint of _band_to_points: out (B, ky, kx) = Ey^H @ grad @ conj(Ex), with Ex (B, Mx, kx)
    from _dft_factors(..., adjoint=True)."""
    kx, ky = st.kx_max, st.ky_max
    my, mx = ey.shape[1], ex.shape[1]
    be = st.backend
    if my * mx * kx + ky * my * kx <= ky * my * mx + ky * mx * kx:
        tmp = be.workspace("gemm_tmp", (st.batch, my, kx), st.dtype)
        _gemm(st, grad, ex, tmp, my, kx, mx, lda=mx, ldb=kx, ldc=kx, sa=my * mx, sb=mx * kx, sc=my * kx, cb=1)
        _gemm(
            st,
            ey,
            tmp,
            out,
            ky,
            kx,
            my,
            lda=ky,
            ldb=kx,
            ldc=kx,
            sa=my * ky,
            sb=my * kx,
            sc=ky * kx,
            ta=1,
            ca=1,
        )
    else:
        tmp = be.workspace("gemm_tmp", (st.batch, ky, mx), st.dtype)
        _gemm(
            st,
            ey,
            grad,
            tmp,
            ky,
            mx,
            my,
            lda=ky,
            ldb=mx,
            ldc=mx,
            sa=my * ky,
            sb=my * mx,
            sc=ky * mx,
            ta=1,
            ca=1,
        )
        _gemm(st, tmp, ex, out, ky, kx, mx, lda=mx, ldb=kx, ldc=kx, sa=ky * mx, sb=mx * kx, sc=ky * kx, cb=1)
    return out


def _band_adjoint_to_field(st, band_grad, h):
    """From the gradient of the band spectrum to (grad_field, grad_doe_phase): the transposed
    pruned FFT (scatter with conj(H) * npx * npy, y inverse FFT of the band columns, scatter the
    columns into the ny rows, x inverse FFT), then demodulate."""
    be = st.backend
    cols = be.workspace("cols", (st.batch, st.npy, st.kx_max), st.dtype)
    _launch(
        st,
        "band_scatter_adjoint_kernel",
        (st.kx_max, st.npy, st.batch),
        band_grad,
        h,
        st.params_dev,
        st.npy,
        st.kx_max,
        st.ky_max,
        st.batch,
        float(st.npx * st.npy),
        cols,
    )
    be.fft1(cols, axis=-2, inverse=True)
    rows_fft, rows = _rows_workspace(st)
    _launch(
        st,
        "column_scatter_adjoint_kernel",
        (st.npx, st.ny, st.batch),
        cols,
        st.params_dev,
        st.ny,
        st.npx,
        st.npy,
        st.kx_max,
        st.batch,
        rows,
    )
    be.fft1(rows_fft, axis=-1, inverse=True)
    return _crop_demodulate_adjoint(st, rows, st.ny)


def _crop_demodulate_adjoint(st, padded, rows=None):
    """grad_field, grad_doe_phase from the gradient of the zero-padded modulated field
    ``padded`` (B, rows, npx), rows = npy by default."""
    rows = st.npy if rows is None else rows
    be = st.backend
    grad_field = be.empty((st.batch, st.ny, st.nx), st.dtype)
    if st.has_phase:
        grad_phase = be.empty(st.phase_shape, st.rdtype)
    else:
        grad_phase = None
    _launch(
        st,
        "crop_demodulate_adjoint_kernel",
        (st.nx, st.ny, 1),
        padded,
        st.field,
        st.phase,
        st.params_dev,
        st.nx,
        st.ny,
        st.npx,
        rows,
        st.batch,
        int(st.has_phase),
        int(st.phase_batched),
        grad_field,
        grad_phase if grad_phase is not None else st.phase,
    )
    return grad_field, grad_phase


def _coords(values, batch, name):
    arr = np.asarray(values, dtype=np.float64)
    if arr.ndim == 1:
        arr = np.broadcast_to(arr, (batch, arr.shape[0]))
    if arr.ndim != 2 or arr.shape[0] != batch:
        raise ValueError(f"{name} must be (M,) or ({batch}, M), got shape {arr.shape}")
    if arr.shape[1] == 0:
        raise ValueError(f"{name} is empty")
    return np.ascontiguousarray(arr)


def _center_extent(xs, ys):
    cx = 0.5 * (xs.min(axis=1) + xs.max(axis=1))
    cy = 0.5 * (ys.min(axis=1) + ys.max(axis=1))
    return np.stack([cx, cy], axis=1), xs.max(axis=1) - xs.min(axis=1), ys.max(axis=1) - ys.min(axis=1)


def _window_center(center, window_center_mm, batch):
    """The output window centre (B, 2): the nodes' own, or ``window_center_mm`` (spatial tiles of a
    sensor patch keep the whole patch's centre, hence its band limits and its result)."""
    if window_center_mm is None:
        return center
    return _per_batch(window_center_mm, batch, "window_center_mm", (2,))


def sensor_window_center(pixel_centers_x_mm, pixel_centers_y_mm, pixel_pitch_mm, gauss_nodes=3):
    """Centre (B, 2) in mm of the output window that :func:`sensor_intensity` forms for these pixels
    (the middle of its Gauss nodes' extent); pass it as ``window_center_mm`` when evaluating a part
    of the patch so that the part equals the same pixels of the whole patch."""
    cx = np.asarray(pixel_centers_x_mm, dtype=np.float64)
    batch = cx.shape[0] if cx.ndim == 2 else 1
    _, _, xs, ys, _, _ = _sensor_nodes(pixel_centers_x_mm, pixel_centers_y_mm, pixel_pitch_mm, gauss_nodes, batch)
    return _center_extent(xs, ys)[0]


def _sensor_nodes(pixel_centers_x_mm, pixel_centers_y_mm, pixel_pitch_mm, gauss_nodes, batch):
    cx = _coords(pixel_centers_x_mm, batch, "pixel_centers_x_mm")
    cy = _coords(pixel_centers_y_mm, batch, "pixel_centers_y_mm")
    pp = np.broadcast_to(np.asarray(pixel_pitch_mm, dtype=np.float64), (2,))
    if np.any(pp <= 0):
        raise ValueError("pixel_pitch_mm must be positive")
    g = int(gauss_nodes)
    if g < 1:
        raise ValueError("gauss_nodes must be >= 1")
    t, w = gauss_legendre(g)
    xs = (cx[:, :, None] + 0.5 * pp[0] * t[None, None, :]).reshape(batch, -1)
    ys = (cy[:, :, None] + 0.5 * pp[1] * t[None, None, :]).reshape(batch, -1)
    return cx.shape[1], cy.shape[1], xs, ys, w, 0.25 * pp[0] * pp[1]


# ---------------------------------------------------------------------------------------------
# public API
# ---------------------------------------------------------------------------------------------
def propagate(
    backend,
    field,
    pitch_mm,
    origin_mm,
    wavelength_um,
    distance_mm,
    out_x_mm,
    out_y_mm,
    *,
    doe_phase=None,
    doe_scale=None,
    carrier_cpmm=None,
    pad_to=None,
    dtype=None,
):
    """Propagate a sampled field by ``distance_mm`` and evaluate it at arbitrary output points.

    Band-limited (shifted) angular spectrum method with a matrix-DFT output; see the module
    docstring for the conventions.

    Args:
        backend: a :class:`~rwwarp.backend.Backend` or a device string ("cpu", "cuda:0", ...).
        field: (B, Ny, Nx) or (Ny, Nx) complex field, numpy or device array (field units).
        pitch_mm: sample pitch (mm), scalar or (B,).
        origin_mm: (x, y) of sample (row 0, column 0) (mm), shape (2,) or (B, 2).
        wavelength_um: wavelength (um), scalar or (B,).
        distance_mm: propagation distance z (mm), scalar or (B,); negative back-propagates.
        out_x_mm: output x coordinates (mm), (Mx,) or (B, Mx), absolute, any spacing.
        out_y_mm: output y coordinates (mm), (My,) or (B, My).
        doe_phase: optional DOE phase phi0 (rad), (Ny, Nx) shared or (B, Ny, Nx); the field is
            multiplied by ``exp(1j * doe_scale[b] * phi0)`` first.
        doe_scale: (B,) or scalar multiplier of ``doe_phase``,
            ``(n(lambda)-1)/(n0-1) * lambda0/lambda`` (computed by the caller); default 1.
        carrier_cpmm: optional (2,) or (B, 2) carrier (fx0, fy0) in cycles/mm factored out of the
            field (true field = field * exp(2j pi (fx0 x + fy0 y))).
        pad_to: padded FFT size, int or (npy, npx); default the next 2-3-5-7-smooth size >= 2N.
        dtype: complex64 or complex128; default the field's complex dtype, else complex128.

    Returns:
        (B, My, Mx) complex device array: the true field U(x_n, y_m) (carrier restored), same
        field units as the input (so that ``sum |U|^2 * pitch_out^2`` is the power).
    """
    probe = get_backend(backend)
    batch = _batch_of(field)
    xs = _coords(out_x_mm, batch, "out_x_mm")
    ys = _coords(out_y_mm, batch, "out_y_mm")
    center, ex, ey = _center_extent(xs, ys)
    st = _setup(
        probe,
        field,
        pitch_mm,
        origin_mm,
        wavelength_um,
        distance_mm,
        doe_phase=doe_phase,
        doe_scale=doe_scale,
        carrier_cpmm=carrier_cpmm,
        pad_to=pad_to,
        dtype=dtype,
        out_center_mm=center,
    )
    _check_window(st, ex, ey, "propagate")
    coords = _upload_coords(st, xs, ys)
    band, _ = _band_spectrum(st)
    ext, eyf = _dft_factors(st, coords)
    out = st.backend.empty((st.batch, ys.shape[1], xs.shape[1]), st.dtype)
    return _band_to_points(st, band, ext, eyf, out)


def _batch_of(field):
    shape = tuple(getattr(field, "shape", np.shape(field)))
    return 1 if len(shape) == 2 else int(shape[0])


def propagate_adjoint(
    backend,
    grad_out,
    field,
    pitch_mm,
    origin_mm,
    wavelength_um,
    distance_mm,
    out_x_mm,
    out_y_mm,
    *,
    doe_phase=None,
    doe_scale=None,
    carrier_cpmm=None,
    pad_to=None,
    dtype=None,
):
    """Adjoint (vector-Jacobian product) of :func:`propagate`.

    Args:
        grad_out: (B, My, Mx) gradient of a real loss with respect to the output U, in the
            convention ``dL/dRe U + 1j dL/dIm U``.
        field, ...: exactly the arguments of the forward call (``field`` is needed for the DOE
            phase gradient).

    Returns:
        ``(grad_field, grad_doe_phase)``: (B, Ny, Nx) complex device array (same convention) and,
        when ``doe_phase`` was given, a real device array of the shape of ``doe_phase`` (1/rad
        units of the loss; summed over the batch for a shared phase), else None. ``grad_field`` is
        ``A^H grad_out`` for the linear map A: field -> U.
    """
    probe = get_backend(backend)
    batch = _batch_of(field)
    xs = _coords(out_x_mm, batch, "out_x_mm")
    ys = _coords(out_y_mm, batch, "out_y_mm")
    center, _, _ = _center_extent(xs, ys)
    st = _setup(
        probe,
        field,
        pitch_mm,
        origin_mm,
        wavelength_um,
        distance_mm,
        doe_phase=doe_phase,
        doe_scale=doe_scale,
        carrier_cpmm=carrier_cpmm,
        pad_to=pad_to,
        dtype=dtype,
        out_center_mm=center,
    )
    g = st.backend.to_device(grad_out, st.dtype)
    if tuple(g.shape) != (st.batch, ys.shape[1], xs.shape[1]):
        raise ValueError(f"grad_out shape {tuple(g.shape)} != {(st.batch, ys.shape[1], xs.shape[1])}")
    coords = _upload_coords(st, xs, ys)
    h = _transfer(st, 1.0 / (st.npx * st.npy))
    ex, eyf = _dft_factors(st, coords, adjoint=True)
    band_grad = st.backend.workspace("band_grad", (st.batch, st.ky_max, st.kx_max), st.dtype)
    _points_to_band(st, g, ex, eyf, band_grad)
    return _band_adjoint_to_field(st, band_grad, h)


def _grid_setup(backend, field, pitch_mm, origin_mm, wavelength_um, distance_mm, out_origin_mm, doe_phase,
                doe_scale, carrier_cpmm, pad_to, dtype):
    """Shared state of :func:`propagate_grid` and its adjoint (output window shifted by ``out_origin_mm``)."""
    probe = get_backend(backend)
    batch = _batch_of(field)
    origin = _per_batch(origin_mm, batch, "origin_mm", (2,))
    shift = (
        np.zeros((batch, 2))
        if out_origin_mm is None
        else _per_batch(out_origin_mm, batch, "out_origin_mm", (2,)) - origin
    )
    st = _setup(
        probe,
        field,
        pitch_mm,
        origin_mm,
        wavelength_um,
        distance_mm,
        doe_phase=doe_phase,
        doe_scale=doe_scale,
        carrier_cpmm=carrier_cpmm,
        pad_to=pad_to,
        dtype=dtype,
        shift_mm=shift,
    )
    return st


def propagate_grid(
    backend,
    field,
    pitch_mm,
    origin_mm,
    wavelength_um,
    distance_mm,
    *,
    out_origin_mm=None,
    doe_phase=None,
    doe_scale=None,
    carrier_cpmm=None,
    pad_to=None,
    dtype=None,
):
    """Fixed-grid band-limited ASM: the propagated field on the input's own sampling.

    Zero-pad, FFT, multiply by the (shifted) band-limited transfer function, inverse FFT, crop.
    The output has the input's shape and pitch; its sample (row j, column i) sits at
    ``out_origin_mm + (i, j) * pitch_mm`` (default: the input origin; any real shift is allowed,
    Matsushima's shifted ASM).

    Args: as :func:`propagate`, plus ``out_origin_mm``: (2,) or (B, 2) (mm) or None.

    Returns:
        (B, Ny, Nx) complex device array, with the carrier (if any) still factored out:
        the true field is ``out * exp(2j pi (fx0 x + fy0 y))``.
    """
    st = _grid_setup(backend, field, pitch_mm, origin_mm, wavelength_um, distance_mm, out_origin_mm,
                     doe_phase, doe_scale, carrier_cpmm, pad_to, dtype)
    pitch = st.params[:, _P_LPX] / st.npx
    _check_window(st, st.nx * pitch, st.ny * pitch, "propagate_grid")
    padded = _pad_fft(st, st.field, st.has_phase)
    h = _transfer(st, 1.0)
    _launch(
        st,
        "spectrum_multiply_kernel",
        (st.npx, st.npy, st.batch),
        h,
        st.params_dev,
        st.npx,
        st.npy,
        st.kx_max,
        st.ky_max,
        st.batch,
        0,
        padded,
    )
    st.backend.fft2(padded, inverse=True)
    out = st.backend.empty((st.batch, st.ny, st.nx), st.dtype)
    _launch(st, "crop_kernel", (st.nx, st.ny, st.batch), padded, st.nx, st.ny, st.npx, st.npy, st.batch, out)
    return out


def propagate_grid_adjoint(
    backend,
    grad_out,
    field,
    pitch_mm,
    origin_mm,
    wavelength_um,
    distance_mm,
    *,
    out_origin_mm=None,
    doe_phase=None,
    doe_scale=None,
    carrier_cpmm=None,
    pad_to=None,
    dtype=None,
):
    """Adjoint of :func:`propagate_grid`: ``grad_out`` (B, Ny, Nx) in the convention
    ``dL/dRe + 1j dL/dIm`` -> ``(grad_field, grad_doe_phase or None)`` (device arrays; see
    :func:`propagate_adjoint`)."""
    st = _grid_setup(backend, field, pitch_mm, origin_mm, wavelength_um, distance_mm, out_origin_mm,
                     doe_phase, doe_scale, carrier_cpmm, pad_to, dtype)
    g = st.backend.to_device(grad_out, st.dtype)
    if tuple(g.shape) != (st.batch, st.ny, st.nx):
        raise ValueError(f"grad_out shape {tuple(g.shape)} != {(st.batch, st.ny, st.nx)}")
    padded = _pad_fft(st, g, False)
    h = _transfer(st, 1.0)
    _launch(
        st,
        "spectrum_multiply_kernel",
        (st.npx, st.npy, st.batch),
        h,
        st.params_dev,
        st.npx,
        st.npy,
        st.kx_max,
        st.ky_max,
        st.batch,
        1,
        padded,
    )
    st.backend.fft2(padded, inverse=True)
    return _crop_demodulate_adjoint(st, padded)


def sensor_intensity(
    backend,
    field,
    pitch_mm,
    origin_mm,
    wavelength_um,
    distance_mm,
    pixel_centers_x_mm,
    pixel_centers_y_mm,
    pixel_pitch_mm,
    *,
    gauss_nodes=3,
    doe_phase=None,
    doe_scale=None,
    carrier_cpmm=None,
    pad_to=None,
    dtype=None,
    return_nodes=False,
    window_center_mm=None,
):
    """Power landing in each sensor pixel: ``|U|^2`` integrated over the pixel's area.

    The propagated field (:func:`propagate`) is evaluated at ``gauss_nodes`` x ``gauss_nodes``
    Gauss-Legendre nodes inside every pixel (matrix DFT) and the weighted ``|U|^2`` summed in one
    kernel: ``I[b, py, px] = (ppx ppy / 4) sum_{gy, gx} w_gy w_gx |U(x_gx, y_gy)|^2`` with nodes
    ``x_gx = x_px + ppx t_gx / 2``, ``y_gy = y_py + ppy t_gy / 2``. Box integration, exact for
    intensities that are polynomials of degree ``2 gauss_nodes - 1`` across a pixel.

    Args:
        field ... distance_mm, doe_phase, doe_scale, carrier_cpmm, pad_to, dtype: as :func:`propagate`.
        pixel_centers_x_mm: (Px,) or (B, Px) absolute x of the pixel centres (mm).
        pixel_centers_y_mm: (Py,) or (B, Py) absolute y of the pixel centres (mm).
        pixel_pitch_mm: pixel size (mm), scalar or (px, py); pixels are boxes of that size
            centred on the given centres.
        gauss_nodes: Gauss-Legendre nodes per axis inside each pixel.
        return_nodes: also return the node field (B, Py*G, Px*G) (row py*G+gy, column px*G+gx),
            which :func:`sensor_intensity_adjoint` can reuse.
        window_center_mm: optional (2,) or (B, 2) centre (mm) of the output window that sets the
            shifted band limits, instead of the middle of these pixels' nodes
            (:func:`sensor_window_center` of a whole patch: a part of it then equals those pixels
            of the whole).

    Returns:
        (B, Py, Px) real device array (field units^2 * mm^2, i.e. power per pixel), or
        ``(intensity, nodes)`` when ``return_nodes``.
    """
    probe = get_backend(backend)
    batch = _batch_of(field)
    npx_, npy_, xs, ys, w, area = _sensor_nodes(
        pixel_centers_x_mm, pixel_centers_y_mm, pixel_pitch_mm, gauss_nodes, batch
    )
    center, ex, ey = _center_extent(xs, ys)
    center = _window_center(center, window_center_mm, batch)
    st = _setup(
        probe,
        field,
        pitch_mm,
        origin_mm,
        wavelength_um,
        distance_mm,
        doe_phase=doe_phase,
        doe_scale=doe_scale,
        carrier_cpmm=carrier_cpmm,
        pad_to=pad_to,
        dtype=dtype,
        out_center_mm=center,
    )
    _check_window(st, ex, ey, "sensor_intensity")
    be = st.backend
    coords = _upload_coords(st, xs, ys)
    w_dev = be.to_device(w.astype(st.rdtype))
    band, _ = _band_spectrum(st)
    ext, eyf = _dft_factors(st, coords)
    g = len(w)
    if return_nodes:
        nodes = be.empty((st.batch, ys.shape[1], xs.shape[1]), st.dtype)
    else:
        nodes = be.workspace("nodes", (st.batch, ys.shape[1], xs.shape[1]), st.dtype)
    _band_to_points(st, band, ext, eyf, nodes)
    inten = be.empty((st.batch, npy_, npx_), st.rdtype)
    _launch(
        st, "sensor_reduce_kernel", (npx_, npy_, st.batch), nodes, w_dev, npx_, npy_, g, st.batch, area, inten
    )
    if return_nodes:
        return inten, nodes
    return inten


def _band_gradient(
    backend,
    grad_intensity,
    field,
    pitch_mm,
    origin_mm,
    wavelength_um,
    distance_mm,
    pixel_centers_x_mm,
    pixel_centers_y_mm,
    pixel_pitch_mm,
    *,
    gauss_nodes,
    doe_phase,
    doe_scale,
    carrier_cpmm,
    pad_to,
    dtype,
    nodes,
    window_center_mm,
    need_band,
):
    """The part the adjoints of :func:`sensor_intensity` share: the setup of the forward call, its node
    field (given or recomputed), and dL/dC, the gradient of the band spectrum C (workspace
    'band_grad'). Returns ``(st, band_grad, h, band)``; ``band`` (C itself) only with ``need_band``."""
    probe = get_backend(backend)
    batch = _batch_of(field)
    npx_, npy_, xs, ys, w, area = _sensor_nodes(
        pixel_centers_x_mm, pixel_centers_y_mm, pixel_pitch_mm, gauss_nodes, batch
    )
    center, _, _ = _center_extent(xs, ys)
    center = _window_center(center, window_center_mm, batch)
    st = _setup(
        probe,
        field,
        pitch_mm,
        origin_mm,
        wavelength_um,
        distance_mm,
        doe_phase=doe_phase,
        doe_scale=doe_scale,
        carrier_cpmm=carrier_cpmm,
        pad_to=pad_to,
        dtype=dtype,
        out_center_mm=center,
    )
    be = st.backend
    g = len(w)
    gi = be.to_device(grad_intensity, st.rdtype)
    if tuple(gi.shape) != (st.batch, npy_, npx_):
        raise ValueError(f"grad_intensity shape {tuple(gi.shape)} != {(st.batch, npy_, npx_)}")
    coords = _upload_coords(st, xs, ys)
    w_dev = be.to_device(w.astype(st.rdtype))
    if nodes is not None:
        nodes = be.to_device(nodes, st.dtype)
        if tuple(nodes.shape) != (st.batch, ys.shape[1], xs.shape[1]):
            raise ValueError(f"nodes shape {tuple(nodes.shape)} != {(st.batch, ys.shape[1], xs.shape[1])}")
    if need_band:  # the band spectrum C itself is needed (the distance gradient)
        band, h = _band_spectrum(st)
    else:
        band, h = None, _transfer(st, 1.0 / (st.npx * st.npy))
    if nodes is None:
        if band is None:
            band, _ = _band_spectrum(st)
        ext, eyf = _dft_factors(st, coords)
        nodes = be.workspace("nodes", (st.batch, ys.shape[1], xs.shape[1]), st.dtype)
        _band_to_points(st, band, ext, eyf, nodes)
    g_nodes = be.workspace("nodes_grad", (st.batch, ys.shape[1], xs.shape[1]), st.dtype)
    _launch(
        st,
        "sensor_reduce_adjoint_kernel",
        (xs.shape[1], ys.shape[1], st.batch),
        nodes,
        w_dev,
        gi,
        npx_,
        npy_,
        g,
        st.batch,
        area,
        g_nodes,
    )
    ex, eyf = _dft_factors(st, coords, adjoint=True)
    band_grad = be.workspace("band_grad", (st.batch, st.ky_max, st.kx_max), st.dtype)
    _points_to_band(st, g_nodes, ex, eyf, band_grad)
    return st, band_grad, h, band if need_band else None


def sensor_intensity_adjoint(
    backend,
    grad_intensity,
    field,
    pitch_mm,
    origin_mm,
    wavelength_um,
    distance_mm,
    pixel_centers_x_mm,
    pixel_centers_y_mm,
    pixel_pitch_mm,
    *,
    gauss_nodes=3,
    doe_phase=None,
    doe_scale=None,
    carrier_cpmm=None,
    pad_to=None,
    dtype=None,
    nodes=None,
    window_center_mm=None,
):
    """Gradient of a real loss through :func:`sensor_intensity`.

    Args:
        grad_intensity: (B, Py, Px) real, dL/dI for each pixel.
        field ... gauss_nodes, doe_phase, ...: the arguments of the forward call.
        nodes: the node field returned by ``sensor_intensity(..., return_nodes=True)``; recomputed
            when None.
        window_center_mm: as the forward call.

    Returns:
        ``(grad_field, grad_doe_phase or None)`` as :func:`propagate_adjoint`
        (``grad_field = dL/dRe field + 1j dL/dIm field``).
    """
    st, band_grad, h, _ = _band_gradient(
        backend, grad_intensity, field, pitch_mm, origin_mm, wavelength_um, distance_mm,
        pixel_centers_x_mm, pixel_centers_y_mm, pixel_pitch_mm, gauss_nodes=gauss_nodes, doe_phase=doe_phase,
        doe_scale=doe_scale, carrier_cpmm=carrier_cpmm, pad_to=pad_to, dtype=dtype, nodes=nodes,
        window_center_mm=window_center_mm, need_band=False)
    return _band_adjoint_to_field(st, band_grad, h)


def sensor_intensity_distance_adjoint(
    backend,
    grad_intensity,
    field,
    pitch_mm,
    origin_mm,
    wavelength_um,
    distance_mm,
    pixel_centers_x_mm,
    pixel_centers_y_mm,
    pixel_pitch_mm,
    *,
    gauss_nodes=3,
    doe_phase=None,
    doe_scale=None,
    carrier_cpmm=None,
    pad_to=None,
    dtype=None,
    nodes=None,
    need_field=True,
    window_center_mm=None,
):
    """Gradient of a real loss through :func:`sensor_intensity`, the propagation distance included.

    The distance enters through the transfer function only: ``H = exp(2 pi i z w)``,
    ``w = sqrt(1/lambda^2 - u^2 - v^2)`` (cycles/mm), so ``dH/dz = 2 pi i w H`` and
    ``dL/dz = Re sum_band conj(G) 2 pi i w C`` with ``C = H FFT(field)`` the band spectrum and ``G`` its
    gradient (the adjoint of the matrix DFT applied to the node gradient), evaluated on the device by
    ``band_distance_grad_kernel``. The global phase ``exp(2 pi i z / lambda)`` is left out of ``w``
    (intensities do not see it). The Matsushima band limits also depend on z; they are held fixed
    (their jumps have zero derivative almost everywhere), as are the sensor nodes.

    Args:
        grad_intensity ... nodes, window_center_mm: as :func:`sensor_intensity_adjoint` (``nodes``
            from ``sensor_intensity(..., return_nodes=True)``, recomputed when None).
        need_field: also form ``grad_field`` and ``grad_doe_phase`` (the transposed pruned FFT);
            False returns None for both.

    Returns:
        ``(grad_field or None, grad_doe_phase or None, grad_distance)``: the first two as
        :func:`sensor_intensity_adjoint`, ``grad_distance`` a numpy float64 (B,) array, dL/dz in
        loss units per mm (one small device-to-host copy of B x ky partial sums).
    """
    st, band_grad, h, band = _band_gradient(
        backend, grad_intensity, field, pitch_mm, origin_mm, wavelength_um, distance_mm,
        pixel_centers_x_mm, pixel_centers_y_mm, pixel_pitch_mm, gauss_nodes=gauss_nodes, doe_phase=doe_phase,
        doe_scale=doe_scale, carrier_cpmm=carrier_cpmm, pad_to=pad_to, dtype=dtype, nodes=nodes,
        window_center_mm=window_center_mm, need_band=True)
    be = st.backend
    partial = be.empty((st.batch, st.ky_max), be.phase_dtype)
    _launch(
        st,
        "band_distance_grad_kernel",
        (st.ky_max, st.batch, 1),
        band,
        band_grad,
        st.params_dev,
        st.kx_max,
        st.ky_max,
        st.batch,
        0,
        partial,
        local=(64, 1, 1),
    )
    grad_distance = np.asarray(be.to_host(partial), dtype=np.float64).sum(axis=1)
    if not need_field:
        return None, None, grad_distance
    grad_field, grad_phase = _band_adjoint_to_field(st, band_grad, h)
    return grad_field, grad_phase, grad_distance
