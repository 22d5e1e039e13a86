"""Rays per second through the Cooke triplet (6 surfaces + sensor), float64, at 1M and 16M rays.

Reports compile time apart from run time, and the memory-bandwidth floor: each surface launch reads
and writes one ray (pos, dir, opl, valid, wl: 64 B in, 60 B out), over the copy bandwidth measured
with ``wp.copy`` on the same device.

    python perf/bench_trace.py [--device cuda] [--sizes 1000000 16000000]
"""
import argparse
import math
import time

import warp as wp

from rwwarp.io import load_lens
from rwwarp.trace import Tracer, pupil_grid  # noqa: F401

from _common import device_name, save, timed


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--sizes", type=int, nargs="+", default=[1_000_000, 16_000_000])
    ap.add_argument("--dtype", default="float64")
    ap.add_argument("--repeat", type=int, default=5)
    a = ap.parse_args()
    lens = load_lens("cooke_triplet")
    t0 = time.perf_counter()
    tr = Tracer(lens, [0.5875618], device=a.device, dtype=a.dtype)
    src = tr.sources([14.0])
    u, v, cell = pupil_grid(8, "circle")
    tr._run(src, u, v, cell)  # compiles (or loads from the kernel cache)
    wp.synchronize_device(tr.device)
    compile_s = time.perf_counter() - t0
    dev = tr.device
    # copy bandwidth: 256 MB (device) / 64 MB (cpu) float64 copy
    nbw = (32 if dev.startswith("cuda") else 8) * 1_000_000
    x = wp.zeros(nbw, dtype=wp.float64, device=dev)
    y = wp.zeros(nbw, dtype=wp.float64, device=dev)
    bw_t = timed(lambda: wp.copy(y, x), lambda: wp.synchronize_device(dev), 5)
    bandwidth = 2 * 8 * nbw / bw_t
    x = y = None  # free the bandwidth buffers
    rows = []
    n_launch = len(lens.surfaces) + 1
    for n in a.sizes:
        g = int(math.ceil(math.sqrt(n)))
        nr = g * g  # full square grid generated on the device; samples outside the pupil start invalid
        valid = {}
        t = timed(lambda: valid.setdefault("r", tr._run(src, None, None, (2.0 / g) ** 2, grid_n=g)),
                  lambda: wp.synchronize_device(dev), a.repeat)
        n_valid = int(valid["r"].count_valid()[0])
        bytes_moved = nr * (124 * n_launch + 60)
        floor = bytes_moved / bandwidth
        rows.append({"rays": nr, "valid_rays": n_valid, "time_s": t, "rays_per_s": nr / t, "floor_s": floor,
                     "fraction_of_floor": floor / t})
        print(f"{nr:>10d} rays ({n_valid} in the pupil): {t * 1e3:9.2f} ms  {nr / t / 1e6:8.2f} Mrays/s  "
              f"floor {floor * 1e3:.2f} ms ({t / floor:.1f}x the floor)")
    res = {"benchmark": "trace", "lens": "cooke_triplet (6 surfaces + sensor, 14 deg)", "device": a.device,
           "device_name": device_name(a.device), "dtype": a.dtype, "compile_or_load_s": compile_s,
           "copy_bandwidth_GBps": bandwidth / 1e9, "launches_per_trace": n_launch + 1, "results": rows}
    p = save(f"bench_trace_{'gpu' if a.device.startswith('cuda') else 'cpu'}", res)
    print(f"compile/load {compile_s:.2f} s, copy bandwidth {bandwidth / 1e9:.1f} GB/s -> {p}")


if __name__ == "__main__":
    main()
