"""Shared helpers of the benchmarks: device naming, timing bracketed by synchronisation, results I/O."""
from __future__ import annotations

import json
import os
import platform
import subprocess
import time
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"


def count_warp_launches(fn) -> int:
    """Calls of ``warp.launch`` (every thread, backward included) while ``fn()`` runs."""
    import threading
    import warp as wp
    orig, n, lock = wp.launch, [0], threading.Lock()

    def counted(*args, **kw):
        with lock:
            n[0] += 1
        return orig(*args, **kw)
    wp.launch = counted
    try:
        fn()
    finally:
        wp.launch = orig
    return n[0]


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


class GpuMemory:
    """Used memory (MiB) of every GPU sampled every ``period`` s by ``nvidia-smi`` in a thread:
    ``peaks`` {index: MiB} and ``peak_times`` {index: s after the sampler started, when the peak was first seen},
    ``peak`` / ``peak_at_s`` those of the process's first visible GPU (nvidia-smi numbers the physical GPUs
    whatever ``CUDA_VISIBLE_DEVICES`` says: its first entry when it is set, else GPU 0). Without nvidia-smi
    nothing is sampled."""

    def __init__(self, period=0.05):
        import threading
        self.period, self.peaks, self.peak_times, self._stop = period, {}, {}, threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)

    @staticmethod
    def _first():
        import os
        first = (os.environ.get("CUDA_VISIBLE_DEVICES") or "0").split(",")[0].strip()
        return int(first) if first.isdigit() else 0

    @property
    def peak(self) -> int:
        return self.peaks.get(self._first(), 0)

    @property
    def peak_at_s(self):
        """Seconds from the sampler's start to the first sample at the peak (of the first visible GPU), or None."""
        return self.peak_times.get(self._first())

    def _run(self):
        while not self._stop.is_set():
            try:
                out = subprocess.run(["nvidia-smi", "--query-gpu=index,memory.used", "--format=csv,noheader,nounits"],
                                     capture_output=True, text=True, timeout=5).stdout
            except Exception:  # noqa: BLE001 (no nvidia-smi: nothing sampled)
                return
            for line in out.strip().splitlines():
                i, used = (int(x) for x in line.split(","))
                if used > self.peaks.get(i, -1):
                    self.peaks[i] = used
                    self.peak_times[i] = round(time.perf_counter() - self._t0, 2)
            time.sleep(self.period)

    def __enter__(self):
        self._t0 = time.perf_counter()
        self._t.start()
        return self

    def __exit__(self, *a):
        self._stop.set()
        self._t.join()
