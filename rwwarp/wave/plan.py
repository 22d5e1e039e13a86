"""Sampling plans: how big, how fine and how many rays a ray-wave PSF needs (adaptive modelling).

A plan is chosen per batch of point sources from a cheap pilot trace (a coarse pupil grid):

* window: the beam footprint on the DOE plane plus a margin of ``margin_samples`` samples;
* pitch: Nyquist for the field after the DOE with the chief ray's carrier removed,
  ``pitch <= 1 / (2 * safety * (max |f_field - f_chief| + max |f_doe|))`` (cycles/mm), and at most half
  the DOE feature size for pixel-map DOEs (the paper's choice);
* padding: the band-limited ASM needs a period ``L >= window + sensor patch`` (shifted band limit),
  rounded up to a VkFFT-friendly length (2^a 3^b 5^c 7^d);
* rays: ``rays_per_sample`` rays per sample along each axis across the footprint.

``plan="paper"`` reproduces the paper's fixed grid: the whole DOE aperture at half the DOE
feature size (1 um features -> 0.5 um), padded 2x, output on the same grid.
Every choice is recorded with its reason in :attr:`Plan.reasons`.
"""
from __future__ import annotations

import copy
import math
import warnings
from dataclasses import asdict, dataclass, is_dataclass

import numpy as np


from ..errors import SamplingWarning


def nice_fft_length(n: int) -> int:
    """Smallest integer >= n whose prime factors are all in {2, 3, 5, 7} (fast for VkFFT)."""
    from .propagate import next_fft_size
    return next_fft_size(n)


@dataclass(frozen=True)
class Plan:
    """Sampling of one batch (immutable: a caller's plan is never changed by a call that uses it).

    ``pitch_mm`` of the wave-plane grid, ``n_grid`` samples per side, ``n_pad`` FFT length of the
    band-limited ASM (``method="asm"``), ``ray_grid`` pupil samples across the diameter, ``reasons``
    (text, a tuple). ``method``: ``"asm"`` (band-limited angular spectrum over the whole beam) or
    ``"focal"`` (reference wave handled analytically, :mod:`rwwarp.wave.focal`), which also uses the sensor-side
    grid ``sensor_pitch_mm`` x ``n_sensor`` and its FFT length ``n_sensor_fft``. ``estimate``: the
    planner's cost estimate (``memory_bytes``, ``flops``) for the whole batch, or None. ``model_error``: the
    ray-wave model's own error estimated from the scene (:mod:`rwwarp.wave.model_error`; the worst source's
    :meth:`~rwwarp.wave.model_error.ModelError.to_dict`), or None. ``wave_step_mm``: the reduced distance (mm; it propagates over
    it stretched for the rim's obliquity, :func:`rwwarp.wave.wave_step.rim_obliquity`) of the wave step that replaces the geometric field's edge by the diffracted one before the DOE
    (:func:`rwwarp.wave.wave_step.apply_wave_step`), or None (the one-step model). ``pixel_field``: for
    ``method="pixel"``, the sensor field's form and its tiling (:func:`rwwarp.wave.pixel_scale.plan_field`), else None.
    """

    pitch_mm: float
    n_grid: int
    n_pad: int
    ray_grid: int
    kind: str = "auto"
    output_on_grid: bool = False
    reasons: tuple = ()
    method: str = "asm"
    sensor_pitch_mm: float | None = None
    n_sensor: int | None = None
    n_sensor_fft: int | None = None
    estimate: dict | None = None
    model_error: dict | None = None
    wave_step_mm: float | None = None
    pixel_field: dict | None = None

    def __post_init__(self):
        object.__setattr__(self, "reasons", tuple(self.reasons))
        from .methods import names
        if self.method not in names():
            raise ValueError(f"Plan.method must be a registered propagation method ({', '.join(map(repr, names()))}), "
                             f"got {self.method!r}")

    def with_reasons(self, *more) -> "Plan":
        """A copy with ``more`` reasons appended."""
        return self.evolved(reasons=tuple(self.reasons) + tuple(more))

    def evolved(self, **changes) -> "Plan":
        """``dataclasses.replace(self, **changes)`` without re-running every field through ``__init__``: the same
        plan (``reasons`` made a tuple, a new ``method`` checked), made with one dict copy (the planners make
        several a source)."""
        bad = set(changes).difference(self.__dataclass_fields__)
        if bad:
            raise TypeError(f"Plan.evolved: no field(s) {', '.join(sorted(bad))}")
        new = object.__new__(Plan)
        d = new.__dict__
        d.update(self.__dict__)
        d.update(changes)
        if "reasons" in changes:
            d["reasons"] = tuple(d["reasons"])
        if "method" in changes:
            from .methods import names
            if d["method"] not in names():
                raise ValueError(f"Plan.method must be a registered propagation method "
                                 f"({', '.join(map(repr, names()))}), got {d['method']!r}")
        return new

    def to_dict(self) -> dict:
        """The plan as a new dict of its fields (``reasons`` a list; nested dicts, lists and arrays copied: the
        caller may change it), what ``dataclasses.asdict`` gives, made without its generic recursion (every PSF
        result carries its plans' dicts; issue 25's warm call)."""
        own = self.__dict__
        d = {name: _plain(own[name]) for name in _PLAN_FIELDS}
        d["reasons"] = list(d["reasons"])
        return d

    def explain(self) -> str:
        """Human-readable summary of the plan, its cost estimate and why."""
        from .methods import get
        head = (f"plan {self.kind} ({self.method}): " + get(self.method).explain_grids(self)
                + f"pupil rays {self.ray_grid} across")
        lines = [head]
        if self.model_error:
            lines.append(f"  model error: ~{self.model_error['estimate']:.2g} of the peak (N_F "
                         f"{self.model_error['fresnel_number']:.4g}, rim slope {self.model_error['rim_slope_rad']:.3g} rad)"
                         + (f"; wave step over {self.wave_step_mm:.4g} mm before the DOE" if self.wave_step_mm else ""))
        if self.estimate:
            lines.append(f"  estimate: peak memory {self.estimate['memory_bytes'] / 2 ** 30:.3g} GiB, "
                         f"{self.estimate['flops'] / 1e9:.3g} GFLOP")
        return "\n".join(lines + [f"  - {r}" for r in self.reasons])


def _plain(v):
    """``v`` as ``dataclasses.asdict`` copies a field's value: dicts, lists and tuples rebuilt (keys too), a dataclass
    as a dict, immutable scalars kept, anything else deep-copied."""
    if v is None or type(v) in (int, float, str, bool, complex):
        return v
    if type(v) is dict:
        return {_plain(k): _plain(x) for k, x in v.items()}
    if type(v) in (list, tuple):
        return type(v)(_plain(x) for x in v)
    if is_dataclass(v) and not isinstance(v, type):
        return asdict(v)
    return copy.deepcopy(v)


_PLAN_FIELDS = tuple(Plan.__dataclass_fields__)   # in their order


def check_explicit(plan: Plan, needed_pitch_mm: float, needed_pad: int, window_mm: float):
    """Warn (:class:`SamplingWarning`) where an explicit plan violates a sampling criterion."""
    if plan.pitch_mm > needed_pitch_mm * 1.0001:
        warnings.warn(f"Nyquist criterion violated: pitch {plan.pitch_mm * 1e3:.4g} um > "
                      f"{needed_pitch_mm * 1e3:.4g} um needed by the local wavefront slope and DOE features; "
                      f"the field will alias. Fix: pitch_mm <= {needed_pitch_mm:.4g} or plan='auto'",
                      SamplingWarning, stacklevel=3)
    if plan.n_pad < needed_pad:
        warnings.warn(f"band-limit (padding) criterion violated: FFT length {plan.n_pad} < {needed_pad} "
                      f"needed for the window plus the sensor patch; wrap-around will alias. "
                      f"Fix: n_pad >= {needed_pad} or plan='auto'", SamplingWarning, stacklevel=3)
    if plan.n_grid * plan.pitch_mm < window_mm * 0.999:
        warnings.warn(f"window criterion violated: grid {plan.n_grid} x {plan.pitch_mm * 1e3:.4g} um = "
                      f"{plan.n_grid * plan.pitch_mm:.4g} mm does not cover the beam footprint "
                      f"{window_mm:.4g} mm; rays outside are lost. Fix: n_grid >= "
                      f"{math.ceil(window_mm / plan.pitch_mm) + 2}", SamplingWarning, stacklevel=3)
    ray_pitch = window_mm / max(plan.ray_grid, 1)
    if ray_pitch > plan.pitch_mm * 1.0001:
        warnings.warn(f"ray density criterion violated: {plan.ray_grid} rays across a {window_mm:.4g} mm "
                      f"footprint leave samples without rays (ray spacing {ray_pitch * 1e3:.4g} um > pitch "
                      f"{plan.pitch_mm * 1e3:.4g} um). Fix: ray_grid >= {math.ceil(window_mm / plan.pitch_mm)}",
                      SamplingWarning, stacklevel=3)


# ---------------------------------------------------------------------------------------------- cost
def default_memory_budget_bytes(device: str = "cpu") -> int:
    """Default memory budget (bytes) of one PSF call on ``device``: half of what the operating system
    reports available (``MemAvailable``) on the CPU, half the free memory of a CUDA device."""
    dev = str(device)
    if dev.startswith("cuda"):
        try:
            import cupy
            idx = int(dev.split(":")[1]) if ":" in dev else 0
            with cupy.cuda.Device(idx):
                free, _ = cupy.cuda.runtime.memGetInfo()
            return int(free) // 2
        except Exception:  # no CuPy: a conservative 8 GiB
            return 8 * 2 ** 30
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024 // 2
    except OSError:
        pass
    return 4 * 2 ** 30


def estimate_cost(plan: Plan, n_sources: int, size: int, gauss_nodes: int) -> dict:
    """Peak memory (bytes, the planned arrays of one batch) and work (flops) of a ray-wave batch.

    Counted: the traced rays (two ping-pong ray states of position, direction, OPL and validity, plus
    tube areas, weights and wavelengths: ~200 bytes a ray, and the 32-byte power terms summed per
    source by :func:`rwwarp.wave.reduce.source_sums`), the splat accumulators and the field
    (~64 bytes a wave-plane sample), and the propagation's arrays: for ``asm`` the padded FFT
    (``n_pad^2``, two complex buffers) and the output matrix DFT; for ``focal`` the two separable
    kernel matrices (``n_sensor x n_grid``), the sensor-side FFT (``n_sensor_fft^2``, three complex
    buffers) and its output DFT. Flops: ~400 a ray and surface-free step, 5 N log2 N per FFT,
    8 per complex multiply-add. Checked against measured peak RSS in ``perf/bench_focal.py``. Each method's
    own count: :meth:`rwwarp.wave.methods.Propagation.estimate` (``pixel``: :func:`rwwarp.wave.pixel_scale.pixel_cost`).
    """
    from .methods import get
    return get(plan.method).estimate(plan, n_sources, size, gauss_nodes)


class MemoryBudgetError(MemoryError):
    """A planned computation would exceed the memory budget; the message names the estimate and the knob."""


def check_budget(estimate: dict, budget_bytes: int, what: str, knobs: str):
    """Raise :class:`MemoryBudgetError` when ``estimate['memory_bytes']`` exceeds ``budget_bytes``."""
    if estimate["memory_bytes"] > budget_bytes:
        raise MemoryBudgetError(
            f"{what} needs an estimated {estimate['memory_bytes'] / 2 ** 30:.3g} GiB, over the memory budget of "
            f"{budget_bytes / 2 ** 30:.3g} GiB (memory_budget_gb). What drives it: {knobs}. Reduce one of them, "
            f"split the batch (batch=...), or raise memory_budget_gb if the machine has the memory.")


# ---------------------------------------------------------------------------------------------- focal
def landing_points(xy, f, inv_lam, distance_mm):
    """Where straight rays from wave-plane points ``xy`` (N, 2) mm with transverse frequencies ``f`` (N, 2)
    cycles/mm (``n d_xy / lambda``) meet the sensor ``distance_mm`` behind: ``xy + z f / w(f)``,
    ``w = sqrt(inv_lam^2 - |f|^2)``. Rays with ``|f| >= inv_lam`` (evanescent) give NaN."""
    w2 = inv_lam ** 2 - np.sum(f * f, axis=-1)
    w = np.sqrt(np.where(w2 > 0, w2, np.nan))
    return xy + distance_mm * f / w[..., None]


FIT_WIDE = 16   # fit_quadratic_transfers: from this many sources on, its sums run down the points of a (P, S) copy


def fit_quadratic_transfers(u, t, ok, g, q):
    """:func:`fit_quadratic_transfer`'s least-squares fit along one axis, for ``S`` sources at once.

    Per source ``k``: the line ``t = c0 + c1 u`` through the points ``(u[k, i], t[k, i])`` with ``ok[k, i]``
    (``u``: frequency offsets ``f_a - f_c,a`` (cycles/mm), ``t``: ``d w / d f_a = (x_a - L_a) / z`` (dimensionless);
    (S, P) arrays, ``ok`` (S, P) bool: the points of each source, the others padding that no sum sees), in closed
    form: ``c1 = sum (u - <u>) (t - <t>) / sum (u - <u>)^2``, ``c0 = <t> - c1 <u>`` over the source's points (means
    ``<.>``), each sum added in the points' order, first to last (unlike ``np.sum``'s pairwise summation, whose
    rounding depends on a row's length; padding enters as ``-0.0``, the exact additive identity): a source's
    values are the same bits alone and in any padded batch. Few sources: each row's running sum (``np.cumsum``);
    from ``FIT_WIDE`` sources on, ``np.add.reduce`` down the points of a C-contiguous (P, S) copy, which numpy
    adds row after row, vectorised across the sources (the same bits; a narrow one spends its time in per-row
    calls). Falls back to the Taylor values ``g[k]``, ``q[k]`` (mm^0 and mm) where the source
    has fewer than 3 points or no spread in ``u`` (``max u - min u <= 0``, or NaN), or where ``c0`` / ``c1`` are not
    finite or the fit would not focus (``c1 >= 0``). Computed in float64. Returns ``(g_fit, q_fit)``, (S,) each:
    ``c0`` (the slope ``g`` of ``w_G``) and ``c1`` (its curvature ``q``, mm)."""
    u, t, ok = np.asarray(u), np.asarray(t), np.asarray(ok, dtype=bool)
    g = np.asarray(g, dtype=np.float64)
    q = np.asarray(q, dtype=np.float64)
    if u.ndim != 2 or u.shape != t.shape or u.shape != ok.shape or g.shape != u.shape[:1] or q.shape != g.shape:
        raise ValueError(f"fit_quadratic_transfers: u, t, ok must be (S, P) arrays alike and g, q (S,), got "
                         f"{u.shape}, {t.shape}, {ok.shape}, {g.shape}, {q.shape}")
    n = ok.sum(axis=1)
    nz = np.maximum(n, 1)
    wide = len(n) >= FIT_WIDE
    pts = 0 if wide else 1          # the points' axis
    if wide:                        # points first, (P, S) contiguous: every sum one row-after-row reduction
        u, t, ok = (np.ascontiguousarray(x.T) for x in (u, t, ok))

        def ssum(x):
            return np.add.reduce(x, axis=0)

        def col(v):
            return v[None, :]
    else:                           # few sources: (S, P), each row's running sum
        def ssum(x):
            return np.cumsum(x, axis=1)[:, -1]

        def col(v):
            return v[:, None]
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        U = np.where(ok, u, -0.0).astype(np.float64, copy=False)   # padding: -0.0, seen by no sum
        T = np.where(ok, t, -0.0).astype(np.float64, copy=False)
        spread = np.max(np.where(ok, U, -np.inf), axis=pts, initial=-np.inf) - \
            np.min(np.where(ok, U, np.inf), axis=pts, initial=np.inf)
        mu = ssum(U) / nz
        mt = ssum(T) / nz
        U -= col(mu)
        T -= col(mt)
        T *= U
        U *= U
        suu = ssum(np.where(ok, U, -0.0))
        sut = ssum(np.where(ok, T, -0.0))
        c1 = sut / suu
        c0 = mt - c1 * mu
    good = (n >= 3) & (spread > 0) & np.isfinite(c0) & np.isfinite(c1) & (c1 < 0)
    return np.where(good, c0, g), np.where(good, c1, q)


def fit_quadratic_transfer(freqs, landings, points, f_c, g, q, distance_mm):
    """The separable quadratic transfer that best matches a beam's straight-ray landings (least squares).

    The focal method (:mod:`rwwarp.wave.focal`) splits the angular-spectrum transfer ``exp(2 pi i z w(f))`` into
    a separable quadratic part ``w_G(f) = w_c + g.(f - f_c) + sum_a q_a (f_a - f_c,a)^2 / 2`` and an exact
    remainder. Any ``g`` and (negative) ``q`` keep the split exact; they only decide how far the remainder
    moves light, ``z |grad w(f) - g - q (f - f_c)|``, and so how wide the sensor-side box must be. The Taylor
    choice at ``f_c`` leaves the cubic term of ``w`` (159 um on the Cooke triplet at 14 deg); fitting
    ``-grad w = (L - x) / z`` over the beam's rays per axis (``L``: exact landings (mm), ``x``: wave-plane points
    (mm), ``f``: frequencies (cycles/mm), lists over the kept orders; ``f_c`` (2,) cycles/mm, ``distance_mm``
    ``z``) halves it or better. Falls back to the Taylor values ``g, q`` ((2,) each; dimensionless and mm)
    where the fit is degenerate or would not focus (``q >= 0``). One source of
    :func:`fit_quadratic_transfers` (the same bits as in any batch of them). Returns ``(g, q)``."""
    f = np.concatenate(freqs) - f_c
    t = np.concatenate([(x - L) / distance_mm for L, x in zip(landings, points)])      # = grad w(f)
    g, q = np.asarray(g, dtype=np.float64), np.asarray(q, dtype=np.float64)
    ok = np.ones((1, len(f)), dtype=bool)
    out = [fit_quadratic_transfers(f[None, :, a], t[None, :, a], ok, g[a:a + 1], q[a:a + 1]) for a in range(2)]
    return np.array([out[0][0][0], out[1][0][0]]), np.array([out[0][1][0], out[1][1][0]])


def _order_index(m):
    """A diffraction order's index: an int for the integer orders of a wrapped relief, the float ``alpha``
    for the single exact term of a relief that does not wrap inside the beam."""
    return int(m) if float(m) == int(m) else float(m)


FOCAL_SHIFT_MARGIN = 1.5   # sensor-side margin in units of the remainder's largest displacement
FOCAL_PITCH_FACTOR = 3.0   # wave-plane period of the focal sum, in nyquist_safety x sensor-side boxes
FOCAL_TAPER_GUARD = 1.5    # V kept whole within this many remainder displacements (+ 3 / B) of the patch
FOCAL_SPREAD = 2.0         # wave-plane period over the spread of all kept orders' light, per nyquist_safety
FOCAL_MAIN_SPREAD = 3.0    # ... over the main order's (most of the power: its copies alias more)
FOCAL_RIM_RAYS = 400       # least rays across the pupil (where the wave-plane grid has that many samples)
FOCAL_EDGE_SPREAD = 12.0   # wave-plane period over the main order's spread with straight pupil edges, per safety
FOCAL_EDGE_ALL_SPREAD = 6.0  # ... over the spread of every kept order's light (weaker: fewer of their tails alias)
FOCAL_MARGIN_B = 6.0       # sensor-side margin beyond the patch and the remainder's displacement, in 1 / B
FOCAL_EDGE_MARGIN_B = 12.0 # ... with straight pupil edges (their 1 / r tails ring from a nearer cut)
FOCAL_RAY_SPREAD = 14.0    # wave-plane period over the main order's straight-ray landing extent, per nyquist_safety
FOCAL_RAY_MAX_GRID = 2048  # ... while the wave-plane grid stays within this many samples a side
#: where the cap binds, the rim's sampling error grows as (wanted period / planned period)^FOCAL_RAY_CAP_POWER from the
#: rules' ~SAMPLING_TOL: fitted on the Cooke triplet 5 mm defocused (0.532 um, on axis, 16 px of 5 um; against
#: rs_lens_psf, converged to 1e-10): 7.7e-3 / 1.4e-3 / 2.5e-4 of the peak at a wanted/planned ratio 4.25 / 2.13 / 1.06
#: (grids of 2258 / 4097 / 8193 samples) against 7.4e-3 / 1.3e-3 / 2.3e-4 by this law (2: 3.6e-3 / 9.1e-4 / 2.2e-4);
#: checked on the Cooke with a 10 % weaker front curvature (ratio 3.55, 4509^2 planned: 3.4e-3 by self-convergence
#: against 3x the period, 4.8e-3 by this law)
FOCAL_RAY_CAP_POWER = 2.5
#: with a ``tolerance``, the cap gives way up to this many samples a side (a complex128 grid of 4 GiB; the plan's memory
#: estimate is then checked against the budget like any other)
FOCAL_RAY_TOL_MAX_GRID = 16384
#: without a ``tolerance``, a capped plan warns (:class:`SamplingWarning`) where its estimated rim error exceeds this
FOCAL_RAY_CAP_WARN = 1e-3
FOCAL_LIT_SHIFT_MARGIN = 3.0  # FOCAL_SHIFT_MARGIN where the main order's rays land beyond V's taper guard (lit taper)
#: the sampling error (max |error| / peak) the focal rules above were set for: issue 27's target for refractive
#: lenses, 2e-4 (measured against rs_lens_psf: 2e-5..1.5e-4 of the peak, tests/rwwarp/test_focal.py)
SAMPLING_TOL = 2e-4
#: the share of a requested ``tolerance`` that the focal plan's sampling may spend (the rest is the model's own): a
#: tenth, so that a tolerance up to 2e-3 keeps the default plan (tolerance=1e-3, the wave step's usual request, included)
SAMPLING_SHARE = 0.1
#: how far a requested tolerance relaxes the accuracy-driven focal rules at most (their error was measured up to
#: here: perf/results/map_ab_cpu_session24/README.md)
SAMPLING_RELAX_MAX = 16.0
#: the relaxed plan's error grows as relax^SAMPLING_RELAX_POWER (measured on the A489's worst beam of the 10 x 10 x 3
#: map, 14.3 deg at 0.45 um, 32 px, against a converged plan: 1.3e-4, 3.5e-4, 1.1e-3, 2.8e-3 of the peak at relax 1,
#: 2, 4, 8: exponent 1.45)
SAMPLING_RELAX_POWER = 1.5


def sampling_relax(tolerance) -> float:
    """How much coarser than its default the focal plan's accuracy-driven rules may sample for a requested
    ``tolerance`` (max |error| / peak, or None): the relaxation whose error, ``SAMPLING_TOL x
    relax^SAMPLING_RELAX_POWER``, is the sampling's share of it, ``SAMPLING_SHARE x tolerance``; between 1 (the
    default rules; None gives 1) and ``SAMPLING_RELAX_MAX``. Dimensionless. The rules it relaxes
    (:func:`focal_plan_from`): the main order's ray-landing period ``FOCAL_RAY_SPREAD`` (the rim's cell phase,
    error ~ 1 / period^2: divided by ``sqrt(relax)``) and the rim's ray count ``FOCAL_RIM_RAYS`` (error first
    order in the ray pitch: divided by ``relax``); from ``LIT_RELAX`` on a lit taper's margin
    (:func:`lit_shift_margin`), and the pixel integration's bound (:func:`gauss_tol`). The aliasing rules (spreads,
    the sensor-side pitch, the 1 / B margins) and ``nyquist_safety`` stay (the A489's corner beam erred 1.3e-4 /
    2.0e-4 / 3.9e-2 of the peak at safety 2 / 1.5 / 1: not a smooth law)."""
    if tolerance is None:
        return 1.0
    t = float(tolerance)
    if not (t > 0 and math.isfinite(t)):
        raise ValueError(f"sampling_relax: tolerance must be a positive number or None, got {tolerance!r}")
    return min(max((SAMPLING_SHARE * t / SAMPLING_TOL) ** (1.0 / SAMPLING_RELAX_POWER), 1.0), SAMPLING_RELAX_MAX)


#: from this relaxation on (:func:`sampling_relax`) a lit taper's sensor-side margin is FOCAL_SHIFT_MARGIN displacements
#: (its 3 displacements took a BK7 singlet at 40 deg from 2.7e-4 to 5.4e-5 of the peak, a budget of >= 8e-4 holds it)
LIT_RELAX = 4.0


def lit_shift_margin(tolerance) -> float:
    """The sensor-side margin (in the remainder's largest displacements) where the main order's rays land beyond
    ``V``'s taper guard, for a requested ``tolerance`` (or None): ``FOCAL_LIT_SHIFT_MARGIN`` unless
    :func:`sampling_relax` reaches ``LIT_RELAX``, then ``FOCAL_SHIFT_MARGIN`` (the unlit margin)."""
    return FOCAL_SHIFT_MARGIN if sampling_relax(tolerance) >= LIT_RELAX else FOCAL_LIT_SHIFT_MARGIN


#: the pixel integration's error bound (:func:`rwwarp.wave.sensor_grid.auto_gauss_nodes`) of the default plan
GAUSS_TOL = 1e-7


def gauss_tol(tolerance) -> float:
    """The error bound (relative, dimensionless) the automatic pixel integration keeps for a requested
    ``tolerance`` (max |error| / peak, or None): ``GAUSS_TOL`` (1e-7) by default, else ``SAMPLING_TOL x
    sampling_relax(tolerance)`` where that relaxes. The bound (the highest intensity frequency's
    Gauss-Legendre remainder, unit amplitude) exceeds the measured error by 100-1000x on the A489's beams (32 px,
    against 10 nodes: 3 nodes 4.4e-6..7.1e-5 of the peak where the bound reads 3.8e-3..3.5e-2; 4 nodes <= 1.4e-6)."""
    r = sampling_relax(tolerance)
    return GAUSS_TOL if r == 1.0 else max(GAUSS_TOL, SAMPLING_TOL * r)


def plan_focal(xy, freq, doe_freq, orders, centers, carrier, inv_lam, distance_mm, width_mm, size, pixel_mm,
               rays_per_sample, nyquist_safety, order_tol=1e-8, patch_tol=1e-5, straight_edges=False,
               sampling_tol=None):
    """Sampling of the focal propagation (:mod:`rwwarp.wave.focal`) for one batch, from a pilot trace.

    Per source ``k``: ``xy[k]`` (N, 2) wave-plane points of the pilot rays (mm), ``freq[k]`` (N, 2) their
    transverse frequencies before the DOE (cycles/mm), ``doe_freq[k]`` (N, 2) the DOE's
    ``grad(phi0) / (2 pi)`` there or None, ``orders[k]`` a list of ``(m, c_m)`` DOE orders,
    ``centers`` (S, 2) patch centres T, ``carrier`` (S, 2) the chief frequency ``f_c`` after the main
    order, ``inv_lam`` (S,) ``n / lambda`` (1/mm). ``width_mm``: beam footprint on the wave plane.

    Rules (each recorded in the plan's reasons):

    * an order is computed iff it carries ``|c_m|^2 >= order_tol``, the bounding box of its pilot
      rays' landing points comes within a diffraction margin of the patch, and the share of its power
      that box puts on the patch (by area) is at least ``patch_tol``; the others' power is reported as
      leaving the patch;
    * the quadratic part of the transfer is fitted to the kept rays (:func:`fit_quadratic_transfer`),
      which halves the remainder's displacement off axis;
    * the sensor-side grid covers the patch widened by the remainder's largest displacement (``H_R`` moves
      light no farther, so only this part of ``V`` can reach the patch), plus a margin of ``FOCAL_MARGIN_B / B``
      (``B``: the beam's largest frequency offset from ``f_c``, so ~12 Airy radii; ``FOCAL_EDGE_MARGIN_B / B``
      with ``straight_edges``) and ``FOCAL_SHIFT_MARGIN`` times
      the displacement; its pitch samples ``B`` ``nyquist_safety`` times above Nyquist; ``V`` is tapered to
      zero between the patch widened by ``FOCAL_TAPER_GUARD`` displacements plus ``3 / B`` and the grid's edge
      (``taper_guard_mm``, :func:`rwwarp.wave.focal.sensor_taper`);
    * the wave-plane pitch sets the period of the generalised-Fresnel sum, ``1 / (|A| pitch)`` (``|A| ~ n /
      (lambda z)``): ``nyquist_safety`` times the largest of ``FOCAL_PITCH_FACTOR`` sensor-side grids (the
      cell-phase error near the patch), ``FOCAL_MAIN_SPREAD`` times the spread of the main order's landing
      points under the quadratic transfer and ``FOCAL_SPREAD`` times that of every kept order's (aliasing);
      with ``straight_edges`` (a square pupil) ``FOCAL_EDGE_SPREAD`` times the main order's spread and
      ``FOCAL_EDGE_ALL_SPREAD`` times every kept order's: the patch's
      space-bandwidth product, not the beam's; and at least ``FOCAL_RAY_SPREAD x nyquist_safety`` times the
      extent of the main order's straight-ray landings (an aberrated spot: the rim's phase slope per cell),
      as far as a wave-plane grid of ``FOCAL_RAY_MAX_GRID`` samples a side (the reasons say where it is capped);
    * where the main order's rays land beyond ``V``'s taper guard (a spot wider than the patch lights the
      taper), the sensor-side margin takes ``FOCAL_LIT_SHIFT_MARGIN`` displacements instead of
      ``FOCAL_SHIFT_MARGIN`` (``geometry["lit_taper"]`` per source; ``method="auto"`` then takes the focal path);
    * rays: ``rays_per_sample x max(min(samples, FOCAL_RIM_RAYS), samples / 4)`` across the footprint
      (``samples``: wave-plane samples across it).

    Returns ``(plan, geometry)``; ``geometry`` has ``sensor_origin`` (S, 2), ``orders`` (the kept
    ``(m, c_m)`` per source), ``lost_power`` (S,), the fraction in dropped orders, ``transfer``, the
    fitted ``(g, q)`` (S, 2) each, and ``taper_guard_mm``, for :class:`rwwarp.wave.focal.FocalPropagator`.
    """
    from .focal import transfer_curvature
    S = len(xy)
    z = float(distance_mm)
    half_w = 0.5 * size * pixel_mm
    w_c, g, q = transfer_curvature(carrier, inv_lam)
    mb = FOCAL_EDGE_MARGIN_B if straight_edges else FOCAL_MARGIN_B   # sensor-side margin, in 1 / B
    boxes, kept, lost, bands, shifts = [], [], np.zeros(S), np.zeros(S), np.zeros(S)
    g_fit, q_fit = g.copy(), q.copy()
    spread = spread_main = 0.0   # the light's extent at the sensor under the quadratic transfer (all, main order)
    ray_spread = 0.0             # the main order's straight-ray landing extent (the geometric spot, no margins)
    lit = np.zeros(S, dtype=bool)  # per source: the main order's rays land beyond the taper guard
    lit_margin = lit_shift_margin(sampling_tol)
    for k in range(S):
        T = centers[k]
        main_m, main_c = max(orders[k], key=lambda mc: abs(mc[1]))
        live = []
        for m, c in orders[k]:
            if abs(c) ** 2 < order_tol:
                lost[k] += abs(c) ** 2
                continue
            live.append((m, c))
        # every live order at once ((M, N, 2) arrays; elementwise, max and min: the values of one order at a time):
        # its frequencies, landings, landing box, band, whether it misses the patch and its share of the patch
        band = 1e-9
        if live:
            if doe_freq[k] is not None:   # m * doe_freq in doe_freq's precision, as a Python number multiplies it
                ms = np.array([m for m, _ in live], dtype=np.asarray(doe_freq[k]).dtype)[:, None, None]
                F = freq[k][None] + ms * doe_freq[k][None]
            else:
                F = freq[k][None] + np.zeros((len(live), 1, 1), dtype=np.asarray(freq[k]).dtype)   # freq + 0.0
            Ls = landing_points(xy[k], F, inv_lam[k], z)
            full = np.isfinite(Ls).all(axis=2).all(axis=1)
            LLO, LHI = Ls.min(axis=1), Ls.max(axis=1)
            o_band = np.max(np.abs(F - carrier[k]), axis=(1, 2))
            for j in np.flatnonzero(~full):
                # an order some of whose rays do not land (evanescent): its landing rays' box and band
                ok = np.isfinite(Ls[j]).all(axis=1)
                if ok.any():
                    LLO[j], LHI[j] = Ls[j][ok].min(0), Ls[j][ok].max(0)
                    o_band[j] = np.max(np.abs(F[j][ok] - carrier[k]))
            landed = full | np.isfinite(Ls).all(axis=2).any(axis=1)
            if landed.any():
                band = max(band, float(np.max(o_band[landed])))
        margin = mb / band
        keep, used, lo, hi = [], [], T - half_w, T + half_w
        main_box = None
        if live:
            miss = np.any(LLO > T + half_w + margin, axis=1) | np.any(LHI < T - half_w - margin, axis=1)
            reach = np.prod(np.minimum(LHI - LLO, 2 * (half_w + margin)) + 1e-12, axis=1)
            area = np.prod(LHI - LLO + 1e-12, axis=1)
        for j, (m, c) in enumerate(live):
            if not landed[j]:
                lost[k] += abs(c) ** 2
                continue
            if miss[j]:
                lost[k] += abs(c) ** 2      # every ray of this order misses the patch
                continue
            # a strongly defocused order spreads its power over its landing box: estimate the share that
            # reaches the patch by area; below patch_tol it is left out (a uniform background of that power
            # over the patch changes a focused core by ~2 sqrt(patch_tol / pixels), < 1e-4 at 1e-5 and 64
            # pixels), and its power is reported
            share = float(reach[j]) / float(area[j])
            if m != main_m and abs(c) ** 2 * share < patch_tol:
                lost[k] += abs(c) ** 2
                continue
            keep.append((_order_index(m), complex(c)))
            if full[j]:   # every ray lands (the usual case): the arrays themselves, else the landing rays'
                used.append((j, F[j], Ls[j], xy[k], m == main_m))
            else:
                ok = np.isfinite(Ls[j]).all(axis=1)
                used.append((j, F[j][ok], Ls[j][ok], xy[k][ok], m == main_m))
            if m == main_m:
                ray_spread = max(ray_spread, float(np.max(LHI[j] - LLO[j])))
                main_box = (LLO[j], LHI[j])
        if used:
            g_fit[k], q_fit[k] = fit_quadratic_transfer([u[1] for u in used], [u[2] for u in used],
                                                        [u[3] for u in used], carrier[k], g[k], q[k], z)
        mlo, mhi = lo.copy(), hi.copy()
        whole = [u for u in used if full[u[0]]]
        if whole:
            # the kept orders whose every ray lands, at once: landings under the quadratic transfer
            idx = [u[0] for u in whole]
            LG = xy[k][None] - z * (g_fit[k] + (F[idx] - carrier[k]) * q_fit[k])
            shifts[k] = max(shifts[k], float(np.max(np.abs(Ls[idx] - LG))))
            lo = np.minimum(lo, LG.min(axis=(0, 1)))
            hi = np.maximum(hi, LG.max(axis=(0, 1)))
            for i, u in enumerate(whole):
                if u[4]:
                    mlo, mhi = np.minimum(mlo, LG[i].min(0)), np.maximum(mhi, LG[i].max(0))
        for j, f, L, x, main in used:
            if full[j]:
                continue
            lg = x - z * (g_fit[k] + (f - carrier[k]) * q_fit[k])       # landing under the quadratic transfer
            d = float(np.max(np.abs(L - lg)))
            shifts[k] = max(shifts[k], d)
            lo = np.minimum(lo, lg.min(0))
            hi = np.maximum(hi, lg.max(0))
            if main:
                mlo, mhi = np.minimum(mlo, lg.min(0)), np.maximum(mhi, lg.max(0))
        if not keep:  # nothing reaches the patch: keep the main order so the (dark) patch is computed
            keep.append((_order_index(main_m), complex(main_c)))
            lost[k] -= abs(main_c) ** 2
        # the quadratic model's field has tails as wide as the remainder's displacement, and H_R carries the
        # box's cut edge that far: the margin grows with it (measured on the Cooke triplet at 14 deg against
        # rs_lens_psf, fitted transfer, 95 um shift, 16 px: 1.25e-4, 8.7e-5, 6.6e-5 at 1, 1.5, 2 shifts)
        # an aberrated spot wider than the guard lights V where it is tapered: the taper's own spectrum (~ 1 /
        # its width, beyond the beam's band, where H_R moves light farther than `shifts`) then reaches the
        # patch. A BK7 singlet at 40 deg (16 px, the period of FOCAL_RAY_SPREAD), against rs_lens_psf: 2.7e-4 /
        # 5.4e-5 of the peak with 1.5 / 3 displacements of margin (6 / B -> 9 / B instead: 5.1e-5); the A489 at
        # 10 deg and the singlet at 35 deg moved by < 20 %. The wider margin is taken only where the rays light it.
        guard = half_w + FOCAL_TAPER_GUARD * shifts[k] + 3.0 / band
        if used and main_box is not None:
            lit[k] = bool(np.any(main_box[0] < T - guard) or np.any(main_box[1] > T + guard))
        margin_k = margin + (lit_margin if lit[k] else FOCAL_SHIFT_MARGIN) * shifts[k]
        lo = np.minimum(lo, T - half_w - shifts[k]) - margin_k
        hi = np.maximum(hi, T + half_w + shifts[k]) + margin_k
        # V is computed only near the patch: the remainder moves light at most shifts[k], so what lies farther
        # (defocused DOE orders, the aberrated quadratic-model spot) cannot reach it, and the taper keeps its
        # cut edge from ringing. Its whole spread still sets the period (aliasing), below.
        spread = max(spread, float(np.max(hi - lo)))
        spread_main = max(spread_main, float(np.max(mhi - mlo)) + 2.0 * margin_k)
        lo, hi = T - half_w - shifts[k] - margin_k, T + half_w + shifts[k] + margin_k
        boxes.append((lo, hi))
        kept.append(keep)
        bands[k] = band
    return focal_plan_from(boxes, kept, lost, bands, shifts, g_fit, q_fit, lit, spread, spread_main, ray_spread,
                           z, half_w, mb, width_mm, rays_per_sample, nyquist_safety, straight_edges,
                           sampling_tol=sampling_tol)


def capped_rim_error(want_mm: float, period_mm: float, relax: float = 1.0) -> float:
    """The estimated sampling error (max |error| / peak) of a focal plan whose ray-landing period was capped:
    ``want_mm`` the period the rules ask for, ``period_mm`` the one planned (both mm on the sensor side, the
    periodic sum's period); the rules' error (``SAMPLING_TOL``, times ``relax^SAMPLING_RELAX_POWER`` for a relaxed
    plan) grown by ``(want / period)^FOCAL_RAY_CAP_POWER``."""
    base = SAMPLING_TOL * relax ** SAMPLING_RELAX_POWER
    return base * (float(want_mm) / float(period_mm)) ** FOCAL_RAY_CAP_POWER


def focal_plan_from(boxes, kept, lost, bands, shifts, g_fit, q_fit, lit, spread, spread_main, ray_spread, z, half_w,
                    mb, width_mm, rays_per_sample, nyquist_safety, straight_edges, sampling_tol=None):
    """The last part of :func:`plan_focal`: its grids, reasons and geometry from the per-source results of its
    loop (``boxes``: the sensor-side boxes ``(lo, hi)`` (2,) mm; ``kept`` orders, ``lost`` power, ``bands``
    cycles/mm, ``shifts`` mm, the fitted transfer ``g_fit`` / ``q_fit`` (S, 2), ``lit`` (S,) bool; ``spread``,
    ``spread_main``, ``ray_spread`` mm over the sources; ``z`` mm, ``half_w`` mm the patch's half width, ``mb``
    the margin in 1 / B). Also used by :mod:`rwwarp.wave.focal_sources` (many sources, each its own plan).
    ``sampling_tol``: the caller's ``tolerance`` (max |error| / peak) or None; above ``SAMPLING_TOL / SAMPLING_SHARE``
    it relaxes the ray-landing period and the rim's ray count (:func:`sampling_relax`), else the default rules."""
    relax = sampling_relax(sampling_tol)
    lit_margin = lit_shift_margin(sampling_tol)
    A = np.abs(1.0 / (z * q_fit))
    box = max(float(np.max(hi - lo)) for lo, hi in boxes)

    hs = 1.0 / (2.0 * nyquist_safety * float(np.max(bands)))
    ns = int(math.ceil(box / hs)) + 2
    room = 2.0 * float(np.max(shifts)) + mb / float(np.min(bands))
    nf = nice_fft_length(ns + int(math.ceil(room / hs)))
    sensor_origin = np.array([0.5 * (lo + hi) - 0.5 * (ns - 1) * hs for lo, hi in boxes])
    # the wave-plane pitch: the sum is periodic over 1 / (|A| pitch). Near the patch the splatted field, a cell
    # average weighted by the kernel at the cell centre, errs with the kernel's phase slope across a cell, so
    # the period is FOCAL_PITCH_FACTOR x nyquist_safety sensor-side grids (Cooke triplet, 16 px, against
    # rs_lens_psf: 14 deg 1.3e-4 / 6.5e-5 and on axis 1.5e-4 / 6.6e-5 at 2 x 2 / 3 x 2 grids); and it clears
    # the spread of the light, its periodic copies must miss the patch: 3 x safety spreads of the main order
    # (A489 at 10 deg: 1.1e-3 / 5.8e-4 at 2 / 3), 2 x of the weaker ones. A straight pupil edge's
    # diffraction falls off as 1 / r (a round one's as r^-3/2), so its copies reach the patch with more (the
    # aliased share falls as 1 / period^2): the period is FOCAL_EDGE_SPREAD spreads of the main order and
    # FOCAL_EDGE_ALL_SPREAD of all kept orders per nyquist_safety (a thin
    # lens + square DOE 20 mm before the sensor, 16 px, against rs_thin_lens_psf: 3.7e-4 / 1.5e-4 / 7.5e-5
    # at 12 / 18 / 24 spreads with a 6 / B sensor-side margin; with 12 / B, the default, 5.1e-5 / 1.5e-5 at 12 /
    # 24 spreads, and at 24 spreads 1.2e-5 / 1.0e-5 at 24 / 32 px, 1.5e-6 / 2.4e-5 for a weaker / stronger DOE,
    # where 12 spreads gave 3.0e-4 for the stronger one).
    if straight_edges:
        period = max(FOCAL_EDGE_SPREAD * spread_main, FOCAL_EDGE_ALL_SPREAD * spread) * nyquist_safety
    else:
        period = max(FOCAL_PITCH_FACTOR * box, FOCAL_MAIN_SPREAD * spread_main, FOCAL_SPREAD * spread) * nyquist_safety
    # an aberrated beam (a geometric spot many Airy radii wide, the patch inside it): near the pupil's rim the field's
    # phase slope relative to the reference wave is 2 pi A (L - T) (L: where the rim's rays land), so a wave-plane
    # cell spans pi |L - T| / period rad of it there. The rim cells' sum (the hard edge, partly covered cells, the
    # kernel taken at the cell centre) errs as the square of that phase (measured against rs_lens_psf, 16 px, the
    # error / peak falls as 1 / period^2: A489 at 10 deg 8.1e-4 / 3.1e-4 / 1.7e-4 and a BK7 singlet at 35 deg 6.9e-4 /
    # 3.2e-4 / 1.9e-4 at 1 / 1.5 / 2 x the period of the rules above; shifting the grid by half a cell or
    # doubling the rays leaves it, a smooth window that takes the rim away removes 97 % of it). The period is
    # therefore at least FOCAL_RAY_SPREAD x safety landing extents of the main order's rays: ~0.11 rad per cell
    # at the rim. A focused beam's landing extent is a few Airy radii, and the rules above already exceed it.
    # It may grow the wave-plane grid to FOCAL_RAY_MAX_GRID samples a side, no further: a strongly defocused beam
    # (the Cooke triplet with its front curvature 10 % weaker, a design mid-optimisation: a 1.4 mm spot about a
    # 60 um patch) would ask for 16026^2 samples (90 GiB with gradients) where the rules above plan 4509^2; its
    # own error there, 3.4e-3 of the peak against 3 x the period (self-convergence), is stated in the reasons.
    window_mm = width_mm + 2.0 * width_mm / 31.0
    ray_factor = FOCAL_RAY_SPREAD if relax == 1.0 else FOCAL_RAY_SPREAD / math.sqrt(relax)
    rim_rays = FOCAL_RIM_RAYS if relax == 1.0 else FOCAL_RIM_RAYS / relax
    want = ray_factor * ray_spread * nyquist_safety
    cap = max(period, (FOCAL_RAY_MAX_GRID - 3) / (window_mm * float(np.max(A))))
    if want > cap and sampling_tol is not None:
        # the caller asked for an accuracy: the cap gives way, as far as FOCAL_RAY_TOL_MAX_GRID samples, to the period
        # whose estimated rim error (capped_rim_error) meets the tolerance (or the default rules' error, if tighter)
        rules = capped_rim_error(1.0, 1.0, relax)        # the rules' own error (the period they ask for)
        target = max(float(sampling_tol), rules)
        need = want * (rules / target) ** (1.0 / FOCAL_RAY_CAP_POWER)
        cap = max(cap, min(need, (FOCAL_RAY_TOL_MAX_GRID - 3) / (window_mm * float(np.max(A)))))
    ray_capped = want > cap
    period = max(period, min(want, cap))
    rim_err = capped_rim_error(want, period, relax) if ray_capped else None
    pitch = 1.0 / (float(np.max(A)) * period)
    window = width_mm + 2.0 * width_mm / 31.0
    n_grid = int(math.ceil(window / pitch)) + 3
    # (1e-9: a cap lifted for the tolerance meets it exactly)
    if rim_err is not None and rim_err > (FOCAL_RAY_CAP_WARN if sampling_tol is None else float(sampling_tol)) * (1 + 1e-9):
        warnings.warn(f"focal plan: the main order's rays land over {ray_spread * 1e3:.4g} um (a defocused or strongly "
                      f"aberrated beam); their period {want * 1e3:.4g} um is capped at {n_grid} wave-plane "
                      f"samples ({period * 1e3:.4g} um), so the pupil rim's sampling error is ~{rim_err:.2g} of the peak "
                      f"(the default rules' ~{SAMPLING_TOL:g}; "
                      f"{'the tolerance ' + format(float(sampling_tol), '.3g') if sampling_tol is not None else 'warned above ' + format(FOCAL_RAY_CAP_WARN, 'g')}). "
                      "The error follows the spread of the ray landings, not the patch: refocus, or accept it (the "
                      "plan's reasons carry the estimate)", SamplingWarning, stacklevel=2)
    # rays: the splat is first order across a tube (its phase slope), so a tube may span several samples
    # (Cooke triplet, 14 deg, 64 px, against the stored truth: 2.14e-5 / 2.22e-5 / 2.37e-5 at samples / 2, 3,
    # 4 rays across); the pupil rim's error is first order in the ray pitch (on axis, 16 px: 1.5e-4 / 6.6e-5
    # at 179 / 357 rays across), so at least FOCAL_RIM_RAYS rays cross the pupil where the grid has that many
    samples = width_mm / pitch
    ray_grid = int(math.ceil(rays_per_sample * max(min(samples, rim_rays), samples / 4))) + 1
    reasons = (
        "focal propagation: reference wave to the patch centre handled analytically (rwwarp.wave.focal)",
        f"DOE orders computed: {sorted({m for kk in kept for m, _ in kk})}; power in orders that miss the patch: "
        f"{float(np.max(lost)):.3g}",
        f"sensor-side box {box * 1e3:.4g} um (patch {2 * half_w * 1e3:.4g} um, H_R shift {np.max(shifts) * 1e3:.3g} um, "
        f"margin {mb:g}/B + {lit_margin if lit.any() else FOCAL_SHIFT_MARGIN:g} shift{' (rays land in the taper)' if lit.any() else ''} = {mb * 1e3 / np.min(bands) + (lit_margin if lit.any() else FOCAL_SHIFT_MARGIN) * 1e3 * np.max(shifts):.3g} um) at {hs * 1e3:.4g} um (band B = {np.max(bands):.4g} cycles/mm, "
        f"safety {nyquist_safety}) -> {ns}^2, FFT {nf}^2",
        f"wave-plane pitch 1 / (|A| period), period {period * 1e3:.4g} um (light spread {spread * 1e3:.4g} um, main order's ray landings {ray_spread * 1e3:.4g} um{f' (their period {want * 1e3:.4g} um capped at {n_grid} samples: the rim errs by ~{rim_err:.2g} of the peak, FOCAL_RAY_CAP_POWER)' if ray_capped else ''}{', straight pupil edges' if straight_edges else ''}) = {pitch * 1e3:.4g} um over the footprint "
        f"{width_mm:.4g} mm -> {n_grid}^2 samples (quadratic transfer fitted to the beam: H_R shift "
        f"{np.max(shifts) * 1e3:.3g} um)",
        f"rays: {rays_per_sample} x max(min(samples, {rim_rays:.4g}), samples / 4) -> {ray_grid} across the pupil",
    ) + ((f"sampling for the tolerance {float(sampling_tol):.3g}: ray-landing period {ray_factor:.3g} x safety "
          f"landing extents, {rim_rays:.4g} rim rays, a lit taper's margin {lit_margin:g} shifts, pixel integration "
          f"bound {gauss_tol(sampling_tol):.3g} (relaxed {relax:.3g}x: the sampling error ~{SAMPLING_TOL:g} x "
          f"{relax:.3g}^{SAMPLING_RELAX_POWER:g} = {SAMPLING_TOL * relax ** SAMPLING_RELAX_POWER:.2g} of the peak, "
          f"SAMPLING_SHARE {SAMPLING_SHARE:g} of the tolerance or less)",) if relax > 1.0 else ())
    plan = Plan(pitch, n_grid, nf, ray_grid, "auto", False, reasons, "focal", hs, ns, nf)
    centre = np.array([0.5 * (lo + hi) for lo, hi in boxes])
    return plan, {"sensor_origin": sensor_origin, "sensor_center": centre, "orders": kept, "lost_power": lost,
                  "lit_taper": lit,
                  "transfer": (g_fit, q_fit),
                  # V whole within 1.5 shifts + 3 / B of the nodes (AC254, 16 px, against rs_lens_psf: 7.7e-5 at 1
                  # shift, 3.0e-5 at 1.5), tapered over the rest of the margin
                  "taper_guard_mm": FOCAL_TAPER_GUARD * float(np.max(shifts)) + 3.0 / float(np.min(bands))}


def auto_sizes(need_pitch, width, feature, out_width, rays_per_sample):
    """Adaptive band-limited ASM plan sizes for a beam footprint ``width`` (mm) that needs a pitch <=
    ``need_pitch`` (mm):
    ``(pitch_mm, n_grid, n_pad, ray_grid)``. ``feature``: DOE pixel size (mm) or None; ``out_width``:
    sensor patch width (mm)."""
    pitch = need_pitch
    if feature is not None:
        # align the grid with DOE pixels: an integer number of samples per feature
        pitch = feature / math.ceil(feature / pitch)
    window = width + 2.0 * width / 31.0  # footprint + 2 pilot cells (31-ray pilot grid)
    n_grid = int(math.ceil(window / pitch)) + 3
    # the shifted band limit needs L >= window + patch; measured (perf/README): tight padding leaves
    # 1e-3..5e-3 errors from the band-limit edges, 2x padding brings them to ~2e-4
    n_pad = nice_fft_length(max(2 * n_grid, math.ceil(1.05 * (n_grid * pitch + out_width) / pitch) + 4))
    ray_grid = int(math.ceil(rays_per_sample * width / pitch)) + 1
    return pitch, n_grid, n_pad, ray_grid
