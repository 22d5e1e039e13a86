# Session 24 study (see README.md): run from the tree root with PYTHONPATH=TREE; scratch files in /tmp/mp (truth_rs.py FIELD_INDEX WL RADIAL ANGULAR writes the truths and patch centres the studies read).
import os, sys, time, warnings
sys.path.insert(0, os.path.join(os.getcwd(), "perf"))
warnings.simplefilter("ignore")
import numpy as np, rwwarp as rw
import rwwarp.wave.plan as P
from bench_map import field_grid
lens = rw.load_lens("a489_doe")
fields, _ = field_grid(10, lens)
for spec in sys.argv[1:]:
    fi, wl = spec.split(":"); fi, wl = int(fi), float(wl)
    P.FOCAL_RAY_SPREAD, P.FOCAL_RIM_RAYS = 28.0, 800
    ref = rw.psf(lens, fields[fi], wl, size=32, nyquist_safety=3.0, gauss_nodes=8)
    P.FOCAL_RAY_SPREAD, P.FOCAL_RIM_RAYS = 14.0, 400
    c = ref.center_mm
    tf = f"/tmp/mp/truth_{fi}_{wl}_64.npy"
    T = np.load(tf) if os.path.exists(tf) else None
    for tol in (None, 1.6e-3, 3.2e-3, 6.4e-3, 1.28e-2, 0.2):
        p = rw.psf(lens, fields[fi], wl, size=32, center_mm=c, tolerance=tol)
        pl = p.plan
        e = abs(p.data - ref.data).max() / ref.data.max()
        et = abs(p.data - T).max() / T.max() if T is not None else float("nan")
        print(f"{fi} {wl} tol {tol} relax {P.sampling_relax(tol):.3g}: n_grid {pl['n_grid']} rays {pl['ray_grid']} n_s {pl['n_sensor']} nf {pl['n_sensor_fft']} err_ref {e:.3g} err_truth {et:.3g} share*tol {0.25 * tol if tol else float('nan'):.3g} ws {pl.get('wave_step_mm')}", flush=True)
