"""The ``model="ray"`` PSF: the DOE as a local grating (rays bent by the phase gradient, first order),
geometric PSF by binning ray power into sensor pixels. Refuses discontinuous DOEs.

A field none of whose rays reach the sensor raises the same :class:`~rwwarp.errors.LensError` as the
ray-wave model (no all-zero PSF centred at NaN).
"""
from __future__ import annotations

import numpy as np

from .errors import GeometryError, LensError
from .trace import Tracer, pupil_grid


def grating_to_sensor(pos, dirs, n_after, lam_mm, grad, z_sensor, xp=np):
    """The ray model's last step (its one home): rays at the wave-plane surface (positions ``pos`` and
    unit directions ``dirs``, (..., 3), mm) cross the DOE as a local grating, first order,
    ``n' d'_xy = n d_xy + lambda / (2 pi) grad(phi0)`` (``grad``: ``(gx, gy)`` in rad/mm at the rays, or
    None without a DOE; ``lam_mm`` in mm and ``n_after`` broadcast against the rays), and go straight on
    to the sensor plane ``z = z_sensor`` (mm). Returns ``(hx, hy, ok)``: the landing points (mm) and
    where the bent ray exists (no evanescent order). Array namespace ``xp``: numpy, or torch (then
    differentiable in everything but ``ok``)."""
    tx = n_after * dirs[..., 0]
    ty = n_after * dirs[..., 1]
    if grad is not None:
        tx = tx + lam_mm / (2.0 * np.pi) * grad[0]
        ty = ty + lam_mm / (2.0 * np.pi) * grad[1]
    tz2 = n_after * n_after - tx * tx - ty * ty
    ok = tz2 > 0
    tz = xp.sqrt(xp.where(ok, tz2, 1.0))
    run = z_sensor - pos[..., 2]
    return pos[..., 0] + run * tx / tz, pos[..., 1] + run * ty / tz, ok


def _ray_model(lens, fields, wls, size, pixel, device, dtype, object_distance_mm, rays_per_sample, center_mm):
    """Geometric PSF with the DOE as a local grating (ray bending by the phase gradient)."""
    from . import doe
    from .lens import snap_to_pixel as _snap_center
    from .trace import field_label as _fmt_field
    plane = lens.wave_plane_index()
    s = lens.surfaces[plane]
    prof = None
    if s.type == "doe":
        prof = doe.profile_from_dict(s.profile)
        if doe.surface_has_steps(s, lens.source):
            raise LensError("the ray model cannot handle a discontinuous DOE phase (pixel map or quantised "
                            "levels): its local grating needs the phase gradient. Use model='ray-wave'.",
                            file=lens.source, surface=lens.surface_label(plane), keyword="profile")
    uniq = sorted(set(wls))
    tr = Tracer(lens, uniq, device=device, dtype=dtype)
    wl_idx = [uniq.index(w) for w in wls]
    src = tr.sources(fields, wl_idx, object_distance=object_distance_mm)
    grid = 401
    u, v, cell = pupil_grid(grid, src["shape"])
    rays = tr._run(src, u, v, cell, upto=plane + 1)
    nsrc, npup = len(fields), len(u)
    pos = rays.pos.numpy().reshape(nsrc, npup, 3)
    dr = rays.dir.numpy().reshape(nsrc, npup, 3)
    valid = rays.valid.numpy().reshape(nsrc, npup).astype(bool)
    weight = rays.weight.numpy().reshape(nsrc, npup)
    entering = weight.sum(1)
    n_pl = np.array([lens.indices(w)[plane] for w in wls])[:, None]
    lam = np.array(wls, dtype=np.float64)[:, None] * 1e-3
    grad = None if prof is None else prof.gradient(pos[..., 0], pos[..., 1], s.design_wavelength_um)
    hx, hy, ok = grating_to_sensor(pos, dr, n_pl, lam, grad, lens.sensor_z)
    valid &= ok
    hit = np.stack([hx, hy], -1)
    for k in range(nsrc):
        if not np.any(valid[k] & (weight[k] > 0)):
            raise GeometryError("no rays reach the sensor (the field is fully vignetted or misses a surface)",
                            file=lens.source, field=_fmt_field(fields[k]))
    centers = np.zeros((nsrc, 2))
    for k in range(nsrc):
        c = hit[k, valid[k], :2].mean(0) if center_mm is None else np.asarray(center_mm, float)
        centers[k] = [_snap_center(c[0], pixel, lens.sensor.resolution[0]),
                      _snap_center(c[1], pixel, lens.sensor.resolution[1])]
    data = np.zeros((nsrc, size, size))
    for k in range(nsrc):
        ix = np.floor((hit[k, :, 0] - centers[k, 0]) / pixel + 0.5).astype(np.int64) + size // 2
        iy = np.floor((hit[k, :, 1] - centers[k, 1]) / pixel + 0.5).astype(np.int64) + size // 2
        m = valid[k] & (ix >= 0) & (ix < size) & (iy >= 0) & (iy < size)
        np.add.at(data[k], (iy[m], ix[m]), weight[k, m])
        data[k] /= entering[k]
    return {"data": data, "centers": centers, "valid_fraction": (weight * valid).sum(1) / entering}
