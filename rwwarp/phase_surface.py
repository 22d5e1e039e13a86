"""Diffractive phase on a refracting surface (a DOE anywhere): diffraction orders traced as rays.

A ``standard`` surface (plane, sphere, conic, even or odd asphere: any sag the tracer handles) may carry a
diffractive phase ``Surface.phase`` (a profile dict) of which the diffraction order ``Surface.diffraction_order``
``m`` (default 1, the design order) is traced. Such surfaces may stand anywhere in the lens (in front of,
between or behind refracting elements), and there may be several; the flat wave-plane DOE (surface type
``doe``, applied by the wave models as a phase mask with all its orders) stays as it is.

Phase (radians), ``rho = r / R`` with ``r = hypot(x, y)`` in the surface's local coordinates (mm)::

    even_poly   phi = sum_i A_i rho^(2 i), i = 1..8      (Zemax BINARY_2: XDAT 2 = R, XDAT 3.. = A_i;
                                                          PARM 0 = the order m)
    fresnel     phi = -pi r^2 / (lambda0 f)              (converted to even_poly with R = 1 mm)

Method (the tracer's ``phase_surface_kernel``, :mod:`rwwarp.kernels.trace`): at the ray's intersection with
the surface (the same Newton root as a refracting surface) the local grating equation bends the ray,
``n' d'_t = n d_t + (m lambda / 2 pi) grad_t phi`` (tangential components; the normal one follows from
``|d'| = 1``), and the optical path gains ``m lambda phi / (2 pi)``. Sign and scaling are Zemax's for
BINARY_2 (a negative A_1 converges; the paraxial power is ``-m lambda A_1 / (pi R^2)``).

Why a single smooth order traced as rays is right: a continuous relief (a kinoform) whose zones are many
wavelengths wide is, in the thin-element picture, the transmission ``exp(i s(lambda) wrap(phi))``, a Fourier
series over orders ``sum_m c_m exp(i m phi)`` (:mod:`rwwarp.wave.focal`), each term a smooth phase. The eikonal
carries a smooth phase exactly as it carries a refracting surface's path: the rays of order m are the normals of
the wavefront whose path jumps by ``m lambda phi / 2 pi`` at the surface, and the grating equation above is the
tangential gradient of that jump (Malus-Dupin), so the rays stay orthogonal to the wavefronts and the coherent
ray-wave PSF from the last surface sees ``exp(i m phi)`` in the rays' paths, with no sampling of the relief.
Its errors are those of the thin-element approximation itself (the relief's depth and the shadowing of zones a
few wavelengths wide are neglected, as in Zemax's and optiland's models), and, at the wave stage, the ray-wave
model's own. The order's phase ``m phi`` does not depend on the wavelength (only its efficiency does), hence the
``m lambda / 2 pi`` scaling. Checked against an independent numpy trace (rays to 1e-14 mm), ray-transfer
matrices, the Airy pattern of a stigmatic diffractive singlet (1.3e-4), the Rayleigh-Sommerfeld sum over the
traced rays (3.7e-5) and optiland (``tests/rwwarp/test_phase_surface*.py``).

Several orders (``Surface.diffraction_orders``, e.g. ``(0, 1, 2)``, holding the design order): the relief is the
kinoform blazed for ``m0 = diffraction_order`` (depth ``|m0|`` waves at the surface's ``design_wavelength_um``), so
at ``lambda`` its transmission ``exp(1j m0 s(lambda) wrap(phi)) = sum_m c_m exp(1j m phi)``, ``c_m =
exp(1j pi (alpha - m)) sinc(alpha - m)``, ``alpha = m0 s(lambda)``, ``eta_m = |c_m|^2 = sinc^2(m0 s - m)``, with
``s(lambda) = (n'(lambda) - n(lambda)) / (n'(lambda0) - n(lambda0)) * lambda0 / lambda`` the relief's phase depth
over its design depth (the index step of the two media, dispersion included; :func:`relief_scale`,
:func:`order_weights`; the series is the flat DOE's, :func:`rwwarp.wave.focal.doe_order_coefficients`). The
ray-wave PSF then traces each order (a combination per multi-order surface) on its own plan and sums ``c_m U_m``
coherently at the sensor's pixel nodes before the pixel values (:mod:`rwwarp.phase_orders`); the plan's reasons
list the orders and efficiencies, and skip those below ``order_tol`` (default 1e-4). Checked against a
thin-element Fresnel-Hankel truth of the wrapped relief (5.8e-4 / 4.1e-4 of the peak, focal / ASM; the design
order alone is 0.185 off; ``tests/rwwarp/test_phase_orders.py``).

Limits: without ``diffraction_orders`` only the traced order is kept: the relief's efficiency into that order
(``sinc^2(s(lambda) - m)`` for a kinoform, see :mod:`rwwarp.doe`) and the light in the other orders are ignored
(the flat wave-plane DOE keeps them). ``diffraction_orders`` is read by the ray-wave PSF and by
:class:`torch_bridge.phase_orders.OrderSet` (its gradients; ``torch_bridge.HybridLens.psf`` / ``psf_map``, ``LiveProvider``) only (not
the ray or paraxial-wave models, nor ``CachedProvider``, which follows the design order); a relief needs different indices on its two sides. A discontinuous profile (quantised levels, pixel maps, zones comparable to the wavelength) is not a
smooth phase: its wraps diffract, and it needs a wave step (the wave-plane DOE), which is refused here. An
evanescent order (``|n' d'_t| >= n'``) makes the ray invalid. Mirrors with a phase, and phases behind a mirror,
are not supported. The tracer differentiates their terms (``wp.Tape``); ``torch_bridge.HybridLens`` learns their
coefficients (quantity ``phase``, ``torch_bridge/phase_params.py``).

Functions: :func:`phase_profile` (the surface's profile as even_poly terms), :func:`phase_columns` (the
tracer's parameter row entries), :func:`phase_power` (paraxial power, 1/mm), :func:`relief_scale` and
:func:`order_weights` (the orders' weights off the design wavelength), :func:`check_phase_surface` (validation with
clear errors).
"""
from __future__ import annotations

import math

from .errors import LensError

#: the phase terms A_1 .. A_N the tracer carries (rho^2 .. rho^16); :data:`rwwarp.kernels.trace.N_PHASE`
MAX_PHASE_TERMS = 8
#: profile kinds a phase surface takes
PHASE_KINDS = ("even_poly", "fresnel")
#: largest |diffraction order|
MAX_ORDER = 1000
#: most orders one surface's ``diffraction_orders`` may list (:mod:`rwwarp.phase_orders`)
MAX_TRACED_ORDERS = 9


def phase_profile(surface):
    """``(R, [A_1, ...])``: the phase of ``surface`` (a ``standard`` surface with ``phase``) as even-polynomial
    terms per unit order, ``phi = sum_i A_i (r / R)^(2 i)`` (R in mm, A_i in radians). A ``fresnel`` phase of focal
    length f (mm) at the surface's ``design_wavelength_um`` becomes ``R = 1``, ``A_1 = -pi / (lambda0 f)``."""
    p = surface.phase
    if p["kind"] == "fresnel":
        return 1.0, [-math.pi / (float(surface.design_wavelength_um) * 1e-3 * float(p["focal_length"]))]
    return float(p["norm_radius"]), [float(a) for a in p["coefficients"]]


def phase_columns(surface):
    """``(m, R, coefficients)``: what the tracer's row holds for a phase surface (order, mm, radians)."""
    rnorm, coeffs = phase_profile(surface)
    return float(surface.diffraction_order), rnorm, coeffs


def phase_power(surface, wavelength_um: float) -> float:
    """Paraxial power (1/mm) the phase of ``surface`` adds at ``wavelength_um`` (um) in its order m:
    ``-m lambda A_1 / (pi R^2)`` (the grating equation's ``d(n u) = (m lambda / 2 pi) dphi/dr`` for
    ``phi ~ A_1 r^2 / R^2``)."""
    rnorm, coeffs = phase_profile(surface)
    a1 = coeffs[0] if coeffs else 0.0
    return -surface.diffraction_order * wavelength_um * 1e-3 * a1 / (math.pi * rnorm * rnorm)


def relief_scale(lens, i: int, wavelength_um: float) -> float:
    """``s(lambda)``: the phase depth of surface ``i``'s relief at ``wavelength_um`` (um) over its depth at the
    design wavelength ``lambda0`` (the surface's ``design_wavelength_um``), dispersion included. The relief is the
    interface itself (the thin-element picture), so its index step is that of the media on its two sides::

        s(lambda) = (n'(lambda) - n(lambda)) / (n'(lambda0) - n(lambda0)) * lambda0 / lambda

    (``n`` before, ``n'`` after; in air before a glass of index n' it is :func:`rwwarp.doe.wavelength_scale`'s
    ``(n' - 1) / (n'0 - 1) lambda0 / lambda``). :class:`LensError` when the two sides have the same index at
    ``lambda0`` (no relief to weigh the orders by)."""
    from . import materials
    media = lens.media()
    before = "air" if i == 0 else media[i - 1]
    after = media[i]
    s = lens.surfaces[i]
    lam0 = float(s.design_wavelength_um)

    def step(w):
        return float(materials.get_material(after).n(w)) - float(materials.get_material(before).n(w))

    d0 = step(lam0)
    if abs(d0) < 1e-9:
        raise LensError(f"diffraction_orders: the phase surface has the same index on both sides ({before!r} / "
                        f"{after!r}), so it has no relief whose depth weighs its orders; put the phase on an "
                        "interface between two media", file=lens.source, surface=lens.surface_label(i),
                        keyword="diffraction_orders")
    return step(float(wavelength_um)) / d0 * lam0 / float(wavelength_um)


def order_weights(lens, i: int, wavelength_um: float, orders=None):
    """``[(m, c_m, eta_m), ...]``: the complex weight ``c_m`` and efficiency ``eta_m = |c_m|^2`` of each order m of
    surface ``i``'s phase at ``wavelength_um`` (um), for ``orders`` (default the surface's ``diffraction_orders``,
    else its ``diffraction_order``). The relief is the kinoform blazed for the design order ``m0 =
    diffraction_order`` (depth ``|m0|`` waves at lambda0), ``exp(1j m0 s(lambda) wrap(phi))`` with ``phi`` the
    phase per unit order (:func:`phase_profile`), so ``c_m`` is the Fourier coefficient of the flat DOE's
    continuous relief with ``alpha = m0 s(lambda)`` (:func:`rwwarp.wave.focal.doe_order_coefficients`, the one
    home of that series; ``eta_m = sinc^2(m0 s - m)``, ``sum over all m of eta_m = 1``)."""
    from .wave.focal import doe_order_coefficients
    s = lens.surfaces[i]
    if orders is None:
        orders = s.diffraction_orders if s.diffraction_orders is not None else (s.diffraction_order,)
    alpha = float(s.diffraction_order) * relief_scale(lens, i, wavelength_um)
    c = doe_order_coefficients(alpha, None, [int(m) for m in orders])
    return [(int(m), complex(cm), float(abs(cm) ** 2)) for m, cm in zip(orders, c)]


def check_phase_surface(s, i, lens) -> None:
    """Validate surface ``i``'s ``phase``, ``diffraction_order`` and ``diffraction_orders`` (raise
    :class:`LensError` naming them)."""
    f = lens.source
    label = lens.surface_label(i)
    order = s.diffraction_order
    if isinstance(order, bool) or not isinstance(order, int) or abs(order) > MAX_ORDER:
        raise LensError(f"diffraction_order must be an integer within +-{MAX_ORDER}, got {order!r}", file=f,
                        surface=label, keyword="diffraction_order")
    orders = s.diffraction_orders
    if orders is not None:
        if s.phase is None:
            raise LensError("diffraction_orders needs a phase on the surface", file=f, surface=label,
                            keyword="diffraction_orders")
        if (not isinstance(orders, (tuple, list)) or not orders or
                any(isinstance(m, bool) or not isinstance(m, int) or abs(m) > MAX_ORDER for m in orders)):
            raise LensError(f"diffraction_orders must be a non-empty list of integers within +-{MAX_ORDER}, got "
                            f"{orders!r}", file=f, surface=label, keyword="diffraction_orders")
        if len(set(orders)) != len(orders) or len(orders) > MAX_TRACED_ORDERS:
            raise LensError(f"diffraction_orders must be distinct, at most {MAX_TRACED_ORDERS}, got {orders!r}",
                            file=f, surface=label, keyword="diffraction_orders")
        if order not in orders:
            raise LensError(f"diffraction_orders {list(orders)} must hold the design order diffraction_order = "
                            f"{order} (the PSF patch is centred on it)", file=f, surface=label,
                            keyword="diffraction_orders")
    if s.phase is None:
        return
    if s.type != "standard":
        raise LensError(f"a phase is carried by a 'standard' (refracting) surface, not a {s.type!r} one (the flat "
                        "wave-plane DOE is surface type 'doe')", file=f, surface=label, keyword="phase")
    if s.mirror:
        raise LensError("a diffractive phase on a mirror is not supported", file=f, surface=label, keyword="phase")
    if any(t.type == "standard" and t.mirror for t in lens.surfaces[:i]):
        raise LensError("a phase surface behind a mirror (light going -z) is not supported", file=f, surface=label,
                        keyword="phase")
    if s.levels is not None:
        raise LensError("a phase surface is a smooth relief traced in one order: quantised levels need the "
                        "wave-plane DOE (surface type 'doe')", file=f, surface=label, keyword="levels")
    p = s.phase
    kind = p.get("kind") if isinstance(p, dict) else None
    if kind not in PHASE_KINDS:
        raise LensError(f"phase kind {kind!r} is not traced on a surface (supported: {PHASE_KINDS}; other "
                        "profiles only on the wave-plane DOE)", file=f, surface=label, keyword="phase")
    from . import doe
    try:
        doe.profile_from_dict(p)
    except LensError as e:
        raise type(e)(str(e).replace("profile", "phase"), file=f, surface=label, keyword="phase") from None
    if kind == "even_poly" and len(p["coefficients"]) > MAX_PHASE_TERMS:
        raise LensError(f"phase has {len(p['coefficients'])} terms; a phase surface carries at most "
                        f"{MAX_PHASE_TERMS} (rho^2 .. rho^{2 * MAX_PHASE_TERMS})", file=f, surface=label,
                        keyword="phase")
