"""perf/design_report.py and perf/design_seeds.py on the GPU runs' layout (one folder per arm and seed,
``<experiment>_gpu/seed<S>_<arm>/``): synthetic run folders with ``summary.json`` files of the format
``torch_bridge/train.py`` writes (keys as in ``perf/results/design/a489_aberration_gpu_short/summary.json``
plus the ``run`` record with its segments), numbers made up here. The expected means, spreads, differences
and verdicts are worked out by hand in each test from the numbers it writes."""
from __future__ import annotations

import csv
import json
import shutil
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "perf"))

import design_report  # noqa: E402
import design_seeds as ds  # noqa: E402

# pure arithmetic on a few numbers: the only error is float64 rounding (~1e-14 on values ~30)
TOL = 1e-12
H100, H200 = "NVIDIA H100 80GB HBM3", "NVIDIA H200"


def _metric(psnr, ssim):
    return {"psnr": psnr, "ssim": ssim, "one_minus_lpips": float("nan")}


def _depth(depth_mm, raw, rec, nodes=None):
    """One ``eval.depths`` entry: all-node averages ``raw`` / ``rec`` = (PSNR dB, SSIM) and ``nodes`` =
    [((x, y) mm, rec PSNR)] (raw node values = rec - 1 dB; only the rec PSNR of nodes is read)."""
    nodes = nodes or [((0.1875, 0.1875), rec[0] + 1.0), ((1.3125, 1.3125), rec[0] - 1.0)]
    return {"depth_mm": depth_mm,
            "nodes": [{"node": i, "position_mm": list(p), "field_deg": [p[0] * 7.1, p[1] * 7.1],
                       "raw": _metric(v - 1.0, 0.5), "rec": _metric(v, 0.55)}
                      for i, (p, v) in enumerate(nodes)],
            "raw": _metric(*raw), "rec": _metric(*rec), "psf_energy": 0.99}


def _segment(commit, card, start, end, wall, dirty=False, ranks=None):
    seg = {"commit": commit, "dirty": dirty, "device": "cuda:0", "card": card, "memory_gb": 85.0,
           "host": "gpu-host", "start_step": start, "started_utc": "2026-11-27T10:00:00Z", "end_step": end,
           "wall_s": wall}
    return seg if ranks is None else {**seg, "ranks": ranks}   # segments before session 22 have no "ranks"


def _result(arm, seed, depths=None, rms=(7.5, 60.0, 30.0), steps_done=3000, steps_total=3000, joint=2000,
            segments=None, evaluated=True, method="e2e"):
    """An arm's ``summary.json`` entry (the keys ``train.train_arm`` writes)."""
    segments = segments if segments is not None else [_segment("a" * 40, H100, 0, steps_done, 1000.0)]
    r = {"arm": arm, "method": method, "steps_done": steps_done, "steps_total": steps_total,
         "train_wall_s": 900.0, "last": {"step": steps_done - 1, "phase": "finetune", "loss": 0.006},
         "notes": [],
         "run": {"commit": segments[-1]["commit"], "dirty": False, "device": "cuda:0",
                 "card": segments[-1]["card"], "memory_gb": 85.0, "host": "gpu-host",
                 "steps_done": steps_done,
                 "steps_total": steps_total,
                 "joint_steps": joint, "finetune_steps": steps_total - joint, "seed": seed,
                 "wall_s_total": sum(s["wall_s"] for s in segments), "segments": segments,
                 "resumed_without_optimizer": False},
         "replans": 0, "feature_projections": 0, "replan_log": [], "field_build": [], "step_log": []}
    if steps_done < steps_total:
        r["stopped_early"] = True
    if evaluated:
        r["eval"] = {"depths": depths or [_depth(None, (24.0, 0.60), (23.0, 0.63))],
                     "rms_um": {"fractions": [0.0, 0.5, 0.9], "per_field": list(rms), "on_axis": rms[0],
                                "off_axis": rms[1], "avg": rms[2]},
                     "efl_mm": 7.95, "doe_coefficients": [0.0, 0.0], "sensor_distance_mm": 2.9472}
        r["objective_initial"] = {"loss": 0.013, "mse": 0.009}
        r["objective_final"] = {"loss": 0.012, "mse": 0.008}
        r["eval_wall_s"] = 12.0
        r["rms_design_log"] = []
        r["run"]["finished_utc"] = "2026-11-27T11:00:00Z"
    return r


def _write(exp_dir: Path, arm, seed, result=None, progress=None, result_json=True, config_seed=None):
    """A run folder ``seed<S>_<arm>/`` as ``rwwarp design --arm ARM --set seed=S --out`` leaves it."""
    d = exp_dir / f"seed{seed}_{arm}"
    (d / arm).mkdir(parents=True)
    cfg = {"experiment": exp_dir.name[:-4], "base": {"seed": seed},
           "arms": [{"name": arm, "config": {"seed": seed if config_seed is None else config_seed,
                                             "train": {"joint_steps": 2000, "finetune_steps": 1000}}}]}
    (d / "config_resolved.json").write_text(json.dumps(cfg))
    if result is not None:
        (d / "summary.json").write_text(json.dumps({arm: result}))
        if result_json and "eval" in result:
            (d / arm / "result.json").write_text(json.dumps(result))
    if progress is not None:
        (d / "progress.json").write_text(json.dumps(progress))
    return d


def _aberration(tmp_path):
    """Both arms, both seeds finished; e2e_doe beats blank_doe in both seeds."""
    e = tmp_path / "a489_aberration_gpu"
    segs = [_segment("abcdef1" + "0" * 33, H100, 0, 1400, 1200.5),
            _segment("1234567" + "0" * 33, H200, 1400, 3000, 3000.25, dirty=True, ranks=4)]
    _write(e, "e2e_doe", 0, _result("e2e_doe", 0, [_depth(None, (24.0, 0.61), (23.0, 0.630))],
                                    rms=(7.4, 56.0, 27.0), segments=segs))
    _write(e, "e2e_doe", 1, _result("e2e_doe", 1, [_depth(None, (24.2, 0.62), (23.4, 0.640))],
                                    rms=(7.6, 57.0, 28.0)))
    _write(e, "blank_doe", 0, _result("blank_doe", 0, [_depth(None, (23.9, 0.60), (22.5, 0.610))],
                                      method="fixed"))
    _write(e, "blank_doe", 1, _result("blank_doe", 1, [_depth(None, (24.1, 0.60), (22.6, 0.612))],
                                      method="fixed"))
    return e


def test_means_spreads_and_a_verdict_that_holds(tmp_path):
    col = ds.collect(_aberration(tmp_path), "a489_aberration")
    assert col["arms"] == ["blank_doe", "e2e_doe"] and col["not_run"] == []
    rows = {r["arm"]: r for r in ds.arm_table(col)}
    e = rows["e2e_doe"]
    assert e["seeds"] == [0, 1]
    # by hand: PSNR rec 23.0 and 23.4 -> mean 23.2, half range 0.2; off-axis RMS 56, 57 -> 56.5 +- 0.5
    assert e["agg"]["psnr_rec"]["mean"] == pytest.approx(23.2, abs=TOL)
    assert e["agg"]["psnr_rec"]["half_range"] == pytest.approx(0.2, abs=TOL)
    assert e["agg"]["rms_off_um"]["mean"] == pytest.approx(56.5, abs=TOL)
    assert e["agg"]["rms_off_um"]["half_range"] == pytest.approx(0.5, abs=TOL)
    assert e["agg"]["ssim_rec"]["mean"] == pytest.approx(0.635, abs=TOL)
    assert e["values"]["psnr_raw"] == {0: 24.0, 1: 24.2}
    c = {x["label"].split(" (")[0]: x for x in ds.comparisons(col)}
    k = c["e2e_doe reconstructs better than blank_doe"]
    # differences 23.0 - 22.5 = 0.5 and 23.4 - 22.6 = 0.8, mean 0.65, both positive
    assert k["diffs"][0] == pytest.approx(0.5, abs=TOL) and k["diffs"][1] == pytest.approx(0.8, abs=TOL)
    assert k["mean"] == pytest.approx(0.65, abs=TOL)
    assert k["verdict"] == "holds"
    # network gain of blank_doe: 22.5 - 23.9 = -1.4 and 22.6 - 24.1 = -1.5: both negative -> reversed
    g = c["blank_doe: the network improves on the raw image"]
    assert g["verdict"] == "reversed" and g["mean"] == pytest.approx(-1.45, abs=TOL)
    # the run record: segments' wall time summed, cards and commits in order of first use
    r = col["runs"][("e2e_doe", 0)]
    assert r["wall_s"] == pytest.approx(4200.75, abs=TOL)
    assert r["cards"] == [H100, f"{H200} x 4"] and r["commits"] == ["abcdef1", "1234567+dirty"]
    assert (r["steps_done"], r["steps_total"], r["joint"], r["finetune"]) == (3000, 3000, 2000, 1000)


def _cooke(tmp_path):
    """cooke_hybrid: e2e against rms_spot with seeds that disagree on PSNR; e2e_from_rms seed 1 stopped at
    a checkpoint (its summary carries an evaluation-like block with absurd numbers that must not be used);
    paraxial seed 1 killed (only progress.json); rms_spot seed 1 and nothing else of paraxial missing."""
    e = tmp_path / "cooke_hybrid_gpu"
    d = lambda rec: [_depth(float("inf"), (20.0, 0.5), (rec, 0.6))]  # noqa: E731
    _write(e, "rms_spot", 0, _result("rms_spot", 0, d(25.0), rms=(5.0, 9.0, 6.0), method="rms"))
    _write(e, "rms_spot", 1, _result("rms_spot", 1, d(25.5), rms=(5.2, 9.2, 6.4), method="rms"))
    _write(e, "e2e", 0, _result("e2e", 0, d(25.3), rms=(8.0, 12.0, 10.0)))     # +0.3 dB, +4.0 um
    _write(e, "e2e", 1, _result("e2e", 1, d(25.1), rms=(8.2, 12.4, 10.4)))     # -0.4 dB, +4.0 um
    _write(e, "e2e_from_rms", 0, _result("e2e_from_rms", 0, d(26.0), rms=(4.0, 8.0, 5.0)))
    bad = _result("e2e_from_rms", 1, d(99.0), rms=(1.0, 1.0, 1.0), steps_done=1400)  # unfinished
    _write(e, "e2e_from_rms", 1, bad, result_json=False)
    _write(e, "paraxial", 0, _result("paraxial", 0, d(24.0), rms=(9.0, 14.0, 11.0),
                                     method="paraxial_achromat"))
    _write(e, "paraxial", 1, None, progress={"state": "dead", "arm": "paraxial", "phase": "joint",
                                             "step": 620, "checkpoint_step": 600, "steps_total": 3000,
                                             "joint_steps": 2000})
    return e


def test_unfinished_arms_are_excluded_and_verdicts_wait_for_them(tmp_path):
    col = ds.collect(_cooke(tmp_path), "cooke_hybrid")
    assert col["arms"] == ["paraxial", "rms_spot", "e2e", "e2e_from_rms"]   # the config's arms, in order
    assert col["not_run"] == []
    runs = col["runs"]
    f1 = runs[("e2e_from_rms", 1)]
    assert f1["state"] == "in progress" and f1["steps_done"] == 1400
    p = runs[("paraxial", 1)]                # killed: the last checkpoint is what a resume starts from
    assert (p["state"], p["steps_done"], p["steps_total"], p["joint"], p["finetune"]) == (
        "in progress", 600, 3000, 2000, 1000)
    rows = {r["arm"]: r for r in ds.arm_table(col)}
    f = rows["e2e_from_rms"]
    assert f["seeds"] == [0]                 # the unfinished seed's 99 dB / 1 um never enter
    assert f["agg"]["psnr_rec"]["mean"] == 26.0 and f["agg"]["psnr_rec"]["n"] == 1
    assert f["agg"]["rms_avg_um"]["mean"] == 5.0
    assert rows["paraxial"]["seeds"] == [0]
    c = {x["label"].split(" (")[0]: x for x in ds.comparisons(col)}
    # e2e - rms_spot PSNR: 25.3 - 25.0 = +0.3, 25.1 - 25.5 = -0.4: the seeds disagree
    k = c["e2e reconstructs better than rms_spot"]
    assert k["verdict"] == "not resolved (seeds disagree)"
    assert k["diffs"][0] == pytest.approx(0.3, abs=TOL) and k["diffs"][1] == pytest.approx(-0.4, abs=TOL)
    assert k["mean"] == pytest.approx(-0.05, abs=TOL)
    # RMS avg: 10.0 - 6.0 = 4.0, 10.4 - 6.4 = 4.0: e2e larger in both -> holds
    r = c["e2e has the larger RMS spot than rms_spot"]
    assert r["verdict"] == "holds" and r["mean"] == pytest.approx(4.0, abs=TOL)
    # e2e_from_rms needs its seed 1: waiting, no mean, seed 0 shown so far (26.0 - 25.0 = +1.0)
    w = c["e2e_from_rms reconstructs better than rms_spot"]
    assert w["verdict"] == "waiting for seed 1 of e2e_from_rms (in progress: step 1400 of 3000)"
    assert w["mean"] is None and list(w["diffs"]) == [0] and w["diffs"][0] == pytest.approx(1.0, abs=TOL)
    g = c["paraxial: the network improves on the raw image"]
    assert g["verdict"] == "waiting for seed 1 of paraxial (in progress: step 600 of 3000)"
    text = "\n".join(ds.section(col["folder"], "Cooke", "cooke_hybrid"))
    assert "| e2e_from_rms | 1 | in progress: step 1400 of 3000 | 1400 / 3000 (2000 + 1000) |" in text
    assert "| e2e_from_rms | inf | 0 | 4.0 (seed 0 only) | 8.0 (seed 0 only) | 5.0 (seed 0 only) |" in text
    assert "26.00 (seed 0 only)" in text and "99.00" not in text


def test_not_run_combinations_and_a_reversed_verdict(tmp_path):
    e = _cooke(tmp_path)
    shutil.rmtree(e / "seed1_rms_spot")
    col = ds.collect(e, "cooke_hybrid")
    assert col["not_run"] == [("rms_spot", 1)]
    c = {x["label"].split(" (")[0]: x for x in ds.comparisons(col)}
    assert c["e2e reconstructs better than rms_spot"]["verdict"] == "waiting for seed 1 of rms_spot (not run)"
    text = "\n".join(ds.section(e, "Cooke", "cooke_hybrid"))
    assert "| rms_spot | 1 | not run | - | - | - | - |" in text
    assert "Not run (protocol's arms x seeds): seed 1 of rms_spot." in text
    # both seeds with the end-to-end spot smaller than the RMS design's: reversed
    a = tmp_path / "x" / "cooke_hybrid_gpu"
    d = [_depth(float("inf"), (20.0, 0.5), (25.0, 0.6))]
    for s, (rz, re_) in enumerate([(6.0, 5.0), (6.5, 6.0)]):
        _write(a, "rms_spot", s, _result("rms_spot", s, d, rms=(1.0, 2.0, rz)))
        _write(a, "e2e", s, _result("e2e", s, d, rms=(1.0, 2.0, re_)))
    col = ds.collect(a, "cooke_hybrid", arms=["rms_spot", "e2e"])
    c = {x["label"].split(" (")[0]: x for x in ds.comparisons(col)}
    r = c["e2e has the larger RMS spot than rms_spot"]
    assert r["verdict"] == "reversed" and r["mean"] == pytest.approx(-0.75, abs=TOL)   # (-1.0 - 0.5) / 2


def test_edof_off_axis_node_per_depth(tmp_path):
    """The off-axis value is the node farthest from the axis (here the first of the list, as on an
    evaluation grid), not the last node; one depth holds, the other is reversed."""
    e = tmp_path / "a489_edof_gpu"

    def dd(corner_200, corner_10k):
        nodes = lambda corner: [((1.3125, 1.3125), corner), ((0.1875, 0.1875), 30.0),  # noqa: E731
                                ((1.3125, 0.1875), 50.0)]
        return [_depth(200.0, (29.0, 0.7), (30.0, 0.7), nodes(corner_200)),
                _depth(10000.0, (27.0, 0.6), (28.0, 0.6), nodes(corner_10k))]
    # (paraxial, raywave) corner PSNRs per seed: 200 mm raywave higher in both, 10 m lower in both;
    # the last node (50 dB in every arm) would give a difference of 0 at both depths
    for s, (p200, w200, p10, w10) in enumerate([(20.0, 21.0, 18.0, 17.5), (20.5, 21.1, 18.2, 18.0)]):
        _write(e, "paraxial_doe", s, _result("paraxial_doe", s, dd(p200, p10)))
        _write(e, "raywave_doe", s, _result("raywave_doe", s, dd(w200, w10)))
    col = ds.collect(e, "a489_edof")
    c = {x["label"]: x for x in ds.comparisons(col) if x["key"] == "psnr_rec_off"}
    assert [x["depth"] for x in c.values()] == ["200mm", "10000mm"]
    k200 = next(x for x in c.values() if x["depth"] == "200mm")
    k10 = next(x for x in c.values() if x["depth"] == "10000mm")
    assert k200["verdict"] == "holds" and k200["mean"] == pytest.approx((1.0 + 0.6) / 2, abs=TOL)
    assert k10["verdict"] == "reversed" and k10["mean"] == pytest.approx((-0.5 - 0.2) / 2, abs=TOL)
    rows = [r for r in ds.arm_table(col) if r["arm"] == "raywave_doe"]
    assert [r["depth"] for r in rows] == ["200mm", "10000mm"]


def test_verdict_rules():
    assert ds.verdict({0: 0.5, 1: 0.1}, +1, []) == "holds"
    assert ds.verdict({0: -0.5, 1: -0.1}, +1, []) == "reversed"
    assert ds.verdict({0: -0.5, 1: -0.1}, -1, []) == "holds"
    assert ds.verdict({0: 0.5, 1: -0.1}, +1, []) == "not resolved (seeds disagree)"
    assert ds.verdict({0: 0.5, 1: 0.0}, +1, []) == "not resolved (seeds disagree)"
    assert ds.verdict({0: 0.5, 1: None}, +1, []).startswith("not resolved (no value")
    assert ds.verdict({0: 0.5}, +1, ["seed 1 of e2e (not run)"]) == "waiting for seed 1 of e2e (not run)"
    agg = ds.aggregate({0: 3.0, 1: None, 2: 5.0})          # None (NaN in the file) left out
    assert (agg["mean"], agg["half_range"], agg["n"], agg["seeds"]) == (4.0, 1.0, 2, [0, 2])
    assert ds.aggregate({0: None}) is None


def test_problem_runs_are_not_used(tmp_path):
    """A folder whose seed differs from the run's own record (copied into the wrong folder) is not used."""
    e = _aberration(tmp_path)
    r = _result("e2e_doe", 2, [_depth(None, (24.0, 0.61), (40.0, 0.9))])
    _write(e, "e2e_doe", 3, r, config_seed=3)
    col = ds.collect(e, "a489_aberration")
    rec = col["runs"][("e2e_doe", 3)]
    assert rec["problems"] == ["run.seed says seed 2, the folder name seed 3"]
    row = next(r for r in ds.arm_table(col) if r["arm"] == "e2e_doe")
    assert row["seeds"] == [0, 1] and row["agg"]["psnr_rec"]["mean"] == pytest.approx(23.2, abs=TOL)
    # seed 3 has a folder for e2e_doe but not for blank_doe and is not usable: the check waits
    k = next(x for x in ds.comparisons(col) if x["label"].startswith("e2e_doe reconstructs"))
    assert k["verdict"] == ("waiting for seed 3 of e2e_doe (not used: run.seed says seed 2, the folder name "
                            "seed 3), seed 3 of blank_doe (not run)")


def test_report_writes_the_seed_sections_and_keeps_the_discussion(tmp_path):
    _aberration(tmp_path)
    _cooke(tmp_path)
    (tmp_path / "README.md").write_text("old\n<!-- discussion -->\nmine\n<!-- /discussion -->\n")
    assert design_report.main(["--results", str(tmp_path)]) == 0
    text = (tmp_path / "README.md").read_text()
    assert "<!-- discussion -->\nmine\n<!-- /discussion -->" in text
    assert "GPU runs, one folder per arm and seed (`a489_aberration_gpu/`)" in text
    assert "GPU runs, one folder per arm and seed (`cooke_hybrid_gpu/`)" in text
    assert "e2e_doe reconstructs better than blank_doe (reconstructed PSNR, depth default): **holds** " \
           "(mean +0.65 dB; seed 0: +0.50, seed 1: +0.80)" in text
    assert "| e2e_doe | 0 | finished | 3000 / 3000 (2000 + 1000) | 1.17 h | " + f"{H100}, {H200} x 4 | " \
           "abcdef1, 1234567+dirty |" in text
    assert "nan" not in text.lower()         # the NaN 1-LPIPS of the files is not a figure shown


def test_protocol_arms_are_the_configs():
    assert ds.protocol_arms("a489_aberration") == ["blank_doe", "e2e_doe"]
    assert ds.protocol_arms("cooke_hybrid") == ["paraxial", "rms_spot", "e2e", "e2e_from_rms"]
    assert ds.protocol_arms("a489_edof") == ["paraxial_doe", "raywave_doe"]


def test_the_real_format_reads_as_its_table(tmp_path):
    """The shortened GPU run of the repository (``a489_aberration_gpu_short``, written by ``rwwarp design``,
    one run folder for both arms) split into seed folders: the figures read from ``summary.json`` are the
    numbers of its ``table.csv`` (written from the same results by ``torch_bridge.report.write_table``);
    without a ``run`` record (older version) the schedule comes from ``config_resolved.json`` and the wall
    time is training + evaluation."""
    src = ROOT / "perf" / "results" / "design" / "a489_aberration_gpu_short"
    summ = json.loads((src / "summary.json").read_text())
    e = tmp_path / "a489_aberration_gpu"
    for arm, r in summ.items():
        d = e / f"seed0_{arm}"
        d.mkdir(parents=True)
        (d / "summary.json").write_text(json.dumps({arm: r}))
        shutil.copy(src / "config_resolved.json", d / "config_resolved.json")
    col = ds.collect(e, "a489_aberration")
    with open(src / "table.csv", newline="") as f:
        table = {row["design"]: row for row in csv.DictReader(f)}
    cols = ("rms_on_um", "rms_off_um", "rms_avg_um", "psnr_raw", "ssim_raw", "psnr_rec", "ssim_rec")
    for arm in summ:
        rec = col["runs"][(arm, 0)]
        assert ds.usable(rec) and (rec["steps_done"], rec["joint"], rec["finetune"]) == (180, 60, 120)
        fig = rec["figures"]["default"]
        for k in cols:              # table.csv holds repr(float): exact
            assert fig[k] == float(table[arm][k]), (arm, k)
        wall = float(table[arm]["train_wall_s"]) + summ[arm]["eval_wall_s"]
        assert rec["wall_s"] == pytest.approx(wall, abs=TOL)
        assert rec["wall_from"] == "train+eval" and rec["cards"] == []
    assert col["not_run"] == [("blank_doe", 1), ("e2e_doe", 1)]
    k = next(x for x in ds.comparisons(col) if x["label"].startswith("e2e_doe reconstructs"))
    assert k["verdict"] == "waiting for seed 1 of e2e_doe (not run), seed 1 of blank_doe (not run)"
    expect = float(table["e2e_doe"]["psnr_rec"]) - float(table["blank_doe"]["psnr_rec"])
    assert k["diffs"][0] == pytest.approx(expect, abs=TOL)


def test_side_by_side_with_the_paper():
    """Ours beside the paper's rows (``perf/paper_tables.py``) and the margins, worked out by hand: e2e_doe
    27.0 / 29.0 dB raw / rec against blank_doe 26.5 / 27.5 -> +0.50 / +1.50 dB; the paper's asphe_score rows
    24.7 - 24.4 = +0.30 raw, 32.5 - 28.8 = +3.70 rec. An arm the paper has no row for is left out; the EDoF rows
    are matched per depth."""
    import paper_tables as pt

    def row(arm, depth, **means):
        return {"arm": arm, "depth": depth, "agg": {k: {"mean": v} for k, v in means.items()}}

    rows = [row("blank_doe", "default", psnr_raw=26.5, psnr_rec=27.5, ssim_raw=0.6, ssim_rec=0.7),
            row("e2e_doe", "default", psnr_raw=27.0, psnr_rec=29.0, ssim_raw=0.61, ssim_rec=0.72),
            row("other_arm", "default", psnr_raw=1.0, psnr_rec=1.0)]
    text = "\n".join(pt.side_by_side("a489_aberration", rows))
    assert "| blank_doe | default | Refractive lens | 26.50 | 24.4 | 0.600 | 0.702 | 27.50 | 28.8 |" in text
    assert "| e2e_doe | default | Hybrid lens (ours) | 27.00 | 24.7 |" in text
    assert "other_arm" not in text
    assert "- e2e_doe - blank_doe: raw +0.50 (paper +0.30), reconstructed +1.50 (paper +3.70) dB" in text
    edof = [row("paraxial_doe", "300mm", psnr_raw=20.0, psnr_rec=21.0),
            row("raywave_doe", "300mm", psnr_raw=20.5, psnr_rec=23.0)]
    text = "\n".join(pt.side_by_side("a489_edof", edof))
    # 22.4 - 19.0 = +3.40 raw, 28.9 - 18.7 = +10.20 rec at 30 cm
    assert "raywave_doe - paraxial_doe at 300mm: raw +0.50 (paper +3.40), reconstructed +2.00 (paper +10.20) dB" in text
    assert pt.side_by_side("no_such_experiment", rows) == []
