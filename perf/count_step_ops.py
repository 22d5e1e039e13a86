"""Operations one design step of the cooke_hybrid ``e2e`` arm dispatches, by stage, on the CPU (issue 25).

    python perf/count_step_ops.py [--tag before|after] [--out perf/results/step_ops_cpu.json] [--steps 2]

On a GPU the gpu preset's joint step is bound by its launches (~15,650 kernels and copies a step, 36 % of the
wall time busy: perf/results/session16_h200x4/README.md). Each aten operation of the step is about one GPU kernel,
each Warp launch, copy or memset one more, and each wave-backend enqueue one more; this script counts them on the
CPU, where the same Python runs, at the gpu preset's *structure*:

* the preset's e2e arm as ``torch_bridge.train.train_arm`` steps it: ``train_step`` (draws, live PSFs of the 16
  nodes x 3 colours = 48 focal sources, packed tiles of 7 sources as the preset's memory budget gives on the GPU,
  render, the ``paper`` NAFNet (width 32, 28 blocks in the last encoder stage), loss, backward), the network's
  gradient clip, both Adam steps with their learning rates, the DOE feature limit, and the metrics row;
* sizes cut so that a step takes seconds on two cores: PSFs ``--psf`` px (preset: 63), crops ``--crop`` px
  (preset: 256; batch 8 kept), ``nyquist_safety`` 1 and ``rays_per_sample`` 0.5 (preset 1.5 and 1.2). The counts
  depend on the structure (sources, tiles, network blocks, batch), not on these sizes, except where a size changes
  the structure: the focal operators' groups (``focal_groups``: members stacked by their window sizes) and the
  Gauss node counts, reported with the counts;
* where torch_bridge takes another path on CUDA than on the CPU the CUDA one is taken here: the per-image blur is
  batched (``evaluate._blur_patch``: one call on CUDA, one per image on the CPU) and the optimisers and the gradient
  clip use torch's multi-tensor (``foreach``) kernels (their default on CUDA, not on the CPU).

Counted per stage (each timed step after the warm-up; the last one's breakdown saved):

* ``aten``: every aten operation dispatched (a ``TorchDispatchMode``; forward and backward, views included) and
  ``aten_kernels``: those that launch work on a GPU (views, reshapes, ``empty`` and ``detach`` left out);
* ``warp``: ``warp.launch`` calls (the tape's adjoint replays included), ``warp.copy`` calls and array
  ``zero_``/``fill_`` calls (memsets on a GPU), and ``upload``: calls of ``torch_bridge.functions.upload`` naming a
  device (a host-to-device copy on a GPU; none on the CPU);
* ``backend``: wave-backend (OpenCL on the CPU, CuPy on CUDA) kernel enqueues, FFTs and GEMMs, and the calls of
  the packed focal operators (``backend_focal_*``: built, moved to a distance, applied forward / adjoint /
  distance derivative). Those run in numpy on the CPU and in CuPy on CUDA, where each call is several kernels
  (matrix products, element-wise work); the numpy operations themselves are not counted (see the README).

Backward operations are put in the stage whose forward created their autograd node (the node's sequence number
against the ones taken at the stage boundaries); nodes made during the backward (the live tiles' checkpoint
recompute) count as optics.
"""
from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from collections import Counter, defaultdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

# aten operations that launch nothing on a GPU (metadata, views, allocation without initialisation)
NO_KERNEL = {
    "view", "_unsafe_view", "as_strided", "reshape", "t", "transpose", "permute", "expand", "squeeze", "unsqueeze",
    "select", "slice", "detach", "alias", "empty", "empty_like", "empty_strided", "lift_fresh", "set_", "resize_",
    "view_as_real", "view_as_complex", "_reshape_alias", "unbind", "split", "split_with_sizes", "chunk",
    "unflatten", "flatten", "diagonal", "narrow", "movedim", "_conj", "conj", "real", "imag", "_neg_view",
    "expand_as", "view_as", "_has_compatible_shallow_copy_type", "is_same_size", "_local_scalar_dense",
    "new_empty", "new_empty_strided", "numpy_T", "mT", "adjoint", "_to_copy_noop", "lift_fresh_copy",
    "sym_size", "sym_stride", "sym_numel", "sym_storage_offset", "dim", "size", "stride", "is_contiguous",
}
STAGES = ["draws", "optics_fwd", "render_fwd", "net_fwd", "loss_fwd", "net_bwd", "loss_bwd", "render_bwd",
          "optics_bwd", "metrics", "grad_clip", "opt_net", "opt_optics", "optics_post", "other"]


class Counts:
    """Per-stage counters of aten ops, Warp launches/copies/memsets and backend enqueues, with the stage set by
    :meth:`stage` and the backward's ops attributed by their autograd node's sequence number."""

    def __init__(self):
        self.cur = "other"
        self.off = False            # True while the stage probe runs (its ops are not counted)
        self.bounds = []            # [(first sequence number, stage)] of the forward stages, in order
        self.params = {}            # id(leaf tensor) -> stage, for AccumulateGrad
        self.reset()

    def reset(self):
        self.aten, self.kern, self.warp, self.backend = Counter(), Counter(), Counter(), Counter()
        self.names = defaultdict(Counter)
        self.bounds = []

    def stage(self, name):
        """Enter forward stage ``name`` (its autograd nodes start at the next sequence number)."""
        import torch
        self.off = True
        try:
            with torch.enable_grad():
                probe = torch.zeros((), requires_grad=True) * 1.0
        finally:
            self.off = False
        self.bounds.append((probe.grad_fn._sequence_nr() + 1, name))
        self.cur = name

    def where(self):
        """The stage of the operation now being dispatched."""
        import torch
        node = torch._C._current_autograd_node()
        if node is None:
            return self.cur
        name = type(node).__name__
        if name == "AccumulateGrad":
            return self.params.get(id(node.variable), "optics_bwd")
        seq = node._sequence_nr()
        got = None
        for first, st in self.bounds:
            if seq >= first:
                got = st
        if got is None or got in ("backward", "metrics", "grad_clip", "opt_net", "opt_optics", "optics_post"):
            return "optics_bwd"        # a node made during the backward: the live tiles' recompute
        return {"optics_fwd": "optics_bwd", "render_fwd": "render_bwd", "net_fwd": "net_bwd",
                "loss_fwd": "loss_bwd", "draws": "optics_bwd"}.get(got, got)


def install(counts):
    """Patch warp.launch / copy / array.zero_ / fill_ and the wave backends' enqueues to count into ``counts``;
    returns the undo function."""
    import warp as wp

    from rwwarp.wave import backend as B
    lock = threading.Lock()
    undo = []

    def wrap(owner, name, key):
        orig = getattr(owner, name)

        def f(*a, **k):
            with lock:
                (counts.backend if key.startswith("backend") else counts.warp)[counts.where() + "|" + key] += 1
            return orig(*a, **k)
        setattr(owner, name, f)
        undo.append((owner, name, orig))
    wrap(wp, "launch", "launch")
    wrap(wp, "copy", "copy")
    wrap(wp.array, "zero_", "memset")
    wrap(wp.array, "fill_", "memset")
    for cls in {type(b) for b in [B.get_backend("cpu")]} | {c for c in vars(B).values()
                                                           if isinstance(c, type) and issubclass(c, B.Backend)}:
        for name in ("launch", "_fft", "gemm"):
            if name in vars(cls):
                wrap(cls, name, f"backend_{name.strip('_')}")

    # the packed focal operators' calls (numpy on the CPU; on CUDA each is a set of CuPy kernels: matrix products
    # and element-wise work): built (__init__: a new tile's group), moved to a distance, applied
    from rwwarp.wave.focal_packed import PackedFocalPropagator as P
    for name in ("__init__", "at_distance", "forward", "forward_pair", "adjoint", "adjoint_pair",
                 "distance_derivative", "distance_derivative_pair"):
        wrap(P, name, "backend_focal_" + name.strip("_"))
    # torch_bridge.functions.upload: host data to the module's device (a host-to-device copy on a GPU, none on the
    # CPU, where it only wraps the array): counted where a device is named, through the profiler hook (the function
    # is imported by name into several modules)
    from torch_bridge import functions as TF
    code = TF.upload.__code__
    prev = sys.getprofile()

    def prof(frame, event, arg):
        if event == "call" and frame.f_code is code and frame.f_locals.get("device") is not None:
            with lock:
                counts.warp[counts.where() + "|upload"] += 1
    sys.setprofile(prof)

    def restore():
        sys.setprofile(prev)
        for owner, name, orig in reversed(undo):
            setattr(owner, name, orig)
    return restore


class AtenCounter:
    """A TorchDispatchMode that counts every aten op into ``counts`` by stage."""

    def __init__(self, counts):
        from torch.utils._python_dispatch import TorchDispatchMode
        c = counts

        class Mode(TorchDispatchMode):
            def __torch_dispatch__(self, func, types, args=(), kwargs=None):
                if c.off:
                    return func(*args, **(kwargs or {}))
                st = c.where()
                name = func.__name__.split(".")[0]
                c.aten[st] += 1
                if name.rstrip("_") not in NO_KERNEL and name not in NO_KERNEL:
                    c.kern[st] += 1
                    c.names[st][name] += 1
                return func(*args, **(kwargs or {}))
        self.mode = Mode()

    def __enter__(self):
        self.mode.__enter__()
        return self

    def __exit__(self, *exc):
        return self.mode.__exit__(*exc)


def build(a):
    """The arm (gpu preset's e2e arm at the reduced sizes, on the CPU)."""
    import torch_bridge
    from torch_bridge.train import Arm, _seed_all, load_config
    exp = load_config(str(Path(torch_bridge.__file__).resolve().parent / "configs" / "cooke_hybrid.yaml"),
                      preset="gpu")
    arm_cfg = next(x for x in exp["arms"] if x["name"] == "e2e")
    cfg = dict(arm_cfg["config"], device="cpu", progress=False)
    cfg["optics"] = dict(cfg["optics"], psf_size=a.psf, nyquist_safety=1.0, rays_per_sample=a.rays)
    cfg["data"] = dict(cfg["data"], crop=a.crop)
    cfg["network"] = dict(cfg["network"], preset=a.network)
    _seed_all(int(cfg["seed"]))
    arm = Arm("e2e", cfg, exp["source"], Path("unused"), progress=False)
    arm.provider.tile = a.tile      # the tile the gpu preset's budget gives on the GPU (7 sources)
    return arm, cfg


def cuda_structure(arm):
    """The CUDA paths where torch_bridge's differ by device: the batched per-image blur and foreach optimisers."""
    import torch

    from torch_bridge import evaluate, train
    from torch_bridge.imaging import spatially_varying_blur

    def blur_batched(images, kernels, boundary):
        return spatially_varying_blur(images, kernels, boundary=boundary, per_image=True)
    evaluate._blur_patch = train._blur_patch = blur_batched
    for opt in (arm.opt_net, arm.opt_optics):
        if opt is not None:
            for g in opt.param_groups:
                g["foreach"] = True
    orig = torch.nn.utils.clip_grad_norm_

    def clip(params, max_norm, **kw):
        return orig(params, max_norm, foreach=True, **kw)
    return clip


def run_step(arm, cfg, step, counts, clip):
    """One step as ``torch_bridge.train.train_arm`` runs it, the stages marked in ``counts``."""
    import torch

    from torch_bridge import train as T
    t_cfg = cfg["train"]
    psfs, forward, crit = arm.psfs, arm.net.forward, arm.criterion.forward
    import torch_bridge.losses as L
    psnr = L.psnr

    def psfs_m(*x, **k):
        counts.stage("optics_fwd")
        out = psfs(*x, **k)
        counts.stage("render_fwd")
        return out

    def forward_m(*x, **k):
        counts.stage("net_fwd")
        return forward(*x, **k)

    def crit_m(*x, **k):
        counts.stage("loss_fwd")
        return crit(*x, **k)

    def psnr_m(*x, **k):
        counts.stage("metrics")
        return psnr(*x, **k)
    backward = torch.Tensor.backward

    def backward_m(self, *x, **k):
        counts.stage("backward")       # nodes made from here on: the live tiles' recompute (optics)
        return backward(self, *x, **k)
    arm.psfs, arm.net.forward, arm.criterion.forward, L.psnr = psfs_m, forward_m, crit_m, psnr_m
    torch.Tensor.backward = backward_m
    try:
        counts.params = {id(p): "net_bwd" for p in arm.net.parameters()}
        counts.params.update({id(p): "optics_bwd" for p in arm.module.parameters()})
        counts.stage("draws")
        s = T.train_step(arm, step, {}, None)
        counts.stage("grad_clip")
        if t_cfg["grad_clip"]:
            clip(arm.net.parameters(), t_cfg["grad_clip"])
        counts.stage("opt_net")
        arm.opt_net.step()
        counts.stage("opt_optics")
        if s["optics_step"]:
            for g in arm.opt_optics.param_groups:
                g["lr"] = float(t_cfg["lr_optics"][g["name"]]) * T._lr_factor(t_cfg["lr_decay"], step,
                                                                             t_cfg["joint_steps"])
            arm.opt_optics.step()
            counts.stage("optics_post")
            arm.limit_feature()
        counts.stage("metrics")
        row = {"loss": s["loss"], "psnr": s["psnr"], "replans": getattr(arm.provider, "replans", 0),
               "memory_gb": T._memory_gb(arm.device), **T._torch_gb(arm.device), **T._provider_gb(arm.provider)}
        counts.stage("other")
        return row
    finally:
        arm.psfs, arm.net.forward, arm.criterion.forward, L.psnr = psfs, forward, crit, psnr
        torch.Tensor.backward = backward


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tag", default="current", help="key of this run in the JSON (e.g. before, after)")
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent / "results" / "step_ops_cpu.json"))
    ap.add_argument("--steps", type=int, default=2, help="counted steps after the warm-up step")
    ap.add_argument("--psf", type=int, default=15)
    ap.add_argument("--crop", type=int, default=32)
    ap.add_argument("--rays", type=float, default=0.5)
    ap.add_argument("--tile", type=int, default=7)
    ap.add_argument("--network", default="paper")
    ap.add_argument("--pack-waste", type=float, default=None,
                    help="the live provider's pack_waste (default: its own, 1.5): members stacked into one focal "
                         "operator while padding grows their work by at most this factor (fewer groups: fewer "
                         "operator calls, more padded work)")
    ap.add_argument("--top", type=int, default=12, help="most frequent aten ops listed per stage")
    a = ap.parse_args(argv)
    import torch
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    arm, cfg = build(a)
    if a.pack_waste is not None:
        arm.provider.pack_waste = float(a.pack_waste)
    clip = cuda_structure(arm)
    counts = Counts()
    restore = install(counts)
    steps = []
    try:
        for k in range(a.steps + 1):
            prov = arm.provider
            made0 = getattr(prov, "plans_made", 0)
            counts.reset()
            t = time.perf_counter()
            if k == 0:
                run_step(arm, cfg, k, counts, clip)     # warm-up: plans, kernel builds (counted, not kept)
                print(f"warm-up step {time.perf_counter() - t:.1f} s", flush=True)
                continue
            with AtenCounter(counts):
                row = run_step(arm, cfg, k, counts, clip)
            wall = time.perf_counter() - t
            per = {}
            for st in STAGES:
                w = {key.split("|")[1]: n for key, n in counts.warp.items() if key.split("|")[0] == st}
                b = {key.split("|")[1]: n for key, n in counts.backend.items() if key.split("|")[0] == st}
                if counts.aten[st] or w or b:
                    per[st] = {"aten": counts.aten[st], "aten_kernels": counts.kern[st], "warp": w, "backend": b,
                               "top": counts.names[st].most_common(a.top)}
            focal = sum(n for key, n in counts.backend.items() if "|backend_focal_" in key)
            tot = {"aten": sum(counts.aten.values()), "aten_kernels": sum(counts.kern.values()),
                   "warp": sum(counts.warp.values()), "backend": sum(counts.backend.values()) - focal,
                   "focal_operator_calls": focal}
            # each counted operation one launch (a lower bound on a GPU: see the module docstring); the focal
            # operators' calls (several CuPy kernels each) apart
            tot["launch_estimate"] = tot["aten_kernels"] + tot["warp"] + tot["backend"]
            steps.append({"step": k, "wall_s": round(wall, 2), "plans_made": getattr(prov, "plans_made", 0) - made0,
                          "total": tot, "stages": per, "loss": row["loss"]})
            print(f"step {k}: {wall:.1f} s (counting), plans made {steps[-1]['plans_made']}, totals {tot}", flush=True)
            for st, v in per.items():
                print(f"  {st:12s} aten {v['aten']:6d} kernels {v['aten_kernels']:6d} warp {v['warp']} "
                      f"backend {v['backend']}", flush=True)
    finally:
        restore()
    prov = arm.provider
    # the last call's packed tiles: members and focal-operator groups each (each group one set of operator calls)
    tiles = [(len(t[1].members), len(t[1].groups)) for t in getattr(prov, "_packed", {}).values()]
    from _common import git_commit
    rec = {"commit": git_commit(), "machine": "CPU (2 shared cores), torch threads 1",
           "config": "cooke_hybrid gpu preset, e2e arm", "sizes": {"psf_size": a.psf, "crop": a.crop,
                                                                  "batch": cfg["data"]["batch_size"],
                                                                  "rays_per_sample": a.rays, "nyquist_safety": 1.0,
                                                                  "network": a.network, "live_tile": a.tile,
                                                                  "pack_waste": arm.provider.pack_waste},
           "sources_per_step": 3 * len(arm.fields), "tiles_members_and_groups": tiles,
           "wall_s_total": round(time.perf_counter() - t0, 1), "steps": steps}
    out = Path(a.out)
    data = json.loads(out.read_text()) if out.exists() else {}
    data[a.tag] = rec
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(data, indent=1) + "\n")
    print("written", out, "key", a.tag)


if __name__ == "__main__":
    main()
