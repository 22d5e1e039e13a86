"""The wave step's principle on the radial wave truth, free of rwwarp's sampling (issue 27): which distance the step
must propagate over.

The wave step (rwwarp/wave/wave_step.py) replaces the geometric field on the DOE plane by ``S_T P_D[U_geo / S_T]``:
the converging sphere removed, the rest propagated as a wave over a distance ``D``, the sphere put back. Here the
same operation is written on the quadrature of ``tests/rwwarp/_wave_truth.py`` (not with rwwarp's code): the
geometric field ``1 / s`` on the beam's disc (radius ``s a``, ``s = d2 / f``), its Hankel angular spectrum, the exact
transfer ``exp(2 pi i D sqrt(1 / lambda^2 - nu^2))`` (its constant phase removed), the exact sphere
``exp(-i k sqrt(r^2 + d2^2))``, the DOE, the exact angular spectrum to the sensor; against the two-step truth (the
lens's wave propagated exactly to the DOE). Distances ``D``: the reduced distance ``d = z1 d2 / f`` (Fresnel's
scaling), ``d / m_z``, ``d / m_z^2`` and ``d / m_z^3`` (``m_z`` the rim ray's direction cosine, ``f / sqrt(a^2 +
f^2)``; the step's stretch on the axis, ``rwwarp.wave.wave_step.rim_obliquity``), and ``d`` with the Fresnel transfer
``exp(-i pi lambda D nu^2)`` instead of the exact one (the transfer's own part). Scene: perf/model_error_issue_level.py's
(thin lens f = 50 mm, a = 5 mm, DOE ``4 rho^4``, 0.55 um, on axis), DOE 5 / 10 / 20 / 35 / 45 mm before the sensor.
Metric: max |I - truth| / max truth over the radii 0-40 um (161 points).

Writes perf/results/wave_step_obliquity.json. CPU (numpy), about 2 minutes on a shared 2-core CPU.
Usage: python perf/wave_step_obliquity.py [--distances 5 10]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy.special import j0

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "rwwarp"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import save                                                         # noqa: E402
from _wave_truth import F_MM, LAM_MM, _gl, _hankel, _j0_sum, _lens_spectrum, _rmatmul   # noqa: E402

A_MM, COEFFS, Q = 5.0, (0.0, 4.0), 3.0


def errors(d2_mm: float, distances: dict, rho_mm: np.ndarray) -> dict:
    """max |I_D - I_truth| / max I_truth over ``rho_mm`` for each named ``(D mm, fresnel)`` of ``distances``."""
    k = 2 * np.pi / LAM_MM
    z1, s = F_MM - d2_mm, d2_mm / F_MM
    na = A_MM / np.hypot(A_MM, F_MM)
    band = 2.0 * na / LAM_MM
    rb, d = s * A_MM, z1 * d2_mm / F_MM
    dens = Q * (na / LAM_MM + band)
    nu, wnu = _gl(0.0, band, Q * (A_MM + F_MM * band * LAM_MM))
    H = lambda z: np.exp(2j * np.pi * z * np.sqrt(1 / LAM_MM ** 2 - nu ** 2))
    W = lambda r: sum(c * (r / rb) ** (2 * (i + 1)) for i, c in enumerate(COEFFS))
    r1, w1 = _gl(0.0, rb + 0.15 * rb + 30 * np.sqrt(LAM_MM * d), dens)
    J = j0(2 * np.pi * np.outer(r1, nu))
    fields = [2 * np.pi * _rmatmul(J, _lens_spectrum(A_MM, Q, nu, dens) * H(z1) * nu * wnu)]   # the truth on the DOE
    rg, wg = _gl(0.0, rb, dens)
    G = _hankel(np.full(len(rg), 1 / s, complex), rg, wg, nu)          # the geometric field, sphere removed
    sphere = np.exp(-1j * k * np.hypot(r1, d2_mm))
    for D, fresnel in distances.values():
        T = np.exp(-1j * np.pi * LAM_MM * D * nu ** 2) if fresnel else H(D) * np.exp(-2j * np.pi * D / LAM_MM)
        fields.append(2 * np.pi * _rmatmul(J, G * T * nu * wnu) * sphere)
    spectra = [2 * np.pi * _rmatmul(J.T, f * np.exp(1j * W(r1)) * r1 * w1) for f in fields]
    U = _j0_sum(rho_mm, nu, np.stack(spectra, 1) * (H(d2_mm) * nu * wnu)[:, None])
    I = np.abs(U) ** 2
    peak = I[:, 0].max()
    return {name: float(np.max(np.abs(I[:, j + 1] - I[:, 0])) / peak) for j, name in enumerate(distances)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--distances", type=float, nargs="*", default=[5.0, 10.0, 20.0, 35.0, 45.0])
    args = ap.parse_args()
    t0 = time.perf_counter()
    mz = F_MM / np.hypot(A_MM, F_MM)
    rho = np.linspace(0.0, 0.04, 161)
    rows = []
    for d2 in args.distances:
        d = (F_MM - d2) * d2 / F_MM
        dist = {"d": (d, False), "d/m_z": (d / mz, False), "d/m_z^2": (d / mz ** 2, False), "d/m_z^3": (d / mz ** 3, False),
                "d, Fresnel transfer": (d, True)}
        e = errors(d2, dist, rho)
        rows.append({"doe_to_sensor_mm": d2, "reduced_distance_mm": d, "distances_mm": {k: v[0] for k, v in dist.items()},
                     "error": e})
        print(f"DOE {d2:4g} mm (d {d:.4g} mm): " + "  ".join(f"{k} {v:.2e}" for k, v in e.items()), flush=True)
    data = {"scene": {"focal_length_mm": F_MM, "stop_radius_mm": A_MM, "doe": "4 rho^4 rad", "wavelength_um": LAM_MM * 1e3,
                      "rim_direction_cosine": mz},
            "metric": "max |I - truth| / max truth over 0-40 um (radial, no pixels)", "rows": rows,
            "total_s": time.perf_counter() - t0}
    print("wrote", save("wave_step_obliquity", data))


if __name__ == "__main__":
    main()
