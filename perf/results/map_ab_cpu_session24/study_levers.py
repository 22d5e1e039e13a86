# Session 24 study (see README.md): run from the tree root with PYTHONPATH=TREE; scratch files in /tmp/mp (truth_rs.py FIELD_INDEX WL RADIAL ANGULAR writes the truths and patch centres the studies read).
import os, sys, time, warnings, json
sys.path.insert(0, os.path.join(os.getcwd(), "perf"))
warnings.simplefilter("ignore")
import numpy as np, rwwarp as rw
import rwwarp.wave.plan as P
from bench_map import WLS, field_grid
lens = rw.load_lens("a489_doe")
fields, _ = field_grid(10, lens)
fi, wl = int(sys.argv[1]), float(sys.argv[2])
c = tuple(np.load(f"/tmp/mp/center_{fi}_{wl}.npy"))
tf = f"/tmp/mp/truth_{fi}_{wl}_64.npy"
T = np.load(tf) if os.path.exists(tf) else None
def run(rs, rim, safety=2.0):
    P.FOCAL_RAY_SPREAD, P.FOCAL_RIM_RAYS = rs, rim
    t0 = time.perf_counter()
    p = rw.psf(lens, fields[fi], wl, size=32, center_mm=c, nyquist_safety=safety)
    return p, time.perf_counter() - t0
ref, tr = run(28.0, 800, 3.0)
print("ref plan", ref.plan["n_grid"], ref.plan["ray_grid"], f"{tr:.1f}s")
if T is not None:
    print("ref vs truth maxpeak %.3g" % (abs(ref.data - T).max() / T.max()))
for rs, rim, sf in [(14, 400, 2), (7, 400, 2), (3.5, 400, 2), (0, 400, 2), (14, 200, 2), (14, 100, 2), (14, 50, 2), (7, 100, 2), (14, 400, 1.5), (14, 400, 1.0)]:
    p, t = run(rs, rim, sf)
    e = abs(p.data - ref.data).max() / ref.data.max()
    et = abs(p.data - T).max() / T.max() if T is not None else float("nan")
    print(f"rs {rs:5} rim {rim:4} safety {sf}: n_grid {p.plan['n_grid']:5} rays {p.plan['ray_grid']:4} n_s {p.plan['n_sensor']}  err vs ref {e:.3g}  vs truth {et:.3g}  {t:.2f}s")
