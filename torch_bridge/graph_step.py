"""The network's training step replayed as a CUDA graph (``train.cuda_graph``; issue 25: no Python on the hot path).

On a GPU the design loop's network step (NAFNet forward, loss, backward: ~2,700 operations at the ``paper``
preset) is bound by the host launching its kernels one by one, not by the device. :class:`GraphedNetStep`
records that work once in a :class:`torch.cuda.CUDAGraph` and replays it every step: one launch instead of
thousands. What it captures has static shapes and no host reads:

* the network's forward on a static input buffer ``raw`` (B, C, H, W), which requires grad;
* the loss (:class:`~torch_bridge.losses.ReconstructionLoss` with tensor parts) against a static ``gt`` buffer;
* the backward: the network's gradients (``param.grad``, graph-owned tensors written in place by each replay) and
  the input's gradient ``raw.grad`` (computed every replay: one more backward-data convolution of the network's
  first layer and the residual's add; the optics steps need it, the others ignore it -- one capture serves both);
* the training PSNR and the four values ``[loss, mse, perceptual, psnr]`` in one (4,) tensor.

Outside the graph, eager as before: the draws, the PSFs, the rendering and noise (their inputs change shape with
the optics' plans), the copy of ``raw`` and ``gt`` into the static buffers, the optics' backward from ``raw.grad``
(an optics step), the gradient clipping and both Adam optimisers (their learning rates change every step as
Python floats; nothing of them is captured).

Rules the caller keeps (:func:`torch_bridge.train.train_step` does): the network's ``.grad`` tensors are never
set to None or replaced after the capture (``zero_grad(set_to_none=True)`` on the network is skipped: each replay
overwrites them, it does not accumulate); the network's parameters are updated in place (Adam, ``load_state_dict``
copy in place); every step has the same input shape and dtype (a different one raises). Warm-up: three
forward/backward passes on a side stream before the capture (cuDNN and the allocator settle; torch's documented
recipe), their gradients dropped. Memory: the graph's private pool keeps the step's activations between steps
(eager frees them), so the step's peak is held; :meth:`release` frees it (the design loop calls it before the
evaluation).

Precision: the network runs in its parameters' dtype (float32; the design loop uses no autocast); the PSFs'
float64 -> float32 conversion (:func:`~torch_bridge.functions.mixed_precision`) is before the graph, eager.
Adam is not captured (``capturable=True`` would make its step count and learning rate device tensors, which the
checkpoints, the portable packs and the per-step learning-rate schedule would all have to follow; on CUDA its
foreach step is ~15 operations a step against the ~4,200 captured here).

Not graphed: DDP (``group`` given: the all-reduce hooks run per bucket from Python; the step stays eager, one
note), the CPU (no graphs; the option is ignored with one note: presets are shared by CPU and GPU runs).
"""
from __future__ import annotations

import torch

__all__ = ["GraphedNetStep", "arm_graph"]


class GraphedNetStep:
    """The network's forward, loss, backward and PSNR of one training step, captured once and replayed.

    Parameters
    ----------
    net : torch.nn.Module
        The reconstruction network (on a CUDA device; its parameters' ``.grad`` become graph-owned).
    criterion : callable
        ``criterion(rec, gt, tensors=True) -> (loss, {"mse": tensor, "perceptual": tensor})`` (dimensionless,
        images in [0, 1]): :class:`~torch_bridge.losses.ReconstructionLoss`.
    warmup : int
        Eager forward/backward passes on a side stream before the capture (default 3).

    The capture happens at the first call (with that call's images), which also replays it once.
    """

    def __init__(self, net, criterion, warmup: int = 3):
        self.net, self.criterion, self.warmup = net, criterion, int(warmup)
        self.graph = None
        self.captures = 0       # captures made (1 after the first call; a test checks the graph is not re-captured)
        self.replays = 0

    def _capture(self, raw: torch.Tensor, gt: torch.Tensor):
        from torch_bridge.losses import psnr_tensor
        self.raw = torch.empty_like(raw, memory_format=torch.contiguous_format).requires_grad_(True)
        self.gt = torch.empty_like(gt, memory_format=torch.contiguous_format)
        with torch.no_grad():
            self.raw.copy_(raw)
            self.gt.copy_(gt)
        params = [p for p in self.net.parameters() if p.requires_grad]

        def body():
            rec = self.net(self.raw)
            loss, parts = self.criterion(rec, self.gt, tensors=True)
            loss.backward()
            r = rec.detach()
            vals = torch.stack([loss.detach(), parts["mse"].to(loss.dtype), parts["perceptual"].to(loss.dtype),
                                psnr_tensor(r, self.gt).to(loss.dtype)])
            return r, vals
        side = torch.cuda.Stream(device=raw.device)
        side.wait_stream(torch.cuda.current_stream(raw.device))
        with torch.cuda.stream(side):
            for _ in range(self.warmup):
                for p in params:
                    p.grad = None
                self.raw.grad = None
                body()
        torch.cuda.current_stream(raw.device).wait_stream(side)
        # the capture's backward allocates every .grad anew in the graph's pool: each replay writes them in place
        for p in params:
            p.grad = None
        self.raw.grad = None
        g = torch.cuda.CUDAGraph()
        with torch.cuda.graph(g):
            self.rec, self.vals = body()
        self.graph = g
        self.raw_grad = self.raw.grad
        self.shape, self.dtype = tuple(raw.shape), raw.dtype
        self.captures += 1

    def __call__(self, raw: torch.Tensor, gt: torch.Tensor):
        """One replay on ``raw`` (the rendered images, (B, C, H, W), any grad) and ``gt`` (their targets, same
        shape). Returns ``(rec, values, raw_grad)``: the reconstruction (a copy: the next replay overwrites the
        static one), ``values`` (4,) ``[loss, mse, perceptual, psnr_dB]`` (a copy, on the device) and the loss's
        gradient with respect to ``raw`` (the static buffer: use it before the next call). The network's
        gradients are in its parameters' ``.grad``."""
        if self.graph is None:
            if raw.device.type != "cuda" or gt.device != raw.device:
                raise ValueError(f"GraphedNetStep needs CUDA images and targets on one card, got {raw.device} and "
                                 f"{gt.device}")
            with torch.cuda.device(raw.device):      # the capture's stream and pool on the images' card
                self._capture(raw, gt)
        else:
            if tuple(raw.shape) != self.shape or raw.dtype != self.dtype or tuple(gt.shape) != self.shape:
                raise ValueError(f"GraphedNetStep was captured for images {self.shape} {self.dtype}; got "
                                 f"{tuple(raw.shape)} {raw.dtype} and targets {tuple(gt.shape)} (train.cuda_graph "
                                 "needs the same shapes every step)")
            with torch.no_grad():
                self.raw.copy_(raw)
                self.gt.copy_(gt)
        with torch.cuda.device(self.raw.device):
            self.graph.replay()
        self.replays += 1
        return self.rec.clone(), self.vals.clone(), self.raw_grad

    def release(self):
        """Free the graph and its pool (the network's ``.grad`` are set to None); the next call captures anew."""
        if self.graph is None:
            return
        for p in self.net.parameters():
            p.grad = None
        self.graph = self.raw = self.gt = self.rec = self.vals = self.raw_grad = None


def arm_graph(arm, group=None):
    """The :class:`GraphedNetStep` of ``arm`` (:class:`torch_bridge.train.Arm`) when ``train.cuda_graph`` is on and
    the step can be graphed (a CUDA device, one process), made at the first call and kept as ``arm.net_graph``;
    else None. Off the GPU or under DDP (``group`` given) the option is ignored: one warning and one line in
    ``arm.notes`` (``result.json``), once an arm."""
    if not arm.cfg["train"].get("cuda_graph"):
        return None
    if getattr(arm, "net_graph", None) is not None:
        return arm.net_graph
    why = None
    if arm.device.type != "cuda":
        why = f"train.cuda_graph ignored on device {arm.device} (CUDA graphs need a CUDA device): the step runs eager"
    elif group is not None:
        why = ("train.cuda_graph ignored in a distributed run (DDP's all-reduce hooks run from Python per bucket): "
               "the step runs eager")
    if why is not None:
        if not getattr(arm, "graph_noted", False):
            import warnings
            arm.graph_noted = True
            arm.notes.append(why)
            warnings.warn(why, UserWarning, stacklevel=3)
        return None
    arm.net_graph = GraphedNetStep(arm.net, arm.criterion)
    return arm.net_graph
