"""Pixel-integrated sensor power by the band-limited angular spectrum (:mod:`rwwarp.wave.propagate`).

:meth:`SensorPropagator.forward` evaluates ``|U|^2`` (or the z-flux) at Gauss-Legendre nodes inside each
sensor pixel (the matrix DFT of :mod:`rwwarp.wave.propagate_stages` to those nodes) and sums them with the
nodes' weights: power per pixel. :meth:`SensorPropagator.adjoint` and :meth:`SensorPropagator.distance_adjoint`
give the gradients with respect to the field, the DOE phase and the propagation distance (its
:class:`SensorGeometry` holds the arguments the three share; ``SensorPropagator._band_gradient`` the shared
backward pass). :func:`sensor_window_center` is the output-window centre a patch's
pixels form (pass it as ``window_center_mm`` for a part of the patch).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .backend import get_backend
from .propagate_setup import (
    check_pixel_values, gauss_legendre, _batch_of, _center_extent, _check_window, _coords, _setup, _window_center,
)
from .propagate_stages import (
    _band_adjoint_to_field, _band_distance_adjoint, _band_obliquity, _band_spectrum, _band_to_points, _dft_factors, _launch,
    _points_to_band, _transfer, _upload_coords,
)


def sensor_window_center(pixel_centers_x_mm, pixel_centers_y_mm, pixel_pitch_mm, gauss_nodes=3):
    """Centre (B, 2) in mm of the output window that :class:`SensorPropagator` forms for these pixels
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


@dataclass(frozen=True)
class SensorGeometry:
    """What a band-limited sensor propagation shares between its forward pass and its adjoints: the
    sampled wave-plane field's grid, the wavelength and distance, and the sensor pixels.

    ``pitch_mm`` (scalar or (B,)), ``origin_mm`` ((2,) or (B, 2), the first sample's (x, y)),
    ``wavelength_um`` (in the medium after the plane; scalar or (B,)), ``distance_mm`` (plane to
    sensor; scalar or (B,)), ``pixel_centers_x_mm`` / ``pixel_centers_y_mm`` ((P,) or (B, P), absolute),
    ``pixel_pitch_mm`` (scalar or (px, py)), ``gauss_nodes`` (Gauss-Legendre nodes per pixel axis),
    ``doe_scale`` (per-source DOE wavelength remap, with a DOE phase), ``carrier_cpmm`` ((B, 2) tilt
    removed from the field, cycles/mm), ``pad_to`` (FFT size), ``dtype`` (complex dtype) and
    ``window_center_mm`` (the output-window centre that sets the shifted band limits; default the
    middle of these pixels' nodes), ``pixel_values`` (what a pixel records: ``"intensity"``, ``|U|^2``
    integrated over it, the default of this low-level operator, or ``"flux"``, the power through it, see
    :mod:`rwwarp.wave.propagate` "Pixel values"). Lengths in mm."""
    pitch_mm: object
    origin_mm: object
    wavelength_um: object
    distance_mm: object
    pixel_centers_x_mm: object
    pixel_centers_y_mm: object
    pixel_pitch_mm: object
    gauss_nodes: int = 3
    doe_scale: object = None
    carrier_cpmm: object = None
    pad_to: object = None
    dtype: object = None
    window_center_mm: object = None
    pixel_values: str = "intensity"

    def with_(self, **changes) -> "SensorGeometry":
        """A copy with some fields replaced (e.g. ``distance_mm``, the pixel centres of a tile)."""
        return replace(self, **changes)


class SensorPropagator:
    """Band-limited angular spectrum from a sampled wave-plane field to the power in sensor pixels,
    with its adjoints: :meth:`forward`, :meth:`adjoint` (field and DOE phase) and
    :meth:`distance_adjoint` (the distance too). Built from a backend (name or object) and a
    :class:`SensorGeometry`; the sensor nodes and their weights are formed once, the FFT plans and
    DFT factors are cached by the backend between calls.

    The field enters every call (it sets the batch and is uploaded into the padded FFT), so the
    adjoints take the forward call's field and DOE phase again, and optionally its node field."""

    def __init__(self, backend, geometry: SensorGeometry):
        self.backend = get_backend(backend)
        self.geometry = geometry
        self.flux = check_pixel_values(geometry.pixel_values, "SensorGeometry") == "flux"

    def _prepare(self, field, doe_phase):
        """The setup of one call: (setup, (npx, npy, xs, ys, weights, area), window extent)."""
        g = self.geometry
        batch = _batch_of(field)
        npx_, npy_, xs, ys, w, area = _sensor_nodes(g.pixel_centers_x_mm, g.pixel_centers_y_mm,
                                                    g.pixel_pitch_mm, g.gauss_nodes, batch)
        center, ex, ey = _center_extent(xs, ys)
        center = _window_center(center, g.window_center_mm, batch)
        st = _setup(self.backend, field, g.pitch_mm, g.origin_mm, g.wavelength_um, g.distance_mm,
                    doe_phase=doe_phase, doe_scale=g.doe_scale, carrier_cpmm=g.carrier_cpmm, pad_to=g.pad_to,
                    dtype=g.dtype, out_center_mm=center)
        return st, (npx_, npy_, xs, ys, w, area), (ex, ey)

    def forward(self, field, doe_phase=None, return_nodes=False):
        """Power landing in each sensor pixel: ``|U|^2`` (``pixel_values="intensity"``) or the z-flux
        ``Re(conj(U) U_w)`` (``"flux"``) integrated over the pixel's area.

        The propagated field (band-limited ASM, :mod:`rwwarp.wave.propagate`) is evaluated at
        ``gauss_nodes`` x ``gauss_nodes`` Gauss-Legendre nodes inside every pixel (matrix DFT; with one node, at
        the pixel centre: the field at arbitrary points) and the weighted ``|U|^2`` summed in one
        kernel: ``I[b, py, px] = (ppx ppy / 4) sum_{gy, gx} w_gy w_gx |U(x_gx, y_gy)|^2`` with nodes
        ``x_gx = x_px + ppx t_gx / 2``, ``y_gy = y_py + ppy t_gy / 2``. Box integration, exact for
        intensities that are polynomials of degree ``2 gauss_nodes - 1`` across a pixel. With ``"flux"``
        the band spectrum ``C`` and ``c C`` (``c = lambda w = k_z / k``, the direction cosine) go through two
        matrix DFTs to the same nodes, ``U`` and ``U_w``, and ``Re(conj(U) U_w)`` is summed instead.

        Args:
            field: (B, Ny, Nx) or (Ny, Nx) complex wave-plane field, numpy or device array (field units).
            doe_phase: optional DOE phase phi0 (rad), (Ny, Nx) shared or (B, Ny, Nx); the field is multiplied
                by ``exp(1j * doe_scale[b] * phi0)`` first (the rest is the :class:`SensorGeometry`; pixels
                are boxes of ``pixel_pitch_mm`` centred on the given centres).
            return_nodes: also return the node field (B, Py*G, Px*G) (row py*G+gy, column px*G+gx),
                which :meth:`adjoint` can reuse (with ``"flux"`` the pair ``(U, U_w)``).

        Returns:
            (B, Py, Px) real device array (field units^2 * mm^2, i.e. power per pixel), or
            ``(intensity, nodes)`` when ``return_nodes``.
        """
        st, (npx_, npy_, xs, ys, w, area), (ex, ey) = self._prepare(field, doe_phase)
        _check_window(st, ex, ey, "SensorPropagator.forward")
        be = st.backend
        coords = _upload_coords(st, xs, ys)
        w_dev = be.to_device(w.astype(st.rdtype))
        band, _ = _band_spectrum(st)
        ext, eyf = _dft_factors(st, coords)
        g = len(w)
        shape = (st.batch, ys.shape[1], xs.shape[1])
        new = (lambda tag: be.empty(shape, st.dtype)) if return_nodes else (lambda tag: be.workspace(tag, shape, st.dtype))
        inten = be.empty((st.batch, npy_, npx_), st.rdtype)
        if self.flux:
            nodes = self._flux_nodes(st, band, ext, eyf, new)
            u, u_w = nodes
        else:
            nodes = u = u_w = _band_to_points(st, band, ext, eyf, new("nodes"))
        _launch(st, "sensor_reduce_kernel", (npx_, npy_, st.batch), u, u_w, w_dev, npx_, npy_, g, st.batch, area, inten)
        if return_nodes:
            return inten, nodes
        return inten

    @staticmethod
    def _flux_nodes(st, band, ext, eyf, new):
        """``(U, U_w)``: the node fields of ``C`` and ``c C`` (``new(tag)`` gives the arrays)."""
        u = _band_to_points(st, band, ext, eyf, new("nodes"))
        wb = _band_obliquity(st, band, 1, st.backend.workspace("band_w", band.shape, st.dtype))
        return u, _band_to_points(st, wb, ext, eyf, new("nodes_w"))

    def _band_gradient(self, grad_intensity, field, doe_phase, nodes, need_band):
        """The part the adjoints share: the setup of the forward call, its node field (given or
        recomputed), and dL/dC, the gradient of the band spectrum C (workspace 'band_grad'). Returns
        ``(st, band_grad, h, band)``; ``band`` (C itself) only with ``need_band``.

        ``"flux"``: the pixel value is ``sum w Re(conj(U) U_w)``, so the node gradients are ``w U_w`` for
        ``U`` and ``w U`` for ``U_w`` (torch's convention), and ``dL/dC = A^H(w U_w) + c A^H(w U)`` (``A``: the
        matrix DFT; ``c`` is real)."""
        st, (npx_, npy_, xs, ys, w, area), _ = self._prepare(field, doe_phase)
        be = st.backend
        g = len(w)
        gi = be.to_device(grad_intensity, st.rdtype)
        if tuple(gi.shape) != (st.batch, npy_, npx_):
            raise ValueError(f"grad_intensity shape {tuple(gi.shape)} != {(st.batch, npy_, npx_)}")
        coords = _upload_coords(st, xs, ys)
        w_dev = be.to_device(w.astype(st.rdtype))
        shape = (st.batch, ys.shape[1], xs.shape[1])
        if nodes is not None:
            if self.flux:
                if not (isinstance(nodes, tuple) and len(nodes) == 2):
                    raise ValueError("nodes: pixel_values='flux' takes the pair (U, U_w) its forward call returned")
                nodes = tuple(be.to_device(n, st.dtype) for n in nodes)
                bad = [tuple(n.shape) for n in nodes if tuple(n.shape) != shape]
            else:
                nodes = be.to_device(nodes, st.dtype)
                bad = [tuple(nodes.shape)] if tuple(nodes.shape) != shape else []
            if bad:
                raise ValueError(f"nodes shape {bad[0]} != {shape}")
        if need_band:  # the band spectrum C itself is needed (the distance gradient)
            band, h = _band_spectrum(st)
        else:
            band, h = None, _transfer(st, 1.0 / (st.npx * st.npy))
        if nodes is None:
            if band is None:
                band, _ = _band_spectrum(st)
            ext, eyf = _dft_factors(st, coords)
            if self.flux:
                nodes = self._flux_nodes(st, band, ext, eyf, lambda tag: be.workspace(tag, shape, st.dtype))
            else:
                nodes = be.workspace("nodes", shape, st.dtype)
                _band_to_points(st, band, ext, eyf, nodes)
        ex, eyf = _dft_factors(st, coords, adjoint=True)
        band_grad = be.workspace("band_grad", (st.batch, st.ky_max, st.kx_max), st.dtype)
        grid = (xs.shape[1], ys.shape[1], st.batch)
        if self.flux:
            g_nodes = be.workspace("nodes_grad", shape, st.dtype)
            _launch(st, "sensor_reduce_adjoint_kernel", grid, nodes[1], w_dev, gi, npx_, npy_, g, st.batch,
                    0.5 * area, g_nodes)
            _points_to_band(st, g_nodes, ex, eyf, band_grad)
            _launch(st, "sensor_reduce_adjoint_kernel", grid, nodes[0], w_dev, gi, npx_, npy_, g, st.batch,
                    0.5 * area, g_nodes)
            part = _points_to_band(st, g_nodes, ex, eyf, be.workspace("band_grad_w", band_grad.shape, st.dtype))
            _band_obliquity(st, part, 1, band_grad, accumulate=True)
        else:
            g_nodes = be.workspace("nodes_grad", shape, st.dtype)
            _launch(st, "sensor_reduce_adjoint_kernel", grid, nodes, w_dev, gi, npx_, npy_, g, st.batch, area, g_nodes)
            _points_to_band(st, g_nodes, ex, eyf, band_grad)
        return st, band_grad, h, band if need_band else None

    def adjoint(self, grad_intensity, field, doe_phase=None, nodes=None):
        """Gradient of a real loss through :meth:`forward`.

        Args:
            grad_intensity: (B, Py, Px) real, dL/dI for each pixel.
            field, doe_phase: those of the forward call.
            nodes: the node field returned by ``forward(..., return_nodes=True)``; recomputed when None.

        Returns:
            ``(grad_field, grad_doe_phase or None)``: (B, Ny, Nx) complex device array
            ``dL/dRe field + 1j dL/dIm field`` and, with a DOE phase, a real device array of its shape (loss
            units per rad; summed over the batch for a shared phase).
        """
        st, band_grad, h, _ = self._band_gradient(grad_intensity, field, doe_phase, nodes, need_band=False)
        return _band_adjoint_to_field(st, band_grad, h)

    def distance_adjoint(self, grad_intensity, field, doe_phase=None, nodes=None, need_field=True):
        """Gradient of a real loss through :meth:`forward`, the propagation distance included.

        The distance enters through the transfer function only: ``H = exp(2 pi i z w)``,
        ``w = sqrt(1/lambda^2 - u^2 - v^2)`` (cycles/mm), so ``dH/dz = 2 pi i w H`` and
        ``dL/dz = Re sum_band conj(G) 2 pi i w C`` with ``C = H FFT(field)`` the band spectrum and ``G`` its
        gradient (the adjoint of the matrix DFT applied to the node gradient), evaluated on the device by
        ``band_distance_grad_kernel``. The global phase ``exp(2 pi i z / lambda)`` is left out of ``w``
        (intensities do not see it). The Matsushima band limits also depend on z; they are held fixed
        (their jumps have zero derivative almost everywhere), as are the sensor nodes.

        Args:
            grad_intensity, field, doe_phase, nodes: as :meth:`adjoint` (``nodes``
                from ``forward(..., return_nodes=True)``, recomputed when None).
            need_field: also form ``grad_field`` and ``grad_doe_phase`` (the transposed pruned FFT);
                False returns None for both.

        Returns:
            ``(grad_field or None, grad_doe_phase or None, grad_distance)``: the first two as
            :meth:`adjoint`, ``grad_distance`` a numpy float64 (B,) array, dL/dz in
            loss units per mm (one small device-to-host copy of B x ky partial sums).
        """
        st, band_grad, h, band = self._band_gradient(grad_intensity, field, doe_phase, nodes, need_band=True)
        return _band_distance_adjoint(st, band, band_grad, h, need_field)

