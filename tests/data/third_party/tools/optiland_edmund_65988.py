"""Reference values of optiland for Edmund Optics' 65-988 plastic hybrid asphere (issue 27, item 4): run in a
separate virtual environment with optiland (never rwwarp's), e.g.

    python -m venv /tmp/optiland_venv && /tmp/optiland_venv/bin/pip install optiland==0.6.3
    /tmp/optiland_venv/bin/python tests/data/third_party/tools/optiland_edmund_65988.py \
        > tests/data/third_party/optiland_edmund_65988.json

The prescription is read here from the maker's CODE V file itself (``files/ray-optics/CODV_65988.seq``, Edmund
Optics' sequence file as kept by mjhoptics/ray-optics, BSD-3-Clause) by a few lines of parsing, not from the
converted ``synthetic/edmund_65988_hybrid_binary2.zmx`` that rwwarp loads, so the comparison also tests that
conversion. CODE V's ``DIF DOE`` with ``HCT R`` adds the phase (2 pi / HWL) * HOR * sum_j C_j r^(2 j) (rad;
C_j in mm^(1 - 2 j), the optical path at the construction wavelength HWL); optiland's ``RadialPhaseProfile`` takes
the phase's coefficients in rad / mm^(2 j), so a_j = HOR * 2 pi C_j / HWL (HWL in mm). The glass ('E48', Zeon's
Zeonex E48R, a private glass given as an index table) is replaced per wavelength by a non-dispersive
``IdealMaterial`` of the index the file tabulates (587.6 nm -> 1.53116 for d, 486.1 nm -> 1.5378 for F; C,
656.2725 nm, linearly between the 650 and 700 nm entries): rwwarp's test substitutes the same indices.

optiland's .zmx reader does not take BINARY_2 and its paraxial trace leaves the phase out (its f2 is the refracting
singlet's), so the first-order data are taken from a real ray at 1e-5 of the pupil radius, as in
``optiland_hybrid_singlet.py``. Fields 0, 2.5 and 5 deg (the file itself has only the axis) are evaluation
points; optiland's surfaces carry no apertures (rwwarp's CIR 6.0 semi-diameters clip no ray of a 12 mm pupil).
The asphere's Newton tolerance is tightened to ``NEWTON_TOL`` (below).

Writes JSON: versions, the prescription as parsed, per wavelength the index, EFL / BFL from the real ray, and per
field the image-plane ray coordinates and direction cosines for a list of normalised pupil points
(``trace_generic``, no ray aiming) and the RMS spot radius of optiland's 101 x 101 uniform grid.
"""
import importlib.metadata as md
import json
import math
import re
import sys
from pathlib import Path

import numpy as np
from optiland.materials import IdealMaterial
from optiland.optic import Optic
from optiland.phase.radial import RadialPhaseProfile

SEQ = Path(__file__).resolve().parents[1] / "files" / "ray-optics" / "CODV_65988.seq"
#: optiland's even-asphere intersection stops its Newton iteration at |sag residual| < tol (default 1e-10): that
#: leaves off-axis rays of this strong asphere up to 5.4e-8 mm off at the image (5 deg; 3e-9 in direction cosines),
#: and 1e-15 brings them to 4e-15 mm of rwwarp's (measured with both; the on-axis rays agree either way)
NEWTON_TOL = 1e-15


def _num(s):
    return float(s.replace(";", ""))


def parse_seq(text):
    """The few CODE V lines of this file (continuations '&' joined): EPD, wavelengths, the two surfaces."""
    text = re.sub(r"&\s*\r?\n", " ", text)
    lines = [ln.strip() for ln in text.splitlines()]
    P = {"surfaces": []}
    for ln in lines:
        tok = ln.replace(";", " ; ").split()
        if not tok:
            continue
        key = tok[0]
        if key == "EPD":
            P["epd"] = _num(tok[1])
        elif key == "WL":
            P["wavelengths_nm"] = [_num(t) for t in tok[1:]]
        elif key == "REF":
            P["ref"] = int(tok[1])
        elif key == "S":
            P["surfaces"].append({"r": _num(tok[1]), "t": _num(tok[2])})
        elif key == "K":
            P["surfaces"][-1]["k"] = _num(tok[1])
        elif key == "A":  # A a ; B b ; C c ; D d
            vals = [t for t in tok if t not in (";",)]
            P["surfaces"][-1]["asph"] = {vals[i]: _num(vals[i + 1]) for i in range(0, len(vals), 2)}
        elif key == "HOR":
            P["surfaces"][-1]["hor"] = _num(tok[1])
        elif key == "HWL":
            P["surfaces"][-1]["hwl_nm"] = _num(tok[1])
        elif key == "HCO":
            P["surfaces"][-1].setdefault("hco", {})[tok[1]] = _num(tok[2])
    return P


def build(P, n_glass, wavelength_um, fields_deg):
    """The optic at one wavelength with a non-dispersive glass of index ``n_glass``."""
    s1, s2 = P["surfaces"]
    a = s1["asph"]
    hwl_mm = s1["hwl_nm"] * 1e-6
    nc = max(int(k[1:]) for k in s1["hco"])
    coef = [s1["hor"] * 2 * math.pi * s1["hco"].get(f"C{j}", 0.0) / hwl_mm for j in range(1, nc + 1)]
    lens = Optic()
    lens.add_surface(index=0, thickness=np.inf)
    lens.add_surface(index=1, radius=s1["r"], thickness=s1["t"], material=IdealMaterial(n=n_glass), is_stop=True,
                     conic=s1["k"], surface_type="even_asphere",
                     coefficients=[0.0, a["A"], a["B"], a["C"], a["D"]],
                     interaction_type="phase", phase_profile=RadialPhaseProfile(coefficients=coef))
    lens.surface_group.surfaces[1].geometry.tol = NEWTON_TOL
    lens.add_surface(index=2, radius=s2["r"], thickness=s2["t"])
    lens.add_surface(index=3)
    lens.set_aperture(aperture_type="EPD", value=P["epd"])
    lens.set_field_type(field_type="angle")
    for f in fields_deg:
        lens.add_field(y=f)
    lens.add_wavelength(value=wavelength_um, is_primary=True)
    return lens, coef


def main():
    raw = SEQ.read_bytes()
    P = parse_seq(raw.decode("ascii"))
    # the file's private-glass table (PWL nm -> 'E48' index) at the three wavelengths
    n_tab = {587.5618: 1.53116, 486.1327: 1.5378,
             656.2725: 1.5286 + (1.527 - 1.5286) * (656.2725 - 650.0) / (700.0 - 650.0)}
    fields = [0.0, 2.5, 5.0]
    out = {"about": "optiland reference for synthetic/edmund_65988_hybrid_binary2.zmx, built from "
                    "files/ray-optics/CODV_65988.seq (tools/optiland_edmund_65988.py)",
           "versions": {"optiland": md.version("optiland"), "numpy": np.__version__},
           "optiland_even_asphere_newton_tol": NEWTON_TOL,
           "source_sha256": __import__("hashlib").sha256(raw).hexdigest(),
           "prescription": P, "fields_deg": fields, "per_wavelength": []}
    px = np.array([0.0, 0.3, -0.5, 0.7, 0.0, 0.0, 0.45, -0.6, 0.95, 0.0])
    py = np.array([0.0, 0.0, 0.2, 0.0, 0.6, -0.9, 0.45, -0.6, 0.0, 0.95])
    t2 = P["surfaces"][1]["t"]
    for wnm in P["wavelengths_nm"]:
        w = wnm / 1000.0
        n = n_tab[wnm]
        lens, coef = build(P, n, w, fields)
        out["phase_coefficients_rad_per_mm2j"] = coef
        h = 1e-5 * P["epd"] / 2
        ray = lens.trace_generic(Hx=np.zeros(1), Hy=np.zeros(1), Px=np.zeros(1), Py=np.array([1e-5]), wavelength=w)
        slope = float(np.asarray(ray.M)[0] / np.asarray(ray.N)[0])
        entry = {"wavelength_um": w, "n_glass": n, "efl_real_ray": -h / slope,
                 "bfl_real_ray": t2 - float(np.asarray(ray.y)[0]) / slope,
                 "paraxial_f2_without_phase": float(np.asarray(lens.paraxial.f2())), "fields": []}
        for f in fields:
            hy = f / max(fields)
            rays = lens.trace_generic(Hx=np.zeros_like(px), Hy=np.full_like(px, hy), Px=px, Py=py, wavelength=w)
            xy = np.stack([np.asarray(rays.x), np.asarray(rays.y)], 1)
            grid = lens.trace(Hx=0.0, Hy=hy, wavelength=w, num_rays=101, distribution="uniform")
            gx, gy = np.asarray(grid.x), np.asarray(grid.y)
            keep = np.asarray(grid.i) > 0
            gx, gy = gx[keep], gy[keep]
            rms = float(np.sqrt(np.mean((gx - gx.mean()) ** 2 + (gy - gy.mean()) ** 2)))
            entry["fields"].append({"field_deg": f, "Px": px.tolist(), "Py": py.tolist(), "xy": xy.tolist(),
                                    "L": np.asarray(rays.L).tolist(), "M": np.asarray(rays.M).tolist(),
                                    "rms_spot_mm": rms, "n_grid_rays": int(keep.sum())})
        out["per_wavelength"].append(entry)
    json.dump(out, sys.stdout, indent=1)
    print()


if __name__ == "__main__":
    main()
