"""The ray-wave model's own error, estimated from the scene (issue 27); :mod:`rwwarp.wave.wave_step` removes it.

The ray-wave model forms the field on the wave plane (the DOE, else the last surface) geometrically: each
ray tube carries its power and optical path there, so the beam ends at the plane with a hard edge, the
limiting aperture's shadow. Physically that edge has diffracted on the way from the aperture to the plane:
it is blurred over about ``sqrt(lambda d)`` and rings. The model leaves that out.

Derivation (scalar, Fresnel order, about the beam's convergence). A field ``V(xi) S_R(xi)`` on the aperture
(``S_R``: a spherical wave converging to a point a distance ``R_A`` behind it) propagated a distance
``z1`` is, by the Fresnel scaling theorem, ``(1 / s) [P_{z1 / s} V]((x - T) / s + T) S_{R}(x)`` with ``s = 1 -
z1 / R_A`` and ``R = R_A - z1`` the plane's distance to the focus ``T``; the geometric model keeps
``(1 / s) V((x - T) / s + T) S_R(x)``. Written on the wave plane's own coordinates, the truth is the geometric
field with its converging sphere removed, ``G = U_geo / S_R``, propagated as a wave over the *reduced
distance*

    d = z1 R / (z1 + R)            (1 / d = 1 / z1 + 1 / R; d = z1 for a collimated beam, R -> inf)

and multiplied by the sphere again: ``U_true = S_R P_d[G]`` (:func:`rwwarp.wave.wave_step.apply_wave_step`). Its
Fresnel number is

    N_F = n r_w^2 / (lambda d) = n a^2 (f - z1) / (lambda f z1)     (thin lens: f, aperture radius a),

``r_w`` the beam's radius on the plane. Without a DOE the two fields give the same intensity at the focus
(the extra Fresnel propagation is a pure phase in the Fourier plane): the model's error needs a phase
that varies across the blurred edge, the wavefront ``Phi`` after the DOE relative to the sphere converging to the
sensor patch.

The main order: the rim's edge waves (:mod:`rwwarp.wave.edge_wave` evaluates this). Across the rim the hard step
becomes the Fresnel edge; the difference lives within ``~ sqrt(lambda d)`` of the rim, and at each rim point it
meets the phase's local radial slope ``s`` (rad per beam radius). The 1-D edge's Fourier pair turns each plane-wave
component of the edge by its Fresnel phase, so the rim point's *edge wave* on the sensor, ``2 exp(i Phi) / (i s)``
(the boundary term of the pupil integral), becomes ``2 exp(i Phi) (exp(-i psi) - 1) / (i s)`` with ``psi = s^2 /
(4 pi N_F + 2 c)`` (``c`` the radial curvature of ``Phi`` at the rim: a chirp turns its curvature as it
propagates; exact in Fresnel order for a defocus, "Other orders" below). Summed around the rim at each sensor
point (a tilt ``t`` of the observation adds ``-t . n`` to the slope and the phase) it is the change ``dU`` of the
field ``U`` there, and

    E = max_t |2 Re(conj(U) dU) + |dU|^2| / max_t |U + dU|^2      (max |I_model - I_true| / max I_true)

over the PSF's peak and its bright part. ``Phi`` is a 2-D polynomial (degree 6) fitted to the pilot rays'
frequencies after the DOE against the sphere to the patch (:func:`rwwarp.wave.edge_wave.fit_pupil_phase`), so a
decentred DOE off axis (coma, astigmatism about the beam's own centre) is read as it is. Nothing is fitted.

*The rim.* The edge that diffracts is the pupil's rim imaged onto the plane, and the sum runs on it: the pilot rays'
map from their pupil coordinates to the plane (a polynomial of degree :data:`rwwarp.wave.edge_wave.RIM_MAP_DEGREE`,
least squares) evaluated on the pupil's rim, its radius about the beam's centre as harmonics
(:func:`rwwarp.wave.edge_wave.fit_rim`, :func:`rwwarp.wave.edge_wave.rim_radius`); the pupil's samples are its inside.
Where the map is linear (the thin lens) that rim is the circle of radius ``beam_r`` (half the footprint's smaller
extent) the sum took before, to 1e-15 (within 1e-9 the circle itself is used: those estimates are unchanged); an
oblique beam through a real lens is not a circle: the A489 at F/4 and 10 deg, radii 0.977-1.030 of ``beam_r`` at 0.45
um (the stop's rim traced by the truth's own rays: the same to 6e-5). The error is a coherent sum of edge waves whose
phase at the rim moves by ``S`` rad per unit of radius, so a rim misplaced by 1-3 % of the radius (0.3-1 rad at ``S``
34 rad) changes it by a factor: on that beam the circle read 0.384 against the truth's 0.131 (2.93x; 2.71x against the
main-order truth), the imaged rim reads 0.171 (1.30x / 1.20x). Measured on the beam itself (``perf/model_error_a489.py
--rim-check``): the footprint's amplitude diffracted over ``d`` by the exact angular spectrum and the traced phase
applied after it (this module's picture, the beam's aberration before the DOE taken as applied at the plane)
reproduces the main-order truth on the real footprint (0.131 against 0.142; 0.95x / 1.04x at 0.55 / 0.65 um) and reads
0.326 (2.3x) on the circle; the fitted phase's residual there is 0.03 rad RMS. Where a pilot ray is lost (vignetting)
or the pilot is not the circular pupil grid, the circle is kept.

*Why the old scalar law failed, and its place now.* To first order in ``psi`` and for a radial phase on the axis,
``dU = -S / (2 pi N_F) exp(i Phi(1))``: the error ``E = S / (pi N_F)`` of a rim slope ``S``, the law :func:`model_error`
``E = C S / N_F (1 + (S / S0)^2)`` with ``C = 0.25``, ``S0 = 25`` rad calibrated on a = 2.5 mm, ``A rho^4`` (A = 1,
3, 8), 10 and 35 mm (N_F 57, 530). It misses two things the sum keeps. (a) Below N_F ~ 50 with S > 10 the edge
wave's Fresnel phase ``psi`` is no longer small: ``|exp(-i psi) - 1| = 2 |sin(psi / 2)|`` grows slower than
``psi`` and the edge wave turns by ``psi / 2`` against the core's field, so the error grows slower than ``1 /
N_F`` (the 1 / sqrt(N_F)-like saturation) and, at some ``S``, faster (interference: at N_F 20.5 the rim slopes 12 /
15 / 24 rad give ``E N_F / S`` = 0.14 / 0.31 / 0.19, no smooth law in ``(S, N_F)`` follows that). The law read 2.3x
high at N_F 20.5, S 12 and 4.3x at N_F 9.1; the sum 0.92x / 0.90x. (b) Off axis the DOE's phase about the
beam's own centre has coma and astigmatism; the rim phase ``Phi(n(theta))`` then varies around the rim, the rim's
edge waves reach no sensor point in phase, and the radial slope's RMS (the law's ``S``) overstates them: a = 1.5
mm, 20 mm (N_F 54.5), 0.5 deg (the beam 0.44 of its radius off the DOE's centre), the law 4.0x, the sum 1.00x (the
beam's own tilt is a shift of ``t``: it moves the spot and changes nothing). (c) Steep rims: the edge wave's reach
is a shift of ``S / (2 pi N_F)`` of the beam's radius (0.3-0.9 at S 100-300 rad, N_F 20-57), over which the rim's
profile is no longer quadratic; the sum carries each rim point's edge wave by the ray traced back over the reduced
distance (:mod:`rwwarp.wave.edge_wave`, "Steep rims"), which the first sum, on the quadratic profile, left out (it read
0.16-0.6x on ``c rho^4`` at N_F 55-57, S 100-140 rad, and 2-12x on ``rho^6`` / ``rho^8``). The law remains the
fallback for a phase too steep for the sum's sampling (slopes beyond :data:`rwwarp.wave.edge_wave.MAX_SLOPE_RAD`, 400
rad: the estimate's note says so) and the ``S`` in the plan's line. The sum was checked on radial wave truths up to
rim slopes of 300 rad (:data:`CHECKED_SLOPE_RAD`; beyond it the note says so) and off the axis up to the pilot's RMS
rim slope of 206 rad at 0.5 deg (:data:`CHECKED_OFF_AXIS_SLOPE_RAD`; below).
The A489's own beams (its stop diffracted as a wave through the asphere to the DOE plane: ``tests/rwwarp/_a489_truth.py``,
``perf/model_error_a489.py``) at F/8, F/4 and F/2.2, 0-10 deg, continuous even-polynomial DOEs with rim slopes 15-92
rad: estimate / measured 0.51-1.18 over 10 cases (0.51 at F/8 on axis with the steep DOE); F/2.2 at 5 / 10 deg 0.89x /
0.64x; at 0.45 / 0.65 um with every order of the wrapped relief, F/4 and F/8, 0 and 10 deg, F/2.2 on axis: 0.59-1.37x
(F/4, 0.45 um, 10 deg: 1.30x; 2.93x on the circle before the rim was imaged, "The rim" above).

Checks (``tests/rwwarp/test_model_error.py``; truths: the radially symmetric Gauss-Hankel quadrature of the exact
angular spectrum, thin lens f = 50 mm, 0.55 um, sensor at the lens focus, DOE pupil phase ``sum_i c_i rho^(2i)``;
off axis the 2-D angular-spectrum truth against the 2-D geometric model; estimate / measured; "before": the sum on
the quadratic profile, "now": with the traced rays):

=======================================  =======  =====  ========  ===============  ===========  =========
case (a mm, DOE-to-sensor mm, phase)     N_F      S      measured  law (before)     sum before   sum now
=======================================  =======  =====  ========  ===============  ===========  =========
2.5, 10, 3 rho^4 (law calibration)       56.8     12     4.13e-2   6.5e-2 (1.57)    0.96         1.02
2.5, 35, 3 rho^4 (law calibration)       530      12     5.56e-3   7.0e-3 (1.25)    0.97         0.97
2.5, 10, 8 rho^4 (law calibration)       56.8     32     0.446     0.37 (0.83)      0.94         0.95
2.5, 20, 3 rho^4                         152      12     1.76e-2   2.4e-2 (1.38)    0.99         1.01
2.5, 45, 2 rho^2                         2045     4      3.41e-4   5.0e-4 (1.47)    1.17         1.18
1.5, 35, -3 rho^2 + 3 rho^4              191      6      8.37e-3   8.3e-3 (0.99)    1.06         1.05
1.5, 35, 3 rho^6                         191      18     2.71e-2   3.6e-2 (1.32)    0.99         1.02
1.5, 10, 3 rho^4                         20.5     12     7.94e-2   0.18 (2.27)      0.92         1.09
1.0, 10, 3 rho^4                         9.1      12     9.39e-2   0.41 (4.33)      0.90         1.35
1.5, 14, 4 rho^4                         31.8     16     0.218     0.18 (0.81)      0.97         1.00
1.5, 20, 3 rho^4, 0.3 deg (2-D)          54.5     13.7   6.34e-2   8.2e-2 (1.29)    1.21         1.23
1.5, 20, 3 rho^4, 0.5 deg (2-D)          54.5     17.7   3.04e-2   0.122 (4.01)     1.00         1.02
1.5, 20, 3 rho^4, 0.7 deg (2-D)          54.5     23.3   3.56e-2   0.199 (5.6)      0.93         0.95
steep (truth with the widened band):
1.5, 20, 25 rho^4                        54.5     100    0.116     -                0.39         0.93
1.0, 10, 10 rho^4                        9.1      40     0.609     -                1.03         1.25
1.5, 10, 25 rho^4                        20.5     100    0.278     -                0.62         0.76
2.5, 10, -50 rho^2 + 50 rho^4            56.8     100    4.43e-2   -                1.49         0.71
2.5, 10, 25 rho^6                        56.8     150    6.37e-2   -                2.01         1.34
1.5, 20, 50 rho^4                        54.5     200    0.234     (2.5e2)          (the law)    1.02
2.5, 10, 20 rho^8                        56.8     160    8.40e-3   -                12.5         1.26
1.5, 20, 75 rho^4                        54.5     300    0.247     -                (the law)    1.07
1.5, 20, 25 rho^4, 0.5 deg (2-D)         54.5     147    5.78e-2   -                (the law)    0.96
1.5, 20, 35 rho^4, 0.5 deg (2-D)         54.5     206    6.85e-2   -                (the law)    0.96
=======================================  =======  =====  ========  ===============  ===========  =========

(``S``: the analytic rim slope on the axis, the pilot's RMS rim slope off axis. The 2-D truth's own error is
~7e-4 of the peak. Other radial cases measured while deriving the first sum, not in the tests: 0.82 .. 1.02, among them
6 rho^4 at N_F 20.5 (S 24) 0.82 and 8 rho^4 at N_F 25 (S 32, error 1.15 of the peak) 0.86.)

Other orders. A relief of depth ``s 2 pi`` (``s = s(lambda)``, 1 at the design wavelength:
:func:`rwwarp.doe.wavelength_scale`) transmits ``exp(i s wrap(phi0)) = sum_m c_m exp(i m phi0)``, ``c_m = sinc(m - s)
exp(i pi (s - m))`` (the Fourier series of one zone; quantised levels: :func:`rwwarp.wave.focal.doe_order_coefficients`),
so order ``m`` carries ``eta_m = sinc^2(m - s)`` of the light (the A489's fused-silica relief: 0.829 / 0.080 / 0.031 in
orders 1 / 2 / 0 at 0.45 um, s = 1.237; 0.918 / 0.033 / 0.018 in 1 / 0 / 2 at 0.65 um, s = 0.840). Order ``m`` leaves
the DOE with ``m phi0``: against the sphere to the patch its pupil phase is ``Phi_m = Phi_1 + (m - 1) phi0``, a defocus
of rim slope ``S_m = S_1 + (m - 1) S_phi0`` (``S_phi0`` the DOE's own rim slope over the beam). An order focuses on the
sensor where ``S_m ~ 0``; otherwise its light spreads over a disc of tilt radius ``~|S_m|`` (its intensity ``~4 eta_m /
S_m^2`` of a focused beam's peak) and its rim's edge wave has the amplitude ``2 |c_m| / |S_m|``. On the A489 (the sensor
near the bare asphere's focus) the zero order is nearly focused at 0.65 um (``S_0`` 7.9 rad against the main order's
87 rad at F/4): with 3.6 % of the main order's light its peak is 8x the main order's spread one (the truth's).

The edge's diffraction over ``d`` acts on the field before the DOE, the same for every order, and the truth is linear
in the DOE's transmission: by the duality of the main order's derivation (:mod:`rwwarp.wave.edge_wave`) each order's
rim edge wave is turned by the Fresnel phase of its own slope, ``psi_m = s_m^2 / (4 pi N_F + 2 c_m)``. So the fields
add, ``U = sum_m c_m U_m`` and ``dU = sum_m c_m dU_m`` (each ``(U_m, dU_m)`` the edge-wave evaluation on ``Phi_m``,
fitted to the pilot rays' frequencies of that order, less the main order's mean tilt: an order's own tilt is its
offset on the sensor), and

    E = max_t |2 Re(conj(U) dU) + |dU|^2| / max_t |U + dU|^2

(:func:`rwwarp.wave.edge_wave.edge_wave_orders_error`): the measured error's normalisation, over the truth's peak
whichever order makes it. The orders counted are those whose geometric footprint on the sensor covers the patch
centre, up to :data:`rwwarp.wave.edge_wave.MAX_SLOPE_RAD` (steeper ones, ``|c_m| <= 0.05`` on the A489, are left out
and the note says so). ``main_estimate`` is the main order alone, ``orders_estimate`` the difference (signed). Nothing
fitted. What this replaces: the main order's error over its own peak plus an orders' term, the change of the on-axis
intensity over the on-axis intensity of all orders (off the axis an in-phase upper bound, now kept only beside the
scalar law). It failed both ways: (1) an order focused on the patch raises the peak the error is measured against (the
A489 at F/4, 0.65 um, on axis: measured 0.340, old estimate 1.04, 3.07x; now 0.382, 1.12x); (2) a defocused main order's
axis is not its peak (``|U(0)|^2 = (sin(S / 4) / (S / 4))^2`` for a defocus), so the orders' change over it over-counted
(F/4 at 0.45 um: the orders' term 0.69 where removing the orders moves the truth's error by 0.5 %; old 3.08x, now 0.313,
1.01x) or under-read (F/8 at 0.65 um on axis: measured 0.734, 0.167 with the main order alone; old 0.167, 0.23x; now
0.756, 1.03x). Checked (held out, none of them sets anything): the thin-lens truth with the wrapped transmission
(``tests/rwwarp/test_model_error_orders.py``: thin lens, DOE ``-40 rho^2`` rad 20 mm before the lens focus, used at
0.909x / 1.127x its design phase): measured 4.65e-3 / 2.16e-3, estimate 4.49e-3 / 2.37e-3 (0.97x / 1.10x; before 0.99x /
1.63x; the main order's edge waves alone 4.9e-4); the stored Cooke design at 0.47 / 0.63 um on axis against its
one-step vs wave-path difference 1.06e-2 / 1.11e-2: 1.89e-2 / 1.27e-2 (1.78x / 1.15x; before 1.74x / 1.28x); the
A489 + DOE (``tests/rwwarp/_a489_truth.py``, every order of its relief, the glass at the wavelength) at 0.45 / 0.65
um, F/4 and F/8, on axis and at 10 deg: docs/accuracy.md ("Other wavelengths"; the F/4 case at 0.45 um and 10 deg
read 2.9x on the circle, not an orders effect (the main order alone 2.7x the main-order truth) nor the beam's
aberration before the DOE diffracting over ``d`` (0.75 rad there, which the plan's note reports beyond
:data:`PRE_DOE_PHASE_RAD`): the picture that leaves that out reproduces the truth on the real footprint; the rim's
shape, "The rim" above: 1.30x now).

Scope of the scene reading (:func:`estimate_for_raywave`): the limiting aperture is the stop, imaged into
the space in front of the wave plane (paraxially, through the refracting surfaces between them); apertures
that vignette the beam elsewhere are not counted. Distances are axial; an off-axis beam's edge sees its
Fresnel number change by O(theta^2). Lengths in mm, wavelengths in um, phases in rad.
"""
from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass, fields as _dc_fields

import numpy as np

from .edge_wave import MAX_SLOPE_RAD, edge_wave_error, edge_wave_orders_error, fit_pupil_phase, fit_rim, max_slope

#: calibration of the scalar law :func:`model_error` (module docstring; now the fallback and the small-psi limit):
#: E = C S / N_F (1 + (S / S0)^2)
MODEL_ERROR_C = 0.25
MODEL_ERROR_S0 = 25.0
#: the largest rim slope (rad) at which the edge-wave estimate was checked against a wave truth (radial truths, module
#: docstring and :mod:`rwwarp.wave.edge_wave`, "Steep rims"); beyond it the plan's note says so
CHECKED_SLOPE_RAD = 300.0
#: ... and off the DOE's axis (a decentred DOE's coma and astigmatism about the beam's centre: the 2-D truth at 0.5 deg,
#: the pilot's RMS rim slope up to 206 rad); a beam off the axis beyond it gets the note too
CHECKED_OFF_AXIS_SLOPE_RAD = 200.0
#: rim rays: pilot points at least this share of the footprint's largest radius from its centre
RIM_SHARE = 0.9


def reduced_distance_mm(aperture_to_plane_mm: float, plane_to_focus_mm: float) -> float:
    """The reduced distance ``d = z1 R / (z1 + R)`` (mm) over which the geometric field of a beam converging
    to a focus ``R`` (mm, signed: > 0 behind the plane, inf collimated, < 0 diverging from a point in front)
    behind the plane has to diffract as a wave, ``z1`` (mm, >= 0) behind its limiting aperture."""
    z1, R = float(aperture_to_plane_mm), float(plane_to_focus_mm)
    if not math.isfinite(z1) or z1 < 0:
        raise ValueError(f"aperture_to_plane_mm must be a finite distance >= 0, got {aperture_to_plane_mm!r}")
    if math.isnan(R) or R == 0:
        raise ValueError(f"plane_to_focus_mm must be nonzero (inf: collimated), got {plane_to_focus_mm!r}")
    if z1 == 0:
        return 0.0
    if math.isinf(R):
        return z1
    return z1 * R / (z1 + R)


def fresnel_number(beam_radius_mm: float, aperture_to_plane_mm: float, plane_to_focus_mm: float,
                   wavelength_um: float, n: float = 1.0) -> float:
    """Fresnel number ``N_F = n r_w^2 / (lambda |d|)`` of the limiting aperture seen from the wave plane:
    ``r_w`` the beam's radius on the plane (mm), ``d`` the :func:`reduced_distance_mm`, ``lambda`` the vacuum
    wavelength (um), ``n`` the medium's index. inf where the plane is at the aperture (``z1 = 0``). For a
    thin lens of focal length f and aperture radius a with the plane z1 behind it: ``a^2 (f - z1) / (lambda f
    z1)``."""
    d = reduced_distance_mm(aperture_to_plane_mm, plane_to_focus_mm)
    if not (wavelength_um > 0 and beam_radius_mm >= 0 and n > 0):
        raise ValueError(f"need wavelength_um > 0, beam_radius_mm >= 0, n > 0; got {wavelength_um!r}, "
                         f"{beam_radius_mm!r}, {n!r}")
    if d == 0:
        return math.inf
    return n * beam_radius_mm ** 2 / (wavelength_um * 1e-3 * abs(d))


def model_error(fresnel_number_: float, rim_slope_rad: float) -> float:
    """The scalar law of the model error (the fallback of :func:`estimate_for_raywave` where the pupil phase is
    too steep for :func:`rwwarp.wave.edge_wave.edge_wave_error`; module docstring: where it fails) ``E = C S / N_F
    (1 + (S / S0)^2)`` (max |I_model - I_true| over the PSF's
    peak, dimensionless) for the Fresnel number ``N_F`` of :func:`fresnel_number` and the rim slope
    ``S = rho dW/drho`` (rad) of the wavefront after the DOE relative to the sphere converging to the sensor
    patch (module docstring: derivation and calibration)."""
    nf, s = float(fresnel_number_), abs(float(rim_slope_rad))
    if not nf > 0 or not math.isfinite(s):
        raise ValueError(f"need a Fresnel number > 0 and a finite rim slope, got {fresnel_number_!r}, {rim_slope_rad!r}")
    if math.isinf(nf):
        return 0.0
    return MODEL_ERROR_C * s / nf * (1.0 + (s / MODEL_ERROR_S0) ** 2)


def other_orders_error(fresnel_number_: float, rim_slope_rad: float, efficiency_ratio: float) -> float:
    """The error (over the PSF's peak, dimensionless) one of a wrapped DOE's other diffraction orders adds to
    :func:`model_error`: ``E_m = 8 sqrt(eta_m / eta_0) |sin(S_m^2 / (8 pi N_F))| / S_m`` (module docstring,
    "Other orders"), for the order's rim slope ``S_m`` (rad, against the sphere converging to the patch: its
    defocus there), ``N_F`` of :func:`fresnel_number` and its efficiency over the main order's,
    ``eta_m / eta_0`` (>= 0)."""
    nf, sm, r = float(fresnel_number_), abs(float(rim_slope_rad)), float(efficiency_ratio)
    if not nf > 0 or not math.isfinite(sm) or not (r >= 0 and math.isfinite(r)):
        raise ValueError(f"need a Fresnel number > 0, a finite rim slope and an efficiency ratio >= 0, got "
                         f"{fresnel_number_!r}, {rim_slope_rad!r}, {efficiency_ratio!r}")
    if math.isinf(nf) or sm == 0 or r == 0:
        return 0.0
    return 8.0 * math.sqrt(r) * abs(math.sin(sm * sm / (8.0 * math.pi * nf))) / sm


@dataclass(frozen=True)
class ModelError:
    """A source's estimated model error and what it is made of: ``estimate`` (dimensionless, relative to
    the PSF's peak), ``fresnel_number``, ``aperture_to_plane_mm`` (z1), ``plane_to_focus_mm`` (R),
    ``reduced_distance_mm`` (d), ``beam_radius_mm`` (r_w), ``rim_slope_rad`` (S), ``wavelength_um``."""

    estimate: float
    fresnel_number: float
    aperture_to_plane_mm: float
    plane_to_focus_mm: float
    reduced_distance_mm: float
    beam_radius_mm: float
    rim_slope_rad: float
    wavelength_um: float
    note: str = ""
    #: the other DOE orders' share of ``estimate``: the estimate with every order that lights the patch, summed
    #: coherently, less the main order's alone (signed: a focused order's peak lowers the relative error; 0 for one order)
    orders_estimate: float = 0.0
    #: the main order's share: the rim's edge waves on the beam's pupil phase (:mod:`rwwarp.wave.edge_wave`)
    main_estimate: float = 0.0

    def to_dict(self) -> dict:
        """The fields by name, numbers as floats (its fields are numbers and text: no deep copy needed)."""
        return {f.name: (v if isinstance(v, str) else float(v))
                for f in _ME_FIELDS for v in (getattr(self, f.name),)}

    def text(self) -> str:
        """One line for the plan's reasons and ``--explain``."""
        return (f"model error (geometric field at the wave plane): ~{self.estimate:.2g} of the peak "
                f"(N_F {self.fresnel_number:.4g}: beam radius {self.beam_radius_mm:.4g} mm, {self.aperture_to_plane_mm:.4g} mm "
                f"behind the stop's image, focus {self.plane_to_focus_mm:.4g} mm on, reduced distance "
                f"{self.reduced_distance_mm:.4g} mm; rim slope {self.rim_slope_rad:.3g} rad; "
                f"the rim's edge waves on the pupil phase {self.main_estimate:.2g}"
                + (f" for the DOE's main order alone, {self.estimate:.2g} with its other orders that light the patch "
                   f"(their share {self.orders_estimate:+.2g})" if self.orders_estimate != 0 else "")
                + ", rwwarp.wave.model_error)"
                + (f"; {self.note}" if self.note else ""))


_ME_FIELDS = _dc_fields(ModelError)


def stop_to_plane_mm(lens, plane: int, wavelength_um: float) -> float:
    """Distance (mm, >= 0) from the image of the aperture stop, formed by the refracting surfaces between
    the stop and surface ``plane``, to that surface's vertex plane: the diffraction distance of the
    geometric field's edge. 0 where the stop is at or behind the plane, or its image lies behind it."""
    from .. import paraxial
    stop = lens.stop_index
    if stop >= plane:
        return 0.0
    P = np.array(paraxial.surface_powers(lens, wavelength_um), float)
    if lens.surfaces[plane].type == "doe":
        P[plane] = 0.0      # the DOE acts after the field is formed: the image space is the one in front of it
    n = paraxial.signed_indices(lens, wavelength_um)
    t = [s.thickness for s in lens.surfaces]
    # a paraxial ray through the stop's centre; its height on the plane over its slope after the plane's own
    # refraction (a curved last surface: the field is formed on its vertex plane, in the medium after it)
    ys, _, nus = paraxial.ynu_steps(P[stop:plane + 1], t[stop:plane + 1], n[stop:plane + 1], 0.0, 1.0)
    if nus[-1] == 0:
        return math.inf   # the stop's image at infinity: no finite distance (telecentric in front of the plane)
    z1 = float(ys[-1] * n[plane] / nus[-1])
    return max(z1, 0.0)


def _rim_slope(xy, xc, rr, rim, beam_r, df):
    """``S = 2 pi RMS_rim[(x - x_c) . df (r_w / |x - x_c|)^3]`` (rad) of the frequency offsets ``df`` (cycles/mm)
    less their mean (:func:`estimate_for_raywave`)."""
    df = df - df.mean(0)
    sl = np.sum((xy[rim] - xc) * df[rim], axis=1) * (beam_r / np.maximum(rr[rim], 1e-300)) ** 3
    return 2 * math.pi * float(np.sqrt(np.mean(sl * sl)))


def _other_orders(surface, prof, xy, wavelength_um, m0, alpha=None, phi=None):
    """The wrapped DOE's orders other than ``m0`` and their weight over ``m0``'s, ``[(m, c_m / c_0)]`` (complex;
    ``|c_m / c_0|^2 = eta_m / eta_0``, the efficiencies):
    the orders a focal plan keeps (``m0 +- FOCAL_MAX_ORDER`` and, for ``N`` levels, ``1 +- N``, ``1 +- 2N``) from
    the relief's order weights (:func:`rwwarp.wave.focal.doe_order_coefficients`); none where the relief does not
    wrap over the beam (one smooth order). ``alpha`` (the relief's scale at ``wavelength_um``) and ``phi`` (its
    design phase at ``xy``): when already computed."""
    from .. import doe
    from .focal import FOCAL_MAX_ORDER, doe_order_coefficients
    if phi is None:
        phi = prof.phase(xy[:, 0], xy[:, 1], surface.design_wavelength_um)
    span = float(np.ptp(phi)) if phi.size else 0.0
    if not surface.levels and span <= 2 * math.pi:
        return []
    if alpha is None:
        alpha = doe.wavelength_scale(surface.material, surface.design_wavelength_um, wavelength_um)
    ms = set(range(int(m0) - FOCAL_MAX_ORDER, int(m0) + FOCAL_MAX_ORDER + 1))
    if surface.levels:
        ms |= {1 + j * int(surface.levels) for j in (-2, -1, 1, 2)}
    ms = sorted(ms - {int(m0)})
    eta = np.abs(doe_order_coefficients(alpha, surface.levels, ms)) ** 2
    eta0 = float(np.abs(doe_order_coefficients(alpha, surface.levels, [int(m0)])[0]) ** 2)
    if eta0 <= 0:
        return []
    c = doe_order_coefficients(alpha, surface.levels, ms)
    c0 = doe_order_coefficients(alpha, surface.levels, [int(m0)])[0]
    return [(m, complex(cm / c0)) for m, cm, e in zip(ms, c, eta) if e > 1e-8 * eta0]


def _main_order(surface, prof, xy, wavelength_um, alpha=None, phi=None):
    """The DOE's main-order factor m (its phase is ``m phi0``): ``alpha`` where the relief does not wrap over
    the beam, else the integer order nearest ``alpha`` (at least 1). ``alpha``, ``phi``: as :func:`_other_orders`."""
    from .. import doe
    if alpha is None:
        alpha = doe.wavelength_scale(surface.material, surface.design_wavelength_um, wavelength_um)
    if phi is None:
        phi = prof.phase(xy[:, 0], xy[:, 1], surface.design_wavelength_um)
    span = float(np.ptp(phi)) if phi.size else 0.0
    if not surface.levels and span <= 2 * math.pi:
        return float(alpha)
    return float(max(1, round(alpha)))


def estimate_for_raywave(rw) -> list:
    """:class:`ModelError` per source of a :class:`rwwarp.wave.raywave.RayWave`, from its pilot trace (host arrays
    only, no launch): the beam's radius on the wave plane (half the footprint's smaller extent), its focus
    before the DOE (``rw.target``), the stop's image (:func:`stop_to_plane_mm`), and the rim slope of the
    wavefront after the DOE's main order relative to the sphere converging to the patch centre on the
    sensor: ``S = 2 pi RMS_rim[(x - x_c) . (f - f_sphere) (r_w / |x - x_c|)^3]`` over the pilot rays within
    ``RIM_SHARE`` of the footprint's largest radius (``f``: the rays' transverse frequency after the DOE, cycles/mm; ``f - f_sphere``
    less its mean over the beam: a tilt moves the PSF and changes nothing else), reported as ``rim_slope_rad``. The
    main order's estimate (``main_estimate``) is the rim's edge waves summed on the pupil phase fitted to the same
    frequencies (``(x - x_c) / r_w`` against ``2 pi r_w (f - f_sphere)``: :func:`rwwarp.wave.edge_wave.fit_pupil_phase`,
    :func:`rwwarp.wave.edge_wave.edge_wave_error`); the scalar law :func:`model_error` on ``S`` where that phase is
    too steep to sample (the note says so); plus, for a wrapped DOE, its other kept orders' edge waves (module
    docstring, "Other orders": ``orders_estimate``). The result is kept (the latest :data:`MEMO_SIZE`, in this module, not
    on ``rw``: a frozen plan and its copies share it) under a digest of every input it reads (the pilot's arrays, the
    patch centres, the foci, the wavelengths, the planes, the lens and the DOE's profile): the planner asks twice per
    batch (:func:`rwwarp.wave.pixel_scale.consider_pixel`, :func:`rwwarp.wave.wave_step.plan_wave_step`) and the
    second ask costs the digest (~0.1 ms); any changed input recomputes."""
    key = _memo_key(rw)
    hit = _MEMO.get(key)
    if hit is not None:
        _MEMO.move_to_end(key)
        return list(hit)
    out = _estimate_for_raywave(rw)
    _MEMO[key] = tuple(out)
    while len(_MEMO) > MEMO_SIZE:
        _MEMO.popitem(last=False)
    return out


#: the estimates kept (:func:`estimate_for_raywave`), the latest MEMO_SIZE, under the digest of their inputs
MEMO_SIZE = 512
_MEMO: "OrderedDict[bytes, tuple]" = OrderedDict()


def _memo_key(rw, lens_fp: bytes | None = None) -> bytes:
    """A digest of what :func:`_estimate_for_raywave` reads from ``rw``; ``lens_fp``: its lens's
    :func:`rwwarp.wave.plan_cache.lens_fingerprint` when already computed."""
    return _memo_key_from(_memo_prefix(rw.pilot), rw, lens_fp)


def _memo_prefix(pilot):
    """The digest state of :func:`_memo_key` after the pilot's rows (``pos_p``, ``dir_s``, ``ok``): the bulk of
    the hashed bytes, the same for every key of the same pilot rows (:func:`estimate_sources` keeps it across
    calls)."""
    import hashlib
    h = hashlib.blake2b(digest_size=20)
    _memo_update(h, (pilot.pos_p, pilot.dir_s, pilot.ok))
    return h


def _memo_update(h, arrays):
    """Feed each array's dtype, shape and bytes to the digest ``h``."""
    for arr in arrays:
        a = np.ascontiguousarray(arr)
        h.update(repr((a.dtype.str, a.shape)).encode())
        h.update(a.tobytes())


def _memo_key_from(h, rw, lens_fp: bytes | None) -> bytes:
    """:func:`_memo_key` from the state ``h`` after the pilot's rows (:func:`_memo_prefix`, updated here)."""
    _memo_update(h, (rw.centers, rw.target, rw.wls, rw.n_after, rw.lam_mm))
    from .plan_cache import lens_fingerprint
    # the whole lens by value (every surface field, the DOE profile, the glasses' data), never by identity: a new
    # lens may reuse a collected one's id()
    h.update(repr((rw.plane, float(rw.z_plane), float(rw.z_sensor), int(rw.nsrc))).encode())
    h.update(lens_fingerprint(rw.lens) if lens_fp is None else lens_fp)
    return h.digest()


def estimate_sources(lens, plane: int, pilot, centers, target, wls, n_after, lam_mm, z_plane: float,
                     z_sensor: float, key_states: dict | None = None) -> list:
    """:class:`ModelError` of each of ``S`` sources of one lens, each planned on its own, in one call: source ``k``'s
    is what :func:`estimate_for_raywave` gives its single-source plan, and it is kept in (and read from) the same
    memo under the same key. The sources the memo does not hold are estimated together (the lens's fingerprint
    and DOE profile, and each wavelength's stop image, computed once; each source's estimate the same arithmetic
    on its own rows). ``pilot``: the sources' :class:`rwwarp.wave.pilot.Pilot` (S rows), ``centers`` (S, 2) mm
    patch centres (a sequence of (1, 2) or (2,) rows), ``target`` (S, 3) mm reference-sphere centres, ``wls`` um,
    ``n_after`` (S,) the index behind the wave plane (surface ``plane``), ``lam_mm`` (S,) mm; ``z_plane``,
    ``z_sensor`` mm. ``key_states``: a dict the caller keeps across calls with the same ``pilot`` (source index ->
    the memo key's digest state after that source's pilot rows), so each source's rows are hashed once."""
    from types import SimpleNamespace
    from .plan_cache import lens_fingerprint
    S = len(wls)
    wls = [float(w) for w in wls]
    n_after, lam_mm = np.asarray(n_after), np.asarray(lam_mm)
    centers = np.asarray(centers, dtype=np.float64).reshape(S, 2)
    target = np.asarray(target)
    fp = lens_fingerprint(lens)
    out, keys = [None] * S, [None] * S
    for k in range(S):
        sl = slice(k, k + 1)
        row = SimpleNamespace(pilot=SimpleNamespace(pos_p=pilot.pos_p[sl], dir_s=pilot.dir_s[sl], ok=pilot.ok[sl]),
                              centers=centers[sl], target=target[sl], wls=(wls[k],), n_after=n_after[sl],
                              lam_mm=lam_mm[sl], plane=plane, z_plane=z_plane, z_sensor=z_sensor, nsrc=1)
        if key_states is None:
            keys[k] = _memo_key(row, fp)
        else:
            st = key_states.get(k)
            if st is None:
                st = key_states[k] = _memo_prefix(row.pilot)
            keys[k] = _memo_key_from(st.copy(), row, fp)
        hit = _MEMO.get(keys[k])
        if hit is not None:
            _MEMO.move_to_end(keys[k])
            out[k] = hit[0]
    miss = [k for k in range(S) if out[k] is None]
    if miss:
        view = SimpleNamespace(lens=lens, plane=plane, nsrc=len(miss), wls=[wls[k] for k in miss],
                               pilot=SimpleNamespace(pos_p=pilot.pos_p[miss], dir_s=pilot.dir_s[miss],
                                                     ok=pilot.ok[miss]),
                               n_after=n_after[miss], lam_mm=lam_mm[miss], centers=centers[miss], target=target[miss],
                               z_plane=z_plane, z_sensor=z_sensor)
        for k, e in zip(miss, _estimate_for_raywave(view)):
            out[k] = e
            _MEMO[keys[k]] = (e,)
        while len(_MEMO) > MEMO_SIZE:
            _MEMO.popitem(last=False)
    return out


def _estimate_for_raywave(rw) -> list:
    """:func:`estimate_for_raywave` without the memo (every source of ``rw``; each source's estimate reads only its
    own rows)."""
    from .. import doe
    from ..doe import is_flat_profile
    lens, plane = rw.lens, rw.plane
    s = lens.surfaces[plane]
    prof = None
    if s.type == "doe" and not is_flat_profile(s.profile):
        from pathlib import Path
        prof = doe.profile_from_dict(s.profile, base=None if lens.source is None else Path(lens.source).parent)
    note = ""
    if prof is not None and s.profile.get("kind") == "pixel_map":   # no gradient (quantised smooth reliefs keep theirs)
        prof, note = None, "a DOE with steps (pixel map): its phase slope is not counted"
    out = []
    pos, dirs, ok = rw.pilot.pos_p, rw.pilot.dir_s, rw.pilot.ok
    # the pilot's pupil coordinates (its chief ray, then the cell-centre grid on the unit disc): where the rays are
    # these, the rim is the pupil's rim imaged
    from ..pupil import pupil_grid
    from .pilot import PILOT_GRID
    pu, pv, _ = pupil_grid(PILOT_GRID, "circle")
    pupil_uv = np.stack([np.concatenate([[0.0], pu]), np.concatenate([[0.0], pv])], 1)
    if pos.shape[1] != len(pupil_uv):
        pupil_uv = None
    stop_image = {}   # per wavelength (um): the stop's image distance, one paraxial trace each
    alphas = {}       # per wavelength (um): the DOE relief's phase scale
    lens_note = note
    for k in range(rw.nsrc):
        note = lens_note   # each source's own notes (a source's did run on into the next ones')
        w = float(rw.wls[k])
        n = float(rw.n_after[k])
        inv_lam = n / float(rw.lam_mm[k])
        sel = ok[k]
        # the pilot points lie on the wave-plane surface (curved for a last refracting surface): carried along
        # their rays to its vertex plane, where the field is formed
        p3, d3 = pos[k, sel], dirs[k, sel]
        xy = p3[:, :2] + ((rw.z_plane - p3[:, 2]) / d3[:, 2])[:, None] * d3[:, :2]
        z1 = stop_image.get(w)
        if z1 is None:
            z1 = stop_image[w] = stop_to_plane_mm(lens, plane, w)
        R = float(rw.target[k, 2] - rw.z_plane)
        if abs(R) > 1e5 or R == 0:
            R = math.inf
        if len(xy) < 3:
            out.append(ModelError(0.0, math.inf, z1, R, 0.0, 0.0, 0.0, w, note))
            continue
        xc = xy.mean(0)
        # the pilot's 31 x 31 cell-centre grid: its outermost points lie half a cell (1 / 30 of their
        # span) inside the beam's edge
        beam_r = 0.5 * float(np.min(xy.max(0) - xy.min(0))) * 31.0 / 30.0
        f = inv_lam * dirs[k, sel, :2]
        # the beam's rim: the pupil's rim imaged onto the plane by the pilot rays (where every ray arrived and the
        # pupil grid is the pilot's); None: the circle of radius beam_r about xc
        rim_h = _rim_harmonics(pupil_uv[sel], xy, xc, beam_r) if pupil_uv is not None and bool(np.all(sel)) else None
        grad = None
        if prof is not None:
            gx, gy = prof.gradient(xy[:, 0], xy[:, 1], s.design_wavelength_um)
            grad = np.stack([gx, gy], 1) / (2 * math.pi)
            alpha = alphas.get(w)
            if alpha is None:   # the relief's scale, once a wavelength
                alpha = alphas[w] = doe.wavelength_scale(s.material, s.design_wavelength_um, w)
            phi = prof.phase(xy[:, 0], xy[:, 1], s.design_wavelength_um)
            m0 = _main_order(s, prof, xy, w, alpha, phi)
            f = f + m0 * grad
        T = np.array([rw.centers[k, 0], rw.centers[k, 1], rw.z_sensor])
        P = np.concatenate([xy, np.full((len(xy), 1), rw.z_plane)], 1)
        to_T = T[None, :] - P
        f_sph = inv_lam * to_T[:, :2] / np.linalg.norm(to_T, axis=1, keepdims=True)
        rr = np.linalg.norm(xy - xc, axis=1)
        rim = rr >= RIM_SHARE * rr.max()
        # a tilt (a constant frequency offset: the PSF off the patch centre) commutes with the diffraction
        # and changes no intensity: W is taken against the sphere to the patch less its mean tilt.
        # Each rim ray's rho dW/drho, carried to the beam's edge as rho^3 (its pilot point lies 3-10 % inside; a
        # defocus's slope grows as rho^2, a spherical aberration's as rho^4),
        # then the RMS around the rim: the edge's whole ring diffracts, so a slope on one side only (a decentred
        # DOE off axis) counts by its share (the max read 1.65x / 10x the measured error at 0.2 / 0.5 deg, the
        # RMS 1.03x / 4x: tests/rwwarp/test_model_error.py)
        slope = _rim_slope(xy, xc, rr, rim, beam_r, f - f_sph)
        if not math.isfinite(z1):
            out.append(ModelError(0.0, math.inf, z1, R, z1, beam_r, slope, w, note, 0.0, 0.0))
            continue
        d = reduced_distance_mm(z1, R)
        nf = fresnel_number(beam_r, z1, R, w, n)
        pre = _pre_doe_phase_rad(d3, P, rw.target[k], rw.z_plane, float(rw.lam_mm[k]) / n, d)
        if pre > PRE_DOE_PHASE_RAD:
            note = "; ".join(x for x in (note, f"the beam's aberration before the DOE diffracts again over d (phase up to "
                                         f"{pre:.2g} rad), which the edge waves leave out: on the A489 the estimate read "
                                         "0.64-1.37x the measured error at 0.5-3.3 rad (0.51-1.27x below 0.11 rad)") if x)
        main = model_error(nf, slope)
        ph = None
        if math.isfinite(nf) and len(xy) >= 6:
            # the rim's edge waves summed on the beam's own pupil phase (rwwarp.wave.edge_wave): on and off the
            # DOE's axis, no constant fitted; the scalar law above only where the phase is too steep to sample
            tilt = (f - f_sph).mean(0)
            ph = fit_pupil_phase((xy - xc) / beam_r, 2 * math.pi * beam_r * ((f - f_sph) - tilt))
            ew, _ = edge_wave_error(nf, ph, rim=rim_h)
            if ew is None:
                ph = None
                note = "; ".join(x for x in (note, "pupil phase too steep for the edge-wave sum: the scalar law") if x)
            else:
                main = ew
                off = float(np.hypot(*xc)) >= AXIS_SHARE * beam_r
                limit = CHECKED_OFF_AXIS_SLOPE_RAD if off else CHECKED_SLOPE_RAD
                if slope > limit:
                    note = "; ".join(x for x in (note, f"rim slope {slope:.3g} rad: beyond the {limit:g} rad checked "
                                                 f"against a wave truth{' off the axis' if off else ''}") if x)
        other = 0.0
        if grad is not None and math.isfinite(nf):
            dist = rw.z_sensor - rw.z_plane
            cand = _other_orders(s, prof, xy, w, m0, alpha, phi)
            # every candidate order's frequencies at once (M, N, 2): the same values as order by order
            fm = _order_frequencies(f, grad, [m - m0 for m, _ in cand])
            reach = _reaches_patch_orders(xy, fm, inv_lam, dist, T[:2], rr, rim)
            orders = [(m, c) for (m, c), r in zip(cand, reach) if r]
            if orders and ph is not None:
                # every order that lights the patch, coherently with the main one (module docstring, "Other
                # orders"): each order's pupil phase against the same sphere, less the main order's tilt (an order's
                # own tilt is its offset on the sensor)
                parts, left = [(1.0 + 0j, ph)], []
                for (m, c), fmj in zip(orders, fm[reach]):
                    phm = fit_pupil_phase((xy - xc) / beam_r, 2 * math.pi * beam_r * ((fmj - f_sph) - tilt))
                    if max_slope(phm) > MAX_SLOPE_RAD:
                        left.append((m, abs(c)))
                    else:
                        parts.append((c, phm))
                e_all, _ = edge_wave_orders_error(nf, parts, rim=rim_h)
                other = e_all - main
                if left:
                    note = "; ".join(x for x in (note, f"{len(left)} DOE order(s) steeper than {MAX_SLOPE_RAD:g} rad left "
                                                 f"out (amplitude <= {max(a for _, a in left):.2g} of the main order's)")
                                     if x)
            elif orders:
                # the main order on the scalar law (its phase too steep to sample): each order adds at most its
                # edge wave in phase with the core (an upper bound)
                slopes = _rim_slopes(xy, xc, rr, rim, beam_r, fm[reach] - f_sph)
                for (m, c), sl in zip(orders, slopes):
                    other += other_orders_error(nf, sl, abs(c) ** 2)
        out.append(ModelError(main + other, nf, z1, R, d, beam_r, slope, w, note, other, main))
    return out


#: the phase (rad) with which the beam's aberration before the DOE diffracts again over the reduced distance
#: (:func:`_pre_doe_phase_rad`) beyond which the plan's note says the edge waves leave it out: the wave step's own
#: criterion (:data:`rwwarp.wave.wave_step.STEP_PHASE_MAX`, E_step <= 1e-3)
PRE_DOE_PHASE_RAD = 0.1


def _pre_doe_phase_rad(dirs, pts, target, z_plane: float, lam_medium_mm: float, d_mm: float) -> float:
    """``phi = pi |d| max |m - m_T|^2 / lambda_m`` (rad): the Fresnel phase with which the beam's aberration before the
    DOE (the rays' directions ``dirs`` (N, 3) at ``pts`` (N, 3) mm against the directions ``m_T`` to the sphere of its
    focus ``target`` (3,) mm) diffracts over the reduced distance ``d_mm`` (mm; ``lam_medium_mm``: the wavelength in
    the medium, mm). The edge waves take that aberration as applied at the wave plane (:mod:`rwwarp.wave.edge_wave`):
    exact as ``phi -> 0``; the same quantity as the wave step's own phase error
    (:func:`rwwarp.wave.wave_step.step_phase_rad`). 0 without rays or distance."""
    if len(dirs) == 0 or not d_mm or not math.isfinite(d_mm):
        return 0.0
    to_t = np.asarray(target, float)[None, :] - pts
    to_t = to_t / np.linalg.norm(to_t, axis=1, keepdims=True) * (1.0 if target[2] >= z_plane else -1.0)
    a2 = float(np.max(np.sum((dirs[:, :2] - to_t[:, :2]) ** 2, axis=1)))
    return math.pi * abs(d_mm) * a2 / lam_medium_mm


#: the beam's rim from the pilot rays (:func:`rwwarp.wave.edge_wave.fit_rim`; a module name, so a diagnostic can read it)
_rim_harmonics = fit_rim

#: a beam counts as on the DOE's axis (the checked slope's limit, :data:`CHECKED_SLOPE_RAD`) where its centre lies
#: within this share of its radius from the axis
AXIS_SHARE = 0.05
def _order_frequencies(f, grad, dm) -> np.ndarray:
    """``f + dm_j grad`` for each order offset ``dm_j`` (M,): (M, N, 2) cycles/mm (each row as ``f + dm * grad``)."""
    if not len(dm):
        return np.zeros((0,) + f.shape)
    return f[None] + np.asarray(dm, dtype=np.float64)[:, None, None] * grad[None]


def _rim_slopes(xy, xc, rr, rim, beam_r, df) -> np.ndarray:
    """:func:`_rim_slope` of each order's frequency offsets ``df`` (M, N, 2) at once (rad, (M,)); the same sums in
    the same order as one by one."""
    df = df - df.mean(1, keepdims=True)
    sl = np.sum((xy[rim] - xc)[None] * df[:, rim], axis=2) * ((beam_r / np.maximum(rr[rim], 1e-300)) ** 3)[None]
    return 2 * math.pi * np.sqrt(np.mean(sl * sl, axis=1))


def _reaches_patch_orders(xy, fm, inv_lam, dist_mm, center_mm, rr, rim) -> np.ndarray:
    """:func:`_reaches_patch` of each order (frequencies ``fm`` (M, N, 2) cycles/mm) at once: (M,) bool. Orders
    with an evanescent ray are taken one by one."""
    out = np.zeros(len(fm), dtype=bool)
    if not len(fm):
        return out
    s = fm / inv_lam
    c2 = 1.0 - np.sum(s * s, axis=2)
    whole = np.all(c2 > 0, axis=1)
    if np.any(whole):
        sw = s[whole]
        land = xy[None] + dist_mm * sw / np.sqrt(c2[whole])[..., None]
        lc = land.mean(1)
        r_land = np.mean(np.linalg.norm(land[:, rim] - lc[:, None], axis=2), axis=1)
        c = np.asarray(center_mm)
        out[whole] = [bool(np.linalg.norm(c - lc[i]) < r_land[i]) for i in range(len(lc))]
    for j in np.flatnonzero(~whole):
        out[j] = _reaches_patch(xy, fm[j], inv_lam, dist_mm, center_mm, rr, rim)
    return out


def _reaches_patch(xy, f, inv_lam, dist_mm, center_mm, rr, rim) -> bool:
    """Whether an order (rays of transverse frequency ``f``, cycles/mm, from ``xy`` on the plane) lights the
    patch centre ``center_mm`` on the sensor ``dist_mm`` behind: the centre inside its footprint there (the
    rim rays' landing points, their mean distance from the footprint's centre as its radius). Evanescent rays
    land nowhere."""
    s = f / inv_lam                                   # direction sines
    c2 = 1.0 - np.sum(s * s, axis=1)
    ok = c2 > 0
    if not np.any(ok & rim):
        return False
    land = xy[ok] + dist_mm * s[ok] / np.sqrt(c2[ok])[:, None]
    lc = land.mean(0)
    r_land = float(np.mean(np.linalg.norm(land[rim[ok]] - lc, axis=1)))
    return bool(np.linalg.norm(np.asarray(center_mm) - lc) < r_land)


def worst(estimates) -> ModelError | None:
    """The source with the largest estimate (None for an empty list)."""
    return max(estimates, key=lambda e: e.estimate) if estimates else None


class ModelErrorWarning(UserWarning):
    """The ray-wave model's estimated own error exceeds the tolerance asked for (:func:`warn_over_tolerance`)."""


def warn_over_tolerance(plans, tolerance: float, stacklevel: int = 2) -> list:
    """Warn (:class:`ModelErrorWarning`) where a plan (a :class:`rwwarp.wave.plan.Plan` or its dict) computed without
    the wave step has a model-error estimate above ``tolerance`` (relative to the PSF's peak). Returns the
    offending estimates (dicts)."""
    import warnings
    bad = []
    for p in plans:
        if p is None:
            continue
        d = p if isinstance(p, dict) else p.to_dict()
        me = d.get("model_error")
        if me and me["estimate"] > tolerance and not d.get("wave_step_mm"):
            bad.append(me)
    if bad:
        w = max(bad, key=lambda e: e["estimate"])
        warnings.warn(f"the ray-wave model's own error is estimated at {w['estimate']:.2g} of the PSF's peak, above "
                      f"the tolerance {tolerance:.2g} ({len(bad)} PSF(s); Fresnel number {w['fresnel_number']:.4g} of "
                      f"the stop seen from the DOE plane {w['aperture_to_plane_mm']:.4g} mm behind its image, rim slope "
                      f"{w['rim_slope_rad']:.3g} rad): the geometric field at the DOE plane leaves out the rim's "
                      "diffraction on the way there. "
                      + (f"The wave step was refused: its own error, ~{w['step_error']:.2g} (the beam's aberration "
                         f"before the DOE transported twice, phase {w['step_phase_rad']:.3g} rad), is above the "
                         "tolerance too (rwwarp.wave.wave_step); move the DOE nearer the stop"
                         if w.get("step_error", 0.0) > tolerance else
                         "Use method='auto' with this tolerance or method='two-step' (the wave step, "
                         "rwwarp.wave.wave_step), or move the DOE nearer the stop"), ModelErrorWarning,
                      stacklevel=stacklevel)
    return bad
