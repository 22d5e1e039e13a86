"""One design step of the cached provider on the CPU: the A489 + DOE (a learning even-polynomial DOE), 4 nodes x 2
wavelengths, ASM entries, one node a chunk (``psfs(..., chunk=1)``) forward and backward; the median wall time (s) of
5 steps after one warm-up, the last step's log entry and the DOE gradient's sum (equal between trees that compute
the same gradient). Old tree against new: ``PYTHONPATH=OLD_TREE python perf/bench_cached_step.py``, or
``farm-bench --vs`` the two.

    python perf/bench_cached_step.py
"""
import statistics, sys, time, warnings
import numpy as np
import torch
warnings.simplefilter("ignore")
import rwwarp as rw
import torch_bridge as tb
from torch_bridge import design as dz
torch.set_num_threads(1)
lens = rw.load_lens("a489_doe")
d = lens.doe_index
lens = lens.with_surface(d, profile={**lens.surfaces[d].profile, "coefficients": [-20.0, 8.0, 3.0, -1.0]})
m = tb.HybridLens(lens, learn={"doe": "all"}, nyquist_safety=1.0, rays_per_sample=1.2)
fields = dz.field_angles(lens, dz.node_positions_mm("grid", 1.0, (2, 2), region="quadrant"), 0.55)
prov = dz.CachedProvider(m, fields, 21, 0.003, wavelength_ref_um=0.55, memory_budget_bytes=10 ** 12)
wls = [0.47, 0.63]
prov.prepare(wls, [None])
ts = []
for k in range(6):
    m.zero_grad()
    t = time.perf_counter()
    p = prov.psfs(wls, chunk=1)
    p.sum().backward()
    ts.append(time.perf_counter() - t)
print("step", statistics.median(ts[1:]), prov.step_log[-1], float(m.doe.grad.abs().sum()))
