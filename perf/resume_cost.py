"""What a portable checkpoint costs: its size for the paper's NAFNet, and what resuming from the small
forms (bfloat16 weights, no Adam moments) changes against an uninterrupted run, on the CPU.

    python perf/resume_cost.py [--out perf/results/design/resume_cost_cpu.json]

1. Sizes (MiB = 2**20 bytes): the NAFNet ``paper`` preset (17.1 M parameters) after one Adam step,
   serialised as ``rwwarp design pack`` stores it: weights float32 / bfloat16, Adam moments full /
   bfloat16 / none, and the number of parts of 15 MiB (the transfer limit is 16 MiB a file, 64 MiB and
   8 files a command).
2. Cost: a small design (the A489 + DOE of the tests, the ``small`` NAFNet, 10 joint + 30 fine-tune
   steps) run straight, and stopped after ``--stop`` steps, packed in each form and resumed in a fresh
   folder. Per form: the mean training loss over the resumed steps and the final evaluation (reconstructed
   PSNR) against the straight run. The full form must reproduce the straight run exactly.
"""
from __future__ import annotations

import argparse
import copy
import csv
import io
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402

from torch_bridge.runs import _portable_state, git_commit, pack, unpack  # noqa: E402
from torch_bridge.train import train  # noqa: E402

CFG = {
    "experiment": "resume_cost", "seed": 3,
    "lens": {"file": "a489_doe", "doe_levels": 16},
    "optics": {"learn": {"doe": "all"}, "psf_size": 15, "pixel_um": 3.0,
               "nodes": {"layout": "diagonal", "fractions": [0.0, 0.6], "half_size_mm": 1.5},
               "wavelengths_um": [[0.63], [0.55], [0.47]], "nyquist_safety": 1.0, "rays_per_sample": 1.2,
               "doe_budget_cpmm": 10},
    "data": {"crop": 32, "batch_size": 4, "eval_images": 8},
    "network": {"preset": "small"},
    "loss": {"alpha": 0.1, "perceptual": "ssim"},
    "train": {"joint_steps": 10, "finetune_steps": 30, "lr_network": 1e-3, "lr_optics": {"doe": 0.5},
              "log_every": 1, "image_every": 0, "checkpoint_every": 0, "optics_every": 1},
    "eval": {"rms_fractions": [0.0, 0.6], "rms_grid": 15, "batch_size": 4},
    "progress": False,
    "arms": [{"name": "e2e", "design": {"method": "e2e"}}],
}
FORMS = [("float32", "full"), ("float32", "none"), ("bfloat16", "none"), ("bfloat16", "bfloat16"),
         ("bfloat16", "full")]


def sizes() -> dict:
    """Bytes of the NAFNet ``paper`` state in each pack form (after one Adam step on a 64 px crop)."""
    from torch_bridge.network import build_network
    torch.manual_seed(0)
    net = build_network("paper", 3, zero_init=False)
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    net(torch.rand(1, 3, 64, 64)).square().mean().backward()
    opt.step()
    st = {"step": 1, "net": net.state_dict(), "opt_net": opt.state_dict()}
    out = {"parameters": sum(p.numel() for p in net.parameters())}
    for w, o in FORMS + [("float32", "bfloat16")]:
        buf = io.BytesIO()
        torch.save(_portable_state(st, w, o), buf)
        n = buf.tell()
        out[f"weights_{w}_adam_{o}"] = {"mib": round(n / 2 ** 20, 2), "parts_15mib": -(-n // (15 * 2 ** 20)),
                                        "commands_64mib": -(-n // (64 * 2 ** 20))}
    return out


def _losses(path: Path):
    with open(path, newline="") as f:
        return [(int(r["step"]), float(r["loss"]), float(r["psnr_train"])) for r in csv.DictReader(f)]


def cost(stop: int) -> dict:
    """Straight run against resumes from each pack form after ``stop`` steps."""
    res = {"stop_after": stop, "steps_total": CFG["train"]["joint_steps"] + CFG["train"]["finetune_steps"]}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        t = time.perf_counter()
        ref = train(copy.deepcopy(CFG), out_dir=tmp / "straight")["e2e"]
        res["straight_s"] = round(time.perf_counter() - t, 1)
        ref_l = _losses(tmp / "straight" / "e2e" / "metrics.csv")
        cut = copy.deepcopy(CFG)
        cut["train"]["stop_after"] = stop
        train(cut, out_dir=tmp / "cut")
        after = [x for x in ref_l if x[0] >= stop]
        res["straight"] = {"mean_loss_after": sum(x[1] for x in after) / len(after),
                           "psnr_rec": ref["eval"]["depths"][0]["rec"]["psnr"],
                           "objective_final": ref["objective_final"]["loss"]}
        for w, o in FORMS:
            key = f"weights_{w}_adam_{o}"
            man = pack(tmp / "cut", tmp / f"pack_{key}", weights=w, optimizer=o)
            unpack(tmp / f"pack_{key}", tmp / key)
            r = train(copy.deepcopy(CFG), out_dir=tmp / key)["e2e"]
            lo = [x for x in _losses(tmp / key / "e2e" / "metrics.csv") if x[0] >= stop]
            d = [a[1] - b[1] for a, b in zip(lo, after)]
            res[key] = {"pack_mib": round(man["bytes"] / 2 ** 20, 3),
                        "mean_loss_after": sum(x[1] for x in lo) / len(lo),
                        "max_abs_loss_diff": max(abs(x) for x in d),
                        "first_step_loss_diff": d[0],
                        "psnr_rec": r["eval"]["depths"][0]["rec"]["psnr"],
                        "psnr_rec_diff_db": r["eval"]["depths"][0]["rec"]["psnr"] - res["straight"]["psnr_rec"],
                        "objective_final": r["objective_final"]["loss"],
                        "bit_equal": all(a == b for a, b in zip(lo, after))}
            print(key, json.dumps(res[key]), flush=True)
    return res


def main(argv=None) -> int:
    """Run both measurements and write the JSON (``--out``)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default="perf/results/design/resume_cost_cpu.json")
    ap.add_argument("--stop", type=int, default=15, help="steps before the interruption")
    a = ap.parse_args(argv)
    out = {"commit": git_commit(), "sizes_nafnet_paper": sizes()}
    print(json.dumps(out["sizes_nafnet_paper"], indent=1), flush=True)
    out["cost_small_design"] = cost(a.stop)
    p = Path(a.out)
    tmp = p.with_name("." + p.name + ".tmp")
    tmp.write_text(json.dumps(out, indent=1))
    tmp.replace(p)
    print(f"wrote {p}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
