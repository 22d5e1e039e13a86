"""A wave-exact truth through the Cooke-type hybrid of the paper's Cooke experiment for the ray-wave model's own error
(issue 27), shared by ``tests/rwwarp/test_model_error_cooke.py`` and ``perf/model_error_cooke.py``. The structure of
``_a489_truth.py`` (beside this file), whose lens-agnostic helpers it imports (the periodic :class:`Grid` with its
exact angular-spectrum transfer functions, :func:`wpm_zone`, :func:`catalogue_index`, :func:`measured_error`, the
ray-surface intersection and Snell's law); no rwwarp code. The lens is read as numbers from
``torch_bridge/configs/lenses/cooke_hybrid.json`` (the experiment's lens: six spherical surfaces, N-SK16 for every
element, the glass's Sellmeier coefficients from ``rwwarp/data/glasses.json``; the 8 x 8 mm DOE 23.17 mm behind the
last surface, 20 mm before the sensor).

Geometry (z from the first vertex, mm; the source at infinity, a plane wave of field angle ``theta`` tilted in x, |U| =
1 on the plane ``z = -1``): the lens's aperture stop is surface 3 (the middle element's rear, R = 22.4 mm, 5.24 mm
of air behind it). The experiment's lens file sets the beam by its entrance pupil (a floating stop); here the stop is
a physical iris: a hard disc of radius ``a`` on the plane ``z_I = z_3 + sag_3(a)`` (the plane where surface 3 meets
the iris's rim: inside the disc that plane lies in air), ``a`` the radius there of the on-axis real marginal ray of the
entrance pupil's radius ``epd / 2`` (so on the axis the iris cuts the entrance pupil's rays exactly).

* truth ("two-step"): the geometric field on the iris plane (elements 1 and 2 carry no aperture: the beam that
  reaches the iris is smooth, edge-free) cut by the disc, then propagated as a wave all the way to the DOE plane: the
  exact angular spectrum in air to surface 4's sag zone, the WPM through it (air -> N-SK16), the angular spectrum in
  the glass, the WPM through surface 5's sag zone (N-SK16 -> air), the angular spectrum in air to the DOE plane;
* model ("one-step", the ray-wave model's geometric field): rays traced from the entrance plane to the DOE plane
  (Snell, exact intersections), the field ``sqrt(dA_0 / dA) exp(i k OPL)`` on the DOE grid (each sample's ray found by
  Newton's method), cut where its ray crossed the iris plane outside the disc (the rim's samples weighted by the share
  of their cell inside, the cell mapped back to the iris);
* both: the same DOE (``exp(+i phi)``, ``phi = sum_i c_i (r / R)^(2i)`` about the axis, at its design wavelength),
  the same exact angular spectrum to the sensor (20 mm), evaluated on a patch by a matrix DFT.

``pupil="entrance"`` (:class:`Cooke`): the rays cut as rwwarp cuts the lens file's floating stop instead, by the
entrance pupil's disc (the edge still diffracts from the iris's plane).

Convergence (perf/model_error_cooke.py, stage guard; docs/accuracy.md): the guarded truth (``band=120`` cycles/mm about the chief ray on every free-space step, a 1 mm margin) reads on the axis 3.39e-3
of the peak at pitches of 2 and 1.5 um and slices of 1 and 0.5 um (the truth moved by 1e-6 / 9e-6 of its peak); at 5
deg 12.4e-3 / 7.37e-3 / 4.90e-3 at slices of 1 / 0.5 / 0.25 um: first order in the slice (a Richardson extrapolation
gives 2.4e-3). Its source: the WPM's cut-sample phase applied after the slice's step, so the refraction's frequency
step comes at the slice's end (first order in the slice times the beam's tilt times the surface's slope; on a flat
tilted interface against Snell, ``test_wpm_tilted_interface.py``); ``sub_slice="split"`` (:func:`wpm_zone_local`'s
``split``) reads 3.16e-3 / 2.70e-3 at 1 / 0.5 um (the truth moved 4.7e-4 of its peak, 11x less), 3.37e-3 on the
axis at 1 um; ``sub_slice="snell"`` (the default: the post-step phase from Snell's refracted frequency) 2.58e-3 /
2.54e-3 / 2.45e-3 at 1 / 0.5 / 0.25 um (the truth moved 4.3e-5, then 1.6e-4), 3.35e-3 on the axis at
1 um. Without the guard (``band=None``, the earlier
truth) the hard edge's wide-angle light wraps round the periodic window and the error grows as the pitch falls
(2.1 / 2.5 / 3.1e-3 at 2 / 1.5 / 1 um).

Fields are ``U ~ exp(+i k OPL)``; the carrier ``exp(2 pi i sin(theta) x / lambda)`` is taken out of every grid; each
plane's window follows the chief ray (a roll of the periodic grid). Both fields keep ``int |U|^2 dA``. Lengths in mm,
the wavelength in mm (``LAM_MM``), phases in rad.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from _a489_truth import A489, LAM_MM, Grid, _fast, _fft2, _ifft2, catalogue_index, measured_error, wpm_zone

__all__ = ["Cooke", "truth_and_model", "band_window", "window_guard", "measured_error", "LAM_MM", "LENS_FILE"]

ROOT = Path(__file__).resolve().parents[2]
LENS_FILE = ROOT / "torch_bridge" / "configs" / "lenses" / "cooke_hybrid.json"
_hit, _refract = A489._hit, A489._refract


class Cooke:
    """The Cooke hybrid's surfaces as numbers (``LENS_FILE``), entrance pupil diameter ``epd_mm`` (mm; the file's
    11.75 mm is F/4), the DOE's design phase ``coeffs`` (rad, even polynomial on ``norm_mm``), the wavelength
    ``lam_mm`` (mm). ``coeffs=None``: the quadratic term that puts the paraxial focus on the sensor
    (:meth:`focusing_coefficient`), rounded to 1 rad. ``pupil``: "iris" (the physical stop: the rays through the
    iris's disc) or "entrance" (the lens file's floating stop, as rwwarp traces it: the rays through the entrance
    pupil's disc of radius ``epd / 2`` about the chief ray aimed at the stop surface's vertex; the edge still
    diffracts from the iris's plane, where the truth starts)."""

    def __init__(self, epd_mm=3.0, coeffs=None, norm_mm=4.0, lam_mm=LAM_MM, pupil="iris"):
        if pupil not in ("iris", "entrance"):
            raise ValueError(f"Cooke: pupil={pupil!r}, one of 'iris', 'entrance'")
        self.pupil = pupil
        spec = json.loads(LENS_FILE.read_text())
        if not np.isfinite(lam_mm) or lam_mm <= 0:
            raise ValueError(f"Cooke: wavelength lam_mm={lam_mm!r} (mm) must be a positive number")
        if not np.isfinite(epd_mm) or epd_mm <= 0:
            raise ValueError(f"Cooke: entrance pupil diameter epd_mm={epd_mm!r} (mm) must be a positive number")
        if spec.get("object_distance", "inf") != "inf":
            raise ValueError("Cooke: the lens file's object must be at infinity")
        self.lam, self.k, self.epd = float(lam_mm), 2 * np.pi / lam_mm, float(epd_mm)
        surfs = spec["surfaces"]
        self.zv, self.c, self.n_after = [], [], []
        z = 0.0
        for s in surfs[:-1]:
            if s["type"] != "standard" or s.get("conic", 0.0) or s.get("aspheric"):
                raise ValueError("Cooke: only spherical standard surfaces are written here")
            self.zv.append(z)
            self.c.append(1.0 / float(s["radius"]))
            self.n_after.append(1.0 if s["material"] == "air" else catalogue_index(s["material"], lam_mm))
            z += float(s["thickness"])
        self.n_before = [1.0] + self.n_after[:-1]
        self.stop = next(i for i, s in enumerate(surfs) if s.get("stop"))
        doe = surfs[-1]
        self.zD, self.zS = z, z + float(doe["thickness"])
        self.doe_half = float(doe["semi_diameter"])
        if abs(float(doe["design_wavelength_um"]) * 1e-3 - self.lam) > 1e-9:
            raise ValueError("Cooke: only the DOE's design wavelength is written here (not its relief's other "
                             "orders)")
        self.norm = float(norm_mm)
        # the iris: the on-axis marginal ray of the entrance pupil's rim (found with the iris at the vertex, then on
        # the plane where surface 3 meets the rim)
        self.a, self.zI = 1.0, self.zv[self.stop]
        for _ in range(3):
            x, _, _ = self._trace(np.array([0.5 * self.epd]), np.zeros(1), 0.0, self.zI)
            self.a = float(abs(x[0]))
            self.zI = self.zv[self.stop] + float(self.sag(self.stop, self.a ** 2)) + 1e-6
        self.coeffs = (float(np.round(self.focusing_coefficient())),) if coeffs is None else \
            tuple(float(c) for c in coeffs)

    # -- surfaces ---------------------------------------------------------------------------------------------------
    def sag(self, i, r2):
        c = self.c[i]
        return c * r2 / (1 + np.sqrt(1 - c * c * r2))

    def dsag_over_r(self, i, r2):
        """(d sag / dr) / r of surface ``i``."""
        c = self.c[i]
        return c / np.sqrt(1 - c * c * r2)

    def doe_phase(self, x, y):
        """The DOE's design phase (rad) at (x, y) (mm)."""
        rho2 = (x * x + y * y) / self.norm ** 2
        return sum(c * rho2 ** (i + 1) for i, c in enumerate(self.coeffs))

    def focusing_coefficient(self):
        """The DOE's quadratic coefficient (rad on ``norm_mm``) that moves the lens's paraxial focus (traced here, a
        0.01 mm ray on the axis) onto the sensor: ``-pi R^2 / (lambda f_D)``, ``1 / f_D = 1 / (zS - zD) - 1 / L``."""
        x, _, _, d = self._trace(np.array([1e-2]), np.zeros(1), 0.0, self.zD, direction=True)
        L = -x[0] * d[2, 0] / d[0, 0]
        return -np.pi * self.norm ** 2 / self.lam * (1.0 / (self.zS - self.zD) - 1.0 / L)

    # -- rays ---------------------------------------------------------------------------------------------------------
    def _trace(self, u, v, theta_rad, z_plane, direction=False):
        """Rays of the plane wave entering at (u, v) on the plane z = -1 to the plane ``z_plane`` (every surface
        whose vertex lies before it traced): (x, y, phase), phase ``k`` times the path from the entrance plane plus
        ``k sin(theta) u`` (the entering wave's phase there); ``direction``: the rays' unit directions too."""
        u, v = np.asarray(u, float), np.asarray(v, float)
        p = np.stack([u, v, np.full_like(u, -1.0)])
        d = np.stack([np.full_like(u, np.sin(theta_rad)), np.zeros_like(u), np.full_like(u, np.cos(theta_rad))])
        opl, n = np.sin(theta_rad) * u, 1.0
        for i, zv in enumerate(self.zv):
            if zv >= z_plane:
                break
            t, p, N = _hit(p, d, zv, lambda r2, i=i: self.sag(i, r2), lambda r2, i=i: self.dsag_over_r(i, r2))
            opl = opl + n * t
            d = _refract(d, N, self.n_before[i] / self.n_after[i])
            n = self.n_after[i]
        t = (z_plane - p[2]) / d[2]
        opl = opl + n * t
        out = (p[0] + t * d[0], p[1] + t * d[1], self.k * opl)
        return out + (d,) if direction else out

    def medium(self, z):
        """The index of the medium at ``z`` on the axis."""
        n = 1.0
        for i, zv in enumerate(self.zv):
            if zv < z:
                n = self.n_after[i]
        return n

    def chief(self, theta_rad):
        """The entrance coordinate u (mm) of the chief ray (through the iris's centre, or for ``pupil="entrance"``
        the stop surface's vertex; Newton)."""
        u, e = 0.0, 1e-5
        zc = self.zI if self.pupil == "iris" else self.zv[self.stop]
        for _ in range(30):
            x, _, _ = self._trace(np.array([u, u + e]), np.zeros(2), theta_rad, zc)
            u -= x[0] / ((x[1] - x[0]) / e)
            if abs(x[0]) < 1e-12:
                break
        return u

    def chief_x(self, theta_rad, z_plane):
        x, _, _ = self._trace(np.array([self.chief(theta_rad)]), np.zeros(1), theta_rad, z_plane)
        return float(x[0])

    def geometric_field(self, X, Y, theta_rad, z_plane, h, soft=0.0, tol=1e-11):
        """The geometric field at the plane ``z_plane`` (air or glass, outside every sag zone) on the samples (X, Y)
        (mm), carrier removed: each sample's ray found by Newton's method from the entrance plane, amplitude
        ``sqrt(|d(u, v) / d(x, y)|)``, phase ``k`` times the path ``- 2 pi nu0 x``, cut by the iris (rim samples: the
        share of their cell, of side ``h`` (mm), inside, the cell mapped back to the iris plane; ``soft`` > 0: a cos^2
        roll-off of the amplitude over the iris's outer ``soft`` share of its radius instead of the hard rim)."""
        shape = X.shape
        X, Y = X.ravel(), Y.ravel()
        e = 1e-5
        uc = self.chief(theta_rad)
        x0, y0, _ = self._trace(np.array([uc, uc + e, uc]), np.array([0.0, 0.0, e]), theta_rad, z_plane)
        mx, my = (x0[1] - x0[0]) / e, (y0[2] - y0[0]) / e
        xi0, yi0, _ = self._trace(np.array([uc, uc + e, uc]), np.array([0.0, 0.0, e]), theta_rad, self.zI)
        ax_, ay_ = (xi0[1] - xi0[0]) / e, (yi0[2] - yi0[0]) / e      # entrance -> iris scale
        keep = np.hypot((X - x0[0]) / mx * ax_, Y / my * ay_) < 1.25 * self.a
        out = np.zeros(X.shape, complex)
        xt, yt = X[keep], Y[keep]
        u, v = uc + (xt - x0[0]) / mx, yt / my
        tr = lambda uu, vv, z=z_plane: self._trace(uu, vv, theta_rad, z)      # noqa: E731
        for _ in range(40):
            x, y, _ = tr(u, v)
            a1, a2, _ = tr(u + e, v)
            b1, b2, _ = tr(u, v + e)
            j11, j21, j12, j22 = (a1 - x) / e, (a2 - y) / e, (b1 - x) / e, (b2 - y) / e
            rx, ry = x - xt, y - yt
            det = j11 * j22 - j12 * j21
            u = u - (j22 * rx - j12 * ry) / det
            v = v - (-j21 * rx + j11 * ry) / det
            if max(np.abs(rx).max(), np.abs(ry).max()) < tol:
                break
        x, y, ph = tr(u, v)
        a1, a2, _ = tr(u + e, v)
        b1, b2, _ = tr(u, v + e)
        det = np.abs((a1 - x) * (b2 - y) - (b1 - x) * (a2 - y)) / e ** 2
        xs, ys, _ = tr(u, v, self.zI)
        a1, a2, _ = tr(u + e, v, self.zI)
        b1, b2, _ = tr(u, v + e, self.zI)
        det_i = np.abs((a1 - xs) * (b2 - ys) - (b1 - xs) * (a2 - ys)) / e ** 2
        if self.pupil == "iris":
            rs, a, hs = np.hypot(xs, ys), self.a, h * np.sqrt(det_i / det)   # the cell's side mapped to the iris
        else:
            rs, a, hs = np.hypot(u - uc, v), 0.5 * self.epd, h / np.sqrt(det)  # ... to the entrance plane
        if soft > 0:
            w = np.clip((rs - (1 - soft) * a) / (soft * a), 0.0, 1.0)
            ap = np.cos(0.5 * np.pi * w) ** 2
        else:
            ap = np.clip(0.5 + (a - rs) / hs, 0.0, 1.0)
        nu0 = np.sin(theta_rad) / self.lam
        out[keep] = ap / np.sqrt(det) * np.exp(1j * (ph - 2 * np.pi * nu0 * xt))
        return out.reshape(shape)


def wpm_zone_local(grid: Grid, V, z_from, z_to, surf_z, n_before, n_after, lam, dz, band=None, nearest=False,
                   split=False, snell=False):
    """The WPM through the slab ``z_from .. z_to`` (mm) cut by the surface ``z = surf_z`` (mm, array on the grid), as
    :func:`_a489_truth.wpm_zone` (each slice both media's exact transfer; a sample whose slice the surface cuts takes
    the medium after's and the phase of its length ``g`` in the medium before) but with that phase
    ``g (k_z,before(nu) - k_z,after(nu))`` at the sample's own transverse frequency ``nu`` (cycles/mm: the local
    phase gradient of the field over 2 pi, from its neighbours, plus the carrier), not one frequency for the whole
    beam: a tilted beam's local frequencies differ from the carrier by the converging beam's own spread, and the
    carrier's phase is then wrong by ``g 2 pi lambda nu0 |1 / n_before - 1 / n_after| (nu - nu0)`` to first order, a
    tilt across the beam proportional to the slice (the earlier truth's first-order slice error at 5 deg). ``band``
    (cycles/mm, None: 0.9 times the medium's cut-off): the local frequency's largest offset from the carrier.
    ``nearest``: a cut sample whose slice lies mostly before the surface (``g >= dz / 2``) takes the medium before's
    transfer and the phase of its length ``dz - g`` in the medium after instead (each sample the medium it mostly
    lies in). ``split``: the cut sample's phase ``Phi = g dk`` split about the slice's air (after) step, ``Phi (1 -
    g / (2 dz))`` before it and ``Phi g / (2 dz)`` after (the pre-step's share continuous over the cut, 0 where the
    surface leaves it: ``g (1 - g / (2 dz))``'s gradient ``(1 - g / dz) dg/dx dk`` is the refraction's frequency step
    taken over the part ``dz - g`` that lies in the medium after, as the real wave takes it). Without it the whole
    phase comes after the step: the refracted frequency is then taken only at the slice's end and the tilted wave's
    phase over the slice is off by ``~ (dz - g) 2 pi tan(theta_after) d nu``, ``d nu = |grad surf_z| dk / (2 pi)``:
    a first-order slice error on a surface crossed obliquely (``test_wpm_tilted_interface.py``, against Snell on a
    flat tilted interface). ``snell`` (with ``split``; a trial): the post-step phase set so that a locally plane wave
    gets ``g k_z,before(nu_1) + (dz - g) k_z,after(nu_2)`` over the slice exactly, ``nu_2`` Snell's refracted
    frequency on the surface's local slope (``surf_z``'s gradient)."""
    if nearest and split:
        raise ValueError("wpm_zone_local: nearest and split are exclusive")
    if snell and not split:
        raise ValueError("wpm_zone_local: snell needs split")
    gsy, gsx = np.gradient(np.asarray(surf_z, float) * np.ones(np.shape(V)), grid.h)
    nsl = max(1, int(np.ceil((z_to - z_from) / dz)))
    dz = (z_to - z_from) / nsl
    Hb, Ha = grid.transfer(n_before, lam, dz), grid.transfer(n_after, lam, dz)
    nmin = min(n_before, n_after)
    cap = 0.9 * nmin / lam if band is None else float(band)
    h, nu0 = grid.h, grid.nu0

    def kz(n, fx, fy):
        return 2 * np.pi * np.sqrt(np.maximum((n / lam) ** 2 - fx * fx - fy * fy, 0.0))

    for i in range(nsl):
        z = z_from + i * dz
        g = np.clip(surf_z - z, 0.0, dz)
        A = _fft2(V)
        if np.all(g >= dz):
            V = _ifft2(A * Hb)
            continue
        if np.all(g <= 0):
            V = _ifft2(A * Ha)
            continue
        cut = (g > 0) & (g < dz)
        # the local frequency from the neighbours' phase difference (no unwrapping; the field is sampled well
        # within its band), capped at ``cap`` from the carrier
        fx = np.angle(np.roll(V, -1, axis=1) * np.conj(np.roll(V, 1, axis=1)))[cut] / (4 * np.pi * h)
        fy = np.angle(np.roll(V, -1, axis=0) * np.conj(np.roll(V, 1, axis=0)))[cut] / (4 * np.pi * h)
        r = np.hypot(fx, fy)
        f = np.where(r > cap, cap / np.maximum(r, 1e-30), 1.0)
        fx, fy = nu0 + fx * f, fy * f
        dk = kz(n_before, fx, fy) - kz(n_after, fx, fy)
        if split:
            # the pre-step phase g (1 - g / (2 dz)) dk on the cut samples (0 elsewhere: continuous at g = 0 and at g
            # = dz, where it is dz dk / 2 -- the full samples take the medium before's step, not this one)
            pre = np.zeros(V.shape, complex)
            gc = g[cut]
            pre[cut] = gc * (1 - 0.5 * gc / dz) * dk
            full_b = g >= dz
            pre[full_b] = 0.5 * dz * np.mean(dk)
            Pa = _ifft2(_fft2(V * np.exp(1j * pre)) * Ha)
            V = np.where(full_b, _ifft2(A * Hb), Pa) if full_b.any() else Pa
            if snell:
                # the post-step phase that makes the slice's phase g k_z,b(nu_1) + (dz - g) k_z,a(nu_2) on a locally
                # plane wave: nu_2 the refracted frequency (Snell on the surface's local slope), the step's own
                # phase dz k_z,a(nu_1 + dnu) at the frequency the pre-step phase's gradient gave
                sx, sy = gsx[cut], gsy[cut]
                k1 = kz(n_before, fx, fy)
                f2x, f2y = fx, fy
                for _ in range(30):
                    k2 = kz(n_after, f2x, f2y)
                    f2x, f2y = fx + sx * (k1 - k2) / (2 * np.pi), fy + sy * (k1 - k2) / (2 * np.pi)
                w = (1 - gc / dz) * dk / (2 * np.pi)
                q = (gc * k1 + (dz - gc) * kz(n_after, f2x, f2y) - dz * kz(n_after, fx + w * sx, fy + w * sy)
                     - gc * (1 - 0.5 * gc / dz) * dk)
                V[cut] *= np.exp(1j * q)
            else:
                V[cut] *= np.exp(1j * 0.5 * gc * gc / dz * dk)
            continue
        Pa = _ifft2(A * Ha)
        full = (g >= dz) | ((g >= 0.5 * dz) if nearest else False)
        if full.any():
            V = np.where(full, _ifft2(A * Hb), Pa)
        else:
            V = Pa
        gc = g[cut]
        V[cut] *= np.exp(1j * np.where(full[cut], gc - dz, gc) * dk)
    return V


def band_window(g: Grid, band=None, taper=0.3, center=0.0):
    """The spectral window on the grid ``g`` (its frequencies, cycles/mm, carrier included): 1 within ``band`` -
    ``taper`` share of it of the carrier plus ``center`` (cycles/mm, in x: the chief ray's frequency over the
    carrier's), ``cos^2`` to 0 at ``band`` (cycles/mm); None: 1 (the grid's whole band)."""
    if band is None:
        return 1.0
    if not np.isfinite(band) or band <= 0 or not 0 < taper <= 1:
        raise ValueError(f"band_window: band={band!r} (cycles/mm) must be > 0 and taper={taper!r} in (0, 1]")
    q = np.clip((np.hypot(g.NX - g.nu0 - center, g.NY) - band * (1 - taper)) / (band * taper), 0.0, 1.0)
    return np.cos(0.5 * np.pi * q) ** 2


def window_guard(band, lam_mm, z_mm, window_mm, beam_mm, target_mm):
    """The periodic window's guard (mm) for a free-space step: ``window_mm - beam_mm - target_mm - shift``, ``shift =
    z tan(asin(lambda band))`` the farthest a kept plane wave moves over ``z_mm``; > 0: no kept light leaving the
    beam (``beam_mm``: its half-width on the plane it leaves) re-enters the window within ``target_mm`` (the
    half-width that must stay clean on the plane it reaches) of the centre. Lengths in mm, ``band`` in cycles/mm."""
    s = lam_mm * band
    if not 0 < s < 1:
        raise ValueError(f"window_guard: lambda band = {s!r} must lie in (0, 1)")
    return window_mm - beam_mm - target_mm - z_mm * s / np.sqrt(1 - s * s)


def truth_and_model(lens: Cooke, field_deg: float, h=1.5e-3, dz=1e-3, soft=0.0, margin=0.3, patch_x=None,
                    patch_y=None, patch_pitch=0.5e-3, patch_half=None, gauss=1, with_model=True, element="wave",
                    sub_slice="snell", band=None, taper=0.3):
    """(truth, model, info): the sensor irradiance of the truth and of the one-step model on the same patch (power
    per mm^2; the entering plane wave has |U| = 1), and what was measured (``info``: the patch's axes, the powers on
    the planes, timings). ``h``: the grids' pitch (mm), ``dz``: the WPM's slice (mm; a pair: surface 4's zone's and surface 5's), ``soft``: the iris's cos^2
    roll-off share (0: the hard iris; > 0: no edge, the truth against geometric optics), ``margin`` (mm): the window
    beyond the beam's diameter at the iris. The patch: pixel centres ``patch_x`` / ``patch_y`` (mm; the truth's
    x is the field's direction) or, if None, the truth's spot (where it exceeds 1 % of its peak, plus 10 um) at
    ``patch_pitch`` (mm) about its peak; ``gauss`` > 1: each value the mean over a pixel of side ``patch_pitch`` by
    ``gauss`` x ``gauss`` Gauss-Legendre nodes (a box-integrated pixel, divided by its area). ``element``: "wave"
    (the last element's two sag zones by the WPM) or "geometric" (a diagnostic: the truth starts from the traced
    field 1 um behind the last surface's vertex instead, the iris-to-there distance left to geometric optics).
    ``sub_slice``: the transverse frequency at which the WPM's sub-slice phase ``g (k_z,before - k_z,after)`` is
    taken: "carrier" (the entering wave's, ``sin(theta) / lambda``, as ``_a489_truth.py``) or "chief" (the chief
    ray's in the medium before the surface, ``n d_x / lambda``; the same on the axis) or "local" (each sample's own,
    :func:`wpm_zone_local`; "nearest": the same, each cut sample in the medium it mostly lies in; "split": each
    sample's own, the phase split about the slice's step (11x the earlier rule's convergence at 5 deg); "snell",
    the default: "split" with :func:`wpm_zone_local`'s ``snell``, at 5 deg within 5 % at a 1 um slice). ``band``
    (cycles/mm; None: the grid's whole band, the earlier truth): every free-space step (iris to surface 4's zone,
    the glass, surface 5's
    zone to the DOE plane, the DOE plane to the sensor) keeps only the transverse frequencies within ``band`` of the
    carrier, rolled off as ``cos^2`` over its top ``taper`` share: the periodic window's guard against the edge's
    wide-angle light, which on the grid's full band crosses the window over the 32 mm to the DOE (or the DOE's 20 mm
    to the sensor) and re-enters on its far side (a wrap that grows with the band, 1 / (2 h): the pitch-dependent
    error of the earlier truth; :func:`window_guard` states the condition, ``test_cooke_truth_window.py`` the proof
    on a case with an exact answer)."""
    if sub_slice not in ("carrier", "chief", "local", "nearest", "split", "snell"):
        raise ValueError(f"truth_and_model: sub_slice={sub_slice!r}, one of 'carrier', 'chief', 'local', 'nearest', "
                         "'split', 'snell'")
    t0 = time.perf_counter()
    th = np.radians(field_deg)
    lam, nu0 = lens.lam, np.sin(th) / lens.lam
    info = {}
    s4, s5 = lens.stop + 1, lens.stop + 2
    if s5 != len(lens.zv) - 1:
        raise ValueError("Cooke: the truth expects two surfaces (one element) between the iris and the DOE")
    N = _fast((2 * lens.a + 2 * margin) / h)
    z0 = lens.zI if element == "wave" else lens.zv[s5] + 1e-3
    g = Grid(N, h, lens.chief_x(th, z0), nu0)
    uc = lens.chief(th)

    def chief_nu(z):
        """The chief ray's transverse frequency over the carrier's at the plane ``z`` (cycles/mm)."""
        *_, dch = lens._trace(np.array([uc]), np.zeros(1), th, z, direction=True)
        return lens.medium(z) * float(dch[0, 0]) / lam - nu0

    def prop(V, n, dz, z):
        """The exact angular spectrum over ``dz`` (mm) in the index ``n`` from the plane ``z``, on the band ``band``
        about the chief ray's frequency there (the 5 deg beam's rim reaches 88 cycles/mm over the carrier at the
        iris: a band about the carrier would cut it)."""
        return _ifft2(_fft2(V) * g.transfer(n, lam, dz) * band_window(g, band, taper, chief_nu(z + 1e-9)))

    X, Y = g.mesh()
    V = lens.geometric_field(X, Y, th, z0, h, soft=soft)
    info["power_iris"] = float(np.sum(np.abs(V) ** 2) * h * h)
    # surface 4's sag zone (air -> glass) and surface 5's (glass -> air), their extents from the rim rays
    t = np.linspace(0, 2 * np.pi, 256, endpoint=False)
    zones = []
    for i in (s4, s5):
        uc = lens.chief(th)
        # the iris's rim in entrance coordinates: scale from the axis (small field: the pupil's image is near a disc)
        xr, yr, _ = lens._trace(uc + 0.5 * lens.epd * 1.05 * np.cos(t), 0.5 * lens.epd * 1.05 * np.sin(t), th,
                                lens.zv[i] + 1e-9)
        rmax2 = float(np.max(xr ** 2 + yr ** 2)) + 0.05
        sg = float(lens.sag(i, rmax2))
        zones.append((min(lens.zv[i], lens.zv[i] + sg) - 1e-3, max(lens.zv[i], lens.zv[i] + sg) + 1e-3))
    dzs = tuple(dz) if np.ndim(dz) else (dz, dz)          # the slice in surface 4's zone and in surface 5's
    zprev = lens.zI if element == "wave" else z0
    for (za, zb), i, dz in (zip(zones, (s4, s5), dzs) if element == "wave" else ()):
        V = prop(V, lens.n_before[i], za - zprev, zprev)
        V = g.move(V, lens.chief_x(th, za))
        X, Y = g.mesh()
        nu_s = nu0
        if sub_slice == "chief":
            *_, dch = lens._trace(np.array([lens.chief(th)]), np.zeros(1), th, za, direction=True)
            nu_s = lens.n_before[i] * float(dch[0, 0]) / lam
        if sub_slice in ("local", "nearest", "split", "snell"):
            V = wpm_zone_local(g, V, za, zb, lens.zv[i] + lens.sag(i, X * X + Y * Y), lens.n_before[i],
                               lens.n_after[i], lam, dz, band, nearest=sub_slice == "nearest",
                               split=sub_slice in ("split", "snell"), snell=sub_slice == "snell")
        else:
            V = wpm_zone(g, V, za, zb, lens.zv[i] + lens.sag(i, X * X + Y * Y), lens.n_before[i], lens.n_after[i],
                         lam, dz, nu_s)
        zprev = zb
    V = prop(V, 1.0, lens.zD - zprev, zprev)
    V = g.move(V, lens.chief_x(th, lens.zD))
    X, Y = g.mesh()
    info["power_doe_truth"] = float(np.sum(np.abs(V) ** 2) * h * h)
    info["t_truth_s"] = time.perf_counter() - t0
    fields = [V]
    if with_model:
        t1 = time.perf_counter()
        Vm = lens.geometric_field(X, Y, th, lens.zD, h, soft=soft)
        info["power_doe_model"] = float(np.sum(np.abs(Vm) ** 2) * h * h)
        info["t_model_s"] = time.perf_counter() - t1
        fields.append(Vm)
    inside = (np.abs(X) <= lens.doe_half) & (np.abs(Y) <= lens.doe_half)
    tdoe = np.exp(1j * lens.doe_phase(X, Y)) * inside
    # the sensor step's band about the chief ray's frequency behind the DOE (its phase's slope added)
    xc = lens.chief_x(th, lens.zD)
    e = 1e-4
    nu_doe = (lens.doe_phase(xc + e, 0.0) - lens.doe_phase(xc - e, 0.0)) / (2 * e) / (2 * np.pi)
    Hs = g.transfer(1.0, lam, lens.zS - lens.zD) * band_window(g, band, taper, chief_nu(lens.zD) + nu_doe)
    spectra = [_fft2(f * tdoe) * Hs for f in fields]
    if patch_x is None:
        Ic = np.abs(_ifft2(spectra[0])) ** 2
        W = N * h
        iy, ix = np.unravel_index(np.argmax(Ic), Ic.shape)
        xg = lens.chief_x(th, lens.zS)
        xpk, ypk = g.x[ix] + W * np.round((xg - g.x[ix]) / W), g.y[iy]
        if patch_half is None:
            m = Ic > 0.01 * Ic.max()
            dxs = (X[m] - g.x[ix] + W / 2) % W - W / 2
            patch_half = float(np.max(np.hypot(dxs, Y[m] - ypk))) + 0.01
        patch_x = xpk + np.arange(-patch_half, patch_half + 1e-12, patch_pitch)
        patch_y = ypk + np.arange(-patch_half, patch_half + 1e-12, patch_pitch)
    gx0, gy0 = g.x[0], g.y[0]

    def sensor(px, py, pitch, gauss_nodes=1):
        """(truth, model) irradiance (power per mm^2) at the pixel centres ``px`` x ``py`` (mm), each the mean over
        its pixel of side ``pitch`` (mm) by ``gauss_nodes``^2 Gauss-Legendre nodes (1: the centre's value)."""
        px, py = np.asarray(px, float), np.asarray(py, float)
        if gauss_nodes > 1:
            gn, gw = np.polynomial.legendre.leggauss(gauss_nodes)
            off, wts = 0.5 * pitch * gn, 0.5 * gw
        else:
            off, wts = np.zeros(1), np.ones(1)
        qx = (px[:, None] + off[None, :]).ravel()
        qy = (py[:, None] + off[None, :]).ravel()
        nu = np.fft.fftfreq(N, h)
        ex = np.exp(2j * np.pi * np.outer(nu, qx - gx0))
        ey = np.exp(2j * np.pi * np.outer(qy - gy0, nu))
        res = []
        for S in spectra:
            Iq = (np.abs(ey @ S @ ex / N ** 2) ** 2).reshape(len(py), len(off), len(px), len(off))
            res.append(np.einsum("aibj,ij->ab", Iq, np.outer(wts, wts)))
        return res[0], (res[1] if with_model else None)

    out = sensor(patch_x, patch_y, patch_pitch, gauss)
    info.update(patch_x=np.asarray(patch_x, float), patch_y=np.asarray(patch_y, float), grid_n=N, zones=zones,
                iris_radius=lens.a, iris_z=lens.zI, sensor=sensor,
                t_total_s=time.perf_counter() - t0,
                band_edge=float(np.sum(np.abs(spectra[0][np.abs(g.NX - nu0) > 0.8 / (2 * h)]) ** 2)
                                / np.sum(np.abs(spectra[0]) ** 2)))
    return out[0], (out[1] if with_model else None), info
