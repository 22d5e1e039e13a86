"""Scaling of the torch.distributed paths (issue 14) against the number of ranks.

* **PSF map** (:func:`rwwarp.distributed.psf_map`): a bundled lens, fields x wavelengths, ray-wave;
  throughput in PSFs/s of the map itself (after a warm-up map in the same processes: kernels
  compiled, planner warm), and the wall time of the whole command including the start of the
  processes (torch's launcher).
* **Design step** (:func:`torch_bridge.train.train_step` with a group): one joint optics step (PSFs of
  the nodes shared out, render, NAFNet forward/backward, all-reductions), median over steps after a
  warm-up step; float32 network as in training.

Each configuration runs in its own processes started through :func:`rwwarp.distributed.launch`
(gloo on the CPU, NCCL with ``--device cuda``: one GPU a rank). With one rank the launcher still
starts one worker (WORLD_SIZE 1: the single-process paths). On the CPU the ranks share the cores
(torch's launcher gives each worker one OpenMP thread when there are several).

    python perf/bench_distributed.py [--ranks 1 2] [--device cpu] [--out perf/results/distributed_cpu.json]
"""
from __future__ import annotations

import argparse
import copy
import os
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import device_name, git_commit

MAP = {"lens": "a489_doe", "max_field_deg": 14.0, "fields": 6, "wavelengths_um": [0.47, 0.55, 0.63], "size": 32}
DESIGN = {
    "experiment": "bench", "seed": 3, "progress": False,
    "lens": {"file": "a489_doe", "doe_levels": 16},
    "optics": {"learn": {"doe": "all"}, "psf_size": 15, "pixel_um": 3.0,
               "nodes": {"layout": "grid", "grid": [2, 2], "region": "full", "half_size_mm": 1.5},
               "wavelengths_um": [[0.63], [0.55], [0.47]], "nyquist_safety": 1.0, "rays_per_sample": 1.2},
    "data": {"crop": 32, "batch_size": 4, "eval_images": 2},
    "network": {"preset": "tiny"},
    "loss": {"alpha": 0.1, "perceptual": "ssim"},
    "train": {"joint_steps": 100, "finetune_steps": 0, "lr_network": 1e-3, "lr_optics": {"doe": 0.5}},
    "arms": [{"name": "e2e", "design": {"method": "e2e"}}],
}


def _map_worker(device: str, repeat: int):
    import numpy as np

    import rwwarp as rw
    from rwwarp import distributed as D
    lens = rw.load_lens(MAP["lens"])
    fields = [(0.0, float(f)) for f in np.linspace(0.0, MAP["max_field_deg"], MAP["fields"])]
    D.psf_map(lens, fields[:2], MAP["wavelengths_um"], size=MAP["size"], device=device)   # warm-up
    times, m = [], None
    for _ in range(repeat):
        _barrier()
        t = time.perf_counter()
        m = D.psf_map(lens, fields, MAP["wavelengths_um"], size=MAP["size"], device=device)
        times.append(time.perf_counter() - t)
    if m is None:
        return None
    return {"map_s": times, "psfs": int(m.data.shape[0] * m.data.shape[1]), "ranks": m.info["ranks"],
            "units": len(m.info["units"]), "data": m.data}


def _design_worker(device: str, steps: int):
    import torch

    from torch_bridge.distributed import current_group
    from torch_bridge.train import Arm, _seed_all, load_config, train_step
    cfg0 = copy.deepcopy(DESIGN)
    cfg0["device"] = device
    exp = load_config(cfg0)
    cfg = exp["arms"][0]["config"]
    g = current_group(device)
    if g is not None:
        cfg = dict(cfg, device=g.device(device))
    _seed_all(int(cfg["seed"]))
    arm = Arm("e2e", cfg, exp["source"], Path("unused"), progress=False)
    t = time.perf_counter()
    arm.provider.prepare(sorted({w for c in arm.wls for w in c}), arm.depths)
    prep = time.perf_counter() - t
    times, losses = [], []
    for step in range(steps + 1):
        _barrier()
        t = time.perf_counter()
        s = train_step(arm, step, {}, g)
        arm.opt_net.step()
        arm.opt_optics.step()
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        _barrier()
        if step:
            times.append(time.perf_counter() - t)
        losses.append(s["loss"])
    if g is not None and g.rank != 0:
        return None
    return {"step_s": times, "prepare_s": prep, "losses": losses, "nodes": len(arm.fields),
            "batch": cfg["data"]["batch_size"]}


def _barrier():
    if int(os.environ.get("WORLD_SIZE", "1")) > 1:
        import torch.distributed as dist
        if dist.is_initialized():
            dist.barrier()


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ranks", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--repeat", type=int, default=3, help="timed maps per configuration")
    ap.add_argument("--steps", type=int, default=5, help="timed design steps per configuration")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    import numpy as np

    from rwwarp.distributed import launch
    out = {"benchmark": "bench_distributed", "device": a.device, "machine": device_name(a.device),
           "cpu_count": os.cpu_count(), "commit": git_commit(), "backend": "nccl" if a.device.startswith("cuda")
           else "gloo", "map_problem": MAP,
           "design_problem": {"lens": "a489_doe", "psf_size": DESIGN["optics"]["psf_size"], "nodes": 4,
                              "batch_size": DESIGN["data"]["batch_size"], "crop": DESIGN["data"]["crop"],
                              "network": "tiny NAFNet, float32", "wavelengths": "one per channel"},
           "load_average_before": os.getloadavg(), "map": [], "design": []}
    ref = None
    for n in a.ranks:
        t = time.perf_counter()
        r = launch(_map_worker, n, a.device, a.repeat)[0]
        wall = time.perf_counter() - t
        best = min(r["map_s"])
        err = 0.0 if ref is None else float(np.max(np.abs(r["data"] - ref)))
        ref = r["data"] if ref is None else ref
        row = {"ranks": n, "psfs": r["psfs"], "units": r["units"], "map_s": r["map_s"], "best_map_s": best,
               "psfs_per_s": r["psfs"] / best, "command_wall_s": wall, "max_abs_diff_vs_1_rank": err,
               "per_rank": r["ranks"]}
        out["map"].append(row)
        print(f"map, {n} rank(s): {r['psfs']} PSFs in {best:.2f} s ({row['psfs_per_s']:.2f} PSF/s), command "
              f"{wall:.1f} s with the launch; max |diff| vs 1 rank {err:.2g}", flush=True)
    for n in a.ranks:
        t = time.perf_counter()
        r = launch(_design_worker, n, a.device, a.steps)[0]
        wall = time.perf_counter() - t
        med = statistics.median(r["step_s"])
        row = {"ranks": n, "step_s": r["step_s"], "median_step_s": med, "prepare_s": r["prepare_s"],
               "losses": r["losses"], "command_wall_s": wall, "nodes": r["nodes"], "batch": r["batch"]}
        out["design"].append(row)
        print(f"design step, {n} rank(s): median {med:.3f} s over {len(r['step_s'])} steps (field cache "
              f"{r['prepare_s']:.1f} s); losses {[f'{x:.6g}' for x in r['losses']]}", flush=True)
    out["load_average_after"] = os.getloadavg()
    p = Path(a.out) if a.out else Path(__file__).resolve().parent / "results" / (
        "distributed_cpu.json" if a.device == "cpu" else "distributed_gpu.json")
    p.parent.mkdir(parents=True, exist_ok=True)
    import json
    p.write_text(json.dumps(out, indent=1, default=float) + "\n")
    print(f"written to {p}")


if __name__ == "__main__":
    main()
