"""PSF maps sharded over processes with ``torch.distributed`` (NCCL on GPUs, gloo on CPUs).

:func:`psf_map` computes the same map as :func:`rwwarp.psf_map` (every (field, wavelength) pair, and
optionally every depth) with its sources split across the ranks of a ``torch.distributed`` job:

* **Work units.** The sources are cut into the same batches :func:`rwwarp.psf_map` makes (one
  planning pilot per depth; every source on its own plan, packed batches), so every PSF is computed
  with exactly the plan the single-process map gives it (its own: a PSF does not depend on its batch):
  the sharded map equals ``rw.psf_map`` (measured: bit for bit on the CPU, test tolerance 1e-12).
  Every rank plans every unit (one pilot trace of all sources a depth: the costs below need every unit's plans),
  keeps its own units' planned members and runs them (:func:`rwwarp.map_run.run_planned`): each source's pilot is
  traced and planned once on a rank, not again for its run. Until the assignment, a rank holds every depth's
  planned members (their total is bounded as one ``rw.psf_map`` call's: ``checks.MAX_SOURCES`` sources).
* **Balance by estimated work, not by count.** Each batch's cost is the planner's estimate, the sum
  of its sources' (:func:`rwwarp.wave.plan.estimate_cost` of each source's own plan): off-axis and
  large-aperture sources cost more. Batches are
  assigned largest first to the least-loaded rank (LPT; within 4/3 of the best split).
* **Devices.** Each rank runs on its own device: ``device="cuda"`` becomes ``cuda:LOCAL_RANK``;
  ``cpu`` stays ``cpu``.
* **Output.** ``out=None``: the PSFs are gathered on rank 0, which returns the :class:`PSFMap`
  (other ranks return None). ``out=FOLDER``: streaming, for maps larger than memory: every batch is
  written as soon as it is done to ``FOLDER/shards/d<depth>_b<batch>.npz`` (a temporary name, then
  renamed) and rank 0 writes ``FOLDER/index.json`` at the end; :func:`load_map` assembles it (or
  reads single batches). The format is numpy's own ``.npz``: no new dependency, one writer per file
  (HDF5 needs an MPI build of h5py for several writers to one file, Zarr would be a new dependency
  for what is here a handful of arrays per batch).
* **Progress.** With ``progress=True`` rank 0 shows one tqdm bar counting every rank's finished
  PSFs (each rank adds to a counter in the job's key-value store; a thread on rank 0 polls it).
* **Failures.** An exception on one rank ends that process; the launcher (torchrun or
  :func:`launch`) then stops the others and reports the failing rank's error. Every collective has
  the process group's timeout (``timeout_s``), so a rank that hangs cannot block the rest forever.

Without ``torch.distributed`` (no ``WORLD_SIZE`` > 1 in the environment and no initialised group)
:func:`psf_map` runs in this process and never imports torch; ``torch.distributed`` is imported only
when more processes are asked for. :func:`launch` starts ``N`` workers through torch's own launcher
(``torch.distributed.launcher.elastic_launch``, what ``torchrun`` uses); the same code runs unchanged
under an external ``torchrun --nproc-per-node N``. ``rwwarp map LENS --procs N`` uses it.

NCCL: the NCCL paths (``cuda:LOCAL_RANK``, ``backend="nccl"``) are written but have only run on gloo
(CPU) here: no multi-GPU machine was available.

Lengths in mm, wavelengths in um, fields in degrees.
"""
from __future__ import annotations

import json
import os
import threading
import time
from pathlib import Path

import numpy as np

__all__ = ["DistributedError", "assign", "launch", "load_map", "plan_work", "psf_map", "world"]

DEFAULT_TIMEOUT_S = 1800.0
_PROGRESS_KEY = "rwwarp/psf_done"


class DistributedError(RuntimeError):
    """A worker of a distributed run failed: ``rank`` and the worker's own error ``message``."""

    def __init__(self, rank, message: str):
        super().__init__(f"rank {rank}: {message}")
        self.rank, self.message = rank, message


# ---------------------------------------------------------------------------------------------- ranks
def world() -> tuple:
    """``(rank, world_size, local_rank)`` of this process: from an initialised ``torch.distributed``
    group, else from the launcher's environment (``RANK``, ``WORLD_SIZE``, ``LOCAL_RANK``), else
    ``(0, 1, 0)``. Imports torch only when the environment names more than one process."""
    ws = int(os.environ.get("WORLD_SIZE", "1") or 1)
    if ws > 1:
        import torch.distributed as dist
        if dist.is_available() and dist.is_initialized():
            return dist.get_rank(), dist.get_world_size(), int(os.environ.get("LOCAL_RANK", "0"))
        return int(os.environ.get("RANK", "0")), ws, int(os.environ.get("LOCAL_RANK", "0"))
    return 0, 1, 0


def rank_device(device: str, local_rank: int) -> str:
    """This rank's device: ``cuda`` (or ``cuda:K``) -> ``cuda:LOCAL_RANK``; anything else unchanged."""
    return f"cuda:{local_rank}" if str(device).startswith("cuda") else str(device)


def init_group(device: str = "cpu", timeout_s: float = DEFAULT_TIMEOUT_S):
    """Initialise the default process group from the launcher's environment if it is not yet
    (NCCL for a CUDA device, gloo otherwise; ``timeout_s`` for every collective) and return
    ``torch.distributed``. Sets the CUDA device to ``LOCAL_RANK`` for NCCL."""
    import datetime

    import torch.distributed as dist
    if not dist.is_initialized():
        backend = "nccl" if str(device).startswith("cuda") else "gloo"
        if backend == "nccl":
            import torch
            torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", "0")))
        dist.init_process_group(backend, timeout=datetime.timedelta(seconds=float(timeout_s)))
    return dist


# ---------------------------------------------------------------------------------------------- planning
def assign(costs, n_ranks: int) -> list:
    """Work units to ranks, balanced by cost: largest first to the least-loaded rank (ties: the lower
    rank, the lower unit index), deterministic. Returns one list of unit indices per rank (sorted)."""
    loads = [0.0] * n_ranks
    out = [[] for _ in range(n_ranks)]
    for k in sorted(range(len(costs)), key=lambda k: (-float(costs[k]), k)):
        r = min(range(n_ranks), key=lambda r: (loads[r], r))
        out[r].append(k)
        loads[r] += float(costs[k])
    return [sorted(u) for u in out]


def _check_args(lens, fields, wavelengths_um, depths_mm, kw):
    """The argument checks of :func:`rwwarp.psf_map` (:func:`rwwarp.map_run.map_args`: the same checks and
    messages, the same resolved budget, RayWave options and ``focal_precision``), plus ``depths_mm``. Returns
    ``(MapArgs, depths)``."""
    from . import checks
    from .map_run import map_args
    depths = [None] if depths_mm is None else list(depths_mm)
    if not depths:
        raise ValueError("depths_mm must hold at least one object distance (mm) or be None")
    a = map_args(lens, fields, wavelengths_um, n_depths=len(depths), **kw)
    for d in depths:
        checks.check_object_distance(d, "depths_mm")
    return a, depths


def plan_work(lens, a, depths=(None,)) -> list:
    """The work units of a map: ``[{"depth": k, "pairs": [(i, j), ...], "cost": flops}, ...]``.

    ``a``: the map's checked arguments (:func:`rwwarp.map_run.map_args`). Per depth, the batches
    :func:`rwwarp.psf_map` makes for these arguments (:func:`rwwarp.map_run.map_units`: every source on its own
    plan, from one pilot of all, packed by :func:`rwwarp.psf.pack_sources`), so each PSF is the one it is there.
    ``cost``: for the wave models, the sum of the sources' estimated flops
    (:func:`rwwarp.wave.plan.estimate_cost`); for the ray model (a fixed 401^2-ray pupil grid a source), the
    number of its sources."""
    return _plan_units(lens, a, depths)[0]


def _plan_units(lens, a, depths) -> tuple:
    """:func:`plan_work` and each unit's planned members (:func:`rwwarp.map_run.plan_units`; None for the ray
    model): ``(units, members)``, ``members[u]`` for ``units[u]``. The members are what :func:`_run_unit` runs:
    every source's pilot is traced and planned once."""
    from .map_run import plan_units
    pairs = [(i, j) for i in range(len(a.fields)) for j in range(len(a.wls))]
    units, members = [], []
    for k, od in enumerate(depths):
        for c, cst, m in plan_units(lens, a, pairs, od):
            units.append({"depth": k, "pairs": [tuple(p) for p in c], "cost": float(len(c) if cst is None else cst)})
            members.append(m)
    return units, members


def _run_unit(lens, a, unit, od, members=None):
    """One batch exactly as :func:`rwwarp.psf_map` computes it: its planned ``members`` (:func:`_plan_units`, the
    plans ``rw.psf_map`` gives its sources) run by :func:`rwwarp.map_run.run_planned`; the ray model (``members``
    None): :func:`rwwarp.map_run.run_sources` on the unit's pairs. Returns
    ``[(i, j, psf, centre, valid_fraction, dropped, plan)]``."""
    from .map_run import run_planned, run_sources
    out = []

    def store(chunk, res):
        plans = res.get("plans", [res.get("plan")] * len(chunk))
        for k, (i, j) in enumerate(chunk):
            out.append((i, j, np.asarray(res["data"][k]), np.asarray(res["centers"][k]),
                        float(res["valid_fraction"][k]),
                        int(res["dropped_rays"][k]) if "dropped_rays" in res else 0, plans[k]))
    if members is None:
        run_sources(lens, a, list(unit), od, store)
    else:
        store(list(unit), run_planned(a, members))
    return out


# ---------------------------------------------------------------------------------------------- progress
class _Progress:
    """Rank 0: one tqdm bar over every rank's finished PSFs. The other ranks add to a counter in the
    job's key-value store (a key of its own per map); on rank 0 a thread polls it and adds rank 0's own
    count (so only that thread uses the store on rank 0)."""

    _calls = 0   # maps made in this process: the same sequence on every rank (psf_map is collective)

    def __init__(self, store, total: int, rank: int, enabled: bool, desc: str):
        _Progress._calls += 1
        self.key = f"{_PROGRESS_KEY}/{_Progress._calls}"
        self.store, self.rank, self.total = store, rank, total
        self.own, self.bar, self._stop, self._thread = 0, None, threading.Event(), None
        if enabled and rank == 0:
            from tqdm.auto import tqdm
            self.bar = tqdm(total=total, desc=desc, unit="PSF")
            if store is not None:
                self._thread = threading.Thread(target=self._poll, daemon=True)
                self._thread.start()

    def _show(self):
        n = self.own + int(self.store.add(self.key, 0))
        self.bar.update(max(0, min(n, self.total) - self.bar.n))

    def _poll(self):
        while not self._stop.wait(0.25):
            try:
                self._show()
            except Exception:  # noqa: BLE001 - the store went away (job ending): stop polling
                return

    def add(self, n: int):
        if self.rank == 0:
            self.own += int(n)
            if self._thread is None and self.bar is not None:
                self.bar.update(n)
        elif self.store is not None and n:
            self.store.add(self.key, int(n))

    def close(self):
        """Rank 0, after every rank has finished (the gather): the final count, then the bar closes."""
        if self.bar is None:
            return
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            try:
                self._show()
            except Exception:  # noqa: BLE001 - a missing store only leaves the bar short
                self.bar.update(max(0, self.total - self.bar.n))
        self.bar.close()


def _default_store(dist):
    try:
        from torch.distributed.distributed_c10d import _get_default_store
        return _get_default_store()
    except Exception:  # noqa: BLE001 - no store API: rank 0's bar then counts its own work only
        return None


# ---------------------------------------------------------------------------------------------- the map
def psf_map(lens, fields, wavelengths_um, depths_mm=None, *, model: str = "ray-wave", size: int = 64,
            device: str = "cpu", plan="auto", dtype: str = "float64", amplitude: str = "energy",
            rays_per_sample: float = 1.0, pixel_mm=None, center_mm=None, use_reference: bool = True,
            gauss_nodes: int | None = None, batch: int | None = None, nyquist_safety: float = 2.0,
            method: str = "auto", memory_budget_gb: float | None = None, progress: bool = False,
            out=None, timeout_s: float = DEFAULT_TIMEOUT_S, object_distance_mm=None, focal_patch_tol: float = 1e-5,
            deterministic: bool = False, pixel_values: str = "flux", focal_precision: str = "auto",
            tolerance: float | None = None):
    """The map of :func:`rwwarp.psf_map` computed by every rank of the current job (see the module
    docstring). Arguments as :func:`rwwarp.psf_map` (taken, checked, planned and run by the same code,
    :mod:`rwwarp.map_run`; no ``cache``: kept plans do not cross processes); ``depths_mm``: a list of object
    distances (mm, None: the lens's own) to map at each, or None for one map at ``object_distance_mm``.

    Returns on rank 0 a :class:`~rwwarp.psf.PSFMap` (``depths_mm`` None) or a list of them (one per
    depth), with ``info["ranks"]`` (units, PSFs, estimated and measured seconds per rank) and
    ``info["units"]``; None on the other ranks. With ``out`` (a folder) the PSFs are streamed to
    shards instead of gathered and every rank returns None but rank 0, which returns the index
    (:func:`load_map` reads it back). The warnings of :func:`rwwarp.psf_map` (model error over ``tolerance``, rays
    outside the window, PSFs cut by their patch) come from rank 0 for the gathered map, from each rank for its
    own batches when streaming."""
    from .map_run import finish_map
    from .psf import PSFMap
    kw = dict(model=model, size=size, device=device, plan=plan, dtype=dtype, amplitude=amplitude,
              rays_per_sample=rays_per_sample, pixel_mm=pixel_mm, center_mm=center_mm, use_reference=use_reference,
              gauss_nodes=gauss_nodes, batch=batch, nyquist_safety=nyquist_safety, method=method,
              memory_budget_gb=memory_budget_gb, focal_patch_tol=focal_patch_tol, deterministic=deterministic,
              pixel_values=pixel_values, focal_precision=focal_precision, tolerance=tolerance)
    single_depth = depths_mm is None
    depths_in = [object_distance_mm] if single_depth else depths_mm
    a, depths = _check_args(lens, fields, wavelengths_um, depths_in, kw)
    rank, ws, local = world()
    dist = None
    if ws > 1:
        dist = init_group(device, timeout_s)
        rank, ws = dist.get_rank(), dist.get_world_size()
        if rank_device(device, local) != device:   # this rank's device: its budget, RayWave options, precision
            kw["device"] = rank_device(device, local)
            a, depths = _check_args(lens, fields, wavelengths_um, depths_in, kw)
    fields, wls = a.fields, a.wls
    t0 = time.perf_counter()
    # ---- plan: every rank the same pilot and units, checked alike on every rank so that each assigns the same
    # (every rank plans every unit, for the costs the assignment needs; each keeps its own units' planned members
    # and runs them: every source's pilot traced and planned once on its rank)
    units, planned = _plan_units(lens, a, depths)
    if dist is not None:
        every = [None] * ws
        dist.all_gather_object(every, units)
        for r, theirs in enumerate(every):
            if [u["pairs"] for u in theirs] != [u["pairs"] for u in units]:
                raise DistributedError(r, "planned other work units than rank "
                                       f"{rank} for the same map (a non-deterministic pilot?)")
    owners = assign([u["cost"] for u in units], ws)
    mine = owners[rank]
    for u in set(range(len(units))) - set(mine):
        planned[u] = None   # another rank's: its tracer and plans can go
    t_plan = time.perf_counter() - t0
    store = _default_store(dist) if dist is not None else None
    total = sum(len(u["pairs"]) for u in units)
    bar = _Progress(store, total, rank, progress, f"{model} PSFs ({ws} rank{'s' if ws > 1 else ''})")
    shards = None
    if out is not None:
        shards = Path(out) / "shards"
        shards.mkdir(parents=True, exist_ok=True)
    results, streamed, t1 = {}, [], time.perf_counter()
    try:
        for u in mine:
            unit = units[u]
            rows = _run_unit(lens, a, unit["pairs"], depths[unit["depth"]], planned[u])
            planned[u] = None   # done: its operators and tracer can go
            if shards is not None:
                _write_shard(shards / f"d{unit['depth']}_b{u}.npz", rows)
                streamed.append((unit["depth"], [(i, j, float(np.sum(d)), v, n, p) for i, j, d, _, v, n, p in rows]))
            else:
                results[u] = rows
            bar.add(len(unit["pairs"]))
    finally:
        if dist is None:
            bar.close()
    t_work = time.perf_counter() - t1
    # streaming: each rank's warnings for its own batches (the PSFs are on disk, not gathered)
    for k in range(len(depths) if shards is not None else 0):
        power, valid = np.zeros((len(fields), len(wls))), np.zeros((len(fields), len(wls)))
        dropped, plans = np.zeros((len(fields), len(wls)), dtype=np.int64), []
        for i, j, p, v, n, pl in (r for d, rows in streamed if d == k for r in rows):
            power[i, j], valid[i, j], dropped[i, j] = p, v, n
            plans.append(pl)
        finish_map(a, power, valid.ravel(), dropped.ravel(), plans)
    me = {"rank": rank, "units": mine, "psfs": sum(len(units[u]["pairs"]) for u in mine),
          "estimated_flops": sum(units[u]["cost"] for u in mine), "work_s": t_work, "device": kw["device"]}
    # ---- gather (or collect the shard index) on rank 0
    if dist is not None:
        gathered = [None] * ws if rank == 0 else None
        dist.gather_object((me, results), gathered, dst=0)
        bar.close()
        if rank != 0:
            return None
        per_rank = [g[0] for g in gathered]
        for g in gathered:
            results.update(g[1])
    else:
        per_rank = [me]
    pixel = a.pixel
    info_common = {"ranks": per_rank, "world_size": ws, "plan_s": t_plan, "time_s": time.perf_counter() - t0,
                   "units": [{"depth": u["depth"], "pairs": u["pairs"], "cost": u["cost"],
                              "rank": next(r for r in range(ws) if k in owners[r])} for k, u in enumerate(units)]}
    if shards is not None:
        index = {"fields_deg": [np.atleast_1d(f).tolist() for f in fields], "wavelengths_um": wls, "depths_mm": depths,
                 "single_depth": single_depth, "size": kw["size"], "pixel_mm": pixel, "model": model,
                 "shards": [{"file": f"shards/d{u['depth']}_b{k}.npz", **{kk: v for kk, v in u.items()}}
                            for k, u in enumerate(info_common["units"])], "info": info_common}
        _atomic_json(Path(out) / "index.json", index)
        return index
    maps = []
    for k, od in enumerate(depths):
        data = np.zeros((len(fields), len(wls), kw["size"], kw["size"]))
        centers = np.zeros((len(fields), len(wls), 2))
        valid = np.zeros((len(fields), len(wls)))
        dropped = np.zeros((len(fields), len(wls)), dtype=np.int64)
        plans = []
        for u, rows in results.items():
            if units[u]["depth"] != k:
                continue
            for i, j, d, c, v, n, pl in rows:
                data[i, j], centers[i, j], valid[i, j], dropped[i, j] = d, c, v, n
                plans.append(pl)
        info = dict(info_common, object_distance_mm=od, valid_fraction=list(valid.ravel()),
                    dropped_rays=dropped.ravel())
        # the warnings of rw.psf_map, from the same code (rwwarp.map_run.finish_map)
        info["power_in_patch"] = finish_map(a, data.sum(axis=(2, 3)), info["valid_fraction"], info["dropped_rays"],
                                            plans)
        maps.append(PSFMap(data, pixel, centers, fields, wls, model, info))
    return maps[0] if single_depth else maps


def _write_shard(path: Path, rows):
    tmp = path.with_name(f".{path.stem}.tmp{os.getpid()}.npz")
    with open(tmp, "wb") as fh:
        np.savez(fh, index=np.array([(i, j) for i, j, *_ in rows], dtype=np.int64).reshape(-1, 2),
                 psf=np.stack([r[2] for r in rows]), centers_mm=np.stack([r[3] for r in rows]),
                 valid_fraction=np.array([r[4] for r in rows]), dropped_rays=np.array([r[5] for r in rows]))
    os.replace(tmp, path)


def _atomic_json(path: Path, obj):
    tmp = path.with_name(f".{path.stem}.tmp{os.getpid()}.json")
    tmp.write_text(json.dumps(obj, indent=1, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o)))
    os.replace(tmp, path)


def load_map(folder):
    """Assemble a streamed map (``psf_map(..., out=folder)``) into a :class:`PSFMap` (or a list, one
    per depth, when it was made with ``depths_mm``)."""
    from .psf import PSFMap
    folder = Path(folder)
    idx = json.loads((folder / "index.json").read_text())
    fields = [tuple(f) if len(f) > 1 else f[0] for f in idx["fields_deg"]]
    nf, nw, n = len(fields), len(idx["wavelengths_um"]), idx["size"]
    maps = []
    for k, od in enumerate(idx["depths_mm"]):
        data, centers = np.zeros((nf, nw, n, n)), np.zeros((nf, nw, 2))
        for s in idx["shards"]:
            if s["depth"] != k:
                continue
            with np.load(folder / s["file"]) as z:
                for (i, j), p, c in zip(z["index"], z["psf"], z["centers_mm"]):
                    data[i, j], centers[i, j] = p, c
        maps.append(PSFMap(data, idx["pixel_mm"], centers, fields, idx["wavelengths_um"], idx["model"],
                           dict(idx["info"], object_distance_mm=od)))
    return maps[0] if idx["single_depth"] else maps


# ---------------------------------------------------------------------------------------------- launching
def launch(fn, nprocs: int, *args, timeout_s: float = DEFAULT_TIMEOUT_S, start_method: str = "spawn") -> list:
    """Run ``fn(*args)`` in ``nprocs`` worker processes through torch's launcher (the elastic agent
    behind ``torchrun``: standalone rendezvous on this host, no restarts) and return the workers'
    return values by rank. ``fn`` must be importable by name (a module-level function). A failing
    worker stops all of them; the first failure is raised as :class:`DistributedError` with that
    rank's error message (the launcher records each worker's exception)."""
    import uuid

    from torch.distributed.elastic.multiprocessing.errors import ChildFailedError
    from torch.distributed.launcher.api import LaunchConfig, elastic_launch
    import dataclasses
    extra = {}
    if "shutdown_timeout" in {f.name for f in dataclasses.fields(LaunchConfig)}:
        extra["shutdown_timeout"] = 10   # torch >= 2.12; older launchers have a fixed one
    cfg = LaunchConfig(min_nodes=1, max_nodes=1, nproc_per_node=int(nprocs), run_id=str(uuid.uuid4()),
                       rdzv_backend="c10d", rdzv_endpoint="localhost:0", max_restarts=0, monitor_interval=0.1,
                       start_method=start_method, rdzv_configs={"timeout": int(timeout_s)}, **extra)
    # as torchrun does: one OpenMP thread a worker unless the caller chose (N workers share the cores)
    omp = os.environ.get("OMP_NUM_THREADS")
    if omp is None and nprocs > 1:
        os.environ["OMP_NUM_THREADS"] = "1"
    try:
        res = elastic_launch(cfg, fn)(*args)
    except ChildFailedError as e:
        rank, failure = e.get_first_failure()
        raise DistributedError(rank, _failure_message(failure)) from None
    finally:
        if omp is None:
            os.environ.pop("OMP_NUM_THREADS", None)
    return [res[r] for r in sorted(res)]


def _failure_message(failure) -> str:
    """The worker's own error (the last line of its recorded traceback) from a ProcessFailure."""
    msg = failure.message
    if isinstance(msg, dict):
        inner = msg.get("message")
        msg = inner.get("message") if isinstance(inner, dict) else (inner or json.dumps(msg))
    text = str(msg).strip()
    if not text or text.startswith("To enable traceback"):
        text = f"exit code {failure.exitcode}"
    return text
