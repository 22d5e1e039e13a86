"""An independent numpy ray trace of refracting surfaces carrying a diffractive phase, written from the
equations (not from rwwarp's kernels): used by test_phase_surface.py as the truth.

A surface is a dict: ``z`` vertex (mm), ``c`` curvature (1/mm), ``k`` conic, ``a`` {power: coefficient} of the
even asphere (r^4, r^6, ...), ``n`` index after it, optional ``phase`` = (m, R, [A_1, ...]) (radians on
(r / R)^(2 i)). Sag in the r form, ``z(r) = c r^2 / (1 + sqrt(1 - (1 + k) c^2 r^2)) + sum a_p r^p`` with
``dz/dr = c r / sqrt(1 - (1 + k) c^2 r^2) + sum p a_p r^(p-1)``; intersection by bisection-safeguarded Newton
on the ray parameter (60 steps); the grating equation solved in an orthonormal frame (e1, e2, N) of the
tangent plane: ``n' d'.e_j = n d.e_j + (m lambda / 2 pi) dphi/ds_j``, ``dphi/ds_j = (phi_x, phi_y, 0).e_j``
(the derivative of phi(x, y) along the surface in direction e_j), ``n' d'.N = +sqrt(n'^2 - ...)``; the path
gains ``m lambda phi / 2 pi``.
"""
import numpy as np


def sag(s, r):
    c, k = s["c"], s["k"]
    z = c * r * r / (1.0 + np.sqrt(1.0 - (1.0 + k) * c * c * r * r))
    dz = c * r / np.sqrt(1.0 - (1.0 + k) * c * c * r * r)
    for p, a in s.get("a", {}).items():
        z = z + a * r ** p
        dz = dz + p * a * r ** (p - 1)
    return z, dz


def phase(s, x, y):
    m, R, A = s["phase"]
    rho2 = (x * x + y * y) / (R * R)
    phi = sum(a * rho2 ** (i + 1) for i, a in enumerate(A))
    dphi_drho2 = sum((i + 1) * a * rho2 ** i for i, a in enumerate(A))
    # d rho2 / dx = 2 x / R^2
    return m, phi, dphi_drho2 * 2.0 * x / (R * R), dphi_drho2 * 2.0 * y / (R * R)


def intersect(s, p, d):
    """Ray parameter t of p + t d on surface s (Newton from the vertex plane)."""
    t = (s["z"] - p[:, 2]) / d[:, 2]
    for _ in range(60):
        x = p + t[:, None] * d
        r = np.hypot(x[:, 0], x[:, 1])
        z, dz = sag(s, r)
        g = x[:, 2] - s["z"] - z
        with np.errstate(invalid="ignore", divide="ignore"):
            drdt = np.where(r > 0, (x[:, 0] * d[:, 0] + x[:, 1] * d[:, 1]) / np.where(r > 0, r, 1.0), 0.0)
        t = t - g / (d[:, 2] - dz * drdt)
    return t


def trace(surfaces, p, d, opl, n0, lam_mm):
    """Trace rays (p, d: (N, 3); opl: (N,)) through ``surfaces`` starting in index n0. Returns p, d, opl at
    the last surface (after its interaction)."""
    p, d, opl = p.copy(), d.copy(), opl.copy()
    n = n0
    for s in surfaces:
        t = intersect(s, p, d)
        p = p + t[:, None] * d
        opl = opl + n * t
        r = np.hypot(p[:, 0], p[:, 1])
        _, dz = sag(s, r)
        with np.errstate(invalid="ignore", divide="ignore"):
            ux = np.where(r > 0, p[:, 0] / np.where(r > 0, r, 1.0), 0.0)
            uy = np.where(r > 0, p[:, 1] / np.where(r > 0, r, 1.0), 0.0)
        N = np.stack([-dz * ux, -dz * uy, np.ones_like(r)], 1)
        N /= np.linalg.norm(N, axis=1)[:, None]
        N *= np.sign(np.sum(N * d, 1))[:, None]
        # tangent frame: e1 perpendicular to N and y, e2 = N x e1
        e1 = np.cross(np.array([0.0, 1.0, 0.0]), N)
        e1 /= np.linalg.norm(e1, axis=1)[:, None]
        e2 = np.cross(N, e1)
        k1 = n * np.sum(d * e1, 1)
        k2 = n * np.sum(d * e2, 1)
        if s.get("phase") is not None:
            m, phi, gx, gy = phase(s, p[:, 0], p[:, 1])
            f = m * lam_mm / (2.0 * np.pi)
            k1 = k1 + f * (gx * e1[:, 0] + gy * e1[:, 1])
            k2 = k2 + f * (gx * e2[:, 0] + gy * e2[:, 1])
            opl = opl + f * phi
        n2 = s["n"]
        kn = np.sqrt(n2 * n2 - k1 * k1 - k2 * k2)
        d = (k1[:, None] * e1 + k2[:, None] * e2 + kn[:, None] * N) / n2
        n = n2
    return p, d, opl


def to_plane(p, d, opl, n, z):
    """Carry rays straight to the plane z (mm) in index n."""
    t = (z - p[:, 2]) / d[:, 2]
    return p + t[:, None] * d, d, opl + n * t
