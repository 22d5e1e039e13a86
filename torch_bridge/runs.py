"""Runs that survive interruption: background runs, progress files, status, portable checkpoints.

A design run (``rwwarp design CONFIG``) writes its outputs into a *run folder* (``--out``, default
``out/design/<experiment>[_<preset>]``). This module adds, on top of :mod:`torch_bridge.train`:

* ``--detach``: the run starts in its own process session (``setsid``: it survives the shell and the
  terminal that started it), its output goes to ``RUN_DIR/run.log`` and its process id to
  ``RUN_DIR/run.pid`` (JSON: pid, start time of the process in clock ticks since boot, command, host);
* ``RUN_DIR/progress.json``, replaced atomically every ``train.log_every`` steps and at each phase
  change: state, arm, phase, step, steps/s, ETA, last loss / training PSNR, peak GPU memory;
* :func:`status` (``rwwarp design status RUN_DIR``): reads those files from any other process and says
  whether the run's process is alive (the pid *and* its start time must match: a reused pid is not
  taken for the run);
* :func:`pack` (``rwwarp design pack RUN_DIR``): a *portable checkpoint*: every arm's ``checkpoint.pt``
  (network weights in float32 or bfloat16, with or without the network's Adam moments) and the small
  files of the run folder in one stream, cut into parts of at most ``part_mib`` MiB with a manifest
  (sha256 of every part and of the whole); :func:`unpack` (``--resume PACK``) checks and reassembles it
  into a run folder, from which the run resumes.

Sizes are MiB = 2**20 bytes; times are seconds (wall clock).
"""
from __future__ import annotations

import csv
import datetime as _dt
import hashlib
import io
import json
import os
import random
import socket
import subprocess
import sys
import time
from pathlib import Path

__all__ = ["CSV_FIELDS", "PACK_MANIFEST", "ProgressFile", "cli_status", "detach", "git_commit", "pack", "process_alive",
           "provider_gb", "read_row", "status", "unpack", "write_json_atomic"]

PACK_MANIFEST = "pack.json"
PACK_FORMAT = "rwwarp-design-pack-1"
# small files of a run folder that travel in a pack (the per-arm ones from each arm's folder)
_RUN_FILES = ("config_resolved.json", "progress.json", "summary.json", "table.md", "table.csv")
_ARM_FILES = ("metrics.csv", "result.json", "lens.json")
# and of a finished arm, its evaluation's PSFs and sample crops: the table's figure (``designs.png``) is drawn
# from them whenever the experiment runs again, also in a folder the pack was moved to
_ARM_EVAL_FILES = ("eval_psfs.npz", "eval_sample_*.npz")


def _utc() -> str:
    return _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


def write_json_atomic(path, obj) -> None:
    """Write ``obj`` as JSON to ``path`` through a temporary file in the same folder and a rename, so a
    reader in another process sees the old or the new file, never a partial one."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(obj, indent=1, default=str))
    os.replace(tmp, path)


def git_commit(path=None) -> dict:
    """The git commit of the source tree this code runs from: ``{"commit": sha or None, "dirty": bool or
    None}`` (None where git or the repository is absent, e.g. an installed wheel). ``$RWWARP_COMMIT``, when
    set, is the commit (``dirty`` None): a working tree copied to another machine has no ``.git``, or a stale one."""
    env = os.environ.get("RWWARP_COMMIT", "").strip()
    if env:
        return {"commit": env, "dirty": None}
    root = Path(path or Path(__file__).resolve().parents[1])
    try:
        sha = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True,
                             timeout=10)
        if sha.returncode != 0:
            return {"commit": None, "dirty": None}
        st = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                            capture_output=True, text=True, timeout=10)
        return {"commit": sha.stdout.strip(), "dirty": bool(st.stdout.strip()) if st.returncode == 0 else None}
    except (OSError, subprocess.SubprocessError):
        return {"commit": None, "dirty": None}


def device_info(device) -> dict:
    """The card a run uses: ``{"device": "cuda:0" | "cpu", "card": name, "memory_gb": total (1e9 bytes)}``;
    on the CPU the card is the processor model (``/proc/cpuinfo``) and the number of usable cores."""
    import torch
    dev = torch.device(device)
    if dev.type == "cuda" and torch.cuda.is_available():
        p = torch.cuda.get_device_properties(dev)
        return {"device": str(dev), "card": p.name, "memory_gb": round(p.total_memory / 1e9, 1),
                "host": socket.gethostname()}
    name = None
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                name = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"device": "cpu", "card": name or "cpu", "cores": len(os.sched_getaffinity(0))
            if hasattr(os, "sched_getaffinity") else os.cpu_count(), "host": socket.gethostname()}


# ============================================================================================== progress
class ProgressFile:
    """``progress.json`` of a run folder, replaced atomically (:func:`write_json_atomic`).

    :meth:`update` merges keys into the record and writes it; every record carries ``pid``, ``host``
    and ``updated_utc``. :meth:`rate` keeps the steps/s of the current arm (steps done by this process
    over its wall time) and the ETA of the arm (remaining steps / steps per second, s)."""

    def __init__(self, path, **fixed):
        self.path = Path(path)
        self.rec = {"pid": os.getpid(), "host": socket.gethostname(), **fixed}
        self._t0 = None
        self._s0 = 0

    def start_arm(self, step: int):
        """Start timing an arm at step ``step`` (its first step in this process)."""
        self._t0, self._s0 = time.perf_counter(), int(step)

    def rate(self, step: int, total: int) -> dict:
        """``steps_per_s`` and ``eta_s`` (this arm) after ``step`` steps of ``total``; None before a step."""
        if self._t0 is None or step <= self._s0:
            return {"steps_per_s": None, "eta_s": None}
        sps = (step - self._s0) / max(1e-9, time.perf_counter() - self._t0)
        return {"steps_per_s": round(sps, 5), "eta_s": round((total - step) / sps, 1)}

    def update(self, **kw):
        """Merge ``kw`` into the record and replace the file."""
        self.rec.update(kw)
        self.rec["updated_utc"] = _utc()
        write_json_atomic(self.path, self.rec)


# ============================================================================================== detach / status
def _proc_start_ticks(pid: int):
    """Start time of process ``pid`` in clock ticks since boot (field 22 of /proc/PID/stat), or None."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return int(stat[stat.rindex(")") + 2:].split()[19])


def process_alive(pid: int, start_ticks=None) -> bool:
    """True when process ``pid`` exists (and, with ``start_ticks``, started at that time: not a reused
    pid) and is not a zombie."""
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        if stat[stat.rindex(")") + 2] == "Z":
            return False
    except OSError:
        return start_ticks is None
    return start_ticks is None or _proc_start_ticks(pid) == int(start_ticks)


def detach(argv: list, run_dir, env=None) -> dict:
    """Start ``python -m torch_bridge.train ARGV`` in its own process session (``setsid``), standard
    output and error appended to ``run_dir/run.log``, no standard input; writes ``run_dir/run.pid``
    (pid, process start time, command, host, start time UTC) and returns that record. Refuses
    (RuntimeError) when the pid file names a process of this run that is still alive."""
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    pidf = run_dir / "run.pid"
    if pidf.exists():
        try:
            old = json.loads(pidf.read_text())
        except ValueError:
            old = None
        if old and process_alive(old["pid"], old.get("start_ticks")):
            raise RuntimeError(f"{run_dir}: a run is already going on there (pid {old['pid']}, started "
                               f"{old.get('started_utc')}); see: rwwarp design status {run_dir}")
    cmd = [sys.executable, "-m", "torch_bridge.train"] + list(argv)
    log = open(run_dir / "run.log", "ab")
    log.write(f"\n==== {_utc()} {' '.join(cmd)}\n".encode())
    log.flush()
    env = dict(os.environ if env is None else env)
    src = str(Path(__file__).resolve().parents[1])
    env["PYTHONPATH"] = src + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env.setdefault("PYTHONUNBUFFERED", "1")
    p = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT,
                         start_new_session=True, env=env, close_fds=True)
    log.close()
    rec = {"pid": p.pid, "start_ticks": None, "cmd": cmd, "cwd": os.getcwd(), "host": socket.gethostname(),
           "started_utc": _utc()}
    for _ in range(50):                     # /proc/PID appears at once; wait a little if it did not
        rec["start_ticks"] = _proc_start_ticks(p.pid)
        if rec["start_ticks"] is not None or p.poll() is not None:
            break
        time.sleep(0.01)
    write_json_atomic(pidf, rec)
    return rec


def status(run_dir) -> dict:
    """State of the run in ``run_dir`` read from its files, from any process: ``alive`` (its process
    runs), ``state`` (running / done / failed / stopped / dead: not alive but not finished either, e.g.
    killed), the pid record, ``progress`` (the last ``progress.json``), per arm ``arms`` (checkpoint step,
    finished or not) and the last lines of ``run.log``. Raises FileNotFoundError when ``run_dir`` is not a
    run folder."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise FileNotFoundError(f"{run_dir}: no such folder")
    pid = prog = None
    if (run_dir / "run.pid").exists():
        pid = json.loads((run_dir / "run.pid").read_text())
    if (run_dir / "progress.json").exists():
        prog = json.loads((run_dir / "progress.json").read_text())
    if pid is None and prog is None and not (run_dir / "config_resolved.json").exists():
        raise FileNotFoundError(f"{run_dir}: not a design run folder (no run.pid, progress.json or "
                                "config_resolved.json)")
    alive = False
    if pid is not None:
        alive = process_alive(pid["pid"], pid.get("start_ticks"))
    elif prog is not None and prog.get("host") == socket.gethostname() and prog.get("state") == "running":
        alive = process_alive(prog["pid"])
    arms = {}
    for d in sorted(p for p in run_dir.iterdir() if p.is_dir()):
        ck, res = d / "checkpoint.pt", d / "result.json"
        if not ck.exists() and not res.exists():
            continue
        a = {"checkpoint": ck.exists(), "finished": False}
        if res.exists():
            try:
                r = json.loads(res.read_text())
                a["finished"] = "eval" in r
                a["steps_done"] = r.get("steps_done")
            except ValueError:
                pass
        if ck.exists():
            a["checkpoint_mib"] = round(ck.stat().st_size / 2 ** 20, 2)
            a["checkpoint_utc"] = _dt.datetime.fromtimestamp(ck.stat().st_mtime, _dt.timezone.utc).strftime(
                "%Y-%m-%dT%H:%M:%SZ")
        arms[d.name] = a
    state = (prog or {}).get("state", "unknown")
    if not alive and state not in ("done", "failed", "stopped", "unknown"):
        state = "dead"             # killed (SIGKILL, machine taken back) while running or evaluating
    log_tail = []
    if (run_dir / "run.log").exists():
        with open(run_dir / "run.log", "rb") as f:
            f.seek(max(0, f.seek(0, 2) - 4096))
            log_tail = f.read().decode(errors="replace").splitlines()[-5:]
    return {"run_dir": str(run_dir), "alive": alive, "state": state, "pid": pid, "progress": prog, "arms": arms,
            "log_tail": log_tail}


def format_status(st: dict) -> str:
    """A few human-readable lines of a :func:`status` record."""
    p = st["progress"] or {}
    pid = (st["pid"] or {}).get("pid", p.get("pid"))
    lines = [f"{st['run_dir']}: {'ALIVE' if st['alive'] else 'not running'} (pid {pid}); state {st['state']}"]
    if p:
        def f(k, fmt):
            return "-" if p.get(k) is None else format(p[k], fmt)
        lines.append(f"  arm {p.get('arm')} ({p.get('arm_index', 0) + 1}/{p.get('arms_total')}), phase "
                     f"{p.get('phase')}, step {p.get('step')}/{p.get('steps_total')}, {f('steps_per_s', '.3f')} "
                     f"steps/s, ETA {f('eta_s', '.0f')} s, loss {f('loss', '.5f')}, PSNR {f('psnr_train', '.2f')} "
                     f"dB, peak GPU {f('peak_gpu_gb', '.2f')} GB, memory in use {f('memory_gb', '.2f')} GB"
                     f"{' (OVER BUDGET)' if p.get('memory_over_budget') else ''}; last checkpoint at step "
                     f"{p.get('checkpoint_step', '-')}; updated {p.get('updated_utc')}")
        if p.get("phase") == "eval" and p.get("eval_nodes"):
            lines.append(f"  evaluation PSFs: {p.get('eval_nodes_done')}/{p['eval_nodes']} nodes, ETA "
                         f"{f('eval_eta_s', '.0f')} s (then the crops through the network)")
        if p.get("error"):
            lines.append(f"  error: {p['error']}")
        if p.get("memory_over_budget"):
            lines.append(f"  warning: {p['memory_over_budget']}")
    for name, a in st["arms"].items():
        lines.append(f"  {name}: {'finished' if a['finished'] else 'unfinished'}"
                     + (f", checkpoint {a['checkpoint_mib']} MiB at {a['checkpoint_utc']}" if a["checkpoint"]
                        else ""))
    return "\n".join(lines)


def cli_status(argv: list) -> int:
    """``rwwarp design status RUN_DIR [--json]``: print :func:`status` (lines, or JSON) and return 0 while
    the run's process is alive, 1 when it is not, 2 for a folder that is not a run. Needs only the
    standard library (``rwwarp design status`` loads this file without torch: ~0.1 s)."""
    import argparse
    ap = argparse.ArgumentParser(prog="rwwarp design status", description="state of a design run (any process)")
    ap.add_argument("run_dir")
    ap.add_argument("--json", action="store_true", help="print the status record as JSON")
    a = ap.parse_args(argv)
    try:
        st = status(a.run_dir)
    except (FileNotFoundError, ValueError) as e:
        print(f"rwwarp design status: error: {e}", file=sys.stderr)
        return 2
    print(json.dumps(st, indent=1) if a.json else format_status(st))
    return 0 if st["alive"] else 1


# ============================================================================================== pack / unpack
def _sha256(b) -> str:
    return hashlib.sha256(b).hexdigest()


def _portable_state(st: dict, weights: str, optimizer: str) -> dict:
    """A checkpoint dict with the network weights cast to ``weights`` and the network's Adam state kept
    (``full``), cast to bfloat16 (``bfloat16``) or dropped (``none``)."""
    import torch
    st = dict(st)
    if weights == "bfloat16":
        st["net"] = {k: v.to(torch.bfloat16) if v.is_floating_point() else v for k, v in st["net"].items()}
    if optimizer == "none":
        st["opt_net"] = None
    elif optimizer == "bfloat16" and st.get("opt_net") is not None:
        o = dict(st["opt_net"])
        o["state"] = {k: {n: (t.to(torch.bfloat16) if torch.is_tensor(t) and t.is_floating_point() and t.dim() > 0
                              else t) for n, t in s.items()} for k, s in o["state"].items()}
        st["opt_net"] = o
    st["portable"] = {"weights": weights, "optimizer": optimizer}
    return st


def pack(run_dir, out=None, weights: str = "float32", optimizer: str = "full", part_mib: float = 15.0,
         arms=None) -> dict:
    """Write a portable checkpoint of the run folder ``run_dir`` into the folder ``out`` (default
    ``run_dir/pack``): ``pack.json`` (manifest) and ``pack.partNNN`` files of at most ``part_mib`` MiB.

    The stream holds every arm's ``checkpoint.pt`` (or those named in ``arms``) with the network weights
    in ``weights`` (``float32``: exact; ``bfloat16``: half the bytes, rounded) and the network's Adam
    state ``optimizer`` (``full``: exact; ``bfloat16``; ``none``: dropped, a resumed run restarts Adam),
    the other state (optics, optics optimiser, RNG states, plans) unchanged, and the small files
    (configuration, metrics, results). Finished arms travel without their checkpoint (their
    ``result.json``, ``lens.json`` and ``metrics.csv`` are enough for the table; ``network.pt`` stays
    behind). Returns the manifest. Written atomically: the parts and the manifest appear only once all
    are written."""
    import torch
    if weights not in ("float32", "bfloat16"):
        raise ValueError(f"pack: weights must be 'float32' or 'bfloat16', got {weights!r}")
    if optimizer not in ("full", "bfloat16", "none"):
        raise ValueError(f"pack: optimizer must be 'full', 'bfloat16' or 'none', got {optimizer!r}")
    if not (0.01 <= float(part_mib) <= 16.0):
        raise ValueError(f"pack: part_mib must be in [0.01, 16] MiB (the transfer limit is 16 MiB a file), "
                         f"got {part_mib}")
    run_dir = Path(run_dir)
    if not (run_dir / "config_resolved.json").exists():
        raise FileNotFoundError(f"pack: {run_dir} is not a design run folder (no config_resolved.json)")
    st = status(run_dir)
    if st["alive"]:
        raise RuntimeError(f"pack: the run in {run_dir} is still going on (pid {st['pid']['pid']}); stop it first "
                           "(the checkpoint may be rewritten while it is read)")
    files, states, info = {}, {}, {}
    for n in _RUN_FILES:
        if (run_dir / n).exists():
            files[n] = (run_dir / n).read_bytes()
    names = [n for n, a in st["arms"].items() if arms is None or n in set(arms)]
    if arms is not None and set(arms) - set(names):
        raise ValueError(f"pack: no checkpoint or result for arm(s) {sorted(set(arms) - set(names))} in {run_dir}")
    for n in names:
        a = st["arms"][n]
        for f in _ARM_FILES:
            if (run_dir / n / f).exists():
                files[f"{n}/{f}"] = (run_dir / n / f).read_bytes()
        if a["finished"] or not a["checkpoint"]:
            if a["finished"]:
                for pat in _ARM_EVAL_FILES:
                    for f in sorted((run_dir / n).glob(pat)):
                        files[f"{n}/{f.name}"] = f.read_bytes()
            info[n] = {"finished": a["finished"], "step": a.get("steps_done")}
            continue
        ck = torch.load(run_dir / n / "checkpoint.pt", map_location="cpu", weights_only=False)
        states[n] = _portable_state(ck, weights, optimizer)
        info[n] = {"finished": False, "step": int(ck["step"])}
    buf = io.BytesIO()
    torch.save({"format": PACK_FORMAT, "states": states, "files": files}, buf)
    blob = buf.getvalue()
    out = Path(out or run_dir / "pack")
    out.mkdir(parents=True, exist_ok=True)
    for old in list(out.glob("pack.part*")) + [out / PACK_MANIFEST]:
        if old.exists():
            old.unlink()
    size = max(1, int(float(part_mib) * 2 ** 20))
    parts = []
    for k in range(0, max(1, len(blob)), size):
        chunk = blob[k:k + size]
        name = f"pack.part{len(parts):03d}"
        tmp = out / f".{name}.tmp"
        tmp.write_bytes(chunk)
        os.replace(tmp, out / name)
        parts.append({"file": name, "bytes": len(chunk), "sha256": _sha256(chunk)})
    man = {"format": PACK_FORMAT, "created_utc": _utc(), "run_dir": str(run_dir), "weights": weights,
           "optimizer": optimizer, "bytes": len(blob), "sha256": _sha256(blob), "part_mib": float(part_mib),
           "parts": parts, "arms": info, **git_commit()}
    write_json_atomic(out / PACK_MANIFEST, man)
    return man


def unpack(pack_path, run_dir) -> dict:
    """Check the portable checkpoint at ``pack_path`` (its folder, or its ``pack.json``) and write it
    into the run folder ``run_dir``: each arm's ``checkpoint.pt`` (weights back in float32) and the small
    files. Every part's and the whole stream's sha256 must match the manifest (ValueError naming the
    part otherwise; FileNotFoundError for a missing part). Existing files of ``run_dir`` with the same
    names are replaced. Returns the manifest."""
    import torch
    p = Path(pack_path)
    man_path = p / PACK_MANIFEST if p.is_dir() else p
    if not man_path.exists():
        raise FileNotFoundError(f"--resume {pack_path}: no {PACK_MANIFEST} there (write one with: rwwarp design "
                                "pack RUN_DIR)")
    man = json.loads(man_path.read_text())
    if man.get("format") != PACK_FORMAT:
        raise ValueError(f"{man_path}: not a design pack (format {man.get('format')!r}, expected {PACK_FORMAT!r})")
    chunks = []
    for part in man["parts"]:
        f = man_path.parent / part["file"]
        if not f.exists():
            raise FileNotFoundError(f"{man_path}: part {part['file']} is missing (all {len(man['parts'])} parts "
                                    "must be in the folder of pack.json)")
        b = f.read_bytes()
        if len(b) != part["bytes"] or _sha256(b) != part["sha256"]:
            raise ValueError(f"{f}: damaged or from another pack ({len(b)} bytes, sha256 differs from "
                             f"{man_path.name})")
        chunks.append(b)
    blob = b"".join(chunks)
    if _sha256(blob) != man["sha256"]:
        raise ValueError(f"{man_path}: the parts do not add up to the packed stream (sha256)")
    data = torch.load(io.BytesIO(blob), map_location="cpu", weights_only=False)
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    for rel, b in data["files"].items():
        dst = run_dir / rel
        dst.parent.mkdir(parents=True, exist_ok=True)
        tmp = dst.with_name(f".{dst.name}.tmp")
        tmp.write_bytes(b)
        os.replace(tmp, dst)
    for name, st in data["states"].items():
        st = dict(st)
        st["net"] = {k: v.float() if v.is_floating_point() else v for k, v in st["net"].items()}
        if st.get("opt_net") is not None:
            o = dict(st["opt_net"])
            o["state"] = {k: {n: (t.float() if torch.is_tensor(t) and t.is_floating_point() and t.dim() > 0 else t)
                              for n, t in s.items()} for k, s in o["state"].items()}
            st["opt_net"] = o
        d = run_dir / name
        d.mkdir(parents=True, exist_ok=True)
        tmp = d / "checkpoint.tmp"
        torch.save(st, tmp)
        os.replace(tmp, d / "checkpoint.pt")
    return man


# ---------------------------------------------------------------------------------------------- resume helpers
def rng_state(gen) -> dict:
    """The random states a checkpoint keeps: Python's, numpy's, torch's (CPU and every CUDA device) and the arm's
    generator ``gen``'s."""
    import numpy as np
    import torch
    return {"python": random.getstate(), "numpy": np.random.get_state(), "torch": torch.get_rng_state(),
            "gen": gen.get_state(), "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None}


def set_rng_state(st: dict, gen) -> None:
    """Restore the states :func:`rng_state` returned (``gen``: the arm's generator); CUDA's where the machine has it."""
    import numpy as np
    import torch
    random.setstate(st["python"])
    np.random.set_state(st["numpy"])
    torch.set_rng_state(st["torch"])
    gen.set_state(st["gen"])
    if st.get("cuda") is not None and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(st["cuda"])


def truncate_csv(path: Path, step: int, fields=None):
    """Drop rows at or after ``step`` (a resumed run rewrites them). With ``fields``, the file is
    rewritten with those columns (a CSV of an older version gets the new ones, empty in old rows)."""
    if not path.exists():
        return
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
        old = list(rows[0].keys()) if rows else None
    if old is None:
        return
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(fields or old), restval="", extrasaction="ignore")
        w.writeheader()
        for r in rows:
            if int(r["step"]) < step:
                w.writerow(r)


# ---------------------------------------------------------------------------------------------- metrics.csv rows
# fft_plans_built: the wave backend's FFT plans built since the process started (each a VkFFT kernel build, NVRTC on
# CUDA, 0.3-1 s at lengths of a few thousand); it stops growing once every plan a step needs is kept
# torch_gb / torch_peak_gb (CUDA; empty on the CPU): torch's allocator after the step (what is held between steps:
# growth there is something kept) and its peak since the run started (the row where it jumps is the step that raised it)
# provider_held_gb: what the PSF provider keeps between steps (GB = 1e9 bytes; a live provider's packed tiles' operators
# and plan tables, LiveProvider.held_bytes; a cached provider's fields and operators, CachedProvider.cache_bytes)
# live_unit_gb: the estimated recorded peak (forward + backward, GB) of the largest checkpoint unit of the last live
# call (LiveProvider.unit_record_bytes; held to the record share, half of optics.memory_budget_gb): the plans of a
# learning lens grow, and this is where the step's peak follows them (empty without a live tile)
CSV_FIELDS = ["step", "phase", "loss", "mse", "perceptual", "psnr_train", "lr_network", "optics_step", "wall_s",
               "replans", "memory_gb", "torch_gb", "torch_peak_gb", "fft_plans_built", "provider_held_gb",
               "live_unit_gb"]


def read_row(row):
    """``row`` (a metrics row, dict, or None) with its device-tensor values (0-d) read as floats, all in one host read
    (a read waits for the device: the design loop reads its rows at the log steps only)."""
    if row is None:
        return None
    import torch
    keys = [k for k, v in row.items() if torch.is_tensor(v)]
    if not keys:
        return row
    vals = torch.stack([row[k].detach().reshape(()).double() for k in keys]).tolist()
    return {**row, **dict(zip(keys, vals))}


def provider_gb(provider) -> dict:
    """``provider_held_gb`` and ``live_unit_gb`` of the metrics (GB = 1e9 bytes; see ``CSV_FIELDS``), empty strings
    where the provider has no such figure."""
    held = provider.held_bytes() if hasattr(provider, "held_bytes") else \
        provider.cache_bytes() if hasattr(provider, "cache_bytes") else None
    units = [b for b in getattr(provider, "unit_record_bytes", None) or [] if b is not None]
    return {"provider_held_gb": "" if held is None else round(held / 1e9, 6),
            "live_unit_gb": round(max(units) / 1e9, 6) if units else ""}
