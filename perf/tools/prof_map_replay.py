"""cProfile of a replayed 10 x 10 x 3 A489 + DOE map, 64 px (a rw.PlanCache hit: no planning; the kept batches'
trace and splat replayed as CUDA graphs, their stacked focal propagations eager): where a hit's time goes.
    python perf/tools/prof_map_replay.py   (on a GPU machine)"""
import cProfile, pstats, time, warnings
warnings.simplefilter("ignore")
import numpy as np, rwwarp as rw, cupy
lens = rw.load_lens("a489_doe")
u = np.linspace(-0.9, 0.9, 10) * 10.0
fields = [(float(x), float(y)) for y in u for x in u]
wls = [0.45, 0.55, 0.65]
cache = rw.PlanCache()
for _ in range(3):
    m = rw.psf_map(lens, fields, wls, device="cuda", size=64, cache=cache)
print("replay", m.info.get("cache"), m.info.get("replay"))
cupy.cuda.Device().synchronize()
t0 = time.perf_counter(); rw.psf_map(lens, fields, wls, device="cuda", size=64, cache=cache); print("hit s", time.perf_counter() - t0)
pr = cProfile.Profile(); pr.enable(); rw.psf_map(lens, fields, wls, device="cuda", size=64, cache=cache); pr.disable()
st = pstats.Stats(pr); st.sort_stats("cumulative").print_stats(35); st.sort_stats("tottime").print_stats(25)
