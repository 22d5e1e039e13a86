"""The paper's simulated figures of merit for its three design experiments, stored as data, and the rows of
``perf/results/design/README.md`` that set them beside ours.

Source: the paper (SIGGRAPH Asia 2024, end-to-end hybrid refractive-diffractive lens design with the ray-wave
model), its tables "cooke_score" (Cooke-type hybrid: RMS radius um on axis / off axis / average, then PSNR dB /
SSIM / 1-LPIPS of the simulated "raw" and the reconstructed "rec" images), "asphe_score" (A489 aberration
correction) and "edof_score" (large-field EDoF at three object depths). Values copied as printed (the Cooke PSNRs
25.041 and 36.462 with the digits the paper gives). Our arms map to the paper's rows as ``PROTOCOL.md`` section 2
describes; an arm without a row (``e2e_from_rms``, an end-to-end design started from the RMS design) is shown
without one.
"""
from __future__ import annotations

# the paper's comparisons: (design arm, baseline arm); the margin is design - baseline, ours beside the paper's
MARGINS = {"cooke_hybrid": [("e2e", "rms_spot"), ("e2e", "paraxial")],
           "a489_aberration": [("e2e_doe", "blank_doe")],
           "a489_edof": [("raywave_doe", "paraxial_doe")]}

# (row label, RMS radius um (on, off, avg) or None, raw (PSNR, SSIM, 1-LPIPS), rec (PSNR, SSIM, 1-LPIPS))
PAPER = {
    "cooke_hybrid": {
        "table": "cooke_score",
        "rows": {"paraxial": ("Paraxial wave optics", (16.1, 55.0, 32.0), (17.7, 0.520, 0.443),
                              (25.041, 0.688, 0.569)),
                 "rms_spot": ("Ray tracing (Zemax)", (7.6, 19.6, 10.1), (24.8, 0.728, 0.706),
                              (36.462, 0.963, 0.924)),
                 "e2e": ("Ray-wave model (ours)", (10.7, 28.4, 15.4), (27.1, 0.795, 0.713),
                         (39.9, 0.982, 0.963))},
    },
    "a489_aberration": {
        "table": "asphe_score",
        "rows": {"blank_doe": ("Refractive lens", None, (24.4, 0.702, 0.677), (28.8, 0.835, 0.746)),
                 "e2e_doe": ("Hybrid lens (ours)", None, (24.7, 0.733, 0.707), (32.5, 0.931, 0.880))},
    },
    "a489_edof": {
        "table": "edof_score",
        # per evaluation depth (our tag: depth_mm as design_seeds.depth_tag writes it)
        "rows": {("paraxial_doe", "200mm"): ("Baseline, 20 cm", None, (18.7, 0.497, 0.531), (16.1, 0.341, 0.509)),
                 ("paraxial_doe", "300mm"): ("Baseline, 30 cm", None, (19.0, 0.539, 0.473), (18.7, 0.520, 0.437)),
                 ("paraxial_doe", "10000mm"): ("Baseline, 10 m", None, (18.9, 0.523, 0.517), (18.6, 0.502, 0.493)),
                 ("raywave_doe", "200mm"): ("Ours, 20 cm", None, (21.5, 0.575, 0.587), (27.5, 0.821, 0.782)),
                 ("raywave_doe", "300mm"): ("Ours, 30 cm", None, (22.4, 0.659, 0.635), (28.9, 0.869, 0.842)),
                 ("raywave_doe", "10000mm"): ("Ours, 10 m", None, (21.7, 0.598, 0.524), (27.4, 0.818, 0.787))},
    },
}


def paper_row(experiment: str, arm: str, depth: str | None):
    """The paper's row for one of our arms (and evaluation depth tag, for the EDoF experiment), or None."""
    exp = PAPER.get(experiment)
    if exp is None:
        return None
    rows = exp["rows"]
    return rows.get((arm, depth)) if (arm, depth) in rows else rows.get(arm)


def _mean(agg, digits):
    return "-" if agg is None else f"{agg['mean']:.{digits}f}"


def side_by_side(experiment: str, rows: list) -> list:
    """Markdown lines: for each of our arm rows (``design_seeds.arm_table``: ``arm``, ``depth``, ``agg``) with a
    paper row, ours (mean over the finished seeds) beside the paper's: RMS radius on / off / avg (um, where the
    paper gives it), PSNR (dB) and SSIM raw and reconstructed; then the margins the paper's ranking rests on
    (design minus baseline arm, raw and reconstructed PSNR, dB), ours beside the paper's. 1-LPIPS is the paper's
    only (the LPIPS weights are not on the package registries). Empty when the experiment has no table."""
    exp = PAPER.get(experiment)
    if exp is None:
        return []
    has_rms = any(r[1] is not None for r in exp["rows"].values())
    head = ["arm", "depth", "paper's row"]
    if has_rms:
        head += ["RMS on/off/avg um, ours", "paper"]
    head += ["PSNR raw dB, ours", "paper", "SSIM raw, ours", "paper", "PSNR rec dB, ours", "paper", "SSIM rec, ours",
             "paper", "1-LPIPS raw / rec, paper"]
    L = [f"Beside the paper's table \"{exp['table']}\" (ours: the mean over the finished seeds; the paper: one run "
         "on DIV2K; `perf/paper_tables.py`):", "",
         "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    found = {}
    for row in rows:
        p = paper_row(experiment, row["arm"], row["depth"])
        if p is None:
            continue
        label, rms, raw, rec = p
        a = row["agg"]
        found[(row["arm"], row["depth"])] = (a, raw, rec)
        cells = [row["arm"], row["depth"] or "-", label]
        if has_rms:
            cells += ["/".join(_mean(a.get(k), 1) for k in ("rms_on_um", "rms_off_um", "rms_avg_um")),
                      "-" if rms is None else "/".join(f"{v:g}" for v in rms)]
        for key_p, key_s, ref in (("psnr_raw", "ssim_raw", raw), ("psnr_rec", "ssim_rec", rec)):
            cells += [_mean(a.get(key_p), 2), f"{ref[0]:g}", _mean(a.get(key_s), 3), f"{ref[1]:.3f}"]
        cells.append(f"{raw[2]:.3f} / {rec[2]:.3f}")
        L.append("| " + " | ".join(cells) + " |")
    lines = []
    for design, base in MARGINS.get(experiment, []):
        for (arm, depth), (a, raw, rec) in found.items():
            if arm != design or (base, depth) not in found:
                continue
            b, braw, brec = found[(base, depth)]
            ours = []
            for key, pd, pb in (("psnr_raw", raw[0], braw[0]), ("psnr_rec", rec[0], brec[0])):
                x, y = a.get(key), b.get(key)
                ours.append(("-" if x is None or y is None else f"{x['mean'] - y['mean']:+.2f}") +
                            f" (paper {pd - pb:+.2f})")
            at = "" if depth in (None, "default") else f" at {depth}"
            lines.append(f"- {design} - {base}{at}: raw {ours[0]}, reconstructed {ours[1]} dB")
    if lines:
        L += ["", "Margins (design minus baseline, PSNR, ours then the paper's):", ""] + lines
    return L + [""]
