"""Speed against accuracy: time per PSF against relative L2 error to a converged reference, per method.

For each case (lens, field, wavelength) a converged reference is computed first
(:func:`rwwarp.convergence.converged_reference`: the adaptive plan's knobs doubled one at a time until
the PSF changes by < tol, or the work caps of this device are hit; the reference's own estimated error
is written next to it and drawn as the floor of the chart). Then every method computes the PSF on the
reference's sensor patch (same ``center_mm``) and is timed (median of ``--repeat`` runs after one
untimed run, which gives the error):

* ``adaptive``: rwwarp's band-limited ASM plan (``method="asm"``) over a ladder of
  ``nyquist_safety x rays_per_sample``;
* ``focal``: the focal propagation (``method="focal"``, :mod:`rwwarp.wave.focal`) over ``nyquist_safety``;
* ``paper``: rwwarp with ``plan="paper"`` (the paper's fixed grid over the whole DOE, 10^6 rays);
  skipped (and said so in the JSON) where its predicted time or memory is out of reach;
* ``float32``: the adaptive plan with a float32 ray trace;
* ``ray``: the geometric ray model (DOE as a local grating);
* ``paraxial-wave``: the refractive part replaced by its paraxial thin lens;
* ``deeplens``: DeepLens (``deeplens-core``, see ``_deeplens.py``) ``HybridLens.psf`` at several ray counts
  (and its 0.5 um grid where memory allows), 64 px patches, when importable (the A489 cases; its fixed
  DOE grid must cover the whole DOE, see the JSON notes); ``deeplens_method`` (JSON): rwwarp with
  DeepLens's discretisation, which explains DeepLens's error (see the DeepLens section below).

Cases: the A489 + DOE singlet on axis and at 10 deg (0.7 field), and the Cooke triplet with an
even-polynomial DOE 5 mm before the sensor (on axis; ``--full`` adds 14 deg).

    python perf/speed_accuracy.py --quick            # CPU, < 10 min on 2 cores without DeepLens
    python perf/speed_accuracy.py                    # CPU, the committed run (15 min without DeepLens,
                                                     # ~30 min with it, on 2 quiet cores)
    python perf/speed_accuracy.py --device cuda      # GPU, with DeepLens when importable

Writes ``perf/results/speed_accuracy_<cpu|gpu>.json``, ``.png`` and ``_psfs.npz`` (the reference PSFs and
DeepLens's patches, 64 x 64, keys ``<case>/reference``, ``<case>/deeplens_<spp>``).
"""
import argparse
import json
import math
import os
import sys
import time
import traceback
import warnings

import numpy as np
from _common import RESULTS, device_name, git_commit, save

import rwwarp as rw
from rwwarp import convergence as cv
from rwwarp.lens import Surface
from rwwarp.wave.plan import nice_fft_length
from rwwarp.psf import RayWave
from rwwarp.trace import as_field_list

SIZE = 64
PSFS = {}   # arrays written next to the JSON (<name>_psfs.npz): references and DeepLens patches, for diagnosis
DEEPLENS_SPP_QUICK = (1_000_000, 4_000_000)              # DeepLens asserts >= 10^6 rays
DEEPLENS_SPP = (1_000_000, 4_000_000, 16_777_216)        # 16.7M: its default
DEEPLENS_SPP_UPSAMPLED = (4_000_000, 16_777_216)         # with upsample_factor=2 (0.5 um), where memory allows
DEEPLENS_WARM = []


# ------------------------------------------------------------------------------------------- lenses / cases
def cooke_with_doe(distance_mm=5.0, semi_diameter_mm=15.0, coefficients=(-1000.0, 50.0)):
    """The Cooke triplet with a flat DOE plane ``distance_mm`` before the sensor, even-polynomial phase
    ``sum a_i rho^(2i)`` (rad, rho = r / semi_diameter): a1 = -1000 rad is a weak diffractive lens
    (f ~ 640 mm at 0.55 um, about 40 um of defocus at the sensor), a2 adds some spherical phase. The
    Cooke file gives only the entrance pupil diameter; the DOE's semi-diameter covers the 14 deg beam."""
    lens = rw.load_lens("cooke_triplet")
    surfs = [Surface(**{k: getattr(s, k) for k in s.__dataclass_fields__}) for s in lens.surfaces]
    surfs[-1].thickness = lens.surfaces[-1].thickness - distance_mm
    surfs.append(Surface(type="doe", semi_diameter=semi_diameter_mm, shape="circle", thickness=distance_mm,
                         design_wavelength_um=0.55, material="fused_silica",
                         profile={"kind": "even_poly", "norm_radius": semi_diameter_mm,
                                  "coefficients": [float(c) for c in coefficients]}))
    out = lens.replace(surfaces=surfs, name="Cooke triplet + even-poly DOE 5 mm before the sensor")
    out.validate()
    return out


def cases(full):
    a489 = rw.load_lens("a489_doe")
    cooke = cooke_with_doe()
    out = [{"name": "a489_on_axis", "lens": a489, "lens_name": "a489_doe", "field_deg": 0.0, "wavelength_um": 0.55},
           {"name": "a489_10deg", "lens": a489, "lens_name": "a489_doe", "field_deg": 10.0, "wavelength_um": 0.55},
           {"name": "cooke_doe_on_axis", "lens": cooke, "lens_name": "cooke_triplet + DOE", "field_deg": 0.0,
            "wavelength_um": 0.5876}]
    if full:
        out.append({"name": "cooke_doe_14deg", "lens": cooke, "lens_name": "cooke_triplet + DOE", "field_deg": 14.0,
                    "wavelength_um": 0.5876})
    return out


# ------------------------------------------------------------------------------------------- helpers
def default_label():
    d = cv.Settings()
    return f"adaptive s={d.nyquist_safety:g} r={d.rays_per_sample:g}"


def available_bytes(device):
    if device.startswith("cuda"):
        try:
            import cupy
            return cupy.cuda.runtime.memGetInfo()[0]
        except Exception:
            return None
    try:
        import psutil
        return psutil.virtual_memory().available
    except Exception:
        return None


def timed_psf(fn, repeat):
    """(result of the first call, its time, median time of ``repeat`` more calls)."""
    t0 = time.perf_counter()
    first = fn()
    t_first = time.perf_counter() - t0
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return first, t_first, float(np.median(ts)) if ts else t_first


def point(label, p, ref, t, t_first, **extra):
    row = {"label": label, "time_s": t, "first_call_s": t_first, "error": cv.rel_l2(p.data, ref.data),
           "patch_power": float(p.data.sum())}
    if p.plan:
        row["plan"] = cv._plan_summary(p.plan)
    row.update(extra)
    return row


def run_rwwarp_methods(case, ref, device, quick, repeat, log):
    lens, fld, wl = case["lens"], case["field_deg"], case["wavelength_um"]
    center = tuple(float(c) for c in ref.center_mm)
    base = dict(size=SIZE, device=device, center_mm=center)
    methods = {}

    def run(label, **kw):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            p, t1, t = timed_psf(lambda: rw.psf(lens, fld, wl, **base, **kw), repeat)
        row = point(label, p, ref, t, t1, settings={k: v for k, v in kw.items() if k != "plan"})
        msgs = sorted({str(w.message).split(":")[0] for w in caught if issubclass(w.category, rw.SamplingWarning)})
        if msgs:
            row["warnings"] = msgs
        log(f"  {label:34s} {t * 1e3:10.1f} ms  error {row['error']:.3g}")
        return row

    # the library's defaults (its pixel quadrature), then, where the reference settled on another node count,
    # the same ladder with the reference's quadrature; the other rwwarp methods use the reference's quadrature
    # so that their curves show their own model error
    g_ref = ref.info["convergence"]["settings"]["gauss_nodes"]   # None: rw.psf's automatic choice
    g_lab = "auto" if g_ref is None else g_ref
    ladder = [(1.0, 1.0), (1.5, 1.0), (2.0, 1.0), (2.0, 1.5), (3.0, 1.5)] if quick else list(cv.LADDER)
    methods["adaptive"] = [run(f"adaptive s={s:g} r={r:g}", nyquist_safety=s, rays_per_sample=r, method="asm")
                           for s, r in ladder]
    # the focal propagation (rwwarp.wave.focal: the converging wave handled analytically, grids follow the patch)
    # over its own ladder of wave-plane / sensor-side safety
    flad = [(1.0, 1.0), (2.0, 1.0), (3.0, 1.0)] if quick else [(1.0, 1.0), (1.5, 1.0), (2.0, 1.0), (3.0, 1.0), (4.0, 1.5)]
    methods["focal"] = [run(f"focal s={s:g} r={r:g}", nyquist_safety=s, rays_per_sample=r, method="focal")
                        for s, r in flad]
    if g_ref is not None and g_ref != cv.Settings().gauss_nodes:
        lad = ladder[1:] if quick else ladder
        methods["adaptive_gauss"] = [run(f"adaptive s={s:g} r={r:g} g={g_lab}", nyquist_safety=s, rays_per_sample=r,
                                         gauss_nodes=g_ref) for s, r in lad]
    f32 = [(1.5, 1.0), (2.0, 1.0)] if quick else [(1.5, 1.0), (2.0, 1.0), (3.0, 1.5)]
    methods["float32"] = [run(f"float32 s={s:g} r={r:g} g={g_lab}", nyquist_safety=s, rays_per_sample=r,
                              dtype="float32", gauss_nodes=g_ref) for s, r in f32]
    methods["ray"] = [run("ray model (401^2 rays)", model="ray")]
    methods["paraxial-wave"] = [run(f"paraxial-wave s={s:g} r={r:g} g={g_lab}", model="paraxial-wave",
                                    nyquist_safety=s, rays_per_sample=r, gauss_nodes=g_ref)
                                for s, r in ((1.5, 1.0), (2.0, 1.0))]
    methods["paper"] = run_paper(case, ref, device, repeat, methods["adaptive"], run, log, g_ref, quick)
    return methods


def run_paper(case, ref, device, repeat, adaptive_rows, run, log, gauss_nodes, quick):
    """plan="paper" (the fixed grid over the whole DOE at the Nyquist pitch of the beam, 10^6 rays) and the
    paper's literal grid (0.5 um: half the 1 um DOE feature size, 2x padding, 10^6 rays), each unless its
    predicted time (CPU: > 120 s) or memory is out of reach."""
    lens, fld, wl = case["lens"], case["field_deg"], case["wavelength_um"]
    pixel = lens.sensor.pixel_pitch
    center = tuple(float(c) for c in ref.center_mm)
    pl = RayWave(lens, as_field_list(fld), [wl], SIZE, pixel, device, "paper", center_mm=center).plan
    rows = [guarded(pl, "paper grid (whole DOE, 10^6 rays)", dict(plan="paper"), device, adaptive_rows, run, log,
                    gauss_nodes)]
    half = lens.surfaces[lens.doe_index].semi_diameter
    n = int(round(2 * half / 0.5e-3))
    lit = rw.Plan(0.5e-3, n, 2 * n, 1000, "paper", False,
                  ["the paper's grid: whole DOE at 0.5 um (half the 1 um feature size), padded 2x, 1000^2 rays"])
    if quick or not device.startswith("cuda"):
        # measured on 2 CPU cores: the 12000^2 FFT of the A489 took > 10 min and ~14 GB before the OOM killer
        rows.append({"label": "paper grid literal (0.5 um)", "skipped": True, "plan": cv._plan_summary(lit),
                     "reason": f"GPU only (FFT {lit.n_pad}^2; the A489's 12000^2 ran > 10 min on 2 CPU cores and "
                               f"was killed for memory at ~14 GB)"})
    else:
        rows.append(guarded(lit, "paper grid literal (0.5 um)", dict(plan=lit), device, adaptive_rows, run, log,
                            gauss_nodes))
    return rows


def guarded(pl, label, kw, device, adaptive_rows, run, log, gauss_nodes):
    ad = next(r for r in adaptive_rows if r["label"] == default_label())
    ratio = max(pl.ray_grid ** 2 / ad["plan"]["rays"], (pl.n_pad / ad["plan"]["n_pad"]) ** 2)
    t_pred = ad["time_s"] * ratio
    # ~100 B per padded sample (workspaces, cached transfer function; 14 GB measured at 12000^2), rays 140 B
    mem_pred = 100.0 * pl.n_pad ** 2 + 48.0 * pl.n_grid ** 2 + 140.0 * pl.ray_grid ** 2
    avail = available_bytes(device)
    info = {"plan": cv._plan_summary(pl), "predicted_time_s": t_pred, "predicted_bytes": mem_pred}
    reason = None
    if avail is not None and mem_pred > 0.6 * avail:
        reason = (f"predicted memory {mem_pred / 2 ** 30:.1f} GiB > 60% of the {avail / 2 ** 30:.1f} GiB available "
                  f"(FFT {pl.n_pad}^2 over the whole DOE)")
    elif not device.startswith("cuda") and t_pred > 120.0:
        reason = f"predicted {t_pred:.0f} s per PSF on this CPU (> 120 s; FFT {pl.n_pad}^2 over the whole DOE)"
    if reason:
        log(f"  {label} skipped: {reason}")
        return {"label": label, "skipped": True, "reason": reason, **info}
    row = run(f"{label} g={'auto' if gauss_nodes is None else gauss_nodes}", gauss_nodes=gauss_nodes, **kw)
    row.update({k: v for k, v in info.items() if k != "plan"})
    row["plan"] = cv._plan_summary(pl)
    return row


# ------------------------------------------------------------------------------------------- DeepLens
# Why DeepLens is ~39 % off at 10 deg while ~7 % on axis (measured on CPU with deeplens-core 2.5.6; see
# perf/README.md): not the alignment. Its patch is registered below over flips and every crop of a larger
# (96 px) patch, and the best shift (3-4 px) is well inside the search; registering with zeros shifted in or
# cropping changes the error by < 0.5 %. Its source is the same as ours (y axis, 10 m from the first vertex,
# y = depth tan(field)); its chief ray lands 1.2 um from ours. The error is its discretisation: each
# random ray is splatted bilinearly onto the fixed 1 um DOE grid with its full phase (no reference wave
# factored out) and unit amplitude. At 10 deg the beam's local spatial frequency on the DOE plane reaches
# 481 cycles/mm against the 500 cycles/mm Nyquist limit of that grid (229 on axis), where the bilinear
# splat attenuates the field by sinc^2(f p) (0.44 at 481/mm) and aliases: a bias that no ray count removes
# (GPU: 38.7 / 38.5 / 38.7 % at 1M / 4M / 16.7M rays). rwwarp run with DeepLens's discretisation
# (``deeplens_method`` rows: amplitude="paper", no reference wave, point sampling, explicit grid) gives
# about 40 % at 1 um too, and 15 % / 8 % at 0.5 / 0.25 um (the rest: unit amplitude, ~6 %); on axis it
# matches DeepLens's patch to 0.6 %. On axis DeepLens's 7 % is mostly pixel integration (it point-samples
# |U|^2; 2.9 % against a point-sampled reference). DeepLens's own remedy is a finer grid
# (``upsample_factor=2``: 0.5 um, a 12000^2 FFT), run where memory allows (``deeplens`` rows with ``upsample_factor`` 2; ~13 GiB, so on the GPU).
DEEPLENS_MARGIN = 16     # DeepLens patches are computed SIZE + 2 * margin wide and registered by cropping
DEEPLENS_DEPTH_MM = 10000.0
DEEPLENS_METHOD_PITCH_UM = (1.0, 0.5, 0.25)   # rwwarp with DeepLens's discretisation at these grid pitches


def run_deeplens(case, ref, ref_point, device, quick, repeat, log, spps=None):
    """DeepLens ``HybridLens.psf`` at several ray counts (and, where memory allows, its 0.5 um grid), each
    registered to the reference and to the point-sampled reference. On the CPU each point is one call
    (after one warm-up call per process); on the GPU the median of ``repeat`` after an untimed one."""
    import torch
    import _deeplens as dlm
    dev = "cuda" if device.startswith("cuda") else "cpu"
    lens = dlm.a489_hybridlens(dev)
    sync = (lambda: torch.cuda.synchronize()) if dev == "cuda" else (lambda: None)
    pt = dlm.point_for_field(lens, case["field_deg"], DEEPLENS_DEPTH_MM)
    ks = SIZE + 2 * DEEPLENS_MARGIN
    cpu_reps = 0 if dev == "cpu" else repeat
    if dev == "cpu" and not DEEPLENS_WARM:
        with torch.no_grad():
            lens.psf(points=[0.0, 0.0, -DEEPLENS_DEPTH_MM], ks=ks, wvln=case["wavelength_um"], spp=1_000_000)
        DEEPLENS_WARM.append(True)
    info = {"point": pt, "chief_ray_mm_deeplens_frame": dlm.chief_ray_mm(lens, pt), "ks_computed": ks,
            "doe_grid": f"{dlm.DOE_RES}^2 at {dlm.DOE_PITCH_MM * 1e3:g} um, padded 2x"}
    rows = []
    todo = [(spp, 1) for spp in (spps or (DEEPLENS_SPP_QUICK if quick else DEEPLENS_SPP))]
    todo += [(spp, 2) for spp in DEEPLENS_SPP_UPSAMPLED]
    for spp, up in todo:
        label = f"DeepLens {spp / 1e6:.3g}M rays" + ("" if up == 1 else f", {dlm.DOE_PITCH_MM * 1e3 / up:g} um grid")
        if up > 1:
            n_pad = 2 * dlm.DOE_RES * up
            need = 100.0 * n_pad ** 2   # ~100 B per padded sample, as for the paper grid (ASM temporaries)
            avail = available_bytes(device)
            if avail is None or need > 0.6 * avail:
                log(f"  {label} skipped (memory)")
                rows.append({"label": label, "spp": spp, "upsample_factor": up, "skipped": True,
                             "reason": f"predicted {need / 2 ** 30:.0f} GiB (FFT {n_pad}^2) > 60% of the "
                                       f"{(avail or 0) / 2 ** 30:.0f} GiB available"})
                continue

        def f(spp=spp, up=up):
            with torch.no_grad():
                out = lens.psf(points=pt, ks=ks, wvln=case["wavelength_um"], spp=spp, upsample_factor=up)
            sync()
            return out
        if dev == "cuda":
            torch.cuda.reset_peak_memory_stats()
        p, t1, t = timed_psf(f, cpu_reps)
        d = p.detach().cpu().numpy().astype(np.float64)
        aligned, how = dlm.register(d, ref.data)
        aligned_pt, how_pt = dlm.register(d, ref_point)
        row = {"label": label, "spp": spp, "upsample_factor": up, "time_s": t, "first_call_s": t1,
               "timing": "one call after a warm-up" if dev == "cpu" else f"median of {cpu_reps} after one",
               "error": cv.rel_l2(aligned, ref.data), "alignment": how,
               "error_vs_point_sampled_reference": cv.rel_l2(aligned_pt, ref_point),
               "alignment_vs_point_sampled": how_pt, **info}
        if dev == "cuda":
            row["peak_bytes"] = torch.cuda.max_memory_allocated()
        log(f"  {label:34s} {t * 1e3:10.1f} ms  error {row['error']:.3g} "
            f"(point-sampled ref: {row['error_vs_point_sampled_reference']:.3g}; shift {how['shift_px']})")
        rows.append(row)
        PSFS[f"{case['name']}/deeplens_{spp}" + ("" if up == 1 else f"_up{up}")] = d
    return rows


def run_deeplens_method(case, ref_point, device, log):
    """rwwarp with DeepLens's discretisation: unit ray amplitude (``amplitude="paper"``), the full phase
    splatted (``use_reference=False``), |U|^2 point-sampled (``gauss_nodes=1``), on an explicit grid at
    DeepLens's 1 um pitch and finer; errors against the point-sampled reference. Shows that DeepLens's
    off-axis error is its grid pitch (it falls with the pitch, not with rays) and not its implementation
    or our comparison."""
    lens, fld, wl = case["lens"], case["field_deg"], case["wavelength_um"]
    center = tuple(float(c) for c in ref_point.center_mm)
    auto = RayWave(lens, as_field_list(fld), [wl], SIZE, lens.sensor.pixel_pitch, device, "auto",
                   center_mm=center).plan
    foot = auto.n_grid * auto.pitch_mm          # the beam's footprint window (DeepLens covers the whole DOE)
    rows = []
    for p_um in DEEPLENS_METHOD_PITCH_UM:
        p = p_um * 1e-3
        n = int(math.ceil(foot / p)) + 4
        rays = 2 * n if p_um >= 0.5 else n      # >= 1 ray per sample per axis (DeepLens: ~1.6 at 1M rays)
        pl = rw.Plan(p, n, nice_fft_length(2 * n), rays, "explicit",
                     reasons=[f"DeepLens's discretisation at {p_um:g} um"])
        kw = dict(size=SIZE, device=device, center_mm=center, plan=pl, amplitude="paper", use_reference=False,
                  gauss_nodes=1)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", rw.SamplingWarning)
            t0 = time.perf_counter()
            q = rw.psf(lens, fld, wl, **kw)
            t = time.perf_counter() - t0
        row = {"label": f"rwwarp with DeepLens's discretisation, {p_um:g} um", "pitch_um": p_um, "time_s": t,
               "error_vs_point_sampled_reference": cv.rel_l2(q.data, ref_point.data),
               "plan": cv._plan_summary(pl)}
        log(f"  {row['label']:50s} {t:6.1f} s  error vs point-sampled ref {row['error_vs_point_sampled_reference']:.3g}")
        rows.append(row)
    return rows


def deeplens_importable():
    try:
        import _deeplens
        return _deeplens.deeplens_importable()
    except Exception:
        return False


# ------------------------------------------------------------------------------------------- chart
STYLE = {"adaptive": ("C0", "o", "rwwarp band-limited ASM (adaptive plan)"),
         "adaptive_gauss": ("C9", "o", "rwwarp adaptive, reference's pixel quadrature"), "paper": ("C1", "s", "rwwarp paper grid"),
         "float32": ("C2", "^", "rwwarp float32 trace"), "ray": ("C3", "x", "ray model"),
         "paraxial-wave": ("C4", "D", "paraxial-wave model"), "deeplens": ("C5", "P", "DeepLens 2.5.6"),
         "focal": ("C6", "v", "rwwarp focal (rwwarp.wave.focal)")}


def chart_deeplens(ax, pts, color, marker, label, handles):
    """DeepLens's points: a line over ray counts on its default 1 um grid, its 0.5 um grid apart; filled
    against the reference, open against the point-sampled reference."""
    for up, pp in ((1, [r for r in pts if r.get("upsample_factor", 1) == 1]),
                   (2, [r for r in pts if r.get("upsample_factor", 1) > 1])):
        if not pp:
            continue
        mk = marker if up == 1 else "*"
        ls = "-" if len(pp) > 1 else "none"
        h, = ax.loglog([r["time_s"] for r in pp], [r["error"] for r in pp], marker=mk, color=color, ls=ls)
        handles.setdefault(label if up == 1 else "DeepLens 2.5.6, 0.5 um grid (upsample_factor=2)", h)
        h2, = ax.loglog([r["time_s"] for r in pp], [r["error_vs_point_sampled_reference"] for r in pp],
                        marker=mk, color=color, mfc="none", ls=":" if len(pp) > 1 else "none")
        handles.setdefault("DeepLens vs point-sampled reference", h2)
    for r in pts:
        ax.annotate(f"{r['spp'] / 1e6:.3g}M", (r["time_s"], r["error"]), fontsize=6, xytext=(3, 3),
                    textcoords="offset points")


def chart(res, path):
    """Time per PSF (x, log) against error to the reference (y, log), one panel per case, one shared legend.
    Points at the reference's own settings (error < 1e-12) are left out; the shaded band lies below the
    reference's own estimated error (not resolved)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker
    cs = res["cases"]
    ncol = 2
    nrow = math.ceil((len(cs) + 1) / ncol)   # one panel for the legend and notes
    fig, axes = plt.subplots(nrow, ncol, figsize=(6.2 * ncol, 4.4 * nrow), squeeze=False)
    handles = {}
    notes = []
    for ax, c in zip(axes.flat, cs):
        ts, es = [], []
        for m, rows in c["methods"].items():
            pts = sorted((r for r in rows if not r.get("skipped") and r.get("error") is not None
                          and r["error"] > 1e-12), key=lambda r: r["time_s"])
            if not pts:
                continue
            color, marker, label = STYLE.get(m, ("k", ".", m))
            if m == "deeplens":
                ts += [r["time_s"] for r in pts]
                es += [r["error"] for r in pts] + [r["error_vs_point_sampled_reference"] for r in pts]
                chart_deeplens(ax, pts, color, marker, label, handles)
                continue
            line = "none" if m in ("paper", "ray") or len(pts) == 1 else "-"
            h, = ax.loglog([r["time_s"] for r in pts], [r["error"] for r in pts], marker=marker, color=color,
                           ls=line)
            handles.setdefault(label, h)
            ts += [r["time_s"] for r in pts]
            es += [r["error"] for r in pts]
            if m == "paper":
                for r in pts:
                    ax.annotate("literal 0.5 um" if "literal" in r["label"] else "whole DOE",
                                (r["time_s"], r["error"]), fontsize=6, xytext=(4, 3), textcoords="offset points")
        notes += [(c["name"], f"{r['label']} skipped: {r['reason']}") for rows in c["methods"].values()
                  for r in rows if r.get("skipped")]
        if c.get("deeplens_method"):
            notes.append((c["name"], "rwwarp with DeepLens's discretisation (unit ray amplitude, full phase "
                          "splatted on a fixed grid, point-sampled; DeepLens: 1 um), error vs the point-sampled "
                          "reference: " + ", ".join(f"{r['pitch_um']:g} um {r['error_vs_point_sampled_reference']:.2g}"
                                                    for r in c["deeplens_method"])))
        conv = c["reference"]["convergence"]
        floor = conv["estimated_error"]
        h = ax.axhline(floor, color="0.5", ls="--", lw=1)
        handles.setdefault("reference's own error estimate (below: not resolved)", h)
        lo = max(min(es + [floor]) / 3, 1e-9)
        ax.axhspan(lo, floor, color="0.5", alpha=0.08, lw=0)
        ax.set_ylim(lo, max(es + [1.0]) * 3)
        if ts and max(ts) / min(ts) > 12:
            ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        state = "converged" if conv["converged"] else "capped"
        ax.set_title(f"{c['lens']}, {c['field_deg']} deg, {c['wavelength_um']} um (reference {state}, "
                     f"est. error {floor:.1g})", fontsize=8.5)
        ax.set_xlabel("time per PSF (s)")
        ax.set_ylabel("relative L2 error to the converged reference")
        ax.grid(True, which="both", alpha=0.3)
    rest = list(axes.flat)[len(cs):]
    for ax in rest:
        ax.axis("off")
    leg_ax = rest[0]
    leg = leg_ax.legend(list(handles.values()), list(handles.keys()), loc="upper left", fontsize=8,
                        frameon=False)
    fig.suptitle(f"rwwarp speed vs accuracy on {res['device_name']} ({SIZE}x{SIZE} px PSFs)", fontsize=11)
    fig.tight_layout()
    if notes:
        import textwrap
        # one line per note, the cases it holds for named together; placed under the legend
        grouped = {}
        for case, text in notes:
            grouped.setdefault(text.replace(case, "").strip(), []).append(case)
        txt = "\n".join(textwrap.fill(f"{', '.join(cs_)}: {t}", 110, subsequent_indent="    ")
                        for t, cs_ in grouped.items())
        fig.canvas.draw()
        bottom = leg_ax.transAxes.inverted().transform(leg.get_window_extent().p0)[1]
        leg_ax.text(0.0, bottom - 0.02, txt, transform=leg_ax.transAxes, fontsize=5.5, va="top")
    fig.savefig(path, dpi=130)
    plt.close(fig)


# ------------------------------------------------------------------------------------------- main
def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--quick", action="store_true", help="CPU run in < 10 min: fewer points, lower caps")
    ap.add_argument("--full", action="store_true", help="add the Cooke 14 deg case")
    ap.add_argument("--repeat", type=int, default=None, help="timed runs per point (default 1 CPU, 3 GPU)")
    ap.add_argument("--tol", type=float, default=1e-5, help="reference convergence tolerance (relative L2)")
    ap.add_argument("--max-ray-grid", type=int, default=None, help="reference cap: pupil rays across")
    ap.add_argument("--max-fft", type=int, default=None, help="reference cap: FFT length")
    ap.add_argument("--cases", nargs="*", default=None, help="case names to run (default all)")
    ap.add_argument("--no-deeplens", action="store_true")
    ap.add_argument("--deeplens-spp", type=int, nargs="*", default=None,
                    help="DeepLens ray counts (>= 10^6; default 1M 4M 16.7M, --quick 1M 4M)")
    ap.add_argument("--out", default=None, help="results folder (default perf/results or $RWWARP_RESULTS)")
    ap.add_argument("--chart-only", default=None, metavar="JSON", help="redraw the chart of a results file")
    a = ap.parse_args()
    if a.chart_only:
        chart(json.load(open(a.chart_only)), os.path.splitext(a.chart_only)[0] + ".png")
        return
    gpu = a.device.startswith("cuda")
    repeat = a.repeat if a.repeat is not None else (3 if gpu else 1)
    max_grid = a.max_ray_grid or (16384 if gpu else (2048 if a.quick else 8192))
    max_fft = a.max_fft or (16384 if gpu else (4096 if a.quick else 8192))
    tag = "gpu" if gpu else "cpu"
    out_dir = a.out or os.environ.get("RWWARP_RESULTS", str(RESULTS))

    def log(msg):
        print(msg, flush=True)

    t_all = time.perf_counter()
    # warm-up: kernel compilation / cache load, reported apart
    t0 = time.perf_counter()
    rw.psf(rw.load_lens("a489_doe"), 0.0, 0.55, size=SIZE, device=a.device)
    compile_s = time.perf_counter() - t0
    have_dl = (not a.no_deeplens) and deeplens_importable()
    res = {"benchmark": "speed_accuracy", "device": a.device, "device_name": device_name(a.device),
           "quick": a.quick, "size_px": SIZE, "repeat": repeat, "commit": git_commit(),
           "first_call_s": compile_s, "load_average_start": os.getloadavg(),
           "note_cpu": "on a shared machine other processes can inflate CPU times; the load averages are recorded",
           "reference": {"method": "rwwarp.convergence.converged_reference (knobs doubled one at a time)",
                         "tol": a.tol, "max_rays": max_grid ** 2, "max_fft": max_fft},
           "error_metric": "relative L2 over the 64x64 patch, same sensor pixels (center_mm of the reference)",
           "timing": "wall time of one rw.psf call (pilot trace, plan, trace, splat, propagation, host copy), "
                     "median of `repeat` runs after an untimed one",
           "deeplens": "importable" if have_dl else "not importable here (runs on the GPU machine)",
           "cases": []}
    for case in cases(a.full):
        if a.cases and case["name"] not in a.cases:
            continue
        log(f"== {case['name']}")
        t0 = time.perf_counter()
        ref, hist = cv.converged_reference(case["lens"], case["field_deg"], case["wavelength_um"], SIZE, a.device,
                                           tol=a.tol, max_rays=max_grid ** 2, max_fft=max_fft,
                                           callback=lambda e: log(f"  ref {e['role']:5s} {e['knob']!s:16s} "
                                                                  f"{e['plan']['rays'] / 1e6:7.2f}M rays FFT "
                                                                  f"{e['plan']['n_pad']:6d} {e['time_s']:7.2f} s "
                                                                  f"change {e['change']}"))
        conv = ref.info["convergence"]
        PSFS[f"{case['name']}/reference"] = ref.data
        log(f"  reference: converged={conv['converged']} combined change {conv['combined_change']:.3g} "
            f"estimated error {conv['estimated_error']:.3g} ({time.perf_counter() - t0:.0f} s)")
        c = {"name": case["name"], "lens": case["lens_name"], "field_deg": case["field_deg"],
             "wavelength_um": case["wavelength_um"], "center_mm": list(conv["center_mm"]),
             "reference": {"convergence": conv, "history": hist, "time_s": time.perf_counter() - t0,
                           "patch_power": float(ref.data.sum())}}
        c["methods"] = run_rwwarp_methods(case, ref, a.device, a.quick, repeat, log)
        if case["lens_name"] == "a489_doe":
            if have_dl:
                import gc
                gc.collect()   # DeepLens needs 4-6 GB of host memory of its own (16.7M rays: 5.6 GB peak)
                try:
                    s = cv.Settings(**{**conv["settings"], "gauss_nodes": 1})
                    ref_pt, _ = cv.psf_at(case["lens"], case["field_deg"], case["wavelength_um"], SIZE, a.device, s,
                                          center_mm=tuple(conv["center_mm"]))
                    PSFS[f"{case['name']}/reference_point_sampled"] = ref_pt.data
                    c["methods"]["deeplens"] = run_deeplens(case, ref, ref_pt.data, a.device, a.quick, repeat, log,
                                                            spps=a.deeplens_spp)
                    # why DeepLens's error is what it is: its discretisation reproduced in rwwarp
                    c["deeplens_method"] = run_deeplens_method(case, ref_pt, a.device, log)
                except Exception as e:
                    traceback.print_exc()
                    c["methods"]["deeplens"] = [{"label": "DeepLens", "skipped": True,
                                                 "reason": f"{type(e).__name__}: {e}"}]
            else:
                c["methods"]["deeplens"] = [{"label": "DeepLens", "skipped": True,
                                             "reason": "deeplens-core not importable on this machine"}]
        else:
            c["methods"]["deeplens"] = [{"label": "DeepLens", "skipped": True, "reason":
                                         "not run: DeepLens's fixed DOE grid spans the whole DOE (30 mm here) at "
                                         "the pitch the beam needs (~1.5 um): a 20000^2 field padded to 40000^2"}]
        c["summary"] = summarise(c)
        res["cases"].append(c)
        log("  summary: " + json.dumps(c["summary"], default=float))
    res["total_time_s"] = time.perf_counter() - t_all
    res["load_average_end"] = os.getloadavg()
    p = save(f"speed_accuracy_{tag}", res, out_dir)
    np.savez_compressed(os.path.join(out_dir, f"speed_accuracy_{tag}_psfs.npz"), **PSFS)
    png = os.path.join(out_dir, f"speed_accuracy_{tag}.png")
    chart(res, png)
    log(f"-> {p}\n-> {png}  ({res['total_time_s']:.0f} s)")


def summarise(c):
    """Fastest point of each method, and where the default adaptive plan sits against the paper grid."""
    out = {"reference_estimated_error": c["reference"]["convergence"]["estimated_error"]}
    for m, rows in c["methods"].items():
        # a rung at the reference's own settings reproduces it (error 0): not a measurement of accuracy
        pts = [r for r in rows if not r.get("skipped") and r["error"] > 1e-12]
        if pts:
            best = min(pts, key=lambda r: r["error"])
            out[m] = {"best_error": best["error"], "its_time_s": best["time_s"], "label": best["label"]}
    ad = next((r for r in c["methods"]["adaptive"] if r["label"] == default_label()), None)
    adg = next((r for r in c["methods"].get("adaptive_gauss", []) if r["label"].startswith(default_label() + " ")),
               None) or ad
    pa = next((r for r in c["methods"]["paper"] if not r.get("skipped")), None)
    if ad:
        out["default_adaptive"] = {"time_s": ad["time_s"], "error": ad["error"]}
    if adg and pa:
        # same pixel quadrature on both sides
        out["paper_vs_default_adaptive"] = {"adaptive": adg["label"], "time_ratio": pa["time_s"] / adg["time_s"],
                                            "error_ratio": pa["error"] / max(adg["error"], 1e-300)}
    return out


if __name__ == "__main__":
    sys.exit(main())
