"""Lens model: a sequence of surfaces, a sensor, an object distance; the native JSON format.

Units: lengths in mm, wavelengths in micrometres (um), angles in degrees at the public interface.
z is the optical axis, light travels +z, the first surface's vertex sits at z = 0.

A :class:`Surface` is ``geometry + material after it + interaction + aperture``:

========== ======================================================================
type       meaning
========== ======================================================================
standard   plane (``radius`` None), sphere, or even asphere (``conic``, ``aspheric``
           = coefficients of r^4, r^6, ..., r^20); refracts into ``material``
thin_lens  ideal stigmatic lens of ``focal_length`` (like Zemax PARAXIAL)
aperture   a plane that only clips (circle or square); stop by default
doe        a plane that carries a diffractive phase ``profile`` (see :mod:`rwwarp.doe`);
           ``material`` is its substrate (for the wavelength remap), the medium is unchanged
========== ======================================================================

A ``standard`` surface may also carry a diffractive ``phase`` traced in one ``diffraction_order``
(:mod:`rwwarp.phase_surface`): a DOE on a curved surface, in front of or between lenses, several of them.

Native file (``format: "rwwarp-lens/1"``) holds inputs only; :meth:`Lens.to_dict` and
:meth:`Lens.from_dict` round-trip it exactly.
"""
from __future__ import annotations

import copy
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import GeometryError, LensError, LensFileError
from . import materials

FORMAT = "rwwarp-lens/1"
SURFACE_TYPES = ("standard", "thin_lens", "aperture", "doe")
MAX_ASPHERIC = 9  # r^4 .. r^20


@dataclass
class Surface:
    """One optical surface. Lengths in mm.

    ``radius`` is the vertex radius of curvature (None = flat); ``thickness`` the axial distance to
    the next surface (the last surface's thickness is the distance to the sensor).
    ``semi_diameter`` None means unlimited (no clipping).
    """

    type: str = "standard"
    thickness: float = 0.0
    radius: float | None = None
    conic: float = 0.0
    aspheric: list = field(default_factory=list)
    material: str = "air"
    semi_diameter: float | None = None
    shape: str = "circle"
    stop: bool = False
    focal_length: float | None = None
    profile: dict | None = None
    design_wavelength_um: float = 0.55
    levels: int | None = None
    a2: float = 0.0  # r^2 coefficient of the even asphere, 1/mm (Zemax EVENASPH PARM 1, DeepLens use_ai2)
    #: central obstruction (blocks rays inside it): {"shape": "circle", "radius": r} or
    #: {"shape": "rectangle", "half_x": a, "half_y": b} (mm, centred on the axis); None: none
    obscuration: dict | None = None
    #: a reflecting standard surface (Zemax GLAS MIRROR): light turns back, the medium is unchanged (its
    #: ``material`` is the medium in front of it); thicknesses after an odd number of mirrors are negative
    mirror: bool = False
    #: power series in r (Zemax ODDASPHE): sag += sum_i odd_aspheric[i-1] r^i, i = 1..8 (mm^(1-i))
    odd_aspheric: list = field(default_factory=list)
    #: a diffractive phase on a standard surface (:mod:`rwwarp.phase_surface`): {"kind": "even_poly",
    #: "norm_radius": R, "coefficients": [A1, ...]} (radians on rho^2, rho^4, ...) or {"kind": "fresnel",
    #: "focal_length": f}; traced in order ``diffraction_order``. None: none
    phase: dict | None = None
    #: the diffraction order m a ``phase`` is traced in (Zemax BINARY_2 PARM 0); also the order the relief is
    #: blazed for (its depth is |m| waves at ``design_wavelength_um``)
    diffraction_order: int = 1
    #: several orders of a ``phase`` traced and summed coherently by the ray-wave PSF (:mod:`rwwarp.phase_orders`),
    #: e.g. (0, 1, 2); None (default): only ``diffraction_order``, today's single-order path
    diffraction_orders: tuple | None = None

    def __post_init__(self):
        if self.type == "doe" and self.material == "air":
            self.material = "fused_silica"  # a DOE's material is its substrate (the medium is unchanged)

    @property
    def curvature(self) -> float:
        """Vertex curvature, 1/mm (0 for flat)."""
        return 0.0 if self.radius is None or self.radius == 0 else 1.0 / self.radius

    @property
    def paraxial_curvature(self) -> float:
        """Vertex curvature including the r^2 asphere term, 1/mm: c + 2 a2 (what paraxial optics sees)."""
        if self.type != "standard":
            return self.curvature
        b2 = self.odd_aspheric[1] if len(self.odd_aspheric) > 1 else 0.0
        return self.curvature + 2.0 * (self.a2 + b2)

    @property
    def refracts(self) -> bool:
        return self.type == "standard"

    def sag(self, r):
        """Surface sag z(r) in mm at radial distance ``r`` (mm); NaN where the conic is undefined."""
        r2 = np.asarray(r, dtype=np.float64) ** 2
        c, k = self.curvature, self.conic
        with np.errstate(invalid="ignore"):
            arg = 1.0 - (1.0 + k) * c * c * r2
            z = c * r2 / (1.0 + np.sqrt(arg))
        if self.a2:
            z = z + self.a2 * r2
        if self.odd_aspheric:
            r = np.sqrt(r2)
            for i, b in enumerate(self.odd_aspheric):
                z = z + b * r ** (i + 1)
        rp = r2 * r2
        for a in self.aspheric:
            z = z + a * rp
            rp = rp * r2
        return z


@dataclass
class Sensor:
    """Image sensor: ``pixel_pitch`` in mm, ``resolution`` (nx, ny) in pixels."""

    pixel_pitch: float = 0.004
    resolution: tuple = (2000, 2000)

    @property
    def half_size(self):
        """Half width and height of the sensor, mm."""
        return (0.5 * self.pixel_pitch * self.resolution[0], 0.5 * self.pixel_pitch * self.resolution[1])


def snap_to_pixel(x, pixel, n_pixels):
    """Centre of the sensor pixel containing x (mm), along an axis of ``n_pixels`` pixels of pitch ``pixel``
    (mm): the pixel centres sit at (i + 0.5 - n/2) * pixel."""
    i = np.floor(np.asarray(x) / pixel + n_pixels / 2.0)
    return (i + 0.5 - n_pixels / 2.0) * pixel


@dataclass
class Lens:
    """An optical system: surfaces, sensor, object distance (mm from the first vertex, inf allowed).

    ``entrance_pupil_diameter`` (mm), when given, sets the system aperture (Zemax ENPD); the stop
    surface then floats (it does not clip). Otherwise the stop's own semi-diameter sets it.
    """

    surfaces: list
    sensor: Sensor = field(default_factory=Sensor)
    object_distance: float = math.inf
    wavelengths_um: list = field(default_factory=lambda: [0.55])
    name: str = ""
    entrance_pupil_diameter: float | None = None
    fields_deg: list | None = None
    primary_wavelength_um: float | None = None  # the file's primary wavelength (Zemax PWAV), um
    source: str | None = None  # file it came from (for messages); not serialised
    #: how the source file numbers each surface (``"SURF 3"`` in a Zemax file), for messages; not serialised
    surface_labels: list | None = field(default=None, compare=False, repr=False)
    #: per surface, the height (mm) up to which the source file draws it where it does not clip there (a
    #: Zemax ``DIAM``): only the crossing check looks at it (``semi_diameter`` clips); not serialised
    surface_extents: list | None = field(default=None, compare=False, repr=False)
    #: surfaces that cross (or a negative gap) are a :class:`~rwwarp.errors.GeometryWarning` instead of a
    #: :class:`~rwwarp.errors.GeometryError`: lens files load so unless ``strict=True`` (see
    #: :func:`rwwarp.load_lens`); the tracer traces them sequentially, as OpticStudio and optiland do
    allow_crossing: bool = field(default=False, compare=False, repr=False)

    def __post_init__(self):
        self.validate()

    def surface_label(self, i):
        """Surface ``i`` as the source file numbers it (``"SURF 3"`` for a Zemax file), else ``i``: error
        messages name surfaces this way."""
        labels = self.surface_labels
        if labels is not None and isinstance(i, (int, np.integer)) and 0 <= i < len(labels):
            return labels[i]
        return i

    # ------------------------------------------------------------------ geometry
    @property
    def vertex_z(self) -> np.ndarray:
        """z of each surface vertex, mm (first at 0)."""
        t = np.array([s.thickness for s in self.surfaces], dtype=np.float64)
        return np.concatenate([[0.0], np.cumsum(t[:-1])])

    @property
    def sensor_z(self) -> float:
        """z of the sensor plane, mm."""
        return float(sum(s.thickness for s in self.surfaces))

    @property
    def stop_index(self) -> int:
        """Index of the aperture stop: the surface marked ``stop``, else the first aperture, else 0."""
        for i, s in enumerate(self.surfaces):
            if s.stop:
                return i
        for i, s in enumerate(self.surfaces):
            if s.type == "aperture":
                return i
        return 0

    @property
    def doe_index(self) -> int | None:
        """Index of the DOE surface, or None."""
        idx = [i for i, s in enumerate(self.surfaces) if s.type == "doe"]
        return idx[0] if idx else None

    def wave_plane_index(self) -> int:
        """Surface index of the plane where the wave models form the field: the DOE, else the last
        surface. Rays go straight from it to the sensor, so a LensError names any refracting surface
        behind the DOE."""
        d = self.doe_index
        if d is None:
            return len(self.surfaces) - 1
        for k in range(d + 1, len(self.surfaces)):
            if self.surfaces[k].type in ("standard", "thin_lens"):
                raise LensError("the wave models need the DOE behind every refracting surface (surface "
                                f"{k} follows the DOE)", file=self.source, surface=k)
        return d

    def media(self):
        """Material name of the medium after each surface (a DOE and an aperture keep the medium)."""
        out, cur = [], "air"
        for s in self.surfaces:
            if s.type in ("standard", "thin_lens"):
                cur = s.material
            out.append(cur)
        return out

    def directions(self) -> np.ndarray:
        """+1 / -1: the sense along z in which light travels after each surface (mirrors turn it back)."""
        out, cur = [], 1.0
        for s in self.surfaces:
            if s.type == "standard" and s.mirror:
                cur = -cur
            out.append(cur)
        return np.array(out)

    def indices(self, wavelength_um) -> np.ndarray:
        """Refractive index after each surface at ``wavelength_um`` (um); shape (n_surfaces,)."""
        return np.array([materials.get_material(m).n(wavelength_um) for m in self.media()], dtype=np.float64)

    def validate(self):
        """Check types, values and that consecutive surfaces do not cross; raise :class:`LensError`."""
        f = self.source
        if not self.surfaces:
            raise LensError("a lens needs at least one surface", file=f)
        from .io.validate_input import check_doe_steepness, check_lens_values
        check_lens_values(self)  # types, finiteness and ranges of every value (issue 12)
        if not (self.object_distance > 0):
            raise LensError(f"object_distance must be > 0 mm or inf, got {self.object_distance}", file=f)
        for w in self.wavelengths_um:
            if not (0.2 <= float(w) <= 20.0):
                raise LensError(f"wavelength {w} um outside 0.2..20 um (wavelengths are in micrometres)", file=f)
        p = self.sensor.pixel_pitch
        if not (p > 0) or len(self.sensor.resolution) != 2 or min(self.sensor.resolution) < 1:
            raise LensError(f"sensor needs pixel_pitch > 0 and a 2-entry resolution, got {self.sensor}", file=f)
        nstop = sum(1 for s in self.surfaces if s.stop)
        if nstop > 1:
            raise LensError(f"{nstop} surfaces are marked stop; at most one may be", file=f)
        for i, s in enumerate(self.surfaces):
            if s.type not in SURFACE_TYPES:
                raise LensError(f"unknown surface type {s.type!r} (expected one of {SURFACE_TYPES})",
                                file=f, surface=i, keyword="type")
            if not math.isfinite(s.thickness):
                raise LensError(f"thickness must be finite, got {s.thickness}", file=f, surface=i, keyword="thickness")
            if s.semi_diameter is not None and not (s.semi_diameter > 0):
                raise LensError(f"semi_diameter must be > 0 mm, got {s.semi_diameter}", file=f, surface=i,
                                keyword="semi_diameter")
            if s.obscuration is not None:
                ob = s.obscuration
                ok = isinstance(ob, dict) and ((ob.get("shape") == "circle" and set(ob) == {"shape", "radius"})
                                               or (ob.get("shape") == "rectangle"
                                                   and set(ob) == {"shape", "half_x", "half_y"}))
                if ok:
                    vals = [v for k2, v in ob.items() if k2 != "shape"]
                    ok = all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0
                             for v in vals)
                if not ok:
                    raise LensError(f"obscuration must be {{'shape': 'circle', 'radius': r}} or {{'shape': "
                                    f"'rectangle', 'half_x': a, 'half_y': b}} with sizes > 0 mm, got {ob!r}",
                                    file=f, surface=i, keyword="obscuration")
            if s.shape not in ("circle", "square"):
                raise LensError(f"shape must be 'circle' or 'square', got {s.shape!r}", file=f, surface=i,
                                keyword="shape")
            if len(s.odd_aspheric) > 8:
                raise LensError(f"at most 8 odd_aspheric terms (r^1..r^8), got {len(s.odd_aspheric)}", file=f,
                                surface=i, keyword="odd_aspheric")
            if len(s.aspheric) > MAX_ASPHERIC:
                raise LensError(f"at most {MAX_ASPHERIC} aspheric terms (r^4..r^20), got {len(s.aspheric)}",
                                file=f, surface=i, keyword="aspheric")
            if s.type == "thin_lens" and (s.focal_length is None or s.focal_length == 0
                                          or not math.isfinite(s.focal_length)):
                raise LensError("thin_lens needs a finite non-zero focal_length", file=f, surface=i,
                                keyword="focal_length")
            if s.phase is not None or s.diffraction_order != 1 or s.diffraction_orders is not None:
                from .phase_surface import check_phase_surface
                check_phase_surface(s, i, self)
            if s.type == "doe":
                if s.profile is None:
                    raise LensError("doe needs a profile", file=f, surface=i, keyword="profile")
                if s.levels is not None and int(s.levels) < 2:
                    raise LensError(f"levels must be >= 2 or null, got {s.levels}", file=f, surface=i,
                                    keyword="levels")
                from . import doe as _doe
                try:
                    prof = _doe.profile_from_dict(s.profile, base=Path(f).parent if f else None)
                except LensError as e:
                    raise type(e)(str(e), file=f, surface=i, keyword="profile") from None
                check_doe_steepness(s, i, self, prof)
            for m in ([s.material] if s.type in ("standard", "thin_lens", "doe") else []):
                try:
                    materials.get_material(m)
                except LensError as e:
                    raise type(e)(str(e), file=f, surface=i, keyword="material") from None
        if sum(1 for s in self.surfaces if s.type == "doe") > 1:
            raise LensError("at most one DOE surface is supported", file=f)
        self._check_crossing()

    def crossings(self) -> list:
        """Where consecutive surfaces cross: ``[(i, height_mm, gap_mm), ...]``, one entry (the most negative
        gap) per pair ``(i, i + 1)`` whose sag difference along the travel direction is below -1e-9 mm at
        some height up to the smaller of their extents (``semi_diameter``, else ``surface_extents``, else
        the vertex only). A floating stop plane without an aperture is a reference plane and never crosses."""
        z = self.vertex_z
        sense = self.directions()  # the gap after surface i is crossed in the sense sense[i] along z
        ext = self.surface_extents
        out = []
        for i in range(len(self.surfaces) - 1):
            a, b = self.surfaces[i], self.surfaces[i + 1]
            if any(s.type == "aperture" and s.semi_diameter is None for s in (a, b)):
                continue  # a floating stop plane (no aperture) is a reference plane, not a physical surface
            sds = []
            for j, s in ((i, a), (i + 1, b)):
                h = s.semi_diameter
                if h is None and ext is not None and j < len(ext) and ext[j] is not None and ext[j] > 0:
                    h = float(ext[j])
                if h is not None:
                    sds.append(h)
            h = min(sds) if sds else 0.0
            r = np.linspace(0.0, h, 33)
            za, zb = z[i] + a.sag(r), z[i + 1] + b.sag(r)
            ok = np.isfinite(za) & np.isfinite(zb)
            if np.any(sense[i] * (zb[ok] - za[ok]) < -1e-9):
                j = int(np.argmax(sense[i] * (za[ok] - zb[ok])))
                out.append((i, float(r[ok][j]), float(zb[ok][j] - za[ok][j])))
        return out

    def _check_crossing(self):
        gaps = self.crossings()
        if gaps:
            def where(i, h, g):
                return (f"surfaces {self.surface_label(i)} and {self.surface_label(i + 1)} cross at height {h:.4g} mm "
                        f"(gap {g:.4g} mm)")
            i, h, g = gaps[0]
            if not self.allow_crossing:
                raise GeometryError(
                    f"{where(i, h, g)}; check the thickness {self.surfaces[i].thickness} mm (load_lens loads such "
                    "a file with a warning unless strict=True; Lens(..., allow_crossing=True) does the same)",
                    file=self.source, surface=i, keyword="thickness")
            import warnings
            from .errors import GeometryWarning
            warnings.warn(f"{self.source or 'lens'}: " + "; ".join(where(*x) for x in gaps) + ": traced "
                          "sequentially (each ray meets the surfaces in order, travelling back where they cross), as "
                          "OpticStudio, optiland and DeepLens trace it; load with strict=True to refuse",
                          GeometryWarning, stacklevel=3)
        sense = self.directions()
        if sense[-1] * self.surfaces[-1].thickness <= 0:
            raise GeometryError(f"the sensor must lie behind the last surface (thickness "
                                f"{self.surfaces[-1].thickness} mm)", file=self.source,
                                surface=len(self.surfaces) - 1, keyword="thickness")

    # ------------------------------------------------------------------ paraxial (see analysis.py)
    def efl(self, wavelength_um: float = 0.5876) -> float:
        """Paraxial effective focal length in air, ``1 / phi`` (mm), at ``wavelength_um`` (um); see
        :meth:`efl_image_space` for ``n' / phi`` where the image space is not air."""
        from .paraxial import efl
        return efl(self, wavelength_um)

    def efl_image_space(self, wavelength_um: float = 0.5876) -> float:
        """Paraxial effective focal length in image space, ``n' / phi`` (mm; n' the image-space index):
        the rear principal plane to focus distance; equal to :meth:`efl` when the image space is air."""
        from .paraxial import efl_image_space
        return efl_image_space(self, wavelength_um)

    def bfl(self, wavelength_um: float = 0.5876) -> float:
        """Paraxial back focal length from the last surface, mm, at ``wavelength_um`` (um)."""
        from .paraxial import bfl
        return bfl(self, wavelength_um)

    # ------------------------------------------------------------------ editing
    def replace(self, **changes) -> "Lens":
        """A deep copy with top-level attributes changed (validated)."""
        new = copy.deepcopy(self)
        for k, v in changes.items():
            setattr(new, k, v)
        new.validate()
        return new

    def with_surface(self, index: int, **changes) -> "Lens":
        """A deep copy with surface ``index`` changed (validated)."""
        new = copy.deepcopy(self)
        for k, v in changes.items():
            setattr(new.surfaces[index], k, v)
        new.validate()
        return new

    # ------------------------------------------------------------------ native JSON
    def to_dict(self) -> dict:
        """Native ``rwwarp-lens/1`` dictionary (inputs only)."""
        out = {"format": FORMAT, "name": self.name,
               "object_distance": "inf" if math.isinf(self.object_distance) else self.object_distance,
               "wavelengths_um": list(self.wavelengths_um)}
        if self.entrance_pupil_diameter is not None:
            out["entrance_pupil_diameter"] = self.entrance_pupil_diameter
        if self.fields_deg is not None:
            out["fields_deg"] = copy.deepcopy(self.fields_deg)
        if self.primary_wavelength_um is not None:
            out["primary_wavelength_um"] = self.primary_wavelength_um
        out["surfaces"] = [_surface_to_dict(s) for s in self.surfaces]
        out["sensor"] = {"pixel_pitch": self.sensor.pixel_pitch, "resolution": list(self.sensor.resolution)}
        return out

    @classmethod
    def from_dict(cls, d: dict, source: str | None = None, strict: bool = True) -> "Lens":
        """Build from a native ``rwwarp-lens/1`` dictionary; raises :class:`LensFileError`. ``strict=False``
        (what :func:`rwwarp.load_lens` passes unless told ``strict=True``) loads crossing surfaces with a
        :class:`~rwwarp.errors.GeometryWarning` instead of a :class:`GeometryError`."""
        if not isinstance(d, dict) or d.get("format") != FORMAT:
            raise LensFileError(f"not a {FORMAT} file (format = {d.get('format') if isinstance(d, dict) else d!r})",
                                file=source)
        allowed = {"format", "name", "object_distance", "wavelengths_um", "surfaces", "sensor",
                   "entrance_pupil_diameter", "fields_deg", "primary_wavelength_um"}
        _no_unknown(d, allowed, source, None)
        if "surfaces" not in d or not isinstance(d["surfaces"], list):
            raise LensFileError("missing list 'surfaces'", file=source, keyword="surfaces")
        surfaces = [_surface_from_dict(sd, i, source) for i, sd in enumerate(d["surfaces"])]
        sens = d.get("sensor", {})
        _no_unknown(sens, {"pixel_pitch", "resolution"}, source, None, prefix="sensor.")
        res = sens.get("resolution", [2000, 2000])
        if not isinstance(res, list) or len(res) != 2:
            raise LensFileError(f"sensor.resolution must be a list of two integers, got {_brief(res)}", file=source,
                                keyword="sensor.resolution")
        sensor = Sensor(pixel_pitch=_num(sens.get("pixel_pitch", 0.004), source, None, "sensor.pixel_pitch"),
                        resolution=tuple(_integer(v, source, None, "sensor.resolution") for v in res))
        od = d.get("object_distance", "inf")
        od = math.inf if (isinstance(od, str) and od.lower() in ("inf", "infinity")) or od is None else \
            _num(od, source, None, "object_distance")
        wls = d.get("wavelengths_um", [0.55])
        if not isinstance(wls, list):
            raise LensFileError(f"wavelengths_um must be a list of numbers (um), got {_brief(wls)}", file=source,
                                keyword="wavelengths_um")
        wls = [_num(w, source, None, "wavelengths_um") for w in wls]
        epd = d.get("entrance_pupil_diameter")
        name = d.get("name", "")
        if not isinstance(name, str):
            raise LensFileError(f"name must be a string, got {_brief(name)}", file=source, keyword="name")
        return cls(surfaces=surfaces, sensor=sensor, object_distance=od, wavelengths_um=wls,
                   name=name, entrance_pupil_diameter=None if epd is None else
                   _num(epd, source, None, "entrance_pupil_diameter"),
                   fields_deg=copy.deepcopy(d.get("fields_deg")), source=source,
                   primary_wavelength_um=None if d.get("primary_wavelength_um") is None else
                   _num(d["primary_wavelength_um"], source, None, "primary_wavelength_um"),
                   allow_crossing=not strict)

    def save(self, path, format: str | None = None) -> None:
        """Write the lens to ``path``: native JSON, a Zemax sequential ``.zmx``
        (:mod:`rwwarp.io.zemax_write`) or a DeepLens JSON (:mod:`rwwarp.io.deeplens_write`).
        ``format``: ``"json"``, ``"zmx"`` or ``"deeplens"``; default from the suffix (``.zmx`` ->
        zmx, anything else -> json). Same as :func:`rwwarp.io.save_lens`."""
        fmt = format or ("zmx" if Path(path).suffix.lower() == ".zmx" else "json")
        if fmt == "json":
            Path(path).write_text(json.dumps(self.to_dict(), indent=1) + "\n")
        elif fmt in _WRITERS:
            _WRITERS[fmt](self, path)
        else:
            raise ValueError(f"format must be {', '.join(repr(f) for f in ['json', *_WRITERS])}, got {format!r}")

    def __repr__(self) -> str:
        """One line: name, surfaces, EFL and sensor (``str(lens)`` / ``print(lens)`` give the surface table)."""
        try:
            efl = f", EFL {self.efl(self._wl()):.4f} mm at {self._wl():g} um"
        except Exception:  # noqa: BLE001 - an afocal or odd lens still has a repr
            efl = ""
        return (f"Lens({self.name or self.source or 'unnamed'!r}: {len(self.surfaces)} surfaces{efl}, sensor "
                f"{self.sensor.resolution[0]}x{self.sensor.resolution[1]} px of {self.sensor.pixel_pitch * 1e3:g} um)")

    def __str__(self) -> str:
        """The lens as ``rwwarp info`` prints it: a heading (EFL, BFL, fields, wavelengths, sensor) and the surface
        table (lengths in mm, wavelengths in um, fields in deg)."""
        wl = self._wl()
        try:
            par = f"EFL {self.efl(wl):.6f} mm, BFL {self.bfl(wl):.6f} mm at {wl:g} um"
        except Exception:  # noqa: BLE001
            par = "no paraxial focus"
        fields = "-" if not self.fields_deg else ", ".join(
            f"{f:g}" if not isinstance(f, (list, tuple)) else f"({f[0]:g}, {f[1]:g})" for f in self.fields_deg)
        head = [f"{self.name or self.source or 'lens'}: {len(self.surfaces)} surfaces; {par}",
                f"wavelengths {', '.join(f'{w:g}' for w in self.wavelengths_um)} um; fields {fields} deg; sensor "
                f"{self.sensor.resolution[0]}x{self.sensor.resolution[1]} px of {self.sensor.pixel_pitch * 1e3:g} um"]
        return "\n".join(head + surface_table(self))

    def _wl(self) -> float:
        if self.primary_wavelength_um is not None:
            return float(self.primary_wavelength_um)
        return float(self.wavelengths_um[len(self.wavelengths_um) // 2])


# The other file formats live in rwwarp.io, a layer above this model (its readers build Lens objects, so
# this module cannot import them). rwwarp.io registers its writers here when it is imported, and
# ``import rwwarp`` (run before any rwwarp submodule) imports it: Lens.save knows no format by name.
_WRITERS: dict = {}  # format name -> write(lens, path)


def register_writer(fmt: str, write) -> None:
    """Make ``Lens.save(path, format=fmt)`` call ``write(lens, path)``."""
    _WRITERS[fmt] = write


_SURFACE_KEYS = {"type", "thickness", "radius", "conic", "aspheric", "material", "semi_diameter", "shape",
                 "stop", "focal_length", "profile", "design_wavelength_um", "levels", "a2", "obscuration",
                 "mirror", "odd_aspheric", "phase", "diffraction_order", "diffraction_orders"}
_DEFAULTS = Surface()


def _surface_to_dict(s: Surface) -> dict:
    d = {"type": s.type}
    keys = {"standard": ["radius", "conic", "aspheric", "material", "semi_diameter", "shape", "thickness", "stop"],
            "thin_lens": ["focal_length", "material", "semi_diameter", "shape", "thickness", "stop"],
            "aperture": ["semi_diameter", "shape", "thickness", "stop"],
            "doe": ["semi_diameter", "shape", "thickness", "design_wavelength_um", "material", "levels",
                    "profile", "stop"]}[s.type]
    if s.type == "standard" and s.a2:
        keys = keys[:2] + ["a2"] + keys[2:]
    if s.obscuration is not None:
        keys = keys + ["obscuration"]
    if s.type == "standard" and s.mirror:
        keys = keys + ["mirror"]
    if s.type == "standard" and s.odd_aspheric:
        keys = keys + ["odd_aspheric"]
    if s.type == "standard" and s.phase is not None:
        keys = keys + ["phase", "diffraction_order", "design_wavelength_um"]
        if s.diffraction_orders is not None:
            keys = keys + ["diffraction_orders"]
    for k in keys:
        v = getattr(s, k)
        if k == "stop" and not v:
            continue
        d[k] = copy.deepcopy(list(v) if k in ("aspheric", "odd_aspheric", "diffraction_orders") else v)
    return d


def _surface_from_dict(sd, i, source) -> Surface:
    if not isinstance(sd, dict):
        raise LensFileError(f"surface entry must be an object, got {type(sd).__name__}", file=source, surface=i)
    _no_unknown(sd, _SURFACE_KEYS, source, i)
    kw = {}
    for k, v in sd.items():
        if k in ("thickness", "conic", "design_wavelength_um", "a2"):
            kw[k] = _num(v, source, i, k)
        elif k in ("radius", "semi_diameter", "focal_length"):
            kw[k] = None if v is None else _num(v, source, i, k)
        elif k in ("aspheric", "odd_aspheric"):
            if not isinstance(v, list):
                raise LensFileError(f"{k} must be a list of numbers, got {_brief(v)}", file=source, surface=i,
                                    keyword=k)
            kw[k] = [_num(a, source, i, k) for a in v]
        elif k in ("levels", "diffraction_order"):
            kw[k] = None if v is None and k == "levels" else _integer(v, source, i, k)
        elif k == "diffraction_orders":
            if v is not None and not isinstance(v, list):
                raise LensFileError(f"{k} must be a list of integers or null, got {_brief(v)}", file=source,
                                    surface=i, keyword=k)
            kw[k] = None if v is None else tuple(_integer(a, source, i, k) for a in v)
        elif k in ("stop", "mirror"):
            if not isinstance(v, bool):
                raise LensFileError(f"{k} must be true or false, got {_brief(v)}", file=source, surface=i,
                                    keyword=k)
            kw[k] = v
        elif k in ("profile", "obscuration", "phase"):
            kw[k] = copy.deepcopy(v)
        else:
            if not isinstance(v, str):
                raise LensFileError(f"{k} must be a string, got {_brief(v)}", file=source, surface=i, keyword=k)
            kw[k] = v
    typ = kw.get("type", "standard")
    if typ == "doe" and "material" not in kw:
        kw["material"] = "fused_silica"
    if typ == "standard" and kw.get("radius") == 0:
        kw["radius"] = None
    return Surface(**kw)


def _brief(v, n=60) -> str:
    r = repr(v)
    return r if len(r) <= n else r[:n] + "..."


def _num(v, source, surface, key) -> float:
    """A JSON number (not a bool, string, list or object); NaN and inf pass here and are refused by
    :meth:`Lens.validate`, which names them."""
    from .io.validate_input import is_real
    if not is_real(v):
        raise LensFileError(f"{key} must be a number, got {type(v).__name__} {_brief(v)}", file=source,
                            surface=surface, keyword=key)
    try:
        return float(v)
    except OverflowError:
        raise LensFileError(f"{key} = {_brief(v, 30)} overflows float64", file=source, surface=surface,
                            keyword=key) from None


def _integer(v, source, surface, key) -> int:
    from .io.validate_input import is_real
    if not is_real(v) or not math.isfinite(_num(v, source, surface, key)) or float(v) != int(v):
        raise LensFileError(f"{key} must be an integer, got {_brief(v)}", file=source, surface=surface, keyword=key)
    return int(v)


def _no_unknown(d, allowed, source, surface, prefix=""):
    if not isinstance(d, dict):
        raise LensFileError(f"{prefix or 'entry'} must be an object", file=source, surface=surface)
    bad = sorted(set(d) - set(allowed))
    if bad:
        raise LensFileError(f"unknown key(s) {', '.join(prefix + b for b in bad)}; allowed: {sorted(allowed)}",
                            file=source, surface=surface, keyword=prefix + bad[0])


def surface_notes(lens) -> list:
    """Per surface, the lines that describe it beyond radius, conic, thickness, medium and semi-diameter: its
    aspheric terms (sag coefficients of r^2, r^4 ... in mm^(1-i)), a thin lens's focal length (mm), a DOE's
    relief material, profile and design wavelength (um), a mirror, an obscuration. A list of lists of strings."""
    media = lens.media()
    out = []
    for i, s in enumerate(lens.surfaces):
        notes = []
        if s.type == "standard":
            if s.a2:
                notes.append(f"r^2 {s.a2:.6e}")
            if s.aspheric:
                notes.append("even asphere " + ", ".join(f"r^{2 * k + 4} {c:.6e}" for k, c in enumerate(s.aspheric)))
            if s.odd_aspheric:
                notes.append("odd asphere " + ", ".join(f"r^{k + 1} {c:.6e}" for k, c in enumerate(s.odd_aspheric)
                                                        if c))
            if s.mirror:
                notes.append("mirror")
            if s.phase is not None:
                notes.append(f"diffractive phase {s.phase.get('kind')}, order {s.diffraction_order} (traced as rays)"
                             + ("" if s.diffraction_orders is None else
                                f"; orders {list(s.diffraction_orders)} summed coherently (ray-wave PSF)"))
        elif s.type == "thin_lens":
            notes.append(f"ideal thin lens, f = {s.focal_length:g} mm")
        elif s.type == "doe":
            kind = (s.profile or {}).get("kind", "blank")
            notes.append(f"DOE: relief in {s.material} (no thickness: the medium stays {media[i]}), profile {kind}, "
                         f"design {s.design_wavelength_um:g} um" + (f", {s.levels} levels" if s.levels else ""))
        if s.obscuration:
            notes.append(f"obscuration {s.obscuration}")
        out.append(notes)
    return out


def surface_table(lens) -> list:
    """Lines of ``rwwarp info``'s surface table: radius (mm), conic, thickness (mm) and the medium it lies in
    (the medium after the surface: a DOE or an aperture keeps the one before it), semi-diameter (mm); below a
    surface its :func:`surface_notes`."""
    media = lens.media()
    out = [f"{'#':>3} {'type':<9} {'radius':>11} {'conic':>9} {'thickness':>10} {'medium after':<13} {'semi-diam':>9}"]
    for i, (s, notes) in enumerate(zip(lens.surfaces, surface_notes(lens))):
        rad = "inf" if s.radius is None else f"{s.radius:.5f}"
        sd = "-" if s.semi_diameter is None else f"{s.semi_diameter:.4f}"
        conic = f"{s.conic:.6g}" if s.type == "standard" else "-"
        out.append(f"{i:>3} {s.type:<9} {rad:>11} {conic:>9} {s.thickness:>10.5f} {media[i]:<13} {sd:>9}"
                   f"{'  STOP' if i == lens.stop_index else ''}")
        out += [f"{'':>9}{n}" for n in notes]
    return out
