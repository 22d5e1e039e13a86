"""Planning and memory figures of a design preset, on the CPU, without tracing at full size.

For every arm of a config preset: the node fields, the provider the training would use, and per
(depth, wavelength) entry the sampling plan (ray grid, DOE-plane grid, FFT size), the sources per
field-build batch under the memory budget and the library's own peak estimates
(:meth:`torch_bridge.design.CachedProvider.build_batch`; for a live provider the recorded
forward + backward bytes per source of :meth:`torch_bridge.HybridLens.bytes_per_source` and the
tile the budget gives). Only the pilot traces (31 x 31 rays per source) run.

    python perf/plan_memory.py a489_aberration --preset gpu [--budget-gb 39.6]

``--budget-gb``: the budget assumed when the config sets none (default 39.6 GB: half the free
memory of an idle 80 GB H100, what :func:`torch_bridge.modules.default_memory_budget_bytes` gives
there). Sizes in GB = 1e9 bytes.
"""
from __future__ import annotations

import argparse
import math
import sys
import warnings
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def plan_preset(config: str, preset: str, budget_gb: float, arms=None) -> list:
    """Rows (dicts) of the planning figures of every arm (or those named in ``arms``)."""
    import torch_bridge as tb
    from torch_bridge import design as dz
    from torch_bridge import train as T
    exp = T.load_config(config, preset)
    rows = []
    for a in exp["arms"]:
        if arms and a["name"] not in arms:
            continue
        cfg = a["config"]
        o = cfg["optics"]
        lens0 = T.build_lens(cfg, exp["source"])
        method = cfg["design"]["method"]
        learn = T._learn_dict(o["learn"]) if method in ("e2e", "rms") else {}
        live = T._refractive_learns(learn, lens0)
        lens = lens0
        if cfg["design"]["init"] in ("paraxial_achromat", "rms") or method == "paraxial_achromat":
            lens = T.Arm._achromat(type("A", (), {"cfg": cfg})(), lens)
        module = tb.HybridLens(lens, learn=learn, nyquist_safety=o["nyquist_safety"],
                               rays_per_sample=o["rays_per_sample"])
        pixel = (o["pixel_um"] * 1e-3) if o["pixel_um"] else lens.sensor.pixel_pitch
        size = int(o["psf_size"])
        wls = [[float(w) for w in c] for c in o["wavelengths_um"]]
        wl_ref = wls[len(wls) // 2][len(wls[0]) // 2]
        nd = o["nodes"]
        half = nd["half_size_mm"] or [0.5 * lens.sensor.resolution[0] * lens.sensor.pixel_pitch,
                                      0.5 * lens.sensor.resolution[1] * lens.sensor.pixel_pitch]
        pos = dz.node_positions_mm(nd["layout"], half, nd["grid"], nd["fractions"], nd["region"])
        fields = dz.field_angles(lens, pos, wl_ref)
        budget = T._budget_bytes(o) or int(budget_gb * 1e9)
        cache = o["cache_fields"]
        if cache == "auto" or method != "e2e":
            cache = not (method == "e2e" and live)
        allw = sorted({w for c in wls for w in c})
        depths = [T._depth_value(d) for d in o["depths_mm"]]
        if o["model"] == "paraxial-wave" or cache:
            prov = dz.CachedProvider(module, fields, size, pixel, model=o["model"], wavelength_ref_um=wl_ref,
                                     doe_budget_cpmm=o["doe_budget_cpmm"], memory_budget_bytes=budget,
                                     min_feature_mm=T._feature_mm(o))
            for d in depths:
                geo, gf, depth = prov._geometry(d)
                centres = dz.common_centres(geo, gf, wl_ref, depth)
                for w in allw:
                    key = prov._key(w, d)
                    plan = prov._auto_plan(key)
                    rw = geo.raywave(gf, [w] * len(gf), size, object_distance_mm=depth, pixel_mm=pixel, plan=plan,
                                     center_mm=centres, requires_grad=False)
                    est = prov.build_batch(rw)
                    rows.append({"arm": a["name"], "provider": "cached", "wl": w, "depth": d, "nsrc": rw.nsrc,
                                 "ray_grid": plan.ray_grid, "n_grid": plan.n_grid, "n_pad": plan.n_pad,
                                 "pitch_um": plan.pitch_mm * 1e3, "rays_per_source": plan.ray_grid ** 2,
                                 "old_one_batch": rw.nsrc * module.bytes_per_source(rw, record=True),
                                 "cache_entry": rw.nsrc * plan.n_grid ** 2 * 16, **est})
        else:
            tile = max(1, int(budget // max(1, module.bytes_per_source(
                module.raywave(fields[-1:], [wls[-1][0]], size, pixel_mm=pixel)))))
            for d in depths:
                for w in allw:
                    rw = module.raywave(fields, [w] * len(fields), size, object_distance_mm=d, pixel_mm=pixel)
                    per = module.bytes_per_source(rw, record=True)
                    rows.append({"arm": a["name"], "provider": "live", "wl": w, "depth": d, "nsrc": rw.nsrc,
                                 "ray_grid": rw.plan.ray_grid, "n_grid": rw.plan.n_grid, "n_pad": rw.plan.n_pad,
                                 "pitch_um": rw.plan.pitch_mm * 1e3, "rays_per_source": rw.plan.ray_grid ** 2,
                                 "batch": tile, "per_source": per, "fixed": module.bytes_fixed(rw),
                                 "budget": budget, "peak": module.bytes_fixed(rw) + min(tile, rw.nsrc) * per,
                                 "old_one_batch": rw.nsrc * per, "cache_entry": 0})
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("config")
    ap.add_argument("--preset", default="gpu")
    ap.add_argument("--budget-gb", type=float, default=39.6)
    ap.add_argument("--arms", nargs="*")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                    help="preset overrides, e.g. optics.nyquist_safety=1.5 (values parsed as YAML)")
    a = ap.parse_args(argv)
    config = a.config
    if a.set:
        import yaml
        from torch_bridge import train as T
        path = Path(config)
        if not path.exists():
            path = T.CONFIG_DIR / (config if config.endswith(".yaml") else config + ".yaml")
        config = yaml.safe_load(path.read_text())
        if not str(config["lens"]["file"]).endswith(".json") or "/" in str(config["lens"]["file"]):
            config["lens"]["file"] = str((path.parent / config["lens"]["file"]).resolve()) \
                if (path.parent / config["lens"]["file"]).exists() else config["lens"]["file"]
        for kv in a.set:
            k, v = kv.split("=", 1)
            d = config["presets"][a.preset]
            *head, last = k.split(".")
            for h in head:
                d = d.setdefault(h, {})
            d[last] = yaml.safe_load(v)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rows = plan_preset(config, a.preset, a.budget_gb, a.arms)
    G = 1e9
    print(f"{a.config} --preset {a.preset}" + (f" --set {' '.join(a.set)}" if a.set else ""))
    print(f"{'arm':14s} {'prov':6s} {'wl':>5s} {'src':>3s} {'pitch':>6s} {'ray_grid':>8s} {'Mrays/src':>9s} "
          f"{'n_grid':>6s} {'n_pad':>6s} {'batch':>5s} {'GB/src':>7s} {'fixed':>6s} {'peak':>6s} {'budget':>6s} "
          f"{'old1batch':>9s} {'cacheGB':>7s}")
    for r in rows:
        print(f"{r['arm']:14s} {r['provider']:6s} {r['wl']:5.3f} {r['nsrc']:3d} {r['pitch_um']:6.3f} "
              f"{r['ray_grid']:8d} {r['rays_per_source'] / 1e6:9.2f} {r['n_grid']:6d} {r['n_pad']:6d} "
              f"{min(r['batch'], r['nsrc']):5d} {r['per_source'] / G:7.2f} {r['fixed'] / G:6.2f} {r['peak'] / G:6.2f} "
              f"{r['budget'] / G:6.1f} {r['old_one_batch'] / G:9.1f} {r['cache_entry'] / G:7.2f}")
    by_arm = {}
    for r in rows:
        by_arm.setdefault(r["arm"], []).append(r)
    for arm, rs in by_arm.items():
        print(f"{arm}: max peak per build batch {max(r['peak'] for r in rs) / G:.2f} GB; cached fields "
              f"{sum(r['cache_entry'] for r in rs) / G:.2f} GB in all")
    for w in {str(c.message) for c in caught}:
        print("warning:", w[:300])
    return 0


if __name__ == "__main__":
    sys.exit(main())
