"""The sensor field of ``method="pixel"`` as the Kirchhoff (Rayleigh-Sommerfeld) sum of the wave-plane field, tile
by tile through the non-uniform FFT (issue 27 item 5).

The Debye form (:mod:`rwwarp.wave.pixel_scale`: one plane wave per ray) leaves out the boundary wave of the
wave-plane field's hard edge: measured 1.2e-3 of the peak on the DeepLens EF35 f/2 on axis and 1.9e-3 on the
Cooke triplet at 14 deg against the full computation, following no sampling knob (``perf/pixel_study.py``). This
form sums the wave-plane field itself, rim included, with the exact kernel
``G = (n / (i lambda)) (dz / r) exp(i k0 n r) / r`` (first Rayleigh-Sommerfeld; ``k0 = 2 pi / lambda``):

* the rays continued straight to the wave plane ``z_w`` give its samples ``p_j``, optical path ``L_j``, field
  ``|W_j| = sqrt(q_j / (d_z,j dA_j))`` (the flux through the plane is the ray's power ``q_j``; ``dA_j`` its tube's
  area there, :func:`rwwarp.wave.pixel_scale.tube_areas`), the sum's weight ``W_j dA_j``;
* for a tile of the sensor grid centred at ``X``, ``r_j = |X - p_j|``, ``u_j = (X - p_j) / r_j``; a sample
  ``X + D`` (``D`` in the sensor plane) is at ``|X + D - p| = r + u.D + (|D|^2 - (u.D)^2) / (2 r) - (u.D) (|D|^2 -
  (u.D)^2) / (2 r^2) + ...``. The linear term is a plane wave of frequency ``n u_xy / lambda``: the type-1
  non-uniform FFT onto the tile. The quadratic one, ``eps_j(D) = k0 n sum_a g_a,j b_a(D)`` with
  ``g = ((1 - u_x^2) / (2 r), -u_x u_y / r, (1 - u_y^2) / (2 r))`` on the monomials ``b = (D_x^2, D_x D_y, D_y^2)``,
  is split into its midrange over the rays (a phase common to the tile's samples, which ``|U|^2`` and
  ``Re(conj(U) U_w)`` do not see) and the rest, taken to second order (``exp(i eps) ~ 1 + i eps - eps^2 / 2``: 3 + 6
  more transforms); the cubic term on its 4 monomials (4; its midrange dropped likewise) and the amplitude's change
  ``dz / r^2`` to first order (2: each sample's rest from the midrange of ``u_xy / r``; the common change, exactly
  ``r^2 / |R + D|^2`` for the midrange's sample, multiplies the tile). (Before: the quadratic term on 4 coefficients
  of the redundant basis ``|D|^2, -D_x^2, -D_x D_y, -D_y^2`` and the cubic one on 6: 4 + 10 + 6 transforms for the
  same sums, and the common amplitude change to first order only: 2.5e-5 of the peak off the Rayleigh-Sommerfeld test,
  now 1.9e-6.)
* ``U_w`` (for ``pixel_values="flux"``): each term times ``u_z``, the obliquity towards the tile (its first-order
  rest with the rays' mean ``u_z``).

The quadrature over the pupil grid's cells has its aliases ``lambda z / (n delta_p)`` away (0.65 mm on the EF35 at
601 rays), beyond the grid as the Debye form's. Cost (:func:`tile_cost`, :func:`rwwarp.wave.pixel_scale.pixel_cost`):
per tile ``N_TERMS`` (16; 17 for ``U_w``) NUFFTs of every wave-plane sample, the plane waves at the NUFFT's full
spread, each group of corrections at the narrowest spread its size allows (:func:`group_spreads`: the gridding error
times the group's size within ``KIRCHHOFF_NUFFT_ERROR``); tiles ``2 a`` wide with ``k0 n 2 a^2 max|g - mid g| <=
KIRCHHOFF_EPS`` (at most ``KIRCHHOFF_TILE_MAX``) and the expansion's estimated error within
``KIRCHHOFF_EXPANSION_MAX``. The spreading is most of it (every tile takes every wave-plane sample: ~0.39 M on the
EF50 f/1.8 at 15.3 um, 64 px). Memory: one tile at a time, its vectors in chunks whose grids fit
``KIRCHHOFF_GRID_BYTES``. Arrays: numpy or CuPy (``xp``).

Where it runs (:func:`rwwarp.wave.pixel_scale.plan_field`): on the fewest tiles (:func:`region_tiles`, each at most
:func:`tile_limit` a side, the curvature seen from the region's corners, and as large as keeps the expansion's
estimate within ``KIRCHHOFF_EXPANSION_MAX``) that cover the spot's region, the pilot landings' box widened by 12 / B a
side; the Debye form's samples elsewhere (the two differ by < 2e-6 of the peak there on the A489 test). EF50 f/1.8 at
10 deg, 15.3 um, 64 px: 4 tiles of 242 (eps 0.113 rad), 19.4 GFLOP, against 12 of 148 (eps 0.042, 23 + 1 NUFFTs,
all corrections at ``REST_SPREAD``), 39.5 GFLOP, before; the two differ by at most 1.1e-5 of the peak.

Error estimate (:func:`kirchhoff_error_estimate`; "auto" compares it with the tolerance, ``--explain`` prints its
parts): the tile part from the planned tiles' rests (the expansion's single-family terms derived, its interference
term calibrated: ``KIRCHHOFF_INTERFERENCE``; the corrections' NUFFT per group), a quadrature part 7.5e-5
(calibrated: the median of the calibration cases' measured error less their tile part: EF35 f/2 on axis and 2 deg,
EF50 f/1.8 and RF50 f/1.8 on axis (5 px), RF50 2 deg, Cooke triplet 0 / 14 deg (9 px): 0.8-3.2x the measured), and
1 % of the Debye form's estimate where its samples are kept beyond the tiles. Against measured errors
(``perf/pixel_auto.py``; the full computation on the central 9 px, focal at 9x finer pixels box-summed; this CPU;
at 6ae611f): 64 px at the lens's own 15.3 um pixel, the Kirchhoff form where "auto" takes it: EF50 f/1.8 0 deg
4.6e-5 (est 2.9e-4), 10 deg 4.8e-5 (5.4e-4), EF35 f/2 0 deg 3.8e-5 (2.4e-4), 10 deg 2.7e-4 (4.0e-4), EF85 f/1.8 0 deg
2.9e-5 (2.0e-4), RF50 10 deg 1.0e-4 (2.0e-4), EF100 f/2.8 0 deg 4.3e-4 (1.3e-4), 10 deg 1.05e-4 (3.2e-4), EF40 f/2.8
0 deg 3.2e-4 (1.5e-4), Sigma 70 f/2.8 0 deg 1.7e-4 (1.2e-4); the A489 on axis, 5 px, 300 rays, 6.5e-5 (est 2.0e-4,
``tests/rwwarp/test_pixel_scale.py``). So the estimate is 0.3-11x the measured error: a scale (1e-4 to 5e-4), not a
bound; every measured error of the form is below 1e-3 (largest 8.5e-4, EF85 10 deg on 9 px at 601 rays, before these
changes; 2.6e-4 at 64 px, 672 rays, in the Debye form that "auto" takes there). What it misses: on the f/2.8 lenses
at ``RAY_MIN`` = 601 rays across, 1.7-4.3e-4, moving with the rays but not monotonically
(:data:`KIRCHHOFF_QUAD_ERROR`), at the level the full computation itself is converged to; not resolved here.
"""
from __future__ import annotations

import math

import numpy as np

#: the largest phase rest (rad) at a tile's corner, taken to second order: the tile's largest size (0.05 before: the
#: EF50 f/1.8 at 10 deg in 12 tiles of 148, 39.5 GFLOP; at 0.12 4 of 242, the expansion's estimate within
#: KIRCHHOFF_EXPANSION_MAX deciding; docs/propagation.md)
KIRCHHOFF_EPS = 0.12
#: largest tile side (samples): one weight vector's NUFFT grids ((2 x 1024)^2 cells, GRID_CELL_BYTES a cell) stay ~220 MiB
KIRCHHOFF_TILE_MAX = 1024
#: bytes the NUFFT grids of one tile may take at once: its weight vectors go through in chunks that fit
KIRCHHOFF_GRID_BYTES = 256 * 2 ** 20
#: bytes a NUFFT grid cell takes per weight vector at the peak of :func:`rwwarp.wave.nufft.nufft_type1`
#: (the complex accumulator, its FFT and the FFT's temporary: 51 measured with tracemalloc; tests/rwwarp/test_pixel_cost.py)
GRID_CELL_BYTES = 52
#: bytes a wave-plane sample takes in one tile beside its weight vectors and the NUFFT's spreading arrays: its kernel
#: terms (distance, direction, weight, quadratic and cubic coefficients, NUFFT phases); and the spreading arrays'
#: bytes a sample and cell row of the footprint (2 spread rows: Gaussians, indices, products). tracemalloc in
#: tests/rwwarp/test_pixel_cost.py
POINT_BYTES = 240
SPREAD_ROW_BYTES = 44
#: the NUFFT's spreading half-width (cells) for the tile's correction terms (all but U's and U_w's plane waves): each is
#: below KIRCHHOFF_EPS (~5%) of the field, so the NUFFT's 1.7e-3 at 3 (against 3.5e-6 at NUFFT_SPREAD = 6, of the
#: term's own size) is ~1e-4 of the field; the Rayleigh-Sommerfeld test's error stayed 2.4e-5 / 7.4e-6 (6: 2.5e-5 /
#: 7.5e-6). 36 cells a point instead of 144: the spreading, most of the work, ~3x less
REST_SPREAD = 3
#: the terms of one tile, each a NUFFT weight vector: U's 1 (the plane waves), 3 + 6 (the quadratic rest to second
#: order, on the 3 quadratic monomials D_x^2, D_x D_y, D_y^2), 2 (the amplitude's first-order change), 4 (the cubic
#: phase, on the 4 cubic monomials); U_w ("flux") one more. (Before: 4 + 10 and 6 on the redundant basis |D|^2, D_x^2,
#: D_x D_y, D_y^2 and |D|^2 D_x, ...: 23 terms for the same sums.)
N_TERMS = 16
#: the NUFFT spreads of a tile's correction groups (:func:`group_spreads`): each group (``lin``: the quadratic rest to
#: first order, size ``eps``; ``quad``: second order, ``eps^2 / 2``; ``amp``; ``cub``) the narrowest spread (at least
#: ``MIN_SPREAD``) whose Gaussian gridding error ``2 exp(-pi s (R - 1/2) / R)`` of the field (R = 2; REST_SPREAD's
#: 1.7e-3 at 3), times the group's size and doubled in the intensity, stays below this (of the peak)
KIRCHHOFF_NUFFT_ERROR = 4e-5
MIN_SPREAD = 2
#: the correction groups, in the order of their vectors (:func:`_terms`)
GROUPS = ("lin", "quad", "amp", "cub")


#: the corrections' NUFFT error per unit of their size at REST_SPREAD, in the intensity: 2 gridding_error(3) (kept for
#: callers; the estimate takes each group at its own spread now)
KIRCHHOFF_REST_ERROR = 3.4e-3
#: :func:`kirchhoff_error_estimate`: the pupil quadrature's share (the rays as point samples of whole cells, the rim a
#: staircase of them), with the reference's own convergence (~1e-4: docs "What the error follows"): the calibration
#: cases' measured error less their tile part, their median (module docstring). Not a model of the rays: 0.6-1.1e-4
#: at 300 rays across (A489, Cooke triplet, small patches); on the f/2.8 camera lenses on axis, 64 px, 1.7-4.3e-4 at 601
#: rays and not monotonic in them (601 / 721 / 901: EF100 4.3 / 2.7 / 1.5e-4, EF40 3.2 / 2.7 / 0.98e-4, Sigma 70
#: 1.7 / 1.9 / 3.5e-4), the level the reference itself is converged to (~1e-4: docs "What the error follows"); the f/1.8
#: lenses at 630-760 rays 3-5e-5. The part of the estimate that under-estimates there (2-3x)
KIRCHHOFF_QUAD_ERROR = 7.5e-5
#: :func:`kirchhoff_error_estimate`: the Debye samples beyond the near tiles, this fraction of the Debye form's
#: estimate (measured against the Kirchhoff form on every tile: EF35 / EF50 at 64 px 7.6e-6 / 1.4e-6, A489 9 px
#: 7.6e-7: 0.005 / 0.0008 / 0.002 of their Debye estimates)
KIRCHHOFF_FAR_SHARE = 0.01
#: :func:`kirchhoff_error_estimate`: the share of the bound ``eps^3 / 3`` (two families of rays interfering, each with
#: its own third-order rest) taken for the tiles' expansion. Calibrated: the largest tiles against tiles 2-4x smaller
#: (FIELD_FORM "kirchhoff", the same rays; max |difference| / peak): EF50 f/1.8 64 px 0 deg 6.2e-7 (eps 0.068 against
#: 0.017 rad), 10 deg 1.1e-5 (0.113 / 0.042); EF35 f/2 0 deg 2.7e-6 (0.052 / 0.013); EF100 f/2.8 10 deg 5.9e-6 (0.088 /
#: 0.017); RF50 f/1.8 10 deg 8.5e-6 (0.046 / 0.015); A489 9 px 3.5e-5 (0.054 / 0.013): 0.002-0.27 of eps^3 / 3 (the
#: A489's 0.67 within its derived cubic part, 2 eps cubic = 5.6e-4); the whole difference taken as this term, 0.3 is
#: above each. (A field of one family of rays sees the truncation as a phase error: e^4 / 4 in |U|^2, derived.)
KIRCHHOFF_INTERFERENCE = 0.3
#: the tiles' side: the largest whose expansion's estimated error (:func:`kirchhoff_error_estimate`'s ``expansion``)
#: is within this (of the peak), its quadratic rest at most KIRCHHOFF_EPS (rwwarp.wave.pixel_scale.plan_field)
KIRCHHOFF_EXPANSION_MAX = 4e-4


def gridding_error(spread: int) -> float:
    """The Gaussian gridding's error of :func:`rwwarp.wave.nufft.nufft_type1` at half-width ``spread`` (cells, R = 2),
    relative to the term's own size in the field: ``2 exp(-pi spread 3 / 4)`` (1.7e-3 at 3, 1.6e-4 at 4)."""
    return 2.0 * math.exp(-0.75 * math.pi * int(spread))


def group_sizes(eps_rad: float, cubic_rad: float, amp: float) -> dict:
    """The largest size (of the field's terms, at a tile's corner) of each correction group: ``lin`` ``eps``, ``quad``
    ``eps^2 / 2``, ``amp`` the amplitude's change ``amp``, ``cub`` the cubic phase."""
    e = abs(float(eps_rad))
    return {"lin": e, "quad": 0.5 * e * e, "amp": abs(float(amp)), "cub": abs(float(cubic_rad))}


def group_spreads(eps_rad: float, cubic_rad: float, amp: float) -> dict:
    """The NUFFT spread of each correction group (:data:`GROUPS`): the narrowest (``MIN_SPREAD`` .. ``REST_SPREAD``
    + 2) with ``2 size gridding_error(s) <= KIRCHHOFF_NUFFT_ERROR`` (:func:`group_sizes`)."""
    out = {}
    for g, size in group_sizes(eps_rad, cubic_rad, amp).items():
        s = MIN_SPREAD
        while s < REST_SPREAD + 2 and 2.0 * size * gridding_error(s) > KIRCHHOFF_NUFFT_ERROR:
            s += 1
        out[g] = s
    return out


def kirchhoff_error_estimate(eps_rad: float, cubic_rad: float, ray_grid: int, debye_estimate: float | None = None,
                             ray_min: int = 600, amp: float = 0.0, spreads: dict | None = None) -> dict:
    """The estimated error of the Kirchhoff form (``method="pixel"``, :func:`kirchhoff_samples`) against the full
    computation (the same rays' wave-plane field propagated exactly), max |difference| over the PSF's peak, and its
    parts. The form sums the wave-plane field with the exact kernel, so what is left is what it approximates:

    * ``tile``: the kernel's expansion over a tile, ``expansion``: the quadratic rest (``eps_rad`` at the tile's
      corner) to second order, the cubic phase's rest (``cubic_rad``) and the amplitude's rest (``amp``) to first,
      neither multiplied by the quadratic rest. Where one family of rays makes the field at a sample (one stationary
      point), their truncation is a phase error and an amplitude error of that family: in ``|U|^2``
      ``|1 + i e - e^2 / 2|^2 - 1 = e^4 / 4``, ``2 eps cubic + cubic^2`` (the cubic phase's missing product with the
      quadratic one, and its square) and ``2 amp eps^2``: derived. Where two families interfere, the third-order term
      ``eps^3 / 6`` of each differs and enters their interference to first order: at most ``eps^3 / 3``; measured
      0.002-0.27 of that, ``KIRCHHOFF_INTERFERENCE`` = 0.3 of it taken (calibrated; its cases where it is defined).
      (The amplitude's term is conservative by 2: ``|(1 + a) e^(i e)|^2`` less the truncated sum's is ``a e^2``.) Then the corrections' NUFFT (each group at
      its spread, ``spreads`` from :func:`group_spreads`; None: all at ``REST_SPREAD``), ``nufft``:
      ``2 sum_groups size gridding_error(spread)``;
    * ``quadrature``: the pupil grid's cells as point samples (whole cells at the rim; the lattice's aliases beyond
      the grid), calibrated: ``KIRCHHOFF_QUAD_ERROR``; measured alike at 300 and 600 rays across (``ray_grid``,
      ``ray_min``: kept in the signature, not used: the planner takes ``RAY_MIN`` = 600 or more; the Debye form's
      aliases' skirts grew its error below ~300);
    * ``far``: where the Debye form's samples are kept beyond the near tiles (``debye_estimate`` given,
      :func:`rwwarp.wave.pixel_scale.pixel_error_estimate`), ``KIRCHHOFF_FAR_SHARE`` of it.

    Validated against measured errors in ``perf/pixel_auto.py`` (the table in the module docstring of
    :mod:`rwwarp.wave.pixel_scale`). Returns ``estimate`` (the sum) and the parts (dimensionless): ``tile`` (with
    ``expansion`` and ``nufft``, its two shares)."""
    eps, cub, am = abs(float(eps_rad)), abs(float(cubic_rad)), abs(float(amp))
    sizes = group_sizes(eps, cub, am)
    sp = spreads if spreads is not None else {g: REST_SPREAD for g in GROUPS}
    nufft = 2.0 * sum(sizes[g] * gridding_error(sp[g]) for g in GROUPS)
    expansion = (KIRCHHOFF_INTERFERENCE * eps ** 3 / 3.0 + eps ** 4 / 4.0 + 2.0 * eps * cub + cub ** 2
                 + 2.0 * am * eps ** 2 + am ** 2)
    tile = expansion + nufft
    quad = KIRCHHOFF_QUAD_ERROR
    far = KIRCHHOFF_FAR_SHARE * float(debye_estimate) if debye_estimate is not None else 0.0
    return {"estimate": float(tile + quad + far), "tile": float(tile), "expansion": float(expansion),
            "nufft": float(nufft), "quadrature": float(quad), "far": float(far)}


def tile_rests(P, T, lam_mm: float, n_med: float, h_mm: float, nt: int, norm: float) -> tuple:
    """``(eps, cubic, amp)`` at the corners of a tile of ``nt`` samples of ``h_mm`` centred at ``T`` (3,) (mm): the
    quadratic rest ``k0 n 2 a^2 norm`` (rad; ``a`` the half side, ``norm`` from :func:`tile_limit`), the largest cubic
    phase ``k0 n |u.D| (|D|^2 - (u.D)^2) / (2 r^2)`` (rad) and the largest first-order change of the amplitude
    ``2 |u.D| / r`` over the wave-plane samples ``P`` (J, 3) (mm) and the corners and edge midpoints ``D``, the last two
    less their midrange over the samples (:func:`kirchhoff_samples` takes the midrange of the cubic phase as a phase
    common to the tile's samples, unseen in ``|U|^2``, and that of the amplitude's change as a common factor). numpy."""
    kn = 2.0 * math.pi / lam_mm * n_med
    a = 0.5 * int(nt) * h_mm
    P = np.asarray(P, float)
    d = np.asarray(T, float) - P
    r = np.sqrt(np.sum(d * d, -1))
    u = d / r[:, None]
    mid = lambda v: v - 0.5 * (np.max(v, -1, keepdims=True) + np.min(v, -1, keepdims=True))
    c = mid(np.stack(_cubic(r, u)))             # the cubic phase less its midrange (common: dropped, unseen in |U|^2)
    al = u[:, :2] / r[:, None]                  # the amplitude's change -2 a.D less its midrange (a common factor)
    alm = 0.5 * (al.max(0) + al.min(0))
    cub, amp = 0.0, 0.0
    for Dx, Dy in ((a, a), (a, -a), (a, 0.0), (0.0, a)):
        m = np.array([Dx ** 3, Dx * Dx * Dy, Dx * Dy * Dy, Dy ** 3])
        cub = max(cub, float(np.max(kn * np.abs(m @ c))))
        amp = max(amp, float(np.max(2.0 * np.abs((al - alm) @ np.array([Dx, Dy])))))
    return kn * 2.0 * a * a * float(norm), cub, amp


#: the vectors of each correction group (:func:`_terms`)
GROUP_VECTORS = {"lin": 3, "quad": 6, "amp": 2, "cub": 4}


def calls(kc: int, spreads: dict | None = None) -> list:
    """The correction NUFFT calls of one tile: ``[(vectors, spread), ...]``, the groups (:data:`GROUPS`) of one spread
    together (``spreads``: group -> spread, :func:`group_spreads`; None: all at ``REST_SPREAD``), in chunks of at most
    ``kc`` vectors. The plane waves (1, or 2 for "flux") go first in their own call at ``NUFFT_SPREAD``."""
    sp = spreads if spreads is not None else {g: REST_SPREAD for g in GROUPS}
    out = []
    for s in sorted({int(sp[g]) for g in GROUPS}, reverse=True):
        k = sum(GROUP_VECTORS[g] for g in GROUPS if int(sp[g]) == s)
        out += [(min(kc, k - c0), s) for c0 in range(0, k, kc)]
    return out


def n_vectors(flux: bool) -> int:
    """Number of NUFFT weight vectors per tile (:data:`N_TERMS`, one more for ``pixel_values="flux"``)."""
    return N_TERMS + (1 if flux else 0)


def chunk_vectors(nt: int, points: int, flux: bool, grid_bytes: int | None = None) -> int:
    """How many of a tile's weight vectors go through the NUFFT at once: the most whose grids
    (``GRID_CELL_BYTES`` a cell of the ``(2 nt)^2`` oversampled grid, ``nt`` the tile's side) and vectors (16 bytes
    a point) fit ``grid_bytes`` (None: ``KIRCHHOFF_GRID_BYTES``), at least one."""
    from .nufft import NUFFT_OVERSAMPLE
    M = NUFFT_OVERSAMPLE * int(nt)
    b = KIRCHHOFF_GRID_BYTES if grid_bytes is None else int(grid_bytes)
    return max(1, min(n_vectors(flux), b // (GRID_CELL_BYTES * M * M + 16 * int(points))))


def _coefficients(r, u, xp):
    """(3, J): ``g = ((1 - u_x^2) / (2 r), -u_x u_y / r, (1 - u_y^2) / (2 r))`` (1/mm) of the quadratic term
    ``(|D|^2 - (u.D)^2) / (2 r) = sum_a g_a b_a(D)`` on the monomials ``b = (D_x^2, D_x D_y, D_y^2)``."""
    ux, uy = u[:, 0], u[:, 1]
    return xp.stack([0.5 * (1.0 - ux * ux) / r, -ux * uy / r, 0.5 * (1.0 - uy * uy) / r])


def _cubic(r, u, xp=np):
    """The four coefficients (1/mm^2) of the third-order phase ``-(u.D) (|D|^2 - (u.D)^2) / (2 r^2)`` on the
    monomials ``(D_x^3, D_x^2 D_y, D_x D_y^2, D_y^3)``: ``c ((u.D)^3 - (u.D) |D|^2)``, ``c = 1 / (2 r^2)``."""
    ux, uy, c = u[:, 0], u[:, 1], 0.5 / (r * r)
    return (c * (ux ** 3 - ux), c * (3.0 * ux * ux * uy - uy), c * (3.0 * ux * uy * uy - ux), c * (uy ** 3 - uy))


def _rest_norm(g, xp):
    """The largest ``|sum_a (g_a - mid g_a) b_a(D)| / |D|^2`` over the rays and directions (1/mm): the spectral norm
    of the rest's 2 x 2 form ``[[d0, d1 / 2], [d1 / 2, d2]]``, ``mid``: the midrange over the rays."""
    d = g - 0.5 * (xp.max(g, 1) + xp.min(g, 1))[:, None]
    a, c, b = d[0], d[2], 0.5 * d[1]
    return float(xp.max(xp.abs(0.5 * (a + c)) + xp.sqrt(0.25 * (a - c) ** 2 + b * b)))


def tile_limit(P, points_T, lam_mm: float, n_med: float, h_mm: float, tile_max: int = KIRCHHOFF_TILE_MAX,
               xp=np) -> tuple:
    """``(nt_max, norm)``: the largest even tile side (samples of ``h_mm``) whose quadratic rest stays below
    ``KIRCHHOFF_EPS`` rad at its corners (``k0 n 2 a^2 norm``, ``a`` the half side, ``norm`` (1/mm) the rest's largest
    spread over the wave-plane samples ``P`` (J, 3) (mm), :func:`_rest_norm`), seen from each point of ``points_T``
    ((m, 3) mm: the tiles' centres or their region's corners; the largest norm), at most ``tile_max``."""
    k0 = 2.0 * math.pi / lam_mm
    P = xp.asarray(P, dtype=xp.float64)
    norm = 0.0
    for T in np.atleast_2d(np.asarray(points_T, float)):
        Tx = xp.asarray(T)
        r0 = xp.sqrt(xp.sum((Tx - P) ** 2, -1))
        norm = max(norm, _rest_norm(_coefficients(r0, (Tx - P) / r0[:, None], xp), xp))
    half = math.sqrt(KIRCHHOFF_EPS / (k0 * n_med * 2.0 * max(norm, 1e-30)))     # a: |D|^2 <= 2 a^2
    return max(8, min(int(tile_max), 2 * int(half / h_mm))), norm


def region_tiles(region, nt_max: int, n: int) -> tuple:
    """``(nt, origins)``: the fewest square tiles of at most ``nt_max`` (even) samples a side that cover ``region``
    ``(y0, y1, x0, x1)`` (sample indices of the ``n``-sample grid, half-open), all of one side ``nt`` (even, the
    smallest that covers it in that count), ``origins`` their first samples ``(sy, sx)`` (kept inside the grid:
    a last tile may overlap its neighbour)."""
    y0, y1, x0, x1 = (int(v) for v in region)
    wy, wx = max(1, y1 - y0), max(1, x1 - x0)
    ty, tx = math.ceil(wy / nt_max), math.ceil(wx / nt_max)
    nt = min(nt_max, 2 * math.ceil(max(wy / ty, wx / tx) / 2), 2 * (n // 2))
    fit = lambda s: max(0, min(int(s), n - nt))
    return nt, tuple((fit(y0 + i * nt), fit(x0 + j * nt)) for i in range(ty) for j in range(tx))


def kirchhoff_tiles(P, T, lam_mm: float, n_med: float, h_mm: float, n: int, tile_max: int = KIRCHHOFF_TILE_MAX,
                    xp=np):
    """``(n_t, t)``: the sensor grid of ``n`` samples a side in ``t x t`` tiles of ``n_t`` (even) for
    :func:`kirchhoff_samples`: the quadratic term's rest, spread over the wave-plane samples ``P`` (J, 3) (mm)
    seen from the patch centre ``T`` (3,), below ``KIRCHHOFF_EPS`` rad at a tile's corner; ``n_t <= tile_max``."""
    nt, _ = tile_limit(P, [T], lam_mm, n_med, h_mm, tile_max, xp)
    t = max(1, int(math.ceil(n / nt)))
    return 2 * int(math.ceil(n / (2 * t))), t


def _terms(w, r, u, flux, xp):
    """The tile's weight vectors as ``(make, key)`` pairs, in the order of :func:`_coefficient`: ``make()`` the (J,)
    complex vector (made when its chunk runs), ``key`` what it multiplies in ``U`` / ``U_w``."""
    g = _coefficients(r, u, xp)
    g = g - 0.5 * (xp.max(g, 1) + xp.min(g, 1))[:, None]
    pairs = [(a, b) for a in range(3) for b in range(a, 3)]
    mid = lambda v: v - 0.5 * (xp.max(v) + xp.min(v))
    cub = [mid(c) for c in _cubic(r, u, xp)]    # less the midrange: a phase common to the tile, unseen in |U|^2
    al = [mid(u[:, i] / r) for i in range(2)]   # less the midrange: the common factor amp_factor() applies
    out = [(lambda: w, ("one",))]
    out += [(lambda a=a: w * g[a], ("lin", a)) for a in range(3)]
    out += [(lambda a=a, b=b: w * g[a] * g[b], ("quad", a, b)) for a, b in pairs]
    out += [(lambda i=i: w * al[i], ("amp", i)) for i in range(2)]
    out += [(lambda i=i: w * cub[i], ("cub", i)) for i in range(4)]
    out += [(lambda: w * u[:, 2], ("flux",))] if flux else []
    return out


def _coefficient(key, Dx, Dy, kn):
    """What the NUFFT of the term ``key`` (:func:`_terms`) multiplies in ``U`` at ``D = (Dx, Dy)`` (mm; arrays that
    broadcast to the tile), and the factor its share of ``U_w`` takes beside the rays' mean ``u_z``."""
    basis = lambda a: (Dx ** 2, Dx * Dy, Dy ** 2)[a]
    if key[0] == "one":
        return 1.0, 0.0
    if key[0] == "lin":        # exp(i eps) to second order: 1 + i eps - eps^2 / 2, eps = kn sum_a g_a b_a
        return (1j * kn) * basis(key[1]), 1.0
    if key[0] == "quad":
        a, b = key[1], key[2]
        return (-0.5 * kn * kn * (1.0 if a == b else 2.0)) * basis(a) * basis(b), 1.0
    if key[0] == "amp":        # the amplitude dz / r^2 at X + D: times 1 - 2 u.D / r to first order
        return -2.0 * (Dx, Dy)[key[1]], 1.5
    if key[0] == "cub":
        # the third-order phase -(u.D) (|D|^2 - (u.D)^2) / (2 r^2), to first order (< 0.01 rad: a u-odd phase, a
        # shift of the spot between tiles, measured 6e-3 of the peak on an f/10 lens with 0.33 mm tiles without it)
        return (1j * kn) * (Dx ** 3, Dx ** 2 * Dy, Dx * Dy ** 2, Dy ** 3)[key[1]], 1.0
    return 0.0, None            # "flux": U_w's plane waves, times 1


def near_tiles(n: int, nt: int, t: int, h_mm: float, reach_mm: float | None):
    """The tiles ``(ay, ax)`` of the ``n``-sample grid (``t x t`` tiles of ``nt``, laid as :func:`kirchhoff_samples`
    lays them, pitch ``h_mm``) that come within ``reach_mm`` of its centre (all where ``reach_mm`` is None)."""
    out = []
    for ay in range(t):
        for ax in range(t):
            gap = []
            for a in (ay, ax):      # the tile's samples (m - n/2) h, m = a nt .. min(a nt + nt, n) - 1: distance from 0
                lo, hi = (a * nt - n // 2) * h_mm, (min(a * nt + nt, n) - 1 - n // 2) * h_mm
                gap.append(max(lo, -hi, 0.0))
            if reach_mm is None or math.hypot(*gap) <= reach_mm:
                out.append((ay, ax))
    return out


def kirchhoff_samples(P, L, amp_dA, lam_mm: float, n_med: float, T, carrier, h_mm: float, n: int, flux: bool,
                      xp=np, tile_max: int = KIRCHHOFF_TILE_MAX, grid_bytes: int | None = None, base=None,
                      reach_mm: float | None = None, tiling=None, spreads: dict | None = None):
    """``|U|^2`` (``flux`` False) or ``Re(conj(U) U_w)`` on the sensor grid ``T + (m - n/2) h`` (mm; ``m = 0 ..
    n-1`` per axis, array ``[y, x]``), ``U`` the Rayleigh-Sommerfeld sum of the wave-plane samples.

    ``P`` (J, 3) the samples on the wave plane (mm), ``L`` (J,) their optical paths (mm), ``amp_dA`` (J,) complex
    ``W_j dA_j`` without the phase ``exp(i k0 L)`` (sqrt(power) x mm), ``T`` (3,) the patch centre on the sensor
    (mm), ``carrier`` (2,) the frequency the grid is centred on (cycles/mm), ``h_mm`` the grid's pitch (it must
    sample the samples' frequencies ``n u_xy / lambda`` within +-1 / (2 h) of ``carrier``). Tiles as
    :func:`kirchhoff_tiles` (``tile_max``), one after the other; a tile's weight vectors go through the NUFFT in
    chunks (:func:`chunk_vectors`, ``grid_bytes``), so memory is bounded whatever ``n``. ``reach_mm``: only the tiles
    within it of ``T`` (:func:`near_tiles`), the others taken from ``base`` ((n, n), e.g. the Debye form's samples;
    not changed). ``tiling``: ``(nt, origins)`` (:func:`region_tiles`: tiles of ``nt`` samples starting at
    ``origins`` ``(sy, sx)``, the planned region near the spot) instead of the regular tiles; the samples beyond them
    from ``base`` (zeros where None). ``spreads``: the correction groups' NUFFT spreads (:func:`group_spreads`, as
    planned; None: all at ``REST_SPREAD``). Returns (n, n) float64 in ``xp``. Raises ``FloatingPointError`` where a frequency lies beyond the
    grid's band."""
    from . import nufft
    k0 = 2.0 * math.pi / lam_mm
    kn = k0 * n_med
    P = xp.asarray(P, dtype=xp.float64)
    T = np.asarray(T, float)
    if tiling is not None:
        nt, origins = int(tiling[0]), [tuple(int(v) for v in o) for o in tiling[1]]
        if nt % 2 or nt > n or any(min(o) < 0 or max(o) > n - nt for o in origins):
            raise ValueError(f"kirchhoff_samples: tiling {nt} samples at {origins} does not fit the {n}-sample grid")
    else:
        nt, t = kirchhoff_tiles(P, T, lam_mm, n_med, h_mm, n, tile_max, xp)
        origins = [(ay * nt, ax * nt) for ay, ax in near_tiles(n, nt, t, h_mm, reach_mm)]
    kc = chunk_vectors(nt, len(P), flux, grid_bytes)
    if reach_mm is not None and base is None:
        raise ValueError("kirchhoff_samples: reach_mm needs base, the samples of the tiles beyond it")
    out = xp.zeros((n, n)) if base is None else xp.array(base, dtype=xp.float64, copy=True)
    m = xp.asarray(np.arange(-nt // 2, nt // 2) * h_mm)
    Dy, Dx = m[:, None], m[None, :]
    for sy, sx in origins:
        m0y, m0x = sy + nt // 2 - n // 2, sx + nt // 2 - n // 2
        X = xp.asarray([T[0] + m0x * h_mm, T[1] + m0y * h_mm, T[2]])
        d = X - P
        r = xp.sqrt(xp.sum(d * d, -1))
        u = d / r[:, None]
        del d
        w = amp_dA * xp.exp(1j * k0 * (L + n_med * r)) * (n_med / (1j * lam_mm)) * u[:, 2] / r
        tx = 2.0 * math.pi * (n_med * u[:, 0] / lam_mm - carrier[0]) * h_mm
        ty = 2.0 * math.pi * (n_med * u[:, 1] / lam_mm - carrier[1]) * h_mm
        if float(xp.max(xp.abs(tx))) >= math.pi or float(xp.max(xp.abs(ty))) >= math.pi:
            raise FloatingPointError("pixel method (Kirchhoff form): a wave-plane sample's direction to the "
                                     "patch lies beyond the sensor grid's band: please report this lens and field")
        # U_w: each term times u_z (dz / r: its change 1 - u.D / r); the rests with the rays' mean u_z (u_z
        # spreads by ~3% at f/2, the rests are < KIRCHHOFF_EPS of the field: ~1e-3 of a term ~1e-3 of it)
        uz = float(xp.sum(xp.abs(w) * u[:, 2]) / xp.sum(xp.abs(w))) if flux else 0.0
        terms = _terms(w, r, u, flux, xp)
        U = xp.zeros((nt, nt), dtype=xp.complex128)
        Uw = xp.zeros((nt, nt), dtype=xp.complex128) if flux else None
        main = [q for q in terms if q[1][0] in ("one", "flux")]
        sp = spreads if spreads is not None else {g: REST_SPREAD for g in GROUPS}
        parts = [(main, None)]          # the corrections by spread, as calls() counts them
        for sv in sorted({int(sp[g]) for g in GROUPS}, reverse=True):
            rest = [q for q in terms if q[1][0] in GROUPS and int(sp[q[1][0]]) == sv]
            parts += [(rest[c0:c0 + kc], sv) for c0 in range(0, len(rest), kc)]
        for part, spread in parts:
            N = nufft.nufft_type1(tx, ty, xp.stack([make() for make, _ in part]), nt, xp, spread=spread)
            for (_, key), Nq in zip(part, N):
                cu, cw = _coefficient(key, Dx, Dy, kn)
                if cw is None:
                    Uw += Nq
                    continue
                U += cu * Nq
                if flux and cw:
                    Uw += (cw * uz) * cu * Nq
            del N
        # the amplitude's common change (a: the midrange of u_xy / r over the samples; each sample's first-order rest
        # in the "amp" terms): dz / r^2 at X + D times r^2 / |R + D|^2 (1 - 2 a.D to first order), U_w's obliquity
        # dz / r once more
        # (exactly for a sample at the midrange's r and u: |R + D|^2 / r^2 = 1 + 2 a.D + |D|^2 / r^2)
        al = [0.5 * float(xp.max(u[:, i] / r) + xp.min(u[:, i] / r)) for i in range(2)]
        rm = 0.5 * float(xp.max(r) + xp.min(r))
        q = 1.0 + 2.0 * (al[0] * Dx + al[1] * Dy) + (Dx * Dx + Dy * Dy) / (rm * rm)
        U /= q
        if flux:
            Uw /= q * xp.sqrt(q)
        It = xp.real(xp.conj(U) * Uw) if flux else xp.abs(U) ** 2
        del U, Uw, terms, w, r, u, tx, ty
        hy, hx = min(nt, n - sy), min(nt, n - sx)
        out[sy:sy + hy, sx:sx + hx] = It[:hy, :hx]
    return out


def tile_cost(nt: int, points: int, flux: bool, grid_bytes: int | None = None, spreads: dict | None = None) -> dict:
    """Peak memory (bytes) and work (flops) of one tile of :func:`kirchhoff_samples`: ``nt`` samples a side,
    ``points`` wave-plane samples. Memory: ``POINT_BYTES`` a sample, and the larger NUFFT call's vectors (16 bytes a
    sample), grids (``GRID_CELL_BYTES`` a cell of the ``(2 nt)^2`` grid) and spreading arrays (``SPREAD_ROW_BYTES``
    a sample and footprint row), ~3 complex ``nt^2`` arrays (``U``, ``U_w``, a coefficient,
    products). Flops of the NUFFTs (:func:`rwwarp.wave.nufft.nufft_flops`: one call for the plane waves of ``U``
    and ``U_w``, one a chunk of the corrections at their group's spread, :func:`calls`; ``spreads`` None: all at
    ``REST_SPREAD``) and ~10 a term and sample to form the vectors and
    combine them (``nt^2``)."""
    from .nufft import NUFFT_OVERSAMPLE, nufft_flops
    K, kc = n_vectors(flux), chunk_vectors(nt, points, flux, grid_bytes)
    M = NUFFT_OVERSAMPLE * int(nt)
    main = 2 if flux else 1                      # the plane waves of U (and U_w): one call at NUFFT_SPREAD
    rest = calls(kc, spreads)
    nufft = nufft_flops(points, main, nt) + sum(nufft_flops(points, k, nt, sp) for k, sp in rest)
    from .nufft import NUFFT_SPREAD
    call = lambda k, spread: k * (GRID_CELL_BYTES * M * M + 16 * points) + SPREAD_ROW_BYTES * 2 * spread * points
    mem = POINT_BYTES * points + max([call(main, NUFFT_SPREAD)] + [call(k, sp) for k, sp in rest]) + 3 * 16 * nt * nt
    return {"memory_bytes": int(mem), "flops": float(nufft + 10.0 * K * (points + nt * nt) + 200.0 * points),
            "nufft_flops": float(nufft), "vectors": K, "chunk": kc, "calls": rest}
