"""Shared helpers of the benchmarks: device naming, timing bracketed by synchronisation, results I/O."""
from __future__ import annotations

import json
import os
import platform
import subprocess
import time
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"

# rw.psf keeps its plans in a process-wide cache by default (rwwarp.wave.plan_cache.default_cache, issue 25): a
# benchmark's repeated call would time a cache hit, not the planned computation it measured before. Off here unless
# the environment says otherwise (RWWARP_PLAN_CACHE=1); a script that times the cache passes its own rw.PlanCache.
os.environ.setdefault("RWWARP_PLAN_CACHE", "0")


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


def process_tree(pid: int) -> set:
    """``pid`` and every process below it (Linux ``/proc/<pid>/task/<tid>/children``); the pids that have gone are
    left out, so a tree read while processes end is what was alive."""
    out, todo = set(), [int(pid)]
    while todo:
        p = todo.pop()
        if p in out:
            continue
        out.add(p)
        try:
            tasks = os.listdir(f"/proc/{p}/task")
        except OSError:
            continue
        for t in tasks:
            try:
                with open(f"/proc/{p}/task/{t}/children") as f:
                    todo += [int(c) for c in f.read().split()]
            except OSError:
                pass
    return out


class _Sampler:
    """A thread that runs ``self._run`` while the ``with`` block runs (``self._t0``: its start, ``perf_counter``
    s; ``self._stop``: set at the block's end)."""

    def __init__(self, period=0.05):
        import threading
        self.period, self._stop = period, threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)

    def _run(self):
        raise NotImplementedError

    def __enter__(self):
        self._t0 = time.perf_counter()
        self._t.start()
        return self

    def __exit__(self, *a):
        self._stop.set()
        self._t.join()


class ProcessGpuMemory(_Sampler):
    """GPU memory (MiB) used by one process and its children, sampled every ``period`` s by ``nvidia-smi
    --query-compute-apps`` in a thread: the sum over the tree's processes of what the driver reports for each (its
    context and every allocation: torch's, Warp's and CuPy's pools), on every GPU. Other processes on the same
    GPUs (a design run beside a smoke run) do not count, unlike :class:`GpuMemory`'s device-wide figure.

    ``peak`` / ``peak_at_s``: the largest sum and when it was first seen (s after the sampler started);
    ``matched``: whether any sample listed one of the tree's processes. Where nvidia-smi lists other pids than this
    system's (a container in another PID namespace) nothing matches: a caller must treat ``matched`` False after a
    process ran on a GPU as "not measured", not as zero. Without nvidia-smi nothing is sampled."""

    def __init__(self, pid: int, period=0.05):
        super().__init__(period)
        self.pid, self.peak, self.peak_at_s, self.matched = int(pid), 0, None, False

    def sample(self) -> int | None:
        """One reading: MiB used by the tree now (0 when none of its processes is listed), None without nvidia-smi."""
        try:
            out = subprocess.run(["nvidia-smi", "--query-compute-apps=pid,used_memory", "--format=csv,noheader,nounits"],
                                 capture_output=True, text=True, timeout=5).stdout
        except Exception:  # noqa: BLE001 (no nvidia-smi)
            return None
        tree, used = process_tree(self.pid), 0
        for line in out.strip().splitlines():
            parts = [x.strip() for x in line.split(",")]
            if len(parts) == 2 and parts[0].isdigit() and parts[1].isdigit() and int(parts[0]) in tree:
                used += int(parts[1])
                self.matched = True
        return used

    def _run(self):
        while not self._stop.is_set():
            used = self.sample()
            if used is None:
                return
            if used > self.peak:
                self.peak, self.peak_at_s = used, round(time.perf_counter() - self._t0, 2)
            self._stop.wait(self.period)


class GpuMemory(_Sampler):
    """Used memory (MiB) of every GPU sampled every ``period`` s by ``nvidia-smi`` in a thread:
    ``peaks`` {index: MiB} and ``peak_times`` {index: s after the sampler started, when the peak was first seen},
    ``peak`` / ``peak_at_s`` those of the process's first visible GPU (nvidia-smi numbers the physical GPUs
    whatever ``CUDA_VISIBLE_DEVICES`` says: its first entry when it is set, else GPU 0). Without nvidia-smi
    nothing is sampled."""

    def __init__(self, period=0.05):
        super().__init__(period)
        self.peaks, self.peak_times = {}, {}

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
