"""Planning time of ``HybridLens.raywaves_alone`` (the live provider's re-planning: every source on its own focal
plan from one pilot trace) for the ``cooke_hybrid`` lens, 12 sources (4 diagonal nodes x 3 wavelengths, 31 px of
4 um), on the CPU. The first call (kernel builds) is reported apart; then ``--runs`` calls, wall and process CPU
time (s) and their medians. Compare trees by alternating ``PYTHONPATH=TREE python perf/time_raywaves_alone.py``.
"""
import argparse
import pathlib
import statistics
import time

import numpy as np

import rwwarp as rw
import torch_bridge as tb
from torch_bridge.live import common_centres


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args()
    lens = rw.load_lens(str(pathlib.Path(tb.__file__).parent / "configs/lenses/cooke_hybrid.json"))
    m = tb.HybridLens(lens, learn={"doe": "all", "thickness": [6]}, method="auto", focal_patch_tol=1e-3,
                      nyquist_safety=1.0)
    nodes = [(0.0, 0.0), (0.0, 3.0), (3.0, 3.0), (0.0, 6.0)]     # deg
    wls = [0.52, 0.55, 0.58]                                     # um
    fields = [f for f in nodes for _ in wls]
    ws = [w for _ in nodes for w in wls]
    centres = np.repeat(common_centres(m, nodes, 0.55), len(wls), axis=0)
    times = []
    for _ in range(args.runs + 1):
        t0, c0 = time.perf_counter(), time.process_time()
        rs = m.raywaves_alone(fields, ws, 31, centers_mm=centres, pixel_mm=0.004, method="focal")
        times.append((time.perf_counter() - t0, time.process_time() - c0))
    wall, cpu = [t for t, _ in times[1:]], [c for _, c in times[1:]]
    print(f"first call {times[0][0]:.3f} s; {len(rs)} sources planned ({rs[0].plan.method}, "
          f"{rs[0].plan.n_grid}^2 .. {rs[-1].plan.n_grid}^2 samples)")
    print(f"wall {[round(t, 4) for t in wall]} median {statistics.median(wall):.4f} s | "
          f"cpu {[round(t, 4) for t in cpu]} median {statistics.median(cpu):.4f} s")


if __name__ == "__main__":
    main()
