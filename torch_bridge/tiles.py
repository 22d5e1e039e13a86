"""The one tiling and checkpoint loop of the torch bridge: :func:`run_tiles`.

:meth:`torch_bridge.HybridLens.psf_map` (tiles of sources), :class:`torch_bridge.live.LiveProvider` (chunks of
sources, planned as the loop reaches them) and :class:`torch_bridge.design.CachedProvider` (propagation chunks
of a cached entry, and focal nodes) all compute a list of tiles whose outputs are stacked along the first axis,
each tile a function of the same learning tensors. With more than one tile and a gradient wanted each tile is a
checkpoint (:class:`torch_bridge.functions.Recompute`): its forward runs without a tape, and again under a fresh
tape in the backward pass, so the peak memory is one tile's whatever the tile count (each tile's forward runs
exactly twice). What the callers differ in (when to checkpoint, the host-table cache of one call, what they log
per tile, the packed tiles) stays with them: the checkpoint decision is an argument, the rest lives in their
``run`` closures and the ``after`` hook.
"""
from __future__ import annotations

import functools

import torch

__all__ = ["RecordedOnce", "run_tiles", "wants_grad"]


class RecordedOnce(torch.autograd.Function):
    """The last tile of :func:`run_tiles` with ``keep_last``: ``RecordedOnce.apply(run, *tensors)`` records
    ``run(*tensors, record=True)`` in the forward pass (run once, not recomputed) and keeps its graph (the Warp tapes
    of its trace and splat: rays and their gradients) only until its backward has run: freed there, not with the
    caller's graph, so the checkpointed tiles recomputed after it in the backward pass do not find it still held
    (a recorded tile of a learning lens can take the record share of a design step's budget alone). A second
    backward raises (``retain_graph`` is not supported)."""

    @staticmethod
    def forward(ctx, run, *tensors):
        ts = [t.detach().requires_grad_(t.requires_grad) for t in tensors]
        with torch.enable_grad():
            out = run(*ts, record=True)
        ctx.graph = (out, ts)
        return out.detach()

    @staticmethod
    def backward(ctx, grad_out):
        if ctx.graph is None:
            raise RuntimeError("run_tiles: the recorded last tile's backward ran twice; its graph is freed after one "
                               "(retain_graph is not supported)")
        out, ts = ctx.graph
        ctx.graph = None
        need = [t for t in ts if t.requires_grad]
        got = iter(torch.autograd.grad(out, need, grad_out, allow_unused=True)) if need else iter(())
        return (None, *[next(got) if t.requires_grad else None for t in ts])


def wants_grad(tensors) -> bool:
    """True when autograd records and one of ``tensors`` requires a gradient."""
    return torch.is_grad_enabled() and any(t.requires_grad for t in tensors)


def run_tiles(tiles, run, tensors, *, checkpoint: bool | None = None, progress: str | None = None,
              total: int | None = None, after=None, unit: str = "tile", keep_last: bool = False) -> torch.Tensor:
    """Outputs of ``run(tile, *tensors, record=...)`` for every tile of ``tiles``, concatenated along the first
    axis (one tile: its output itself).

    ``tiles``: a sequence or an iterable (a generator may plan each tile when the loop reaches it: tile ``k+1``
    is asked for after tile ``k`` ran and its ``after`` hook returned). ``tensors``: the tensors the tiles
    depend on and gradients flow to (a tile must read them only through its arguments). ``checkpoint``: each
    tile a :class:`~torch_bridge.functions.Recompute` when a gradient is wanted (:func:`wants_grad`); None
    (default): when there is more than one tile (a sequence's length, else ``total``). Without a checkpoint a
    tile runs with ``record=torch.is_grad_enabled()``. ``progress``: a tqdm bar with this description (its
    ``unit``; ``total`` for an iterable). ``after(tile, out)``: called after each tile's forward (the caller's
    per-tile logging). ``keep_last``: with checkpoints, the last tile is recorded as it runs, not checkpointed
    (its forward runs once, :class:`RecordedOnce`): its tape lives from its forward to its backward, which comes first
    in the backward pass, and is freed there, before the other tiles are recomputed, so the peak is one recorded tile
    beside whatever the caller runs between (a design step's network, which the caller's budget gives the other
    share: :class:`torch_bridge.live.LiveProvider`); the tile count must be known (a sequence, or ``total``). The
    backward pass then runs once (``retain_graph`` is not supported)."""
    from .functions import Recompute
    tensors = list(tensors)
    n = len(tiles) if hasattr(tiles, "__len__") else total
    if checkpoint is None:
        if n is None:
            raise ValueError("run_tiles: checkpoint=None needs the tile count (a sequence, or total=)")
        checkpoint = n > 1
    ckpt = bool(checkpoint) and wants_grad(tensors)
    it = tiles
    if progress:
        from tqdm.auto import tqdm
        it = tqdm(tiles, desc=progress, unit=unit, total=n)
    if keep_last and ckpt and n is None:
        raise ValueError("run_tiles: keep_last needs the tile count (a sequence, or total=)")
    outs = []
    for k, tile in enumerate(it):
        if ckpt and not (keep_last and k == n - 1):
            out = Recompute.apply(functools.partial(run, tile), *tensors)
        elif ckpt:
            out = RecordedOnce.apply(functools.partial(run, tile), *tensors)
        else:
            out = run(tile, *tensors, record=torch.is_grad_enabled())
        outs.append(out)
        if after is not None:
            after(tile, out)
    if not outs:
        raise ValueError("run_tiles: no tiles")
    return outs[0] if len(outs) == 1 else torch.cat(outs, 0)
