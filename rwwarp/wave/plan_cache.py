"""A bounded cache of planned PSF computations for repeated calls (:class:`PlanCache`, issue 25).

A wave-model call of :func:`rwwarp.psf` / :func:`rwwarp.psf_map` spends most of its host time before the
first launch of the PSF itself: a pilot trace, the plan of every source, the tracers and the batches, and on
the focal path the propagation operators (their factors are the largest arrays of a small PSF). A call with
``cache=PlanCache(...)`` keeps all of that for the next call with the same lens values and the same arguments,
and runs only the PSF's own launches then (trace, splat, propagation).

What makes a hit: the lens's numbers (:func:`lens_fingerprint`: every surface field, the DOE profile and its
arrays, the sensor, the object distance, pupil and the dispersion data of every material the lens names, so an
in-place change of any of them is a miss), the call's arguments (fields, wavelengths, model, size, device,
precision, plan, ...) and, where ``memory_budget_gb`` is not given, that the kept batches still fit the budget
the call would have (half the available memory at the time of the call). The kept computation is planned on a
private copy of the lens (a later change of the caller's lens cannot reach it), so a hit gives the bits the
uncached call gives (same plans, same launches, same order of sums).

Bounds, explicit: ``max_entries`` (least recently used entries go first) and ``max_bytes``, the memory the kept
entries hold (the focal operators' factors, the kept DOE factors and phases, the batch tracers' tables and work
arrays: rays, splat sums, field, reused by every run; the arrays of the entry's private copy of the lens;
:meth:`PlanCache.nbytes`); an entry over ``max_bytes`` on its
own is not kept. :meth:`PlanCache.clear` drops everything; ``cache=None`` keeps nothing. Calls through one cache run
one at a time (its lock is held for the whole wave computation: a kept batch's work arrays serve one run at a time).
The ray model (``model="ray"``) has no plan and is not cached.

The default of :func:`rwwarp.psf` (``cache="auto"``) is one process-wide cache, :func:`default_cache`: at most
:data:`SHARED_MAX_ENTRIES` entries and :data:`SHARED_MAX_BYTES` held bytes. It is *shared*: a call that finds it
busy (another thread is running through it) or a lens it cannot fingerprint runs uncached instead of waiting or
failing, and a lens with multi-order phase surfaces is not cached. Turned off by ``cache=None`` (or False) on a
call, for the whole process by :func:`set_default_cache(None) <set_default_cache>` or by the environment variable
``RWWARP_PLAN_CACHE=0`` (read at every call). :func:`rwwarp.psf_map` keeps nothing unless given a cache.
Module-level settings outside a call's arguments (``rwwarp.wave.pixel_scale.FIELD_FORM``, a patched planner
function) are not in the key: clear the cache (``default_cache().clear()``) or pass ``cache=None`` after changing one.
"""
from __future__ import annotations

import dataclasses
import hashlib
import math
import pickle
import struct
import threading
import types
from collections import OrderedDict

import numpy as np

__all__ = ["PlanCache", "lens_fingerprint", "default_cache", "set_default_cache", "resolve_cache"]

#: default bounds of a :class:`PlanCache`
DEFAULT_MAX_ENTRIES = 8
DEFAULT_MAX_BYTES = 1 << 30
#: bounds of the process-wide cache of :func:`default_cache` (what ``rw.psf`` keeps between calls by default): the
#: issue 25 PSFs at 64 px held 27-227 MiB an entry on an H100 (session 14: A489 0 / 10 deg 27 / 59, AC254 83, Cooke
#: 0 / 14 deg 85 / 227), 480 MiB the five together, so all five stay kept when a caller goes round them
SHARED_MAX_ENTRIES = 8
SHARED_MAX_BYTES = 512 << 20
#: the environment variable that turns the default cache off (``0``, ``off``, ``false``, ``no``)
ENV_VAR = "RWWARP_PLAN_CACHE"


def _feed(h, v):
    """Feed ``v`` (numbers, strings, None, lists, tuples, dicts, numpy arrays, dataclasses) into the hash ``h``
    with its type, so that equal values and only those give equal bytes (1 and 1.0 differ: a cache is
    exact)."""
    if v is None:
        h.update(b"N")
    elif isinstance(v, bool) or isinstance(v, np.bool_):
        h.update(b"B1" if v else b"B0")
    elif isinstance(v, (int, np.integer)):
        h.update(b"I" + str(int(v)).encode() + b";")
    elif isinstance(v, (float, np.floating)):
        h.update(b"F" + struct.pack("<d", float(v)))
    elif isinstance(v, complex):
        h.update(b"C" + struct.pack("<dd", v.real, v.imag))
    elif isinstance(v, str):
        b = v.encode()
        h.update(b"S" + str(len(b)).encode() + b":" + b)
    elif isinstance(v, bytes):
        h.update(b"Y" + str(len(v)).encode() + b":" + v)
    elif isinstance(v, np.ndarray):
        a = np.ascontiguousarray(v)
        h.update(b"A" + a.dtype.str.encode() + str(a.shape).encode())
        if a.dtype == object:
            for x in a.reshape(-1):
                _feed(h, x)
        else:
            h.update(a.view(np.uint8).reshape(-1).data if a.size else b"")
    elif isinstance(v, (list, tuple)):
        h.update((b"L" if isinstance(v, list) else b"T") + str(len(v)).encode() + b"[")
        for x in v:
            _feed(h, x)
        h.update(b"]")
    elif isinstance(v, dict):
        h.update(b"D" + str(len(v)).encode() + b"{")
        for k in sorted(v, key=repr):
            _feed(h, repr(k))
            _feed(h, v[k])
        h.update(b"}")
    elif dataclasses.is_dataclass(v) and not isinstance(v, type):
        h.update(b"O" + type(v).__qualname__.encode() + b"(")
        for f in dataclasses.fields(v):
            _feed(h, f.name)
            _feed(h, getattr(v, f.name))
        h.update(b")")
    else:
        raise TypeError(f"lens_fingerprint: cannot fingerprint a value of type {type(v).__name__} ({v!r:.60})")


def _digest(v) -> bytes:
    """16-byte digest of the value ``v``: of its pickle (exact: floats by their bits, arrays by their bytes,
    dataclasses by their fields; ~20 us for a lens), or, for a value pickle refuses, of :func:`_feed`'s encoding.
    Equal digests mean equal values; unequal ones may (rarely: the same value built another way, e.g. a list
    shared by two surfaces) mean equal values too, which costs a miss, never a wrong hit."""
    try:
        return hashlib.blake2b(pickle.dumps(v, protocol=4), digest_size=16).digest()
    except Exception:  # noqa: BLE001 - a value pickle refuses: the slower explicit encoding
        h = hashlib.blake2b(digest_size=16)
        _feed(h, v)
        return h.digest()


def lens_fingerprint(lens) -> bytes:
    """A digest (16 bytes) of everything of ``lens`` a PSF depends on: every field of the :class:`~rwwarp.lens.Lens`
    and of each :class:`~rwwarp.lens.Surface` (radii, thicknesses, aspheric terms, apertures, the DOE profile and
    its arrays, ...), the :class:`~rwwarp.lens.Sensor`, and the dispersion data (formula, coefficients) of every
    material the surfaces name, as the glass catalogues resolve it now. Computed afresh each call (a change made
    in place to any of these gives another digest). A profile that reads its data from a file (a pixel map's
    ``file``) adds the file's size and modification time (not its contents)."""
    from .. import materials
    files = []
    for s in lens.surfaces:
        prof = s.profile
        if isinstance(prof, dict) and prof.get("file") is not None:
            from pathlib import Path
            p = Path(str(prof["file"])).expanduser()
            if not p.is_absolute() and lens.source is not None:
                p = Path(lens.source).parent / p
            try:
                st = p.stat()
                files.append((str(p), st.st_size, st.st_mtime_ns))
            except OSError:
                files.append((str(p), None))
    glass = []
    for name in sorted({s.material for s in lens.surfaces}):
        try:
            m = materials.get_material(name)
        except Exception as e:  # noqa: BLE001 - an unknown glass fails later, where the PSF needs it
            glass.append(("unresolved", name, type(e).__name__))
            continue
        glass.append((name, m.formula, tuple(m.coefficients)))
    return _digest((lens, glass, files))


def _array_bytes(a) -> int:
    """Bytes of the arrays in ``a`` (an array, or tuples / lists of them; other values count 0)."""
    if isinstance(a, (tuple, list)):
        return sum(_array_bytes(x) for x in a)
    if isinstance(a, (bytes, str)):
        return 0
    n = getattr(a, "nbytes", None)
    if n is None:
        n = getattr(a, "capacity", 0)   # a Warp array
    return int(n or 0)


def _nested_array_bytes(v, seen: set, depth: int = 0) -> int:
    """Bytes of the numpy arrays inside ``v`` (through dicts, lists, tuples and objects' attributes, 12 levels at
    most; each array, and each container, counted once through ``seen``, a set of ids)."""
    if v is None or isinstance(v, (str, bytes, int, float, complex, bool)) or depth > 12 or id(v) in seen:
        return 0
    seen.add(id(v))
    if isinstance(v, np.ndarray):
        return int(v.nbytes)
    if isinstance(v, dict):
        items = v.values()
    elif isinstance(v, (list, tuple, set, frozenset)):
        items = v
    elif hasattr(v, "__dict__") and not isinstance(v, (type, types.ModuleType)) and not callable(v):
        items = vars(v).values()
    else:
        return 0
    return sum(_nested_array_bytes(x, seen, depth + 1) for x in items)


def lens_bytes(lens, seen: set | None = None) -> int:
    """Bytes of the numpy arrays a lens object holds (a pixel-map DOE's inline data, tabulated profiles, what its
    surfaces and the lens keep): what a kept entry's private copy of the lens holds besides its plans."""
    return _nested_array_bytes(lens, set() if seen is None else seen)


def held_bytes(batches) -> int:
    """Device (and host) bytes the kept batches hold between calls: the members' focal operators, a batch's stacked
    focal operators (:func:`rwwarp.wave.focal_packed.run_focal_members`) and kept DOE factors / phases, each tracer's
    parameter and index tables and work arrays (:attr:`rwwarp.trace.Tracer.pool`), and the arrays of the entry's private
    copy of the lens (:func:`lens_bytes`: a pixel-map DOE's data)."""
    total = 0
    seen = set()
    arrays_seen = set()
    for _, packed in batches:
        objs = [packed] + list(packed.members)
        for m in objs:
            lens = getattr(m, "lens", None)
            if lens is not None and id(lens) not in seen:
                seen.add(id(lens))
                total += lens_bytes(lens, arrays_seen)
            op = getattr(m, "_focal_op", None)
            if op is not None and id(op) not in seen:
                seen.add(id(op))
                total += int(op.nbytes)
            for _, value in (getattr(m, "_memo", None) or {}).values():
                total += _array_bytes(value)
            for op, fac, rows in (m.__dict__.get("_stacked_ops") or {}).values():   # stacked focal operators
                if id(op) not in seen:
                    seen.add(id(op))
                    total += int(op.nbytes) + _array_bytes(fac) + _array_bytes(rows)
            tr = m.tracer_made() if hasattr(m, "tracer_made") else getattr(m, "tracer", None)
            if tr is not None and id(tr) not in seen:
                seen.add(id(tr))
                total += int(tr.params_np.nbytes + tr.index_np.nbytes)
                if tr.pool is not None and id(tr.pool) not in seen:   # a map's CPU batches share one pool
                    seen.add(id(tr.pool))
                    total += sum(_array_bytes(a) for a in tr.pool.values())   # rays, splat sums, field
    return total


class PlanCache:
    """Planned PSF computations kept for repeated :func:`rwwarp.psf` / :func:`rwwarp.psf_map` calls (pass it as
    ``cache=``): the pilot trace, the plans, the batches (:class:`rwwarp.wave.packed.PackedRayWave`, their tracers)
    and the propagation operators of a call, reused by the next call with the same lens values and arguments
    (module docstring: what makes a hit; a hit gives the same bits).

    ``max_entries``: calls kept (least recently used first out; default 8). ``max_bytes``: device memory the kept
    entries may hold together (bytes; default 1 GiB): an entry that would take the total over it evicts the
    least recently used ones, and one over it on its own is not kept. :meth:`clear` drops everything.
    ``hits``, ``misses`` and ``evictions`` count the look-ups.

    ``graphs``: on a CUDA device a hit replays each kept batch's device work as a CUDA graph, recorded on its first
    hit (:mod:`rwwarp.wave.graph_replay`: the same bits, one launch instead of tens; the call's ``info["replay"]``
    says "graph: trace and splat" or why a batch ran eagerly); False runs every hit eagerly. No effect on the CPU.

    ``shared``: a call that finds the cache busy (another thread runs through it), or a lens it cannot fingerprint,
    runs uncached instead of waiting or raising (``info["cache"]`` "busy" / "off"); the process-wide
    :func:`default_cache` is made so."""

    def __init__(self, max_entries: int = DEFAULT_MAX_ENTRIES, max_bytes: int = DEFAULT_MAX_BYTES,
                 graphs: bool = True, shared: bool = False):
        if isinstance(max_entries, bool) or not isinstance(max_entries, (int, np.integer)) or max_entries < 1:
            raise ValueError(f"PlanCache: max_entries must be an integer >= 1, got {max_entries!r}")
        if isinstance(max_bytes, bool) or not isinstance(max_bytes, (int, float, np.integer)) or \
                not (max_bytes >= 0 and math.isfinite(max_bytes)):
            raise ValueError(f"PlanCache: max_bytes must be a number of bytes >= 0, got {max_bytes!r}")
        self.max_entries = int(max_entries)
        self.max_bytes = int(max_bytes)
        if not isinstance(graphs, (bool, np.bool_)):
            raise ValueError(f"PlanCache: graphs must be True or False, got {graphs!r}")
        self.graphs = bool(graphs)
        if not isinstance(shared, (bool, np.bool_)):
            raise ValueError(f"PlanCache: shared must be True or False, got {shared!r}")
        self.shared = bool(shared)
        self._entries: OrderedDict = OrderedDict()   # key -> (batches, held bytes, budget check)
        self.hits = self.misses = self.evictions = 0
        self.lock = threading.RLock()

    def __len__(self) -> int:
        return len(self._entries)

    def __repr__(self) -> str:
        return (f"PlanCache({'shared, ' if self.shared else ''}{len(self)}/{self.max_entries} entries, {self.nbytes() / 2 ** 20:.3g} of "
                f"{self.max_bytes / 2 ** 20:.4g} MiB; {self.hits} hits, {self.misses} misses, {self.evictions} evicted)")

    def nbytes(self) -> int:
        """Bytes the kept entries hold (focal operators, DOE factors and phases, tracer tables and work arrays)."""
        return int(sum(e[1] for e in self._entries.values()))

    def clear(self):
        """Drop every entry (their device arrays go with the last reference)."""
        with self.lock:
            self._entries.clear()

    @staticmethod
    def key(lens, args: tuple) -> tuple:
        """The look-up key of a call: the lens's :func:`lens_fingerprint` and a digest of the call's arguments
        ``args`` (a tuple of numbers, strings, None, arrays, plans, ...: every value that changes the result)."""
        return (lens_fingerprint(lens), _digest(args))

    def lookup(self, lens, args: tuple, budget_bytes: int | None = None):
        """``(key, batches)``: the call's :meth:`key` and its kept batches (a list of ``(pairs, PackedRayWave)``), or
        None for them. ``budget_bytes``: the memory budget the call would plan under when it was not given
        explicitly; an entry is used only while every batch of it still fits that budget (else it is dropped and
        the call plans again)."""
        key = self.key(lens, args)
        with self.lock:
            e = self._entries.get(key)
            if e is not None and budget_bytes is not None and e[2] > budget_bytes:
                del self._entries[key]
                e = None
            if e is None:
                self.misses += 1
                return key, None
            self._entries.move_to_end(key)
            self.hits += 1
            return key, e[0]

    def store(self, key, batches, need_bytes: int):
        """Keep ``batches`` (``(pairs, PackedRayWave)`` pairs, already run once) under ``key``; ``need_bytes``: the
        planned peak memory of its largest batch (checked against an implicit budget on a hit). Evicts the least
        recently used entries past ``max_entries`` / ``max_bytes``; an entry over ``max_bytes`` alone is not kept.
        Returns True when kept."""
        held = held_bytes(batches)
        with self.lock:
            self._entries.pop(key, None)
            if held > self.max_bytes:
                return False
            self._entries[key] = (batches, held, int(need_bytes))
            while len(self._entries) > self.max_entries or self.nbytes() > self.max_bytes:
                self._entries.popitem(last=False)
                self.evictions += 1
            return True


_DEFAULT = None
_DEFAULT_SET = False
_DEFAULT_LOCK = threading.Lock()


def default_cache():
    """The process-wide :class:`PlanCache` that ``rw.psf(..., cache="auto")`` (its default) uses: made on first use
    with :data:`SHARED_MAX_ENTRIES` entries and :data:`SHARED_MAX_BYTES` bytes (512 MiB of kept device and host
    arrays, counted as :meth:`PlanCache.nbytes` counts them) and ``shared=True``, or the one given to
    :func:`set_default_cache`. None where the environment variable ``RWWARP_PLAN_CACHE`` is ``0`` / ``off`` /
    ``false`` / ``no`` (read at every call) or :func:`set_default_cache` was given None."""
    import os
    if os.environ.get(ENV_VAR, "").strip().lower() in ("0", "off", "false", "no"):
        return None
    global _DEFAULT
    with _DEFAULT_LOCK:
        if _DEFAULT is None and not _DEFAULT_SET:
            _DEFAULT = PlanCache(SHARED_MAX_ENTRIES, SHARED_MAX_BYTES, shared=True)
        return _DEFAULT


def set_default_cache(cache):
    """Make ``cache`` what ``cache="auto"`` uses from now on: a :class:`PlanCache`, None (nothing kept), or ``"auto"``
    (the built-in one of :func:`default_cache`, made anew on next use). The one it replaces is cleared. Returns the
    setting it replaces (a cache, None, or "auto"), so that ``set_default_cache(old)`` restores it."""
    if not (cache is None or isinstance(cache, PlanCache) or (isinstance(cache, str) and cache == "auto")):
        raise TypeError(f"set_default_cache: a rwwarp.PlanCache, None or \"auto\", got {type(cache).__name__}")
    global _DEFAULT, _DEFAULT_SET
    with _DEFAULT_LOCK:
        old = _DEFAULT if (_DEFAULT is not None or _DEFAULT_SET) else "auto"
        if isinstance(cache, str):
            _DEFAULT, _DEFAULT_SET = None, False
        else:
            _DEFAULT, _DEFAULT_SET = cache, True
    if isinstance(old, PlanCache) and old is not cache:
        old.clear()
    return old


def resolve_cache(cache):
    """The :class:`PlanCache` (or None) a public call's ``cache`` argument names: ``"auto"``: :func:`default_cache`;
    None or False: None; a :class:`PlanCache`: itself. Anything else: TypeError."""
    if isinstance(cache, str) and cache == "auto":
        return default_cache()
    if cache is None or cache is False:
        return None
    if not isinstance(cache, PlanCache):
        raise TypeError(f"cache must be a rwwarp.PlanCache, \"auto\" or None, got {type(cache).__name__}")
    return cache
