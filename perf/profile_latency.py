"""Where one PSF's latency goes on a device: the warm ``rw.psf`` call planned every time and through a
:class:`rwwarp.PlanCache` (issue 25: <= 2 ms at 64 px on an H100), Warp launches a call, stage timings
(synchronised) and a cProfile by own time.

    python perf/profile_latency.py cuda [--lens a489_doe] [--field 0] [--size 64] [--reps 20]
    python perf/profile_latency.py cuda --issue25 [--json perf/results/latency_gpu.json]   # the issue's five PSFs

``--issue25``: Cooke triplet 0 / 14 deg, AC254 0 deg, A489 0 / 10 deg at 0.55 um, ``--size`` px: per PSF the
uncached and cached warm medians and minima (ms) and the Warp launches of each call; no stages or profile.
"""
import argparse
import cProfile
import json
import pstats
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import rwwarp as rw  # noqa: E402
from rwwarp.psf import RayWave  # noqa: E402

ISSUE25 = [("cooke_triplet", 0.0), ("cooke_triplet", 14.0), ("ac254_100_a", 0.0), ("a489_doe", 0.0), ("a489_doe", 10.0)]


def sync(device):
    if device.startswith("cuda"):
        import warp as wp
        wp.synchronize()
        try:
            import cupy
            cupy.cuda.Device().synchronize()
        except ImportError:
            pass


def warm_times(lens, field, wl, device, size, reps, cache=None, method="auto"):
    """(median ms, min ms, launches a call) of repeated ``rw.psf`` calls after 3 warm-up calls."""
    kw = dict(device=device, size=size, cache=cache, method=method)
    for _ in range(3):
        rw.psf(lens, field, wl, **kw)
    sync(device)
    t = []
    for _ in range(reps):
        t0 = time.perf_counter()
        rw.psf(lens, field, wl, **kw)
        sync(device)
        t.append(time.perf_counter() - t0)
    from _common import count_warp_launches
    n = count_warp_launches(lambda: rw.psf(lens, field, wl, **kw))
    return 1e3 * float(np.median(t)), 1e3 * float(np.min(t)), n


def _has_graphs() -> bool:
    """True when the rwwarp imported replays cached batches as CUDA graphs (PlanCache(graphs=))."""
    import inspect
    return "graphs" in inspect.signature(rw.PlanCache).parameters


def issue25(a):
    rows = []
    for (name, field), method in ((c, m) for c in ISSUE25 for m in a.methods.split(",")):
        lens = rw.load_lens(name)
        plain = warm_times(lens, field, a.wl, a.device, a.size, a.reps, method=method)
        eager_cache = rw.PlanCache(graphs=False) if _has_graphs() else rw.PlanCache()
        cached = warm_times(lens, field, a.wl, a.device, a.size, a.reps, eager_cache, method=method)
        row = {}
        if _has_graphs():   # the same, each hit replayed as a CUDA graph (rwwarp.wave.graph_replay)
            cache = rw.PlanCache()
            graph = warm_times(lens, field, a.wl, a.device, a.size, a.reps, cache, method=method)
            p = rw.psf(lens, field, a.wl, device=a.device, size=a.size, cache=cache, method=method)
            row = {"graph_median_ms": graph[0], "graph_min_ms": graph[1], "graph_launches": graph[2],
                   "replay": p.info.get("replay")}
            ref = rw.psf(lens, field, a.wl, device=a.device, size=a.size, method=method)
            row["graph_vs_uncached_max_rel"] = float(np.max(np.abs(p.data - ref.data)) / np.max(ref.data))
        else:
            cache = eager_cache
            p = rw.psf(lens, field, a.wl, device=a.device, size=a.size, cache=cache, method=method)
        rows.append({"lens": name, "field_deg": field, "asked": method, "method": p.plan["method"], "n_grid": p.plan["n_grid"],
                     "ray_grid": p.plan["ray_grid"], "uncached_median_ms": plain[0], "uncached_min_ms": plain[1],
                     "uncached_launches": plain[2], "cached_median_ms": cached[0], "cached_min_ms": cached[1],
                     "cached_launches": cached[2], "cache_held_bytes": cache.nbytes(), **row})
        r = rows[-1]
        print(f"{name:14s} {field:5.1f} deg {method:5s}->{r['method']:5s} grid {r['n_grid']:5d} rays {r['ray_grid']:4d}: "
              f"uncached {plain[0]:8.2f} ms (min {plain[1]:.2f}, {plain[2]} launches), cached {cached[0]:8.2f} ms "
              f"(min {cached[1]:.2f}, {cached[2]} launches), cache holds {cache.nbytes() / 2 ** 20:.3g} MiB"
              + (f"; graph replay {row['graph_median_ms']:8.3f} ms (min {row['graph_min_ms']:.3f}, "
                 f"{row['graph_launches']} launches, {row['replay']}, vs uncached {row['graph_vs_uncached_max_rel']:.2e})"
                 if row else ""), flush=True)
    if a.json:
        from _common import git_commit
        commit = git_commit()   # $RWWARP_COMMIT on a copied tree
        out = {"commit": commit, "device": a.device, "size": a.size, "wavelength_um": a.wl, "reps": a.reps, "rows": rows}
        try:
            import warp as wp
            out["device_name"] = wp.get_device(a.device if a.device.startswith("cuda") else "cpu").name
        except Exception:  # noqa: BLE001
            pass
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        Path(a.json).write_text(json.dumps(out, indent=1) + "\n")
        print(f"wrote {a.json}")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("device", nargs="?", default="cpu")
    ap.add_argument("--lens", default="a489_doe")
    ap.add_argument("--field", type=float, default=0.0)
    ap.add_argument("--wl", type=float, default=0.55)
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--reps", type=int, default=20)
    ap.add_argument("--issue25", action="store_true", help="the issue's five PSFs, uncached and cached")
    ap.add_argument("--methods", default="auto",
                    help="--issue25: comma-separated propagation methods to time each PSF with (e.g. auto,focal)")
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    warnings.simplefilter("ignore")
    if a.issue25:
        return issue25(a)
    lens = rw.load_lens(a.lens)
    med, mn, n = warm_times(lens, a.field, a.wl, a.device, a.size, a.reps)
    print(f"rw.psf median {med:.2f} ms, min {mn:.2f} ms over {a.reps}, {n} Warp launches a call")
    cache = rw.PlanCache()
    med, mn, n = warm_times(lens, a.field, a.wl, a.device, a.size, a.reps, cache)
    print(f"rw.psf with a PlanCache: median {med:.2f} ms, min {mn:.2f} ms over {a.reps}, {n} Warp launches a call "
          f"({cache})")
    # stages
    stages = {"init": [], "field": [], "intensity": []}
    for _ in range(a.reps):
        t0 = time.perf_counter()
        r = RayWave(lens, [(0.0, a.field)], [a.wl], a.size, lens.sensor.pixel_pitch, device=a.device)
        sync(a.device)
        t1 = time.perf_counter()
        u = r.field_array()
        sync(a.device)
        t2 = time.perf_counter()
        phi0, scale = r.doe_phase()
        r.intensity(u, phi0, scale)
        sync(a.device)
        t3 = time.perf_counter()
        stages["init"].append(t1 - t0)
        stages["field"].append(t2 - t1)
        stages["intensity"].append(t3 - t2)
    print("stages of an asm RayWave (median ms): " + ", ".join(f"{k} {1e3 * np.median(v):.2f}" for k, v in stages.items()))
    for label, c in (("uncached", None), ("cached", cache)):
        pr = cProfile.Profile()
        pr.enable()
        for _ in range(5):
            rw.psf(lens, a.field, a.wl, device=a.device, size=a.size, cache=c)
        sync(a.device)
        pr.disable()
        print(f"---- cProfile, 5 {label} calls")
        pstats.Stats(pr).sort_stats("tottime").print_stats(25)


if __name__ == "__main__":
    main()
