"""Warp copies and memsets of a live design step (issue 25: on a GPU each is one more launch in a step bound by its
launches): a tracer with gradients keeps its parameter rows as views of one array (loaded, read and zeroed in one
operation each), after a backward pass only those gradients are zeroed (the tape's other gradient arrays are
the call's own and die with its graph; a replay of the graph zeroes them first), and a recorded trace takes its
gradient buffers from one zeroed block (rwwarp.grad_block.GradBlock); the parameter table in fewer operations."""
from __future__ import annotations


import numpy as np
import pytest
import torch

import torch_bridge as tb
from torch_bridge import design as dz
from _lenses import wrapping_doe_lens
from _op_count import OpCounter, count_warp_copies  # noqa: E402

LEARN = {"curvature": "all", "doe": "all"}


def _provider(fields=(0.0, 5.0)):
    lens = wrapping_doe_lens(None)
    # the coarse plan (nyquist_safety 1): operations are counted, not the sampling
    m = tb.HybridLens(lens, learn=LEARN, method="focal", rays_per_sample=0.5, focal_patch_tol=1e-3,
                      nyquist_safety=1.0)
    return lens, m, dz.LiveProvider(m, list(fields), 12, lens.sensor.pixel_pitch, pack=True, replan_every=100)


def _grads(m):
    return {q: getattr(m, q).grad.detach().clone() for q in LEARN}


def _tile(prov):
    """The packed tile of the provider's last call."""
    return next(iter(prov._packed.values()))[1]


def test_consecutive_and_replayed_backward_passes_give_the_same_gradients():
    """The same step twice on one provider (kept plans, the same lens values): the second backward pass gives the
    first's gradients bit for bit (a parameter gradient left over from the first would add to it). The tile's trace
    and splat (:class:`torch_bridge.functions.TraceSplat`) differentiated twice through one graph
    (``retain_graph``; the step's propagation frees its operators after one backward, so the trace alone) adds
    the same table gradient twice: exactly 2x (the replay zeroes the call's gradient arrays before it runs
    again)."""
    from torch_bridge.functions import trace_splat
    lens, m, prov = _provider()
    prov.psfs([0.5, 0.6])                                   # plans
    g = torch.as_tensor(np.random.default_rng(0).standard_normal((2, 2, 12, 12)))
    got = []
    for _ in range(2):
        m.zero_grad(set_to_none=True)
        (prov.psfs([0.5, 0.6]) * g).sum().backward()
        got.append(_grads(m))
    for q in LEARN:
        assert float(got[0][q].abs().max()) > 0
        assert torch.equal(got[0][q], got[1][q]), q
    prw = _tile(prov).raywave
    table = m.param_table(prw, m.values()).detach().requires_grad_(True)
    u = trace_splat(table, prw, m.host_table(prw, table))
    w = torch.as_tensor(np.random.default_rng(1).standard_normal(tuple(u.shape)))
    loss = (u.real * w).sum() + (u.imag * w.flip(-1)).sum()
    once = torch.autograd.grad(loss, table, retain_graph=True)[0]
    loss.backward(retain_graph=True)
    loss.backward()
    assert float(once.abs().max()) > 0
    assert torch.equal(table.grad, 2 * once)


def test_parameter_rows_are_views_of_one_array_loaded_in_one_copy():
    """A tracer with gradients: its rows are views of ``params_block`` (a write through the block shows in each
    row); ``load_params`` from the host and from a device table put the table's values in every row."""
    import warp as wp

    lens, m, prov = _provider()
    prov.psfs([0.5, 0.6])
    rw = _tile(prov).raywave
    tr = rw.tracer
    assert tr.params_block is not None and len(tr.params) == tr.params_block.shape[0]
    tab = tr.params_np.copy()
    new = tab.copy()
    new[:, 0] += np.arange(len(tab)) * 1e-6                   # a column every surface has (small: a valid lens)
    rw.load_params(new)
    assert np.array_equal(np.stack([p.numpy() for p in tr.params]), new)
    rw.load_params(tab, device_table=wp.array(tab, dtype=tr.scalar, device=tr.device))
    assert np.array_equal(tr.params_block.numpy(), tab)
    assert np.array_equal(np.stack([p.numpy() for p in tr.params]), tab)


def test_a_packed_step_makes_a_bounded_number_of_copies_and_memsets(monkeypatch):
    """Forward and backward of a packed step on kept plans (A489 + DOE, 4 surfaces, 2 and 3 focal sources): Warp
    copies (``wp.copy``, ``array.assign`` through it) and memsets (``array.zero_`` / ``fill_``). Measured 12 copies
    and 19 memsets for both (before: 24 and 86, the parameter rows copied one a surface, every gradient of the
    tape zeroed after the backward pass and each ray state's and parameter-row copy's gradient zeroed on its own
    instead of one block a trace, rwwarp.grad_block). Bound: 12 copies and 35 copies and memsets."""
    got = {}
    for fields in ((0.0, 5.0), (0.0, 2.5, 5.0)):
        _, m, prov = _provider(fields)
        prov.psfs([0.5, 0.6])
        c = count_warp_copies(monkeypatch)
        prov.psfs([0.5, 0.6]).sum().backward()
        monkeypatch.undo()
        got[len(fields)] = (c["copy"], c["zero_"] + c["fill_"])
    assert got[2] == got[3]
    copies, memsets = got[2]
    assert copies <= 12 and copies + memsets <= 35


@pytest.mark.parametrize("name", ["cooke_triplet", "a489_doe"])
def test_param_table_equals_the_tracers_table_and_its_gradient_is_the_selection(name):
    """HybridLens.param_table (z, curvature, conic and aspheric columns as one block) with curvatures, conics and
    thicknesses moved off the lens's values: equal to the table rwwarp's Tracer builds in numpy from the lens at
    those values (``to_lens``; measured: exactly); its gradient against ``sum(table * W)`` is the selection by
    hand: ``W[s, curvature]`` and ``W[s, conic]`` on the standard surfaces, ``sum_{i > j} W[i, z]`` for thickness
    ``j`` (z the running sum), to 1e-15 of the largest (measured: exactly). Forward and backward with the
    weighting take 59 (cooke_triplet) and 62 (a489_doe) aten operations (column by column before: 150 and
    153); bound 70."""
    import rwwarp as rw
    from rwwarp.trace import COLUMNS as COL, Tracer
    lens = rw.load_lens(name)
    learn = {"curvature": "all", "conic": "all", "thickness": "all"}
    m = tb.HybridLens(lens, learn=learn, method="focal", rays_per_sample=0.5, focal_patch_tol=1e-3,
                      nyquist_safety=1.0)
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for q in learn:
            p = getattr(m, q)
            p.add_(1e-3 * torch.randn(p.shape, dtype=p.dtype, generator=g) * p.abs().clamp_min(1e-2))
    rwv = m.raywave([0.0], [0.55], 12, pixel_mm=lens.sensor.pixel_pitch)
    values = m.values()
    with OpCounter() as ops:
        tab = m.param_table(rwv, values)
        W = torch.sin(torch.arange(tab.numel(), dtype=tab.dtype)).reshape(tab.shape)
        (tab * W).sum().backward()
    ref = Tracer(m.to_lens(), [0.55]).params_np
    assert np.array_equal(tab.detach().numpy(), ref)
    assert ops.n <= 70
    std = m.standard_mask.numpy()
    n = len(lens.surfaces)
    full = {q: torch.zeros_like(values[q]) for q in learn}
    full["curvature"][std] = W[:n][std, COL.curvature]
    full["conic"][std] = W[:n][std, COL.conic]
    full["thickness"] = torch.flip(torch.cumsum(torch.flip(W[1:, COL.z], [0]), 0), [0])
    for q in learn:
        idx = getattr(m, f"{q}_index")
        want = full[q].reshape(-1)[idx]
        got = getattr(m, q).grad.reshape(-1)
        assert float(want.abs().max()) > 0
        assert float((got - want).abs().max()) <= 1e-15 * float(want.abs().max()), q


def test_grad_block_hands_out_zeroed_disjoint_gradients():
    """GradBlock: each attached array gets a zeroed gradient of its own shape and dtype, the views do not overlap
    (a write through one shows in the block where it should and nowhere else), and it refuses an array past its
    room or of another scalar type."""
    import pytest
    import warp as wp

    from rwwarp.grad_block import GradBlock
    gb = GradBlock("cpu", wp.float64, 3 * 4 + 5 + 2 * 3)
    a = gb.attach(wp.empty(4, dtype=wp.vec3d, device="cpu"))
    b = gb.attach(wp.empty(5, dtype=wp.float64, device="cpu"))
    c = gb.attach(wp.empty((2, 3), dtype=wp.float64, device="cpu"))
    assert a.requires_grad and a.grad.shape == (4,) and a.grad.dtype == wp.vec3d and c.grad.shape == (2, 3)
    assert not np.any(gb.block.numpy())
    b.grad.fill_(2.0)
    c.grad.fill_(3.0)
    a.grad.fill_(wp.vec3d(1.0, 1.0, 1.0))
    assert np.array_equal(gb.block.numpy(), np.repeat([1.0, 2.0, 3.0], [12, 5, 6]))
    with pytest.raises(ValueError, match="left"):
        gb.attach(wp.empty(1, dtype=wp.float64, device="cpu"))
    with pytest.raises(ValueError, match="cannot hold"):
        GradBlock("cpu", wp.float64, 4).attach(wp.empty(1, dtype=wp.float32, device="cpu"))


def test_packed_rim_cells_are_each_sources_disc_cells_then_zeros(monkeypatch):
    """Tracer.packed_rim_cells of sources with 3, 5 and 4 cell-grid sides in 25 slots each: source k's slots hold
    rwwarp.pupil.disc_cells(side) (the host table) and zeros past it, exactly; made with one memset (not one a
    source with fewer cells than slots) and one copy a source."""
    import rwwarp as rw
    from rwwarp.pupil import disc_cells
    from rwwarp.trace import Tracer
    tr = Tracer(rw.load_lens("cooke_triplet"), [0.55])
    sides = [3, 5, 4]
    for g in sides:
        tr.rim_cells(g)                                     # the per-size device tables, made before counting
    c = count_warp_copies(monkeypatch)
    got = tr.packed_rim_cells(sides, 25).numpy().reshape(3, 25, 3)
    monkeypatch.undo()
    for k, g in enumerate(sides):
        want = np.zeros((25, 3))
        want[:g * g] = disc_cells(g)
        assert np.array_equal(got[k], want), g
    assert c["copy"] == 3 and c["zero_"] + c["fill_"] <= 1


def test_a_packed_step_on_kept_tiles_uploads_no_index_again():
    """Forward and backward of a packed step on kept plans (A489 + DOE, 2 and 3 focal sources): the calls of
    ``torch_bridge.functions.upload`` that name a device (each a host-to-device copy on a GPU). The tile's member
    rows (its groups, their Gauss-node subsets, the output order) are uploaded once per tile (PackedTile.index),
    not every call: measured 4 uploads a step from the second step on (before: 11); bound 4. The PSFs of the
    third step equal the second's bit for bit (the same values, the same rows)."""
    import sys

    from torch_bridge import functions as TF
    code = TF.upload.__code__
    for fields in ((0.0, 5.0), (0.0, 2.5, 5.0)):
        _, m, prov = _provider(fields)
        got, outs = [], []
        for _ in range(3):
            n = [0]

            def prof(frame, event, arg):
                if event == "call" and frame.f_code is code and frame.f_locals.get("device") is not None:
                    n[0] += 1
            prev = sys.getprofile()
            sys.setprofile(prof)
            try:
                out = prov.psfs([0.5, 0.6])
                out.sum().backward()
            finally:
                sys.setprofile(prev)
            got.append(n[0])
            outs.append(out.detach())
        assert got[1] == got[2] <= 4, got
        assert torch.equal(outs[1], outs[2])


def test_live_pack_waste_reaches_the_live_provider():
    """``optics.live_pack_waste`` (default 1.5) is the live provider's ``pack_waste``; the gpu preset's e2e arm
    with it set to 3 (on the CPU, the cpu-sized network) builds its provider with that factor."""
    from pathlib import Path

    import torch_bridge
    from torch_bridge.config import DEFAULTS
    from torch_bridge.train import Arm, load_config
    assert DEFAULTS["optics"]["live_pack_waste"] == 1.5
    exp = load_config(str(Path(torch_bridge.__file__).resolve().parent / "configs" / "cooke_hybrid.yaml"),
                      preset="cpu_lens", overrides={"optics": {"live_pack_waste": 3.0}})
    arm_cfg = next(x for x in exp["arms"] if x["name"] == "e2e")
    cfg = dict(arm_cfg["config"], device="cpu", progress=False)
    arm = Arm("e2e", cfg, exp["source"], Path("unused"), progress=False)
    assert isinstance(arm.provider, dz.LiveProvider) and arm.provider.pack_waste == 3.0
