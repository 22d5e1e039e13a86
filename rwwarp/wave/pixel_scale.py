"""Pixels much larger than the diffraction scale (issue 27 item 5): ``method="pixel"``.

When a sensor pixel spans many Airy radii (``r_A = 0.61 / B``, ``B`` the beam's largest transverse frequency
offset from the chief ray's, cycles/mm), the focal and ASM methods still sample the wave at the diffraction
scale over the whole beam and then integrate each pixel with Gauss-Legendre nodes; their cost grows with the
patch's and the beam's space-bandwidth products together (EF50 f/1.8, 15.3 um pixels, 64 px: 0.4-16 TFLOP).
This method's cost follows the patch at the field's own Nyquist rate and the rays the aberrations need.

The method (scalar, the same ray picture as the other methods, propagation in the image medium):

1. **The sensor field as a sum of plane waves, one per ray tube (Debye).** Behind the last surface every
   ray is a local plane wave of transverse frequency ``f = n d_xy / lambda`` (cycles/mm). The sensor-plane
   field near the patch centre ``T`` is ``U(x) = int B(f) exp(2 pi i f.(x - T)) d^2 f``; by stationary phase
   of the wave-plane field's Fourier transform, ``B`` at a ray's frequency has the ray's phase continued to
   the foot of ``T`` on it, ``Phi = k0 (L + n d.(T - p))`` (``L``: optical path to the ray's point ``p`` on
   the last surface, ``k0 = 2 pi / lambda``), and ``|B|^2 c(f) dA_f = q`` (the ray's power ``q`` over its
   tube's area ``dA_f`` in frequency; ``c = d_z``, the obliquity, for ``pixel_values="flux"``; 1 for
   ``"intensity"``). The integral is the quadrature over the pupil grid's tubes,
   ``U(x) = sum_j sqrt(q_j dA_f,j / c_j) exp(i Phi_j) exp(2 pi i f_j.(x - T))`` (``U_w``: each term times
   ``c_j``), a type-1 non-uniform DFT from the rays' frequencies to a uniform sensor grid of pitch
   ``h <= 1 / (4.4 B)`` (``|U|^2`` has band ``2 B``: the grid samples it above Nyquist). It is evaluated by
   Gaussian gridding on a twice-oversampled grid, one FFT and a deconvolution (:func:`nufft_type1`, relative
   error ~1e-6).
2. **The pixel box applied analytically.** ``I = |U|^2`` (or ``Re(conj(U) U_w)``) is band-limited below the
   grid's Nyquist, so it is its samples' sinc interpolant, and the integral of that over a pixel is exact:
   per axis ``W[p, m] = (h / pi) [Si(pi (b_p - x_m) / h) - Si(pi (a_p - x_m) / h)]``, and the pixel values
   are ``W_y I W_x^T`` (:func:`box_weights`). No Gauss-Legendre nodes: their count is capped at 16 per axis,
   too few where a pixel spans ~50 intensity periods (15.3 um at f/1.8).

Costs: rays ``N_r^2`` with ``N_r = rays_per_sample max(RAY_MIN, 1.25 x 2 B (w / 2 + s))`` (``w``: the sensor
grid's width, ``s``: the spot's reach from ``T``: the quadrature's aliases, at ``1 / delta_f`` from the light,
fall beyond the grid), the sensor grid ``(w / h)^2`` and the twice-oversampled FFTs of its tiles (``TILE``).
EF50 f/1.8 at 15.3 um, 64 px: 0.58 GiB, 10.9 GFLOP (the Debye form), 0.67 GiB, 12.5 GFLOP (the Kirchhoff form on
1 tile of 268^2 over the spot, the Debye samples beyond at ``DEBYE_FAR_SPREAD``; at 10 deg 4 tiles of 242^2 over its
coma spot, 19.4 GFLOP; ``perf/pixel_auto.py``);
:func:`pixel_cost`. The pupil is taken as whole cells (rays at cell centres inside the disc): weighting the rim
cells by their covered part changed nothing on the EF35 and made the ideal lens's Airy test 4x worse.

Error against the full computation (the same rays' field splatted on the wave plane and propagated exactly),
max |difference| over the PSF's peak, :func:`pixel_error_estimate`:

* the Debye step (stationary phase of the wave-plane field's Fourier transform) leaves out the boundary wave
  of that field's hard edge. Without aberrations it cancels at the patch (the ideal lens gives the pixel-
  integrated Airy pattern to 5.7e-5); with a rim slope ``S`` (rad) it does not, ~``S / sqrt(N_F)`` (``N_F``: the
  beam's Fresnel number seen from the patch), and a pixel of ``p`` averages it as ``(r_A / p)^1.6``. Measured
  1e-4 to 2.5e-2 (A489, Cooke triplet, DeepLens camera lenses; docs/propagation.md "Large pixels"); it does not
  fall with more rays, nor move with the grid's margin, the gridding kernel or the tiles (< 1e-4 each, while the
  reference is converged to ~1e-4: ``perf/pixel_study.py``, docs "What the error follows"). The Kirchhoff form
  (:mod:`rwwarp.wave.pixel_kirchhoff`, ``FIELD_FORM``) sums the wave-plane field with the exact kernel instead:
  EF35 on axis 1.2e-3 -> 1.4e-4, Cooke 14 deg 1.9e-3 -> 9.6e-5, at 16-17 transforms per tile against 2, on the tiles
  over the spot's region only (the pilot landings' box + ``KIRCHHOFF_MARGIN / B`` a side, the fewest tiles that
  cover it), the Debye form's samples elsewhere; its own estimate:
  :func:`rwwarp.wave.pixel_kirchhoff.kirchhoff_error_estimate` (the kernel's expansion over a tile, the corrections'
  NUFFT, the pupil quadrature, the Debye samples beyond the tiles);
* the quadrature: the aliases of the ray lattice (beyond the grid by construction, their skirts kept off by
  ``RAY_MIN``), the pupil rim as whole cells; the NUFFT (1e-6) and the box weights (exact for the band-limited
  samples) are below that.

**Which form, and whether** (:func:`plan_forms`, :func:`choose_form`, :func:`consider_pixel`). Both forms are
planned from the pilot (:func:`plan_field`: tiling, points; :func:`pixel_cost`) with their error estimates; the form
that runs is the one of fewer flops whose estimate is within the tolerance (``rw.psf(..., tolerance=)``, default
``DEFAULT_TOLERANCE`` = 1e-3 of the peak) and whose memory fits the budget (``FIELD_FORM`` "debye" / "kirchhoff"
forces one). ``method="auto"`` then runs the pixel method where that form exists, the pixel spans at least
``MIN_PIXEL_AIRY`` Airy radii, the wave step is not wanted and it plans fewer flops than the focal / ASM plan;
``--explain`` (``plan.explain()``) shows a line per form (``debye form: error ~..., GiB, GFLOP`` with the estimate's
parts), the form chosen and why (``sensor field form kirchhoff: the form of fewer flops whose error estimate is
within the tolerance 0.001 (debye ~0.0016 / 8.5 GFLOP, kirchhoff ~0.00013 / 15.5 GFLOP)``) and ``method auto: pixel
(...)`` or ``pixel method not chosen: ...``. An explicit ``method="pixel"`` with no form within the tolerance runs
the Kirchhoff form where it needs at most ``KIRCHHOFF_MAX_TILES`` tiles, else the Debye form (as before).

Not handled: DOEs (their diffraction orders); ``method="auto"`` does not pick it for a lens with a DOE that
is not blank. Units: mm, um for wavelengths at the public interface, cycles/mm. Arrays: numpy or CuPy
(``xp``), as the tracer's device.
"""
from __future__ import annotations

import math

import numpy as np

from . import nufft
from .nufft import NUFFT_OVERSAMPLE, NUFFT_SPREAD, nufft_flops  # noqa: F401  (their home: rwwarp.wave.nufft)
#: largest side (samples) of one NUFFT tile of the sensor grid (its oversampled FFT: 2x that, ~230 MB with its
#: accumulators at 1536)
TILE = 1536
#: the sensor grid samples |U|^2 (band 2 B) this much above its Nyquist rate
GRID_MARGIN = 1.1
#: rays: the quadrature's aliases fall this far beyond the grid (times rays_per_sample)
RAY_SAFETY = 1.25
#: ... and at least this many across the pupil: the aliases of a bright core lie 1 / delta_f from it, and an
#: aberrated core's skirt reaches the grid from there (EF35 f/2 at 2 deg, 5 px, against the full computation:
#: 2.0e-3 / 1.3e-3 / 8.6e-4 / 9.5e-4 at 149 / 297 / 593 / 1185 rays across: the Debye floor from ~600)
RAY_MIN = 600
#: auto picks the method only for pixels at least this many Airy radii wide
MIN_PIXEL_AIRY = 4.0
#: default tolerance (of the PSF's peak) for method="auto"
DEFAULT_TOLERANCE = 1e-3
#: calibration of :func:`pixel_error_estimate` (docstring there)
PIXEL_ERROR_C = 0.06
PIXEL_ERROR_POWER = 1.6
PIXEL_ERROR_FLOOR = 2e-4
#: the sensor field's form: "debye" (one plane wave per ray), "kirchhoff" (the wave-plane field summed with the
#: exact kernel, its rim's boundary wave included: :mod:`rwwarp.wave.pixel_kirchhoff`) or "auto": kirchhoff where its
#: tiles (their size set by the kernel's curvature over the patch) number at most KIRCHHOFF_MAX_TILES, else debye
FIELD_FORM = "auto"
KIRCHHOFF_MAX_TILES = 4
#: the Kirchhoff form only on the tiles within the spot's reach (the pilot landings' largest offset from the patch
#: centre + 12 / B) of the patch centre, the Debye form's samples elsewhere (``KIRCHHOFF_MAX_TILES`` counts those tiles)
KIRCHHOFF_NEAR = True
#: the Kirchhoff tiles' region: the pilot landings' box about the patch centre widened by this many 1 / B a side
#: (:func:`plan_field`)
KIRCHHOFF_MARGIN = 12.0
#: the Gaussian gridding's half-width (cells) of the Debye samples kept beyond the Kirchhoff tiles: their relative error
#: exp(-pi 5 (R - 1/2) / R) ~ 7.6e-6 of the field's norm (1e-6 at NUFFT_SPREAD = 6), at most ~1.5e-5 of the peak in
#: the intensity there (where the light is, the Kirchhoff tiles' own NUFFTs at the full spread); 100 cells a point
#: instead of 144
DEBYE_FAR_SPREAD = 5


# ---------------------------------------------------------------------------------------------- numerics
def box_weights(edges_lo_mm, pixel_mm, x0_mm, h_mm, n):
    """Per-axis weights (npix, n) of the exact pixel integral of a band-limited function from its samples.

    A function whose spectrum lies inside ``|nu| < 1 / (2 h)`` is ``sum_m I_m sinc((x - x_m) / h)`` with
    ``x_m = x0 + m h`` (mm); its integral over ``[a_p, a_p + pixel]`` (``edges_lo_mm``: the pixels' lower
    edges) is ``sum_m W[p, m] I_m`` with ``W[p, m] = (h / pi) (Si(pi (b_p - x_m) / h) - Si(pi (a_p - x_m) /
    h))`` (mm). Samples beyond the grid count as zero. Returns a float64 numpy array."""
    from scipy.special import sici
    a = np.asarray(edges_lo_mm, float)[:, None]
    xm = float(x0_mm) + float(h_mm) * np.arange(int(n))[None, :]
    s_hi = sici(np.pi * (a + float(pixel_mm) - xm) / h_mm)[0]
    s_lo = sici(np.pi * (a - xm) / h_mm)[0]
    return (h_mm / np.pi) * (s_hi - s_lo)


def _grid_diff(a, valid, axis, xp):
    """Differences of ``a`` (S, N, N, k) along the pupil grid's ``axis`` (2: columns, 1: rows), per cell: central
    where both neighbours are valid; at the pupil's edge (one neighbour) second order one-sided from two
    neighbours where both are valid (``(-3 a0 + 4 a1 - a2) / 2``), first order from one; 0 where none is."""
    n = a.shape[axis]
    shape = [1, 1, 1]
    shape[axis] = n
    idx = xp.arange(n).reshape(shape)
    av = xp.where(valid[..., None], a, 0.0)

    def nb(s):       # the neighbour s cells on, and whether it is a valid ray of the grid
        inside = (idx + s >= 0) & (idx + s < n)
        return xp.roll(av, -s, axis=axis), xp.roll(valid, -s, axis=axis) & inside
    (f1, v1), (f2, v2), (b1, w1), (b2, w2) = nb(1), nb(2), nb(-1), nb(-2)
    one_f = xp.where((v1 & v2)[..., None], 0.5 * (-3.0 * av + 4.0 * f1 - f2), f1 - av)
    one_b = xp.where((w1 & w2)[..., None], 0.5 * (3.0 * av - 4.0 * b1 + b2), av - b1)
    return xp.where((v1 & w1)[..., None], 0.5 * (f1 - b1),
                    xp.where(v1[..., None], one_f, xp.where(w1[..., None], one_b, 0.0)))


def tube_areas(f, valid, xp=np):
    """Area (in (cycles/mm)^2) of each ray tube in frequency: ``|det d f / d(i, j)|`` on the pupil grid (``f``
    (S, N, N, 2) transverse frequencies, ``valid`` (S, N, N) bool; differences as :func:`_grid_diff`: second
    order at the rim too, where an aberration's mapping bends fastest), 0 for a ray with no valid neighbour
    along an axis."""
    du, dv = (_grid_diff(f, valid, ax, xp) for ax in (2, 1))
    return xp.abs(du[..., 0] * dv[..., 1] - du[..., 1] * dv[..., 0]) * valid


# ---------------------------------------------------------------------------------------------- error
def pixel_error_estimate(fresnel_number_focus: float, rim_slope_rad: float, pixel_mm: float,
                         airy_mm: float) -> dict:
    """The estimated error of ``method="pixel"`` against the full computation, max |difference| over the
    PSF's peak (dimensionless), and its parts.

    * ``debye``: the stationary-phase (Debye) step leaves out the boundary wave of the wave-plane field's
      hard edge. For an unaberrated beam and the sensor at the reference sphere's centre the two agree
      (both are the pupil function's Fourier transform in the Fresnel approximation; the ideal lens's
      pixel-integrated Airy pattern comes out 5.7e-5 off); an aberration of rim slope ``S`` (rad, against the
      sphere to the patch, :func:`rwwarp.wave.model_error.estimate_for_raywave`) leaves the edge wave,
      ``1 / sqrt(N_F)`` of the field at the edge (``N_F = n r_w^2 / (lambda R)``, the beam seen from the
      patch), uncancelled. A pixel ``p`` wide averages its ring structure (the Airy radius ``r_A``'s scale):
      ``PIXEL_ERROR_C S / sqrt(N_F) (r_A / p)^PIXEL_ERROR_POWER``;
    * ``floor``: the quadrature (whole pupil cells at the rim; the tails beyond the aliases' distance folded
      back), ``PIXEL_ERROR_FLOOR``.

    Calibration against the full computation box-summed from a fine pixel (docs/propagation.md "Large
    pixels"; 600 rays across or more): ``C`` = (measured - floor) sqrt(N_F) (p / r_A)^1.6 / S is 0.026-0.035 on
    the A489 (0 / 5 / 10 deg at 16 um, 10 deg at 8 / 32 um: 3-12 r_A, N_F 77-84, S 11-37 rad), 0.012 on the Cooke
    triplet at 14 deg (2.8 r_A, N_F 774), 0.010-0.053 on DeepLens camera lenses at 15.3 um (EF50 f/1.8 and EF35
    f/2 on axis, EF35 at 2 deg, RF50 f/1.8 at 2 deg: 11-12 r_A, N_F 3400-5400, S 25-96 rad). The form does not
    capture that 5x spread; ``C = 0.06`` is its upper envelope, so the estimate is 1.1-6x the measured error."""
    nf, s = float(fresnel_number_focus), abs(float(rim_slope_rad))
    debye = PIXEL_ERROR_C * s / math.sqrt(max(nf, 1e-30)) * min(1.0, airy_mm / pixel_mm) ** PIXEL_ERROR_POWER
    return {"estimate": float(debye + PIXEL_ERROR_FLOOR), "debye": float(debye), "floor": PIXEL_ERROR_FLOOR,
            "pixel_over_airy": float(pixel_mm / airy_mm)}


# ---------------------------------------------------------------------------------------------- plan
def pixel_band(ok, freq, carrier) -> float:
    """The band ``B`` of :func:`plan_pixel` (cycles/mm): the largest ``|f - f_c|`` (one component) over every source's
    valid pilot rays (``ok`` (S, N), ``freq`` (S, N, 2) cycles/mm, ``carrier`` (S, 2)), at least 1e-9."""
    band = 1e-9
    for k in range(len(carrier)):
        band = max(band, float(np.max(np.abs(freq[k][ok[k]] - carrier[k]))))
    return band


def plan_pixel(pos_s, ok, freq, carrier, centers, size: int, pixel_mm: float, rays_per_sample: float = 1.0):
    """Sampling of ``method="pixel"`` for a batch, from its pilot trace.

    ``pos_s`` (S, N, 3) the pilot rays' sensor landings (mm), ``ok`` (S, N) their validity, ``freq`` (S, N, 2)
    their transverse frequencies ``n d_xy / lambda`` (cycles/mm), ``carrier`` (S, 2) the chief ray's,
    ``centers`` (S, 2) the patch centres (mm), ``size`` px of ``pixel_mm``.

    * band ``B = max |f - f_c|`` (cycles/mm), one component; the Airy radius ``0.61 / B``;
    * sensor grid: the patch plus a pixel and ``32 h`` a side, pitch ``h = 1 / (2 GRID_MARGIN 2 B)``, ``n``
      samples (even) per axis, FFT ``NUFFT_OVERSAMPLE n``;
    * rays ``N_r = rays_per_sample max(RAY_MIN, RAY_SAFETY 2 B (w / 2 + s))`` across the pupil (``w``: the grid's width, ``s``:
      the pilot landings' largest distance from the patch centre, plus ``12 / B``): the quadrature's aliases
      lie ``1 / delta_f`` from the light, beyond the grid.

    Returns ``(plan, info)``: a :class:`rwwarp.wave.plan.Plan` with ``method="pixel"`` (``pitch_mm`` = ``sensor_pitch_mm`` =
    ``h``, ``n_grid`` = ``n_sensor`` = ``n``, ``n_pad`` = ``n_sensor_fft`` = the FFT length), and ``info`` with
    ``band``, ``airy_mm``, ``reach_mm``."""
    from .plan import Plan
    S = len(centers)
    band = pixel_band(ok, freq, carrier)
    reach = 0.0
    for k in range(S):
        reach = max(reach, float(np.max(np.abs(pos_s[k][ok[k], :2] - centers[k]))))
    h = 1.0 / (4.0 * GRID_MARGIN * band)
    half = 0.5 * size * pixel_mm + pixel_mm + 32.0 * h
    n = 2 * int(math.ceil(half / h))
    reach += 12.0 / band
    ray_grid = int(math.ceil(rays_per_sample * max(RAY_MIN, RAY_SAFETY * 2.0 * band * (0.5 * n * h + reach)))) + 1
    airy = 0.61 / band
    reasons = (
        f"pixel method (pixels of {pixel_mm / airy:.3g} Airy radii): the sensor field on a grid at its own Nyquist rate, "
        f"each pixel's box integrated exactly (rwwarp.wave.pixel_scale)",
        f"sensor grid: patch {size * pixel_mm * 1e3:.4g} um + {pixel_mm * 1e3:.4g} um + 32 samples a side at "
        f"{h * 1e3:.4g} um (band B = {band:.4g} cycles/mm, |U|^2 to 2 B x {GRID_MARGIN:g}) -> {n}^2, FFT "
        f"{NUFFT_OVERSAMPLE * n}^2",
        f"rays: {rays_per_sample} x max({RAY_MIN}, {RAY_SAFETY:g} x 2 B x (half grid {0.5 * n * h * 1e3:.4g} um + spot "
        f"reach {reach * 1e3:.4g} um)) -> {ray_grid} across the pupil (the quadrature's aliases beyond the grid)",
    )
    nt, t = tiles(n)
    plan = Plan(h, n, NUFFT_OVERSAMPLE * nt, ray_grid, "auto", False, reasons, "pixel", h, n, NUFFT_OVERSAMPLE * nt)
    return plan, {"band": band, "airy_mm": airy, "reach_mm": reach, "margin_mm": KIRCHHOFF_MARGIN / band}


def tiles(n: int):
    """``(n_t, t)``: the sensor grid of ``n`` samples a side in ``t x t`` tiles of ``n_t`` (even, ``<= TILE``)."""
    t = max(1, int(math.ceil(n / TILE)))
    nt = 2 * int(math.ceil(n / (2 * t)))
    return nt, t


def plan_field(pos_s, dir_s, ok, centers, lam_mm, n_after, z_plane: float, z_sensor: float, h_mm: float, n: int,
               ray_grid: int, flux: bool, form: str | None = None, pupil_fill: float = math.pi / 4,
               reach_mm: float | None = None, margin_mm: float | None = None) -> dict:
    """The sensor field's form of a ``method="pixel"`` batch and its tiling, from the pilot trace.

    The pilot rays (``pos_s`` (S, N, 3) their sensor landings, ``dir_s`` (S, N, 3) directions, ``ok`` (S, N)) are
    continued back to the wave plane ``z_plane`` (mm); its points: the pilot's valid fraction of ``pupil_fill
    ray_grid^2`` (``pupil_fill``: the share of the square pupil grid inside the pupil, pi / 4 for a circle). ``form``
    (None: ``FIELD_FORM``): "kirchhoff", "debye" or "auto" (kirchhoff where it takes at most ``KIRCHHOFF_MAX_TILES``
    tiles; :func:`consider_pixel` chooses by the error estimates and the tolerance instead).

    The Kirchhoff form's region: with ``KIRCHHOFF_NEAR``, the pilot landings' bounding box about each patch centre
    (``centers`` (S, 2) mm, on ``z_sensor``) widened by ``margin_mm`` a side (the union over the sources; where
    ``margin_mm`` is None, the square of half side ``reach_mm``), the Debye form's samples elsewhere; else (or where
    ``reach_mm`` is None) the whole grid. It is covered by the fewest tiles of one side whose quadratic rest stays below
    ``KIRCHHOFF_EPS`` (:func:`rwwarp.wave.pixel_kirchhoff.tile_limit`, seen from the region's corners;
    :func:`~rwwarp.wave.pixel_kirchhoff.region_tiles`) and whose expansion's estimated error (the ``expansion`` part
    of :func:`~rwwarp.wave.pixel_kirchhoff.kirchhoff_error_estimate`) stays within ``KIRCHHOFF_EXPANSION_MAX``, each as
    small as covers it in that count.
    Returns ``{"form", "tile", "tiles", "points", "vectors", "near", "reach_mm"}`` (``tile`` samples a side,
    ``tiles`` a side of the grid in tiles of ``tile``, ``vectors`` the NUFFT weight vectors a tile: the chosen
    form's; ``near`` the Kirchhoff tiles, ``reach_mm`` None where they cover the grid) and for the Kirchhoff form
    ``origins`` (the tiles' first samples), ``eps`` and ``cubic`` (rad: the kernel's rests at a tile's corner), ``amp``
    (the amplitude's first-order change there; :func:`~rwwarp.wave.pixel_kirchhoff.tile_rests`) and ``spreads`` (the
    correction groups' NUFFT spreads, :func:`~rwwarp.wave.pixel_kirchhoff.group_spreads`)."""
    from .pixel_kirchhoff import (KIRCHHOFF_EXPANSION_MAX, group_spreads, kirchhoff_error_estimate, n_vectors,
                                  region_tiles, tile_limit, tile_rests)
    form = FIELD_FORM if form is None else form
    if form not in ("auto", "kirchhoff", "debye"):
        raise ValueError(f"pixel method: the sensor field's form must be 'auto', 'kirchhoff' or 'debye', got {form!r}")
    near_only = KIRCHHOFF_NEAR and reach_mm is not None
    lo, hi, pts, wave = np.full(2, np.inf), np.full(2, -np.inf), 0, []
    for k in range(len(centers)):
        sel = np.asarray(ok[k], bool)
        p, dd = np.asarray(pos_s[k], float)[sel], np.asarray(dir_s[k], float)[sel]
        P = p + ((float(z_plane) - p[:, 2]) / dd[:, 2])[:, None] * dd
        T = np.array([float(centers[k][0]), float(centers[k][1]), float(z_sensor)])
        off = p[:, :2] - T[:2]
        if margin_mm is None:
            lo, hi = np.minimum(lo, -float(reach_mm or 0.0)), np.maximum(hi, float(reach_mm or 0.0))
        else:
            lo, hi = np.minimum(lo, off.min(0) - margin_mm), np.maximum(hi, off.max(0) + margin_mm)
        wave.append((P, T, float(lam_mm[k]), float(n_after[k])))
        pts = max(pts, int(math.ceil(float(np.mean(sel)) * pupil_fill * ray_grid ** 2)))
    # the region in samples (sample m at (m - n / 2) h from the patch centre), the whole grid where not near_only
    region = (0, n, 0, n)
    if near_only:
        region = (max(0, math.floor(n / 2 + lo[1] / h_mm)), min(n, math.ceil(n / 2 + hi[1] / h_mm) + 1),
                  max(0, math.floor(n / 2 + lo[0] / h_mm)), min(n, math.ceil(n / 2 + hi[0] / h_mm) + 1))
    nt_max, norms = 1 << 30, []
    for P, T, lam, nm in wave:     # the rest's spread seen from the region's corners (and the centre): the largest
        pts_T = [T] + [T + np.array([(region[2 + c] - n / 2) * h_mm, (region[r] - n / 2) * h_mm, 0.0])
                       for r in (0, 1) for c in (0, 1)]
        ntk, normk = tile_limit(P, pts_T, lam, nm, h_mm)
        nt_max, norms = min(nt_max, ntk), norms + [normk]
    while True:     # the fewest tiles whose expansion's estimated error is within KIRCHHOFF_EXPANSION_MAX
        nt, origins = region_tiles(region, nt_max, n)
        eps, cub, amp = 0.0, 0.0, 0.0
        for (P, T, lam, nm), normk in zip(wave, norms):
            e, c, a = tile_rests(P, T, lam, nm, h_mm, nt, normk)
            eps, cub, amp = max(eps, e), max(cub, c), max(amp, a)
        if nt <= 8 or kirchhoff_error_estimate(eps, cub, ray_grid, amp=amp)["expansion"] <= KIRCHHOFF_EXPANSION_MAX:
            break
        nt_max = max(8, 2 * int(0.45 * nt))
    near = len(origins)
    whole = region == (0, n, 0, n)
    reach = None if whole else (float(reach_mm) if reach_mm is not None else None)
    if form == "auto":
        form = "kirchhoff" if near <= KIRCHHOFF_MAX_TILES else "debye"
    if form == "debye":
        nd, td = tiles(n)
        return {"form": "debye", "tile": int(nd), "tiles": int(td), "points": pts, "vectors": 2 if flux else 1,
                "near": 0, "reach_mm": None}
    return {"form": "kirchhoff", "tile": int(nt), "tiles": int(math.ceil(n / nt)), "points": pts,
            "vectors": n_vectors(flux), "near": int(near), "reach_mm": reach, "origins": origins,
            "eps": float(eps), "cubic": float(cub), "amp": float(amp), "spreads": group_spreads(eps, cub, amp)}


def pixel_cost(plan, n_sources: int, size: int) -> dict:
    """Peak memory (bytes) and work (flops) of ``method="pixel"`` for the form ``plan.pixel_field`` names (None, a
    plan from before it: the Debye form with ``U`` and ``U_w``, all ``ray_grid^2`` rays).

    Both: the traced rays (~232 bytes each, as :func:`rwwarp.wave.plan.estimate_cost`) and their host arrays (~40
    doubles: directions, tube areas, phases, wave-plane points), the sensor grid's ``I`` (8 ``n^2``); flops ~4000 a
    ray (trace), the box products ``W_y I W_x^T``. Per source and tile, one tile at a time:

    * Debye: ``vectors`` (``U``, and ``U_w`` for "flux") NUFFTs (:func:`nufft_flops`) of the points, one a call; the
      grid (``GRID_CELL_BYTES`` a cell of the ``NUFFT_OVERSAMPLE n_t`` FFT), ``U``, ``U_w``, ``I`` of the tile;
    * Kirchhoff: :func:`rwwarp.wave.pixel_kirchhoff.tile_cost` (23-24 NUFFTs in chunks that fit
      ``KIRCHHOFF_GRID_BYTES``) on its ``near`` tiles; where they are not all (``reach_mm``), the Debye form's work
      on the whole grid first and its samples kept (8 ``n^2`` more).

    Returns ``memory_bytes``, ``flops``, and ``nufft_flops`` (the NUFFTs' part), ``form``, ``tiles`` (``t x t``),
    ``tile`` (``n_t``), ``points``, ``vectors``, ``chunk`` (vectors a NUFFT call)."""
    from .pixel_kirchhoff import GRID_CELL_BYTES, N_TERMS, tile_cost
    rays = int(n_sources) * plan.ray_grid ** 2
    n = plan.n_sensor
    f = plan.pixel_field
    if f is None:
        f = dict(zip(("tile", "tiles"), tiles(n)), form="debye", points=plan.ray_grid ** 2, vectors=2)
    nt, t, J, K = int(f["tile"]), int(f["tiles"]), int(f["points"]), int(f["vectors"])
    mem = rays * 232 + plan.ray_grid ** 2 * 8 * 40 + 8 * n * n
    flops = rays * 4000.0 + n_sources * 4.0 * (n * n * size + n * size * size)
    def debye(K, spread=None):    # memory, NUFFT flops, flops of the Debye form on the whole grid, its own tiles
        nd, td = tiles(n)
        M = NUFFT_OVERSAMPLE * nd
        nu = n_sources * td * td * K * nufft_flops(J, 1, nd, spread)
        return GRID_CELL_BYTES * M * M + 3 * 16 * nd * nd, nu, nu + n_sources * td * td * 10.0 * J
    if f["form"] == "kirchhoff":
        near = int(f.get("near", t * t))
        tc = tile_cost(nt, J, K > N_TERMS, spreads=f.get("spreads"))
        nufft, kc = n_sources * near * tc["nufft_flops"], tc["chunk"]
        flops += n_sources * near * tc["flops"]
        tile_mem = tc["memory_bytes"]
        if f.get("reach_mm") is not None:
            dm, dn, df = debye(K - N_TERMS + 1, DEBYE_FAR_SPREAD)
            tile_mem, nufft, flops = max(tile_mem, dm) + 8 * n * n, nufft + dn, flops + df
        mem += tile_mem
    else:
        near, kc = 0, 1
        dm, nufft, df = debye(K)
        mem, flops = mem + dm, flops + df
    return {"memory_bytes": int(mem), "flops": float(flops), "nufft_flops": float(nufft), "form": f["form"],
            "tiles": t, "tile": nt, "points": J, "vectors": K, "chunk": kc, "near": near}


# ---------------------------------------------------------------------------------------------- run
def _device_array(a, xp):
    """A Warp array as an ``xp`` array (a host copy for numpy, a zero-copy view for CuPy)."""
    if xp is np:
        return a.numpy()
    return xp.asarray(a)


def pixel_psf(rw):
    """Power per pixel (S, size, size) of a :class:`rwwarp.wave.raywave.RayWave` whose plan has
    ``method="pixel"`` (module docstring), not yet divided by the entering power; sets the batch's power
    sums (``rw.entering``). Traces ``plan.ray_grid^2`` rays (whole pupil cells) to the last surface."""
    import warp as wp
    from .reduce import source_sums
    tr, src, pl = rw.tracer, rw.src, rw.plan
    xp = np
    if tr.device.startswith("cuda"):
        import cupy as xp
    S, N = rw.nsrc, pl.ray_grid
    with tr.without_gradients():
        rays = tr._run(src, None, None, (2.0 / N) ** 2, upto=rw.plane + 1, grid_n=N)
    K = rw.splatter.K
    terms = wp.empty(S * N * N, dtype=K.vec4d, device=tr.device)
    wp.launch(K.power_sums_kernel, dim=S * N * N, inputs=[rays.valid, rays.weight], outputs=[terms],
              device=tr.device, record_tape=False)
    rw._sums_dev, rw._sums = source_sums(terms, S, wp.float64, tr.device), None
    rw.dropped = wp.zeros(S, dtype=wp.int32, device=tr.device)
    as64 = lambda a: xp.asarray(_device_array(a, xp), dtype=xp.float64)    # no copy when already float64
    pos = as64(rays.pos).reshape(S, N, N, 3)
    d = as64(rays.dir).reshape(S, N, N, 3)
    opl = as64(rays.opl).reshape(S, N, N)
    valid = _device_array(rays.valid, xp).reshape(S, N, N).astype(bool)
    q = as64(rays.weight).reshape(S, N, N)
    # rays that did not arrive carry whatever their last state was: zeros, so no NaN enters the arithmetic
    pos, opl, q = xp.where(valid[..., None], pos, 0.0), xp.where(valid, opl, 0.0), xp.where(valid, q, 0.0)
    d = xp.where(valid[..., None], d, xp.asarray([0.0, 0.0, 1.0]))
    del rays
    h, n = pl.sensor_pitch_mm, pl.n_sensor
    out = np.zeros((S, rw.size, rw.size))
    flux = rw.pixel_values == "flux"
    for k in range(S):
        inv_lam = float(rw.n_after[k] / rw.lam_mm[k])
        f = inv_lam * d[k, ..., :2]
        area = tube_areas(f[None], valid[k][None], xp)[0]
        use = valid[k] & (area > 0) & (q[k] > 0)
        T = xp.asarray([rw.centers[k, 0], rw.centers[k, 1], rw.z_sensor])
        # the ray's phase at the foot of T on it: k0 (L + n d.(T - p)) (rad)
        phase = (2.0 * math.pi / float(rw.lam_mm[k])) * (opl[k] + float(rw.n_after[k]) * xp.sum(d[k] * (T - pos[k]), -1))
        cos = d[k, ..., 2] if flux else xp.ones_like(opl[k])
        amp = xp.sqrt(xp.where(use, q[k] * area / cos, 0.0))
        fc = xp.asarray(rw.carrier[k])
        tx = 2.0 * math.pi * (f[..., 0] - fc[0]) * h
        ty = 2.0 * math.pi * (f[..., 1] - fc[1]) * h
        tx, ty = tx[use], ty[use]
        if float(xp.max(xp.abs(tx))) >= math.pi or float(xp.max(xp.abs(ty))) >= math.pi:
            raise FloatingPointError("pixel method: a ray's frequency lies beyond the sensor grid's band (the "
                                     "pilot trace missed the beam's edge): please report this lens and field")
        from .pixel_kirchhoff import kirchhoff_samples
        Tk = (rw.centers[k, 0], rw.centers[k, 1], rw.z_sensor)
        tw = (rw.z_plane - pos[k, ..., 2]) / d[k, ..., 2]
        Pw = pos[k] + tw[..., None] * d[k]
        form = (pl.pixel_field or {"form": "debye"})["form"]        # the planned form (plan_field); a plan from before it
        rw.pixel_forms = getattr(rw, "pixel_forms", {})
        rw.pixel_forms[k] = form
        reach = (pl.pixel_field or {}).get("reach_mm")
        if form == "kirchhoff":
            # the wave-plane field summed with the exact kernel (rwwarp.wave.pixel_kirchhoff): its rim's boundary wave;
            # with reach, on the tiles near the spot only, the Debye form's samples elsewhere
            I0 = (_debye_samples(xp, amp, phase, use, cos, flux, tx, ty, n, DEBYE_FAR_SPREAD) if reach is not None
                  else None)
            del amp, phase
            dA = tube_areas(Pw[None, ..., :2], valid[k][None], xp)[0]
            ok = valid[k] & (dA > 0) & (q[k] > 0)
            Lw = (opl[k] + float(rw.n_after[k]) * tw)[ok]
            # |W|^2 d_z dA = q: the flux through the wave plane is the ray's power; "intensity" takes the power
            # spectrum as q without the obliquity (as the Debye form's |B|^2 dA_f = q): W sqrt(d_z)
            aw = xp.sqrt(xp.where(ok, q[k] * dA / (d[k, ..., 2] if flux else 1.0), 0.0))[ok]
            f = pl.pixel_field or {}
            tiling = (f["tile"], f["origins"]) if f.get("origins") else None     # the planned region (plan_field)
            I = kirchhoff_samples(Pw[ok], Lw, aw.astype(xp.complex128), float(rw.lam_mm[k]), float(rw.n_after[k]),
                                  Tk, rw.carrier[k], h, n, flux, xp, base=I0,
                                  reach_mm=None if tiling else reach, tiling=tiling, spreads=f.get("spreads"))
            del dA, ok, Lw, aw, I0
        else:
            I = _debye_samples(xp, amp, phase, use, cos, flux, tx, ty, n)
        x0 = rw.centers[k] - 0.5 * n * h
        lo = (np.arange(rw.size) - rw.size // 2) * rw.pixel - 0.5 * rw.pixel
        wx = xp.asarray(box_weights(rw.centers[k, 0] + lo, rw.pixel, x0[0], h, n))
        wy = xp.asarray(box_weights(rw.centers[k, 1] + lo, rw.pixel, x0[1], h, n))
        P = wy @ I @ wx.T
        out[k] = P if xp is np else xp.asnumpy(P)
    return out


def _debye_samples(xp, amp, phase, use, cos, flux, tx, ty, n, spread=None):
    """The Debye form's ``|U|^2`` / ``Re(conj(U) U_w)`` on the sensor grid (:func:`pixel_psf`; ``spread`` the
    gridding's half-width, None: ``NUFFT_SPREAD``)."""
    c = (amp * xp.exp(1j * phase))[use]
    cw = c * cos[use] if flux else None
    nt, t = tiles(n)
    I = xp.zeros((n, n))
    for ay in range(t):
        for ax in range(t):
            # the tile's samples m0 + m', |m'| <= nt / 2: the points' phases shifted by m0 . theta
            m0y, m0x = ay * nt + nt // 2 - n // 2, ax * nt + nt // 2 - n // 2
            shift = xp.exp(1j * (m0x * tx + m0y * ty))
            U = nufft.nufft_type1(tx, ty, c * shift, nt, xp, spread=spread)
            if flux:
                Uw = nufft.nufft_type1(tx, ty, cw * shift, nt, xp, spread=spread)
                It = xp.real(xp.conj(U) * Uw)
                del Uw
            else:
                It = xp.abs(U) ** 2
            del U, shift
            hy, hx = min(nt, n - ay * nt), min(nt, n - ax * nt)
            I[ay * nt:ay * nt + hy, ax * nt:ax * nt + hx] = It[:hy, :hx]
    return I


def field_reason(field: dict, cost: dict) -> str:
    """The plan's line saying which sensor-field form runs (:func:`plan_field`) and what it costs (:func:`pixel_cost`)."""
    if field["form"] == "kirchhoff":
        what = (f"the Kirchhoff (Rayleigh-Sommerfeld) sum of the wave-plane field (rwwarp.wave.pixel_kirchhoff): "
                f"{field['near']} tiles of {field['tile']}^2 (at most the kernel's curvature allows)"
                + (f" over the spot's region (the pilot landings' box + {KIRCHHOFF_MARGIN:g} / B a side), the Debye form's "
                   f"samples elsewhere" if field.get("reach_mm") is not None else " over the whole grid")
                + f", {field['vectors']} NUFFTs of ~{field['points']} wave-plane samples a tile, {cost['chunk']} at a time")
    else:
        what = (f"the Debye plane waves of the rays: {field['tiles']} x {field['tiles']} tiles of {field['tile']}^2, "
                f"{field['vectors']} NUFFT(s) of ~{field['points']} rays a tile")
    return (f"sensor field form {field['form']} (FIELD_FORM {FIELD_FORM!r}): {what}; NUFFTs {cost['nufft_flops'] / 1e9:.3g} of "
            f"{cost['flops'] / 1e9:.3g} GFLOP")


def plan_forms(ppl, info, pos_s, dir_s, ok, centers, lam_mm, n_after, rw, nf: float, slope: float) -> dict:
    """Each sensor-field form of ``method="pixel"`` planned for the batch ``rw`` (a
    :class:`rwwarp.wave.batch_plan.BatchPlan`) on the pixel plan ``ppl`` (:func:`plan_pixel`, ``info`` its second
    value): ``{"debye": (field, cost, error), "kirchhoff": (...)}``, ``field`` from :func:`plan_field`, ``cost`` from
    :func:`pixel_cost`, ``error`` the form's estimate against the full computation (:func:`pixel_error_estimate` from
    the beam's Fresnel number ``nf`` seen from the patch and the rim slope ``slope`` (rad);
    :func:`rwwarp.wave.pixel_kirchhoff.kirchhoff_error_estimate` from the planned tiles' rests, the rays across the
    pupil and, where the Debye form's samples are kept beyond the near tiles, the Debye estimate)."""
    from dataclasses import replace
    from .pixel_kirchhoff import kirchhoff_error_estimate
    debye_err = pixel_error_estimate(nf, slope, rw.pixel, info["airy_mm"])
    out = {}
    for form in ("debye", "kirchhoff"):
        field = plan_field(pos_s, dir_s, ok, centers, lam_mm, n_after, rw.z_plane, rw.z_sensor, ppl.sensor_pitch_mm,
                           ppl.n_sensor, ppl.ray_grid, rw.pixel_values == "flux", form=form,
                           pupil_fill=math.pi / 4 if rw.src["shape"] == "circle" else 1.0, reach_mm=info["reach_mm"],
                           margin_mm=info["margin_mm"])
        cost = pixel_cost(replace(ppl, pixel_field=field), rw.nsrc, rw.size)
        err = debye_err if form == "debye" else kirchhoff_error_estimate(
            field["eps"], field["cubic"], ppl.ray_grid, debye_err["estimate"] if field["reach_mm"] is not None else None,
            RAY_MIN, amp=field.get("amp", 0.0), spreads=field.get("spreads"))
        out[form] = (field, cost, err)
    return out


def choose_form(forms: dict, tolerance: float, explicit: bool, memory_budget_bytes=None) -> tuple:
    """The sensor-field form that runs (``FIELD_FORM`` where it names one; "auto": of the forms :func:`plan_forms`
    planned whose error estimate is within ``tolerance`` and whose memory fits ``memory_budget_bytes``, the one of
    fewer flops; none: the Kirchhoff form for ``"auto"`` (the more accurate: the method is not chosen then), and for
    an explicit ``method="pixel"`` the Kirchhoff form where at most ``KIRCHHOFF_MAX_TILES`` of its tiles are needed,
    else the Debye form). Returns ``(form, reason)``."""
    est = {f: v[2]["estimate"] for f, v in forms.items()}
    flops = {f: v[1]["flops"] for f, v in forms.items()}
    say = ", ".join(f"{f} ~{est[f]:.2g} / {flops[f] / 1e9:.3g} GFLOP" for f in forms)
    if FIELD_FORM in ("debye", "kirchhoff"):
        return FIELD_FORM, f"sensor field form {FIELD_FORM}: FIELD_FORM names it ({say})"
    meet = [f for f in forms if est[f] <= tolerance and (memory_budget_bytes is None
                                                          or forms[f][1]["memory_bytes"] <= memory_budget_bytes)]
    if meet:
        form = min(meet, key=lambda f: flops[f])
        return form, (f"sensor field form {form}: the form of fewer flops whose error estimate is within the "
                      f"tolerance {tolerance:.2g} ({say})")
    if not explicit:
        return "kirchhoff", f"sensor field form kirchhoff: no form's estimate within the tolerance {tolerance:.2g} ({say})"
    form = "kirchhoff" if forms["kirchhoff"][0]["near"] <= KIRCHHOFF_MAX_TILES else "debye"
    return form, (f"sensor field form {form}: no form's estimate within the tolerance {tolerance:.2g} ({say}); "
                  f"method='pixel' asked for: kirchhoff where it needs <= {KIRCHHOFF_MAX_TILES} tiles")


def form_line(form: str, field: dict, cost: dict, err: dict, nf: float, slope: float, ratio: float) -> str:
    """The plan's line of one sensor-field form (:func:`plan_forms`): its error estimate and its parts, its cost."""
    if form == "debye":
        why = (f"{PIXEL_ERROR_C:g} S / sqrt(N_F) (r_A / p)^{PIXEL_ERROR_POWER:g} = {err['debye']:.2g}: rim slope S "
               f"{slope:.3g} rad, N_F {nf:.4g} seen from the patch, p / r_A {ratio:.3g}; + floor {PIXEL_ERROR_FLOOR:g}")
    else:
        sp = field.get("spreads") or {}
        from .pixel_kirchhoff import KIRCHHOFF_INTERFERENCE
        why = (f"tiles {KIRCHHOFF_INTERFERENCE:g} eps^3 / 3 + eps^4 / 4 + 2 eps cubic + cubic^2 + 2 amp eps^2 + amp^2 = "
               f"{err['expansion']:.2g} (eps {field['eps']:.3g}, "
               f"cubic {field['cubic']:.2g} rad, amp {field.get('amp', 0.0):.2g} at a corner of its {field['near']} "
               f"tile(s) of {field['tile']}^2) + the corrections' NUFFT {err['nufft']:.2g} (spreads "
               + ", ".join(f"{g} {v}" for g, v in sp.items()) + "); "
               f"quadrature {err['quadrature']:.2g}"
               + (f"; Debye beyond the tiles {err['far']:.2g}" if field.get("reach_mm") is not None else ""))
    return (f"{form} form: error ~{err['estimate']:.2g} of the peak ({why}), {cost['memory_bytes'] / 2 ** 30:.3g} GiB, "
            f"{cost['flops'] / 1e9:.3g} GFLOP")


def consider_pixel(rw, explicit: bool, pos_s, dir_s, ok, carrier, centers, beam_width_mm: float,
                   rays_per_sample: float = 1.0, tolerance=None, memory_budget_bytes=None, model=None) -> bool:
    """Plan ``method="pixel"`` beside the plan a :class:`rwwarp.wave.raywave.RayWave` (``rw``, at the end of its
    planning) chose, and switch ``rw`` to it where it should run. ``explicit``: ``method="pixel"`` was asked for
    (it runs; a DOE that is not blank is refused with ``ValueError``). Otherwise (``"auto"``) it runs where the
    lens has no DOE (or a blank one), the pixel spans at least ``MIN_PIXEL_AIRY`` Airy radii, a sensor-field form's
    error estimate is at most ``tolerance`` (None: ``DEFAULT_TOLERANCE``; the form of fewer flops among those:
    :func:`plan_forms`, :func:`choose_form`), the model's own
    error (:mod:`rwwarp.wave.model_error`) does not ask for the wave step (a given ``tolerance`` below it), it fits
    ``memory_budget_bytes`` and it plans fewer flops than ``rw.plan``. Pilot arrays as ``RayWave`` holds them
    (mm, (S, N, 3)); ``carrier`` (S, 2) the chief rays' frequencies (cycles/mm), ``centers`` (S, 2) their patch
    centres (mm); ``beam_width_mm``: the footprint's smaller extent on the wave plane. ``rw``: the
    :class:`rwwarp.wave.batch_plan.BatchPlan` planned so far (not changed). Returns ``(plan, chosen)``: when
    chosen, a new plan with the pixel method's ``plan`` (its estimate, error estimate and reasons), ``method``,
    ``focal`` (None), ``carrier``, ``centers`` and ``rim`` (False), and True; otherwise (``"auto"``) a new plan
    whose ``plan`` has a reason saying why not (and ``pixel_alternative`` where it names the pixel method beside
    a plan over the memory budget), and False; ``rw`` itself and False for a lens with a DOE. ``model``: the
    model error of ``rw`` with its patches at ``centers`` already computed (a list of
    :class:`~rwwarp.wave.model_error.ModelError` per source), else computed here."""
    from dataclasses import replace
    from ..doe import is_flat_profile
    from .model_error import estimate_for_raywave
    from .plan import check_budget
    s = rw.lens.surfaces[rw.plane]
    if s.type == "doe" and not is_flat_profile(s.profile):
        if explicit:
            raise ValueError("method='pixel' does not model a DOE (its diffraction orders): use method='auto', "
                             "'focal' or 'asm' for a lens with a DOE that is not blank")
        return rw, False
    pl = rw.plan
    n_after, lam_mm = np.asarray(rw.n_after, float), np.asarray(rw.lam_mm, float)
    freq = (n_after[:, None, None] / lam_mm[:, None, None]) * dir_s[..., :2]
    # the pixel in Airy radii (0.61 / B, as plan_pixel has it) first: auto never takes a pixel this small, and its
    # plan is not made (its reasons' formatting was most of this call's time in a map of small pixels)
    ratio = rw.pixel / (0.61 / pixel_band(ok, freq, carrier))
    if not explicit and ratio < MIN_PIXEL_AIRY:
        # auto never takes it for a pixel this small: its forms are not planned (half a map's planning was theirs)
        return rw.evolved(plan=pl.with_reasons(f"pixel method not chosen: pixel {ratio:.3g} < {MIN_PIXEL_AIRY:g} "
                                                "Airy radii")), False
    ppl, info = plan_pixel(pos_s, ok, freq, carrier, centers, rw.size, rw.pixel, rays_per_sample)
    ratio = rw.pixel / info["airy_mm"]
    # the beam seen from the patch: N_F = n r_w^2 / (lambda R), r_w half the footprint (31 pilot cells: +1/30)
    r_w = 0.5 * beam_width_mm * 31.0 / 30.0
    nf = float(np.min(n_after * r_w ** 2 / (lam_mm * abs(rw.z_sensor - rw.z_plane))))
    if model is None:
        model = estimate_for_raywave(replace(rw, centers=centers))   # the rim slope against the sphere to the chief ray's patch
    slope = max(e.rim_slope_rad for e in model)
    model_err = max(e.estimate for e in model)
    tol = DEFAULT_TOLERANCE if tolerance is None else float(tolerance)
    forms = plan_forms(ppl, info, pos_s, dir_s, ok, centers, lam_mm, n_after, rw, nf, slope)
    form, why_form = choose_form(forms, tol, explicit, memory_budget_bytes)
    field, cost, est = forms[form]
    err = est
    ppl = ppl.evolved(pixel_field=field)
    line = (f"pixel method: error ~{est['estimate']:.2g} of the peak against the full computation ({form} form), "
            f"{cost['memory_bytes'] / 2 ** 30:.3g} GiB, {cost['flops'] / 1e9:.3g} GFLOP")
    form_lines = [form_line(f, *forms[f], nf, slope, ratio) for f in ("debye", "kirchhoff")]
    ppl = ppl.evolved(estimate=cost, model_error=pl.model_error).with_reasons(line, *form_lines, why_form)
    ppl = ppl.with_reasons(field_reason(field, cost))
    if not explicit:
        why = []
        if ratio < MIN_PIXEL_AIRY:
            why.append(f"pixel {ratio:.3g} < {MIN_PIXEL_AIRY:g} Airy radii")
        if err["estimate"] > tol:
            why.append(f"error estimate {err['estimate']:.2g} > tolerance {tol:.2g}")
        if tolerance is not None and model_err > tolerance:
            # the model's own error over the tolerance asks for the wave step, which needs a wave-plane field
            why.append(f"the wave step is wanted (model error ~{model_err:.2g} > tolerance {tol:.2g})")
        if memory_budget_bytes is not None and cost["memory_bytes"] > memory_budget_bytes:
            why.append("over the memory budget")
        if pl.estimate and cost["flops"] >= pl.estimate["flops"]:
            why.append(f"not fewer flops than {pl.method} ({pl.estimate['flops'] / 1e9:.3g} GFLOP)")
        if why:
            alt = rw.pixel_alternative
            if ratio >= MIN_PIXEL_AIRY:   # named where the chosen plan is over the memory budget
                alt = (f"; or the pixel method ({cost['memory_bytes'] / 2 ** 30:.3g} GiB, error "
                       f"~{err['estimate']:.2g} of the peak): method='pixel' or tolerance >= {err['estimate']:.2g}")
            return rw.evolved(plan=pl.with_reasons(f"pixel method not chosen: {'; '.join(why)} ({line})",
                                                    *form_lines),
                           pixel_alternative=alt), False
        ppl = ppl.with_reasons(f"method auto: pixel ({ratio:.3g} Airy radii, error ~{err['estimate']:.2g} <= tolerance "
                               f"{tol:.2g}, {cost['flops'] / 1e9:.3g} GFLOP against {pl.method} "
                               f"{pl.estimate['flops'] / 1e9:.3g} GFLOP)")
    else:
        ppl = ppl.with_reasons("method pixel (asked for)")
    if memory_budget_bytes is not None:
        check_budget(cost, int(memory_budget_bytes), f"the pixel method ({ppl.ray_grid}^2 rays, sensor grid "
                     f"{ppl.n_sensor}^2, FFT {ppl.n_sensor_fft}^2)", "size (patch pixels), the beam's NA (band B), "
                     "rays_per_sample")
    return rw.evolved(plan=ppl, method="pixel", focal=None, rim=False, carrier=np.array(carrier, float),
                   centers=np.array(centers, float)), True
