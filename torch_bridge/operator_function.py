"""The generic autograd path of a registered propagation method (issue 25 item 1).

Every method of :mod:`rwwarp.wave.methods` that forms a field hands out its linear operator
(:meth:`rwwarp.wave.methods.Propagation.operator`): ``forward(field)`` (wave-plane field (S, n, n) -> complex field
(S, My, Mx) at the pixels' Gauss nodes), ``adjoint(grad)`` (its conjugate transpose) and
``distance_derivative(field)`` (d forward / d distance, mm^-1), and for ``pixel_values="flux"`` the pairs
``forward_pair`` / ``adjoint_pair`` / ``distance_derivative_pair`` (the field and its direction-cosine-weighted
field ``U_w``). Two autograd Functions differentiate any such method:

* :class:`OperatorApply`: field (+ distance) -> node field(s) through the operator; backward is the operator's
  adjoint for the field and ``Re sum conj(g) dU/dz`` for the distance (only when the distance needs a gradient;
  a clear error naming the method when its operator has no distance derivative);
* :class:`NodePixels`: node field(s) -> power per pixel (Gauss-Legendre quadrature of ``|U|^2`` or of the
  z-flux ``Re(conj(U) U_w)``, :func:`rwwarp.wave.focal.pixel_power` / :func:`~rwwarp.wave.focal.pixel_flux`);
  backward is their analytic adjoint.

:func:`operator_propagate` chains them for a :class:`~rwwarp.wave.raywave.RayWave` planned with any method
(the focal method's path, :func:`torch_bridge.functions.focal_propagate`, and a new method's, which sets
``torch_path = "operator"``); :func:`torch_bridge.packed.packed_psfs` runs each group of a packed tile through
them. Arrays: the operator's namespace (numpy on the CPU and OpenCL devices, CuPy on CUDA), handed to and from
torch without copies (``torch_bridge.functions._xp_of`` / ``_from_xp``: numpy views, DLPack). Gradients follow
torch's convention for complex tensors (``dL/dRe z + 1j dL/dIm z``), so a linear map's field gradient is its
adjoint applied to the output's gradient. Lengths in mm.
"""
from __future__ import annotations

import contextlib

import numpy as np
import torch

from .functions import _from_xp, _streams, _xp_of

__all__ = ["NodePixels", "OperatorApply", "node_pixels", "operator_propagate"]


def _on_streams(rw):
    """``rw``'s streams and allocator (:func:`torch_bridge.functions._streams`), or nothing for None."""
    return contextlib.nullcontext() if rw is None else _streams(rw)


def _gradient_like(gd, shape):
    """The distance gradient ``gd`` (S,) in the distance's ``shape``: summed for a 0-d distance."""
    return gd.sum() if len(shape) == 0 else gd.reshape(shape)


class OperatorApply(torch.autograd.Function):
    """Wave-plane field -> complex field at the pixels' Gauss nodes through a method's operator.

    ``OperatorApply.apply(field, distance, operator, pair=False, rw=None, name=None, phase_invariant=False)``:
    ``field`` complex (S, n, n)
    (carrier removed, DOE applied as the method does; on the operator's device); ``distance`` the wave-plane to
    sensor distance (mm), a float64 tensor (S,) or 0-d with the value the operator was built for, or None (no
    distance gradient); ``operator`` an object with ``forward`` / ``adjoint`` (and ``distance_derivative`` where
    the distance needs a gradient; the ``*_pair`` variants with ``pair``); ``rw`` the RayWave whose streams and
    allocator it runs on (:func:`torch_bridge.functions._streams`; None: the current ones); ``name`` the method's
    name for error messages. Returns complex128 (S, My, Mx) on ``field``'s device, or with ``pair`` the tuple
    ``(U, U_w)``.

    Backward: ``operator.adjoint(g)`` (``adjoint_pair(g_u, g_w)``) for ``field``; for ``distance``, only when it
    requires grad, ``Re sum conj(g) * operator.distance_derivative(field)`` per source (the plan, band limits and
    nodes held fixed). ``phase_invariant``: the loss does not see a constant phase per source of the output (pixel
    powers and fluxes, :class:`NodePixels`), so where the operator has ``distance_derivative_phase_free`` (``_pair``;
    the ASM's) that form is used: the derivative without the constant phase's term ``i (2 pi / lambda) U``, whose
    contribution is zero but whose rounding is ``1 / (1 - cos theta)`` times the rest, and where it has
    ``adjoint_distance(grads, field, need_field)`` (the ASM's: the band's gradient contracted with the band
    spectrum, no node field formed) both gradients come from that one pass. The field is kept for backward
    only when the distance needs its gradient; the operator is kept until backward has run once, or for good when it
    says it is light (``keep_for_backward``, the ASM's: only its geometry; backward may then run again, as with
    ``retain_graph``)."""

    @staticmethod
    def forward(ctx, field, distance, operator, pair=False, rw=None, name=None, phase_invariant=False):
        ctx.name = name or type(operator).__name__
        need_d = bool(ctx.needs_input_grad[1]) if distance is not None else False
        if need_d and not hasattr(operator, "distance_derivative_pair" if pair else "distance_derivative"):
            raise NotImplementedError(_no_distance(ctx.name, pair))
        xp, f = _xp_of(field.to(torch.complex128))
        with _on_streams(rw):
            u = operator.forward_pair(f) if pair else operator.forward(f)
            out = tuple(_from_xp(a, field.device) for a in (u if pair else (u,)))
        ctx.op, ctx.pair, ctx.rw, ctx.xp = operator, bool(pair), rw, xp
        ctx.phase_free = bool(phase_invariant)
        ctx.keep = bool(getattr(operator, "keep_for_backward", False))
        ctx.f = f if need_d else None              # the field: for d/d(distance) only
        ctx.devices = (field.device, None if distance is None else distance.device)
        ctx.distance_shape = None if distance is None else distance.shape
        return out if pair else out[0]

    @staticmethod
    def backward(ctx, *grads):
        op, xp = ctx.op, ctx.xp
        if op is None:
            raise RuntimeError(f"{ctx.name}: OperatorApply's backward ran twice; it frees its operator after one "
                               "(retain_graph is not supported)")
        need_f = ctx.needs_input_grad[0]
        need_d = ctx.needs_input_grad[1] and ctx.f is not None
        gs = [_xp_of(g.to(torch.complex128))[1] for g in grads]
        gf = gd = None
        with _on_streams(ctx.rw):
            if need_d and ctx.phase_free and hasattr(op, "adjoint_distance"):
                # one pass for both (the ASM's: the band's gradient contracted with the band spectrum)
                g, dl = op.adjoint_distance(gs, ctx.f, need_field=bool(need_f))
                gd = _gradient_like(_from_xp(dl, ctx.devices[1]), ctx.distance_shape)
                gf = _from_xp(g, ctx.devices[0]) if need_f else None
                need_d = need_f = False
            if need_d:
                try:
                    du = _distance_derivative(op, ctx.f, ctx.pair, ctx.phase_free)
                except NotImplementedError as exc:
                    raise NotImplementedError(f"{_no_distance(ctx.name, ctx.pair)}: {exc}") from exc
                dl = sum(xp.real(xp.sum(xp.conj(a) * b, axis=(1, 2))) for a, b in zip(gs, du))
                gd = _gradient_like(_from_xp(dl, ctx.devices[1]), ctx.distance_shape)
            if need_f:
                gf = _from_xp(op.adjoint_pair(*gs) if ctx.pair else op.adjoint(gs[0]), ctx.devices[0])
        if not ctx.keep:
            ctx.op = ctx.f = ctx.rw = None
        return gf, gd, None, None, None, None, None


def _distance_derivative(op, f, pair, phase_free):
    """The operator's distance derivative(s) of ``f`` as a tuple: the ``*_phase_free`` form where allowed and there."""
    name = "distance_derivative_pair" if pair else "distance_derivative"
    if phase_free and hasattr(op, name + "_phase_free"):
        name += "_phase_free"
    du = getattr(op, name)(f)
    return tuple(du) if pair else (du,)


def _no_distance(name, pair):
    what = "distance_derivative_pair" if pair else "distance_derivative"
    return (f"propagation method {name!r}: the distance needs a gradient but its operator has no {what} "
            f"(implement it, or detach the sensor distance)")


class NodePixels(torch.autograd.Function):
    """Node field(s) -> power per pixel, and its analytic adjoint.

    ``NodePixels.apply(u, u_w, gauss_nodes, pixel_mm, size, rw=None)``: ``u`` complex128 (S, size g, size g) at the
    ``g x g`` Gauss-Legendre nodes of each pixel (pixel-major, :func:`rwwarp.wave.focal.pixel_power`), ``u_w``
    the direction-cosine-weighted field (pixel_values "flux": ``Re(conj(U) U_w)`` integrated) or None
    (``|U|^2`` integrated); ``pixel_mm`` the pixel pitch (mm); ``rw`` the RayWave whose streams and allocator
    it runs on (None: the current ones). Returns float64 (S, size, size), field units^2
    mm^2 per pixel (a part of a patch, (S, rows g, cols g) nodes: (S, rows, cols)). The node fields are saved for
    backward by torch (freed after it unless ``retain_graph``)."""

    @staticmethod
    def forward(ctx, u, u_w, gauss_nodes, pixel_mm, size, rw=None):
        from rwwarp.wave.focal import pixel_flux, pixel_power
        xp, a = _xp_of(u.to(torch.complex128))
        b = None if u_w is None else _xp_of(u_w.to(torch.complex128))[1]
        with _on_streams(rw):
            out = (pixel_power(a, gauss_nodes, pixel_mm, size, xp=xp) if b is None
                   else pixel_flux(a, b, gauss_nodes, pixel_mm, size, xp=xp))
            out = _from_xp(out, u.device)
        ctx.args, ctx.rw = (int(gauss_nodes), float(pixel_mm)), rw
        ctx.devices = (u.device, None if u_w is None else u_w.device)
        ctx.save_for_backward(u.to(torch.complex128), None if u_w is None else u_w.to(torch.complex128))
        return out

    @staticmethod
    def backward(ctx, grad):
        from rwwarp.wave.focal import pixel_flux_adjoint, pixel_power_adjoint
        ua, ub = ctx.saved_tensors
        xp, a = _xp_of(ua)
        b = None if ub is None else _xp_of(ub)[1]
        _, g = _xp_of(grad.to(torch.float64))
        with _on_streams(ctx.rw):
            if b is None:
                ga, gb = pixel_power_adjoint(a, g, *ctx.args, xp=xp), None
            else:
                ga, gb = pixel_flux_adjoint(a, b, g, *ctx.args, xp=xp)
            ga = _from_xp(ga, ctx.devices[0]) if ctx.needs_input_grad[0] else None
            gb = _from_xp(gb, ctx.devices[1]) if gb is not None and ctx.needs_input_grad[1] else None
        return ga, gb, None, None, None, None


def node_pixels(u, rw, gauss_nodes=None):
    """:class:`NodePixels` of the node field ``u`` (a tensor, or the pair ``(U, U_w)`` for pixel_values "flux")
    with ``rw``'s pixel pitch (mm), patch size and Gauss nodes (``gauss_nodes`` overrides them)."""
    g = rw.gauss_nodes if gauss_nodes is None else gauss_nodes
    a, b = u if isinstance(u, tuple) else (u, None)
    return NodePixels.apply(a, b, g, rw.pixel, rw.size, rw)


def _distance_value(distance, distance_host, m):
    """The distance (mm) the operator is built for: a float, or with different values per source an (S,) array for a
    method with ``per_source_distances`` (else an error naming the method); None for the RayWave's own.
    ``distance_host`` (a float or one per source) is read instead of the device's ``distance``."""
    if distance_host is None and distance is None:
        return None
    if distance_host is not None:
        zs = np.asarray(distance_host, dtype=np.float64).reshape(-1)
    else:
        zs = distance.detach().to("cpu", torch.float64).reshape(-1).numpy()
    if np.all(zs == zs[0]):
        return float(zs[0])
    if not getattr(m, "per_source_distances", False):
        raise ValueError(f"propagation method {m.name!r} propagates a batch over one distance, got different ones "
                         f"per source ({zs.min():.6g} .. {zs.max():.6g} mm); one lens has one sensor distance")
    return zs.copy()


def operator_propagate(field, distance, rw, distance_host=None, precision="double", method=None, phi0=None,
                       tile_px=None):
    """Power per sensor pixel (S, size, size) of ``rw`` (a :class:`~rwwarp.wave.raywave.RayWave`) from its
    wave-plane field through its method's operator (:meth:`~rwwarp.wave.methods.Propagation.operator` at the
    distance, :class:`OperatorApply`) and the pixel integration ``rw.pixel_values`` names (:class:`NodePixels`):
    the generic differentiable path of any registered method (``method``: its name, default ``rw.plan.method``).

    ``field`` complex (S, n, n), carrier removed; ``distance`` the wave-plane to sensor distance (mm, float64 (S,)
    or 0-d, differentiable; different values per source only for a method with ``per_source_distances``, the ASM)
    or None (the RayWave's own, no gradient); ``distance_host``: its value (mm, a float or one per source) when the
    caller has it on the host (the operator's set-up does not wait for the device); ``precision``
    the operator's ("double" for gradients). ``phi0``: the DOE's relief phase on the windows (rad, (S, n, n),
    differentiable; :meth:`torch_bridge.HybridLens.doe_phase`) or None (no DOE): for a method that takes the field
    with the DOE applied (``doe_in_propagator = False``) or whose operator can leave the planned DOE out
    (``doe_separable``, the ASM: its operator is then built with ``doe=False``) the transmission
    ``exp(1j alpha phi0)`` (``alpha`` the wavelength remap, :func:`torch_bridge.functions.doe_scale`) multiplies
    the field first; a method whose operator applies the planned DOE itself is refused with a phase (its
    gradient would be lost).

    ``tile_px``: evaluate the patch in spatial tiles of ``tile_px`` x ``tile_px`` pixels (methods with
    ``spatial_tiles``, the ASM: each tile keeps the whole patch's band limits, so the result equals the untiled
    one): where a gradient is wanted each tile is a checkpoint (:class:`torch_bridge.functions.Recompute`) that
    keeps no node field and recomputes its tile in backward, so the output side's memory (nodes, DFT factors) is
    one tile's. None: one call."""
    from rwwarp.wave.methods import get

    from .functions import Recompute, backend_for, doe_scale, spatial_tiles, upload
    m = get(rw.plan.method if method is None else method)
    if field.device.type == "cuda":
        backend_for(rw.device)   # the release hook: a failed propagation allocation empties torch's cache first
    if (field.device.type == "cuda") != str(rw.tracer.device).startswith("cuda"):
        # the operator works in its plan's array namespace (numpy for a CPU plan, CuPy for CUDA)
        raise ValueError(f"{m.name} propagation: the field is on {field.device} but its RayWave was planned "
                         f"on {rw.tracer.device}; plan on the field's device (HybridLens.to(device))")
    separate = m.doe_in_propagator and getattr(m, "doe_separable", False)
    if phi0 is not None:
        if m.doe_in_propagator and not separate:
            raise ValueError(f"propagation method {m.name!r} applies the planned DOE inside its operator, so the "
                             f"DOE phase cannot be differentiated through it: set doe_in_propagator = False (the "
                             f"bridge then applies exp(1j alpha phi0) to the field) or doe_separable")
        alpha = upload(doe_scale(rw), torch.float64, phi0.device)
        field = field * torch.exp(1j * alpha[:, None, None] * phi0)
    z = _distance_value(distance, distance_host, m)
    pair = rw.pixel_values == "flux"
    tiles = spatial_tiles(rw.size, tile_px)
    if tiles != [None] and not getattr(m, "spatial_tiles", False):
        raise ValueError(f"propagation method {m.name!r} has no spatial tiles (its operator takes no tile=); "
                         f"propagate without spatial_tile")
    kw = {"doe": False} if separate else {}

    def run(f, d, tile=None, record=True):
        with _streams(rw):
            op = m.operator(rw, z, precision, **kw) if tile is None else m.operator(rw, z, precision, tile=tile, **kw)
        if pair and not hasattr(op, "forward_pair"):
            raise ValueError(f"propagation method {m.name!r}: pixel_values='flux' needs its operator's forward_pair "
                             f"and adjoint_pair (the field and its direction-cosine-weighted field); plan with "
                             f"pixel_values='intensity' or implement them")
        with (contextlib.nullcontext() if record else torch.no_grad()):
            return node_pixels(OperatorApply.apply(f, d, op, pair, rw, m.name, True), rw)

    if tiles == [None]:
        return run(field, distance)
    wants = torch.is_grad_enabled() and (field.requires_grad or (distance is not None and distance.requires_grad))
    parts = []
    for t in tiles:
        if not wants:
            parts.append(run(field, distance, t, record=False))
        elif distance is None:
            parts.append(Recompute.apply(lambda f, record, t=t: run(f, None, t, record), field))
        else:
            parts.append(Recompute.apply(lambda f, d, record, t=t: run(f, d, t, record), field, distance))
    n_col = len({(t[2], t[3]) for t in tiles})
    rows = [torch.cat(parts[k:k + n_col], dim=2) for k in range(0, len(parts), n_col)]
    return torch.cat(rows, dim=1)
