"""The one tiling/checkpoint loop (torch_bridge.tiles.run_tiles) behind HybridLens.psf_map, LiveProvider and
CachedProvider: a tiled map equals the untiled one (PSFs and gradients), and a checkpointed tile's forward runs
exactly twice (once without a tape, once recorded in the backward pass), an untiled one once."""
import collections
import sys
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

import torch_bridge as tb
from torch_bridge import design as dz
from torch_bridge.tiles import run_tiles

sys.path.insert(0, str(Path(__file__).parent))
from test_tiling import FIELDS, singlet  # noqa: E402  (the small singlet + DOE with 8 px patches)

LEARN = {"doe": "all", "curvature": [1], "thickness": [3]}


def test_run_tiles_checkpoints_each_tile_once_and_recomputes_it_once():
    # y = x^3 on index tiles: the gradient is 3 x^2 (each element in one tile); counts per (tile, record)
    x = torch.linspace(-1.0, 2.0, 10, dtype=torch.float64, requires_grad=True)
    tiles = [[0, 1, 2], [3, 4, 5, 6], [7, 8, 9]]
    for checkpoint, want in ((None, {False: 1, True: 1}), (False, {True: 1})):
        calls = collections.Counter()

        def run(tile, t, record=True):
            calls[(tuple(tile), record)] += 1
            with (torch.enable_grad() if record else torch.no_grad()):
                return t[tile] ** 3
        y = run_tiles(tiles, run, [x], checkpoint=checkpoint, after=lambda tile, out: calls.update([("after",)]))
        assert calls[("after",)] == 3   # the hook after each tile's forward
        forward = {k: v for k, v in calls.items() if k != ("after",)}
        assert forward == {(tuple(t), True if checkpoint is False else False): 1 for t in tiles}
        x.grad = None
        y.sum().backward()
        # checkpointed: the recorded forward runs once more in backward, not more; plain: no second run
        for t in tiles:
            assert {r: calls[(tuple(t), r)] for r in (False, True) if calls[(tuple(t), r)]} == want
        assert torch.equal(y.detach(), x.detach() ** 3)
        assert torch.equal(x.grad, 3 * x.detach() ** 2)
    # keep_last: the last tile recorded as it runs (once), the others checkpointed (twice); a generator with total=
    for tiles_in in (tiles, iter(tiles)):
        calls = collections.Counter()
        x.grad = None
        y = run_tiles(tiles_in, run, [x], checkpoint=True, total=3, keep_last=True)
        y.sum().backward()
        assert dict(calls) == {**{(tuple(t), r): 1 for t in tiles[:2] for r in (False, True)}, ((7, 8, 9), True): 1}
        assert torch.equal(x.grad, 3 * x.detach() ** 2)
    with pytest.raises(ValueError, match="keep_last needs the tile count"):
        run_tiles(iter(tiles), run, [x], checkpoint=True, keep_last=True)
    # no gradient wanted: no checkpoint, one plain forward a tile; a generator needs its count for the default
    with torch.no_grad():
        calls.clear()
        run_tiles(iter(tiles), run, [x], checkpoint=True)
        assert sorted(calls.values()) == [1, 1, 1] and all(not r for _, r in calls)
    with pytest.raises(ValueError, match="tile count"):
        run_tiles(iter(tiles), run, [x])


def _hybrid_map(tile):
    """HybridLens.psf_map of 3 fields x 2 wavelengths (8 px) in tiles of ``tile`` sources, its gradients for a
    random loss weight, and the calls of HybridLens._psf_rw by (source, record) after the forward and after the
    backward."""
    hl = tb.HybridLens(singlet(), learn=LEARN, replan=False)
    calls, orig = collections.Counter(), hl._psf_rw

    def counted(rw, values, record=True, **kw):
        calls[(id(rw), record)] += 1
        return orig(rw, values, record=record, **kw)
    hl._psf_rw = counted
    m = hl.psf_map(FIELDS[:3], [0.45, 0.55], 8, tile=tile)
    after_forward = dict(calls)
    (m * torch.from_numpy(np.random.default_rng(0).random((3, 2, 8, 8)))).sum().backward()
    return m.detach(), {q: getattr(hl, q).grad.detach().clone() for q in LEARN}, after_forward, dict(calls)


def test_hybrid_lens_tiles_equal_the_untiled_map_and_run_each_source_twice():
    ref, gref, fwd, every = _hybrid_map(None)
    # one tile: no checkpoint, each source's forward once, recorded
    assert sorted(fwd.values()) == [1] * 6 and all(r for _, r in fwd) and every == fwd
    for tile in (1, 4):
        m, g, fwd, every = _hybrid_map(tile)
        # checkpointed tiles: each source once without a tape in the forward pass ...
        assert len(fwd) == 6 and all(v == 1 and not r for (_, r), v in fwd.items())
        # ... and once recorded in the backward pass, not more
        assert len(every) == 12 and all(v == 1 for v in every.values())
        assert sum(r for _, r in every) == 6
        # every source is computed by the same code on its own plan in either case: the PSFs are bit for bit the
        # same (measured 0.0); a gradient sums the tiles' contributions in another order (measured: tile 1 bit
        # for bit, tile 4 1.2e-16 of the largest thickness gradient): tolerance 1e-15 of the largest
        assert torch.equal(m, ref)
        for q in LEARN:
            assert float((g[q] - gref[q]).abs().max()) <= 1e-15 * float(gref[q].abs().max()), (tile, q)
            assert float(gref[q].abs().max()) > 0


def _live(tile):
    m = tb.HybridLens(singlet(), learn=LEARN, method="focal")
    # pack=False: each focal source alone (HybridLens._psf_rw), whatever the chunk (packing sums in another order)
    prov = dz.LiveProvider(m, FIELDS[:2], 8, 0.004, tile=tile, pack=False)
    out = prov.psfs([0.45, 0.55])
    (out * torch.from_numpy(np.random.default_rng(1).random(tuple(out.shape)))).sum().backward()
    return out.detach(), {q: getattr(m, q).grad.detach().clone() for q in LEARN}


def test_live_provider_chunks_equal_one_chunk():
    ref, gref = _live(None)
    for tile in (3,):
        out, g = _live(tile)
        # each focal source on its own plan in any chunk: PSFs bit for bit (measured 0.0); gradients summed over
        # the 2 checkpointed chunks in another order (measured 1.6e-16 of the largest curvature gradient, the
        # DOE and thickness ones 0.0): tolerance 1e-15 of the largest
        assert torch.equal(out, ref)
        for q in LEARN:
            assert float((g[q] - gref[q]).abs().max()) <= 1e-15 * float(gref[q].abs().max()), (tile, q)
            assert float(gref[q].abs().max()) > 0
