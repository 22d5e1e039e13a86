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
    surfaces drawn to their clear apertures, glass filled, mm axes (:func:`rwwarp.report.layout_figure`)."""
    from .report import layout_figure
    wl = wavelength_um or lens.wavelengths_um[len(lens.wavelengths_um) // 2]
    fields = list(fields_deg) if fields_deg is not None else list(lens.fields_deg or [0.0])
    layout_figure(lens, path, fields, wl, rays=rays)


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
