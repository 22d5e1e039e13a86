"""The wave step (issue 27): the diffraction of the limiting aperture's edge between the aperture and the
wave plane, which the geometric field on the wave plane leaves out, put back before the DOE.

By the Fresnel scaling theorem (:mod:`rwwarp.wave.model_error`, its docstring derives it) the field a beam
converging to ``T`` (a distance ``R`` behind the wave plane) has on the plane, ``z1`` behind its limiting
aperture, is the geometric field with the converging sphere removed, ``G = U_geo / S_T``, propagated as a
wave over the reduced distance ``d = z1 R / (z1 + R)`` and multiplied by the sphere again:

    U = S_T P_d[U_geo / S_T]

``P_d`` is the band-limited angular spectrum on the wave plane's own grid (:func:`rwwarp.wave.propagate.propagate_grid`,
its adjoint :func:`rwwarp.wave.propagate.propagate_grid_adjoint`): one padded FFT pair of the window, the
patch-following cost of the plan (the sphere removed, ``G`` holds only the beam's aberration and its
diffracted edge, so the plan's pitch samples it). The field's geometry is formed exactly where the rays
are exact, and only the edge's diffraction over ``d`` (``sqrt(lambda d)`` wide) is computed as a wave.
Exact for an unaberrated beam to Fresnel order about the sphere, with the distance stretched for the rim's
obliquity (below).

Obliquity (issue 27, the order beyond Fresnel's). The edge's diffraction happens along the rim ray, which meets
the plane at an angle: its direction ``m = (m_t, m_z)`` (unit, ``m_t`` the transverse part). Along that ray the two
legs (the aperture's image to the plane, the plane to the focus) are ``z1 / m_z`` and ``R / m_z``, so the edge is
a Fresnel edge of reduced distance ``d / m_z`` in the plane normal to the ray; the distance between two points of
the wave plane near the ray has the Hessian ``(I - m_t m_t^T) / L`` (``L`` the distance along the ray), i.e. the
plane's coordinates see the Fresnel kernel of the distance tensor ``(d / m_z) (I + m_t m_t^T / m_z^2)``. Across the
rim (its outward normal ``n`` on the plane, the direction in which the edge's pattern varies) that is

    d_eff = (d / m_z) (1 + (n . m_t)^2 / m_z^2)        (d / m_z^3 on the axis, where m_t is along n)

and the step propagates over its mean around the rim (:func:`rim_obliquity`) where that is one number. Off the
axis it is not (below).

Rim-resolved step (issue 27, off axis). Off the axis the rim's stretch varies around the rim (the rim ray's ``1 /
m_z`` and ``(n . m_t)^2`` are larger on the side away from the axis: 1.000 .. 1.053 at 5 deg, 1.008 .. 1.117 at 10
deg, NA 0.1), and one transfer function (isotropic, or a tensor: a tensor is even in ``n`` and the variation is
mostly odd) cannot give each part of the rim its own: against an off-axis truth at NA 0.1 the isotropic step left
1.52e-3 at 5 deg / 5 mm and 1.25e-3 at 10 deg / 10 mm, and a fitted tensor <= 30 % less. The edge's pattern at a rim
point and the edge wave it sends into the beam (to the points along its normal, the stationary ones of the Fresnel
integral) both come from that point's neighbourhood, so the distance belongs to the *source* point: the step
propagates with a kernel whose distance depends on where the light leaves,

    P[G](y) = integral G(x) K_{D(x)}(y - x) dx,

``K_D`` the Fresnel kernel of distance ``D``. ``D(x)`` is the rim's ``D(phi) = d t(phi)`` (:func:`rim_profile`:
:func:`rim_obliquity`'s per-ray stretch fitted by ``RIM_HARMONICS`` harmonics around the rim) carried into the beam
as its harmonic extension ``D_0 + sum_m r^m (a_m cos m phi + b_m sin m phi)`` (:func:`distance_field`): inside the
beam ``G`` (the sphere removed) is smooth, and a harmonic ``D`` keeps the operator's first-order action there,
``(i lambda / 4 pi) laplacian(D G)``, free of any term from ``D``'s own curvature (``laplacian D = 0``), so only the
rim feels the varying distance. The kernel is interpolated in ``D``: with ``K`` Chebyshev nodes ``D_j`` across the
rim's range and the Lagrange weights ``l_j``, ``K_{D(x)} ~ sum_j l_j(D(x)) K_{D_j}``, so

    P[G] = sum_j P_{D_j}[l_j(D(x)) G]

(``K`` padded FFTs forward and back instead of one each; the nodes' ASM pistons ``exp(2 pi i D_j / lambda_m)`` are
taken back to the source's own, ``D`` being the Fresnel scaling's reduced distance, not a path). The interpolation's
error in the transfer's phase at the edge's frequency ``1 / sqrt(lambda_m D)`` is ``2 (x / 2)^K / K!`` with ``x =
pi (D_max - D_min) / (2 D_0)``; ``K`` is the least with that below ``RIM_NODE_TOL`` = 1e-2 (on the axis the range is
0 and ``K = 1``: the isotropic step, bit for bit). At NA 0.1 and 5-10 deg ``K = 2``; on the truth's own FFTs (no
rwwarp) 2, 3, 4 and 6 nodes give the same error to 3 digits (5 deg / 5 mm 1.35e-4, 10 deg / 10 mm 1.45e-4, against
1.64e-3 / 1.23e-3 isotropic), and rwwarp's step then leaves 3.8e-4 / 2.3e-4 (perf/wave_step_off_axis.py,
docs/accuracy.md, "Off axis"). The adjoint is ``sum_j l_j P_{D_j}^H`` (the weights real).

On the axis, the paraxial ``d`` leaves a relative error ``~1.5 NA^2``
in the edge wave, i.e. ``~1.5 NA^2`` of the one-step error it removes: thin lens f = 50 mm, a = 5 mm (NA 0.0995),
DOE ``4 rho^4``, on the axis, the step on the radial Gauss-Hankel truth (exact angular spectrum,
tests/rwwarp/_wave_truth.py) against the two-step truth, max over 0-40 um of the peak: DOE 5 / 10 / 20 / 35 / 45 mm
before the sensor, ``d``: 1.25e-3 / 6.4e-4 / 2.4e-4 / 7.1e-5 / 1.2e-5; ``d / m_z^3``: 3.7e-5 / 6.0e-6 / 1.8e-5 /
7.2e-6 / 5.4e-6 (``d / m_z``: 8.3e-4 at 5 mm, ``d / m_z^2``: 3.9e-4).

The step's own error (:func:`step_phase_rad`). A beam with aberration ``W`` before the DOE (against the sphere
of its own focus ``T``) reaches the plane with it already carried by its rays: ``G(x) = A(x) exp(i k W(x))``,
whose local transverse frequency ``f(x) = grad(k W) / 2 pi`` (cycles/mm) is the rays' direction against the
sphere over the wavelength in the medium, ``f = n (m - m_T) / lambda`` (``m``: a ray's direction cosines,
``m_T``: the sphere's at that point). ``P_d`` multiplies each plane-wave component of ``G`` by ``exp(-i pi
lambda_m d |f|^2)`` (the Fresnel transfer function, ``lambda_m = lambda / n``); by stationary phase, the part
of ``G`` around ``x`` is moved along its ray by ``s = lambda_m d f`` and its phase changes by ``- 2 pi f . s + pi
lambda_m d |f|^2``, so at a fixed point ``x`` the stepped field is ``G`` with its envelope moved by ``s`` and its
phase changed by

    delta(x) = - pi lambda_m d |f(x)|^2 = - pi |s(x)|^2 / (lambda_m d)       (rad)

where the truth has none (the rays moved it already: the transport is counted twice). With
``phi = max |delta|`` over the pilot rays (``pi s^2 / (lambda_m d)`` at the largest shift the plan reports)
the stepped field is the true one to within a phase ``0 <= -delta <= phi`` across the pupil (and its rim moved by
``s = sqrt(phi lambda_m d / pi)``, a share ``sqrt(phi / pi)`` of the edge width). A smooth pupil phase error
lowers the PSF's peak by its variance (Marechal); for ``delta = phi rho^p`` over a round pupil (``p = 2``: a
defocus carried twice, ``p = 4``: coma-like, ``p = 6``: spherical) the variance is ``phi^2 (1 / (p + 1) - 4 /
(p + 2)^2)`` = ``phi^2 / 12``, ``phi^2 / 11.3``, ``phi^2 / 12.4``, so the step's own error is bounded by

    E_step = phi^2 / STEP_ERROR_DIV       (STEP_ERROR_DIV = 10; of the PSF's peak)

valid while ``phi`` is small (``phi <= STEP_PHASE_MAX`` = 0.1 rad: E_step <= 1e-3; above ~1 rad the envelope's
shift is a sizeable part of the edge width and the bound is no longer one). The phase is checked against an
exact trace (tests/rwwarp/test_wave_step_validity.py); the bound ``E_step`` is Marechal's peak drop, not yet
checked against a wave truth of an aberrated beam (none exists here), and a beam left aberrated after the DOE
can change the PSF off its peak to first order in ``phi``. :func:`plan_wave_step` compares
``E_step`` with the tolerance: ``method="auto"`` refuses the step where it exceeds the tolerance (the one-step
plan is kept, the plan's reasons say why), ``method="two-step"`` warns (:class:`WaveStepWarning`) where it
exceeds the tolerance, or without one where ``phi > STEP_PHASE_MAX``. (The criterion it replaces, the shift
``s`` against the pitch, is still reported; the paper's Cooke experiment has ``s`` of the order of the pitch
with ``phi < 0.04`` rad: perf/model_vs_wave_path.py.) Lengths in mm, wavelengths in um.
"""
from __future__ import annotations

import math
import warnings

import numpy as np

from ..errors import SamplingWarning

#: the step's own phase error (rad, :func:`step_phase_rad`) below which it is taken as exact to E_step <= 1e-3
STEP_PHASE_MAX = 0.1
#: E_step = phi^2 / STEP_ERROR_DIV (module docstring: Marechal, the phase error's variance over the pupil)
STEP_ERROR_DIV = 10.0


class WaveStepWarning(UserWarning):
    """The wave step's own error (the beam's aberration before the DOE transported twice: :func:`step_phase_rad`)
    exceeds the tolerance, or ``STEP_PHASE_MAX`` without one: the wave path is not a reference there."""


#: the window is widened on each side by this many edge widths sqrt(lambda d) (the edge's ringing falls
#: off as 1 / distance: what leaves the window is the edge's light at the widest angles)
EDGE_MARGIN = 3.0
#: the window's pitch must resolve the edge: at most sqrt(lambda d) / EDGE_SAMPLES
EDGE_SAMPLES = 4.0


def reference_phase(origin_mm, pitch_mm, n_grid, chief_mm, target_mm, n_medium, lam_mm, carrier_cpmm, xp=np):
    """The phase (rad, (S, n, n)) of the converging sphere to ``target_mm`` ((S, 3)) relative to the chief
    point ``chief_mm`` ((S, 3)) minus the chief carrier ``carrier_cpmm`` ((S, 2) cycles/mm), on each window
    (sample (0, 0) at ``origin_mm`` (S, 2), ``pitch_mm`` a number or (S,)): the phase
    :mod:`rwwarp.kernels.splat` multiplies the residual by, ``k n (|T - c| - |T - p|) - 2 pi f_c . (p - c)``
    (``n`` negative for a beam diverging from ``T``). ``lam_mm`` (S,) vacuum wavelengths."""
    S = origin_mm.shape[0]
    pitch = np.broadcast_to(np.asarray(pitch_mm, float), (S,))
    out = xp.empty((S, n_grid, n_grid))
    g = np.arange(n_grid, dtype=np.float64)
    for k in range(S):
        x = xp.asarray(origin_mm[k, 0] + g * pitch[k])[None, :]
        y = xp.asarray(origin_mm[k, 1] + g * pitch[k])[:, None]
        T, c = target_mm[k], chief_mm[k]
        dz = T[2] - c[2]
        r = xp.sqrt((T[0] - x) ** 2 + (T[1] - y) ** 2 + dz * dz)
        rc = math.sqrt((T[0] - c[0]) ** 2 + (T[1] - c[1]) ** 2 + dz * dz)
        kk = 2 * math.pi / lam_mm[k] * n_medium[k]
        out[k] = kk * (rc - r) - 2 * math.pi * (carrier_cpmm[k, 0] * (x - c[0]) + carrier_cpmm[k, 1] * (y - c[1]))
    return out


def wave_step_geometry(rw):
    """What :func:`apply_wave_step` needs of a :class:`rwwarp.wave.raywave.RayWave` (``rw.wave_step``: per-source
    reduced distances, mm): ``(phase, distances, wavelengths_um_in_medium)``."""
    sign = np.where(rw.target[:, 2] >= rw.z_plane, 1.0, -1.0)
    chief = np.array(rw.chief_plane, float).copy()
    chief[:, 2] = rw.z_plane
    return chief, sign


def _rotation(rw, n, xp):
    """``exp(i phase)`` of :func:`reference_phase` on the batch's windows ((S, n, n))."""
    chief, sign = wave_step_geometry(rw)
    ph = reference_phase(np.asarray(rw.origin, float), rw.plan.pitch_mm, n, chief, np.asarray(rw.target, float),
                         np.asarray(rw.n_after, float) * sign, np.asarray(rw.lam_mm, float),
                         np.asarray(rw.carrier, float), xp)
    return xp.exp(1j * ph)


def apply_wave_step(rw, u, xp=np):
    """The wave step on a batch's wave-plane field ``u`` ((S, n, n) complex, baseband: the chief carrier
    removed, as :meth:`rwwarp.wave.raywave.RayWave.field_array` gives it; numpy or CuPy, ``xp``): ``S_T P_d[u /
    S_T]`` per source with ``d = rw.wave_step[k]`` (mm; 0 leaves a source as it is), rim-resolved where the plan's
    ``rw.wave_step_rim`` (:func:`rim_profile`) has more than one node: ``S_T sum_j P_{D_j}[l_j(D(x)) u / S_T]``
    (module docstring, "Rim-resolved step"). Returns a new array."""
    d = np.asarray(rw.wave_step, float)
    if not np.any(d != 0):
        return u
    n = u.shape[-1]
    rot = _rotation(rw, n, xp)
    g = u * xp.conj(rot)
    out = _run_rows(rw, g, _step_rows(rw, n, xp), False, xp)
    out = xp.where(xp.asarray(d != 0)[:, None, None], out, g)
    return out * rot


def apply_wave_step_adjoint(rw, grad_out, xp=np):
    """Adjoint of :func:`apply_wave_step` (linear in ``u``): ``grad_out`` (S, n, n) in the convention ``dL/dRe +
    1j dL/dIm`` -> the gradient of ``u`` in the same convention."""
    d = np.asarray(rw.wave_step, float)
    if not np.any(d != 0):
        return grad_out
    n = grad_out.shape[-1]
    rot = _rotation(rw, n, xp)
    g = grad_out * xp.conj(rot)          # adjoint of "* rot"
    gf = _run_rows(rw, g, _step_rows(rw, n, xp), True, xp)
    gf = xp.where(xp.asarray(d != 0)[:, None, None], gf, g)
    return gf * rot                        # adjoint of "* conj(rot)"


def _aberration_angle2(rw) -> np.ndarray:
    """Per source (S,), the largest ``|m - m_T|^2`` over its valid pilot rays before the DOE: the squared transverse
    angle of a ray direction ``m`` to the direction ``m_T`` towards the sphere of ``rw.target`` (converging or
    diverging), i.e. the beam's aberration as an angle (rad^2); 0 for a source with no valid ray."""
    out = np.zeros(rw.nsrc)
    pos, dirs, ok = rw.pilot.pos_p, rw.pilot.dir_s, rw.pilot.ok
    for k in range(rw.nsrc):
        p, m = pos[k, ok[k]], dirs[k, ok[k]]
        if len(p) == 0:
            continue
        to_t = np.asarray(rw.target[k])[None, :] - p
        to_t = to_t / np.linalg.norm(to_t, axis=1, keepdims=True) * (1.0 if rw.target[k, 2] >= rw.z_plane else -1.0)
        out[k] = float(np.max(np.sum((m[:, :2] - to_t[:, :2]) ** 2, axis=1)))
    return out


def _rim_samples(rw, k):
    """Source ``k``'s rim rays on the wave plane (:func:`rim_obliquity`): ``(xc, edge_r, phi, t)``, the beam's centre
    (2,) and edge radius (mm, plane coordinates), each rim ray's azimuth about the centre (rad) and its stretch ``t =
    (1 / m_z)(1 + (n . m_t)^2 / m_z^2)``; None for a source with fewer than 3 valid rays or no extent."""
    from .model_error import RIM_SHARE
    pos, dirs, ok = rw.pilot.pos_p, rw.pilot.dir_s, rw.pilot.ok
    p3, m = pos[k, ok[k]], dirs[k, ok[k]]
    if len(p3) < 3:
        return None
    m = m / np.linalg.norm(m, axis=1, keepdims=True)
    # the pilot points carried along their rays to the plane's vertex (as the estimate does)
    xy = p3[:, :2] + ((rw.z_plane - p3[:, 2]) / m[:, 2])[:, None] * m[:, :2]
    xc = xy.mean(0)
    rr = np.linalg.norm(xy - xc, axis=1)
    if rr.max() <= 0:
        return None
    rim = rr >= RIM_SHARE * rr.max()
    # the pilot's 31 x 31 cell-centre grid: its outermost points lie half a cell (1 / 30 of their span) inside
    # the beam's edge; the wider span (a beam cut on one side, e.g. by the DOE's own rim, keeps the other's)
    edge_r = 0.5 * float(np.max(xy.max(0) - xy.min(0))) * 31.0 / 30.0
    nrm = (xy[rim] - xc) / rr[rim, None]
    mt0 = m[:, :2].mean(0)
    mt = mt0 + (m[rim, :2] - mt0) * (edge_r / rr[rim])[:, None]
    mz2 = np.clip(1.0 - np.sum(mt * mt, axis=1), 1e-12, None)
    t = (1.0 + np.sum(nrm * mt, axis=1) ** 2 / mz2) / np.sqrt(mz2)
    return xc, edge_r, np.arctan2(nrm[:, 1], nrm[:, 0]), t


def rim_obliquity(rw) -> np.ndarray:
    """Per source (S,), the factor (>= 1) by which the wave step's distance exceeds the reduced distance ``d``: the
    rim's edge wave travels along the rim ray, tilted to the plane (module docstring, "Obliquity"):

        d_eff / d = mean_rim (1 / m_z) (1 + (n . m_t)^2 / m_z^2)

    over the pilot's rim rays (``RIM_SHARE`` of the largest radius) before the DOE, ``m = (m_t, m_z)`` each ray's
    unit direction with its transverse part's deviation from the beam's mean carried from the pilot point out to the
    beam's edge (linear in the radius, as for a sphere), ``n`` the rim's outward normal on the plane. 1 for a
    source with fewer than 3 valid rays. Its variation around the rim: :func:`rim_profile`."""
    out = np.ones(rw.nsrc)
    for k in range(rw.nsrc):
        got = _rim_samples(rw, k)
        if got is not None:
            out[k] = float(np.mean(got[3]))
    return out


#: harmonics of the rim's stretch around the rim kept by the rim-resolved step (:func:`rim_profile`)
RIM_HARMONICS = 6
#: the rim-resolved step interpolates the transfer function in the distance at Chebyshev nodes; their number is the
#: least whose interpolation error at the edge's frequency ``1 / sqrt(lambda_m D)`` is below this (:func:`rim_profile`)
RIM_NODE_TOL = 1e-2
#: at most this many nodes (FFTs) a source
RIM_MAX_NODES = 6
#: columns of :func:`rim_profile`'s rows: centre x, y, edge radius, node count, then the harmonics' coefficients
RIM_COLS = 5 + 2 * RIM_HARMONICS


def rim_profile(rw, d_mm) -> np.ndarray:
    """Per source, the rim-resolved step's distance field (module docstring, "Rim-resolved step"): a row of
    ``RIM_COLS`` numbers ``(x_c, y_c, r_e, K, D_0, a_1, b_1, ..., a_M, b_M)`` (mm but K), the beam's centre and edge
    radius on the wave plane and the rim's step distance ``D(phi) = D_0 + sum_m a_m cos(m phi) + b_m sin(m phi)`` (the
    reduced distance ``d_mm`` (S,) times the rim's stretch, :func:`rim_obliquity`'s ``t`` fitted around the rim by
    least squares, ``M = RIM_HARMONICS`` or fewer where the pilot has few rim rays), and ``K`` the number of distances
    the step's transfer is interpolated between (1: the rim's variation is negligible, the step is the isotropic one
    over ``rw.wave_step``; else the least number of Chebyshev nodes across the rim's range whose interpolation error
    ``2 (x / 2)^K / K!`` of the transfer's phase ``x = pi lambda_m (D_max - D_min) / 2 * f_e^2`` at the edge's
    frequency ``f_e^2 = 1 / (lambda_m D_0)`` is below ``RIM_NODE_TOL``, at most ``RIM_MAX_NODES``)."""
    d = np.asarray(d_mm, float)
    out = np.zeros((rw.nsrc, RIM_COLS))
    out[:, 3] = 1.0
    for k in range(rw.nsrc):
        got = _rim_samples(rw, k) if d[k] != 0 else None
        if got is None:
            continue
        xc, edge_r, phi, t = got
        M = int(min(RIM_HARMONICS, (len(t) - 1) // 4))
        cols = [np.ones_like(phi)]
        for m in range(1, M + 1):
            cols += [np.cos(m * phi), np.sin(m * phi)]
        coef = np.linalg.lstsq(np.stack(cols, 1), t, rcond=1e-10)[0] * d[k]
        row = np.zeros(RIM_COLS)
        row[:3] = (xc[0], xc[1], edge_r)
        row[4:4 + len(coef)] = coef
        lo, hi = _rim_range(row)
        x = math.pi * 0.5 * (hi - lo) / max(abs(row[4]), 1e-300)
        K = 1                   # (the nodes are distinct: K > 1 only where hi - lo > 0)
        while K < RIM_MAX_NODES and 2.0 * (0.5 * x) ** K / math.factorial(K) > RIM_NODE_TOL:
            K += 1
        row[3] = K
        out[k] = row
    return out


def step_nodes(rw) -> int:
    """The most propagation rows (FFT pairs) a source of ``rw``'s wave step takes: its :func:`rim_profile`'s node count
    (1: the isotropic step, or no step)."""
    prof, d = getattr(rw, "wave_step_rim", None), getattr(rw, "wave_step", None)
    if prof is None or d is None:
        return 1
    on = np.asarray(d, float) != 0
    return int(max(1, np.max(np.asarray(prof, float)[on, 3], initial=1)))


def _rim_range(row):
    """(D_min, D_max) mm of a :func:`rim_profile` row's rim distance over the rim (720 azimuths)."""
    phi = np.linspace(0.0, 2 * math.pi, 720, endpoint=False)
    D = np.full_like(phi, row[4])
    for m in range(1, RIM_HARMONICS + 1):
        D += row[3 + 2 * m] * np.cos(m * phi) + row[4 + 2 * m] * np.sin(m * phi)
    return float(D.min()), float(D.max())


def distance_field(row, origin_mm, pitch_mm, n, xp=np):
    """The step distance (mm, (n, n)) at each sample of a window (sample (0, 0) at ``origin_mm``, pitch ``pitch_mm``)
    for a :func:`rim_profile` row: the harmonic extension of the rim's ``D(phi)`` into the beam, ``D_0 + sum_m
    Re((a_m - i b_m) z^m)`` with ``z = (x - x_c + i (y - y_c)) / r_e`` (``|z|`` held at 1.3 outside, where the
    geometric field is zero), clipped to the rim's range."""
    g = xp.asarray(np.arange(n, dtype=np.float64))
    z = ((origin_mm[0] + g[None, :] * pitch_mm - row[0]) + 1j * (origin_mm[1] + g[:, None] * pitch_mm - row[1])) / row[2]
    a = xp.abs(z)
    z = xp.where(a > 1.3, z * (1.3 / xp.maximum(a, 1e-300)), z)
    D = xp.full((n, n), row[4])
    zm = xp.ones_like(z)
    for m in range(1, RIM_HARMONICS + 1):
        zm = zm * z
        if row[3 + 2 * m] or row[4 + 2 * m]:
            D = D + (complex(row[3 + 2 * m], -row[4 + 2 * m]) * zm).real
    lo, hi = _rim_range(row)
    return xp.clip(D, lo, hi)


def rim_nodes(row):
    """The :func:`rim_profile` row's Chebyshev nodes (K,) mm across the rim's distance range."""
    K = int(row[3])
    lo, hi = _rim_range(row)
    return 0.5 * (lo + hi) + 0.5 * (hi - lo) * np.cos(math.pi * (np.arange(K) + 0.5) / K)


def _step_rows(rw, n, xp):
    """The propagation rows of the step: ``(source, distance_mm, weight)`` per row, ``weight`` the (n, n) Lagrange
    weight of the row's node at each sample's :func:`distance_field` (None: the isotropic step over
    ``rw.wave_step``, or a source without a step: distance 1e-12, replaced afterwards)."""
    d = np.asarray(rw.wave_step, float)
    prof = getattr(rw, "wave_step_rim", None)
    rows = []
    for k in range(rw.nsrc):
        if d[k] == 0 or prof is None or int(prof[k, 3]) <= 1:
            rows.append((k, d[k] if d[k] != 0 else 1e-12, None))
            continue
        D = distance_field(prof[k], np.asarray(rw.origin, float)[k], rw.plan.pitch_mm, n, xp)
        nodes = rim_nodes(prof[k])
        for j, Dj in enumerate(nodes):
            w = xp.ones((n, n))
            for i, Di in enumerate(nodes):
                if i != j:
                    w = w * ((D - Di) / (Dj - Di))
            rows.append((k, float(Dj), w))
    return rows


def _run_rows(rw, g, rows, adjoint, xp):
    """``sum_rows weight * P_D[g]`` (adjoint: ``sum_rows weight * P_D^H[g]``) per source for :func:`_step_rows`
    ``rows`` (the forward weights the input, the adjoint the output); returns the (S, n, n) result."""
    from . import backend as bk
    from .propagate import propagate_grid, propagate_grid_adjoint
    be = bk.get_backend(rw.device)
    ks = [r[0] for r in rows]
    if adjoint:
        src = g[ks]
    else:
        src = xp.stack([g[k] if w is None else g[k] * w for k, _, w in rows])
    wl_med = (np.asarray(rw.lam_mm, float) * 1e3 / np.asarray(rw.n_after, float))[ks]
    origin = np.asarray(rw.origin, float)[ks]
    dist = np.array([r[1] for r in rows])
    wrap = (lambda a: be.wrap_host(np.ascontiguousarray(a))) if (xp is np and hasattr(be, "wrap_host")) else (lambda a: a)
    with warnings.catch_warnings():
        # propagate_grid's padding check counts the whole window; the field is zero in its EDGE_MARGIN margins
        # and spreads about one margin over d, which the FFT length (window + PAD_MARGINS margins) holds
        warnings.simplefilter("ignore", SamplingWarning)
        if adjoint:
            res, _ = propagate_grid_adjoint(be, wrap(src), wrap(xp.zeros_like(src)), rw.plan.pitch_mm, origin, wl_med,
                                            dist, pad_to=rw.wave_step_pad)
        else:
            res = propagate_grid(be, wrap(src), rw.plan.pitch_mm, origin, wl_med, dist, pad_to=rw.wave_step_pad)
    res = be.to_host(res) if xp is np else xp.asarray(res)
    res = res.reshape(src.shape)
    if len(rows) == g.shape[0] and all(w is None for _, _, w in rows):
        return res
    # the ASM's piston exp(2 pi i D / lambda_m) differs between a source's nodes: D is the Fresnel scaling's
    # reduced distance, not a path, so each node's is taken back to the source's own (rw.wave_step[k])
    d = np.asarray(rw.wave_step, float)
    out = xp.zeros_like(g)
    for i, (k, Dj, w) in enumerate(rows):
        piston = complex(np.exp((-1j if not adjoint else 1j) * 2 * math.pi * (Dj - d[k]) / (wl_med[i] * 1e-3)))
        out[k] += res[i] * piston if (w is None or not adjoint) else res[i] * (w * piston)
    return out


def double_transport_shift_mm(rw, d) -> float:
    """Largest transverse shift (mm) the wave step gives the beam's aberration a second time: the rays already
    carry it to the wave plane, and ``P_d`` moves it again by ``d`` times the rays' angle to the sphere of
    ``rw.target`` (pilot rays before the DOE; ``d`` (S,) mm)."""
    d = np.asarray(d, float)
    shift = np.abs(d) * np.sqrt(_aberration_angle2(rw))
    return float(np.max(shift, initial=0.0))


def step_phase_rad(rw, d) -> np.ndarray:
    """Per source (S,), the wave step's own phase error ``phi = max pi lambda_m |d| |f|^2`` (rad; module docstring):
    ``f = n (m - m_T) / lambda`` the pilot rays' transverse frequency before the DOE against the sphere of
    ``rw.target`` (their aberration, already carried to the plane by the rays), ``lambda_m = lambda / n`` and
    ``d`` (S,) the step's reduced distances (mm; 0: no step, phase 0). Equals ``pi s^2 / (lambda_m d)`` for the
    largest shift ``s`` of :func:`double_transport_shift_mm`."""
    d = np.asarray(d, float)
    lam_med = np.asarray(rw.lam_mm, float) / np.asarray(rw.n_after, float)
    return math.pi * np.abs(d) * _aberration_angle2(rw) / lam_med     # |m - m_T|^2 = (lambda_m f)^2


def step_error(phase_rad) -> float:
    """The wave step's own error bound ``E_step = phi^2 / STEP_ERROR_DIV`` (of the PSF's peak) for its phase
    error ``phi`` (rad, :func:`step_phase_rad`; module docstring)."""
    phi = float(phase_rad)
    if not (phi >= 0 and math.isfinite(phi)):
        raise ValueError(f"the step's phase error must be a finite angle >= 0 rad, got {phase_rad!r}")
    return phi * phi / STEP_ERROR_DIV


#: FFT length of the wave step: the window plus this many margins (EDGE_MARGIN edge widths) a side
PAD_MARGINS = 1.0


def _wave_step_pad(n: int, extra: int) -> int:
    """FFT length of the wave step for a window of ``n`` samples with ``extra`` samples of margin a side: the
    periodic copies of the field stay ``PAD_MARGINS`` margins off it (the band-limited ASM's wrap-around)."""
    from .propagate import next_fft_size
    return next_fft_size(int(n + 2 * PAD_MARGINS * extra))


def _caller_stacklevel() -> int:
    """The ``stacklevel`` of the first frame outside the rwwarp package (the user's call) for a warning raised here."""
    import os
    import sys
    pkg = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    f, level = sys._getframe(1), 1
    while f is not None and os.path.abspath(f.f_code.co_filename).startswith(pkg + os.sep):
        f, level = f.f_back, level + 1
    return level


def model_error_needed(method_requested: str, tolerance) -> bool:
    """Whether a plan's decisions read the model-error estimate: the wave step of ``"two-step"``, or ``"auto"``
    with a ``tolerance`` (``plan_sources`` / ``plan_batch`` may skip the estimate elsewhere, where it would only
    be recorded: ``estimate_model_error=False``)."""
    return method_requested == "two-step" or (method_requested == "auto" and tolerance is not None)


def plan_wave_step(rw, tolerance, method_requested: str, memory_budget_bytes=None, estimate=None):
    """Estimate the model error of a :class:`rwwarp.wave.batch_plan.BatchPlan` ``rw`` (:func:`rwwarp.wave.model_error.estimate_for_raywave`),
    record it in its plan (``model_error``, a reason), and decide the wave step: on where
    ``method_requested`` is ``"two-step"``, or ``"auto"`` with the estimate above ``tolerance`` (relative to
    the PSF's peak; None: never automatically). With the step the window is widened by ``EDGE_MARGIN`` edge
    widths ``sqrt(lambda d)`` a side and, where the plan's pitch does not resolve the edge, refined to
    ``sqrt(lambda d) / EDGE_SAMPLES``. Returns a new :class:`~rwwarp.wave.batch_plan.BatchPlan` (``rw`` is not
    changed) with ``model_errors`` (per source), ``wave_step`` ((S,) mm, zeros without the step), ``plan`` and,
    with the step, ``wave_step_pad``, ``origin`` and ``pupil``. A step whose plan exceeds
    ``memory_budget_bytes`` is refused (:class:`rwwarp.wave.plan.MemoryBudgetError`) under ``"two-step"`` and left
    out, with a reason, under ``"auto"``. Where the step is wanted, its own error ``E_step`` (:func:`step_phase_rad`,
    :func:`step_error`; recorded as ``model_error["step_phase_rad"]`` / ``["step_error"]``) is compared with
    ``tolerance``: above it ``"auto"`` refuses the step (the one-step plan kept, a reason says why) and
    ``"two-step"`` takes it and warns (:class:`WaveStepWarning`; without a tolerance where the phase error exceeds
    ``STEP_PHASE_MAX`` rad). ``estimate``: the model error of ``rw`` already computed (a list of
    :class:`~rwwarp.wave.model_error.ModelError` per source, :func:`rwwarp.wave.model_error.estimate_sources`), else
    computed here; an empty list: not estimated (only where :func:`model_error_needed` is False: nothing recorded,
    no step)."""
    from .model_error import estimate_for_raywave, worst
    from .plan import check_budget, estimate_cost
    est = estimate_for_raywave(rw) if estimate is None else list(estimate)
    if not est and model_error_needed(method_requested, tolerance):
        raise ValueError(f"plan_wave_step: method {method_requested!r} with tolerance {tolerance!r} needs the model-error "
                         "estimate; none was given")
    base = {"model_errors": tuple(est), "wave_step": np.zeros(rw.nsrc)}   # every returned plan's (one copy of rw)
    w = worst(est)
    pl = rw.plan
    if w is None:
        return rw.evolved(**base)
    pl = pl.evolved(model_error=w.to_dict(), reasons=pl.reasons + (w.text(),))
    want = method_requested == "two-step" or (method_requested == "auto" and tolerance is not None
                                              and w.estimate > tolerance)
    if want:
        d_red = np.array([e.reduced_distance_mm if math.isfinite(e.reduced_distance_mm) else 0.0 for e in est])
        obl = rim_obliquity(rw)
        d = d_red * obl     # the distance the step propagates over on the plane (module docstring, "Obliquity")
        prof = rim_profile(rw, d_red)      # its variation around the rim ("Rim-resolved step")
        nodes = int(prof[:, 3].max()) if prof.size else 1
        edge = float(np.sqrt(np.max(rw.lam_mm / rw.n_after * np.abs(d)))) if np.any(d) else 0.0
        phases = step_phase_rad(rw, d)
        phi = float(np.max(phases)) if phases.size else 0.0
        e_step = step_error(phi)
        pl = pl.evolved(model_error={**pl.model_error, "step_phase_rad": phi, "step_error": e_step})
        step_bad = (tolerance is not None and e_step > tolerance) or (tolerance is None and phi > STEP_PHASE_MAX)
        if edge > 0 and step_bad and method_requested == "auto":
            return rw.evolved(**base, plan=pl.with_reasons(
                f"wave step refused: its own error ~{e_step:.2g} of the peak (the beam's aberration before the DOE "
                f"transported twice: phase pi s^2 / (lambda d) up to {phi:.3g} rad, E_step = phi^2 / {STEP_ERROR_DIV:g}) "
                f"exceeds the tolerance {tolerance:.2g}; the one-step model is kept (its estimate "
                f"{w.estimate:.2g}; rwwarp.wave.wave_step)"))
        if edge > 0 and step_bad:
            warnings.warn(
                f"method='two-step': the wave step's own error is ~{e_step:.2g} of the PSF's peak (the beam's "
                f"aberration before the DOE is transported twice, a phase error up to {phi:.3g} rad"
                + (f", above the tolerance {tolerance:.2g}" if tolerance is not None else
                   f", above {STEP_PHASE_MAX:g} rad") + f"; the one-step model's estimate is {w.estimate:.2g}): "
                "the wave path is not a reference here (rwwarp.wave.wave_step)", WaveStepWarning,
                stacklevel=_caller_stacklevel())
        if edge > 0:
            one_step = pl
            pitch = pl.pitch_mm
            why = [f"wave step ({'method two-step' if method_requested == 'two-step' else f'model error {w.estimate:.2g} > tolerance {tolerance:.2g}'}): "
                   f"the geometric field's edge diffracted over the reduced distance {np.max(np.abs(d_red)):.4g} mm "
                   f"(x{float(np.max(obl)):.5g} for the rim rays' obliquity: {np.max(np.abs(d)):.4g} mm) "
                   f"(edge width {edge * 1e3:.3g} um) by the band-limited ASM before the DOE (rwwarp.wave.wave_step)"]
            if pitch > edge / EDGE_SAMPLES:
                why.append(f"wave step: pitch {pitch * 1e3:.4g} -> {edge / EDGE_SAMPLES * 1e3:.4g} um (edge width / {EDGE_SAMPLES:g})")
                pitch = edge / EDGE_SAMPLES
            extra = int(math.ceil(EDGE_MARGIN * edge / pitch))
            span = pl.n_grid * pl.pitch_mm
            n_grid = int(math.ceil(span / pitch)) + 2 * extra
            from .methods import get   # each method's rule (focal: >= samples / 4 rays across; asm: rays per sample)
            ray_grid, n_pad = get(pl.method).wave_step_sizes(pl, rw, pitch, extra)
            why.append(f"wave step: window widened by {EDGE_MARGIN:g} edge widths a side -> {n_grid}^2 samples")
            if nodes > 1:
                lo_hi = [_rim_range(r) for r in prof if r[3] > 1]
                why.append(f"wave step rim-resolved: the rim's distance {min(a for a, _ in lo_hi):.4g} .. "
                           f"{max(b for _, b in lo_hi):.4g} mm around it, the transfer interpolated between up to "
                           f"{nodes} distances (rwwarp.wave.wave_step.rim_profile)")
            shift = double_transport_shift_mm(rw, d)
            why.append(f"wave step: the beam's own aberration before the DOE is carried by its rays and diffracted "
                       f"again over d: a second-order shift <= {shift * 1e3:.3g} um (pitch {pitch * 1e3:.3g} um), "
                       f"a phase error pi s^2 / (lambda d) <= {phi:.3g} rad: the step's own error "
                       f"~{e_step:.2g} of the peak (phi^2 / {STEP_ERROR_DIV:g}, rwwarp.wave.wave_step)")
            pl = pl.evolved(pitch_mm=pitch, n_grid=n_grid, n_pad=n_pad, ray_grid=ray_grid,
                         wave_step_mm=float(np.max(np.abs(d_red)))).with_reasons(*why)
            pad = _wave_step_pad(n_grid, extra)
            cost = dict(estimate_cost(pl, rw.nsrc, rw.size, rw.gauss_nodes))
            # the step's padded field and spectrum (complex128) and its FFT pair, per source
            # (the rim-resolved step: one padded field and FFT per node)
            cost["memory_bytes"] = int(cost["memory_bytes"] + 2 * 16 * nodes * pad * pad)
            cost["flops"] = float(cost["flops"] + float(np.sum(prof[:, 3])) * 2 * 5 * pad * pad * math.log2(pad * pad))
            pl = pl.evolved(estimate=cost)
            if memory_budget_bytes is not None and cost["memory_bytes"] > memory_budget_bytes:
                if method_requested == "two-step":
                    check_budget(cost, int(memory_budget_bytes), f"the wave step's plan ({n_grid}^2 samples, FFT "
                                 f"{pad}^2)", "the reduced distance (edge width sqrt(lambda d)), the beam footprint")
                return rw.evolved(**base, plan=one_step.with_reasons(f"wave step left out: its plan needs "
                                                              f"{cost['memory_bytes'] / 2 ** 30:.3g} GiB, over the memory budget"))
            from .doe_sampling import doe_pixel_origin
            mid = 0.5 * (rw.lo + rw.hi)
            origin = doe_pixel_origin(rw.lens, rw.plane, mid - 0.5 * (n_grid - 1) * pitch, pl.pitch_mm)
            return rw.evolved(**dict(base, plan=pl, wave_step=d, wave_step_pad=pad, origin=origin, wave_step_rim=prof,
                           pupil=(None, None, (2.0 / ray_grid) ** 2)))
    return rw.evolved(**base, plan=pl)
