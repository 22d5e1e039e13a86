"""``direct``: brute-force Rayleigh-Sommerfeld summation (first kind) from the wave-plane samples to the
sensor pixels' Gauss nodes, a reference that shares no FFT code with ``asm`` or ``focal``.

For a field ``U0`` on the plane z = 0 (zero outside the window) the field at ``P = (X, Y, z)`` is

    U(P) = integral U0(x, y) G(r) dx dy,   G = z (1 - i k r) exp(i k r) / (2 pi r^3),

``r = |P - (x, y, 0)|``, ``k = 2 pi n / lambda`` (the medium after the plane); the integral is the sum over the
samples times ``pitch^2`` (the samples' carrier restored first: the true field). Its distance derivative is the
exact ``dG/dz = exp(i k r) [(1 - i k r) / r^3 + z^2 (k^2 / r^2 - 3 (1 - i k r) / r^4) / r] / (2 pi)``, and the flux
weight ``U_w = (dU/dz) / (i k)`` (the field of the spectrum times the direction cosine ``k_z / k``), so a pixel's
flux ``Re(conj(U) U_w)`` needs no FFT either. The DOE phase goes in with the field, as the ASM's.

Cost O(N^2 M^2) per source (N^2 samples, M^2 nodes): small cases only. Same window plan as the ASM
(:func:`rwwarp.wave.methods.asm.plan_window`; its FFT length unused). Lengths in mm.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from .asm import plan_window, wave_plane_cost
from .registry import Planned, Propagation, gauss_nodes_xy, register

#: complex kernel entries formed at a time (nodes x samples): bounds the summation's temporary memory
CHUNK = 2 ** 20
#: flops per kernel entry and output (distance, exponential, the 1 - i k r factor, one complex multiply-add)
FLOPS_PER_ENTRY = 60.0


class DirectOperator:
    """The Rayleigh-Sommerfeld sum from the windows of a :class:`~rwwarp.wave.field.WaveField` (``wave``: its
    origins, pitch, medium wavelengths, carrier and DOE phase; its samples are not read) to the nodes
    ``nodes_x_mm`` / ``nodes_y_mm`` ((S, Mx) / (S, My), mm; the output grid of each source is their product)
    ``distance_mm`` (mm) behind the plane, in the array namespace ``xp`` (numpy or CuPy), float64 throughout.
    :meth:`of` builds it for a :class:`~rwwarp.wave.raywave.RayWave` batch and its pixels' Gauss nodes."""

    def __init__(self, wave, nodes_x_mm, nodes_y_mm, distance_mm, xp=np):
        self.xp, self.nsrc = xp, wave.n_sources
        self.z = float(distance_mm)
        if not self.z > 0:
            raise ValueError(f"direct: the distance must be positive (mm), got {self.z!r}")
        self.h2 = float(wave.pitch_mm) ** 2
        self.k = 2.0 * np.pi / wave.wavelength_mm   # rad/mm in the medium
        self.xs, self.ys = wave.coordinates()         # (S, N) sample x, y
        self.nx, self.ny = np.asarray(nodes_x_mm, float), np.asarray(nodes_y_mm, float)   # (S, M) node x, y
        # the true field is samples * exp(2 pi i f_c . (x, y)) (absolute x, y), times the DOE transmission
        car = wave.carrier_cpmm
        t = np.exp(2j * np.pi * (car[:, None, None, 0] * self.xs[:, None, :] + car[:, None, None, 1] * self.ys[:, :, None]))
        if wave.doe_phase is not None:
            t = t * np.exp(1j * np.asarray(wave.doe_scale, float)[:, None, None] * np.asarray(wave.doe_phase))
        self.t = xp.asarray(t)

    @classmethod
    def of(cls, rw, distance_mm=None, xp=np):
        """The operator of a RayWave batch ``rw`` (its :meth:`~rwwarp.wave.raywave.RayWave.wave_field` layout) to
        its pixels' Gauss nodes over ``distance_mm`` (default the lens's plane-to-sensor distance)."""
        n = rw.plan.n_grid
        wave = rw.wave_field(np.zeros((rw.nsrc, n, n), np.complex128))   # the layout only: no trace
        z = float(rw.z_sensor - rw.z_plane) if distance_mm is None else float(distance_mm)
        return cls(wave, *gauss_nodes_xy(rw), z, xp)

    def _kernel(self, k, X, Y, derivative):
        """Kernel rows (m, N^2) for nodes ``X``, ``Y`` (m,) of source ``k``: G or dG/dz."""
        xp = self.xp
        dx = xp.asarray(X)[:, None, None] - xp.asarray(self.xs[k])[None, None, :]
        dy = xp.asarray(Y)[:, None, None] - xp.asarray(self.ys[k])[None, :, None]
        z, kw = self.z, self.k[k]
        r2 = dx * dx + dy * dy + z * z
        r = xp.sqrt(r2)
        e = xp.exp(1j * kw * r) * (1.0 / (2.0 * np.pi))
        a = (1.0 - 1j * kw * r) / (r2 * r)
        if not derivative:
            out = z * a * e
        else:
            out = (a + (z * z / r) * (kw * kw / r2 - 3.0 * a / r)) * e
        return out.reshape(len(X), -1)

    def _apply(self, field, derivative):
        xp = self.xp
        field = xp.asarray(getattr(field, "samples", field))
        S, My, Mx = self.nsrc, self.ny.shape[1], self.nx.shape[1]
        out = xp.empty((S, My, Mx), np.complex128)
        for k in range(S):
            X, Y = np.meshgrid(self.nx[k], self.ny[k])
            X, Y = X.ravel(), Y.ravel()
            u = (field[k] * self.t[k]).reshape(-1) * self.h2
            step = max(1, CHUNK // u.size)
            o = out[k].reshape(-1)
            for a in range(0, X.size, step):
                o[a:a + step] = self._kernel(k, X[a:a + step], Y[a:a + step], derivative) @ u
        return out

    def forward(self, field):
        """The field at the nodes (S, My, Mx) from the wave-plane field (S, n, n) or a
        :class:`~rwwarp.wave.field.WaveField` of this layout (carrier removed, wave step applied, before the DOE)."""
        return self._apply(field, False)

    def distance_derivative(self, field):
        """``d forward(field) / d distance_mm`` (S, My, Mx), exact (grids and nodes held)."""
        return self._apply(field, True)

    def adjoint(self, grad):
        """The conjugate transpose of :meth:`forward`: (S, My, Mx) -> (S, n, n)."""
        xp = self.xp
        grad = xp.asarray(grad)
        S, n = self.nsrc, self.xs.shape[1]
        out = xp.zeros((S, n * n), np.complex128)
        for k in range(S):
            X, Y = np.meshgrid(self.nx[k], self.ny[k])
            X, Y = X.ravel(), Y.ravel()
            gk = grad[k].reshape(-1)
            step = max(1, CHUNK // (n * n))
            for a in range(0, X.size, step):
                out[k] += xp.conj(self._kernel(k, X[a:a + step], Y[a:a + step], False)).T @ gk[a:a + step]
        return out.reshape(S, n, n) * xp.conj(self.t) * self.h2


@register
class Direct(Propagation):
    """Brute-force Rayleigh-Sommerfeld summation (module docstring): the reference of small cases."""

    name = "direct"
    doe_in_propagator = True

    def plan(self, ctx):
        p = plan_window(ctx)
        pl = p.plan if p.plan.method == "direct" else replace(p.plan, method="direct")
        pl = pl.with_reasons("direct: Rayleigh-Sommerfeld sum from every sample to every pixel node (the FFT "
                             "length is not used)")
        return Planned(pl, p.carrier, p.centers, p.lo, p.hi)

    def estimate(self, plan, n_sources, size, gauss_nodes):
        S, m = int(n_sources), int(size) * int(gauss_nodes)
        mem, flops = wave_plane_cost(plan, S)
        n2 = plan.n_grid ** 2
        mem += S * m * m * 16 * 3 + min(CHUNK, m * m * n2) * 16 * 8
        flops += S * 2.0 * FLOPS_PER_ENTRY * n2 * m * m
        return {"memory_bytes": int(mem), "flops": float(flops)}

    def explain_grids(self, plan):
        return super().explain_grids(plan) + "Rayleigh-Sommerfeld sum, "

    def operator(self, rw, distance_mm=None, precision="double"):
        return DirectOperator.of(rw, distance_mm, _xp(rw))

    def pixels(self, rw, field, precision="double", to_host=True):
        from ..focal import pixel_flux, pixel_power
        xp = _xp(rw)
        op = DirectOperator.of(rw, None, xp)
        field = rw.wave_stepped(xp.asarray(field))
        u = op.forward(field)
        if rw.pixel_values == "flux":
            u_w = op.distance_derivative(field) / (1j * xp.asarray(op.k)[:, None, None])
            power = pixel_flux(u, u_w, rw.gauss_nodes, rw.pixel, rw.size, xp=xp)
        else:
            power = pixel_power(u, rw.gauss_nodes, rw.pixel, rw.size, xp=xp)
        return power if (xp is np or not to_host) else xp.asnumpy(power)


def _xp(rw):
    if str(rw.device).startswith("cuda"):
        import cupy
        return cupy
    return np
