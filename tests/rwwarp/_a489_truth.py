"""A wave-exact truth through the real A489 asphere for the ray-wave model's own error (issue 27), shared by
``tests/rwwarp/test_model_error_a489.py`` and ``perf/model_error_a489.py``. It shares no code with rwwarp: the
lens is read as numbers (radii, conic, aspheric terms, thicknesses, the glass's Schott coefficients from
``rwwarp/data/glasses.json``), every ray and wave operation is written here from the equations (numpy, scipy.fft).

Geometry (z from the stop, mm): stop of radius ``a`` at 0; the asphere's vertex at 0.1 (H-K51 behind it); the
spherical rear surface at 7.6; the DOE plane 0.7098 behind it; the sensor 2.9472 behind the DOE. The point source of
field angle ``theta`` (tilted in x) at the lens file's object distance (10 m) fills the stop. Fields are ``U ~ exp(+i k OPL)``, free space multiplies the
angular spectrum by ``exp(2 pi i z sqrt(n^2 / lambda^2 - nu^2))`` (exact, no Fresnel approximation), the DOE by
``exp(+i phi)`` (``phi0 = sum_i c_i (r / R)^(2i)`` about the lens's axis, the design phase; at its design wavelength
``lambda0`` (the file's 0.55 um) the wrapped relief transmits the same field, ``phi = phi0``; at another wavelength
the relief (a surface relief of the file's substrate, fused silica, in air, height ``wrap(phi0) lambda0 / (2 pi
(n0 - 1))``, unquantised) gives ``phi = s wrap(phi0)``, ``wrap`` to [0, 2 pi), ``s = (n_s(lambda) - 1) / (n_s(lambda0)
- 1) lambda0 / lambda`` the thin relief's path difference ``(n_s - 1) height`` in waves: every diffraction order of
the wrapped relief, not its main order alone). The indices (the lens's glass and the DOE's substrate) at the
wavelength ``lam_mm`` from their dispersion formulas' catalogue coefficients (:func:`catalogue_index`).

* truth ("two-step"): the stop's disc propagated as a wave all the way to the DOE plane:
  - front zone (``front="wave"``): the angular spectrum in air to the asphere's vertex plane, then the wave
    propagation method (WPM) in slices ``dz`` through the asphere's sag zone (each slice propagated with air's and
    glass's exact transfer functions, each sample taking the one of its medium; a sample whose slice the surface
    cuts takes air's and the phase ``g (k_zg - k_za)`` of its glass length ``g`` at the beam's carrier direction);
    ``front="geometric"``: the ray-traced (geometric) field on the first plane behind the sag zone instead (the
    edge's diffraction over those ~0.2 mm left out: ~1 % of the reduced distance at F/4);
  - the exact angular spectrum in glass to the rear surface's sag zone, the WPM through it, the angular spectrum in
    air to the DOE plane;
* model ("one-step", the ray-wave model's geometric field): rays traced from the stop to the DOE plane (Snell,
  exact intersections), the field ``sqrt(dA_stop / dA) exp(i k OPL)`` on the DOE grid (each sample's ray found by
  Newton's method), cut where its ray left the stop (the rim's samples weighted by the share of their cell inside);
* both: the same DOE, the same exact angular spectrum to the sensor, evaluated on a fine patch by a matrix DFT.

The carrier ``exp(2 pi i sin(theta) x / lambda)`` is taken out of every grid (its transfer functions read
``nu + nu0``); each plane's window follows the beam (the grids are periodic: a window moved by whole samples is
a roll). Both fields keep ``int |U|^2 dA`` (the angular spectrum's Parseval; the geometric tube's Jacobian), the
power through the stop. Lengths in mm, wavelengths in mm inside this module (``LAM_MM``), phases in rad.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import scipy.fft

LAM_MM = 0.55e-3
ROOT = Path(__file__).resolve().parents[2]


def _fft2(a):
    return scipy.fft.fft2(a, workers=-1)


def _ifft2(a):
    return scipy.fft.ifft2(a, workers=-1)


def catalogue_index(glass: str, lam_mm: float = LAM_MM) -> float:
    """The glass's index at the wavelength ``lam_mm`` (mm) from its dispersion formula's coefficients in rwwarp's
    catalogue data (the data, not rwwarp's code; l in um): Schott ``n^2 = a0 + a1 l^2 + a2 l^-2 + a3 l^-4 + a4 l^-6
    + a5 l^-8``, Sellmeier1 ``n^2 - 1 = sum_i B_i l^2 / (l^2 - C_i)`` (coefficients ``[B1, C1, B2, C2, B3, C3]``, C in
    um^2). ValueError naming the glass for another formula or a wavelength outside its catalogue range."""
    cat = json.loads((ROOT / "rwwarp" / "data" / "glasses.json").read_text())
    g = cat["glasses"][glass]
    lam_um = lam_mm * 1e3
    lo, hi = g.get("range_um", (0.0, np.inf))
    if not lo <= lam_um <= hi:
        raise ValueError(f"{glass}: {lam_um} um outside its catalogue range {lo}-{hi} um")
    c, l2 = g["coefficients"], lam_um ** 2
    if g["formula"] == "Schott":
        return float(np.sqrt(c[0] + c[1] * l2 + c[2] / l2 + c[3] / l2 ** 2 + c[4] / l2 ** 3 + c[5] / l2 ** 4))
    if g["formula"] == "Sellmeier1":
        return float(np.sqrt(1.0 + sum(c[2 * i] * l2 / (l2 - c[2 * i + 1]) for i in range(3))))
    raise ValueError(f"{glass}: formula {g['formula']!r}, only Schott and Sellmeier1 are written here")


def schott_index(glass: str, lam_mm: float = LAM_MM) -> float:
    """:func:`catalogue_index` of a glass whose formula is Schott (ValueError naming the glass otherwise)."""
    cat = json.loads((ROOT / "rwwarp" / "data" / "glasses.json").read_text())
    if cat["glasses"][glass]["formula"] != "Schott":
        raise ValueError(f"{glass}: formula {cat['glasses'][glass]['formula']!r}, not Schott")
    return catalogue_index(glass, lam_mm)


class A489:
    """The A489's surfaces as numbers (from ``rw.load_lens("a489_doe")``'s JSON, read here), stop radius ``a_mm``
    (1.0: the lens file's, F/4), DOE ``coeffs`` (rad, the design phase at the file's design wavelength) on
    ``norm_mm``, the wavelength ``lam_mm`` (mm; the glass's index and the DOE's relief at it: module docstring)."""

    def __init__(self, a_mm=1.0, coeffs=(600.0, 200.0), norm_mm=1.5, lam_mm=LAM_MM):
        spec = json.loads((ROOT / "rwwarp" / "lenses" / "a489_doe.json").read_text())
        surfs = spec["surfaces"]
        s1, s2, doe = surfs[1], surfs[2], surfs[3]
        self.a, self.lam = float(a_mm), float(lam_mm)
        if not np.isfinite(self.lam) or self.lam <= 0:
            raise ValueError(f"A489: wavelength lam_mm={lam_mm!r} (mm) must be a positive number")
        self.k = 2 * np.pi / lam_mm
        self.z1 = float(surfs[0]["thickness"])
        self.c1, self.k1 = 1.0 / float(s1["radius"]), float(s1.get("conic", 0.0))
        self.asph = [float(v) for v in s1.get("aspheric", [])]
        self.z2 = self.z1 + float(s1["thickness"])
        self.c2 = 1.0 / float(s2["radius"])
        self.zD = self.z2 + float(s2["thickness"])
        self.zS = self.zD + float(doe["thickness"])
        self.doe_half = float(doe["semi_diameter"])
        self.n = catalogue_index(s1["material"], lam_mm)
        # the DOE's relief at this wavelength (module docstring): s = 1 exactly at its design wavelength
        self.doe_lam = float(doe["design_wavelength_um"]) * 1e-3
        self.doe_substrate = str(doe["material"])
        if abs(self.lam - self.doe_lam) <= 1e-9 * self.doe_lam:
            self.doe_scale = 1.0
        else:
            n0, ns = catalogue_index(self.doe_substrate, self.doe_lam), catalogue_index(self.doe_substrate, self.lam)
            self.doe_scale = (ns - 1.0) / (n0 - 1.0) * self.doe_lam / self.lam
        self.coeffs, self.norm = tuple(float(c) for c in coeffs), float(norm_mm)
        od = spec.get("object_distance", "inf")
        self.D = np.inf if od == "inf" else float(od)       # the object point's distance before the stop (mm)

    # -- surfaces -------------------------------------------------------------------------------------------
    def sag1(self, r2):
        c, k = self.c1, self.k1
        s = c * r2 / (1 + np.sqrt(1 - (1 + k) * c * c * r2))
        for j, aj in enumerate(self.asph):
            s = s + aj * r2 ** (2 + j)
        return s

    def dsag1_over_r(self, r2):
        """(d sag / dr) / r."""
        c, k = self.c1, self.k1
        d = c / np.sqrt(1 - (1 + k) * c * c * r2)
        for j, aj in enumerate(self.asph):
            d = d + aj * (4 + 2 * j) * r2 ** (1 + j)
        return d

    def sag2(self, r2):
        c = self.c2
        return c * r2 / (1 + np.sqrt(1 - c * c * r2))

    def dsag2_over_r(self, r2):
        c = self.c2
        return c / np.sqrt(1 - c * c * r2)

    def doe_phase(self, x, y):
        """The DOE's phase (rad) at (x, y) (mm) at this wavelength: the design phase ``phi0`` at the design
        wavelength (the wrapped relief's field, unwrapped), ``doe_scale * wrap(phi0)`` at another (the relief)."""
        rho2 = (x * x + y * y) / self.norm ** 2
        phi0 = sum(c * rho2 ** (i + 1) for i, c in enumerate(self.coeffs))
        if self.doe_scale == 1.0:
            return phi0
        return self.doe_scale * np.mod(phi0, 2 * np.pi)

    # -- rays -------------------------------------------------------------------------------------------------
    @staticmethod
    def _hit(p, d, zv, sag, dsag_r, iters=12):
        """Intersection of the rays ``p + t d`` with ``z = zv + sag(x^2 + y^2)`` (Newton on t), and the unit normal
        there (oriented along +z)."""
        t = (zv - p[2]) / d[2]
        for _ in range(iters):
            x, y, z = p[0] + t * d[0], p[1] + t * d[1], p[2] + t * d[2]
            r2 = x * x + y * y
            g = dsag_r(r2)
            f = z - zv - sag(r2)
            fp = d[2] - g * (x * d[0] + y * d[1])
            t = t - f / fp
        x, y, z = p[0] + t * d[0], p[1] + t * d[1], p[2] + t * d[2]
        g = dsag_r(x * x + y * y)
        N = np.stack([-g * x, -g * y, np.ones_like(x)])
        return t, np.stack([x, y, z]), N / np.linalg.norm(N, axis=0)

    @staticmethod
    def _refract(d, N, mu):
        ci = np.sum(d * N, axis=0)
        ct = np.sqrt(1 - mu * mu * (1 - ci * ci))
        return mu * d + (ct - mu * ci) * N

    def trace(self, xs, ys, theta_rad, z_plane, glass_plane=False):
        """Rays from the stop points (xs, ys) (mm, at z = 0) of the source at ``theta_rad`` (:meth:`source`) to the
        plane ``z_plane``: (x, y, phase) with phase ``k`` times the path from the object point (rad). ``glass_plane``: the plane lies in
        the glass (between the two surfaces)."""
        xs, ys = np.asarray(xs, float), np.asarray(ys, float)
        p = np.stack([xs, ys, np.zeros_like(xs)])
        d, opl0 = self.source(xs, ys, theta_rad)
        t, p, N = self._hit(p, d, self.z1, self.sag1, self.dsag1_over_r)
        opl = opl0 + t
        d = self._refract(d, N, 1.0 / self.n)
        if not glass_plane:
            t, p, N = self._hit(p, d, self.z2, self.sag2, self.dsag2_over_r)
            opl = opl + self.n * t
            d = self._refract(d, N, self.n)
            nz = 1.0
        else:
            nz = self.n
        t = (z_plane - p[2]) / d[2]
        opl = opl + nz * t
        return p[0] + t * d[0], p[1] + t * d[1], self.k * opl

    def source(self, xs, ys, theta_rad):
        """The incoming wave on the stop plane: the rays' unit directions (3, ...) and the path (mm) from the object
        point (``D`` before the stop, ``D tan(theta)`` below the axis; a plane wave for D = inf) less ``D /
        cos(theta)``: the field there is ``exp(i k path)``."""
        if np.isinf(self.D):
            d = np.stack([np.full_like(xs, np.sin(theta_rad)), np.zeros_like(xs), np.full_like(xs, np.cos(theta_rad))])
            return d, np.sin(theta_rad) * xs
        xo, D = -self.D * np.tan(theta_rad), self.D
        v = np.stack([xs - xo, ys, np.full_like(xs, D)])
        L = np.linalg.norm(v, axis=0)
        # L - D / cos(theta), written without cancellation
        Lc = D / np.cos(theta_rad)
        path = ((xs - xo) ** 2 - xo ** 2 + ys ** 2) / (L + Lc)
        return v / L, path

    def chief_x(self, theta_rad, z_plane, glass_plane=False):
        x, _, _ = self.trace(np.zeros(1), np.zeros(1), theta_rad, z_plane, glass_plane)
        return float(x[0])

    def geometric_field(self, X, Y, theta_rad, z_plane, glass_plane=False, h=None, soft=0.0, tol=1e-11,
                        chunk=1 << 20):
        """The geometric field at the plane ``z_plane`` on the samples (X, Y) (mm), carrier removed: each sample's
        ray found by Newton's method from the stop, amplitude ``sqrt(|d(xs, ys) / d(x, y)|)``, phase ``k`` times the path
        from the object point ``- 2 pi nu0 x``, cut by the stop (rim samples: the share of their cell, of side ``h``, inside;
        ``soft`` > 0: a cos^2 roll-off of the amplitude over the stop's outer ``soft`` share of its radius instead
        of the hard rim)."""
        shape = X.shape
        X, Y = X.ravel(), Y.ravel()
        e = 1e-5
        # an affine first guess from three rays about the chief ray
        x0, y0, _ = self.trace(np.array([0.0, e, 0.0]), np.array([0.0, 0.0, e]), theta_rad, z_plane, glass_plane)
        mx, my = (x0[1] - x0[0]) / e, (y0[2] - y0[0]) / e
        keep = np.hypot((X - x0[0]) / mx, Y / my) < 1.25 * self.a
        out = np.zeros(X.shape, complex)
        idx = np.flatnonzero(keep)
        for i in range(0, len(idx), chunk):          # in chunks: bounds the trace's temporaries
            sel = idx[i:i + chunk]
            out[sel] = self._geometric_samples(X[sel], Y[sel], (x0[0], mx, my), theta_rad, z_plane, glass_plane,
                                               h, soft, tol, e)
        return out.reshape(shape)

    def _geometric_samples(self, xt, yt, guess, theta_rad, z_plane, glass_plane, h, soft, tol, e):
        """:meth:`geometric_field` on the samples (xt, yt) (1-D), ``guess`` the affine first guess's (x0, mx, my)."""
        xs, ys = (xt - guess[0]) / guess[1], yt / guess[2]
        for _ in range(40):
            x, y, _ = self.trace(xs, ys, theta_rad, z_plane, glass_plane)
            ax, ay, _ = self.trace(xs + e, ys, theta_rad, z_plane, glass_plane)
            bx, by, _ = self.trace(xs, ys + e, theta_rad, z_plane, glass_plane)
            j11, j21, j12, j22 = (ax - x) / e, (ay - y) / e, (bx - x) / e, (by - y) / e
            rx, ry = x - xt, y - yt
            det = j11 * j22 - j12 * j21
            xs = xs - (j22 * rx - j12 * ry) / det
            ys = ys - (-j21 * rx + j11 * ry) / det
            if max(np.abs(rx).max(), np.abs(ry).max()) < tol:
                break
        x, y, ph = self.trace(xs, ys, theta_rad, z_plane, glass_plane)
        ax, ay, _ = self.trace(xs + e, ys, theta_rad, z_plane, glass_plane)
        bx, by, _ = self.trace(xs, ys + e, theta_rad, z_plane, glass_plane)
        det = np.abs((ax - x) * (by - y) - (bx - x) * (ay - y)) / e ** 2
        rs = np.hypot(xs, ys)
        if soft > 0:
            u = np.clip((rs - (1 - soft) * self.a) / (soft * self.a), 0.0, 1.0)
            ap = np.cos(0.5 * np.pi * u) ** 2
        else:
            hs = h / np.sqrt(det)                  # the cell's side mapped back to the stop
            ap = np.clip(0.5 + (self.a - rs) / hs, 0.0, 1.0)
        nu0 = np.sin(theta_rad) / self.lam
        return ap / np.sqrt(det) * np.exp(1j * (ph - 2 * np.pi * nu0 * xt))


class Grid:
    """A square periodic grid of pitch ``h`` (mm), ``N`` samples a side, its x window starting at sample ``j0``
    (x = (j0 + i) h), y centred on 0; the field on it has the carrier ``nu0`` (cycles/mm, x) taken out."""

    def __init__(self, N, h, xc, nu0):
        self.N, self.h, self.nu0 = int(N), float(h), float(nu0)
        self.j0 = int(round(xc / h)) - self.N // 2
        self.x = (self.j0 + np.arange(self.N)) * h
        self.y = (np.arange(self.N) - self.N // 2) * h
        nu = np.fft.fftfreq(self.N, h)
        self.NX, self.NY = np.meshgrid(nu + self.nu0, nu, indexing="xy")

    def mesh(self):
        return np.meshgrid(self.x, self.y, indexing="xy")

    def move(self, V, xc):
        """The periodic field ``V`` on the window centred (to a sample) on ``xc``."""
        j0 = int(round(xc / self.h)) - self.N // 2
        V = np.roll(V, -(j0 - self.j0), axis=1)
        self.j0, self.x = j0, (j0 + np.arange(self.N)) * self.h
        return V

    def transfer(self, n, lam, dz):
        w = (n / lam) ** 2 - self.NX ** 2 - self.NY ** 2
        return np.where(w > 0, np.exp(2j * np.pi * dz * np.sqrt(np.maximum(w, 0.0))), 0.0)

    def propagate(self, V, n, lam, dz):
        return _ifft2(_fft2(V) * self.transfer(n, lam, dz))


def wpm_zone(grid, V, z_from, z_to, surf_z, n_before, n_after, lam, dz, nu0):
    """The WPM through the slab ``z_from .. z_to`` cut by the surface ``z = surf_z`` (array on the grid): medium
    ``n_before`` for z < surf_z, ``n_after`` beyond. Each slice: both media's exact transfer over the slice; a sample
    whose slice the surface cuts takes the medium after's and the phase of its length ``g`` in the medium before at
    the carrier's direction, ``g (k_z,before - k_z,after)``."""
    nsl = max(1, int(np.ceil((z_to - z_from) / dz)))
    dz = (z_to - z_from) / nsl
    Hb, Ha = grid.transfer(n_before, lam, dz), grid.transfer(n_after, lam, dz)
    kzb = 2 * np.pi * np.sqrt((n_before / lam) ** 2 - nu0 ** 2)
    kza = 2 * np.pi * np.sqrt((n_after / lam) ** 2 - nu0 ** 2)
    for i in range(nsl):
        z = z_from + i * dz
        g = np.clip(surf_z - z, 0.0, dz)          # length in the medium before, in this slice
        A = _fft2(V)
        if np.all(g >= dz):
            V = _ifft2(A * Hb)
            continue
        if np.all(g <= 0):
            V = _ifft2(A * Ha)
            continue
        Pa = _ifft2(A * Ha)
        full = g >= dz
        if full.any():
            Pb = _ifft2(A * Hb)
            V = np.where(full, Pb, Pa * np.exp(1j * g * (kzb - kza)))
        else:
            V = Pa * np.exp(1j * g * (kzb - kza))
    return V


def _fast(n):
    return scipy.fft.next_fast_len(int(np.ceil(n / 2)) * 2)


def _rim_rays(lens, theta, z, glass_plane, m=256):
    t = np.linspace(0, 2 * np.pi, m, endpoint=False)
    return lens.trace(lens.a * np.cos(t), lens.a * np.sin(t), theta, z, glass_plane)


def truth_and_model(lens: A489, field_deg: float, h=1.0e-3, dz=0.5e-3, front="wave", soft=0.0, margin=0.15,
                    patch_pitch=0.5e-3, patch_half=None, patch_center=None, with_model=True, keep_fields=False):
    """(truth, model, info): the sensor irradiance of the truth and of the one-step model on the same patch (power
    per mm^2; the stop's plane wave has |U| = 1), and what was measured (``info``: the patch's axes, the powers on
    the planes, the window's losses, timings). ``h``: the grids' pitch (mm), ``dz``: the WPM's slice (mm),
    ``front``: "wave" (the stop's disc propagated through the asphere's sag zone) or "geometric" (the traced field
    behind it), ``soft``: the stop's cos^2 roll-off share (0: the hard stop; > 0: the edge's diffraction suppressed,
    the truth's own error against the geometric field), ``margin`` (mm): the windows beyond the beam's diameter,
    ``patch_pitch`` / ``patch_half`` (mm; None: the truth's spot, where it exceeds 1 % of its peak, plus 10 um),
    ``patch_center`` (x, y) mm (None: the truth's peak on the grid); ``keep_fields``: ``info["doe_fields"]`` the
    truth's and the model's fields on the DOE plane (carrier removed, before the DOE) and ``info["grid"]`` their
    :class:`Grid` (a diagnostic; nothing computed changes)."""
    import time
    t0 = time.perf_counter()
    th = np.radians(field_deg)
    lam, n = lens.lam, lens.n
    nu0 = np.sin(th) / lam
    info = {}
    # planes: behind the asphere's sag zone (zb), before the rear surface's (zc)
    r1 = lens.a + lens.z1 * np.tan(th) + 0.02
    zb = lens.z1 + float(lens.sag1(r1 * r1)) + 1e-3
    xr, yr, _ = _rim_rays(lens, th, lens.z2, True)
    xc2 = lens.chief_x(th, lens.z2, True)
    r2 = float(np.max(np.hypot(xr, yr))) + 0.05
    zc = lens.z2 + float(lens.sag2(r2 * r2)) - 1e-3
    rb_rear = float(np.max(np.hypot(xr - xc2, yr)))
    NA_ = _fast((2 * lens.a + 2 * margin) / h)
    if front == "wave":
        gA = Grid(NA_, h, 0.0, nu0)
        X, Y = gA.mesh()
        R = np.hypot(X, Y)
        ap = np.clip(0.5 + (lens.a - R) / h, 0.0, 1.0)
        if soft > 0:
            u = np.clip((R - (1 - soft) * lens.a) / (soft * lens.a), 0.0, 1.0)
            ap = np.cos(0.5 * np.pi * u) ** 2
        _, path = lens.source(X, Y, th)
        V = ap * np.exp(1j * (lens.k * path - 2 * np.pi * nu0 * X))
        info["power_stop"] = float(np.sum(np.abs(V) ** 2) * h * h)
        V = gA.propagate(V, 1.0, lam, lens.z1)
        V = gA.move(V, lens.z1 * np.tan(th))
        X, Y = gA.mesh()
        V = wpm_zone(gA, V, lens.z1, zb, lens.z1 + lens.sag1(X * X + Y * Y), 1.0, n, lam, dz, nu0)
    else:
        gA = Grid(NA_, h, lens.chief_x(th, zb, True), nu0)
        X, Y = gA.mesh()
        V = lens.geometric_field(X, Y, th, zb, True, h=h, soft=soft)
        info["power_stop"] = float(np.pi * lens.a ** 2) if soft == 0 else None
    info["power_zb"] = float(np.sum(np.abs(V) ** 2) * h * h)
    V = gA.move(V, lens.chief_x(th, zb, True))
    V = gA.propagate(V, n, lam, zc - zb)
    V = gA.move(V, xc2)
    # crop to the rear window
    NB = min(_fast((2 * rb_rear + 2 * margin) / h), NA_)
    i0 = NA_ // 2 - NB // 2
    full = float(np.sum(np.abs(V) ** 2))
    V = V[i0:i0 + NB, i0:i0 + NB]
    info["crop_loss"] = 1.0 - float(np.sum(np.abs(V) ** 2)) / full
    gB = Grid(NB, h, 0.0, nu0)
    gB.j0, gB.x = gA.j0 + i0, (gA.j0 + i0 + np.arange(NB)) * h
    X, Y = gB.mesh()
    V = wpm_zone(gB, V, zc, lens.z2, lens.z2 + lens.sag2(X * X + Y * Y), n, 1.0, lam, dz, nu0)
    V = gB.propagate(V, 1.0, lam, lens.zD - lens.z2)
    xD = lens.chief_x(th, lens.zD)
    V = gB.move(V, xD)
    X, Y = gB.mesh()
    info["power_doe_truth"] = float(np.sum(np.abs(V) ** 2) * h * h)
    info["t_truth_s"] = time.perf_counter() - t0
    fields = [V]
    if with_model:
        t1 = time.perf_counter()
        Vm = lens.geometric_field(X, Y, th, lens.zD, h=h, soft=soft)
        info["power_doe_model"] = float(np.sum(np.abs(Vm) ** 2) * h * h)
        info["t_model_s"] = time.perf_counter() - t1
        fields.append(Vm)
    inside = (np.abs(X) <= lens.doe_half) & (np.abs(Y) <= lens.doe_half)
    info["doe_clipped"] = float(np.sum(np.abs(V[~inside]) ** 2) * h * h / info["power_doe_truth"])
    tdoe = np.exp(1j * lens.doe_phase(X, Y)) * inside
    Hs = gB.transfer(1.0, lam, lens.zS - lens.zD)
    spectra = [_fft2(f * tdoe) * Hs for f in fields]
    # the spot: the truth's irradiance on the grid (periodic), its peak placed near the traced guess
    Ic = np.abs(_ifft2(spectra[0])) ** 2
    W = NB * h
    iy, ix = np.unravel_index(np.argmax(Ic), Ic.shape)
    xg = lens.chief_x(th, lens.zS)
    xpk = gB.x[ix] + W * np.round((xg - gB.x[ix]) / W)
    ypk = gB.y[iy]
    if patch_half is None:
        m = Ic > 0.01 * Ic.max()
        dxs = (X[m] - gB.x[ix] + W / 2) % W - W / 2
        dys = Y[m] - ypk
        patch_half = float(np.max(np.hypot(dxs, dys))) + 0.01
    if patch_center is not None:
        xpk, ypk = patch_center
    px = xpk + np.arange(-patch_half, patch_half + 1e-12, patch_pitch)
    py = ypk + np.arange(-patch_half, patch_half + 1e-12, patch_pitch)
    nu = np.fft.fftfreq(NB, h)
    ex = np.exp(2j * np.pi * np.outer(nu, px - gB.x[0]))            # (N, Px)
    ey = np.exp(2j * np.pi * np.outer(py - gB.y[0], nu))            # (Py, N)
    out = [np.abs(ey @ S @ ex / NB ** 2) ** 2 for S in spectra]
    if keep_fields:
        info.update(doe_fields=fields, grid=gB, sensor_transfer=Hs, doe_transmission=tdoe, patch_dft=(ey, ex))
    info.update(patch_x=px, patch_y=py, NA_grid=NA_, NB_grid=NB, zb=zb, zc=zc, t_total_s=time.perf_counter() - t0,
                band_edge=float(np.sum(np.abs(spectra[0][np.abs(gB.NX - nu0) > 0.8 / (2 * h)]) ** 2)
                                / np.sum(np.abs(spectra[0]) ** 2)))
    return out[0], (out[1] if with_model else None), info


def measured_error(truth, model):
    """max |model - truth| / max truth on the patch (the radial truths' metric, ``_wave_truth.measured_error``)."""
    return float(np.max(np.abs(model - truth)) / truth.max())
