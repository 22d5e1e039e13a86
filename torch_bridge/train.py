"""End-to-end hybrid lens design: joint optimisation of lens, DOE and reconstruction network.

``train(config)`` runs an experiment (one or more *arms*, each a lens design method followed by
network training and evaluation) and writes its table; ``main(argv)`` is the ``rwwarp design
CONFIG`` command line. A config is a YAML or TOML file (or a dict) validated before anything
runs (:func:`load_config`); errors name the key (``arms[1].train.lr_network``) and the file.

Per arm:

1. **Design stage** (``design.method``): ``fixed`` (the lens as loaded, e.g. a blank DOE),
   ``paraxial_achromat`` (analytic Fresnel-phase DOE and refocus, :func:`design.paraxial_achromat`),
   ``rms`` (the "Zemax" arm: the learning quantities minimise the polychromatic RMS spot radius of
   the ray model, :class:`design.RaySpot`), or ``e2e`` (the optics learn with the network below).
   ``design.init`` may first set the DOE to the paraxial achromat (``paraxial_achromat``) or run the
   RMS-spot design from it (``rms``: an e2e design that starts where the "Zemax" arm ends).
2. **Joint phase** (``train.joint_steps``): each step draws image crops and, per colour channel, one
   of its wavelengths (and one depth); computes the RGB PSFs of the nodes (ray-wave, or the
   paraxial-wave model), converts them to float32 (:class:`MixedPrecision`), blurs the crops,
   reconstructs them with the NAFNet and minimises ``MSE + alpha * perceptual``; the optics
   (``e2e`` only) and the network have their own Adam optimisers and learning rates.
3. **Fine-tune phase** (``train.finetune_steps``): the optics are frozen; the network is trained on
   images with sensor noise (``train.noise``).
4. **Evaluation**: ray-wave PSFs with the three wavelengths of each channel averaged, fixed
   validation crops with seeded noise, PSNR / SSIM / 1-LPIPS of the raw and reconstructed images
   per depth and node (the training nodes, or the denser ``eval.grid`` of ``gy x gx`` nodes over the
   same region, whose fields are cached ``eval.node_chunk`` nodes at a time); the ray-model RMS spot
   radius on axis, at the outer node and averaged.

Fabrication limit (``optics.min_feature_um``, default none): after every optics update the DOE is
scaled onto its smallest allowed feature (the narrowest quantisation step over the aperture,
:meth:`HybridLens.limit_doe_feature`; counted in ``result.json`` as ``feature_projections``), and
cached plans sample that limit, so a DOE growing up to it never forces a replan.

Rendering (``render.mode``): ``patch`` (each crop is a patch of the sensor at one PSF node,
blurred by that node's PSF at the native pixel pitch: cheap, and the blur has its real size) or
``full`` (the crop covers the node grid's region and is blurred with a spatially varying PSF,
:func:`torch_bridge.imaging.spatially_varying_blur`). ``train.cuda_graph`` (CUDA, one process; default off): the
network's forward, loss, backward and PSNR are one replayed CUDA graph (:mod:`torch_bridge.graph_step`).

Outputs in ``out_dir/<arm>/``: ``metrics.csv`` (one row per logged step), ``step_XXXXXX.png``
(PSF map, DOE phase, raw and reconstructed crops), ``checkpoint.pt`` (everything needed to resume:
step, optics and network weights, optimiser states, every RNG state, the cached sampling plans),
``lens.json`` (the designed lens), ``network.pt``, ``result.json``; in ``out_dir``: ``table.md``,
``table.csv``, ``summary.json`` and ``designs.png``.
Resuming (the default when a checkpoint exists) continues exactly where the run stopped: the next
step is the same as in an uninterrupted run.
Runs that survive interruption (:mod:`torch_bridge.runs`): ``--detach`` (background, own session,
``run.log``, ``run.pid``), ``progress.json`` (replaced atomically), ``rwwarp design status RUN_DIR``,
``rwwarp design pack RUN_DIR`` (a portable checkpoint in parts of <= 15 MiB) and ``--resume PACK``; each
process adds a segment (commit, card, steps, wall time) to ``result["run"]``. An arm whose
``result.json`` is complete is kept when the experiment runs again (``--fresh`` trains it again).
"""
from __future__ import annotations

import copy
import csv
import json
import math
import random
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch

from torch_bridge.config import (  # noqa: F401
    parse_overrides,
    CONFIG_DIR,
    DEFAULTS,
    SCHEMA,
    ConfigError,
    _budget_bytes,
    _depth_tag,
    _depth_value,
    _feature_mm,
    _json_default,
    _learn_dict,
    _preflight,
    _refractive_learns,
    build_lens,
    load_config,
    resolve_config,
    validate_config,
)
from torch_bridge.budget import memory_gb as _memory_gb, over_budget, torch_gb as _torch_gb
from torch_bridge.evaluate import (_blur_patch, _device_noise, _eval_provider, _psf_kernels, eval_share,
                                   evaluate_arm, objective)
from torch_bridge.report import _designs_figure, _snapshot, write_table
from torch_bridge.runs import rng_state as _rng_state, set_rng_state as _set_rng_state, truncate_csv as _truncate_csv
from torch_bridge.runs import CSV_FIELDS as _CSV_FIELDS, provider_gb as _provider_gb, read_row as _read  # noqa: F401

__all__ = [
    "DEFAULTS",
    "ConfigError",
    "load_config",
    "main",
    "resolve_config",
    "train",
    "train_arm",
    "validate_config",
]


# ============================================================================================== helpers
def _seed_all(seed: int):
    random.seed(seed)
    np.random.seed(seed % (2 ** 32))
    torch.manual_seed(seed)


def _lr_factor(kind, step, total):
    if kind == "none" or total <= 1:
        return 1.0
    return 0.5 * (1.0 + math.cos(math.pi * min(step, total) / total)) * 0.9 + 0.1


# ============================================================================================== one arm
class Arm:
    """State of one arm (lens module, provider, network, optimisers) built from a resolved config."""

    def __init__(self, name: str, cfg: dict, source, out_dir: Path, progress: bool = True):
        import torch_bridge as tb
        from torch_bridge import design as dz
        from torch_bridge.data import ImageSet
        from torch_bridge.losses import LPIPS, ReconstructionLoss
        from torch_bridge.network import build_network
        self.name, self.cfg, self.out = name, cfg, out_dir
        self.progress = progress and cfg["progress"]
        self.device = torch.device(cfg["device"])
        o = cfg["optics"]
        self.lens0 = build_lens(cfg, source)
        method = cfg["design"]["method"]
        self.method = method
        learn = _learn_dict(o["learn"]) if method in ("e2e", "rms") else {}
        self.learn = learn
        self.live = _refractive_learns(learn, self.lens0)
        lens = self.lens0
        if cfg["design"]["init"] in ("paraxial_achromat", "rms") or method == "paraxial_achromat":
            lens = self._achromat(lens)
        self.lens_init = lens
        self.module = tb.HybridLens(lens, learn=learn, nyquist_safety=o["nyquist_safety"],
                                    rays_per_sample=o["rays_per_sample"], method=o["propagation"],
                                    focal_patch_tol=o["focal_patch_tol"],
                                    deterministic=o["deterministic"], pixel_values=o["pixel_values"],
                                    estimate_model_error=o["model_error_estimate"]).to(self.device)
        self.pixel_mm = (o["pixel_um"] * 1e-3) if o["pixel_um"] else lens.sensor.pixel_pitch
        self.size = int(o["psf_size"])
        self.wls = [[float(w) for w in c] for c in o["wavelengths_um"]]
        self.wl_ref = self.wls[len(self.wls) // 2][len(self.wls[0]) // 2]
        self.depths = [_depth_value(d) for d in o["depths_mm"]]
        nd = o["nodes"]
        half = nd["half_size_mm"] or [0.5 * lens.sensor.resolution[0] * lens.sensor.pixel_pitch,
                                      0.5 * lens.sensor.resolution[1] * lens.sensor.pixel_pitch]
        if cfg["render"]["mode"] == "full":
            from torch_bridge.imaging import node_positions
            H = W = cfg["data"]["crop"]
            gy, gx = nd["grid"]
            cy, cx = (H / 2.0, W / 2.0) if nd["region"] == "full" else (float(H), 0.0)
            self.positions = [((c + 0.5 - cx) * self.pixel_mm, (cy - r - 0.5) * self.pixel_mm)
                              for r in node_positions(gy, H) for c in node_positions(gx, W)]
            self.grid = (gy, gx)
        else:
            self.positions = dz.node_positions_mm(nd["layout"], half, nd["grid"], nd["fractions"], nd["region"])
            self.grid = None
        self.fields = dz.field_angles(lens, self.positions, self.wl_ref)
        self.provider = self._provider(o["model"])
        # data, network, losses
        d = cfg["data"]
        self.train_set = ImageSet(d["root"], "train", d["crop"], d["scale"], d["max_images"], d["linearize"])
        self.valid_set = ImageSet(d["root"], "valid", d["crop"], d["scale"], d["max_images"], d["linearize"])
        n = cfg["network"]
        self.net = build_network(n["preset"], 3, width=n["width"], enc_blocks=n["enc_blocks"],
                                 middle_blocks=n["middle_blocks"], dec_blocks=n["dec_blocks"],
                                 zero_init=n["zero_init"]).to(self.device)
        lo = cfg["loss"]
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            self.criterion = ReconstructionLoss(lo["alpha"], lo["perceptual"], lo["vgg_weights"], lo["fallback"],
                                                lo["fallback_alpha"])
        self.notes = [str(w.message) for w in caught]
        if self.criterion.perceptual.active_kind != lo["perceptual"]:
            self.notes.append(f"perceptual term: {self.criterion.perceptual.active_kind} with weight "
                              f"{self.criterion.alpha:g} (loss.fallback_alpha)")
        for w in caught:
            warnings.warn(w.message, UserWarning, stacklevel=2)
        self.criterion.to(self.device)
        self.lpips = None
        if lo["lpips_weights"] and lo["vgg_weights"] and Path(lo["lpips_weights"]).is_file() \
                and Path(lo["vgg_weights"]).is_file():
            self.lpips = LPIPS(lo["vgg_weights"], lo["lpips_weights"])
        t = cfg["train"]
        self.opt_net = torch.optim.Adam(self.net.parameters(), lr=t["lr_network"])
        groups = [{"params": [getattr(self.module, q)], "lr": float(t["lr_optics"].get(q, 0.0)), "name": q}
                  for q in learn if q in t["lr_optics"]] if method == "e2e" else []
        missing = [q for q in learn if q not in t["lr_optics"]] if method == "e2e" else []
        if missing:
            raise ConfigError(f"arm {name}: 'train.lr_optics' has no learning rate for {missing}")
        self.opt_optics = torch.optim.Adam(groups) if groups else None
        self.gen = torch.Generator().manual_seed(int(cfg["seed"]))
        self.step = 0
        self.design_done = False
        self.rms_log = []
        self.feature_projections = 0
        self.objective_initial = None
        self.last_psf = None
        # wall time and machine segments across resumes (checkpointed; :meth:`begin_segment`)
        self.wall_prev = 0.0
        self.segments_prev = []
        self._seg = None
        self._seg_t0 = None
        self.resumed_without_optimizer = False

    # ------------------------------------------------------------------ optics
    def _achromat(self, lens):
        from torch_bridge.ray_spot import with_paraxial_achromat
        return with_paraxial_achromat(lens, [w for c in self.cfg["optics"]["wavelengths_um"] for w in c])

    def _provider(self, model, module=None):
        from torch_bridge import design as dz
        o = self.cfg["optics"]
        module = module or self.module
        cache = o["cache_fields"]
        if cache == "auto" or self.method != "e2e":
            # frozen refractive part during training (every method but e2e with lens quantities)
            cache = not (self.method == "e2e" and self.live)
        if model == "paraxial-wave" or cache:
            return dz.CachedProvider(module, self.fields, self.size, self.pixel_mm, model=model,
                                     wavelength_ref_um=self.wl_ref, doe_budget_cpmm=o["doe_budget_cpmm"],
                                     memory_budget_bytes=_budget_bytes(o), min_feature_mm=_feature_mm(o),
                                     cache_precision=o["cache_precision"], cache_device=o["cache_device"])
        tile = record = None
        if o["memory_budget_gb"]:
            # a tile's recorded sources take half the budget; the network's activations and the allocator's
            # slack the other half (as a cached provider's step: CachedProvider.step_budget_bytes). A packed
            # tile (every member in the slots of the largest) is held to the same half.
            # The tile is what one recorded source of the outer field takes with its propagation's output side
            # (what torch_bridge.packed.packed_recorded_bytes counts a packed member): a tile that fits is then one
            # packed tile, not one of the budget's size less a member that runs alone.
            record = int(o["memory_budget_gb"] * 1e9 / 2)
            probe = module.raywave(self.fields[-1:], [self.wls[-1][0]], self.size, pixel_mm=self.pixel_mm)
            tile = max(1, record // max(1, module.bytes_per_source(probe) + module.output_bytes_per_source(probe)))
        return dz.LiveProvider(module, self.fields, self.size, self.pixel_mm, wavelength_ref_um=self.wl_ref,
                               tile=tile, memory_budget_bytes=_budget_bytes(o), replan_every=o["live_replan_every"],
                               pack=o["live_pack"], record_budget_bytes=record, replan_rule=o["live_replan_rule"],
                               replan_drift=o["live_replan_drift"], replan_drift_hard=o["live_replan_drift_hard"],
                               replan_spread=o["live_replan_spread"], pack_waste=o["live_pack_waste"])

    def limit_feature(self) -> float:
        """After an optics update: project the DOE onto ``optics.min_feature_um`` (a learning DOE only;
        :meth:`HybridLens.limit_doe_feature`). Counts the projections in :attr:`feature_projections`;
        returns the scale applied (1.0: none needed or no limit)."""
        mf = _feature_mm(self.cfg["optics"])
        if mf is None or "doe" not in self.learn:
            return 1.0
        c = self.module.limit_doe_feature(mf)
        if c < 1.0:
            self.feature_projections += 1
        return c

    def optics_learn(self) -> bool:
        return self.method == "e2e" and self.opt_optics is not None

    def psfs(self, wls, depth, grad: bool):
        """(n_nodes, 3, k, k) float64 PSFs (sensor orientation)."""
        if grad:
            return self.provider.psfs(wls, depth)
        with torch.no_grad():
            return self.provider.psfs(wls, depth)

    # ------------------------------------------------------------------ design stage
    def run_design(self):
        """RMS-spot optimisation (``design.method: rms``, or ``design.init: rms`` before an e2e design:
        the paraxial achromat, then the RMS-spot design, then end to end); nothing otherwise."""
        if (self.method != "rms" and self.cfg["design"]["init"] != "rms") or self.design_done:
            self.design_done = True
            return
        from torch_bridge.design import RaySpot, paraxial_efl
        r = self.cfg["design"]["rms"]
        lrs = r["lr"]
        missing = [q for q in self.learn if q not in lrs]
        if missing:
            raise ConfigError(f"arm {self.name}: 'design.rms.lr' has no learning rate for {missing}")
        opt = torch.optim.Adam([{"params": [getattr(self.module, q)], "lr": float(lrs[q])} for q in self.learn])
        wls = r["wavelengths_um"] or [c[len(c) // 2] for c in self.wls]
        spot = RaySpot(self.module, self.fields, wls, grid=r["grid"])
        efl_mm, efl_w = self.cfg["design"]["efl_mm"], self.cfg["design"]["efl_weight"]
        it = range(r["steps"])
        if self.progress:
            from tqdm.auto import tqdm
            it = tqdm(it, desc=f"{self.name}: RMS spot", unit="step", leave=False)
        for k in it:
            opt.zero_grad()
            rms = spot.rms()
            loss = (rms ** 2).mean() * 1e6  # um^2
            if efl_mm and efl_w:
                loss = loss + efl_w * (paraxial_efl(self.module, self.wl_ref) - efl_mm) ** 2
            loss.backward()
            opt.step()
            self.limit_feature()
            self.rms_log.append({"step": k, "rms_um": float(rms.detach().mean() * 1e3), "loss": float(loss.detach())})
        self.provider = self._provider(self.cfg["optics"]["model"])
        self.design_done = True

    # ------------------------------------------------------------------ run segments
    def begin_segment(self, info: dict):
        """Start a segment of this arm's run in this process (after a resume, if any): ``info`` (commit,
        card, host) is recorded with the first step and, at each checkpoint, the last step and the wall
        time (s) of the segment."""
        from torch_bridge.runs import _utc
        self._seg = {**info, "start_step": self.step, "started_utc": _utc()}
        self._seg_t0 = time.perf_counter()

    def segments(self) -> list:
        """Every segment of this arm so far (earlier processes from the checkpoint, then this one)."""
        if self._seg is None:
            return list(self.segments_prev)
        return list(self.segments_prev) + [dict(self._seg, end_step=self.step,
                                                wall_s=round(time.perf_counter() - self._seg_t0, 3))]

    def wall_total(self) -> float:
        """Wall time (s) of this arm over all its segments (design stage, training, checkpoints)."""
        return self.wall_prev + (time.perf_counter() - self._seg_t0 if self._seg_t0 is not None else 0.0)

    # ------------------------------------------------------------------ checkpoint
    def state(self) -> dict:
        """Everything needed to resume (a dict for :func:`torch.save`)."""
        return {"step": self.step, "design_done": self.design_done, "module": self.module.state_dict(),
                "net": self.net.state_dict(), "opt_net": self.opt_net.state_dict(),
                "opt_optics": None if self.opt_optics is None else self.opt_optics.state_dict(),
                "rng": _rng_state(self.gen), "rms_log": self.rms_log,
                "feature_projections": self.feature_projections, "objective_initial": self.objective_initial,
                "last_psf": self.last_psf, "wall_s": self.wall_total(), "segments": self.segments(),
                "plans": {f"{k[0]}|{k[1]}": v for k, v in getattr(self.provider, "plans", {}).items()}}

    def save(self, path: Path):
        """Write :meth:`state` to ``path`` atomically (a temporary file, then a rename)."""
        tmp = path.with_suffix(".tmp")
        torch.save(self.state(), tmp)
        tmp.replace(path)

    def load(self, path: Path):
        """Restore the state saved by :meth:`save` (or a portable checkpoint written back by
        :func:`torch_bridge.runs.unpack`: without the network's Adam state, Adam restarts from zero
        moments and :attr:`resumed_without_optimizer` is set)."""
        st = torch.load(path, map_location="cpu", weights_only=False)
        self.step = int(st["step"])
        self.design_done = bool(st["design_done"])
        self.module.load_state_dict(st["module"])
        self.net.load_state_dict(st["net"])
        if st.get("opt_net") is not None:
            self.opt_net.load_state_dict(st["opt_net"])
        else:
            self.resumed_without_optimizer = True
            self.notes.append(f"resumed at step {self.step} without the network's Adam state (portable checkpoint): "
                              "Adam restarted from zero moments")
        self.wall_prev = float(st.get("wall_s", 0.0))
        self.segments_prev = list(st.get("segments", []))
        if self.opt_optics is not None and st["opt_optics"] is not None:
            self.opt_optics.load_state_dict(st["opt_optics"])
        self.rms_log = st.get("rms_log", [])
        self.feature_projections = st.get("feature_projections", 0)
        self.objective_initial = st.get("objective_initial")
        self.last_psf = None if st.get("last_psf") is None else st["last_psf"].to(self.module.thickness_base.device)
        self.provider = self._provider(self.cfg["optics"]["model"])
        plans = st.get("plans") or {}
        if plans and hasattr(self.provider, "load_plans"):
            def key(s):
                w, d = s.split("|")
                return (float(w), None if d == "None" else float(d))
            self.provider.load_plans({key(k): v for k, v in plans.items()})
        _set_rng_state(st["rng"], self.gen)


def train_step(arm: Arm, step: int, psf_cache: dict, group=None, lazy: bool = False) -> dict:
    """One training step up to the gradients (no optimiser step): the draws (all from the arm's
    generator, in a fixed order), the PSFs, the rendering, the loss and its backward pass. Returns
    ``phase``, ``optics_step``, ``loss`` (float: the whole batch's), ``parts`` (``mse``, ``perceptual``),
    ``psnr``, ``lr_factor`` and, for snapshots, ``psf``, ``gt``, ``raw``, ``rec`` (this rank's crops; detached, so
    nothing of the step's graph outlives it). ``lazy`` (one process): ``loss``, ``parts`` and ``psnr`` are 0-d
    device tensors, not floats (a float is a host read, which waits for the device; the design loop reads them at
    its log steps, :func:`_read`).

    ``train.cuda_graph`` (CUDA, one process): the network's forward, loss, backward and PSNR are a replayed CUDA
    graph (:mod:`torch_bridge.graph_step`); the network's ``.grad`` are then the graph's, never set to None here.

    ``group`` (:class:`torch_bridge.distributed.Group`, None in one process): every rank draws the
    whole batch and trains on its slice; PSF nodes are shared out and their optics gradients
    all-reduced; the network must be wrapped by ``group.ddp`` (done here). The images take the
    network's dtype (float32: the PSFs go through :func:`~torch_bridge.functions.mixed_precision`)."""
    from torch_bridge.functions import mixed_precision
    from torch_bridge.imaging import spatially_varying_blur
    from torch_bridge.graph_step import arm_graph
    from torch_bridge.losses import psnr, psnr_tensor
    cfg = arm.cfg
    t_cfg = cfg["train"]
    B = cfg["data"]["batch_size"]
    n_nodes = len(arm.fields)
    total = t_cfg["joint_steps"] + t_cfg["finetune_steps"]
    net_dtype = next(arm.net.parameters()).dtype
    phase = "joint" if step < t_cfg["joint_steps"] else "finetune"
    # ---- draws (all from the arm's generator, in a fixed order; every rank draws the whole batch)
    choice = [int(torch.randint(len(c), (1,), generator=arm.gen)) for c in arm.wls]
    wls = [c[k] for c, k in zip(arm.wls, choice)]
    depth = arm.depths[int(torch.randint(len(arm.depths), (1,), generator=arm.gen))]
    gt = arm.train_set.sample(B, arm.gen)                                # the whole batch's crops, on the host
    perm = torch.randperm(n_nodes, generator=arm.gen)
    nodes = [int(perm[b % n_nodes]) for b in range(B)]
    noisy = phase == "finetune" or t_cfg["noise_in_joint"]
    # ---- optics
    optics_step = phase == "joint" and arm.optics_learn() and step % t_cfg["optics_every"] == 0
    own = None
    if optics_step:
        if group is None:
            psf = arm.psfs(wls, depth, grad=True)
        else:
            own, psf, own_nodes = group.psfs(arm, wls, depth)
        psf_cache.clear()
        arm.last_psf = psf.detach()
    elif phase == "joint" and arm.optics_learn() and arm.last_psf is not None:
        # between optics updates the network sees the PSFs of the last update (no extra forward)
        psf = arm.last_psf
    else:
        # frozen optics: single-wavelength PSFs cached, a channel combination is a stack of them
        per = []
        for w in wls:
            if (w, depth) not in psf_cache:
                psf_cache[(w, depth)] = arm.psfs([w], depth, grad=False)[:, 0]
            per.append(psf_cache[(w, depth)])
        psf = torch.stack(per, 1)
    if psf.dtype == torch.float64 and net_dtype == torch.float32:
        psf_img = mixed_precision(psf)
    else:
        psf_img = psf.to(net_dtype)
    kern = _psf_kernels(psf_img).to(arm.device)
    # ---- rendering, network and loss: this rank's slice of the batch (each crop is blurred and noised alone, and
    # the noise draws are made for the whole batch, so a slice gets the values the whole batch has there)
    sl = slice(0, B) if group is None else group.batch_slice(B)
    gt = gt[sl].to(arm.device, net_dtype)
    if cfg["render"]["mode"] == "patch":
        raw = _blur_patch(gt, kern[nodes[sl]], cfg["render"]["boundary"])
    else:
        gy, gx = arm.grid
        raw = spatially_varying_blur(gt, kern.reshape(gy, gx, 3, arm.size, arm.size),
                                     boundary=cfg["render"]["boundary"])
    if noisy:
        raw = _device_noise(raw, t_cfg["noise"], arm.gen, batch=B, rows=sl)
    net = arm.net if group is None else group.ddp(arm.net)
    graphed = arm_graph(arm, group)
    lazy = lazy and group is None
    f = _lr_factor(t_cfg["lr_decay"], step, total)
    for g in arm.opt_net.param_groups:
        g["lr"] = t_cfg["lr_network"] * f
    if graphed is None:
        arm.opt_net.zero_grad(set_to_none=True)
    if arm.opt_optics is not None:
        arm.opt_optics.zero_grad(set_to_none=True)
    if graphed is None:
        rec = net(raw)
        loss, parts = arm.criterion(rec, gt, tensors=lazy)
    else:
        # the network's forward, loss, backward (its .grad and raw's gradient) and PSNR: one graph replay
        rec, vals, g_raw = graphed(raw, gt)
        loss, parts = vals[0], {"mse": vals[1], "perceptual": vals[2]}
    efl = term = None
    if optics_step and cfg["design"]["efl_mm"] and cfg["design"]["efl_weight"] and (group is None or group.rank == 0):
        from torch_bridge.design import paraxial_efl
        term = cfg["design"]["efl_weight"] * (paraxial_efl(arm.module, arm.wl_ref).to(loss.dtype) -
                                              cfg["design"]["efl_mm"]) ** 2
        loss = loss + (term if graphed is None else term.detach())
        efl = term.detach() if lazy else float(term.detach())
    if graphed is None:
        loss.backward()
        p_snr = psnr_tensor(rec.detach(), gt) if lazy else psnr(rec.detach(), gt)
        loss_f = loss.detach() if lazy else float(loss.detach())
    else:
        # the optics' backward from the graph's gradient of raw (an optics step), and the EFL term's
        roots, grads = [], []
        if optics_step and raw.requires_grad:
            roots, grads = [raw], [g_raw]
        if term is not None:
            roots, grads = roots + [term], grads + [torch.ones_like(term)]
        if roots:
            torch.autograd.backward(roots, grads)
        loss_f, p_snr = loss.detach(), vals[3]
        if not lazy:   # the four values in one host read
            loss_f, mse, per_, p_snr = torch.stack([loss_f.double(), *vals[1:].double()]).tolist()
            parts = {"mse": mse, "perceptual": per_}
    efl = 0.0 if efl is None else efl
    if group is not None:
        if optics_step:
            group.optics_backward(arm, own, psf, own_nodes)
        img, mse, per_, p_snr = group.mean(loss_f - efl, parts["mse"], parts["perceptual"], p_snr)
        efl = group.broadcast(efl)
        loss_f, parts = img + efl, {"mse": mse, "perceptual": per_}
    # detached: the caller keeps the result until the next step's returns (the design loop's ``s``), and a tensor with
    # its graph would keep the step's recorded tapes alive until then (a TraceSplat node holds its Warp tape, the
    # rays and their gradients, after its backward: the kept last chunk's, up to the live provider's record share)
    return {"phase": phase, "optics_step": optics_step, "loss": loss_f, "parts": parts, "psnr": p_snr,
            "lr_factor": f, "psf": psf.detach(), "gt": gt, "raw": raw.detach(), "rec": rec.detach()}


def train_arm(name: str, cfg: dict, source=None, out_dir=None, resume: bool = True, progress: bool = True,
              group=None, progress_file=None, run_info=None) -> dict:
    """Run one arm (design stage, joint phase, fine-tune phase, evaluation); returns its result dict
    (also written to ``out_dir/result.json``). ``resume``: continue from ``out_dir/checkpoint.pt``.

    ``progress_file`` (:class:`torch_bridge.runs.ProgressFile`, optional): updated every
    ``train.log_every`` steps and at each phase change (step, phase, steps/s, ETA in s, last loss and
    PSNR, peak GPU memory in GB). ``run_info`` (dict: commit, card, host): recorded with each segment of
    the run (a segment: the steps done by one process; a resumed run adds one) in ``result["run"]``.

    ``group`` (:class:`torch_bridge.distributed.Group`): one rank of a distributed run (see
    :mod:`torch_bridge.distributed`); rank 0 alone writes files and evaluates, the other ranks
    return their result without ``eval``."""
    from torch_bridge.design import CachedProvider
    out = Path(out_dir)
    lead = group is None or group.rank == 0
    if lead:
        out.mkdir(parents=True, exist_ok=True)
    _seed_all(int(cfg["seed"]))
    if group is not None:
        cfg = dict(cfg, device=group.device(cfg["device"]))
    arm = Arm(name, cfg, source, out, progress and lead)
    ck = out / "checkpoint.pt"
    csv_path = out / "metrics.csv"
    t_cfg = cfg["train"]
    total = t_cfg["joint_steps"] + t_cfg["finetune_steps"]
    if group is not None:
        group.batch_slice(cfg["data"]["batch_size"])       # a multiple of the ranks, checked before work
        resume_now = group.broadcast(bool(resume and ck.exists()))   # rank 0 decides, before anyone writes
    else:
        resume_now = resume and ck.exists()
    if resume_now:
        arm.load(ck)
        if lead:
            _truncate_csv(csv_path, arm.step, _CSV_FIELDS)
    elif lead:
        for f in out.glob("step_*.png"):
            f.unlink()
        if csv_path.exists():
            csv_path.unlink()
    if run_info is None:
        from torch_bridge.runs import device_info, git_commit
        run_info = {**git_commit(), **device_info(arm.device)}
    arm.begin_segment(run_info)
    pf = progress_file if lead else None
    joint = t_cfg["joint_steps"]

    def report(state, phase, **kw):
        if pf is None:
            return
        peak = None
        if arm.device.type == "cuda":
            peak = round(torch.cuda.max_memory_allocated(arm.device) / 1e9, 3)
        pf.update(state=state, arm=name, phase=phase, step=arm.step, steps_total=total, joint_steps=joint,
                  arm_wall_s=round(arm.wall_total(), 1), peak_gpu_gb=peak, **pf.rate(arm.step, total), **kw)
    t0 = time.perf_counter()
    over = False          # warned that the memory in use exceeded optics.memory_budget_gb (once an arm)
    if pf is not None:
        pf.start_arm(arm.step)
        pf.rec["checkpoint_step"] = arm.step if resume_now else None
    if not arm.design_done:
        report("running", "design")
        arm.run_design()
        if isinstance(arm.provider, CachedProvider) and arm.provider.model == "ray-wave":
            # the training provider is the evaluation's too: its fields serve both
            arm.provider.prepare(sorted({w for c in arm.wls for w in c}), arm.depths, progress=arm.progress)
        if lead:
            # another model's provider is released while the evaluation's fields are held, and filled after
            arm.objective_initial = objective(arm, _eval_provider(arm))
            arm.save(ck)
            if pf is not None:
                pf.update(checkpoint_step=arm.step, step=arm.step)
    if isinstance(arm.provider, CachedProvider):
        allw = sorted({w for c in arm.wls for w in c})
        arm.provider.prepare(allw, arm.depths, progress=arm.progress)
    fcsv = writer = None
    if lead:
        new_csv = not csv_path.exists()
        fcsv = open(csv_path, "a", newline="")
        writer = csv.DictWriter(fcsv, fieldnames=_CSV_FIELDS)
        if new_csv:
            writer.writeheader()
    stop_after = t_cfg["stop_after"]
    from rwwarp.wave.backend import get_backend
    fft_backend = get_backend(arm.module.rw_device)   # its FFT plan builds go into the metrics
    psf_cache = {}
    it = range(arm.step, total)
    if arm.progress:
        from tqdm.auto import tqdm
        it = tqdm(it, desc=f"{name}", unit="step", initial=arm.step, total=total)
    last = None
    try:
        for step in it:
            s = train_step(arm, step, psf_cache, group, lazy=True)
            phase, optics_step, f = s["phase"], s["optics_step"], s["lr_factor"]
            if t_cfg["grad_clip"]:
                torch.nn.utils.clip_grad_norm_(arm.net.parameters(), t_cfg["grad_clip"])
            arm.opt_net.step()
            if optics_step:
                for g in arm.opt_optics.param_groups:
                    g["lr"] = float(t_cfg["lr_optics"][g["name"]]) * _lr_factor(t_cfg["lr_decay"], step,
                                                                               t_cfg["joint_steps"])
                arm.opt_optics.step()
                arm.limit_feature()
                ev = cfg["optics"]["check_sampling_every"]
                if ev and hasattr(arm.provider, "check_sampling") and (step // t_cfg["optics_every"]) % ev == 0:
                    arm.provider.check_sampling()
            arm.step = step + 1
            last = {"step": step, "phase": phase, "loss": s["loss"], "mse": s["parts"]["mse"],
                    "perceptual": s["parts"]["perceptual"], "psnr_train": s["psnr"],
                    "lr_network": t_cfg["lr_network"] * f, "optics_step": int(optics_step),
                    "wall_s": time.perf_counter() - t0, "replans": getattr(arm.provider, "replans", 0),
                    "memory_gb": _memory_gb(arm.device), **_torch_gb(arm.device),
                    "fft_plans_built": fft_backend.fft_plans_built, **_provider_gb(arm.provider)}
            msg = None if over else over_budget(last["memory_gb"], cfg["optics"]["memory_budget_gb"],
                                                f"design arm {name!r}, step {step} ({last['replans']} replans)")
            if msg:
                over = True
                warnings.warn(msg, RuntimeWarning, stacklevel=2)   # shown by default (ResourceWarning is not)
                report("running", phase, memory_over_budget=msg)
            # the step's values are device tensors until a log step reads them (one host read, which waits for the
            # device: none on the other steps; the progress bar's figures are the last log step's)
            if step % t_cfg["log_every"] == 0 or arm.step in (joint, total):
                last = _read(last)
                if arm.progress:
                    it.set_postfix(loss=f"{last['loss']:.4f}", psnr=f"{last['psnr_train']:.2f}", phase=phase,
                                    refresh=False)
            if lead and (step % t_cfg["log_every"] == 0 or arm.step == total):
                writer.writerow(last)
                fcsv.flush()
            if pf is not None and (step % t_cfg["log_every"] == 0 or arm.step in (joint, total)):
                report("running", "joint" if arm.step < joint else "finetune",
                       loss=last["loss"], psnr_train=last["psnr_train"], memory_gb=last["memory_gb"])
            if lead and t_cfg["image_every"] and (step % t_cfg["image_every"] == 0 or arm.step == total):
                _snapshot(arm, out / f"step_{step:06d}.png", s["psf"], s["gt"], s["raw"], s["rec"], step, phase)
            boundary = arm.step == t_cfg["joint_steps"] or arm.step == total
            if lead and ((t_cfg["checkpoint_every"] and arm.step % t_cfg["checkpoint_every"] == 0) or boundary):
                arm.save(ck)
                if pf is not None:
                    pf.update(checkpoint_step=arm.step, step=arm.step)
            if stop_after is not None and arm.step >= stop_after:
                if lead:
                    arm.save(ck)
                    if pf is not None:
                        pf.update(checkpoint_step=arm.step, step=arm.step)
                break
    finally:
        if fcsv is not None:
            fcsv.close()
        if getattr(arm, "net_graph", None) is not None:
            arm.net_graph.release()       # its pool (the step's activations) is not held through the evaluation
            arm.net_graph = None
    last = _read(last)
    result = {"arm": name, "method": arm.method, "steps_done": arm.step, "steps_total": total,
              "train_wall_s": time.perf_counter() - t0, "last": last, "notes": arm.notes,
              "run": {**run_info, "steps_done": arm.step, "steps_total": total, "joint_steps": joint,
                      "finetune_steps": t_cfg["finetune_steps"], "seed": int(cfg["seed"]),
                      "wall_s_total": round(arm.wall_total(), 3), "segments": arm.segments(),
                      "resumed_without_optimizer": arm.resumed_without_optimizer},
              "replans": getattr(arm.provider, "replans", 0),
              "feature_projections": arm.feature_projections,
              "replan_log": getattr(arm.provider, "replan_log", []),
              "field_build": getattr(arm.provider, "build_log", []),
              "step_log": getattr(arm.provider, "step_log", [])[-8:]}
    if group is not None:
        result["world_size"] = group.size
    if arm.step < total or not lead:
        if arm.step < total:
            result["stopped_early"] = True
        elif group is not None:
            eval_share(arm, group)     # this rank's share of the evaluation grid's PSFs, gathered by the lead
        return result
    report("evaluating", "eval")
    evaluate_arm(arm, result, out, report, default=_json_default, group=group)
    report("running", "done")
    return result


# ============================================================================================== experiment
def train(config, preset: str | None = None, arms=None, out_dir=None, resume: bool = True,
          progress: bool | None = None, group=None, overrides: dict | None = None) -> dict:
    """Run an experiment: validate the config (``config``: path or dict, ``preset``: a key of its
    ``presets``), then every arm (or those named in ``arms``) in order, then write the table and the
    comparison figure. Returns ``{arm: result}``. ``out_dir`` overrides the config's; default
    ``out/design/<experiment>[_<preset>]``. ``overrides``: keys set in every arm after the preset
    (:func:`torch_bridge.config.parse_overrides`, the command line's ``--set``).

    Under ``torchrun`` (``WORLD_SIZE`` > 1) or with ``group``, each arm runs on all ranks
    (:mod:`torch_bridge.distributed`); rank 0 writes the outputs, the other ranks return ``{}``."""
    exp = load_config(config, preset, overrides)
    owned = False
    if group is None:
        from torch_bridge.distributed import current_group
        was = torch.distributed.is_available() and torch.distributed.is_initialized()
        group = current_group(str(exp["base"]["device"]))
        owned = group is not None and not was
    try:
        return _train(exp, preset, arms, out_dir, resume, progress, group)
    finally:
        if owned and torch.distributed.is_initialized():
            # the group this call made ends with it: NCCL's communicators are freed, not leaked at exit
            torch.distributed.destroy_process_group()


def _train(exp: dict, preset, arms, out_dir, resume, progress, group) -> dict:
    """The body of :func:`train` once the config is loaded and the group (or None) is known."""
    base = exp["base"]
    out = run_folder(exp, preset, out_dir)
    chosen = exp["arms"] if arms is None else [a for a in exp["arms"] if a["name"] in set(arms)]
    if arms is not None and len(chosen) != len(set(arms)):
        known = [a["name"] for a in exp["arms"]]
        raise ConfigError(f"unknown arm(s) {sorted(set(arms) - set(known))}; the config has {known}")
    _preflight(chosen, out)  # nothing is written before the data, the device and the output folder check out
    lead = group is None or group.rank == 0
    if lead:
        out.mkdir(parents=True, exist_ok=True)
        (out / "config_resolved.json").write_text(json.dumps(exp, indent=1, default=_json_default))
    results = {}
    pf = None
    if lead:
        from torch_bridge.runs import ProgressFile, device_info, git_commit
        pf = ProgressFile(out / "progress.json", experiment=exp["experiment"], preset=preset,
                          arms=[a["name"] for a in chosen], arms_total=len(chosen))
        info = {**git_commit(), **device_info(base["device"] if group is None else group.device(base["device"])),
                "ranks": 1 if group is None else group.size}
    try:
        for i, a in enumerate(chosen):
            cfg = copy.deepcopy(a["config"])
            if progress is not None:
                cfg["progress"] = bool(progress)
            total = cfg["train"]["joint_steps"] + cfg["train"]["finetune_steps"]
            done = _finished_result(out / a["name"], total) if resume else None
            if done is not None:
                # finished in an earlier process (possibly on another machine): kept, not evaluated again
                results[a["name"]] = done
                continue
            if pf is not None:
                pf.rec.update(arm_index=i)
            results[a["name"]] = train_arm(a["name"], cfg, exp["source"], out / a["name"], resume=resume,
                                           progress=cfg["progress"], group=group, progress_file=pf,
                                           run_info=info if lead else None)
    except BaseException as e:
        if pf is not None:
            stopped = isinstance(e, (KeyboardInterrupt, SystemExit))
            pf.update(state="stopped" if stopped else "failed",
                      error=(f"stopped ({type(e).__name__} {e})" if stopped else f"{type(e).__name__}: {e}"))
        raise
    if not lead:
        return {}
    # include arms finished earlier (other invocations) in the table
    for a in exp["arms"]:
        if a["name"] not in results and (out / a["name"] / "result.json").exists():
            results[a["name"]] = json.loads((out / a["name"] / "result.json").read_text())
    order = [a["name"] for a in exp["arms"] if a["name"] in results]
    results = {k: results[k] for k in order}
    if any("eval" in r for r in results.values()):
        write_table(results, out, base["description"] or exp["experiment"], preset)
        _designs_figure(results, out)
    tmp = out / ".summary.json.tmp"
    tmp.write_text(json.dumps(results, indent=1, default=_json_default))
    tmp.replace(out / "summary.json")
    if pf is not None and chosen:
        unfinished = [k for k in (a["name"] for a in chosen) if "eval" not in results.get(k, {})]
        pf.update(state="stopped" if unfinished else "done", phase="done" if not unfinished else pf.rec.get("phase"),
                  unfinished_arms=unfinished, eta_s=None if unfinished else 0.0)
    return results


def run_folder(exp: dict, preset=None, out_dir=None) -> Path:
    """The run folder of a loaded experiment ``exp`` (:func:`load_config`): ``out_dir``, else the
    config's ``out_dir``, else ``out/design/<experiment>[_<preset>]``."""
    base = exp["base"]
    return Path(out_dir or base["out_dir"] or f"out/design/{exp['experiment']}" + (f"_{preset}" if preset else ""))


def _finished_result(arm_dir: Path, total: int):
    """The ``result.json`` of a finished arm (evaluated, ``steps_total`` equal to ``total``), else None."""
    f = arm_dir / "result.json"
    if not f.exists():
        return None
    try:
        r = json.loads(f.read_text())
    except ValueError:
        return None
    return r if "eval" in r and r.get("steps_done") == r.get("steps_total") == total else None


def main(argv=None) -> int:
    """``rwwarp design ...``: the command line (:func:`torch_bridge.command.main`)."""
    from torch_bridge.command import main as command_main
    return command_main(argv)


if __name__ == "__main__":
    sys.exit(main())
