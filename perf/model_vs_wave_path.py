"""The paper's three experiments: the one-step ray-wave model against the wave path (issue 27).

For each design experiment (``torch_bridge/configs/{cooke_hybrid,a489_aberration,a489_edof}.yaml``, its ``gpu``
preset: the paper's aperture, PSF size, pixel and sampling) this computes the experiment's PSFs twice:

* **one-step** (``method="auto"``, no tolerance): the geometric field formed on the DOE's wave plane, then
  propagated (the paper's model);
* **wave path** (``method="two-step"``): the same plan with the wave step (:mod:`rwwarp.wave.wave_step`): the
  geometric field's edge diffracted as a wave from the stop's image to the DOE before the DOE,

for the starting lens the config builds (``torch_bridge.config.build_lens``; the Cooke arms all start from the
paraxial achromat, as ``torch_bridge.train.Arm`` makes it) and for a stored design of
``perf/results/design/`` (evaluated as stored: its own aperture). Per PSF it reports max |difference| over the
wave path's peak, the planner's model-error estimate (``Plan.model_error``) and its ratio to that difference,
which method ``"auto"`` picks and whether ``"auto"`` with ``tolerance=TOLERANCE`` would add the step, the
relative change of the peak intensity (Strehl-like: ``rwwarp.metrics.strehl.peak_intensity_from_psf``), of the
RMS radius and of the 80 % encircled-energy radius, the power in the patch, the wave step's second-order
shift ``s`` of the lens's own aberration (the plan's reasons) and the phase error it brings, ``pi s^2 / (lambda
d)`` (rad; the wave path is taken as a reference only where it is below ``STEP_PHASE_MAX``: docs/accuracy.md),
and both times. For a lens whose DOE is flat it also moves the wave plane to the last refracting surface (the DOE
removed) and reports how much that changes the one-step PSF: a part of the model's error that needs no step.
``--grid-check`` adds the one-step PSF on the wave path's own plan (the step apart from its finer grid).

Then it renders test images with both PSF sets, as the experiments' evaluation does (patch rendering: each
node's PSFs, one wavelength per colour channel, normalised to unit sum, blur the same fixed crops; raw
images, no network, no noise), and reports PSNR / SSIM between the two renderings and of each against the
sharp image. Images: scikit-image's bundled validation samples (``torch_bridge.data.SKIMAGE_VALID``: the
cpu presets' images, offline), or ``--data-root`` (e.g. ``data/debian-photos``).

Fields: the sensor positions of the experiment's nodes (``torch_bridge.design.node_positions_mm``), a 3 x 3
grid over the sensor quadrant (the 10 x 10 evaluation grid, coarsened; its 6 nodes on and above the diagonal,
the lenses being rotationally symmetric) for the Cooke and A489 starting lenses and the config's diagonal (0, 0.5,
0.9 of the corner) for the EDoF start (at two depths) and the stored designs; wavelengths: the middle one of each
colour channel (0.63, 0.55, 0.47 um); EDoF: the evaluation depths 200 mm and 10 m. ``--quick``: the starting
lenses only, two diagonal nodes (0 and 0.9), 0.55 um, EDoF at 200 mm (under a minute). The whole run: about 9
minutes on 2 shared CPU cores. CPU only (PoCL); lengths mm, wavelengths um, fields deg.

Usage: python perf/model_vs_wave_path.py [--quick] [--out perf/results/model_vs_wave_path.json] [--plot docs/model_vs_wave_path.png]
       python perf/model_vs_wave_path.py --replot perf/results/model_vs_wave_path.json [--plot ...]
"""
from __future__ import annotations

import argparse
import math
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(ROOT))

import rwwarp as rw                                            # noqa: E402
from _common import device_name, git_commit                   # noqa: E402

#: the tolerance "auto" is asked for (relative to the peak): the experiments' sensor read noise, 1 % of full scale
TOLERANCE = 1e-2
#: the middle wavelength of each colour channel of the configs (R, G, B), um
WAVELENGTHS_UM = (0.63, 0.55, 0.47)
DESIGNS = ROOT / "perf" / "results" / "design"
#: the wave step's own phase error (rad, at the worst ray: ``one_psf``) below which its result is taken as the
#: reference: a phase error phi at the rim moves the PSF by about phi^2 / 10 of its peak (below 1e-3 here)
STEP_PHASE_MAX = 0.1
#: encircled-energy fraction of the reported radius
EE_FRACTION = 0.8


# ---------------------------------------------------------------------------------------------- scenes
def experiment_config(name: str, preset: str = "gpu") -> tuple:
    """(config of the experiment's first arm under ``preset``, config file)."""
    from torch_bridge.config import CONFIG_DIR, load_config
    src = CONFIG_DIR / f"{name}.yaml"
    return load_config(src, preset)["arms"][0]["config"], src


def starting_lens(cfg: dict, src):
    """The lens the config builds, with the starting DOE its arms use: the Cooke arms' paraxial achromat
    (``design.init: paraxial_achromat``, as ``torch_bridge.train.Arm._achromat``), else the config's DOE."""
    from torch_bridge.config import build_lens
    lens = build_lens(cfg, src)
    if cfg["design"]["init"] in ("paraxial_achromat", "rms") or cfg["design"]["method"] == "paraxial_achromat":
        from torch_bridge.ray_spot import with_paraxial_achromat
        lens = with_paraxial_achromat(lens, [w for c in cfg["optics"]["wavelengths_um"] for w in c])
    return lens


def node_fields(lens, cfg: dict, layout: str, grid=(3, 3), fractions=(0.0, 0.5, 0.9)) -> tuple:
    """(sensor positions (mm), field angles (x, y) deg) of the experiment's nodes (``torch_bridge.design``)."""
    from torch_bridge import design as dz
    half = cfg["optics"]["nodes"]["half_size_mm"]
    pos = dz.node_positions_mm(layout, half, grid, list(fractions), "quadrant")
    return pos, dz.field_angles(lens, pos, 0.55)


def cases(quick: bool) -> list:
    """The scenes: dicts with ``experiment``, ``variant``, ``lens``, ``positions_mm``, ``fields_deg``,
    ``wavelengths_um``, ``depths_mm`` (None: the lens's object distance), ``psf_kw`` and ``note``."""
    out = []
    for exp in ("cooke_hybrid", "a489_aberration", "a489_edof"):
        cfg, src = experiment_config(exp)
        o = cfg["optics"]
        kw = dict(size=int(o["psf_size"]), pixel_mm=float(o["pixel_um"]) * 1e-3, nyquist_safety=o["nyquist_safety"],
                  rays_per_sample=o["rays_per_sample"], focal_patch_tol=o["focal_patch_tol"],
                  pixel_values=o["pixel_values"])
        depths = [None] if exp != "a489_edof" else ([200.0] if quick else [200.0, 10000.0])
        lens = starting_lens(cfg, src)
        if quick:
            pos, fl = node_fields(lens, cfg, "diagonal", fractions=(0.0, 0.9))
            wls = [0.55]
        elif exp == "a489_edof":   # its flat starting DOE: the A489 refocused, at two depths: the diagonal
            pos, fl = node_fields(lens, cfg, "diagonal")
            wls = list(WAVELENGTHS_UM)
        else:   # the 3 x 3 grid's nodes on and above the diagonal (the lenses are rotationally symmetric: the
            # three below mirror them; a first run gave them identical numbers)
            pos, fl = node_fields(lens, cfg, "grid", grid=(3, 3))
            keep = [k for k, (x, y) in enumerate(pos) if y >= x - 1e-9]
            pos, fl = [pos[k] for k in keep], [fl[k] for k in keep]
            wls = list(WAVELENGTHS_UM)
        start_note = ("paraxial achromat (the arms' start)" if exp == "cooke_hybrid"
                      else "the config's DOE (blank)" if exp == "a489_aberration" else "the config's DOE (flat)")
        out.append(dict(experiment=exp, variant="start", lens=lens, positions_mm=pos, fields_deg=fl,
                        wavelengths_um=wls, depths_mm=depths, psf_kw=kw,
                        note=f"gpu preset (paper aperture, EPD {lens_epd(lens):.4g} mm); DOE: {start_note}"))
        if quick:
            continue
        stored = {"cooke_hybrid": "cooke_hybrid_cpu_long/e2e", "a489_aberration": "a489_aberration_gpu_short/e2e_doe",
                  "a489_edof": "a489_edof_cpu/raywave_doe"}[exp]
        p = DESIGNS / stored / "lens.json"
        if not p.exists():
            out.append(dict(experiment=exp, variant="designed", lens=None, note=f"no stored design ({p} missing)"))
            continue
        dl = rw.load_lens(p)
        pos, fl = node_fields(dl, cfg, "diagonal")
        out.append(dict(experiment=exp, variant="designed", lens=dl, positions_mm=pos, fields_deg=fl,
                        wavelengths_um=list(WAVELENGTHS_UM), depths_mm=depths, psf_kw=kw,
                        note=f"stored design perf/results/design/{stored}/lens.json, evaluated as stored "
                             f"(EPD {lens_epd(dl):.4g} mm)"))
    return out


def lens_epd(lens) -> float:
    """Entrance pupil diameter (mm) at 0.55 um."""
    from rwwarp import paraxial
    return 2.0 * paraxial.pupils(lens, 0.55).entrance_radius


# ---------------------------------------------------------------------------------------------- metrics
def rms_radius_um(a: np.ndarray, pixel_mm: float) -> float:
    """RMS radius (um) of a PSF patch about its centroid (pixel centres, the patch's power)."""
    n = a.shape[0]
    c = (np.arange(n) - n // 2) * pixel_mm
    tot = a.sum()
    x0, y0 = (a.sum(0) @ c) / tot, (a.sum(1) @ c) / tot
    r2 = (c[None, :] - x0) ** 2 + (c[:, None] - y0) ** 2
    return float(np.sqrt((a * r2).sum() / tot) * 1e3)


def ee_radius_um(a: np.ndarray, pixel_mm: float, fraction: float = EE_FRACTION) -> float:
    """Radius (um) about the centroid holding ``fraction`` of the patch's power (linear interpolation of
    ``rwwarp.metrics.energy.encircled_energy_from_psf`` on a 1/8-pixel radius grid)."""
    from rwwarp.metrics.energy import encircled_energy_from_psf
    r = np.arange(1, 8 * a.shape[0] // 2 + 1) * pixel_mm / 8
    ee = encircled_energy_from_psf(a, pixel_mm, r, sub=8)
    k = int(np.searchsorted(ee, fraction))
    if k == 0:
        return float(r[0] * 1e3)
    if k >= len(r):
        return float("nan")
    return float((r[k - 1] + (fraction - ee[k - 1]) / (ee[k] - ee[k - 1]) * (r[k] - r[k - 1])) * 1e3)


def shift_from_reasons(plan: dict) -> tuple:
    """(second-order shift, pitch) in um from a wave-step plan's reasons, or (nan, nan)."""
    import re
    for r in plan.get("reasons", []):
        m = re.search(r"second-order shift <= ([0-9.eE+-]+) um \(pitch ([0-9.eE+-]+) um\)", r)
        if m:
            return float(m.group(1)), float(m.group(2))
    return float("nan"), float("nan")


def one_psf(lens, field, wl, depth, kw, moved=None, grid_check: bool = False) -> dict:
    """Both PSFs of one source and the row of the table (``psf_one``, ``psf_two``: the arrays); with ``moved``
    (:func:`without_flat_doe`) also the one-step PSF with the wave plane moved to the last refracting surface
    (``moved_vs_one``, ``moved_vs_two``: max |difference| over the peak); with ``grid_check`` also the one-step
    PSF on the wave path's own plan (its pitch and widened window, without the step): ``grid_vs_two`` is the step's
    effect alone, ``grid_vs_one`` the sampling change."""
    row = {"field_deg": [float(field[0]), float(field[1])], "wavelength_um": wl, "depth_mm": depth}
    kw = dict(kw)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        t = time.perf_counter()
        one = rw.psf(lens, field, wl, method="auto", object_distance_mm=depth, **kw)
        row["time_one_s"] = time.perf_counter() - t
        t = time.perf_counter()
        two = rw.psf(lens, field, wl, method="two-step", object_distance_mm=depth, **kw)
        row["time_two_s"] = time.perf_counter() - t
        auto_tol = rw.plan_psf(lens, field, wl, size=kw["size"], pixel_mm=kw["pixel_mm"], method="auto",
                               rays_per_sample=kw["rays_per_sample"], nyquist_safety=kw["nyquist_safety"],
                               object_distance_mm=depth, focal_patch_tol=kw["focal_patch_tol"], tolerance=TOLERANCE)
    row["warnings"] = sorted({f"{type(w.message).__name__ if isinstance(w.message, Warning) else w.category.__name__}: "
                              f"{str(w.message)[:160]}" for w in caught})
    from rwwarp.metrics.strehl import peak_intensity_from_psf
    a, b = one.data, two.data
    me = one.plan.get("model_error") or {}
    diff = float(np.max(np.abs(a - b)) / b.max())
    pa, pb = peak_intensity_from_psf(a, one.pixel_mm)[0], peak_intensity_from_psf(b, two.pixel_mm)[0]
    shift, pitch = shift_from_reasons(two.plan)
    d_mm = two.plan.get("wave_step_mm") or 0.0
    # the step's own error: the rays carried the beam's aberration W (against the sphere of its focus before the
    # DOE) to the plane; P_d moves it again, by s = d lambda |grad W| / 2 pi, and adds the Fresnel phase
    # lambda d |grad W|^2 / 4 pi = pi s^2 / (lambda d) (rad, at the worst pilot ray; air after the DOE)
    step_phase = math.pi * (shift * 1e-3) ** 2 / (wl * 1e-3 * d_mm) if d_mm > 0 and math.isfinite(shift) else float("nan")
    row.update({
        "auto_method": one.plan["method"], "two_step_method": two.plan["method"],
        "auto_tolerance_adds_step": bool(auto_tol.wave_step_mm),
        "wave_step_mm": two.plan.get("wave_step_mm"),
        "estimate": me.get("estimate"), "fresnel_number": me.get("fresnel_number"), "rim_slope_rad": me.get("rim_slope_rad"),
        # the estimate's parts (rwwarp.wave.model_error: the main order's and the wrapped DOE's other orders')
        "main_estimate": me.get("main_estimate"), "orders_estimate": me.get("orders_estimate"),
        # the planner's own reading of the step's phase error (rwwarp.wave.wave_step.step_phase_rad)
        "plan_step_phase_rad": (two.plan.get("model_error") or {}).get("step_phase_rad"),
        "max_diff_over_peak": diff,
        "estimate_over_measured": (me.get("estimate") / diff) if (me.get("estimate") is not None and diff > 0) else None,
        "peak_rel_change": float(pa / pb - 1.0),
        "rms_radius_um": [rms_radius_um(a, one.pixel_mm), rms_radius_um(b, two.pixel_mm)],
        "ee80_radius_um": [ee_radius_um(a, one.pixel_mm), ee_radius_um(b, two.pixel_mm)],
        "power_in_patch": [float(a.sum()), float(b.sum())],
        "second_order_shift_um": shift, "wave_step_pitch_um": pitch,
        "step_phase_rad": step_phase,
        "step_validated": bool(step_phase <= STEP_PHASE_MAX) if math.isfinite(step_phase) else None,
    })
    row["rms_rel_change"] = row["rms_radius_um"][0] / row["rms_radius_um"][1] - 1.0
    row["ee80_rel_change"] = row["ee80_radius_um"][0] / row["ee80_radius_um"][1] - 1.0
    if grid_check:
        import dataclasses
        from rwwarp.wave.plan import Plan
        names = {f.name for f in dataclasses.fields(Plan)}
        pl = Plan(**{**{k: v for k, v in two.plan.items() if k in names}, "wave_step_mm": None})
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            g = rw.psf(lens, field, wl, method="auto", plan=pl, object_distance_mm=depth, **kw).data
        row["grid_vs_two"] = float(np.max(np.abs(g - b)) / b.max())
        row["grid_vs_one"] = float(np.max(np.abs(g - a)) / b.max())
    if moved is not None:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            t = time.perf_counter()
            m = rw.psf(moved, field, wl, method="auto", object_distance_mm=depth, **kw).data
            row["time_moved_s"] = time.perf_counter() - t
        row["moved_vs_one"] = float(np.max(np.abs(m - a)) / m.max())
        row["moved_vs_two"] = float(np.max(np.abs(m - b)) / b.max())
    row["psf_one"], row["psf_two"] = a, b
    return row


def without_flat_doe(lens):
    """``lens`` with its flat (blank) DOE removed, the gap behind it added to the last refracting surface: the
    wave plane moves to that surface's vertex plane, so the one-step model propagates the field as a wave over
    the gap it leaves out at the DOE. None where the DOE is not flat or not the last surface."""
    import copy
    from rwwarp.doe import is_flat_profile
    d = lens.doe_index
    if d is None or d != len(lens.surfaces) - 1 or not is_flat_profile(lens.surfaces[d].profile):
        return None
    s = list(lens.surfaces)
    rear = copy.deepcopy(s[d - 1])
    rear.thickness = s[d - 1].thickness + s[d].thickness
    return lens.replace(surfaces=s[:d - 1] + [rear])


def applicability(lens) -> str:
    """Whether the wave path applies to ``lens`` and why (the DOE is the wave plane, behind every refracting
    surface; a pixel-map DOE has no slope for the estimate)."""
    d = lens.doe_index
    if d is None:
        return "no DOE: the wave plane is the last surface; the step still applies (the estimate counts the lens's own wavefront)"
    after = [s.type for s in lens.surfaces[d + 1:] if s.type not in ("aperture",)]
    if after:
        return f"the DOE (surface {d}) has refracting surfaces behind it ({after}): the wave plane is not the DOE"
    kind = (lens.surfaces[d].profile or {}).get("kind")
    if kind == "pixel_map":
        return "pixel-map DOE: the estimate leaves its phase slope out (Plan.model_error note); the step applies"
    return (f"applicable: the DOE (surface {d}, {kind}, levels {lens.surfaces[d].levels}) is the wave plane, "
            f"behind the last refracting surface, stop = surface {lens.stop_index}")


# ---------------------------------------------------------------------------------------------- images
def test_crops(data_root, crop: int, per_image: int = 2, seed: int = 0) -> tuple:
    """(crops (N, 3, crop, crop) float64 in [0, 1], description): fixed, seeded crops of the validation images."""
    from torch_bridge.data import ImageSet
    s = ImageSet(data_root, "valid", crop)
    rng = np.random.default_rng(seed)
    out = []
    for im in s.images:
        im = im.numpy().astype(np.float64)
        H, W = im.shape[1:]
        for _ in range(per_image):
            y, x = int(rng.integers(0, H - crop + 1)), int(rng.integers(0, W - crop + 1))
            out.append(im[:, y:y + crop, x:x + crop])
    what = ("scikit-image's bundled validation samples " + ", ".join(f.name for f in s.files)) if data_root is None \
        else f"{data_root} (valid split: {', '.join(f.name for f in s.files)})"
    return np.stack(out), f"{what}; {per_image} seeded {crop} px crops each"


def render(crops: np.ndarray, psfs_rgb: np.ndarray) -> np.ndarray:
    """Each colour channel of ``crops`` (N, 3, H, W) blurred by its PSF (``psfs_rgb`` (3, k, k), normalised to
    unit sum here), reflect padding, 'same' size."""
    from scipy.signal import fftconvolve
    k = psfs_rgb.shape[-1]
    h = k // 2
    out = np.empty_like(crops)
    for c in range(3):
        p = psfs_rgb[c] / psfs_rgb[c].sum()
        pad = np.pad(crops[:, c], ((0, 0), (h, h), (h, h)), mode="reflect")
        out[:, c] = fftconvolve(pad, p[None], mode="same", axes=(1, 2))[:, h:-h, h:-h]
    return np.clip(out, 0.0, 1.0)


def image_metrics(a: np.ndarray, b: np.ndarray) -> tuple:
    """(PSNR dB, SSIM) averaged over the images of two (N, 3, H, W) stacks in [0, 1]."""
    from skimage.metrics import peak_signal_noise_ratio, structural_similarity
    ps = [peak_signal_noise_ratio(x, y, data_range=1.0) for x, y in zip(a, b)]
    ss = [structural_similarity(x, y, data_range=1.0, channel_axis=0) for x, y in zip(a, b)]
    return float(np.mean(ps)), float(np.mean(ss))


# ---------------------------------------------------------------------------------------------- run
def run(quick: bool, data_root=None, crop: int = 128, log=print, grid_check: bool = False) -> dict:
    """Every case's rows and renderings (module docstring)."""
    t_all = time.perf_counter()
    crops, img_desc = test_crops(data_root, crop)
    result = {"commit": git_commit(), "machine": device_name("cpu"), "device": "cpu", "quick": quick,
              "tolerance": TOLERANCE, "images": img_desc, "cases": []}
    for c in cases(quick):
        entry = {k: c[k] for k in ("experiment", "variant", "note")}
        if c["lens"] is None:
            result["cases"].append(entry)
            log(f"{c['experiment']} {c['variant']}: {c['note']}")
            continue
        lens = c["lens"]
        moved = without_flat_doe(lens)
        entry.update({"applicability": applicability(lens), "moved_plane": moved is not None, "positions_mm": [list(map(float, p)) for p in c["positions_mm"]],
                      "wavelengths_um": c["wavelengths_um"], "depths_mm": c["depths_mm"],
                      "psf_size": c["psf_kw"]["size"], "pixel_um": c["psf_kw"]["pixel_mm"] * 1e3, "rows": [], "images": []})
        for depth in c["depths_mm"]:
            for i, fl in enumerate(c["fields_deg"]):
                one_rgb, two_rgb = [], []
                for wl in c["wavelengths_um"]:
                    row = one_psf(lens, fl, wl, depth, c["psf_kw"], moved, grid_check)
                    row["node"] = i
                    row["position_mm"] = [float(v) for v in c["positions_mm"][i]]
                    one_rgb.append(row.pop("psf_one"))
                    two_rgb.append(row.pop("psf_two"))
                    entry["rows"].append(row)
                    log(f"{c['experiment']:16s} {c['variant']:8s} depth {depth} node {i} ({fl[0]:.2f}, {fl[1]:.2f}) deg "
                        f"{wl} um: auto {row['auto_method']}{'+step' if row['auto_tolerance_adds_step'] else ''}, "
                        f"diff {row['max_diff_over_peak']:.2e}, estimate {row['estimate']:.2e}, peak "
                        f"{row['peak_rel_change']:+.2e}, EE80 {row['ee80_rel_change']:+.2e}, "
                        f"{row['time_one_s']:.2f} / {row['time_two_s']:.2f} s, step phase {row['step_phase_rad']:.2g} rad"
                        + (f", moved plane {row['moved_vs_one']:.2e}" if moved is not None else "")
                        + (f", step alone {row['grid_vs_two']:.2e}, grid {row['grid_vs_one']:.1e}" if grid_check else ""))
                if len(one_rgb) == 3:
                    r1, r2 = render(crops, np.stack(one_rgb)), render(crops, np.stack(two_rgb))
                    p12, s12 = image_metrics(r1, r2)
                    p1, s1 = image_metrics(crops, r1)
                    p2, s2 = image_metrics(crops, r2)
                    entry["images"].append({"node": i, "depth_mm": depth, "psnr_one_vs_two": p12, "ssim_one_vs_two": s12,
                                            "psnr_sharp_one": p1, "ssim_sharp_one": s1, "psnr_sharp_two": p2,
                                            "ssim_sharp_two": s2})
        rows = entry["rows"]
        entry["summary"] = summarize(rows, entry["images"])
        result["cases"].append(entry)
    result["total_s"] = time.perf_counter() - t_all
    return result


def summarize(rows: list, images: list) -> dict:
    """Medians and extremes of a case's rows and renderings."""
    d = np.array([r["max_diff_over_peak"] for r in rows])
    e = np.array([r["estimate"] for r in rows])
    out = {"n_psfs": len(rows), "max_diff_over_peak": [float(d.min()), float(np.median(d)), float(d.max())],
           "estimate": [float(e.min()), float(np.median(e)), float(e.max())],
           "estimate_over_measured": [float(np.min(e / d)), float(np.median(e / d)), float(np.max(e / d))],
           "peak_rel_change_maxabs": float(np.max(np.abs([r["peak_rel_change"] for r in rows]))),
           "rms_rel_change_maxabs": float(np.nanmax(np.abs([r["rms_rel_change"] for r in rows]))),
           "ee80_rel_change_maxabs": float(np.nanmax(np.abs([r["ee80_rel_change"] for r in rows]))),
           "auto_methods": sorted({r["auto_method"] for r in rows}),
           "auto_tolerance_adds_step": int(sum(r["auto_tolerance_adds_step"] for r in rows)),
           "step_not_validated": int(sum(r["step_validated"] is False for r in rows)),
           "step_phase_rad": [float(np.nanmin([r["step_phase_rad"] for r in rows])),
                              float(np.nanmax([r["step_phase_rad"] for r in rows]))],
           "time_one_s": float(sum(r["time_one_s"] for r in rows)), "time_two_s": float(sum(r["time_two_s"] for r in rows))}
    ok = [r for r in rows if r["step_validated"]]
    if ok:
        dv = np.array([r["max_diff_over_peak"] for r in ok])
        ev = np.array([r["estimate"] for r in ok])
        out["validated"] = {"n": len(ok), "max_diff_over_peak": [float(dv.min()), float(np.median(dv)), float(dv.max())],
                            "estimate_over_measured": [float(np.min(ev / dv)), float(np.median(ev / dv)), float(np.max(ev / dv))]}
    if "moved_vs_one" in rows[0]:
        mv = np.array([r["moved_vs_one"] for r in rows])
        out["moved_vs_one"] = [float(mv.min()), float(np.median(mv)), float(mv.max())]
    if images:
        out["psnr_one_vs_two_min"] = float(min(i["psnr_one_vs_two"] for i in images))
        out["ssim_one_vs_two_min"] = float(min(i["ssim_one_vs_two"] for i in images))
        out["psnr_sharp_one_mean"] = float(np.mean([i["psnr_sharp_one"] for i in images]))
        out["psnr_sharp_two_mean"] = float(np.mean([i["psnr_sharp_two"] for i in images]))
        out["ssim_sharp_one_mean"] = float(np.mean([i["ssim_sharp_one"] for i in images]))
        out["ssim_sharp_two_mean"] = float(np.mean([i["ssim_sharp_two"] for i in images]))
        out["psnr_sharp_change_maxabs"] = float(max(abs(i["psnr_sharp_one"] - i["psnr_sharp_two"]) for i in images))
    return out


def table(result: dict) -> str:
    """The markdown table of the cases' summaries."""
    tol = result["tolerance"]
    lines = ["| experiment | lens | PSFs | `auto` picks; adds the step at tolerance %g | max diff / peak (min / median / max) "
             "| estimate / measured (min / median / max) | step's own phase (rad, max); PSFs where it is < %g rad: their max diff "
             "| wave plane moved to the last lens surface: change (max) | peak, EE80 radius: largest relative change "
             "| PSNR one-step vs wave path (worst node) | PSNR vs sharp (mean): one-step / wave path | time one-step / wave path |"
             % (tol, STEP_PHASE_MAX),
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    g = lambda v: " / ".join(f"{x:.2g}" for x in v)
    for c in result["cases"]:
        s = c.get("summary")
        if not s:
            lines.append(f"| {c['experiment']} | {c['variant']} | - | {c['note']} | | | | | | | | |")
            continue
        v = s.get("validated")
        val = f"{s['step_phase_rad'][1]:.2g}; " + (f"{v['n']}: {v['max_diff_over_peak'][2]:.2g}" if v else "none")
        lines.append(
            f"| {c['experiment']} | {c['variant']} | {s['n_psfs']} | {', '.join(s['auto_methods'])}; "
            f"{s['auto_tolerance_adds_step']}/{s['n_psfs']} | {g(s['max_diff_over_peak'])} | {g(s['estimate_over_measured'])} "
            f"| {val} | {s['moved_vs_one'][2]:.2g} |" if "moved_vs_one" in s else
            f"| {c['experiment']} | {c['variant']} | {s['n_psfs']} | {', '.join(s['auto_methods'])}; "
            f"{s['auto_tolerance_adds_step']}/{s['n_psfs']} | {g(s['max_diff_over_peak'])} | {g(s['estimate_over_measured'])} "
            f"| {val} | - |")
        lines[-1] += (f" {s['peak_rel_change_maxabs']:.2g}, {s['ee80_rel_change_maxabs']:.2g} | "
                      + (f"{s['psnr_one_vs_two_min']:.1f} dB | {s['psnr_sharp_one_mean']:.2f} / {s['psnr_sharp_two_mean']:.2f} dB"
                         if "psnr_one_vs_two_min" in s else "- | -")
                      + f" | {s['time_one_s']:.0f} / {s['time_two_s']:.0f} s |")
    return "\n".join(lines)


def plot(result: dict, path) -> None:
    """Measured one-step vs wave-path difference against the planner's estimate, per PSF (log-log): filled
    where the wave step's own phase error is below ``STEP_PHASE_MAX`` (its result a reference), open where not."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6.4, 4.8))
    colours = {"cooke_hybrid": "C0", "a489_aberration": "C1", "a489_edof": "C2"}
    markers = {"start": "o", "designed": "s"}
    for c in result["cases"]:
        for r in c.get("rows", []):
            col = colours[c["experiment"]]
            ax.scatter(r["estimate"], r["max_diff_over_peak"], s=18, marker=markers[c["variant"]],
                       facecolors=col if r["step_validated"] else "none", edgecolors=col, linewidths=0.8)
    lo, hi = 1e-4, 30.0
    x = np.array([lo, hi])
    ax.plot(x, x, "k-", lw=0.8, label="measured = estimate")
    ax.plot(x, x / 2, "k:", lw=0.8, label="factor 2 (calibration)")
    ax.plot(x, x * 2, "k:", lw=0.8)
    for name, col in colours.items():
        ax.scatter([], [], color=col, marker="o", s=18, label=name)
    ax.scatter([], [], facecolors="none", edgecolors="k", marker="o", s=18, label=f"step's own phase > {STEP_PHASE_MAX:g} rad")
    ax.scatter([], [], color="k", marker="s", s=18, label="stored design (squares)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlim(lo, hi)
    ax.set_ylim(1e-4, 2.0)
    ax.set_xlabel("model-error estimate (Plan.model_error), of the peak")
    ax.set_ylabel("max |one-step - wave path| / peak")
    ax.set_title("The paper's experiments: one-step model against the wave path", fontsize=10)
    ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="starting lenses, 2 nodes, 0.55 um (1-2 min)")
    ap.add_argument("--out", default=None, help="JSON path (default perf/results/model_vs_wave_path[_quick].json)")
    ap.add_argument("--data-root", default=None, help="image folder (default: scikit-image's bundled samples)")
    ap.add_argument("--crop", type=int, default=128, help="crop size, px")
    ap.add_argument("--grid-check", action="store_true",
                    help="also the one-step PSF on the wave path's plan: the step's effect apart from the sampling change")
    ap.add_argument("--plot", default=None, help="PNG of measured against estimated differences (e.g. docs/model_vs_wave_path.png)")
    ap.add_argument("--replot", default=None, help="a JSON written before: print its table (and --plot) without computing")
    a = ap.parse_args(argv)
    import json
    if a.replot:
        res = json.loads(Path(a.replot).read_text())
        print(table(res))
        if a.plot:
            plot(res, a.plot)
        return 0
    res = run(a.quick, a.data_root, a.crop, grid_check=a.grid_check)
    out = Path(a.out or ROOT / "perf" / "results" / f"model_vs_wave_path{'_quick' if a.quick else ''}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=1, default=float))
    print(table(res))
    if a.plot:
        plot(res, a.plot)
    print(f"total {res['total_s']:.0f} s; written {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
