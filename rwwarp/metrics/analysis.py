"""Ray-based analysis: RMS spot radius, spot diagrams, real-ray focal length (differentiable).

Lengths in mm internally; :func:`spot_rms` returns micrometres (as optical designers quote it).
"""
from __future__ import annotations

import numpy as np
import warp as wp

from ..errors import GeometryError
from ..kernels.trace import make_analysis_kernels
from ..trace import Tracer, pupil_grid


def spot_rms(lens, field_deg=0.0, wavelength_um: float = 0.5876, grid: int = 401, reference: str = "centroid",
             ray_aiming: bool = False, layout: str = "edges", device: str = "cpu", dtype: str = "float64"):
    """RMS spot radius at the sensor plane, um.

    ``grid`` x ``grid`` square pupil grid clipped to the entrance pupil (``layout="edges"``: Zemax's
    convention, grid points include the pupil edge). ``reference``: ``"centroid"`` or ``"chief"``
    (the ray through the pupil centre). ``field_deg``: one field (deg) or a list (returns an array).
    """
    from .. import checks
    checks.check_lens(lens)
    fields = checks.check_fields(field_deg, "field_deg")
    single = isinstance(field_deg, tuple) or not isinstance(field_deg, (list, np.ndarray))
    wavelength_um = checks.check_wavelength(wavelength_um, lens)
    grid = checks.check_grid(grid)
    checks.check_choice(reference, "reference", ("centroid", "chief"))
    checks.check_choice(layout, "layout", ("edges", "centers"))
    checks.check_choice(dtype, "dtype", ("float64", "float32"))
    checks.check_device(device)
    tr = Tracer(lens, [wavelength_um], device=device, dtype=dtype)
    rays = tr.trace(fields, grid=grid, ray_aiming=ray_aiming, layout=layout)
    r = rays.numpy()
    out = np.zeros(len(fields))
    chief = None
    if reference == "chief":
        chief = tr.trace(fields, pupil=(np.zeros(1), np.zeros(1), 1.0), ray_aiming=ray_aiming).numpy()
    elif reference != "centroid":
        raise ValueError(f"reference must be 'centroid' or 'chief', got {reference!r}")
    if r["valid"].size == 0:
        raise checks.ArgumentError(f"grid={grid} with layout={layout!r} puts no pupil sample inside the "
                                   "circular pupil; use grid=1 or grid >= 3")
    for k in range(len(fields)):
        ok = r["valid"][k]
        if not ok.any():
            raise GeometryError(f"field_deg={fields[k]!r} at {wavelength_um:g} um: no ray of the {grid}x{grid} "
                                "pupil grid reaches the sensor (the field is fully vignetted or misses a surface)",
                                file=lens.source, field=fields[k])
        xy = r["pos"][k, ok, :2]
        c = xy.mean(0) if chief is None else chief["pos"][k, 0, :2]
        if chief is not None and not np.all(np.isfinite(c)):
            raise GeometryError(f"field_deg={fields[k]!r}: the chief ray does not reach the sensor "
                                "(use reference='centroid')", file=lens.source, field=fields[k])
        out[k] = 1e3 * np.sqrt(np.mean(np.sum((xy - c) ** 2, axis=1)))
        if not np.isfinite(out[k]):
            raise GeometryError(f"field_deg={fields[k]!r}: the RMS spot radius is not finite (rays overflow)",
                                file=lens.source, field=fields[k])
    return out[0] if single else out


def spot_diagram(lens, field_deg=0.0, wavelength_um: float = 0.5876, grid: int = 41, device: str = "cpu"):
    """Spot-diagram data: (x, y) sensor hits (mm) of valid rays, per field. Returns a list of (n, 2) arrays."""
    from .. import checks
    checks.check_lens(lens)
    fields = checks.check_fields(field_deg, "field_deg")
    wavelength_um = checks.check_wavelength(wavelength_um, lens)
    grid = checks.check_grid(grid)
    checks.check_device(device)
    tr = Tracer(lens, [wavelength_um], device=device)
    r = tr.trace(fields, grid=grid).numpy()
    return [r["pos"][k, r["valid"][k], :2] for k in range(len(fields))]


def spot_rms_tape(tracer: Tracer, fields, grid: int = 101, layout: str = "edges"):
    """RMS radius (mm) per field as a Warp array computed on the device; call inside a ``wp.Tape``
    (tracer built with ``requires_grad=True``) to differentiate it w.r.t. ``tracer.params``."""
    K = make_analysis_kernels(tracer.scalar)
    src = tracer.sources(fields)
    u, v, cell = pupil_grid(grid, src["shape"], layout=layout)
    rays = tracer._run(src, u, v, cell)
    from ..wave.reduce import source_sums
    n = len(src["wl"])
    terms = wp.zeros(n * len(u), dtype=wp.types.vector(4, tracer.scalar), device=tracer.device, requires_grad=True)
    wp.launch(K.moments_kernel, dim=n * len(u), inputs=[rays.pos, rays.valid, len(u)], outputs=[terms],
              device=tracer.device)
    mom = source_sums(terms, n, tracer.scalar, tracer.device, requires_grad=True)   # deterministic tree
    rms = wp.zeros(n, dtype=tracer.scalar, device=tracer.device, requires_grad=True)
    wp.launch(K.rms_kernel, dim=n, inputs=[mom], outputs=[rms], device=tracer.device)
    return rms


def efl_tape(tracer: Tracer, height_mm: float = 1e-4):
    """Real-ray focal length (mm) from a ray parallel to the axis at ``height_mm``: ``-h / tan(u')``.
    Equals the paraxial EFL to O(h^2); differentiable under ``wp.Tape``."""
    K = make_analysis_kernels(tracer.scalar)
    src = tracer.sources([0.0])
    src["finite"][:] = 0
    src["aim"][:] = [0.0, 0.0, 0.0]
    src["half_y"][:] = height_mm
    rays = tracer._run(src, np.zeros(1), np.ones(1), 1.0)
    out = wp.zeros(1, dtype=tracer.scalar, device=tracer.device, requires_grad=True)
    wp.launch(K.slope_efl_kernel, dim=1, inputs=[rays.dir, tracer.scalar(height_mm)], outputs=[out],
              device=tracer.device)
    return out
