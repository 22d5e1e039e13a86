"""Free-space wave propagation: band-limited angular spectrum method, evaluated anywhere.

Method. The field (optionally times a DOE phase) is zero-padded to (npy, npx), Fourier
transformed (pyvkfft), multiplied by the angular-spectrum transfer function
``H = exp(2 pi i z sqrt(1/lambda^2 - u^2 - v^2))`` (evanescent waves dropped) inside the band limit of
Matsushima & Shimobaba (2009), in its shifted form (Matsushima 2010) when the output window is
off the input window, and brought back either

* at arbitrary output coordinates (:class:`SensorPropagator`, the sensor path): a separable
  matrix DFT ``U = Ey C Ex^T`` over the band (two tiled complex GEMM launches) to Gauss-Legendre nodes
  inside each sensor pixel, which is the exact trigonometric interpolation of the band-limited result,
  so the output pitch is free of the input pitch; or
* on the input grid, possibly shifted (:func:`propagate_grid`, a plane-to-plane step such as
  :mod:`rwwarp.wave.wave_step`): inverse FFT and crop, the classic fixed-grid method.

All device work runs in the OpenCL C kernels of ``kernels/opencl/angular_spectrum.cl`` (also built for
CUDA, see :mod:`rwwarp.wave.backend`); this module only computes per-batch parameters on the host and
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
* **Pixel values.** ``pixel_values="intensity"`` (the default of these low-level calls) integrates ``|U|^2``;
  ``"flux"`` integrates the z-flux ``S_z = Re(conj(U) dU/dz / (i k)) = Re(conj(U) U_w)``,
  ``U_w = F^-1[(k_z / k) F U]`` (the Poynting vector's z-component, obliquity included: ``cos theta |U|^2``
  for a plane wave at ``theta``), for ``U`` the scalar field itself. The ray-wave model (:class:`RayWave`,
  :func:`rwwarp.psf`) defaults to ``"flux"`` and hands in the field whose flux through the wave plane is the
  traced power (docs/propagation.md "Pixel values").
* **Carrier.** With ``carrier_cpmm = (fx0, fy0)`` the field handed in is the true field times
  ``exp(-2 pi i (fx0 x + fy0 y))``; the transfer function is evaluated at the true frequencies.
  :class:`SensorPropagator` evaluates the true field (carrier restored) at its nodes;
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

Where the code lives
--------------------
* this module: the fixed-grid calls :func:`propagate_grid`, :func:`propagate_grid_adjoint` (the wave step's
  plane-to-plane propagation), :class:`PointPropagator` (the field at any points: the ASM's registered operator),
  and re-exports
  of the others (import them from here);
* :mod:`rwwarp.wave.propagate_setup`: FFT sizes, Gauss-Legendre nodes, Matsushima's band limit
  (:func:`band_limits`), the per-batch parameter rows;
* :mod:`rwwarp.wave.propagate_stages`: the device stages (pad + FFT, transfer function on the band,
  matrix DFT to points, and their adjoints);
* :mod:`rwwarp.wave.propagate_sensor`: :class:`SensorPropagator`, pixel-integrated powers and their gradients.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .backend import get_backend
from .propagate_sensor import (
    SensorGeometry, SensorPropagator, sensor_window_center,
)
from .propagate_setup import (
    band_limits, gauss_legendre, next_fft_size, _P_LPX, _batch_of, _center_extent, _check_window, _coords,
    _per_batch, _setup, _window_center,
)
from .propagate_stages import (
    _band_adjoint_to_field, _band_distance_adjoint, _band_obliquity, _band_spectrum, _band_to_points,
    _crop_demodulate_adjoint, _dft_factors, _launch, _pad_fft, _points_to_band, _transfer, _upload_coords,
)

__all__ = [
    "band_limits",
    "gauss_legendre",
    "next_fft_size",
    "PointGeometry",
    "PointPropagator",
    "propagate_grid",
    "propagate_grid_adjoint",
    "SensorGeometry",
    "SensorPropagator",
    "sensor_window_center",
]


@dataclass(frozen=True)
class PointGeometry:
    """What :class:`PointPropagator` needs: the sampled field's grid (``pitch_mm``, ``origin_mm``
    (x, y) of sample (0, 0)), ``wavelength_um``, ``distance_mm``, the output points ``out_x_mm`` /
    ``out_y_mm`` ((M,) or (B, M), absolute mm), and ``doe_scale``, ``carrier_cpmm``, ``pad_to``, ``dtype``,
    ``window_center_mm`` (as :class:`SensorGeometry` documents them: a part of a larger set of points keeps the
    whole set's window centre, hence its band limits and its values)."""
    pitch_mm: object
    origin_mm: object
    wavelength_um: object
    distance_mm: object
    out_x_mm: object
    out_y_mm: object
    doe_scale: object = None
    carrier_cpmm: object = None
    pad_to: object = None
    dtype: object = None
    window_center_mm: object = None


class PointPropagator:
    """Band-limited angular spectrum of a sampled field to arbitrary output points (matrix DFT), with
    its adjoint: :meth:`forward` and :meth:`adjoint` on one :class:`PointGeometry`. The field at any points
    (lengths mm): what a wave plane handing its field to another method needs, and the ASM's operator in the
    method registry (:class:`rwwarp.wave.methods.asm.AsmOperator`)."""

    def __init__(self, backend, geometry: PointGeometry):
        self.backend = get_backend(backend)
        self.geometry = geometry

    def _prepare(self, field, doe_phase):
        g = self.geometry
        batch = _batch_of(field)
        xs = _coords(g.out_x_mm, batch, "out_x_mm")
        ys = _coords(g.out_y_mm, batch, "out_y_mm")
        center, ex, ey = _center_extent(xs, ys)
        center = _window_center(center, g.window_center_mm, batch)
        st = _setup(self.backend, field, g.pitch_mm, g.origin_mm, g.wavelength_um, g.distance_mm,
                    doe_phase=doe_phase, doe_scale=g.doe_scale, carrier_cpmm=g.carrier_cpmm, pad_to=g.pad_to,
                    dtype=g.dtype, out_center_mm=center)
        return st, xs, ys, ex, ey

    def forward(self, field, doe_phase=None):
        """The propagated field at the output points, (B, My, Mx) complex device array (carrier
        restored)."""
        st, xs, ys, ex, ey = self._prepare(field, doe_phase)
        _check_window(st, ex, ey, "propagate")
        coords = _upload_coords(st, xs, ys)
        band, _ = _band_spectrum(st)
        ext, eyf = _dft_factors(st, coords)
        out = st.backend.empty((st.batch, ys.shape[1], xs.shape[1]), st.dtype)
        return _band_to_points(st, band, ext, eyf, out)

    def forward_weighted(self, field, doe_phase=None, powers=(1,), minus_one=False):
        """``U_w`` at the output points, (B, My, Mx) complex device array: the field of the band spectrum
        weighted by the direction cosine ``c = lambda w = k_z / k`` of each plane wave (``w = sqrt(1/lambda^2 -
        u^2 - v^2)`` cycles/mm, lambda in the medium, mm). Since ``dH/dz = 2 pi i w H`` (the transfer function
        carries the whole ``exp(2 pi i z w)``), ``d forward / d distance_mm = (2 pi i / lambda) U_w`` at fixed
        band limits and points (:meth:`rwwarp.wave.methods.asm.AsmOperator.distance_derivative`).
        ``powers``: the powers ``p`` of ``c`` whose fields ``F^-1[c^p C]`` are formed from one band spectrum
        (0: the field itself); with more than one, a tuple of them in that order. ``minus_one``: the weights
        ``c^(p-1) (c - 1)`` instead (each ``p >= 1``; ``c - 1`` without cancellation): ``(2 pi i / lambda)`` times
        them is the distance derivative of the field with its constant phase ``exp(2 pi i z / lambda)`` removed."""
        st, xs, ys, ex, ey = self._prepare(field, doe_phase)
        _check_window(st, ex, ey, "propagate")
        coords = _upload_coords(st, xs, ys)
        band, _ = _band_spectrum(st)
        ext, eyf = _dft_factors(st, coords)
        outs = []
        for p in powers:
            wb = band if int(p) == 0 and not minus_one else _band_obliquity(
                st, band, int(p), st.backend.workspace("band_w", band.shape, st.dtype), minus_one=minus_one)
            out = st.backend.empty((st.batch, ys.shape[1], xs.shape[1]), st.dtype)
            outs.append(_band_to_points(st, wb, ext, eyf, out))
        return outs[0] if len(outs) == 1 else tuple(outs)

    def adjoint(self, grad_out, field, doe_phase=None, grad_weighted=None):
        """``(grad_field, grad_doe_phase or None)`` for a real loss's gradient ``grad_out`` at the output
        points: torch's convention, ``dL/dRe U + 1j dL/dIm U``). ``grad_weighted``: also the gradient of the
        direction-cosine-weighted field ``U_w`` (:meth:`forward_weighted`), whose adjoint ``c A^H`` adds on the
        band (pixel_values "flux")."""
        st, band_grad, h, _ = self._band_gradient(grad_out, field, doe_phase, grad_weighted, need_band=False)
        return _band_adjoint_to_field(st, band_grad, h)

    def distance_adjoint(self, grad_out, field, doe_phase=None, grad_weighted=None, need_field=True):
        """:meth:`adjoint` and the distance's gradient in one set-up: ``(grad_field or None, grad_doe_phase or None,
        grad_distance)``, ``grad_distance`` numpy float64 (B,) (loss units per mm; one small device-to-host copy).
        ``dL/dz = Re sum_band conj(G) 2 pi i (w - 1/lambda) C`` (``G`` the band's gradient, ``C`` the band spectrum,
        ``dH/dz = 2 pi i w H``) for a loss that does not see a constant phase per source (pixel powers and fluxes):
        the constant phase's term ``2 pi i / lambda`` is left out (zero for such a loss, ``1 / (1 - c)`` times the
        rest, so only its rounding would remain). The band limits and points are held fixed (they move with z in
        jumps of zero derivative almost everywhere). ``need_field=False``: only the distance's gradient."""
        st, band_grad, h, band = self._band_gradient(grad_out, field, doe_phase, grad_weighted, need_band=True)
        return _band_distance_adjoint(st, band, band_grad, h, need_field)

    def _band_gradient(self, grad_out, field, doe_phase, grad_weighted, need_band):
        """``(st, band_grad, h, band or None)``: the set-up, ``G = A^H grad_out (+ c A^H grad_weighted)`` on the band
        (workspace 'band_grad'), the adjoint's transfer function and, with ``need_band``, the band spectrum."""
        st, xs, ys, _, _ = self._prepare(field, doe_phase)
        shape = (st.batch, ys.shape[1], xs.shape[1])
        gs = [st.backend.to_device(a, st.dtype) for a in ((grad_out,) if grad_weighted is None
                                                          else (grad_out, grad_weighted))]
        for g in gs:
            if tuple(g.shape) != shape:
                raise ValueError(f"grad_out shape {tuple(g.shape)} != {shape}")
        coords = _upload_coords(st, xs, ys)
        if need_band:
            band, h = _band_spectrum(st)
        else:
            band, h = None, _transfer(st, 1.0 / (st.npx * st.npy))
        ex, eyf = _dft_factors(st, coords, adjoint=True)
        band_grad = st.backend.workspace("band_grad", (st.batch, st.ky_max, st.kx_max), st.dtype)
        _points_to_band(st, gs[0], ex, eyf, band_grad)
        if grad_weighted is not None:
            part = _points_to_band(st, gs[1], ex, eyf, st.backend.workspace("band_grad_w", band_grad.shape, st.dtype))
            _band_obliquity(st, part, 1, band_grad, accumulate=True)
        return st, band_grad, h, band


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

    Args:
        backend: a :class:`~rwwarp.wave.backend.Backend` or a device string ("cpu", "cuda:0", ...).
        field: (B, Ny, Nx) or (Ny, Nx) complex field, numpy or device array (field units).
        pitch_mm: sample pitch (mm), scalar or (B,).
        origin_mm: (x, y) of sample (row 0, column 0) (mm), shape (2,) or (B, 2).
        wavelength_um: wavelength (um), scalar or (B,).
        distance_mm: propagation distance z (mm), scalar or (B,); negative back-propagates.
        out_origin_mm: (x, y) of output sample (0, 0) (mm), (2,) or (B, 2); None: ``origin_mm``.
        doe_phase: optional DOE phase phi0 (rad), (Ny, Nx) shared or (B, Ny, Nx); the field is
            multiplied by ``exp(1j * doe_scale[b] * phi0)`` first.
        doe_scale: (B,) or scalar multiplier of ``doe_phase``,
            ``(n(lambda)-1)/(n0-1) * lambda0/lambda`` (computed by the caller); default 1.
        carrier_cpmm: optional (2,) or (B, 2) carrier (fx0, fy0) in cycles/mm factored out of the
            field (true field = field * exp(2j pi (fx0 x + fy0 y))).
        pad_to: padded FFT size, int or (npy, npx); default the next 2-3-5-7-smooth size >= 2N.
        dtype: complex64 or complex128; default the field's complex dtype, else complex128.

    Returns:
        (B, Ny, Nx) complex device array, with the carrier (if any) still factored out:
        the true field is ``out * exp(2j pi (fx0 x + fy0 y))``.
    """
    st = _grid_setup(backend, field, pitch_mm, origin_mm, wavelength_um, distance_mm, out_origin_mm,
                     doe_phase, doe_scale, carrier_cpmm, pad_to, dtype)
    pitch = st.params[:, _P_LPX] / st.npx
    _check_window(st, st.nx * pitch, st.ny * pitch, "propagate_grid")
    padded = _grid_transfer(st, st.field, st.has_phase, conjugate=0)
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
    ``dL/dRe + 1j dL/dIm`` -> ``(grad_field, grad_doe_phase or None)``: (B, Ny, Nx) complex device array
    ``A^H grad_out`` (A: field -> output, the same convention) and, when ``doe_phase`` was given, a real device
    array of its shape (loss units per rad; summed over the batch for a shared phase), else None. The other
    arguments are exactly those of the forward call."""
    st = _grid_setup(backend, field, pitch_mm, origin_mm, wavelength_um, distance_mm, out_origin_mm,
                     doe_phase, doe_scale, carrier_cpmm, pad_to, dtype)
    g = st.backend.to_device(grad_out, st.dtype)
    if tuple(g.shape) != (st.batch, st.ny, st.nx):
        raise ValueError(f"grad_out shape {tuple(g.shape)} != {(st.batch, st.ny, st.nx)}")
    padded = _grid_transfer(st, g, False, conjugate=1)
    return _crop_demodulate_adjoint(st, padded)


def _grid_transfer(st, src, has_phase: bool, conjugate: int):
    """The fixed-grid ASM's core, shared by :func:`propagate_grid` and its adjoint: zero-pad and FFT
    ``src``, multiply by the band-limited transfer function (its conjugate with ``conjugate=1``: the
    adjoint), inverse FFT. Returns the padded (B, npy, npx) array."""
    padded = _pad_fft(st, src, has_phase)
    h = _transfer(st, 1.0)
    _launch(st, "spectrum_multiply_kernel", (st.npx, st.npy, st.batch), h, st.params_dev, st.npx, st.npy,
            st.kx_max, st.ky_max, st.batch, conjugate, padded)
    st.backend.fft2(padded, inverse=True)
    return padded
