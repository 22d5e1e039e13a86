"""Run-to-run bits of the ray-wave PSF and its lens gradients, default against ``deterministic=True``.

    python perf/check_determinism.py --device cuda [--out DIR]

Cooke triplet at 10 deg (focal path), 32 px, gradient of a weighted PSF sum w.r.t. all curvatures; each
mode runs ``--runs`` times on fresh modules. Prints, per mode, whether the PSFs and the gradients were
bit-equal over the runs, their largest spread (relative), the time of a forward + backward and the peak
memory; writes ``determinism_<device>.json``. On the CPU both modes are deterministic (Warp's CPU kernels
run in order); on a GPU the default path's float64 atomics add in arrival order.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--size", type=int, default=32)
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    import torch

    import rwwarp as rw
    import torch_bridge as tb
    lens = rw.load_lens("cooke_triplet")
    cuda = a.device.startswith("cuda")
    out = {"device": torch.cuda.get_device_name() if cuda else "cpu", "size": a.size, "runs": a.runs, "modes": {}}
    for det in (False, True):
        ps, gs, ts = [], [], []
        if cuda:
            torch.cuda.reset_peak_memory_stats()
        for _ in range(a.runs):
            m = tb.HybridLens(lens, learn={"curvature": "all"}, method="focal", deterministic=det).to(a.device)
            t = time.perf_counter()
            p = m.psf(10.0, 0.55, a.size)
            w = torch.linspace(0.0, 1.0, p.numel(), dtype=p.dtype, device=p.device).reshape(p.shape)
            (p * w).sum().backward()
            if cuda:
                torch.cuda.synchronize()
            ts.append(time.perf_counter() - t)
            ps.append(p.detach().cpu())
            gs.append(m.curvature.grad.detach().cpu())
        spread_p = max(float((q - ps[0]).abs().max() / ps[0].abs().max()) for q in ps)
        spread_g = max(float((q - gs[0]).abs().max() / gs[0].abs().max()) for q in gs)
        r = {"psf_bit_equal": all(torch.equal(q, ps[0]) for q in ps),
             "grad_bit_equal": all(torch.equal(q, gs[0]) for q in gs),
             "psf_spread_rel": spread_p, "grad_spread_rel": spread_g,
             "time_s": ts, "peak_GB": torch.cuda.max_memory_allocated() / 1e9 if cuda else None,
             "ray_grid": m.raywave([10.0], [0.55], a.size).plan.ray_grid}
        out["modes"]["deterministic" if det else "default"] = r
        print("deterministic" if det else "default", r, flush=True)
    if a.out:
        p = Path(a.out) / f"determinism_{a.device.replace(':', '')}.json"
        p.write_text(json.dumps(out, indent=1))
        print("written to", p)


if __name__ == "__main__":
    main()
