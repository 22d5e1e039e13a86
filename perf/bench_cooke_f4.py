"""The paper's Cooke experiment at its own aperture (F/4): one end-to-end joint step on one device.

    python perf/bench_cooke_f4.py --device cuda --out OUT_DIR [--commit SHA] [--steps 3]

The ``cooke_hybrid`` lens (f = 47 mm, F/4, 8 x 8 mm DOE 20 mm before the sensor) starting from its
paraxial achromatic DOE, the ``gpu`` preset's optics: 4 x 4 nodes over a sensor quadrant, 63 px PSFs of
4 um pixels, 3 wavelengths per RGB channel, curvatures + DOE + DOE-to-sensor distance learning, live
ray-wave PSFs (:class:`torch_bridge.design.LiveProvider`, ``HybridLens(method="auto")``: the focal
propagation wherever the band-limited ASM's plan would be large). A joint step as the training runs it,
without data loading: PSFs of all nodes and wavelengths with their graph, an RGB batch (8 x 256 x 256,
random scenes) rendered with the spatially varying blur, read noise, NAFNet (``paper`` preset) forward,
MSE loss, backward into the network and the lens, one Adam step on both.

Reports (``cooke_f4_<device>.json``): the first call (planning, Warp kernel build, first trace) and the
warm step times, the split optics / network, every source's plan (wave-plane grid, rays, DOE orders),
peak memory (torch's allocator peak, CuPy's pool, and the device's used memory sampled every 50 ms by
``nvidia-smi``), device name, sizes and commit.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

import rwwarp as rw
import torch_bridge as tb
from torch_bridge import design as dz
from torch_bridge.imaging import render_rgb
from torch_bridge.network import build_network

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import GpuMemory

LENS = Path(tb.__file__).parent / "configs" / "lenses" / "cooke_hybrid.json"
WAVELENGTHS = [[0.60, 0.63, 0.66], [0.52, 0.55, 0.58], [0.45, 0.47, 0.49]]


def build(device, rays_per_sample, nyquist_safety, patch_tol):
    lens = rw.load_lens(str(LENS))
    allw = [w for c in WAVELENGTHS for w in c]
    a, dist = dz.paraxial_achromat(lens, allw)
    d = len(lens.surfaces) - 1
    s = lens.surfaces[d]
    coeffs = [0.0] * len(s.profile["coefficients"])
    coeffs[0] = a
    lens = lens.with_surface(d, profile={**s.profile, "coefficients": coeffs}, thickness=dist)
    m = tb.HybridLens(lens, learn={"curvature": "all", "doe": "all", "thickness": [d]}, method="auto",
                      rays_per_sample=rays_per_sample, nyquist_safety=nyquist_safety, focal_patch_tol=patch_tol)
    m = m.to(device)
    pos = dz.node_positions_mm("grid", 4.0, grid=(4, 4), region="quadrant")
    fields = [tuple(f) for f in dz.field_angles(lens, pos)]
    return lens, m, fields


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--out", default="perf/results")
    ap.add_argument("--commit", default="")
    ap.add_argument("--steps", type=int, default=3)
    ap.add_argument("--size", type=int, default=63)
    ap.add_argument("--crop", type=int, default=256)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--rays-per-sample", type=float, default=1.0)
    ap.add_argument("--nyquist-safety", type=float, default=1.5)
    ap.add_argument("--patch-tol", type=float, default=1e-3)
    ap.add_argument("--nodes", type=int, default=16, help="first N of the 4 x 4 nodes")
    a = ap.parse_args()
    dev = torch.device(a.device)
    cuda = dev.type == "cuda"
    sync = torch.cuda.synchronize if cuda else (lambda: None)
    lens, m, fields = build(a.device, a.rays_per_sample, a.nyquist_safety, a.patch_tol)
    fields = fields[:a.nodes]
    prov = dz.LiveProvider(m, fields, a.size, 0.004, wavelength_ref_um=0.55, tile=1)
    # time spent planning (HybridLens.raywave: pilot trace, plan, RayWave set-up) inside the step
    plan_time = [0.0]
    raw = m.raywave

    def timed_raywave(*args, **kw):
        t = time.perf_counter()
        try:
            return raw(*args, **kw)
        finally:
            plan_time[0] += time.perf_counter() - t
    m.raywave = timed_raywave
    net = build_network("paper").to(dev)
    opt = torch.optim.Adam([{"params": net.parameters(), "lr": 1e-4},
                            {"params": [p for p in m.parameters() if p.requires_grad], "lr": 1e-6}])
    gen = torch.Generator(device="cpu").manual_seed(0)
    allw = [w for c in WAVELENGTHS for w in c]
    channels = [[0, 1, 2], [3, 4, 5], [6, 7, 8]]
    g = int(round(len(fields) ** 0.5))

    def step():
        plan_time[0] = 0.0
        t0 = time.perf_counter()
        psfs = prov.psfs(allw)                                   # (nodes, 9, k, k), graph kept
        grid = psfs.reshape(g, len(fields) // g, len(allw), a.size, a.size).float()
        sync()
        t1 = time.perf_counter()
        img = torch.rand(a.batch, 3, a.crop, a.crop, generator=gen).to(dev)
        blurred = render_rgb(img, grid, channels) + 0.01 * torch.randn(img.shape, generator=gen).to(dev)
        out = net(blurred)
        loss = torch.nn.functional.mse_loss(out, img)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sync()
        t2 = time.perf_counter()
        print(f"step: psfs {t1 - t0:.2f} s (planning {plan_time[0]:.2f} s), render + network + backward "
              f"{t2 - t1:.2f} s", flush=True)
        return t1 - t0, t2 - t1, float(loss.detach()), plan_time[0]

    res = {"device": torch.cuda.get_device_name(0) if cuda else "cpu", "commit": a.commit, "lens": str(LENS.name),
           "f_number": lens.efl(0.55) / lens.entrance_pupil_diameter if callable(getattr(lens, "efl", None)) else None,
           "epd_mm": lens.entrance_pupil_diameter, "nodes": len(fields), "wavelengths": allw, "psf_size": a.size,
           "pixel_um": 4.0, "crop": a.crop, "batch": a.batch, "rays_per_sample": a.rays_per_sample,
           "nyquist_safety": a.nyquist_safety, "focal_patch_tol": a.patch_tol, "network": "NAFNet paper preset"}
    with GpuMemory() as mem:
        t = time.perf_counter()
        first = step()
        res["first_step_s"] = time.perf_counter() - t
        res["first_split_s"] = {"optics_forward": first[0], "render_network_backward": first[1],
                                "planning_in_forward": first[3]}
        times = []
        for _ in range(a.steps):
            t = time.perf_counter()
            o, n, loss, pt = step()
            times.append({"step_s": time.perf_counter() - t, "psf_forward_s": o, "planning_in_forward_s": pt,
                          "render_network_backward_s": n, "loss": loss})
    res["steps"] = times
    res["step_s_median"] = float(np.median([x["step_s"] for x in times])) if times else None
    if cuda:
        res["torch_max_allocated_GB"] = torch.cuda.max_memory_allocated() / 1e9
        try:
            import cupy
            res["cupy_pool_total_GB"] = cupy.get_default_memory_pool().total_bytes() / 1e9
        except ImportError:
            pass
        res["device_used_peak_GB_nvidia_smi"] = mem.peak * 1.048576e-3
    m.raywave = raw
    plans = []
    for f in fields:
        for w in allw:
            r = m.raywave([f], [w], a.size, pixel_mm=0.004, requires_grad=False)
            pl = r.plan
            plans.append({"field_deg": list(f), "wl_um": w, "method": pl.method, "n_grid": pl.n_grid,
                          "ray_grid": pl.ray_grid, "orders": None if r.focal is None else [k for k, _ in r.focal["orders"][0]],
                          "estimate_GB": pl.estimate["memory_bytes"] / 1e9})
    res["plans"] = plans
    res["plans_summary"] = {"n_grid_max": max(p["n_grid"] for p in plans),
                            "n_grid_median": float(np.median([p["n_grid"] for p in plans])),
                            "rays_total_M": sum(p["ray_grid"] ** 2 for p in plans) / 1e6,
                            "methods": sorted({p["method"] for p in plans})}
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    name = f"cooke_f4_{'gpu' if cuda else 'cpu'}.json"
    (out / name).write_text(json.dumps(res, indent=1))
    print(json.dumps({k: v for k, v in res.items() if k != "plans"}, indent=1))


if __name__ == "__main__":
    main()
