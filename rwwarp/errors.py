"""Exceptions and warnings of rwwarp.

Every error about user input is a :class:`LensError` (or a subclass) whose message names the
place at fault: the file, the surface number (0-based as stored, and the keyword), the field.
"""


class LensError(ValueError):
    """Invalid lens description: bad file, impossible geometry, unknown glass or surface type."""

    def __init__(self, message, *, file=None, surface=None, keyword=None, field=None):
        where = []
        if file is not None:
            where.append(f"file {file}")
        if surface is not None:
            where.append(f"surface {surface}")
        if keyword is not None:
            where.append(f"keyword {keyword!r}")
        if field is not None:
            where.append(f"field {field}")
        self.file, self.surface, self.keyword, self.field = file, surface, keyword, field
        super().__init__(f"{', '.join(where)}: {message}" if where else message)


class LensFileError(LensError):
    """A lens file could not be parsed (syntax, missing keys, unsupported entries)."""


class GlassError(LensError):
    """A material name is not in the glass table or a dispersion formula is unsupported."""


class GeometryError(LensError):
    """Surfaces cross, a thickness is impossible, or no ray reaches the image."""


class ArgumentError(LensError):
    """An argument of a public function is of the wrong type or out of range; the message names the
    argument, the value and the accepted range (see :mod:`rwwarp.checks`). A ``ValueError``."""


class GeometryWarning(UserWarning):
    """A lens file was loaded although its surfaces cross (or a thickness is negative) inside the heights
    the file gives them: OpticStudio, optiland and DeepLens load such files and trace them sequentially
    (each ray meets the surfaces in order, travelling back where two surfaces cross), and rwwarp does
    the same. The message names the two surfaces, the height and the gap. ``rwwarp.load_lens(path,
    strict=True)`` refuses such a file with a :class:`GeometryError` instead."""


class SamplingWarning(UserWarning):
    """A requested simulation setting violates a sampling criterion (aliasing is likely)."""


class PatchWarning(UserWarning):
    """A PSF does not fit its patch: less than 95 % of the power reaching the sensor lies inside it
    (:func:`rwwarp.psf_map` names the field, the wavelength and the fraction; pass a larger ``size``).
    Not a :class:`SamplingWarning`: the PSF inside the patch is right, the patch is too small."""


class PerformanceWarning(UserWarning):
    """Work that gives the right result at a needless cost the caller can remove (e.g. FFT plans rebuilt because
    the plan cache's bounds are smaller than the work's set of plans)."""
