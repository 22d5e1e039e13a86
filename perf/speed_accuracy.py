"""Speed against accuracy: time per PSF against relative L2 error to a converged reference, per method.

For each case (lens, field, wavelength) a converged reference is computed first
(:func:`rwwarp.convergence.converged_reference`: the adaptive plan's knobs doubled one at a time until
the PSF changes by < tol, or the work caps of this device are hit; the reference's own estimated error
is written next to it and drawn as the floor of the chart). Then every method computes the PSF on the
reference's sensor patch (same ``center_mm``) and is timed (median of ``--repeat`` runs after one
untimed run, which gives the error):

* ``adaptive``: rwwarp's default ray-wave plan over a ladder of ``nyquist_safety x rays_per_sample``;
* ``paper``: rwwarp with ``plan="paper"`` (the paper's fixed grid over the whole DOE, 10^6 rays);
  skipped (and said so in the JSON) where its predicted time or memory is out of reach;
* ``float32``: the adaptive plan with a float32 ray trace;
* ``ray``: the geometric ray model (DOE as a local grating);
* ``paraxial-wave``: the refractive part replaced by its paraxial thin lens;
* ``deeplens``: DeepLens (``deeplens-core``) ``HybridLens.psf`` at several ray counts, ks = 64, when
  importable (the A489 cases; its fixed DOE grid must cover the whole DOE, see the JSON notes).

Cases: the A489 + DOE singlet on axis and at 10 deg (0.7 field), and the Cooke triplet with an
even-polynomial DOE 5 mm before the sensor (on axis; ``--full`` adds 14 deg).

    python perf/speed_accuracy.py --quick            # CPU, < 10 min on 2 cores
    python perf/speed_accuracy.py                    # CPU, the committed run (about an hour)
    python perf/speed_accuracy.py --device cuda      # GPU, with DeepLens when importable

Writes ``perf/results/speed_accuracy_<cpu|gpu>.json``, ``.png`` and ``_psfs.npz`` (the reference PSFs and
DeepLens's patches, 64 x 64, keys ``<case>/reference``, ``<case>/deeplens_<spp>``).
"""
import argparse
import json
import math
import os
import sys
import tempfile
import time
import traceback
import warnings

import numpy as np
from _common import RESULTS, device_name, git_commit, save

import rwwarp as rw
from rwwarp import convergence as cv
from rwwarp.lens import Surface
from rwwarp.psf import RayWave
from rwwarp.trace import as_field_list

SIZE = 64
PSFS = {}   # arrays written next to the JSON (<name>_psfs.npz): references and DeepLens patches, for diagnosis
DEEPLENS_SPP_QUICK = (1_000_000, 16_777_216)
DEEPLENS_SPP = (1_000_000, 4_000_000, 16_777_216)


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
    methods["adaptive"] = [run(f"adaptive s={s:g} r={r:g}", nyquist_safety=s, rays_per_sample=r) for s, r in ladder]
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
def register(dl, ref, max_shift=10):
    """Best match of a DeepLens patch to the reference over flips and integer shifts (|s| <= max_shift px),
    after scaling it to the reference's patch power. Returns (aligned array, description)."""
    best = None
    n = ref.shape[0]
    for fy in (False, True):
        for fx in (False, True):
            a = dl[::-1] if fy else dl
            a = a[:, ::-1] if fx else a
            for sy in range(-max_shift, max_shift + 1):
                for sx in range(-max_shift, max_shift + 1):
                    b = np.zeros_like(a)
                    ys, yd = (slice(0, n - sy), slice(sy, n)) if sy >= 0 else (slice(-sy, n), slice(0, n + sy))
                    xs, xd = (slice(0, n - sx), slice(sx, n)) if sx >= 0 else (slice(-sx, n), slice(0, n + sx))
                    b[yd, xd] = a[ys, xs]
                    b = b * (ref.sum() / max(b.sum(), 1e-300))
                    e = cv.rel_l2(b, ref)
                    if best is None or e < best[0]:
                        best = (e, b, {"flip_y": fy, "flip_x": fx, "shift_px": [sx, sy]})
    return best[1], best[2]


def run_deeplens(case, ref, ref_point, device, quick, repeat, log):
    import torch
    torch.set_default_dtype(torch.float64)
    from bench_psf import deeplens_json
    from deeplens.hybridlens import HybridLens
    path = os.path.join(tempfile.mkdtemp(), "a489_doe_deeplens.json")
    deeplens_json(path)
    dev = "cuda" if device.startswith("cuda") else "cpu"
    lens = HybridLens(filename=path, device=dev)
    for k in ("alpha2", "alpha4", "alpha6", "alpha8", "alpha10"):
        if hasattr(lens.doe, k):
            setattr(lens.doe, k, torch.zeros(1, device=dev, dtype=torch.float64))
    sync = (lambda: torch.cuda.synchronize()) if dev == "cuda" else (lambda: None)
    depth = 10000.0
    scale = float(lens.calc_scale(-depth))
    half = float(lens.sensor_size[0]) / 2.0
    y_norm = depth * math.tan(math.radians(float(case["field_deg"]))) / (scale * half)
    rows = []
    for spp in (DEEPLENS_SPP_QUICK if quick else DEEPLENS_SPP):
        def f(spp=spp):
            with torch.no_grad():
                out = lens.psf(points=[0.0, y_norm, -depth], ks=SIZE, wvln=case["wavelength_um"], spp=spp)
            sync()
            return out
        if dev == "cuda":
            torch.cuda.reset_peak_memory_stats()
        p, t1, t = timed_psf(f, repeat)
        d = p.detach().cpu().numpy().astype(np.float64)
        aligned, how = register(d, ref.data)
        aligned_pt, how_pt = register(d, ref_point)
        row = {"label": f"DeepLens {spp / 1e6:.3g}M rays", "spp": spp, "time_s": t, "first_call_s": t1,
               "error": cv.rel_l2(aligned, ref.data), "alignment": how,
               "error_vs_point_sampled_reference": cv.rel_l2(aligned_pt, ref_point),
               "alignment_vs_point_sampled": how_pt, "y_norm": y_norm}
        if dev == "cuda":
            row["peak_bytes"] = torch.cuda.max_memory_allocated()
        log(f"  {row['label']:34s} {t * 1e3:10.1f} ms  error {row['error']:.3g} "
            f"(point-sampled ref: {row['error_vs_point_sampled_reference']:.3g})")
        rows.append(row)
        PSFS[f"{case['name']}/deeplens_{spp}"] = d
    return rows


def deeplens_importable():
    try:
        import deeplens  # noqa: F401  (importability check)
        return True
    except Exception:
        return False


# ------------------------------------------------------------------------------------------- chart
STYLE = {"adaptive": ("C0", "o", "rwwarp adaptive (defaults)"),
         "adaptive_gauss": ("C9", "o", "rwwarp adaptive, reference's pixel quadrature"), "paper": ("C1", "s", "rwwarp paper grid"),
         "float32": ("C2", "^", "rwwarp float32 trace"), "ray": ("C3", "x", "ray model"),
         "paraxial-wave": ("C4", "D", "paraxial-wave model"), "deeplens": ("C5", "P", "DeepLens 2.5.6")}


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
            if m == "deeplens":
                h2, = ax.loglog([r["time_s"] for r in pts], [r["error_vs_point_sampled_reference"] for r in pts],
                                marker=marker, color=color, mfc="none", ls=":")
                handles.setdefault("DeepLens vs point-sampled reference", h2)
                es += [r["error_vs_point_sampled_reference"] for r in pts]
                for r in pts:
                    ax.annotate(f"{r['spp'] / 1e6:.3g}M", (r["time_s"], r["error"]), fontsize=6, xytext=(3, 3),
                                textcoords="offset points")
        notes += [f"{c['name']}: {r['label']} skipped: {r['reason']}" for rows in c["methods"].values()
                  for r in rows if r.get("skipped")]
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
    leg_ax.legend(list(handles.values()), list(handles.keys()), loc="upper left", fontsize=8, frameon=False)
    if notes:
        import textwrap
        txt = "\n".join(textwrap.fill(n, 95, subsequent_indent="    ") for n in notes)
        leg_ax.text(0.0, 0.0, txt, transform=leg_ax.transAxes, fontsize=6, va="bottom")
    fig.suptitle(f"rwwarp speed vs accuracy on {res['device_name']} ({SIZE}x{SIZE} px PSFs)", fontsize=11)
    fig.tight_layout()
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
                try:
                    s = cv.Settings(**{**conv["settings"], "gauss_nodes": 1})
                    ref_pt, _ = cv.psf_at(case["lens"], case["field_deg"], case["wavelength_um"], SIZE, a.device, s,
                                          center_mm=tuple(conv["center_mm"]))
                    PSFS[f"{case['name']}/reference_point_sampled"] = ref_pt.data
                    c["methods"]["deeplens"] = run_deeplens(case, ref, ref_pt.data, a.device, a.quick, repeat, log)
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
