# Session 24 study (see README.md): run from the tree root with PYTHONPATH=TREE; scratch files in /tmp/mp (truth_rs.py FIELD_INDEX WL RADIAL ANGULAR writes the truths and patch centres the studies read).
import os, sys, time, warnings
sys.path.insert(0, os.path.join(os.getcwd(), "perf"))
warnings.simplefilter("ignore")
import numpy as np, rwwarp as rw
from rwwarp.ground_truth import rs_lens_psf
from bench_map import WLS, field_grid
lens = rw.load_lens("a489_doe")
fields, _ = field_grid(10, lens)
fi, wl, rn, an = int(sys.argv[1]), float(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
p = rw.psf(lens, fields[fi], wl, size=32)
t0 = time.perf_counter()
T = rs_lens_psf(lens, fields[fi], wl, p.center_mm, 32, p.pixel_mm, radial_nodes=rn, angular_nodes=an)
print("truth s", time.perf_counter() - t0, "field", fields[fi], "center", p.center_mm)
np.save(f"/tmp/mp/truth_{fi}_{wl}_{rn}.npy", T); np.save(f"/tmp/mp/center_{fi}_{wl}.npy", np.array(p.center_mm))
print("default err maxpeak", np.abs(p.data - T).max() / T.max(), "rel", np.linalg.norm(p.data - T) / np.linalg.norm(T))
