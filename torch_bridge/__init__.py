"""torch bridge of rwwarp: autograd Functions around the ray-wave stages, ``nn.Module`` lenses,
mixed precision, tiled PSF maps with checkpointing, and image simulation.

torch is imported only inside this package (rwwarp itself stays numpy-only)::

    import torch, rwwarp as rw, torch_bridge as tb
    lens = tb.HybridLens(rw.load_lens("a489_doe.json"), learn={"doe": "all"})
    psf = lens.psf(field_deg=10.0, wavelength_um=0.55, size=64)      # (64, 64) float64, with gradients
    loss = -(psf * weights).sum(); loss.backward()

Units: mm, um (wavelengths), degrees (fields), radians (phases). See :mod:`torch_bridge.functions`
(gradient conventions, devices), :mod:`torch_bridge.modules` (parameters, plans) and
:mod:`torch_bridge.imaging` (image simulation).
"""
from .functions import (
    MixedPrecision,
    QuantizeSTE,
    TraceSplat,
    mixed_precision,
    quantize_ste,
    raywave_psf,
)
from .modules import QUANTITIES, HybridLens

__all__ = ["QUANTITIES", "HybridLens", "MixedPrecision", "QuantizeSTE", "TraceSplat", "mixed_precision",
           "quantize_ste", "raywave_psf"]
