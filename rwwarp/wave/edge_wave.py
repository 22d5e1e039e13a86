"""The rim's edge wave: the model error of the main order from the beam's pupil phase (issue 27).

:mod:`rwwarp.wave.model_error` derives the picture; this module evaluates it for any pupil phase, on or off the
DOE's axis. Coordinates ``u`` on the wave plane are over the beam's radius (``|u| <= 1`` the beam, ``n(theta)``
the rim's outward normal), ``Phi(u)`` (rad) the wavefront after the DOE against the sphere converging to the
patch centre. On the sensor (the sphere's centre) the geometric model's field at the observation point of
*tilt* ``t`` (rad per unit ``u``: a sensor offset ``lambda z t / (2 pi r_w)``) is, over the unaberrated peak's
amplitude,

    U(t) = (1 / pi) int_disc exp(i (Phi(u) - t . u)) d^2u .

The truth has the aperture's edge diffracted over the reduced distance ``d`` first (``N_F = r_w^2 / (lambda d)``):
across the rim the hard step becomes the Fresnel edge, and the difference ``h`` (edge minus step) lives within
``~ sqrt(lambda d)`` of the rim. Locally at each rim point the phase across the edge is linear, of radial slope
``s(theta) = n . grad Phi - t . n`` (rad per unit u, the tilt included), and the 1-D edge's Fourier pair gives
``int h(x) exp(i s x) dx = (exp(-i psi) - 1) / (i s)``: each plane-wave component of the edge is turned by
the Fresnel phase of its frequency, ``psi = s^2 / (4 pi N_F)``. A chirp across the edge (the radial curvature
``c(theta) = n^T H_Phi n`` at the rim) turns its curvature as it propagates; for a defocus this is exact in Fresnel
order as ``psi = s^2 / (4 pi N_F + 2 c)`` (:mod:`rwwarp.wave.model_error`, "Other orders"), used here for every
phase. So the truth's field is ``U + dU`` with

    dU(t) = (1 / 2 pi) int_0^(2 pi) 2 exp(i (Phi(n) - t . n)) (exp(-i psi) - 1) / (i s) dtheta

and the error over the PSF's peak is ``E = max_t |2 Re(conj(U) dU) + |dU|^2| / max_t |U + dU|^2`` (the truth's
peak: an edge wave that lowers the peak raises ``E``). Small ``psi`` and a
radial phase give ``E = S / (pi N_F)`` on the axis (the old ``C S / N_F``); as ``psi`` grows, ``|exp(-i psi) - 1|
<= 2`` saturates and the edge wave's phase turns against the core's: the error grows slower than ``1 / N_F``
(module docstring of :mod:`rwwarp.wave.model_error`: the measured cases). Off the DOE's axis, the rim phase
``Phi(n(theta))`` varies around the rim (a decentred DOE's coma and astigmatism): the rim's edge waves reach no
sensor point in phase, and the max over ``t`` takes the best one; a tilt of the whole beam is a shift of ``t``
and changes nothing. No constant is fitted.

*Steep rims.* The phase ``psi`` above takes the rim's profile as quadratic over the edge wave's reach. That reach
is a shift: by Fresnel duality the truth is ``U_true(t) = (1 / pi) int_disc P_d[exp(i (Phi - t . u))](v) d^2v`` (the
reduced propagation moved from the disc onto the DOE's phase, ``P_d`` its kernel ``(N_F / i) exp(i pi N_F |w|^2)``),
and by stationary phase ``P_d[exp(i Phi_t)]`` at a rim point ``n`` is carried by the ray leaving ``u = n - grad
Phi_t(u) / k`` (``k = 2 pi N_F``), with the phase ``L = Phi_t(u) + k |n - u|^2 / 2`` (the stationary value) and the
amplitude ``det(I + H_Phi(u) / k)^(-1/2)``. The interior's stationary points are the same rays in both fields (``grad
Phi_t = 0``: no shift), so the difference is the rim's boundary term, the truth's ``2 A exp(i L) / (i s_ray)`` less
the model's ``2 exp(i Phi_t(n)) / (i s)``. The shift ``|u - n| ~ s / k`` is ``S / (2 pi N_F)`` of the beam's radius:
0.03-0.1 on the cases first checked (where the quadratic profile was exact enough), 0.3-0.8 on steep rims (S 100-200
rad at N_F 20-57), where the quadratic profile read 0.16-0.6x the measured error (25 / 35 rho^4 at N_F 56.8) and
2-12x (rho^6, rho^8). Here the ray is traced along the rim point's radius (``u = (1 - eps) n``: the points that
count are where ``grad Phi_t`` is normal to the rim), on the exact radial profile ``p(r) = Phi(r n)`` (a polynomial):
one Newton step on ``eps = (p'(1 - eps) - t . n) / k`` from the quadratic profile's root (a second changed the
estimates by < 4 %), the phase ``psi = Phi_t(n) - L`` from the stationary value at the step (second order in its
error; none, the phase at the quadratic root, read 0.37-7x), so that the edge factor is

    2 (a exp(-i psi) - 1) / (i s),   a = 1 + (a_ray - 1) q / (1 + q),   q = s^2 / (4 pi N_F),

``a_ray = (s / s_ray) ((1 + p''(r) / k) (1 + c_tt(r) / k))^(-1/2)`` the ray's amplitude against the model's (``s_ray
= p'(r) - t . n`` its slope, ``c_tt = (p'(r) + d^2 Phi(r n) / dtheta^2 / r) / r`` the tangential curvature; each
factor held at >= 1 / 2, ``a_ray`` at most :data:`MAX_AMPLITUDE`, 1 where the shift reaches :data:`MAX_SHIFT`). For a
defocus ``a_ray = 1`` and ``psi`` is the quadratic one exactly. The amplitude is *blended in* with the Fresnel phase
``q``: where ``q`` is small the amplitude's change is of the order of the boundary expansion's next term (``c / s^2``
relative), which neither field keeps, and the old form (``a = 1``) matched the truths there (0.88-1.0); taken in full
it read 1.3-1.6x on them; phase only (``a = 1``) read 0.34 / 0.38 / 2.3x on steep cases (N_F 20.5 S 100, ``-50 rho^2
+ 50 rho^4``, ``20 rho^8``). The blend ``q / (1 + q)`` is the one choice made on truths (a = 2.5 mm, 10 mm, ``c
rho^4``, c = 10 .. 35); every other case is held out. Where the quadratic profile is exact to :data:`QUAD_PHASE_RAD`
(the shift's higher powers of the profile, bounded over the observed tilts) no ray is traced and ``a_ray`` is the
rim's own (``r = 1``).

Checked (radially symmetric wave-exact truths, thin lens f = 50 mm, 0.55 um, ``tests/rwwarp/_wave_truth.py`` with the
band widened over the DOE's frequencies and rolled off, ``steep_band``; estimate / measured, before -> now): S 40-200
rad over N_F 9.1-530: ``c rho^4`` 0.16-1.64 -> 0.76-1.25, ``-50 rho^2 + 50 rho^4`` (S 100) 1.49 -> 0.71, ``-25 rho^2 +
25 rho^4`` (S 50) 0.71 -> 0.76, ``10 / 25 rho^6`` (S 60 / 150) 1.87 / 2.01 -> 1.68 / 1.34, ``-30 rho^2 + 30 rho^6`` (S
120) 0.73 -> 1.54, ``20 rho^8`` (S 160) 12.5 -> 1.26, defocus 25 / 50 rho^2 0.99 / 0.98 (unchanged); S 300 (``75
rho^4`` at N_F 530 / 152 / 54.5, ``50 rho^6`` at N_F 56.8, the ray shifted up to 0.88 of the radius; before: beyond the
sampling limit, the scalar law) 1.01 / 1.01 / 1.07 / 1.10; below 35 rad
(the first cases) 0.88-1.0 -> 0.96-1.32 (N_F >= 50: 0.96-1.03; N_F 20.5 / 9.1, where the ray shifts 0.09 / 0.21 of
the radius: 1.12 / 1.32). Off the DOE's axis (the 2-D truth, a = 1.5 mm, 20 mm, 0.5 deg: the beam 0.44 of its
radius off the DOE's centre, so coma and astigmatism about its own; ``tests/rwwarp/test_model_error.py``): 10 / 25
rho^4, the pilot's RMS rim slope 59 / 147 rad, 0.96 / 0.96 (before: 0.92 / the scalar law's ~420x, the phase beyond
the old sampling limit); 35 rho^4 (206 rad, the truth at 2 um samples) 0.96. One off-axis geometry only: the A489's beams 5-10 deg off axis (S up to ~56 rad on the
designed DOE, N_F 100-145, where the traced rays change nothing: the shift is < 0.1) are not themselves checked
against a wave truth. The radial ray is exact for a radial phase; off axis the rays' tangential shift is left out.

``U`` is one zero-padded FFT of ``exp(i Phi)`` sampled on the disc (the cells on the rim weighted by their
share inside it; the samples' period in tilt, ``pi n``, at least ``2.5 max|grad Phi| + 40`` rad, so the sampled
pupil's aliases fall outside the observed tilts), read on the tilt step ``pi / 2``. ``dU`` is summed on the rim
(trapezoid nodes 1.25 times the integrand's bandwidth ``max |dPhi/dtheta| + |t|``) at the observation points: the
tilts within :data:`SEARCH_RAD` of ``U``'s peak and those where ``|U|^2`` is at least :data:`BRIGHT_SHARE` of it (an
aberrated PSF's largest change may lie away from its peak; a wide bright part thinned to the step ``pi``, at most
:data:`MAX_POINTS`, the brightest), then refined on the steps ``pi / 2`` and ``pi / 4`` around the :data:`REFINE`
points of the largest change and of the largest truth intensity (``U`` there summed directly on the samples). On
the tests' cases this reads the same as the full ``pi / 4`` grid (to 1.3 %). Phases in rad, lengths over the beam's
radius (dimensionless).

*A rim that is not the unit circle* (``rim``: harmonics of its radius ``rho(theta)``, :func:`rim_radius`; the pupil's
rim imaged onto the plane by the pilot rays, :mod:`rwwarp.wave.model_error`, "The rim"): ``U`` is the FFT over its
inside (the samples widened to its largest radius at the same pitch), and each rim node sits at ``rho n``: in ``r' = r
/ rho`` its radial profile is ``p(rho r')``, its tilt projection ``rho t . n``, its Fresnel number ``rho^2 N_F`` and its
weight ``rho^2`` (the polar boundary term ``rho exp(i Phi) / (i dPhi/dr)``), which for a circle of radius ``rho0`` is
the unit circle's sum on ``Phi(rho0 u)`` at ``rho0^2 N_F`` (``tests/rwwarp/test_edge_wave_fast.py``: 0.1-1.1 % apart,
the observation grid not scaled). The rim's tilt against the radius (``rho' / rho``, 0.05 at most on the A489) is left
out.

Several coherent parts (:func:`edge_wave_orders_error`: a wrapped DOE's diffraction orders, each with its own pupil
phase and weight ``c_m``): ``U`` is the FFT of ``sum_m c_m exp(i Phi_m)`` on the samples set by the steepest part,
``dU = sum_m c_m dU_m`` with each part's rim sum as above, the observation points chosen on the sum's ``|U|^2``; the
derivation is :mod:`rwwarp.wave.model_error`'s "Other orders". One part gives :func:`edge_wave_error` exactly (the same
arithmetic).

Cost (numpy, a shared 2-core host at load ~2.5, CPU time, min of 7; the first sum on the quadratic profile in
brackets): 1.0-1.1 ms (1.0-1.1) a phase of rim slopes up to ~40 rad (radial, coma; the quadratic path); traced: 2.0
ms (2.0) at 100 rad and 2.3 ms (2.5) at 140 rad (25 / 35 rho^4 at N_F 57), 2.4 ms (1.8) and 5.2 ms (4.4) for 3x / 6x
the tests' coma at N_F 54.5; 16-40 ms at 300 rad (before: beyond the sampling limit, the scalar law). The planner's
whole estimate per source on the A489 (21 sources, 0-10 deg, three wavelengths, all on the quadratic path): 2.4-2.5
ms (2.6-3.0); with the rim imaged (:mod:`rwwarp.wave.model_error`, "The rim") 6.9 ms against 4.9 ms on the circle,
measured together at a host load ~3 (the map's fit and the rim's harmonics ~0.8 ms, the rest the rim's mask and
per-node arrays). The traced terms cost a table per rim node (its projections t . n every :data:`TAU_STEP`, ~80 array
operations an entry), read linearly per point and node; the rim sum runs in float32 real arithmetic (half the
float64 complex sum's time), which pays for most of them. The fit, ~0.6 ms (:func:`fit_pupil_phase`: the normal
equations, no tall LAPACK solve). Where the bright part is wide the estimate depends on which of its points are
observed: on the A489 beams 5-10 deg off axis, observing all of the bright part read up to 2-4.5x the values of the
first version (d8e73cb: the 1024 brightest points on the pi / 4 grid), which the point selection used here reads
0.57-2.5x (before the traced rays); the plan's note flags slopes beyond
:data:`rwwarp.wave.model_error.CHECKED_SLOPE_RAD` (off the axis
:data:`~rwwarp.wave.model_error.CHECKED_OFF_AXIS_SLOPE_RAD`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import fft as sfft

#: degree of the 2-D pupil polynomial fitted to the pilot rays (:func:`fit_pupil_phase`): monomials u_x^i u_y^j,
#: 1 <= i + j <= PUPIL_DEGREE
PUPIL_DEGREE = 6
#: the observation points searched for the largest error: tilts within this radius (rad per unit u) of the
#: model PSF's peak (1.6 Airy radii: the first zero of the Airy pattern is at |t| = 3.83)
SEARCH_RAD = 6.0
#: the largest phase slope (rad per unit u) the sum is evaluated for (beyond it :func:`edge_wave_error` returns None and
#: the estimate falls back to the scalar law; the sum was checked against radial wave truths up to 300 rad, off the
#: DOE's axis up to the pilot's RMS rim slope 206 rad, the phase's largest slope ~350 rad)
MAX_SLOPE_RAD = 400.0
#: the pupil samples across the beam's diameter are at least this many
MIN_SAMPLES = 48
#: ... and the PSF's bright part: the tilts where the model's intensity is at least this share of its peak
BRIGHT_SHARE = 0.05
#: at most this many observation points on the coarse tilt grid (step pi / 2, a wide bright part thinned to pi; the
#: brightest)
MAX_POINTS = 128
#: the tilt step of the fine grid (rad per unit u): the coarse points of the largest change and of the largest truth
#: intensity, REFINE of each, are refined on it
FINE_STEP = math.pi / 4
REFINE = 3
#: the rays are traced to the rim (module docstring, "Steep rims") where the quadratic profile's error, the shift's
#: higher-order phase, could exceed this (rad)
QUAD_PHASE_RAD = 0.1
#: Newton steps of the traced ray's shift (from the quadratic profile's; the phase is then second order in its error)
NEWTON_STEPS = 1
#: the traced terms are tabulated per rim node on the tilts' projections t . n this far apart (rad per unit u) and read
#: linearly
TAU_STEP = 4.0
#: the traced shift is held within this share of the beam's radius (beyond: the untraced amplitude)
MAX_SHIFT = 0.9
#: the traced amplitude ratio is held at most this (a ray near a caustic)
MAX_AMPLITUDE = 3.0


@dataclass(frozen=True)
class PupilPhase:
    """A polynomial pupil phase ``Phi(u) = sum_k c_k u_x^(p_k) u_y^(q_k)`` (rad; ``u`` over the beam's radius).
    ``powers`` (K, 2) int, ``coeffs`` (K,) rad."""

    powers: np.ndarray
    coeffs: np.ndarray

    def _coef_matrix(self, orders):
        """``C`` (D, D) per derivative order ``(dx, dy)`` in ``orders``: the derivative is ``sum_pq C[p, q] ux^p uy^q``
        (kept on the phase per ``orders``: a phase is evaluated several times; the caller must not change it)."""
        memo = self.__dict__.setdefault("_coef_memo", {})
        key = tuple(tuple(o) for o in orders)
        got = memo.get(key)
        if got is None:
            got = memo[key] = self._coef_matrix_new(orders)
            got.flags.writeable = False
        return got

    def _coef_matrix_new(self, orders):
        P = np.asarray(self.powers, int).reshape(-1, 2)
        c = np.asarray(self.coeffs, float)
        d = max(self.degree, 0)
        out = np.zeros((len(orders), d + 1, d + 1))
        for k, (dx, dy) in enumerate(orders):
            ok = (P[:, 0] >= dx) & (P[:, 1] >= dy)
            p, q = P[ok, 0], P[ok, 1]
            f = c[ok].copy()
            for a in range(dx):                                      # falling factorials p (p - 1) ..
                f = f * (p - a)
            for a in range(dy):
                f = f * (q - a)
            np.add.at(out[k], (p - dx, q - dy), f)
        return out

    def _eval(self, ux, uy, orders=((0, 0),)):
        """The derivatives ``orders`` ((dx, dy) each) of Phi at ``(ux, uy)`` (broadcast), one array each: the table of
        powers ``ux^p``, ``uy^q`` once, then a product with the coefficients."""
        ux, uy = np.broadcast_arrays(np.asarray(ux, float), np.asarray(uy, float))
        C = self._coef_matrix(orders)
        X, Y = _power_tables(ux.ravel(), uy.ravel(), C.shape[1] - 1)
        X, Y = np.stack(X, 1), np.stack(Y, 1)                        # (N, D)
        # sum_pq X[n, p] C[k, p, q] Y[n, q]: the monomials (N, D^2) times the coefficients (D^2, K)
        D = X.shape[1]
        out = (X[:, :, None] * Y[:, None, :]).reshape(-1, D * D) @ C.reshape(len(C), D * D).T
        return [out[:, k].reshape(ux.shape) for k in range(len(C))]

    def _grid(self, x):
        """Phi on the grid ``ux = x[j]``, ``uy = x[i]`` ((len(x), len(x)), rows: uy): separable, two small products."""
        C = self._coef_matrix(((0, 0),))[0]
        X = np.stack(_power_tables(np.asarray(x, float), np.asarray(x, float), C.shape[0] - 1)[0], 1)
        return X @ C.T @ X.T

    @property
    def degree(self) -> int:
        """The largest total power (0 without terms)."""
        return int(np.max(np.sum(self.powers, 1))) if len(self.powers) else 0

    def value(self, ux, uy):
        """Phi (rad) at ``(ux, uy)``."""
        return self._eval(ux, uy)[0]

    def gradient(self, ux, uy):
        """``(dPhi/dux, dPhi/duy)`` (rad per unit u)."""
        return tuple(self._eval(ux, uy, ((1, 0), (0, 1))))

    def hessian(self, ux, uy):
        """``(Phi_xx, Phi_xy, Phi_yy)`` (rad per unit u^2)."""
        return tuple(self._eval(ux, uy, ((2, 0), (1, 1), (0, 2))))


_VARIANT = 1
_NEWTON = 2


def _radial_profiles(phase, cx, cy):
    """``prof`` (degree + 1, nth): ``Phi(r (cx, cy)) = sum_j prof[j] r^j`` along each rim node's radius."""
    d = max(phase.degree, 0)
    P = np.asarray(phase.powers, int).reshape(-1, 2)
    out = np.zeros((d + 1, len(cx)))
    if not len(P):
        return out
    X, Y = _power_tables(np.asarray(cx, float), np.asarray(cy, float), d)
    X, Y = np.stack(X), np.stack(Y)                                   # (d + 1, nth)
    np.add.at(out, P.sum(1), np.asarray(phase.coeffs, float)[:, None] * X[P[:, 0]] * Y[P[:, 1]])
    return out


def _horner(C, r):
    """``sum_j C[j] r^j`` (``C`` (J, nth), ``r`` (..., nth))."""
    out = C[-1] * np.ones_like(r)
    for cj in C[-2::-1]:
        out = out * r + cj
    return out


def _power_tables(ux, uy, degree):
    """``[ux^0 .. ux^degree]``, ``[uy^0 .. uy^degree]`` (repeated products: no ``**`` per term)."""
    X, Y = [np.ones_like(ux)], [np.ones_like(uy)]
    for _ in range(degree):
        X.append(X[-1] * ux)
        Y.append(Y[-1] * uy)
    return X, Y


def _powers(degree):
    return np.array([(i, n - i) for n in range(1, degree + 1) for i in range(n, -1, -1)], int)


def fit_pupil_phase(u, grad, degree: int = PUPIL_DEGREE) -> PupilPhase:
    """Least-squares :class:`PupilPhase` (monomials of degree 1 .. ``degree``, no constant) whose gradient matches
    ``grad`` (N, 2) (rad per unit u) at the points ``u`` (N, 2) (over the beam's radius): the pilot rays'
    transverse frequencies against the sphere to the patch, times ``2 pi r_w``. The degree drops until the
    points outnumber the unknowns. Solved by the normal equations of the column-scaled system with one step of
    iterative refinement (a tall LAPACK least-squares solve took ~100 ms a call on a loaded host)."""
    u, g = np.asarray(u, float), np.asarray(grad, float)
    if u.ndim != 2 or u.shape[1] != 2 or g.shape != u.shape or len(u) < 2:
        raise ValueError(f"fit_pupil_phase: need u and grad of the same shape (N >= 2, 2), got {u.shape}, {g.shape}")
    if not (np.all(np.isfinite(u)) and np.all(np.isfinite(g))):
        raise ValueError("fit_pupil_phase: u and grad must be finite")
    while degree > 1 and len(_powers(degree)) > len(u):
        degree -= 1
    P = _powers(degree)
    # the design matrix from one table of powers (d/dux of ux^p uy^q = p ux^(p-1) uy^q), its columns scaled to
    # unit norm; the normal equations (K x K, K <= 27) and one step of iterative refinement: a tall least-squares
    # solve (LAPACK, threaded) cost ~100 ms a call on a loaded 2-core host, this ~0.6 ms
    X, Y = _power_tables(u[:, 0], u[:, 1], degree)
    D = degree + 1
    M = (np.stack(X, 1)[:, :, None] * np.stack(Y, 1)[:, None, :]).reshape(len(u), D * D)   # ux^i uy^j at i D + j
    Dx, Dy = np.zeros((D * D, len(P))), np.zeros((D * D, len(P)))
    k = np.arange(len(P))
    px, qx = P[:, 0], P[:, 1]
    Dx[np.maximum(px - 1, 0) * D + qx, k] = px                      # p ux^(p-1) uy^q (0 where p = 0)
    Dy[px * D + np.maximum(qx - 1, 0), k] = qx
    A = np.concatenate([M @ Dx, M @ Dy], 0)
    scale = np.maximum(np.sqrt(np.sum(A * A, 0)), 1e-300)
    A = A / scale
    b = np.concatenate([g[:, 0], g[:, 1]])
    G = A.T @ A
    G[np.diag_indices_from(G)] += 1e-14 * np.trace(G)        # rank-deficient point sets stay solvable
    coef = np.linalg.solve(G, A.T @ b)
    coef = coef + np.linalg.solve(G, A.T @ (b - A @ coef))
    coef = coef / scale
    return PupilPhase(P, coef)


def radial_pupil_phase(coeffs) -> PupilPhase:
    """The :class:`PupilPhase` of ``sum_i c_i rho^(2 i)`` (rad, ``i = 1 ..``; ``rho = |u|``), expanded binomially."""
    terms = {}
    for i, c in enumerate(coeffs, start=1):
        for j in range(i + 1):     # (ux^2 + uy^2)^i
            key = (2 * j, 2 * (i - j))
            terms[key] = terms.get(key, 0.0) + float(c) * math.comb(i, j)
    keys = sorted(terms)
    return PupilPhase(np.array(keys, int).reshape(-1, 2), np.array([terms[k] for k in keys], float))


def max_slope(phase: PupilPhase) -> float:
    """The largest ``|grad Phi|`` (rad per unit u) of the pupil ``phase`` over the beam (9 radii x 96 azimuths: the
    sampling's measure, compared with :data:`MAX_SLOPE_RAD`); :class:`ValueError` where it is not finite."""
    th = np.linspace(0.0, 2 * math.pi, 97)[:-1]
    rr = np.linspace(0.0, 1.0, 9)
    gx, gy = phase.gradient(np.outer(rr, np.cos(th)), np.outer(rr, np.sin(th)))
    g = float(np.sqrt(np.max(gx * gx + gy * gy)))
    if not math.isfinite(g):
        raise ValueError("edge_wave_error: the pupil phase is not finite on the beam")
    return g


def rim_radius(rim, theta) -> np.ndarray:
    """The rim's radius ``rho(theta) = Re sum_m rim[m] exp(i m theta)`` (over the beam's radius) at the polar angles
    ``theta`` (rad) of the beam's own coordinates ``u``; ``rim`` None: the unit circle (1)."""
    theta = np.asarray(theta, float)
    if rim is None:
        return np.ones_like(theta)
    c = np.asarray(rim, complex)
    z = np.exp(1j * theta)
    zm = np.ones_like(z)
    out = np.full(theta.shape, c[0].real)
    for cm in c[1:]:                                   # exp(i m theta) by repeated products
        zm = zm * z
        out = out + (cm * zm).real
    return out


def _check_rim(rim):
    """``rim`` as a complex array of its harmonics (:func:`rim_radius`), or None; :class:`ValueError` for a rim not
    within 0.5 .. 1.5 of the beam's radius or not finite."""
    if rim is None:
        return None
    c = np.asarray(rim, complex).ravel()
    if not len(c) or not np.all(np.isfinite(c)):
        raise ValueError("edge_wave_error: rim must be finite harmonics of the rim's radius (rim[0]: its mean)")
    rr = rim_radius(c, np.linspace(0.0, 2 * math.pi, 257))
    if rr.min() < 0.5 or rr.max() > 1.5:
        raise ValueError(f"edge_wave_error: the rim's radius {rr.min():.3g} .. {rr.max():.3g} of the beam's radius is "
                         "outside 0.5 .. 1.5")
    return c


def _rim_summer(nf: float, phase: PupilPhase, tobs: float, rim=None):
    """The rim's edge-wave sum ``dU(t)`` of one pupil ``phase`` (module docstring) as a function of the tilts
    ``(tx, ty)`` (rad per unit u), set up for observed tilts up to ``|t| = tobs`` (the trapezoid nodes and the traced
    rays' tables; the refinement's rings reach a few :data:`FINE_STEP` further). Returns ``(rim_sum, s0, den, cx, cy, traced)``:
    the function, on its rim nodes the radial slope, the Fresnel phase's denominator and the normal, and whether
    the rays are traced ("Steep rims"). ``rim``: the rim's radius ``rho(theta)`` (:func:`rim_radius`; None: the unit
    circle): each node's radius is scaled to it (``r = rho r'``: the profile's coefficients by ``rho^j``, the tilt's
    projection and the Fresnel number by ``rho`` and ``rho^2``, the node's length by ``rho^2`` in the polar boundary
    term ``rho e^(i Phi) / (i dPhi/dr)``), its slope along the radius (the rim's tilt ``rho' / rho``) left out; the
    returned slope, denominator and normal are then the scaled ones (``rho n`` for the normal)."""
    # the rim: nodes enough for the integrand's turns around it (|dPhi/dtheta| + |t|; the trapezoid rule on a
    # periodic integrand is exact for harmonics below the node count), 1.25 times over (the estimates unchanged to 4
    # digits against twice and against the 8 times over first used)
    th = np.linspace(0.0, 2 * math.pi, 97)[:-1]
    cx, cy = np.cos(th), np.sin(th)
    g1x, g1y = phase.gradient(cx, cy)
    dth = np.abs(g1y * cx - g1x * cy)                              # |dPhi/dtheta| on the rim
    r_top = 1.0 if rim is None else float(np.max(rim_radius(rim, th)))   # a wider rim: the tilt's turns grow
    nth = int(min(4096, 1.25 * (float(dth.max()) * r_top ** 2 + (tobs + 4 * FINE_STEP) * r_top) + 32))
    th = 2 * math.pi * np.arange(nth) / nth
    cx, cy = np.cos(th), np.sin(th)
    # the phase along each rim node's radius, p(r) = Phi(r n) = sum_j prof[j] r^j (exact: Phi is a polynomial), and
    # its derivatives: on the rim (r = 1) the phase, the radial slope and the radial curvature
    prof = _radial_profiles(phase, cx, cy)
    if rim is not None:
        # a rim at rho(theta) n: the profile in r' = r / rho (its rim at r' = 1), the normal scaled for the tilt's
        # projection, the Fresnel number per node (rho^2 N_F), the node's weight rho^2
        rho = rim_radius(rim, th)
        prof = prof * rho[None, :] ** np.arange(len(prof))[:, None]
        cx, cy = rho * cx, rho * cy
        nf = nf * rho * rho
        wnode = (rho * rho).astype(np.float32)
    dprof = np.arange(1, len(prof))[:, None] * prof[1:]
    ddprof = np.arange(1, len(dprof))[:, None] * dprof[1:]
    phi, s0, c = prof.sum(0), dprof.sum(0), ddprof.sum(0)
    # a rim point whose chirp focuses within the reduced distance (4 pi N_F + 2 c <= 0) is outside the one-edge
    # picture: its curvature is held at -pi N_F (the edge wave then turns by at most s^2 / (2 pi N_F))
    den = 4 * math.pi * nf + 2 * np.maximum(c, -math.pi * nf)
    kf = 2 * math.pi * nf
    rmax = 1.0 if rim is None else float(np.max(rho))
    # the truth's edge wave at a rim point n is carried by the ray that reaches n after the reduced distance, from
    # u = (1 - eps) n with eps = (p'(1 - eps) - t.n) / (2 pi N_F) (module docstring, "Steep rims"); the tangential
    # curvature's part d^2/dtheta^2 Phi(r n) spectrally (the profiles are trigonometric polynomials of degree <= D)
    harm = sfft.fftfreq(nth, 1.0 / nth)
    tang = sfft.ifft(-(harm * harm) * sfft.fft(prof, axis=1), axis=1).real
    ctt1 = s0 + tang.sum(0)                                          # tangential curvature on the rim (no tilt)
    amp1 = np.sqrt(np.maximum(1 + c / kf, 0.5) / np.maximum(1 + ctt1 / kf, 0.5))
    # the quadratic profile (the rim's slope and curvature) is exact to QUAD_PHASE_RAD where the shift's higher
    # powers, sum_(j >= 3) |p^(j)(1)| eps^j / j!, stay below it: then no ray is traced
    tmax = (tobs + 4 * FINE_STEP) * rmax
    eps_max = (float(np.max(np.abs(s0))) + tmax) / (0.5 * float(np.min(den)))
    hi, dj, fact = 0.0, ddprof, 2.0
    for j in range(3, len(prof)):
        dj = np.arange(1, len(dj))[:, None] * dj[1:]
        fact *= j
        hi += float(np.max(np.abs(dj.sum(0)))) * eps_max ** j / fact
    traced = hi > QUAD_PHASE_RAD

    inv_den2 = 2.0 / den
    # the quadratic profile's amplitude ratio less 1, per node (untraced)
    beta1 = amp1 - 1.0

    def traced_terms(tn):
        """(psi - the quadratic profile's psi, the ray's amplitude ratio less 1) at the tilts' projections ``tn``
        (..., nth): one Newton step on eps = (p'(1 - eps) - t.n) / k from the quadratic root, the phase from the
        stationary value of L(r) = p(r) - t.n r + k (1 - r)^2 / 2 there (second order in the step's error)."""
        sl = s0 - tn
        eps0 = sl * inv_den2
        r = 1.0 - eps0
        fp = np.maximum(_horner(ddprof, r) * (1.0 / kf) + 1.0, 0.5)
        eps = eps0 - (eps0 - (_horner(dprof, r) - tn) * (1.0 / kf)) / fp
        np.clip(eps, -MAX_SHIFT, MAX_SHIFT, out=eps)
        r = 1.0 - eps
        pd1 = _horner(dprof, r)
        fp = np.maximum(_horner(ddprof, r) * (1.0 / kf) + 1.0, 0.5)
        dpsi = phi - tn * eps - _horner(prof, r) - (0.5 * kf) * eps * eps - 0.5 * sl * eps0
        sd = pd1 - tn                                    # the ray's radial slope (rad per unit u)
        ctt = np.maximum((pd1 + _horner(tang, r) / r) / (r * kf) + 1.0, 0.5)
        bad = (sd == 0.0) | (np.abs(eps) >= MAX_SHIFT)
        beta = np.minimum(sl / np.where(bad, 1.0, sd) / np.sqrt(fp * ctt), MAX_AMPLITUDE) - 1.0
        beta[bad] = 0.0
        return dpsi, beta

    if traced:
        # tabulated per node on the projections t.n of every tilt the search can reach (the coarse points' and
        # the refinement's rings), TAU_STEP apart, and read linearly: both are smooth in t.n (no oscillation)
        tau_max = tmax + 6 * FINE_STEP * rmax
        ntau = max(9, int(math.ceil(2 * tau_max / TAU_STEP)) + 1)
        dtau = 2 * tau_max / (ntau - 1)
        taus = -tau_max + dtau * np.arange(ntau)
        tab_psi, tab_beta = (np.ascontiguousarray(v.T).ravel() for v in traced_terms(taus[:, None] + 0.0 * s0))
        base = np.arange(nth) * ntau

    # the rim sum in float32, real arithmetic (its phases stay below ~10^3 rad: ~10^-4 rad of rounding; the estimates
    # moved by < 2e-6 of themselves against the float64 sum on 16 radial and coma phases, S 4-200 rad, at about half
    # its time); the means accumulate in float64
    f4 = np.float32
    cx4, cy4, s04, phi4 = cx.astype(f4), cy.astype(f4), s0.astype(f4), phi.astype(f4)
    q4, beta14 = (0.25 * inv_den2).astype(f4), beta1.astype(f4)
    kf4 = (0.5 / kf).astype(f4) if rim is not None else f4(0.5 / kf)
    if traced:
        tab_psi4, tab_beta4, tau4, itau4 = tab_psi.astype(f4), tab_beta.astype(f4), f4(tau_max), f4(1.0 / dtau)

    def rim_sum(tx, ty):
        out = np.empty(len(tx), complex)
        step = max(1, 65536 // nth)
        tx4, ty4 = np.asarray(tx, f4), np.asarray(ty, f4)
        for a in range(0, len(tx), step):
            tn = tx4[a:a + step, None] * cx4 + ty4[a:a + step, None] * cy4
            sl = s04 - tn
            sl2 = sl * sl
            half = q4 * sl2                              # the quadratic profile's psi / 2 (exact for a defocus)
            if traced:
                u = (tn + tau4) * itau4
                i = np.minimum(u.astype(np.intp), ntau - 2)
                f = u - i
                i += base
                p0, b0 = tab_psi4[i], tab_beta4[i]
                i += 1
                half += f4(0.5) * (p0 + f * (tab_psi4[i] - p0))
                beta = b0 + f * (tab_beta4[i] - b0)
            else:
                beta = beta14
            # the amplitude's change, blended in as the edge wave's Fresnel phase grows (module docstring)
            ps = sl2 * kf4
            beta = beta * (ps / (f4(1.0) + ps))
            # 2 ((1 + beta) exp(-i psi) - 1) / (i s) exp(i (Phi - t.n))
            #   = -(2 / s) ((2 + beta) sin(psi / 2) + i beta cos(psi / 2)) exp(i (Phi - t.n - psi / 2))
            rs = f4(-2.0) / np.where(sl == 0, f4(1.0), sl)
            re = rs * (f4(2.0) + beta) * np.sin(half)
            im = rs * beta * np.cos(half)
            if rim is not None:
                re, im = re * wnode, im * wnode
            arg = phi4 - tn - half
            c, sn = np.cos(arg), np.sin(arg)
            out.real[a:a + step] = np.mean(re * c - im * sn, axis=1, dtype=np.float64)
            out.imag[a:a + step] = np.mean(re * sn + im * c, axis=1, dtype=np.float64)
        return out

    return rim_sum, s0, den, cx, cy, traced


def edge_wave_error(fresnel_number_: float, phase: PupilPhase, search_rad: float = SEARCH_RAD, rim=None):
    """The main order's model error ``E = max_t |2 Re(conj(U) dU) + |dU|^2| / max_t |U + dU|^2`` (dimensionless,
    over the truth PSF's peak) for the pupil ``phase`` (:class:`PupilPhase`, rad, against the sphere to the patch) and the
    Fresnel number ``N_F`` of the rim over the reduced distance (module docstring). Returns ``(E, info)``,
    ``info`` a dict: ``peak_tilt`` (rad per unit u, where ``|U|`` peaks), ``strehl`` / ``strehl_true`` (``max |U|^2`` /
    ``max |U + dU|^2``, over the unaberrated peak), ``max_psi_rad`` (the largest Fresnel phase of the rim's edge wave
    at the peak, on the quadratic profile), ``samples`` (across the beam), ``rim_nodes``, ``points`` (observation
    points), ``traced`` (whether the rays were traced back to the rim: module docstring, "Steep rims"); ``(None, info)``
    where the phase's largest slope exceeds :data:`MAX_SLOPE_RAD`. 0 for ``N_F = inf``. Cost: module docstring.
    :func:`edge_wave_orders_error` with one order; ``rim``: as there."""
    return edge_wave_orders_error(fresnel_number_, [(1.0, phase)], search_rad, rim)


def edge_wave_orders_error(fresnel_number_: float, orders, search_rad: float = SEARCH_RAD, rim=None):
    """The model error of a field made of several coherent parts, each with its own pupil phase: a wrapped DOE's
    diffraction orders (:mod:`rwwarp.wave.model_error`, "Other orders"). ``orders``: ``[(w_m, phase_m)]``, the main
    order first (``w`` its complex weight, 1 for it; the others ``c_m / c_main``), each ``phase_m`` (:class:`PupilPhase`,
    rad) against the same sphere to the patch and with the same tilt removed (an order's own tilt, its lateral
    offset on the sensor, is kept). The fields add, ``U = sum_m w_m U_m`` and ``dU = sum_m w_m dU_m`` (the edge's
    diffraction acts on the field before the DOE, linear in the DOE's transmission: each order's rim edge wave turns
    by its own slope's Fresnel phase), and ``E = max_t |2 Re(conj(U) dU) + |dU|^2| / max_t |U + dU|^2``: the change
    over the truth's peak, whichever order makes it (a focused zero order's peak included). The observation points
    are chosen on ``|U|^2`` of all the orders. Returns ``(E, info)`` as :func:`edge_wave_error` (``max_psi_rad`` the
    main order's); ``(None, info)`` where the main order's largest slope exceeds :data:`MAX_SLOPE_RAD`; the other
    orders must stay within it (:class:`ValueError`). 0 for ``N_F = inf``. ``rim``: the beam's rim where it is not the
    unit circle, harmonics of its radius over the beam's radius (:func:`rim_radius`; the aperture's rim imaged onto
    the plane: :func:`rwwarp.wave.model_error.estimate_for_raywave`); the pupil is then the inside of that rim and
    the edge waves are summed on it (:func:`_rim_summer`). None: the unit circle."""
    nf = float(fresnel_number_)
    if not nf > 0:
        raise ValueError(f"edge_wave_error: need a Fresnel number > 0, got {fresnel_number_!r}")
    if not orders:
        raise ValueError("edge_wave_orders_error: need at least the main order")
    if math.isinf(nf):
        return 0.0, {"peak_tilt": (0.0, 0.0), "strehl": 1.0, "max_psi_rad": 0.0, "samples": 0}
    rim = _check_rim(rim)
    weights = [complex(w) for w, _ in orders]
    phases = [ph for _, ph in orders]
    # the phases' largest slopes set the sampling
    gmaxes = [max_slope(ph_) for ph_ in phases]
    gmax = max(gmaxes)
    if gmaxes[0] > MAX_SLOPE_RAD:
        return None, {"peak_tilt": (0.0, 0.0), "strehl": float("nan"), "max_psi_rad": float("nan"),
                      "samples": 0, "max_slope_rad": gmaxes[0]}
    if gmax > MAX_SLOPE_RAD:
        raise ValueError(f"edge_wave_orders_error: an order's phase slope {gmax:.4g} rad exceeds MAX_SLOPE_RAD "
                         f"({MAX_SLOPE_RAD:g})")
    # the samples' period in tilt, pi n, holds the spot (|t| <= gmax about its centre) and its neighbourhood
    # twice over (2.5 gmax + 40 rad): the sampled pupil's aliases of U fall outside the observed tilts
    n = sfft.next_fast_len(max(MIN_SAMPLES, int(math.ceil((2.5 * gmax + 40.0) / math.pi))))
    h = 2.0 / n
    if rim is None:
        x = -1.0 + h * (np.arange(n) + 0.5)
        w = np.clip((1.0 - np.sqrt(x[None, :] ** 2 + x[:, None] ** 2)) / h + 0.5, 0.0, 1.0)   # the cell's share inside the rim
    else:
        # the same pitch (the tilt grid's steps unchanged), the samples widened to the rim's largest radius
        rr_max = float(np.max(rim_radius(rim, np.linspace(0.0, 2 * math.pi, 257)))) + h
        nw = n + 2 * max(0, int(math.ceil((rr_max - 1.0) / h)))
        x = h * (np.arange(nw) - 0.5 * (nw - 1))
        rr = np.sqrt(x[None, :] ** 2 + x[:, None] ** 2)
        w = np.clip((rim_radius(rim, np.arctan2(x[:, None], x[None, :])) - rr) / h + 0.5, 0.0, 1.0)
    g = w * np.exp(1j * phases[0]._grid(x))
    if weights[0] != 1.0:
        g = weights[0] * g
    for wt, ph_ in zip(weights[1:], phases[1:]):
        g = g + wt * w * np.exp(1j * ph_._grid(x))
    # coarse: the FFT on the tilt step pi / 2 (twice the samples' span)
    m = 2 * n
    F = sfft.fft(sfft.fft(g, n=m, axis=1), n=m, axis=0)           # rows: t_y, columns: t_x; U pi / h^2
    t = 2 * math.pi * sfft.fftfreq(m, h)
    # the samples start at u = x[0], not 0: exp(-i t . u) = exp(-i t x[0]) exp(-2 pi i k j / m)
    ph = np.exp(-1j * t * x[0])
    I = (F.real ** 2 + F.imag ** 2).ravel()                       # |U|^2 pi^2 / h^4 (ph has modulus 1)
    k = int(np.argmax(I))
    iy, ix = divmod(k, m)
    # the observation points: the tilts near the peak and the PSF's bright part (an aberrated PSF's largest
    # change may lie away from its peak), at most MAX_POINTS of them, the brightest
    r = int(math.ceil(search_rad / FINE_STEP + 1e-9))
    dy, dx = np.divmod(np.arange((2 * r + 1) ** 2), 2 * r + 1)
    dy, dx = dy - r, dx - r
    close = (dx * dx + dy * dy) * FINE_STEP ** 2 <= (search_rad + 1e-9) ** 2
    dy, dx = dy[close], dx[close]
    coarse = (dy % 2 == 0) & (dx % 2 == 0)
    near = ((iy + dy[coarse] // 2) % m) * m + (ix + dx[coarse] // 2) % m
    mask = I >= BRIGHT_SHARE * float(I[k])
    mask[near] = True
    sel = np.flatnonzero(mask)
    levels = [FINE_STEP]
    if len(sel) > MAX_POINTS:
        # a wide bright part: every other coarse point (step pi, aligned with the peak), the near ones kept; the
        # refinement below then climbs pi / 2 -> pi / 4
        sy, sx = np.divmod(sel, m)
        sel = np.union1d(sel[((sy - iy) % 2 == 0) & ((sx - ix) % 2 == 0)], near)
        levels = [2 * FINE_STEP, FINE_STEP]
    if len(sel) > MAX_POINTS:
        sel = sel[np.argpartition(I[sel], len(sel) - MAX_POINTS)[-MAX_POINTS:]]
    sy, sx = np.divmod(sel, m)
    tx, ty = t[sx], t[sy]
    Uk = F.ravel()[sel] * (ph[sy] * ph[sx] * (h * h / math.pi))
    # each order's rim sum, set up for the coarse points' tilts
    tobs = float(np.max(np.hypot(tx, ty)))
    summers = [_rim_summer(nf, ph_, tobs, rim) for ph_ in phases]
    _, s0, den, cx, cy, traced = summers[0]
    nth = len(cx)

    def rim_sum(tx, ty):
        out = weights[0] * summers[0][0](tx, ty) if weights[0] != 1.0 else summers[0][0](tx, ty)
        for wt, sm in zip(weights[1:], summers[1:]):
            out = out + wt * sm[0](tx, ty)
        return out

    dU = rim_sum(tx, ty)
    dI = np.abs(2 * (np.conj(Uk) * dU).real + np.abs(dU) ** 2)
    J = np.abs(Uk + dU) ** 2
    # refine: the tilt step pi / 2 (where the coarse points were thinned), then pi / 4, around the REFINE points of the
    # largest change and of the largest truth found so far (and the model's peak); U there summed directly on the
    # samples (separable), dU on the rim
    ring_x, ring_y = np.array([-1, 0, 1, -1, 1, -1, 0, 1]), np.array([-1, -1, -1, 0, 0, 1, 1, 1])
    seen = set(zip(np.round(tx / FINE_STEP).astype(int).tolist(), np.round(ty / FINE_STEP).astype(int).tolist()))
    ptx, pty, pU, pdU = [tx], [ty], [Uk], [dU]
    for level in levels:
        dIall, Jall = np.concatenate([dI]), np.concatenate([J])
        Tx, Ty = np.concatenate(ptx), np.concatenate(pty)
        cand = np.unique(np.concatenate([np.argsort(dIall)[-REFINE:], np.argsort(Jall)[-REFINE:]]))
        ftx = np.concatenate([(Tx[cand, None] + level * ring_x[None]).ravel(), t[ix] + level * ring_x])
        fty = np.concatenate([(Ty[cand, None] + level * ring_y[None]).ravel(), t[iy] + level * ring_y])
        keys = list(zip(np.round(ftx / FINE_STEP).astype(int).tolist(), np.round(fty / FINE_STEP).astype(int).tolist()))
        new, kept = [], set()
        for q, kk in enumerate(keys):
            if kk not in seen and kk not in kept:
                kept.add(kk)
                new.append(q)
        if not new:
            continue
        seen |= kept
        ftx, fty = ftx[new], fty[new]
        ux_, ix_ = np.unique(ftx, return_inverse=True)
        uy_, iy_ = np.unique(fty, return_inverse=True)
        Gx = g @ np.exp(-1j * np.outer(x, ux_))                     # (n_y, tilts x)
        Ey = np.exp(-1j * np.outer(uy_, x))                         # (tilts y, n_y)
        Uf = np.sum(Ey[iy_] * Gx.T[ix_], axis=1) * (h * h / math.pi)
        dUf = rim_sum(ftx, fty)
        ptx.append(ftx); pty.append(fty); pU.append(Uf); pdU.append(dUf)
        dI = np.concatenate([dI, np.abs(2 * (np.conj(Uf) * dUf).real + np.abs(dUf) ** 2)])
        J = np.concatenate([J, np.abs(Uf + dUf) ** 2])
    Uall = np.concatenate(pU)
    # E is over the *truth's* peak, |U + dU|^2 (near the model's: an edge wave that lowers the peak raises E)
    itrue = float(np.max(J))
    ipk = float(max(float(I[k]) * (h * h / math.pi) ** 2, np.max(np.abs(Uall) ** 2)))
    psi = (s0 - t[ix] * cx - t[iy] * cy) ** 2 / den
    info = {"peak_tilt": (float(t[ix]), float(t[iy])), "strehl": ipk, "strehl_true": itrue,
            "max_psi_rad": float(np.max(np.abs(psi))), "samples": n, "rim_nodes": nth, "points": len(dI),
            "traced": bool(traced)}
    return (float(dI.max() / itrue) if itrue > 0 else 0.0), info


#: the pupil-to-plane map's polynomial degree and the rim radius's harmonics (:func:`fit_rim`)
RIM_MAP_DEGREE = 4
RIM_HARMONICS = 8


def fit_rim(uv, xy, xc, beam_r: float):
    """The beam's rim on the wave plane, the pupil's rim imaged (the aperture's edge that diffracts), as harmonics of
    its radius over ``beam_r`` (mm) about ``xc`` (mm) (:func:`rim_radius`): the map from the pilot
    rays' pupil coordinates ``uv`` (N, 2, the unit disc) to their points ``xy`` (N, 2) mm on the plane fitted by a
    polynomial of degree :data:`RIM_MAP_DEGREE` (least squares) and evaluated on the unit circle. The circle the
    estimate took before (radius ``beam_r``, half the footprint's smaller extent) is its value for a linear map; an
    oblique beam's footprint is not a circle (the A489 at 10 deg: radii 0.977-1.030 of ``beam_r``). None where the
    rays are too few for the fit, where the rim is that circle (to 1e-9) or where it leaves 0.5-1.5 of ``beam_r``."""
    uv, xy = np.asarray(uv, float), np.asarray(xy, float)
    P = _map_powers(RIM_MAP_DEGREE)
    if len(uv) < 3 * len(P) or beam_r <= 0:
        return None
    coef = _lsq(_monomials(uv, P), xy)
    a = 2 * math.pi * np.arange(256) / 256
    rim = _monomials(np.stack([np.cos(a), np.sin(a)], 1), P) @ coef
    u = (rim - np.asarray(xc, float)) / beam_r
    rho = np.hypot(u[:, 0], u[:, 1])
    z = (u[:, 0] + 1j * u[:, 1]) / rho                          # exp(i theta)
    zm = np.cumprod(np.repeat(z[:, None], RIM_HARMONICS, 1), axis=1)   # exp(i m theta), m = 1 ..
    B = np.concatenate([np.ones((len(z), 1)), zm.real, zm.imag], 1)
    c = _lsq(B, rho)
    if np.max(np.abs(rho - 1.0)) < 1e-9:
        return None                                    # the circle itself (a linear map)
    if rho.min() < 0.5 or rho.max() > 1.5 or not np.all(np.isfinite(c)):
        return None                                    # no smooth rim about the centre: the circle kept
    return np.concatenate([[c[0]], c[1:RIM_HARMONICS + 1] - 1j * c[RIM_HARMONICS + 1:]])


def _lsq(A, b):
    """Least squares ``A x = b`` (``b`` (N,) or (N, K)) by the normal equations of the column-scaled system with one
    step of iterative refinement (a LAPACK least-squares solve cost ~15 ms a call on a loaded 2-core host, this
    ~0.1 ms: :func:`fit_pupil_phase`)."""
    scale = np.maximum(np.sqrt(np.sum(A * A, 0)), 1e-300)
    A = A / scale
    G = A.T @ A
    x = np.linalg.solve(G, A.T @ b)
    x = x + np.linalg.solve(G, A.T @ (b - A @ x))
    return x / (scale if np.ndim(b) == 1 else scale[:, None])


def _monomials(uv, P) -> np.ndarray:
    """``u^i v^j`` (N, K) of the points ``uv`` (N, 2) for the powers ``P`` (K, 2) (tables of repeated products)."""
    d = int(P.max()) if len(P) else 0
    U = np.cumprod(np.concatenate([np.ones((len(uv), 1)), np.repeat(uv[:, :1], d, 1)], 1), axis=1)
    V = np.cumprod(np.concatenate([np.ones((len(uv), 1)), np.repeat(uv[:, 1:2], d, 1)], 1), axis=1)
    return U[:, P[:, 0]] * V[:, P[:, 1]]


def _map_powers(degree: int) -> np.ndarray:
    """The monomials ``u^i v^j``, ``i + j <= degree``, as (K, 2) powers."""
    return np.array([(i, n - i) for n in range(degree + 1) for i in range(n, -1, -1)], int)
