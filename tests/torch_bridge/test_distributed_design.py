"""Distributed end-to-end design (torch_bridge.distributed, issue 14): one joint step on 2 gloo ranks
(started through torch's launcher) gives the single-process step's loss and gradients: the network's
(DistributedDataParallel) and the optics' (PSF nodes shared out, dL/dP and optics gradients
all-reduced). Run in float64 (network and images) so that only the order of reductions differs."""
import copy
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")

from test_train import TINY  # the tiny A489 + DOE design of the training tests

# the smallest design that still splits both ways: 2 PSF nodes (one a rank), 2 crops (one a rank)
CFG = copy.deepcopy(TINY)
CFG["optics"]["psf_size"] = 9
CFG["data"].update({"crop": 16, "batch_size": 2})
CFG["train"].update({"joint_steps": 1, "finetune_steps": 0})


# a design whose refractive part learns (LiveProvider: every optics step traces), on the focal path
# (each source planned on its own, so a rank's share of the nodes is planned as in one process)
CFG_LIVE = copy.deepcopy(CFG)
CFG_LIVE["optics"]["learn"] = {"doe": "all", "curvature": [1]}
CFG_LIVE["optics"]["propagation"] = "focal"
CFG_LIVE["train"]["lr_optics"] = {"doe": 0.5, "curvature": 1e-5}


def _step(group, cfg0=CFG, provider="CachedProvider"):
    """One joint step (an optics step) of a fresh arm in float64: (loss, network grads, optics grads)."""
    from torch_bridge.train import Arm, _seed_all, load_config, train_step
    exp = load_config(cfg0)
    cfg = exp["arms"][0]["config"]
    _seed_all(int(cfg["seed"]))
    arm = Arm("e2e", cfg, exp["source"], Path("unused"), progress=False)
    assert type(arm.provider).__name__ == provider
    arm.net.double()
    arm.criterion.double()
    s = train_step(arm, 0, {}, group)
    assert s["optics_step"]
    net = {n: p.grad.detach().clone() for n, p in arm.net.named_parameters()}
    optics = {g["name"]: g["params"][0].grad.detach().clone() for g in arm.opt_optics.param_groups}
    return s["loss"], net, optics


CASES = {"cached": (CFG, "CachedProvider"), "live": (CFG_LIVE, "LiveProvider")}


# the evaluation grid's PSFs shared out: a 2 x 3 grid in chunks of 2 nodes (3 chunks: two on rank 0, one on rank 1,
# so one rank's share is padded for the all-gather)
CFG_EVAL = copy.deepcopy(CFG)
CFG_EVAL["eval"].update({"grid": [2, 3], "node_chunk": 2})


def _eval_grid(group):
    """The evaluation grid's per-depth PSFs of a fresh arm of CFG_EVAL (the distributed ones with ``group``)."""
    from torch_bridge.evaluate import _eval_psfs, eval_depths
    from torch_bridge.train import Arm, _seed_all, load_config
    exp = load_config(CFG_EVAL)
    cfg = exp["arms"][0]["config"]
    _seed_all(int(cfg["seed"]))
    arm = Arm("e2e", cfg, exp["source"], Path("unused"), progress=False)
    psfs, pos, fields = _eval_psfs(arm, eval_depths(cfg), group=group)
    return {d: v.cpu() for d, v in psfs.items()}, pos


def _worker():
    """Rank r: the distributed step of each case, then the single-process step (same seed) of case r to
    compare (rank 0 the first case's, rank 1 the second's: the two references at once, not one after the
    other on rank 0). Both cases in one launch: a launch starts two fresh interpreters (torch, warp and
    OpenCL imported and initialised in each), which cost more than a case's step itself. Then the evaluation
    grid's PSFs, shared out (every rank) and in one process (rank 1)."""
    from torch_bridge.distributed import current_group
    g = current_group("cpu", timeout_s=300)
    dist = {name: _step(g, *args) for name, args in CASES.items()}
    single = {name: _step(None, *args) for name, args in list(CASES.items())[g.rank::g.size]}
    grid = _eval_grid(g)
    grid_single = _eval_grid(None) if g.rank == 1 else None
    return single, dist if g.rank == 0 else None, grid, grid_single


@pytest.fixture(scope="module")
def steps():
    """{case: (distributed step, single-process step)}: the distributed step as rank 0 computed it (every
    rank ends it with the same all-reduced gradients), the single-process one from the rank that made it."""
    from rwwarp.distributed import launch
    ranks = launch(_worker, 2)
    dist = ranks[0][1]
    got = {name: (dist[name], ref) for single, _, _, _ in ranks for name, ref in single.items()}
    assert sorted(got) == sorted(CASES)
    got["eval_grid"] = (ranks[0][2], ranks[1][2], ranks[1][3])
    return got


def test_the_evaluation_grid_shared_out_gives_the_single_process_psfs(steps):
    """The evaluation grid's PSFs computed by 2 ranks (chunks dealt out round robin, all-gathered) are the
    single process's on both ranks, node for node: the chunks are the same, so the numbers are bit for bit the
    same (measured: equal)."""
    (d0, pos0), (d1, pos1), (single, pos) = steps["eval_grid"]
    assert pos0 == pos and pos1 == pos and len(pos) == 6
    for depth, ref in single.items():
        assert ref.shape[0] == 6 and float(ref.abs().max()) > 0
        assert torch.equal(d0[depth], ref) and torch.equal(d1[depth], ref), depth


@pytest.mark.parametrize("case", list(CASES))
def test_one_distributed_design_step_equals_the_single_process_step(steps, case):
    (loss, net, optics), (loss1, net1, optics1) = steps[case]
    # measured: the loss and the network gradients bit for bit, the DOE gradient to 5e-20 (of 1e-4);
    # live: the loss to 1.3e-16 relative, DOE 2.7e-20 (of 2.7e-4), curvature 7.1e-15 (of 34):
    # the only difference is the order of the reductions (DDP mean, all-reduced dL/dP)
    assert abs(loss - loss1) <= 1e-10 * abs(loss1)
    for k in net1:
        assert torch.allclose(net[k], net1[k], rtol=1e-10, atol=1e-10 * float(net1[k].abs().max())), k
    for k in optics1:
        scale = float(optics1[k].abs().max())
        assert scale > 0 and float((optics[k] - optics1[k]).abs().max()) <= 1e-10 * scale, k


def _failed_run_worker(root):
    """Rank r: a design run that stops at its pre-flight check (a missing data folder) after it made the
    process group itself; returns (the error's message, whether a group is still initialised afterwards)."""
    from torch_bridge.train import ConfigError, train
    cfg = copy.deepcopy(CFG)
    cfg["data"]["root"] = str(Path(root) / "missing")
    try:
        train(cfg, out_dir=str(Path(root) / "run"))
    except ConfigError as e:
        return str(e), torch.distributed.is_initialized()
    return "no error", torch.distributed.is_initialized()


def test_a_run_ends_the_process_group_it_made(tmp_path):
    """``train`` under a launcher makes the process group (gloo here, NCCL on GPUs) and ends it when it returns
    or fails, so no rank leaves its communicators to the interpreter's exit (NCCL warns of a leak then). Two
    fresh ranks: each run fails its pre-flight check after the group exists."""
    from rwwarp.distributed import launch
    ranks = launch(_failed_run_worker, 2, str(tmp_path))
    assert [("data.root" in msg, alive) for msg, alive in ranks] == [(True, False), (True, False)]
