"""Pictures: lens layout with traced rays, PSF maps, log-PSF comparisons (matplotlib, Agg backend)."""
from __future__ import annotations

import numpy as np


def field_label(f) -> str:
    """Short text for a field angle (deg): a number or an (x, y) pair."""
    if np.ndim(f) == 0:
        return f"{float(f):g} deg"
    x, y = float(f[0]), float(f[1])
    return f"{y:g} deg" if x == 0 else f"({x:g}, {y:g}) deg"


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def layout(lens, path, fields_deg=None, wavelength_um=None, rays: int = 7):
    """Save a 2D (y-z) layout of ``lens`` with a meridional fan of ``rays`` rays per field to ``path`` (PNG):
    surfaces drawn to their clear apertures, glass filled, mm axes (:func:`layout_figure`)."""
    wl = wavelength_um or lens.wavelengths_um[len(lens.wavelengths_um) // 2]
    fields = list(fields_deg) if fields_deg is not None else list(lens.fields_deg or [0.0])
    layout_figure(lens, path, fields, wl, rays=rays)


def _fan(lens, field, wl, u, v, device="cpu", start: bool = False):
    """Positions after every surface ((n_surfaces + 1, n, 3): ``history[0]`` is ON THE FIRST SURFACE, the
    last entry on the sensor) and validity of rays. ``start=True`` also returns the generated rays (the
    source rays: position on the entrance-pupil plane and object-space direction, each (n, 3))."""
    from .trace import Tracer
    tr = Tracer(lens, [wl], device=device)
    src = tr.sources([field])
    r = tr._run(src, np.asarray(u, float), np.asarray(v, float), 1.0, keep=True)
    hist = np.stack([h.numpy().reshape(-1, 3) for h in r.history])
    ok = r.valid.numpy().astype(bool).ravel()
    if not start:
        return hist, ok, src
    g = tr._run(src, np.asarray(u, float), np.asarray(v, float), 1.0, upto=0)  # the generated rays only
    return hist, ok, src, g.pos.numpy().reshape(-1, 3), g.dir.numpy().reshape(-1, 3)


def layout_rays(lens, field_deg, wavelength_um, rays: int = 9, device: str = "cpu"):
    """The polylines :func:`layout_figure` draws for one field (deg) at ``wavelength_um`` (um): a meridional
    fan of ``rays`` rays across the entrance pupil. Returns ``(paths, valid)``: ``paths`` (rays, n_surfaces + 2,
    3) in mm, ``valid`` (rays,) the rays that reach the sensor.

    Each path starts on its source ray in object space: at the object point for an object closer than twice
    the lens's track, else on the plane 10 % of the track (at least 1 mm) in front of the first vertex,
    along the ray's object-space direction (parallel for an object at infinity); it then visits every
    surface and ends on the sensor. (The drawing used to extend the rays back from the first surface along
    their in-glass direction.)"""
    v = np.linspace(-1, 1, int(rays))
    hist, ok, src, p0, d0 = _fan(lens, field_deg, wavelength_um, np.zeros(len(v)), v, device, start=True)
    z_first = float(lens.vertex_z[0])
    track = max(float(lens.sensor_z) - z_first, 1.0)
    od = float(src["object_distance"])
    if np.isfinite(od) and od <= 2.0 * track:
        start = np.broadcast_to(np.asarray(src["pos"][0], float), p0.shape).copy()
    else:
        z0 = z_first - 0.1 * track
        with np.errstate(invalid="ignore", divide="ignore"):
            t = np.where(np.abs(d0[:, 2]) > 1e-12, (z0 - p0[:, 2]) / np.where(d0[:, 2] != 0, d0[:, 2], 1.0), 0.0)
        start = p0 + t[:, None] * d0
    return np.concatenate([start[None], hist], axis=0).transpose(1, 0, 2), ok


def clear_semi_diameters(lens, fields_deg, wavelengths_um, grid: int = 21, device: str = "cpu") -> np.ndarray:
    """Clear semi-diameter of each surface, mm: its ``semi_diameter`` where set, else the largest
    radial height at that surface of the rays (``grid`` x ``grid`` pupil, every field and wavelength)
    that reach the sensor (as Zemax's automatic semi-diameters)."""
    from .trace import pupil_grid
    shape = lens.surfaces[lens.stop_index].shape
    u, v, _ = pupil_grid(grid, shape, layout="edges")
    h = np.zeros(len(lens.surfaces))
    for wl in wavelengths_um:
        for f in fields_deg:
            hist, ok, _ = _fan(lens, f, wl, u, v, device)
            if not ok.any():
                continue
            r = np.hypot(hist[:len(lens.surfaces), ok, 0], hist[:len(lens.surfaces), ok, 1])
            h = np.maximum(h, np.nanmax(r, axis=1))
    for i, s in enumerate(lens.surfaces):
        if s.semi_diameter is not None:
            h[i] = s.semi_diameter  # (a square's half side: its extent in the y-z section)
    return h


def layout_figure(lens, path, fields_deg, wavelength_um, device: str = "cpu", rays: int = 9):
    """Save the y-z layout: surfaces to their clear apertures (:func:`clear_semi_diameters`), lens
    elements filled between surfaces in glass, a meridional fan of ``rays`` rays per field. mm axes."""
    plt = _plt()
    z = lens.vertex_z
    sd = clear_semi_diameters(lens, fields_deg, [wavelength_um], device=device)
    fig, ax = plt.subplots(figsize=(9, 4.2))
    colors = plt.cm.viridis(np.linspace(0, 0.85, max(len(fields_deg), 1)))
    for k, f in enumerate(fields_deg):
        paths, ok = layout_rays(lens, f, wavelength_um, rays, device)
        first = True
        for j in range(rays):
            if ok[j]:
                ax.plot(paths[j, :, 2], paths[j, :, 1], color=colors[k], lw=0.7, label=field_label(f) if first else None)
                first = False
    media = lens.media()
    edge = []
    for i, s in enumerate(lens.surfaces):
        h = sd[i] if sd[i] > 0 else 1.0
        r = np.linspace(-h, h, 121)
        sag = s.sag(np.abs(r)) if s.type == "standard" else np.zeros_like(r)
        edge.append((z[i] + (s.sag(h) if s.type == "standard" else 0.0), h))
        if s.type == "aperture":
            ax.plot([z[i], z[i]], [h, h * 1.25], color="tab:red", lw=2)
            ax.plot([z[i], z[i]], [-h, -h * 1.25], color="tab:red", lw=2)
        else:
            style = {"standard": ("k", "-"), "thin_lens": ("tab:blue", "-"), "doe": ("tab:purple", "--")}[s.type]
            ax.plot(z[i] + sag, r, color=style[0], ls=style[1], lw=1.2)
    # glass elements: between a surface whose medium after it is not air and the next surface
    for i in range(len(lens.surfaces) - 1):
        if media[i].lower() == "air" or lens.surfaces[i].type not in ("standard",):
            continue
        j = i + 1
        (za, ha), (zb, hb) = edge[i], edge[j]
        H = max(ha, hb)
        for sgn in (1, -1):
            ax.plot([za, za], [sgn * ha, sgn * H], color="k", lw=1.0)
            ax.plot([zb, zb], [sgn * hb, sgn * H], color="k", lw=1.0)
            ax.plot([za, zb], [sgn * H, sgn * H], color="k", lw=1.0)
        sa, sb = lens.surfaces[i], lens.surfaces[j]
        ra = np.linspace(-ha, ha, 121)
        rb = np.linspace(hb, -hb, 121)
        za_c = z[i] + (sa.sag(np.abs(ra)) if sa.type == "standard" else 0 * ra)
        zb_c = z[j] + (sb.sag(np.abs(rb)) if sb.type == "standard" else 0 * rb)
        poly_z = np.concatenate([[za], za_c, [za, zb], zb_c, [zb]])
        poly_y = np.concatenate([[-H], ra, [H, H], rb, [-H]])
        ax.fill(poly_z, poly_y, color="tab:cyan", alpha=0.15, lw=0)
    ax.axvline(lens.sensor_z, color="gray", lw=1.5)
    ax.set_xlabel("z (mm)")
    ax.set_ylabel("y (mm)")
    # two lines, wrapped: a long lens name (the demo's) no longer runs off the figure
    import textwrap
    name = textwrap.fill(lens.name or "lens", 95)
    ax.set_title(f"{name}\nlayout at {wavelength_um:g} um: surfaces to their clear apertures, rays from the object side",
                 fontsize=9)
    ax.set_aspect("equal", adjustable="datalim")
    if fields_deg:
        ax.legend(fontsize=7, loc="best", title="field", title_fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)
    return sd


def _tile_extent_um(m):
    """imshow extent (um) of a PSF tile: sample centres at ``(i - n // 2) * pixel`` from the patch centre."""
    n = m.data.shape[-1]
    p = m.pixel_mm * 1e3
    return [(-(n // 2) - 0.5) * p, (n - n // 2 - 0.5) * p] * 2


def _in_patch(m):
    """Fraction of each PSF's traced power inside its patch (n_fields, n_wavelengths), or None."""
    v = m.info.get("power_in_patch") if isinstance(m.info, dict) else None
    if v is None and isinstance(m.info, dict) and m.info.get("valid_fraction") is not None:
        vf = np.asarray(m.info["valid_fraction"], float).reshape(m.data.shape[:2])
        v = m.data.sum(axis=(2, 3)) / np.where(vf > 0, vf, np.inf)
    return None if v is None else np.asarray(v, float).reshape(m.data.shape[:2])


def psf_map_figure(m, path, log: bool = True):
    """Save a grid picture of a :class:`~rwwarp.psf.PSFMap` (fields x wavelengths), log10 scale by default:
    each tile normalised to its own peak (stated in the title), one colour bar, axes in um from the patch
    centre, the fraction of the traced power inside each patch in the tile's title."""
    plt = _plt()
    nf, nw = m.data.shape[:2]
    inside = _in_patch(m)
    ext = _tile_extent_um(m)
    fig, axes = plt.subplots(nw, nf, figsize=(2.1 * nf + 1.2, 2.1 * nw + 0.7), squeeze=False,
                             layout="constrained")
    im = None
    for i in range(nf):
        for j in range(nw):
            d = m.data[i, j]
            peak = max(d.max(), 1e-300)
            ax = axes[j, i]
            if log:
                im = ax.imshow(np.log10(np.maximum(d / peak, 1e-6)), origin="lower", cmap="inferno", vmin=-6,
                               vmax=0, extent=ext)
            else:
                im = ax.imshow(d / peak, origin="lower", cmap="inferno", vmin=0, vmax=1, extent=ext)
            ax.tick_params(labelsize=6)
            t = f"{field_label(m.fields_deg[i])}, {m.wavelengths_um[j]:.3g} um"
            if inside is not None:
                t += f"\nin patch {inside[i, j]:.3f}, peak {peak:.2g}"
            ax.set_title(t, fontsize=7)
            if j == nw - 1:
                ax.set_xlabel("x (um)", fontsize=7)
            if i == 0:
                ax.set_ylabel("y (um)", fontsize=7)
    cb = fig.colorbar(im, ax=axes, shrink=0.85, pad=0.02)
    cb.set_label("log10(power / tile peak)" if log else "power / tile peak", fontsize=8)
    cb.ax.tick_params(labelsize=7)
    fig.suptitle(f"{m.model} PSFs, each tile normalised to its own peak ({'log10, 6 decades' if log else 'linear'}); "
                 f"{m.data.shape[-1]} px of {m.pixel_mm * 1e3:.3g} um;\npeak and 'in patch': fractions of the power "
                 "entering the pupil per pixel / of the traced power inside the tile", fontsize=8)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def rgb_psf_map(m, path):
    """Save an RGB composite of a 3-wavelength PSF map (one tile per field; red = longest wavelength): each
    tile normalised to its brightest channel, sqrt scale (stated in the title and on the colour bar), axes in
    um from the patch centre. Wavelengths that share a patch centre show lateral colour as it is."""
    plt = _plt()
    nf = m.data.shape[0]
    cols = int(np.ceil(np.sqrt(nf)))
    rows = int(np.ceil(nf / cols))
    ext = _tile_extent_um(m)
    fig, axes = plt.subplots(rows, cols, figsize=(2.4 * cols + 1.0, 2.4 * rows + 0.8), squeeze=False,
                             layout="constrained")
    wl = list(m.wavelengths_um)
    order = np.argsort(wl)[::-1] if m.data.shape[1] == 3 else [0, 0, 0]  # R, G, B = long, middle, short
    for k in range(rows * cols):
        ax = axes[k // cols, k % cols]
        if k >= nf:
            ax.axis("off")
            continue
        rgb = np.moveaxis(m.data[k][list(order)], 0, -1)
        rgb = np.sqrt(rgb / max(rgb.max(), 1e-300))
        ax.imshow(rgb, origin="lower", extent=ext)
        c = m.centers_mm[k, int(order[1])]
        ax.set_title(f"{field_label(m.fields_deg[k])}, centre ({c[0]:.3f}, {c[1]:.3f}) mm", fontsize=7)
        ax.tick_params(labelsize=6)
        ax.set_xlabel("x (um)", fontsize=7)
        ax.set_ylabel("y (um)", fontsize=7)
    import matplotlib as mpl
    sm = mpl.cm.ScalarMappable(norm=mpl.colors.Normalize(0, 1), cmap="gray")
    cb = fig.colorbar(sm, ax=axes, shrink=0.85, pad=0.02)
    cb.set_label("each channel: sqrt(power / tile's brightest channel peak)", fontsize=7)
    cb.ax.tick_params(labelsize=6)
    names = ", ".join(f"{c} {wl[int(i)]:.3g} um" for c, i in zip("RGB", order)) if m.data.shape[1] == 3 else \
        f"{wl[0]:.3g} um"
    fig.suptitle(f"{m.model} PSFs, RGB ({names});\neach tile normalised to its own peak, sqrt scale; "
                 f"{m.data.shape[-1]} px of {m.pixel_mm * 1e3:.3g} um", fontsize=8)
    fig.savefig(path, dpi=110)
    plt.close(fig)
