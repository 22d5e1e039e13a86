"""The wave-plane field as one object (:class:`WaveField`): what passes from the splat to the DOE to a
propagation method (:mod:`rwwarp.wave.methods`).

The samples alone do not say where they lie, how finely, at which wavelength or relative to which wave:
:class:`WaveField` keeps them together. Lengths in mm, frequencies in cycles/mm. The ray-wave code and
:mod:`torch_bridge` still pass the raw arrays (with the :class:`~rwwarp.wave.raywave.RayWave` that knows the
rest); :meth:`RayWave.wave_field <rwwarp.wave.raywave.RayWave.wave_field>` bundles them.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np


@dataclass(frozen=True)
class WaveField:
    """A sampled complex field on the wave plane, one window per source ``S``.

    ``samples``: complex (S, N, N) array (numpy or CuPy), rows y, columns x, the carrier removed: the true
    field is ``samples * exp(2 pi i carrier . (x, y))`` (absolute x, y in mm). ``origin_mm`` (S, 2): (x, y) of
    sample (0, 0); samples at ``origin + (j, i) * pitch_mm``. ``pitch_mm``: sample spacing (mm).
    ``wavelength_mm`` (S,): the wavelength in the medium after the plane (``lambda / n``, mm).
    ``carrier_cpmm`` (S, 2): the removed tilt (cycles/mm). The reference wave the splat interpolated
    against (:mod:`rwwarp.wave.splat`): ``chief_mm`` (S, 3) the chief ray's point on the plane, ``target_mm``
    (S, 3) the reference sphere's centre, ``opl_chief_mm`` (S,) the chief ray's optical path to the plane
    (a constant phase per source). ``z_mm``: the plane's z (mm). ``doe_phase`` (S, N, N) rad and
    ``doe_scale`` (S,): the DOE's phi0 on the windows and its wavelength remap when a DOE is still to be
    applied (None otherwise)."""

    samples: object
    origin_mm: np.ndarray
    pitch_mm: float
    wavelength_mm: np.ndarray
    carrier_cpmm: np.ndarray
    chief_mm: np.ndarray | None = None
    target_mm: np.ndarray | None = None
    opl_chief_mm: np.ndarray | None = None
    z_mm: float | None = None
    doe_phase: object = None
    doe_scale: np.ndarray | None = None

    def __post_init__(self):
        s = self.samples
        shape = tuple(getattr(s, "shape", ()))
        if len(shape) != 3 or shape[1] != shape[2]:
            raise ValueError(f"WaveField.samples must be (S, N, N), got shape {shape}")
        S = shape[0]
        for name, want in (("origin_mm", (S, 2)), ("wavelength_mm", (S,)), ("carrier_cpmm", (S, 2))):
            a = np.asarray(getattr(self, name), dtype=np.float64)
            if a.shape != want or not np.all(np.isfinite(a)):
                raise ValueError(f"WaveField.{name} must be finite of shape {want}, got {a.shape}")
            object.__setattr__(self, name, a)
        if not (np.isfinite(self.pitch_mm) and self.pitch_mm > 0):
            raise ValueError(f"WaveField.pitch_mm must be a positive length (mm), got {self.pitch_mm!r}")
        if np.any(np.asarray(self.wavelength_mm) <= 0):
            raise ValueError("WaveField.wavelength_mm must be positive (mm)")

    @property
    def n_sources(self) -> int:
        """S, the number of windows."""
        return int(self.samples.shape[0])

    @property
    def n_grid(self) -> int:
        """N, samples per side."""
        return int(self.samples.shape[-1])

    def coordinates(self):
        """Sample coordinates ``(x (S, N), y (S, N))`` in mm (numpy)."""
        g = np.arange(self.n_grid) * float(self.pitch_mm)
        return self.origin_mm[:, 0:1] + g[None, :], self.origin_mm[:, 1:2] + g[None, :]

    def with_samples(self, samples) -> "WaveField":
        """A copy with other samples of the same layout (e.g. after the DOE or the wave step)."""
        return replace(self, samples=samples)


def raywave_field(rw, samples=None) -> WaveField:
    """The :class:`WaveField` of a :class:`~rwwarp.wave.raywave.RayWave` ``rw``: its last traced field
    (:meth:`~rwwarp.wave.raywave.RayWave.field_array`, traced now when ``samples`` is None) with its windows,
    pitch, medium wavelengths, carrier, reference wave and DOE phase (None without a DOE). Not for a plan that
    forms no wave-plane field (``method="pixel"``)."""
    from .methods import get
    if not get(rw.plan.method).forms_field:
        raise ValueError(f"method={rw.plan.method!r} forms no wave-plane field (RayWave.wave_field)")
    u = rw.field_array() if samples is None else samples
    phi0, scale = rw.doe_phase()
    return WaveField(u, rw.origin, float(rw.plan.pitch_mm), rw.lam_mm / rw.n_after, rw.carrier,
                     chief_mm=np.array(rw.chief_plane), target_mm=np.array(rw.target),
                     opl_chief_mm=np.array(rw.opl_chief), z_mm=float(rw.z_plane), doe_phase=phi0, doe_scale=scale)
