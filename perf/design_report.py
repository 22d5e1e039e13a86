"""Write ``perf/results/design/README.md`` from the design results found there.

For every ``<experiment>_<preset>/`` folder written by ``rwwarp design`` (``table.md``, ``summary.json``,
``designs.png``) the README gets the table as measured and the paper's ranking checked on the numbers
of ``summary.json`` (nothing is typed in by hand):

* Cooke-type hybrid: does the end-to-end design reconstruct better (PSNR of the reconstructed image,
  dB) than the RMS-spot ("Zemax") design, and is its RMS spot radius (um, ray model) larger?
* Large-field EDoF: does the ray-wave-designed DOE beat the paraxial-wave-designed one off axis
  (reconstructed PSNR at the outermost node, every evaluation depth)?
* Aberration correction: does the end-to-end DOE beat the blank DOE?
* For every arm: does the network improve on the raw image (reconstructed minus raw PSNR)?

The GPU runs (``PROTOCOL.md``: every arm with seeds 0 and 1) land one folder per arm and seed,
``<experiment>_gpu/seed<S>_<arm>/``; such a folder of folders gets a section from
:func:`design_seeds.section`: per arm the mean over the finished seeds and half their range, each seed's
value, the runs' steps, wall time, cards and commits, and the checks above per seed with a verdict
("holds" / "reversed" only when every seed agrees; unfinished arms are listed, never used).

The hand-written discussion between ``<!-- discussion -->`` and ``<!-- /discussion -->`` in an
existing README is kept.

    .venv/bin/python perf/design_report.py [--results perf/results/design]
"""
from __future__ import annotations

import argparse
import json
import math
import re
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from design_seeds import is_seed_layout, outer_node, section  # noqa: E402

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results" / "design"

RUN = {
    "cooke_hybrid": "Cooke-type hybrid (paraxial achromat vs RMS spot vs end-to-end)",
    "a489_aberration": "Aberration correction (A489 asphere, blank DOE vs end-to-end DOE)",
    "a489_edof": "Large-field EDoF (paraxial-wave vs ray-wave designed DOE)",
}


def _depth_tag(d):
    return "default" if d is None else ("inf" if math.isinf(d) else f"{d:g}mm")


def _rec(r, depth_index=0):
    return r["eval"]["depths"][depth_index]["rec"]["psnr"]


def _raw(r, depth_index=0):
    return r["eval"]["depths"][depth_index]["raw"]["psnr"]


def _yes(b):
    return "**yes**" if b else "**no**"


def checks(experiment: str, s: dict) -> list[str]:
    """Lines (markdown) with the paper's ranking tested on the numbers of ``summary.json`` (``s``)."""
    out = []
    done = {a: r for a, r in s.items() if "eval" in r}
    if experiment == "cooke_hybrid" and "rms_spot" in done:
        z = done["rms_spot"]
        dz = _rec(z)
        rz = z["eval"].get("rms_um", {}).get("avg")
        for name in [a for a in done if a.startswith("e2e")]:
            e = done[name]
            de = _rec(e)
            re_ = e["eval"].get("rms_um", {}).get("avg")
            out.append(f"- {name} reconstructs better than the RMS-spot design: {_yes(de > dz)} "
                       f"(reconstructed PSNR {de:.2f} vs {dz:.2f} dB)")
            if re_ is not None and rz is not None:
                out.append(f"- {name} has the larger RMS spot (average over the fields): {_yes(re_ > rz)} "
                           f"({re_:.1f} vs {rz:.1f} um)")
        if "paraxial" in done:
            p = done["paraxial"]
            rp = p["eval"].get("rms_um", {}).get("avg")
            out.append(f"- Paraxial achromat for reference: reconstructed PSNR {_rec(p):.2f} dB, RMS spot "
                       f"{rp:.1f} um" if rp is not None else f"- Paraxial achromat: reconstructed PSNR {_rec(p):.2f} dB")
        for a, r in done.items():
            c = ", ".join(f"{v:.1f}" for v in r["eval"].get("doe_coefficients", []))
            out.append(f"- {a}: DOE coefficients [{c}] (rad), DOE-to-sensor distance "
                       f"{r['eval'].get('sensor_distance_mm', float('nan')):.3f} mm")
    if experiment == "a489_edof" and {"paraxial_doe", "raywave_doe"} <= set(done):
        p, w = done["paraxial_doe"], done["raywave_doe"]
        wins = []
        for i, (dp, dw) in enumerate(zip(p["eval"]["depths"], w["eval"]["depths"])):
            rp, rw_ = outer_node(dp)["rec"]["psnr"], outer_node(dw)["rec"]["psnr"]
            ap = dp["rec"]["psnr"]
            aw = dw["rec"]["psnr"]
            wins.append(rw_ > rp)
            pos = outer_node(dw).get("position_mm")
            where = f" at {tuple(round(v, 2) for v in pos)} mm" if pos else ""
            out.append(f"- {_depth_tag(dw['depth_mm'])}: off-axis node{where}: ray-wave DOE {rw_:.2f} dB vs "
                       f"paraxial DOE {rp:.2f} dB (reconstructed); all nodes: {aw:.2f} vs {ap:.2f} dB")
        out.insert(0, f"- Ray-wave-designed DOE beats the paraxial-designed DOE off axis at every evaluation "
                      f"depth: {_yes(all(wins))} ({sum(wins)} of {len(wins)} depths)")
    if experiment == "a489_aberration" and {"blank_doe", "e2e_doe"} <= set(done):
        b, e = done["blank_doe"], done["e2e_doe"]
        out.append(f"- End-to-end DOE reconstructs better than the blank DOE: {_yes(_rec(e) > _rec(b))} "
                   f"({_rec(e):.2f} vs {_rec(b):.2f} dB); off-axis RMS spot "
                   f"{e['eval']['rms_um']['off_axis']:.1f} vs {b['eval']['rms_um']['off_axis']:.1f} um")
    for a, r in done.items():
        gains = [d["rec"]["psnr"] - d["raw"]["psnr"] for d in r["eval"]["depths"]]
        oi, of = r.get("objective_initial") or {}, r.get("objective_final") or {}
        obj = ""
        if "loss" in oi and "loss" in of:
            obj = f"; objective {oi['loss']:.5f} -> {of['loss']:.5f} ({'lower' if of['loss'] < oi['loss'] else 'not lower'})"
        out.append(f"- {a}: network gain (reconstructed - raw PSNR) "
                   + ", ".join(f"{g:+.2f}" for g in gains) + " dB" + obj)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", default=str(RESULTS))
    a = ap.parse_args(argv)
    root = Path(a.results)
    readme = root / "README.md"
    keep = ""
    if readme.exists():
        m = re.search(r"<!-- discussion -->.*?<!-- /discussion -->", readme.read_text(), re.DOTALL)
        keep = m.group(0) if m else ""
    lines = ["# End-to-end design results", "",
             ("Written by `perf/design_report.py` from the folders below (tables as measured by "
              "`rwwarp design`; the ranking lines are computed from each `summary.json`)."), "",
             "Run an experiment (results land in `perf/results/design/<experiment>_<preset>/`):", "",
             "```bash"]
    for name in RUN:
        for preset in ("cpu", "gpu"):
            lines.append(f".venv/bin/rwwarp design {name} --preset {preset} --out perf/results/design/{name}_{preset}")
    lines += ["```", "",
              ("One arm at a time: `--arm NAME` (the table then includes arms finished earlier in the same "
               "folder); `--fresh` ignores checkpoints; `--check` only validates the config; `--table` "
               "rewrites the table and figure from the finished arms. Then "
               "`.venv/bin/python perf/design_report.py` rewrites this file."), "",
              ("The GPU runs of the three experiments follow `PROTOCOL.md` (written before them: images, "
               "schedule, seeds, GPU-hours, how a run moves between machines)."), ""]
    if keep:
        lines += [keep, ""]
    folders = [p for p in root.iterdir()
               if p.is_dir() and ((p / "summary.json").exists() or is_seed_layout(p))]
    for d in sorted(folders):
        if is_seed_layout(d):
            # the GPU runs: one folder per arm and seed (design_seeds), aggregated over the seeds
            exp = next((n for n in RUN if d.name.startswith(n + "_")), None)
            lines += section(d, RUN.get(exp, exp or d.name), exp)
            if not (d / "summary.json").exists():
                continue
        exp, _, preset = d.name.rpartition("_")
        for name in RUN:
            if d.name.startswith(name + "_"):
                exp, preset = name, d.name[len(name) + 1:]
        s = json.loads((d / "summary.json").read_text())
        lines.append(f"## {RUN.get(exp, exp)}: preset {preset}")
        lines.append("")
        if (d / "table.md").exists():
            t = (d / "table.md").read_text().splitlines()
            lines += [ln for ln in t if not ln.startswith("# ")]
        lines.append("")
        lines.append("Paper's ranking, checked on these numbers:")
        lines.append("")
        lines += checks(exp, s)
        lines.append("")
        if (d / "designs.png").exists():
            lines.append(f"![{d.name}]({d.name}/designs.png)")
            lines.append("")
    readme.write_text("\n".join(lines).rstrip() + "\n")
    print(f"wrote {readme}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
