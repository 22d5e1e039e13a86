"""The focal propagation of several single-source plans at once (:class:`PackedFocalPropagator`).

Each source keeps its own plan (wave-plane pitch and grid, sensor-side pitch, grid and FFT length, fitted
transfer, taper, output nodes: :class:`rwwarp.wave.focal.FocalPropagator`); the sources are stacked on the leading
(source) axis of the operator's matrices, so their products and adjoints run as batched matrix products
(``xp.matmul`` over the source axis), whatever their shapes: every factor is padded to the group's largest
grids with zeros. Step 1 is the focal operator's own separable sum (zero rows past a member's sensor-side
grid, zero columns past its wave-plane grid). Step 2's zero-padded FFT of the sensor-side field is written as
the equal matrix DFT ``W v W^T`` (``W[m, j] = exp(-2 pi i m j / n_fft)``, the member's own ``n_fft``; zero
rows past it), so members of different FFT lengths stack too; the remainder transfer, band limit and output
factors are each member's own (zero past its FFT length and its output nodes). The padding adds exact zeros
to each sum, so a member's result is its operator's up to the order of the floating-point sums (the DFT
against the FFT: ~1e-15 relative). :func:`focal_groups` splits a set of members where padding would waste
too much work. Units: mm, cycles/mm, radians; arrays numpy (CPU) or CuPy (CUDA).
"""
from __future__ import annotations

import numpy as np

from .sensor_grid import gauss_nodes_xy

from .focal import (
    _cis, distance_factors, focal_adjoint, focal_distance_derivative, sensor_taper, spectrum_to_nodes,
    transfer_curvature,
)

__all__ = ["PackedFocalPropagator", "focal_groups", "member_nodes", "member_order_tables"]

#: Output node coordinates ``(nx, ny)`` (mm) of a single-source focal RayWave (its patch's Gauss-Legendre nodes)
member_nodes = gauss_nodes_xy


def _work(n: int, ns: int, nf: int, m: int) -> int:
    """Complex multiply-adds of one source's forward: step 1 (two products), the matrix DFT, the output DFT."""
    return n * n * ns + n * ns * ns + nf * ns * (ns + nf) + nf * m * (nf + m)


def _shape(rw):
    pl = rw.plan
    return int(pl.n_grid), int(pl.n_sensor), int(pl.n_sensor_fft), int(rw.size) * int(rw.gauss_nodes)


def focal_groups(members, waste: float = 1.5) -> list:
    """Indices of ``members`` (single-source focal RayWaves) stacked into one :class:`PackedFocalPropagator`
    each: largest first, a member joins the open group while padding it to the group's largest grids
    (wave plane, sensor side, FFT length, output nodes) grows its work (:func:`_work`: the matrix products of
    one forward) by at most ``waste`` times. Returns a list of index lists (each sorted) covering every
    member once, in the order of their first member."""
    if not waste >= 1.0:
        raise ValueError(f"focal_groups: waste must be >= 1, got {waste!r}")
    for k, m in enumerate(members):
        if m.nsrc != 1 or m.plan.method != "focal":
            raise ValueError(f"focal_groups: member {k} is not a single-source focal RayWave")
    shapes = [_shape(m) for m in members]
    order = sorted(range(len(members)), key=lambda k: (-_work(*shapes[k]), k))
    groups, cur, top = [], [], None
    for k in order:
        if cur:
            pad = tuple(max(a, b) for a, b in zip(top, shapes[k]))
            if _work(*pad) <= waste * _work(*shapes[k]):
                cur.append(k)
                top = pad
                continue
            groups.append(sorted(cur))
        cur, top = [k], shapes[k]
    if cur:
        groups.append(sorted(cur))
    return sorted(groups, key=lambda g: g[0])


def _fft_freqs(n_fft, pitch_mm, width: int) -> np.ndarray:
    """``numpy.fft.fftfreq(n_fft[k], pitch_mm[k])`` (cycles/mm) of every member in row ``k`` of an (S, ``width``)
    array, zero past its own ``n_fft[k]`` (the same arithmetic: index ``m``, or ``m - n`` past ``(n - 1) // 2``,
    times ``1 / (n d)``)."""
    n = np.asarray(n_fft, dtype=np.int64)[:, None]
    m = np.arange(int(width))[None, :]
    idx = np.where(m <= (n - 1) // 2, m, m - n)
    val = 1.0 / (n[:, 0] * np.asarray(pitch_mm, dtype=np.float64))
    return np.where(m < n, idx * val[:, None], 0.0)


class PackedFocalPropagator:
    """The focal propagation (:class:`~rwwarp.wave.focal.FocalPropagator`) of several sources at one distance, each
    with its own wave-plane pitch and grid, sensor-side pitch, grid and FFT length, transfer, taper and output
    nodes, stacked and zero-padded as the module docstring says. Fields in and gradients out are (S, n, n),
    ``n`` the largest wave-plane grid (a member's samples past its own grid must be zero on the way in; they
    come out zero); outputs (S, M, M), ``M`` the most output nodes per side (zero past a member's own).

    Parameters (per source ``S``; lengths mm): ``origin_mm`` (S, 2); ``pitch_mm`` (S,); ``n_grid`` (S,) ints;
    ``wavelength_mm`` (S,) in the image medium; ``distance_mm`` float; ``carrier_cpmm`` (S, 2);
    ``sensor_origin_mm`` (S, 2); ``sensor_pitch_mm`` (S,); ``n_sensor`` (S,) ints; ``n_fft`` (S,) ints;
    ``nodes_x_mm``, ``nodes_y_mm``: per source (M_k,) arrays; ``transfer``: per source None or ``(g, q)``
    ((2,) each); ``taper_guard_mm``: per source None or float; ``precision`` of step 1's products as
    :class:`~rwwarp.wave.focal.FocalPropagator` (step 2 in complex128). :meth:`from_members` reads them from
    single-source focal RayWaves."""

    def __init__(self, origin_mm, pitch_mm, n_grid, wavelength_mm, distance_mm, carrier_cpmm, sensor_origin_mm,
                 sensor_pitch_mm, n_sensor, n_fft, nodes_x_mm, nodes_y_mm, xp=np, transfer=None,
                 taper_guard_mm=None, precision="double"):
        self.xp = xp
        origin = np.asarray(origin_mm, dtype=np.float64).reshape(-1, 2)
        S = origin.shape[0]
        per = lambda v, dt: np.broadcast_to(np.asarray(v, dtype=dt), (S,)).copy()
        h, hs = per(pitch_mm, np.float64), per(sensor_pitch_mm, np.float64)
        n_k, ns_k, nf_k = per(n_grid, np.int64), per(n_sensor, np.int64), per(n_fft, np.int64)
        nodes_x = [np.asarray(v, dtype=np.float64).reshape(-1) for v in nodes_x_mm]
        nodes_y = [np.asarray(v, dtype=np.float64).reshape(-1) for v in nodes_y_mm]
        if len(nodes_x) != S or len(nodes_y) != S:
            raise ValueError(f"PackedFocalPropagator: nodes_x_mm and nodes_y_mm need one array per source ({S})")
        if np.any(ns_k > nf_k) or np.any(ns_k < 1) or np.any(n_k < 1):
            raise ValueError(f"PackedFocalPropagator: grids must be >= 1 and n_sensor <= n_fft; got n_grid "
                             f"{n_k.tolist()}, n_sensor {ns_k.tolist()}, n_fft {nf_k.tolist()}")
        lam = per(wavelength_mm, np.float64)
        z = float(distance_mm)
        if not z > 0:
            raise ValueError(f"distance_mm must be > 0 (wave plane before the sensor), got {z}")
        f_c = np.asarray(carrier_cpmm, dtype=np.float64).reshape(S, 2)
        s0 = np.asarray(sensor_origin_mm, dtype=np.float64).reshape(S, 2)
        inv_lam = 1.0 / lam
        w_c, g, q = transfer_curvature(f_c, inv_lam)
        transfer = [None] * S if transfer is None else list(transfer)
        guards = [None] * S if taper_guard_mm is None else list(taper_guard_mm)
        if len(transfer) != S or len(guards) != S:
            raise ValueError(f"PackedFocalPropagator: transfer and taper_guard_mm need one entry per source ({S})")
        for k, tk in enumerate(transfer):
            if tk is not None:   # a fitted quadratic (rwwarp.wave.plan.fit_quadratic_transfer), per source
                g[k] = np.asarray(tk[0], dtype=np.float64).reshape(2)
                q[k] = np.asarray(tk[1], dtype=np.float64).reshape(2)
                if not np.all(q[k] < 0):
                    raise ValueError(f"transfer of source {k}: the quadratic coefficients q must be negative")
        N, NS, NF = int(n_k.max()), int(ns_k.max()), int(nf_k.max())
        M = max(max(len(v) for v in nodes_x), max(len(v) for v in nodes_y))
        self.S, self.n, self.ns, self.nf, self.m = S, N, NS, NF, M
        self.pitch, self.spitch = h, hs
        self.n_grids, self.n_sensors, self.n_ffts = n_k, ns_k, nf_k
        self.n_nodes = [(len(a), len(b)) for a, b in zip(nodes_x, nodes_y)]
        xs = origin[:, None, :] + np.arange(N)[None, :, None] * h[:, None, None]
        ps = s0[:, None, :] + np.arange(NS)[None, :, None] * hs[:, None, None]
        if precision not in ("double", "single"):
            raise ValueError(f"precision must be 'double' or 'single', got {precision!r}")
        self.precision = precision
        # ---- the factors that do not depend on the distance, built once (at_distance shares them)
        row_in = np.arange(NS)[None, :] < ns_k[:, None]          # (S, NS): a member's own sensor-side rows
        col_in = np.arange(N)[None, :] < n_k[:, None]            # (S, N): its own wave-plane samples
        taper = np.ones((2, S, NS))
        tapered = [k for k, gk in enumerate(guards) if gk is not None]
        if tapered:
            # the taper over each member's own sensor-side grid (its ends set it), the members at once
            kk = np.array(tapered)
            gk = np.array([float(guards[k]) for k in tapered])
            for ax, nodes in enumerate((nodes_x, nodes_y)):
                lo = np.array([nodes[k].min() for k in tapered]) - gk
                hi = np.array([nodes[k].max() for k in tapered]) + gk
                taper[ax, kk] = sensor_taper(ps[kk, :, ax], lo, hi, n_own=ns_k[kk])
        self._host = {"origin": origin, "s0": s0, "g": g, "q": q, "row_in": row_in, "col_in": col_in,
                      "taper": np.where(row_in[None], taper, 0.0)}
        # step 2 per source: its own FFT length and sensor pitch set its frequencies and padding room
        f_in = np.arange(NF)[None, :] < nf_k[:, None]                      # (S, NF): a member's own frequencies
        nu_h = _fft_freqs(nf_k, hs, NF)
        # output factors' offsets from each member's sensor origin (zero past a member's nodes)
        d_out, ok_out = [], []
        for ax, nodes in enumerate((nodes_x, nodes_y)):
            d = np.zeros((S, M))
            ok = np.zeros((S, M), dtype=bool)
            for k, v in enumerate(nodes):
                d[k, :len(v)] = v - s0[k, ax]
                ok[k, :len(v)] = True
            d_out.append(d)
            ok_out.append(ok)
        # every small host array in one copy to the device (rwwarp.device_upload.upload_arrays); the geometry
        # (wave-plane and sensor-side grids, transfer gradient) kept there for every distance's factors
        from ..device_upload import upload_arrays
        (nf_d, f_in_d, row_in_d, nu, f_c_d, inv_lam_d, g_d, q_d, w_c_d, room_d, dx_d, dy_d, okx_d, oky_d, xs_d,
         ps_d) = upload_arrays(xp, [nf_k, f_in, row_in, nu_h, f_c, inv_lam, g, q, w_c, (nf_k - ns_k) * hs,
                                    d_out[0], d_out[1], ok_out[0], ok_out[1], xs, ps])
        self._dev = {"xs": xs_d, "ps": ps_d, "g": g_d}
        self._toe = xp.arange(NS)[:, None] - xp.arange(N)[None, :] + (N - 1)
        # the zero-padded FFT as a matrix: W[m, j] = exp(-2 pi i (m j mod nf) / nf) (exact integer phase index)
        # (formed on the operator's device from index vectors: no (S, nf, ns) host array or copy)
        nfd = nf_d[:, None, None]
        mj = (xp.arange(NF)[:, None] * xp.arange(NS)[None, :])[None] % nfd
        W = _cis(-2.0 * np.pi * mj / nfd, xp)
        self._W = xp.where(f_in_d[:, :, None] & row_in_d[:, None, :], W, 0.0)
        fx = f_c_d[:, 0:1, None] + nu[:, None, :]
        fy = f_c_d[:, 1:2, None] + nu[:, :, None]
        arg = inv_lam_d[:, None, None] ** 2 - fx ** 2 - fy ** 2
        w = xp.sqrt(xp.maximum(arg, 0.0))
        nux, nuy = nu[:, None, :], nu[:, :, None]
        gx, gy = g_d[:, None, None, 0], g_d[:, None, None, 1]
        qx, qy = q_d[:, None, None, 0], q_d[:, None, None, 1]
        wg = w_c_d[:, None, None] + gx * nux + gy * nuy + 0.5 * (qx * nux ** 2 + qy * nuy ** 2)
        ws = xp.where(arg > 0, w, 1.0)
        room = room_d[:, None, None]
        # the band: propagating and (at distance z) displaced by at most the padding room,
        # |z (fx / w + g + q nu)| <= room on both axes: kept where z <= room / |slope|
        slope = xp.maximum(xp.abs(fx / ws + gx + qx * nux), xp.abs(fy / ws + gy + qy * nuy))
        self._band = {"ok": (arg > 0) & f_in_d[:, None, :] & f_in_d[:, :, None], "slope": slope, "room": room,
                      "rem": w - wg, "c": w / inv_lam_d[:, None, None]}
        # output factors: U(p) = 1/nf sum_m B_m exp(2 pi i nu_m (p - s0)) per axis, zero past a member's nodes
        def out_factor(d, ok):
            F = _cis(2.0 * np.pi * nu[:, None, :] * d[:, :, None], xp) / nf_d[:, None, None]
            return xp.where(ok[:, :, None], F, 0.0)
        self._Fx = out_factor(dx_d, okx_d)
        self._Fy = out_factor(dy_d, oky_d)
        self._set_distance(z)

    def _set_distance(self, z: float):
        """Build the factors that depend on the wave-plane-to-sensor distance ``z`` (mm): step 1's (its
        quadratic phases ``A = 1 / (z q)`` and displaced grid ``u0 = s0 + z g``), the band kept within the
        padding room, the remainder transfer and the direction cosine on that band."""
        xp, H = self.xp, self._host
        S, N, NS = self.S, self.n, self.ns
        h, hs = self.pitch, self.spitch
        self.z = z
        A = 1.0 / (z * H["q"])
        cdt = np.complex64 if self.precision == "single" else np.complex128
        # ---- step 1: FocalPropagator's factors, each source with its own pitches (focal.py gives the split)
        jj = np.arange(NS, dtype=np.float64)
        ii = np.arange(N, dtype=np.float64)
        mm = np.arange(-(N - 1), NS, dtype=np.float64)
        hc, hsc = h[:, None], hs[:, None]
        host = [A]
        for ax in range(2):
            a = np.pi * A[:, ax:ax + 1]
            u0 = H["s0"][:, ax:ax + 1] + z * H["g"][:, ax:ax + 1]
            x0 = H["origin"][:, ax:ax + 1]
            b = a * hc * hsc
            u = u0 + jj[None, :] * hsc
            x = x0 + ii[None, :] * hc
            P = -a * u * u + 2.0 * a * x0 * hsc * jj[None, :] + b * jj[None, :] ** 2 + 2.0 * a * u0 * x0
            Q = -a * x * x + 2.0 * a * u0 * hc * ii[None, :] + b * ii[None, :] ** 2
            K = -b * mm[None, :] ** 2
            amp = np.sqrt(np.abs(A[:, ax:ax + 1])) * hc
            host += [(amp * _cis(P, np) * H["taper"][ax]).astype(cdt), np.where(H["col_in"], _cis(Q, np), 0.0).astype(cdt),
                     _cis(K, np).astype(cdt)]
        # the distance's host factors in one copy to the device (rwwarp.device_upload.upload_arrays)
        from ..device_upload import upload_arrays
        Ad, *fac = upload_arrays(xp, host)
        self._geo = {"xs": self._dev["xs"], "ps": self._dev["ps"], "g": self._dev["g"], "A": Ad}
        self._E = []
        for ax in range(2):
            Pd, Qd, Kd = fac[3 * ax:3 * ax + 3]
            self._E.append(Kd[:, self._toe] * Pd[:, :, None] * Qd[:, None, :])
        self._dE = None
        bd = self._band
        keep = bd["ok"] & (z * bd["slope"] <= bd["room"])
        rem = xp.where(keep, bd["rem"], 0.0)
        self._HR = xp.where(keep, _cis(2.0 * np.pi * z * rem, xp), 0.0)
        # c = lambda' w = k_z / k, the direction cosine (pixel_values "flux"; 0 off a member's kept band)
        self._c = xp.where(keep, bd["c"], 0.0)
        self._rem = rem
        self._dHR = None

    def at_distance(self, distance_mm: float) -> "PackedFocalPropagator":
        """The same operator at another wave-plane-to-sensor distance (mm; a learning thickness moves it): a new
        operator sharing this one's distance-free factors (the matrix DFT, the output factors, the frequencies
        and band slopes), with the distance's own built (:meth:`_set_distance`)."""
        import copy
        z = float(distance_mm)
        if not z > 0:
            raise ValueError(f"distance_mm must be > 0 (wave plane before the sensor), got {z}")
        out = copy.copy(self)
        out._set_distance(z)
        return out

    @classmethod
    def from_members(cls, members, distance_mm, precision="double", xp=None):
        """The stacked operator of single-source focal RayWaves ``members`` (one group of
        :func:`focal_groups`) at the wave-plane-to-sensor distance ``distance_mm`` (mm), in the array
        namespace of their device (``xp``: numpy on the CPU, CuPy on CUDA, unless given)."""
        if xp is None:
            xp = np
            if str(members[0].device).startswith("cuda"):
                import cupy as xp
        nodes = [member_nodes(m) for m in members]
        pl = [m.plan for m in members]
        cat = lambda name: np.concatenate([np.asarray(getattr(m, name), dtype=np.float64) for m in members])
        return cls(cat("origin"), [p.pitch_mm for p in pl], [p.n_grid for p in pl],
                   cat("lam_mm") / cat("n_after"), distance_mm, cat("carrier"),
                   np.concatenate([np.asarray(m.focal["sensor_origin"], dtype=np.float64).reshape(-1, 2)
                                   for m in members]),
                   [p.sensor_pitch_mm for p in pl], [p.n_sensor for p in pl], [p.n_sensor_fft for p in pl],
                   [nd[0][0] for nd in nodes], [nd[1][0] for nd in nodes], xp=xp,
                   transfer=[m.focal.get("transfer") for m in members],
                   taper_guard_mm=[m.focal.get("taper_guard_mm") for m in members], precision=precision)

    @property
    def nbytes(self) -> int:
        """Bytes the operator holds on its device (factors of both steps, the distance-free band data
        :meth:`at_distance` shares; the distance-derivative factors once formed)."""
        arrays = [*self._E, self._W, self._HR, self._c, self._rem, self._Fx, self._Fy, *self._band.values()]
        if self._dE is not None:
            arrays += [*self._dE, self._dHR]
        return int(sum(a.nbytes for a in arrays))

    # ------------------------------------------------------------------ operator
    def _step1(self, field, ex, ey):
        xp = self.xp
        t = xp.matmul(field.astype(ex.dtype, copy=False), xp.swapaxes(ex, 1, 2))
        return xp.matmul(ey, t).astype(np.complex128, copy=False)

    def _dft2(self, v):
        """The zero-padded 2-D FFT of the sensor-side field as ``W v W^T`` (S, nf, nf)."""
        xp = self.xp
        return xp.matmul(xp.matmul(self._W, v), xp.swapaxes(self._W, 1, 2))

    def _dft2_adjoint(self, b):
        """Adjoint of :meth:`_dft2`: ``W^H b conj(W)``, (S, nf, nf) -> (S, ns, ns)."""
        xp = self.xp
        return xp.matmul(xp.matmul(xp.conj(xp.swapaxes(self._W, 1, 2)), b), xp.conj(self._W))

    def _out(self, b):
        """The output DFT (:func:`rwwarp.wave.focal.spectrum_to_nodes`), (S, nf, nf) -> (S, M, M)."""
        return spectrum_to_nodes(b, self._Fx, self._Fy, self.xp)

    def sensor_grid_field(self, field):
        """Step 1: ``V`` (S, ns, ns) on the sensor-side grids from the wave-plane fields (S, n, n)."""
        return self._step1(field, *self._E)

    def forward(self, field):
        """Complex field at the output nodes, (S, M, M) (up to a constant phase per source; zero past a
        member's own nodes)."""
        return self._out(self._dft2(self.sensor_grid_field(field)) * self._HR)

    def forward_pair(self, field):
        """``(U, U_w)`` at the output nodes, (S, M, M) each: :meth:`forward` and the field of the sensor-plane
        spectrum weighted by the direction cosine ``c = k_z / k`` (pixel_values "flux", as
        :meth:`rwwarp.wave.focal.FocalPropagator.forward_pair`)."""
        b = self._dft2(self.sensor_grid_field(field)) * self._HR
        return self._out(b), self._out(b * self._c)

    def _distance_factors(self):
        """d/dz of the step-1 factors and of ``H_R`` at fixed grids, band masks and carriers
        (:func:`rwwarp.wave.focal.distance_factors`, built once)."""
        if self._dE is None:
            self._dE, self._dHR = distance_factors(self._E, self._geo, self.z, self._HR, self._rem)
        return self._dE, self._dHR

    def distance_derivative(self, field):
        """``dU/dz`` (S, M, M): the exact derivative of :meth:`forward` with respect to the distance (grids,
        band masks and carriers held fixed; :func:`rwwarp.wave.focal.focal_distance_derivative`)."""
        return focal_distance_derivative(field, self._E, self._HR, self._c, self._Fx, self._Fy,
                                         *self._distance_factors(), self._dft2, False, self.xp)

    def distance_derivative_pair(self, field):
        """``(dU/dz, dU_w/dz)``: the exact distance derivatives of :meth:`forward_pair` (the weight ``c`` does not
        depend on the distance)."""
        return focal_distance_derivative(field, self._E, self._HR, self._c, self._Fx, self._Fy,
                                         *self._distance_factors(), self._dft2, True, self.xp)

    def adjoint(self, grad):
        """Adjoint of :meth:`forward` (the conjugate-transpose linear map), (S, M, M) -> (S, n, n)
        (:func:`rwwarp.wave.focal.focal_adjoint`)."""
        return focal_adjoint(grad, None, self._E, self._HR, self._c, self._Fx, self._Fy, self._dft2_adjoint, self.xp)

    def adjoint_pair(self, grad_u, grad_w):
        """Adjoint of :meth:`forward_pair`: the field's gradient from those of ``U`` and ``U_w`` (S, M, M) each
        (torch's convention), (S, n, n)."""
        return focal_adjoint(grad_u, grad_w, self._E, self._HR, self._c, self._Fx, self._Fy, self._dft2_adjoint,
                             self.xp)


# ---------------------------------------------------------------------------------------------------------------
# A batch of single-source focal plans run together (rwwarp.wave.packed.PackedRayWave: maps, kept batches)

def _profile(m):
    """The DOE profile a single-source focal member's plan applies (None: no DOE, or a blank one)."""
    return m.focal["profile"]


def packed_doe_phase(members, n: int, xp=np):
    """The unwrapped DOE phase phi0 (rad, at the DOE's design wavelength) on each member's wave-plane window,
    (S, n, n) in the array namespace ``xp`` (computed there: on CUDA no host grid is formed or copied), ``n`` the
    batch's slot side (samples past a member's own grid are computed but multiply zeros). Rows are y, columns x,
    as :meth:`rwwarp.wave.raywave.RayWave.doe_orders_factor`. None when no member has a DOE profile; a
    :class:`TypeError` for a profile without a smooth kind (a pixel map): such members run alone."""
    profs = [_profile(m) for m in members]
    if all(p is None for p in profs):
        return None
    p0 = profs[0]
    if any(p is None for p in profs) or not hasattr(p0, "kind") or not hasattr(p0, "values"):
        raise TypeError("packed_doe_phase: the members need one smooth DOE profile")
    from .doe_phase import profile_phase
    s = members[0].lens.surfaces[members[0].plane]
    origin = np.concatenate([np.asarray(m.origin, dtype=np.float64).reshape(-1, 2) for m in members])
    pitch = np.array([m.plan.pitch_mm for m in members], dtype=np.float64)
    g = xp.asarray(np.arange(n, dtype=np.float64)[None, :] * pitch[:, None])     # (S, n) mm
    ox, oy = xp.asarray(origin[:, 0]), xp.asarray(origin[:, 1])
    x = ox[:, None, None] + g[:, None, :]
    y = oy[:, None, None] + g[:, :, None]
    return profile_phase(p0.kind, p0.values, x, y, norm_radius=p0.norm_radius,
                         design_wavelength_um=s.design_wavelength_um, xp=xp)


def member_order_tables(members, blank=None):
    """The host tables (:func:`rwwarp.wave.focal.order_tables`) of single-source focal RayWaves' kept DOE orders
    (each plan's ``focal["orders"][0]``) and chief-ray wrap zones (``focal["central_zone"][0]``), for
    :func:`rwwarp.wave.focal.batch_order_series`. ``blank``: ``blank(member)``, the orders standing for a DOE a
    member's plan has no profile for (torch_bridge: a blank DOE about to learn, ``[(alpha, 1)]``,
    ``exp(1j alpha phi0)`` with ``alpha`` the wavelength remap; no zone); without it such a member is an error."""
    from .focal import order_tables
    orders, zones = [], []
    for k, m in enumerate(members):
        if m.focal["profile"] is None:
            if blank is None:
                raise ValueError(f"member_order_tables: member {k}'s plan has no DOE profile")
            orders.append(blank(m))
            zones.append(None)
            continue
        orders.append(m.focal["orders"][0])
        z = m.focal.get("central_zone")
        zones.append(None if z is None else z[0])
    return order_tables(orders, zones)


#: Bytes the stacked operators and wave-plane arrays of one group may hold at once (:func:`run_focal_members` splits
#: a group above it): the members' own path holds one member's at a time, a stack its group's together, so a batch
#: on the stacked path may use up to this much beyond the largest member's propagation that its memory plan counts
#: (:func:`rwwarp.wave.packed.packed_bytes`).
STACK_MAX_BYTES = 2 << 30


def stacked_bytes(shape, count: int) -> int:
    """Bytes of ``count`` members stacked in one :class:`PackedFocalPropagator` padded to ``shape`` = (wave-plane
    grid, sensor-side grid, FFT length, output nodes a side) (:func:`_shape`): step 1's two factors, the matrix DFT,
    the transfer and band arrays, the output factors and the forward's work arrays, complex128; and the group's
    wave-plane arrays, ``6 n^2`` complex128 a member (its field slice, the DOE phase, ``exp(i phi0)``, the order sum
    and the modulated field: :func:`run_focal_members`), which dominate where the grid is large (the Cooke hybrid's
    ~2300^2: 0.5 GB a member)."""
    n, ns, nf, m = (int(v) for v in shape)
    return int(count) * 16 * (2 * ns * n + nf * ns + 6 * nf * nf + 2 * m * nf + m * m + ns * ns + 6 * n * n)


def _chunks(group, shapes, max_bytes):
    """``group`` (indices) split in order so that each part's stacked operators stay within ``max_bytes``."""
    out, cur, top = [], [], None
    for k in group:
        pad = shapes[k] if top is None else tuple(max(a, b) for a, b in zip(top, shapes[k]))
        if cur and stacked_bytes(pad, len(cur) + 1) > max_bytes:
            out.append(cur)
            cur, pad = [], shapes[k]
        cur.append(k)
        top = pad
    if cur:
        out.append(cur)
    return out


def run_focal_members(members, u_all, precision: str, keep: dict | None = None, waste: float = 1.5,
                      max_bytes: int = STACK_MAX_BYTES) -> list:
    """Pixel values (not normalised; each (1, size, size), in the order of ``members``) of single-source focal
    RayWaves (one lens, patch size and pixel, no wave step) from their wave-plane fields ``u_all`` ((S, n, n),
    member k's field in row k, zero past its own grid; numpy or CuPy), propagated as a few stacked operators
    (:class:`PackedFocalPropagator`, members grouped by their Gauss node count and :func:`focal_groups`), each
    group's DOE transmission in one batch (:func:`packed_doe_phase`, :func:`member_order_tables`,
    :func:`rwwarp.wave.focal.batch_order_series`). Each
    member's values are its own :meth:`~rwwarp.wave.raywave.RayWave.focal_intensity` up to the order of the
    floating-point sums. ``keep``: a dict in which the operators and DOE factors are kept for the next run with
    the same members (a kept batch), else built for this run only. ``max_bytes``: a group whose stacked operators
    would hold more (:func:`stacked_bytes`) is run in parts within it (a member alone may exceed it: its own plan
    was checked against the memory budget). Arrays stay where ``u_all`` is."""
    from .focal import batch_order_series, pixel_flux, pixel_power
    xp = np if isinstance(u_all, np.ndarray) else __import__("cupy")
    m0 = members[0]
    z = float(m0.z_sensor - m0.z_plane)
    by_nodes = {}
    for k, m in enumerate(members):
        by_nodes.setdefault(int(m.gauss_nodes), []).append(k)
    out = [None] * len(members)
    shapes = [_shape(m) for m in members]
    parts = []
    for gn, idx in by_nodes.items():
        for sub in focal_groups([members[k] for k in idx], waste):
            parts += [(gn, c) for c in _chunks([idx[i] for i in sub], shapes, max_bytes)]
    for gn, g in parts:
        ms = [members[k] for k in g]
        key = (tuple(g), precision, z)
        hit = None if keep is None else keep.get(key)
        n = max(int(m.plan.n_grid) for m in ms)
        if hit is None:
            op = PackedFocalPropagator.from_members(ms, z, precision, xp)
            phi0 = packed_doe_phase(ms, n, xp)
            fac = None if phi0 is None else batch_order_series(phi0, member_order_tables(ms), xp)
            hit = (op, fac, xp.asarray(np.array(g)))
            if keep is not None:
                keep[key] = hit
        op, fac, rows = hit
        u = u_all[rows, :n, :n]
        if fac is not None:
            u = u * fac
        if m0.pixel_values == "flux":
            vals = pixel_flux(*op.forward_pair(u), gn, m0.pixel, m0.size, xp=xp)
        else:
            vals = pixel_power(op.forward(u), gn, m0.pixel, m0.size, xp=xp)
        for i, k in enumerate(g):
            out[k] = vals[i:i + 1]
    return out
