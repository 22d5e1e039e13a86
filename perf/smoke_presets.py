"""GPU smoke run of the design presets: every arm of every experiment's ``gpu`` preset for a few steps,
each in its own process, with the GPU memory its processes use sampled (nvidia-smi's per-process figures every 50
ms: the CUDA context and torch's, Warp's and CuPy's pools all count; ``--memory device``: the whole device's used
memory, the session-21 form) against the preset's ``optics.memory_budget_gb``. Per process, a smoke can run
beside design runs on the same GPUs: their memory is not its.

    python perf/smoke_presets.py [--configs cooke_hybrid a489_aberration a489_edof] [--arms NAME ...]
                                 [--steps 3] [--out DIR] [--timeout 280]

Each arm runs ``steps - 1`` joint steps and one fine-tune step (both phases and the optics update are
reached), then its evaluation on ``--eval-images`` images, from a fresh folder. An arm passes when its
process exits 0, every step was logged and the sampled peak stays inside the preset's memory budget
(GB = 1e9 bytes; a preset without a budget fails: every gpu preset must state one). Writes
``smoke_presets.json`` (card, commit, per arm: exit code, wall time, steps, step times, peak memory,
budget) under ``--out`` ($RWWARP_RESULTS or perf/results) and exits 1 when any arm fails.
"""
from __future__ import annotations

import argparse
import copy
import csv
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import GpuMemory, ProcessGpuMemory, git_commit, save  # noqa: E402

CONFIGS = ("cooke_hybrid", "a489_aberration", "a489_edof")


def smoke_config(name: str, steps: int, eval_images: int, budget_gb: float | None = None, sets=()) -> dict:
    """The bundled config ``name`` with its gpu preset cut to ``steps`` steps (``steps - 1`` joint, 1
    fine-tune), a log line per step, no images or checkpoints, and a lens path made absolute;
    ``budget_gb``: the preset's ``optics.memory_budget_gb`` replaced (GB, a trial of a smaller budget);
    ``sets``: ``KEY=VALUE`` strings (dotted keys, YAML values) set in the gpu preset."""
    from torch_bridge.train import CONFIG_DIR
    c = yaml.safe_load((CONFIG_DIR / f"{name}.yaml").read_text())
    lens_file = c.get("lens", {}).get("file")
    if lens_file and (CONFIG_DIR / lens_file).exists():
        c["lens"]["file"] = str(CONFIG_DIR / lens_file)
    g = c["presets"]["gpu"]
    g.setdefault("train", {}).update(joint_steps=max(1, steps - 1), finetune_steps=1, log_every=1, image_every=0,
                                     checkpoint_every=0)
    g.setdefault("data", {})["eval_images"] = int(eval_images)
    if budget_gb is not None:
        g.setdefault("optics", {})["memory_budget_gb"] = float(budget_gb)
    for kv in sets:
        key, _, value = kv.partition("=")
        *path, last = key.split(".")
        d = g
        for k in path:
            d = d.setdefault(k, {})
        d[last] = yaml.safe_load(value)
    return c


def run_arm(cfg_path: Path, arm: str, out: Path, timeout: float, memory: str = "process") -> dict:
    """One arm in its own process; returns exit code, wall time, peak used memory (MiB; ``peak_measured`` False when
    it could not be read) and the log tail. ``memory``: ``"process"`` (what the arm's processes hold, from the
    driver's per-process figures: other runs on the same GPU do not count) or ``"device"`` (the device's used
    memory, everything on it: the GPU must be the arm's alone). The arm runs with Python's fault handler on (a
    crash prints every thread's Python stack) and its whole log is kept as ``out / arm / run.log``."""
    cmd = [sys.executable, "-X", "faulthandler", "-m", "torch_bridge.train", str(cfg_path), "--preset", "gpu", "--arm", arm,
           "--out", str(out), "--fresh", "--no-progress"]
    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    with (ProcessGpuMemory(p.pid) if memory == "process" else GpuMemory()) as mem:
        try:
            so, se = p.communicate(timeout=timeout)
            rc, log = p.returncode, so + se
        except subprocess.TimeoutExpired:
            p.kill()
            so, se = p.communicate()
            rc, log = 124, (so or "") + (se or "")
    (out / arm).mkdir(parents=True, exist_ok=True)
    (out / arm / "run.log").write_text(log)
    keep = 40 if rc < 0 else 12   # a crash: room for the fault handler's stacks
    # per process: a run that reached its steps on a GPU and was never listed by the driver was not measured
    measured = memory != "process" or mem.matched
    return {"rc": rc, "wall_s": round(time.perf_counter() - t0, 2), "peak_mib": mem.peak, "peak_at_s": mem.peak_at_s,
            "peak_measured": measured, "memory": memory,
            "log_tail": [ln for ln in log.splitlines() if "Warning" not in ln][-keep:]}


def wanted(config: str, arm: str, arms) -> bool:
    """Whether ``--arms`` selects ``arm`` of ``config``: no list selects all; ``CONFIG:ARM`` entries select only
    their config's arms (a config not named in any of them keeps all its arms unless a plain ``ARM`` entry
    names some other arm); plain ``ARM`` entries select that arm in any config."""
    if not arms:
        return True
    scoped = [x.split(":", 1) for x in arms if ":" in x]
    plain = [x for x in arms if ":" not in x]
    if any(c == config for c, _ in scoped):
        return [config, arm] in [list(x) for x in scoped] or arm in plain
    return arm in plain if plain else True


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--configs", nargs="+", default=list(CONFIGS))
    ap.add_argument("--arms", nargs="+", default=None,
                    help="only these arms (default: every arm): ARM (in every config that has it) or CONFIG:ARM (only "
                         "that config's; a config none of whose arms is named this way runs all its arms)")
    ap.add_argument("--steps", type=int, default=3)
    ap.add_argument("--eval-images", type=int, default=2)
    ap.add_argument("--budget-gb", type=float, default=None,
                    help="replace each preset's optics.memory_budget_gb (GB) for this run")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="set a key of the gpu preset for this run (dotted, YAML value), e.g. optics.cache_precision=single")
    ap.add_argument("--timeout", type=float, default=280.0, help="seconds per arm")
    ap.add_argument("--memory", choices=("process", "device"), default="process",
                    help="the peak checked against the budget: the arm's processes' GPU memory (default; other runs "
                         "on the GPU do not count, so a smoke can share GPUs with design runs) or the whole device's")
    ap.add_argument("--out", default=os.environ.get("RWWARP_RESULTS"))
    a = ap.parse_args(argv)
    if a.steps < 2:
        ap.error("--steps must be >= 2 (a joint and a fine-tune step)")
    from torch_bridge.train import load_config
    out = Path(a.out or Path(__file__).resolve().parent / "results")
    work = out / "smoke_runs"
    work.mkdir(parents=True, exist_ok=True)
    try:
        card = subprocess.run(["nvidia-smi", "--query-gpu=name,memory.total", "--format=csv,noheader"],
                              capture_output=True, text=True).stdout.strip().splitlines()
    except FileNotFoundError:   # no NVIDIA driver: the arms will fail their device check and say so
        card = []
    report = {"card": card[0] if card else "none", "steps": a.steps, "arms": []}
    ok_all = True
    for name in a.configs:
        c = smoke_config(name, a.steps, a.eval_images, a.budget_gb, a.set)
        cfg_path = work / f"{name}_smoke.yaml"
        cfg_path.write_text(yaml.safe_dump(c))
        exp = load_config(copy.deepcopy(c), "gpu")
        budget = exp["base"]["optics"].get("memory_budget_gb")
        for arm in exp["arms"]:
            if not wanted(name, arm["name"], a.arms):
                continue
            r = run_arm(cfg_path, arm["name"], work / name, a.timeout, a.memory)
            rows = []
            mf = work / name / arm["name"] / "metrics.csv"
            if mf.exists():
                rows = list(csv.DictReader(open(mf)))
            steps = [int(x["step"]) for x in rows]
            within = budget is not None and r["peak_measured"] and r["peak_mib"] * 2 ** 20 <= budget * 1e9
            ok = r["rc"] == 0 and len(steps) >= a.steps and within
            ok_all &= ok
            entry = {"config": name, "arm": arm["name"], "ok": ok, "budget_gb": budget,
                     "peak_gb": round(r["peak_mib"] * 2 ** 20 / 1e9, 2), "within_budget": within,
                     "steps_logged": len(steps), "step_wall_s": [float(x["wall_s"]) for x in rows],
                     "step_memory_gb": [float(x["memory_gb"]) for x in rows if x.get("memory_gb")],
                     # when the peak was sampled (s from the process's start; the steps' wall_s count from the arm's
                     # start, a few seconds later): before the first step's end it was the field builds or set-up
                     "peak_at_s": r["peak_at_s"], "memory": r["memory"], "peak_measured": r["peak_measured"],
                     **{k: r[k] for k in ("rc", "wall_s")}}
            if not ok:
                entry["log_tail"] = r["log_tail"]
            report["arms"].append(entry)
            print(f"{'PASS' if ok else 'FAIL'} {name}/{arm['name']}: rc {r['rc']}, {len(steps)} steps, "
                  f"{r['wall_s']:.0f} s, " + (f"peak {entry['peak_gb']:.1f} GB at {r['peak_at_s']} s" if r["peak_measured"]
                                             else "peak NOT MEASURED (the driver listed none of the arm's processes: "
                                                  "another PID namespace? use --memory device)")
                  + f" ({r['memory']}) / budget {budget} GB", flush=True)
            if not ok:
                print("\n".join("    " + ln for ln in r["log_tail"]), flush=True)
    report["passed"] = bool(ok_all)
    p = save("smoke_presets", report, out)
    print(f"{'passed' if ok_all else 'FAILED'}; {p}")
    return 0 if ok_all else 1


if __name__ == "__main__":
    sys.exit(main())
