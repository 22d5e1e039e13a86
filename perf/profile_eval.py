"""Where an arm's evaluation (``torch_bridge.evaluate.evaluate``) spends its time, on a small grid.

    python perf/profile_eval.py --config a489_aberration --preset cpu --grid 3 3 [--images 16] [--profile]

Builds the config's arm (``--arm``, default the first; untrained: the evaluation's cost does not depend
on the weights), then runs :func:`torch_bridge.evaluate.evaluate` on an ``eval.grid`` of ``--grid`` nodes
and prints its ``timing_s`` (wall s of the PSFs, the images and the RMS spot) with the sizes. ``--profile``:
one more run under cProfile (host time by function, cumulative). ``--reference``: alternate the evaluation
with the reference loop kept in ``tests/torch_bridge/_eval_reference.py`` (the node-by-node image loop as it
was before the batched one), ``--repeat`` times each, and print both timings and the largest difference of
their per-node metrics."""
from __future__ import annotations

import argparse
import cProfile
import io
import json
import pstats
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--config", default="a489_aberration")
    ap.add_argument("--preset", default="cpu")
    ap.add_argument("--arm", default=None, help="the arm (default: the config's first)")
    ap.add_argument("--device", default=None, help="override the preset's device")
    ap.add_argument("--grid", type=int, nargs=2, default=[2, 2], help="eval.grid (gy gx)")
    ap.add_argument("--chunk", type=int, default=16, help="eval.node_chunk")
    ap.add_argument("--images", type=int, default=None, help="data.eval_images (default: the preset's)")
    ap.add_argument("--crop", type=int, default=None, help="data.crop (default: the preset's)")
    ap.add_argument("--network", default=None, help="network.preset (default: the preset's)")
    ap.add_argument("--data-root", default=None, help="data.root (default: the preset's; None: bundled samples)")
    ap.add_argument("--profile", action="store_true", help="one more run under cProfile")
    ap.add_argument("--reference", action="store_true",
                    help="alternate with the reference image loop (tests/torch_bridge/_eval_reference.py)")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--threads", type=int, default=None, help="torch.set_num_threads (1: steadier timings on a "
                    "shared machine)")
    ap.add_argument("--parts", action="store_true",
                    help="time one node's image parts alone at the config's crop and eval_images (no PSF build: a "
                         "Gaussian kernel), the reference's against the batched: blur (crop by crop / one call), "
                         "noise, network (eval.batch_size batches), PSNR + SSIM of the raw and reconstructed crops "
                         "(scikit-image on the host / torch float64); --repeat times, medians")
    ap.add_argument("--out", default=None, help="write the figures as JSON here")
    a = ap.parse_args()

    import torch

    if a.threads:
        torch.set_num_threads(a.threads)
    import torch_bridge
    from torch_bridge.evaluate import evaluate
    from torch_bridge.runs import git_commit
    from torch_bridge.train import Arm, _seed_all, load_config
    over = {"eval": {"grid": list(a.grid), "node_chunk": a.chunk}, "progress": False}
    data = {}
    if a.images:
        data["eval_images"] = a.images
    if a.crop:
        data["crop"] = a.crop
    if a.data_root:
        data["root"] = a.data_root
    if data:
        over["data"] = data
    if a.network:
        over["network"] = {"preset": a.network}
    if a.device:
        over["device"] = a.device
    exp = load_config(str(Path(torch_bridge.__file__).resolve().parent / "configs" / f"{a.config}.yaml"),
                      preset=a.preset, overrides=over)
    arm_cfg = next(x for x in exp["arms"] if a.arm in (None, x["name"]))
    cfg = arm_cfg["config"]
    _seed_all(int(cfg["seed"]))
    out = Path(tempfile.mkdtemp(prefix="profile_eval_"))
    arm = Arm(arm_cfg["name"], cfg, exp["source"], out, progress=False)
    sizes = {"config": a.config, "preset": a.preset, "arm": arm.name, "device": str(arm.device),
             "grid": list(a.grid), "node_chunk": a.chunk, "eval_images": cfg["data"]["eval_images"],
             "crop": cfg["data"]["crop"], "psf_size": arm.size, "network": cfg["network"]["preset"],
             "wavelengths": sum(len(c) for c in arm.wls), "eval_batch": cfg["eval"]["batch_size"],
             "threads": torch.get_num_threads(), **git_commit()}
    print(json.dumps(sizes))
    if a.parts:
        sizes["parts"] = parts(arm, a.repeat)
        print(json.dumps(sizes["parts"], indent=1))
    ref = None
    if a.reference:
        sys.path.insert(0, str(ROOT / "tests" / "torch_bridge"))
        from _eval_reference import evaluate_reference as ref
    runs = []
    for r in range(a.repeat if not a.parts else 0):
        for name, fn in (("new", evaluate), ("reference", ref)):
            if fn is None:
                continue
            t0 = time.perf_counter()
            res = fn(arm)
            wall = time.perf_counter() - t0
            runs.append({"impl": name, "repeat": r, "wall_s": round(wall, 2), "timing_s": res["timing_s"],
                         "nodes": [{p: n[p] for p in ("raw", "rec")} for n in res["depths"][0]["nodes"]]})
            print(name, r, f"wall {wall:.2f} s", res["timing_s"], flush=True)
    if a.reference:
        new = [x for x in runs if x["impl"] == "new"][0]["nodes"]
        old = [x for x in runs if x["impl"] == "reference"][0]["nodes"]
        diff = {f"{p}.{m}": max(abs(u[p][m] - v[p][m]) for u, v in zip(new, old)) for p in ("raw", "rec")
                for m in ("psnr", "ssim")}
        print("largest |new - reference| per node:", diff)
    if a.profile:
        pr = cProfile.Profile()
        pr.enable()
        evaluate(arm)
        pr.disable()
        s = io.StringIO()
        pstats.Stats(pr, stream=s).sort_stats("cumulative").print_stats(45)
        print(s.getvalue())
    if a.out:
        Path(a.out).write_text(json.dumps({"sizes": sizes, "runs": [{k: v for k, v in x.items() if k != "nodes"}
                                                                    for x in runs]}, indent=1))


def parts(arm, repeat: int) -> dict:
    """Median wall s of one node's image parts (see --parts), each timed alone, reference and batched alternated."""
    import statistics

    import torch

    from torch_bridge.evaluate import _blur_one, _blur_patch, _device_noise, _noise
    from torch_bridge.losses import image_metrics_per_image
    sys.path.insert(0, str(ROOT / "tests" / "torch_bridge"))
    from _eval_reference import image_metrics_skimage
    cfg = arm.cfg
    ev = cfg["eval"]
    gt = arm.valid_set.fixed_crops(cfg["data"]["eval_images"], seed=ev["seed"]).to(arm.device)
    k = arm.size
    x = torch.arange(k, dtype=torch.float32) - k // 2
    ker = torch.exp(-(x[:, None] ** 2 + x[None, :] ** 2) / 8.0)
    ker = (ker / ker.sum()).expand(3, k, k).to(arm.device)
    bnd = cfg["render"]["boundary"]
    g = torch.Generator().manual_seed(0)
    sync = torch.cuda.synchronize if arm.device.type == "cuda" else (lambda: None)
    raw = _blur_one(gt, ker, bnd)
    arm.net.eval()
    with torch.no_grad():
        rec = torch.cat([arm.net(raw[i:i + ev["batch_size"]]) for i in range(0, raw.shape[0], ev["batch_size"])])
    jobs = {
        "blur_reference": lambda: _blur_patch(gt, ker[None].expand(gt.shape[0], -1, -1, -1), bnd),
        "blur_batched": lambda: _blur_one(gt, ker, bnd),
        "noise_reference": lambda: _noise(raw, ev["noise"], g),
        "noise_batched": lambda: _device_noise(raw, ev["noise"], g),
        "network": lambda: torch.cat([arm.net(raw[i:i + ev["batch_size"]])
                                      for i in range(0, raw.shape[0], ev["batch_size"])]),
        "metrics_reference": lambda: (image_metrics_skimage(raw, gt), image_metrics_skimage(rec, gt)),
        "metrics_batched": lambda: (image_metrics_per_image(raw, gt, "torch"), image_metrics_per_image(rec, gt, "torch")),
    }
    times = {name: [] for name in jobs}
    with torch.no_grad():
        for _ in range(max(1, repeat)):
            for name, fn in jobs.items():
                sync()
                t0 = time.perf_counter()
                fn()
                sync()
                times[name].append(time.perf_counter() - t0)
    arm.net.train()
    return {name: round(statistics.median(v), 4) for name, v in times.items()}


if __name__ == "__main__":
    main()
