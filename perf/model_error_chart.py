"""The ray-wave model's own error against the Fresnel number (issue 27): computed, not copied.

Scene (docs/accuracy.md, "The model's own error and the wave step"): ideal thin lens f = 50 mm, round stop
a = 5 mm (EPD 10), a radial DOE ``3 rho^4`` (rad) on the beam, sensor at the lens focus, 48 px of 0.5 um,
0.55 um, on axis; the DOE 5 .. 45 mm before the sensor. For each distance:

* ``fresnel_number``: the plan's (``Plan.model_error``, from rwwarp's pilot trace) and the thin lens's
  ``a^2 (f - z1) / (lambda f z1)``;
* ``estimate``: the plan's (the rim's edge waves summed on the pilot's pupil phase, :mod:`rwwarp.wave.edge_wave`);
* ``estimate_scalar_law``: the old scalar law ``E = 0.25 S / N_F (1 + (S / 25)^2)`` on the plan's ``N_F`` and ``S``
  (:func:`rwwarp.wave.model_error.model_error`, for comparison);
* ``one_step``: rwwarp's one-step PSF (``method="auto"`` without a tolerance) against the wave-exact two-step
  truth (``tests/rwwarp/_wave_truth.py``: Gauss-Hankel angular spectrum, lens -> DOE -> sensor, integrated over
  the pixels), max |difference| over the truth's peak;
* ``one_step_radial``: the same for the truth's own geometric model (free of rwwarp's sampling);
* ``wave_step``: rwwarp's ``method="two-step"`` PSF against the same truth.

Writes perf/results/model_error_chart.json and docs/model_error_vs_fresnel.png (log-log, with the 13 / N_F
line of issue 27's original measurement). CPU (PoCL); about 3 minutes on a shared 2-core CPU.
Usage: python perf/model_error_chart.py [--distances 5 10 20] [--no-plot] [--replot perf/results/model_error_chart.json]
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

import rwwarp as rw                                            # noqa: E402
from rwwarp.wave import model_error                           # noqa: E402
from _common import device_name, git_commit, save             # noqa: E402
from _wave_truth import F_MM, analytic_inputs, pixel_truth, radial_truth, thin_lens_doe   # noqa: E402

A_MM, COEFFS, PIXEL_MM, SIZE, WAVELENGTH_UM = 5.0, (0.0, 3.0), 0.5e-3, 48, 0.55
DISTANCES_MM = (5.0, 7.0, 10.0, 14.0, 20.0, 28.0, 35.0, 45.0)
#: issue 27's original measurement of the one-step error: ~13 / N_F
ORIGINAL_C = 13.0
PNG = ROOT / "docs" / "model_error_vs_fresnel.png"


def versions() -> dict:
    import importlib.metadata
    out = {"python": sys.version.split()[0], "rwwarp": rw.__version__}
    for m, dist in (("numpy", "numpy"), ("scipy", "scipy"), ("warp", "warp-lang"), ("pyopencl", "pyopencl"),
                    ("pyvkfft", "pyvkfft"), ("matplotlib", "matplotlib")):
        try:
            out[m] = importlib.metadata.version(dist)
        except Exception:   # optional: absent
            out[m] = None
    return out


def one_distance(d2_mm: float) -> dict:
    """The row of one DOE-to-sensor distance ``d2_mm`` (mm)."""
    lens = thin_lens_doe(d2_mm, A_MM, COEFFS, pixel=PIXEL_MM)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t = time.perf_counter()
        one = rw.psf(lens, 0.0, WAVELENGTH_UM, size=SIZE, method="auto")
        t_one = time.perf_counter() - t
        t = time.perf_counter()
        two = rw.psf(lens, 0.0, WAVELENGTH_UM, size=SIZE, method="two-step")
        t_two = time.perf_counter() - t
    x, y = one.coords_mm()
    rho = np.linspace(0.0, 1.5 * np.hypot(np.abs(x).max(), np.abs(y).max()) + PIXEL_MM, 1201)
    t = time.perf_counter()
    truth_r, model_r = radial_truth(A_MM, d2_mm, COEFFS, rho)
    t_truth = time.perf_counter() - t
    T, M = pixel_truth(truth_r, rho, x, y, one.pixel_mm), pixel_truth(model_r, rho, x, y, one.pixel_mm)
    peak = T.max()
    me = one.plan["model_error"]
    nf_thin, slope = analytic_inputs(A_MM, d2_mm, COEFFS)
    return {"doe_to_sensor_mm": d2_mm, "fresnel_number": me["fresnel_number"], "fresnel_number_thin_lens": nf_thin,
            "rim_slope_rad": me["rim_slope_rad"], "rim_slope_rad_exact": slope, "estimate": me["estimate"],
            "estimate_scalar_law": model_error.model_error(me["fresnel_number"], me["rim_slope_rad"]),
            "one_step": float(np.max(np.abs(one.data - T)) / peak),
            "one_step_radial": float(np.max(np.abs(M - T)) / peak),
            "wave_step": float(np.max(np.abs(two.data - T)) / peak),
            "one_step_method": one.plan["method"], "wave_step_method": two.plan["method"],
            "wave_step_mm": two.plan["wave_step_mm"],
            "time_one_step_s": t_one, "time_two_step_s": t_two, "time_truth_s": t_truth}


def plot(rows, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    nf = np.array([r["fresnel_number_thin_lens"] for r in rows])
    fig, ax = plt.subplots(figsize=(6.4, 4.4), dpi=100)
    line = np.geomspace(nf.min() / 1.5, nf.max() * 1.5, 50)
    ax.loglog(line, ORIGINAL_C / line, ":", color="0.5", label="13 / N_F (issue 27's original measurement)")
    ax.loglog(nf, [r["one_step"] for r in rows], "o-", color="C3", label="one-step PSF vs wave truth (measured)")
    ax.loglog(nf, [r["estimate"] for r in rows], "s--", color="C0", mfc="none",
              label="estimate: the rim's edge waves (Plan.model_error)")
    if all("estimate_scalar_law" in r for r in rows):
        ax.loglog(nf, [r["estimate_scalar_law"] for r in rows], "x:", color="C0", alpha=0.6,
                  label="old scalar law 0.25 S / N_F (1 + (S/25)^2)")
    ax.loglog(nf, [r["wave_step"] for r in rows], "^-", color="C2", label='with the wave step (method="two-step")')
    for r in rows:
        ax.annotate(f'{r["doe_to_sensor_mm"]:g} mm', (r["fresnel_number_thin_lens"], r["one_step"]),
                    textcoords="offset points", xytext=(4, 5), fontsize=7, color="C3")
    ax.set_xlabel("Fresnel number N_F = a^2 (f - z1) / (lambda f z1)  (dimensionless)")
    ax.set_ylabel("max |PSF - truth| / truth's peak  (dimensionless)")
    ax.set_title("Ray-wave model error vs Fresnel number (labels: DOE-to-sensor distance)\n"
                 "thin lens f 50 mm, EPD 10 mm, DOE 3 rho^4 (S = 12 rad), 48 px of 0.5 um, 0.55 um", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--distances", type=float, nargs="+", default=list(DISTANCES_MM),
                    help="DOE-to-sensor distances (mm), each in (0, 50)")
    ap.add_argument("--no-plot", action="store_true")
    ap.add_argument("--png", type=Path, default=PNG)
    ap.add_argument("--replot", type=Path, metavar="JSON", help="only redraw the PNG from a results JSON")
    args = ap.parse_args(argv)
    if args.replot:
        import json
        plot(json.loads(args.replot.read_text())["rows"], args.png)
        print("wrote", args.png)
        return
    bad = [d for d in args.distances if not 0 < d < F_MM]
    if bad:
        ap.error(f"--distances must lie in (0, {F_MM:g}) mm (the DOE between the lens and its focus), got {bad}")
    t0 = time.perf_counter()
    rows = []
    for d2 in sorted(args.distances):
        r = one_distance(d2)
        rows.append(r)
        print(f"DOE {d2:4g} mm: N_F {r['fresnel_number']:7.1f} (thin lens {r['fresnel_number_thin_lens']:7.1f})  "
              f"estimate {r['estimate']:.2e}  one-step {r['one_step']:.2e} ({r['one_step_method']}; radial model "
              f"{r['one_step_radial']:.2e})  wave step {r['wave_step']:.2e}  "
              f"[{r['time_one_step_s']:.1f} / {r['time_two_step_s']:.1f} / truth {r['time_truth_s']:.1f} s]", flush=True)
    data = {"commit": git_commit(), "device": device_name("cpu"), "versions": versions(),
            "scene": {"focal_length_mm": F_MM, "stop_radius_mm": A_MM, "doe_coefficients_rad": list(COEFFS),
                      "doe_norm": "the beam's radius on the DOE plane", "pixel_mm": PIXEL_MM, "size_px": SIZE,
                      "wavelength_um": WAVELENGTH_UM, "field_deg": 0.0},
            "metric": "max |PSF - truth| / max truth, per pixel (truth integrated over the pixels)",
            "original_measurement": f"{ORIGINAL_C:g} / N_F", "rows": rows,
            "total_s": time.perf_counter() - t0}
    print("wrote", save("model_error_chart", data))
    if not args.no_plot:
        plot(rows, args.png)
        print("wrote", args.png, f"({args.png.stat().st_size / 1024:.0f} KB)")


if __name__ == "__main__":
    main()
