"""cProfile of rw.psf / rw.psf_map on a device: where the time goes (top functions by cumulative time)."""
import cProfile
import pstats
import sys
import os

os.environ.setdefault("RWWARP_PLAN_CACHE", "0")   # time the planned call, not rw.psf's default cache (perf/_common.py)

import rwwarp as rw

device = sys.argv[1] if len(sys.argv) > 1 else "cpu"
lens = rw.load_lens("a489_doe")
rw.psf(lens, 0.0, 0.55, size=64, device=device)
rw.psf_map(lens, [(0, 0), (0, 5)], [0.45, 0.55, 0.65], size=64, device=device, batch=3)
pr = cProfile.Profile()
pr.enable()
rw.psf_map(lens, [(0, 0), (0, 5)], [0.45, 0.55, 0.65], size=64, device=device, batch=3)
pr.disable()
pstats.Stats(pr).sort_stats("cumulative").print_stats(28)
pstats.Stats(pr).sort_stats("tottime").print_stats(14)
