"""Figures and tables of a design experiment: the step snapshots (PSFs, DOE phase, crops), the
comparison figure ``designs.png`` and ``table.md`` / ``table.csv`` (numbers as measured)."""
from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from torch_bridge.config import _depth_tag

__all__ = ["write_table"]


def _doe_phase_image(lens, n: int | None = None):
    """The DOE's wrapped design phase (rad) on an n x n grid over its aperture, and its half width (mm).
    Default ``n``: 4 samples per 2 pi zone at the steepest point (256 to 4096), so the zones are resolved
    and not drawn as moire."""
    from rwwarp import doe as rdoe
    s = lens.surfaces[lens.doe_index]
    prof = rdoe.profile_from_dict(s.profile)
    h = s.semi_diameter or 1.0
    if n is None:
        e = np.linspace(-h, h, 65)
        gx, gy = prof.gradient(*np.meshgrid(e, e), s.design_wavelength_um)
        zones_per_mm = float(np.max(np.hypot(gx, gy))) / (2 * np.pi)
        n = int(np.clip(4 * 2 * h * zones_per_mm, 256, 4096))
    g = np.linspace(-h, h, n)
    x, y = np.meshgrid(g, g[::-1])
    return rdoe.design_phase(prof, x, y, s.design_wavelength_um, s.levels), h


def _rgb_psf(p):
    """(3, k, k) -> (k, k, 3) display image (sqrt, per-image max), image orientation."""
    a = np.clip(p, 0, None)
    a = np.sqrt(a / max(a.max(), 1e-30))
    return a.transpose(1, 2, 0)[::-1]


def _snapshot(arm, path, psf, gt, raw, rec, step, phase):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    p = psf.detach().float().cpu().numpy()
    nn_ = p.shape[0]
    ncol = max(nn_, 4)
    fig, ax = plt.subplots(2, ncol, figsize=(2.2 * ncol, 4.6))
    for j in range(ncol):
        for r in range(2):
            ax[r, j].axis("off")
    for j in range(nn_):
        ax[0, j].imshow(_rgb_psf(p[j]))
        f = arm.fields[j]
        ax[0, j].set_title(f"PSF ({f[0]:.1f}, {f[1]:.1f}) deg\nRGB, sqrt, tile / its max", fontsize=7)
    ph, h = _doe_phase_image(arm.module.to_lens())
    im = ax[1, 0].imshow(ph, cmap="twilight", extent=(-h, h, -h, h), vmin=0.0, vmax=2 * np.pi)
    ax[1, 0].set_title("DOE phase (rad, wrapped)", fontsize=7)
    ax[1, 0].axis("on")
    ax[1, 0].tick_params(labelsize=6)
    ax[1, 0].set_xlabel("x (mm)", fontsize=6)
    fig.colorbar(im, ax=ax[1, 0], fraction=0.046, pad=0.04).ax.tick_params(labelsize=5)
    for j, (img, t) in enumerate(((gt, "ground truth"), (raw, "raw"), (rec, "reconstructed"))):
        ax[1, j + 1].imshow(img[0].detach().float().clamp(0, 1).cpu().numpy().transpose(1, 2, 0))
        ax[1, j + 1].set_title(t, fontsize=7)
    fig.suptitle(f"{arm.name}: step {step} ({phase})", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _object_label(key, lens_distance_mm=None) -> str:
    """Title text for the object distance an ``eval_psfs.npz`` key names (``str(depth_mm)``: "None" = the lens's
    own object distance ``lens_distance_mm``, mm, "inf", or mm)."""
    if key in (None, "None", "default"):
        if lens_distance_mm is None:
            return "object: the lens's distance"
        key = str(lens_distance_mm)
    try:
        d = float(key)
    except ValueError:
        return f"object {key}"
    return "object at infinity" if math.isinf(d) else f"object at {d:g} mm"


def _node_fields(result, key) -> list:
    """The (x, y) field angles (deg) of the evaluation nodes at the depth ``key`` from an arm's result.json
    dict (``eval.depths[k].nodes[n].field_deg``); [] where the result does not hold them (image mode)."""
    try:
        for d in result["eval"]["depths"]:
            if str(d.get("depth_mm")) == str(key) or len(result["eval"]["depths"]) == 1:
                return [n.get("field_deg") if isinstance(n.get("node"), int) else None for n in d["nodes"]]
    except (KeyError, TypeError):
        pass
    return []


# at most this many nodes are drawn one panel each; a larger evaluation grid (the gpu presets' 10 x 10) is drawn as
# one mosaic placed by field position, plus single panels of a few nodes from the axis to the corner
SINGLE_PANELS = 8


def _grid_layout(fields) -> tuple | None:
    """Row and column of each node in a regular grid of its field angles ``fields`` ([(x, y)] deg), rows from the
    top (largest y first); None when the nodes do not form a full grid (every (x, y) pair once)."""
    if not fields or any(f is None for f in fields):
        return None
    xs = sorted({round(float(f[0]), 6) for f in fields})
    ys = sorted({round(float(f[1]), 6) for f in fields}, reverse=True)
    if len(xs) * len(ys) != len(fields):
        return None
    at = [(ys.index(round(float(f[1]), 6)), xs.index(round(float(f[0]), 6))) for f in fields]
    return (at, len(ys), len(xs)) if len(set(at)) == len(at) else None


def psf_mosaic(psfs, fields, gap: int = 2):
    """One display image of many PSFs: ``psfs`` (N, 3, k, k) placed by their field angles ``fields`` ([(x, y)] deg,
    a full grid), each tile RGB, sqrt scale over its own maximum (:func:`_rgb_psf`), ``gap`` px of white between
    tiles. Returns (image (H, W, 3) in [0, 1], rows, cols), or None when the nodes do not form a grid."""
    lay = _grid_layout(fields)
    if lay is None:
        return None
    at, nr, nc = lay
    k = psfs.shape[-1]
    img = np.ones((nr * (k + gap) - gap, nc * (k + gap) - gap, 3))
    for p, (r, c) in zip(psfs, at):
        img[r * (k + gap):r * (k + gap) + k, c * (k + gap):c * (k + gap) + k] = _rgb_psf(p)
    return img, nr, nc


def _designs_figure(results: dict, out: Path):
    """One row per arm: DOE phase, evaluation PSFs (RGB, sqrt scale) of the nodes, raw / rec crop. More than
    ``SINGLE_PANELS`` nodes on a grid: one mosaic of all of them by field position and single panels of the
    diagonal's nodes (at most 4, from the axis to the corner)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    import rwwarp as rw
    arms = [a for a in results if (out / a / "lens.json").exists()]
    if not arms:
        return
    psfs = {a: np.load(out / a / "eval_psfs.npz") for a in arms}
    first = psfs[arms[0]]
    key0 = next(iter(first.keys()))
    nn_ = first[key0].shape[0]
    fields0 = _node_fields(results.get(arms[0]), key0)
    mosaic = nn_ > SINGLE_PANELS and _grid_layout(fields0) is not None
    if mosaic:
        at, nr, nc = _grid_layout(fields0)
        diag = [at.index((nr - 1 - i * (nr - 1) // 3, i * (nc - 1) // 3)) for i in range(4)
                if (nr - 1 - i * (nr - 1) // 3, i * (nc - 1) // 3) in at]
        shown = list(dict.fromkeys(diag))
    else:
        shown = list(range(nn_))
    ncol = 1 + int(mosaic) + len(shown) + 2
    fig, ax = plt.subplots(len(arms), ncol, figsize=(2.0 * ncol, 2.1 * len(arms)), squeeze=False)
    for i, a in enumerate(arms):
        for j in range(ncol):
            ax[i, j].axis("off")
        lens = rw.load_lens(out / a / "lens.json")
        ph, h = _doe_phase_image(lens)
        im = ax[i, 0].imshow(ph, cmap="twilight", extent=(-h, h, -h, h), vmin=0.0, vmax=2 * np.pi)
        ax[i, 0].set_title(f"{a}: DOE phase (rad, wrapped)", fontsize=7)
        ax[i, 0].axis("on")
        ax[i, 0].tick_params(labelsize=5)
        ax[i, 0].set_xlabel("x (mm)", fontsize=6)
        ax[i, 0].set_ylabel("y (mm)", fontsize=6)
        cb = fig.colorbar(im, ax=ax[i, 0], fraction=0.046, pad=0.04)
        cb.set_label("rad", fontsize=6)
        cb.ax.tick_params(labelsize=5)
        p = psfs[a][key0]
        nodes = _node_fields(results.get(a), key0)
        c0 = 1
        if mosaic:
            m = psf_mosaic(p, nodes)
            if m is not None:
                xs, ys = [f[0] for f in nodes], [f[1] for f in nodes]
                dx = (max(xs) - min(xs)) / max(m[2] - 1, 1) / 2     # half a tile: the extent covers the tiles
                dy = (max(ys) - min(ys)) / max(m[1] - 1, 1) / 2
                ax[i, 1].imshow(m[0], extent=(min(xs) - dx, max(xs) + dx, min(ys) - dy, max(ys) + dy))
                ax[i, 1].axis("on")
                ax[i, 1].tick_params(labelsize=5)
                ax[i, 1].set_xlabel("field x (deg)", fontsize=6)
                ax[i, 1].set_ylabel("field y (deg)", fontsize=6)
                ax[i, 1].set_title(f"PSFs of the {m[1]} x {m[2]} nodes\n{_object_label(key0, lens.object_distance)}; "
                                   "RGB, sqrt, / tile max", fontsize=6)
            c0 = 2
        for jj, j in enumerate(shown):
            ax[i, c0 + jj].imshow(_rgb_psf(p[j]))
            where = f"node {j}" if j >= len(nodes) or nodes[j] is None else \
                f"node {j}: ({nodes[j][0]:.1f}, {nodes[j][1]:.1f}) deg"
            ax[i, c0 + jj].set_title(f"PSF {where}\n{_object_label(key0, lens.object_distance)}; RGB, sqrt, / tile max", fontsize=6)
        smp = sorted((out / a).glob("eval_sample_*.npz"))
        if smp:
            s = np.load(smp[0])
            ax[i, ncol - 2].imshow(np.clip(s["raw"][0].transpose(1, 2, 0), 0, 1))
            ax[i, ncol - 2].set_title("raw (outer node)", fontsize=7)
            ax[i, ncol - 1].imshow(np.clip(s["rec"][0].transpose(1, 2, 0), 0, 1))
            ax[i, ncol - 1].set_title("reconstructed", fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "designs.png", dpi=100)
    plt.close(fig)


def _fmt(m):
    lp = m.get("one_minus_lpips")
    lp_s = "-" if lp is None or (isinstance(lp, float) and not math.isfinite(lp)) else f"{lp:.3f}"
    return f"{m['psnr']:.2f}/{m['ssim']:.3f}/{lp_s}"


def write_table(results: dict, out: Path, title: str = "", preset=None):
    """``table.md`` and ``table.csv`` of an experiment from its arms' results (numbers as measured)."""
    lines = [f"# {title}" + (f" (preset {preset})" if preset else ""), "",
             ("| design | depth | RMS radius um (on/off-axis/avg) | PSNR/SSIM/1-LPIPS raw | PSNR/SSIM/1-LPIPS rec | "
              "EFL mm |"), "|---|---|---|---|---|---|"]
    rows = []
    for a, r in results.items():
        if "eval" not in r:
            continue
        e = r["eval"]
        rms = e.get("rms_um", {})
        rms_s = f"{rms['on_axis']:.1f}/{rms['off_axis']:.1f}/{rms['avg']:.1f}" if "on_axis" in rms else "-"
        for d in e["depths"]:
            dep = _depth_tag(d["depth_mm"])
            lines.append(f"| {a} | {dep} | {rms_s} | {_fmt(d['raw'])} | {_fmt(d['rec'])} | {e['efl_mm']:.2f} |")
            rows.append({"design": a, "depth": dep, "rms_on_um": rms.get("on_axis"), "rms_off_um": rms.get("off_axis"),
                         "rms_avg_um": rms.get("avg"), "psnr_raw": d["raw"]["psnr"], "ssim_raw": d["raw"]["ssim"],
                         "one_minus_lpips_raw": d["raw"]["one_minus_lpips"], "psnr_rec": d["rec"]["psnr"],
                         "ssim_rec": d["rec"]["ssim"], "one_minus_lpips_rec": d["rec"]["one_minus_lpips"],
                         "efl_mm": e["efl_mm"], "train_wall_s": r.get("train_wall_s")})
    lines.append("")
    lines.append("Per node (PSNR raw / rec, dB; node positions on the sensor in mm):")
    lines.append("")
    for a, r in results.items():
        if "eval" in r:
            for d in r["eval"]["depths"]:
                lines.append(f"- {a}, depth {_depth_tag(d['depth_mm'])}: " + ", ".join(
                    f"node {n['node']}" + (f" {tuple(round(v, 2) for v in n['position_mm'])}" if 'position_mm' in n
                                           else "") + f": {n['raw']['psnr']:.2f} / {n['rec']['psnr']:.2f}"
                    for n in d["nodes"]))
    lines.append("")
    lines.append("Objective (MSE + alpha * perceptual on the evaluation crops, first evaluation depth; initial = "
                 "the arm's starting lens with the untrained network) and wall time:")
    lines.append("")
    for a, r in results.items():
        if "eval" in r:
            oi, of = r.get("objective_initial") or {}, r.get("objective_final") or {}
            obj = f"{oi['loss']:.5f} -> {of['loss']:.5f}" if "loss" in oi and "loss" in of else "-"
            lines.append(f"- {a}: objective {obj}; training {r.get('train_wall_s', float('nan')):.0f} s, "
                         f"evaluation {r.get('eval_wall_s', float('nan')):.0f} s")
    (out / "table.md").write_text("\n".join(lines) + "\n")
    if rows:
        with open(out / "table.csv", "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
