"""Argument checks at the public edge (project issue 12): one place, small functions.

Each ``check_*`` function returns the normalised value (floats, ints, lists) or raises
:class:`~rwwarp.errors.ArgumentError` (a :class:`~rwwarp.errors.LensError`, so a ``ValueError``) whose
message names the argument, the value given and the accepted range, e.g.
``wavelength_um=550 is outside 0.2-20 um; wavelengths are in micrometres``.

Units: lengths in mm, wavelengths in um, field angles in degrees.
"""
from __future__ import annotations

import math
import numbers
import re

from .errors import ArgumentError

WAVELENGTH_RANGE_UM = (0.2, 20.0)
MAX_FIELD_DEG = 89.9
MAX_SIZE = 8192          # PSF patch side (pixels)
MAX_GRID = 4001          # pupil grid side for spot_rms / spot_diagram
MAX_BATCH = 100_000
MAX_SOURCES = 100_000    # fields x wavelengths in one call
MAX_LENGTH_MM = 1e6
_DEVICE_RE = re.compile(r"^(cpu|cuda|cuda:\d+|opencl:\d+:\d+)$")


def _brief(v, n=60) -> str:
    r = repr(v)
    return r if len(r) <= n else r[:n] + "..."


def _is_real(v) -> bool:
    return isinstance(v, numbers.Real) and not isinstance(v, bool)


def _to_float(v, name):
    if _is_real(v):
        try:
            return float(v)
        except OverflowError:
            raise ArgumentError(f"{name}={_brief(v, 30)} overflows float64") from None
    # 0-d numpy arrays and torch scalars
    try:
        import numpy as np
        if isinstance(v, np.ndarray) and v.ndim == 0 and np.issubdtype(v.dtype, np.number) \
                and not np.issubdtype(v.dtype, np.complexfloating) and v.dtype != bool:
            return float(v)
    except ImportError:  # pragma: no cover
        pass
    raise ArgumentError(f"{name} must be a number, got {type(v).__name__} {_brief(v)}")


def check_number(v, name: str, *, lo=None, hi=None, lo_open=False, allow_inf=False, unit: str = "") -> float:
    """A finite real number (or +inf when ``allow_inf``) in [lo, hi] (``lo_open``: (lo, hi])."""
    x = _to_float(v, name)
    u = f" {unit}" if unit else ""
    if math.isnan(x) or (math.isinf(x) and not (allow_inf and x > 0)):
        raise ArgumentError(f"{name}={x} is not allowed; {name} must be a finite number"
                            + (f" ({unit})" if unit else "") + (" or inf" if allow_inf else ""))
    if lo is not None and (x <= lo if lo_open else x < lo):
        rng = f"> {lo:g}" if lo_open else f">= {lo:g}"
        raise ArgumentError(f"{name}={x:g} is out of range; it must be {rng}{u}"
                            + (f" and <= {hi:g}{u}" if hi is not None else ""))
    if hi is not None and math.isfinite(x) and x > hi:
        raise ArgumentError(f"{name}={x:g} is out of range; it must be <= {hi:g}{u}")
    return x


def check_int(v, name: str, *, lo: int = 1, hi: int | None = None) -> int:
    """An integer (an integral float is accepted; bools, fractions, NaN are not) in [lo, hi]."""
    ok = isinstance(v, numbers.Integral) and not isinstance(v, bool)
    if not ok and _is_real(v) and math.isfinite(float(v)) and float(v).is_integer():
        ok = True
    if not ok:
        raise ArgumentError(f"{name} must be an integer, got {type(v).__name__} {_brief(v)}")
    x = int(v)
    if x < lo or (hi is not None and x > hi):
        raise ArgumentError(f"{name}={_brief(x, 30)} is out of range; it must be an integer in "
                            f"{lo}..{hi if hi is not None else ''}")
    return x


def check_wavelength(w, lens=None, name: str = "wavelength_um") -> float:
    """A wavelength in um within 0.2-20 um and within the glass data of every material of ``lens``."""
    x = _to_float(w, name)
    lo, hi = WAVELENGTH_RANGE_UM
    if not (lo <= x <= hi):  # NaN fails too
        hint = ""
        if math.isfinite(x) and 200 <= x <= 20000:
            hint = f" (did you mean {x / 1000:g} um?)"
        raise ArgumentError(f"{name}={x:g} is outside {lo:g}-{hi:g} um; wavelengths are in micrometres{hint}")
    if lens is not None:
        _check_glass_range(x, lens, name)
    return x


def _check_glass_range(x, lens, name):
    from . import materials

    seen = set()
    for i, s in enumerate(lens.surfaces):
        names = []
        if s.type in ("standard", "thin_lens"):
            names.append(s.material)
        if s.type == "doe":
            names.append(s.material)
        for m in names:
            if m in seen or not isinstance(m, str):
                continue
            seen.add(m)
            try:
                rng = materials.get_material(m).wavelength_range_um
            except Exception:  # unknown glass: Lens.validate reports it
                continue
            if rng is not None and not (rng[0] - 1e-9 <= x <= rng[1] + 1e-9):
                raise ArgumentError(f"{name}={x:g} is outside the glass data of {m} ({rng[0]:g}-{rng[1]:g} um) "
                                    f"at surface {i}; choose a wavelength within it")


def check_wavelengths(ws, lens=None, name: str = "wavelengths_um") -> list:
    """A non-empty list of wavelengths (um); a single number is accepted as a list of one."""
    if _is_real(ws):
        ws = [ws]
    if isinstance(ws, (str, bytes, dict, set)) or not hasattr(ws, "__len__"):
        raise ArgumentError(f"{name} must be a list of wavelengths in um, got {type(ws).__name__} {_brief(ws)}")
    ws = list(ws)
    if not ws:
        raise ArgumentError(f"{name} is empty; give at least one wavelength (um)")
    one = name.replace("wavelengths", "wavelength")
    return [check_wavelength(w, lens, f"{name}[{k}]" if len(ws) > 1 else one) for k, w in enumerate(ws)]


def check_field(f, name: str = "field_deg"):
    """One field: a number (y angle, deg) or an (x, y) pair; |angle| <= 89.9 deg. Returns it normalised
    (a float, or a tuple of two floats)."""
    import numpy as np

    if isinstance(f, np.ndarray) and f.ndim == 0:
        f = f.item()
    if isinstance(f, (list, tuple, np.ndarray)):
        vals = list(f)
        if len(vals) != 2:
            raise ArgumentError(f"{name}={_brief(f)}: a field is a number (y angle) or an (x, y) pair in "
                                f"degrees, got {len(vals)} values")
        return tuple(check_number(v, name, lo=-MAX_FIELD_DEG, hi=MAX_FIELD_DEG, unit="deg") for v in vals)
    return check_number(f, name, lo=-MAX_FIELD_DEG, hi=MAX_FIELD_DEG, unit="deg")


def check_fields(fields, name: str = "fields", single: str = "field_deg"):
    """A non-empty list of fields (each a number or an (x, y) pair, deg); a single field is a list of one.
    Messages name ``name[k]``, or ``single`` when there is one field."""
    import numpy as np

    if isinstance(fields, (str, bytes, dict, set)):
        raise ArgumentError(f"{name} must be a list of field angles (deg), got {type(fields).__name__}")
    if _is_real(fields) or (isinstance(fields, np.ndarray) and fields.ndim == 0):
        return [check_field(fields, single)]
    if isinstance(fields, tuple):  # as rwwarp.trace.as_field_list: a tuple is one (x, y) field
        return [check_field(fields, single)]
    try:
        items = list(fields)
    except TypeError:
        raise ArgumentError(f"{name} must be a list of field angles (deg), got {type(fields).__name__}") from None
    if not items:
        raise ArgumentError(f"{name} is empty; give at least one field angle (deg)")
    if len(items) > MAX_SOURCES:
        raise ArgumentError(f"{name} has {len(items)} entries; at most {MAX_SOURCES}")
    out = [check_field(f, f"{name}[{k}]" if len(items) > 1 else single) for k, f in enumerate(items)]
    if any(isinstance(f, tuple) for f in out):  # mixed y angles and (x, y) pairs: all pairs (as numpy wants)
        out = [f if isinstance(f, tuple) else (0.0, f) for f in out]
    return out


def check_size(size, name: str = "size") -> int:
    """PSF patch side in pixels: an integer 1..8192."""
    return check_int(size, name, lo=1, hi=MAX_SIZE)


def check_grid(grid, name: str = "grid") -> int:
    """Pupil grid side: an integer 1..4001."""
    return check_int(grid, name, lo=1, hi=MAX_GRID)


def check_batch(batch, name: str = "batch"):
    """Sources per launch: None or an integer >= 1."""
    return None if batch is None else check_int(batch, name, lo=1, hi=MAX_BATCH)


def check_object_distance(d, name: str = "object_distance_mm"):
    """None (the lens's own), or a distance > 0 mm (inf allowed)."""
    if d is None:
        return None
    return check_number(d, name, lo=0.0, lo_open=True, allow_inf=True, hi=MAX_LENGTH_MM * 1e6, unit="mm")


def check_pixel_mm(p, name: str = "pixel_mm"):
    """None (the sensor's pitch) or a pitch in (0, 10] mm, at least 1e-6 mm."""
    if p is None:
        return None
    return check_number(p, name, lo=1e-6, hi=10.0, unit="mm")


def check_center(c, name: str = "center_mm"):
    """None (where the chief ray lands), an (x, y) pair in mm, or a list of pairs (one per source)."""
    import numpy as np

    if c is None:
        return None
    try:
        arr = np.asarray(c, dtype=np.float64)
    except (TypeError, ValueError):
        raise ArgumentError(f"{name} must be an (x, y) pair in mm or a list of pairs, got {_brief(c)}") from None
    if arr.size == 0 or arr.shape[-1] != 2 or arr.ndim > 2:
        raise ArgumentError(f"{name} must be an (x, y) pair in mm or a list of pairs, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)) or np.max(np.abs(arr)) > MAX_LENGTH_MM:
        raise ArgumentError(f"{name}={_brief(c)} must be finite and within +-{MAX_LENGTH_MM:g} mm")
    return c


def check_positive(v, name: str, *, hi=None, unit: str = "") -> float:
    """A finite number > 0 (and <= hi)."""
    return check_number(v, name, lo=0.0, lo_open=True, hi=hi, unit=unit)


def check_nyquist_safety(v, name: str = "nyquist_safety") -> float:
    """Adaptive plan safety factor in [0.5, 16]."""
    return check_number(v, name, lo=0.5, hi=16.0)


def check_rays_per_sample(v, name: str = "rays_per_sample") -> float:
    """Rays per DOE-plane sample along each axis in [0.1, 16]."""
    return check_number(v, name, lo=0.1, hi=16.0)


def check_choice(v, name: str, choices) -> str:
    if not isinstance(v, str) or v not in choices:
        raise ArgumentError(f"{name}={_brief(v)} is not one of {', '.join(repr(c) for c in choices)}")
    return v


def check_device(device, name: str = "device") -> str:
    """``"cpu"``, ``"cuda"``, ``"cuda:N"`` or ``"opencl:P:D"``; a CUDA device must exist."""
    if not isinstance(device, str) or not _DEVICE_RE.match(device):
        raise ArgumentError(f"{name}={_brief(device)} is not a device; use 'cpu', 'cuda', 'cuda:N' or "
                            "'opencl:P:D'")
    if device.startswith("cuda"):
        idx = 0 if device == "cuda" else int(device.split(":")[1])
        try:
            import warp as wp
            wp.config.quiet = True
            wp.init()
            count = wp.get_cuda_device_count()
        except Exception:  # noqa: BLE001 - no usable CUDA driver
            count = 0
        if idx >= count:
            raise ArgumentError(f"{name}={device!r}: no such CUDA GPU ({count} found); use device='cpu'")
    return device


def check_lens(lens, name: str = "lens"):
    """A :class:`~rwwarp.lens.Lens`.

    The class is recognised by its qualified name, not imported: this module sits below
    :mod:`rwwarp.lens` (``Lens.efl`` -> :mod:`rwwarp.paraxial` -> here), so importing it would close a
    circle. Subclasses pass too."""
    if not any(c.__module__ == "rwwarp.lens" and c.__qualname__ == "Lens" for c in type(lens).__mro__):
        raise ArgumentError(f"{name} must be a rwwarp Lens (rw.load_lens(...)), got {type(lens).__name__}")
    return lens


__all__ = [n for n in dir() if n.startswith("check_")] + ["ArgumentError"]
