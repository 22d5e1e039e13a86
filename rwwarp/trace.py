"""Host side of the coherent ray tracer: sources, pupil sampling, one Warp launch per surface.

Kernels are in :mod:`rwwarp.kernels.trace`. Lengths in mm, wavelengths in um, field angles in
degrees. Precision (``"float64"`` default, ``"float32"``) and device (``"cpu"``, ``"cuda:0"``) are
explicit arguments.

Typical use::

    tr = Tracer(lens, wavelengths_um=[0.5876], device="cpu")
    rays = tr.trace(fields_deg=[0.0, 14.0], grid=101)           # to the sensor plane
    xy, ok = rays.numpy()["pos"][..., :2], rays.numpy()["valid"]
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from .errors import GeometryError, LensError
from .kernels import trace as ktrace
from . import paraxial

wp.config.quiet = True
wp.config.log_level = wp.LOG_WARNING  # no per-module load messages (compile time is reported by perf/)
_WP_INIT = False


def init_warp():
    """Initialise Warp once (quietly)."""
    global _WP_INIT
    if not _WP_INIT:
        wp.init()
        _WP_INIT = True


def warp_scalar(dtype: str):
    """Warp scalar type for ``"float64"`` / ``"float32"``."""
    if dtype in ("float64", np.float64, "f8"):
        return wp.float64
    if dtype in ("float32", np.float32, "f4"):
        return wp.float32
    raise ValueError(f"dtype must be 'float64' or 'float32', got {dtype!r}")


def warp_device(device: str) -> str:
    """Warp device name for an rwwarp device string (``cpu``, ``cuda``, ``cuda:N``, ``opencl:P:D`` -> cpu)."""
    if device is None or device == "cpu" or device.startswith("opencl"):
        return "cpu"
    if device == "cuda":
        return "cuda:0"
    if device.startswith("cuda"):
        return device
    raise ValueError(f"unknown device {device!r}: use 'cpu', 'cuda', 'cuda:N' or 'opencl:P:D'")


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
        keep = u * u + v * v <= 1.0 + 1e-12
        u, v = u[keep], v[keep]
    return u, v, cell * cell


@dataclass
class Rays:
    """Rays on the device (structure of arrays), ``n_sources x n_pupil`` of them, source-major."""

    pos: wp.array
    dir: wp.array
    opl: wp.array
    valid: wp.array
    wl: wp.array
    weight: wp.array
    n_sources: int
    n_pupil: int

    def numpy(self) -> dict:
        """Host copies reshaped to ``(n_sources, n_pupil, ...)``."""
        s, p = self.n_sources, self.n_pupil
        return {"pos": self.pos.numpy().reshape(s, p, 3), "dir": self.dir.numpy().reshape(s, p, 3),
                "opl": self.opl.numpy().reshape(s, p), "valid": self.valid.numpy().reshape(s, p).astype(bool),
                "weight": self.weight.numpy().reshape(s, p)}

    def count_valid(self) -> np.ndarray:
        """Number of valid rays per source."""
        return self.valid.numpy().reshape(self.n_sources, self.n_pupil).sum(axis=1)


def field_direction(field_deg) -> np.ndarray:
    """Unit propagation direction of a plane wave at field angle (x, y) degrees (direction tangents)."""
    fx, fy = _field_pair(field_deg)
    d = np.array([math.tan(math.radians(fx)), math.tan(math.radians(fy)), 1.0])
    return d / np.linalg.norm(d)


def as_field_list(fields_deg) -> list:
    """Normalise a field spec: a number (y angle), an (x, y) tuple, or a list of either -> list."""
    if np.ndim(fields_deg) == 0 or isinstance(fields_deg, tuple):
        return [fields_deg]
    return list(fields_deg)


def _field_pair(field_deg):
    if np.ndim(field_deg) == 0:
        return 0.0, float(field_deg)
    f = [float(v) for v in field_deg]
    if len(f) != 2:
        raise LensError(f"a field is a number (y angle) or an (x, y) pair in degrees, got {field_deg!r}")
    return f[0], f[1]


class Tracer:
    """Sequential coherent ray tracer for one lens (float64 by default), one launch per surface.

    Parameters
    ----------
    lens : Lens
    wavelengths_um : list of float
        Wavelengths (um) the refractive-index tables are built for; sources refer to them by index.
    device : str
        ``"cpu"`` or ``"cuda"``/``"cuda:N"``.
    dtype : str
        ``"float64"`` (default) or ``"float32"``.
    requires_grad : bool
        Allocate gradient buffers for surface parameters and rays (for ``wp.Tape``).
    """

    def __init__(self, lens, wavelengths_um, device: str = "cpu", dtype: str = "float64",
                 requires_grad: bool = False):
        init_warp()
        self.lens = lens
        self.wavelengths_um = [float(w) for w in wavelengths_um]
        self.device = warp_device(device)
        self.scalar = warp_scalar(dtype)
        self.np_dtype = np.float64 if self.scalar == wp.float64 else np.float32
        self.K = ktrace.make_trace_kernels(self.scalar)
        self.requires_grad = requires_grad
        wl0 = self.wavelengths_um[0]
        self.pupils = paraxial.pupils(lens, wl0)
        nw = len(self.wavelengths_um)
        idx = np.stack([lens.indices(w) for w in self.wavelengths_um], axis=1)  # (n_surf, n_wl)
        self.n_obj_np = np.ones(nw)
        self.index_np = idx
        self.params_np = self._surface_params()
        self.kinds = [self._kind(s) for s in lens.surfaces]
        self._upload()

    # -------------------------------------------------------------- setup
    def _kind(self, s):
        return {"standard": ktrace.KIND_REFRACT, "thin_lens": ktrace.KIND_THIN}.get(s.type, ktrace.KIND_PLANE)

    def _surface_params(self) -> np.ndarray:
        lens = self.lens
        z = lens.vertex_z
        out = np.zeros((len(lens.surfaces) + 1, ktrace.N_PARAMS))
        stop = lens.stop_index
        for i, s in enumerate(lens.surfaces):
            p = out[i]
            p[ktrace.P_Z] = z[i]
            p[ktrace.P_C] = s.curvature if s.type == "standard" else 0.0
            p[ktrace.P_K] = s.conic if s.type == "standard" else 0.0
            if s.type == "standard":
                p[ktrace.P_A0:ktrace.P_A0 + len(s.aspheric)] = s.aspheric
            sd = s.semi_diameter
            if i == stop and lens.entrance_pupil_diameter is not None:
                sd = None  # floating stop: the entrance pupil sets the beam
            p[ktrace.P_SD] = -1.0 if sd is None else sd
            p[ktrace.P_SQUARE] = 1.0 if s.shape == "square" else 0.0
            if s.type == "thin_lens":
                uinv, v = paraxial.thin_lens_conjugates(lens, self.wavelengths_um[0], i)
                p[ktrace.P_POWER] = 1.0 / s.focal_length
                p[ktrace.P_UINV] = uinv
                p[ktrace.P_V] = v
        out[-1, ktrace.P_Z] = lens.sensor_z
        out[-1, ktrace.P_SD] = -1.0
        return out

    def _upload(self):
        dev, sc, g = self.device, self.scalar, self.requires_grad
        self.params = [wp.array(p, dtype=sc, device=dev, requires_grad=g) for p in self.params_np]
        nw = len(self.wavelengths_um)
        self.n_obj = wp.array(self.n_obj_np, dtype=sc, device=dev)
        self.n_tables = [wp.array(self.index_np[i], dtype=sc, device=dev) for i in range(self.index_np.shape[0])]
        self.n_before = [self.n_obj] + self.n_tables[:-1]
        self._n_wl = nw

    def set_params(self, params_np: np.ndarray):
        """Replace the per-surface parameter table (``(n_surfaces + 1, N_PARAMS)``, last row = sensor)."""
        self.params_np = np.array(params_np, dtype=np.float64)
        self._upload()

    # -------------------------------------------------------------- sources
    def sources(self, fields_deg, wavelength_index=0, ray_aiming: bool = False, object_distance=None):
        """Per-source arrays for the generation kernel.

        ``fields_deg``: list of fields (number = y angle, or (x, y) pair), degrees.
        ``wavelength_index``: int or list (one per field). ``object_distance``: mm, default the lens's.
        Returns a dict of numpy arrays.
        """
        fields = as_field_list(fields_deg)
        n = len(fields)
        wli = np.broadcast_to(np.asarray(wavelength_index, dtype=np.int32), (n,)).copy()
        if np.any(wli < 0) or np.any(wli >= self._n_wl):
            raise LensError(f"wavelength index out of range 0..{self._n_wl - 1}: {wli}")
        od = self.lens.object_distance if object_distance is None else float(object_distance)
        pup = self.pupils
        dirs = np.zeros((n, 3))
        pos = np.zeros((n, 3))
        finite = np.zeros(n, dtype=np.int32)
        aim = np.zeros((n, 3))
        aim[:, 2] = pup.entrance_z
        for k, f in enumerate(fields):
            fx, fy = _field_pair(f)
            if not (abs(fx) < 89.0 and abs(fy) < 89.0):
                raise LensError(f"field angle must be within +-89 deg, got {f}", field=f)
            d = field_direction((fx, fy))
            dirs[k] = d
            if math.isfinite(od):
                finite[k] = 1
                dist = pup.entrance_z + od
                pos[k] = [-math.tan(math.radians(fx)) * dist, -math.tan(math.radians(fy)) * dist, -od]
        shape = self.lens.surfaces[self.lens.stop_index].shape
        half = np.full(n, pup.entrance_radius)
        src = {"pos": pos, "dir": dirs, "finite": finite, "aim": aim, "half_x": half, "half_y": half.copy(),
               "wl": wli, "shape": shape, "fields": fields}
        if ray_aiming:
            self._aim_at_stop(src)
        return src

    def _aim_at_stop(self, src, iterations: int = 12):
        """Move each source's pupil centre on the EP plane so its chief ray hits the stop centre."""
        stop = self.lens.stop_index
        if stop == 0 and self.lens.surfaces[0].type != "standard":
            # the stop is the first (plane) surface: the paraxial EP is the stop itself
            return
        n = len(src["wl"])
        aim = src["aim"].copy()
        h = 1e-4 * max(self.pupils.entrance_radius, 1e-3)
        for _ in range(iterations):
            trial = np.concatenate([aim, aim + [h, 0, 0], aim + [0, h, 0]])
            sub = {k: (np.concatenate([v, v, v]) if isinstance(v, np.ndarray) else v) for k, v in src.items()}
            sub["aim"] = trial
            rays = self._run(sub, np.zeros(1), np.zeros(1), 1.0, upto=stop + 1)
            xy = rays.pos.numpy()[:, :2].reshape(3, n, 2)
            ok = rays.valid.numpy().reshape(3, n)
            if not ok.all():
                bad = [src["fields"][k] for k in range(n) if not ok[:, k].all()]
                raise GeometryError("ray aiming failed: the chief ray misses a surface before the stop",
                                    file=self.lens.source, surface=stop, field=bad[0])
            r0, rx, ry = xy[0], xy[1], xy[2]
            jac = np.stack([(rx - r0) / h, (ry - r0) / h], axis=2)  # (n, 2 stop coords, 2 aim coords)
            step = np.linalg.solve(jac, -r0[..., None])[..., 0]
            aim[:, :2] += step
            if np.max(np.abs(r0)) < 1e-12:
                break
        src["aim"] = aim

    # -------------------------------------------------------------- tracing
    def trace(self, fields_deg=0.0, grid: int = 101, wavelength_index=0, ray_aiming: bool = False,
              jitter: float = 0.0, layout: str = "centers", upto: int | None = None,
              object_distance=None, pupil=None) -> Rays:
        """Trace a pupil grid for each field to surface ``upto`` (exclusive; default: the sensor plane).

        ``grid``: pupil samples across the diameter; ``pupil``: optional explicit ``(u, v)`` arrays.
        ``pupil``: optional explicit ``(u, v, cell_area)`` in normalised pupil units.
        Returns :class:`Rays` after the last traced surface (at the sensor by default). Record on a
        ``wp.Tape`` around this call to differentiate (with ``requires_grad=True``).
        """
        src = self.sources(fields_deg, wavelength_index, ray_aiming, object_distance)
        if pupil is None:
            u, v, cell = pupil_grid(grid, src["shape"], jitter=jitter, layout=layout)
        else:
            u, v, cell = pupil
        return self._run(src, u, v, cell, upto=upto)

    def _run(self, src, u, v, cell=1.0, upto=None, keep=False, grid_n: int = 0):
        """Generate and trace. ``grid_n > 0``: the pupil is the full ``grid_n x grid_n`` cell-centre grid,
        generated on the device (``u``, ``v`` ignored; no upload)."""
        dev, sc, K = self.device, self.scalar, self.K
        nsrc = len(src["wl"])
        npup = grid_n * grid_n if grid_n > 0 else len(u)
        if grid_n > 0:
            u = v = np.zeros(1)
        n = nsrc * npup
        g = self.requires_grad

        def arr(x, dtype):
            return wp.array(np.ascontiguousarray(x), dtype=dtype, device=dev)

        def new():
            return (wp.empty(n, dtype=K.vec3, device=dev, requires_grad=g),
                    wp.empty(n, dtype=K.vec3, device=dev, requires_grad=g),
                    wp.empty(n, dtype=sc, device=dev, requires_grad=g),
                    wp.empty(n, dtype=wp.int32, device=dev))
        pos, dr, opl, valid = new()
        wl = wp.empty(n, dtype=wp.int32, device=dev)
        weight = wp.empty(n, dtype=sc, device=dev)
        inputs = [arr(u, sc), arr(v, sc), arr(src["pos"], K.vec3), arr(src["dir"], K.vec3),
                  arr(src["finite"], wp.int32), arr(src["aim"], K.vec3), arr(src["half_x"], sc),
                  arr(src["half_y"], sc), arr(src["wl"], wp.int32), self.n_obj, sc(cell),
                  int(src["shape"] == "circle"), int(src.get("relative_opl", False)), int(grid_n), npup]
        wp.launch(K.generate_kernel, dim=n, inputs=inputs, outputs=[pos, dr, opl, valid, wl, weight], device=dev)
        nsurf = len(self.lens.surfaces)
        last = nsurf + 1 if upto is None else upto
        t_start = wp.zeros(1, dtype=sc, device=dev)  # placeholder for non-refracting surfaces
        history = []
        for i in range(last):
            kind = self.kinds[i] if i < nsurf else ktrace.KIND_PLANE
            n_in = self.n_before[i] if i < nsurf else self.n_tables[-1]
            n_out = self.n_tables[i] if i < nsurf else self.n_tables[-1]
            p2, d2, o2, v2 = new()
            if kind == ktrace.KIND_REFRACT:
                # converge the intersection off the tape; the surface kernel differentiates one step.
                # A buffer per surface: the adjoint reads it again during tape.backward()
                t_start = wp.empty(n, dtype=sc, device=dev)
                wp.launch(K.intersect_kernel, dim=n, inputs=[pos, dr, valid, self.params[i]], outputs=[t_start],
                          device=dev, record_tape=False)
            wp.launch(K.surface_kernel, dim=n,
                      inputs=[pos, dr, opl, valid, wl, self.params[i], n_in, n_out, kind, t_start],
                      outputs=[p2, d2, o2, v2], device=dev)
            if keep:
                history.append(p2)
            pos, dr, opl, valid = p2, d2, o2, v2
        rays = Rays(pos, dr, opl, valid, wl, weight, nsrc, npup)
        if keep:
            rays.history = history
        return rays
