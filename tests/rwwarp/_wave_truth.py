"""An independent, radially symmetric wave-exact truth for the ray-wave model's own error (issue 27), shared by
``tests/rwwarp/test_model_error.py`` and ``perf/model_error_chart.py``.

Written from the equations, rotationally symmetric (a round stop, an ideal thin lens, a radial DOE), so the 2-D
problem is 1-D: the field's angular spectrum is its Hankel transform ``F(nu) = 2 pi int f(r) J0(2 pi nu r) r
dr``, free space multiplies it by ``exp(2 pi i z sqrt(1 / lambda^2 - nu^2))`` (exact, no Fresnel
approximation), and ``f(r) = 2 pi int F(nu) J0(2 pi nu r) nu dnu`` brings it back. Both integrals are composite
Gauss-Legendre sums over the hard edges (no staircase of samples at the rim).

* truth ("two-step"): ``exp(-i k sqrt(r^2 + f^2))`` on ``r < a`` at the lens, propagated z1 to the DOE plane,
  the DOE phase applied, propagated d2 = f - z1 to the sensor (at the lens focus);
* model ("one-step", the ray-wave model's geometric field): the lens's converging wave truncated
  geometrically at the DOE plane, ``exp(-i k sqrt(r^2 + d2^2)) / s`` on ``r < s a`` (s = d2 / f: rays go straight
  to the focus, the tube's power conserved), the same DOE and propagation to the sensor.

Their difference is the model's error alone, free of rwwarp's sampling. The band of the sums is 2 NA / lambda
(3 NA / lambda moved the measured errors by 3 %, 1.5 NA / lambda by 10 %). Lengths in mm, phases in rad.
"""
import numpy as np
from scipy.special import j0

from rwwarp.lens import Lens, Sensor, Surface

F_MM, LAM_MM = 50.0, 0.55e-3
#: rows of a J0 matrix formed at once (bounds the memory of the large apertures: 2048 x 10^4 x 8 B = 160 MB)
_CHUNK = 2048


def _gl(a, b, per_mm, per_panel=16):
    """Composite Gauss-Legendre nodes and weights on [a, b], ``per_mm`` nodes per unit length."""
    npan = max(1, int(np.ceil((b - a) * per_mm / per_panel)))
    t, w = np.polynomial.legendre.leggauss(per_panel)
    e = np.linspace(a, b, npan + 1)
    h = 0.5 * (e[1:] - e[:-1])
    return ((0.5 * (e[1:] + e[:-1]))[:, None] + h[:, None] * t[None]).ravel(), (h[:, None] * w[None]).ravel()


def _rmatmul(J, x):
    """``J @ x`` for a real matrix ``J`` and a real or complex vector / matrix ``x``, the real and imaginary parts as
    real columns (a complex ``x`` would make numpy copy ``J`` into a complex matrix, twice its memory and time)."""
    x = np.asarray(x)
    if not np.iscomplexobj(x):
        return J @ x
    xr = np.ascontiguousarray(x, dtype=np.complex128).view(np.float64).reshape(x.shape[0], -1)
    y = np.ascontiguousarray(J @ xr).view(np.complex128)
    return y.reshape((J.shape[0],) + x.shape[1:])


def _j0_sum(out_pts, in_pts, weighted):
    """``2 pi sum_j J0(2 pi out_i in_j) weighted_j`` for every output point, in row chunks."""
    res = np.empty((len(out_pts),) + np.shape(weighted)[1:], dtype=np.result_type(weighted, np.float64))
    for i in range(0, len(out_pts), _CHUNK):
        res[i:i + _CHUNK] = _rmatmul(j0(2 * np.pi * np.outer(out_pts[i:i + _CHUNK], in_pts)), weighted)
    return 2 * np.pi * res


def _hankel(f, r, wr, nu):
    return _j0_sum(nu, r, f * r * wr)


_LENS_SPECTRA = {}


def _lens_spectrum(a_mm, q, nu, dens):
    """The converging wave's angular spectrum on the stop (independent of the DOE's place: kept per (a, q, nodes))."""
    key = (float(a_mm), float(q), len(nu), float(nu[-1]))
    if key not in _LENS_SPECTRA:
        k = 2 * np.pi / LAM_MM
        r0, w0 = _gl(0.0, a_mm, dens)
        _LENS_SPECTRA[key] = _hankel(np.exp(-1j * k * np.hypot(r0, F_MM)), r0, w0, nu)
    return _LENS_SPECTRA[key]


def radial_truth(a_mm, d2_mm, coeffs, rho_mm, q=3.0, alpha=None, sensor_mm=None, band=None, taper=0.0):
    """(truth, model) sensor irradiance at the radii ``rho_mm`` (power per mm^2 over the power entering the
    stop of radius ``a_mm``): thin lens F_MM, DOE ``sum_i c_i (r / r_b)^(2 i)`` (rad, ``r_b = s a`` the beam's
    radius on the DOE plane) ``d2_mm`` before the lens focus, the sensor ``sensor_mm`` behind the DOE (None:
    at the lens focus). ``alpha`` (None: the phase as it is): a wrapped relief used at ``alpha`` times its
    design wavelength's phase, the transmission ``exp(1j alpha (phi0 mod 2 pi))``, every diffraction order.
    ``band`` (cycles/mm, None: ``2 NA / lambda``): the angular spectrum's band, for a DOE whose slope takes the light
    beyond it (:func:`steep_band`); ``taper`` (0: a hard cut): the spectrum rolled off as ``cos^2`` over this share of
    the band at its top (the cut's end-point ringing on a steep DOE's weak, wide PSF is else of the order of its
    error)."""
    k = 2 * np.pi / LAM_MM
    z1, s = F_MM - d2_mm, d2_mm / F_MM
    na = a_mm / np.hypot(a_mm, F_MM)
    V = 2.0 * na / LAM_MM if band is None else float(band)   # the angular spectrum's band (cycles/mm)
    rb, d = s * a_mm, z1 * d2_mm / F_MM
    dens = q * (na / LAM_MM + V)                   # nodes per mm on the planes: the phase's and J0's oscillations
    nu, wnu = _gl(0.0, V, q * (a_mm + F_MM * V * LAM_MM))   # spectrum nodes: the field's extent after propagation
    win = np.ones_like(nu)
    if taper > 0:
        x = np.clip((nu - V * (1.0 - taper)) / (V * taper), 0.0, 1.0)
        win = np.cos(0.5 * np.pi * x) ** 2
    H = lambda z: win * np.exp(2j * np.pi * z * np.sqrt(1 / LAM_MM ** 2 - nu ** 2))
    W0 = lambda r: sum(c * (r / rb) ** (2 * (i + 1)) for i, c in enumerate(coeffs))
    W = W0 if alpha is None else (lambda r: alpha * np.mod(W0(r), 2 * np.pi))
    z2 = d2_mm if sensor_mm is None else float(sensor_mm)
    F0 = _lens_spectrum(a_mm, q, nu, dens)
    r1, w1 = _gl(0.0, rb + 0.15 * rb + 30 * np.sqrt(LAM_MM * d), dens)   # the beam and its edge's ringing
    # truth: the field on the DOE plane f1(r) = 2 pi sum_nu J0(2 pi r nu) F0 H(z1) nu w_nu, the DOE applied, and its
    # spectrum F1(nu) = 2 pi sum_r J0(2 pi nu r) f1 e^{iW} r w_r: both sums read the same J0 matrix (transposed), so
    # it is formed once per chunk of rows r (each row's f1 needs only its own row); the same sums as two passes
    # in another order (rounding: the truth and the model moved by <= 4e-15 of their peaks, measured)
    g1 = F0 * H(z1) * nu * wnu
    F1 = np.zeros(len(nu), dtype=complex)
    for i in range(0, len(r1), _CHUNK):
        r, w = r1[i:i + _CHUNK], w1[i:i + _CHUNK]
        J = j0(2 * np.pi * np.outer(r, nu))
        F1 += _rmatmul(J.T, 2 * np.pi * _rmatmul(J, g1) * np.exp(1j * W(r)) * r * w)
    F1 *= 2 * np.pi
    rg, wg = _gl(0.0, rb, dens)
    Fm = _hankel(np.exp(-1j * k * np.hypot(rg, d2_mm)) / s * np.exp(1j * W(rg)), rg, wg, nu)
    # truth and model to the sensor through one J0 matrix (two columns)
    both = _j0_sum(np.asarray(rho_mm, float), nu, np.stack([F1, Fm], 1) * (H(z2) * nu * wnu)[:, None])
    I = np.abs(both) ** 2 / (np.pi * a_mm ** 2)
    return I[:, 0], I[:, 1]


def measured_error(a_mm, d2_mm, coeffs, rho_mm=None, band=None, taper=0.0, q=3.0):
    """max |model - truth| / max truth of :func:`radial_truth` on the radii ``rho_mm`` (None: 0..40 um, 161)."""
    rho = np.linspace(0.0, 0.04, 161) if rho_mm is None else np.asarray(rho_mm, float)
    truth, model = radial_truth(a_mm, d2_mm, coeffs, rho, q=q, band=band, taper=taper)
    return float(np.max(np.abs(model - truth)) / truth.max())


def steep_band(a_mm, d2_mm, coeffs, margin=1.0):
    """The band (cycles/mm) for a steep DOE: ``2 NA / lambda`` plus ``margin`` times the DOE's largest frequency
    on the beam, ``max |dW/dr| / (2 pi)`` (the light it deflects beyond the lens's cone)."""
    rb = a_mm * d2_mm / F_MM
    na = a_mm / np.hypot(a_mm, F_MM)
    r = np.linspace(0.0, 1.0, 201)
    slope = np.abs(sum(2 * (i + 1) * c * r ** (2 * i + 1) for i, c in enumerate(coeffs)))
    return 2.0 * na / LAM_MM + margin * float(slope.max()) / (2 * np.pi * rb)


def steep_radii(a_mm, d2_mm, coeffs, step_mm=0.5e-3, margin=1.3):
    """Sensor radii (mm) covering the geometric spot of a steep DOE (its rays' largest landing radius, ``lambda d2
    max |dW/dr| / (2 pi)``, ``margin`` times over, plus 20 um) on the step ``step_mm``."""
    rb = a_mm * d2_mm / F_MM
    r = np.linspace(0.0, 1.0, 201)
    slope = np.abs(sum(2 * (i + 1) * c * r ** (2 * i + 1) for i, c in enumerate(coeffs)))
    top = margin * LAM_MM * d2_mm * float(slope.max()) / (2 * np.pi * rb) + 0.02
    return np.arange(0.0, top + step_mm, step_mm)


def analytic_inputs(a_mm, d2_mm, coeffs):
    """N_F = a^2 (f - z1) / (lambda f z1) and the rim slope S = rho dW/drho at rho = 1 (rad)."""
    z1 = F_MM - d2_mm
    nf = a_mm ** 2 * (F_MM - z1) / (LAM_MM * F_MM * z1)
    return nf, sum(2 * (i + 1) * c for i, c in enumerate(coeffs))


def thin_lens_doe(d2_mm, a_mm=2.5, coeffs=(0.0, 3.0), pixel=0.5e-3, doe_share=1.5):
    """The scene of the truth in rwwarp: round stop, ideal thin lens F_MM, radial DOE (a dispersion-free
    substrate) d2_mm before the sensor at the lens focus; the DOE's semi-diameter ``doe_share`` times the
    on-axis beam's radius."""
    rb = a_mm * d2_mm / F_MM
    surfs = [Surface(type="aperture", semi_diameter=a_mm, shape="circle", stop=True),
             Surface(type="thin_lens", focal_length=F_MM, semi_diameter=1.2 * a_mm, thickness=F_MM - d2_mm),
             Surface(type="doe", semi_diameter=doe_share * rb, thickness=d2_mm, material="1.5/1e9",
                     profile={"kind": "even_poly", "coefficients": list(coeffs), "norm_radius": rb})]
    return Lens(surfs, Sensor(pixel, (4000, 4000)), wavelengths_um=[0.55])


def pixel_truth(I_r, rho, x, y, pixel, nodes=4):
    """Radial irradiance ``I_r`` (at the radii ``rho``, mm) integrated over square pixels (side ``pixel`` mm)
    centred at (x, y) (Gauss-Legendre, interpolated): the power per pixel."""
    t, w = np.polynomial.legendre.leggauss(nodes)
    off = 0.5 * pixel * t
    X = x[None, :, None, None] + off[None, None, None, :]
    Y = y[:, None, None, None] + off[None, None, :, None]
    v = np.interp(np.hypot(X, Y), rho, I_r)
    return (v * (w[None, None, :, None] * w[None, None, None, :])).sum((2, 3)) * (0.5 * pixel) ** 2
