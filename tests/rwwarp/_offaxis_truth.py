"""An independent, off-axis two-step wave truth for the wave step (issue 27) at the issue's NA (0.1): thin lens ->
DOE -> sensor for a beam tilted by the field angle, written from the equations (numpy FFTs, not rwwarp's code).
Shared by ``tests/rwwarp/test_wave_step_off_axis.py`` and ``perf/wave_step_off_axis.py``.

Equations (lengths mm, frequencies cycles/mm, phases rad; ``w(f) = sqrt(1 / lambda^2 - |f|^2)``):

* the stop (radius ``a``, on the axis, at the ideal thin lens F_MM): the lens's sphere converging to
  ``T = (0, F tan(field), F)`` on the stop's disc, ``disc(x) exp(-i k |T - x|)``, amplitude 1 (the power entering
  the stop ``pi a^2``). The disc is band-limited (its exact spectrum ``a J1(2 pi a rho) / rho`` rolled off as
  ``cos^2`` over the top third of ``band_disc``) so that the sampled field does not alias: the PSF patch (radius
  ``rho_p``) reads only the pupil's content within ``rho_p / (lambda F)`` ~ 1.5 cycles/mm of each ray, far inside
  the band (its change with the band is measured, perf/wave_step_off_axis.py);
* the exact angular spectrum over ``z1 = F - d2`` to the DOE plane, on the chief ray's carrier ``f_c = sin(theta) /
  lambda`` (the baseband field, its transfer ``exp(2 pi i z1 (w(f_c + nu) - w_c + nu . f_c / w_c))``: the grid
  follows the chief ray, ``z1 tan(theta)`` off the axis on the DOE plane);
* the DOE's phase ``sum_i c_i (r / R)^(2 i)`` (centred on the axis, ``R`` its norm radius), the field cut at
  ``1.15 s a + 30 sqrt(lambda d)`` from the beam's centre (as tests/rwwarp/_wave_truth.py; ``cos^2`` over its
  last 15 %), the new carrier the DOE's local frequency at the chief point added;
* the exact angular spectrum over ``d2`` to the sensor, read at the pixels' 4 x 4 Gauss nodes by a matrix DFT
  (the periodic crop's trigonometric interpolation). Returns the power per pixel over the power entering the
  stop, as ``rw.psf`` (and tests/rwwarp/_wave_truth.py's ``pixel_truth``).
"""
import numpy as np
import scipy.fft
from scipy.special import j1

F_MM, LAM_MM = 50.0, 0.55e-3


def thin_lens_doe_off_axis(a_mm, d2_mm, coeffs, semi_mm, pixel=0.5e-3):
    """The truth's scene in rwwarp: stop (radius ``a_mm``) at the ideal thin lens F_MM, the DOE ``sum c_i (r /
    r_b)^(2 i)`` (``r_b = a d2 / F``, centred on the axis, clear radius ``semi_mm``; a dispersion-free substrate)
    ``d2_mm`` before the sensor at the lens focus."""
    from rwwarp.lens import Lens, Sensor, Surface
    rb = a_mm * d2_mm / F_MM
    surfs = [Surface(type="aperture", semi_diameter=a_mm, shape="circle", stop=True),
             Surface(type="thin_lens", focal_length=F_MM, semi_diameter=1.2 * a_mm, thickness=F_MM - d2_mm),
             Surface(type="doe", semi_diameter=semi_mm, thickness=d2_mm, material="1.5/1e9",
                     profile={"kind": "even_poly", "coefficients": list(coeffs), "norm_radius": rb})]
    return Lens(surfs, Sensor(pixel, (40000, 40000)), wavelengths_um=[0.55])


def _w(fx, fy):
    """The axial frequency sqrt(1 / lambda^2 - |f|^2) (cycles/mm; 0 where evanescent) of the transverse (fx, fy)."""
    return np.sqrt(np.maximum(1.0 / LAM_MM ** 2 - fx ** 2 - fy ** 2, 0.0))


def _disc_band_limited(n, h, a_mm, band):
    """The disc of radius ``a_mm`` band-limited to ``band`` cycles/mm (cos^2 over its top third), on the
    centred n x n grid of pitch h (sample n // 2 at 0)."""
    nu = np.fft.fftfreq(n, h)
    rho = np.hypot(nu[None, :], nu[:, None])
    D = np.where(rho > 0, a_mm * j1(2 * np.pi * a_mm * rho) / np.where(rho > 0, rho, 1.0), np.pi * a_mm ** 2)
    x = np.clip((rho - band * 2.0 / 3.0) / (band / 3.0), 0.0, 1.0)
    D *= np.cos(0.5 * np.pi * x) ** 2
    del rho, x
    out = scipy.fft.ifft2(D, workers=-1).real / (h * h)
    return np.fft.fftshift(out)


def offaxis_truth(a_mm, d2_mm, coeffs, norm_radius_mm, field_deg, px, py, pixel, h=2e-3, band_disc=60.0,
                  margin_mm=0.4, nodes=4, cut_share=1.0, ray_amplitude=False, step=None):
    """Power per pixel (over the power entering the stop) of the two-step truth (module docstring) at the pixel
    centres ``px`` (M,) x ``py`` (M,) (mm, absolute sensor coordinates; side ``pixel`` mm): stop radius ``a_mm``,
    DOE ``sum c_i (r / norm_radius_mm)^(2 i)`` ``d2_mm`` before the sensor at the lens focus, the beam at
    ``field_deg`` (y). ``h`` the grids' pitch (mm), ``band_disc`` the stop disc's band (cycles/mm), ``margin_mm``
    the stop grid's margin beyond the disc, ``cut_share`` scales the DOE plane's cut radius. ``step`` (None: the
    truth) ``(D_x, D_y)`` mm: the wave step's principle instead of the exact field on the DOE plane, the geometric
    field (``1 / s`` on the stop's shadow, radius ``s a`` about the chief point, band-limited to 70 cycles/mm) with the
    sphere to T removed, propagated by the Fresnel transfer ``exp(-i pi lambda (D_x nu_x^2 + D_y nu_y^2))``, the
    sphere put back (isotropic: ``D_x = D_y``); or a callable ``step(g, x, nu)`` that steps that geometric field ``g``
    (n1 x n1, sample n1 // 2 on the chief point; ``x`` the grid's coordinates about it, mm, ``nu`` its FFT frequencies,
    cycles/mm) itself (perf/wave_step_off_axis.py's rim-resolved principle)."""
    k = 2 * np.pi / LAM_MM
    z1, rb = F_MM - d2_mm, a_mm * d2_mm / F_MM
    d = z1 * d2_mm / F_MM
    yT = F_MM * np.tan(np.radians(field_deg))
    fc = np.sin(np.arctan2(yT, F_MM)) / LAM_MM           # the chief ray's carrier (y)
    wc = _w(0.0, fc)
    n1 = scipy.fft.next_fast_len(int(np.ceil((2 * a_mm + 2 * margin_mm) / h)))
    x = (np.arange(n1) - n1 // 2) * h
    u = _disc_band_limited(n1, h, a_mm, band_disc).astype(complex)
    L = np.sqrt(x[None, :] ** 2 + (x[:, None] - yT) ** 2 + F_MM ** 2)
    u *= np.exp(1j * (-k * L - 2 * np.pi * fc * x[:, None]))
    if ray_amplitude:     # the ray tube's power kept through the ideal lens: |u|^2 m_z = const (m_z = F / L)
        u *= np.sqrt(L / F_MM)
    del L
    nu = np.fft.fftfreq(n1, h)
    H = np.exp(2j * np.pi * z1 * (_w(nu[None, :], fc + nu[:, None]) - wc + nu[:, None] * fc / wc))
    u = scipy.fft.ifft2(scipy.fft.fft2(u, workers=-1) * H, workers=-1)
    del H
    # the DOE plane, the grid following the chief ray (its point c1 = (0, z1 tan theta) at sample n1 // 2)
    c1 = z1 * yT / F_MM
    if step is not None:
        g = _disc_band_limited(n1, h, rb, 70.0) * (F_MM / d2_mm)
        if callable(step):
            u = step(g, x, nu)
        else:
            P = np.exp(-1j * np.pi * LAM_MM * (step[0] * nu[None, :] ** 2 + step[1] * nu[:, None] ** 2))
            u = scipy.fft.ifft2(scipy.fft.fft2(g, workers=-1) * P, workers=-1)
            del P
        del g
        u *= np.exp(1j * (-k * np.sqrt(x[None, :] ** 2 + (x[:, None] + c1 - yT) ** 2 + d2_mm ** 2)
                          - 2 * np.pi * fc * x[:, None]))
    rcut = cut_share * (1.15 * rb + 30 * np.sqrt(LAM_MM * d))
    half = int(np.ceil((rcut + 0.05) / h))
    sl = slice(n1 // 2 - half, n1 // 2 + half)
    v = u[sl, sl]
    del u
    n2 = v.shape[0]
    xs = (np.arange(n2) - half) * h
    R2 = np.hypot(xs[None, :], xs[:, None])
    t = np.clip((R2 - 0.85 * rcut) / (0.15 * rcut), 0.0, 1.0)
    v = v * np.cos(0.5 * np.pi * t) ** 2
    r_abs = np.hypot(xs[None, :], xs[:, None] + c1)
    W = lambda r: sum(c * (r / norm_radius_mm) ** (2 * (i + 1)) for i, c in enumerate(coeffs))
    dW = lambda r: sum(2 * (i + 1) * c * r ** (2 * i + 1) / norm_radius_mm ** (2 * (i + 1)) for i, c in enumerate(coeffs))
    g = dW(abs(c1)) * np.sign(c1) / (2 * np.pi) if c1 != 0 else 0.0    # the DOE's local frequency at c1 (y)
    f2 = fc + g
    w2 = _w(0.0, f2)
    v = v * np.exp(1j * (W(r_abs) - W(abs(c1)) - 2 * np.pi * g * xs[:, None]))
    S = scipy.fft.fft2(v, workers=-1)
    del v, R2, t, r_abs
    nu2 = np.fft.fftfreq(n2, h)
    S *= np.exp(2j * np.pi * d2_mm * (_w(nu2[None, :], f2 + nu2[:, None]) - w2 + nu2[:, None] * f2 / w2)) / n2 ** 2
    # the sensor: the grid's centre at c1 + d2 tan(theta_2)
    ys0 = c1 + d2_mm * f2 / w2
    tg, wg = np.polynomial.legendre.leggauss(nodes)
    xn = (np.asarray(px, float)[:, None] + 0.5 * pixel * tg[None]).ravel()
    yn = (np.asarray(py, float)[:, None] + 0.5 * pixel * tg[None]).ravel() - ys0
    ey = np.exp(2j * np.pi * np.outer(yn - xs[0], nu2))
    ex = np.exp(2j * np.pi * np.outer(xn - xs[0], nu2)).T
    U = ey @ S @ ex
    m, mx = len(py), len(px)
    P = np.einsum("injm,n,m->ij", (np.abs(U) ** 2).reshape(m, nodes, mx, nodes), wg, wg) * (0.5 * pixel) ** 2
    return P / (np.pi * a_mm ** 2)
