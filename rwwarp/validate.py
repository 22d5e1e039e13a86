"""The paper's accuracy study (its Section 4): ray-wave vs scalar-diffraction ground truth vs ray model.

System: an ideal thin lens (f = 100 mm) with a DOE attached, square aperture, lambda = 0.55 um.
DOEs: (a) constant phase (pure aperture diffraction), (b) a continuous kinoform (Fresnel-zone phase
``-pi r^2 / (lambda0 f0)``, wrapped to [0, 2 pi)), (c) the same kinoform quantised to 16 levels on a
10 um pixel map (discontinuous). The sensor sits at the paraxial focus of lens + DOE.
Ground truth: :func:`rwwarp.ground_truth.rs_thin_lens_psf`, a direct Rayleigh-Sommerfeld summation
independent of the angular-spectrum code. Lengths in mm, wavelength in um.
"""
from __future__ import annotations

import time
import warnings
from pathlib import Path

import numpy as np

from .errors import LensError


def _case_lens(kind, side_mm, f_mm, f0_mm, pixel_mm, doe_pitch_mm):
    from .lens import Lens, Surface, Sensor
    from . import doe
    dist = f_mm if kind == "a" else 1.0 / (1.0 / f_mm + 1.0 / f0_mm)
    surfs = [Surface(type="aperture", semi_diameter=side_mm / 2, shape="square", stop=True),
             Surface(type="thin_lens", focal_length=f_mm, semi_diameter=side_mm, shape="square", thickness=0.0)]
    if kind == "a":
        prof = {"kind": "even_poly", "norm_radius": side_mm / 2, "coefficients": [0.0]}
        gt_phase = None
    elif kind == "b":
        prof = {"kind": "fresnel", "focal_length": f0_mm}
        k0 = np.pi / (0.55e-3 * f0_mm)
        gt_phase = lambda x, y: -k0 * (x * x + y * y)  # exp(i wrap(phi)) = exp(i phi) at the design wavelength
    else:
        n = int(round(side_mm / doe_pitch_mm))
        c = (np.arange(n) - (n - 1) / 2) * doe_pitch_mm
        x, y = np.meshgrid(c, -c, indexing="xy")  # row 0 at +y (doe.py pixel-map convention)
        phi = doe.quantize(-np.pi * (x * x + y * y) / (0.55e-3 * f0_mm), 16)
        prof = {"kind": "pixel_map", "pitch": doe_pitch_mm, "data": phi.tolist()}
        gt_phase = (phi, doe_pitch_mm)
    surfs.append(Surface(type="doe", semi_diameter=side_mm / 2, shape="square", thickness=dist, profile=prof,
                         design_wavelength_um=0.55, material="1.5/1e9"))
    lens = Lens(surfs, Sensor(pixel_mm, (4000, 4000)), wavelengths_um=[0.55], name=f"validation ({kind})")
    return lens, dist, gt_phase


def run_validation(out: Path, device: str = "cpu", quick: bool = False, side_mm: float = 2.0, progress=None) -> str:
    """Run the three cases, write ``report.md`` and ``validation.png`` into ``out``; return the Markdown.
    ``progress``: a callable given one line of text as each step starts and ends (``rwwarp validate``
    prints them on stderr), or None."""
    say = progress or (lambda msg: None)
    t_all = time.perf_counter()
    from .psf import psf
    from .ground_truth import rs_thin_lens_psf
    from .plots import _plt
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    f_mm, f0_mm = 100.0, 1000.0
    size = 32 if quick else 64
    pixel = 0.55e-3 * f_mm / side_mm / 3  # 3 pixels per lambda f / a
    rows, panels = [], []
    names = {"a": "(a) constant phase, square aperture", "b": "(b) continuous kinoform (Fresnel zones)",
             "c": "(c) 16-level discontinuous (10 um pixels)"}
    for kind in ("a", "b", "c"):
        lens, dist, gt_phase = _case_lens(kind, side_mm, f_mm, f0_mm, pixel, 0.01)
        say(f"[{'abc'.index(kind) + 1}/3] {names[kind]}: ray-wave PSF, {size} px ...")
        t = time.perf_counter()
        p = psf(lens, 0.0, 0.55, size=size, device=device, nyquist_safety=3.0)
        t_rw = time.perf_counter() - t
        x, y = p.coords_mm()
        say(f"      ray-wave {t_rw:.1f} s; Rayleigh-Sommerfeld ground truth ...")
        t = time.perf_counter()
        gt = rs_thin_lens_psf(f_mm, "square", side_mm / 2, 0.55, dist, x, y, pixel, doe_phase=gt_phase)
        t_gt = time.perf_counter() - t
        err = float(np.linalg.norm(p.data - gt) / np.linalg.norm(gt))
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                r = psf(lens, 0.0, 0.55, size=size, model="ray", center_mm=p.center_mm)
            ray_err = float(np.linalg.norm(r.data - gt) / np.linalg.norm(gt))
            ray_img, ray_txt = r.data, f"{ray_err:.3g}"
        except LensError as e:
            ray_img, ray_txt = None, "refused: " + str(e).split(": ", 1)[-1].split(".")[0]
        say(f"      ground truth {t_gt:.1f} s; rel. L2 error {err:.3g} ({time.perf_counter() - t_all:.0f} s so far)")
        rows.append((names[kind], err, ray_txt, t_rw, t_gt, p.plan["n_grid"], p.plan["n_pad"]))
        panels.append((names[kind], p.data, gt, ray_img))
    plt = _plt()
    fig, axes = plt.subplots(3, 3, figsize=(9.6, 9), layout="constrained")
    half = size * pixel * 1e3 / 2  # um
    ext = [-half, half, -half, half]
    im = None
    for i, (name, a, b, c) in enumerate(panels):
        vmax = b.max()
        for j, (img, title) in enumerate(((a, "ray-wave"), (b, "ground truth (RS)"), (c, "ray model"))):
            ax = axes[i, j]
            ax.tick_params(labelsize=7)
            if img is None:
                ax.set_xticks([])
                ax.set_yticks([])
                ax.text(0.5, 0.5, "cannot model a\ndiscontinuous phase", ha="center", va="center")
            else:
                im = ax.imshow(np.log10(np.maximum(img / vmax, 1e-5)), origin="lower", cmap="inferno", vmin=-5,
                               vmax=0, extent=ext)
            if i == 0:
                ax.set_title(title)
            if i == 2:
                ax.set_xlabel("x (um)", fontsize=8)
            if j == 0:
                ax.set_ylabel(f"{name}\ny (um)", fontsize=8)
    cb = fig.colorbar(im, ax=axes, shrink=0.8, pad=0.02)
    cb.set_label("log10(power per pixel / ground-truth peak of the row)")
    fig.suptitle(f"thin lens f = {f_mm:g} mm + DOE, {side_mm:g} mm square aperture, 0.55 um (log10 PSF, {size} px of "
                 f"{pixel * 1e3:.3g} um; each row over its ground truth's peak)", fontsize=9)
    fig.savefig(out / "validation.png", dpi=110)
    plt.close(fig)
    md = ["# Ray-wave validation against scalar diffraction", "",
          f"Thin lens f = {f_mm:g} mm with a DOE attached, {side_mm:g} mm square aperture, 0.55 um; "
          f"{size}x{size} sensor pixels of {pixel * 1e3:.3g} um at the focus of lens + DOE (f0 = {f0_mm:g} mm "
          f"for (b), (c)). Ground truth: direct Rayleigh-Sommerfeld summation (rwwarp.ground_truth). "
          f"Device {device}.", "",
          "| DOE | ray-wave rel. L2 error | ray model rel. L2 error | ray-wave time (s) | ground truth time (s) | grid | FFT |",
          "|---|---|---|---|---|---|---|"]
    for name, err, ray_txt, t_rw, t_gt, ng, npd in rows:
        md.append(f"| {name} | {err:.3g} | {ray_txt} | {t_rw:.2f} | {t_gt:.1f} | {ng} | {npd} |")
    md += ["", "![log PSFs](validation.png)", ""]
    text = "\n".join(md)
    (out / "report.md").write_text(text)
    return text
