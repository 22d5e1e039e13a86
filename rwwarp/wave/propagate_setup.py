"""Host-side set-up of the band-limited angular spectrum path (:mod:`rwwarp.wave.propagate`).

Where each piece lives here:

* :func:`next_fft_size` (VkFFT's fast lengths) and :func:`gauss_legendre` (the pixel-integration nodes);
* :func:`band_limits`: Matsushima's band limit on one axis (2009; its shifted form, 2010, for an output
  window off the input window);
* the per-batch parameter row mirrored from ``kernels/opencl/angular_spectrum.cl`` (``_P_*``), the padded
  sizes and band extents of a call (:class:`_Setup`, :func:`_setup`), the alias check
  (:func:`_check_window`) and the coordinate helpers of the output windows.

Conventions (units, pixel centres, carrier, normalisation): :mod:`rwwarp.wave.propagate`.
"""

from __future__ import annotations

import warnings

import numpy as np

from .backend import Backend, complex_dtype, get_backend, real_dtype
from ..errors import SamplingWarning

# Per-batch parameter row, mirrored from kernels/opencl/angular_spectrum.cl (P_* macros).
_P_LAMBDA, _P_Z, _P_ZFRAC, _P_LPX, _P_LPY, _P_X0, _P_Y0, _P_XS, _P_YS = range(9)
_P_CX, _P_CY, _P_ULO, _P_UHI, _P_VLO, _P_VHI, _P_QX0, _P_QY0, _P_KXB, _P_KYB = range(9, 19)
_P_DOE_SCALE = 19
_NPAR = 20
# Columns the transfer function depends on (cache key).
_H_COLS = [c for c in range(_NPAR) if c not in (_P_X0, _P_Y0, _P_DOE_SCALE)]

_KX_ROUND = 64

#: What a sensor pixel records (:mod:`rwwarp.wave.propagate`, "Pixel values"): ``"flux"``, the power through the
#: pixel (the z-component of the Poynting vector of the scalar field, ``Re(conj(U) dU/dz / (i k))``), or
#: ``"intensity"``, ``|U|^2`` integrated over the pixel (the convention before issue 27).
PIXEL_VALUES = ("flux", "intensity")


def check_pixel_values(pixel_values, where: str) -> str:
    """``pixel_values`` if it is one of :data:`PIXEL_VALUES`, else a ValueError naming ``where``."""
    if not isinstance(pixel_values, str) or pixel_values not in PIXEL_VALUES:
        raise ValueError(f"{where}: pixel_values must be 'flux' or 'intensity', got {pixel_values!r}")
    return pixel_values


def _round_up(n, m):
    return -(-int(n) // int(m)) * int(m)


_FFT_SIZES: dict = {}   # n -> next_fft_size(n), computed once each


def next_fft_size(n: int) -> int:
    """Smallest integer >= n whose prime factors are all in {2, 3, 5, 7} (VkFFT's fast radices)."""
    n = max(int(n), 1)
    got = _FFT_SIZES.get(n)
    if got is None:
        if len(_FFT_SIZES) > 65536:   # bounded: a long run's sizes
            _FFT_SIZES.clear()
        got = _FFT_SIZES[n] = _next_fft_size(n)
    return got


def _next_fft_size(n: int) -> int:
    while True:
        m = n
        for p in (2, 3, 5, 7):
            while m % p == 0:
                m //= p
        if m == 1:
            return n
        n += 1


_LEGGAUSS: dict = {}   # order -> (nodes, weights), computed once


def gauss_legendre(order: int):
    """Gauss-Legendre nodes ``t`` and weights ``w`` on [-1, 1] (numpy float64 arrays of ``order``; new arrays
    each call, the values computed once per order)."""
    key = int(order)
    tw = _LEGGAUSS.get(key)
    if tw is None:
        tw = np.polynomial.legendre.leggauss(key)
        if len(_LEGGAUSS) < 256:
            _LEGGAUSS[key] = tw
    return tw[0].copy(), tw[1].copy()


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


def _batch_of(field):
    shape = tuple(getattr(field, "shape", np.shape(field)))
    return 1 if len(shape) == 2 else int(shape[0])
