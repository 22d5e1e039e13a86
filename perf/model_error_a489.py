"""The planner's model-error estimate on the A489 + DOE's own beams, against a wave-exact truth (issue 27, item 1).

For each case (``rw.load_lens("a489_doe")``: the asphere, its 3 x 3 mm DOE 2.95 mm before the sensor, the source
at the lens file's 10 m; stop radius 1.0 mm (F/4, the file's) or 0.5 mm (F/8); field 0 / 5 / 10 deg; 0.55 um; the
DOE ``600 rho^2 + 200 rho^4`` rad, rho = r / 1.5 mm, continuous: at its design wavelength the wrapped relief
transmits the same field; the planner's rim slopes 20-80 rad): the measured model error
(``tests/rwwarp/_a489_truth.py``: the stop's disc propagated as a wave through the real lens, the angular spectrum
in air and glass and the wave propagation method through the two surfaces' sag zones, written from the equations,
numpy, no rwwarp code; against the geometric field traced to the DOE plane; the same DOE and exact angular spectrum to
the sensor; max |difference| over the truth's peak on the spot's patch, 0.5 um samples), the estimate
(``rw.plan_psf(...).model_error``, what ``--explain`` prints), their ratio, and the truth's convergence: the same case
with the grid's pitch and the WPM's slice halved (F/8; at F/4 the slice halved and the pitch 0.7x), the front zone
traced geometrically instead (its share of the error), and the smooth-pupil control (the stop's amplitude a cos^2
over its whole radius: no edge, the truth against geometric optics). A steeper DOE (4x) at F/8 (``--set steep``);
``--front-check``: the WPM's slice through the asphere halved where the refined pair traced that zone; ``--f22``: one
F/2.2 case on axis, unrefined; ``--f22-off``: the same at 5 and 10 deg; ``--wavelengths``: F/4 on axis and at 10 deg
at 0.45 and 0.65 um (the truth's glass index and the DOE's wrapped relief at that wavelength, every order:
``_a489_truth.py``; the estimate at that wavelength), the base runs first, then their checks unless ``--no-checks``;
``--merge``: the sets into perf/results/model_error_a489.json.
CPU only (2 shared cores: main set ~35 min, steep ~15 min, front check ~25 min, F/2.2 ~25 min a field, wavelengths
~2 min a base run, ~8 min a case's checks; --wavelengths-f8 ~1 min a case).
Usage: python perf/model_error_a489.py [--quick] [--set all|main|steep] [--front-check] [--f22] [--f22-off]
[--wavelengths [--no-checks]] [--wavelengths-f8] [--reestimate] [--pupil-check] [--rim-check] [--f22-wavelengths] [--merge] (--quick: F/8 only)
"""
from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "rwwarp"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import rwwarp as rw                                                    # noqa: E402
from _common import device_name, save                                  # noqa: E402
from _a489_truth import A489, measured_error, truth_and_model          # noqa: E402

COEFFS = (600.0, 200.0)
#: (stop radius mm, field deg, pitch mm, slice mm, the refined run's pitch and slice, the refined pair's front zone):
#: F/8 refines the whole truth (pitch and slice halved); F/4 (a 2304^2 grid through the asphere's 0.13 mm sag zone,
#: ~4 CPU-minutes a run here) refines with the front zone traced (the pair "geometric" at both samplings), the
#: front zone's own share measured at the base sampling
CASES = [(0.5, 0.0, 1.5e-3, 1e-3, 0.75e-3, 0.5e-3, "wave"), (0.5, 5.0, 1.5e-3, 1e-3, 0.75e-3, 0.5e-3, "wave"),
         (0.5, 10.0, 1.5e-3, 1e-3, 0.75e-3, 0.5e-3, "wave"),
         (1.0, 0.0, 1.0e-3, 1e-3, 0.7e-3, 0.5e-3, "geometric"), (1.0, 10.0, 1.0e-3, 1e-3, 0.7e-3, 0.5e-3, "geometric"),
         (1.0, 5.0, 1.0e-3, 1e-3, 0.7e-3, 0.5e-3, "geometric")]
#: a steeper DOE at F/8 (4x the coefficients: the plan's rim slopes ~60-80 rad at N_F 30), its 1.6x wider spectrum on
#: a 0.75 um grid
STEEP = (2400.0, 800.0)
#: F/2.2 (--f22): a quarter of COEFFS, the plan's rim slope 92 rad on its 0.70 mm beam
F22_COEFFS = (150.0, 50.0)
STEEP_CASES = [(0.5, f, 0.75e-3, 1e-3, 0.5e-3, 0.5e-3, "geometric") for f in (0.0, 5.0, 10.0)]
#: --f22-off: the --f22 case's settings off the axis (deg)
F22_OFF_FIELDS = (5.0, 10.0)
#: --wavelengths: the F/4 cases on axis and at 10 deg (CASES' settings) at these wavelengths (um), the DOE's relief
#: (COEFFS at its 0.55 um design wavelength) remapped: every order of the wrapped relief (``_a489_truth.py``)
WAVELENGTHS = (0.45, 0.65)
WAVELENGTH_CASES = [c for c in CASES if c[0] == 1.0 and c[1] in (0.0, 10.0)]
#: --wavelengths-f8: the F/8 cases on axis and at 10 deg (CASES' settings: the whole truth refined) at WAVELENGTHS,
#: held out from the estimate's orders term (nothing set on them): model_error_a489_wavelengths_f8.json
WAVELENGTH_F8_CASES = [c for c in CASES if c[0] == 0.5 and c[1] in (0.0, 10.0)]


def pupil_check(a_mm, field_deg, wavelength_um, coeffs=COEFFS, n=2048, span=8.0):
    """A diagnostic of the estimate's own picture (--pupil-check): the main order's pupil phase the planner fits
    (captured from :mod:`rwwarp.wave.model_error`) and its Fresnel number, the uniform disc diffracted over the reduced
    distance exactly (2-D FFT, ``n`` samples over ``span`` beam radii, transfer ``exp(-i pi nu^2 / N_F)``) and
    multiplied by that phase, against the disc with the phase: max |difference| over the peak, beside the edge-wave
    sum's value on the same phase (``main_estimate``). Equal where the sum is faithful to its one-edge picture."""
    import math
    from rwwarp.wave import model_error as me
    got = {}
    fit, ewe = me.fit_pupil_phase, me.edge_wave_error
    me.fit_pupil_phase = lambda u, g, *a: got.setdefault("phase", fit(u, g, *a))
    me.edge_wave_error = lambda nf, ph, *a: (got.setdefault("nf", nf), ewe(nf, ph, *a))[1]
    try:
        me._MEMO.clear()
        est = estimate(a_mm, field_deg, coeffs, wavelength_um)
    finally:
        me.fit_pupil_phase, me.edge_wave_error = fit, ewe
    ph, nf = got["phase"], got["nf"]
    h = span / n
    x = (np.arange(n) - n // 2) * h
    X, Y = np.meshgrid(x, x)
    r = np.hypot(X, Y)
    disc = np.clip((1.0 - r) / h + 0.5, 0.0, 1.0)
    f = np.fft.fftfreq(n, h)
    FX, FY = np.meshgrid(f, f)
    blurred = np.fft.ifft2(np.fft.fft2(disc) * np.exp(-1j * math.pi * (FX ** 2 + FY ** 2) / nf))
    inside = r <= 1.6
    phase = np.where(inside, ph.value(np.where(inside, X, 0.0), np.where(inside, Y, 0.0)), 0.0)
    Im = np.abs(np.fft.fft2(disc * np.exp(1j * phase))) ** 2
    It = np.abs(np.fft.fft2(np.where(inside, blurred, 0.0) * np.exp(1j * phase))) ** 2
    row = {"stop_radius_mm": a_mm, "field_deg": field_deg, "wavelength_um": wavelength_um, "fresnel_number": nf,
           "main_estimate": est["main_estimate"], "pupil_truth": float(np.max(np.abs(It - Im)) / It.max()),
           "peak_truth_over_model": float(It.max() / Im.max()), "samples": n, "span_radii": span}
    print(f"F/{7.95 / (2 * a_mm):.2f} {field_deg} deg {wavelength_um} um: edge-wave sum {row['main_estimate']:.3f}, the "
          f"disc diffracted exactly with the same phase {row['pupil_truth']:.3f} (N_F {nf:.1f})", flush=True)
    return row


def rim_check(a_mm, field_deg, wavelength_um, coeffs=COEFFS):
    """A diagnostic of the estimate's picture on the real beam (--rim-check): the main-order truth (the DOE's main
    order alone) and its fields on the DOE plane, and the picture (the geometric field's amplitude diffracted over the
    reduced distance ``d`` by the exact angular spectrum, its phase applied after: the beam's aberration before the
    DOE taken as applied at the plane) on the same grid and the same propagation to the sensor, with (1) the
    footprint's real amplitude or the estimate's circle (radius ``beam_r`` about the pilot's centre) and (2) the
    traced phase or the estimate's fitted pupil phase; beside them the wave step (the aberration diffracted over
    ``d`` as well), the fit's residual and the rim's radii (the stop's rim traced, over ``beam_r``). Returns its row."""
    import math
    from rwwarp.wave import model_error as me
    lam = wavelength_um * 1e-3
    lens = A489(a_mm=a_mm, coeffs=coeffs, lam_mm=lam)
    lens.doe_scale = 1.0
    c0 = time.process_time()
    T, M, info = truth_and_model(lens, field_deg, h=1e-3, dz=1e-3, front="wave", keep_fields=True)
    V, Vm = info["doe_fields"]
    g, Hs, tdoe, (ey, ex) = info["grid"], info["sensor_transfer"], info["doe_transmission"], info["patch_dft"]
    got, fit, rh = {}, me.fit_pupil_phase, me._rim_harmonics
    me.fit_pupil_phase = lambda u, gr, *a: got.setdefault("phase", fit(u, gr, *a))
    me._rim_harmonics = lambda uv, xy, xc, br: (got.setdefault("xc", (xc, br)), rh(uv, xy, xc, br))[1]
    try:
        me._MEMO.clear()
        est = estimate(a_mm, field_deg, coeffs, wavelength_um)
    finally:
        me.fit_pupil_phase, me._rim_harmonics = fit, rh
        me._MEMO.clear()
    ph, (xc, br), d = got["phase"], got["xc"], est["reduced_distance_mm"]
    xc = np.array([xc[1], xc[0]])                      # rwwarp's field lies along y, the truth's along x
    X, Y = g.mesh()
    N, k = g.N, 2 * math.pi / lam
    nu = np.fft.fftfreq(N, g.h)
    NX, NY = np.meshgrid(nu, nu)
    H = np.exp(2j * math.pi * d * (np.sqrt(np.maximum(1 / lam ** 2 - NX ** 2 - NY ** 2, 0)) - 1 / lam))

    def prop(F):
        return np.fft.ifft2(np.fft.fft2(F) * H)

    def sensor(F, t):
        return np.abs(ey @ (np.fft.fft2(F * t) * Hs) @ ex / N ** 2) ** 2

    def pic(a, F, t):
        Im, It = sensor(a * F, t), sensor(prop(a) * F, t)
        return float(np.max(np.abs(It - Im)) / It.max())
    wide = A489(a_mm=1.25 * a_mm, coeffs=coeffs, lam_mm=lam)
    Vext = wide.geometric_field(X, Y, np.radians(field_deg), lens.zD, h=g.h)       # the phase beyond the rim
    real = np.exp(1j * np.angle(np.where(np.abs(Vext) > 0, Vext, 1.0)))
    R = np.hypot(X - xc[0], Y - xc[1])
    circle = np.clip((br - R) / g.h + 0.5, 0.0, 1.0) * float(np.median(np.abs(Vm)[np.abs(Vm) > 0.5 * np.abs(Vm).max()]))
    px, py = info["patch_x"], info["patch_y"]
    Tp = np.array([0.5 * (px[0] + px[-1]), 0.5 * (py[0] + py[-1])])
    sph = np.exp(-1j * k * np.sqrt((X - Tp[0]) ** 2 + (Y - Tp[1]) ** 2 + (lens.zS - lens.zD) ** 2)
                 - 2j * math.pi * g.nu0 * X)
    inside = R < 1.6 * br
    Pf = np.where(inside, ph.value(np.where(inside, Y / br, 0.0), np.where(inside, (X - xc[0]) / br, 0.0)), 0.0)
    fitted = np.exp(1j * Pf) * sph
    row = {"stop_radius_mm": a_mm, "field_deg": field_deg, "wavelength_um": wavelength_um, "doe_coefficients": list(coeffs),
           "measured_main_order": measured_error(T, M), "estimate_main": est["main_estimate"],
           "fresnel_number": est["fresnel_number"], "reduced_distance_mm": d, "beam_radius_mm": br,
           "picture_real_footprint_traced_phase": pic(np.abs(Vm), real, tdoe),
           "picture_real_footprint_fitted_phase": pic(np.abs(Vm), fitted, 1.0),
           "picture_circle_traced_phase": pic(circle, real, tdoe),
           "picture_circle_fitted_phase": pic(circle, fitted, 1.0)}
    # which part of the footprint: its shape with a uniform amplitude; discs about the pilot's centre of the traced
    # rim's mean and largest radius (the traced phase / the fitted phase)
    th = np.radians(field_deg)
    t = np.linspace(0, 2 * np.pi, 360, endpoint=False)
    xr, yr, _ = lens.trace(a_mm * np.cos(t), a_mm * np.sin(t), th, lens.zD)
    rim = np.hypot(xr - xc[0], yr - xc[1]) / br
    share = np.where(np.abs(Vext) > 0, np.abs(Vm) / np.where(np.abs(Vext) > 0, np.abs(Vext), 1.0), 0.0)
    row["picture_real_footprint_uniform_amplitude"] = [pic(share, real, tdoe), pic(share, fitted, 1.0)]
    for name, rad in (("mean", rim.mean()), ("largest", rim.max())):
        disc = np.clip((rad * br - R) / g.h + 0.5, 0.0, 1.0)
        row[f"picture_disc_rim_{name}_radius"] = [pic(disc, real, tdoe), pic(disc, fitted, 1.0)]
    # the fit's residual on the footprint (less piston and tilt)
    m = np.abs(Vm) > 0.5 * np.abs(Vm).max()
    res = real * tdoe / sph * np.exp(-1j * Pf)
    r = np.angle(res * np.conj(np.mean(res[m])))
    A = np.stack([np.ones(m.sum()), X[m], Y[m]], 1)
    rr = r[m] - A @ np.linalg.lstsq(A, r[m], rcond=None)[0]
    row.update(fit_residual_rms_rad=float(rr.std()), fit_residual_max_rad=float(np.abs(rr).max()))
    # the wave step: the aberration before the DOE diffracted over d too (the sphere to the incoming focus removed)
    t = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    rs = np.sqrt(np.linspace(0.01, 1.0, 20))
    xs, ys = (a_mm * rs[:, None] * np.cos(t)).ravel(), (a_mm * rs[:, None] * np.sin(t)).ravel()
    x1, y1, _ = lens.trace(xs, ys, th, lens.zD)
    x2, y2, _ = lens.trace(xs, ys, th, lens.zD + 1.0)
    dv = np.stack([x2 - x1, y2 - y1, np.ones_like(x1)])
    dv /= np.linalg.norm(dv, axis=0)
    P = np.stack([x1, y1, np.full_like(x1, lens.zD)])
    Q = np.eye(3)[None] - np.einsum("in,jn->nij", dv, dv)
    F = np.linalg.solve(Q.sum(0), np.einsum("nij,jn->i", Q, P))
    s_in = np.exp(-1j * k * np.sqrt((X - F[0]) ** 2 + (Y - F[1]) ** 2 + (F[2] - lens.zD) ** 2) - 2j * math.pi * g.nu0 * X)
    Vws = prop(Vm / s_in) * s_in
    row.update(wave_step_vs_model=float(np.max(np.abs(sensor(Vws, tdoe) - M)) / sensor(Vws, tdoe).max()),
               wave_step_field_difference=float(np.max(np.abs(Vws - V)) / np.max(np.abs(V))))
    row.update(rim_radius_min=float(rim.min()), rim_radius_max=float(rim.max()), rim_radius_mean=float(rim.mean()),
               cpu_s=time.process_time() - c0)
    print(f"F/{7.95 / (2 * a_mm):.2f} {field_deg} deg {wavelength_um} um: main-order truth {row['measured_main_order']:.3f}, "
          f"estimate {row['estimate_main']:.3f}; picture: footprint {row['picture_real_footprint_traced_phase']:.3f} / "
          f"{row['picture_real_footprint_fitted_phase']:.3f}, circle {row['picture_circle_traced_phase']:.3f} / "
          f"{row['picture_circle_fitted_phase']:.3f} (traced / fitted phase); wave step {row['wave_step_vs_model']:.3f}; "
          f"rim {rim.min():.4f}-{rim.max():.4f}", flush=True)
    return row


def reestimate(name):
    """Recompute the planner's estimate on the stored rows of ``perf/results/<name>.json`` (every list of rows in it;
    the truths unchanged: their code is not touched by the estimate's), the previous estimate kept as ``before_rim``
    (the estimate before the rim was the pupil's rim imaged, commit 365c3c9) with its ratio, and as ``before`` where
    that was not yet kept (the orders' change)."""
    import json
    from _common import RESULTS, git_commit
    path = RESULTS / f"{name}.json"
    d = json.loads(path.read_text())
    commit = git_commit()
    for key, rows in d.items():
        if not (isinstance(rows, list) and rows and isinstance(rows[0], dict) and "measured" in rows[0]):
            continue
        for r in rows:
            prev = {k: r[k] for k in ("estimate", "main_estimate", "orders_estimate", "ratio", "estimate_commit",
                                      "commit") if k in r}
            r.setdefault("before", prev)
            r.setdefault("before_rim", prev)
            w = r.get("wavelength_um", 0.55)
            est = estimate(r["stop_radius_mm"], r["field_deg"], tuple(r["doe_coefficients"]), w)
            r.update(est)
            r["ratio"] = est["estimate"] / r["measured"]
            r["ratio_main"] = est["main_estimate"] / r["measured"]
            r["estimate_commit"] = commit
            print(f"{name}[{key}] F/{r.get('f_number', round(7.95 / (2 * r['stop_radius_mm']), 2))} {r['field_deg']} deg "
                  f"{w} um: measured {r['measured']:.4f} estimate {r['before_rim']['estimate']:.4f} -> "
                  f"{est['estimate']:.4f} (ratio {r['before_rim']['estimate'] / r['measured']:.2f} -> {r['ratio']:.2f})",
                  flush=True)
    if "ratio_min" in d:
        d["ratio_min"] = min(r["ratio"] for r in d["rows"])
        d["ratio_max"] = max(r["ratio"] for r in d["rows"])
    if "ratio_min_all_sets" in d:
        allr = [r["ratio"] for v in d.values() if isinstance(v, list) for r in v if isinstance(r, dict) and "ratio" in r]
        d["ratio_min_all_sets"], d["ratio_max_all_sets"] = min(allr), max(allr)
    path.write_text(json.dumps(d, indent=1))
    return path


def run_f22(field_deg, co=F22_COEFFS, wavelength_um=0.55, main_order_only=False):
    """The --f22 case (stop radius 1.807 mm, 0.8 um grid, 1 um slices, the asphere's zone traced, not refined) at
    ``field_deg`` (deg) and ``wavelength_um`` (um; off 0.55 the glass at that wavelength and the DOE's wrapped relief,
    every order; ``main_order_only``: the diagnostic of :func:`run_case`): its row."""
    a = 7.95 / 4.4
    est = estimate(a, field_deg, co, wavelength_um)
    c0 = time.process_time()
    lens = A489(a_mm=a, coeffs=co, lam_mm=wavelength_um * 1e-3)
    if main_order_only:
        lens.doe_scale = 1.0
    T, M, info = truth_and_model(lens, field_deg, h=0.8e-3, dz=1e-3, front="geometric")
    err = measured_error(T, M)
    row = {"stop_radius_mm": a, "f_number": 2.2, "field_deg": field_deg, "wavelength_um": wavelength_um,
           "doe_coefficients": list(co), "pitch_mm": 0.8e-3, "slice_mm": 1e-3, "front": "geometric", "measured": err,
           "ratio": est["estimate"] / err, "cpu_s": time.process_time() - c0,
           "power_doe_truth_over_stop": info["power_doe_truth"] / info["power_stop"], "crop_loss": info["crop_loss"],
           "doe_clipped": info["doe_clipped"], "spectrum_beyond_0p8_nyquist": info["band_edge"],
           "grids": [info["NA_grid"], info["NB_grid"]], **est}
    print(f"F/2.2 {field_deg} deg {wavelength_um} um: measured {err:.4f} estimate {est['estimate']:.4f} ratio {row['ratio']:.2f} "
          f"(N_F {est['fresnel_number']:.1f}, S {est['rim_slope_rad']:.1f} rad) cpu {row['cpu_s']:.0f} s", flush=True)
    return row


def estimate(a_mm, field_deg, coeffs=COEFFS, wavelength_um=0.55):
    """The planner's model-error dict for the A489 + DOE with the stop radius ``a_mm`` (mm), the field ``field_deg``
    (deg), the DOE ``coeffs`` (rad, its design phase at 0.55 um) at ``wavelength_um`` (um)."""
    lens = rw.load_lens("a489_doe")
    lens.surfaces[0].semi_diameter = a_mm
    lens.surfaces[3].profile = {"kind": "even_poly", "norm_radius": 1.5, "coefficients": list(coeffs)}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        me = rw.plan_psf(lens, field_deg, wavelength_um, size=64, method="focal").model_error
    return {k: me[k] for k in ("estimate", "main_estimate", "orders_estimate", "fresnel_number", "rim_slope_rad",
                               "reduced_distance_mm", "beam_radius_mm", "note")}


def run_case(a_mm, field_deg, h, dz, h2, dz2, refine_front, refine=True, coeffs=COEFFS, wavelength_um=0.55,
             checks=True, main_order_only=False):
    """One case (module docstring): the base run's measured error and the estimate; ``checks``: then the front
    zone traced, the smooth pupil and (``refine``) the refined pair (:func:`case_checks`). Lengths mm, deg, um.
    ``main_order_only``: a diagnostic, the DOE transmitting its main order alone (``exp(i phi0)``, no wrapped
    relief) at any wavelength; compare with the estimate's ``main_estimate`` (``ratio_main``)."""
    lens = A489(a_mm=a_mm, coeffs=coeffs, lam_mm=wavelength_um * 1e-3)
    if main_order_only:
        lens.doe_scale = 1.0
    row = {"stop_radius_mm": a_mm, "f_number": round(7.95 / (2 * a_mm), 2), "field_deg": field_deg, "pitch_mm": h,
           "slice_mm": dz, "doe_coefficients": list(coeffs), "doe_norm_mm": 1.5, "wavelength_um": wavelength_um,
           "doe_scale": lens.doe_scale, "glass_index": lens.n}
    c0 = time.process_time()
    T, M, info = truth_and_model(lens, field_deg, h=h, dz=dz, front="wave")
    row["cpu_s"] = time.process_time() - c0
    err = measured_error(T, M)
    row.update(measured=err, truth_peak=float(T.max()), model_peak=float(M.max()),
               patch_half_mm=float(info["patch_x"][-1] - info["patch_x"][0]) / 2, patch_pitch_mm=0.5e-3,
               grids=[info["NA_grid"], info["NB_grid"]], crop_loss=info["crop_loss"], doe_clipped=info["doe_clipped"],
               power_stop=info["power_stop"], power_doe_truth=info["power_doe_truth"],
               power_doe_model=info["power_doe_model"], spectrum_beyond_0p8_nyquist=info["band_edge"])
    est = estimate(a_mm, field_deg, coeffs, wavelength_um)
    row.update(est)
    row["ratio"] = est["estimate"] / err
    row["ratio_main"] = est["main_estimate"] / err
    if main_order_only:
        row["doe"] = "main order only (exp(i phi0)), a diagnostic"
    half = row["patch_half_mm"]
    row["patch_center_mm"] = [float(info["patch_x"][0]) + half, float(info["patch_y"][0]) + half]
    print(f"F/{row['f_number']} {field_deg} deg {wavelength_um} um DOE {coeffs}: measured {err:.4f} estimate "
          f"{est['estimate']:.4f} ratio {row['ratio']:.2f} (N_F {est['fresnel_number']:.1f}, S {est['rim_slope_rad']:.1f} rad) "
          f"cpu {row['cpu_s']:.0f} s", flush=True)
    if checks:
        case_checks(row, lens, h, dz, h2, dz2, refine_front, refine, T, M)
    return row


def case_checks(row, lens, h, dz, h2, dz2, refine_front, refine=True, T=None, M=None):
    """The base run's checks added to ``row`` (its patch): the front zone traced, the smooth pupil, and (``refine``)
    the refined pair (pitch ``h2``, slice ``dz2``, mm; ``refine_front``); ``T``, ``M``: the base run's irradiances
    (None: recomputed, only where the refined pair's front is "wave")."""
    field_deg, half, centre = row["field_deg"], row["patch_half_mm"], tuple(row["patch_center_mm"])
    # the front zone traced geometrically: its share of the error
    Tg, Mg, _ = truth_and_model(lens, field_deg, h=h, dz=dz, front="geometric", patch_half=half,
                                patch_center=centre)
    row["measured_front_geometric"] = measured_error(Tg, Mg)
    # the smooth pupil: no edge, the truth against geometric optics
    Ts, Ms, _ = truth_and_model(lens, field_deg, h=h, dz=dz, front=refine_front, soft=1.0)
    row["smooth_pupil_difference"] = measured_error(Ts, Ms)
    print(f"   front traced: {row['measured_front_geometric']:.4f}; smooth pupil ({refine_front} front): "
          f"{row['smooth_pupil_difference']:.2e}", flush=True)
    if refine:
        c0 = time.process_time()
        T2, M2, i2 = truth_and_model(lens, field_deg, h=h2, dz=dz2, front=refine_front, patch_half=half,
                                     patch_center=centre)
        row["refined"] = {"pitch_mm": h2, "slice_mm": dz2, "front": refine_front, "cpu_s": time.process_time() - c0}
        err2 = measured_error(T2, M2)
        if refine_front == "wave" and T is None:
            T, M, _ = truth_and_model(lens, field_deg, h=h, dz=dz, front="wave", patch_half=half, patch_center=centre)
        T1 = T if refine_front == "wave" else Tg
        row["refined"].update(measured=err2, truth_change=float(np.max(np.abs(T2 - T1)) / T2.max()),
                              base_measured=measured_error(T1, M if refine_front == "wave" else Mg))
        print(f"   refined (h {h2 * 1e3:.2f} um, dz {dz2 * 1e3:.2f} um): measured {err2:.4f}, the truth moved by "
              f"{row['refined']['truth_change']:.2e} of its peak", flush=True)
    return row


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--no-refine", action="store_true")
    ap.add_argument("--set", choices=("all", "main", "steep"), default="all",
                    help="main: the 600 rho^2 + 200 rho^4 DOE at F/8 and F/4; steep: 4x it at F/8 (written to "
                         "model_error_a489_<set>.json; --merge joins the two into model_error_a489.json)")
    ap.add_argument("--merge", action="store_true")
    ap.add_argument("--f22-off", action="store_true",
                    help="the --f22 case at 5 and 10 deg: model_error_a489_f22_off.json (a rerun adds the missing)")
    ap.add_argument("--wavelengths", action="store_true",
                    help="F/4 on axis and at 10 deg at 0.45 and 0.65 um (the DOE's relief remapped): "
                         "model_error_a489_wavelengths.json; the base runs of every case first, then their checks "
                         "(front traced, smooth pupil, refined pair) unless --no-checks (a rerun adds the missing)")
    ap.add_argument("--no-checks", action="store_true")
    ap.add_argument("--wavelengths-f8", action="store_true",
                    help="as --wavelengths on the F/8 cases (0 and 10 deg), every check: "
                         "model_error_a489_wavelengths_f8.json (~1 min a case here)")
    ap.add_argument("--f22-wavelengths", action="store_true",
                    help="the --f22 case on axis at 0.45 and 0.65 um (every order of the wrapped relief): "
                         "model_error_a489_f22_wavelengths.json (a rerun adds the missing; ~5 CPU-minutes a case)")
    ap.add_argument("--pupil-check", action="store_true",
                    help="the edge-wave sum against the exact diffraction of its own fitted pupil phase (F/4: 10 deg at "
                         "0.45 / 0.55 / 0.65 um, axis at 0.55 um): model_error_a489_pupil_check.json (~1 min)")
    ap.add_argument("--rim-check", action="store_true",
                    help="the estimate's picture on the real beam at F/4, 10 deg, 0.45 / 0.55 / 0.65 um (the main-order "
                         "truth, the footprint or the circle, the traced or the fitted phase, the wave step): "
                         "model_error_a489_rim_check.json (~4 CPU-minutes a case)")
    ap.add_argument("--reestimate", action="store_true",
                    help="the planner's estimate recomputed on every stored row (the main set, steep, F/2.2, the "
                         "wavelengths' and the main-order diagnostics'), the previous kept as 'before_rim'")
    ap.add_argument("--main-order-only", action="store_true",
                    help="with --wavelengths: a diagnostic, the DOE's main order alone (no wrapped relief's other "
                         "orders), base runs only: model_error_a489_wavelengths_main_order.json")
    ap.add_argument("--front-check", action="store_true",
                    help="the WPM's slice through the asphere's sag zone halved (1 -> 0.5 um) on the cases whose "
                         "refined pair traced the front zone: model_error_a489_front.json")
    ap.add_argument("--f22", action="store_true",
                    help="one F/2.2 case (the experiments' aperture, stop radius 1.807 mm), axis, the DOE 150 rho^2 + 50 "
                         "rho^4 (the plan's rim slope 92 rad), the asphere's zone traced, 0.8 um grid, no refinement: "
                         "model_error_a489_f22.json (~25 CPU-minutes here)")
    args = ap.parse_args()
    if args.f22:
        print("wrote", save("model_error_a489_f22", {"rows": [run_f22(0.0)]}))
        return
    if args.pupil_check:
        rows = [pupil_check(1.0, f, w) for f, w in ((10.0, 0.45), (10.0, 0.55), (10.0, 0.65), (0.0, 0.55))]
        print("wrote", save("model_error_a489_pupil_check", {"rows": rows, "device": device_name("cpu")}))
        return
    if args.rim_check:
        rows = []
        for w in (0.45, 0.55, 0.65):
            rows.append(rim_check(1.0, 10.0, w))
            save("model_error_a489_rim_check", {"rows": rows, "device": device_name("cpu")})
        return
    if args.reestimate:
        from _common import RESULTS
        for name in ("model_error_a489", "model_error_a489_main", "model_error_a489_steep", "model_error_a489_f22",
                     "model_error_a489_f22_off", "model_error_a489_f22_wavelengths",
                     "model_error_a489_f22_wavelengths_main_order", "model_error_a489_wavelengths",
                     "model_error_a489_wavelengths_main_order", "model_error_a489_wavelengths_f8",
                     "model_error_a489_wavelengths_f8_main_order"):
            if (RESULTS / f"{name}.json").exists():
                print("wrote", reestimate(name))
        return
    if args.f22_wavelengths:
        import json
        from _common import RESULTS, git_commit
        name = "model_error_a489_f22_wavelengths" + ("_main_order" if args.main_order_only else "")
        prev = RESULTS / f"{name}.json"
        rows = json.loads(prev.read_text())["rows"] if prev.exists() else []
        # the main-order diagnostic at 0.65 um only (where the orders lower the estimate)
        for w in ((0.65,) if args.main_order_only else WAVELENGTHS):
            if w not in [r["wavelength_um"] for r in rows]:
                row = run_f22(0.0, wavelength_um=w, main_order_only=args.main_order_only)
                if args.main_order_only:
                    row["doe"] = "main order only (exp(i phi0)), a diagnostic"
                    row["ratio_main"] = row["main_estimate"] / row["measured"]
                rows.append({**row, "commit": git_commit()})
                save(name, {"rows": rows, "device": device_name("cpu")})
        return
    if args.f22_off or args.wavelengths or args.wavelengths_f8:
        import json
        from _common import RESULTS, git_commit
        commit = git_commit()
        name = "model_error_a489_f22_off" if args.f22_off else \
            "model_error_a489_wavelengths" + ("_f8" if args.wavelengths_f8 else "") + \
            ("_main_order" if args.main_order_only else "")
        args.no_checks = args.no_checks or args.main_order_only
        prev = RESULTS / f"{name}.json"
        rows = json.loads(prev.read_text())["rows"] if prev.exists() else []      # kept: a rerun adds the missing
        out = lambda: save(name, {"rows": rows, "device": device_name("cpu")})     # noqa: E731
        if args.f22_off:
            for f in F22_OFF_FIELDS:
                if f not in [r["field_deg"] for r in rows]:
                    rows.append({**run_f22(f), "commit": commit})
                    out()
        else:
            todo = [(w, c) for w in WAVELENGTHS for c in (WAVELENGTH_F8_CASES if args.wavelengths_f8 else WAVELENGTH_CASES)]
            for w, c in todo:                          # the base runs first
                if not any((r["wavelength_um"], r["field_deg"]) == (w, c[1]) for r in rows):
                    rows.append({**run_case(*c, refine=not args.no_refine, wavelength_um=w, checks=False,
                                            main_order_only=args.main_order_only), "commit": commit})
                    out()
            for w, c in ([] if args.no_checks else todo):
                row = next(r for r in rows if (r["wavelength_um"], r["field_deg"]) == (w, c[1]))
                if "smooth_pupil_difference" not in row:
                    c0 = time.process_time()
                    lens = A489(a_mm=c[0], coeffs=COEFFS, lam_mm=w * 1e-3)
                    case_checks(row, lens, *c[2:], refine=not args.no_refine)
                    row["checks_cpu_s"], row["checks_commit"] = time.process_time() - c0, commit
                    out()
        print("wrote", out())
        return
    if args.front_check:
        import json
        from _common import RESULTS
        prev = RESULTS / "model_error_a489_front.json"
        rows = json.loads(prev.read_text())["rows"] if prev.exists() else []      # kept: a rerun adds the missing
        done = {(r["stop_radius_mm"], r["field_deg"], tuple(r["doe_coefficients"])) for r in rows}
        for (a, f, h, dz, _, _, fr), co in [(c, COEFFS) for c in CASES] + [(c, STEEP) for c in STEEP_CASES]:
            if fr != "geometric" or (args.quick and a > 0.5) or (a, f, tuple(co)) in done:
                continue
            lens = A489(a_mm=a, coeffs=co)
            c0 = time.process_time()
            T, M, info = truth_and_model(lens, f, h=h, dz=dz, front="wave")
            half = float(info["patch_x"][-1] - info["patch_x"][0]) / 2
            centre = (float(info["patch_x"][0]) + half, float(info["patch_y"][0]) + half)
            T2, M2, _ = truth_and_model(lens, f, h=h, dz=0.5 * dz, front="wave", patch_half=half, patch_center=centre)
            row = {"stop_radius_mm": a, "field_deg": f, "doe_coefficients": list(co), "pitch_mm": h, "slice_mm": dz,
                   "measured": measured_error(T, M), "measured_half_slice": measured_error(T2, M2),
                   "truth_change": float(np.max(np.abs(T2 - T)) / T2.max()), "cpu_s": time.process_time() - c0}
            rows.append(row)
            print(f"a {a} {f} deg {co}: slice {dz * 1e3:.2f} -> {dz * 5e2:.2f} um: measured {row['measured']:.4f} -> "
                  f"{row['measured_half_slice']:.4f}, the truth moved by {row['truth_change']:.2e}", flush=True)
            save("model_error_a489_front", {"rows": rows})
        return
    if args.merge:
        import json
        from _common import RESULTS
        parts = [json.loads((RESULTS / f"model_error_a489_{s}.json").read_text()) for s in ("main", "steep")]
        rows = parts[0]["rows"] + parts[1]["rows"]
        f22 = RESULTS / "model_error_a489_f22.json"
        extra = json.loads(f22.read_text())["rows"] if f22.exists() else []
        front = RESULTS / "model_error_a489_front.json"
        for fr in (json.loads(front.read_text())["rows"] if front.exists() else []):
            for row in rows:
                if (row["stop_radius_mm"], row["field_deg"], row["doe_coefficients"]) == \
                        (fr["stop_radius_mm"], fr["field_deg"], fr["doe_coefficients"]):
                    row["front_slice_check"] = fr
        r = np.array([x["ratio"] for x in rows])
        more = {}
        for key, part in (("f22_off_unrefined", "f22_off"), ("wavelengths", "wavelengths"),
                          ("wavelengths_f8", "wavelengths_f8")):
            f = RESULTS / f"model_error_a489_{part}.json"
            if f.exists():
                more[key] = json.loads(f.read_text())["rows"]
        r_all = np.array([x["ratio"] for x in rows + extra + sum(more.values(), [])])
        print("wrote", save("model_error_a489", {"rows": rows, "f22_unrefined": extra, **more,
                                                 "ratio_min": float(r.min()), "ratio_max": float(r.max()),
                                                 "ratio_min_all_sets": float(r_all.min()),
                                                 "ratio_max_all_sets": float(r_all.max()),
                                                 "wall_s": sum(p["wall_s"] for p in parts), "device": parts[0]["device"],
                                                 "commit": parts[0]["commit"]}))
        return
    todo = ([(c, COEFFS) for c in CASES] if args.set in ("all", "main") else []) + \
           ([(c, STEEP) for c in STEEP_CASES] if args.set in ("all", "steep") else [])
    rows, t0 = [], time.time()
    name = "model_error_a489" + ("" if args.set == "all" else "_" + args.set) + ("_quick" if args.quick else "")
    for case, co in todo:
        if args.quick and case[0] > 0.5:
            continue
        rows.append(run_case(*case, refine=not args.no_refine, coeffs=co))
        save(name + "_partial", {"rows": rows})
    r = np.array([x["ratio"] for x in rows])
    out = {"rows": rows, "ratio_min": float(r.min()), "ratio_max": float(r.max()), "wall_s": time.time() - t0,
           "device": device_name("cpu")}
    print(f"estimate / measured: {r.min():.2f} .. {r.max():.2f} over {len(r)} cases")
    print("wrote", save(name, out))


if __name__ == "__main__":
    main()
