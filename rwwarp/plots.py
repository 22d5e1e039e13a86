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
    """Save a 2D (y-z) layout of ``lens`` with a meridional fan of ``rays`` rays per field to ``path`` (PNG)."""
    from .trace import Tracer
    plt = _plt()
    wl = wavelength_um or lens.wavelengths_um[len(lens.wavelengths_um) // 2]
    fields = fields_deg if fields_deg is not None else (lens.fields_deg or [0.0])
    tr = Tracer(lens, [wl])
    z = lens.vertex_z
    fig, ax = plt.subplots(figsize=(9, 4))
    colors = plt.cm.viridis(np.linspace(0, 0.85, len(fields)))
    u = np.zeros(rays)
    v = np.linspace(-1, 1, rays)
    ymax = 0.0
    for k, f in enumerate(fields):
        src = tr.sources([f])
        r = tr._run(src, u, v, 1.0, keep=True)
        start = np.stack([src["aim"][0][None, :] + np.stack([u, v * src["half_y"][0], 0 * u], 1)])[0]
        pts = [start] + [h.numpy() for h in r.history]
        ok = r.valid.numpy().astype(bool)
        pts = np.stack(pts)  # (n_planes, rays, 3)
        # start the drawing at the first surface
        pts[0] = pts[1] - (pts[1] - pts[0]) * np.clip((pts[1, :, 2:3] - min(z[0], 0) + 0.2 * lens.sensor_z * 0.05)
                                                      / np.maximum(pts[1, :, 2:3] - pts[0, :, 2:3], 1e-9), 0, 1)
        for j in range(rays):
            if ok[j]:
                ax.plot(pts[:, j, 2], pts[:, j, 1], color=colors[k], lw=0.7)
        ymax = max(ymax, np.max(np.abs(pts[:, ok, 1])) if ok.any() else 0)
    for i, s in enumerate(lens.surfaces):
        h = s.semi_diameter or ymax * 1.05 or 1.0
        r = np.linspace(-h, h, 101)
        sag = s.sag(np.abs(r)) if s.type == "standard" else np.zeros_like(r)
        style = {"standard": ("k", "-"), "thin_lens": ("tab:blue", "-"), "aperture": ("tab:red", "-"),
                 "doe": ("tab:purple", "--")}[s.type]
        if s.type == "aperture":
            ax.plot([z[i], z[i]], [h, h * 1.3], color=style[0], lw=2)
            ax.plot([z[i], z[i]], [-h, -h * 1.3], color=style[0], lw=2)
        else:
            ax.plot(z[i] + sag, r, color=style[0], ls=style[1], lw=1.2)
    ax.axvline(lens.sensor_z, color="gray", lw=1.5)
    ax.set_xlabel("z (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_title(lens.name or "lens layout")
    ax.set_aspect("equal", adjustable="datalim")
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def psf_map_figure(m, path, log: bool = True):
    """Save a grid picture of a :class:`~rwwarp.psf.PSFMap` (fields x wavelengths), log10 scale by default."""
    plt = _plt()
    nf, nw = m.data.shape[:2]
    fig, axes = plt.subplots(nw, nf, figsize=(1.8 * nf + 0.5, 1.8 * nw + 0.3), squeeze=False)
    for i in range(nf):
        for j in range(nw):
            d = m.data[i, j]
            img = np.log10(np.maximum(d / max(d.max(), 1e-300), 1e-6)) if log else d
            axes[j, i].imshow(img, origin="lower", cmap="inferno")
            axes[j, i].set_xticks([])
            axes[j, i].set_yticks([])
            if j == 0:
                axes[j, i].set_title(field_label(m.fields_deg[i]), fontsize=8)
            if i == 0:
                axes[j, i].set_ylabel(f"{m.wavelengths_um[j]:.3g} um", fontsize=8)
    fig.suptitle(f"{m.model} PSFs ({'log10, 6 decades' if log else 'linear'}), each tile {m.data.shape[-1]} px of "
                 f"{m.pixel_mm * 1e3:.3g} um", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def rgb_psf_map(m, path):
    """Save an RGB composite of a 3-wavelength PSF map (one tile per field)."""
    plt = _plt()
    nf = m.data.shape[0]
    cols = int(np.ceil(np.sqrt(nf)))
    rows = int(np.ceil(nf / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(2 * cols, 2 * rows), squeeze=False)
    for k in range(rows * cols):
        ax = axes[k // cols, k % cols]
        ax.axis("off")
        if k < nf:
            d = m.data[k][::-1] if m.data.shape[1] == 3 else np.repeat(m.data[k][:1], 3, 0)
            rgb = np.moveaxis(d, 0, -1)
            rgb = np.sqrt(rgb / max(rgb.max(), 1e-300))
            ax.imshow(rgb, origin="lower")
            ax.set_title(field_label(m.fields_deg[k]), fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
