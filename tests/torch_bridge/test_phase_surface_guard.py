"""HybridLens refuses phase surfaces (rwwarp.phase_surface) with a LensError naming the surface, until its
thin-lens conjugates and ray model take their power."""
import pytest

from rwwarp.errors import LensError
from rwwarp.lens import Lens, Surface
from torch_bridge.modules import HybridLens


def test_hybrid_lens_refuses_phase_surfaces():
    lens = Lens([Surface(radius=40.0, thickness=4.0, material="N-BK7", semi_diameter=5.0, stop=True,
                         phase={"kind": "even_poly", "norm_radius": 5.0, "coefficients": [-100.0]}),
                 Surface(radius=-80.0, thickness=45.0, semi_diameter=5.0)], wavelengths_um=[0.55])
    with pytest.raises(LensError, match="phase surfaces") as e:
        HybridLens(lens)
    assert e.value.surface == 0 and e.value.keyword == "phase"
