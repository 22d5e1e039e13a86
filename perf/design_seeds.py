"""Seeds of the GPU design runs: one folder per arm and seed, aggregated (``perf/design_report.py``).

Layout (``perf/results/design/PROTOCOL.md``, sections 4-6): every arm of an experiment runs with the
seeds 0 and 1, each arm and seed in its own run folder

    <experiment>_gpu/seed<S>_<arm>/   summary.json, table.md, table.csv, designs.png, config_used.yaml,
                                      config_resolved.json, <arm>/result.json, metrics.csv, lens.json
                                      (progress.json while the arm is not finished)

written by ``rwwarp design <experiment> --preset gpu --arm <arm> --set seed=<S> --out ...``. An arm whose run
stopped at a checkpoint (to resume on another machine) has no evaluation yet: its ``summary.json`` (if any:
``train.stop_after``) says ``steps_done < steps_total``, its ``progress.json`` the step reached and the last
checkpoint; ``result.json`` is written only after the evaluation (``torch_bridge/train.py``).

What this module computes (nothing typed in by hand; the test builds folders and checks it):

* :func:`read_run`: one folder -> its arm, seed, state (finished or in progress), steps, the run's
  segments (wall time, cards, commits) and, when finished, the figures of merit (:func:`figures`).
* :func:`collect`: the folders of an experiment, with the protocol's arm x seed combinations not run.
* :func:`aggregate`: mean over the finished seeds and the spread, **half the range** (max - min) / 2.
* :func:`comparisons`: the paper's ranking (the checks of ``design_report.checks``) per seed, with the
  verdict of :func:`verdict`: "holds" / "reversed" only when every seed has a difference of the same sign,
  "not resolved (seeds disagree)" otherwise, "waiting for ..." while a seed of an arm it needs is not
  finished (unfinished arms are never used in a mean or a verdict).
* :func:`section`: the README lines of one experiment.

Units: RMS spot radius um, PSNR dB, SSIM 1, wall time s (h in the text), depths mm.
"""
from __future__ import annotations

import json
import math
import re
from pathlib import Path

from paper_tables import side_by_side

HERE = Path(__file__).resolve().parent
CONFIGS = HERE.parent / "torch_bridge" / "configs"

PROTOCOL_SEEDS = (0, 1)              # PROTOCOL.md section 4: every arm runs with seed 0 and seed 1
SEED_DIR = re.compile(r"^seed(\d+)_(.+)$")

# figures of merit: (key, column title, where in an arm's eval: per depth or per arm, digits)
FIGURES = (
    ("rms_on_um", "RMS radius on axis (um)", 1),
    ("rms_off_um", "RMS radius off axis (um)", 1),
    ("rms_avg_um", "RMS radius avg (um)", 1),
    ("psnr_raw", "PSNR raw (dB)", 2),
    ("ssim_raw", "SSIM raw", 3),
    ("psnr_rec", "PSNR rec (dB)", 2),
    ("ssim_rec", "SSIM rec", 3),
)


def depth_tag(d) -> str:
    """The depth label of ``eval.depths[k].depth_mm`` (mm; None: the lens's own object distance)."""
    return "default" if d is None else ("inf" if math.isinf(d) else f"{d:g}mm")


def protocol_arms(experiment: str, config_dir=CONFIGS) -> list:
    """The arm names of ``experiment`` in its config (``torch_bridge/configs/<experiment>.yaml``), in order;
    [] when there is no such config."""
    f = Path(config_dir) / f"{experiment}.yaml"
    if not f.exists():
        return []
    import yaml
    cfg = yaml.safe_load(f.read_text())
    return [a["name"] for a in cfg.get("arms", [])]


def is_seed_layout(folder) -> bool:
    """True when ``folder`` holds run folders ``seed<S>_<arm>/`` (the GPU runs' layout)."""
    folder = Path(folder)
    return folder.is_dir() and any(p.is_dir() and SEED_DIR.match(p.name) for p in folder.iterdir())


def _load(path: Path):
    """JSON of ``path`` or None (absent); a damaged file is a ValueError naming it."""
    if not path.exists():
        return None
    try:
        return json.loads(path.read_text())
    except ValueError as e:
        raise ValueError(f"{path}: not valid JSON ({e})") from None


def _num(v):
    """float(v), or None for None / NaN / not a number."""
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return None if math.isnan(f) else f


def outer_node(depth: dict) -> dict:
    """The off-axis node of one evaluation depth: the node farthest from the axis (largest radius of
    ``position_mm``, else of ``field_deg``); the last node when neither is recorded. (On the CPU presets'
    diagonal the last node is the outermost; on an evaluation grid it is not.)"""
    nodes = depth["nodes"]
    for key in ("position_mm", "field_deg"):
        if all(isinstance(n.get(key), (list, tuple)) and len(n[key]) == 2 for n in nodes):
            return max(nodes, key=lambda n: math.hypot(*n[key]))
    return nodes[-1]


def figures(result: dict) -> dict:
    """Figures of merit of a finished arm's result (``summary.json[arm]``): ``{depth tag: {key: value}}``
    with the keys of :data:`FIGURES` (RMS radius um, the same at every depth; PSNR dB / SSIM of the raw and
    reconstructed images over all nodes) and ``psnr_rec_off`` (reconstructed PSNR of the outermost node,
    :func:`outer_node`). Missing or NaN values are None."""
    ev = result["eval"]
    rms = ev.get("rms_um") or {}
    out = {}
    for d in ev["depths"]:
        f = {"rms_on_um": _num(rms.get("on_axis")), "rms_off_um": _num(rms.get("off_axis")),
             "rms_avg_um": _num(rms.get("avg")),
             "psnr_raw": _num(d["raw"].get("psnr")), "ssim_raw": _num(d["raw"].get("ssim")),
             "psnr_rec": _num(d["rec"].get("psnr")), "ssim_rec": _num(d["rec"].get("ssim")),
             "psnr_rec_off": _num(outer_node(d)["rec"].get("psnr")) if d.get("nodes") else None}
        out[depth_tag(d.get("depth_mm"))] = f
    return out


def _schedule(run: dict | None, config: dict | None, arm: str, progress: dict | None):
    """(joint, fine-tune) steps of the arm: from result["run"], else config_resolved.json, else
    progress.json; (None, None) when none says."""
    if run and run.get("joint_steps") is not None and run.get("finetune_steps") is not None:
        return int(run["joint_steps"]), int(run["finetune_steps"])
    for a in (config or {}).get("arms", []):
        if a.get("name") == arm:
            t = a.get("config", {}).get("train", {})
            if "joint_steps" in t and "finetune_steps" in t:
                return int(t["joint_steps"]), int(t["finetune_steps"])
    if progress and progress.get("joint_steps") is not None and progress.get("steps_total") is not None:
        return int(progress["joint_steps"]), int(progress["steps_total"]) - int(progress["joint_steps"])
    return None, None


def read_run(folder) -> dict:
    """One run folder ``seed<S>_<arm>/``: a dict with ``folder``, ``seed``, ``arm``, ``state`` ("finished"
    or "in progress"), ``steps_done`` / ``steps_total`` / ``joint`` / ``finetune`` (steps), ``segments``
    (the run's segments: commit, card, start/end step, wall_s), ``wall_s`` (sum of the segments' wall time,
    s; for a result without a run record, training + evaluation time, ``wall_from`` says which; a segment
    ends at its last checkpoint, so time a stopped process spent after it is not counted), ``cards`` and
    ``commits`` (in order of first use),
    ``resumed_without_optimizer``, ``result`` (``summary.json[arm]`` or ``<arm>/result.json`` of a finished
    arm, else None), ``figures`` (:func:`figures`, finished arms only) and ``problems`` (strings; a run with
    a problem, e.g. a seed that differs from its folder name, is not used)."""
    folder = Path(folder)
    m = SEED_DIR.match(folder.name)
    if not m:
        raise ValueError(f"{folder}: not a seed run folder (expected seed<S>_<arm>)")
    seed, arm = int(m.group(1)), m.group(2)
    summ = _load(folder / "summary.json") or {}
    res = _load(folder / arm / "result.json")
    prog = _load(folder / "progress.json")
    config = _load(folder / "config_resolved.json")
    problems = []
    others = sorted(set(summ) - {arm})
    if others:
        problems.append(f"summary.json also holds arm(s) {others} (ignored)")
    cands = [r for r in (summ.get(arm), res) if isinstance(r, dict)]

    def finished(r):
        return "eval" in r and r.get("steps_done") is not None and r.get("steps_done") == r.get("steps_total")
    done = [r for r in cands if finished(r)]
    r = done[0] if done else None
    if len(done) == 2 and figures(done[0]) != figures(done[1]):
        problems.append("summary.json and result.json hold different evaluations (summary.json used)")
    best = r or max(cands, key=lambda x: x.get("steps_done") or 0, default=None)
    run = (best or {}).get("run") or {}
    joint, ft = _schedule(run, config, arm, prog)
    total = (best or {}).get("steps_total")
    if total is None and prog and prog.get("arm") == arm:
        total = prog.get("steps_total")
    if total is None and joint is not None:
        total = joint + ft
    steps = (best or {}).get("steps_done") or 0
    if r is None and prog and prog.get("arm") == arm:
        ck = prog.get("checkpoint_step")
        steps = max(steps, int(ck if ck is not None else (prog.get("step") or 0)))
    seeds_seen = {}
    if run.get("seed") is not None:
        seeds_seen["run.seed"] = int(run["seed"])
    for a in (config or {}).get("arms", []):
        if a.get("name") == arm and a.get("config", {}).get("seed") is not None:
            seeds_seen["config_resolved.json"] = int(a["config"]["seed"])
    for where, s in seeds_seen.items():
        if s != seed:
            problems.append(f"{where} says seed {s}, the folder name seed {seed}")
    if best is not None and best.get("arm") not in (None, arm):
        problems.append(f"the result is of arm {best.get('arm')!r}, the folder name says {arm!r}")
    segs = list(run.get("segments") or [])
    walls = [_num(s.get("wall_s")) for s in segs]
    wall = sum(w for w in walls if w is not None) if segs else None
    wall_from = "segments" if segs else None
    if wall is None and best is not None and _num(best.get("train_wall_s")) is not None:
        # a result of an older version (no run record): training + evaluation of its one process
        wall, wall_from = _num(best["train_wall_s"]) + (_num(best.get("eval_wall_s")) or 0.0), "train+eval"
    cards, commits = [], []
    for s in segs:
        c = s.get("card")
        if c and int(s.get("ranks") or 1) > 1:
            c = f"{c} x {int(s['ranks'])}"   # one arm on several cards (--procs N), recorded since session 22
        if c and c not in cards:
            cards.append(c)
        h = s.get("commit")
        if h:
            h = h[:7] + ("+dirty" if s.get("dirty") else "")
            if h not in commits:
                commits.append(h)
    return {"folder": folder.name, "path": folder, "seed": seed, "arm": arm,
            "state": "finished" if r is not None else "in progress",
            "steps_done": int(steps), "steps_total": None if total is None else int(total),
            "joint": joint, "finetune": ft, "segments": segs, "wall_s": wall, "wall_from": wall_from,
            "cards": cards, "commits": commits,
            "resumed_without_optimizer": bool(run.get("resumed_without_optimizer")),
            "evaluated": r is not None, "result": r, "figures": figures(r) if r is not None else None,
            "problems": problems, "has_designs": (folder / "designs.png").exists()}


def usable(rec: dict | None) -> bool:
    """A run that enters means and verdicts: finished (evaluated, all steps done) and without problems."""
    return rec is not None and rec["state"] == "finished" and not rec["problems"]


def collect(folder, experiment: str | None = None, arms=None, seeds=PROTOCOL_SEEDS) -> dict:
    """Every ``seed<S>_<arm>/`` of ``folder`` (:func:`read_run`) with the protocol: ``arms`` (default
    :func:`protocol_arms` of ``experiment``) x ``seeds``. Returns ``{"experiment", "runs": {(arm, seed):
    record}, "arms": protocol arms then others found, "seeds": protocol seeds then others found,
    "not_run": [(arm, seed)] of the protocol without a folder, "extra_arms": arms not in the protocol}``."""
    folder = Path(folder)
    if experiment is None:
        experiment = folder.name[:-len("_gpu")] if folder.name.endswith("_gpu") else folder.name
    arms = list(protocol_arms(experiment) if arms is None else arms)
    runs = {}
    for p in sorted(folder.iterdir()):
        if p.is_dir() and SEED_DIR.match(p.name):
            rec = read_run(p)
            runs[(rec["arm"], rec["seed"])] = rec
    found_arms = [a for a in sorted({a for a, _ in runs}) if a not in arms]
    all_seeds = list(seeds) + sorted({s for _, s in runs} - set(seeds))
    not_run = [(a, s) for a in arms for s in seeds if (a, s) not in runs]
    return {"experiment": experiment, "folder": folder, "runs": runs, "arms": arms + found_arms,
            "seeds": all_seeds, "not_run": not_run, "extra_arms": found_arms}


def aggregate(values: dict) -> dict | None:
    """Mean and spread of ``{seed: value}`` (values of finished runs only; None values are left out):
    ``{"mean", "half_range" ((max - min) / 2), "min", "max", "n", "seeds"}``; None when no value."""
    v = {s: x for s, x in values.items() if x is not None}
    if not v:
        return None
    xs = list(v.values())
    return {"mean": sum(xs) / len(xs), "half_range": (max(xs) - min(xs)) / 2, "min": min(xs), "max": max(xs),
            "n": len(xs), "seeds": sorted(v)}


def _state_text(rec: dict | None) -> str:
    if rec is None:
        return "not run"
    if rec["problems"]:
        return "not used: " + "; ".join(rec["problems"])
    if rec["state"] == "finished":
        return "finished"
    tot = "?" if rec["steps_total"] is None else rec["steps_total"]
    text = f"in progress: step {rec['steps_done']} of {tot}"
    if rec["steps_total"] is not None and rec["steps_done"] >= rec["steps_total"]:
        text += " (evaluation not written yet)"
    return text


def arm_table(col: dict) -> list:
    """Rows of the figures-of-merit table: one per arm and evaluation depth, ``{"arm", "depth", "seeds"
    (finished seeds used), "values": {key: {seed: value}}, "agg": {key: aggregate(...)}}``. Only usable
    runs (:func:`usable`) contribute; an arm without one has a single row with empty values."""
    rows = []
    for arm in col["arms"]:
        recs = {s: col["runs"].get((arm, s)) for s in col["seeds"]}
        ok = {s: r for s, r in recs.items() if usable(r)}
        depths = []
        for r in ok.values():
            for d in r["figures"]:
                if d not in depths:
                    depths.append(d)
        for d in depths or [None]:
            vals = {k: {s: (r["figures"].get(d) or {}).get(k) for s, r in ok.items()} for k, _, _ in FIGURES}
            rows.append({"arm": arm, "depth": d, "seeds": sorted(ok), "values": vals,
                         "agg": {k: aggregate(v) for k, v in vals.items()}})
    return rows


def verdict(diffs: dict, expected: int, waiting: list) -> str:
    """The verdict on a difference (a - b) whose sign the paper expects to be ``expected`` (+1: a larger,
    -1: a smaller), from ``diffs`` = {seed: difference} of the seeds where both arms are finished.
    ``waiting``: the arm/seed runs the check needs that are not finished ("seed 1 of e2e (not run)"):
    then "waiting for ...". Otherwise "holds" (every seed's sign is the expected one), "reversed" (every
    seed's sign is the opposite), "not resolved (seeds disagree)" (signs differ or a difference is 0),
    "not resolved (no value)" when a seed has no number (NaN or missing)."""
    if waiting:
        return "waiting for " + ", ".join(waiting)
    if not diffs:
        return "not resolved (no seed finished)"
    if any(v is None for v in diffs.values()):
        return "not resolved (no value for seed " + ", ".join(str(s) for s, v in diffs.items() if v is None) \
            + ")"
    signs = {(v > 0) - (v < 0) for v in diffs.values()}
    if signs == {expected}:
        return "holds"
    if signs == {-expected}:
        return "reversed"
    return "not resolved (seeds disagree)"


def _need(col: dict, arms) -> tuple:
    """(seeds where every arm of ``arms`` is usable, what the check still waits for)."""
    waiting, seeds = [], []
    for s in col["seeds"]:
        recs = [(a, col["runs"].get((a, s))) for a in arms]
        if s not in PROTOCOL_SEEDS and all(r is None for _, r in recs):
            continue
        miss = [f"seed {s} of {a} ({_state_text(r)})" for a, r in recs if not usable(r)]
        waiting += miss
        if not miss:
            seeds.append(s)
    return seeds, waiting


def _compare(col, label, a, b, key, depth, expected, unit, fmt):
    """One check: arm ``a`` against arm ``b`` on figure ``key`` at ``depth`` (None: the first depth)."""
    seeds, waiting = _need(col, [a, b] if b else [a])
    diffs, pairs = {}, {}
    for s in seeds:
        fa = col["runs"][(a, s)]["figures"]
        d = depth if depth is not None else next(iter(fa))
        va = (fa.get(d) or {}).get(key)
        if b is None:            # the network's gain: reconstructed - raw of the same arm
            vb = (fa.get(d) or {}).get("psnr_raw")
        else:
            vb = (col["runs"][(b, s)]["figures"].get(d) or {}).get(key)
        pairs[s] = (va, vb)
        diffs[s] = None if va is None or vb is None else va - vb
    v = verdict(diffs, expected, waiting)
    agg = aggregate(diffs) if not waiting else None
    return {"label": label, "a": a, "b": b, "key": key, "depth": depth, "expected": expected, "diffs": diffs,
            "pairs": pairs, "verdict": v, "mean": None if agg is None else agg["mean"], "unit": unit,
            "fmt": fmt}


def _depths(col, arms) -> list:
    """Evaluation depth tags of the usable runs of ``arms`` (in order of appearance)."""
    out = []
    for (a, s), r in col["runs"].items():
        if a in arms and usable(r):
            for d in r["figures"]:
                if d not in out:
                    out.append(d)
    return out or [None]


def comparisons(col: dict) -> list:
    """The paper's ranking on the seeds (the checks of ``design_report.checks``), one dict per check with
    ``label``, ``diffs`` ({seed: a - b}), ``pairs`` ({seed: (a, b)}), ``mean`` (over the seeds, once none
    is waiting) and ``verdict`` (:func:`verdict`):

    * a489_aberration: e2e_doe vs blank_doe, reconstructed PSNR (paper: higher);
    * cooke_hybrid: every ``e2e*`` arm vs rms_spot, reconstructed PSNR (higher) and average RMS spot
      radius (larger);
    * a489_edof: raywave_doe vs paraxial_doe, reconstructed PSNR of the outermost node, per depth (higher);
    * every arm: reconstructed minus raw PSNR, per depth (the network improves the image: positive)."""
    exp, arms, out = col["experiment"], col["arms"], []
    if exp == "a489_aberration" and {"e2e_doe", "blank_doe"} <= set(arms):
        for d in _depths(col, ["e2e_doe", "blank_doe"]):
            out.append(_compare(col, f"e2e_doe reconstructs better than blank_doe (reconstructed PSNR, depth "
                                f"{d or '-'})", "e2e_doe", "blank_doe", "psnr_rec", d, +1, "dB", ".2f"))
    if exp == "cooke_hybrid" and "rms_spot" in arms:
        for e in [a for a in arms if a.startswith("e2e")]:
            for d in _depths(col, [e, "rms_spot"]):
                out.append(_compare(col, f"{e} reconstructs better than rms_spot (reconstructed PSNR, depth "
                                    f"{d or '-'})", e, "rms_spot", "psnr_rec", d, +1, "dB", ".2f"))
            out.append(_compare(col, f"{e} has the larger RMS spot than rms_spot (average over the fields)",
                                e, "rms_spot", "rms_avg_um", None, +1, "um", ".1f"))
    if exp == "a489_edof" and {"raywave_doe", "paraxial_doe"} <= set(arms):
        for d in _depths(col, ["raywave_doe", "paraxial_doe"]):
            out.append(_compare(col, f"raywave_doe beats paraxial_doe off axis (reconstructed PSNR of the "
                                f"outermost node, depth {d or '-'})", "raywave_doe", "paraxial_doe",
                                "psnr_rec_off", d, +1, "dB", ".2f"))
    for a in arms:
        for d in _depths(col, [a]):
            out.append(_compare(col, f"{a}: the network improves on the raw image (reconstructed - raw PSNR, "
                                f"depth {d or '-'})", a, None, "psnr_rec", d, +1, "dB", ".2f"))
    return out


# ============================================================================================== markdown
def _cell(vals: dict, agg: dict | None, digits: int) -> str:
    if agg is None:
        return "-"
    per = " / ".join(f"{vals[s]:.{digits}f}" for s in agg["seeds"])
    if agg["n"] == 1:
        return f"{agg['mean']:.{digits}f} (seed {agg['seeds'][0]} only)"
    return f"{agg['mean']:.{digits}f} ± {agg['half_range']:.{digits}f} ({per})"


def _hours(s) -> str:
    return "-" if s is None else (f"{s / 3600:.2f} h" if s >= 600 else f"{s:.0f} s")


def section(folder, title: str | None = None, experiment: str | None = None) -> list:
    """Markdown lines of one experiment's GPU runs in ``folder`` (``<experiment>_gpu/``)."""
    folder = Path(folder)
    col = collect(folder, experiment)
    exp = col["experiment"]
    seeds = col["seeds"]
    L = [f"## {title or exp}: GPU runs, one folder per arm and seed (`{folder.name}/`)", "",
         (f"Each `seed<S>_<arm>/` is one run of `rwwarp design {exp} --preset gpu --arm <arm> "
          f"--set seed=<S>` (`PROTOCOL.md`: seeds {', '.join(map(str, PROTOCOL_SEEDS))}). Values: the mean "
          "over the finished seeds "
          "± half their range ((max - min) / 2), then each seed's value in seed order. Arms not finished "
          "are not used in any mean or verdict."), ""]
    if (folder / "README.md").exists():
        L += [f"Commands as run: [`{folder.name}/README.md`]({folder.name}/README.md).", ""]
    heads = ["arm", "depth", "seeds used"] + [t for _, t, _ in FIGURES]
    L += ["| " + " | ".join(heads) + " |", "|" + "---|" * len(heads)]
    for row in arm_table(col):
        cells = [row["arm"], row["depth"] or "-", ", ".join(map(str, row["seeds"])) or "none finished"]
        cells += [_cell(row["values"][k], row["agg"][k], dg) for k, _, dg in FIGURES]
        L.append("| " + " | ".join(cells) + " |")
    L += [""] + side_by_side(exp, arm_table(col))
    L += ["Runs (steps done of the schedule, joint + fine-tune; wall time = sum of the run's segments, "
          "each up to its last checkpoint; cards and commits of the segments):", "",
          "| arm | seed | state | steps | wall time | cards | commits |", "|---|---|---|---|---|---|---|"]
    for arm in col["arms"]:
        for s in seeds:
            r = col["runs"].get((arm, s))
            if r is None:
                if s in PROTOCOL_SEEDS and arm not in col["extra_arms"]:
                    L.append(f"| {arm} | {s} | not run | - | - | - | - |")
                continue
            sched = "" if r["joint"] is None else f" ({r['joint']} + {r['finetune']})"
            steps = f"{r['steps_done']} / {r['steps_total'] if r['steps_total'] is not None else '?'}{sched}"
            st = _state_text(r) + ("; resumed without the Adam state" if r["resumed_without_optimizer"]
                                   else "")
            wall = _hours(r["wall_s"]) + (" (train + eval, no segments recorded)"
                                          if r["wall_from"] == "train+eval" else "")
            L.append(f"| {arm} | {s} | {st} | {steps} | {wall} | {', '.join(r['cards']) or '-'} | "
                     f"{', '.join(r['commits']) or '-'} |")
    totals = {(r["joint"], r["finetune"]) for r in col["runs"].values() if usable(r)}
    if len(totals) > 1:
        L += ["", "**The finished runs do not share one schedule** (joint + fine-tune): "
              + ", ".join(f"{j} + {f}" for j, f in sorted(totals, key=str)) + "."]
    L += ["", "Paper's ranking, checked on every seed (a - b per seed; the verdict needs every seed to "
          "agree):",
          ""]
    for c in comparisons(col):
        per = ", ".join(f"seed {s}: " + ("-" if v is None else f"{v:+{c['fmt']}}")
                        for s, v in c["diffs"].items())
        if c["verdict"].startswith("waiting"):
            tail = f" (so far {per} {c['unit']})" if c["diffs"] else ""
            L.append(f"- {c['label']}: **{c['verdict']}**{tail}")
        else:
            mean = "" if c["mean"] is None else f"mean {c['mean']:+{c['fmt']}} {c['unit']}; "
            L.append(f"- {c['label']}: **{c['verdict']}** ({mean}{per})")
    runs = sorted(col["runs"].items(), key=lambda kv: kv[0])
    prog = [f"seed {s} of {a}: {_state_text(r)}" for (a, s), r in runs
            if not usable(r)]
    if prog:
        L += ["", "Not used (in progress or with a problem): " + "; ".join(prog) + "."]
    if col["not_run"]:
        L += ["", "Not run (protocol's arms x seeds): "
              + ", ".join(f"seed {s} of {a}" for a, s in col["not_run"])
              + "."]
    if col["extra_arms"]:
        L += ["", "Arms not in the experiment's config: " + ", ".join(col["extra_arms"]) + "."]
    figs = [r for _, r in runs if r["has_designs"]]
    if figs:
        L += ["", "Figures: " + ", ".join(f"[{r['folder']}]({folder.name}/{r['folder']}/designs.png)"
                                           for r in figs)]
    return L + [""]
