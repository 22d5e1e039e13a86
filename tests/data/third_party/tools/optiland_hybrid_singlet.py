"""Reference values of optiland for the hybrid diffractive-asphere singlet (issue 27): run in a separate
virtual environment with optiland (never rwwarp's), e.g.

    python -m venv /tmp/optiland_venv && /tmp/optiland_venv/bin/pip install optiland==0.6.3
    /tmp/optiland_venv/bin/python tests/data/third_party/tools/optiland_hybrid_singlet.py \
        > tests/data/third_party/optiland_hybrid_singlet.json

optiland 0.6.3's .zmx reader does not take BINARY_2, so the prescription of
``synthetic/hybrid_singlet_binary2.zmx`` is built here through optiland's API: the front surface an even
asphere (conic, r^4, r^6) with optiland's ``phase`` interaction and a ``RadialPhaseProfile`` whose
coefficients are the file's BINARY_2 terms times the order over the normalisation radius's powers,
``a_2i = m A_i / R^(2 i)`` (rad / mm^(2 i)). The glass is replaced by a non-dispersive index per wavelength
(optiland's N-BK7 there) only through rwwarp's test; optiland uses its own N-BK7.

Writes JSON: versions, prescription, per wavelength the index after each surface, EFL / BFL (paraxial), and
per (field, wavelength) the image-plane ray coordinates for a list of normalised pupil points (optiland's
trace_generic without ray aiming) and the RMS spot radius of a 101 x 101 uniform grid.
"""
import importlib.metadata as md
import json

import numpy as np
from optiland.materials import IdealMaterial
from optiland.optic import Optic
from optiland.phase.radial import RadialPhaseProfile

# the prescription (mm): an achromatised diffractive-asphere singlet, made up for rwwarp (not a published one)
P = {
    "epd": 10.0,
    "r1": 40.0, "k1": -0.6, "asph1": [-1.2e-6, 4.0e-10],     # r^4, r^6 (mm^-3, mm^-5)
    "order": 1, "rnorm": 5.0, "A": [-136.0, 4.5, -0.8],        # BINARY_2 terms (rad on rho^2, rho^4, rho^6)
    "t1": 4.0, "glass": "N-BK7",
    "r2": -85.0, "t2": 48.66,
    "wavelengths_um": [0.4861327, 0.5875618, 0.6562725], "primary": 1,
    "fields_deg": [0.0, 3.0, 5.0],
}


def build(index_override=None, wavelengths=None):
    """The optic; ``index_override``: a non-dispersive glass of that index; ``wavelengths``: those alone
    (the first primary: optiland's paraxial data are at the primary wavelength)."""
    lens = Optic()
    lens.add_surface(index=0, thickness=np.inf)
    a = [m_ * P["order"] / P["rnorm"] ** (2 * (i + 1)) for i, m_ in enumerate(P["A"])]
    mat = P["glass"] if index_override is None else IdealMaterial(n=index_override)
    lens.add_surface(index=1, radius=P["r1"], thickness=P["t1"], material=mat, is_stop=True, conic=P["k1"],
                     surface_type="even_asphere", coefficients=[0.0] + list(P["asph1"]),
                     interaction_type="phase", phase_profile=RadialPhaseProfile(coefficients=a))
    lens.add_surface(index=2, radius=P["r2"], thickness=P["t2"])
    lens.add_surface(index=3)
    lens.set_aperture(aperture_type="EPD", value=P["epd"])
    lens.set_field_type(field_type="angle")
    for f in P["fields_deg"]:
        lens.add_field(y=f)
    if wavelengths is None:
        for k, w in enumerate(P["wavelengths_um"]):
            lens.add_wavelength(value=w, is_primary=(k == P["primary"]))
    else:
        for k, w in enumerate(wavelengths):
            lens.add_wavelength(value=w, is_primary=(k == 0))
    return lens


def main():
    lens = build()
    out = {"about": "optiland reference for synthetic/hybrid_singlet_binary2.zmx (tools/optiland_hybrid_singlet.py)",
           "versions": {"optiland": md.version("optiland"), "numpy": np.__version__},
           "prescription": P, "per_wavelength": []}
    px = np.array([0.0, 0.3, -0.5, 0.7, 0.0, 0.0, 0.45, -0.6, 0.95, 0.0])
    py = np.array([0.0, 0.0, 0.2, 0.0, 0.6, -0.9, 0.45, -0.6, 0.0, 0.95])
    fmax = max(P["fields_deg"])
    for w in P["wavelengths_um"]:
        n_glass = float(np.asarray(lens.surface_group.surfaces[1].material_post.n(w)).ravel()[0])
        # optiland at that index (non-dispersive): what rwwarp is compared with
        mono = build(index_override=n_glass, wavelengths=[w])
        # optiland 0.6.3's paraxial trace leaves the phase out (its f2 is the refracting singlet's), so the first-order
        # data are taken from a real ray at 1e-5 of the pupil radius (5e-5 mm): EFL = -h / tan(u'), BFL = where it
        # crosses the axis behind the last surface (the aperture terms are ~(h / f)^2 ~ 1e-12 relative)
        h = 1e-5 * P["epd"] / 2
        ray = mono.trace_generic(Hx=np.zeros(1), Hy=np.zeros(1), Px=np.zeros(1), Py=np.array([1e-5]), wavelength=w)
        slope = float(np.asarray(ray.M)[0] / np.asarray(ray.N)[0])
        entry = {"wavelength_um": w, "n_glass": n_glass,
                 "efl_real_ray": -h / slope, "bfl_real_ray": P["t2"] - float(np.asarray(ray.y)[0]) / slope,
                 "paraxial_f2_without_phase": float(np.asarray(mono.paraxial.f2())), "fields": []}
        for f in P["fields_deg"]:
            hy = f / fmax if fmax else 0.0
            rays = mono.trace_generic(Hx=np.zeros_like(px), Hy=np.full_like(px, hy), Px=px, Py=py, wavelength=w)
            xy = np.stack([np.asarray(rays.x), np.asarray(rays.y)], 1)
            grid = mono.trace(Hx=0.0, Hy=hy, wavelength=w, num_rays=101, distribution="uniform")
            gx, gy = np.asarray(grid.x), np.asarray(grid.y)
            keep = np.asarray(grid.i) > 0
            gx, gy = gx[keep], gy[keep]
            rms = float(np.sqrt(np.mean((gx - gx.mean()) ** 2 + (gy - gy.mean()) ** 2)))
            entry["fields"].append({"field_deg": f, "Px": px.tolist(), "Py": py.tolist(), "xy": xy.tolist(),
                                    "L": np.asarray(rays.L).tolist(), "M": np.asarray(rays.M).tolist(),
                                    "rms_spot_mm": rms, "n_grid_rays": int(keep.sum())})
        out["per_wavelength"].append(entry)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
