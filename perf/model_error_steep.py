"""The edge-wave estimate of the model error on steep rims (issue 27): radial wave-exact truths, computed, not copied.

For each case (thin lens f = 50 mm, round stop a, radial DOE ``sum_i c_i rho^(2 i)`` d2 before the sensor at the lens
focus, 0.55 um, on axis): the measured model error (``tests/rwwarp/_wave_truth.py``: the Gauss-Hankel angular
spectrum, lens -> DOE -> sensor, against the geometric "one-step" field, max |difference| over the truth's peak, on
the radii of the whole geometric spot; the band widened over the DOE's frequencies 1.5 times and rolled off over its
top 30 %, 4 nodes per oscillation: ``steep_band``, ``steep_radii``), the estimate
(:func:`rwwarp.wave.edge_wave.edge_wave_error` on the analytic pupil phase and N_F), their ratio, the rim slope S and
the edge wave's shift ``S / (2 pi N_F)`` (of the beam's radius), whether the rays were traced, and the estimate's CPU
time. Writes perf/results/model_error_steep.json. CPU; about 7 minutes on a shared 2-core host.
Usage: python perf/model_error_steep.py [--quick]  (--quick: the a <= 1.5 mm cases only)
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "rwwarp"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from rwwarp.wave.edge_wave import edge_wave_error, radial_pupil_phase   # noqa: E402
from _common import save                                                # noqa: E402
from _wave_truth import analytic_inputs, measured_error, steep_band, steep_radii   # noqa: E402

#: (a mm, d2 mm, DOE coefficients rad): rho^4 series over N_F 9-530, balanced, rho^6, rho^8, defocus; S 300
CASES = [(2.5, 10.0, (0.0, 10.0)), (2.5, 10.0, (0.0, 15.0)), (2.5, 10.0, (0.0, 25.0)), (2.5, 10.0, (0.0, 35.0)),
         (2.5, 10.0, (0.0, 50.0)), (1.5, 20.0, (0.0, 10.0)), (1.5, 20.0, (0.0, 25.0)), (1.5, 20.0, (0.0, 40.0)),
         (1.5, 20.0, (0.0, 50.0)), (2.5, 20.0, (0.0, 25.0)), (2.5, 20.0, (0.0, 50.0)), (2.5, 35.0, (0.0, 50.0)),
         (1.5, 10.0, (0.0, 10.0)), (1.5, 10.0, (0.0, 25.0)), (1.0, 10.0, (0.0, 10.0)), (2.5, 10.0, (-25.0, 25.0)),
         (2.5, 10.0, (-50.0, 50.0)), (2.5, 10.0, (0.0, 0.0, 10.0)), (2.5, 10.0, (0.0, 0.0, 25.0)),
         (2.5, 10.0, (-30.0, 0.0, 30.0)), (2.5, 10.0, (20.0, 10.0)), (2.5, 10.0, (50.0,)),
         (2.5, 10.0, (0.0, 0.0, 0.0, 20.0)), (2.5, 35.0, (0.0, 75.0)), (2.5, 20.0, (0.0, 75.0)),
         (1.5, 20.0, (0.0, 75.0)), (2.5, 10.0, (0.0, 0.0, 50.0))]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    rows = []
    for a, d2, c in CASES:
        if args.quick and a > 1.5:
            continue
        err = measured_error(a, d2, c, rho_mm=steep_radii(a, d2, c), band=steep_band(a, d2, c, 1.5), taper=0.3, q=4.0)
        nf, s = analytic_inputs(a, d2, c)
        ts = []
        for _ in range(5):
            t0 = time.process_time()
            est, info = edge_wave_error(nf, radial_pupil_phase(c))
            ts.append(time.process_time() - t0)
        row = {"a_mm": a, "d2_mm": d2, "coeffs": list(c), "fresnel_number": nf, "rim_slope_rad": s,
               "shift": s / (2 * math.pi * nf), "measured": err, "estimate": est,
               "ratio": None if est is None else est / err, "traced": info.get("traced"),
               "estimate_ms": 1e3 * min(ts)}
        rows.append(row)
        print(f"a {a} d2 {d2} {c}: N_F {nf:.1f} S {s:.0f} shift {row['shift']:.2f} measured {err:.3e} estimate "
              f"{est:.3e} ratio {row['ratio']:.2f} traced {row['traced']} {row['estimate_ms']:.1f} ms", flush=True)
    r = np.array([x["ratio"] for x in rows if x["ratio"] is not None])
    print(f"estimate / measured: {r.min():.2f} .. {r.max():.2f} over {len(r)} cases")
    print("wrote", save("model_error_steep", {"rows": rows, "ratio_min": float(r.min()), "ratio_max": float(r.max())}))


if __name__ == "__main__":
    main()
