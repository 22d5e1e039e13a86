"""Differentiable multi-order PSF of a lens with multi-order phase surfaces (:mod:`rwwarp.phase_orders`).

:class:`OrderSet` holds one :class:`~rwwarp.wave.raywave.RayWave` (with gradients) per kept order combination of
one (field, wavelength), each planned alone for the design order's patch as :func:`rwwarp.psf` plans them, and
the weights ``c`` of the combinations. :meth:`OrderSet.psf` maps a surface parameter table (the design order's
layout, :data:`rwwarp.trace.COLUMNS`) to the PSF (1, size, size), fraction of the entering power per pixel:
each order's field is traced and splatted (:func:`torch_bridge.functions.trace_splat`, its table the given one
with that order's own diffraction-order and thin-lens conjugate columns), carried to the pixels' Gauss nodes by
its method's operator (:class:`torch_bridge.operator_function.OperatorApply`), made absolute
(:func:`rwwarp.phase_orders.node_phase`, a constant of the plan) and summed ``sum c U_m`` before the pixel
integration (:class:`~torch_bridge.operator_function.NodePixels`). Backward is the sum of the orders' adjoints.

Held fixed (not differentiated): the orders' weights (they depend on the wavelength and the media only), the
thin lenses' conjugate columns (``uinv``, ``v``: the values at the plans' lens), the sensor distance (the
operators' own), the plans. A flat wave-plane DOE in the same lens is refused. Lengths mm, wavelengths um.
"""
from __future__ import annotations

import numpy as np
import torch

from rwwarp.phase_orders import ORDER_TOL, multi_order_surfaces, node_phase, order_combinations, order_lens

__all__ = ["OrderSet", "warn_design_order_only"]


class OrderSet:
    """The order combinations of one (field, wavelength) of ``lens`` (:mod:`rwwarp.phase_orders`), ready to be
    differentiated. ``field_deg`` (deg, y or (x, y)), ``wavelength_um`` (um), ``size`` (px), ``pixel_mm`` (mm,
    default the sensor's), ``order_tol`` (skip combinations of lower efficiency); ``opts``: further
    :class:`~rwwarp.wave.raywave.RayWave` keywords (``method``, ``pixel_values``, ``device``, ...; the energy
    amplitude convention). Attributes: ``rws`` (design order first), ``coefs`` (complex weights), ``orders``
    (per combination {surface: order}), ``table`` (the design order's parameter table, numpy)."""

    def __init__(self, lens, field_deg, wavelength_um: float, size: int, pixel_mm: float | None = None,
                 order_tol: float = ORDER_TOL, **opts):
        from rwwarp.wave.raywave import RayWave
        if not multi_order_surfaces(lens):
            raise ValueError("OrderSet: the lens has no surface with diffraction_orders")
        if lens.doe_index is not None:
            raise ValueError("OrderSet: a flat wave-plane DOE beside multi-order phase surfaces is not supported")
        if opts.get("amplitude", "energy") != "energy":
            raise ValueError("OrderSet: the energy amplitude convention only")
        pixel = float(pixel_mm or lens.sensor.pixel_pitch)
        kept, _ = order_combinations(lens, float(wavelength_um), order_tol)
        self.coefs = [d["c"] for d in kept]
        self.orders = [dict(d["orders"]) for d in kept]
        self.rws = []
        for d in kept:
            o = dict(opts)
            if self.rws:
                o["center_mm"] = tuple(self.rws[0].centers[0])
                o["gauss_nodes"] = self.rws[0].gauss_nodes
            self.rws.append(RayWave(order_lens(lens, d["orders"]), [field_deg], [float(wavelength_um)], size, pixel,
                                    requires_grad=True, **o))
        if any(np.any(getattr(rw, "wave_step", 0.0)) for rw in self.rws):
            raise ValueError("OrderSet: the wave step (method='two-step', or 'auto' with a model tolerance) is not "
                             "supported with diffraction_orders")
        self.table = np.array(self.rws[0].tracer.params_np, dtype=np.float64)
        # each order's own columns (its diffraction orders, the thin lenses' conjugates behind it): constant offsets
        self._delta = [np.array(rw.tracer.params_np, dtype=np.float64) - self.table for rw in self.rws]

    def psf(self, table: torch.Tensor, precision: str = "double") -> torch.Tensor:
        """The multi-order PSF (1, size, size), fraction of the entering power per pixel, differentiable in
        ``table`` (float64 (n_surfaces + 1, N_PARAMS), the design order's layout); ``precision``: the focal
        operator's ("double" for gradients)."""
        from rwwarp.wave.methods import get

        from .functions import _streams, power_sums, trace_splat
        from .operator_function import OperatorApply, node_pixels
        rw0 = self.rws[0]
        pair = rw0.pixel_values == "flux"
        acc_u = acc_w = None
        for rw, c, delta in zip(self.rws, self.coefs, self._delta):
            t = table + torch.as_tensor(delta, dtype=table.dtype, device=table.device)
            u = trace_splat(t, rw, t.detach().cpu().numpy())
            m = get(rw.plan.method)
            with _streams(rw):
                op = m.operator(rw, None, precision)
            out = OperatorApply.apply(u, None, op, pair, rw, m.name)
            a, b = out if pair else (out, None)
            w = torch.as_tensor(c * node_phase(rw), dtype=torch.complex128, device=a.device)
            acc_u = a * w if acc_u is None else acc_u + a * w
            if b is not None:
                acc_w = b * w if acc_w is None else acc_w + b * w
        power = node_pixels((acc_u, acc_w) if pair else acc_u, rw0)
        return power / power_sums(rw0, power.device)[0][:, None, None]


def warn_design_order_only(module, who: str) -> None:
    """Warn (``UserWarning``) that ``who`` (a design provider) computes the design order only where ``module``'s lens
    has multi-order phase surfaces (:meth:`torch_bridge.HybridLens.psf` / ``psf_map`` sum the kept orders)."""
    if getattr(module, "_multi_order", False):
        import warnings
        warnings.warn(f"{who}: the lens's phase surfaces keep several diffraction_orders; this provider computes the "
                      "design order only (HybridLens.psf / psf_map sum the kept orders)", UserWarning, stacklevel=3)
