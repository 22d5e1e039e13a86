"""Diffractive optical element (DOE) phase profiles, quantisation, wavelength remap, height export.

The phase arithmetic -- :func:`wrap_phase`, :func:`quantize`, :func:`relief_phase` and the profile
evaluations :func:`radial_phase`, :func:`fresnel_phase`, :func:`zernike_phase`, :func:`cubic_phase`,
:func:`pixel_map_indices` / :func:`pixel_map_phase` -- is written once against an array namespace ``xp``
(numpy, CuPy or torch; default: the namespace of the input, :func:`array_namespace`), so the numpy
profile classes below and the torch design loop (``torch_bridge``, which passes ``torch`` and tensors of
learnable values) evaluate the same code. This module never imports torch or CuPy itself.

Units: lengths (x, y, radii, pitches, focal lengths) in mm, wavelengths in micrometres (um), phase
in radians, heights in micrometres.

A DOE stores its phase ``phi0(x, y)`` at the design wavelength ``lambda0``. At wavelength
``lambda`` the field is multiplied by ``exp(j * s(lambda) * phi0)`` with the wavelength remap of a
surface-relief element of substrate index ``n``::

    s(lambda) = (n(lambda) - 1) / (n(lambda0) - 1) * lambda0 / lambda      (wavelength_scale)

The relief is physical, so the phase that is scaled is the *wrapped* (and, with ``levels``,
quantised) ``phi0 mod 2 pi`` (see :func:`modulation_phase`).

Profile kinds (``profile_from_dict``; ``rho = r / norm_radius``, ``r = hypot(x, y)``):

=========== ======================================================================================
kind        phase phi0 (radians)
=========== ======================================================================================
even_poly   ``sum_i a_i rho^(2i)``, i = 1, 2, ... (Zemax Binary 2 with diffraction order 1)
            keys ``norm_radius`` (mm), ``coefficients`` [a1, a2, ...]
poly        ``sum_k c_k rho^k``, k = 1, 2, 3, ... (odd + even, radial; EDoF designs)
            keys ``norm_radius``, ``coefficients`` [c1, c2, ...]
fresnel     ``-pi r^2 / (lambda0 f)`` (an ideal diffractive lens of focal length f at lambda0)
            key ``focal_length`` (mm); lambda0 is the surface's ``design_wavelength_um``
zernike     ``sum_j z_j Z_j(rho, theta)``, Noll-ordered and Noll-normalised (j = 1 piston,
            2 tilt x, 3 tilt y, 4 defocus, ...); keys ``norm_radius``, ``coefficients``
            [z1, z2, ...]; the polynomials are evaluated everywhere (no mask at rho > 1)
cubic       ``alpha * ((x/R)^3 + (y/R)^3)``; keys ``norm_radius`` (R), ``alpha`` (radians)
pixel_map   a phase map (radians) sampled piecewise-constant (nearest pixel), centred on the
            axis, zero outside; keys ``pitch`` (mm) and ``file`` (.npy, relative to the lens
            file) or ``data`` (nested list). ``data[row][col]``: rows run from +y (top) to -y,
            columns from -x to +x (the array as an image is displayed); pixel (row, col) has its
            centre at ``x = (col - (nx-1)/2) pitch``, ``y = ((ny-1)/2 - row) pitch``.
=========== ======================================================================================

Functions: :func:`profile_from_dict` (validate and build), :func:`get_profile` (a DOE surface's
profile), :func:`surface_is_continuous`, :func:`surface_feature_size_mm` (sampling plans),
:func:`wrap_phase`, :func:`quantize`, :func:`relief_phase`, :func:`wavelength_scale`, :func:`design_phase`
(wrapped and quantised phi0), :func:`modulation_phase` (the phase applied at a wavelength),
:func:`height_map_um`, :func:`export_height_map`, :func:`profile_with_values` (the inverse of
:attr:`Profile.values`, the learnable numbers). The phase itself in any array namespace (numpy, CuPy,
torch) lives in :mod:`rwwarp.wave.doe_phase` and is re-exported here: :func:`array_namespace`,
:func:`profile_phase` / :func:`profile_gradient` (any smooth kind by name, from its learnable values: the
profile classes' :meth:`~Profile.phase` / :meth:`~Profile.gradient` and torch_bridge call them),
:func:`radial_phase`, :func:`radial_gradient_over_r`, :func:`fresnel_phase`, :func:`fresnel_gradient`,
:func:`zernike_phase`, :func:`cubic_phase`, :func:`cubic_gradient`, :func:`pixel_map_indices`,
:func:`pixel_map_phase`, :func:`wrap_phase`, :func:`quantize`, :func:`relief_phase`, :func:`wrap_zone`,
:func:`zone_relief_phase`.
"""
from __future__ import annotations

import functools
import math
import os
import stat
from collections import namedtuple
from pathlib import Path

import numpy as np

from .wave.doe_phase import TWO_PI
from .wave.doe_phase import (  # noqa: F401  (the phase over an array namespace; re-exported here)
    SMOOTH_KINDS,
    _zernike_radial_q,
    array_namespace,
    cubic_gradient,
    cubic_phase,
    fresnel_gradient,
    fresnel_phase,
    fresnel_quadratic,
    noll_to_nm,
    pixel_map_indices,
    pixel_map_phase,
    profile_gradient,
    profile_phase,
    profile_quadratic,
    quantize,
    radial_gradient_over_r,
    radial_phase,
    relief_phase,
    wrap_phase,
    wrap_zone,
    zernike_phase,
    zone_relief_phase,
)
from .errors import LensError, LensFileError

KINDS = ("even_poly", "poly", "fresnel", "zernike", "cubic", "pixel_map")
_KEYS = {
    "even_poly": ({"kind", "norm_radius", "coefficients"}, {"norm_radius", "coefficients"}),
    "poly": ({"kind", "norm_radius", "coefficients"}, {"norm_radius", "coefficients"}),
    "fresnel": ({"kind", "focal_length"}, {"focal_length"}),
    "zernike": ({"kind", "norm_radius", "coefficients"}, {"norm_radius", "coefficients"}),
    "cubic": ({"kind", "norm_radius", "alpha"}, {"norm_radius", "alpha"}),
    "pixel_map": ({"kind", "file", "data", "pitch"}, {"pitch"}),
}


# ====================================================================== helpers
def _f64(a):
    return np.asarray(a, dtype=np.float64)


def _number(d, key, *, positive=False, nonzero=False):
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise LensFileError(f"profile.{key} must be a number, got {v!r}")
    v = float(v)
    if not math.isfinite(v):
        raise LensFileError(f"profile.{key} must be finite, got {v}")
    if positive and not v > 0:
        raise LensFileError(f"profile.{key} must be > 0, got {v}")
    if nonzero and v == 0:
        raise LensFileError(f"profile.{key} must be non-zero, got {v}")
    return v


def _coefficients(d, key="coefficients"):
    v = d[key]
    if not isinstance(v, (list, tuple)):
        raise LensFileError(f"profile.{key} must be a list of numbers (radians), got {type(v).__name__}")
    out = []
    for i, a in enumerate(v):
        if isinstance(a, bool) or not isinstance(a, (int, float)) or not math.isfinite(float(a)):
            raise LensFileError(f"profile.{key}[{i}] must be a finite number, got {a!r}")
        out.append(float(a))
    return out


def _aperture_samples(semi_diameter, shape, n):
    """Sample points (x, y) in mm covering the aperture (n x n grid, clipped to a circle if circular)."""
    t = np.linspace(-semi_diameter, semi_diameter, n)
    x, y = np.meshgrid(t, t, indexing="xy")
    if shape == "circle":
        keep = x * x + y * y <= semi_diameter * semi_diameter * (1 + 1e-12)
        x, y = x[keep], y[keep]
    return x.ravel(), y.ravel()


# ====================================================================== profiles
class Profile:
    """Base class of DOE phase profiles. Coordinates in mm, phase in radians, wavelengths in um."""

    kind = ""
    is_continuous = True  # False where the phase has steps (pixel maps); quantisation is per surface

    @property
    def values(self):
        """The profile's learnable numbers, in the order torch_bridge's ``HybridLens`` learns them and
        :func:`profile_phase` takes them: coefficients (rad), ``[focal_length]`` (mm, fresnel), ``[alpha]``
        (rad, cubic), the phase map (rad, pixel_map); :func:`profile_with_values` writes them back."""
        raise NotImplementedError

    def phase(self, x_mm, y_mm, design_wavelength_um: float = 0.55) -> np.ndarray:
        """Unwrapped phase phi0 (radians, float64) at (``x_mm``, ``y_mm``) for the design wavelength (um)."""
        raise NotImplementedError

    def gradient(self, x_mm, y_mm, design_wavelength_um: float = 0.55):
        """Phase gradient ``(dphi/dx, dphi/dy)`` in rad/mm at (``x_mm``, ``y_mm``), float64 arrays."""
        raise NotImplementedError

    def to_dict(self) -> dict:
        """The native ``profile`` dictionary (inputs only); ``profile_from_dict(p.to_dict())`` rebuilds it."""
        raise NotImplementedError

    def quadratic_coefficient(self, design_wavelength_um: float = 0.55) -> float:
        """Rotationally symmetric r^2 coefficient of phi0 near the axis, rad/mm^2 (paraxial power hook).

        ``phi0 ~ q r^2`` gives a paraxial focal length ``f = -pi / (lambda0 q)`` at the design wavelength.
        """
        return 0.0

    def max_gradient(self, semi_diameter: float, design_wavelength_um: float = 0.55,
                     shape: str = "circle") -> float:
        """Largest |grad phi0| (rad/mm) over the aperture (circle of radius ``semi_diameter`` mm, or
        the square of half side ``semi_diameter``), from a dense grid (radially exact for radial kinds)."""
        x, y = _aperture_samples(float(semi_diameter), shape, 257)
        gx, gy = self.gradient(x, y, design_wavelength_um)
        return float(np.max(np.hypot(gx, gy))) if x.size else 0.0

    def feature_size_mm(self, semi_diameter: float, design_wavelength_um: float = 0.55,
                        shape: str = "circle", levels=None) -> float:
        """Smallest feature of the (wrapped) profile over the aperture, mm.

        Smooth kinds: the narrowest 2 pi zone ``2 pi / max|grad phi0|`` (inf for a flat phase), divided
        by ``levels`` when the relief is quantised (the width of one step). Pixel maps: the pitch.
        Sampling plans need at least two samples per feature (Nyquist).
        """
        g = self.max_gradient(semi_diameter, design_wavelength_um, shape)
        return math.inf if g == 0 else TWO_PI / g / (1 if levels is None else int(levels))

    def __repr__(self):
        return f"{type(self).__name__}({self.to_dict()})"

    def __eq__(self, other):
        return type(self) is type(other) and self.to_dict() == other.to_dict()


class _SmoothProfile(Profile):
    """A smooth kind: phase and gradient by the shared dispatch over its learnable ``values``
    (:func:`profile_phase`, :func:`profile_gradient`, numpy float64)."""

    norm_radius = None

    @property
    def values(self) -> list:
        return list(self.coefficients)

    def phase(self, x_mm, y_mm, design_wavelength_um=0.55):
        return profile_phase(self.kind, self.values, x_mm, y_mm, norm_radius=self.norm_radius,
                             design_wavelength_um=design_wavelength_um, xp=np)

    def gradient(self, x_mm, y_mm, design_wavelength_um=0.55):
        return profile_gradient(self.kind, self.values, x_mm, y_mm, norm_radius=self.norm_radius,
                                design_wavelength_um=design_wavelength_um, xp=np)

    def quadratic_coefficient(self, design_wavelength_um=0.55):
        return profile_quadratic(self.kind, self.values, norm_radius=self.norm_radius,
                                 design_wavelength_um=design_wavelength_um)

    def to_dict(self):
        return {"kind": self.kind, "norm_radius": self.norm_radius, "coefficients": list(self.coefficients)}


class _RadialProfile(_SmoothProfile):
    """phi0 = g(r) for the rotationally symmetric polynomial kinds (even_poly, poly)."""

    def __init__(self, norm_radius: float, coefficients):
        self.norm_radius = float(norm_radius)
        self.coefficients = [float(a) for a in coefficients]

    def max_gradient(self, semi_diameter, design_wavelength_um=0.55, shape="circle"):
        rmax = float(semi_diameter) * (math.sqrt(2.0) if shape == "square" else 1.0)
        r = np.linspace(0.0, rmax, 4097)
        g = radial_gradient_over_r(self.kind, self.coefficients, self.norm_radius, r * r)
        return float(np.max(np.abs(g * r)))


class EvenPolyProfile(_RadialProfile):
    """``phi0 = sum_i a_i rho^(2i)``, rho = r / norm_radius (Zemax Binary 2, order 1). Radians."""

    kind = "even_poly"


class PolyProfile(_RadialProfile):
    """``phi0 = sum_k c_k rho^k`` (k = 1, 2, ...), rho = r / norm_radius: odd and even radial terms.

    The rho^1 term is a cone: its gradient is undefined on the axis and reported as 0 there.
    """

    kind = "poly"


class FresnelProfile(_SmoothProfile):
    """``phi0 = -pi r^2 / (lambda0 f)``: ideal diffractive lens of focal length ``focal_length`` (mm)
    at the design wavelength lambda0 (passed to :meth:`phase` in um)."""

    kind = "fresnel"

    def __init__(self, focal_length: float):
        self.focal_length = float(focal_length)

    @property
    def values(self):
        return [self.focal_length]

    def max_gradient(self, semi_diameter, design_wavelength_um=0.55, shape="circle"):
        rmax = float(semi_diameter) * (math.sqrt(2.0) if shape == "square" else 1.0)
        return abs(2.0 * self.quadratic_coefficient(design_wavelength_um)) * rmax

    def to_dict(self):
        return {"kind": self.kind, "focal_length": self.focal_length}


class ZernikeProfile(_SmoothProfile):
    """``phi0 = sum_j z_j Z_j``: Noll-ordered, Noll-normalised Zernike polynomials in rho = r/norm_radius.

    ``Z_j = N_n^m R_n^|m|(rho) {cos(m theta) for m > 0, sin(|m| theta) for m < 0, 1 for m = 0}`` with
    ``N = sqrt(n + 1)`` (m = 0) or ``sqrt(2 (n + 1))``. Evaluated by :func:`zernike_phase` (Cartesian form,
    ``rho^m cos(m theta) = Re((x + i y)^m) / R^m``), so values and gradients have no singularity.
    """

    kind = "zernike"

    def __init__(self, norm_radius: float, coefficients):
        self.norm_radius = float(norm_radius)
        self.coefficients = [float(a) for a in coefficients]



class CubicProfile(_SmoothProfile):
    """``phi0 = alpha ((x/R)^3 + (y/R)^3)`` (cubic phase plate, EDoF), R = norm_radius (mm), alpha in rad."""

    kind = "cubic"

    def __init__(self, norm_radius: float, alpha: float):
        self.norm_radius = float(norm_radius)
        self.alpha = float(alpha)

    @property
    def values(self):
        return [self.alpha]

    def max_gradient(self, semi_diameter, design_wavelength_um=0.55, shape="circle"):
        k = 3.0 * abs(self.alpha) / self.norm_radius ** 3
        s = float(semi_diameter)
        # |grad| = k sqrt(x^4 + y^4): largest at a square corner, or on an axis for a circle
        return k * s * s * (math.sqrt(2.0) if shape == "square" else 1.0)

    def to_dict(self):
        return {"kind": self.kind, "norm_radius": self.norm_radius, "alpha": self.alpha}


@functools.lru_cache(maxsize=16)
def _load_npy(path: str, mtime_ns: int, size: int):
    arr = np.load(path, allow_pickle=False)
    arr = np.array(arr, dtype=np.float64)
    arr.setflags(write=False)
    return arr


class PixelMapProfile(Profile):
    """Phase map (radians) of ``pitch`` mm square pixels, centred on the axis, nearest-pixel sampled,
    zero outside. ``data[row, col]`` with row 0 at +y (top) and column 0 at -x.

    Either ``file`` (a .npy of a 2-D float array, relative paths resolved against ``base``, the lens
    file's folder) or inline ``data``. The phase has steps: no gradient (:meth:`gradient` raises).
    """

    kind = "pixel_map"
    is_continuous = False

    def __init__(self, pitch: float, data=None, file: str | None = None, base=None):
        self.pitch = float(pitch)
        self.file = file
        self.base = None if base is None else Path(base)
        self._inline = data is not None
        self._data = None
        if data is not None:
            self._data = self._check(np.array(data, dtype=np.float64))
            self._data.setflags(write=False)
        elif file is not None:
            path = self.path
            if path.exists():
                self._data = self._load(path)
            elif self.base is not None or path.is_absolute():
                raise LensFileError(f"profile.file: pixel map {str(path)!r} not found")
            # else: relative path without a base folder: resolved lazily (against the working folder)

    @property
    def path(self) -> Path:
        """Resolved path of the .npy file (relative paths against ``base``)."""
        p = Path(self.file).expanduser()
        return p if p.is_absolute() or self.base is None else self.base / p

    @staticmethod
    def _check(arr):
        if arr.ndim != 2 or min(arr.shape) < 1:
            raise LensFileError(f"profile pixel map must be a non-empty 2-D array, got shape {arr.shape}")
        if not np.all(np.isfinite(arr)):
            raise LensFileError("profile pixel map contains non-finite values")
        return arr

    def _load(self, path):
        try:
            st = os.stat(path)
            if not stat.S_ISREG(st.st_mode) or st.st_size > 2 ** 30:  # no FIFOs/devices (would block), <= 1 GiB
                raise ValueError("not a regular file of at most 1 GiB")
            arr = _load_npy(str(Path(path).resolve()), st.st_mtime_ns, st.st_size)
        except (OSError, ValueError, EOFError, TypeError) as e:
            raise LensFileError(f"profile.file: cannot read pixel map {str(path)!r} ({e})") from None
        return self._check(arr)

    @property
    def values(self) -> np.ndarray:
        """The learnable values: the phase map :attr:`data` (rad, (ny, nx))."""
        return self.data

    @property
    def data(self) -> np.ndarray:
        """The phase map (radians), float64, read-only; shape (ny, nx)."""
        if self._data is None:
            path = self.path
            if not path.exists():
                raise LensFileError(f"profile.file: pixel map {str(path)!r} not found (relative paths are "
                                    "resolved against the lens file's folder)")
            self._data = self._load(path)
        return self._data

    def indices(self, x_mm, y_mm):
        """Nearest-pixel (row, col) indices for (x, y) in mm and a mask of points inside the map
        (:func:`pixel_map_indices`)."""
        return pixel_map_indices(self.pitch, self.data.shape, x_mm, y_mm, np)

    def phase(self, x_mm, y_mm, design_wavelength_um=0.55):
        return pixel_map_phase(self.data, *self.indices(x_mm, y_mm), np)

    def gradient(self, x_mm, y_mm, design_wavelength_um=0.55):
        raise LensError("discontinuous phase: no gradient (a pixel map has steps; the ray model cannot "
                        "bend rays by it, use the ray-wave model)")

    def max_gradient(self, semi_diameter, design_wavelength_um=0.55, shape="circle"):
        raise LensError("discontinuous phase: no gradient")

    def feature_size_mm(self, semi_diameter, design_wavelength_um=0.55, shape="circle", levels=None):
        return self.pitch

    @property
    def half_size(self):
        """Half width and height of the map, mm."""
        ny, nx = self.data.shape
        return 0.5 * nx * self.pitch, 0.5 * ny * self.pitch

    def to_dict(self):
        d = {"kind": self.kind}
        if self._inline:
            d["data"] = self._data.tolist()
        else:
            d["file"] = self.file
        d["pitch"] = self.pitch
        return d


def profile_from_dict(d: dict, base=None) -> Profile:
    """Build a :class:`Profile` from a native ``profile`` dictionary.

    ``base``: folder against which a pixel map's relative ``file`` is resolved (the lens file's folder).
    Raises :class:`~rwwarp.errors.LensFileError` (a :class:`LensError`) for a non-dict, a missing or
    unknown ``kind``, unknown or missing keys, and bad values; the message names the key.
    """
    if not isinstance(d, dict):
        raise LensFileError(f"profile must be an object with a 'kind', got {type(d).__name__}")
    kind = d.get("kind")
    if kind not in KINDS:
        raise LensFileError(f"profile.kind {kind!r} unknown (expected one of {KINDS})")
    allowed, required = _KEYS[kind]
    bad = sorted(set(d) - allowed)
    if bad:
        raise LensFileError(f"unknown profile key(s) {', '.join('profile.' + b for b in bad)} for kind "
                            f"{kind!r}; allowed: {sorted(allowed)}")
    missing = sorted(required - set(d))
    if missing:
        raise LensFileError(f"profile kind {kind!r} needs {', '.join('profile.' + m for m in missing)}")
    if kind == "even_poly":
        return EvenPolyProfile(_number(d, "norm_radius", positive=True), _coefficients(d))
    if kind == "poly":
        return PolyProfile(_number(d, "norm_radius", positive=True), _coefficients(d))
    if kind == "fresnel":
        return FresnelProfile(_number(d, "focal_length", nonzero=True))
    if kind == "zernike":
        return ZernikeProfile(_number(d, "norm_radius", positive=True), _coefficients(d))
    if kind == "cubic":
        return CubicProfile(_number(d, "norm_radius", positive=True), _number(d, "alpha"))
    # pixel_map
    pitch = _number(d, "pitch", positive=True)
    has_file, has_data = d.get("file") is not None, d.get("data") is not None
    if has_file == has_data:
        raise LensFileError("profile kind 'pixel_map' needs exactly one of profile.file (.npy path) and "
                            "profile.data (nested list)")
    if has_file:
        if not isinstance(d["file"], str) or not d["file"]:
            raise LensFileError(f"profile.file must be a path string, got {d['file']!r}")
        return PixelMapProfile(pitch, file=d["file"], base=base)
    try:
        arr = np.array(d["data"], dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise LensFileError(f"profile.data must be a rectangular 2-D list of numbers ({e})") from None
    return PixelMapProfile(pitch, data=arr)


def profile_with_values(profile: dict, values) -> dict:
    """A copy of the native ``profile`` dictionary with its learnable values replaced: the inverse of
    :attr:`Profile.values` (torch_bridge's ``HybridLens.to_lens`` writes its learnt values back with it).
    ``values``: numbers in the order of ``values`` (coefficients in rad; ``[focal_length]`` in mm;
    ``[alpha]`` in rad); a pixel map's (ny, nx) phase map (rad), written inline (``data``, no ``file``)."""
    p = dict(profile)
    kind = p.get("kind")
    if kind in ("even_poly", "poly", "zernike"):
        p["coefficients"] = [float(x) for x in values]
    elif kind in ("cubic", "fresnel"):
        p["alpha" if kind == "cubic" else "focal_length"] = float(values[0])
    elif kind == "pixel_map":
        p.pop("file", None)
        p["data"] = np.asarray(values, dtype=np.float64).tolist()
    else:
        raise LensFileError(f"profile.kind {kind!r} unknown (expected one of {KINDS})")
    return p


def get_profile(surface, source=None) -> Profile:
    """The :class:`Profile` of a DOE ``surface``; ``source`` is the lens file (``lens.source``) so that a
    pixel map's relative path resolves against its folder."""
    if surface.profile is None:
        raise LensError("surface has no DOE profile", keyword="profile")
    return profile_from_dict(surface.profile, base=Path(source).parent if source else None)


def surface_feature_size_mm(surface, source=None) -> float:
    """Smallest feature (mm) of a DOE ``surface`` over its aperture, quantisation included; inf for a flat
    phase. Needs a ``semi_diameter`` for smooth profiles."""
    prof = get_profile(surface, source)
    if surface.semi_diameter is None and prof.is_continuous:
        raise LensError("the feature size of a smooth DOE profile needs the surface's semi_diameter",
                        keyword="semi_diameter")
    return prof.feature_size_mm(surface.semi_diameter, surface.design_wavelength_um, surface.shape,
                                surface.levels)


def surface_has_steps(surface, source=None) -> bool:
    """True when the DOE's relief has phase steps, so sampling plans must resolve its features: a pixel
    map, or a quantised (``levels``) phase that is not flat. A flat (or constant) phase stays flat when
    quantised (every level rounds the same), so a blank DOE with a fabrication ``levels`` setting -- the
    paper's baseline arm, DeepLens's default 16 levels -- has no features and no sampling limit."""
    prof = get_profile(surface, source)
    if not prof.is_continuous:
        return True
    if surface.levels is None:
        return False
    if surface.semi_diameter is not None:
        return prof.max_gradient(surface.semi_diameter, surface.design_wavelength_um, surface.shape) > 0
    d = prof.to_dict()
    return any(float(c) for c in d.get("coefficients", [])) or float(d.get("alpha", 0.0)) != 0.0 or \
        d.get("kind") not in ("even_poly", "poly", "zernike", "cubic")


def surface_is_continuous(surface, source=None) -> bool:
    """True when the DOE's phase is smooth: a smooth profile kind and no quantisation (``levels`` None)."""
    return surface.levels is None and get_profile(surface, source).is_continuous


def is_flat_profile(profile: dict) -> bool:
    """True for a polynomial-type DOE profile dictionary whose coefficients are all zero (no phase to apply)."""
    if profile.get("kind") in ("even_poly", "poly", "zernike"):
        return not any(float(c) for c in profile.get("coefficients", []))
    if profile.get("kind") == "cubic":
        return float(profile.get("alpha", 0.0)) == 0.0
    return False


def _indices(substrate, wavelengths_um):
    from . import materials
    mat = materials.get_material(substrate)
    w = np.atleast_1d(_f64(wavelengths_um))
    return np.array([float(mat.n(float(v))) for v in w.ravel()]).reshape(w.shape)


def wavelength_scale(substrate: str, design_wavelength_um: float, wavelength_um):
    """Phase remap of a surface-relief DOE: ``(n(lambda) - 1) / (n(lambda0) - 1) * lambda0 / lambda``.

    ``substrate`` a material name (:func:`rwwarp.materials.get_material`), wavelengths in um; scalar in,
    float out; array in, array out.
    """
    n0 = _indices(substrate, design_wavelength_um)[0]
    n = _indices(substrate, wavelength_um)
    s = (n - 1.0) / (n0 - 1.0) * float(design_wavelength_um) / np.atleast_1d(_f64(wavelength_um))
    return float(s[0]) if np.ndim(wavelength_um) == 0 else s.reshape(np.shape(wavelength_um))


def design_phase(profile: Profile, x_mm, y_mm, design_wavelength_um: float, levels=None):
    """The relief phase at the design wavelength: ``phi0`` wrapped to [0, 2 pi), quantised to ``levels``
    when given. Radians, float64."""
    return relief_phase(profile.phase(x_mm, y_mm, design_wavelength_um), levels, np)


def modulation_phase(profile: Profile, x_mm, y_mm, design_wavelength_um: float, wavelength_um: float,
                     substrate: str = "fused_silica", levels=None):
    """Phase (radians) the DOE adds at ``wavelength_um``: ``wavelength_scale * design_phase``.

    The DOE multiplies the field by ``exp(1j * modulation_phase)``.
    """
    s = wavelength_scale(substrate, design_wavelength_um, wavelength_um)
    return s * design_phase(profile, x_mm, y_mm, design_wavelength_um, levels)


def height_map_um(phi0, substrate: str, design_wavelength_um: float):
    """Relief height (um) of a phase ``phi0`` (radians): ``wrap(phi0) * lambda0 / (2 pi (n0 - 1))``.

    ``n0`` is the substrate index at ``design_wavelength_um`` (um); the height lies in
    [0, lambda0 / (n0 - 1)). Pass an already quantised phase for a stepped relief.
    """
    n0 = _indices(substrate, design_wavelength_um)[0]
    return wrap_phase(phi0) * float(design_wavelength_um) / (TWO_PI * (n0 - 1.0))


HeightMap = namedtuple("HeightMap", "height_um pitch_mm npy_path png_path")


def export_height_map(profile: Profile, surface, path_prefix, pitch_mm: float, levels=None) -> HeightMap:
    """Write the fabrication height map of a DOE ``surface`` with ``profile``.

    Samples the relief over the surface's aperture (``semi_diameter``, ``shape``) on a grid of
    ``pitch_mm`` (mm) centred on the axis, quantised to ``levels`` (None: the surface's own
    ``levels``; continuous if that is None too), zero outside a circular aperture. Writes
    ``<path_prefix>.npy`` (float64 heights in um, row 0 at +y, column 0 at -x) and
    ``<path_prefix>.png`` (image with a colour bar, axes in mm). Returns a :class:`HeightMap`.
    """
    if surface.semi_diameter is None:
        raise LensError("cannot export a height map of a DOE without a semi_diameter",
                        keyword="semi_diameter")
    if not pitch_mm > 0:
        raise LensError(f"pitch_mm must be > 0, got {pitch_mm}")
    levels = surface.levels if levels is None else levels
    sd = float(surface.semi_diameter)
    n = max(1, int(math.ceil(2.0 * sd / pitch_mm - 1e-9)))
    t = (np.arange(n) - (n - 1) / 2.0) * pitch_mm
    h = np.empty((n, n), dtype=np.float64)
    n0 = _indices(surface.material, surface.design_wavelength_um)[0]
    k = float(surface.design_wavelength_um) / (TWO_PI * (n0 - 1.0))
    rows = max(1, 4_000_000 // n)
    for r0 in range(0, n, rows):
        yy = t[::-1][r0:r0 + rows][:, None]  # row 0 at +y
        xx = t[None, :]
        phi = design_phase(profile, xx, yy, surface.design_wavelength_um, levels)
        blk = phi * k
        if surface.shape == "circle":
            blk = np.where(xx * xx + yy * yy <= sd * sd, blk, 0.0)
        h[r0:r0 + rows] = blk
    prefix = str(path_prefix)
    npy_path, png_path = Path(prefix + ".npy"), Path(prefix + ".png")
    npy_path.parent.mkdir(parents=True, exist_ok=True)
    np.save(npy_path, h)
    _save_png(h, pitch_mm, png_path, levels, surface)
    return HeightMap(h, float(pitch_mm), npy_path, png_path)


def _save_png(h, pitch_mm, path, levels, surface):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    step = max(1, int(math.ceil(max(h.shape) / 2048)))
    half = 0.5 * h.shape[0] * pitch_mm
    fig = Figure(figsize=(6, 5), dpi=150)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    im = ax.imshow(h[::step, ::step], extent=(-half, half, -half, half), origin="upper", cmap="viridis",
                   interpolation="nearest")
    fig.colorbar(im, ax=ax, label="height (um)")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    q = "continuous" if levels is None else f"{int(levels)} levels"
    ax.set_title(f"DOE height map, {surface.material} at {surface.design_wavelength_um} um, {q}", fontsize=9)
    fig.savefig(path)

