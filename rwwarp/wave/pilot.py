"""The pilot trace of a batch of point sources (:class:`Pilot`, :func:`trace_pilot`).

Every discrete decision of :class:`rwwarp.wave.raywave.RayWave` (chief rays, sampling plan, windows, sensor
patches, DOE orders, model-error estimate) is made from a coarse trace: the chief ray and a
``PILOT_GRID x PILOT_GRID`` cell-centre pupil grid of every source, traced to the wave plane and on to the
sensor. Its rays are independent of one another, so a source's pilot rays are the same bits whatever batch
they are traced in (given its entrance pupil is laid at the same wavelength): one trace of many sources
(:func:`trace_pilot`, one set of launches) serves the single-source plans of each (:meth:`Pilot.subset`).
Host numpy arrays, read-only. Lengths in mm, wavelengths in um.
"""
from __future__ import annotations

from dataclasses import dataclass, fields as _dc_fields

import numpy as np

from ..trace import Tracer, pupil_grid
from ..fields import _field_pair

__all__ = ["PILOT_GRID", "Pilot", "own_pupil_sources", "pilot_from_tracer", "trace_pilot"]

#: pupil samples per axis of the pilot's cell-centre grid (the chief ray, pupil sample 0, is added)
PILOT_GRID = 31

_ARRAYS = ("pos_p", "pos_s", "dir_s", "opl_p", "ok", "valid_plane")


def _frozen(a) -> np.ndarray:
    """A read-only copy of ``a`` (the pilot owns its arrays: no caller's array is shared or changed)."""
    out = np.array(a, copy=True)
    out.flags.writeable = False
    return out


def _dtype_name(dtype, where: str) -> str:
    """"float64" or "float32" for a trace precision given as a name or numpy type; ``ValueError`` otherwise."""
    try:
        name = np.dtype(dtype).name
    except TypeError:
        name = None
    if name not in ("float64", "float32"):
        raise ValueError(f"{where}: dtype must be 'float64' or 'float32', got {dtype!r}")
    return name


@dataclass(frozen=True, eq=False, repr=False)
class Pilot:
    """The pilot rays of a batch of ``S`` point sources on the host (numpy, read-only), ``N`` rays a source:
    pupil sample 0 is the chief ray (pupil centre), then the :data:`PILOT_GRID` cell-centre grid inside the
    pupil (:func:`rwwarp.trace.pupil_grid`). Source ``k``'s rows are what a trace of it alone gives.

    Arrays (row ``k`` = source ``k``):

    * ``pos_p`` (S, N, 3) mm: ray positions after the wave-plane surface (``lens.wave_plane_index()``), on
      that surface (a curved one: not yet carried to its vertex plane);
    * ``pos_s`` (S, N, 3) mm: positions on the sensor plane;
    * ``dir_s`` (S, N, 3): unit direction cosines after the last surface (image space);
    * ``opl_p`` (S, N) float64 mm: optical path length up to the wave-plane surface (from the chief ray's
      source sphere when ``relative_opl``, the reference the field trace uses);
    * ``ok`` (S, N) bool: the ray reached the sensor;
    * ``valid_plane`` (S, N) bool: the ray reached the wave-plane surface.

    Positions and directions are in the trace precision (``dtype``); ``opl_p`` is float64.

    What the trace was made for (a :class:`RayWave` given the pilot checks that they are its own):
    ``fields`` (deg, ``(x, y)`` pairs), ``wls`` (um, one per source), ``pupil_wls`` (um: the wavelength each
    source's paraxial entrance pupil was laid at: its own with ``own_pupils``, else the batch's shortest),
    ``object_distance_mm`` (mm, inf for an object at infinity), ``relative_opl``, ``dtype``
    ("float64" / "float32") and ``plane`` (the wave-plane surface's index).
    """

    pos_p: np.ndarray
    pos_s: np.ndarray
    dir_s: np.ndarray
    opl_p: np.ndarray
    ok: np.ndarray
    valid_plane: np.ndarray
    fields: tuple
    wls: tuple
    pupil_wls: tuple
    object_distance_mm: float
    relative_opl: bool
    dtype: str
    plane: int

    def __post_init__(self):
        n = len(self.wls)
        if not (len(self.fields) == len(self.pupil_wls) == n):
            raise ValueError(f"Pilot: {len(self.fields)} fields, {n} wavelengths and {len(self.pupil_wls)} pupil "
                             "wavelengths: one each per source")
        set_ = object.__setattr__      # frozen: the normalised values are set once, here
        set_(self, "fields", tuple(_field_pair(f) for f in self.fields))
        set_(self, "wls", tuple(float(w) for w in self.wls))
        set_(self, "pupil_wls", tuple(float(w) for w in self.pupil_wls))
        set_(self, "object_distance_mm", float(self.object_distance_mm))
        set_(self, "relative_opl", bool(self.relative_opl))
        set_(self, "plane", int(self.plane))
        set_(self, "dtype", _dtype_name(self.dtype, "Pilot"))
        n_rays = np.shape(self.pos_p)[1] if np.ndim(self.pos_p) == 3 else -1
        for name in _ARRAYS:
            a = _frozen(getattr(self, name))
            want = (n, n_rays, 3) if name in ("pos_p", "pos_s", "dir_s") else (n, n_rays)
            if a.shape != want or n_rays < 1:
                raise ValueError(f"Pilot: {name} has shape {a.shape}; expected (S, N{', 3' if len(want) == 3 else ''}) "
                                 f"= {want} for {n} source(s) of N rays (pos_p's second axis)")
            if name in ("ok", "valid_plane") and a.dtype != bool:
                raise ValueError(f"Pilot: {name} must be bool, got {a.dtype}")
            set_(self, name, a)

    def __len__(self) -> int:
        """The number of sources."""
        return len(self.wls)

    def __repr__(self) -> str:
        return (f"Pilot({len(self)} source(s) x {self.pos_p.shape[1]} rays, wls {list(self.wls)} um, pupils at "
                f"{list(self.pupil_wls)} um, {self.dtype}, wave plane {self.plane})")

    def subset(self, indices) -> "Pilot":
        """The pilot of sources ``indices`` (ints, in that order; a slice is taken too), as a trace of those
        sources alone gives it: rays are independent, so the rows are the same bits (the pupil wavelengths
        stay what they were: a source's rays follow its pupil, :attr:`pupil_wls`)."""
        idx = np.arange(len(self))[indices] if isinstance(indices, slice) else \
            np.asarray(indices, dtype=np.int64).ravel()
        if idx.size and (idx.min() < -len(self) or idx.max() >= len(self)):
            raise IndexError(f"Pilot.subset: indices {idx.tolist()} out of range for {len(self)} source(s)")
        kw = {f.name: getattr(self, f.name) for f in _dc_fields(self)}
        for name in _ARRAYS:
            kw[name] = kw[name][idx]
        for name in ("fields", "wls", "pupil_wls"):
            kw[name] = tuple(kw[name][int(i)] for i in idx)
        return Pilot(**kw)

    def check_for(self, fields, wls, pupil_wls, object_distance_mm, relative_opl, dtype, plane, where="RayWave"):
        """Raise ``ValueError`` naming what differs unless this pilot was traced for these sources: ``fields``
        (deg), ``wls`` and ``pupil_wls`` (um, one per source), ``object_distance_mm`` (mm, resolved),
        ``relative_opl``, ``dtype`` and wave-plane index ``plane``. (The lens itself cannot be checked: a
        pilot must come from the same lens values.)"""
        want = {"number of sources": (len(self), len(wls)),
                "fields (deg)": (self.fields, tuple(_field_pair(f) for f in fields)),
                "wavelengths (um)": (self.wls, tuple(float(w) for w in wls)),
                "entrance-pupil wavelengths (um; own_pupils)": (self.pupil_wls, tuple(float(w) for w in pupil_wls)),
                "object distance (mm)": (self.object_distance_mm, float(object_distance_mm)),
                "relative OPL (use_reference)": (self.relative_opl, bool(relative_opl)),
                "dtype": (self.dtype, _dtype_name(dtype, where)), "wave-plane surface": (self.plane, int(plane))}
        bad = [f"{k}: pilot {a!r}, {where} {b!r}" for k, (a, b) in want.items() if a != b]
        if bad:
            raise ValueError(f"{where}: the pilot given was traced for other sources or settings ({'; '.join(bad)}); "
                             "trace it with rwwarp.wave.pilot.trace_pilot for the same sources and options")


# ---------------------------------------------------------------------------------------------- sources
def _tracer_sources(tr, fields, wls, uniq, object_distance_mm):
    """The tracer's sources (:meth:`rwwarp.trace.Tracer.sources`): every pupil at the tracer's first
    wavelength."""
    return tr.sources(fields, [uniq.index(w) for w in wls], object_distance=object_distance_mm)


def own_pupil_sources(tr, fields, wls, uniq, object_distance_mm):
    """:meth:`rwwarp.trace.Tracer.sources` with each source's entrance pupil at its own wavelength (um), as a
    tracer of that wavelength alone lays it: a source's rays do not depend on the others in its batch.
    ``uniq``: the tracer's wavelengths (sorted), ``wls`` one per field."""
    from .. import paraxial
    src = tr.sources(fields, [uniq.index(w) for w in wls], object_distance=object_distance_mm)
    saved = tr.pupils
    try:
        for w in uniq:
            ks = [k for k, wk in enumerate(wls) if wk == w]
            # the tracer's own pupils are at its first wavelength: the same call, not made again
            tr.pupils = saved if float(w) == tr.wavelengths_um[0] else paraxial.pupils(tr.lens, w)
            sub = tr.sources([fields[k] for k in ks], uniq.index(w), object_distance=object_distance_mm)
            for key in ("pos", "dir", "finite", "aim", "half_x", "half_y"):
                src[key][ks] = sub[key]
    finally:
        tr.pupils = saved
    return src


def batch_sources(tr, fields, wls, object_distance_mm, own_pupils: bool):
    """The tracer ``tr``'s sources of ``fields`` (deg) at ``wls`` (um, one per field; ``tr`` built for their
    sorted distinct values) and the wavelength (um) each source's entrance pupil is laid at: its own with
    ``own_pupils``, else the tracer's first (shortest). ``object_distance_mm``: mm, None for the lens's."""
    uniq = sorted(set(wls))
    src = (own_pupil_sources if own_pupils else _tracer_sources)(tr, fields, wls, uniq, object_distance_mm)
    return src, tuple(float(w) for w in wls) if own_pupils else (float(uniq[0]),) * len(wls)


def pilot_from_tracer(tr, src, plane: int, wls, pupil_wls, dtype: str) -> Pilot:
    """Trace the pilot of the sources ``src`` (:meth:`rwwarp.trace.Tracer.sources`, with ``relative_opl`` set as
    the field trace will have it) with ``tr``: the chief ray and the :data:`PILOT_GRID` pupil grid of every
    source in one set of launches (one per surface), without gradients, to the wave-plane surface ``plane``
    and on to the sensor. ``wls``, ``pupil_wls``: um per source (:func:`batch_sources`); ``dtype``: the
    tracer's precision. Returns the :class:`Pilot` (host copies)."""
    nsrc = len(src["wl"])
    pu, pv, _ = pupil_grid(PILOT_GRID, src["shape"])
    pu, pv = np.concatenate([[0.0], pu]), np.concatenate([[0.0], pv])
    with tr.without_gradients():   # the plan reads these rays on the host; nothing differentiates them
        rays = tr._run(src, pu, pv, 1.0, keep=(plane,))
    at_plane, opl_plane, valid_plane = rays.kept[plane]
    return Pilot(pos_p=at_plane.numpy().reshape(nsrc, -1, 3), pos_s=rays.pos.numpy().reshape(nsrc, -1, 3),
                 dir_s=rays.dir.numpy().reshape(nsrc, -1, 3),
                 opl_p=opl_plane.numpy().reshape(nsrc, -1).astype(np.float64),
                 ok=rays.valid.numpy().reshape(nsrc, -1).astype(bool),
                 valid_plane=valid_plane.numpy().reshape(nsrc, -1).astype(bool),
                 fields=tuple(src["fields"]), wls=tuple(wls), pupil_wls=tuple(pupil_wls),
                 object_distance_mm=src["object_distance"], relative_opl=bool(src.get("relative_opl", False)),
                 dtype=dtype, plane=plane)


def pilot_or_trace(pilot, tr, src, plane: int, fields, wls, pupil_wls, use_reference: bool, dtype: str,
                   where: str) -> Pilot:
    """The planners' pilot: ``pilot`` checked against these sources (:meth:`Pilot.check_for`; ``TypeError`` for
    another type, both naming ``where``), or, where it is None, traced with ``tr`` (:func:`pilot_from_tracer`).
    Arguments as those two take them."""
    if pilot is None:
        return pilot_from_tracer(tr, src, plane, wls, pupil_wls, dtype)
    if not isinstance(pilot, Pilot):
        raise TypeError(f"{where}: pilot must be a rwwarp.wave.pilot.Pilot (rwwarp.wave.pilot.trace_pilot, "
                        f"Pilot.subset) or None, got {type(pilot).__name__}")
    pilot.check_for(fields, wls, pupil_wls, src["object_distance"], use_reference, dtype, plane, where)
    return pilot


def trace_pilot(lens, fields, wls, device: str = "cpu", dtype: str = "float64", object_distance_mm=None,
                own_pupils: bool = False, use_reference: bool = True) -> Pilot:
    """The :class:`Pilot` of a batch of sources, traced once (one set of launches for all of them, not one
    per source): ``fields`` (deg: a y angle or an (x, y) pair each), ``wls`` (um, one per field), on
    ``device`` ("cpu", "cuda[:N]") in ``dtype`` ("float64" / "float32"), object at ``object_distance_mm``
    (mm; None: the lens's). ``own_pupils``: each source's entrance pupil laid at its own wavelength (so its
    rays are what a trace of it alone gives, :meth:`Pilot.subset`), else every pupil at the shortest
    wavelength of the batch (:class:`rwwarp.wave.raywave.RayWave`'s default). ``use_reference``: OPL from the
    chief ray's source sphere (as the RayWave it is for). The same bits as the pilot a
    :class:`~rwwarp.wave.raywave.RayWave` of these sources and options traces itself."""
    fields = list(fields)
    wls = [float(w) for w in wls]
    if len(fields) != len(wls) or not fields:
        raise ValueError(f"trace_pilot: {len(fields)} fields and {len(wls)} wavelengths; give one wavelength "
                         "per field (at least one source)")
    tr = Tracer(lens, sorted(set(wls)), device=device, dtype=dtype)
    src, pupil_wls = batch_sources(tr, fields, wls, object_distance_mm, own_pupils)
    src["relative_opl"] = bool(use_reference)
    return pilot_from_tracer(tr, src, lens.wave_plane_index(), wls, pupil_wls, dtype)
