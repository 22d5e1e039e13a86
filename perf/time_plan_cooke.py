"""Planning time of the ``cooke_hybrid`` design step on the CPU: the ``gpu`` preset's e2e arm (the paraxial achromat
start), its 16 field nodes (4 x 4 grid, quadrant) x 3 wavelengths (one per colour channel: 0.63, 0.55, 0.47 um),
63 px of 4 um, every source planned on its own with ``method="focal"`` from one pilot trace, as
:class:`torch_bridge.live.LiveProvider` plans them (:meth:`torch_bridge.HybridLens.raywaves_alone`). The first
call (kernel builds) is reported apart; then ``--runs`` calls, wall and process CPU time (ms) and their medians; ``--profile``:
a cProfile of one more call (cumulative, top ``--top`` rows). Compare trees by alternating
``PYTHONPATH=TREE python perf/time_plan_cooke.py``.
"""
import argparse
import cProfile
import pstats
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def setup():
    """(module, fields, wavelengths, centres, size, pixel) of the gpu preset's e2e arm on the CPU."""
    import numpy as np
    from torch_bridge import design as dz
    from torch_bridge import train as T
    from torch_bridge.live import common_centres
    import torch_bridge as tb
    exp = T.load_config("cooke_hybrid", "gpu")
    a = next(a for a in exp["arms"] if a["name"] == "e2e")
    cfg = a["config"]
    o = cfg["optics"]
    lens = T.build_lens(cfg, exp["source"])
    from torch_bridge.ray_spot import with_paraxial_achromat
    lens = with_paraxial_achromat(lens, [w for c in o["wavelengths_um"] for w in c])
    m = tb.HybridLens(lens, learn=T._learn_dict(o["learn"]), nyquist_safety=o["nyquist_safety"],
                      rays_per_sample=o["rays_per_sample"], method=o["propagation"],
                      focal_patch_tol=o["focal_patch_tol"])
    pixel = o["pixel_um"] * 1e-3
    wls = [[float(w) for w in c] for c in o["wavelengths_um"]]
    wl_ref = wls[1][1]
    nd = o["nodes"]
    pos = dz.node_positions_mm(nd["layout"], nd["half_size_mm"], nd["grid"], nd["fractions"], nd["region"])
    nodes = dz.field_angles(lens, pos, wl_ref)
    step = [c[1] for c in wls]                     # one wavelength per channel
    fields = [f for f in nodes for _ in step]
    ws = [w for _ in nodes for w in step]
    centres = np.repeat(common_centres(m, nodes, wl_ref), len(step), axis=0)
    return m, fields, ws, centres, int(o["psf_size"]), pixel


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--profile", action="store_true")
    ap.add_argument("--top", type=int, default=30)
    args = ap.parse_args()
    m, fields, ws, centres, size, pixel = setup()
    plan = lambda: m.raywaves_alone(fields, ws, size, centers_mm=centres, pixel_mm=pixel, method="focal")
    t0 = time.perf_counter()
    rs = plan()
    first = time.perf_counter() - t0
    times, cpu = [], []
    for _ in range(args.runs):
        t0, c0 = time.perf_counter(), time.process_time()
        rs = plan()
        times.append((time.perf_counter() - t0) * 1e3)
        cpu.append((time.process_time() - c0) * 1e3)
    print(f"first call {first:.3f} s; {len(rs)} sources planned ({rs[0].plan.method}, n_grid "
          f"{min(r.plan.n_grid for r in rs)}..{max(r.plan.n_grid for r in rs)}, "
          f"ray_grid {min(r.plan.ray_grid for r in rs)}..{max(r.plan.ray_grid for r in rs)})")
    print(f"wall ms {[round(t, 1) for t in times]} median {statistics.median(times):.1f} ms "
          f"({statistics.median(times) / len(rs):.2f} ms a source); process CPU ms {[round(t, 1) for t in cpu]} "
          f"median {statistics.median(cpu):.1f} ms")
    if args.profile:
        pr = cProfile.Profile()
        pr.enable()
        plan()
        pr.disable()
        pstats.Stats(pr).sort_stats("cumulative").print_stats(args.top)
        pstats.Stats(pr).sort_stats("tottime").print_stats(args.top)


if __name__ == "__main__":
    main()
