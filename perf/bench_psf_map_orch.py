"""HybridLens.psf_map forward + backward of a small DOE lens (A489 + DOE, 3 x 3 fields x 3 wavelengths, 27
sources, size 16 px): host seconds and Warp launches of one call (plans made in the call: replan=True).

Run under the PYTHONPATH of the code to time (e.g. the tree before and after a change, alternately: the machine
is shared): ``python perf/bench_psf_map_orch.py [repeats [size [method [device]]]]`` (environment ``BENCH_SLOT_WASTE``: psf_map's
``slot_waste``, "none" for None). Prints one line per repeat: seconds, launches.
Units: s."""
from __future__ import annotations

import os
import sys
import time

import numpy as np
import torch
import warp as wp

import rwwarp as rw
import torch_bridge as tb


def main(repeats: int = 3, size: int = 16, method: str = "focal", device: str = "cpu"):
    lens = rw.load_lens("a489_doe")
    m = tb.HybridLens(lens, learn={"curvature": "all", "doe": "all"}, method=method, rays_per_sample=0.5,
                      focal_patch_tol=1e-3).to(device)
    fields = [(x, y) for y in (0.0, 2.5, 5.0) for x in (0.0, 2.5, 5.0)]
    wls = [0.5, 0.55, 0.6]
    g = torch.as_tensor(np.random.default_rng(0).standard_normal((len(fields), len(wls), size, size)), device=device)
    count, real = [0], wp.launch

    def counting(*a, **k):
        count[0] += 1
        return real(*a, **k)
    wp.launch = counting
    # BENCH_SLOT_WASTE: psf_map's slot_waste ("none": None; unset: the default, and the only choice before it existed)
    sw = os.environ.get("BENCH_SLOT_WASTE")
    kw = {} if sw is None else {"slot_waste": None if sw == "none" else float(sw)}
    m.psf_map(fields, wls, size, **kw)   # warm-up (kernels compiled, caches)
    for _ in range(int(repeats)):
        m.zero_grad()
        count[0] = 0
        t0 = time.perf_counter()
        out = m.psf_map(fields, wls, size, **kw)
        (out * g).sum().backward()
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        dt = time.perf_counter() - t0
        print(f"{dt:.3f} s  {count[0]} launches  sum {float(out.detach().sum()):.15g}  "
              f"grad {float(m.curvature.grad.abs().sum()):.15g}", flush=True)


if __name__ == "__main__":
    main(*(int(a) for a in sys.argv[1:2]), *(sys.argv[2:3] and [int(sys.argv[2])]), *sys.argv[3:5])
