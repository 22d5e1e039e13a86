"""Launches, torch operations and wall time of the optics part of one end-to-end design step, with the focal
sources one at a time (``LiveProvider(pack=False)``) and packed (``pack=True``, torch_bridge/packed.py).

    python perf/bench_packed_step.py [--fields 4] [--size 15] [--device cpu] [--out perf/results/packed_step_cpu.json]

The cooke_hybrid lens and learning quantities of its gpu preset (curvatures, DOE, sensor distance), one
wavelength per colour channel (0.63, 0.55, 0.47 um), ``--fields`` field angles on the diagonal, kept plans
(``replan_every=3`` as the gpu preset). A step: the provider's PSFs, a loss, its backward (the network's
part is the same either way and left out). Counted per step: Warp launches (every ``warp.launch``, the
tape's adjoint launches included), torch (aten) operations (a ``TorchDispatchMode``, backward included), and
the step's wall time and CPU time of the process (all its threads: on a shared machine the wall time also
holds the waits for a core); the first call (planning) is reported apart from the steady steps on kept plans.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--fields", type=int, default=4)
    ap.add_argument("--size", type=int, default=15)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--steps", type=int, default=2)
    ap.add_argument("--rays-per-sample", type=float, default=0.5)
    ap.add_argument("--nyquist-safety", type=float, default=1.0)
    ap.add_argument("--out", default=None)
    a = ap.parse_args()

    import torch
    import warp as wp
    from torch.utils._python_dispatch import TorchDispatchMode

    import rwwarp as rw
    import torch_bridge as tb
    from torch_bridge import design as dz

    root = Path(__file__).resolve().parent.parent
    lens = rw.load_lens(str(root / "torch_bridge" / "configs" / "lenses" / "cooke_hybrid.json"))
    fields = [(0.0, float(f)) for f in np.linspace(0.0, 9.0, a.fields)]
    wls = [0.63, 0.55, 0.47]
    launches = [0]
    real = wp.launch

    def counting(*x, **k):
        launches[0] += 1
        return real(*x, **k)
    wp.launch = counting

    class Ops(TorchDispatchMode):
        def __init__(self):
            super().__init__()
            self.n = 0

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            self.n += 1
            return func(*args, **(kwargs or {}))

    res = {"lens": "cooke_hybrid", "fields_deg": fields, "wavelengths_um": wls, "size": a.size, "device": a.device,
           "rays_per_sample": a.rays_per_sample, "nyquist_safety": a.nyquist_safety, "modes": {}}
    ref = None
    for pack in (False, True):
        m = tb.HybridLens(lens, learn={"curvature": "all", "doe": "all", "thickness": [6]}, method="auto",
                          rays_per_sample=a.rays_per_sample, nyquist_safety=a.nyquist_safety, focal_patch_tol=1e-3)
        m = m.to(a.device)
        prov = dz.LiveProvider(m, fields, a.size, lens.sensor.pixel_pitch, replan_every=3, pack=pack)
        g = None
        rows = []
        for step in range(1 + a.steps):
            launches[0] = 0
            ops = Ops()
            t, c = time.perf_counter(), time.process_time()
            with ops:
                out = prov.psfs(wls)
                if g is None:
                    g = torch.as_tensor(np.random.default_rng(0).standard_normal(tuple(out.shape)), device=out.device)
                loss = (out * g).sum()
                m.zero_grad()
                loss.backward()
            if a.device.startswith("cuda"):
                torch.cuda.synchronize()
            rows.append({"step": step, "wall_s": time.perf_counter() - t, "cpu_s": time.process_time() - c,
                         "warp_launches": launches[0],
                         "torch_ops": ops.n, "plans_made": prov.plans_made, "packs_made": prov.packs_made})
            print(("packed" if pack else "one at a time"), rows[-1], flush=True)
        grads = {q: getattr(m, q).grad.detach().cpu().numpy() for q in ("curvature", "doe", "thickness")}
        psf = out.detach().cpu().numpy()
        res["modes"]["packed" if pack else "per_source"] = rows
        if ref is None:
            ref = (psf, grads)
        else:
            res["psf_rel_diff"] = float(np.max(np.abs(psf - ref[0]) / np.abs(ref[0]).max(axis=(2, 3), keepdims=True)))
            res["grad_rel_diff"] = {q: float(np.abs(grads[q] - ref[1][q]).max() / np.abs(ref[1][q]).max())
                                    for q in grads}
            print("packed vs one at a time:", res["psf_rel_diff"], res["grad_rel_diff"], flush=True)
    plans = [(r.plan.n_grid, r.plan.n_sensor, r.plan.n_sensor_fft, r.gauss_nodes) for r in
             (e[0] for e in prov._focal_rws.values())]
    res["plans"] = plans
    if a.out:
        Path(a.out).write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
