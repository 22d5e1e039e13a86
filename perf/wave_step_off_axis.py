"""The wave step off axis at the issue's NA (issue 27): rwwarp's PSF (``method="auto", tolerance=1e-3``, which adds
the wave step, rim-resolved where the rim's stretch varies; the same step isotropic, one distance for the whole rim,
the step before; and with the stretch switched off) against the independent off-axis two-step truth of
tests/rwwarp/_offaxis_truth.py (numpy FFTs from the equations, not rwwarp's code).

Scene: the ideal thin lens f = 50 mm, stop radius 5 mm at the lens (NA 0.0995), 0.55 um, 64 px of 0.5 um; the DOE
5 / 10 mm before the sensor at the lens focus. A DOE centred on the axis cannot keep the issue's ``4 rho^4`` (norm
radius the on-axis beam's, 0.5 / 1 mm) on an off-axis beam (at 5 deg the beam lands 3.9 mm off the axis, 8 beam radii),
so off axis the DOE is ``8 rho^2`` (the same norm radius, the same rim slope 16 rad as ``4 rho^4``): a quadratic phase
is the same about every point, so each field's beam sees the same DOE (defocus plus a tilt), and only the beam's
obliquity changes with the field; the DOE's clear radius 9 mm covers 10 deg. The control is the issue's own case
(``4 rho^4``, on the axis, 5 mm). Metric: max |PSF - truth| / max truth over the 64 x 64 pixels (4 x 4 Gauss nodes
each, ``|U|^2`` per pixel over the power entering the stop: ``rw.psf(..., pixel_values="intensity")``; the default
"flux" PSF, the Poynting vector's z-component, is the truth times ~cos of the beam's angle, so it is compared after a
least-squares scale, which is reported). The truth's convergence: its pitch
halved (2 -> 1 um) and its disc's band doubled (60 -> 120 cycles/mm at 1.5 um), its DOE-plane cut widened 1.5x, on the
10 deg cases. Times: the one-step plan (``method="auto"``) and the wave path (tolerance 1e-3), median of 3 warm calls.
The default ``method="asm"`` patch centre is recorded (the chief ray's landing on the DOE's main order, as the step's).

Writes perf/results/wave_step_off_axis.json. CPU (numpy + Warp CPU), about 12 minutes on a shared 2-core CPU (with
the convergence and the principle; 2.5 GB, the halved pitch's truths more).
The principle (:func:`principle`, no rwwarp): the truth's own FFTs with the geometric field stepped over d, d times
the isotropic mean stretch, a fitted tensor and rim-resolved (:func:`rim_resolved_step`), to tell the isotropic
transfer's share of the error.
Usage: python perf/wave_step_off_axis.py [--no-convergence] [--no-principle]
"""
from __future__ import annotations

import argparse
import re
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "rwwarp"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import rwwarp as rw                                        # noqa: E402
import rwwarp.wave.wave_step as ws                         # noqa: E402
from _common import git_commit, save                       # noqa: E402
from _offaxis_truth import F_MM, LAM_MM, offaxis_truth, thin_lens_doe_off_axis   # noqa: E402
import scipy.fft                                           # noqa: E402

A_MM, PIXEL, SIZE = 5.0, 0.5e-3, 64


def lens_of(d2_mm: float, coeffs, semi_mm: float):
    """The scene (tests/rwwarp/_offaxis_truth.py, ``thin_lens_doe_off_axis``) with A_MM and PIXEL."""
    return thin_lens_doe_off_axis(A_MM, d2_mm, coeffs, semi_mm, PIXEL)


def psfs(lens, field_deg, pixel_values="intensity"):
    """(one-step, auto + tolerance 1e-3, the same with the stretch off, the same isotropic, the stretch factor); the
    pixels ``|U|^2`` integrated (``pixel_values="intensity"``: the truth's scalar convention; the default "flux"
    multiplies by the Poynting vector's z-component, 0.991 of it at 10 deg, 5 mm: reported apart)."""
    kw = dict(size=SIZE, pixel_values=pixel_values)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        two = rw.psf(lens, field_deg, 0.55, method="auto", tolerance=1e-3, **kw)
        # the one-step patch on the step's centre (its own default centre off axis is the chief ray's landing
        # without the DOE's deflection, 0.24 mm from the spot at 10 deg, 5 mm)
        one = rw.psf(lens, field_deg, 0.55, method="asm", center_mm=two.center_mm, **kw)
        flat = no_stretch(lambda: rw.psf(lens, field_deg, 0.55, method="auto", tolerance=1e-3, **kw))
        iso = isotropic(lambda: rw.psf(lens, field_deg, 0.55, method="auto", tolerance=1e-3, **kw))
    m = [re.search(r"\(x([0-9.]+) for the rim rays' obliquity", r) for r in two.plan["reasons"]]
    stretch = [float(x.group(1)) for x in m if x]
    m0 = [re.search(r"\(x([0-9.]+) for the rim rays' obliquity", r) for r in flat.plan["reasons"]]
    assert [float(x.group(1)) for x in m0 if x] == [1.0], "the stretch was not switched off"
    assert not any("rim-resolved" in r for r in flat.plan["reasons"] + iso.plan["reasons"])
    return one, two, flat, iso, (stretch[0] if stretch else None)


def no_stretch(call):
    """``call()`` with the rim's stretch off: every rim ray's ``t = 1`` (rwwarp.wave.wave_step._rim_samples), the step
    over the reduced distance itself (rim_obliquity 1, rim_profile one node)."""
    keep = ws._rim_samples

    def flat(r, k):
        got = keep(r, k)
        return None if got is None else (*got[:3], np.ones_like(got[3]))
    ws._rim_samples = flat
    try:
        return call()
    finally:
        ws._rim_samples = keep


def isotropic(call):
    """``call()`` with the step isotropic (the rim's mean stretch, one node: the step before the rim-resolved one)."""
    keep = ws.rim_profile

    def one_node(r, d):
        p = keep(r, d)
        p[:, 3] = 1
        return p
    ws.rim_profile = one_node
    try:
        return call()
    finally:
        ws.rim_profile = keep


def timings(lens, field_deg, repeats=3):
    """(one-step, wave path) seconds, the median of ``repeats`` warm calls each (one call of each first), every call
    planning afresh: ``rw.psf`` with method "auto" (the one-step plan) and with tolerance 1e-3 (the wave path)."""
    kw = dict(size=SIZE, pixel_values="intensity", method="auto")
    out = {"one_step": [], "wave_path": []}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rw.psf(lens, field_deg, 0.55, **kw)
        rw.psf(lens, field_deg, 0.55, tolerance=1e-3, **kw)
        for _ in range(repeats):
            for name, extra in (("one_step", {}), ("wave_path", {"tolerance": 1e-3})):
                t0 = time.perf_counter()
                rw.psf(lens, field_deg, 0.55, **kw, **extra)
                out[name].append(time.perf_counter() - t0)
    return float(np.median(out["one_step"])), float(np.median(out["wave_path"]))


def err(p, T):
    """max |p - T| / max T (of the truth's peak; both power per pixel over the power entering the stop)."""
    return float(np.max(np.abs(p - T)) / T.max())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--no-convergence", action="store_true")
    ap.add_argument("--no-principle", action="store_true")
    args = ap.parse_args()
    t00 = time.perf_counter()
    cases = [("4 rho^4", (0.0, 4.0), 5.0, 0.0, 1.5 * A_MM * 5.0 / F_MM)]
    for d2 in (5.0, 10.0):
        for fld in (0.0, 5.0, 10.0):
            cases.append(("8 rho^2", (8.0, 0.0), d2, fld, 9.0))
    rows = []
    for doe, coeffs, d2, fld, semi in cases:
        t0 = time.perf_counter()
        lens = lens_of(d2, coeffs, semi)
        one, two, flat, iso, stretch = psfs(lens, fld)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            asm_default = rw.psf(lens, fld, 0.55, size=SIZE, method="asm", pixel_values="intensity")
        px, py = two.coords_mm()
        t1 = time.perf_counter()
        T = offaxis_truth(A_MM, d2, coeffs, A_MM * d2 / F_MM, fld, px, py, two.pixel_mm)
        t2 = time.perf_counter()
        assert np.allclose(one.center_mm, two.center_mm)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            flux = rw.psf(lens, fld, 0.55, size=SIZE, method="auto", tolerance=1e-3).data
        scale = float(np.sum(flux * T) / np.sum(T * T))
        row = {"doe": doe, "doe_to_sensor_mm": d2, "field_deg": fld, "stretch": stretch,
               "wave_step_mm": two.plan.get("wave_step_mm"), "estimate": two.plan["model_error"]["estimate"],
               "nodes": int(max([int(x) for r in two.plan["reasons"] for x in re.findall(r"between up to (\d+) distances", r)]
                                + [1])),
               "error_one_step": err(one.data, T), "error_step": err(two.data, T),
               "error_step_isotropic": err(iso.data, T), "error_step_no_stretch": err(flat.data, T),
               "asm_default_center_mm": [float(c) for c in asm_default.center_mm],
               "asm_default_center_is_the_steps": bool(np.allclose(asm_default.center_mm, two.center_mm)),
               "peak_ratio_step": float(two.data.max() / T.max()),
               "flux_scale": scale, "error_step_flux_scaled": err(flux / scale, T), "psf_s": t1 - t0, "truth_s": t2 - t1}
        row["time_one_step_s"], row["time_wave_path_s"] = timings(lens, fld)
        row["time_ratio"] = row["time_wave_path_s"] / row["time_one_step_s"]
        if not args.no_convergence and fld == 10.0:
            conv = {}
            for name, kw in [("pitch 1 um", dict(h=1e-3)), ("band 120 at 1.5 um", dict(h=1.5e-3, band_disc=120.0)),
                             ("cut 1.5x", dict(cut_share=1.5))]:
                Tc = offaxis_truth(A_MM, d2, coeffs, A_MM * d2 / F_MM, fld, px, py, two.pixel_mm, **kw)
                conv[name] = {"truth_change": err(Tc, T), "error_step": err(two.data, Tc),
                              "error_step_no_stretch": err(flat.data, Tc)}
                print(f"   {name}: truth moved {conv[name]['truth_change']:.2e}; step {conv[name]['error_step']:.2e}, "
                      f"no stretch {conv[name]['error_step_no_stretch']:.2e}", flush=True)
            row["convergence"] = conv
        rows.append(row)
        print(f"{doe} {d2:g} mm {fld:g} deg: stretch x{stretch}, one-step {row['error_one_step']:.2e}, step "
              f"{row['error_step']:.2e} ({row['nodes']} node(s); isotropic {row['error_step_isotropic']:.2e}), no "
              f"stretch {row['error_step_no_stretch']:.2e}, time {row['time_one_step_s']:.2f} -> "
              f"{row['time_wave_path_s']:.2f} s (x{row['time_ratio']:.2f}), flux PSF x{scale:.5f} then "
              f"{row['error_step_flux_scaled']:.2e} (psf {t1 - t0:.0f} s, truth "
              f"{t2 - t1:.0f} s)", flush=True)
    data = {"machine": "2-core CPU (shared), numpy + Warp CPU",
            "scene": {"focal_length_mm": F_MM, "stop_radius_mm": A_MM, "wavelength_um": 0.55, "pixels": SIZE,
                      "pixel_um": PIXEL * 1e3, "doe_norm_radius": "A d2 / F (the on-axis beam's radius)",
                      "method": "auto, tolerance 1e-3 (adds the wave step, rim-resolved where the rim's stretch varies); "
                                "'isotropic': one node (the rim's mean stretch, the step before); 'no stretch': every "
                                "rim ray's stretch 1",
                      "times": "median of 3 warm calls each, planned afresh: one-step = rw.psf(method='auto'), "
                               "wave path = the same with tolerance 1e-3",
                      "pixel_values": "intensity (|U|^2, the truth's); flux_scale: the default flux PSF over the truth "
                                      "(least squares), error_step_flux_scaled: its error after that scale"},
            "truth": {"module": "tests/rwwarp/_offaxis_truth.py", "pitch_um": 2.0, "disc_band_cpmm": 60.0,
                      "on_axis_vs_radial_truth": "7.8e-6 of the peak (4 rho^4, 5 mm; the radial truth on 12001 radii: "
                                                 "on 1201 its linear interpolation reads the peak 1.07e-4 low)"},
            "metric": "max |PSF - truth| / max truth over 64 x 64 px of 0.5 um", "rows": rows,
            "principle": None if args.no_principle else principle(),
            "total_s": time.perf_counter() - t00, "commit": git_commit()}
    print("wrote", save("wave_step_off_axis", data))



def rim_stretch(d2_mm: float, field_deg: float, n_rim: int = 720):
    """The rim's obliquity from the geometry (the stop's rim rays to T): per rim point ``(d / m_z)(1 + (n . m_t)^2 /
    m_z^2)`` over ``d`` (module docstring of rwwarp.wave.wave_step, "Obliquity"), its mean (the isotropic stretch),
    the least-squares tensor ``(s_x, s_y)`` fitted to it around the rim (``n^T diag(s_x, s_y) n``) and what is left."""
    yT = F_MM * np.tan(np.radians(field_deg))
    phi = np.linspace(0.0, 2 * np.pi, n_rim, endpoint=False)
    n = np.stack([np.cos(phi), np.sin(phi)], 1)
    v = np.stack([-A_MM * n[:, 0], yT - A_MM * n[:, 1], np.full(n_rim, F_MM)], 1)
    m = v / np.linalg.norm(v, axis=1, keepdims=True)
    t = (1.0 + np.sum(n * m[:, :2], 1) ** 2 / m[:, 2] ** 2) / m[:, 2]
    A = np.stack([n[:, 0] ** 2, n[:, 1] ** 2], 1)
    sx, sy = np.linalg.lstsq(A, t, rcond=None)[0]
    return {"mean": float(t.mean()), "tensor": (float(sx), float(sy)), "min": float(t.min()), "max": float(t.max()),
            "left_after_tensor": float(np.max(np.abs(A @ [sx, sy] - t)))}


def rim_resolved_step(d, d2_mm, field_deg, nodes=2, harmonics=8):
    """The rim-resolved step on the truth's own grid (numpy, from the geometry, not rwwarp's code): the rim's
    distance ``d t(phi)`` (:func:`rim_stretch`'s per-point stretch, 720 azimuths) extended harmonically into the beam
    (``sum_m r^m`` times its Fourier terms, ``r`` over the beam radius, held at 1.3 outside), the Fresnel transfer
    interpolated in the distance between ``nodes`` Chebyshev nodes across the rim's range (Lagrange weights of the
    local distance on the input): ``step(g, x, nu) = sum_j F^-1[exp(-i pi lambda D_j nu^2) F[l_j(D(x)) g]]``."""
    yT = F_MM * np.tan(np.radians(field_deg))
    phi = np.linspace(0.0, 2 * np.pi, 720, endpoint=False)
    n = np.stack([np.cos(phi), np.sin(phi)], 1)
    v = np.stack([-A_MM * n[:, 0], yT - A_MM * n[:, 1], np.full(720, F_MM)], 1)
    m = v / np.linalg.norm(v, axis=1, keepdims=True)
    t = (1.0 + np.sum(n * m[:, :2], 1) ** 2 / m[:, 2] ** 2) / m[:, 2]
    c = np.fft.rfft(t)[:harmonics + 1] / len(t)
    lo, hi = d * t.min(), d * t.max()
    if hi - lo <= 1e-9 * d:          # on the axis: one distance all round
        return (d * float(t.mean()),) * 2
    Dn = 0.5 * (lo + hi) + 0.5 * (hi - lo) * np.cos(np.pi * (np.arange(nodes) + 0.5) / nodes)
    rb = A_MM * d2_mm / F_MM

    def step(g, x, nu):
        z = (x[None, :] + 1j * x[:, None]) / rb
        z = np.where(np.abs(z) > 1.3, z * 1.3 / np.maximum(np.abs(z), 1e-300), z)
        D = np.full(z.shape, c[0].real)
        for k in range(1, harmonics + 1):
            D += 2 * (c[k] * z ** k).real
        D = np.clip(d * D, lo, hi)
        acc = 0
        for j in range(nodes):
            w = np.ones_like(D)
            for i in range(nodes):
                if i != j:
                    w *= (D - Dn[i]) / (Dn[j] - Dn[i])
            P = np.exp(-1j * np.pi * LAM_MM * Dn[j] * (nu[None, :] ** 2 + nu[:, None] ** 2))
            acc = acc + P * scipy.fft.fft2(g * w, workers=-1)
        return scipy.fft.ifft2(acc, workers=-1)
    return step


def principle(d2s=(5.0, 10.0), fields=(0.0, 5.0, 10.0)) -> list:
    """The wave step's principle on the truth's own FFTs (no rwwarp): the truth against the geometric field stepped
    over ``d``, ``d`` times the isotropic mean stretch, and the fitted tensor (:func:`rim_stretch`)."""
    rows = []
    for d2 in d2s:
        d = (F_MM - d2) * d2 / F_MM
        for fld in fields:
            rs = rim_stretch(d2, fld)
            yT = F_MM * np.tan(np.radians(fld))
            c = (np.arange(SIZE) - SIZE // 2) * PIXEL
            # the patch about the beam's landing point after the DOE's deflection (8 rho^2: 2 pi g = 64 c1 / r_b^2 ...)
            rb = A_MM * d2 / F_MM
            c1 = (F_MM - d2) * yT / F_MM
            sin2 = np.sin(np.arctan2(yT, F_MM)) + 0.55e-3 * (2 * 8.0 * c1 / rb ** 2) / (2 * np.pi)
            yc = c1 + d2 * sin2 / np.sqrt(1 - sin2 ** 2)
            args = (A_MM, d2, (8.0, 0.0), rb, fld, c, c + yc, PIXEL)
            T = offaxis_truth(*args)
            e = {}
            for name, D in [("d", (d, d)), ("d x mean", (d * rs["mean"],) * 2),
                            ("d x tensor", (d * rs["tensor"][0], d * rs["tensor"][1])),
                            ("d x rim-resolved", rim_resolved_step(d, d2, fld))]:
                e[name] = err(offaxis_truth(*args, step=D), T)
            rows.append({"doe_to_sensor_mm": d2, "field_deg": fld, "rim": rs, "error": e})
            print(f"principle {d2:g} mm {fld:g} deg: stretch mean {rs['mean']:.4f} tensor ({rs['tensor'][0]:.4f}, "
                  f"{rs['tensor'][1]:.4f}) range {rs['min']:.4f}..{rs['max']:.4f}: "
                  + "  ".join(f"{k} {v:.2e}" for k, v in e.items()), flush=True)
    return rows


if __name__ == "__main__":
    main()
