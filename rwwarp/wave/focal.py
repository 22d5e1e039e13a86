"""Focal propagation: the wave plane to a sensor patch with the converging reference wave handled
analytically, so the sampling follows the patch and not the converging beam.

The problem. Behind the last lens (or the DOE) the field ``U0(x)`` on the wave plane converges to
the sensor: its phase carries ``NA / lambda`` cycles/mm across a footprint of several mm, and a
grid that samples it (the band-limited angular spectrum path, :mod:`rwwarp.wave.propagate`) grows as
``(footprint NA / lambda)^2``. But only a patch of width ``W`` is asked for: the information that
reaches it is ``footprint W / (lambda z)`` samples per axis.

The method (exact for the scalar field; only sampling is approximate). Let ``w(f) =
sqrt(1/lambda'^2 - |f|^2)`` (``lambda' = lambda / n`` in the image medium, ``f`` in cycles/mm); the
angular-spectrum transfer over the distance ``z`` is ``H(f) = exp(2 pi i z w(f))``. Expand the exponent
to second order about the chief ray's frequency ``f_c``, keeping only the diagonal curvature
``Q = diag(d2w/dfx2, d2w/dfy2)`` so that it stays separable:

    H_G(f) = exp(2 pi i z [w_c + g.(f - f_c) + (f - f_c)^T Q (f - f_c) / 2]),   g = grad w(f_c) = -f_c / w_c.

Its kernel is a separable chirp centred on the chief ray's lateral walk ``-z g`` (a Fresnel kernel
about the chief ray, exact Gaussian-integral inverse transform):

    h_G(r) = C exp(2 pi i f_c.r) exp(-i pi (r + z g)^T A (r + z g)),   A = (z Q)^-1,
    |C| = sqrt(|A_xx A_yy|).

H = H_G H_R with the smooth remainder ``H_R = H / H_G`` (third and higher orders of the transfer about
the chief ray, exact). So

1. **Generalised-Fresnel step, summed directly.** ``V(p) = sum_x U0(x) h_G(p - x) dx^2`` on a sensor-side
   grid ``p`` around the patch. ``h_G`` is separable, so this is two matrix products per source. For
   ``p`` near the reference point ``T`` (patch centre), the kernel's chirp cancels the converging
   wave's (``U0 ~ R'(x) exp(+i pi (x - x_T)^T A (x - x_T))`` with ``x_T = T + z g``), leaving
   ``R'(x) exp(2 pi i x^T A (p - T))``: a smooth integrand. The sum is therefore accurate on a DOE-plane
   pitch set by the patch (``|A| |p - T|``), by the residual's own band (rays landing at ``s`` give
   ``|A| |s - T|``) and by the DOE orders that reach the patch, not by the beam's NA. The chirps are
   evaluated pointwise in float64, never sampled.
2. **Exact remainder on the sensor side.** ``V`` (the chief carrier removed) is Fourier transformed
   on a padded grid, multiplied by ``H_R(f_c + nu)`` and brought to the Gauss-Legendre nodes of the
   output pixels by a separable matrix DFT (exact trigonometric interpolation). ``H_R`` moves light
   by at most ``max |z grad(w - w_G)|`` (a few tens of um): the padding covers it.

``V`` is only band-limited to the beam's angular spread ``NA / lambda`` and compact (the focused
spot plus the patch), so both sensor-side grids are of patch size.

Pixel values (:mod:`rwwarp.wave.propagate`, "Pixel values"). The z-flux ``Re(conj(U) dU/dz / (i k))`` needs
``U_w = F^-1[c(f) F U]``, the field weighted by the direction cosine ``c(f) = lambda' w(f) = k_z / k`` in the
frequency domain. Step 2 holds the sensor-plane spectrum itself: ``B`` at the true frequencies ``f_c + nu``
(the operator is shift invariant, ``H = H_G H_R``, so weighting the output spectrum is weighting the input's),
so :meth:`FocalPropagator.forward_pair` applies ``c`` to ``B`` before a second output DFT. No approximation is
added: the weight is exact on the same periodic sensor-side grid that ``H_R`` is applied on, and being real,
smooth and non-oscillating it moves no light (its kernel spans a few wavelengths, far inside the padding that
``H_R``'s displacement needs); frequencies the remainder's band limit drops are dropped from both ``U`` and
``U_w``. The demodulation by ``f_c`` and the constant phase per source are common to both and cancel in
``conj(U) U_w``. Where a DOE's orders other
than the main one miss the patch, they are not computed (their power is reported); orders that do
reach it are summed coherently on the same grid (:func:`doe_order_coefficients`).

Units: mm, cycles/mm, radians. Arrays are numpy (CPU) or CuPy (CUDA): the array module follows the
input field.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .backend import ensure_cufft_plan_cache
from .doe_phase import wrap_zone, zone_relief_phase

#: candidate DOE orders of the focal method: -FOCAL_MAX_ORDER .. FOCAL_MAX_ORDER about the main order (the
#: planner keeps those that reach the patch)
FOCAL_MAX_ORDER = 8

__all__ = ["doe_order_coefficients", "doe_order_series", "exact_zone", "order_series_horner", "OrderTables",
           "order_tables", "batch_order_series", "FocalPropagator",
           "transfer_curvature", "pixel_power", "pixel_power_adjoint",
           "pixel_flux", "pixel_flux_adjoint", "focal_pixels", "pixel_weights", "plane_direction_cosines",
           "sensor_taper", "spectrum_to_nodes", "nodes_to_spectrum", "focal_adjoint", "focal_distance_derivative"]


def doe_order_coefficients(alpha: float, levels, orders) -> np.ndarray:
    """Fourier coefficients ``c_m`` of a DOE's transmission over its relief phase.

    The DOE multiplies the field by ``t(phi0) = exp(1j alpha q(wrap(phi0)))`` (``alpha``: the
    wavelength remap factor, ``q``: rounding to ``levels`` equal steps, or none). ``t`` is
    2 pi-periodic in ``phi0``, so ``t = sum_m c_m exp(1j m phi0)`` with

    * continuous relief: ``c_m = exp(1j pi (alpha - m)) sinc(alpha - m)``;
    * ``N = levels`` steps: ``c_m = sinc(m / N) / N * sum_k exp(1j 2 pi k (alpha - m) / N)``,

    (``sinc(x) = sin(pi x) / (pi x)``). ``sum |c_m|^2 = 1`` (Parseval). Each term ``exp(1j m phi0)`` is as
    smooth as ``phi0`` itself. Returns complex ``c_m`` for the integer array ``orders``.
    """
    m = np.asarray(orders, dtype=np.float64)
    a = float(alpha)
    if levels is None:
        return np.exp(1j * np.pi * (a - m)) * np.sinc(a - m)
    n = int(levels)
    k = np.arange(n)
    ph = np.exp(2j * np.pi * np.outer(a - m, k) / n).sum(axis=1)
    return np.sinc(m / n) / n * ph


def doe_order_series(phi0, orders, central_zones=None, xp=np):
    """A DOE's transmission as its kept diffraction orders, ``sum_m c_m exp(1j m phi0)``, per source.

    ``phi0``: the unwrapped DOE phase at the design wavelength (rad, (S, n, n), array namespace ``xp``:
    numpy, CuPy or torch, differentiable in torch); ``orders``: per source a list of ``(m, c_m)``
    (:func:`doe_order_coefficients`, as a focal plan keeps them); ``central_zones``: per source None or
    ``(k_c, alpha)``, the wrap zone the chief ray crosses, computed exactly as
    ``exp(1j alpha (phi0 - 2 pi k_c))`` where ``floor(phi0 / 2 pi) == k_c`` (the series converges slowly
    next to a zone boundary the relief touches without crossing; the zone mask is a plan decision and
    carries no gradient). Returns (S, n, n) complex."""
    out = []
    for k, ol in enumerate(orders):
        p = phi0[k]
        ints = all(float(m) == int(m) for m, _ in ol)
        if ints and len(ol) > 1:
            coef = {int(m): complex(c) for m, c in ol}
            lo, hi = min(coef), max(coef)
            acc = order_series_horner(_cis(p, xp), [coef.get(m, 0j) for m in range(lo, hi + 1)], lo, xp)
        else:
            acc = xp.zeros_like(p) * 0j
            for m, c in ol:
                acc = acc + (complex(c) * xp.exp(1j * float(m) * p) if m != 0 else complex(c) * xp.ones_like(p))
        z = None if central_zones is None else central_zones[k]
        if z is not None:
            acc = exact_zone(acc, p, z[0], float(z[1]), xp)
        out.append(acc)
    return xp.stack(out)


def order_series_horner(e, coefs, lo: int, xp=np):
    """``sum_j coefs[j] e^(lo + j)`` for ``e = exp(1j phi0)`` (an array of ``xp``): the integer orders
    ``lo .. lo + len(coefs) - 1`` of a DOE's transmission. ``coefs``: complex numbers, or arrays broadcasting
    with ``e`` (one per member of a batch, as torch_bridge's packed tiles). Horner's rule from the highest
    order down (``|e| = 1``, so the recursion is stable), times ``e^lo`` (``conj(e) = 1 / e`` for negative
    ``lo``). The one evaluation of the series: :func:`doe_order_series` (per source) and
    :func:`batch_order_series` (a packed batch, in rwwarp and torch_bridge) call it."""
    acc = xp.zeros_like(e) + coefs[-1]
    for j in range(len(coefs) - 2, -1, -1):
        acc = acc * e + coefs[j]
    if lo != 0:
        f = e if lo > 0 else xp.conj(e)
        for _ in range(abs(lo)):
            acc = acc * f
    return acc


def exact_zone(acc, phi0, zone, alpha, xp=np):
    """``acc`` (a DOE transmission, complex array of ``xp``) with its value replaced where the unwrapped phase
    ``phi0`` (rad) lies in wrap zone ``zone`` (:func:`~rwwarp.wave.doe_phase.wrap_zone`) by the exact
    continuous-relief transmission ``exp(1j alpha (phi0 - 2 pi zone))``
    (:func:`~rwwarp.wave.doe_phase.zone_relief_phase`; ``alpha`` the wavelength remap). ``zone``, ``alpha``:
    numbers, or arrays broadcasting with ``phi0`` (one per member of a batch). The zone mask is a plan
    decision and carries no gradient; the exact term is differentiable in ``phi0`` (torch). numpy: computed
    only inside the zone (a small part of the window), on a copy."""
    inside = wrap_zone(phi0, xp) == zone
    if xp is np:
        acc = acc.copy()
        if np.ndim(zone) or np.ndim(alpha):      # one per member: their values at the zone's samples
            zone, alpha = (np.broadcast_to(a, inside.shape)[inside] for a in (zone, alpha))
        acc[inside] = _cis(zone_relief_phase(phi0[inside], zone, alpha), np)
        return acc
    return xp.where(inside, xp.exp(1j * zone_relief_phase(phi0, zone, alpha)), acc)


class OrderTables(NamedTuple):
    """A batch's kept DOE orders as host tables (:func:`order_tables`), read by :func:`batch_order_series`.

    ``series``: (Ns,) int64, the members with several integer orders, summed by one Horner recursion over the
    union ``lo .. lo + J - 1`` of their orders; ``coefs``: (Ns, J, 2) float64, real and imaginary parts of each
    one's ``c_m`` (0 for an order it does not keep). ``terms``: (Nt,) int64, the others (one order, e.g. a
    wavelength remap ``m = alpha`` of a relief that does not wrap, or a blank DOE's ``(alpha, 1)``; or several
    orders not all integers), each an explicit sum; ``terms_mc``: (Nt, K, 3) float64, per order ``m``,
    ``Re c``, ``Im c`` (K the most orders of one member; padded with ``c = 0``). ``series_zones``,
    ``terms_zones``: (Ns, 2), (Nt, 2) float64, each member's chief-ray wrap zone ``(k_c, alpha)`` (``k_c =
    2^60`` where it has none: no phase reaches it), or None where no member of the part has one (no zone is
    evaluated there). ``order``: (S,) int64, the rows of ``[series, terms]`` in member order, None when they
    are already. Units: orders and ``alpha`` dimensionless, ``k_c`` in zones of 2 pi."""
    series: np.ndarray
    lo: int
    coefs: np.ndarray
    series_zones: np.ndarray | None
    terms: np.ndarray
    terms_mc: np.ndarray
    terms_zones: np.ndarray | None
    order: np.ndarray | None

    @property
    def size(self) -> int:
        """The number of members ``S``."""
        return len(self.series) + len(self.terms)


def order_tables(orders, central_zones=None) -> OrderTables:
    """The host tables (:class:`OrderTables`) of a batch's kept DOE orders, built once per batch and read by
    :func:`batch_order_series` for every phase. ``orders``: per member a list of ``(m, c_m)`` (a focal plan's
    ``focal["orders"][0]``, :func:`doe_order_coefficients`; a blank DOE as ``[(alpha, 1)]``, ``alpha`` the
    wavelength remap); ``central_zones``: None, or per member None or ``(k_c, alpha)`` (the plan's
    ``focal["central_zone"][0]``). A member is a Horner series when it keeps several orders, all integers, else
    a sum of terms (:func:`doe_order_series` makes the same split per source)."""
    orders = [list(ol) for ol in orders]
    S = len(orders)
    zs = [None] * S if central_zones is None else list(central_zones)
    if len(zs) != S:
        raise ValueError(f"order_tables: {len(zs)} central zones for {S} members' orders")
    series = [k for k, ol in enumerate(orders) if len(ol) > 1 and all(float(m) == int(m) for m, _ in ol)]
    terms = [k for k in range(S) if k not in set(series)]
    coefs, lo = np.zeros((0, 1, 2)), 0
    if series:
        cs = [{int(m): complex(c) for m, c in orders[k]} for k in series]
        lo, hi = min(min(c) for c in cs), max(max(c) for c in cs)
        coefs = np.zeros((len(series), hi - lo + 1, 2))
        for i, c in enumerate(cs):
            for m, v in c.items():
                coefs[i, m - lo] = (v.real, v.imag)
    mc = np.zeros((len(terms), max([1] + [len(orders[k]) for k in terms]), 3))
    for i, k in enumerate(terms):
        for j, (m, c) in enumerate(orders[k]):
            mc[i, j] = (float(m), complex(c).real, complex(c).imag)

    def zones(rows):
        if all(zs[k] is None for k in rows):
            return None
        return np.array([[2.0 ** 60, 0.0] if zs[k] is None else [float(zs[k][0]), float(zs[k][1])] for k in rows])
    seq = series + terms
    order = None if seq == list(range(S)) else np.argsort(seq)
    return OrderTables(np.array(series, dtype=np.int64), lo, coefs, zones(series), np.array(terms, dtype=np.int64),
                       mc, zones(terms), order)


def batch_order_series(phi0, tables: OrderTables, xp=np, put=None):
    """``sum_m c_m exp(1j m phi0)`` of each member's kept DOE orders with its chief-ray wrap zone exact, (S, n, n)
    complex: per member what :func:`doe_order_series` gives it alone, evaluated for a batch at once (the one
    implementation of the packed batches of rwwarp, :func:`rwwarp.wave.focal_packed.run_focal_members`, and
    torch_bridge, :func:`torch_bridge.packed.packed_doe_factor`). ``phi0``: the unwrapped DOE phase (rad,
    (S, n, n)) in the array namespace ``xp`` (numpy, CuPy, or torch, differentiable in ``phi0``, on any device);
    ``tables``: :func:`order_tables`. The series members share one Horner recursion in ``exp(1j phi0)``
    (:func:`order_series_horner`) over the union of their orders; the others are ``sum c exp(1j m phi0)``;
    zones by :func:`exact_zone`, one zone and remap per member, in the parts that have one. Phases by
    ``xp.exp(1j x)`` (numpy 2.4's complex exp is faster than :func:`_cis`'s cos + i sin here, 16 vs 20 ms for
    2 x 459^2, the same values). ``put(name, host)``: a host table (float64, or int64 row indices) as an array
    of ``xp`` beside ``phi0`` (default ``xp.asarray``, moved to ``phi0``'s device where the arrays have ``.to``,
    as torch's; torch_bridge passes its upload cache). Computed on ``phi0``'s device (nothing is copied to the
    host): device-generic, run here on the CPU only (numpy, torch)."""
    if put is None:
        put = _put_beside(phi0, xp)
    S = tables.size
    if phi0.shape[0] != S:
        raise ValueError(f"batch_order_series: phi0 has {phi0.shape[0]} members, the order tables {S}")
    parts = []
    for rows, name, zones in ((tables.series, "series", tables.series_zones),
                              (tables.terms, "terms", tables.terms_zones)):
        if not len(rows):
            continue
        p = phi0 if len(rows) == S else phi0[put(name, rows)]
        if name == "series":
            t = put("coefs", tables.coefs)
            c = t[..., 0] + 1j * t[..., 1]
            e = xp.exp(1j * p)
            acc = order_series_horner(e, [c[:, j, None, None] for j in range(c.shape[1])], tables.lo, xp)
        else:
            t = put("terms_mc", tables.terms_mc)
            acc = None
            for j in range(t.shape[1]):
                term = (t[:, j, 1] + 1j * t[:, j, 2])[:, None, None] * xp.exp(1j * t[:, j, 0, None, None] * p)
                acc = term if acc is None else acc + term
        if zones is not None:
            z = put(name + "_zones", zones)
            acc = exact_zone(acc, p, z[:, 0, None, None], z[:, 1, None, None], xp)
        parts.append(acc)
    out = parts[0] if len(parts) == 1 else xp.concatenate(parts, 0)
    return out if tables.order is None else out[put("order", tables.order)]


def _put_beside(phi0, xp):
    """The default ``put`` of :func:`batch_order_series`: ``xp.asarray``, moved to ``phi0``'s device where the
    namespace's arrays move with ``.to`` (torch; numpy and CuPy arrays have no ``.to``)."""
    def put(name, host):
        a = xp.asarray(host)
        return a.to(phi0.device) if hasattr(a, "to") and hasattr(phi0, "device") else a
    return put


def _cis(p, xp):
    """``exp(1j p)`` for real ``p``: on numpy as ``cos + 1j sin`` (numpy's complex exp is several times slower),
    elsewhere (CuPy, torch with autograd) ``xp.exp``."""
    if xp is np:
        return np.cos(p) + 1j * np.sin(p)
    return xp.exp(1j * p)


def plane_direction_cosines(n_fft: int, pitch_mm, carrier_cpmm, wavelength_mm) -> np.ndarray:
    """``c = k_z / k = sqrt(1 - lambda^2 |f|^2)`` (0 for evanescent ``f``) on the (S, n_fft, n_fft) FFT grids of
    wave-plane windows: true frequency ``f = fftfreq(n_fft, pitch) + carrier`` (rows y, columns x). ``pitch_mm``
    scalar or (S,), ``carrier_cpmm`` (S, 2) cycles/mm, ``wavelength_mm`` (S,) in the medium."""
    car = np.asarray(carrier_cpmm, dtype=np.float64).reshape(-1, 2)
    S = car.shape[0]
    pitch = np.broadcast_to(np.asarray(pitch_mm, dtype=np.float64), (S,))
    lam = np.broadcast_to(np.asarray(wavelength_mm, dtype=np.float64), (S,))
    out = np.empty((S, int(n_fft), int(n_fft)))
    for k in range(S):
        f = np.fft.fftfreq(int(n_fft), pitch[k])
        arg = 1.0 - lam[k] ** 2 * ((f[None, :] + car[k, 0]) ** 2 + (f[:, None] + car[k, 1]) ** 2)
        out[k] = np.sqrt(np.maximum(arg, 0.0))
    return out


def transfer_curvature(f_c, inv_lam):
    """``w_c = w(f_c)``, gradient ``g`` and diagonal second derivatives ``(Qxx, Qyy)`` of
    ``w(f) = sqrt(inv_lam^2 - |f|^2)`` at ``f_c`` ((S, 2) cycles/mm; ``inv_lam`` (S,) 1/mm)."""
    f_c = np.asarray(f_c, dtype=np.float64)
    w_c = np.sqrt(inv_lam ** 2 - np.sum(f_c ** 2, axis=1))
    g = -f_c / w_c[:, None]
    q = -(1.0 / w_c[:, None]) - f_c ** 2 / w_c[:, None] ** 3
    return w_c, g, q


def distance_factors(E, geo, z, HR, rem):
    """d/dz of a focal operator's step-1 factors ``E`` (two (S, ns, n) arrays) and of its remainder transfer
    ``HR`` at fixed grids, band mask and carrier, the geometry ``geo`` (``xs``, ``ps``, ``g``, ``A``) and
    ``rem`` (the remainder's phase over 2 pi z) of :class:`FocalPropagator` or
    :class:`rwwarp.wave.focal_packed.PackedFocalPropagator`: ``E = sqrt|A| h exp(-i pi A d^2)`` with
    ``A = 1 / (z Q)`` and ``d = p + z g - x``, so ``dE/dz = E (-1 / (2 z) + i pi (A / z) d^2 - 2 i pi A d g)``;
    ``dH_R/dz = 2 pi i (w - w_G) H_R``. Returns ``([dE_x, dE_y], dH_R)``; z in mm."""
    dE = []
    for ax in range(2):
        g = geo["g"][:, None, None, ax]
        d = geo["ps"][:, :, None, ax] + z * g - geo["xs"][:, None, :, ax]
        a = geo["A"][:, None, None, ax]
        fac = -0.5 / z + 1j * np.pi * (a / z) * d * d - 2j * np.pi * a * d * g
        dE.append(E[ax] * fac)
    return dE, HR * (2j * np.pi * rem)


def spectrum_to_nodes(b, Fx, Fy, xp=np):
    """The output DFT of a focal operator, ``U = Fy B Fx^T``: a padded sensor-side spectrum ``B`` (S, nf, nf)
    at the output nodes (S, My, Mx), ``Fx`` (S, Mx, nf) and ``Fy`` (S, My, nf) its factors."""
    return xp.matmul(Fy, xp.matmul(b, xp.swapaxes(Fx, 1, 2)))


def nodes_to_spectrum(grad, Fx, Fy, xp=np):
    """Adjoint of :func:`spectrum_to_nodes`: (S, My, Mx) -> (S, nf, nf)."""
    t = xp.matmul(xp.conj(xp.swapaxes(Fy, 1, 2)), grad)
    return xp.matmul(t, xp.conj(Fx))


def focal_adjoint(grad_u, grad_w, E, HR, c, Fx, Fy, dft_adjoint, xp=np):
    """The adjoint of a focal operator (:class:`FocalPropagator`, :class:`rwwarp.wave.focal_packed.PackedFocalPropagator`:
    the two share it), from its factors: the wave-plane field's gradient (S, n, n) from the gradients ``grad_u``
    of ``U`` and ``grad_w`` of ``U_w`` (None: the adjoint of ``forward`` alone) at the output nodes (S, My, Mx),
    torch's convention. In order: the output DFT's adjoint (:func:`nodes_to_spectrum`; ``U_w``'s weighted by the
    direction cosine ``c``), the remainder transfer's (``conj(HR)``), step 2's padded DFT's (``dft_adjoint``:
    (S, nf, nf) -> (S, ns, ns), the operator's own) and step 1's (``E = (E_x, E_y)``, (S, ns, n) each)."""
    b = nodes_to_spectrum(grad_u, Fx, Fy, xp)
    if grad_w is not None:
        b = b + nodes_to_spectrum(grad_w, Fx, Fy, xp) * c
    v = dft_adjoint(b * xp.conj(HR))
    ex, ey = E
    t = xp.matmul(xp.conj(xp.swapaxes(ey, 1, 2)), v.astype(ey.dtype, copy=False))   # (S, n, ns)
    return xp.matmul(t, xp.conj(ex)).astype(np.complex128, copy=False)              # (S, n, n)


def focal_distance_derivative(field, E, HR, c, Fx, Fy, dE, dHR, dft, pair, xp=np):
    """``dU/dz`` at the output nodes (S, My, Mx), or with ``pair`` ``(dU/dz, dU_w/dz)``: the exact distance
    derivative of a focal operator's forward (pair) from its factors (shared by :class:`FocalPropagator` and
    :class:`rwwarp.wave.focal_packed.PackedFocalPropagator`), grids, band mask and carrier held fixed:
    ``dB/dz = dft(dV/dz) HR + dft(V) dHR`` with ``V = E_y f E_x^T`` (step 1 in complex128), ``E``, ``dE`` the
    step-1 factors and their derivatives (:func:`distance_factors`), ``dft`` step 2's padded DFT
    ((S, ns, ns) -> (S, nf, nf), the operator's own); the weight ``c`` does not depend on z."""
    ex, ey = E
    dex, dey = dE
    f = field.astype(np.complex128, copy=False)
    t = xp.matmul(f, xp.swapaxes(ex.astype(np.complex128, copy=False), 1, 2))
    v = xp.matmul(ey.astype(np.complex128, copy=False), t)
    dv = xp.matmul(dey, t) + xp.matmul(ey, xp.matmul(field, xp.swapaxes(dex, 1, 2)))
    db = dft(dv) * HR + dft(v) * dHR
    if pair:
        return spectrum_to_nodes(db, Fx, Fy, xp), spectrum_to_nodes(db * c, Fx, Fy, xp)
    return spectrum_to_nodes(db, Fx, Fy, xp)


class FocalPropagator:
    """The planned focal propagation of one batch of sources (set up once, applied to many fields).

    Parameters (per source ``S``; lengths mm). The operator itself does not depend on the patch centre
    ``T``: it enters through the caller's choice of the sensor-side grid and of the wave-plane pitch, which
    are only accurate near ``T`` (see the module docstring).
    ----------
    origin_mm : (S, 2)  centre of wave-plane sample (0, 0); samples at ``origin + (i, j) * pitch_mm``.
    pitch_mm : float    wave-plane pitch.  ``n_grid``: samples per side.
    wavelength_mm : (S,) wavelength in the image medium (``lambda / n``), mm.
    distance_mm : float  wave plane to sensor.
    carrier_cpmm : (S, 2) chief frequency ``f_c`` (cycles/mm) removed from the field handed in: the
        field passed to :meth:`forward` is ``U0(x) exp(-2 pi i f_c . (x - x_ref))`` (any constant
        ``x_ref``: constants drop out of intensities).
    sensor_origin_mm : (S, 2), sensor_pitch_mm : float, n_sensor : int  the sensor-side grid of step 1.
    n_fft : int  FFT length (>= n_sensor) of step 2.
    nodes_x_mm, nodes_y_mm : (S, M)  output coordinates (e.g. Gauss nodes of the pixels).
    xp : numpy or cupy.
    transfer : None or ``(g, q)``, (S, 2) each: the quadratic part's gradient (dimensionless) and diagonal
        curvature (mm) in place of the Taylor values at ``f_c`` (any choice keeps the operator exact; a fit
        to the beam narrows the sensor-side box, :func:`rwwarp.wave.plan.fit_quadratic_transfer`).
    precision : "double" | "single"  arithmetic of step 1's matrix products (the phases of its chirp factors
        are formed in float64, the factors rounded to the working precision before their product; step 2 and
        the output are complex128). ``"single"`` halves step 1's time and memory on the CPU; against rs_lens_psf the Cooke triplet (0 / 14 deg), the AC254 and the A489 read the same
        to 3 digits (5.91e-5 / 3.91e-5 / 2.96e-5 / 2.91e-5). Gradients use ``"double"``.
    taper_guard_mm : None or float  ``V`` is kept whole within this distance of the output nodes' extent
        (the remainder's largest displacement over the beam's band plus its kernel's spread) and tapered
        smoothly (C-infinity) to zero between there and the sensor-side grid's edge. The remainder cannot
        carry what lies farther to the nodes, and a cut ``V`` would ring through the trigonometric
        interpolation of step 2 (Gibbs): a square aperture's tails, decaying as ``1 / r``, showed it.
    """

    def __init__(self, origin_mm, pitch_mm, n_grid, wavelength_mm, distance_mm, carrier_cpmm,
                 sensor_origin_mm, sensor_pitch_mm, n_sensor, n_fft, nodes_x_mm, nodes_y_mm, xp=np, transfer=None, taper_guard_mm=None,
                 precision="double"):
        self.xp = xp
        origin = np.asarray(origin_mm, dtype=np.float64)
        S = origin.shape[0]
        lam = np.broadcast_to(np.asarray(wavelength_mm, dtype=np.float64), (S,))
        z = float(distance_mm)
        if not z > 0:
            raise ValueError(f"distance_mm must be > 0 (wave plane before the sensor), got {z}")
        f_c = np.asarray(carrier_cpmm, dtype=np.float64).reshape(S, 2)
        s0 = np.asarray(sensor_origin_mm, dtype=np.float64).reshape(S, 2)
        inv_lam = 1.0 / lam
        w_c, g, q = transfer_curvature(f_c, inv_lam)
        if transfer is not None:   # a fitted quadratic (rwwarp.wave.plan.fit_quadratic_transfer): the split stays exact
            g = np.asarray(transfer[0], dtype=np.float64).reshape(S, 2)
            q = np.asarray(transfer[1], dtype=np.float64).reshape(S, 2)
            if not np.all(q < 0):
                raise ValueError("transfer: the quadratic coefficients q must be negative (a converging split)")
        A = 1.0 / (z * q)                                 # (S, 2), negative
        self.S, self.n, self.ns, self.nf = S, int(n_grid), int(n_sensor), int(n_fft)
        self.pitch, self.spitch, self.z = float(pitch_mm), float(sensor_pitch_mm), z
        h, hs = self.pitch, self.spitch
        xs = origin[:, None, :] + np.arange(self.n)[None, :, None] * h          # (S, n, 2) plane coords
        ps = s0[:, None, :] + np.arange(self.ns)[None, :, None] * hs            # (S, ns, 2) sensor grid
        # the window-sized factors are formed on the operator's device (xp), from small host vectors
        X = {k: xp.asarray(v) for k, v in (("xs", xs), ("ps", ps), ("g", g), ("A", A), ("q", q), ("w_c", w_c),
                                          ("f_c", f_c), ("inv_lam", inv_lam))}
        # step 1 factors: E[a][s, j, i] = exp(-i pi A (p_j + z g - x_i)^2) per axis (the carrier of h_G
        # and the field's removed carrier cancel up to a constant; the sensor field is demodulated by f_c)
        self._E = []
        # formed from chirps and one Toeplitz factor (no (ns, n) transcendental per entry): with u_j = u0 + j hs
        # (u0 = p_0 + z g), x_i = x0 + i h, a = pi A and b = a h hs, -a (u_j - x_i)^2 is the phase of
        # P_j Q_i K(j - i): P_j = exp(-i a u_j^2 + 2 i a x0 hs j + i b j^2 + 2 i a u0 x0),
        # Q_i = exp(-i a x_i^2 + 2 i a u0 h i + i b i^2), K(m) = exp(-i b m^2)
        if precision not in ("double", "single"):
            raise ValueError(f"precision must be 'double' or 'single', got {precision!r}")
        self.precision = precision
        cdt = np.complex64 if precision == "single" else np.complex128   # the factors are formed in it directly
        jj = np.arange(self.ns, dtype=np.float64)
        ii = np.arange(self.n, dtype=np.float64)
        mm = np.arange(-(self.n - 1), self.ns, dtype=np.float64)
        # (ns, n) Toeplitz index, formed on the operator's device (no host matrix, no copy)
        toe = xp.arange(self.ns)[:, None] - xp.arange(self.n)[None, :] + (self.n - 1)
        for ax in range(2):
            a = np.pi * A[:, ax:ax + 1]                                   # (S, 1)
            u0 = s0[:, ax:ax + 1] + z * g[:, ax:ax + 1]
            x0 = origin[:, ax:ax + 1]
            b = a * h * hs
            u = u0 + jj[None, :] * hs
            x = x0 + ii[None, :] * h
            P = -a * u * u + 2.0 * a * x0 * hs * jj[None, :] + b * jj[None, :] ** 2 + 2.0 * a * u0 * x0
            Q = -a * x * x + 2.0 * a * u0 * h * ii[None, :] + b * ii[None, :] ** 2
            K = -b * mm[None, :] ** 2
            amp = np.sqrt(np.abs(A[:, ax:ax + 1])) * h
            Pd = amp * _cis(P, np)
            if taper_guard_mm is not None:   # the taper weights the sensor-side points p (rows of E)
                nd = np.asarray((nodes_x_mm, nodes_y_mm)[ax], dtype=np.float64).reshape(S, -1)
                Pd = Pd * sensor_taper(ps[:, :, ax], nd.min(1) - float(taper_guard_mm), nd.max(1) + float(taper_guard_mm))
            Pd = xp.asarray(Pd.astype(cdt))
            Qd = xp.asarray(_cis(Q, np).astype(cdt))
            Kd = xp.asarray(_cis(K, np).astype(cdt))
            # demodulating by f_c: h_G carries exp(2 pi i f_c.(p - x)); the field carries exp(-2 pi i f_c.x)
            # removed, the output exp(2 pi i f_c.p) is removed: nothing left but constants
            self._E.append(Kd[:, toe] * Pd[:, :, None] * Qd[:, None, :])
        self._geo = X
        self._dE = None
        # step 2: remainder transfer on the padded sensor grid (true frequency f_c + nu)
        nu_h = np.fft.fftfreq(self.nf, d=hs)                                   # (nf,)
        nu = xp.asarray(nu_h)
        fx = X["f_c"][:, 0:1, None] + nu[None, None, :]                        # (S, 1, nf)
        fy = X["f_c"][:, 1:2, None] + nu[None, :, None]                        # (S, nf, 1)
        arg = X["inv_lam"][:, None, None] ** 2 - fx ** 2 - fy ** 2
        w = xp.sqrt(xp.maximum(arg, 0.0))
        nux, nuy = nu[None, None, :], nu[None, :, None]
        gx, gy = X["g"][:, None, None, 0], X["g"][:, None, None, 1]
        qx, qy = X["q"][:, None, None, 0], X["q"][:, None, None, 1]
        wg = X["w_c"][:, None, None] + gx * nux + gy * nuy + 0.5 * (qx * nux ** 2 + qy * nuy ** 2)
        # band limit of the remainder: a component moved by H_R further than the padding would wrap
        # around the periodic sensor grid; it lands far outside the patch, so it is dropped (the same
        # criterion as Matsushima's band-limited ASM, applied to the remainder's displacement)
        ws = xp.where(arg > 0, w, 1.0)
        dx = z * (fx / ws + gx + qx * nux)
        dy = z * (fy / ws + gy + qy * nuy)
        room = (self.nf - self.ns) * hs
        keep = (arg > 0) & (xp.abs(dx) <= room) & (xp.abs(dy) <= room)
        rem = xp.where(keep, w - wg, 0.0)
        self._HR = xp.where(keep, _cis(2.0 * np.pi * z * rem, xp), 0.0)
        # c = lambda' w = k_z / k, the direction cosine (pixel_values "flux"; 0 off the kept band, where H_R is 0)
        self._c = xp.where(keep, w / X["inv_lam"][:, None, None], 0.0)
        self._keep_mean = xp.mean(keep)   # read on demand (kept_band_fraction): no device sync at set-up
        self._rem = rem           # d(phase of H_R)/dz / (2 pi), kept band (for the distance derivative)
        self._dHR = None
        # output factors: U(p) = 1/nf^2 sum_m B_m exp(2 pi i nu_m (p - s0))
        nx = xp.asarray(np.asarray(nodes_x_mm, float) - s0[:, 0:1])
        ny = xp.asarray(np.asarray(nodes_y_mm, float) - s0[:, 1:2])
        self._Fx = _cis(2.0 * np.pi * nu[None, None, :] * nx[:, :, None], xp) / self.nf
        self._Fy = _cis(2.0 * np.pi * nu[None, None, :] * ny[:, :, None], xp) / self.nf

    @property
    def nbytes(self) -> int:
        """Bytes the operator holds on its device: the step-1 factors, the remainder transfer and its phase,
        the output factors and, once formed, the distance-derivative factors."""
        arrays = [*self._E, self._HR, self._rem, self._c, self._Fx, self._Fy]
        if self._dE is not None:
            arrays += [*self._dE, self._dHR]
        return int(sum(a.nbytes for a in arrays))

    @property
    def kept_band_fraction(self) -> float:
        """Fraction of the padded sensor grid's frequencies the remainder's band limit keeps (0..1)."""
        return float(self._keep_mean)

    # ------------------------------------------------------------------ operator
    def sensor_grid_field(self, field):
        """Step 1: ``V`` (S, ns, ns) on the sensor-side grid (rows y, columns x) from the wave-plane field
        (S, n, n) (carrier removed)."""
        xp = self.xp
        ex, ey = self._E
        t = xp.matmul(field.astype(ex.dtype, copy=False), xp.swapaxes(ex, 1, 2))   # (S, n_y, ns_x)
        return xp.matmul(ey, t).astype(np.complex128, copy=False)                # (S, ns_y, ns_x)

    def forward(self, field):
        """Complex field at the output nodes, (S, My, Mx) (up to a constant phase per source)."""
        return self._to_nodes(self._spectrum(field))

    def forward_pair(self, field):
        """``(U, U_w)`` at the output nodes, each (S, My, Mx): the field (:meth:`forward`) and the field of its
        sensor-plane spectrum weighted by the direction cosine ``c = k_z / k``; ``Re(conj(U) U_w)`` is the
        z-flux (:func:`pixel_flux`; the same constant phase per source in both)."""
        b = self._spectrum(field)
        return self._to_nodes(b), self._to_nodes(b * self._c)

    def _spectrum(self, field):
        """``B = FFT(V) H_R`` on the padded sensor-side grid, (S, nf, nf) (true frequency ``f_c + nu``)."""
        return self._fft(self.sensor_grid_field(field)) * self._HR

    def _to_nodes(self, b):
        """The output DFT of a padded spectrum (S, nf, nf) to the nodes, (S, My, Mx) (:func:`spectrum_to_nodes`)."""
        return spectrum_to_nodes(b, self._Fx, self._Fy, self.xp)

    def _distance_factors(self):
        """d/dz of the step-1 factors and of ``H_R`` at fixed grids, band mask and carrier (built once,
        :func:`distance_factors`)."""
        if self._dE is None:
            self._dE, self._dHR = distance_factors(self._E, self._geo, self.z, self._HR, self._rem)
        return self._dE, self._dHR

    def _fft(self, v):
        """Step 2's zero-padded FFT of the sensor-side field: (S, ns, ns) -> (S, nf, nf)."""
        if self.xp is not np:
            ensure_cufft_plan_cache()   # in the thread that runs it (torch's backward runs on a thread of its own)
        return self.xp.fft.fft2(v, s=(self.nf, self.nf))

    def _fft_adjoint(self, b):
        """Adjoint of :meth:`_fft`: (S, nf, nf) -> (S, ns, ns)."""
        if self.xp is not np:
            ensure_cufft_plan_cache()
        return (self.xp.fft.ifft2(b) * (self.nf * self.nf))[:, :self.ns, :self.ns]

    def distance_derivative(self, field):
        """``dU/dz`` (S, My, Mx) at the output nodes: the exact derivative of :meth:`forward` with respect
        to the propagation distance ``distance_mm`` (grids, band mask and carrier held fixed; the constant
        phase per source that :meth:`forward` drops does not change intensities; :func:`focal_distance_derivative`)."""
        return focal_distance_derivative(field, self._E, self._HR, self._c, self._Fx, self._Fy,
                                         *self._distance_factors(), self._fft, False, self.xp)

    def distance_derivative_pair(self, field):
        """``(dU/dz, dU_w/dz)``: the exact distance derivatives of :meth:`forward_pair` (the weight does not
        depend on the distance)."""
        return focal_distance_derivative(field, self._E, self._HR, self._c, self._Fx, self._Fy,
                                         *self._distance_factors(), self._fft, True, self.xp)

    def adjoint(self, grad):
        """Adjoint of :meth:`forward` (the conjugate-transpose linear map), (S, My, Mx) -> (S, n, n)
        (:func:`focal_adjoint`)."""
        return focal_adjoint(grad, None, self._E, self._HR, self._c, self._Fx, self._Fy, self._fft_adjoint, self.xp)

    def adjoint_pair(self, grad_u, grad_w):
        """Adjoint of :meth:`forward_pair`: the field's gradient from those of ``U`` and ``U_w`` (S, My, Mx) each
        (torch's convention), (S, n, n)."""
        return focal_adjoint(grad_u, grad_w, self._E, self._HR, self._c, self._Fx, self._Fy, self._fft_adjoint,
                             self.xp)


def sensor_taper(p, lo, hi, n_own=None):
    """A C-infinity window over sensor-grid points ``p`` (S, ns) mm: 1 on ``[lo, hi]`` ((S,) mm each), falling
    to 0 at the grid's ends as ``1 - s(t)``, ``s(t) = e(t) / (e(t) + e(1 - t))``, ``e(t) = exp(-1 / t)``
    (``t``: 0 at ``lo`` or ``hi``, 1 at the grid's end). ``n_own`` (S,) ints: row ``k``'s grid is its first
    ``n_own[k]`` points (its end the last of them; 1 past them), as packed members' grids of several lengths are
    (None: every row's whole). Returns (S, ns) floats in [0, 1]."""
    p = np.asarray(p, dtype=np.float64)
    lo = np.asarray(lo, dtype=np.float64)[:, None]
    hi = np.asarray(hi, dtype=np.float64)[:, None]
    S, ns = p.shape
    n = np.full(S, ns) if n_own is None else np.asarray(n_own, dtype=np.int64)
    own = np.arange(ns)[None, :] < n[:, None]
    first, last = p[:, :1], p[np.arange(S), n - 1][:, None]
    t = np.zeros_like(p)
    below, above = own & (p < lo), own & (p > hi)
    np.divide(lo - p, np.broadcast_to(lo - first, p.shape), out=t, where=below)
    np.divide(p - hi, np.broadcast_to(last - hi, p.shape), out=t, where=above)
    t = np.clip(t, 0.0, 1.0)

    def e(u):
        return np.where(u > 0, np.exp(-1.0 / np.where(u > 0, u, 1.0)), 0.0)
    return np.where(own, 1.0 - e(t) / (e(t) + e(1.0 - t)), 1.0)


_PIXEL_WEIGHTS: dict = {}   # (gauss_nodes, pixel_mm) -> weights, computed once (a few dozen entries at most)


def pixel_weights(gauss_nodes: int, pixel_mm: float) -> np.ndarray:
    """Gauss-Legendre quadrature weights (g, g) of one pixel's area (mm^2), node order as the output nodes
    (a new array each call; the values are computed once per ``(gauss_nodes, pixel_mm)``)."""
    key = (int(gauss_nodes), float(pixel_mm))
    w = _PIXEL_WEIGHTS.get(key)
    if w is None:
        _, wts = np.polynomial.legendre.leggauss(key[0])
        w = np.outer(wts, wts) * (0.5 * key[1]) ** 2
        if len(_PIXEL_WEIGHTS) < 256:
            _PIXEL_WEIGHTS[key] = w
    return w.copy()


def pixel_power(u_nodes, gauss_nodes: int, pixel_mm: float, size: int, xp=np):
    """Power per pixel from the field at ``g x g`` Gauss-Legendre nodes per pixel: ``u_nodes`` (S, size*g,
    size*g) ordered pixel-major (pixel i, node a at column ``i*g + a``). Returns (S, size, size). A part of a
    patch (S, rows g, cols g) gives (S, rows, cols): the pixel counts are read from the node array's shape."""
    g = int(gauss_nodes)
    w2 = xp.asarray(pixel_weights(g, pixel_mm))
    inten = (u_nodes.real ** 2 + u_nodes.imag ** 2).reshape(_pixel_grid(u_nodes, g))
    return _node_sum(inten, w2)


def pixel_power_adjoint(u_nodes, grad_power, gauss_nodes: int, pixel_mm: float, xp=np):
    """Gradient of ``sum(grad_power * pixel_power(u_nodes))`` with respect to the node field, in torch's
    convention for complex inputs (``2 dL/d conj(u)``): ``2 w_ab grad_power[i, j] u`` at node (i a, j b).
    ``u_nodes`` (S, size g, size g), ``grad_power`` (S, size, size)."""
    g = int(gauss_nodes)
    S, rows, cols = grad_power.shape
    w2 = xp.asarray(pixel_weights(g, pixel_mm))
    wg = grad_power[:, :, None, :, None] * w2[None, None, :, None, :]
    return 2.0 * wg.reshape(S, rows * g, cols * g) * u_nodes


def focal_pixels(op, field, pixel_values: str, gauss_nodes: int, pixel_mm: float, size: int):
    """The pixel values ``pixel_values`` names ("flux": :func:`pixel_flux` of :meth:`FocalPropagator.forward_pair`;
    "intensity": :func:`pixel_power` of :meth:`FocalPropagator.forward`) of a wave-plane field (S, n, n) through
    the operator ``op``: ``(values (S, size, size), node fields)`` (the pair ``(U, U_w)`` for the flux)."""
    if pixel_values == "flux":
        u = op.forward_pair(field)
        return pixel_flux(*u, gauss_nodes, pixel_mm, size, xp=op.xp), u
    u = op.forward(field)
    return pixel_power(u, gauss_nodes, pixel_mm, size, xp=op.xp), u


def pixel_flux(u_nodes, u_w_nodes, gauss_nodes: int, pixel_mm: float, size: int, xp=np):
    """Power through each pixel (pixel_values "flux") from the node fields ``(U, U_w)`` of
    :meth:`FocalPropagator.forward_pair`: the z-flux ``Re(conj(U) U_w)`` summed with the Gauss-Legendre weights of
    the pixel's area (node order as :func:`pixel_power`). Returns (S, size, size)."""
    g = int(gauss_nodes)
    w2 = xp.asarray(pixel_weights(g, pixel_mm))
    flux = u_nodes.real * u_w_nodes.real + u_nodes.imag * u_w_nodes.imag
    flux = flux.reshape(_pixel_grid(u_nodes, g))
    return _node_sum(flux, w2)


def _pixel_grid(u_nodes, g: int):
    """``(S, rows, g, cols, g)``: the node array's shape split into pixels of ``g x g`` nodes."""
    S, my, mx = u_nodes.shape
    if my % g or mx % g:
        raise ValueError(f"node field shape {tuple(u_nodes.shape)} is not a whole number of pixels of {g} x {g} "
                         "Gauss nodes")
    return S, my // g, g, mx // g, g


def _node_sum(v, w2):
    """``sum_ab w2[a, b] v[s, i, a, j, b]``: (S, size, g, size, g) node values and (g, g) weights -> (S, size, size)
    (a product and a reduction: on a GPU two launches and little host work, where ``einsum`` spends ~0.1 ms of
    host time a call parsing and dispatching)."""
    return (v * w2[None, None, :, None, :]).sum(axis=(2, 4))


def pixel_flux_adjoint(u_nodes, u_w_nodes, grad_power, gauss_nodes: int, pixel_mm: float, xp=np):
    """Gradients of ``sum(grad_power * pixel_flux(u_nodes, u_w_nodes))`` with respect to ``u_nodes`` and
    ``u_w_nodes`` in torch's convention (``2 dL/d conj(u)``): ``(w_ab grad_power[i, j] U_w, w_ab grad_power[i, j] U)``
    at node (i a, j b) (``Re(conj(a) b) = (conj(a) b + a conj(b)) / 2``)."""
    g = int(gauss_nodes)
    S, rows, cols = grad_power.shape
    w2 = xp.asarray(pixel_weights(g, pixel_mm))
    wg = (grad_power[:, :, None, :, None] * w2[None, None, :, None, :]).reshape(S, rows * g, cols * g)
    return wg * u_w_nodes, wg * u_nodes
