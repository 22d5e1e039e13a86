"""Pupil sampling: the stratified pupil grids the tracer starts rays on, and the exact rim cells of a
circular pupil (the fraction of each grid cell inside the unit disc and the centroid of that part), with
their host and device caches. Coordinates are normalised pupil units over [-1, 1]^2.
"""
from __future__ import annotations

import functools
import threading
from collections import OrderedDict

import numpy as np

from .kernels import trace as ktrace


def disc_cell_fractions(n: int) -> np.ndarray:
    """Fraction of each cell of the ``n x n`` cell grid over [-1, 1]^2 (row-major, rows +v) that lies in
    the unit disc, exactly: 1 inside, 0 outside, and for a cell the circle crosses the integral over x of
    the chord ``min(y1, s) - max(y0, -s)`` (``s = sqrt(1 - x^2)``), split where it changes form and
    integrated with ``int s dx = (x s + asin x) / 2``. The ray-wave field weights its rim rays by it
    (:func:`disc_cells`): a staircase aperture errs by O(cell) at the rim."""
    return _disc_cell_fractions(int(n)).copy()


@functools.lru_cache(maxsize=16)
def _disc_cell_fractions(n: int) -> np.ndarray:
    h = 2.0 / n
    g = -1.0 + h * np.arange(n)                      # lower cell edges
    g1 = g + h                                       # upper cell edges
    # per axis: the nearest |x| in a cell (0 if it spans 0) and the farthest |x|^2; a cell's nearest and
    # farthest squared radius are sums over the two axes (an outer sum: rows +v, columns +u)
    near2 = (np.minimum(np.abs(g), np.abs(g1)) * (g * g1 > 0)) ** 2
    far1 = np.maximum(np.abs(g), np.abs(g1)) ** 2
    far = far1[None, :] + far1[:, None]
    out = np.where(far <= 1.0, 1.0, 0.0).ravel()
    cut = (near2[None, :] + near2[:, None] < 1.0) & (far > 1.0)
    k = np.flatnonzero(cut)                          # the cells the circle crosses
    if k.size:
        row, col = np.divmod(k, n)
        a, b, c, d = g[col], g1[col], g[row], g1[row]

        def F(x):   # int sqrt(1 - x^2) dx
            x = np.clip(x, -1.0, 1.0)
            return 0.5 * (x * np.sqrt(1.0 - x * x) + np.arcsin(x))

        rc = np.sqrt(np.clip(1.0 - c * c, 0.0, None))
        rd = np.sqrt(np.clip(1.0 - d * d, 0.0, None))
        knots = np.stack([a, b, -rc, rc, -rd, rd, -np.ones_like(a), np.ones_like(a)], 1)
        knots = np.sort(np.clip(knots, a[:, None], b[:, None]), axis=1)
        lo, hi = knots[:, :-1], knots[:, 1:]
        xm = 0.5 * (lo + hi)
        sm = np.sqrt(np.clip(1.0 - xm * xm, 0.0, None))
        cc, dd = c[:, None], d[:, None]
        # on each piece the chord is (s or d) - (-s or c), or nothing: integrate each term exactly
        live = (hi > lo) & (np.abs(xm) < 1.0) & (np.minimum(dd, sm) > np.maximum(cc, -sm))
        si = F(hi) - F(lo)
        width = hi - lo
        area = np.where(sm < dd, si, dd * width) + np.where(-sm > cc, si, -cc * width)
        out[k] = np.sum(np.where(live, area, 0.0), axis=1) / (h * h)
    return np.clip(out, 0.0, 1.0)


def _nbytes(a) -> int:
    """Bytes of a numpy array or a Warp array (``capacity``)."""
    return int(a.nbytes) if hasattr(a, "nbytes") else int(a.capacity)


class _BytesLRU:
    """A least-recently-used cache bounded by the bytes of its values (``nbytes``), thread-safe. The rim
    cells of a pupil grid cost tens of ms to make; a design step plans each source's own grid (dozens of
    sizes), which a cache of a fixed number of entries cycles through without a hit."""

    def __init__(self, max_bytes: int):
        self.max_bytes = int(max_bytes)
        self._d = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()

    def get(self, key, make):
        with self._lock:
            v = self._d.get(key)
            if v is not None:
                self._d.move_to_end(key)
                return v
        v = make()
        with self._lock:
            if key not in self._d:
                self._d[key] = v
                self._bytes += _nbytes(v)
                while len(self._d) > 1 and self._bytes > self.max_bytes:
                    _, old = self._d.popitem(last=False)
                    self._bytes -= _nbytes(old)
        return v


#: Host bytes kept of :func:`disc_cells` results, and device bytes of their copies (per process; a
#: 1400^2 pupil grid's cells take 47 MB; a miss on the device costs an upload, one on the host tens of ms).
RIM_CACHE_HOST_BYTES = 1 << 30
RIM_CACHE_DEVICE_BYTES = 1 << 28
_DISC_CELLS = _BytesLRU(RIM_CACHE_HOST_BYTES)
_RIM_CELLS = _BytesLRU(RIM_CACHE_DEVICE_BYTES)   # (device, n) -> the device array of disc_cells(n)


def disc_cells(n: int) -> np.ndarray:
    """Per cell of the ``n x n`` grid over [-1, 1]^2 (row-major, rows +v): ``(f, du, dv)``, the fraction
    of the cell inside the unit disc (:func:`disc_cell_fractions`, exact) and the offset (normalised pupil
    units) from the cell's centre to the centroid of that part (0 for whole cells; from a 24 x 24
    sub-grid of each cell the circle crosses; for a sliver no sub-sample falls in, the cell's point nearest
    the disc's centre). A rim ray starts at that centroid, inside the disc, so
    that a clear aperture which is the disc's image does not clip it. Read-only (cached, see
    :data:`RIM_CACHE_HOST_BYTES`)."""
    return _DISC_CELLS.get(int(n), lambda: _make_disc_cells(int(n)))


def _make_disc_cells(n: int) -> np.ndarray:
    f = _disc_cell_fractions(n)
    out = np.zeros((n * n, 3))
    out[:, 0] = f
    part = np.flatnonzero((f > 0.0) & (f < 1.0))
    if part.size:
        h = 2.0 / n
        m = 24
        t = ((np.arange(m) + 0.5) / m - 0.5) * h
        su, sv = np.meshgrid(t, t, indexing="xy")
        su, sv = su.ravel(), sv.ravel()
        row, col = np.divmod(part, n)
        cu = -1.0 + (2.0 * col + 1.0) / n
        cv = -1.0 + (2.0 * row + 1.0) / n
        for a in range(0, part.size, 512):
            b = slice(a, a + 512)
            uu = cu[b, None] + su[None, :]
            vv = cv[b, None] + sv[None, :]
            ins = (uu * uu + vv * vv <= 1.0)
            cnt = np.maximum(ins.sum(1), 1)
            du = (su[None, :] * ins).sum(1) / cnt
            dv = (sv[None, :] * ins).sum(1) / cnt
            # a sliver no sub-sample falls in: the cell's point nearest the disc's centre (inside the disc,
            # since the disc meets the cell)
            none = ins.sum(1) == 0
            du = np.where(none, np.clip(-cu[b], -0.5 * h, 0.5 * h), du)
            dv = np.where(none, np.clip(-cv[b], -0.5 * h, 0.5 * h), dv)
            out[part[b], 1] = du
            out[part[b], 2] = dv
    out.setflags(write=False)
    return out


def pupil_grid(n: int, shape: str = "circle", jitter: float = 0.0, seed: int = 0, layout: str = "centers",
               clip: bool = True):
    """Deterministic stratified pupil samples in normalised coordinates.

    A square ``n x n`` grid over [-1, 1]^2 (``layout="centers"``: cell centres, ``"edges"``: including
    the edges, Zemax style), optionally jittered within each cell by ``jitter`` (0..1, fraction of the
    cell), clipped to the unit circle (``shape="circle"``) or kept whole (``"square"``).
    Returns ``(u, v, cell_area)``: arrays of accepted samples and the normalised area per sample.
    """
    if n < 1:
        raise ValueError(f"pupil grid needs n >= 1, got {n}")
    if layout == "centers":
        g = -1.0 + (2.0 * np.arange(n) + 1.0) / n
        cell = 2.0 / n
    elif layout == "edges":
        g = np.linspace(-1.0, 1.0, n) if n > 1 else np.zeros(1)
        cell = 2.0 / max(n - 1, 1)
    else:
        raise ValueError(f"layout must be 'centers' or 'edges', got {layout!r}")
    u, v = np.meshgrid(g, g, indexing="xy")
    u, v = u.ravel(), v.ravel()
    if jitter:
        rng = np.random.default_rng(seed)
        u = u + jitter * cell * (rng.random(u.size) - 0.5)
        v = v + jitter * cell * (rng.random(v.size) - 0.5)
    if shape == "circle" and clip:
        keep = u * u + v * v <= 1.0 + ktrace.EDGE_RTOL  # the kernels' tolerance (kernels.trace.EDGE_RTOL)
        u, v = u[keep], v[keep]
    return u, v, cell * cell


def device_disc_cells(n: int, device: str):
    """:func:`disc_cells` of an ``n x n`` pupil grid as a Warp array of ``wp.vec3d`` on ``device`` (made once
    per grid size and device, shared by the process, up to :data:`RIM_CACHE_DEVICE_BYTES`; read-only)."""
    import warp as wp
    return _RIM_CELLS.get((str(device), int(n)),
                          lambda: wp.array(np.ascontiguousarray(disc_cells(n)), dtype=wp.vec3d, device=device))
