"""``asm``: the band-limited angular spectrum over the whole beam (:mod:`rwwarp.wave.propagate`,
:class:`rwwarp.wave.propagate_sensor.SensorPropagator`): its planning (the wave-plane Nyquist pitch, window,
padded FFT and ray grid; ``plan="auto"``, ``"paper"`` or an explicit :class:`~rwwarp.wave.plan.Plan`), its cost
and its pixels. Lengths in mm."""
from __future__ import annotations

import math

import numpy as np

from .registry import Planned, Propagation, register


def wave_plane_nyquist(ctx):
    """``(nyq_pitch, need_pitch, reasons)``: the wave-plane pitch (mm) the field's local frequencies (carrier
    removed) and the DOE's allow, the pitch after ``nyquist_safety`` and the DOE feature size, and why."""
    nyq_pitch = float(np.min(1.0 / (2.0 * (ctx.fmax + ctx.f_doe + 1e-9))))
    need_pitch = nyq_pitch / ctx.nyquist_safety
    reasons = [f"Nyquist of the field (carrier removed) and DOE: max local frequency "
               f"{np.max(ctx.fmax + ctx.f_doe):.4g} cycles/mm -> pitch <= {nyq_pitch * 1e3:.4g} um, / safety "
               f"{ctx.nyquist_safety} for edge diffraction -> {need_pitch * 1e3:.4g} um"]
    feature = ctx.feature
    if feature is not None:
        if feature / 2.0 < need_pitch:
            reasons.append(f"DOE feature size {feature * 1e3:.4g} um -> pitch <= half of it")
        need_pitch = min(need_pitch, feature / 2.0)
    return nyq_pitch, need_pitch, reasons


def plan_window(ctx) -> Planned:
    """The wave-plane sampling of the whole beam (the ASM's plan): ``plan="auto"`` (Nyquist pitch, footprint
    window, FFT padded for the band limit, rays per sample), ``"paper"`` (the whole DOE aperture at half its
    feature size, padded 2x, 1000^2 rays) or an explicit :class:`~rwwarp.wave.plan.Plan` (checked, warnings)."""
    from ..plan import Plan, auto_sizes, check_explicit, nice_fft_length
    nyq_pitch, need_pitch, reasons = wave_plane_nyquist(ctx)
    plan, width, lo, hi = ctx.plan, ctx.width, ctx.lo, ctx.hi
    window = width + 2.0 * ctx.pilot_cell
    if isinstance(plan, Plan):
        pl = plan
        check_explicit(pl, nyq_pitch, nice_fft_length(math.ceil((window + ctx.out_width) / pl.pitch_mm) + 4), window)
    elif plan == "auto":
        pitch, n_grid, n_pad, ray_grid = auto_sizes(need_pitch, width, ctx.feature, ctx.out_width, ctx.rays_per_sample)
        reasons += [f"window = beam footprint {width:.4g} mm + 2 pilot cells -> {n_grid} samples",
                    f"padding: max(2 x window, window + sensor patch {ctx.out_width:.4g} mm) (band limit) -> FFT {n_pad}",
                    f"rays: {ctx.rays_per_sample} per sample per axis -> {ray_grid} across the pupil"]
        pl = Plan(pitch, n_grid, n_pad, ray_grid, "auto", False, reasons)
    elif plan == "paper":
        s = ctx.lens.surfaces[ctx.plane]
        half = s.semi_diameter or float(np.max(np.abs(np.concatenate([lo, hi]))))
        pitch = (ctx.feature or 2 * need_pitch) / 2.0
        n_grid = int(round(2 * half / pitch))
        pl = Plan(pitch, n_grid, 2 * n_grid, 1000, "paper", False,
                  ["paper: whole DOE aperture at half the DOE feature size, padded 2x, 1000x1000 pupil rays "
                   "(10^6)"])
        lo = np.full_like(lo, -half)
        hi = np.full_like(hi, half)
    else:
        raise ValueError(f"plan must be 'auto', 'paper' or a Plan, got {plan!r}")
    centers = ctx.centers
    if ctx.center_mm is None:
        centers, why = doe_landing_centres(ctx)
        if why:
            pl = pl.with_reasons(why)
    return Planned(pl, ctx.carrier, centers, lo, hi)


def doe_landing_centres(ctx):
    """``(centers, reason)``: the patch centres ((S, 2) mm, snapped to pixels) where the beam lands after the DOE on
    the wave plane, as the focal method centres its patches (:func:`rwwarp.wave.methods.main_order.main_order_centres`:
    the chief ray on the DOE's main order, its local frequency added to the ray's; so the patch does not move with
    the method "auto" chooses). None, blank or a pixel map (steps, no gradient to deflect the rays by): the chief
    rays' landings ``ctx.centers`` and an empty reason."""
    from ...doe import is_flat_profile
    from .main_order import doe_orders, main_order_centres
    s = ctx.lens.surfaces[ctx.plane]
    if s.type != "doe" or is_flat_profile(s.profile) or s.profile.get("kind") == "pixel_map":
        return ctx.centers, ""
    f_c = doe_orders(ctx)[3]
    centers = main_order_centres(ctx, f_c)
    moved = np.hypot(*(centers - np.asarray(ctx.centers, float)).T)
    if not np.any(moved > 0):
        return ctx.centers, ""
    return centers, (f"patch centred where the chief ray lands on the DOE's main order (as the focal method): "
                     f"{int(np.sum(moved > 0))} source(s) moved up to {float(moved.max()) * 1e3:.4g} um from its "
                     f"landing without the DOE (rwwarp.wave.methods.asm.doe_landing_centres)")


def wave_plane_cost(plan, n_sources: int):
    """``(memory_bytes, flops)`` of a batch's trace, splat and field (shared by the methods that form one):
    ~232 bytes and ~4000 flops a ray, ~64 bytes a wave-plane sample (:func:`rwwarp.wave.plan.estimate_cost`)."""
    S = int(n_sources)
    rays = S * plan.ray_grid ** 2
    n2 = plan.n_grid ** 2
    return rays * 232 + S * n2 * 64, rays * 4000.0


@register
class AngularSpectrum(Propagation):
    """The band-limited (shifted, Matsushima) angular spectrum over the whole beam's padded FFT, a matrix DFT
    to the pixels' Gauss nodes (:class:`rwwarp.wave.propagate_sensor.SensorPropagator`); the DOE phase goes in
    with the field (its operator applies the planned one, or leaves it to the caller: ``doe=False``, which
    :mod:`torch_bridge` uses to differentiate the DOE phase)."""

    name = "asm"
    torch_path = "operator"
    doe_in_propagator = True
    doe_separable = True
    spatial_tiles = True
    per_source_distances = True
    fft_padded = True

    def plan(self, ctx):
        return plan_window(ctx)

    def estimate(self, plan, n_sources, size, gauss_nodes):
        S, m = int(n_sources), int(size) * int(gauss_nodes)
        mem, flops = wave_plane_cost(plan, S)
        npd = plan.n_pad
        mem += S * (2 * npd * npd * 16 + 2 * npd * m * 16 + m * m * 16)
        flops += S * (5.0 * npd * npd * math.log2(max(npd * npd, 2)) + 8.0 * (npd * npd * m + npd * m * m))
        return {"memory_bytes": int(mem), "flops": float(flops)}

    def explain_grids(self, plan):
        return super().explain_grids(plan) + f"FFT {plan.n_pad}^2, "

    def operator(self, rw, distance_mm=None, precision="double", doe=True, tile=None):
        """:class:`AsmOperator` of ``rw`` over ``distance_mm`` (mm; None: the lens's); ``doe=False`` leaves the
        planned DOE out (the field comes with it applied); ``tile = (r0, r1, c0, c1)``: those sensor pixel rows /
        columns only, with the whole patch's band limits (equal to those pixels of the whole patch)."""
        return AsmOperator(rw, distance_mm, doe=doe, tile=tile)

    def pixels(self, rw, field, precision="double", to_host=True):
        phi0, scale = rw.doe_phase()
        return rw.intensity(field, phi0, scale, to_host=to_host)


class AsmOperator:
    """The ASM's linear map, wave-plane field (S, n, n) (carrier removed, wave step applied; the DOE phase of
    ``rw`` applied inside unless ``doe=False``) -> the field at the pixels' Gauss nodes (S, size g, size g),
    carrier restored (:class:`rwwarp.wave.propagate.PointPropagator`), over ``distance_mm`` (mm, a float or one
    per source; default the lens's). ``tile = (r0, r1, c0, c1)``: the nodes of those sensor pixel rows / columns
    only (S, (r1 - r0) g, (c1 - c0) g), with the whole patch's window centre (so its band limits, and its values,
    are the whole patch's). Arrays in and out are of the operator's namespace ``xp``: numpy on the CPU and OpenCL
    devices (the OpenCL result is copied to the host), CuPy on CUDA (device memory, no copy).
    :meth:`distance_derivative` is the exact d/dz at the fixed band limits (``dH/dz = 2 pi i w H``); the ``*_pair``
    methods add the direction-cosine-weighted field ``U_w`` (pixel_values "flux"). ``keep_for_backward``: it holds
    only its geometry (the FFT plans and work arrays are the backend's caches), so an autograd Function may keep
    it."""

    keep_for_backward = True

    def __init__(self, rw, distance_mm=None, doe=True, tile=None):
        from .. import backend as bk
        from ..propagate import PointGeometry, PointPropagator
        from ..propagate_setup import _center_extent
        from .registry import gauss_nodes_xy
        self.rw = rw
        self.be = bk.get_backend(rw.device)
        if self.be.kind == "cuda":
            import cupy
            self.xp = cupy
        else:
            self.xp = np
        z = float(rw.z_sensor - rw.z_plane) if distance_mm is None else distance_mm
        self.z = np.broadcast_to(np.asarray(z, dtype=np.float64), (rw.nsrc,)).copy()   # mm, one per source
        nx, ny = gauss_nodes_xy(rw)
        phi0, scale = rw.doe_phase() if doe else (None, None)
        self.phi0 = phi0
        center = None
        if tile is not None:
            r0, r1, c0, c1 = (int(t) for t in tile)
            size = int(rw.size)
            if not (0 <= r0 < r1 <= size and 0 <= c0 < c1 <= size):
                raise ValueError(f"AsmOperator: tile {tuple(tile)} is not inside the {size} x {size} pixel patch")
            g = int(rw.gauss_nodes)
            center = _center_extent(nx, ny)[0]          # the whole patch's window centre
            nx = np.ascontiguousarray(nx[:, c0 * g:c1 * g])
            ny = np.ascontiguousarray(ny[:, r0 * g:r1 * g])
        self.tile = None if tile is None else (r0, r1, c0, c1)
        lam_um = np.array(rw.wls, dtype=np.float64) / rw.n_after       # in the medium after the plane
        self._dz = 2j * np.pi / (lam_um * 1e-3)                          # 2 pi i / lambda (rad/mm), (S,)
        geo = PointGeometry(rw.plan.pitch_mm, rw.origin, lam_um, self.z,
                            nx, ny, doe_scale=scale, carrier_cpmm=rw.carrier, pad_to=rw.plan.n_pad,
                            window_center_mm=center)
        self.prop = PointPropagator(self.be, geo)

    def forward(self, field):
        """The field at the nodes (S, My, Mx) of ``xp``."""
        return self._out(self.prop.forward(self._dev(field), self.phi0))

    def forward_pair(self, field):
        """``(U, U_w)`` at the nodes (S, My, Mx) of ``xp``: the field and the field of its direction-cosine-weighted
        band spectrum (``c = k_z / k``; pixel_values "flux" integrates ``Re(conj(U) U_w)``), one band spectrum."""
        return tuple(self._out(a) for a in self.prop.forward_weighted(self._dev(field), self.phi0, (0, 1)))

    def adjoint(self, grad):
        """``A^H grad``: (S, My, Mx) -> (S, n, n) of ``xp`` (the map is linear in the field)."""
        g, _ = self.prop.adjoint(self._dev(grad), self._zero(), self.phi0)
        return self._out(g)

    def adjoint_pair(self, grad_u, grad_w):
        """``A^H grad_u + A_w^H grad_w`` (S, n, n) of ``xp``: the adjoint of :meth:`forward_pair`."""
        g, _ = self.prop.adjoint(self._dev(grad_u), self._zero(), self.phi0, grad_weighted=self._dev(grad_w))
        return self._out(g)

    def distance_derivative(self, field):
        """``d forward(field) / d distance_mm`` (S, My, Mx) of ``xp``: the transfer function's exact derivative
        ``2 pi i w H`` (``w = c / lambda``, :meth:`~rwwarp.wave.propagate.PointPropagator.forward_weighted`), the
        band limits and nodes held fixed (they move with z in jumps of zero derivative almost everywhere)."""
        u_w = self._out(self.prop.forward_weighted(self._dev(field), self.phi0))
        return u_w * self.xp.asarray(self._dz)[:, None, None]

    def distance_derivative_pair(self, field):
        """``(dU/dz, dU_w/dz)`` (mm^-1) of :meth:`forward_pair`: ``(2 pi i / lambda) (U_w, U_ww)``, ``U_ww`` the field
        of ``c^2`` times the band spectrum (the band limits and nodes held fixed)."""
        dz = self.xp.asarray(self._dz)[:, None, None]
        return tuple(self._out(a) * dz for a in self.prop.forward_weighted(self._dev(field), self.phi0, (1, 2)))

    def distance_derivative_phase_free(self, field):
        """``d [exp(-2 pi i z / lambda) forward(field)] / d distance_mm`` (S, My, Mx) of ``xp``: the distance
        derivative without its constant phase's term ``(2 pi i / lambda) forward``
        (``(2 pi i / lambda) F^-1[(c - 1) C]``, ``c - 1`` formed without cancellation), which a loss invariant to a constant phase per source (pixel powers and
        fluxes) does not see; that term is ``1 / (1 - c)`` times the rest near the axis, so its rounding would
        dominate (:class:`torch_bridge.operator_function.OperatorApply` uses this form)."""
        u = self._out(self.prop.forward_weighted(self._dev(field), self.phi0, (1,), minus_one=True))
        return u * self.xp.asarray(self._dz)[:, None, None]

    def distance_derivative_pair_phase_free(self, field):
        """:meth:`distance_derivative_pair` without the constant phase's term (as
        :meth:`distance_derivative_phase_free`): ``(2 pi i / lambda) F^-1[(c - 1) C, c (c - 1) C]``."""
        dz = self.xp.asarray(self._dz)[:, None, None]
        return tuple(self._out(a) * dz for a in self.prop.forward_weighted(self._dev(field), self.phi0, (1, 2),
                                                                           minus_one=True))

    def adjoint_distance(self, grads, field, need_field=True):
        """The adjoint and the distance's gradient in one pass, for a loss that does not see a constant phase per
        source (pixel powers and fluxes): ``(A^H g or None, dL/dz)`` with ``grads`` the output's gradient(s)
        (``(g,)``, or ``(g_u, g_w)`` for :meth:`forward_pair`) and ``field`` the forward call's; ``dL/dz`` (S,) of
        ``xp`` (loss units per mm) is ``Re sum conj(g) dU/dz`` without the constant phase's term, as
        :meth:`distance_derivative_phase_free` gives it
        (:meth:`~rwwarp.wave.propagate.PointPropagator.distance_adjoint`: the band's gradient contracted with the
        band spectrum, no node field formed)."""
        gw = self._dev(grads[1]) if len(grads) > 1 else None
        g, _, gd = self.prop.distance_adjoint(self._dev(grads[0]), self._dev(field), self.phi0, grad_weighted=gw,
                                              need_field=need_field)
        return (None if g is None else self._out(g)), self.xp.asarray(gd)

    def _zero(self):
        n = self.rw.plan.n_grid
        return self._dev(self.xp.zeros((self.rw.nsrc, n, n), np.complex128))

    def _out(self, a):
        return a if self.xp is not np else np.asarray(self.be.to_host(a))

    def _dev(self, a):
        if self.xp is not np:
            return self.be.to_device(a, np.complex128)
        a = np.ascontiguousarray(a, np.complex128)
        return self.be.wrap_host(a) if hasattr(self.be, "wrap_host") else self.be.to_device(a)
