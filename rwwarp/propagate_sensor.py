"""Pixel-integrated sensor intensity by the band-limited angular spectrum (:mod:`rwwarp.propagate`).

:func:`sensor_intensity` evaluates ``|U|^2`` at Gauss-Legendre nodes inside each sensor pixel (the
matrix DFT of :mod:`rwwarp.propagate_stages` to those nodes) and sums them with the nodes' weights:
power per pixel. :func:`sensor_intensity_adjoint` and :func:`sensor_intensity_distance_adjoint` give the
gradients with respect to the field, the DOE phase and the propagation distance (``_band_gradient``
holds the shared backward pass). :func:`sensor_window_center` is the output-window centre a patch's
pixels form (pass it as ``window_center_mm`` for a part of the patch).
"""

from __future__ import annotations

import numpy as np

from .backend import get_backend
from .propagate_setup import (
    gauss_legendre, _batch_of, _center_extent, _check_window, _coords, _setup, _window_center,
)
from .propagate_stages import (
    _band_adjoint_to_field, _band_spectrum, _band_to_points, _dft_factors, _launch, _points_to_band,
    _transfer, _upload_coords,
)


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
