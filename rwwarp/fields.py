"""Field angles: the field specs of the public calls (a number: the y angle; an (x, y) pair; a list of either) as
lists, (x, y) pairs and plane-wave directions, and their labels in messages. Angles in degrees. Also read as
``rwwarp.trace.<name>`` (their earlier home)."""
from __future__ import annotations

import math

import numpy as np

from .errors import LensError


def field_direction(field_deg) -> np.ndarray:
    """Unit propagation direction of a plane wave at field angle (x, y) degrees (direction tangents)."""
    fx, fy = _field_pair(field_deg)
    d = np.array([math.tan(math.radians(fx)), math.tan(math.radians(fy)), 1.0])
    return d / np.linalg.norm(d)


def as_field_list(fields_deg) -> list:
    """Normalise a field spec: a number (y angle), an (x, y) tuple, or a list of either -> list."""
    if isinstance(fields_deg, tuple) or (not isinstance(fields_deg, list) and np.ndim(fields_deg) == 0):
        return [fields_deg]
    return list(fields_deg)


def field_pairs(fields_deg) -> list:
    """A field spec (a number: the y angle; an (x, y) pair; or a list of either, mixed allowed; degrees) as a
    list of (x, y) float pairs in degrees."""
    return [_field_pair(f) for f in as_field_list(fields_deg)]


def field_label(f) -> str:
    """A field for messages: ``"14 deg"`` or ``"(0, 2) deg"``."""
    return f"{float(f):g} deg" if np.ndim(f) == 0 else f"({float(f[0]):g}, {float(f[1]):g}) deg"


def _field_pair(field_deg):
    if np.ndim(field_deg) == 0:
        return 0.0, float(field_deg)
    f = [float(v) for v in field_deg]
    if len(f) != 2:
        raise LensError(f"a field is a number (y angle) or an (x, y) pair in degrees, got {field_deg!r}")
    return f[0], f[1]
