"""The lenses bundled with rwwarp: ``rw.load_lens(NAME)`` and ``rwwarp psf NAME`` take these names."""
from __future__ import annotations

from pathlib import Path


def bundled_lenses() -> list:
    """Names of the bundled lenses (the stems of the ``.json`` and ``.zmx`` files in this folder), sorted."""
    here = Path(__file__).resolve().parent
    return sorted({p.stem for p in here.iterdir() if p.suffix in (".json", ".zmx")})
