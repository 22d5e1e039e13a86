"""Where a GPU's time goes in the issue-25 figures (on a GPU machine):
(1) the floor of a cooke_hybrid design step set by its network alone: NAFNet `paper`, batch 8 x 3 x 256^2, forward +
L1 loss + backward + Adam step, fp32 and bf16 autocast, eager (median ms of 10 after 3 warm-up);
(2) the 10 x 10 x 3 A489 + DOE map, 64 px: wall of two warm calls, of calls with a rw.PlanCache (the first plans, the
next replay), planning alone (rwwarp.wave.packed.source_plans of
the 300 sources, warm), and a cProfile of one warm call (cumulative, rwwarp's functions).
    python perf/tools/gpu_breakdown.py [--out FILE.json]"""
import argparse, cProfile, io, json, os, pstats, time, warnings
warnings.simplefilter("ignore")
import numpy as np


def network_floor():
    import torch
    from torch_bridge.network import build_network
    net = build_network("paper").cuda()
    opt = torch.optim.Adam(net.parameters(), 1e-4)
    x = torch.rand(8, 3, 256, 256, device="cuda")
    y = torch.rand(8, 3, 256, 256, device="cuda")
    out = {"params_M": sum(p.numel() for p in net.parameters()) / 1e6}
    for label, dt in (("fp32", None), ("bf16_autocast", torch.bfloat16)):
        ts = []
        for i in range(13):
            torch.cuda.synchronize(); t0 = time.perf_counter()
            with torch.autocast("cuda", dtype=dt, enabled=dt is not None):
                loss = (net(x) - y).abs().mean()
            opt.zero_grad(set_to_none=True); loss.backward(); opt.step()
            torch.cuda.synchronize(); ts.append(time.perf_counter() - t0)
        out[label + "_ms"] = 1e3 * float(np.median(ts[3:]))
    return out


def map_breakdown():
    import rwwarp as rw
    from rwwarp.wave.packed import source_plans
    lens = rw.load_lens("a489_doe")
    u = np.linspace(-0.9, 0.9, 10) * 10.0
    fields = [(float(x), float(y)) for y in u for x in u]
    wls = [0.45, 0.55, 0.65]
    rw.psf_map(lens, fields, wls, device="cuda", size=64)
    walls = []
    for _ in range(2):
        t0 = time.perf_counter(); rw.psf_map(lens, fields, wls, device="cuda", size=64); walls.append(time.perf_counter() - t0)
    cache = rw.PlanCache()
    cached = []
    for _ in range(3):   # a map of a fixed lens: planned once, then its kept batches replayed
        t0 = time.perf_counter(); rw.psf_map(lens, fields, wls, device="cuda", size=64, cache=cache)
        cached.append(time.perf_counter() - t0)
    ff = [f for f in fields for _ in wls]; ww = [w for _ in fields for w in wls]
    pixel = lens.sensor.pixel_pitch
    source_plans(lens, ff, ww, 64, pixel, device="cuda")
    t0 = time.perf_counter(); source_plans(lens, ff, ww, 64, pixel, device="cuda"); t_plan = time.perf_counter() - t0
    pr = cProfile.Profile(); pr.enable(); rw.psf_map(lens, fields, wls, device="cuda", size=64); pr.disable()
    s = io.StringIO(); pstats.Stats(pr, stream=s).sort_stats("cumulative").print_stats("rwwarp|warp/_src/context|cupy", 45)
    s2 = io.StringIO(); pstats.Stats(pr, stream=s2).sort_stats("tottime").print_stats(30)
    return {"psfs": 300, "map_wall_s": walls, "psf_per_s": 300 / min(walls), "plan_300_s": t_plan,
            "cached_map_wall_s": cached, "cached_psf_per_s": 300 / min(cached[1:]),
            "plan_ms_per_source": 1e3 * t_plan / 300}, s.getvalue() + "\n" + s2.getvalue()


if __name__ == "__main__":
    ap = argparse.ArgumentParser(); ap.add_argument("--out", default=None)
    ap.add_argument("--map-only", action="store_true", help="skip the network floor"); a = ap.parse_args()
    import torch
    res = {"card": torch.cuda.get_device_name(0), "commit": os.environ.get("RWWARP_COMMIT", "?")}
    if not a.map_only:
        res["network_floor"] = network_floor(); print(json.dumps(res, indent=1), flush=True)
    m, prof = map_breakdown(); res["map"] = m
    print(json.dumps(m, indent=1)); print(prof)
    if a.out:
        json.dump(res, open(a.out, "w"), indent=1)
        open(a.out.replace(".json", "_profile.txt"), "w").write(prof)
