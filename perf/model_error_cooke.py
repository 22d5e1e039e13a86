"""The ray-wave model's own error on the Cooke hybrid of the paper's Cooke experiment, against a wave-exact truth
(issue 27: the Cooke's DOE position, ~32 mm of the beam behind the stop, had never been measured on the Cooke itself).

The lens: ``torch_bridge/configs/lenses/cooke_hybrid.json`` (the experiment's: the Cooke triplet with N-SK16
elements, the 8 x 8 mm DOE 23.17 mm behind the last surface and 20 mm before the sensor), stopped down to an entrance
pupil of ``EPD`` mm (the file's 11.75 mm is F/4: its truth, ~6000^2 samples and ~700 WPM slices, is out of reach on
2 CPU cores), with the DOE's quadratic term that focuses the beam on the sensor (``-678 rho^2`` rad, rho = r / 4 mm,
at 0.55 um, its design wavelength). For each case (0 and 5 deg):

* the truth (``tests/rwwarp/_cooke_truth.py``: the geometric field on the stop's plane cut by the hard disc, then the
  exact angular spectrum and the WPM through the last element to the DOE plane; numpy, no rwwarp code) against its own
  one-step model (the geometric field traced to the DOE plane; the same DOE and exact angular spectrum to the sensor):
  max |difference| over the truth's peak on the spot (0.5 um samples) -- the model's own error;
* the planner's estimate (``rw.plan_psf(..., method="focal").model_error["estimate"]``) and its ratio to it;
* rwwarp's PSFs (``rw.psf``, 32 px of 1 um, ``pixel_values="intensity"``): method "auto" (the one-step model) and
  "auto" with ``tolerance=1e-3`` (the wave step where the estimate exceeds it), each against the truth's pixels (box
  integrated by 3 x 3 Gauss-Legendre nodes, over the entering power ``pi (EPD / 2)^2``): max |difference| over the
  truth's largest pixel.

The truth is the guarded one (``band``: every free-space step's band about the chief ray, cycles/mm, and a margin
that keeps the edge's wide-angle light from wrapping round the periodic window; rows before commit 59f8548 were
computed on the whole band with a 0.3 mm margin: the pitch-dependent error docs/accuracy.md describes).
The WPM's sub-slice rule is ``sub_slice="snell"`` (BASE, TEST, ``--sub-slice``'s default since commit a6b9c70;
"split" from f92dd76;
rows without a ``sub_slice`` key and earlier rows: the carrier rule, first order in the slice at 5 deg --
the refraction taken at the slice's end, docs/accuracy.md).
Stage guard: the convergence in pitch, slice and band (``--pitches``, ``--slices``, ``--band``, ``--margin``,
``--sub-slice``, ``--rw``). Checks: the truth with its pitch or slice refined (2 -> 1.0 um, 1 -> 0.5 / 0.25 um),
its window's margin doubled,
and the smooth-pupil control (the stop's amplitude a cos^2 over its radius: no edge; the truth against geometric
optics). The test's reduced sampling (``test_model_error_cooke.py``) is measured here too.
CPU only (2 shared cores): ~2-3 min a base case, ~4-8 min a refined one.
Stages: guard (the guarded truth's convergence, rows "guarded"), base (the cases with rwwarp's PSFs), smooth (the
smooth pupil), test (the test's sampling), slice / pitch /
margin (the truth refined against the base, on its patch), slice4 (the slice at 0.25 um on the stored base patch),
element (a diagnostic: the last element traced instead of the WPM); ``--pupil entrance``: rwwarp's entrance-pupil
disc instead of the physical iris (keys suffixed _entrance).
Usage: python perf/model_error_cooke.py [--stage base|smooth|slice|pitch|margin|test|slice4|element] [--fields 0 5]
[--pupil iris|entrance] (the results merged into perf/results/model_error_cooke.json)
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
from _common import device_name, git_commit, save                     # noqa: E402
from _cooke_truth import LENS_FILE, Cooke, measured_error, truth_and_model  # noqa: E402

EPD = 3.0
WL = 0.55
PIX_MM, SIZE = 1e-3, 32
BASE = dict(h=2.0e-3, dz=1e-3, margin=1.0, band=120.0, sub_slice="snell")   # the guarded truth (stage guard)
TEST = dict(h=3.0e-3, dz=1e-3, margin=0.8, band=120.0, sub_slice="snell")   # the test's reduced sampling
#: the guarded truth (``band``: the free-space steps' band, cycles/mm, about the carrier; the window's margin (mm)
#: wide enough that no kept plane wave wraps back onto the beam: _cooke_truth.window_guard)
GUARD = dict(margin=1.0, band=120.0)


def rw_lens(epd_mm: float, coeffs) -> "rw.Lens":
    """The experiment's lens file with the entrance pupil ``epd_mm`` (mm) and the DOE's ``coeffs`` (rad on 4 mm)."""
    lens = rw.load_lens(str(LENS_FILE))
    lens.entrance_pupil_diameter = float(epd_mm)
    lens.surfaces[-1].profile = {"kind": "even_poly", "norm_radius": 4.0, "coefficients": list(coeffs)}
    return lens


def rw_psfs(lens, field_deg: float) -> dict:
    """rwwarp's one-step PSF (method "auto") and its wave path (tolerance 1e-3), 32 px of 1 um, |U|^2 per pixel."""
    out = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for key, kw in (("one_step", {}), ("wave_path", {"tolerance": 1e-3})):
            t0 = time.perf_counter()
            p = rw.psf(lens, field_deg, WL, size=SIZE, pixel_mm=PIX_MM, method="auto", pixel_values="intensity", **kw)
            out[key] = p
            out[key + "_s"] = time.perf_counter() - t0
    return out


def against_truth(sensor, psf, truth_lens: Cooke, field_deg: float) -> dict:
    """rwwarp's PSF against the truth's pixels on its own patch (rwwarp's y is the truth's x: the field's
    direction; the sign of the field's landing matched to the truth's chief ray)."""
    px, py = psf.coords_mm()
    th = np.radians(field_deg)
    xs = truth_lens.chief_x(th, truth_lens.zS)
    sgn = 1.0 if field_deg == 0 or np.sign(psf.center_mm[1]) == np.sign(xs) else -1.0
    T, M = sensor(sgn * py, px, PIX_MM, 3)                       # rows: the truth's y = rwwarp's x
    P_in = np.pi * (0.5 * truth_lens.epd) ** 2
    T, M = T * PIX_MM ** 2 / P_in, M * PIX_MM ** 2 / P_in
    # R[i, j]: rwwarp's pixel at x = px[i], y = py[j], the truth's (x_t = sgn py[j], y_t = px[i]) (a mirror in y_t
    # where sgn < 0: the scene is symmetric about the meridional plane)
    R = psf.data.T
    return {"error": float(np.max(np.abs(R - T)) / T.max()), "own_model_error_on_patch": measured_error(T, M),
            "rw_vs_own_model": float(np.max(np.abs(R - M)) / M.max()), "sum_ratio": float(R.sum() / T.sum()),
            "truth_peak_on_patch_fraction": float(T.max())}


def run_case(field_deg: float, samp: dict, epd_mm=EPD, with_rw=True, soft=0.0, pupil="iris",
             element="wave") -> tuple:
    """One case: the truth against its one-step model, the estimate, rwwarp's PSFs (``with_rw``) -> (row, (T, M,
    info)); ``samp``: the truth's pitch, slice and margin (mm), ``soft``/``pupil``/``element``: truth_and_model's."""
    lens = Cooke(epd_mm=epd_mm, pupil=pupil)
    c0, w0 = time.process_time(), time.perf_counter()
    T, M, info = truth_and_model(lens, field_deg, patch_pitch=0.5e-3, soft=soft, element=element, **samp)
    row = {"field_deg": field_deg, "epd_mm": epd_mm, "pupil": pupil, "element": element, "iris_radius_mm": lens.a,
           "doe_coefficients": list(lens.coeffs),
           "pitch_mm": samp["h"], "slice_mm": samp["dz"], "margin_mm": samp["margin"], "band": samp.get("band"),
           "soft": soft,
           "measured": measured_error(T, M), "grid_n": info["grid_n"],
           # a diagnostic: the truth scaled to the model's power on the DOE plane (the WPM's obliquity: see docs)
           "measured_power_matched": measured_error(T * info["power_doe_model"] / info["power_doe_truth"], M),
           "band_edge": info["band_edge"],
           "power_doe_truth_over_iris": info["power_doe_truth"] / info["power_iris"],
           "power_doe_model_over_iris": info["power_doe_model"] / info["power_iris"],
           "truth_wall_s": info["t_truth_s"], "model_wall_s": info["t_model_s"],
           "patch_half_mm": float(info["patch_x"][-1] - info["patch_x"][0]) / 2,
           "patch_center_mm": [float(np.mean(info["patch_x"])), float(np.mean(info["patch_y"]))]}
    me = plan_error(epd_mm, field_deg, lens.coeffs)
    row.update(estimate=me["estimate"], ratio=me["estimate"] / row["measured"],
               fresnel_number=me["fresnel_number"], rim_slope_rad=me["rim_slope_rad"])
    if with_rw:
        ps = rw_psfs(rw_lens(epd_mm, lens.coeffs), field_deg)
        for key in ("one_step", "wave_path"):
            p = ps[key]
            row[key] = {**against_truth(info["sensor"], p, lens, field_deg), "wall_s": ps[key + "_s"],
                        "method": p.plan.get("method"), "wave_step_mm": p.plan.get("wave_step_mm"),
                        "center_mm": [float(c) for c in p.center_mm]}
    row["cpu_s"], row["wall_s"] = time.process_time() - c0, time.perf_counter() - w0
    print({k: v for k, v in row.items()}, flush=True)
    return row, (T, M, info)


def plan_error(epd_mm, field_deg, coeffs) -> dict:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return rw.plan_psf(rw_lens(epd_mm, coeffs), field_deg, WL, size=SIZE, pixel_mm=PIX_MM,
                           method="focal").model_error


def main():
    import json
    ap = argparse.ArgumentParser()
    ap.add_argument("--stage", choices=("base", "smooth", "slice", "pitch", "margin", "test",
                                                  "element", "slice4", "chief", "guard", "zones"),
                    default="base")
    ap.add_argument("--fields", type=float, nargs="+", default=[0.0, 5.0])
    ap.add_argument("--pitches", type=float, nargs="+", default=[2.0], help="stage guard: the pitches (um)")
    ap.add_argument("--slices", type=float, nargs="+", default=[1.0], help="stage guard: the WPM slices (um)")
    ap.add_argument("--rw", action="store_true", help="stage guard: rwwarp's PSFs against each truth")
    ap.add_argument("--sub-slice", choices=("carrier", "chief", "local", "nearest", "split", "snell"),
                    default="snell",
                    help="stage guard: the WPM's sub-slice frequency (truth_and_model's sub_slice)")
    ap.add_argument("--band", type=float, default=None, help="stage guard: the band (cycles/mm; GUARD's if unset)")
    ap.add_argument("--margin", type=float, default=None, help="stage guard: the margin (mm; GUARD's if unset)")
    ap.add_argument("--pupil", choices=("iris", "entrance"), default="iris",
                    help="the truth's pupil: the physical iris at the stop, or rwwarp's entrance-pupil disc (keys "
                         "suffixed _entrance)")
    args = ap.parse_args()
    from _common import RESULTS
    prev = RESULTS / "model_error_cooke.json"
    res = json.loads(prev.read_text()) if prev.exists() else {}
    res.update({"device": device_name("cpu"), "lens": str(LENS_FILE.relative_to(ROOT)), "wavelength_um": WL,
                "pixel_mm": PIX_MM, "size": SIZE})
    commit = git_commit()
    sfx = "" if args.pupil == "iris" else "_entrance"
    gsfx = sfx                 # stage guard's rows: "guarded" + gsfx
    sfx += "_guarded"          # the other stages' keys since BASE is guarded (keys without it: the earlier truth)
    res["keys_note"] = ("keys without 'guarded' (rows, smooth_pupil, test_sampling, convergence_*, element_geometric, "
                        "sub_slice_chief and their _entrance forms): the earlier truth on the grid's whole band with a "
                        "0.3 mm margin (commits 31ad22e-24b45e1), whose error grew as the pitch fell (the wrap: "
                        "docs/accuracy.md); 'guarded' and '*_guarded': the guarded truth (band about the chief ray)")
    out = lambda: save("model_error_cooke", res)                        # noqa: E731
    for f in args.fields:
        if args.stage == "base":
            row, _ = run_case(f, BASE, pupil=args.pupil)
            key = "rows" + sfx
            res[key] = [r for r in res.get(key, []) if r["field_deg"] != f] + [{**row, "commit": commit}]
        elif args.stage == "guard":
            # the guarded truth (GUARD) at the pitches --pitches (um) and slices --slices (um), each on the first
            # run's patch; each row: the measured error, the truth's and the model's change from the previous row
            rows, prev_tm, pxy = [], None, {}
            lens = Cooke(epd_mm=EPD, pupil=args.pupil)
            me = plan_error(EPD, f, lens.coeffs)
            for hp in args.pitches:
                for dzs in args.slices:
                    import resource
                    over = {**({"band": args.band} if args.band else {}),
                            **({"margin": args.margin} if args.margin else {})}
                    samp = dict(h=hp * 1e-3, dz=dzs * 1e-3, sub_slice=args.sub_slice, **{**GUARD, **over})
                    t0 = time.perf_counter()
                    T, M, i1 = truth_and_model(lens, f, patch_pitch=0.5e-3, **samp, **pxy)
                    pxy = pxy or dict(patch_x=i1["patch_x"], patch_y=i1["patch_y"])
                    row = {"field_deg": f, "pupil": args.pupil, **samp, "grid_n": i1["grid_n"],
                           "measured": measured_error(T, M),
                           "measured_power_matched": measured_error(
                               T * i1["power_doe_model"] / i1["power_doe_truth"], M),
                           "estimate": me["estimate"], "ratio": me["estimate"] / measured_error(T, M),
                           "power_doe_truth_over_iris": i1["power_doe_truth"] / i1["power_iris"],
                           "power_doe_model_over_iris": i1["power_doe_model"] / i1["power_iris"],
                           "wall_s": time.perf_counter() - t0,
                           "max_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6, "commit": commit}
                    if prev_tm is not None:
                        row["truth_change"] = float(np.max(np.abs(T - prev_tm[0])) / T.max())
                        row["model_change"] = float(np.max(np.abs(M - prev_tm[1])) / M.max())
                    if args.rw:
                        ps = rw_psfs(rw_lens(EPD, lens.coeffs), f)
                        for key in ("one_step", "wave_path"):
                            row[key] = {**against_truth(i1["sensor"], ps[key], lens, f), "wall_s": ps[key + "_s"],
                                        "wave_step_mm": ps[key].plan.get("wave_step_mm")}
                    prev_tm = (T, M)
                    rows.append(row)
                    print(row, flush=True)
                    key = "guarded" + gsfx
                    ident = ("field_deg", "h", "dz", "band", "margin", "sub_slice")
                    res[key] = [r for r in res.get(key, []) if tuple(r.get(i, "carrier") for i in ident) !=
                                tuple(row[i] for i in ident)] + [row]
                    out()
        elif args.stage == "zones":
            # which sag zone carries the 5 deg slice error: the slice halved in one zone only (guarded truth, 2 um)
            lens = Cooke(epd_mm=EPD, pupil=args.pupil)
            pxy, rows = {}, []
            for pair in ((1e-3, 1e-3), (0.5e-3, 1e-3), (1e-3, 0.5e-3)):
                t0 = time.perf_counter()
                T, M, i1 = truth_and_model(lens, f, patch_pitch=0.5e-3, h=2e-3, dz=pair, **GUARD, **pxy)
                pxy = pxy or dict(patch_x=i1["patch_x"], patch_y=i1["patch_y"])
                rows.append({"field_deg": f, "h": 2e-3, "dz_zone4": pair[0], "dz_zone5": pair[1], **GUARD,
                             "measured": measured_error(T, M), "wall_s": time.perf_counter() - t0, "commit": commit})
                if len(rows) > 1:
                    rows[-1]["truth_change_from_1um"] = float(np.max(np.abs(T - T0)) / T.max())
                else:
                    T0 = T
                print(rows[-1], flush=True)
            res["zones_guarded" + gsfx] = [r for r in res.get("zones_guarded" + gsfx, []) if r["field_deg"] != f] + rows
        elif args.stage == "slice4":
            # the WPM's slice at a quarter (0.25 um), on the stored base row's patch (its truth not recomputed)
            base = next(r for r in res["rows" + sfx] if r["field_deg"] == f)
            c, half = base["patch_center_mm"], base["patch_half_mm"]
            t0 = time.perf_counter()
            T, M, i1 = truth_and_model(Cooke(epd_mm=EPD, pupil=args.pupil), f,
                                      patch_x=c[0] + np.arange(-half, half + 1e-12, 0.5e-3),
                                      patch_y=c[1] + np.arange(-half, half + 1e-12, 0.5e-3),
                                      patch_pitch=0.5e-3, **{**BASE, "dz": 0.25e-3})
            row = {"field_deg": f, **BASE, "dz": 0.25e-3, "measured": measured_error(T, M),
                   "power_doe_truth_over_iris": i1["power_doe_truth"] / i1["power_iris"],
                   "wall_s": time.perf_counter() - t0, "commit": commit}
            res["convergence_slice_quarter" + sfx] = [row]
            print(row, flush=True)
        elif args.stage == "chief":
            # the WPM's sub-slice phase at the chief ray's transverse frequency (not the carrier's): slices 1 and
            # 0.5 um on the stored base patch
            base = next(r for r in res["rows" + sfx] if r["field_deg"] == f)
            c, half = base["patch_center_mm"], base["patch_half_mm"]
            pxy = dict(patch_x=c[0] + np.arange(-half, half + 1e-12, 0.5e-3),
                       patch_y=c[1] + np.arange(-half, half + 1e-12, 0.5e-3), patch_pitch=0.5e-3)
            rows, Ts = [], []
            for dzc in (1e-3, 0.5e-3):
                t0 = time.perf_counter()
                T, M, i1 = truth_and_model(Cooke(epd_mm=EPD, pupil=args.pupil), f,
                                           **{**BASE, "dz": dzc, "sub_slice": "chief"}, **pxy)
                Ts.append(T)
                rows.append({"field_deg": f, **BASE, "dz": dzc, "sub_slice": "chief", "measured": measured_error(T, M),
                             "power_doe_truth_over_iris": i1["power_doe_truth"] / i1["power_iris"],
                             "wall_s": time.perf_counter() - t0, "commit": commit})
                print(rows[-1], flush=True)
            rows[-1]["truth_change_from_1um"] = float(np.max(np.abs(Ts[1] - Ts[0])) / Ts[1].max())
            res["sub_slice_chief" + sfx] = [r for r in res.get("sub_slice_chief" + sfx, [])
                                            if r["field_deg"] != f] + rows
            print(rows[-1], flush=True)
        elif args.stage == "element":
            # a diagnostic: the last element traced (the truth from the traced field behind it), hard and smooth
            for soft in (0.0, 1.0):
                row, _ = run_case(f, BASE, with_rw=False, soft=soft, pupil=args.pupil, element="geometric")
                key = "element_geometric" + sfx
                res[key] = [r for r in res.get(key, []) if (r["field_deg"], r["soft"]) != (f, soft)] + \
                    [{**row, "commit": commit}]
                out()
        elif args.stage in ("smooth", "test"):
            row, _ = run_case(f, TEST if args.stage == "test" else BASE, with_rw=False,
                              soft=1.0 if args.stage == "smooth" else 0.0, pupil=args.pupil)
            key = {"smooth": "smooth_pupil", "test": "test_sampling"}[args.stage] + sfx
            res[key] = [r for r in res.get(key, []) if r["field_deg"] != f] + [{**row, "commit": commit}]
        else:
            # convergence: the base truth against one with the slice halved, the pitch 1.5 -> 1.0 um, or the
            # window's margin doubled, on the base patch
            samp = {"slice": {**BASE, "dz": 0.5e-3}, "pitch": {**BASE, "h": 1.0e-3},
                    "margin": {**BASE, "margin": 2 * BASE["margin"]}}[args.stage]
            T0, M0, i0 = truth_and_model(Cooke(epd_mm=EPD, pupil=args.pupil), f, patch_pitch=0.5e-3, **BASE)
            t0 = time.perf_counter()
            T, M, i1 = truth_and_model(Cooke(epd_mm=EPD, pupil=args.pupil), f, patch_x=i0["patch_x"],
                                       patch_y=i0["patch_y"],
                                      patch_pitch=0.5e-3, **samp)
            row = {"field_deg": f, **samp, "measured": measured_error(T, M), "base_measured": measured_error(T0, M0),
                   "power_doe_truth_over_iris": i1["power_doe_truth"] / i1["power_iris"],
                   "base_power_doe_truth_over_iris": i0["power_doe_truth"] / i0["power_iris"],
                   "truth_change": float(np.max(np.abs(T - T0)) / T.max()),
                   "model_change": float(np.max(np.abs(M - M0)) / M.max()), "wall_s": time.perf_counter() - t0,
                   "commit": commit}
            key = "convergence_" + args.stage + sfx
            res[key] = [r for r in res.get(key, []) if r["field_deg"] != f] + [row]
            print(key, row, flush=True)
        out()
    print("wrote", out())


if __name__ == "__main__":
    main()
