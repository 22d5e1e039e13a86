"""rwwarp: differentiable ray-wave simulation and design of hybrid refractive-diffractive lenses.

Coherent ray tracing and ray-to-field splatting run as Warp kernels (float64, differentiable);
DOE phase, band-limited angular-spectrum propagation and sensor integration run as OpenCL kernels
with VkFFT (PoCL on the CPU, the vendor's OpenCL or CUDA/NVRTC on a GPU).

Units: lengths in mm, wavelengths in um, field angles in degrees.

    import rwwarp as rw
    lens = rw.load_lens("a489_doe")                  # bundled lens, native JSON, DeepLens JSON or .zmx
    lens.efl(0.5876), lens.bfl(0.5876)               # mm
    rw.spot_rms(lens, field_deg=14.0, wavelength_um=0.5876)   # um
    p = rw.psf(lens, field_deg=0.0, wavelength_um=0.55, model="ray-wave", size=64, device="cpu")
"""
from .errors import LensError, LensFileError, GlassError, GeometryError, ArgumentError, SamplingWarning
from .lens import Lens, Surface, Sensor
from .io import load_lens
from .metrics.analysis import spot_rms, spot_diagram
from .psf import psf, psf_map, plan_psf, PSF, PSFMap
from .wave.plan import Plan
from .wave.plan_cache import PlanCache
from .metrics import (mtf, through_focus_mtf, strehl, encircled_energy, ensquared_energy,
                      chromatic_focal_shift, field_curves)

from .metrics.curves import ChromaticFocalShift, FieldCurves
from .metrics import MTF, ThroughFocusMTF
from .metrics.energy import EnergyCurve
from .metrics.strehl import Strehl

__version__ = "0.1.0"


def layout(lens, path, fields_deg=None, wavelength_um=None, rays: int = 7):
    """Save a 2D (y-z) layout picture of ``lens`` to ``path`` (PNG): surfaces to their clear apertures, glass
    filled, a meridional fan of ``rays`` rays per field (deg; default the lens's fields) at ``wavelength_um``
    (um; default the lens's middle wavelength); axes in mm."""
    from .plots import layout as _layout
    return _layout(lens, path, fields_deg=fields_deg, wavelength_um=wavelength_um, rays=rays)


from .lenses import bundled_lenses

__all__ = ["LensError", "ArgumentError", "LensFileError", "GlassError", "GeometryError", "SamplingWarning", "Lens", "Surface",
           "Sensor", "load_lens", "spot_rms", "spot_diagram", "psf", "psf_map", "plan_psf", "PSF", "PSFMap", "Plan", "PlanCache",
           "mtf", "through_focus_mtf", "strehl", "encircled_energy", "ensquared_energy", "chromatic_focal_shift",
           "field_curves", "layout", "bundled_lenses", "MTF", "ThroughFocusMTF", "EnergyCurve", "Strehl",
           "ChromaticFocalShift", "FieldCurves", "__version__"]


def __dir__():
    """The public names only (``dir(rw)``), not the submodules that importing the package binds."""
    return sorted(__all__)
