"""The one PSF-map orchestrator: what :func:`rwwarp.psf_map` and the sharded :func:`rwwarp.distributed.psf_map`
share, so that both take the same arguments, plan the same batches, run them the same way and warn alike.

* :func:`map_args` checks the arguments of a map (the messages of the public edge) and resolves what follows
  from them once: the memory budget (bytes), the pixel pitch (mm), the :class:`rwwarp.wave.raywave.RayWave`
  options (``model_tolerance``, ``allow_pixel`` included) and ``focal_precision`` ("auto" resolved per device).
* :func:`map_units` cuts a map's (field, wavelength) pairs into its batches: for the wave models every source on
  its own plan from one pilot, packed (:func:`rwwarp.psf.wave_members`, :func:`rwwarp.psf.pack_sources`), each
  batch with its planned flops; for the ray model chunks of ``batch`` pairs. :func:`plan_units` also keeps each
  batch's planned members, which :func:`run_planned` runs without planning them again (the distributed map).
* :func:`run_sources` computes pairs (a whole map, or one batch of it on a rank) and hands each batch's result to
  ``store(pairs, result)``: the wave models through :func:`rwwarp.psf._wave_map` (a ``pixel`` member alone, the
  rest packed; the plan cache), the ray model in chunks of ``batch``.
* :func:`finish_map` gives the map's warnings (model error over ``tolerance``, rays dropped outside the wave-plane
  window, PSFs cut by their patch) and the fraction of each PSF's traced power inside its patch.

Lengths in mm, wavelengths in um, fields in degrees. No torch here.
"""
from __future__ import annotations

import contextlib
import copy
import math
from dataclasses import dataclass

import numpy as np

from .wave.methods import get as get_method
from .wave.packed import PackedRayWave, packed_bytes, source_plans
from .wave.paraxial_wave import paraxial_equivalent

MODELS = ("ray-wave", "ray", "paraxial-wave")


def _check_tolerance(tolerance):
    """``tolerance`` (a model error relative to the PSF's peak) as a float in (0, 1], or None."""
    if tolerance is None:
        return None
    if isinstance(tolerance, bool) or not isinstance(tolerance, (int, float)) or not (0 < tolerance <= 1):
        raise ValueError(f"tolerance must be a number in (0, 1] (the model error accepted, relative to the PSF's "
                         f"peak) or None, got {tolerance!r}")
    return float(tolerance)


WAVE_MODELS = ("ray-wave", "paraxial-wave")


@dataclass(frozen=True)
class MapArgs:
    """Checked arguments of a map. ``fields`` (deg, the tracer's list form), ``wls`` (um), ``size`` (px),
    ``pixel`` (mm), ``budget`` (bytes: ``memory_budget_gb`` or the device default), ``opts`` (the
    :class:`~rwwarp.wave.raywave.RayWave` options with ``memory_budget_bytes``, ``model_tolerance`` and
    ``allow_pixel``), ``focal_precision`` ("single" / "double", resolved), ``tolerance`` (None or in (0, 1])."""

    model: str
    fields: list
    wls: list
    size: int
    pixel: float
    device: str
    dtype: str
    rays_per_sample: float
    center_mm: object
    batch: int | None
    budget: int
    memory_budget_gb: float | None
    focal_precision: str
    tolerance: float | None
    opts: dict
    #: multi-order phase surfaces (:mod:`rwwarp.phase_orders`): efficiency below which an order is skipped
    order_tol: float = 1e-4


def map_args(lens, fields, wavelengths_um, *, model="ray-wave", size=64, device="cpu", plan="auto",
             dtype="float64", amplitude="energy", object_distance_mm=None, rays_per_sample=1.0, pixel_mm=None,
             center_mm=None, use_reference=True, gauss_nodes=None, batch=None, nyquist_safety=2.0, method="auto",
             memory_budget_gb=None, focal_patch_tol=1e-5, focal_precision="auto", deterministic=False,
             pixel_values="flux", tolerance=None, n_depths: int = 1, order_tol: float = 1e-4) -> MapArgs:
    """The arguments of :func:`rwwarp.psf_map` checked (a clear error naming the argument and its range) and
    resolved (:class:`MapArgs`); ``n_depths``: object distances mapped (the distributed map's ``depths_mm``),
    for the bound on the number of sources. Arguments as :func:`rwwarp.psf`."""
    from . import checks
    from .wave.methods import choices as method_choices
    from .trace import as_field_list
    from .wave.plan import default_memory_budget_bytes
    checks.check_lens(lens)
    checks.check_choice(model, "model", MODELS)
    fields = checks.check_fields(fields)
    wavelengths_um = checks.check_wavelengths(wavelengths_um, lens)
    size = checks.check_size(size)
    checks.check_device(device)
    checks.check_choice(dtype, "dtype", ("float64", "float32"))
    checks.check_object_distance(object_distance_mm)
    checks.check_rays_per_sample(rays_per_sample)
    checks.check_pixel_mm(pixel_mm)
    checks.check_center(center_mm)
    checks.check_batch(batch)
    checks.check_nyquist_safety(nyquist_safety)
    if not isinstance(deterministic, bool):
        raise TypeError(f"deterministic must be True or False, got {deterministic!r}")
    if gauss_nodes is not None:
        checks.check_int(gauss_nodes, "gauss_nodes", lo=1, hi=64)
    checks.check_choice(pixel_values, "pixel_values", ("flux", "intensity"))
    if n_depths == 1:
        checks.check_int(len(fields) * len(wavelengths_um), "number of (field, wavelength) pairs", lo=1,
                         hi=checks.MAX_SOURCES)
    else:
        checks.check_int(len(fields) * len(wavelengths_um) * n_depths, "number of (field, wavelength, depth) sources",
                         lo=1, hi=checks.MAX_SOURCES)
    if amplitude not in ("energy", "paper"):
        raise ValueError(f"amplitude must be 'energy' or 'paper', got {amplitude!r}")
    checks.check_choice(method, "method", method_choices())
    tolerance = _check_tolerance(tolerance)
    focal_patch_tol = checks.check_number(focal_patch_tol, "focal_patch_tol", lo=0.0, hi=1.0)
    order_tol = checks.check_number(order_tol, "order_tol", lo=0.0, hi=1.0)
    if focal_precision not in ("auto", "single", "double"):
        raise ValueError(f"focal_precision must be 'auto', 'single' or 'double', got {focal_precision!r}")
    if memory_budget_gb is not None:
        gb = memory_budget_gb
        if not (isinstance(gb, (int, float)) and math.isfinite(gb) and gb > 0):
            raise ValueError(f"memory_budget_gb must be a positive number of GiB, got {memory_budget_gb!r}")
        budget = int(memory_budget_gb * 2 ** 30)
    else:
        budget = default_memory_budget_bytes(device)
    if focal_precision == "auto":   # as RayWave.run resolves it
        focal_precision = "double" if str(device).startswith("cuda") else "single"
    opts = dict(device=device, plan=plan, dtype=dtype, amplitude=amplitude, rays_per_sample=rays_per_sample,
                center_mm=center_mm, use_reference=use_reference, gauss_nodes=gauss_nodes,
                nyquist_safety=nyquist_safety, method=method, focal_patch_tol=focal_patch_tol,
                deterministic=deterministic, memory_budget_bytes=budget, pixel_values=pixel_values,
                model_tolerance=tolerance, allow_pixel=True)
    return MapArgs(model, as_field_list(fields), [float(w) for w in wavelengths_um], size,
                   float(pixel_mm or lens.sensor.pixel_pitch), device, dtype, rays_per_sample, center_mm, batch,
                   budget, memory_budget_gb, focal_precision, tolerance, opts, order_tol)


def map_units(lens, a: MapArgs, pairs, object_distance_mm=None) -> list:
    """The batches :func:`run_sources` computes ``pairs`` (indices into ``a.fields`` and ``a.wls``) in, at the
    object distance ``object_distance_mm`` (mm, None: the lens's): ``[(batch_pairs, flops), ...]``. Wave models:
    every source planned on its own from one pilot of all, packed (``flops``: the sum of the members' planned
    flops, :func:`rwwarp.wave.plan.estimate_cost`); ray model: chunks of ``a.batch`` pairs (``flops`` None)."""
    return [(c, cost) for c, cost, _ in plan_units(lens, a, pairs, object_distance_mm)]


def plan_units(lens, a: MapArgs, pairs, object_distance_mm=None) -> list:
    """:func:`map_units` with each batch's planned members: ``[(batch_pairs, flops, members), ...]``, ``members``
    the batch's single-source :class:`~rwwarp.wave.raywave.RayWave` s in the order of ``batch_pairs`` (planned as
    :func:`rwwarp.psf._wave_map` plans them: :func:`rwwarp.psf.wave_members`, one pilot trace of all ``pairs`` a
    system) for :func:`run_planned`; None for the ray model (nothing to plan)."""
    pairs = [tuple(p) for p in pairs]
    if a.model not in WAVE_MODELS:
        b = a.batch or len(pairs)
        return [(pairs[k:k + b], None, None) for k in range(0, len(pairs), b)]
    out = []
    for members, sys_pairs in wave_members(lens, a.fields, a.wls, pairs, a.model, a.size, a.pixel,
                                           object_distance_mm, a.opts):
        for idx in pack_sources(members, a.size, a.batch, batch_budget(a.device, a.batch, a.budget)):
            out.append(([sys_pairs[q] for q in idx], sum(float(members[q].plan.estimate["flops"]) for q in idx),
                        [members[q] for q in idx]))
    return out


def run_planned(a: MapArgs, members) -> dict:
    """One batch of :func:`plan_units` (its ``members``) computed as :func:`rwwarp.psf._wave_map` computes it
    uncached: a ``pixel`` member alone (:meth:`~rwwarp.wave.raywave.RayWave.run`), the others packed
    (:class:`~rwwarp.wave.packed.PackedRayWave`), with ``a.focal_precision``. Returns the batch's result dict."""
    if members[0].plan.method == "pixel":
        return members[0].run(a.focal_precision)
    from .wave.packed import PackedRayWave
    return PackedRayWave(list(members)).run(a.focal_precision)


def run_sources(lens, a: MapArgs, pairs, object_distance_mm, store, cache=None, info: dict | None = None):
    """Compute the PSFs of ``pairs`` (indices into ``a.fields`` and ``a.wls``; a whole map, or one batch of
    :func:`map_units`) at ``object_distance_mm`` (mm,
    None: the lens's), handing each batch's result dict (``data``, ``centers``, ``valid_fraction``,
    ``dropped_rays``, ``plan``, ``plans``) to ``store(batch_pairs, result)``. Wave models:
    :func:`rwwarp.psf._wave_map` (every source on its own plan, a ``pixel`` member alone, the rest packed;
    ``cache``: a :class:`~rwwarp.wave.plan_cache.PlanCache`, its outcome in ``info["cache"]``); ray model: chunks
    of ``a.batch`` pairs. Every batch with ``a.focal_precision``."""
    pairs = [tuple(p) for p in pairs]
    info = {} if info is None else info
    from .phase_orders import check_multi_order, multi_order_psf, multi_order_surfaces
    if multi_order_surfaces(lens):   # several orders of a phase surface, summed coherently (rwwarp.phase_orders)
        if cache is not None and cache.shared:   # the default cache: not for these (check_multi_order refuses one)
            cache = None
            info["cache"] = "off"
        check_multi_order(lens, a.model, a.opts.get("amplitude", "energy"), cache)
        for pr in pairs:
            res = multi_order_psf(lens, [a.fields[pr[0]]], [a.wls[pr[1]]], a.size, a.pixel, a.opts,
                                  object_distance_mm, a.focal_precision, a.order_tol)
            info.setdefault("orders", []).append(res["orders"][0])
            store([pr], res)
        return
    if a.model in WAVE_MODELS:
        held = False
        if cache is not None and cache.shared:
            held = cache.lock.acquire(blocking=False)
            if not held:   # a shared cache another thread is running through: this call runs uncached, not waiting
                cache = None
                info["cache"] = "busy"
        try:
            with (contextlib.nullcontext() if cache is None or held else cache.lock):   # a kept batch: one call at a time
                _wave_map(lens, a.fields, a.wls, pairs, a.model, a.size, a.pixel, object_distance_mm, a.batch,
                          a.budget, a.memory_budget_gb, a.focal_precision, a.opts, cache, info, store)
        finally:
            if held:
                cache.lock.release()
        return
    from .ray_model import _ray_model
    for chunk, _ in map_units(lens, a, pairs, object_distance_mm):
        res = _ray_model(lens, [a.fields[i] for i, _ in chunk], [a.wls[j] for _, j in chunk], a.size, a.pixel,
                         a.device, a.dtype, object_distance_mm, a.rays_per_sample, a.center_mm)
        store(chunk, res)


def finish_map(a: MapArgs, power, valid_fraction, dropped_rays, plans, stacklevel: int = 3) -> np.ndarray:
    """The warnings of a finished map (``power``: each PSF's sum, (n_fields, n_wavelengths); ``valid_fraction`` and
    ``dropped_rays`` per PSF, ``plans`` every PSF's plan dict or None): a plan without the wave step whose
    model-error estimate is over ``a.tolerance`` (:class:`~rwwarp.wave.model_error.ModelErrorWarning`), rays
    that fell outside the wave-plane window (:class:`~rwwarp.errors.SamplingWarning`), PSFs keeping less than
    95 % of their traced power in their patch (:class:`~rwwarp.errors.PatchWarning`). ``stacklevel``: the
    caller's frame seen from here. Returns the fraction of each PSF's traced power inside its patch
    (n_fields, n_wavelengths)."""
    import warnings
    from .trace import field_label as _fmt_field
    if a.tolerance is not None and a.model in WAVE_MODELS:
        from .wave.model_error import warn_over_tolerance
        warn_over_tolerance(plans, a.tolerance, stacklevel=stacklevel + 1)
    dropped = np.asarray(dropped_rays)
    if np.any(dropped):
        from .errors import SamplingWarning
        warnings.warn(f"{int(dropped.sum())} rays fell outside the wave-plane window and were not "
                      "splatted (their power is missing from the PSF): report this lens", SamplingWarning,
                      stacklevel=stacklevel)
    # a PSF that does not fit its patch is said, not silently cut (issue 13): fraction of the traced power inside
    power = np.asarray(power, float)
    vf = np.asarray(valid_fraction, float).reshape(power.shape)
    inside = power / np.where(vf > 0, vf, np.inf)
    cut = [f"{_fmt_field(a.fields[i])} at {a.wls[j]:g} um: {inside[i, j]:.3f}"
           for i, j in zip(*np.nonzero((inside < 0.95) & (vf > 0)))]
    if cut:
        from .errors import PatchWarning
        warnings.warn(f"{len(cut)} PSF(s) keep less than 95 % of their traced power in the {a.size}x{a.size} px patch "
                      f"({'; '.join(cut[:6])}{'; ...' if len(cut) > 6 else ''}); pass a larger size", PatchWarning,
                      stacklevel=stacklevel)
    return inside


def _wave_map(lens, fields, wavelengths_um, pairs, model, size, pixel, object_distance_mm, batch, budget,
              memory_budget_gb, focal_precision, opts, cache, info, store):
    """The wave models' part of :func:`psf_map`: plan (or take from ``cache``) and run every batch, handing each
    batch's result to ``store(pairs, result)``. ``focal_precision`` resolved ("single" / "double")."""
    kept = key = None
    if cache is not None:
        args = (model, fields, wavelengths_um, size, pixel, object_distance_mm, batch, focal_precision,
                memory_budget_gb, tuple(sorted((k, v) for k, v in opts.items() if k != "memory_budget_bytes")))
        try:
            key, kept = cache.lookup(lens, args, None if memory_budget_gb is not None else budget)
        except TypeError:   # a value the fingerprint cannot read (rwwarp.wave.plan_cache.lens_fingerprint)
            if not cache.shared:
                raise
            cache = None    # the default cache: this call runs uncached
            info["cache"] = "off"
    if cache is not None:
        info["cache"] = "miss" if kept is None else "hit"
    from .wave.plan_cache import held_bytes
    if kept is not None:
        from .wave.graph_replay import run_kept
        info["replay"] = []
        for chunk, packed in kept:   # the pilot, plans, batches and operators of an earlier call
            res, how = run_kept(packed, focal_precision, graphs=cache.graphs)   # a CUDA graph where it can be
            info["replay"].append(how)
            store(chunk, res)
    else:
        keep = cache is not None
        work_pool = {}
        run_lens = copy.deepcopy(lens) if keep else lens   # kept batches see no later change of the caller's lens
        new, need, held = [], 0, 0
        for members, sys_pairs in wave_members(run_lens, fields, wavelengths_um, pairs, model, size, pixel,
                                               object_distance_mm, opts):
            for chunk_idx in pack_sources(members, size, batch, batch_budget(opts.get("device", "cpu"), batch, budget)):
                if not get_method(members[chunk_idx[0]].plan.method).packable:
                    # no wave-plane field to pack: computed alone, and a call with such a member keeps nothing
                    store([sys_pairs[k] for k in chunk_idx], members[chunk_idx[0]].run(focal_precision))
                    keep, new = False, []
                    members[chunk_idx[0]] = None
                    continue
                packed = PackedRayWave([members[k] for k in chunk_idx], hold=keep)
                if str(packed.device) == "cpu":
                    # the CPU's batches share their work arrays (rays, splat sums, field; Tracer.work_array), each
                    # batch's read before the next runs: no allocation and first touch of fresh pages a batch. Kept
                    # batches too (a hit runs them one after the other under the cache's lock, each read before the
                    # next): the entry holds one set of work arrays, the largest batch's, not one a batch
                    packed.tracer.pool = work_pool
                res = packed.run(focal_precision, keep_operators=keep)
                store([sys_pairs[k] for k in chunk_idx], res)
                if keep:
                    new.append(([sys_pairs[k] for k in chunk_idx], packed))
                    need = max(need, packed_bytes(packed.members, size))
                    held = held_bytes(new)   # the whole entry: its batches share one CPU work pool
                    if held > cache.max_bytes:   # over the cache's bound: nothing of this call is kept
                        keep, new = False, []
                for k in chunk_idx:
                    members[k] = None   # done: its operators and tracer can go
        if keep:
            cache.store(key, new, need)


def wave_members(lens, fields, wavelengths_um, pairs, model, size, pixel, object_distance_mm, opts) -> list:
    """Every (field, wavelength) pair of ``pairs`` (indices into ``fields`` (deg) and ``wavelengths_um``)
    planned on its own (:func:`rwwarp.wave.packed.source_plans`) for the wave models: ``[(members, pairs), ...]``,
    one entry per system (ray-wave: the lens; paraxial-wave: its equivalent at each wavelength), ``members``
    in the order of that entry's ``pairs``. ``opts``: the :class:`RayWave` options (``device``, ``plan``, ...,
    ``memory_budget_bytes``); ``size`` px of ``pixel`` mm; ``object_distance_mm`` (mm, None: the lens's)."""
    out = []
    if model == "ray-wave":
        out.append((source_plans(lens, [fields[i] for i, _ in pairs], [wavelengths_um[j] for _, j in pairs], size,
                                 pixel, object_distance_mm=object_distance_mm, **opts), list(pairs)))
        return out
    for j, w in enumerate(wavelengths_um):
        sub = [(i, jj) for i, jj in pairs if jj == j]
        if not sub:
            continue
        eq, eq_fields = paraxial_equivalent(lens, [fields[i] for i, _ in sub], [w], object_distance_mm)
        out.append((source_plans(eq, list(eq_fields), [w] * len(sub), size, pixel, **opts), sub))
    return out


#: On the CPU, without ``batch``, a packed batch's planned bytes (:func:`rwwarp.wave.packed.packed_bytes`) are kept
#: under this as well as the memory budget: its threads take whole sources (rwwarp.wave.splat.Splatter.sums) and its
#: launches cost little, so a larger batch only adds memory (the 10 x 10 x 3 A489 + DOE map at 32 px held 6.3 GiB
#: in batches up to the budget)
CPU_BATCH_BYTES = 512 * 2 ** 20


def batch_budget(device: str, batch: int | None, budget_bytes: int) -> int:
    """The bytes a packed batch may plan (:func:`pack_sources`): ``budget_bytes``, and on the CPU without ``batch``
    at most :data:`CPU_BATCH_BYTES` (a member larger than that alone still runs, alone)."""
    if batch is None and str(device) == "cpu":
        return min(int(budget_bytes), CPU_BATCH_BYTES)
    return int(budget_bytes)


def pack_sources(members, size: int, batch: int | None, budget_bytes: int) -> list:
    """Batches of indices into ``members`` (single-source :class:`RayWave` s, each on its own plan) for
    :class:`PackedRayWave`: members of one propagation method (and rim weighting), largest first (a batch's
    arrays are sized to its largest member, so similar members share one), at most ``batch`` a batch (None:
    no limit) and within ``budget_bytes`` (:func:`rwwarp.wave.packed.packed_bytes`). A member over the budget on
    its own has already been refused by its plan's check."""
    order = sorted(range(len(members)), key=lambda k: (members[k].plan.method, members[k].rim,
                                                       -members[k].plan.ray_grid, -members[k].plan.n_grid, k))
    # packed_bytes of the open batch with one more member, from running maxima (the same sum, in O(1) a member)
    rays_k = {k: members[k].plan.ray_grid ** 2 for k in order}
    n_k = {k: members[k].plan.n_grid for k in order}
    prop_k = {k: members[k].plan.estimate["memory_bytes"] - (rays_k[k] * 232 + n_k[k] ** 2 * 64) for k in order}
    out, cur = [], []
    for k in order:
        if cur:
            m0 = members[cur[0]]
            same = (m0.plan.method, m0.rim) == (members[k].plan.method, members[k].rim) and \
                get_method(m0.plan.method).packable
            rays, n, prop = max(top[0], rays_k[k]), max(top[1], n_k[k]), max(top[2], prop_k[k])
            fits = (len(cur) + 1) * (rays * 232 + n * n * 64) + prop <= budget_bytes
            if same and fits and (batch is None or len(cur) < batch):
                cur.append(k)
                top = (rays, n, prop)
                continue
            out.append(cur)
        cur, top = [k], (rays_k[k], n_k[k], prop_k[k])
    if cur:
        out.append(cur)
    return out
