"""Lens files: :func:`load_lens` reads any supported format, :func:`save_lens` writes one.

The formats, one module each:

* native ``rwwarp-lens/1`` JSON: :meth:`rwwarp.lens.Lens.from_dict` / :meth:`~rwwarp.lens.Lens.to_dict`;
* Zemax sequential ``.zmx``: :mod:`rwwarp.io.zemax` (read), :mod:`rwwarp.io.zemax_write` (write);
* DeepLens JSON: :mod:`rwwarp.io.deeplens` (read), :mod:`rwwarp.io.deeplens_write` (write).

This module sits above :mod:`rwwarp.lens` (the readers build :class:`~rwwarp.lens.Lens` objects): it
registers the writers with :func:`rwwarp.lens.register_writer` so that ``lens.save(path)`` reaches them
without the model importing its file formats. ``rw.load_lens`` is :func:`load_lens`.
"""
from __future__ import annotations

from pathlib import Path

from .. import lens as _lens
from . import validate_input as vi
from ..errors import LensError, LensFileError
from .deeplens import lens_from_deeplens
from .deeplens_write import write_deeplens
from .zemax import read_zmx
from .zemax_write import write_zmx
from ..lens import FORMAT, Lens

__all__ = ["load_lens", "save_lens"]

_lens.register_writer("zmx", write_zmx)
_lens.register_writer("deeplens", write_deeplens)


def load_lens(path, strict: bool = False) -> Lens:
    """Load a lens from a native JSON, DeepLens JSON, or Zemax ``.zmx`` file.

    Surfaces that cross inside the heights the file gives them (or a negative gap, such as an
    optimiser's -1e-8 mm between two flats) load with a :class:`~rwwarp.errors.GeometryWarning` naming
    the two surfaces, the height and the gap, and are traced sequentially, as OpticStudio, optiland and
    DeepLens trace them; ``strict=True`` refuses them with a :class:`GeometryError`.

    Bundled lenses can be named without a path (e.g. ``"a489_doe"``, ``"cooke_triplet"``).
    Raises :class:`LensError` (subclasses :class:`LensFileError`, :class:`GlassError`,
    :class:`GeometryError`) naming the file and the surface at fault.
    """
    vi.check_path_string(path)
    p = Path(path)
    try:
        exists = p.exists()
    except (OSError, ValueError):  # over-long or odd paths
        exists = False
    if not exists:
        bundled = Path(__file__).resolve().parents[1] / "lenses"
        for cand in (bundled / p.name, bundled / (p.name + ".json"), bundled / (p.name + ".zmx")):
            try:
                if p.name and cand.is_file():
                    p = cand
                    break
            except (OSError, ValueError):
                continue
        else:
            raise LensFileError("no such file (and no bundled lens of that name)", file=vi._short(str(path)))
    try:
        if p.suffix.lower() == ".zmx":
            lens = read_zmx(p, strict=strict)
        else:
            d = vi.parse_json(vi.read_lens_bytes(p), p)
            if isinstance(d, dict) and isinstance(d.get("surfaces"), list) and len(d["surfaces"]) > vi.MAX_SURFACES:
                raise LensFileError(f"{len(d['surfaces'])} surfaces; at most {vi.MAX_SURFACES} are supported",
                                    file=str(p), keyword="surfaces")
            if isinstance(d, dict) and d.get("format") == FORMAT:
                lens = Lens.from_dict(d, source=str(p), strict=strict)
            else:
                lens = lens_from_deeplens(d, source=str(p), strict=strict)
        vi.check_loaded(lens)
    except LensError:
        raise
    except (TypeError, ValueError, OverflowError, KeyError, IndexError, AttributeError, ZeroDivisionError,
            RecursionError, MemoryError, UnicodeError, OSError) as e:  # last line of defence: a LensError
        raise LensFileError(f"cannot interpret the file ({type(e).__name__}: {str(e)[:200]})", file=str(p)) from None
    return lens


def save_lens(lens: Lens, path, format: str | None = None) -> None:
    """Write ``lens`` to ``path`` (see :meth:`rwwarp.lens.Lens.save`): ``format`` ``"json"`` (native),
    ``"zmx"`` or ``"deeplens"``; default from the suffix (``.zmx`` -> zmx, anything else -> json)."""
    lens.save(path, format)
