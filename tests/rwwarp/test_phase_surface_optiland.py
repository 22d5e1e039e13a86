"""The hybrid diffractive-asphere singlet written as a .zmx (BINARY_2 on a curved even asphere,
tests/data/third_party/synthetic/hybrid_singlet_binary2.zmx, made up for rwwarp: an achromatised N-BK7
singlet, not a published prescription) against optiland 0.6.3's ray trace of the same prescription built
through optiland's API (its reader does not take BINARY_2): tests/data/third_party/optiland_hybrid_singlet.json,
made by tests/data/third_party/tools/optiland_hybrid_singlet.py in a separate environment.

optiland 0.6.3's paraxial trace leaves the phase out (its f2 is the refracting singlet's, 53.2 mm at d against
50.5 mm with the diffractive power), so the first-order data are compared with optiland's real ray at 1e-5 of
the pupil radius; at optiland's indices (non-dispersive model glasses) the comparison tests geometry, phase and
tracing, not glass data."""
import json
from pathlib import Path

import numpy as np
import pytest

import rwwarp as rw
from rwwarp.trace import Tracer

DATA = Path(__file__).resolve().parents[1] / "data" / "third_party"
REF = json.loads((DATA / "optiland_hybrid_singlet.json").read_text())
ZMX = DATA / "synthetic" / "hybrid_singlet_binary2.zmx"


def test_zmx_holds_the_reference_prescription():
    """The file loads as a phase surface on the curved asphere with the prescription optiland traced."""
    P = REF["prescription"]
    lens = rw.load_lens(ZMX)
    s = lens.surfaces[0]
    assert s.type == "standard" and s.phase is not None and s.stop
    assert (s.radius, s.conic, s.aspheric, s.thickness, s.material) == (P["r1"], P["k1"], P["asph1"], P["t1"],
                                                                        P["glass"])
    assert s.phase == {"kind": "even_poly", "norm_radius": P["rnorm"], "coefficients": P["A"]}
    assert s.diffraction_order == P["order"]
    assert (lens.surfaces[1].radius, lens.surfaces[1].thickness) == pytest.approx((P["r2"], P["t2"]), rel=1e-15)
    assert lens.entrance_pupil_diameter == P["epd"] and lens.wavelengths_um == P["wavelengths_um"]
    assert REF["versions"]["optiland"] == "0.6.3"


def _at_reference_index(entry):
    lens = rw.load_lens(ZMX)
    return lens.with_surface(0, material=f"{entry['n_glass']!r}/1e300")


@pytest.mark.parametrize("k", range(3))
def test_first_order_data_match_optiland(k):
    """EFL and BFL (rwwarp's paraxial trace with the phase power) against optiland's real ray at 5e-5 mm:
    rel 1e-9 (measured <= 3e-13: the ray's (h/f)^2 terms and rounding). The diffractive power makes the
    singlet nearly achromatic: EFL(F) - EFL(C) = -1.8e-3 mm (2e-5 relative), against 0.82 mm for the refracting
    singlet alone (optiland's paraxial f2)."""
    e = REF["per_wavelength"][k]
    lens = _at_reference_index(e)
    w = e["wavelength_um"]
    assert lens.efl(w) == pytest.approx(e["efl_real_ray"], rel=1e-9)
    assert lens.bfl(w) == pytest.approx(e["bfl_real_ray"], rel=1e-9)
    assert abs(lens.efl(w) - e["paraxial_f2_without_phase"]) > 2.0  # optiland's paraxial f2 has no phase


@pytest.mark.parametrize("k", range(3))
def test_first_order_diffraction_spots_match_optiland(k):
    """Order 1 at each wavelength and field (0, 3, 5 deg): rwwarp's rays at optiland's pupil points land where
    optiland's do (measured <= 1.5e-12 mm at 5 deg; bound 1e-11 mm) with the same direction cosines (measured 6e-14;
    bound 1e-12), and the RMS spot of optiland's 101 x 101 uniform grid, the same 7841 rays, agrees to 3e-8
    relative (measured <= 8.3e-9: optiland's grid coordinates are not bit for bit linspace(-1, 1, 101)'s)."""
    e = REF["per_wavelength"][k]
    lens = _at_reference_index(e)
    w = e["wavelength_um"]
    tr = Tracer(lens, [w])
    g = np.linspace(-1.0, 1.0, 101)
    U, V = np.meshgrid(g, g)
    inside = U ** 2 + V ** 2 <= 1.0
    for f in e["fields"]:
        px, py = np.array(f["Px"]), np.array(f["Py"])
        r = tr.trace([f["field_deg"]], pupil=(px, py, 1.0)).numpy()
        assert r["valid"][0].all()
        assert np.max(np.abs(r["pos"][0, :, :2] - np.array(f["xy"]))) < 1e-11
        assert np.max(np.abs(r["dir"][0, :, 0] - np.array(f["L"]))) < 1e-12
        assert np.max(np.abs(r["dir"][0, :, 1] - np.array(f["M"]))) < 1e-12
        grid = tr.trace([f["field_deg"]], pupil=(U[inside], V[inside], 1.0)).numpy()
        ok = grid["valid"][0]
        assert ok.sum() == f["n_grid_rays"]
        xy = grid["pos"][0, ok, :2]
        rms = np.sqrt(np.mean(np.sum((xy - xy.mean(0)) ** 2, axis=1)))
        assert rms == pytest.approx(f["rms_spot_mm"], rel=3e-8)
