"""Focal propagation on a CUDA device: warm time per PSF and agreement with the CPU result.

    python perf/bench_focal_gpu.py OUT_DIR

Writes ``focal_gpu.json``: per case the warm time (median of 5), the plan, the relative L2 difference
between the CUDA PSF (Warp CUDA + CuPy) and the CPU PSF (Warp CPU + numpy) of the same plan, and the
GPU's name.
"""
import json
import os
import sys
import time

import numpy as np

import rwwarp as rw


def main(out_dir):
    import cupy
    dev = cupy.cuda.runtime.getDeviceProperties(0)["name"].decode()
    commit = __import__("_common").git_commit()   # $RWWARP_COMMIT on a copied tree
    res = {"device": dev, "commit": commit, "cases": {}}
    cases = [("cooke_triplet", 0.0, 0.5876, 64), ("cooke_triplet", 14.0, 0.5876, 64), ("ac254_100_a", 0.0, 0.5876, 64),
             ("a489_doe", 0.0, 0.55, 64), ("a489_doe", 10.0, 0.55, 64)]
    for name, field, wl, size in cases:
        lens = rw.load_lens(name)
        row = {}
        for method in ("focal", "asm"):
            if method == "asm" and name != "a489_doe":
                continue
            p = rw.psf(lens, field, wl, size=size, device="cuda", method=method)
            ts = []
            for _ in range(5):
                cupy.cuda.Device(0).synchronize()
                t = time.perf_counter()
                p = rw.psf(lens, field, wl, size=size, device="cuda", method=method)
                ts.append(time.perf_counter() - t)
            entry = {"warm_s_median": float(np.median(ts)), "warm_s_min": float(np.min(ts)),
                     "plan": {k: p.plan[k] for k in ("method", "n_grid", "ray_grid", "n_pad", "n_sensor", "n_sensor_fft")},
                     "sum": float(p.data.sum())}
            if method == "focal" and name != "cooke_triplet" or (name == "cooke_triplet" and field == 0.0):
                q = rw.psf(lens, field, wl, size=size, device="cpu", method=method)
                entry["rel_l2_cuda_vs_cpu"] = float(np.linalg.norm(p.data - q.data) / np.linalg.norm(q.data))
            row[method] = entry
            print(name, field, method, json.dumps(entry), flush=True)
        res["cases"][f"{name}@{field:g}deg"] = row
    with open(os.path.join(out_dir, "focal_gpu.json"), "w") as fh:
        json.dump(res, fh, indent=1)


if __name__ == "__main__":
    main(sys.argv[1])
