"""End-to-end design on ``torch.distributed`` (gloo on CPUs, NCCL on GPUs), launched by ``torchrun`` or
``rwwarp design CONFIG --procs N`` (torch's launcher, :func:`rwwarp.distributed.launch`).

What is split, and how one step stays the single-process step (same seed, any number of ranks):

* **Draws.** Every rank draws the whole batch (crops, wavelengths, depth, nodes, noise) from the
  arm's generator in the same order, so the generators stay in step and a checkpoint holds the
  state of any rank. Rank ``r`` trains on its contiguous slice of ``batch_size / world_size``
  crops (``data.batch_size`` must be a multiple of the number of ranks).
* **PSF nodes.** On an optics step each rank computes the PSFs of its contiguous share of the nodes
  (with gradients; a frozen-refractive design, :class:`~torch_bridge.design.CachedProvider`: each node
  is propagated with its entry's plan, exactly as in one process), the shares are all-gathered
  into the full PSF tensor ``P`` (a leaf), every rank renders and reconstructs its crops, the
  gradients ``dL/dP`` are all-reduced (mean over ranks, as DDP averages the network's), each rank
  back-propagates its own nodes' share into the optics, and the optics gradients are all-reduced
  (sum). A design whose refractive part learns (:class:`~torch_bridge.design.LiveProvider`) shares
  its nodes the same way: focal sources are planned one by one, so a share's PSFs and gradients are
  those of the one-process step (band-limited ASM sources are planned per chunk of the share).
* **Network.** :class:`torch.nn.parallel.DistributedDataParallel` (gradients averaged over ranks).
* **Outputs.** Rank 0 alone writes the CSV, snapshots, checkpoints (the full state: a run resumes
  on any number of ranks), the evaluation, the table and the figures.

Equal slices make the mean of the ranks' losses the full batch's loss (MSE and the perceptual terms
are batch means), so the loss and gradients equal the single-process step's up to the order of
floating-point reductions (measured in ``tests/torch_bridge/test_distributed_design.py``).

NCCL (``cuda:LOCAL_RANK``): run on 2 H200s (``perf/results/distributed_gpu_h200x2.json``): the
``cooke_hybrid`` gpu preset's joint step took 24.1 s on one GPU and 12.0 s on two, with the same losses
over three steps (float32 network: 1.2e-6 relative at the third).
"""
from __future__ import annotations

import math
import os

import torch

__all__ = ["Group", "current_group"]


def current_group(device: str = "cpu", timeout_s: float | None = None):
    """A :class:`Group` when this process is one of several (``WORLD_SIZE`` > 1 or an initialised
    process group), else None. Initialises the process group if needed (gloo on the CPU, NCCL for
    CUDA; ``timeout_s`` for every collective)."""
    from rwwarp.distributed import DEFAULT_TIMEOUT_S, init_group
    ws = int(os.environ.get("WORLD_SIZE", "1") or 1)
    if ws <= 1 and not (torch.distributed.is_available() and torch.distributed.is_initialized()):
        return None
    dist = init_group(device, timeout_s or DEFAULT_TIMEOUT_S)
    if dist.get_world_size() <= 1:
        return None
    return Group(dist)


class Group:
    """The ranks of a distributed design run and the collectives of one training step."""

    def __init__(self, dist):
        self.dist = dist
        self.rank, self.size = dist.get_rank(), dist.get_world_size()
        self.local_rank = int(os.environ.get("LOCAL_RANK", "0"))
        self._ddp = None

    # ------------------------------------------------------------------ setup
    def device(self, device: str) -> str:
        """This rank's device: ``cuda[:K]`` -> ``cuda:LOCAL_RANK``, else unchanged."""
        return f"cuda:{self.local_rank}" if str(device).startswith("cuda") else str(device)

    def barrier(self):
        self.dist.barrier()

    def broadcast(self, obj):
        """``obj`` of rank 0 on every rank."""
        box = [obj]
        self.dist.broadcast_object_list(box, src=0)
        return box[0]

    def ddp(self, net):
        """``net`` wrapped in DistributedDataParallel (once; the wrapper shares the module's weights)."""
        if self._ddp is None or self._ddp.module is not net:
            from torch.nn.parallel import DistributedDataParallel
            dev = next(net.parameters()).device
            self._ddp = DistributedDataParallel(net, device_ids=[dev.index] if dev.type == "cuda" else None)
        return self._ddp

    def batch_slice(self, batch: int) -> slice:
        """This rank's contiguous share of a batch (``batch`` a multiple of the number of ranks)."""
        if batch % self.size:
            raise ValueError(f"data.batch_size {batch} is not a multiple of the {self.size} ranks")
        n = batch // self.size
        return slice(self.rank * n, (self.rank + 1) * n)

    def node_share(self, n_nodes: int, provider) -> tuple:
        """(first node, node count per rank) of this rank's share: contiguous shares of
        ``ceil(n / ranks)`` nodes for the ray-wave providers (cached and live); all nodes on rank 0
        otherwise."""
        from torch_bridge.design import CachedProvider, LiveProvider
        if isinstance(provider, (CachedProvider, LiveProvider)):
            c = max(1, math.ceil(n_nodes / self.size))
            return min(self.rank * c, n_nodes), c
        return (0 if self.rank == 0 else n_nodes), n_nodes

    # ------------------------------------------------------------------ PSFs
    def own_psfs(self, arm, wls, depth):
        """(my nodes, len(wls), k, k) float64 PSFs of this rank's nodes, with gradients."""
        from torch_bridge.design import CachedProvider, LiveProvider
        p = arm.provider
        n = len(arm.fields)
        lo, c = self.node_share(n, p)
        hi = min(lo + c, n)
        if hi <= lo:
            return torch.zeros((0, len(wls), arm.size, arm.size), dtype=torch.float64, device=arm.device)
        if isinstance(p, LiveProvider):
            return p.psfs(wls, depth, nodes=slice(lo, hi))
        if not isinstance(p, CachedProvider):
            return p.psfs(wls, depth)
        return _cached_share(p, wls, depth, lo // c, c)

    def gather_psfs(self, own, n_nodes: int, c: int):
        """The full (n_nodes, ...) tensor from every rank's share (detached), padded to ``c`` nodes a rank
        for the all-gather."""
        pad = torch.zeros((c,) + tuple(own.shape[1:]), dtype=own.dtype, device=own.device)
        pad[:own.shape[0]] = own.detach()
        parts = [torch.empty_like(pad) for _ in range(self.size)]
        self.dist.all_gather(parts, pad)
        return torch.cat(parts, 0)[:n_nodes]

    def psfs(self, arm, wls, depth):
        """(own PSFs with their graph, full PSF leaf that collects dL/dP, node range of own)."""
        n = len(arm.fields)
        lo, c = self.node_share(n, arm.provider)
        own = self.own_psfs(arm, wls, depth)
        if c >= n:  # one rank computes everything: broadcast it
            full = own.detach().clone() if self.rank == 0 else torch.empty(
                (n, len(wls), arm.size, arm.size), dtype=torch.float64, device=arm.device)
            self.dist.broadcast(full, src=0)
        else:
            full = self.gather_psfs(own, n, c)
        leaf = full.detach().requires_grad_(True)
        return own, leaf, slice(lo, lo + own.shape[0])

    def optics_backward(self, arm, own, leaf, nodes: slice):
        """After each rank's ``loss.backward()``: mean of the ranks' ``dL/dP`` (DDP's convention), this
        rank's share back-propagated into the optics, optics gradients summed over the ranks."""
        g = leaf.grad if leaf.grad is not None else torch.zeros_like(leaf)
        self.dist.all_reduce(g)
        g /= self.size
        if own.shape[0] and own.requires_grad:
            own.backward(g[nodes])
        for grp in arm.opt_optics.param_groups:
            for prm in grp["params"]:
                if prm.grad is None:
                    prm.grad = torch.zeros_like(prm)
                self.dist.all_reduce(prm.grad)

    # ------------------------------------------------------------------ logging
    def mean(self, *values: float) -> list:
        """Means over the ranks of per-rank floats (float64)."""
        # NCCL reduces device tensors only
        dev = torch.device("cuda", self.local_rank) if self.dist.get_backend() == "nccl" else torch.device("cpu")
        t = torch.tensor(values, dtype=torch.float64, device=dev)
        self.dist.all_reduce(t)
        return (t / self.size).tolist()


def _cached_share(p, wls, depth, part: int, c: int):
    """PSFs of one share of the nodes of a :class:`~torch_bridge.design.CachedProvider` (the ``part``-th
    chunk of ``c`` nodes): exactly what ``CachedProvider.psfs(..., chunk=c)`` computes for those nodes."""
    return p.psfs(wls, depth, chunk=c, part=part)
