"""Where one joint design step of a config's ``e2e`` arm (or, with ``--arm``, any arm: one without optics to learn
steps its network on its cached PSFs) spends its time on a device.

    python perf/profile_step.py --config cooke_hybrid --preset gpu --device cuda [--out DIR] [--cuda-graph]

Runs the arm's joint step as ``torch_bridge.train`` does (one wavelength per colour channel, live PSFs,
render, network, backward, both optimisers): one warm-up step, ``--steps`` timed steps (synchronised),
then one step under cProfile (host time by function, own and cumulative) and one under
``torch.profiler`` with CUDA activity (every kernel launched in the process: torch's, Warp's and CuPy's),
which gives the device-busy time against the step's wall time (a step far longer than its kernels is
bound by the host: launches, synchronisations, planning, not arithmetic) and the number of host <->
device copies. Prints the tables and
writes them to ``DIR/profile_step_<config>_<device>.txt``.
"""
from __future__ import annotations

import argparse
import cProfile
import io
import pstats
import time
from pathlib import Path


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--config", default="cooke_hybrid")
    ap.add_argument("--preset", default="gpu")
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--arm", default=None, help="the arm to step (default: the first whose design method is e2e)")
    ap.add_argument("--steps", type=int, default=2)
    ap.add_argument("--out", default=None)
    ap.add_argument("--cache-device", choices=("device", "host"), default=None,
                    help="override the config's optics.cache_device (a cached provider's fields on the device or in "
                         "page-locked host memory)")
    ap.add_argument("--memory", action="store_true",
                    help="one more step (CUDA) with the memory at its phases: allocated, reserved and the peak since "
                         "the previous mark, at the PSFs' forward, the network's forward, the backward and the "
                         "optimisers; and what is held beside them (cached fields, network and Adam state, the "
                         "backend's work arrays, transfer-function cache and FFT plans)")
    ap.add_argument("--track-memory", action="store_true",
                    help="each timed step's memory (GB; CUDA: torch's allocated after the step, its peak in the step, "
                         "reserved, device used; every device: what the provider keeps, LiveProvider.held_bytes, and "
                         "the estimated recorded peak of its largest checkpoint unit, with the re-plans so far): held "
                         "memory that grows with the steps is something kept; a peak that grows follows the plans")
    ap.add_argument("--find-syncs", action="store_true",
                    help="one more step counting the host reads of device data (each waits for the device) by call site")
    ap.add_argument("--cuda-graph", action="store_true",
                    help="train.cuda_graph on: the network's forward, loss, backward and PSNR replayed as one CUDA graph "
                         "(torch_bridge.graph_step; captured in the warm-up step). Time both ways on one machine: run "
                         "the script twice, without and with it")
    ap.add_argument("--pack", action="store_true", help="packed live tiles on (optics.live_pack = true)")
    ap.add_argument("--no-pack", action="store_true",
                    help="live focal sources one at a time (optics.live_pack false), for an A/B against packed tiles")
    ap.add_argument("--budget-gb", type=float, default=None,
                    help="override the config's optics.memory_budget_gb (sets the live PSF tile)")
    ap.add_argument("--live-tile", type=int, default=None,
                    help="sources per live PSF tile, overriding the budget's choice (a tile of every source: no "
                         "checkpoint, no recompute in the backward pass)")
    a = ap.parse_args()
    if a.cuda_graph and a.memory:
        ap.error("--memory marks the network's forward (a Python call), which a graph replay does not make: run "
                 "--memory without --cuda-graph")

    # the allocator `rwwarp design` runs with (torch_bridge/command.py), unless the caller set one: without it
    # the step's varying tiles fragment torch's pool (session 24, H200, cb1c2af: cooke_hybrid e2e reserved 32 GB,
    # 33 GB of the device, for a 19-21 GB step peak, against the design run's 28 GB budget)
    import os
    os.environ.setdefault("PYTORCH_CUDA_ALLOC_CONF", "expandable_segments:True")
    import torch

    from torch_bridge.train import Arm, _seed_all, load_config, train_step
    import torch_bridge
    # the configs of the torch_bridge imported (an older install on PYTHONPATH brings its own)
    exp = load_config(str(Path(torch_bridge.__file__).resolve().parent / "configs" / f"{a.config}.yaml"),
                      preset=a.preset)
    arm_cfg = next(x for x in exp["arms"] if (x["name"] == a.arm if a.arm else x["config"]["design"]["method"] == "e2e"))
    cfg = dict(arm_cfg["config"], device=a.device, progress=False)
    if a.no_pack:
        cfg["optics"] = dict(cfg["optics"], live_pack=False)
    if a.pack:
        cfg["optics"] = dict(cfg["optics"], live_pack=True)
    if a.budget_gb is not None:
        cfg["optics"] = dict(cfg["optics"], memory_budget_gb=a.budget_gb)
    if a.cache_device is not None:
        cfg["optics"] = dict(cfg["optics"], cache_device=a.cache_device)
    if a.cuda_graph:
        cfg["train"] = dict(cfg["train"], cuda_graph=True)
    _seed_all(int(cfg["seed"]))
    arm = Arm(arm_cfg["name"], cfg, exp["source"], Path("unused"), progress=False)
    if a.live_tile is not None:
        arm.provider.tile = int(a.live_tile)
    cuda = a.device.startswith("cuda")

    last = [None]
    # the frozen optics' single-wavelength PSFs, kept across steps as the design loop keeps them (a learning arm's
    # optics steps clear it): an arm without optics to learn (paraxial, rms_spot, blank_doe) times its network steps
    psf_cache = {}

    def step(k):
        # the result kept until the next step's returns, as the design loop keeps it (torch_bridge.train.train_arm);
        # its values device tensors, read at the design loop's log steps only (lazy)
        last[0] = train_step(arm, k, psf_cache, None, lazy=True)
        arm.opt_net.step()
        if arm.opt_optics is not None:
            arm.opt_optics.step()
        if cuda:
            torch.cuda.synchronize()

    lines = []
    summary = {"config": a.config, "preset": a.preset, "device": a.device, "arm": arm_cfg["name"],
               "live_pack": cfg["optics"].get("live_pack"), "pixel_values": cfg["optics"].get("pixel_values"),
               "live_tile": getattr(arm.provider, "tile", None), "cuda_graph": bool(a.cuda_graph)}

    def say(s):
        print(s, flush=True)
        lines.append(s)
    from torch_bridge.design import CachedProvider
    if isinstance(arm.provider, CachedProvider):
        # every wavelength entry's field built first, as the design loop does (torch_bridge.train): a step then meets
        # only built entries (without it a step that draws a new wavelength builds its entry, seconds on a GPU)
        t = time.perf_counter()
        arm.provider.prepare(sorted({w for c in arm.wls for w in c}), arm.depths, progress=False)
        say(f"cached provider's wavelength entries built first: {time.perf_counter() - t:.2f} s")
    t = time.perf_counter()
    step(0)
    say(f"first step (plans, kernel builds) {time.perf_counter() - t:.2f} s")
    times = []
    import sys
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from _common import GpuMemory
    empties = [0]
    if cuda:
        torch.cuda.reset_peak_memory_stats()
        # torch's cache emptied (rwwarp's release hook when a propagation allocation fails: a synchronisation, and
        # torch's next allocations go to the driver)
        _empty = torch.cuda.empty_cache

        def counted_empty():
            empties[0] += 1
            _empty()
        torch.cuda.empty_cache = counted_empty
    from rwwarp.wave.backend import get_backend
    be = get_backend(arm.provider.module.rw_device)
    per_step = []   # FFT plans built (VkFFT kernel builds) and a cached provider's wavelength entries, each step

    def entries():
        return len(getattr(arm.provider, "_cache", {})) + len(getattr(arm.provider, "_focal", {}))
    seen = list(getattr(arm.provider, "step_log", []))   # log entries made before the timed steps (held: identity)
    with GpuMemory(0.05) as mem:
        for k in range(1, a.steps + 1):
            built, n_entries = be.fft_plans_built, entries()
            if cuda and a.track_memory:
                torch.cuda.reset_peak_memory_stats()
            t = time.perf_counter()
            step(k)
            times.append(time.perf_counter() - t)
            per_step.append({"fft_plans_built": be.fft_plans_built - built, "new_entries": entries() - n_entries})
            # a cached provider's chunk sizes this step (each new size is new RayWaves and FFT shapes): the log's
            # entries made since the last step (it keeps its last 64; the step appends one an entry and call)
            log = getattr(arm.provider, "step_log", None)
            if log is not None:
                new_entries = [r for r in log if not any(r is h for h in seen)]
                per_step[-1]["chunks"] = sorted({int(r["chunk"]) for r in new_entries})
                seen[:] = list(log)
            if a.track_memory:
                per_step[-1].update(_step_memory(arm, cuda))
                say(f"step {k}: " + ", ".join(f"{q} {v}" for q, v in per_step[-1].items()))
    if cuda:
        torch.cuda.empty_cache = _empty
        summary["empty_cache_calls"] = empties[0]
        say(f"torch.cuda.empty_cache calls over the timed steps: {empties[0]}")
    summary.update(step_wall_s=times, step_median_s=float(sorted(times)[len(times) // 2]), nodes=len(arm.fields))
    say(f"steps {[round(x, 3) for x in times]} s; nodes {len(arm.fields)}, sources per step {3 * len(arm.fields)}")
    summary["per_step"] = per_step
    say(f"FFT plans built a step {[r['fft_plans_built'] for r in per_step]} (kept {be.memory_report()['fft_plans']}, "
        f"{be.memory_report()['fft_plan_bytes'] / 1e9:.2f} GB of temporary buffers; dropped by the bounds so far "
        f"{be.fft_plans_dropped}); new cached wavelength entries a step {[r['new_entries'] for r in per_step]}")
    prov = arm.provider
    if hasattr(prov, "plans_made"):
        say(f"live plans made {prov.plans_made}, reused {prov.plans_reused} (replan_every {prov.replan_every}; "
            f"kept plans given up: {prov.replans}); packed tiles {'on' if getattr(prov, 'pack', False) else 'off'}, "
            f"built {getattr(prov, 'packs_made', 0)}")
    if hasattr(prov, "tile"):
        say(f"live PSF tile {prov.tile} sources (memory_budget_gb {cfg['optics'].get('memory_budget_gb')})")
    if cuda:
        import cupy
        import warp as wp
        # inside bridge calls Warp and CuPy draw on torch's allocator (torch_bridge.functions.TorchAllocator);
        # what they allocate outside (plans, pilot traces, operator set-up) is in their own pools
        t_peak = torch.cuda.max_memory_allocated() / 1e9
        w_peak = wp.get_mempool_used_mem_high("cuda:0") / 1e9
        c_pool = cupy.get_default_memory_pool().total_bytes() / 1e9
        summary.update(card=torch.cuda.get_device_name(), device_used_peak_gib=mem.peak / 1024,
                       torch_peak_gb=t_peak, warp_pool_peak_gb=w_peak, cupy_pool_gb=c_pool)
        # CuPy's cuFFT plan cache (rwwarp.wave.backend.ensure_cufft_plan_cache): a miss builds a plan (~6 ms)
        buf = io.StringIO()
        import contextlib
        with contextlib.redirect_stdout(buf):
            cupy.fft.config.get_plan_cache().show_info()
        summary["cufft_plan_cache"] = buf.getvalue().strip()
        say("cuFFT plan cache after the timed steps: " + " | ".join(x.strip() for x in buf.getvalue().splitlines()[1:]))
        say(f"peak memory over the timed steps: torch allocator (with Warp and CuPy inside bridge calls) "
            f"{t_peak:.2f} GB, Warp's own pool high-water {w_peak:.2f} GB, CuPy's own pool {c_pool:.2f} GB, "
            f"sum {t_peak + w_peak + c_pool:.2f} GB (an upper bound of the concurrent peak); device used "
            f"(nvidia-smi) {mem.peak / 1024:.2f} GiB; device {torch.cuda.get_device_name()}")
    pr = cProfile.Profile()
    t = time.perf_counter()
    pr.enable()
    step(a.steps + 1)
    pr.disable()
    say(f"profiled step {time.perf_counter() - t:.2f} s (cProfile adds overhead)")
    from _common import count_warp_launches
    summary["warp_launches"] = count_warp_launches(lambda: step(a.steps + 1))
    say(f"Warp launches in one step (every thread): {summary['warp_launches']}")
    for key, n in (("tottime", 40), ("cumtime", 40)):
        s = io.StringIO()
        pstats.Stats(pr, stream=s).sort_stats(key).print_stats(n)
        say(f"== cProfile by {key}\n" + "\n".join(x[:160] for x in s.getvalue().splitlines()[4:]))
    if cuda:
        from torch.profiler import ProfilerActivity, profile
        with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
            t = time.perf_counter()
            step(a.steps + 2)
            wall = time.perf_counter() - t
        ev = [e for e in prof.events() if e.device_type.name == "CUDA"]
        busy = sum(e.device_time for e in ev) / 1e6
        summary.update(profiled_wall_s=wall, device_kernels_and_copies=len(ev), device_busy_s=busy,
                       device_busy_fraction=busy / wall)
        say(f"torch.profiler step: wall {wall:.2f} s, {len(ev)} device kernels/copies, their summed device time {busy:.3f} s")
        # host <-> device traffic of the step (every copy CUPTI saw: torch's, Warp's, CuPy's)
        for kind in ("HtoD", "DtoH"):
            cp = [e for e in ev if e.name.startswith(f"Memcpy {kind}")]
            say(f"Memcpy {kind}: {len(cp)} copies, {sum(e.device_time for e in cp) / 1e3:.2f} ms of device time")
        say(prof.key_averages().table(sort_by="device_time_total", row_limit=30, max_name_column_width=70))
    if cuda and a.memory:
        summary["memory_phases"] = _memory_phases(arm, step, a.steps + 3, say)
    if cuda and a.find_syncs:
        say("== host reads of device data in one step, by call site (project frames)")
        for site, n in _count_syncs(lambda: step(a.steps + 3))[:25]:
            say(f"{n:6d}  {site}")
    if a.out:
        tag = (f"_{a.arm}" if a.arm else "") + ("_pack" if a.pack else "") + (f"_tile{a.live_tile}" if a.live_tile is not None else "") + \
            (f"_cache_{a.cache_device}" if a.cache_device else "") + ("_graph" if a.cuda_graph else "")
        p = Path(a.out) / f"profile_step_{a.config}_{a.device.replace(':', '')}{tag}.txt"
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text("\n".join(lines) + "\n")
        import json

        from _common import git_commit
        summary["commit"] = git_commit()      # $RWWARP_COMMIT when set, else git's HEAD
        p.with_suffix(".json").write_text(json.dumps(summary, indent=1) + "\n")
        print("written to", p, "and", p.with_suffix(".json"))


def _step_memory(arm, cuda: bool) -> dict:
    """The memory after a step (GB = 1e9 bytes, see ``--track-memory``): on CUDA torch's allocated (what is held
    between steps), its peak since the last reset (the step's), reserved and the device's used memory; on every device
    the provider's held bytes and its largest checkpoint unit's estimate (torch_bridge.train's metrics columns), and
    the live re-plans so far."""
    import torch

    from torch_bridge.train import _provider_gb
    out = {}
    if cuda:
        torch.cuda.synchronize()
        free, total = torch.cuda.mem_get_info()
        out.update(torch_gb=round(torch.cuda.memory_allocated() / 1e9, 3),
                   torch_step_peak_gb=round(torch.cuda.max_memory_allocated() / 1e9, 3),
                   reserved_gb=round(torch.cuda.memory_reserved() / 1e9, 3), device_used_gb=round((total - free) / 1e9, 3))
    out.update(_provider_gb(arm.provider))
    r = getattr(arm.provider, "replans", None)
    if r is not None:
        out["replans"] = sum(r.values()) if isinstance(r, dict) else r
    return out


def _memory_phases(arm, step, k, say) -> dict:
    """Step ``k`` with the CUDA memory (GB = 1e9 bytes) marked at its phases: after the PSFs' forward
    (``arm.psfs``), after the network's forward (the rendering and noise before it), after the loss's backward
    (the network's and the optics' gradients: ``train_step`` returns) and after the optimisers. Each mark: torch's
    allocated and reserved memory, the peak allocated since the previous mark and the device's used memory
    (``mem_get_info``). Then the memory held beside the step: the provider's cached fields, the network's weights
    and Adam state, the backend's work arrays (outside torch's allocator), its transfer-function cache and FFT
    plans. Printed with ``say``; returned as a dict."""
    import torch

    from rwwarp.wave.backend import get_backend
    marks = []

    def mark(name):
        torch.cuda.synchronize()
        free, total = torch.cuda.mem_get_info()
        marks.append({"phase": name, "allocated_gb": torch.cuda.memory_allocated() / 1e9,
                      "reserved_gb": torch.cuda.memory_reserved() / 1e9,
                      "peak_since_previous_gb": torch.cuda.max_memory_allocated() / 1e9,
                      "device_used_gb": (total - free) / 1e9})
        torch.cuda.reset_peak_memory_stats()
    psfs, forward = arm.psfs, arm.net.forward

    def psfs_marked(*args, **kw):
        mark("start of the step")
        out = psfs(*args, **kw)
        mark("PSFs' forward")
        return out

    def forward_marked(*args, **kw):
        mark("rendering and noise")
        out = forward(*args, **kw)
        mark("network's forward")
        return out
    arm.psfs, arm.net.forward = psfs_marked, forward_marked
    try:
        torch.cuda.reset_peak_memory_stats()
        k_opt = [0]
        _step_opt = arm.opt_net.step

        def opt_step(*args, **kw):
            if not k_opt[0]:
                mark("loss and backward (network and optics)")
            k_opt[0] += 1
            return _step_opt(*args, **kw)
        arm.opt_net.step = opt_step
        step(k)
        mark("optimisers")
    finally:
        arm.psfs, arm.net.forward = psfs, forward
        arm.opt_net.step = _step_opt
    prov = arm.provider
    be = get_backend(str(arm.module.rw_device))
    params = sum(p.numel() * p.element_size() for p in arm.net.parameters())
    adam = sum(t.numel() * t.element_size() for st in arm.opt_net.state.values() for t in st.values()
               if torch.is_tensor(t))
    held = {"cached_fields_gb": (prov.cache_bytes() if hasattr(prov, "cache_bytes") else 0) / 1e9,
            "network_weights_gb": params / 1e9, "network_adam_state_gb": adam / 1e9,
            "backend_work_arrays_gb": sum(e[0].nbytes for e in be._workspace.values()) / 1e9,
            "backend_transfer_cache_gb": be.cache.nbytes / 1e9, "backend_fft_plans_gb": be._plan_bytes / 1e9}
    say("== memory at the phases of one step (GB): allocated / reserved / peak allocated since the previous mark / "
        "device used")
    for m in marks:
        say(f"  {m['phase']:42s} {m['allocated_gb']:7.2f} {m['reserved_gb']:7.2f} {m['peak_since_previous_gb']:7.2f} "
            f"{m['device_used_gb']:7.2f}")
    say("  held beside the step: " + ", ".join(f"{k} {v:.3f}" for k, v in held.items()))
    return {"marks": marks, "held": held}


def _count_syncs(fn):
    """Run ``fn()`` counting the calls that read device data on the host (Warp ``array.numpy``, CuPy
    ``get`` / scalar conversions, torch's synchronising operations via its sync debug mode), by the innermost
    call site in rwwarp / torch_bridge. Returns ``[(site, count)]``, most frequent first."""
    import collections
    import traceback
    import warnings

    import cupy
    import torch
    import warp as wp
    counts = collections.Counter()

    def site():
        for fr in reversed(traceback.extract_stack()[:-2]):
            if "/rwwarp/" in fr.filename or "/torch_bridge/" in fr.filename:
                return f"{fr.filename.split('/')[-2]}/{fr.filename.split('/')[-1]}:{fr.lineno} {fr.name}"
        return "other"

    patched = []

    def wrap(owner, name, test=None):
        orig = getattr(owner, name)

        def f(self, *a, **k):
            if test is None or test(self):
                counts[site()] += 1
            return orig(self, *a, **k)
        try:
            setattr(owner, name, f)
        except TypeError:   # an extension type (CuPy's ndarray): its reads are not counted
            counts[f"(not counted: {owner.__name__}.{name})"] = 0
            return
        patched.append((owner, name, orig))
    wrap(wp.array, "numpy", lambda x: x.device.is_cuda)
    for n in ("get", "item", "__float__", "__int__", "__bool__", "tolist"):
        wrap(cupy.ndarray, n)
    torch.cuda.set_sync_debug_mode("warn")
    try:
        with warnings.catch_warnings(record=True) as rec:
            warnings.simplefilter("always")
            fn()
        for w in rec:
            if "synchroniz" in str(w.message):
                counts[f"torch {w.filename.split('/')[-1]}:{w.lineno}"] += 1
    finally:
        torch.cuda.set_sync_debug_mode(0)
        for owner, name, orig in patched:
            setattr(owner, name, orig)
    return counts.most_common()


if __name__ == "__main__":
    main()
