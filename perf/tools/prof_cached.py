"""cProfile of warm rw.psf hits with a PlanCache on CUDA (Cooke 14 deg auto, A489 on axis focal; 64 px): where a
replayed call's host time goes.  python perf/tools/prof_cached.py  (on a GPU machine)"""
import cProfile, pstats, sys, time, warnings
warnings.simplefilter("ignore")
import numpy as np, rwwarp as rw, warp as wp, cupy
for name, field, method in [("cooke_triplet", 14.0, "auto"), ("a489_doe", 0.0, "focal")]:
    lens = rw.load_lens(name); cache = rw.PlanCache()
    kw = dict(device="cuda", size=64, cache=cache, method=method)
    for _ in range(5): rw.psf(lens, field, 0.55, **kw)
    wp.synchronize(); cupy.cuda.Device().synchronize()
    pr = cProfile.Profile(); pr.enable()
    t0 = time.perf_counter()
    for _ in range(50): rw.psf(lens, field, 0.55, **kw)
    wp.synchronize(); cupy.cuda.Device().synchronize()
    pr.disable(); print(name, field, method, "ms/call", (time.perf_counter()-t0)/50*1e3)
    st = pstats.Stats(pr); st.sort_stats("tottime").print_stats(28)
