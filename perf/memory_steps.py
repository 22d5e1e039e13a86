"""What a design arm's joint steps hold and peak at, step by step, on any device (the CPU included).

    python perf/memory_steps.py --config cooke_hybrid --preset cpu_lens --steps 20 \\
        --set optics.psf_size=15 optics.rays_per_sample=0.5 optics.live_replan_rule=drift \\
              optics.live_replan_every=8 optics.live_replan_drift=0.05 optics.live_replan_spread=1 \\
              optics.memory_budget_gb=2.0 'optics.nodes.fractions=[0.0,0.5,0.9]' train.optics_every=1 \\
              data.crop=32 data.batch_size=2

Runs the arm's steps as ``torch_bridge.train`` does (the step's result kept until the next step's returns) and
prints per step (MB = 1e6 bytes): what is held after it (after garbage collection: the bytes malloc has in use,
which on the CPU counts torch's, numpy's, Warp's and PoCL's buffers; torch tensors and Warp arrays reachable from
Python), the step's peak resident set (``VmHWM``, reset before the step through ``/proc/self/clear_refs``), the
provider's held bytes and its largest checkpoint unit's estimate (the ``provider_held_gb`` / ``live_unit_gb``
metrics), the largest kept plan's wave-plane grid and the re-plans so far. Held memory that grows with the steps
is something kept; a peak that grows with the plans is the recorded work of a learning lens (perf/results/
session22_cpu_memory/README.md). Linux (glibc's ``mallinfo2``, ``/proc``)."""
from __future__ import annotations

import argparse
import ctypes
import gc
import time
from pathlib import Path


class _Mallinfo2(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks",
                                               "uordblks", "fordblks", "keepcost")]


def malloc_in_use() -> int:
    """Bytes glibc's malloc has handed out and not had back (arenas' used chunks plus mmapped blocks)."""
    libc = ctypes.CDLL("libc.so.6")
    libc.mallinfo2.restype = _Mallinfo2
    m = libc.mallinfo2()
    return int(m.uordblks + m.hblkhd)


def python_reachable() -> tuple[int, int]:
    """(bytes of torch tensors' storages, bytes of Warp arrays that own memory), found among the objects the garbage
    collector tracks (tensors kept only inside an autograd graph are not found: malloc_in_use counts them)."""
    import torch
    t, w = {}, {}
    for o in gc.get_objects():
        if torch.is_tensor(o):
            st = o.untyped_storage()
            t[st.data_ptr()] = st.nbytes()
        elif type(o).__name__ == "array" and type(o).__module__.startswith("warp") and o.ptr and \
                getattr(o, "capacity", 0):
            w[o.ptr] = o.capacity
    return sum(t.values()), sum(w.values())


def _status_kb(key: str) -> int:
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith(key + ":"))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--config", default="cooke_hybrid")
    ap.add_argument("--preset", default="cpu_lens")
    ap.add_argument("--arm", default="e2e")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--set", nargs="*", default=[], help="config overrides KEY=VALUE (as rwwarp design --set)")
    a = ap.parse_args()
    import torch_bridge
    from torch_bridge.config import parse_overrides
    from torch_bridge.train import Arm, _provider_gb, _seed_all, load_config, train_step
    exp = load_config(str(Path(torch_bridge.__file__).resolve().parent / "configs" / f"{a.config}.yaml"),
                      preset=a.preset, overrides=parse_overrides(a.set))
    arm_cfg = next(x for x in exp["arms"] if x["name"] == a.arm)
    cfg = dict(arm_cfg["config"], device=a.device, progress=False)
    _seed_all(int(cfg["seed"]))
    arm = Arm(arm_cfg["name"], cfg, exp["source"], Path("unused"), progress=False)
    prov = arm.provider
    print(f"provider {type(prov).__name__}, tile {getattr(prov, 'tile', None)}, record share "
          f"{(getattr(prov, 'record_budget_bytes', None) or 0) / 1e6:.0f} MB", flush=True)
    s = None
    for k in range(a.steps):
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")   # resets VmHWM to the current resident set
        t = time.perf_counter()
        s = train_step(arm, k, {}, None)
        arm.opt_net.step()
        if s["optics_step"]:
            arm.opt_optics.step()
        dt = time.perf_counter() - t
        peak = _status_kb("VmHWM") / 1e3
        gc.collect()
        tb, wb = python_reachable()
        g = _provider_gb(prov)
        r = getattr(prov, "replans", 0)
        grids = [e[0].plan.n_grid for e in getattr(prov, "_focal_rws", {}).values() if e[0] is not None]
        print(f"step {k} {dt:.1f} s: held {malloc_in_use() / 1e6:.0f} MB (torch {tb / 1e6:.1f}, Warp {wb / 1e6:.1f}), "
              f"peak RSS {peak:.0f} MB, provider held {g['provider_held_gb']} GB, largest unit {g['live_unit_gb']} GB, "
              f"largest grid {max(grids) if grids else '-'}, replans {sum(r.values()) if isinstance(r, dict) else r}",
              flush=True)
    del s


if __name__ == "__main__":
    main()
