"""One PSF and a 5x5 x 3-wavelength PSF map of the A489 + DOE lens: time and peak memory,
rwwarp (adaptive plan) and, when importable, DeepLens (``deeplens-core``) in the same run.

DeepLens is given the same lens written in its own JSON format (from the lens facts, flat Binary2 DOE)
and timed with its ``HybridLens.psf`` (coherent ray tracing + ASM, its own fixed 3000^2 grid padded 2x)
at 1M rays and at its default ray count. PSFs are compared after normalising both to unit sum on
their common centre window (both at the sensor's 1 um pixels; on axis, where no registration is needed).
DeepLens point-samples |U|^2 at the pixel centres where rwwarp integrates over the pixel: that is most of
the ~7 % difference (``speed_accuracy.py`` separates it and explains DeepLens's larger error off axis).

    python perf/bench_psf.py [--device cuda] [--deeplens]
"""
import argparse
import json
import time

import numpy as np

import rwwarp as rw
from _common import device_name, save, sync_fn, timed
from _deeplens import a489_hybridlens, deeplens_json  # noqa: F401  (deeplens_json: kept importable here)

FIELDS5 = [(0.0, f) for f in np.linspace(0.0, 10.0, 5)]
WLS = [0.45, 0.55, 0.65]


def gpu_used():
    try:
        import cupy
        free, total = cupy.cuda.runtime.memGetInfo()
        return total - free
    except Exception:
        return None


def host_peak():
    import resource
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def bench_rwwarp(device, size, repeat):
    lens = rw.load_lens("a489_doe")
    s = sync_fn(device)
    t0 = time.perf_counter()
    p = rw.psf(lens, 0.0, 0.55, size=size, device=device)
    s()
    first = time.perf_counter() - t0
    base = gpu_used()
    out = {"first_call_s": first, "plan": p.plan}
    out["psf_on_axis_s"] = timed(lambda: rw.psf(lens, 0.0, 0.55, size=size, device=device), s, repeat)
    out["psf_7deg_s"] = timed(lambda: rw.psf(lens, 7.0, 0.55, size=size, device=device), s, repeat)
    m = {}

    def run_map():
        m["m"] = rw.psf_map(lens, FIELDS5 * 5, WLS, size=size, device=device, batch=15)

    t0 = time.perf_counter()
    run_map()  # cold: FFT plans and kernel builds for the map's batch shapes
    s()
    out["map_5x5x3_cold_s"] = time.perf_counter() - t0
    out["map_5x5x3_s"] = timed(run_map, s, max(1, repeat // 2))
    used = gpu_used()
    out["device_mem_used_bytes"] = None if used is None or base is None else used
    out["host_peak_rss_bytes"] = host_peak()
    return out, p


def bench_deeplens(device, repeat):
    import torch
    lens = a489_hybridlens(device)
    s = (lambda: torch.cuda.synchronize()) if device.startswith("cuda") else (lambda: None)
    out = {}
    res = {}
    for spp in (1_000_000, 16_777_216):
        with torch.no_grad():
            torch.cuda.reset_peak_memory_stats() if device.startswith("cuda") else None
            f = lambda: res.__setitem__(spp, lens.psf(points=[0.0, 0.0, -10000.0], ks=64, wvln=0.55, spp=spp))
            f()
            t = timed(f, s, repeat)
            out[f"psf_{spp}_s"] = t
            if device.startswith("cuda"):
                out[f"psf_{spp}_peak_bytes"] = torch.cuda.max_memory_allocated()
    with torch.no_grad():
        def loop():
            for fy in np.linspace(0, 10.0 / 14.0, 5):
                for _ in range(5):
                    for w in WLS:
                        lens.psf(points=[0.0, float(fy), -10000.0], ks=64, wvln=w, spp=1_000_000)
        t0 = time.perf_counter()
        loop()
        s()
        out["map_5x5x3_1M_s"] = time.perf_counter() - t0
    return out, {k: v.detach().cpu().numpy() for k, v in res.items()}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--deeplens", action="store_true")
    a = ap.parse_args()
    res = {"benchmark": "psf", "lens": "a489_doe (flat DOE), object at 10 m", "device": a.device,
           "device_name": device_name(a.device), "size_px": a.size, "pixel_um": 1.0}
    r, p = bench_rwwarp(a.device, a.size, a.repeat)
    res["rwwarp"] = r
    print("rwwarp:", json.dumps({k: v for k, v in r.items() if k != "plan"}, default=float))
    if a.deeplens:
        try:
            dl, psfs = bench_deeplens("cuda" if a.device.startswith("cuda") else "cpu", a.repeat)
            ours = p.data / p.data.sum()
            for spp, d in psfs.items():
                d = np.asarray(d, dtype=np.float64)
                d = d / d.sum()
                dl[f"rel_l2_vs_rwwarp_{spp}"] = float(np.linalg.norm(d - ours) / np.linalg.norm(ours))
            res["deeplens"] = dl
            res["ratios"] = {"psf_speedup_vs_1M": dl["psf_1000000_s"] / r["psf_on_axis_s"],
                             "psf_speedup_vs_16M": dl["psf_16777216_s"] / r["psf_on_axis_s"],
                             "map_speedup_vs_1M": dl["map_5x5x3_1M_s"] / r["map_5x5x3_s"]}
            print("deeplens:", json.dumps(dl, default=float))
            print("ratios:", res["ratios"])
        except Exception as e:  # report, don't hide
            import traceback
            res["deeplens_error"] = f"{type(e).__name__}: {e}"
            traceback.print_exc()
            print("deeplens failed:", res["deeplens_error"])
    tag = "gpu" if a.device.startswith("cuda") else "cpu"
    print("->", save(f"bench_psf_{tag}", res))


if __name__ == "__main__":
    main()
