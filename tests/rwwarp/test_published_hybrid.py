"""A published hybrid diffractive-asphere singlet (issue 27, item 4): Edmund Optics' 65-988 plastic hybrid asphere,
a 12 mm pupil Zeonex E48R singlet (EFL 15.02 mm at d) whose front surface (R 9.93 mm, conic -0.71, r^4 / r^6 / r^8 terms)
carries a diffractive r^2 phase in order 1. Source: the maker's CODE V sequence file as kept by mjhoptics/ray-optics
(``src/rayoptics/codev/tests/CODV_65988.seq``, commit 0b1dc26c, BSD-3-Clause; "seq files from the Edmund website"),
stored unchanged as tests/data/third_party/files/ray-optics/CODV_65988.seq.

It is written as a Zemax file, tests/data/third_party/synthetic/edmund_65988_hybrid_binary2.zmx: SURF 1 a
``BINARY_2`` on the curved even asphere. CODE V's ``DIF DOE`` with ``HCT R`` adds the phase
(2 pi / HWL) * HOR * sum_j C_j r^(2 j) (rad; C_j in mm^(1 - 2 j), the optical path it adds at the construction
wavelength HWL = 587.5618 nm, order HOR = 1); Zemax's BINARY_2 adds M * sum_i A_i (r / R_n)^(2 i) (rad), so with the
order M = HOR and R_n = 6 mm (the clear semi-aperture, CIR 6.0): A_1 = 2 pi C_1 R_n^2 / HWL = -695.768 rad
(C_1 = -1.8073e-3 mm^-1). The glass 'E48' (an index table in the file) is the model glass nd 1.53116 / Vd 56.5 there;
the comparisons below substitute the file's tabulated index at each wavelength.

References: (1) the maker's own image distance, the file's last thickness 12.94603 mm (CODE V's paraxial focus at d);
(2) the thick-lens formula with the diffractive surface's paraxial power -2 M C_1 lambda / HWL, written out here;
(3) optiland 0.6.3's ray trace of the same prescription built through optiland's API from the .seq file
(tests/data/third_party/optiland_edmund_65988.json, made by tools/optiland_edmund_65988.py in a separate environment;
its reader does not take BINARY_2). optiland 0.6.3's paraxial trace leaves the phase out, so its first-order data
are those of a real ray at 1e-5 of the pupil radius."""
import hashlib
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

import rwwarp as rw
from rwwarp.trace import Tracer

DATA = Path(__file__).resolve().parents[1] / "data" / "third_party"
SEQ = DATA / "files" / "ray-optics" / "CODV_65988.seq"
ZMX = DATA / "synthetic" / "edmund_65988_hybrid_binary2.zmx"
REF = json.loads((DATA / "optiland_edmund_65988.json").read_text())
MANIFEST = json.loads((DATA / "manifest.json").read_text())


def _seq_numbers():
    """The maker's numbers, read from the CODE V text with regular expressions (independently of the reference
    script's parser): surfaces (R, t), conic, A..C, HOR, HWL (nm), HCO C1, EPD, CIR."""
    t = re.sub(r"&\s*\r?\n\s*", " ", SEQ.read_text())
    f = r"(-?[0-9.]+(?:e-?[0-9]+)?)"
    s = re.findall(rf"^S\s+{f}\s+{f}", t, re.M)
    return {"R": [float(a) for a, _ in s], "t": [float(b) for _, b in s],
            "K": float(re.search(rf"^\s*K\s+{f}", t, re.M).group(1)),
            "ABC": [float(re.search(rf"\b{c}\s+{f}", t).group(1)) for c in "ABC"],
            "HOR": float(re.search(rf"HOR\s+{f}", t).group(1)), "HWL": float(re.search(rf"HWL\s+{f}", t).group(1)),
            "C1": float(re.search(rf"HCO C1\s+{f}", t).group(1)), "EPD": float(re.search(rf"^EPD\s+{f}", t, re.M).group(1)),
            "CIR": float(re.search(rf"CIR\s+{f}", t).group(1))}


def _at_index(n):
    return rw.load_lens(ZMX).with_surface(0, material=f"{n!r}/1e300")


def test_source_is_unchanged_and_recorded():
    """The stored .seq is the repository's bytes (the manifest's and the reference's SHA-256) and the manifest
    records where the converted .zmx came from."""
    sha = hashlib.sha256(SEQ.read_bytes()).hexdigest()
    e = next(e for e in MANIFEST["files"] if e["file"].endswith("/edmund_65988_hybrid_binary2.zmx"))
    assert e["source_sha256"] == sha == REF["source_sha256"]
    assert e["repo"].startswith("mjhoptics/ray-optics") and e["path"] == "src/rayoptics/codev/tests/CODV_65988.seq"
    assert hashlib.sha256(ZMX.read_bytes()).hexdigest() == e["sha256"]
    assert REF["versions"]["optiland"] == "0.6.3"


def test_zmx_is_the_conversion_of_the_makers_file():
    """SURF 1 of the .zmx is a phase surface on the curved even asphere, every number the .seq's, and the BINARY_2
    term is CODE V's C1 converted: A_1 = HOR 2 pi C1 R_n^2 / HWL (rad), order HOR (exact to rounding: 1e-14)."""
    q = _seq_numbers()
    lens = rw.load_lens(ZMX)
    s1, s2 = lens.surfaces
    assert s1.type == "standard" and s1.stop and s1.phase is not None
    assert s1.radius == pytest.approx(q["R"][0], rel=1e-15) and s1.conic == q["K"]
    assert s1.aspheric == q["ABC"] and s1.a2 == 0.0 and s1.thickness == q["t"][0]
    assert s2.radius == pytest.approx(q["R"][1], rel=1e-15) and s2.thickness == q["t"][1]
    assert s1.diffraction_order == q["HOR"] == 1
    rn = s1.phase["norm_radius"]
    assert rn == q["CIR"] == 6.0 and len(s1.phase["coefficients"]) == 1
    a1 = q["HOR"] * 2 * math.pi * q["C1"] * rn ** 2 / (q["HWL"] * 1e-6)
    assert s1.phase["coefficients"][0] == pytest.approx(a1, rel=1e-14)
    assert s1.semi_diameter == q["CIR"]  # the stop's DIAM (the .zmx's DIAM 6.0 on SURF 2 is a height only: no clip)
    assert lens.entrance_pupil_diameter == q["EPD"] and lens.primary_wavelength_um == pytest.approx(q["HWL"] * 1e-3, rel=1e-15)


def test_first_order_data_match_the_maker_a_thick_lens_formula_and_optiland():
    """At d (587.5618 nm, the file's index 1.53116): rwwarp's BFL is the maker's image distance 12.946031 mm to
    2e-5 mm (measured 4.1e-6 mm: the file tabulates E48 at 587.6 nm, CODE V interpolates its table at 587.5618;
    dBFL/dn = -25 mm, so that is 1.7e-7 in index). At every wavelength EFL and BFL equal the thick-lens formula
    with the diffractive power -2 M C1 lambda / HWL on the front surface to 2e-15 (measured <= 2.2e-16), rwwarp's
    EFL without the phase optiland's paraxial f2 (which leaves it out) to 2e-15 (measured 0), and optiland's real ray to
    5e-11 relative (measured <= 7.3e-12: the ray's (h / f)^2 terms, h = 6e-5 mm). The phase is what makes the
    singlet achromatic: EFL(C) - EFL(F) = 0.018 mm against 0.27 mm for optiland's paraxial f2 without it."""
    q = _seq_numbers()
    d = next(e for e in REF["per_wavelength"] if e["n_glass"] == 1.53116)
    assert _at_index(1.53116).bfl(d["wavelength_um"]) == pytest.approx(q["t"][1], abs=2e-5)
    efl = {}
    for e in REF["per_wavelength"]:
        w, n = e["wavelength_um"], e["n_glass"]
        lens = _at_index(n)
        p1 = (n - 1) / q["R"][0] - 2 * q["HOR"] * q["C1"] * w / (q["HWL"] * 1e-3)
        p2 = (1 - n) / q["R"][1]
        p = p1 + p2 - q["t"][0] / n * p1 * p2
        assert lens.efl(w) == pytest.approx(1 / p, rel=2e-15)
        assert lens.bfl(w) == pytest.approx((1 - q["t"][0] / n * p1) / p, rel=2e-15)
        assert lens.efl(w) == pytest.approx(e["efl_real_ray"], rel=5e-11)
        assert lens.bfl(w) == pytest.approx(e["bfl_real_ray"], rel=5e-11)
        assert lens.with_surface(0, phase=None).efl(w) == pytest.approx(e["paraxial_f2_without_phase"], rel=2e-15)
        efl[e["n_glass"]] = (lens.efl(w), e["paraxial_f2_without_phase"])
    (c, c0), (f, f0) = efl[min(efl)], efl[max(efl)]
    assert abs(c - f) < 0.02 and c0 - f0 > 0.25


@pytest.mark.parametrize("k", range(3))
def test_first_order_diffraction_spots_match_optiland(k):
    """Order 1 at C, d, F and fields 0, 2.5, 5 deg: rwwarp's rays at optiland's ten pupil points land where
    optiland's do (measured <= 4.5e-15 mm; bound 5e-14 mm) with the same direction cosines (measured <= 3.9e-16;
    bound 3e-15), and the RMS spot radius of optiland's 101 x 101 uniform grid (the same 7841 rays; 27 nm on axis
    at d, 62 um at 5 deg in F) agrees to 3e-11 relative (measured <= 2.9e-12). optiland's asphere intersection
    was run at a Newton tolerance of 1e-15 (its default 1e-10 leaves off-axis rays up to 5.4e-8 mm off)."""
    e = REF["per_wavelength"][k]
    w = e["wavelength_um"]
    tr = Tracer(_at_index(e["n_glass"]), [w])
    g = np.linspace(-1.0, 1.0, 101)
    U, V = np.meshgrid(g, g)
    inside = U ** 2 + V ** 2 <= 1.0
    for f in e["fields"]:
        r = tr.trace([f["field_deg"]], pupil=(np.array(f["Px"]), np.array(f["Py"]), 1.0)).numpy()
        assert r["valid"][0].all()
        assert np.max(np.abs(r["pos"][0, :, :2] - np.array(f["xy"]))) < 5e-14
        assert np.max(np.abs(r["dir"][0, :, 0] - np.array(f["L"]))) < 3e-15
        assert np.max(np.abs(r["dir"][0, :, 1] - np.array(f["M"]))) < 3e-15
        grid = tr.trace([f["field_deg"]], pupil=(U[inside], V[inside], 1.0)).numpy()
        ok = grid["valid"][0]
        assert ok.sum() == f["n_grid_rays"] == inside.sum()
        xy = grid["pos"][0, ok, :2]
        rms = np.sqrt(np.mean(np.sum((xy - xy.mean(0)) ** 2, axis=1)))
        assert rms == pytest.approx(f["rms_spot_mm"], rel=3e-11)
