"""Phase surfaces (:mod:`rwwarp.phase_surface`: a diffractive phase on a refracting surface) in
:class:`~torch_bridge.HybridLens`: their coefficients as the learnable quantity ``phase``.

``phase`` is a ``(n_surfaces, MAX_PHASE_TERMS)`` float64 tensor (``MAX_PHASE_TERMS`` = 8): row ``i`` holds the
even-polynomial coefficients ``A_1 .. A_8`` (rad, the phase per unit order at ``rho = r / R = 1``, ``R`` the
surface's normalisation radius in mm) of ``phi = sum_k A_k rho^(2 k)`` on surface ``i``; rows of surfaces
without a phase are 0 and cannot learn. Learn entries are ``(surface, k)`` pairs (``k = 0``: ``A_1``, the
``rho^2`` term, which sets the paraxial power ``-m lambda A_1 / (pi R^2)``) or ``"all"`` (every term of every
phase surface). A ``fresnel`` phase of focal length f enters as ``R = 1 mm``, ``A_1 = -pi / (lambda0 f)``
(:func:`rwwarp.phase_surface.phase_profile`). The order ``m`` and ``R`` stay fixed.

The values reach the tracer's parameter table (columns ``COLUMNS.phase0 ..``) through
:meth:`HybridLens.param_table`, so the Warp tape differentiates the grating equation and the path
``m lambda phi / 2 pi`` of every ray (:mod:`rwwarp.kernels.trace`, ``phase_surface_kernel``); their paraxial
power enters the torch y-nu trace of the thin-lens conjugates and :func:`torch_bridge.ray_spot.paraxial_efl`.
The refracting part of a phase surface (curvature, conic, aspheric, thickness) learns as on any ``standard``
surface. :meth:`HybridLens.to_lens` writes the coefficients back (:func:`exported_phase`).
"""
from __future__ import annotations

import math

import numpy as np
import torch
from rwwarp.phase_surface import MAX_PHASE_TERMS, phase_profile
from rwwarp.trace import COLUMNS as COL

__all__ = ["phase_mask", "phase_base", "phase_indices", "write_phase_columns", "phase_powers", "exported_phase"]


def phase_mask(lens) -> list:
    """Per surface of ``lens``: True where it carries a diffractive phase (a ``standard`` surface with ``phase``)."""
    return [s.type == "standard" and getattr(s, "phase", None) is not None for s in lens.surfaces]


def phase_base(lens) -> np.ndarray:
    """``(n_surfaces, MAX_PHASE_TERMS)`` float64: each phase surface's coefficients ``A_1 ..`` (rad at its
    normalisation radius; a ``fresnel`` phase as its ``A_1``), 0 elsewhere."""
    out = np.zeros((len(lens.surfaces), MAX_PHASE_TERMS))
    for i, on in enumerate(phase_mask(lens)):
        if on:
            _, coeffs = phase_profile(lens.surfaces[i])
            out[i, :len(coeffs)] = coeffs
    return out


def phase_indices(spec, shape, mask) -> torch.Tensor:
    """Flat indices (into the ``(n_surfaces, MAX_PHASE_TERMS)`` table) of the learning ``phase`` entries:
    ``spec`` None (none), ``"all"`` (every term of every phase surface) or a list of ``(surface, k)`` pairs
    (``k = 0`` for ``A_1``). ``mask``: :func:`phase_mask`. Raises ``ValueError`` naming a bad entry."""
    ns, nt = int(shape[0]), int(shape[1])
    if spec is None:
        return torch.zeros(0, dtype=torch.long)
    if isinstance(spec, str):
        if spec != "all":
            raise ValueError(f"learn['phase'] must be 'all' or a list of (surface, k) pairs, got {spec!r}")
        flat = [i * nt + k for i in range(ns) if mask[i] for k in range(nt)]
    else:
        flat = []
        for e in spec:
            if not (isinstance(e, (tuple, list)) and len(e) == 2):
                raise ValueError(f"learn['phase'] entries are (surface, k) pairs (k = 0 for A_1, the rho^2 term), "
                                 f"got {e!r}")
            i, k = int(e[0]), int(e[1])
            if not (0 <= i < ns and 0 <= k < nt):
                raise ValueError(f"learn['phase']: entry {tuple(e)!r} outside ({ns} surfaces, {nt} terms)")
            if not mask[i]:
                raise ValueError(f"learn['phase']: surface {i} carries no diffractive phase (Surface.phase; the "
                                 "flat wave-plane DOE learns as 'doe')")
            flat.append(i * nt + k)
    return torch.tensor(sorted(set(flat)), dtype=torch.long)


def write_phase_columns(cols: list, phase: torch.Tensor, mask: torch.Tensor) -> None:
    """Put the ``phase`` values ``(n_surfaces, MAX_PHASE_TERMS)`` into the parameter-table columns ``cols``
    (a list of ``(n_surfaces + 1,)`` tensors, :meth:`HybridLens.param_table`) on the surfaces of ``mask``
    (bool ``(n_surfaces,)``); other rows keep their column. In place on the list."""
    dev, dt = phase.device, phase.dtype
    on = torch.cat([mask.to(dev), torch.zeros(1, dtype=torch.bool, device=dev)])
    ph = torch.cat([phase, torch.zeros(1, phase.shape[1], dtype=dt, device=dev)])
    for k in range(min(COL.n_phase, phase.shape[1])):
        cols[COL.phase0 + k] = torch.where(on, ph[:, k], cols[COL.phase0 + k])


def phase_powers(lens, phase: torch.Tensor, wavelength_um: float) -> torch.Tensor:
    """Paraxial power (1/mm) each surface's phase adds at ``wavelength_um`` (um), ``(n_surfaces,)``,
    differentiable in ``phase``: ``-m lambda A_1 / (pi R^2)`` (:func:`rwwarp.phase_surface.phase_power`, with
    ``A_1`` from the tensor); 0 on surfaces without a phase."""
    lam = float(wavelength_um) * 1e-3
    scale = np.zeros(len(lens.surfaces))
    for i, on in enumerate(phase_mask(lens)):
        if on:
            s = lens.surfaces[i]
            rnorm, _ = phase_profile(s)
            scale[i] = -float(s.diffraction_order) * lam / (math.pi * rnorm * rnorm)
    return torch.as_tensor(scale, dtype=phase.dtype, device=phase.device) * phase[:, 0]


def exported_phase(surface, values) -> dict:
    """The ``phase`` dict of ``surface`` (a template surface with a phase) for the coefficients ``values``
    (``(MAX_PHASE_TERMS,)`` numbers, rad): the surface's own dict when they are its coefficients exactly, else an
    ``even_poly`` one with the surface's normalisation radius (a ``fresnel`` phase becomes ``even_poly`` with
    ``R = 1 mm``), trailing zero terms beyond the surface's own dropped."""
    rnorm, own = phase_profile(surface)
    vals = [float(x) for x in np.asarray(values, dtype=np.float64)]
    nz = np.nonzero(vals)[0]
    keep = max(len(own), int(nz[-1]) + 1 if nz.size else 0)
    if vals[:keep] == [float(a) for a in own] + [0.0] * (keep - len(own)) and keep == len(own):
        return dict(surface.phase)
    return {"kind": "even_poly", "norm_radius": float(rnorm), "coefficients": vals[:keep]}
