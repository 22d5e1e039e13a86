"""Converged reference PSFs, error estimates of cheaper plans, and the cheapest plan for a target error.

The ray-wave PSF has four discretisation knobs (see :mod:`rwwarp.wave.plan`):

* ``nyquist_safety``: how far below the Nyquist pitch of the local wavefront the DOE-plane grid
  goes (halves the pitch when doubled: twice the samples, and twice the rays across the pupil);
* ``rays_per_sample``: rays per DOE-plane sample along each axis (doubling quadruples the rays);
* ``pad_factor``: the FFT length relative to the adaptive plan's (2x the window, band limit);
* ``gauss_nodes``: Gauss-Legendre nodes per axis of the pixel integration (cheap; matters when
  the PSF has structure finer than a pixel: 3 nodes leave ~3e-2 on an f/5 lens with 5 um pixels).
  ``None`` is rw.psf's automatic choice; doubling it means 16 nodes (the automatic ceiling).

:func:`converged_reference` refines them by doubling until the PSF stops changing. Doubling all
of them at once multiplies the work by ~64 per step (16x the rays, 4x the FFT area) and leaves the
CPU after one step, so the knobs are refined one coordinate at a time: every round doubles each
knob on its own, measures the change of the PSF (relative L2), and keeps doubling those whose
change is not yet below the tolerance. The run stops when the combined change
``sqrt(sum_k change_k^2) < tol`` (converged) or when a knob that still matters would exceed the
work caps (``max_rays``, ``max_fft``); then it says so (``converged: False``) with the change it
reached. The PSF returned is the one at the final settings; its error is estimated from the last
changes, ``sum_k (change_k / (1 - 2^-p_k))^2`` under a square root, with ``p_k`` the convergence order
observed for knob k over two doublings (1, i.e. a factor 2, until two are known).

:func:`estimate_error` gives that estimate for any setting (one run per knob doubled), and
:func:`plan_for_error` walks a small ladder of ``nyquist_safety x rays_per_sample`` settings in order of
predicted cost and returns the first whose measured error against the converged reference meets a
target. Everything is host code on top of :func:`rwwarp.psf`; lengths in mm, wavelengths in um, field
angles in degrees, times in seconds (wall clock of the whole ``rw.psf`` call).
"""
from __future__ import annotations

import inspect
import math
import time
import warnings
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from .errors import SamplingWarning
from .wave.plan import Plan, nice_fft_length
from .psf import PSF, RayWave
from .psf import psf as _psf
from .trace import as_field_list

KNOBS = ("nyquist_safety", "rays_per_sample", "pad_factor", "gauss_nodes")

#: (nyquist_safety, rays_per_sample) settings tried by :func:`plan_for_error` (sorted there by predicted
#: cost: ray count ~ (safety * rays_per_sample)^2, FFT area ~ safety^2).
LADDER = ((1.0, 1.0), (1.5, 1.0), (2.0, 1.0), (1.5, 1.5), (2.0, 1.5), (3.0, 1.0), (3.0, 1.5), (4.0, 1.0),
          (3.0, 2.0), (4.0, 2.0))

_DEFAULTS = inspect.signature(_psf).parameters


@dataclass(frozen=True)
class Settings:
    """Discretisation knobs of one ray-wave PSF (the adaptive plan's inputs plus a padding factor);
    the defaults are :func:`rwwarp.psf`'s."""

    nyquist_safety: float = float(_DEFAULTS["nyquist_safety"].default)
    rays_per_sample: float = float(_DEFAULTS["rays_per_sample"].default)
    pad_factor: float = 1.0
    gauss_nodes: int | None = _DEFAULTS["gauss_nodes"].default  # None: chosen per scene by rw.psf

    def doubled(self, *knobs) -> Settings:
        def twice(k):
            v = getattr(self, k)
            if v is None:  # automatic pixel quadrature: its ceiling is 16 nodes
                return 16
            return type(v)(2 * v)
        return replace(self, **{k: twice(k) for k in knobs})

    def to_dict(self) -> dict:
        return asdict(self)


def rel_l2(a, b) -> float:
    """Relative L2 distance ``||a - b|| / ||b||`` of two PSF arrays (b the reference)."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    nb = float(np.linalg.norm(b))
    return float(np.linalg.norm(a - b) / nb) if nb > 0 else float("inf")


def plan_at(lens, field_deg, wavelength_um, size, device="cpu", settings=Settings(), *, center_mm=None,
            pixel_mm=None, object_distance_mm=None, dtype="float64") -> Plan:
    """The adaptive plan (:class:`~rwwarp.wave.plan.Plan`) for one field point at ``settings``.

    Runs only the pilot trace (cheap). ``pad_factor`` scales the adaptive FFT length (rounded up to a
    VkFFT-friendly length); the other arguments as :func:`rwwarp.psf`.
    """
    pixel = float(pixel_mm or lens.sensor.pixel_pitch)
    rwm = RayWave(lens, as_field_list(field_deg), [float(wavelength_um)], size, pixel, device, "auto", dtype,
                  "energy", object_distance_mm, settings.rays_per_sample, center_mm, True, 3,
                  settings.nyquist_safety)
    pl = rwm.plan
    if settings.pad_factor != 1.0:
        n_pad = nice_fft_length(math.ceil(pl.n_pad * settings.pad_factor))
        pl = Plan(pl.pitch_mm, pl.n_grid, n_pad, pl.ray_grid, "auto", pl.output_on_grid,
                  list(pl.reasons) + [f"padding x{settings.pad_factor:g} (convergence study) -> FFT {n_pad}"])
    return pl


def psf_at(lens, field_deg, wavelength_um, size, device="cpu", settings=Settings(), *, center_mm=None,
           pixel_mm=None, object_distance_mm=None, dtype="float64", amplitude="energy",
           plan=None) -> tuple[PSF, float]:
    """Ray-wave PSF at ``settings``; returns ``(psf, seconds)``.

    With ``pad_factor == 1`` this is exactly ``rw.psf(..., plan="auto", method="asm", nyquist_safety=...,
    rays_per_sample=...)``; otherwise the adaptive plan with the FFT length scaled is passed explicitly
    (``plan`` may hand in that plan when the caller already has it).
    """
    kw = dict(size=size, device=device, dtype=dtype, amplitude=amplitude, object_distance_mm=object_distance_mm,
              pixel_mm=pixel_mm, center_mm=center_mm, gauss_nodes=None if settings.gauss_nodes is None else int(settings.gauss_nodes),
              nyquist_safety=settings.nyquist_safety, rays_per_sample=settings.rays_per_sample,
              method="asm")   # the study converges the band-limited ASM's knobs (its plan, as plan_at)
    if settings.pad_factor == 1.0:
        t0 = time.perf_counter()
        p = _psf(lens, field_deg, wavelength_um, plan="auto", **kw)
        return p, time.perf_counter() - t0
    if plan is None:
        plan = plan_at(lens, field_deg, wavelength_um, size, device, settings, center_mm=center_mm,
                       pixel_mm=pixel_mm, object_distance_mm=object_distance_mm, dtype=dtype)
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        # the plan is the adaptive one with a longer FFT: its ray grid covers the beam footprint by design,
        # while the explicit-plan check counts rays across the window (footprint + margins)
        warnings.filterwarnings("ignore", message="ray density", category=SamplingWarning)
        p = _psf(lens, field_deg, wavelength_um, plan=plan, **kw)
    return p, time.perf_counter() - t0


def _plan_summary(plan) -> dict:
    p = plan if isinstance(plan, dict) else plan.to_dict()
    return {"pitch_um": p["pitch_mm"] * 1e3, "n_grid": p["n_grid"], "n_pad": p["n_pad"], "ray_grid": p["ray_grid"],
            "rays": p["ray_grid"] ** 2}


def predicted_cost(plan) -> float:
    """Relative work of a plan, for ordering ladders: pupil rays plus half the FFT area."""
    return float(plan.ray_grid ** 2 + 0.5 * plan.n_pad ** 2)


def _order_factor(changes: list) -> tuple[float, float | None]:
    """Error/change factor 1 / (1 - 2^-p) from the last two changes of one knob (p clamped to [0.5, 4])."""
    if len(changes) >= 2 and changes[-2] > 0 and changes[-1] > 0:
        p = float(np.clip(math.log2(changes[-2] / changes[-1]), 0.5, 4.0))
        return 1.0 / (1.0 - 2.0 ** -p), p
    return 2.0, None


def converged_reference(lens, field_deg, wavelength_um, size, device="cpu", tol=1e-5, *, start=Settings(),
                        max_rays=4096 ** 2, max_fft=8192, max_rounds=6, center_mm=None, pixel_mm=None,
                        object_distance_mm=None, dtype="float64", amplitude="energy", callback=None):
    """A ray-wave PSF refined until doubling any knob changes it by less than ``tol`` (relative L2).

    Parameters
    ----------
    lens, field_deg, wavelength_um, size, device : as :func:`rwwarp.psf` (deg, um, pixels).
    tol : float
        Target for the combined change ``sqrt(sum_k change_k^2)`` of one doubling of each knob.
    start : Settings
        Where the refinement starts (the adaptive defaults).
    max_rays, max_fft : int
        Work caps: pupil rays (``ray_grid^2``) and FFT length per axis of any run. A knob whose doubling
        would pass them is not refined further; if it still matters the result says ``converged: False``.
    max_rounds : int
        At most this many refinement rounds.
    center_mm : (x, y), optional
        Sensor patch centre (mm); default the chief ray's pixel at the start settings. Every run uses it.
    callback : callable, optional
        Called with each history entry as it is made (progress reporting).

    Returns
    -------
    (psf, history)
        ``psf``: :class:`~rwwarp.psf.PSF` at the final settings; ``psf.info["convergence"]`` holds
        ``converged``, ``combined_change`` (the last round's), ``estimated_error``, ``changes`` and
        ``orders`` per knob, ``settings``, ``capped`` (knobs stopped by the caps), ``total_time_s``.
        ``history``: list of dicts, one per PSF computed: ``round``, ``role`` ("state" or "trial"),
        ``knob``, ``settings``, ``plan`` (pitch_um, n_grid, n_pad, ray_grid, rays), ``change`` (trial:
        relative L2 to the state of its round), ``time_s``.
    """
    t_start = time.perf_counter()
    kw = dict(pixel_mm=pixel_mm, object_distance_mm=object_distance_mm, dtype=dtype)
    history = []

    def log(entry):
        history.append(entry)
        if callback is not None:
            callback(entry)

    def fits(pl):
        return pl.ray_grid ** 2 <= max_rays and pl.n_pad <= max_fft

    state = start
    pl = plan_at(lens, field_deg, wavelength_um, size, device, state, center_mm=center_mm, **kw)
    if not fits(pl):
        raise ValueError(f"the start settings already exceed the caps (ray_grid {pl.ray_grid}, FFT {pl.n_pad}); "
                         f"raise max_rays / max_fft or start lower")
    cur, dt = psf_at(lens, field_deg, wavelength_um, size, device, state, center_mm=center_mm, amplitude=amplitude,
                     plan=pl, **kw)
    if center_mm is None:
        center_mm = tuple(float(c) for c in cur.center_mm)
    log({"round": 0, "role": "state", "knob": None, "settings": state.to_dict(), "plan": _plan_summary(pl),
         "change": None, "time_s": dt})
    known = {k: [] for k in KNOBS}   # successive changes measured per knob
    last = {}                         # latest change per knob
    capped = set()
    converged = False
    combined = float("inf")
    for rnd in range(1, max_rounds + 1):
        trials = {}
        for k in KNOBS:
            s2 = state.doubled(k)
            pl2 = plan_at(lens, field_deg, wavelength_um, size, device, s2, center_mm=center_mm, **kw)
            if not fits(pl2):
                capped.add(k)
                continue
            p2, dt = psf_at(lens, field_deg, wavelength_um, size, device, s2, center_mm=center_mm,
                            amplitude=amplitude, plan=pl2, **kw)
            c = rel_l2(p2.data, cur.data)
            trials[k] = (s2, p2, pl2)
            known[k].append(c)
            last[k] = c
            log({"round": rnd, "role": "trial", "knob": k, "settings": s2.to_dict(), "plan": _plan_summary(pl2),
                 "change": c, "time_s": dt})
        if not last:
            break
        combined = math.sqrt(sum(c * c for c in last.values()))
        # a knob capped this round counts with its last measured change (made at coarser settings)
        if combined < tol and len(last) == len(KNOBS):
            converged = True
            break
        thresh = tol / math.sqrt(len(KNOBS))
        grow = sorted((k for k in trials if last[k] >= thresh), key=lambda k: -last[k])
        if not grow:
            # every refinable knob is settled, the rest is capped: nothing more can be done within the caps
            break
        # double every knob that still matters; while that passes the caps, drop the least important of the
        # knobs that cost work (pixel quadrature is cheap and never capped)
        while True:
            new = state.doubled(*grow)
            pl_new = trials[grow[0]][2] if len(grow) == 1 else plan_at(lens, field_deg, wavelength_um, size, device,
                                                                         new, center_mm=center_mm, **kw)
            heavy = [k for k in grow if k != "gauss_nodes"]
            if fits(pl_new) or len(heavy) <= 1:
                break
            grow.remove(min(heavy, key=lambda k: last[k]))
        if len(grow) == 1:
            state, cur = trials[grow[0]][0], trials[grow[0]][1]
            history[len(history) - len(trials) + list(trials).index(grow[0])]["adopted"] = True
        else:
            state, prev = new, cur
            cur, dt = psf_at(lens, field_deg, wavelength_um, size, device, state, center_mm=center_mm,
                             amplitude=amplitude, plan=pl_new, **kw)
            log({"round": rnd, "role": "state", "knob": "+".join(grow), "settings": state.to_dict(),
                 "plan": _plan_summary(pl_new), "change": rel_l2(cur.data, prev.data), "time_s": dt})
        for k in grow:
            capped.discard(k)
    est2, orders = 0.0, {}
    for k, cs in known.items():
        if cs:
            f, p = _order_factor(cs)
            orders[k] = p
            est2 += (f * cs[-1]) ** 2
    cur.info["convergence"] = {
        "converged": converged, "tol": tol, "combined_change": combined, "estimated_error": math.sqrt(est2),
        "changes": dict(last), "change_history": {k: v for k, v in known.items() if v}, "orders": orders,
        "settings": state.to_dict(), "capped": sorted(capped), "max_rays": max_rays, "max_fft": max_fft,
        "center_mm": list(center_mm), "total_time_s": time.perf_counter() - t_start,
        "n_psfs": len(history)}
    return cur, history


def estimate_error(lens, field_deg, wavelength_um, size, device="cpu", settings=Settings(), *, center_mm=None,
                   pixel_mm=None, object_distance_mm=None, dtype="float64", knobs=KNOBS):
    """Error estimate of the PSF at ``settings`` from one doubling of each knob.

    Returns a dict: ``psf`` (the PSF at ``settings``), ``time_s``, ``changes`` (relative L2 of each
    knob's doubling against it) and ``estimated_error = sqrt(sum_k (2 change_k)^2)`` (first-order
    convergence: the remaining error of a knob is about twice its last change; conservative for higher
    orders). Costs one PSF per knob, each more expensive than the one estimated.
    """
    kw = dict(pixel_mm=pixel_mm, object_distance_mm=object_distance_mm, dtype=dtype)
    p, t = psf_at(lens, field_deg, wavelength_um, size, device, settings, center_mm=center_mm, **kw)
    c0 = tuple(float(c) for c in p.center_mm)
    changes = {}
    for k in knobs:
        p2, _ = psf_at(lens, field_deg, wavelength_um, size, device, settings.doubled(k), center_mm=c0, **kw)
        changes[k] = rel_l2(p2.data, p.data)
    est = math.sqrt(sum((2.0 * c) ** 2 for c in changes.values()))
    return {"psf": p, "time_s": t, "changes": changes, "estimated_error": est, "settings": settings.to_dict()}


@dataclass
class PlanChoice:
    """Result of :func:`plan_for_error`. Unpacks as ``plan, error, time_s = choice``.

    ``plan``: the explicit :class:`~rwwarp.wave.plan.Plan` for this field point (pass it as ``plan=``);
    ``settings``: the knobs that produced it (they carry over to other fields: pass
    ``nyquist_safety`` / ``rays_per_sample`` to :func:`rwwarp.psf`); ``error``: measured relative L2
    error against the reference; ``time_s``: median wall time of ``rw.psf`` with these settings;
    ``met``: whether the target was met (else the most accurate rung is returned);
    ``ladder``: every rung tried (settings, plan summary, error, time_s); ``reference_error``: the
    reference's own estimated error (errors below it are not resolved).
    """

    plan: Plan
    error: float
    time_s: float
    settings: dict
    met: bool
    target_error: float
    ladder: list = field(default_factory=list)
    reference_error: float | None = None

    def __iter__(self):
        return iter((self.plan, self.error, self.time_s))


def gauss_nodes_for(lens, field_deg, wavelength_um, size, device="cpu", target_error=1e-3, *, settings=Settings(),
                    center_mm=None, max_nodes=48, **kw) -> tuple[int, list]:
    """Fewest pixel-integration nodes (the automatic count, then doubled) whose doubling changes the PSF by
    < target_error / 4.

    Cheap: only the output evaluation grows with the node count. Returns ``(nodes, changes)``.
    """
    if settings.gauss_nodes is None:   # start from the count rw.psf chooses for this scene
        pixel = float(kw.get("pixel_mm") or lens.sensor.pixel_pitch)
        rwm = RayWave(lens, as_field_list(field_deg), [float(wavelength_um)], size, pixel, device, "auto",
                      kw.get("dtype", "float64"), "energy", kw.get("object_distance_mm"), settings.rays_per_sample,
                      center_mm, True, None, settings.nyquist_safety)
        g = int(getattr(rwm, "gauss_nodes", None) or 3)
    else:
        g = int(settings.gauss_nodes)
    p, _ = psf_at(lens, field_deg, wavelength_um, size, device, replace(settings, gauss_nodes=g), center_mm=center_mm,
                  **kw)
    center = tuple(float(c) for c in p.center_mm)
    changes = []
    while 2 * g <= max_nodes:
        p2, _ = psf_at(lens, field_deg, wavelength_um, size, device, replace(settings, gauss_nodes=2 * g),
                       center_mm=center, **kw)
        changes.append(rel_l2(p.data, p2.data))
        if changes[-1] < target_error / 4:
            break
        g, p = 2 * g, p2
    return g, changes


def plan_for_error(lens, field_deg, wavelength_um, size, device="cpu", target_error=1e-3, *, reference=None,
                   ladder=LADDER, gauss_nodes=None, repeat=1, exhaustive=False, center_mm=None, pixel_mm=None,
                   object_distance_mm=None, dtype="float64", reference_kwargs=None) -> PlanChoice:
    """The cheapest ladder setting whose PSF error against the converged reference is <= ``target_error``.

    Parameters
    ----------
    target_error : float
        Relative L2 error wanted against the converged reference.
    reference : PSF, optional
        A converged reference (from :func:`converged_reference`); computed when omitted, with
        ``reference_kwargs`` passed on (e.g. ``tol``, ``max_rays``).
    ladder : sequence of (nyquist_safety, rays_per_sample)
        Settings tried, in order of :func:`predicted_cost` of their pilot plans.
    gauss_nodes : int, optional
        Pixel-integration nodes for every rung; by default :func:`gauss_nodes_for` picks them first
        (the fewest whose doubling changes the PSF by < target_error / 4).
    repeat : int
        Timed runs per rung after the first (which gives the error); the median is reported.
    exhaustive : bool
        Measure every rung (for charts); otherwise stop at the first that meets the target.

    Returns
    -------
    PlanChoice (unpacks as ``plan, error, time_s``). If no rung meets the target the most accurate one
    is returned with ``met=False``.
    """
    kw = dict(pixel_mm=pixel_mm, object_distance_mm=object_distance_mm, dtype=dtype)
    if reference is None:
        reference, _ = converged_reference(lens, field_deg, wavelength_um, size, device, center_mm=center_mm,
                                           **kw, **(reference_kwargs or {}))
    center = tuple(float(c) for c in reference.center_mm)
    if gauss_nodes is None:
        gauss_nodes, _ = gauss_nodes_for(lens, field_deg, wavelength_um, size, device, target_error, center_mm=center,
                                         **kw)
    rungs = []
    for s, r in ladder:
        st = Settings(float(s), float(r), 1.0, int(gauss_nodes))
        pl = plan_at(lens, field_deg, wavelength_um, size, device, st, center_mm=center, **kw)
        rungs.append((predicted_cost(pl), st, pl))
    rungs.sort(key=lambda t: t[0])
    rows, best = [], None
    for cost, st, pl in rungs:
        p, t_first = psf_at(lens, field_deg, wavelength_um, size, device, st, center_mm=center, **kw)
        err = rel_l2(p.data, reference.data)
        times = [psf_at(lens, field_deg, wavelength_um, size, device, st, center_mm=center, **kw)[1]
                 for _ in range(repeat)] or [t_first]
        t = float(np.median(times))
        row = {"settings": st.to_dict(), "plan": _plan_summary(pl), "predicted_cost": cost, "error": err,
               "time_s": t, "meets": err <= target_error}
        rows.append(row)
        if row["meets"] and (best is None or not best[0]["meets"] or t < best[0]["time_s"]) or best is None or (not best[0]["meets"] and err < best[0]["error"]):
            best = (row, pl)
        if row["meets"] and not exhaustive:
            break
    row, pl = best
    ref_err = reference.info.get("convergence", {}).get("estimated_error") if reference.info else None
    return PlanChoice(pl, row["error"], row["time_s"], row["settings"], row["meets"], target_error, rows, ref_err)
