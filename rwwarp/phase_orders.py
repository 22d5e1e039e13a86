"""Several diffraction orders of phase surfaces, summed coherently at the sensor (issue 27 item 4).

A phase surface (:mod:`rwwarp.phase_surface`) traces one order, ``Surface.diffraction_order`` (the design order
``m0``). Away from its design wavelength its relief sends light into the other orders too: the kinoform blazed
for ``m0`` is, in the thin-element picture, ``exp(1j m0 s(lambda) wrap(phi)) = sum_m c_m exp(1j m phi)`` with
``c_m = exp(1j pi (alpha - m)) sinc(alpha - m)``, ``alpha = m0 s(lambda)`` and ``s`` the relief's phase depth at
``lambda`` over its depth at ``lambda0`` (:func:`rwwarp.phase_surface.relief_scale`, dispersion of the media on
both sides included; the series is :func:`rwwarp.wave.focal.doe_order_coefficients`, the flat DOE's). Each term
is a smooth phase that the rays of order ``m`` carry exactly (the module docstring of
:mod:`rwwarp.phase_surface`), so the field behind the surface is the sum over orders of ``c_m`` times the field
of the lens traced in order ``m``.

``Surface.diffraction_orders`` (e.g. ``(0, 1, 2)``; it must hold ``diffraction_order``) asks the ray-wave PSF
(:func:`rwwarp.psf`, :func:`rwwarp.psf_map`, ``model="ray-wave"``) for those orders. None (the default) keeps the
single-order path, unchanged. Method (:func:`multi_order_psf`), per (field, wavelength):

1. the design-order combination is planned and run as today (:class:`~rwwarp.wave.raywave.RayWave`); its sensor
   patch (centre, pixels, Gauss nodes) is the patch of every order;
2. every other kept combination (one order per multi-order surface; the weights multiply) is a lens copy with
   those orders, planned on its own (its own windows, pitch, method) for the same patch;
3. each combination's complex field at the pixels' Gauss nodes is made absolute: the splat removes the chief
   ray's path ``exp(1j k OPL_c)`` and the carrier ``exp(2 pi i f_c . (x - x_c))`` (:mod:`rwwarp.kernels.splat`),
   the focal method the constant ``exp(2 pi i f_c . p - i pi / 2 + 2 pi i z w_c)`` of its Gaussian kernel
   (:mod:`rwwarp.wave.focal`); they are put back (:func:`absolute_node_fields`);
4. the sum ``U = sum c U_m`` (and its direction-cosine weighted ``U_w``) is integrated over the pixels as every
   PSF is (``pixel_values``: ``Re(conj(U) U_w)`` or ``|U|^2``), over the entering power.

Propagation is linear, so the sum at the sensor equals the sum on any plane; planning each order alone keeps
each order's sampling right (a defocused order needs other windows than the focused one). Combinations whose
efficiency ``|c|^2`` is below ``order_tol`` (default :data:`ORDER_TOL`) are skipped, and said so in the plan's
reasons, which list every order with its efficiency; at most :data:`MAX_COMBINATIONS` are traced (a clear error
beyond: several multi-order surfaces multiply their orders). Cost: one more ray-wave PSF per extra order.

Limits: the ray-wave model only (``"ray"`` and ``"paraxial-wave"`` refuse ``diffraction_orders``); the energy
amplitude convention; no wave step; no ``cache``; the stop must be at or in front of every multi-order surface
(all orders share the entrance pupil, hence the optical-path reference). Gradients:
:class:`torch_bridge.phase_orders.OrderSet` (the same sum through the operators' adjoints; checked against finite
differences), which ``torch_bridge.HybridLens.psf`` / ``psf_map`` and the design loop's ``LiveProvider`` use (``CachedProvider``
follows the design order only, and warns). Lengths mm, wavelengths
um.
"""
from __future__ import annotations

import itertools
from dataclasses import replace

import numpy as np

from .errors import LensError

#: default efficiency below which an order combination is skipped (and reported)
ORDER_TOL = 1e-4
#: most order combinations traced for one PSF
MAX_COMBINATIONS = 9


def multi_order_surfaces(lens) -> list:
    """Indices of the surfaces of ``lens`` with ``diffraction_orders`` set (empty: the single-order path)."""
    return [i for i, s in enumerate(lens.surfaces) if getattr(s, "diffraction_orders", None) is not None]


def order_combinations(lens, wavelength_um: float, order_tol: float = ORDER_TOL):
    """``(kept, skipped)`` order combinations at ``wavelength_um`` (um): each a dict ``{"orders": {surface: m},
    "c": complex weight (the product over the surfaces), "eta": |c|^2}``, the design combination first (always
    kept); the others kept when ``eta >= order_tol``. :class:`ValueError` when more than
    :data:`MAX_COMBINATIONS` are kept."""
    from .phase_surface import order_weights
    idx = multi_order_surfaces(lens)
    per = [order_weights(lens, i, wavelength_um) for i in idx]
    design = {i: lens.surfaces[i].diffraction_order for i in idx}
    combos = []
    for terms in itertools.product(*per):
        c = complex(np.prod([t[1] for t in terms])) if terms else 1.0 + 0j
        combos.append({"orders": {i: t[0] for i, t in zip(idx, terms)}, "c": c, "eta": float(abs(c) ** 2)})
    combos.sort(key=lambda d: (d["orders"] != design, -d["eta"]))
    kept = [d for d in combos if d["orders"] == design or d["eta"] >= order_tol]
    skipped = [d for d in combos if d not in kept]
    if len(kept) > MAX_COMBINATIONS:
        raise ValueError(f"diffraction_orders: {len(kept)} order combinations above order_tol = {order_tol:g} at "
                         f"{wavelength_um:g} um (surfaces {idx}); at most {MAX_COMBINATIONS} are traced: list "
                         "fewer orders or raise order_tol")
    return kept, skipped


def order_lens(lens, orders: dict):
    """A copy of ``lens`` whose surfaces ``orders`` ({index: m}) trace order m alone (``diffraction_orders``
    None); ``lens`` is not changed."""
    return lens.replace(surfaces=[replace(s, diffraction_order=int(orders[i]), diffraction_orders=None) if i in orders else
                    replace(s, diffraction_orders=None) if getattr(s, "diffraction_orders", None) is not None else s
                    for i, s in enumerate(lens.surfaces)])


def describe(kept, skipped, wavelength_um: float, order_tol: float) -> list:
    """Plan reasons (strings) naming the traced and skipped order combinations and their efficiencies."""
    def name(d):
        return ", ".join(f"surface {i} order {m}" for i, m in d["orders"].items())
    lines = [f"diffraction orders at {wavelength_um:g} um: {len(kept)} traced and summed coherently at the sensor "
             f"(efficiencies sum {sum(d['eta'] for d in kept):.4f}): "
             + "; ".join(f"[{name(d)}] eta {d['eta']:.4g}" for d in kept)]
    if skipped:
        lines.append(f"orders skipped (efficiency below order_tol = {order_tol:g}, {sum(d['eta'] for d in skipped):.3g}"
                     " of the light in all): " + "; ".join(f"[{name(d)}] {d['eta']:.3g}" for d in skipped))
    return lines


def check_multi_order(lens, model: str, amplitude: str, cache) -> None:
    """Refuse what the multi-order path does not support (clear errors naming it)."""
    idx = multi_order_surfaces(lens)
    if not idx:
        return
    if model != "ray-wave":
        raise ValueError(f"diffraction_orders (surfaces {idx}) is computed by model='ray-wave' only, got "
                         f"model={model!r}")
    if amplitude != "energy":
        raise ValueError("diffraction_orders needs amplitude='energy'")
    if cache is not None:
        raise ValueError("diffraction_orders: cache is not supported (pass cache=None)")
    if lens.stop_index > min(idx):
        raise LensError(f"diffraction_orders: the stop (surface {lens.stop_index}) lies behind phase surface "
                        f"{min(idx)}, so each order would have its own entrance pupil; put the stop at or in "
                        "front of it", file=lens.source, surface=lens.surface_label(min(idx)),
                        keyword="diffraction_orders")


def node_phase(rw, distance_mm=None):
    """The constant phases the splat and the planned propagation of a :class:`~rwwarp.wave.raywave.RayWave` batch
    drop, as the factor (S, size g, size g) (complex numpy) that makes its node field (the method's operator
    output) the true field: ``exp(1j (k OPL_c - 2 pi f_c . x_c))`` (the splat removes the chief ray's path and the
    carrier about the chief point, :mod:`rwwarp.kernels.splat`; :meth:`RayWave.field` must have run) and, for the
    focal method, ``exp(2 pi i f_c . p - i pi / 2 + 2 pi i z w_c)`` (its output is demodulated, and its Gaussian
    kernel's 2-D integral (``A < 0`` on both axes) and the transfer's constant term are left out,
    :mod:`rwwarp.wave.focal`). ``distance_mm``: the plane-to-sensor distance of the operator (default the lens's)."""
    from .wave.focal import transfer_curvature
    from .wave.sensor_grid import gauss_nodes_xy
    nx, ny = gauss_nodes_xy(rw)
    chief, opl_c = rw._splat_reference
    k = 2.0 * np.pi / np.asarray(rw.lam_mm, dtype=np.float64)          # vacuum wavenumber (OPL carries n)
    fc = np.asarray(rw.carrier, dtype=np.float64)
    theta = k * np.asarray(opl_c, dtype=np.float64) - 2.0 * np.pi * np.sum(fc * np.asarray(chief)[:, :2], axis=1)
    ph = np.broadcast_to(np.exp(1j * theta)[:, None, None], (rw.nsrc, ny.shape[1], nx.shape[1]))
    if rw.plan.method == "focal":
        z = float(rw.z_sensor - rw.z_plane) if distance_mm is None else float(distance_mm)
        lam = np.asarray(rw.lam_mm, dtype=np.float64) / np.asarray(rw.n_after, dtype=np.float64)
        w_c = transfer_curvature(fc, 1.0 / lam)[0]
        car = np.exp(2j * np.pi * (fc[:, None, None, 0] * nx[:, None, :] + fc[:, None, None, 1] * ny[:, :, None]))
        ph = ph * car * np.exp(1j * (2.0 * np.pi * z * w_c - 0.5 * np.pi))[:, None, None]
    elif rw.plan.method not in ("asm", "direct"):
        raise ValueError(f"diffraction_orders: method {rw.plan.method!r} gives no complex field at the pixels; use "
                         "'focal', 'asm' or 'direct'")
    return np.ascontiguousarray(ph)


def absolute_node_fields(rw, field, precision: str = "double"):
    """``(U, U_w)``: the true complex field of a :class:`~rwwarp.wave.raywave.RayWave` batch at its pixels' Gauss
    nodes ((S, size g, size g) complex numpy) from its wave-plane ``field`` (:meth:`RayWave.field_array`, after
    :meth:`RayWave.field` ran), with every constant phase the splat and the propagation drop put back
    (:func:`node_phase`), and the direction-cosine weighted field ``U_w`` (None for ``pixel_values="intensity"``).
    Methods ``focal``, ``asm`` and ``direct``; ``precision``: the focal method's matrix products."""
    name = rw.plan.method
    if np.any(getattr(rw, "wave_step", 0.0)):
        raise ValueError("diffraction_orders: the wave step is not supported (call without tolerance / "
                         "method='two-step')")
    ph = node_phase(rw)
    pair = rw.pixel_values == "flux"
    if name == "focal":
        op = rw.focal_operator(precision=precision)
        xp = op.xp
        u = xp.asarray(field)
        fac = rw.doe_orders_factor(xp)
        if fac is not None:
            u = u * fac
        U, Uw = op.forward_pair(u) if pair else (op.forward(u), None)
    elif name == "asm":
        from .wave.methods.asm import AsmOperator
        op = AsmOperator(rw)
        U = op.forward(field)
        Uw = op._out(op.prop.forward_weighted(op._dev(field), op.phi0)) if pair else None
    else:   # direct (node_phase refused the others)
        from .wave.methods.direct import DirectOperator
        xp = np if isinstance(field, np.ndarray) else __import__("cupy")
        op = DirectOperator.of(rw, None, xp)
        f = xp.asarray(field)
        U = op.forward(f)
        Uw = op.distance_derivative(f) / (1j * xp.asarray(op.k)[:, None, None]) if pair else None
    U = np.asarray(U.get() if hasattr(U, "get") else U)
    Uw = None if Uw is None else np.asarray(Uw.get() if hasattr(Uw, "get") else Uw)
    return U * ph, (None if Uw is None else Uw * ph)


def multi_order_psf(lens, fields, wls, size: int, pixel: float, opts: dict, object_distance_mm=None,
                    focal_precision: str = "double", order_tol: float = ORDER_TOL) -> dict:
    """The ray-wave PSFs of the (field, wavelength) pairs ``fields`` / ``wls`` (deg, um; one source each) of a lens
    with multi-order phase surfaces (module docstring), as :meth:`RayWave.run` returns them (``data`` (S, size,
    size) fractions of the entering power, ``centers``, ``plan`` (the design order's, with the orders in its
    reasons), ``plans``, ``valid_fraction``, ``dropped_rays``) plus ``orders`` (per source the traced
    combinations: orders, weight, efficiency, seconds). ``opts``: :class:`RayWave` keywords (``center_mm`` the
    patch of the design order; None: its chief ray's landing)."""
    import time
    from .wave.focal import pixel_flux, pixel_power
    from .wave.raywave import RayWave
    check_multi_order(lens, "ray-wave", opts.get("amplitude", "energy"), None)
    out = {"data": [], "centers": [], "plans": [], "valid_fraction": [], "dropped_rays": [], "orders": []}
    opts = dict(opts)
    opts["allow_pixel"] = False     # the pixel method forms no complex field
    for fld, wl in zip(fields, wls):
        kept, skipped = order_combinations(lens, wl, order_tol)
        acc_u = acc_w = None
        rec, rw0 = [], None
        for d in kept:
            t0 = time.perf_counter()
            o = dict(opts)
            if rw0 is not None:    # the design order's patch and pixel nodes for every other order
                o["center_mm"] = tuple(rw0.centers[0])
                o["gauss_nodes"] = rw0.gauss_nodes
            rw = RayWave(order_lens(lens, d["orders"]), [fld], [float(wl)], size, pixel,
                         object_distance_mm=object_distance_mm, **o)
            field = rw.field_array()
            if rw0 is None:
                rw0 = rw
            elif not (np.array_equal(rw.src["aim"], rw0.src["aim"]) and np.array_equal(rw.src["half_x"], rw0.src["half_x"])):
                raise LensError("diffraction_orders: the orders' entrance pupils differ (their paraxial pupils depend "
                                "on the order); put the stop in front of the phase surfaces", file=lens.source)
            U, Uw = absolute_node_fields(rw, field, focal_precision)
            acc_u = d["c"] * U if acc_u is None else acc_u + d["c"] * U
            if Uw is not None:
                acc_w = d["c"] * Uw if acc_w is None else acc_w + d["c"] * Uw
            rec.append({"orders": dict(d["orders"]), "c": d["c"], "eta": d["eta"], "method": rw.plan.method,
                        "time_s": time.perf_counter() - t0})
        g = rw0.gauss_nodes
        if acc_w is not None:
            power = pixel_flux(acc_u, acc_w, g, pixel, size)
        else:
            power = pixel_power(acc_u, g, pixel, size)
        data = np.asarray(power) / rw0.entering[:, None, None]
        if not np.all(np.isfinite(data)):
            raise FloatingPointError("non-finite multi-order PSF values (please report this lens and field)")
        plan = rw0.plan.with_reasons(*describe(kept, skipped, wl, order_tol))
        out["data"].append(data[0])
        out["centers"].append(rw0.centers[0])
        out["plans"].append(plan.to_dict())
        out["valid_fraction"].append(float(rw0.valid_fraction[0]))
        out["dropped_rays"].append(int(np.asarray(rw0.dropped.numpy())[0]))
        out["orders"].append(rec)
    out["data"] = np.stack(out["data"])
    out["centers"] = np.stack(out["centers"])
    out["plan"] = out["plans"][-1]
    return out
