"""The A/B table of this directory's README from its wr*_*.json (run.sh's warm_repeats.py outputs) and the PSF
check: every tree's map against the reference's (``--ref``, a .npy of perf/bench_map.py's 300 PSFs), bit for bit
and as max |diff| / each PSF's peak.

    python summarize.py DIR [--ref DIR/wr1_s22_b9.npy] [--json OUT.json]
"""
import argparse, glob, json, os
from collections import defaultdict

import numpy as np

ap = argparse.ArgumentParser()
ap.add_argument("dir")
ap.add_argument("--ref")
ap.add_argument("--json")
a = ap.parse_args()
rows = defaultdict(list)
psf = {}
for f in sorted(glob.glob(os.path.join(a.dir, "wr*_*.json"))):
    d = json.load(open(f))
    name = os.path.basename(f)[:-5].split("_", 1)[1]   # TREE_bBATCH
    rows[name].append({"file": os.path.basename(f), "commit": d["commit"], "cold_s": d["cold_s"],
                       "warm_s": [r["wall_s"] for r in d["warm"]], "cpu_s": [r["cpu_s"] for r in d["warm"]],
                       "load": [[r["load_start"], r["load_end"]] for r in d["warm"]],
                       "n_batches": d["n_batches"], "max_rss_gib": d["max_rss_bytes"] / 2 ** 30})
    npy = f[:-5] + ".npy"
    if a.ref and os.path.exists(npy):
        x, r = np.load(npy), np.load(a.ref)
        pk = r.max(axis=(-2, -1), keepdims=True)
        psf.setdefault(name, []).append({"file": os.path.basename(npy), "equal": bool(np.array_equal(x, r)),
                                         "max_rel_diff": float((np.abs(x - r) / pk).max())})
out = {}
for name, rs in rows.items():
    w = [t for r in rs for t in r["warm_s"]]
    out[name] = {"commit": rs[0]["commit"], "n_batches": rs[0]["n_batches"], "warm_s": w, "least_s": min(w),
                 "median_s": float(np.median(w)), "runs": rs, "psf_vs_ref": psf.get(name)}
    eq = psf.get(name)
    print(f"{name:14s} {rs[0]['commit']} batches {rs[0]['n_batches']:3d}: warm " + " / ".join(f"{t:.1f}" for t in w)
          + f" s, least {min(w):.1f}, median {np.median(w):.1f}"
          + ("" if not eq else f"; PSFs equal ref: {[e['equal'] for e in eq]}, max rel {max(e['max_rel_diff'] for e in eq):.2g}"))
if a.json:
    json.dump({"ref": a.ref and os.path.basename(a.ref), "trees": out}, open(a.json, "w"), indent=1)
