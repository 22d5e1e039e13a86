"""Lens report: a folder of PNG figures and a Markdown page (``rwwarp report LENS``).

Figures (every image has a colour bar with units; per-tile normalisation is stated in the titles):
layout drawn to the real clear apertures (the surfaces' semi-diameters, else the height of the
outermost ray that reaches the sensor), spot diagrams, PSFs across the field, MTF curves
(tangential / sagittal, polychromatic), through-focus MTF, encircled energy, chromatic focal shift,
field curvature and distortion, and the DOE's phase and height map where there is one.

Units: mm, um (wavelengths, spot and PSF coordinates), degrees, lp/mm.
"""
from __future__ import annotations

import math
import time
import traceback
import warnings
from pathlib import Path

import numpy as np

from . import metrics as M
from .metrics import patch_size_for
from .plots import clear_semi_diameters, field_label, layout_figure  # the layout lives in plots (info --plot, demo)

__all__ = ["write_report", "clear_semi_diameters", "layout_figure", "patch_size_for", "spot_data",
           "polychromatic_diffraction_mtf"]


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


# ---------------------------------------------------------------------------------------------- figures
def polychromatic_diffraction_mtf(frequencies_lp_mm, cutoffs_lp_mm, weights=None):
    """Polychromatic diffraction-limited MTF of a circular pupil: the ``weights``-weighted (default equal) mean
    of :func:`rwwarp.metrics.diffraction_mtf_circular` at each wavelength's cutoff ``2 NA / lambda``
    (``cutoffs_lp_mm``, lp/mm) at ``frequencies_lp_mm`` (lp/mm), as Zemax's polychromatic diffraction limit."""
    c = np.atleast_1d(np.asarray(cutoffs_lp_mm, dtype=float))
    w = np.ones(len(c)) if weights is None else np.asarray(weights, dtype=float)
    if w.shape != c.shape or np.any(w < 0) or not w.sum() > 0:
        raise ValueError(f"weights must be {len(c)} non-negative numbers, not all 0, got {weights!r}")
    return sum(wi * M.diffraction_mtf_circular(frequencies_lp_mm, ci) for wi, ci in zip(w, c)) / w.sum()


def spot_data(lens, fields, wls, device="cpu", grid: int = 31):
    """Spot diagram data: for each field (deg) and wavelength (um) the ray hits on the sensor relative to the
    centroid of the reference (middle) wavelength, um ``xy[i][j]`` (n, 2); the RMS radius about each colour's
    own centroid ``rms`` (n_fields, n_wavelengths), um; the Airy radius 1.22 lambda F#_w at the reference
    wavelength with each field's working F# ``1 / (2 NA)`` (image-space NA of the traced cone) ``airy`` (n_fields,),
    um. A ``grid`` x ``grid`` pupil (edges included)."""
    from .trace import Tracer, pupil_grid
    shape = lens.surfaces[lens.stop_index].shape
    u, v, _ = pupil_grid(grid, shape, layout="edges")
    ref_j = len(wls) // 2
    xy = [[None] * len(wls) for _ in fields]
    rms = np.full((len(fields), len(wls)), np.nan)
    airy = np.zeros(len(fields))
    for i, f in enumerate(fields):
        hits = []
        for j, w in enumerate(wls):
            r = Tracer(lens, [w], device=device).trace([f], pupil=(u, v, 1.0)).numpy()
            hits.append(r["pos"][0, r["valid"][0], :2])
        ref = hits[ref_j].mean(0) if len(hits[ref_j]) else np.zeros(2)
        for j, h in enumerate(hits):
            xy[i][j] = (h - ref) * 1e3
            if len(h):
                rms[i, j] = 1e3 * np.sqrt(np.mean(np.sum((h - h.mean(0)) ** 2, 1)))
        na = M.image_space_na(lens, f, wls[ref_j], device=device)
        airy[i] = 1.22 * wls[ref_j] / (2.0 * na)  # um: 1.22 lambda F#_w
    return xy, rms, airy


def _spots(lens, fields, wls, path, device):
    """Spot diagrams, one panel per field on ONE common scale (um, as Zemax), the Airy circle drawn (black), the
    wavelengths drawn widest spot first so the tightest one lies on top, each with its own marker."""
    plt = _plt()
    xy, rms, airy = spot_data(lens, fields, wls, device)
    ref_j = len(wls) // 2
    half = max([float(np.max(np.abs(d))) for row in xy for d in row if len(d)] + list(airy)) * 1.08
    fig, axes = plt.subplots(1, len(fields), figsize=(3.0 * len(fields) + 0.4, 3.6), squeeze=False)
    colors = {w: plt.cm.turbo(float(np.clip((w - 0.38) / 0.4, 0, 1))) for w in wls}
    markers = ["o", "s", "^", "D", "v", "P", "X"]
    th = np.linspace(0, 2 * np.pi, 181)
    for i, f in enumerate(fields):
        ax = axes[0, i]
        order = np.argsort(-np.nan_to_num(rms[i], nan=np.inf), kind="stable")  # widest first: tightest on top
        for j in order:
            w = wls[j]
            d = xy[i][j]
            ax.scatter(d[:, 0], d[:, 1], s=4, marker=markers[j % len(markers)], facecolors="none",
                       edgecolors=[colors[w]], linewidths=0.5, label=f"{w:g} um")
        ax.plot(airy[i] * np.cos(th), airy[i] * np.sin(th), color="k", lw=0.8,
                label="Airy circle" if i == 0 else None)
        ax.set_xlim(-half, half)
        ax.set_ylim(-half, half)
        ax.set_aspect("equal", adjustable="box")
        ax.set_title(f"{field_label(f)}, Airy radius {airy[i]:.2f} um\nRMS " + " / ".join(f"{x:.2f}" for x in rms[i])
                     + " um", fontsize=8)
        ax.set_xlabel("x (um)", fontsize=8)
        if i == 0:
            ax.set_ylabel("y (um)", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.2)
    h, lab = axes[0, 0].get_legend_handles_labels()
    keep = sorted(range(len(lab)), key=lambda k: lab[k])
    axes[0, -1].legend([h[k] for k in keep], [lab[k] for k in keep], fontsize=6, markerscale=2, loc="upper right")
    fig.suptitle(f"spot diagrams, common scale +-{half:.3g} um (centroid of {wls[ref_j]:g} um at 0, 0); black: Airy "
                 f"circle 1.22 lambda F#_w at {wls[ref_j]:g} um", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)
    return rms


def _psf_grid(m, path, title):
    """PSF map figure: rows wavelengths, columns fields; log10 of each tile over its own peak, colour bar."""
    plt = _plt()
    nf, nw = m.data.shape[:2]
    fig, axes = plt.subplots(nw, nf, figsize=(2.3 * nf + 1.0, 2.2 * nw + 0.6), squeeze=False)
    n = m.data.shape[-1]
    half = 0.5 * n * m.pixel_mm * 1e3
    vf = np.asarray(m.info["valid_fraction"], float).reshape(nf, nw)
    im = None
    for i in range(nf):
        for j in range(nw):
            d = m.data[i, j]
            img = np.log10(np.maximum(d / max(d.max(), 1e-300), 1e-6))
            ax = axes[j, i]
            im = ax.imshow(img, origin="lower", cmap="inferno", vmin=-6, vmax=0, extent=(-half, half, -half, half))
            ax.set_title(f"{field_label(m.fields_deg[i])}, {m.wavelengths_um[j]:g} um\nin patch "
                         f"{d.sum() / max(vf[i, j], 1e-300):.3f}", fontsize=7)
            ax.tick_params(labelsize=6)
            if j == nw - 1:
                ax.set_xlabel("x - centre (um)", fontsize=7)
            if i == 0:
                ax.set_ylabel("y - centre (um)", fontsize=7)
    cb = fig.colorbar(im, ax=axes.ravel().tolist(), shrink=0.8)
    cb.set_label("log10(power per pixel / tile peak)", fontsize=8)
    fig.suptitle(title + " (each tile normalised to its own peak)", fontsize=9)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _line_fig(path, title, xlabel, ylabel, curves, xlim=None, ylim=None, legend=True, legend_outside=False):
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7.6 if legend_outside else 6.2, 4.0))
    for x, y, kw in curves:
        ax.plot(x, y, **kw)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=9)
    if xlim:
        ax.set_xlim(*xlim)
    if ylim:
        ax.set_ylim(*ylim)
    ax.grid(alpha=0.3)
    if legend:
        if legend_outside:
            ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0)
        else:
            ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def _doe_figure(lens, path):
    """Phase (wrapped, rad) and relief height (um) of the DOE over its aperture, with colour bars."""
    from . import doe
    plt = _plt()
    i = lens.doe_index
    s = lens.surfaces[i]
    prof = doe.profile_from_dict(s.profile, base=None if lens.source is None else Path(lens.source).parent)
    h = s.semi_diameter or 1.0
    n = 301
    g = np.linspace(-h, h, n)
    x, y = np.meshgrid(g, g)
    ph = doe.design_phase(prof, x, y, s.design_wavelength_um, s.levels)
    if s.shape == "circle":
        ph = np.where(x * x + y * y <= h * h, ph, np.nan)
    height = doe.height_map_um(np.nan_to_num(ph), s.material, s.design_wavelength_um)
    height = np.where(np.isnan(ph), np.nan, height)
    fig, axes = plt.subplots(1, 2, figsize=(9.5, 3.9))
    hmax = float(doe.height_map_um(np.array([2 * np.pi - 1e-12]), s.material, s.design_wavelength_um)[0])
    for ax, data, lab, cm, lim in ((axes[0], ph, "phase phi0 wrapped (rad)", "twilight", (0, 2 * np.pi)),
                                   (axes[1], height, "relief height (um)", "viridis", (0, hmax))):
        im = ax.imshow(data, origin="lower", extent=(-h, h, -h, h), cmap=cm, vmin=lim[0], vmax=lim[1])
        cb = fig.colorbar(im, ax=ax)
        cb.set_label(lab, fontsize=8)
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
    raw = prof.phase(x, y, s.design_wavelength_um)
    axes[0].set_title(f"DOE phase at {s.design_wavelength_um:g} um ({prof.kind})\nunwrapped range "
                      f"{np.nanmax(raw) - np.nanmin(raw):.3g} rad", fontsize=8)
    axes[1].set_title(f"relief in {s.material}" + (f", {s.levels} levels" if s.levels else ""), fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return float(np.nanmax(raw) - np.nanmin(raw))


# ---------------------------------------------------------------------------------------------- report
def _default_fields(lens, wl):
    if lens.fields_deg:
        return list(lens.fields_deg)
    # the sensor's half height seen through the EFL
    fmax = math.degrees(math.atan(lens.sensor.half_size[1] / abs(lens.efl(wl))))
    return [0.0, round(0.7 * fmax, 2), round(fmax, 2)]


def write_report(lens, out, *, fields_deg=None, wavelengths_um=None, model: str = "ray-wave", psf_size=None,
                 mtf_size=None, through_focus_planes: int = 9, device: str = "cpu",
                 progress: bool = True, lens_label: str | None = None, max_size: int = 256, mtf_max=None) -> Path:
    """Write ``out/report.md`` and its PNG figures for ``lens``; returns the Markdown path.

    ``fields_deg`` (deg; default the lens's fields, else 0, 0.7 and 1 x the sensor's half height),
    ``wavelengths_um`` (um; default the lens's), ``model`` for the PSFs, MTF and encircled energy
    (``"ray-wave"``, ``"ray"`` or ``"paraxial-wave"``), ``psf_size`` (sensor pixels per PSF tile),
    ``mtf_size`` (samples of the finely sampled PSFs behind MTF / encircled energy); both default to
    a size that holds every PSF (:func:`patch_size_for`, at most ``max_size``),
    ``through_focus_planes`` (the first through-focus scan, extended until the best focus lies inside it;
    0 skips it), ``mtf_max``: the MTF plot's last frequency (lp/mm; default 1.2 x the sensor's Nyquist frequency
    or the diffraction cutoff where that is lower; ``"cutoff"``: the cutoff), ``progress``: a bar over the sections. A section that fails
    is reported on the page with its error; the others still run.
    """
    from . import paraxial
    from .psf import psf_map
    if model not in M.MODELS:
        raise ValueError(f"model must be one of {M.MODELS}, got {model!r}")
    for name, v in (("psf_size", psf_size), ("mtf_size", mtf_size)):
        if v is not None and int(v) < 8:
            raise ValueError(f"{name} must be >= 8, got {v}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    wls = [float(w) for w in (wavelengths_um or lens.wavelengths_um)]
    wl0 = wls[len(wls) // 2]
    fields = list(fields_deg) if fields_deg is not None else _default_fields(lens, wl0)
    if psf_size is None:
        psf_size = patch_size_for(lens, fields, wls, lens.sensor.pixel_pitch, max_size, device)
    if mtf_size is None:
        mtf_size = patch_size_for(lens, fields, wls, M.default_sampling_mm(lens, fields, wls, device), max_size,
                                  device)
    y_fields = [float(f) if np.ndim(f) == 0 else float(np.hypot(*f)) for f in fields]
    md = [f"# Lens report: {lens.name or lens_label or 'lens'}", ""]
    if lens_label:
        md += [f"Source: `{lens_label}`. Generated by `rwwarp report` on {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}.",
               ""]
    pup = paraxial.pupils(lens, wl0)
    md += ["## System", "", "| quantity | value |", "|---|---|",
           f"| EFL at {wl0:g} um | {lens.efl(wl0):.6f} mm |", f"| BFL | {lens.bfl(wl0):.6f} mm |",
           f"| F/# (paraxial, object at infinity) | {paraxial.f_number(lens, wl0):.4f} |",
           f"| entrance pupil | diameter {2 * pup.entrance_radius:.4f} mm at z = {pup.entrance_z:.4f} mm |",
           f"| object distance | {lens.object_distance:g} mm |",
           f"| wavelengths | {', '.join(f'{w:g}' for w in wls)} um |",
           f"| fields | {', '.join(field_label(f) for f in fields)} |",
           f"| sensor | {lens.sensor.resolution[0]} x {lens.sensor.resolution[1]} px of "
           f"{lens.sensor.pixel_pitch * 1e3:g} um |",
           f"| figure model | {model} |", ""]
    sections = [("layout", "Layout"), ("spots", "Spot diagrams"), ("psf", "PSFs across the field"),
                ("mtf", "MTF and encircled energy"), ("through_focus", "Through-focus MTF"),
                ("chromatic", "Chromatic focal shift"), ("field", "Field curvature and distortion")]
    if lens.doe_index is not None:
        sections.append(("doe", "DOE phase and height"))
    if not through_focus_planes:
        sections = [s for s in sections if s[0] != "through_focus"]
    it = sections
    bar = None
    if progress:
        from tqdm.auto import tqdm
        bar = tqdm(sections, desc="report", unit="section")
        it = bar
    timings = {}
    for key, title in it:
        if bar is not None:
            bar.set_postfix_str(key)
        t0 = time.perf_counter()
        md += [f"## {title}", ""]
        with warnings.catch_warnings(record=True) as rec:
            warnings.simplefilter("always")
            try:
                md += _section(key, lens, fields, y_fields, wls, wl0, model, psf_size, mtf_size,
                               through_focus_planes, device, out, psf_map, mtf_max)
            except Exception as e:  # a failed section is reported, the others still run
                md += [f"**This section failed:** `{type(e).__name__}: {e}`", "", "```",
                       traceback.format_exc(limit=3).strip(), "```", ""]
        msgs = sorted({str(w.message) for w in rec if issubclass(w.category, Warning)})
        if msgs:
            md += ["Warnings:", ""] + [f"* {m}" for m in msgs] + [""]
        timings[key] = time.perf_counter() - t0
    md += ["## Timings", "", "| section | seconds |", "|---|---|"]
    md += [f"| {k} | {v:.1f} |" for k, v in timings.items()] + [""]
    page = out / "report.md"
    page.write_text("\n".join(md) + "\n")
    return page


def _section(key, lens, fields, y_fields, wls, wl0, model, psf_size, mtf_size, tf_planes, device, out, psf_map,
             mtf_max=None):
    if key == "layout":
        sd = layout_figure(lens, out / "layout.png", fields, wl0, device)
        rows = ["![layout](layout.png)", "",
                "| surface | type | radius (mm) | conic | thickness (mm) | medium after | clear semi-diameter (mm) | notes |",
                "|---|---|---|---|---|---|---|---|"]
        from .lens import surface_notes
        notes = dict(enumerate(surface_notes(lens)))  # as `rwwarp info` prints them (aspheres, thin lens, DOE)
        media = lens.media()
        for i, s in enumerate(lens.surfaces):
            rad = "inf" if s.radius is None else f"{s.radius:.5g}"
            tag = " (set)" if s.semi_diameter is not None else " (rays)"
            conic = f"{s.conic:.6g}" if s.type == "standard" else "-"
            rows.append(f"| {i}{' STOP' if i == lens.stop_index else ''} | {s.type} | {rad} | {conic} | {s.thickness:.5g} | "
                        f"{media[i]} | {sd[i]:.4f}{tag} | {'; '.join(notes.get(i, []))} |")
        return rows + [""]
    if key == "spots":
        rms = _spots(lens, fields, wls, out / "spots.png", device)
        rows = ["![spots](spots.png)", "", "RMS spot radius about each colour's centroid (um):", "",
                "| field | " + " | ".join(f"{w:g} um" for w in wls) + " |", "|---|" + "---|" * len(wls)]
        rows += [f"| {field_label(f)} | " + " | ".join(f"{v:.3f}" for v in rms[i]) + " |" for i, f in enumerate(fields)]
        return rows + [""]
    if key == "psf":
        m = psf_map(lens, fields, wls, model=model, size=psf_size, device=device)
        vf = np.asarray(m.info["valid_fraction"], float).reshape(m.data.shape[:2])
        inside = m.data.sum(axis=(2, 3)) / np.maximum(vf, 1e-300)
        if np.any(inside < 0.98):
            warnings.warn(f"some PSFs do not fit their {psf_size}-pixel tiles (as little as {inside.min():.3f} of "
                          "the power inside): raise --psf-size", M.SamplingWarning)
        _psf_grid(m, out / "psf_map.png", f"{model} PSFs on the sensor pixels ({lens.sensor.pixel_pitch * 1e3:g} um)")
        return ["![psf map](psf_map.png)", "",
                f"{model} PSFs, {psf_size} x {psf_size} sensor pixels of {lens.sensor.pixel_pitch * 1e3:g} um; "
                f"log scale, each tile over its own peak. Power inside each tile (of the power reaching the "
                f"sensor): min {inside.min():.3f}, max {inside.max():.3f}.", ""]
    if key == "mtf":
        pixel = M.default_sampling_mm(lens, fields, wls, device)
        m = psf_map(lens, fields, wls, model=model, size=mtf_size, pixel_mm=pixel, device=device)
        na = max(M.image_space_na(lens, f, min(wls), device=device) for f in fields)
        fc = 2 * na / (min(wls) * 1e-3)
        nyq = 0.5 / lens.sensor.pixel_pitch
        # the axis: a little past the sensor's Nyquist frequency (marked), or the cutoff where lower / asked for
        fmax = fc if mtf_max == "cutoff" else (min(fc, 1.2 * nyq) if mtf_max is None else min(float(mtf_max), fc))
        freqs = np.linspace(0, min(fmax, 0.5 / pixel * 0.98), 61)
        tan, sag = M.mtf_from_psf_map(m, freqs)
        vf = np.asarray(m.info["valid_fraction"], float).reshape(m.data.shape[:2])
        inside = m.data.sum(axis=(2, 3)) / np.maximum(vf, 1e-300)
        if np.any(inside < 0.98):
            warnings.warn(f"the finely sampled PSFs keep as little as {inside.min():.3f} of their power in "
                          f"{mtf_size} samples of {pixel * 1e3:.3g} um: raise --mtf-size", M.SamplingWarning)
        plt = _plt()
        colors = plt.cm.viridis(np.linspace(0, 0.85, len(fields)))
        # polychromatic diffraction limit with the figure's weights (equal): the mean of each wavelength's
        # aberration-free MTF, cutoff 2 NA / lambda each (the limit of the shortest alone is higher)
        dl = polychromatic_diffraction_mtf(freqs, [2 * na / (w * 1e-3) for w in wls])
        curves = [(freqs, dl, dict(color="gray", ls=":", lw=1.5, label="diffraction limit (equal weights)"))]
        for i, f in enumerate(fields):
            curves.append((freqs, tan[i], dict(color=colors[i], label=f"{field_label(f)} T")))
            curves.append((freqs, sag[i], dict(color=colors[i], ls="--", label=f"{field_label(f)} S")))
        if nyq <= freqs[-1] * 1.0001:
            curves.append(([nyq, nyq], [0, 1.02], dict(color="tab:red", lw=0.8, label=f"sensor Nyquist {nyq:.0f} lp/mm")))
        _line_fig(out / "mtf.png", f"polychromatic MTF ({model}; {', '.join(f'{w:g}' for w in wls)} um, equal "
                  f"weights)\nT solid, S dashed; sensor Nyquist {nyq:.0f} lp/mm, diffraction cutoff {fc:.0f} lp/mm",
                  "spatial frequency (lp/mm)", "modulation", curves, xlim=(0, freqs[-1]), ylim=(0, 1.02), legend_outside=True)
        r = np.linspace(0, 0.5 * mtf_size * pixel * 1e3, 81)
        ee = M.energy_from_psf_map(m, r, "encircled")
        curves = [(r, ee[i], dict(color=colors[i], label=field_label(f))) for i, f in enumerate(fields)]
        _line_fig(out / "encircled_energy.png", f"polychromatic encircled energy about the centroid ({model})\n"
                  "fraction of the power reaching the sensor", "radius (um)", "encircled energy", curves,
                  ylim=(0, 1.02))
        at = [f for f in (0.25 * nyq, 0.5 * nyq, nyq) if f <= freqs[-1]]
        tat, sat = M.mtf_from_psf_map(m, at) if at else (np.zeros((len(fields), 0)),) * 2
        rows = ["![mtf](mtf.png)", "", "![encircled energy](encircled_energy.png)", "",
                f"Diffraction cutoff 2 NA / lambda = {fc:.1f} lp/mm (NA {na:.4f}); PSFs sampled at "
                f"{pixel * 1e3:.3g} um on {mtf_size} x {mtf_size} samples (sensor pixel MTF not included).", "",
                "| field | " + " | ".join(f"MTF T/S at {f:.0f} lp/mm" for f in at) + " | 80 % EE radius (um) |",
                "|---|" + "---|" * (len(at) + 1)]
        for i, f in enumerate(fields):
            r80 = float(np.interp(0.8, ee[i], r)) if ee[i].max() >= 0.8 else float("nan")
            rows.append(f"| {field_label(f)} | " + " | ".join(f"{tat[i, k]:.3f} / {sat[i, k]:.3f}" for k in range(len(at)))
                        + f" | {r80:.2f} |")
        if model != "ray":
            st = M.strehl_from_psf_map(lens, m, grid=201, device=device)[0]
            rows += ["", "Strehl ratio (PSF peak over the aberration-free peak of the same pupil):", "",
                     "| field | " + " | ".join(f"{w:g} um" for w in wls) + " |", "|---|" + "---|" * len(wls)]
            rows += [f"| {field_label(f)} | " + " | ".join(f"{v:.4f}" for v in st[i]) + " |"
                     for i, f in enumerate(fields)]
        return rows + [""]
    if key == "through_focus":
        na = M.image_space_na(lens, 0.0, wl0, device=device)
        fc = 2 * na / (wl0 * 1e-3)
        freqs = [0.25 * fc, 0.5 * fc]
        pixel = M.default_sampling_mm(lens, [0.0], [wl0], device)
        dz = 4 * wl0 * 1e-3 / (2 * na) ** 2
        # on axis at focus, widened by the defocus blur 2 NA dz
        size = min(patch_size_for(lens, [0.0], [wl0], pixel, mtf_size, device) + 8 * math.ceil(3.0 * na * dz / pixel / 8),
                   max(mtf_size, 32))
        # the scan is extended past an end while the MTF at freqs[0] still rises there, so the peak is inside
        # it; a parabola through the best plane and its neighbours places it between planes (metrics.best_focus)
        b = M.best_focus(lens, 0.0, wl0, freqs, focus_mm=np.linspace(-1, 1, max(int(tf_planes), 3)) * dz,
                         model=model, size=size, pixel_mm=pixel, device=device)
        t = b.scan
        curves = []
        for k, f in enumerate(freqs):
            curves.append((t.focus_mm * 1e3, t.tangential[:, k], dict(color=f"C{k}", marker=".", label=f"{f:.0f} lp/mm T")))
            curves.append((t.focus_mm * 1e3, t.sagittal[:, k], dict(color=f"C{k}", ls="--", label=f"{f:.0f} lp/mm S")))
        best = b.focus_mm
        curves.append(([best * 1e3] * 2, [0, 1.02], dict(color="k", lw=0.8, ls=":", label=f"best focus {best * 1e3:+.1f} um")))
        _line_fig(out / "through_focus.png", f"through-focus MTF on axis at {wl0:g} um ({model}); T solid, S dashed\n"
                  f"{len(t.focus_mm)} planes, {b.step_mm * 1e3:.3g} um apart; best focus: peak of (T + S) / 2 at "
                  f"{freqs[0]:.0f} lp/mm", "sensor shift (um, + away from the lens)", "modulation", curves, ylim=(0, 1.02))
        where = (f"inside the scan ({t.focus_mm[0] * 1e3:+.1f} .. {t.focus_mm[-1] * 1e3:+.1f} um, {len(t.focus_mm)} "
                 f"planes {b.step_mm * 1e3:.3g} um apart; a parabola through the best plane and its neighbours)"
                 if b.interior else "AT THE END of the scan: the MTF still rises there")
        return ["![through focus](through_focus.png)", "",
                f"Best focus at {freqs[0]:.0f} lp/mm: {best * 1e3:+.2f} um from the sensor plane, {where}.", ""]
    if key == "chromatic":
        c = M.chromatic_focal_shift(lens, reference_um=wl0)
        _line_fig(out / "chromatic_focal_shift.png", f"paraxial chromatic focal shift (reference {wl0:g} um)",
                  "wavelength (um)", "focal shift (um)", [(c.wavelengths_um, c.shift_um, dict(color="C0", label="shift"))],
                  legend=False)
        return ["![chromatic focal shift](chromatic_focal_shift.png)", "",
                f"Range over {c.wavelengths_um[0]:g}-{c.wavelengths_um[-1]:g} um: "
                f"{np.ptp(c.shift_um):.2f} um.", ""]
    if key == "field":
        fmax = max(abs(v) for v in y_fields) or 1.0
        fc = M.field_curves(lens, np.linspace(0, fmax, 21), wl0, device=device)
        plt = _plt()
        fig, axes = plt.subplots(1, 2, figsize=(9, 4))
        axes[0].plot(fc.tangential_mm * 1e3, fc.fields_deg, label="tangential")
        axes[0].plot(fc.sagittal_mm * 1e3, fc.fields_deg, "--", label="sagittal")
        axes[0].set_xlabel("focus - sensor plane (um)")
        axes[0].set_ylabel("field (deg)")
        axes[0].set_title(f"field curvature at {wl0:g} um", fontsize=9)
        axes[0].legend(fontsize=7)
        axes[1].plot(fc.distortion_percent, fc.fields_deg)
        axes[1].set_xlabel("F-tan(theta) distortion (%)")
        axes[1].set_ylabel("field (deg)")
        axes[1].set_title("distortion (real chief ray vs paraxial height)", fontsize=9)
        for ax in axes:
            ax.grid(alpha=0.3)
        fig.tight_layout()
        fig.savefig(out / "field_curves.png", dpi=130)
        plt.close(fig)
        return ["![field curvature and distortion](field_curves.png)", "",
                f"At {fmax:g} deg: tangential {fc.tangential_mm[-1] * 1e3:+.2f} um, sagittal "
                f"{fc.sagittal_mm[-1] * 1e3:+.2f} um, distortion {fc.distortion_percent[-1]:+.4f} %.", ""]
    if key == "doe":
        rng = _doe_figure(lens, out / "doe.png")
        return ["![doe](doe.png)", "", f"Unwrapped phase range over the aperture: {rng:.4g} rad"
                + (" (the DOE is blank: no phase)" if rng == 0 else "") + ".", ""]
    raise ValueError(key)
