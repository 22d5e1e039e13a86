"""Device stages of the band-limited angular spectrum path (:mod:`rwwarp.wave.propagate`): the launches of
the OpenCL C kernels of ``kernels/opencl/angular_spectrum.cl``, on the state a :class:`~rwwarp.wave.propagate_setup._Setup`
holds. Nothing returns to the host.

Forward, in the order a call runs them:

* :func:`_pad_fft`: ``FFT(zero-pad(field * exp(i s phi)))`` (the DOE phase ``phi`` scaled by ``s``);
* :func:`_transfer`, :func:`_band_spectrum`: ``C = H * spectrum`` on the band only, with the transfer
  function ``H = exp(2 pi i z sqrt(1/lambda^2 - u^2 - v^2))`` (pruned 2-D FFT: rows, then band columns);
* :func:`_dft_factors`, :func:`_band_to_points`: the separable matrix DFT ``U = Ey C Ex^T`` from the band
  to arbitrary output points (two batched GEMMs, :func:`_gemm`).

Adjoint (gradients, torch's convention, see :mod:`rwwarp.wave.propagate`): :func:`_points_to_band`,
:func:`_band_adjoint_to_field`, :func:`_crop_demodulate_adjoint`.
"""

from __future__ import annotations

import numpy as np

from .propagate_setup import _H_COLS, _round_up

_SRC = "angular_spectrum.cl"
# Launch shapes: work-group of the element-wise kernels, GEMM tile (GPUs), rows per work-item (CPU GEMM).
_LOCAL = (32, 8, 1)
_GEMM_TS = 32
_CPU_GEMM_ROWS = 8


# ---------------------------------------------------------------------------------------------
# launch helpers
# ---------------------------------------------------------------------------------------------
def _launch(st, name, gsize, *args, local=_LOCAL, defines=()):
    st.backend.launch(_SRC, name, st.dtype, gsize, local, *args, defines=defines)


def _gemm(st, a, b, c, m, n, k, *, lda, ldb, ldc, sa, sb, sc, ta=0, ca=0, tb=0, cb=0):
    """c[b] = op(a[b]) @ op(b[b]) over the batch: the vendor BLAS where the backend has one
    (``Backend.vendor_gemm``: cuBLAS on CUDA), else the explicitly vectorised kernel on CPU OpenCL
    devices, the local-memory tiled one on GPUs (same arguments, see angular_spectrum.cl). GPU tiles:
    32 x 32 outputs per work-group, 2 x 2 per work-item (k-step 32) when the problem has few
    tiles, 4 x 4 per work-item (k-step 16) when it fills the device several times over
    (measured on an H100: 1.3-1.5x faster there, slower on small problems)."""
    be = st.backend
    if be.vendor_gemm:   # CUDA: cuBLAS (Backend.vendor_gemm)
        be.gemm(a, b, c, m, n, k, batch=st.batch, lda=lda, ldb=ldb, ldc=ldc, sa=sa, sb=sb, sc=sc, ta=ta, ca=ca,
                tb=tb, cb=cb)
        return
    args = (a, b, m, n, k, lda, ldb, ldc, sa, sb, sc, ta, ca, tb, cb, c)
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


def _band_obliquity(st, src, power, out, accumulate=False, minus_one=False):
    """``out = c^power src`` on the band (``+ out`` with ``accumulate``), ``c = lambda w = k_z / k`` the direction
    cosine of each plane wave (pixel_values "flux"; real, so it is its own adjoint). ``minus_one`` (``power >= 1``):
    ``c^(power-1) (c - 1) src`` instead, ``c - 1`` formed without cancellation. Returns ``out``."""
    if minus_one and int(power) < 1:
        raise ValueError(f"_band_obliquity: minus_one needs power >= 1, got {power}")
    _launch(st, "band_obliquity_kernel", (st.kx_max, st.ky_max, st.batch), src, st.params_dev, st.kx_max,
            st.ky_max, st.batch, int(power), int(bool(accumulate)), int(bool(minus_one)), out)
    return out


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


def _band_distance_adjoint(st, band, band_grad, h, need_field):
    """The distance's gradient from the band spectrum ``band`` and its gradient ``band_grad`` (one launch of
    ``band_distance_grad_kernel``, partial sums per row, one small device-to-host copy: numpy float64 (B,), loss
    units per mm), and with ``need_field`` the field's and DOE phase's gradients (:func:`_band_adjoint_to_field`).
    Returns ``(grad_field or None, grad_doe_phase or None, grad_distance)``; shared by the point and sensor
    propagators' ``distance_adjoint``."""
    be = st.backend
    partial = be.empty((st.batch, st.ky_max), be.phase_dtype)
    _launch(st, "band_distance_grad_kernel", (st.ky_max, st.batch, 1), band, band_grad, st.params_dev, st.kx_max,
            st.ky_max, st.batch, 0, partial, local=(64, 1, 1))
    grad_distance = np.asarray(be.to_host(partial), dtype=np.float64).sum(axis=1)
    if not need_field:
        return None, None, grad_distance
    grad_field, grad_phase = _band_adjoint_to_field(st, band_grad, h)
    return grad_field, grad_phase, grad_distance


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
