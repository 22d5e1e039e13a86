"""Live ray-wave PSFs of a learning lens for end-to-end design (:class:`LiveProvider`), and the patch
centres every provider uses (:func:`common_centres`).

Units: mm, um for wavelengths, degrees for fields.
"""
from __future__ import annotations

import math
import time

import numpy as np
import torch

from rwwarp.wave.methods import get as get_method

from .packed import pack_groups  # noqa: F401  (its home was here)
from .ray_spot import RaySpot
from .wave_step import add_wave_step


def common_centres(module, fields_deg, wavelength_um: float, depth_mm=None, grid: int = 15) -> np.ndarray:
    """Sensor positions (mm, (n_fields, 2)) the PSF patches are centred on: the ray-model centroid at
    ``wavelength_um`` with the DOE's first-order deflection included (the tracer alone would miss it).
    One centre per field for every wavelength, so lateral colour stays in the RGB PSFs. Traced on the CPU
    (a few thousand rays: fewer launches and copies than on a GPU, and too few for torch's threads)."""
    with torch.no_grad():
        return RaySpot(module, fields_deg, [wavelength_um], grid=grid, object_distance_mm=depth_mm,
                       device="cpu").centroids()


class LiveProvider:
    """Ray-wave PSFs of a :class:`~torch_bridge.HybridLens` recomputed at every call (all its
    learning quantities get gradients). Patches are centred per field on :func:`common_centres`
    (the green reference wavelength ``wavelength_ref_um``). ``tile``: sources per chunk; chunks are
    checkpointed (no tape kept in the forward pass, recomputed in the backward pass) so the peak
    memory is one chunk's; each chunk's estimated peak is checked against ``memory_budget_bytes`` (default
    half the available memory) before it is traced.

    ``replan_every``: a focal source's plan (its :class:`rwwarp.psf.RayWave`: pilot trace, grids, kept
    DOE orders, fitted transfer, patch) is made again at most every this many calls; in between the
    source is traced and propagated on its last plan with the current values (a patch centre that moved
    to another pixel moves the plan's sensor-side grid along, :meth:`rwwarp.psf.RayWave.recentre`). A
    plan is made again sooner when more rays fell outside its wave-plane window in the last call than
    at the plan's first use by more than ``window_tol`` of the source's ray grid (``ray_grid^2``; default
    1e-5: the power those rays carried is lost from the field, a PSF error of that order, below a kept
    plan's own, see below). 1 (default): every call plans afresh. The focal operator is exact for any fitted transfer and the grids carry margins
    (``nyquist_safety``, the displacement margins of :func:`rwwarp.wave.plan.plan_focal`), so a plan a few
    small optimiser steps old samples the source as well (a 5e-5 change of a curvature: 4.7e-6 from a
    fresh plan, ``tests/torch_bridge/test_live_replan.py``); gradients are exact at the plan used.
    Kept plans are not part of a training checkpoint: a resumed run plans afresh, so with N > 1 its next
    steps differ from an uninterrupted run's by the plans' age. Counts: :attr:`plans_made`,
    :attr:`plans_reused`, and why kept plans were given up, :attr:`replans` (``"age"``: ``replan_every``
    calls (or steps) old; ``"window"``: rays left the window; ``"drift"``, rule "drift" only: the lens moved
    too far), :attr:`replans_deferred` (due plans kept one more call by the spreading); host seconds spent
    planning, :attr:`plan_seconds`, and judging kept plans, :attr:`drift_seconds`.

    ``replan_rule`` (with ``replan_every`` > 1): ``"calls"`` (default, the rule above): a plan's age counts
    calls, whether or not its source was asked for (a source asked for every ~3rd call, as a colour channel's
    random wavelength, is then nearly always past ``replan_every`` 3 when asked for again). ``"drift"``: a plan is
    kept while the lens has not moved too far from the values it was planned at, measured physically by
    :func:`torch_bridge.replan.wavefront_drift_waves` (the optical path change across the source's beam, waves;
    see :mod:`torch_bridge.replan` for why and the error it makes): made again when the drift exceeds
    ``replan_drift`` (waves), when rays left its window (as above), or when it is ``replan_every`` optimiser
    steps old (calls with other values than the last call's; a call with the same values is not a step). Due
    plans are spread: at most ``ceil(n_sources / replan_spread)`` plans are made again in one call (the
    forced ones first, then the due ones, stalest first: the larger of drift / ``replan_drift`` and age /
    ``replan_every``); a due plan left over is kept one more call (its next use plans it again, forced),
    unless its drift is past ``replan_drift_hard`` (default 2 ``replan_drift``) or rays left its window:
    forced at once. So no plan is used past ``replan_drift_hard`` waves, nor more than once past
    ``replan_drift`` or ``replan_every`` steps; what the spreading costs is the error of that one use (up to
    the error at ``replan_drift_hard``, ``perf/replan_study.py``). ``replan_spread`` 1: no spreading.

    ``pack`` (default True): the focal sources of a chunk, each on its own plan, are computed together
    (:class:`torch_bridge.packed.PackedTile`: one parameter table, one trace + splat launch set and its one
    recorded adjoint, one DOE transmission, the focal propagations as batched matrix products; per source
    the same PSF and gradients as alone, to ~1e-15). A tile is kept while its members are (kept plans), and
    built again, cheaply (no planning), when one of them changes; members whose propagations would pad
    to more than ``pack_waste`` times their own work are stacked apart (:func:`rwwarp.wave.focal_packed.focal_groups`).
    A tile's recorded peak (:func:`torch_bridge.packed.packed_recorded_bytes`: every member in the slots of
    the largest) is checked against ``record_budget_bytes`` (bytes one chunk's recorded sources may take;
    default the whole ``memory_budget_bytes``: a training step passes its share, the rest being the network's
    and the allocator's); a chunk over it is split into tiles that fit. ``slot_waste`` (None, default: no bound):
    members are first split into sets whose padding to the slots of their largest (ray grid, window) costs at most
    that many times their own work (:func:`torch_bridge.packed.slot_sets`; :meth:`~torch_bridge.HybridLens.psf_map`
    uses 1.5: on a CPU the padded work, not the launches, sets the time). The tiles are cut by
    :func:`torch_bridge.packed.pack_units`, as the map's. False: one source at a time
    (:meth:`~torch_bridge.HybridLens._psf_rw`).

    A module with ``method="two-step"`` gives every source its wave step (:mod:`rwwarp.wave.wave_step`): a source
    planned focal on its own gets the step :func:`torch_bridge.wave_step.add_wave_step` plans, and a source with a
    step is computed alone, not packed (a packed tile has no wave step)."""

    def __init__(self, module, fields_deg, size: int, pixel_mm: float, wavelength_ref_um: float = 0.55,
                 tile: int | None = None, memory_budget_bytes: int | None = None, replan_every: int = 1,
                 window_tol: float = 1e-5, pack: bool = True, pack_waste: float = 1.5,
                 record_budget_bytes: int | None = None, replan_rule: str = "calls", replan_drift: float = 0.05,
                 replan_drift_hard: float | None = None, replan_spread: int = 1, slot_waste: float | None = None):
        self.module, self.fields, self.size, self.pixel_mm = module, list(fields_deg), int(size), float(pixel_mm)
        self.wl_ref = float(wavelength_ref_um)
        self.tile = tile
        self.memory_budget_bytes = memory_budget_bytes
        if record_budget_bytes is not None and not record_budget_bytes > 0:
            raise ValueError(f"LiveProvider: record_budget_bytes must be > 0 bytes, got {record_budget_bytes!r}")
        self.record_budget_bytes = None if record_budget_bytes is None else int(record_budget_bytes)
        if int(replan_every) != replan_every or replan_every < 1:
            raise ValueError(f"LiveProvider: replan_every must be an integer >= 1, got {replan_every!r}")
        self.replan_every = int(replan_every)
        if not (np.isfinite(window_tol) and 0 <= window_tol < 1):
            raise ValueError(f"LiveProvider: window_tol must be in [0, 1), got {window_tol!r}")
        self.window_tol = float(window_tol)
        if replan_rule not in ("calls", "drift"):
            raise ValueError(f"LiveProvider: replan_rule must be 'calls' or 'drift', got {replan_rule!r}")
        self.replan_rule = replan_rule
        if not (np.isfinite(replan_drift) and replan_drift > 0):
            raise ValueError(f"LiveProvider: replan_drift must be > 0 waves, got {replan_drift!r}")
        self.replan_drift = float(replan_drift)
        hard = 2.0 * self.replan_drift if replan_drift_hard is None else replan_drift_hard
        if not (np.isfinite(hard) and hard >= self.replan_drift):
            raise ValueError(f"LiveProvider: replan_drift_hard must be >= replan_drift ({self.replan_drift} waves), "
                             f"got {replan_drift_hard!r}")
        self.replan_drift_hard = float(hard)
        if int(replan_spread) != replan_spread or replan_spread < 1:
            raise ValueError(f"LiveProvider: replan_spread must be an integer >= 1, got {replan_spread!r}")
        self.replan_spread = int(replan_spread)
        self.replans = {"age": 0, "window": 0} if replan_rule == "calls" else {"age": 0, "window": 0, "drift": 0}
        self.replans_deferred = 0
        #: optimiser steps seen (rule "drift"): calls whose values differ from the last call's
        self.steps = 0
        self._last_values = None
        self._replan_now = {}    # rule "drift": id of an entry -> reason, the kept plans made again in this call
        self.plan_seconds = 0.0
        self.drift_seconds = 0.0
        #: rule "drift": (key, drift in waves, optimiser steps old, made again, forced) of every kept plan judged in
        #: the last call
        self.judged = []
        # sources whose first plan came out focal: planned on their own from then on (a joint plan of their
        # chunk would only decide the method again)
        self._focal_keys = set()
        # (field, wavelength, depth) -> [RayWave of that source, calls since planned, rays outside its window
        # at its first use, more rays outside it since, optimiser step planned at (rule "drift"), kept one call
        # past due (rule "drift"), the source's geometry on the plan's lens (torch_bridge.replan.source_geometry)]
        self._focal_rws = {}
        self.plans_made = 0
        self.plans_reused = 0
        if not (np.isfinite(pack_waste) and pack_waste >= 1):
            raise ValueError(f"LiveProvider: pack_waste must be >= 1, got {pack_waste!r}")
        self.pack, self.pack_waste = bool(pack), float(pack_waste)
        if slot_waste is not None and not (np.isfinite(slot_waste) and slot_waste >= 1):
            raise ValueError(f"LiveProvider: slot_waste must be >= 1 or None, got {slot_waste!r}")
        self.slot_waste = None if slot_waste is None else float(slot_waste)
        # (id of each member, ...) -> (members, PackedTile) of the last call (see _units)
        self._packed = {}
        #: packed tiles built (a tile is built again only when its members change)
        self.packs_made = 0
        self.unit_record_bytes = []

    def held_bytes(self) -> int:
        """Bytes (on the module's device) the provider keeps between calls: the operators its packed tiles of the
        last call keep (distance-free factors shared across distances, and those of the last distance; the
        members' own focal operators are released at each call) and the parameter tables of the kept plans' and
        tiles' tracers (:func:`rwwarp.wave.plan_cache.held_bytes` counts the same parts of a plan cache). What a call
        records and frees (rays, fields, gradients) is not held."""
        seen, total = set(), 0

        def ops_bytes(ops):
            nonlocal total
            for op in ops or ():
                if id(op) not in seen:
                    seen.add(id(op))
                    total += int(op.nbytes)
        for _, t in self._packed.values():
            for ops in t._base.values():
                ops_bytes(ops)
            if t._ops is not None:
                ops_bytes(t._ops[1])
        rws = [e[0] for e in self._focal_rws.values() if e[0] is not None] + \
              [t.raywave for _, t in self._packed.values()]
        for r in rws:
            op = getattr(r, "_focal_op", None)
            if op is not None:
                ops_bytes([op])
            tr = r.tracer_made() if hasattr(r, "tracer_made") else None
            if tr is not None and id(tr) not in seen:
                seen.add(id(tr))
                total += int(tr.params_np.nbytes + tr.index_np.nbytes)
        return total

    def _usable(self, e) -> bool:
        """A kept focal plan ``e`` (entry of :attr:`_focal_rws`) may serve again (else counted in
        :attr:`replans` by the reason)."""
        if self.replan_rule == "drift":
            why = self._replan_now.get(id(e))
            if why is not None:
                self.replans[why] += 1
                return False
            return True
        if e[3]:
            self.replans["window"] += 1
            return False
        if e[1] >= self.replan_every:
            self.replans["age"] += 1
            return False
        return True

    def _judge(self, keys, values) -> None:
        """Rule "drift": count an optimiser step when ``values`` (the module's, this call) differ from the last
        call's, then decide which kept plans of this call's sources ``keys`` are made again
        (:attr:`_replan_now`: id of the entry -> reason), spreading the due ones
        (:func:`torch_bridge.replan.choose_replans`; see the class docstring)."""
        from .replan import choose_replans, source_geometry, wavefront_drift_waves
        t0 = time.perf_counter()
        # one read of the values to the host (after common_centres' read: the device's queue is empty)
        v = torch.cat([t.detach().reshape(-1).to(torch.float64) for t in values.values()]).cpu().numpy()
        if self._last_values is not None and not np.array_equal(v, self._last_values):
            self.steps += 1
        self._last_values = v
        status, entries = {}, {}
        lens_now = None
        self.judged = []
        for key in dict.fromkeys(keys):
            e = self._focal_rws.get(key)
            if e is None:
                continue
            age = self.steps - e[4]
            d = math.inf
            if e[3]:
                status[id(e)] = (True, True, math.inf, "window")
            else:
                r = e[0]
                if age == 0:
                    d = 0.0
                else:
                    if lens_now is None:
                        lens_now = self.module._once("lens", self.module.to_lens)
                    if e[6] is None:
                        e[6] = source_geometry(r.lens, key[1], key[0])
                    d = wavefront_drift_waves(r.lens, lens_now, key[1], key[0], extents=e[6])
                # due past the drift tolerance or at the age bound; spread like the others, forced once kept past
                # due before or past the hard drift bound
                due = d > self.replan_drift or age >= self.replan_every
                status[id(e)] = (due and (e[5] or d > self.replan_drift_hard), due,
                                 max(d / self.replan_drift, age / self.replan_every),
                                 "drift" if d > self.replan_drift else "age")
            entries[id(e)] = (key, e, age, d)
        quota = -(-len(keys) // self.replan_spread)
        now = choose_replans({k: st[:3] for k, st in status.items()}, quota)
        self._replan_now = {k: status[k][3] for k in now}
        for k, (forced, due, stale, _) in status.items():
            key, e, age, d = entries[k]
            if due and k not in now:
                e[5] = True   # kept one more call past due: its next use plans it again
                self.replans_deferred += 1
            # (key, drift in waves (inf: not judged, rays left the window), optimiser steps old, made again in this
            # call, forced)
            self.judged.append((key, d, age, k in now, forced))
        self.drift_seconds += time.perf_counter() - t0

    def _plan_sources(self, js, src_f, src_w, src_c, depth_mm, check=False) -> list:
        """Plan sources ``js`` (indices into ``src_f`` (deg), ``src_w`` (um), ``src_c`` (mm, (S, 2) patch centres))
        each on its own (focal), all from one pilot trace (:meth:`~torch_bridge.HybridLens.raywaves_alone`: a
        source's pilot rows, and so its plan, are what a trace of it alone gives). With ``method="two-step"`` each
        gets its wave step (:func:`torch_bridge.wave_step.add_wave_step`); ``check`` (one bool, or one per source):
        its recorded peak is checked against the budget (a source planned again alone, without its chunk's joint
        check). Returns the plans in ``js``'s order."""
        checks = [bool(check)] * len(js) if np.ndim(check) == 0 else [bool(c) for c in check]
        if len(checks) != len(js):
            raise ValueError(f"LiveProvider._plan_sources: {len(checks)} checks for {len(js)} sources")
        m = self.module
        t0 = time.perf_counter()
        rs = m.raywaves_alone([src_f[j] for j in js], [src_w[j] for j in js], self.size, centers_mm=src_c[js],
                              object_distance_mm=depth_mm, pixel_mm=self.pixel_mm, method="focal")
        for r, check in zip(rs, checks):
            if m.method == "two-step":
                # each source's focal plan with the wave step "two-step" plans (a joint plan's RayWave has it
                # already): torch_bridge.wave_step.add_wave_step
                add_wave_step(r, m.memory_budget(self.memory_budget_bytes))
            if check:
                m.check_budget(r, m.memory_budget(self.memory_budget_bytes), sources=1)
            self.plans_made += 1
        self.plan_seconds += time.perf_counter() - t0
        return rs

    def _entry(self, r) -> list:
        """A new entry of :attr:`_focal_rws` for the plan ``r`` just made (see ``__init__``)."""
        return [r, 0, None, False, self.steps, False, None]

    def psfs(self, wavelengths_um, depth_mm=None, nodes: slice | None = None) -> torch.Tensor:
        """(n_nodes, len(wavelengths_um), size, size) for one wavelength per channel (um) at the object
        distance ``depth_mm`` (mm, None: the lens's own). ``nodes``: a slice of the nodes to compute
        (a rank's share in a distributed step; default all). The patch centres are those of all
        nodes, and a focal source is planned on its own, so a share's PSFs are the rows of the
        whole map (band-limited ASM sources are planned per chunk of ``tile`` sources within the
        share)."""
        with self.module.same_values():   # no optimiser step inside: the lens export is made once
            return self._psfs(wavelengths_um, depth_mm, nodes)

    def _psfs(self, wavelengths_um, depth_mm, nodes):
        from torch_bridge.tiles import run_tiles
        m = self.module
        cen = common_centres(m, self.fields, self.wl_ref, depth_mm)
        sel = range(len(self.fields))[nodes if nodes is not None else slice(None)]
        fields = [self.fields[i] for i in sel]
        cen = [cen[i] for i in sel]
        wls = [float(w) for w in wavelengths_um]
        if not fields:
            return torch.zeros((0, len(wls), self.size, self.size), dtype=torch.float64,
                               device=next(iter(m.values().values())).device)
        src_f = [f for f in fields for _ in wls]
        src_w = [w for _ in fields for w in wls]
        src_c = np.array([c for c in cen for _ in wls])
        n = len(src_f)
        tile = n if not self.tile else max(1, min(int(self.tile), n))
        values = m.values()
        names = list(values)
        if m._multi_order:   # each source's kept orders (HybridLens.order_set at its node's centre); no packing
            sets = [m.order_set(f, w, self.size, object_distance_mm=depth_mm, pixel_mm=self.pixel_mm,
                                center_mm=tuple(float(v) for v in c)) for f, w, c in zip(src_f, src_w, src_c)]
            out = m.order_psfs(sets, tile, self.memory_budget_bytes, checkpoint=tile < n)
            return out.reshape(len(fields), len(wls), self.size, self.size)
        tables = {}   # host copies of the parameter table for these values (HybridLens.host_table)
        dropped = []  # (key, RayWave, its rays outside the window): read once all sources are queued
        for e in self._focal_rws.values():
            e[1] += 1
            e[0].release_operators()   # the last call's operators (a learning distance rebuilds them anyway)
        if self.replan_rule == "drift" and self.replan_every > 1:
            self._judge([(tuple(np.ravel(f)), w, depth_mm) for f, w in zip(src_f, src_w)], values)
        for t in self._packed.values():
            t[1].release_operators()
        packs = {}    # this call's packed tiles, keyed by their members' identities

        def run(chunk, *ts, record=True):
            units, perm = chunk[0], chunk[1]
            vals = dict(zip(names, ts))
            out = torch.cat([m._psf_packed(u, vals, record=record, tables=tables) if kind == "packed" else
                             m._psf_rw(u, vals, record=record, tables=tables) for kind, u, _ in units], 0)
            return out if perm is None else out[perm.to(out.device, non_blocking=True)]

        def after(chunk, out):
            units, _, keys, sl = chunk
            for kind, u, row in units:
                if kind == "packed":
                    dropped.extend((keys[j - sl.start], r, u.dropped(), i)
                                   for i, (j, r) in enumerate(zip(row, u.members)))
                else:
                    dropped.append((keys[row[0] - sl.start], u, u.dropped, None))
        # the chunks, each a checkpoint when there are several but the last, whose tape is used first in the
        # backward pass and freed there (torch_bridge.tiles.RecordedOnce; a design step gives the network the budget's
        # other share)
        chunks, order = self._chunks(n, tile, src_f, src_w, src_c, depth_mm, packs)
        out = run_tiles(chunks, run, [values[q] for q in names], checkpoint=len(chunks) > 1, after=after,
                        keep_last=True)
        if order is not None:   # the chunks' rows back to the sources' order
            out = out[order.to(out.device, non_blocking=True)]
        self._packed = packs   # the tiles of this call (a tile of the last call not used again is freed)
        # read after every source was queued (a read waits for the device: once, not once per source)
        host = {}
        for key, r, arr, i in dropped:
            e = self._focal_rws.get(key)
            if e is not None and e[0] is r:
                # more rays outside the window than at the plan's first use: plan that source again
                a = host.get(id(arr))
                if a is None:
                    a = host[id(arr)] = (arr, arr.numpy())
                d = int(np.sum(a[1] if i is None else a[1][i]))
                if e[2] is None:
                    e[2] = d
                elif d - e[2] > self.window_tol * r.nsrc * r.plan.ray_grid ** 2:
                    e[3] = True
        return out.reshape(len(fields), len(wls), self.size, self.size)

    def _chunks(self, n, tile, src_f, src_w, src_c, depth_mm, packs):
        """The ``n`` sources of a call in chunks of ``tile``, every chunk planned first (:meth:`_plan_call`: kept plans
        reused, the new ones made together), then each cut into its work (:meth:`_units`; ``packs``: this call's packed
        tiles, filled). Returns ``(chunks, order)``: ``chunks`` the checkpoint units, each ``(units, None, keys, sl)``
        (``keys`` the (field, wavelength, depth) of its planning chunk's sources, ``sl`` their slice), ``order`` the
        permutation (a tensor) that puts the concatenated rows of the chunks back in source order (None: already in
        order).

        With a tile (:attr:`tile` set: a design step's budget) a planning chunk's work is cut again into checkpoint
        units whose estimated recorded bytes (:func:`torch_bridge.packed.packed_recorded_bytes` of a packed tile, the
        :meth:`~torch_bridge.HybridLens.check_budget` figure of a source alone) add up to at most the record budget
        (``record_budget_bytes``, else the memory budget): the tile's source count was set from one source's estimate
        when the provider was made, and the plans of a learning lens grow (the Cooke hybrid's wave-plane grids from
        ~500 to ~1,100 samples a side in 10 optimiser steps on the CPU), so a chunk of ``tile`` sources came to hold
        several packed tiles, each within the budget, all recorded at once in its checkpoint's recomputation. A unit
        over the budget on its own is a checkpoint unit of its own. The estimates of the last call's checkpoint units
        are :attr:`unit_record_bytes`."""
        from .packed import packed_recorded_bytes
        m = self.module
        budget = self.record_budget_bytes or m.memory_budget(self.memory_budget_bytes)
        chunks, rows, est_all = [], [], []
        for sl, keys, rws, fresh in self._plan_call(n, tile, src_f, src_w, src_c, depth_mm):
            # the chunk's RayWaves in source order; a band-limited batch of new sources gives their rows together;
            # single-source focal plans are computed together in packed tiles (torch_bridge.packed)
            units = self._units(sorted(rws), rws, fresh, packs)
            if self.tile is None:
                groups = [units]
                ests = [None]
            else:
                groups, ests, cur, cur_est = [], [], [], 0
                for u in units:
                    kind, obj, _ = u
                    e = packed_recorded_bytes(m, obj.members) if kind == "packed" else \
                        m.recorded_bytes(obj, sources=obj.nsrc)
                    if cur and cur_est + e > budget:
                        groups.append(cur)
                        ests.append(cur_est)
                        cur, cur_est = [], 0
                    cur.append(u)
                    cur_est += e
                groups.append(cur)
                ests.append(cur_est)
            for g, e in zip(groups, ests):
                chunks.append((g, None, keys, sl))
                rows.extend(j for _, _, row in g for j in row)
                est_all.append(e)
        #: estimated recorded bytes (forward + backward) of each checkpoint unit of the last call (None without a tile)
        self.unit_record_bytes = est_all
        order = None if rows == sorted(rows) else torch.as_tensor(np.argsort(rows))
        return chunks, order

    def _plan_call(self, n, tile, src_f, src_w, src_c, depth_mm) -> list:
        """Every chunk's plans of a call, before its tile loop: ``[(sl, keys, rws, fresh)]`` a chunk of ``tile``
        sources (``sl`` their slice, ``keys`` their (field, wavelength, depth), ``rws`` source index -> RayWave,
        ``fresh`` the sources seen for the first time). Chunk by chunk, in source order, a source keeps its plan
        (:meth:`_usable`; moved along with its patch), is planned again on its own when it was planned focal
        before, or is new: the chunk's new sources get one joint plan, which decides the method and checks the
        budget (a band-limited batch serves them together; focal ones are planned on their own). All the sources
        planned on their own in this call are planned at once, from one pilot trace (:meth:`_plan_sources`): each
        plan is what planning that source alone gives (its pilot rows do not depend on the other sources), so
        the PSFs are those of planning chunk by chunk. Which plans are kept or made, and the counts, are as when
        each chunk was planned as the loop reached it (a source repeated in a later chunk takes the plan made
        for it earlier in the call). Should planning fail, the kept plans are left as they were."""
        rws_before, keys_before = dict(self._focal_rws), set(self._focal_keys)
        try:
            return self._plan_chunks(n, tile, src_f, src_w, src_c, depth_mm)
        except BaseException:
            # no entry left waiting for a plan that was not made
            self._focal_rws, self._focal_keys = rws_before, keys_before
            raise

    def _plan_chunks(self, n, tile, src_f, src_w, src_c, depth_mm) -> list:
        """:meth:`_plan_call`'s work (its arguments and result)."""
        m = self.module
        chunks, todo, made, kept = [], [], [], []
        for k in range(0, n, tile):
            sl = slice(k, min(k + tile, n))
            keys = [(tuple(np.ravel(src_f[j])), src_w[j], depth_mm) for j in range(sl.start, sl.stop)]
            rws, fresh, again = {}, [], []
            for j, key in zip(range(sl.start, sl.stop), keys):
                e = self._focal_rws.get(key)
                if e is not None and self._usable(e):
                    kept.append((rws, j, e))   # moved along with its patch once every plan is made (below)
                    self.plans_reused += 1
                elif key in self._focal_keys:
                    # planned focal before: planned again on its own (no joint plan of the chunk first)
                    again.append(j)
                else:
                    fresh.append(j)
            entries = []   # (key, entry) of the plans made in this chunk (rules with kept plans)
            for j in again:
                # planned below with the others (its recorded peak checked alone)
                e = self._entry(None) if self.replan_every > 1 else None
                todo.append((j, True))
                made.append((rws, j, e))
                entries.append((keys[j - sl.start], e))
            if fresh:
                # sources not seen before: one joint plan decides the method and checks the budget
                t0 = time.perf_counter()
                rw = m.raywave([src_f[j] for j in fresh], [src_w[j] for j in fresh], self.size,
                               object_distance_mm=depth_mm, pixel_mm=self.pixel_mm, center_mm=src_c[fresh])
                self.plan_seconds += time.perf_counter() - t0
                # a chunk's recorded trace must fit the budget (HybridLens.check_budget names the knobs)
                per_source = get_method(rw.plan.method).per_source_plans
                m.check_budget(rw, m.memory_budget(self.memory_budget_bytes), sources=1 if per_source else rw.nsrc)
                if per_source:
                    # focal grids follow each source's patch and DOE orders: one plan per source (a single new
                    # source's is the joint plan; the others planned below, without a check of their own)
                    for j in fresh:
                        key = keys[j - sl.start]
                        self._focal_keys.add(key)
                        e = self._entry(rw if len(fresh) == 1 else None) if self.replan_every > 1 else None
                        if len(fresh) == 1:
                            rws[j] = rw
                        else:
                            todo.append((j, False))
                            made.append((rws, j, e))
                        entries.append((key, e))
                    if len(fresh) == 1:
                        self.plans_made += 1
                else:
                    rws[fresh[0]] = rw   # one band-limited batch for the new sources
                    self.plans_made += 1
            # the chunk's new entries in place before the next chunk looks its sources up (plans filled below)
            for key, e in entries:
                if e is not None:
                    self._focal_rws[key] = e
            chunks.append((sl, keys, rws, fresh))
        if todo:
            plans = self._plan_sources([j for j, _ in todo], src_f, src_w, src_c, depth_mm, check=[c for _, c in todo])
            for (rws, j, e), r in zip(made, plans):
                rws[j] = r
                if e is not None:
                    e[0] = r
        for rws, j, e in kept:
            if not np.array_equal(e[0].snapped_centres(src_c[j]), e[0].centers):
                # the patch moved to another pixel: its grids move along (a copy: a graph of an earlier call that
                # still holds the plan keeps its own patch)
                e[0] = _recentred(e[0], src_c[j])
            rws[j] = e[0]
        return chunks

    def _units(self, order, rws, fresh, packs) -> list:
        """The work of one chunk: ``[(kind, object, rows)]`` with ``kind`` "packed" (a
        :class:`~torch_bridge.packed.PackedTile` of single-source focal plans, rows in its members' order) or
        "rw" (one RayWave: a band-limited batch of the new sources ``fresh``, or a source not packed). The packed
        tiles are cut by :func:`torch_bridge.packed.pack_units` (as :meth:`~torch_bridge.HybridLens.psf_map`'s);
        they come from the last call's when their members are the same objects (``packs``: this call's, filled)."""
        from .packed import PackedTile, pack_units, packable
        m = self.module
        units, focal = [], []
        for j in order:
            r = rws[j]
            if r.nsrc > 1:
                units.append(("rw", r, list(fresh)))
            elif self.pack and packable(r):
                focal.append(j)
            else:
                units.append(("rw", r, [j]))

        def tile_for(members):
            key = tuple(id(r) for r in members)
            hit = self._packed.get(key) or packs.get(key)
            if hit is None or any(a is not b for a, b in zip(hit[0], members)):
                hit = (members, PackedTile(members, self.pack_waste))
                self.packs_made += 1
            packs[key] = hit
            return hit[1]
        budget = self.record_budget_bytes or m.memory_budget(self.memory_budget_bytes)
        return units + pack_units(m, focal, rws, budget, waste=self.pack_waste, tile_for=tile_for,
                                  slot_waste=self.slot_waste)


def _recentred(rw, center_mm):
    """A shallow copy of RayWave ``rw`` with its sensor patches moved to ``center_mm`` (mm)."""
    import copy
    from .functions import bridge_state
    out = copy.copy(rw)
    out.recentre(center_mm)
    st = bridge_state(out)
    st.update(bridge_state(rw))
    st.pop("window_center", None)   # follows the centres
    return out
