"""Lenses shared by the bridge tests."""
import rwwarp as rw

_KEEP = object()


def wrapping_doe_lens(levels=_KEEP, coefficients=(-30.0,)):
    """The A489 + DOE with a DOE that wraps in the beam (-30 rad at the 1.5 mm norm radius, r^2): on axis the
    relief stays in one zone at 0.5 and 0.6 um (one non-integer order: c exp(1j m phi0)), at 3-5 deg it wraps
    (integer orders, different sets per wavelength and source, the chief ray's zone exact). ``levels``: the
    DOE's quantisation levels (default: the lens file's)."""
    lens = rw.load_lens("a489_doe")
    s = lens.surfaces[lens.doe_index]
    s.profile = dict(s.profile, coefficients=list(coefficients))
    if levels is not _KEEP:
        s.levels = levels
    return lens
