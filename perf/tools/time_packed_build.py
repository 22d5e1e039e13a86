"""Host and device time of building the stacked focal operators of the ``cooke_hybrid`` design step's packed tiles
(:meth:`rwwarp.wave.focal_packed.PackedFocalPropagator.from_members`), by section, on a device.

    python perf/tools/time_packed_build.py --device cuda [--members 7] [--reps 10]

Plans the gpu preset's 48 sources (``perf/time_plan_cooke.py``'s setup) on ``--device``, groups them in tiles of
``--members`` as the live provider does, and builds each tile's operator ``--reps`` times: the host time of a build
(no synchronisation inside), the time until the device has finished it, and a cProfile of the builds by own time.
"""
import argparse
import cProfile
import io
import pstats
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--members", type=int, default=7)
    ap.add_argument("--reps", type=int, default=10)
    a = ap.parse_args()
    from time_plan_cooke import setup
    from rwwarp.wave.focal_packed import PackedFocalPropagator
    m, fields, ws, centres, size, pixel = setup()
    if a.device != "cpu":
        m = m.to(a.device)
    rs = m.raywaves_alone(fields, ws, size, centers_mm=centres, pixel_mm=pixel, method="focal")
    tiles = [rs[k:k + a.members] for k in range(0, len(rs), a.members)]
    sync = lambda: None
    if a.device.startswith("cuda"):
        import cupy
        sync = cupy.cuda.Device().synchronize
    z = float(rs[0].z_sensor - rs[0].z_plane)
    for t in tiles:   # warm: kernels compiled, pools filled
        PackedFocalPropagator.from_members(t, z)
    sync()
    host, total = [], []
    for _ in range(a.reps):
        for t in tiles:
            t0 = time.perf_counter()
            PackedFocalPropagator.from_members(t, z)
            host.append(time.perf_counter() - t0)
            sync()
            total.append(time.perf_counter() - t0)
    med = lambda v: sorted(v)[len(v) // 2] * 1e3
    print(f"{len(tiles)} tiles of {a.members}; build per tile: host {med(host):.2f} ms, to the device's end "
          f"{med(total):.2f} ms (medians of {len(host)})")
    pr = cProfile.Profile()
    pr.enable()
    for t in tiles:
        PackedFocalPropagator.from_members(t, z)
    sync()
    pr.disable()
    s = io.StringIO()
    pstats.Stats(pr, stream=s).sort_stats("tottime").print_stats(25)
    print(s.getvalue())


if __name__ == "__main__":
    main()
