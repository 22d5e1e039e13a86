"""Summarise the A/B rounds (wr<round>_<tree>_t<tol>.json in the directory given, .npy PSFs beside them) into
ab_session24.json: least / median warm wall and CPU seconds per tree, their ratios, the planned sizes, and each
tree's PSFs against the baseline's (max |diff| over each PSF's peak, over the 300 PSFs)."""
import glob, json, os, sys
import numpy as np

src = sys.argv[1]
out = sys.argv[2] if len(sys.argv) > 2 else os.path.join(os.path.dirname(os.path.abspath(__file__)), "ab_session24.json")
runs = {}
for f in sorted(glob.glob(os.path.join(src, "wr*_*.json"))):
    tree = os.path.basename(f)[:-5].split("_", 1)[1]
    d = json.load(open(f))
    runs.setdefault(tree, []).append((os.path.basename(f), d))
res = {"trees": {}}
base = None
for tree, rs in runs.items():
    walls = [w["wall_s"] for _, d in rs for w in d["warm"]]
    cpus = [w["cpu_s"] for _, d in rs for w in d["warm"]]
    loads = [(w["load_start"], w["load_end"]) for _, d in rs for w in d["warm"]]
    d0 = rs[0][1]
    res["trees"][tree] = {"files": [n for n, _ in rs], "warm_wall_s": walls, "warm_cpu_s": cpus, "loads": loads,
                          "least_wall_s": min(walls), "median_wall_s": float(np.median(walls)),
                          "least_cpu_s": min(cpus), "median_cpu_s": float(np.median(cpus)),
                          "rays": d0.get("rays"), "wave_plane_samples": d0.get("wave_plane_samples"),
                          "wave_steps": d0.get("wave_steps"), "tolerance": d0.get("tolerance"),
                          "max_rss_gib": max(d["max_rss_bytes"] for _, d in rs) / 2 ** 30}
names = list(res["trees"])
old = [n for n in names if n.startswith("old")]
new = [n for n in names if n.startswith("new")]
if old and new:
    o, n = res["trees"][old[0]], res["trees"][new[0]]
    res["ratio_least_wall"] = o["least_wall_s"] / n["least_wall_s"]
    res["ratio_median_wall"] = o["median_wall_s"] / n["median_wall_s"]
    res["ratio_least_cpu"] = o["least_cpu_s"] / n["least_cpu_s"]
    res["ratio_median_cpu"] = o["median_cpu_s"] / n["median_cpu_s"]
    a = np.load(os.path.join(src, o["files"][0][:-5] + ".npy"))
    b = np.load(os.path.join(src, n["files"][0][:-5] + ".npy"))
    e = np.abs(b - a).max(axis=(2, 3)) / a.max(axis=(2, 3))
    res["psf_new_vs_old"] = {"max": float(e.max()), "median": float(np.median(e)),
                             "max_per_wavelength": e.max(axis=0).tolist(),
                             "worst": [int(i) for i in np.unravel_index(e.argmax(), e.shape)]}
    for t, fs in ((o, old), (n, new)):   # repeat runs of one tree: the same bits?
        arrs = [np.load(os.path.join(src, f[:-5] + ".npy")) for f in t["files"]]
        t["runs_equal"] = all(np.array_equal(arrs[0], x) for x in arrs[1:])
json.dump(res, open(out, "w"), indent=1)
print(json.dumps({k: v for k, v in res.items() if k != "trees"}, indent=1))
for k, v in res["trees"].items():
    print(k, {x: v[x] for x in ("least_wall_s", "median_wall_s", "least_cpu_s", "median_cpu_s", "rays", "wave_plane_samples", "wave_steps")})
