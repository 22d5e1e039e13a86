"""HybridLens(deterministic=True): the same values give the same PSFs and gradients bit for bit on every run
(on a GPU: fixed-point splat, a parameter-row copy per ray; the CPU is deterministic either way), equal to
the default path's to rounding, and the memory estimate counts the per-ray copies."""
from __future__ import annotations

import torch

import rwwarp as rw
import torch_bridge as tb
from rwwarp.trace import COLUMNS


def _run(det, device="cpu"):
    lens = rw.load_lens("cooke_triplet")
    # the coarse plan (nyquist_safety 1): what is compared is the deterministic path against itself and the
    # default path, not the sampling (2.2x faster than the default plan; the same measured figures below)
    m = tb.HybridLens(lens, learn={"curvature": [0, 3]}, method="focal", rays_per_sample=0.5,
                      deterministic=det, nyquist_safety=1.0).to(device)
    p = m.psf(10.0, 0.55, 12)
    w = torch.linspace(0.0, 1.0, p.numel(), dtype=p.dtype, device=p.device).reshape(p.shape)
    (p * w).sum().backward()
    return p.detach().cpu(), m.curvature.grad.detach().cpu(), m


def _devices():
    return ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


def test_deterministic_psf_and_gradient_repeat_bit_for_bit_and_match_the_default():
    """Cooke triplet at 10 deg, 12 px, gradient of a weighted PSF sum w.r.t. two curvatures. Against the
    default path, measured on the CPU: PSF 5.1e-16, gradient 1.9e-14 relative (the default plan: 4.5e-16, 9.2e-15);
    tolerances 1e-13 / 1e-12."""
    for dev in _devices():
        p1, g1, _ = _run(True, dev)
        p2, g2, _ = _run(True, dev)
        assert torch.equal(p1, p2) and torch.equal(g1, g2), dev
        p0, g0, _ = _run(False, dev)
        assert float(torch.linalg.norm(p1 - p0) / torch.linalg.norm(p0)) < 1e-13, dev
        assert float((g1 - g0).abs().max() / g0.abs().max()) < 1e-12, dev


def test_deterministic_memory_estimate_counts_the_per_ray_copies():
    """bytes_per_source grows by the per-ray parameter copies: at least 2 x 8 x N_PARAMS (640) bytes a ray and traced
    surface."""
    lens = rw.load_lens("cooke_triplet")
    est = {}
    for det in (False, True):
        m = tb.HybridLens(lens, learn={"curvature": [0]}, method="focal", rays_per_sample=0.5, deterministic=det)
        rw_ = m.raywave([10.0], [0.55], 12)
        est[det] = m.bytes_per_source(rw_)
    rays = rw_.plan.ray_grid ** 2
    assert est[True] - est[False] >= 2 * 16 * COLUMNS.n_params * rays * (rw_.plane + 2)
