"""Direct Rayleigh-Sommerfeld ground truth: an ideal thin lens with a DOE, no FFT, no paraxial step.

System (the paper's validation case): an ideal thin lens of focal length ``f`` and a DOE, both at
``z = 0``, behind a circular or square aperture, lit by an on-axis plane wave of wavelength
``lambda`` carrying unit power through the aperture. Just after the lens + DOE the field is

    U0(p) = A * exp(-1j*k*R(p)) * exp(1j*phi(p)),   R(p) = sqrt(|p|^2 + f^2),  k = 2*pi/lambda,

a perfect spherical wave converging to ``(0, 0, f)`` (the brief's ``exp(-1j*k*(R - f))`` up to the
constant ``exp(1j*k*f)``, which no intensity sees), with ``A = 1/sqrt(aperture area)`` so that
``int |U0|^2 dA = 1``. It is propagated to the plane ``z`` (any distance, not only ``f``) with the
Rayleigh-Sommerfeld integral of the first kind, ``exp(+1j*k*r)`` outgoing waves:

    U(x') = int U0(p) h(x', p) d^2p,
    h = -(1/(2*pi)) d/dz [exp(1j*k*rho)/rho]
      = (z/(2*pi)) * exp(1j*k*rho)/rho^2 * (1/rho - 1j*k)
      = (1/(1j*lambda)) * (z/rho) * exp(1j*k*rho)/rho * (1 + 1j/(k*rho)),
    rho = sqrt(|x' - p|^2 + z^2).

This is exact for the scalar field given its values on the plane z = 0 (Goodman, "Introduction
to Fourier Optics", eq. 3-46 with the exact derivative of the Green's function; no Fresnel or
Fraunhofer step). ``|U|^2`` is the intensity per mm^2 for unit entering power.

Numerics.

* Phase. The integrand's phase ``k*(rho - R)`` is formed as one float64 quantity without
  cancellation: ``rho^2 - R^2 = |x'|^2 - 2 x'.p + (z - f)(z + f)`` (no large terms cancel), then
  ``rho - R = (rho^2 - R^2)/(rho + R)``. Its absolute error is ~1e-16 * |phase| rad.
* Aperture quadrature. The aperture is cut into cells, each integrated with an ``n x n``
  Gauss-Legendre rule (tensor rule on cells inside the aperture; on cells cut by a circular
  rim an iterated rule whose inner limits follow the rim exactly, split where the rim crosses
  the cell's edges, outer variable chosen along the rim so the limits stay analytic).
  - Pixel-map DOE (piecewise constant, discontinuous): the cells are the DOE pixels (clipped to
    the aperture), so no rule ever straddles a phase step; a pixel is subdivided when the lens
    phase changes by more than ``max_cell_phase_rad`` across it.
  - Smooth callable DOE (or none): uniform cells on which the integrand's phase changes by at
    most ``max_cell_phase_rad``, from the bound ``|grad_p k(rho - R)| + |grad phi|`` taken over the
    aperture and the sensor window (the DOE gradient given by the caller or estimated by finite
    differences on a 257 x 257 grid, times 1.25).
  The node count ``n`` is the smallest for which the Gauss-Legendre remainder for a linear phase
  over a cell, ``2^(2n+1) (n!)^4/((2n+1)((2n)!)^3) (Phi/2)^(2n)/2`` (Phi = phase change across
  the cell), is below ``quad_rtol`` (default 1e-9). The brief's rule of thumb, < 0.3 rad per
  cell with a few nodes, is the special case ``max_cell_phase_rad=0.3``; larger cells with more
  nodes reach the same error with far fewer nodes (2 pi-rad cells: 1.4 nodes/rad against 10 for
  0.3-rad cells at 1e-9), which is why 2 pi is the default. The ``tolerance`` option checks the
  result empirically by halving every cell until the PSF changes by less than ``tolerance``.
* Sensor. The pixel values (default the z-flux ``S_z = Re(conj(U) dU/dz / (i k))``, ``dU/dz`` from the
  kernel's exact z-derivative :func:`_rs_block_dz`; ``pixel_values="intensity"``: ``|U|^2``) are integrated
  over each pixel's area with ``g x g`` Gauss-Legendre nodes (box integration, fraction of the entering power
  per pixel, as ``rw.psf``). ``|U|^2`` is
  band-limited to ``2 NA/lambda``; 3 nodes per axis are exact to < 1e-9 relative for pixels
  below ``lambda/(8 NA)``.
* Summation. Sensor points x aperture nodes in blocks of ``chunk_elements`` pairs (float64
  temporaries of 2-15 MB per worker thread), each block reduced by numpy's pairwise sums (no
  BLAS, whose own threads would contend); threads (numpy releases the GIL) split the sensor
  points. Peak memory is the node arrays plus ``workers * 8 * chunk_elements * 8`` bytes
  (< 0.6 GB at the 32-thread maximum). Cost ~35 ns per (sensor node, aperture node) pair on one
  core, dominated by cos/sin; threads scale ~3x on 4 cores and ~6x on 16.

Pixel-map convention (that of ``rwwarp.doe.PixelMapProfile``): ``(pixel_map, pitch_mm)`` with
``pixel_map`` of shape (Ny, Nx) in rad, centred on the axis, row 0 at +y (top), column 0 at -x:
element ``[row, col]`` covers ``x in [(col - Nx/2) pitch, (col + 1 - Nx/2) pitch]`` and
``y in [(Ny/2 - row - 1) pitch, (Ny/2 - row) pitch]``. Outside the map the DOE phase is 0. An
object with ``kind == "pixel_map"``, ``data`` and ``pitch`` (a PixelMapProfile) is accepted as
the pair ``(data, pitch)``. Callable DOEs are ``phi(x_mm, y_mm) -> rad`` on arrays. Phases are
used as given: apply the DOE's wavelength remap (:func:`rwwarp.doe.wavelength_scale`) before calling for another wavelength.
"""

import math
import os
import warnings
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from .analytic import gauss_legendre_exp_error
from .errors import LensError, SamplingWarning

__all__ = ["ApertureQuadrature", "aperture_quadrature", "lens_phase_gradient_bound",
           "rs_thin_lens_field", "rs_thin_lens_psf"]

_TWO_PI = 2.0 * math.pi
_CIRCLE_MIN_CELLS = 16      # cells per diameter, keeps rim cells small next to the rim's curvature
_SQUARE_MIN_CELLS = 2


class ApertureQuadrature:
    """Quadrature nodes over the aperture: ``sum(weight * g(x, y)) ~ int_aperture g``.

    Attributes (1-D arrays of equal length unless noted):
        x_mm, y_mm: node positions, mm.
        weight_mm2: quadrature weights, mm^2 (they sum to the aperture area).
        phase_rad: DOE phase at each node, rad.
        area_mm2: exact aperture area, mm^2 (float).
        nodes_per_axis: Gauss-Legendre order used inside cells (int).
        cells: number of (sub)cells along x and y before clipping to the aperture (tuple).
    """

    def __init__(self, x_mm, y_mm, weight_mm2, phase_rad, area_mm2, nodes_per_axis, cells):
        self.x_mm, self.y_mm = x_mm, y_mm
        self.weight_mm2, self.phase_rad = weight_mm2, phase_rad
        self.area_mm2, self.nodes_per_axis, self.cells = area_mm2, nodes_per_axis, cells

    @property
    def size(self):
        """Number of nodes."""
        return self.x_mm.size


def _check_shape(aperture_shape):
    shape = str(aperture_shape).lower()
    if shape not in ("circle", "square"):
        raise LensError(f"aperture_shape must be 'circle' or 'square', got {aperture_shape!r}",
                        keyword="aperture_shape")
    return shape


def _parse_doe(doe_phase):
    """-> (kind, payload): ('none', None) | ('callable', fn) | ('map', (array, pitch))."""
    if doe_phase is None:
        return "none", None
    if getattr(doe_phase, "kind", None) == "pixel_map" and hasattr(doe_phase, "data"):
        doe_phase = (doe_phase.data, doe_phase.pitch)
    elif callable(doe_phase):
        return "callable", doe_phase
    try:
        pmap, pitch = doe_phase
    except (TypeError, ValueError):
        raise LensError("doe_phase must be None, a callable phi(x_mm, y_mm), or (pixel_map, pitch_mm)",
                        keyword="doe_phase") from None
    pmap = np.asarray(pmap, dtype=np.float64)
    pitch = float(pitch)
    if pmap.ndim != 2 or pmap.size == 0 or not pitch > 0 or not np.all(np.isfinite(pmap)):
        raise LensError("pixel map must be a finite 2-D array with a positive pitch", keyword="doe_phase")
    return "map", (pmap, pitch)


def lens_phase_gradient_bound(focal_mm, aperture_half_mm, wavelength_um, distance_mm,
                              x_range_mm, y_range_mm):
    """Largest |d/dp_x| and |d/dp_y| of the integrand phase k*(rho - R), rad/mm.

    Over p in the aperture's bounding square and x' in the sensor rectangle ``x_range_mm``
    (min, max) by ``y_range_mm``. Sampled on 65 x 65 pupil points against the window's extreme
    and nearest sensor coordinates (the x-derivative is monotone in x'_x), times 1.02.
    """
    k = _TWO_PI / (float(wavelength_um) * 1e-3)
    f, z, h = float(focal_mm), float(distance_mm), float(aperture_half_mm)
    p = np.linspace(-h, h, 65)

    def bound(u_range, v_range):
        pu = p[:, None, None]
        pv = p[None, :, None]
        su = np.array([u_range[0], u_range[1]])[None, None, :, None]
        sv = np.stack([np.full_like(p, v_range[0]), np.full_like(p, v_range[1]),
                       np.clip(p, v_range[0], v_range[1])], axis=-1)[None, :, None, :]
        pu4, pv4 = pu[..., None], pv[..., None]
        rho = np.sqrt((pu4 - su) ** 2 + (pv4 - sv) ** 2 + z * z)
        big_r = np.sqrt(pu4 ** 2 + pv4 ** 2 + f * f)
        return 1.02 * k * float(np.max(np.abs((pu4 - su) / rho - pu4 / big_r)))

    return bound(x_range_mm, y_range_mm), bound(y_range_mm, x_range_mm)


def _doe_gradient_estimate(fn, h, shape):
    """Finite-difference max |grad phi| per axis (rad/mm) on a 257 x 257 grid, times 1.25."""
    g = np.linspace(-h, h, 257)
    yy, xx = np.meshgrid(g, g, indexing="ij")
    phi = np.asarray(fn(xx, yy), dtype=np.float64)
    if phi.shape != xx.shape or not np.all(np.isfinite(phi)):
        raise LensError("the DOE phase callable must return finite values of its input's shape",
                        keyword="doe_phase")
    dy, dx = np.gradient(phi, g, g)
    if shape == "circle":
        inside = xx * xx + yy * yy <= h * h
        dx, dy = dx[inside], dy[inside]
    return 1.25 * float(np.max(np.abs(dx))), 1.25 * float(np.max(np.abs(dy)))


def _nodes_for(omega, quad_rtol, min_nodes, half_width_mm, smooth_scale_mm):
    """Gauss-Legendre order for a cell: the linear-phase remainder, and the amplitude 1/rho^2, 1/R^2
    whose poles lie ``smooth_scale_mm`` (min(z, f)) off the real axis (Bernstein ratio 2 scale/width)."""
    n = max(1, int(min_nodes))
    while n < 64 and gauss_legendre_exp_error(n, omega) > quad_rtol:
        n += 1
    if smooth_scale_mm is not None and half_width_mm > 0:
        conv = smooth_scale_mm / half_width_mm + math.hypot(smooth_scale_mm / half_width_mm, 1.0)
        n = max(n, math.ceil(math.log(10.0 / quad_rtol) / (2.0 * math.log(conv))))
    return min(n, 64)


def _subdivide(edges, parts):
    if parts == 1:
        return edges
    frac = np.arange(parts) / parts
    inner = (edges[:-1, None] + (edges[1:] - edges[:-1])[:, None] * frac[None, :]).ravel()
    return np.append(inner, edges[-1])


def _map_edges(h, count, pitch):
    """Pixel grid lines of a centred map of ``count`` pixels, inside (-h, h), plus -h and h."""
    origin = -0.5 * count * pitch
    j0 = math.ceil((-h - origin) / pitch)
    j1 = math.floor((h - origin) / pitch)
    lines = origin + pitch * np.arange(j0, j1 + 1)
    lines = lines[(lines > -h + 1e-12 * pitch) & (lines < h - 1e-12 * pitch)]
    return np.concatenate([[-h], lines, [h]])


_LEGGAUSS = {}


def _leggauss(n):
    if n not in _LEGGAUSS:
        _LEGGAUSS[n] = np.polynomial.legendre.leggauss(n)
    return _LEGGAUSS[n]


def _rim_cell_nodes(x0, x1, y0, y1, h, min_nodes, quad_rtol):
    """Nodes and weights for the part of the cell [x0,x1] x [y0,y1] inside the circle of radius h.

    The outer variable u runs along the rim (|du/ds| >= 1/sqrt 2), the inner limits +-sqrt(h^2 - u^2)
    are analytic on the cell except at u = +-h; the node count follows the Bernstein-ellipse rate
    rho^(-2n) with rho = r + sqrt(r^2 + 1), r = (distance to +-h)/(half width).
    """
    cx, cy = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
    swap = abs(cx) > abs(cy)
    (u0, u1, v0, v1) = (y0, y1, x0, x1) if swap else (x0, x1, y0, y1)
    u0, u1 = max(u0, -h), min(u1, h)
    if u1 <= u0:
        return None
    ratio = (h - max(abs(u0), abs(u1))) / (0.5 * (u1 - u0))
    if ratio > 0:
        conv = ratio + math.sqrt(ratio * ratio + 1.0)
        n = max(min_nodes, math.ceil(math.log(1e2 / quad_rtol) / (2.0 * math.log(conv))))
    else:
        n = 32
    t, w = _leggauss(min(n, 32))
    cuts = [u0, u1]
    for v in (v0, v1):
        if abs(v) < h:
            s = math.sqrt(h * h - v * v)
            cuts += [c for c in (-s, s) if u0 < c < u1]
    cuts = np.unique(cuts)
    us, vs, ws = [], [], []
    for ua, ub in zip(cuts[:-1], cuts[1:]):
        if ub - ua <= 1e-15 * h:
            continue
        um = 0.5 * (ua + ub)
        # no crossing inside the piece: test two interior points (one may be a point of tangency)
        s1, s2 = (math.sqrt(max(h * h - q * q, 0.0)) for q in (ua + (ub - ua) / 3, ub - (ub - ua) / 3))
        if max(v0, -s1) >= min(v1, s1) and max(v0, -s2) >= min(v1, s2):
            continue
        lo_rim, hi_rim = (-s1 > v0) or (-s2 > v0), (s1 < v1) or (s2 < v1)
        half_u = 0.5 * (ub - ua)
        uu = um + half_u * t
        su = np.sqrt(np.maximum(h * h - uu * uu, 0.0))
        lo = -su if lo_rim else np.full_like(uu, v0)
        hi = su if hi_rim else np.full_like(uu, v1)
        half_v = 0.5 * (hi - lo)
        vv = (0.5 * (hi + lo))[:, None] + half_v[:, None] * t[None, :]
        ww = (half_u * w)[:, None] * half_v[:, None] * w[None, :]
        us.append(np.broadcast_to(uu[:, None], vv.shape).ravel())
        vs.append(vv.ravel())
        ws.append(ww.ravel())
    if not us:
        return None
    u, v, wt = np.concatenate(us), np.concatenate(vs), np.concatenate(ws)
    return (v, u, wt) if swap else (u, v, wt)


def aperture_quadrature(aperture_shape, aperture_half_mm, doe_phase=None, *, gradient_rad_per_mm=(0.0, 0.0),
                        max_cell_phase_rad=_TWO_PI, quad_rtol=1e-9, aperture_cells=None, subdivide=1,
                        min_nodes=2, smooth_scale_mm=None):
    """Gauss-Legendre quadrature of the aperture, aware of DOE pixels (see the module docstring).

    Args:
        aperture_shape: 'circle' (``aperture_half_mm`` = radius) or 'square' (= half side), mm.
        aperture_half_mm: radius or half side, mm.
        doe_phase: None, callable ``phi(x_mm, y_mm)`` (rad), or ``(pixel_map, pitch_mm)``.
        gradient_rad_per_mm: (gx, gy) bound on the integrand phase gradient, rad/mm, including the
            DOE's own gradient for a callable DOE (a pixel map's phase is constant in a cell).
        max_cell_phase_rad: largest phase change across a cell per axis, rad.
        quad_rtol: target Gauss-Legendre remainder per cell (relative), sets the node count.
        aperture_cells: for None/callable DOEs, force this many cells per axis (e.g. to align
            cell edges with known discontinuities); overrides the automatic count.
        subdivide: extra subdivision factor of every cell (refinement level 2**level).
        min_nodes: smallest Gauss-Legendre order.
        smooth_scale_mm: distance of the amplitude's complex poles (min(distance, focal)), mm; raises
            the order where cells are not small against it (high NA). None: ignore.

    Returns:
        :class:`ApertureQuadrature`.
    """
    shape = _check_shape(aperture_shape)
    h = float(aperture_half_mm)
    if not h > 0:
        raise LensError(f"aperture_half_mm must be positive, got {aperture_half_mm}",
                        keyword="aperture_half_mm")
    kind, payload = _parse_doe(doe_phase)
    gx, gy = (float(g) for g in gradient_rad_per_mm)
    phi_max = float(max_cell_phase_rad)
    min_cells = _CIRCLE_MIN_CELLS if shape == "circle" else _SQUARE_MIN_CELLS

    if kind == "map":
        pmap, pitch = payload
        ny, nx = pmap.shape
        base_x, base_y = _map_edges(h, nx, pitch), _map_edges(h, ny, pitch)
        widest_x, widest_y = np.max(np.diff(base_x)), np.max(np.diff(base_y))
        mx = max(1, math.ceil(widest_x * gx / phi_max), math.ceil(widest_x * min_cells / (2 * h) - 1e-9))
        my = max(1, math.ceil(widest_y * gy / phi_max), math.ceil(widest_y * min_cells / (2 * h) - 1e-9))
        edges_x = _subdivide(base_x, mx * int(subdivide))
        edges_y = _subdivide(base_y, my * int(subdivide))
    else:
        if aperture_cells is not None:
            ncx = ncy = int(aperture_cells)
        else:
            ncx = max(min_cells, math.ceil(2 * h * gx / phi_max))
            ncy = max(min_cells, math.ceil(2 * h * gy / phi_max))
        edges_x = np.linspace(-h, h, ncx * int(subdivide) + 1)
        edges_y = np.linspace(-h, h, ncy * int(subdivide) + 1)

    wx_cell, wy_cell = np.max(np.diff(edges_x)), np.max(np.diff(edges_y))
    omega = 0.5 * max(wx_cell * gx, wy_cell * gy)
    nq = _nodes_for(omega, quad_rtol, min_nodes, 0.5 * max(wx_cell, wy_cell), smooth_scale_mm)
    t, w = _leggauss(nq)

    def axis_nodes(edges):
        mid, half = 0.5 * (edges[:-1] + edges[1:]), 0.5 * (edges[1:] - edges[:-1])
        return mid[:, None] + half[:, None] * t[None, :], half[:, None] * w[None, :]

    xn, xw = axis_nodes(edges_x)            # (ncx, nq)
    yn, yw = axis_nodes(edges_y)            # (ncy, nq)
    ncx, ncy = xn.shape[0], yn.shape[0]

    if kind == "map":
        pmap, pitch = payload
        ny, nx = pmap.shape
        cxm = 0.5 * (edges_x[:-1] + edges_x[1:])
        cym = 0.5 * (edges_y[:-1] + edges_y[1:])
        jx = np.floor((cxm + 0.5 * nx * pitch) / pitch).astype(np.int64)
        iy = np.floor(0.5 * ny - cym / pitch).astype(np.int64)            # row 0 at +y
        okx, oky = (jx >= 0) & (jx < nx), (iy >= 0) & (iy < ny)
        cell_phase = np.zeros((ncy, ncx))
        cell_phase[np.ix_(oky, okx)] = pmap[np.ix_(iy[oky], jx[okx])]
    else:
        cell_phase = None

    if shape == "square":
        inside = np.ones((ncy, ncx), dtype=bool)
        rim = np.zeros((ncy, ncx), dtype=bool)
        area = 4.0 * h * h
    else:
        ax2 = np.maximum(edges_x[:-1] ** 2, edges_x[1:] ** 2)
        ay2 = np.maximum(edges_y[:-1] ** 2, edges_y[1:] ** 2)
        bx2 = np.where(edges_x[:-1] * edges_x[1:] <= 0, 0.0, np.minimum(edges_x[:-1] ** 2, edges_x[1:] ** 2))
        by2 = np.where(edges_y[:-1] * edges_y[1:] <= 0, 0.0, np.minimum(edges_y[:-1] ** 2, edges_y[1:] ** 2))
        inside = ay2[:, None] + ax2[None, :] <= h * h
        outside = by2[:, None] + bx2[None, :] >= h * h
        rim = ~inside & ~outside
        area = math.pi * h * h

    iy_in, ix_in = np.nonzero(inside)
    xs = np.broadcast_to(xn[ix_in][:, None, :], (ix_in.size, nq, nq)).ravel()
    ys = np.broadcast_to(yn[iy_in][:, :, None], (iy_in.size, nq, nq)).ravel()
    ws = (yw[iy_in][:, :, None] * xw[ix_in][:, None, :]).ravel()
    parts_x, parts_y, parts_w, parts_phase = [xs], [ys], [ws], []
    if cell_phase is not None:
        parts_phase.append(np.repeat(cell_phase[iy_in, ix_in], nq * nq))

    if np.any(rim):
        for iy, ix in zip(*np.nonzero(rim)):
            got = _rim_cell_nodes(edges_x[ix], edges_x[ix + 1], edges_y[iy], edges_y[iy + 1], h, nq,
                                  quad_rtol)
            if got is None:
                continue
            parts_x.append(got[0])
            parts_y.append(got[1])
            parts_w.append(got[2])
            if cell_phase is not None:
                parts_phase.append(np.full(got[0].size, cell_phase[iy, ix]))

    x_all = np.concatenate(parts_x)
    y_all = np.concatenate(parts_y)
    w_all = np.concatenate(parts_w)
    if kind == "map":
        phase = np.concatenate(parts_phase)
    elif kind == "callable":
        phase = np.asarray(payload(x_all, y_all), dtype=np.float64)
        if phase.shape != x_all.shape or not np.all(np.isfinite(phase)):
            raise LensError("the DOE phase callable must return finite values of its input's shape",
                            keyword="doe_phase")
    else:
        phase = np.zeros_like(x_all)
    return ApertureQuadrature(x_all, y_all, w_all, phase, area, nq, (ncx, ncy))


def _rs_block(xs, ys, cs, m2px, m2py, r2, r, amp, doe, k):
    """sum_p B(x', p) C_p for a block of sensor points, (Ns_block,) complex, without the factor z/(2 pi).

    B = (1/rho - jk)/rho^2 exp(jk(rho - R)), C_p = amp_p exp(j phi_p), amp_p = A w_p > 0. No BLAS
    (its own threads would contend with the worker threads); numpy's pairwise sums.
    """
    d2 = np.multiply.outer(xs, m2px)                   # rho^2 - R^2 = |x'|^2 + z^2 - f^2 - 2 x'.p
    tmp = np.multiply.outer(ys, m2py)
    d2 += tmp
    d2 += cs[:, None]
    rho = np.add(d2, r2, out=tmp)                      # rho^2
    np.sqrt(rho, out=rho)
    phase = np.add(rho, r)
    np.divide(d2, phase, out=phase)                    # rho - R, no cancellation
    phase *= k
    phase += doe
    cos = np.cos(phase, out=d2)
    sin = np.sin(phase, out=phase)
    inv = np.divide(1.0, rho, out=rho)
    scale = inv * inv
    scale *= amp
    b_re = cos * inv
    b_im = sin * inv
    sin *= k
    cos *= k
    b_re += sin
    b_im -= cos
    b_re *= scale
    b_im *= scale
    return b_re.sum(axis=1) + 1j * b_im.sum(axis=1)


def _rs_block_dz(xs, ys, cs, m2px, m2py, r2, r, amp, doe, k, z):
    """sum_p dB/dz(x', p) C_p for a block of sensor points (the z-derivative of the kernel, factor 1/(2 pi) left
    out): with h = (z / (2 pi)) g(rho), g = exp(jk rho) (1/rho^3 - jk/rho^2) and d rho/dz = z / rho,
    dh/dz = (1/(2 pi)) exp(jk rho) [1/rho^3 - jk/rho^2 + (z^2/rho) (k^2/rho^2 + 3jk/rho^3 - 3/rho^4)]
    (the reference phase exp(-jkR) does not depend on the sensor plane)."""
    d2 = np.multiply.outer(xs, m2px) + np.multiply.outer(ys, m2py) + cs[:, None]
    rho = np.sqrt(d2 + r2)
    phase = k * d2 / (rho + r) + doe
    inv = 1.0 / rho
    inv2 = inv * inv
    t = inv * inv2 - 1j * k * inv2 + (z * z) * inv * (k * k * inv2 + 3j * k * inv * inv2 - 3.0 * inv2 * inv2)
    t *= np.cos(phase) + 1j * np.sin(phase)
    t *= amp
    return t.sum(axis=1)


def _rs_sum(xs, ys, quad, amplitude, focal_mm, distance_mm, k, workers, chunk_elements, dz=False):
    """The Rayleigh-Sommerfeld field at the sensor points (or, with ``dz``, its derivative with respect to the
    sensor plane's distance, 1/mm units more)."""
    f, z = float(focal_mm), float(distance_mm)
    px, py = quad.x_mm, quad.y_mm
    r2 = px * px + py * py + f * f
    r = np.sqrt(r2)
    amp = amplitude * quad.weight_mm2
    xs = np.ascontiguousarray(xs, dtype=np.float64).ravel()
    ys = np.ascontiguousarray(ys, dtype=np.float64).ravel()
    cs = xs * xs + ys * ys + (z - f) * (z + f)
    ns, na = xs.size, px.size
    if workers is None:
        workers = min(os.cpu_count() or 1, 32)
    if chunk_elements is None:
        # small blocks stay in cache; with many threads larger ones amortise the GIL hand-offs
        chunk_elements = 1 << 15 if workers <= 2 else 1 << 18
    ba = min(na, 4096)
    bs = max(1, int(chunk_elements) // ba)
    a_data = [(-2.0 * px[s], -2.0 * py[s], r2[s], r[s], amp[s], quad.phase_rad[s])
              for s in (slice(a0, min(a0 + ba, na)) for a0 in range(0, na, ba))]
    out = np.zeros(ns, dtype=np.complex128)

    def work(s0):
        s = slice(s0, min(s0 + bs, ns))
        acc = np.zeros(s.stop - s.start, dtype=np.complex128)
        for block in a_data:
            if dz:
                acc += _rs_block_dz(xs[s], ys[s], cs[s], *block, k, z)
            else:
                acc += _rs_block(xs[s], ys[s], cs[s], *block, k)
        out[s] = acc

    starts = range(0, ns, bs)
    if workers <= 1 or len(starts) == 1:
        for s0 in starts:
            work(s0)
    else:
        with ThreadPoolExecutor(max_workers=int(workers)) as pool:
            list(pool.map(work, starts))
    return out * ((1.0 if dz else z) / _TWO_PI)


def _sensor_values(u, du, k, pixel_values):
    """Pixel-value density at sensor nodes from the field ``u`` and its z-derivative ``du`` (1/mm more):
    ``|U|^2`` ("intensity") or the z-flux ``Re(conj(U) dU/dz / (i k)) = Im(conj(U) dU/dz) / k`` ("flux")."""
    if pixel_values == "flux":
        return (np.conj(u) * du).imag / k
    return u.real ** 2 + u.imag ** 2


def _setup(focal_mm, aperture_shape, aperture_half_mm, wavelength_um, distance_mm, doe_phase,
           x_range, y_range, doe_gradient_rad_per_mm):
    shape = _check_shape(aperture_shape)
    for name, value in (("focal_mm", focal_mm), ("wavelength_um", wavelength_um),
                        ("distance_mm", distance_mm), ("aperture_half_mm", aperture_half_mm)):
        if not float(value) > 0:
            raise LensError(f"{name} must be positive, got {value}", keyword=name)
    kind, payload = _parse_doe(doe_phase)
    gx, gy = lens_phase_gradient_bound(focal_mm, aperture_half_mm, wavelength_um, distance_mm,
                                       x_range, y_range)
    if kind == "callable":
        if doe_gradient_rad_per_mm is None:
            dgx, dgy = _doe_gradient_estimate(payload, float(aperture_half_mm), shape)
        else:
            dgx, dgy = np.broadcast_to(np.asarray(doe_gradient_rad_per_mm, dtype=np.float64), (2,))
        gx, gy = gx + float(dgx), gy + float(dgy)
    return shape, (gx, gy)


def rs_thin_lens_field(focal_mm, aperture_shape, aperture_half_mm, wavelength_um, distance_mm, x_mm, y_mm,
                       doe_phase=None, *, doe_gradient_rad_per_mm=None, max_cell_phase_rad=_TWO_PI,
                       quad_rtol=1e-9, aperture_cells=None, subdivide=1, workers=None,
                       chunk_elements=None):
    """Complex Rayleigh-Sommerfeld field of the thin lens + DOE at arbitrary sensor points.

    Args:
        focal_mm: focal length of the ideal thin lens, mm.
        aperture_shape: 'circle' or 'square' (edges along x and y).
        aperture_half_mm: aperture radius (circle) or half side (square), mm.
        wavelength_um: wavelength, um.
        distance_mm: lens+DOE plane to sensor plane, mm (need not equal ``focal_mm``).
        x_mm, y_mm: sensor coordinates, mm (broadcast together; any shape).
        doe_phase: None, callable ``phi(x_mm, y_mm)`` in rad, or ``(pixel_map, pitch_mm)``.
        doe_gradient_rad_per_mm: bound on |d phi/dx|, |d phi/dy| of a callable DOE (scalar or pair),
            rad/mm; estimated by finite differences when None.
        max_cell_phase_rad, quad_rtol, aperture_cells, subdivide: aperture quadrature controls,
            see :func:`aperture_quadrature`.
        workers: threads (default: all CPUs, at most 32). chunk_elements: sensor x aperture pairs
            per block (default 2**15 for <= 2 threads, else 2**18: ~7 float64 temporaries of that
            size per thread, i.e. <= 15 MB each).

    Returns:
        Complex array of the broadcast shape of ``x_mm, y_mm``: the field in sqrt(1/mm^2), so that
        ``|U|^2`` is the intensity per mm^2 for unit power entering the aperture. Phase reference:
        the input wave ``A exp(-j k R)`` (the brief's U0 times the constant ``exp(-j k f)``).
    """
    x_b, y_b = np.broadcast_arrays(np.asarray(x_mm, dtype=np.float64), np.asarray(y_mm, dtype=np.float64))
    x_range = (float(np.min(x_b)), float(np.max(x_b)))
    y_range = (float(np.min(y_b)), float(np.max(y_b)))
    shape, grad = _setup(focal_mm, aperture_shape, aperture_half_mm, wavelength_um, distance_mm, doe_phase,
                         x_range, y_range, doe_gradient_rad_per_mm)
    quad = aperture_quadrature(shape, aperture_half_mm, doe_phase, gradient_rad_per_mm=grad,
                               max_cell_phase_rad=max_cell_phase_rad, quad_rtol=quad_rtol,
                               aperture_cells=aperture_cells, subdivide=subdivide,
                               smooth_scale_mm=min(float(focal_mm), float(distance_mm)))
    k = _TWO_PI / (float(wavelength_um) * 1e-3)
    field = _rs_sum(x_b, y_b, quad, 1.0 / math.sqrt(quad.area_mm2), focal_mm, distance_mm, k, workers,
                    chunk_elements)
    return field.reshape(x_b.shape)


def rs_thin_lens_psf(focal_mm, aperture_shape, aperture_half_mm, wavelength_um, distance_mm,
                     pixel_centers_x_mm, pixel_centers_y_mm, pixel_mm, doe_phase=None,
                     gauss_nodes_sensor=3, *,
                     tolerance=None, max_refinements=3, doe_gradient_rad_per_mm=None,
                     max_cell_phase_rad=_TWO_PI, quad_rtol=1e-9, aperture_cells=None, workers=None,
                     chunk_elements=None, pixel_values="flux"):
    """Pixel-integrated Rayleigh-Sommerfeld PSF of the thin lens + DOE (ground truth).

    Args:
        focal_mm: focal length of the ideal thin lens, mm.
        aperture_shape: 'circle' or 'square'.
        aperture_half_mm: aperture radius (circle) or half side (square), mm.
        wavelength_um: wavelength, um.
        distance_mm: lens+DOE plane to sensor plane, mm.
        pixel_centers_x_mm: 1-D (Px,) sensor pixel-centre x coordinates, mm.
        pixel_centers_y_mm: 1-D (Py,) sensor pixel-centre y coordinates, mm.
        pixel_mm: pixel pitch (square pixels, 100% fill), mm.
        doe_phase: None, callable ``phi(x_mm, y_mm)`` in rad, or ``(pixel_map, pitch_mm)``
            (see the module docstring for the map convention).
        gauss_nodes_sensor: Gauss-Legendre nodes per axis per pixel for the box integration.
        tolerance: if given, halve every aperture cell (up to ``max_refinements`` times) until the
            relative L2 change of the PSF is below ``tolerance``; a SamplingWarning is issued if it
            never is.
        doe_gradient_rad_per_mm, max_cell_phase_rad, quad_rtol, aperture_cells, workers,
        chunk_elements: see :func:`rs_thin_lens_field`.
        pixel_values: ``"flux"`` (default) integrates the z-flux ``Im(conj(U) dU/dz) / k`` of the field whose
            z-flux through the lens plane is the entering irradiance ``1 / area``: the spherical wave's amplitude
            divided by ``sqrt(cos theta) = sqrt(f / R)`` (its direction cosine toward the focus; a DOE's own
            deflection is left out of it, second order in the DOE's angle), ``dU/dz`` by the kernel's exact
            z-derivative. ``"intensity"``: ``|U|^2`` of :func:`rs_thin_lens_field` (the convention before
            issue 27).

    Returns:
        Array (Py, Px): fraction of the power entering the aperture that lands in each pixel.
        With ``tolerance``: ``(psf, error_estimate)``, the estimate being the relative L2 change at
        the last refinement (an upper estimate of the coarser result's error; the returned PSF
        is the finer one).
    """
    cx = np.asarray(pixel_centers_x_mm, dtype=np.float64).ravel()
    cy = np.asarray(pixel_centers_y_mm, dtype=np.float64).ravel()
    half = 0.5 * float(pixel_mm)
    g = int(gauss_nodes_sensor)
    t, w = np.polynomial.legendre.leggauss(g)
    xn = (cx[:, None] + half * t[None, :]).ravel()           # (Px*g,)
    yn = (cy[:, None] + half * t[None, :]).ravel()           # (Py*g,)
    x_range = (float(xn.min()), float(xn.max()))
    y_range = (float(yn.min()), float(yn.max()))
    shape, grad = _setup(focal_mm, aperture_shape, aperture_half_mm, wavelength_um, distance_mm, doe_phase,
                         x_range, y_range, doe_gradient_rad_per_mm)
    k = _TWO_PI / (float(wavelength_um) * 1e-3)
    xx = np.broadcast_to(xn[None, :], (yn.size, xn.size))
    yy = np.broadcast_to(yn[:, None], (yn.size, xn.size))
    wpix = (half * w)[:, None] * (half * w)[None, :]          # (g_y, g_x), mm^2
    if pixel_values not in ("flux", "intensity"):
        raise ValueError(f"rs_thin_lens_psf: pixel_values must be 'flux' or 'intensity', got {pixel_values!r}")

    def psf_at(level):
        quad = aperture_quadrature(shape, aperture_half_mm, doe_phase, gradient_rad_per_mm=grad,
                                   max_cell_phase_rad=max_cell_phase_rad, quad_rtol=quad_rtol,
                                   aperture_cells=aperture_cells, subdivide=2 ** level,
                                   smooth_scale_mm=min(float(focal_mm), float(distance_mm)))
        amp = 1.0 / math.sqrt(quad.area_mm2)
        du = None
        if pixel_values == "flux":   # 1 / sqrt(cos theta), cos theta = f / R toward the focus
            f = float(focal_mm)
            amp = amp * np.sqrt(np.sqrt(quad.x_mm ** 2 + quad.y_mm ** 2 + f * f) / f)
            du = _rs_sum(xx, yy, quad, amp, focal_mm, distance_mm, k, workers, chunk_elements, dz=True)
        field = _rs_sum(xx, yy, quad, amp, focal_mm, distance_mm, k, workers, chunk_elements)
        inten = _sensor_values(field, du, k, pixel_values).reshape(cy.size, g, cx.size, g)
        return np.einsum("iajb,ab->ij", inten, wpix)

    psf = psf_at(0)
    if tolerance is None:
        return psf
    err = math.inf
    for level in range(1, int(max_refinements) + 1):
        finer = psf_at(level)
        err = float(np.linalg.norm(finer - psf) / np.linalg.norm(finer))
        psf = finer
        if err < tolerance:
            return psf, err
    warnings.warn(f"rs_thin_lens_psf: aperture quadrature not converged to {tolerance:g} after "
                  f"{max_refinements} refinements (last change {err:.2e}); raise max_refinements or "
                  f"lower max_cell_phase_rad", SamplingWarning, stacklevel=2)
    return psf, err


# ---------------------------------------------------------------------------------------------- real lenses
class _Nodes:
    """Quadrature nodes on the wave plane in the form :func:`_rs_sum` takes."""

    def __init__(self, x, y, w, phase):
        self.x_mm, self.y_mm, self.weight_mm2, self.phase_rad = x, y, w, phase


def rs_lens_psf(lens, field_deg, wavelength_um, center_mm, size, pixel_mm, *, radial_nodes=64, angular_nodes=256,
                pixel_nodes=10, fd_step=1e-5, workers=None, include_doe=False, pixel_values="flux"):
    """Independent scalar-diffraction PSF of a real lens: traced rays, ray-tube amplitudes, exact
    Rayleigh-Sommerfeld kernel, summed directly to the sensor pixels (no FFT, no sampled field).

    The pupil (unit disc in the tracer's normalised pupil coordinates) is integrated with a polar product
    rule: Gauss-Legendre in radius (``radial_nodes``, weight ``r dr``) times the periodic trapezoid rule in
    angle (``angular_nodes``), both spectrally accurate for the smooth integrand. Each node is traced
    by :class:`rwwarp.trace.Tracer` through the lens to its last surface (the wave-plane surface: the
    DOE or the last refracting surface) and carried straight, in numpy, to that surface's vertex plane
    (OPL included). The plane field there is ``sqrt(q / J) exp(i k OPL)``, with ``q`` the launched power
    per unit pupil area and ``J = |d(x, y)/d(u, v)|`` the ray-tube Jacobian by central differences of
    step ``fd_step`` (the ray-wave model's amplitude convention: ``|U|^2`` is power per plane area). It is
    propagated to the sensor with the first Rayleigh-Sommerfeld kernel (:func:`_rs_sum`), and ``|U|^2``
    is integrated over each pixel with ``pixel_nodes^2`` Gauss-Legendre nodes. Lenses with a DOE are not
    handled here (use :func:`rs_thin_lens_psf`), unless ``include_doe``: a DOE that is the last surface (the
    wave plane) then multiplies the plane field by ``exp(1j * modulation_phase)`` at the nodes, which is
    accurate only while that phase is smooth over the footprint (LensError when the wrapped relief or its
    quantisation puts a phase step inside it: the polar rule is spectral only for a smooth integrand).

    ``pixel_values`` (:mod:`rwwarp.wave.propagate` "Pixel values"): ``"flux"`` (default) integrates the z-flux
    ``S_z = Re(conj(U) dU/dz / (i k))`` over each pixel, ``dU/dz`` by the exact z-derivative of the same kernel;
    the plane field is then the scalar field whose z-flux through the plane is the ray-tube irradiance
    ``q / J``, ``sqrt(q / (J cos theta)) exp(i k OPL)`` (``cos theta``: the ray's direction cosine to the plane's
    normal, in the image medium; the ray-local form of the model's ``c^(-1/2)``). ``"intensity"``: ``|U|^2``
    of the field ``sqrt(q / J) exp(i k OPL)`` (the convention before issue 27).

    Returns the (size, size) fraction of the entering power per pixel, rows +y, on the patch centred
    at ``center_mm`` (sensor x, y in mm, a pixel centre).
    """
    from .trace import Tracer
    wl = float(wavelength_um)
    plane = len(lens.surfaces) - 1
    doe_s = None
    if lens.doe_index is not None:
        from .doe import is_flat_profile as _is_flat_profile
        doe_s = lens.surfaces[lens.doe_index]
        if lens.doe_index != plane or not (include_doe or _is_flat_profile(doe_s.profile)):
            raise LensError("rs_lens_psf handles refractive lenses only (a blank DOE as the last surface is a "
                            "plane; include_doe=True takes a smooth DOE there)", file=lens.source)
    tr = Tracer(lens, [wl])
    src = tr.sources([field_deg], 0)
    t, wr = np.polynomial.legendre.leggauss(int(radial_nodes))
    r = 0.5 * (t + 1.0)
    wr = 0.5 * wr * r                                  # weight r dr on [0, 1]
    th = np.arange(int(angular_nodes)) * (_TWO_PI / int(angular_nodes))
    rr, tt = np.meshgrid(r, th, indexing="ij")
    w = (wr[:, None] * np.full(th.shape, _TWO_PI / int(angular_nodes))[None, :]).ravel()
    u0, v0 = (rr * np.cos(tt)).ravel(), (rr * np.sin(tt)).ravel()
    n_img = lens.indices(wl)[plane]
    z_plane = lens.vertex_z[plane]
    h = float(fd_step)

    if pixel_values not in ("flux", "intensity"):
        raise ValueError(f"rs_lens_psf: pixel_values must be 'flux' or 'intensity', got {pixel_values!r}")
    cosines = []

    def trace(u, v):
        rays = tr._run(src, u, v, 1.0, upto=plane + 1)
        d = rays.numpy()
        p, dr, opl = d["pos"][0], d["dir"][0], d["opl"][0]
        s = (z_plane - p[:, 2]) / dr[:, 2]             # straight on to the vertex plane
        cosines.append(np.abs(dr[:, 2]) / np.linalg.norm(dr, axis=1))
        return p[:, :2] + s[:, None] * dr[:, :2], opl + n_img * s, d["valid"][0], d["weight"][0]

    xy, opl, ok, q = trace(u0, v0)
    xu1, _, ok1, _ = trace(u0 + h, v0)
    xu0, _, ok2, _ = trace(u0 - h, v0)
    xv1, _, ok3, _ = trace(u0, v0 + h)
    xv0, _, ok4, _ = trace(u0, v0 - h)
    du, dv = (xu1 - xu0) / (2 * h), (xv1 - xv0) / (2 * h)
    jac = np.abs(du[:, 0] * dv[:, 1] - du[:, 1] * dv[:, 0])
    entering = float(np.sum(w * q))
    good = ok & ok1 & ok2 & ok3 & ok4
    k = _TWO_PI * n_img / (wl * 1e-3)
    z = lens.sensor_z - z_plane
    # phase relative to the sphere about the sensor's axis point (0, 0, z) that _rs_sum removes
    big_r = np.sqrt(xy[:, 0] ** 2 + xy[:, 1] ** 2 + z * z)
    ref = opl[good] + big_r[good]
    phase = k * (ref - np.median(ref))
    if doe_s is not None and include_doe:
        phase = phase + _doe_node_phase(lens, doe_s, wl, xy[good, 0], xy[good, 1])
    amp = np.sqrt(q[good] * jac[good]) * w[good]
    if pixel_values == "flux":
        amp = amp / np.sqrt(cosines[0][good])
    nodes = _Nodes(xy[good, 0], xy[good, 1], amp, phase)
    g, gw = np.polynomial.legendre.leggauss(int(pixel_nodes))
    off = (np.arange(size) - size // 2) * pixel_mm
    cx = np.asarray(center_mm, float)[0] + off
    cy = np.asarray(center_mm, float)[1] + off
    nx = (cx[:, None] + 0.5 * pixel_mm * g[None, :]).ravel()
    ny = (cy[:, None] + 0.5 * pixel_mm * g[None, :]).ravel()
    X, Y = np.meshgrid(nx, ny, indexing="xy")
    u = _rs_sum(X.ravel(), Y.ravel(), nodes, 1.0, z, z, k, workers, None)
    du = None if pixel_values != "flux" else _rs_sum(X.ravel(), Y.ravel(), nodes, 1.0, z, z, k, workers, None, dz=True)
    inten = _sensor_values(u, du, k, pixel_values).reshape(size, pixel_nodes, size, pixel_nodes)
    ww = np.outer(gw, gw) * (0.5 * pixel_mm) ** 2
    return np.einsum("iajb,ab->ij", inten, ww) / entering


def _doe_node_phase(lens, s, wavelength_um, x, y):
    """The DOE's modulation phase (rad) at wave-plane nodes; LensError where a step of the relief (a 2 pi wrap
    seen at another wavelength than the design one, or quantisation) falls among them."""
    from pathlib import Path

    from . import doe
    prof = doe.profile_from_dict(s.profile, base=Path(lens.source).parent if lens.source else None)
    scale = float(doe.wavelength_scale(s.material, s.design_wavelength_um, wavelength_um))
    zones = np.floor(np.asarray(prof.phase(x, y, s.design_wavelength_um)) / _TWO_PI)
    if s.levels is not None or (abs(scale - 1.0) > 1e-12 and np.ptp(zones) > 0):
        raise LensError("rs_lens_psf(include_doe=True): the DOE relief has a phase step inside the footprint "
                        "at this wavelength (wrapped or quantised); the smooth quadrature cannot take it",
                        file=lens.source)
    return doe.modulation_phase(prof, x, y, s.design_wavelength_um, wavelength_um, s.material, s.levels)
