"""Shared helpers of the benchmarks: device naming, timing bracketed by synchronisation, results I/O."""
from __future__ import annotations

import json
import os
import platform
import subprocess
import time
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"


def git_commit() -> str:
    """The commit measured: $RWWARP_COMMIT when set (a copied working tree may carry a stale .git),
    else git's HEAD."""
    if os.environ.get("RWWARP_COMMIT"):
        return os.environ["RWWARP_COMMIT"]
    try:
        return subprocess.check_output(["git", "rev-parse", "--short", "HEAD"], cwd=Path(__file__).parent,
                                       stderr=subprocess.DEVNULL, text=True).strip()
    except Exception:
        return os.environ.get("RWWARP_COMMIT", "unknown")


def device_name(device: str) -> str:
    """Human name of the device (GPU model, or CPU model and core count)."""
    if device.startswith("cuda"):
        import warp as wp
        return wp.get_device(device if ":" in device else "cuda:0").name
    name = platform.processor() or "cpu"
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                name = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{name} ({os.cpu_count()} cores)"


def timed(fn, sync, repeat: int = 5):
    """Median wall time (s) of ``fn()`` over ``repeat`` runs, each bracketed by ``sync()``."""
    times = []
    for _ in range(repeat):
        sync()
        t = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - t)
    times.sort()
    return times[len(times) // 2]


def save(name: str, data: dict, out_dir=None) -> Path:
    out = Path(out_dir or os.environ.get("RWWARP_RESULTS", RESULTS))
    out.mkdir(parents=True, exist_ok=True)
    data = dict(data)
    data.setdefault("commit", git_commit())
    p = out / f"{name}.json"
    p.write_text(json.dumps(data, indent=1, default=float) + "\n")
    return p


def sync_fn(device: str):
    """A function that waits for all queued GPU work of ``device`` (Warp, CuPy, and torch where it is
    imported); a no-op on the CPU."""
    if not device.startswith("cuda"):
        return lambda: None
    import sys

    import warp as wp

    def sync():
        wp.synchronize_device(device if ":" in device else "cuda:0")
        try:
            import cupy
            cupy.cuda.runtime.deviceSynchronize()
        except ImportError:
            pass
        if "torch" in sys.modules:
            sys.modules["torch"].cuda.synchronize()
    return sync
