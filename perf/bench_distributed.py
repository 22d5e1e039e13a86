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

``--problem paper`` (multi-GPU run, issue 15): the maps are 10 x 10 fields x 3 wavelengths x 3 depths of
the A489 + DOE and of the Cooke hybrid at F/4 (its paraxial achromatic DOE, ``focal_patch_tol`` 1e-3
as its design configuration), 64 px; the design step is ``cooke_hybrid``'s ``gpu`` preset (e2e arm: 16
nodes, live ray-wave PSFs of curvatures + DOE + distance, NAFNet ``paper``, batch 8 x 256^2), with the
loss and the optics and network gradients of the first step compared between 1 and N ranks, and each
rank's peak memory (torch's allocator, CuPy's pool, ``nvidia-smi`` per GPU). ``--only map|design``
runs one half (the whole does not fit one 10-minute device call).
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
from _common import GpuMemory, device_name, git_commit

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


COOKE = "torch_bridge/configs/lenses/cooke_hybrid.json"
PAPER_MAPS = [
    {"lens": "a489_doe", "half_field_mm": 1.35, "depths_mm": [None, 2000.0, 1000.0], "size": 64,
     "wavelengths_um": [0.47, 0.55, 0.63], "grid": 10, "focal_patch_tol": 1e-5},
    {"lens": "cooke_hybrid (F/4, paraxial achromatic DOE)", "half_field_mm": 3.6, "depths_mm": [None, 20000.0, 10000.0],
     "size": 64, "wavelengths_um": [0.47, 0.55, 0.63], "grid": 10, "focal_patch_tol": 1e-3},
]


def _paper_lens(name: str):
    """The lens of a PAPER_MAPS entry: a bundled lens, or the Cooke hybrid with its paraxial achromatic
    DOE at the distance that focuses it (as the design's paraxial arm starts)."""
    import rwwarp as rw
    if not name.startswith("cooke_hybrid"):
        return rw.load_lens(name)
    from torch_bridge import design as dz
    root = Path(__file__).resolve().parent.parent
    lens = rw.load_lens(str(root / COOKE))
    a, dist = dz.paraxial_achromat(lens, [w for c in ([0.60, 0.63, 0.66], [0.52, 0.55, 0.58], [0.45, 0.47, 0.49])
                                          for w in c])
    d = len(lens.surfaces) - 1
    s = lens.surfaces[d]
    coeffs = [0.0] * len(s.profile["coefficients"])
    coeffs[0] = a
    return lens.with_surface(d, profile={**s.profile, "coefficients": coeffs}, thickness=dist)


def _paper_fields(lens, half_mm: float, n: int):
    """n x n field angles (x, y) (deg) whose paraxial images form a grid of +-half_mm on the sensor."""
    import math

    import numpy as np
    f = lens.efl(0.55)
    v = np.linspace(-half_mm, half_mm, n)
    return [(math.degrees(math.atan(x / f)), math.degrees(math.atan(y / f))) for y in v for x in v]


def _paper_map_worker(device: str, repeat: int):
    import numpy as np

    from rwwarp import distributed as D
    res = []
    # RWWARP_BENCH_MAPS=K: the first K problems only (a CPU smoke run; the Cooke hybrid's maps are GPU-sized)
    for prob in PAPER_MAPS[:int(os.environ.get("RWWARP_BENCH_MAPS", len(PAPER_MAPS)))]:
        lens = _paper_lens(prob["lens"])
        # RWWARP_BENCH_GRID: a smaller field grid for a smoke run of this script on a CPU
        # RWWARP_BENCH_GRIDS="10,4": the field grid of each problem (a shorter run)
        grids = os.environ.get("RWWARP_BENCH_GRIDS")
        n = int(grids.split(",")[PAPER_MAPS.index(prob)]) if grids else int(os.environ.get("RWWARP_BENCH_GRID", prob["grid"]))
        fields = _paper_fields(lens, prob["half_field_mm"], n)
        kw = dict(size=prob["size"], device=device, focal_patch_tol=prob["focal_patch_tol"])
        D.psf_map(lens, fields[:2], prob["wavelengths_um"], **kw)   # warm-up: kernels built, planner warm
        times, maps = [], None
        # RWWARP_BENCH_REPEATS="2,1": timed maps of each problem (the Cooke hybrid's 900 PSFs take
        # two minutes on one GPU, and its first map shows no warm-up effect)
        reps = os.environ.get("RWWARP_BENCH_REPEATS")
        for _ in range(int(reps.split(",")[PAPER_MAPS.index(prob)]) if reps else repeat):
            _barrier()
            t = time.perf_counter()
            maps = D.psf_map(lens, fields, prob["wavelengths_um"], depths_mm=prob["depths_mm"], **kw)
            times.append(time.perf_counter() - t)
            if maps is not None:
                print(f"  {prob['lens']}: {len(fields) * len(prob['wavelengths_um']) * len(prob['depths_mm'])} PSFs "
                      f"in {times[-1]:.2f} s (plan {maps[0].info['plan_s']:.2f} s); per rank "
                      f"{[(r['psfs'], round(r['work_s'], 2)) for r in maps[0].info['ranks']]}", flush=True)
        if maps is None:
            res.append(None)
            continue
        data = np.stack([m.data for m in maps])
        res.append({"map_s": times, "psfs": int(data.shape[0] * data.shape[1] * data.shape[2]),
                    "ranks": maps[0].info["ranks"], "units": len(maps[0].info["units"]),
                    "plan_s": maps[0].info["plan_s"], "data": data, "finite": bool(np.isfinite(data).all())})
    return None if res[0] is None else res


def _paper_design_worker(device: str, steps: int):
    import numpy as np
    import torch

    from torch_bridge.distributed import current_group
    from torch_bridge.train import Arm, _seed_all, load_config, train_step
    root = Path(__file__).resolve().parent.parent
    exp = load_config(str(root / "torch_bridge/configs/cooke_hybrid.yaml"), preset="gpu")
    arm_cfg = next(a for a in exp["arms"] if a["name"] == "e2e")
    cfg = copy.deepcopy(arm_cfg["config"])
    cfg["device"] = device
    cfg["progress"] = False
    g = current_group(device)
    if g is not None:
        cfg = dict(cfg, device=g.device(device))
    dev = torch.device(cfg["device"])
    if dev.type == "cuda":
        dev = torch.device("cuda", dev.index or 0)
        torch.cuda.set_device(dev)
    _seed_all(int(cfg["seed"]))
    arm = Arm("e2e", cfg, exp["source"], Path("unused"), progress=False)
    times, losses, first = [], [], None
    for step in range(steps + 1):
        _barrier()
        t = time.perf_counter()
        s = train_step(arm, step, {}, g)
        if step == 0:
            first = {"optics": {q["name"]: q["params"][0].grad.detach().double().cpu().numpy()
                                for q in arm.opt_optics.param_groups if q["params"][0].grad is not None},
                     "network": np.concatenate([p.grad.detach().double().cpu().numpy().ravel()
                                                for p in arm.net.parameters() if p.grad is not None])}
        arm.opt_net.step()
        arm.opt_optics.step()
        if dev.type == "cuda":
            torch.cuda.synchronize()
        _barrier()
        (times.append(time.perf_counter() - t) if step else None)
        losses.append(s["loss"])
    mem = {"rank": 0 if g is None else g.rank, "device": str(dev)}
    if dev.type == "cuda":
        mem["torch_max_allocated_GB"] = torch.cuda.max_memory_allocated(dev) / 1e9
        try:
            import cupy
            with cupy.cuda.Device(dev.index or 0):
                mem["cupy_pool_total_GB"] = cupy.get_default_memory_pool().total_bytes() / 1e9
        except ImportError:
            pass
    mems = [mem]
    if g is not None:
        mems = [None] * g.size
        g.dist.all_gather_object(mems, mem)
        if g.rank != 0:
            return None
    return {"step_s": times, "losses": losses, "first_step": first, "memory_per_rank": mems,
            "nodes": len(arm.fields), "batch": cfg["data"]["batch_size"], "psf_size": arm.size,
            "provider": type(arm.provider).__name__}


def _launched(fn, n: int, *args):
    """``fn(*args)`` on ``n`` ranks (rwwarp.distributed.launch): (rank 0's result, wall s of the whole
    launch, {GPU index: peak used MiB} sampled meanwhile)."""
    from rwwarp.distributed import launch
    with GpuMemory(0.1) as mem:
        t = time.perf_counter()
        r = launch(fn, n, *args)[0]
        return r, time.perf_counter() - t, dict(mem.peaks)


def _rel(a, b):
    import numpy as np
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.max(np.abs(a - b)) / max(float(np.max(np.abs(b))), 1e-300))


def main_paper(a):
    """The multi-GPU run of issue 15 (see the module docstring)."""
    import json

    import numpy as np

    out = {"benchmark": "bench_distributed --problem paper", "device": a.device, "machine": device_name(a.device),
           "cpu_count": os.cpu_count(), "commit": git_commit(), "backend": "nccl" if a.device.startswith("cuda")
           else "gloo", "nvlink_multicast": os.environ.get("NCCL_NVLS_ENABLE", "unset"),
           "map_problems": PAPER_MAPS, "map": [], "design": []}
    p = Path(a.out) if a.out else Path(__file__).resolve().parent / "results" / f"distributed_paper_{a.only or 'all'}.json"
    p.parent.mkdir(parents=True, exist_ok=True)

    def save():   # after every configuration: a later one that fails or times out keeps the earlier rows
        p.write_text(json.dumps(out, indent=1, default=float) + "\n")
    if a.only in (None, "map"):
        ref = None
        for n in a.ranks:
            rs, wall, peaks = _launched(_paper_map_worker, n, a.device, a.repeat)
            ref = ref or [x["data"] for x in rs]
            for k, (r, r1) in enumerate(zip(rs, ref)):
                best = min(r["map_s"])
                row = {"problem": PAPER_MAPS[k]["lens"], "ranks": n, "psfs": r["psfs"], "units": r["units"],
                       "map_s": r["map_s"], "best_map_s": best, "psfs_per_s": r["psfs"] / best,
                       "plan_s": r["plan_s"], "all_finite": r["finite"],
                       "max_abs_diff_vs_first": float(np.max(np.abs(r["data"] - r1))),
                       "max_psf_value": float(np.max(r1)), "per_rank": r["ranks"],
                       "command_wall_s": wall, "gpu_used_peak_MiB": peaks}
                base = next((x for x in out["map"] if x["problem"] == row["problem"] and x["ranks"] == a.ranks[0]), None)
                if base is not None:
                    row["speedup"] = row["psfs_per_s"] / base["psfs_per_s"]
                    row["parallel_efficiency"] = row["speedup"] * a.ranks[0] / n
                out["map"].append(row)
                save()
                print(f"map {row['problem']}, {n} rank(s): {r['psfs']} PSFs in {best:.2f} s "
                      f"({row['psfs_per_s']:.1f} PSF/s, plan {r['plan_s']:.1f} s), efficiency "
                      f"{row.get('parallel_efficiency', 1.0):.3f}; max |diff| vs {a.ranks[0]} rank(s) "
                      f"{row['max_abs_diff_vs_first']:.3g} (max {row['max_psf_value']:.3g})", flush=True)
            for x in rs:
                x.pop("data", None)
    if a.only in (None, "design"):
        ref = None
        for n in a.ranks:
            r, wall, peaks = _launched(_paper_design_worker, n, a.device, a.steps)
            first = r.pop("first_step")
            ref = ref or first
            row = dict(r, ranks=n, median_step_s=statistics.median(r["step_s"]), command_wall_s=wall,
                       gpu_used_peak_MiB=peaks,
                       loss0_rel_diff_vs_first=None if ref is first else abs(r["losses"][0] - out["design"][0]["losses"][0])
                       / abs(out["design"][0]["losses"][0]),
                       optics_grad_rel_diff_vs_first={q: _rel(first["optics"][q], ref["optics"][q]) for q in ref["optics"]},
                       network_grad_rel_diff_vs_first=_rel(first["network"], ref["network"]))
            base = out["design"][0] if out["design"] else None
            if base is not None:
                row["speedup"] = base["median_step_s"] / row["median_step_s"]
                row["parallel_efficiency"] = row["speedup"] * base["ranks"] / n
            out["design"].append(row)
            save()
            # the first step's gradients, to compare with a run made in another command
            np.savez(p.with_name(f"{p.stem}_grads_{n}ranks.npz"), network=first["network"],
                     **{f"optics_{q}": v for q, v in first["optics"].items()})
            print(f"design step, {n} rank(s): median {row['median_step_s']:.2f} s over {len(r['step_s'])} steps, "
                  f"losses {[f'{x:.7g}' for x in r['losses']]}, grads vs first: optics "
                  f"{row['optics_grad_rel_diff_vs_first']}, network {row['network_grad_rel_diff_vs_first']:.3g}; "
                  f"memory {r['memory_per_rank']}, nvidia-smi {peaks} MiB", flush=True)
    save()
    print(f"written to {p}")


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
    ap.add_argument("--problem", choices=["small", "paper"], default="small",
                    help="small: the CPU-sized problems; paper: issue 15's maps and the cooke_hybrid gpu preset")
    ap.add_argument("--only", choices=["map", "design"], default=None, help="with --problem paper: one half")
    a = ap.parse_args(argv)
    if a.problem == "paper":
        return main_paper(a)
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
