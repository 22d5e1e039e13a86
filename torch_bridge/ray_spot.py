"""The ray model of end-to-end design, differentiable in torch: :class:`RaySpot` and the paraxial helpers.

Rays are traced by Warp to the DOE plane (differentiable through a tape), bent there by the DOE as a
local grating (first order: ``n' t' = n t + lambda/(2 pi) grad phi0``), then straight to the sensor.
Their polychromatic RMS spot radius (about the polychromatic centroid, Zemax's default) is the
"Zemax" merit function of the comparison design; :func:`paraxial_efl` and :func:`paraxial_achromat`
give the paraxial focal length and the paraxial achromatic DOE.

Units: mm, um for wavelengths, degrees for fields, radians for DOE coefficients.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from rwwarp.trace import COLUMNS as COL

__all__ = ["RaySpot", "paraxial_achromat", "paraxial_efl"]

# ---------------------------------------------------------------------------------------------- ray model
class _TraceToPlane(torch.autograd.Function):
    """Parameter table -> ray positions and directions on the DOE plane, (S, N, 3) each, through a
    ``wp.Tape`` (backward replays it)."""

    @staticmethod
    def forward(ctx, table, tracer, src, u, v, upto):
        import warp as wp
        tab = table.detach().cpu().numpy()
        for row, arr in zip(tab, tracer.params):
            arr.assign(np.ascontiguousarray(row, dtype=tracer.np_dtype))
        tape = wp.Tape()
        with tape:
            rays = tracer.run(src, u, v, 1.0, upto=upto)
        S, N = rays.n_sources, rays.n_pupil
        pos = torch.from_numpy(rays.pos.numpy().astype(np.float64).reshape(S, N, 3))
        dr = torch.from_numpy(rays.dir.numpy().astype(np.float64).reshape(S, N, 3))
        ctx.tape, ctx.rays, ctx.tracer, ctx.shape = tape, rays, tracer, (S, N)
        ctx.tab = tab
        valid = torch.from_numpy(rays.valid.numpy().reshape(S, N).astype(bool))
        ctx.mark_non_differentiable(valid)
        return pos.to(table.device), dr.to(table.device), valid

    @staticmethod
    def backward(ctx, g_pos, g_dir, g_valid):
        import warp as wp
        tr, rays = ctx.tracer, ctx.rays
        for row, arr in zip(ctx.tab, tr.params):
            arr.assign(np.ascontiguousarray(row, dtype=tr.np_dtype))
        vec = rays.pos.dtype
        gp = wp.array(g_pos.detach().cpu().numpy().reshape(-1, 3).astype(tr.np_dtype), dtype=vec, device=tr.device)
        gd = wp.array(g_dir.detach().cpu().numpy().reshape(-1, 3).astype(tr.np_dtype), dtype=vec, device=tr.device)
        ctx.tape.backward(grads={rays.pos: gp, rays.dir: gd})
        grads = np.stack([p.grad.numpy().astype(np.float64) for p in tr.params])
        ctx.tape.zero()
        return torch.from_numpy(grads).to(g_pos.device), None, None, None, None, None


def _doe_gradient(prof, values: torch.Tensor, design_wavelength_um: float, x, y):
    """Gradient (d phi0/dx, d phi0/dy) in rad/mm of a smooth DOE (any kind of ``rwwarp.doe.SMOOTH_KINDS``) at
    (x, y) mm from its learnable ``values`` (:func:`rwwarp.doe.profile_gradient` in torch, the function
    :meth:`rwwarp.doe.Profile.gradient` evaluates: differentiable in the values and the coordinates)."""
    from rwwarp.doe import profile_gradient
    return profile_gradient(prof.kind, values, x, y, norm_radius=prof.norm_radius,
                            design_wavelength_um=design_wavelength_um, xp=torch)


class RaySpot:
    """Polychromatic RMS spot radius of a :class:`~torch_bridge.HybridLens` with the ray model
    (the DOE as a local grating, first order), differentiable in every learning quantity.

    ``fields_deg``: node fields (deg); ``wavelengths_um``: the polychromatic set (equal weights);
    ``grid``: pupil samples across the diameter (square grid clipped to the pupil). :meth:`rms`
    returns (n_fields,) radii in mm; :meth:`rms_per_wavelength` (n_fields, n_wavelengths) about each
    colour's own centroid.

    ``device``: where the rays are traced and the spot computed (a torch device or its name); default
    the module's. On a GPU the trace (Warp, CUDA) and the torch arithmetic stay there: the spot's
    ~10^4-10^5 rays are too few for the CPU's threads, which slow down by several times when the host's
    cores are shared (a 300-step RMS design of the Cooke hybrid's gpu preset: 0.19 s a step with one
    torch thread, 1.3 s with two on a 2-core host running other work).
    """

    def __init__(self, module, fields_deg, wavelengths_um, grid: int = 31, object_distance_mm=None,
                 device=None):
        self.module, self.fields, self.wls, self.grid = module, list(fields_deg), [float(w) for w in
                                                                                wavelengths_um], int(grid)
        self.object_distance_mm = object_distance_mm
        self.device = None if device is None else torch.device(device)

    def _hits(self):
        from rwwarp.trace import Tracer, pupil_grid
        lens = self.module.to_lens()
        plane = lens.wave_plane_index()
        values = self.module.values()
        dev = self.device or values["thickness"].device
        if dev.type == "cuda":
            wp_dev = f"cuda:{torch.cuda.current_device() if dev.index is None else dev.index}"
        elif dev.type == "cpu":
            wp_dev = "cpu"
        else:
            raise ValueError(f"RaySpot: device {dev} is not supported (cpu or cuda)")
        tr = Tracer(lens, self.wls, device=wp_dev, dtype="float64", requires_grad=True)
        nf, nw = len(self.fields), len(self.wls)
        fl = [f for f in self.fields for _ in range(nw)]
        wi = [j for _ in self.fields for j in range(nw)]
        src = tr.sources(fl, wi, object_distance=self.object_distance_mm)
        u, v, _ = pupil_grid(self.grid, src["shape"])

        from .functions import bridge_state
        bridge_state(tr)["base_table"] = tr.params_np.copy()
        table = self.module.param_table(tr, values).to(dev)
        pos, dr, valid = _TraceToPlane.apply(table, tr, src, u, v, plane + 1)  # validity: not differentiated
        valid = valid.to(dev)
        from rwwarp.ray_model import grating_to_sensor
        lam = torch.tensor([w * 1e-3 for w in self.wls] * nf, dtype=torch.float64, device=dev)[:, None]
        n_after = torch.tensor([lens.indices(w)[plane] for w in self.wls] * nf, dtype=torch.float64,
                               device=dev)[:, None]
        s = lens.surfaces[plane]
        grad = None
        if s.type == "doe":
            from rwwarp import doe as rdoe
            prof = rdoe.profile_from_dict(s.profile)
            grad = _doe_gradient(prof, values["doe"].to(dev), s.design_wavelength_um, pos[..., 0], pos[..., 1])
        # rwwarp's grating step and transfer, in torch (the sensor z learns with the table)
        hx, hy, ok = grating_to_sensor(pos, dr, n_after, lam, grad, table[-1, COL.z], torch)
        ok = valid & ok
        return hx.reshape(nf, nw, -1), hy.reshape(nf, nw, -1), ok.reshape(nf, nw, -1)

    def rms(self) -> torch.Tensor:
        """Polychromatic RMS radius (mm) about the polychromatic centroid, (n_fields,)."""
        hx, hy, ok = self._hits()
        w = ok.to(hx.dtype)
        n = w.sum((1, 2)).clamp_min(1.0)
        cx = (hx * w).sum((1, 2)) / n
        cy = (hy * w).sum((1, 2)) / n
        r2 = ((hx - cx[:, None, None]) ** 2 + (hy - cy[:, None, None]) ** 2) * w
        return torch.sqrt(r2.sum((1, 2)) / n)

    def centroids(self) -> np.ndarray:
        """Polychromatic centroid (mm) of the valid rays on the sensor, (n_fields, 2) numpy."""
        hx, hy, ok = self._hits()
        w = ok.to(hx.dtype)
        n = w.sum((1, 2)).clamp_min(1.0)
        return torch.stack([(hx * w).sum((1, 2)) / n, (hy * w).sum((1, 2)) / n], 1).detach().cpu().numpy()

    def rms_per_wavelength(self) -> torch.Tensor:
        """RMS radius (mm) of each wavelength about its own centroid, (n_fields, n_wavelengths)."""
        hx, hy, ok = self._hits()
        w = ok.to(hx.dtype)
        n = w.sum(2).clamp_min(1.0)
        cx = (hx * w).sum(2) / n
        cy = (hy * w).sum(2) / n
        return torch.sqrt((((hx - cx[..., None]) ** 2 + (hy - cy[..., None]) ** 2) * w).sum(2) / n)


# ---------------------------------------------------------------------------------------------- paraxial
def paraxial_efl(module, wavelength_um: float) -> torch.Tensor:
    """Paraxial EFL (mm) of a :class:`~torch_bridge.HybridLens` as a differentiable tensor (y-nu trace
    with the current curvatures and thicknesses, DOE power ``-lambda a2 / pi`` of any smooth kind:
    :func:`rwwarp.paraxial.diffractive_power` of :func:`rwwarp.doe.profile_quadratic`; a pixel map adds none;
    a phase surface's ``-m lambda A_1 / (pi R^2)`` from the current ``phase`` values)."""
    from rwwarp import paraxial
    from rwwarp.doe import SMOOTH_KINDS, profile_quadratic

    from .phase_params import phase_mask, phase_powers
    lens = module.lens_template
    v = module.values()
    n = paraxial.signed_indices(lens, wavelength_um)
    n_before = np.concatenate([[paraxial.object_index(lens, wavelength_um)], n[:-1]])
    powers = []
    for i, s in enumerate(lens.surfaces):
        if s.type == "standard":
            P = (n[i] - n_before[i]) * v["curvature"][i]
        elif s.type == "thin_lens":
            P = torch.tensor(1.0 / s.focal_length, dtype=torch.float64)
        elif s.type == "doe" and module.doe_kind in SMOOTH_KINDS:
            # rwwarp.paraxial.doe_power in torch: the phase's r^2 term, the first order's power
            a2 = profile_quadratic(module.doe_kind, v["doe"], norm_radius=s.profile.get("norm_radius"),
                                   design_wavelength_um=s.design_wavelength_um)
            P = torch.as_tensor(paraxial.diffractive_power(a2, wavelength_um), dtype=torch.float64)
        else:
            P = torch.zeros((), dtype=torch.float64)
        powers.append(P)
    if any(phase_mask(lens)):   # a standard surface's diffractive phase adds -m lambda A_1 / (pi R^2)
        ph = phase_powers(lens, v["phase"], wavelength_um)
        powers = [P + ph[i] for i, P in enumerate(powers)]
    one = torch.ones((), dtype=torch.float64)
    _, _, nus = paraxial.ynu_steps(powers, v["thickness"], n, one, 0.0 * one)
    return -1.0 / nus[-1]


def paraxial_achromat(lens, wavelengths_um, doe_kind: str = "even_poly"):
    """The paraxial achromatic DOE (analytic): a Fresnel (quadratic) phase whose power
    ``P(lambda) = -lambda a1 / (pi R^2)`` best cancels the refractive part's focal shift at the DOE plane.

    With ``V(lambda)`` the paraxial vergence (1/mm) of the refractive image seen from the DOE plane,
    the DOE makes it ``V + beta lambda`` (``beta = -a1 / (pi R^2)``); least squares over the wavelengths
    for a constant ``V0`` gives ``beta = -cov(V, lambda) / var(lambda)`` and the sensor goes to
    ``1 / V0`` behind the DOE. Returns ``(coefficient, sensor_distance_mm)``: the phase coefficient
    (rad) of ``rho^2`` (``even_poly`` index 0, ``poly`` index 1) and the DOE-to-sensor distance.
    """
    from rwwarp import paraxial
    plane = lens.wave_plane_index()
    s = lens.surfaces[plane]
    if s.type != "doe":
        raise ValueError("the lens has no DOE")
    lam = np.array([float(w) * 1e-3 for w in wavelengths_um])
    V = []
    blank = lens.with_surface(plane, profile={**s.profile, "coefficients": [0.0] * len(s.profile["coefficients"])})
    for w in wavelengths_um:
        ys, nus = paraxial.ynu_trace(blank, float(w), 1.0, 0.0)
        n_pl = blank.indices(float(w))[plane]
        V.append(-nus[plane - 1] / (ys[plane] * n_pl) if plane > 0 else 0.0)
    V = np.array(V)
    beta = -np.cov(V, lam, bias=True)[0, 1] / np.var(lam)
    V0 = float(np.mean(V + beta * lam))
    R = float(s.profile["norm_radius"])
    a1 = -beta * math.pi * R * R
    return float(a1), 1.0 / V0


def with_paraxial_achromat(lens, wavelengths_um):
    """``lens`` with its DOE set to :func:`paraxial_achromat` over ``wavelengths_um`` (um): the quadratic
    coefficient (rad; ``even_poly`` index 0, ``poly`` index 1), every other coefficient 0, and, when the DOE is
    the last surface, its distance to the sensor (mm) at the achromat's focus. ``lens`` is not changed."""
    d = lens.doe_index
    s = lens.surfaces[d]
    a, dist = paraxial_achromat(lens, list(wavelengths_um))
    coeffs = [0.0] * len(s.profile["coefficients"])
    coeffs[0 if s.profile["kind"] == "even_poly" else 1] = a
    lens = lens.with_surface(d, profile={**s.profile, "coefficients": coeffs})
    if d == len(lens.surfaces) - 1:
        lens = lens.with_surface(d, thickness=dist)
    return lens
