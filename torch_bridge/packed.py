"""Differentiable PSFs of a tile of focal sources computed together, each on its own plan.

A :class:`PackedTile` holds single-source focal :class:`rwwarp.psf.RayWave` s (each its own plan: pilot,
windows, DOE orders, sensor-side grids) and one :class:`rwwarp.wave.packed.PackedRayWave` over them (built with
gradient buffers). :func:`packed_psfs` then runs the ray-wave model for the whole tile with one parameter
table, one trace + splat launch set recorded on one ``wp.Tape`` (:class:`~torch_bridge.functions.TraceSplat`,
whose backward replays it for all members at once), one batched DOE transmission
(:func:`packed_doe_factor`) and the focal propagation of all members as a few batched matrix products
(:class:`PackedFocalPropagate`, :class:`rwwarp.wave.focal_packed.PackedFocalPropagator`). Every member's PSF and
gradients are those of :meth:`torch_bridge.HybridLens._psf_rw` on the member alone up to the order of
floating-point sums (tests/torch_bridge/test_packed_live.py measures it).

Devices: the Warp device is the members' (their tracer's), the torch tensors are the module's, the
propagation's arrays numpy on the CPU and CuPy views of the same device memory on CUDA (DLPack), run on
torch's current stream with torch's allocator (``torch_bridge.functions._streams``), as the single-source
path. Units: mm, um for wavelengths, rad for phases.
"""
from __future__ import annotations

import contextlib

import numpy as np
import torch
from rwwarp.trace import COLUMNS as COL

from .functions import _on_device, _streams, bridge_state, paper_amplitude, upload
from .functions import power_sums, trace_splat

__all__ = ["PackedFocalPropagate", "PackedTile", "pack_groups", "pack_units", "packable", "packed_doe_factor",
           "packed_psfs", "packed_recorded_bytes", "slot_sets"]


class PackedTile:
    """Single-source focal RayWaves ``members`` (of one lens, device and precision, made with
    ``requires_grad=True``; :meth:`torch_bridge.HybridLens.raywave`) computed together: :attr:`raywave`, their
    :class:`rwwarp.wave.packed.PackedRayWave` (one trace and splat for all; the members keep their own plans and
    patches), and :attr:`groups`, the members' indices stacked into one focal operator each
    (:func:`rwwarp.wave.focal_packed.focal_groups`, ``waste``: the padding allowed). Operators are built on first
    use per distance (:meth:`operators`) and dropped by :meth:`release_operators`."""

    def __init__(self, members, waste: float = 1.5):
        from rwwarp.wave.focal_packed import focal_groups
        from rwwarp.wave.packed import PackedRayWave
        self.members = list(members)
        if len({float(m.z_plane) for m in self.members}) != 1:
            raise ValueError("PackedTile: members must share the wave plane's z (plan them from one lens state)")
        self.raywave = PackedRayWave(self.members, requires_grad=True)
        bridge_state(self.raywave)["base_table"] = self.raywave.tracer.params_np.copy()
        self.groups = focal_groups(self.members, waste)
        self._ops = None
        self._base = {}   # precision -> the first operators built (their distance-free factors are shared)
        self._order_tables = None   # the members' DOE order tables (packed_doe_factor), built on first use
        self._index = {}            # (rows, device) -> int64 tensor of member positions (index)

    def operators(self, distance_mm: float, precision: str = "double") -> list:
        """One :class:`rwwarp.wave.focal_packed.PackedFocalPropagator` per group at ``distance_mm`` (mm), built once
        per distance and precision."""
        from rwwarp.wave.focal_packed import PackedFocalPropagator
        key = (float(distance_mm), precision)
        if self._ops is None or self._ops[0] != key:
            base = self._base.get(precision)
            if base is None:
                ops = [PackedFocalPropagator.from_members([self.members[k] for k in g], key[0], precision)
                       for g in self.groups]
                self._base[precision] = ops
            else:   # a learning distance: only the factors that depend on it are built again
                ops = [op.at_distance(key[0]) for op in base]
            self._ops = (key, ops)
        return self._ops[1]

    def index(self, rows, device) -> torch.Tensor:
        """``rows`` (a list of ints: member positions) as an int64 tensor on ``device``, uploaded once per tile and
        device (the groups' and their Gauss-node subsets' rows are the tile's own: every call, and the recompute
        of a checkpointed one, indexes with the same; on a GPU each upload is a host-to-device copy)."""
        key = (tuple(int(r) for r in rows), str(device))
        hit = self._index.get(key)
        if hit is None:
            hit = self._index[key] = upload(np.asarray(key[0], dtype=np.int64), torch.long, device)
        return hit

    def release_operators(self):
        """Drop the operators built at the last distance (the next use builds the distance's factors again;
        the distance-free ones are kept while the tile is)."""
        self._ops = None

    def dropped(self):
        """Rays per member that fell outside its window in the last trace (Warp int32 array (S,))."""
        return self.raywave.dropped


def packable(rw) -> bool:
    """RayWave ``rw`` may be a member of a :class:`PackedTile`: one source, a method whose torch path is the focal
    one and that :class:`rwwarp.wave.packed.PackedRayWave` batches, and no wave step (a packed tile has none: a
    source with one runs alone, :meth:`torch_bridge.HybridLens._psf_rw`)."""
    from rwwarp.wave.methods import get as get_method
    method = get_method(rw.plan.method)
    return (rw.nsrc == 1 and method.torch_path == "focal" and method.packable
            and not np.any(getattr(rw, "wave_step", 0.0)))


def pack_units(module, js, rws, budget_bytes: int, *, waste: float = 1.5, spatial_tile=None, tile_for=None,
               slot_waste: float | None = None) -> list:
    """The one place that cuts sources into packed tiles (:meth:`torch_bridge.HybridLens.psf_map` and
    :class:`torch_bridge.live.LiveProvider`): the sources ``js`` (indices into ``rws``, each a :func:`packable`
    single-source focal RayWave of ``module``, in order) as ``[(kind, object, rows)]``: ``("packed", PackedTile,
    rows)`` for the members of one tile, ``("rw", RayWave, [j])`` for a source that fits with no other. Members
    of one tile share the wave plane's z (one lens state) and, with thin lenses (whose table columns follow the
    tracer's first wavelength), the wavelength; each set is cut by :func:`pack_groups` so that a tile's recorded
    peak (:func:`packed_recorded_bytes` at ``spatial_tile``) stays within ``budget_bytes`` (bytes). ``waste``: the
    padding allowed when stacking members into one focal operator (:class:`PackedTile`). ``tile_for(members)``:
    the tile of those members (the caller's cache of tiles), default a new :class:`PackedTile`. ``slot_waste``
    (None: no bound): the members of a tile are traced and splatted in the slots of the largest (its ray grid, its
    window), so each set is first split by :func:`slot_sets` into sets whose padded work is at most ``slot_waste``
    times their own (where the work, not the launches, sets the time: a CPU)."""
    sets = {}
    for j in js:
        r = rws[j]
        if not packable(r):
            raise ValueError(f"pack_units: source {j} is not packable (method {r.plan.method!r}, {r.nsrc} source(s), "
                             "wave step or not): run it on its own")
        sets.setdefault((float(r.z_plane), r.wls[0] if any(module._thin_surfaces) else None), []).append(j)
    groups = list(sets.values())
    if slot_waste is not None:
        groups = [g for s in groups for g in slot_sets(s, [rws[j] for j in s], slot_waste)]
    fits = lambda g: packed_recorded_bytes(module, [rws[i] for i in g], spatial_tile) <= budget_bytes
    units = []
    for group in groups:
        for cur in pack_groups(group, fits):
            if len(cur) == 1:
                units.append(("rw", rws[cur[0]], cur))
                continue
            members = [rws[i] for i in cur]
            units.append(("packed", PackedTile(members, waste) if tile_for is None else tile_for(members), cur))
    return units


def slot_sets(js, members, waste: float) -> list:
    """``js`` (sources, in order; ``members`` their single-source RayWaves) split into sets whose packed trace and
    splat, every member in the slots of the set's largest ray grid and window
    (:func:`rwwarp.wave.packed.slot_bytes`), is at most
    ``waste`` (>= 1) times the members' own: the members taken largest first, each joining the first set it keeps
    within the bound (else a new set). Each set in source order; the sets in the order of their first source."""
    from rwwarp.wave.packed import slot_bytes
    if not (np.isfinite(waste) and waste >= 1):
        raise ValueError(f"slot_sets: waste must be >= 1, got {waste!r}")
    size = {j: (int(m.plan.ray_grid), int(m.plan.n_grid)) for j, m in zip(js, members)}
    sets = []   # [members, largest ray grid, largest window, own work]
    for j in sorted(js, key=lambda j: (-size[j][0], -size[j][1])):
        rg, ng = size[j]
        for s in sets:
            r2, n2 = max(s[1], rg), max(s[2], ng)
            if (len(s[0]) + 1) * slot_bytes(r2, n2) <= waste * (s[3] + slot_bytes(rg, ng)):
                s[0].append(j)
                s[1], s[2], s[3] = r2, n2, s[3] + slot_bytes(rg, ng)
                break
        else:
            sets.append([[j], rg, ng, slot_bytes(rg, ng)])
    pos = {j: k for k, j in enumerate(js)}
    out = [sorted(s[0], key=pos.get) for s in sets]
    return sorted(out, key=lambda g: pos[g[0]])


def pack_groups(js, fits) -> list:
    """``js`` (sources, in order) cut into consecutive groups that each ``fits(group)`` (a packed tile's recorded
    bytes within the budget), as few as the greedy cut gives and as even as the budget allows: the greedy cut
    (each group as long as it fits) can leave a short last group, often a single source, which then runs on its
    own path (its own trace and splat launches, a cuFFT plan of its own size); the same number of groups of
    near-equal length is taken where each of them fits. A group of one is a source that fits with no other."""
    greedy, cur = [], []
    for j in js:
        if cur and not fits(cur + [j]):
            greedy.append(cur)
            cur = []
        cur.append(j)
    if cur:
        greedy.append(cur)
    n, t = len(js), len(greedy)
    if t < 2 or max(map(len, greedy)) - min(map(len, greedy)) <= 1:
        return greedy
    sizes = [n // t + (i < n % t) for i in range(t)]
    even = [list(js[sum(sizes[:i]):sum(sizes[:i + 1])]) for i in range(t)]
    return even if all(len(g) == 1 or fits(g) for g in even) else greedy


def packed_recorded_bytes(module, members, spatial_tile=None) -> int:
    """Estimated peak bytes (forward + backward) of ``members`` recorded as one :class:`PackedTile`: every member
    in the slots of the largest (its rays with gradients at the largest member's ray grid, its window at the
    largest window: :func:`torch_bridge.budget.bytes_per_source` of the largest sizes) plus each member's own
    propagation and output side."""
    from dataclasses import replace
    rg = max(m.plan.ray_grid for m in members)
    ng = max(m.plan.n_grid for m in members)
    total = 0
    for m in members:
        big = _Sized(m, replace(m.plan, ray_grid=rg, n_grid=ng))
        total += module.bytes_per_source(big) + module.output_bytes_per_source(m, spatial_tile)
    return int(total)


class _Sized:
    """A RayWave's attributes with another plan (for the byte estimates)."""

    def __init__(self, rw, plan):
        self._rw, self.plan = rw, plan

    def __getattr__(self, name):
        return getattr(self._rw, name)


def packed_doe_factor(tile, phi0):
    """The DOE's transmission on each member's wave-plane window, (S, n, n) complex128 (``n`` the tile's slot
    side), or None without a DOE: per member what :func:`torch_bridge.functions.focal_doe_factor` gives it
    alone. ``phi0``: the unwrapped DOE phase on the tile's windows (rad, (S, n, n)), differentiable, on any
    device. rwwarp's one batched evaluation, :func:`rwwarp.wave.focal.batch_order_series`, in torch: the members
    with several integer orders in one Horner recursion over the union of their orders, the others (one order
    ``c exp(1j m phi0)``, or a blank DOE as the one order ``(alpha, 1)``, ``alpha`` the wavelength remap of
    :func:`torch_bridge.functions.doe_scale`) in one product, each member's chief-ray wrap zone exact. Its host
    tables are built once per tile (:func:`rwwarp.wave.focal_packed.member_order_tables`) and uploaded once per
    device (:func:`torch_bridge.functions._on_device`). No member is evaluated alone: one keeping several orders
    not all integers (none the planner makes) is a sum of terms in the same call."""
    if phi0 is None:
        return None
    from rwwarp.wave.focal import batch_order_series
    from rwwarp.wave.focal_packed import member_order_tables
    tables = tile._order_tables
    if tables is None:
        from .functions import doe_scale
        # a blank DOE (planned flat, no orders): exp(1j alpha phi0), one order m = alpha, c = 1, no zone
        tables = tile._order_tables = member_order_tables(tile.members,
                                                          blank=lambda m: [(float(doe_scale(m)[0]), 1.0)])
    rw, dev = tile.raywave, phi0.device

    def put(name, host):
        if host.dtype.kind == "i":          # row indices: a small non-blocking upload (functions.upload)
            return upload(host, torch.long, dev)
        return _on_device(rw, f"packed_orders_{name}_{host.shape}", host, dev)
    return batch_order_series(phi0, tables, torch, put)


class PackedFocalPropagate:
    """Wave-plane fields of a :class:`PackedTile` -> power per sensor pixel of every member, by the members'
    focal propagations stacked per group (:class:`rwwarp.wave.focal_packed.PackedFocalPropagator`), each group
    through the generic operator Functions (:class:`~torch_bridge.operator_function.OperatorApply`, then
    :class:`~torch_bridge.operator_function.NodePixels` per Gauss-node count).

    ``PackedFocalPropagate.apply(field, distance, tile, distance_host)``: ``field`` complex128 (S, n, n) on the
    tile's windows (each member's samples in the top-left ``n_k x n_k`` of its slot, zero elsewhere; DOE
    orders applied), ``distance`` the wave-plane-to-sensor distance, float64 (S,) (mm; one lens: all equal),
    ``distance_host`` its value as a float (mm). Returns float64 (S, size, size), the pixel values the tile's
    ``pixel_values`` names integrated over each pixel (each member with its own Gauss nodes): the z-flux
    ``Re(conj(U) U_w)`` ("flux") or ``|U|^2`` ("intensity"), as :class:`torch_bridge.functions.FocalPropagate`.
    Backward: the operators' adjoints for ``field`` and their exact distance derivatives for ``distance``."""

    @staticmethod
    def apply(field, distance, tile, distance_host):
        from .operator_function import NodePixels, OperatorApply
        prw = tile.raywave
        flux = prw.pixel_values == "flux"
        if (field.device.type == "cuda") != str(prw.tracer.device).startswith("cuda"):
            raise ValueError(f"packed focal propagation: the field is on {field.device} but its RayWaves were "
                             f"planned on {prw.tracer.device}; plan on the field's device (HybridLens.to(device))")
        dev = field.device
        with _streams(prw):
            ops = tile.operators(float(distance_host), "double")
        parts, seq = [], []
        for g, op in zip(tile.groups, ops):
            gi = tile.index(g, dev)
            fg = field[gi, :op.n, :op.n]
            dg = None if distance is None else distance[tile.index(g, distance.device)]
            u = OperatorApply.apply(fg, dg, op, flux, prw, "focal")
            us = u if flux else (u, None)
            for sub, gn in _by_nodes(tile, g):
                m = prw.size * gn
                si = tile.index(sub, dev)
                parts.append(NodePixels.apply(us[0][si, :m, :m], None if us[1] is None else us[1][si, :m, :m],
                                              gn, prw.pixel, prw.size, prw))
                seq += [g[i] for i in sub]
        out = parts[0] if len(parts) == 1 else torch.cat(parts, 0)
        if seq != list(range(len(seq))):
            out = out[tile.index(list(np.argsort(seq)), dev)]
        return out


def _by_nodes(tile, group):
    """The members of ``group`` (positions in it) by their Gauss node count: ``[(positions, nodes), ...]``."""
    by = {}
    for i, k in enumerate(group):
        by.setdefault(int(tile.members[k].gauss_nodes), []).append(i)
    return [(v, gn) for gn, v in by.items()]


def packed_psfs(module, tile, values, record: bool = True, tables: dict | None = None):
    """PSFs (S, size, size) of every member of ``tile`` (a :class:`PackedTile`) for the values ``values`` of
    ``module`` (a :class:`~torch_bridge.HybridLens`), fractions of each member's entering power per pixel:
    per member :meth:`~torch_bridge.HybridLens._psf_rw` of it alone. ``record=False``: a plain forward (no
    tape, no graph); ``tables``: the caller's cache of host tables (:meth:`~torch_bridge.HybridLens.host_table`)."""
    prw = tile.raywave
    ctx = contextlib.nullcontext() if record else torch.no_grad()
    with ctx:
        table = module.param_table(prw, values)
        host = module.host_table(prw, table, tables)
        dist = (table[-1, COL.z] - table[prw.plane, COL.z]).expand(prw.nsrc)
        u = trace_splat(table, prw, host)
        if prw.amplitude != "energy":
            u = paper_amplitude(u, prw)
        fac = packed_doe_factor(tile, module.doe_phase(prw, values, wrap=False))
        if fac is not None:
            u = u * fac
        power = PackedFocalPropagate.apply(u, dist, tile, float(host[-1, COL.z] - host[prw.plane, COL.z]))
        return power / power_sums(prw, power.device)[0][:, None, None]
