"""Build a lens in Python, then add a DOE to a Zemax lens and see what it does to the colour.

1. A plano-convex N-BK7 singlet built from :class:`rwwarp.Surface` objects, its sensor put at the paraxial
   focus: ``print(lens)`` shows the surface table; one ray-wave PSF.
2. The Cooke triplet read from its Zemax file (``rwwarp/lenses/cooke_triplet.zmx``). A flat DOE (fused-silica
   relief, even-polynomial phase ``phi = sum_i a_i rho^(2i)`` in rad, rho = r / norm_radius) is inserted 1 mm
   behind the last lens; ``rwwarp.demo.achromat_doe`` then gives it half the quadratic phase that makes the
   lens a paraxial achromat (F and C lines focus together) and moves the sensor with the d-line focus.
   Printed: the axial colour before and after (um) and the on-axis Strehl ratios; written: the layout and the
   PSFs before/after (PNG) and the hybrid lens (native JSON) in ``--out``.

    python examples/build_lens_and_add_doe.py [--out out/examples/build_lens_and_add_doe] [--device cpu]

Units: lengths in mm, wavelengths in um, fields in deg. About 10 s on 2 CPU cores.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import rwwarp as rw
from rwwarp.demo import achromat_doe


def singlet() -> rw.Lens:
    """A 50 mm f/5 plano-convex N-BK7 singlet, stop at the curved face, sensor at the paraxial focus."""
    surfaces = [rw.Surface(radius=25.84, thickness=4.0, material="N-BK7", semi_diameter=5.0, stop=True),
                rw.Surface(radius=None, thickness=47.0, material="air", semi_diameter=6.0)]
    lens = rw.Lens(surfaces, sensor=rw.Sensor(pixel_pitch=0.002, resolution=(4000, 4000)),
                   wavelengths_um=[0.4861, 0.5876, 0.6563], fields_deg=[0.0, 3.0, 5.0], name="N-BK7 singlet")
    return lens.with_surface(1, thickness=lens.bfl(0.5876))  # sensor at the d-line paraxial focus


def with_flat_doe(lens: rw.Lens, gap_mm: float = 1.0) -> rw.Lens:
    """``lens`` with a flat DOE (zero phase) ``gap_mm`` behind its last surface, the sensor where it was."""
    last = len(lens.surfaces) - 1
    back = lens.surfaces[last].thickness
    half = max(s.semi_diameter or 0.0 for s in lens.surfaces) or 10.0
    doe = rw.Surface(type="doe", thickness=back - gap_mm, semi_diameter=half, material="fused_silica",
                     design_wavelength_um=0.5876,
                     profile={"kind": "even_poly", "norm_radius": half, "coefficients": [0.0, 0.0]})
    surfaces = list(lens.surfaces[:last]) + [lens.with_surface(last, thickness=gap_mm).surfaces[last], doe]
    return lens.replace(surfaces=surfaces, name=f"{lens.name} + DOE")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/examples/build_lens_and_add_doe", help="output folder")
    ap.add_argument("--device", default="cpu", help="cpu or cuda")
    a = ap.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)

    # 1. a lens built in Python
    s = singlet()
    print(s, "\n")
    p = rw.psf(s, 0.0, 0.5876, size=96, device=a.device)  # 96 px of 2 um hold its spherical aberration
    print(p, "\n")

    # 2. a DOE added to a Zemax lens
    zmx = Path(rw.__file__).parent / "lenses" / "cooke_triplet.zmx"
    cooke = rw.load_lens(zmx)
    hybrid, info = achromat_doe(with_flat_doe(cooke), strength=0.5, wavelengths_um=[0.4861, 0.6563],
                                focus_wavelength_um=0.5876)
    print(f"{hybrid.name}: DOE {info['a1_rad']:.1f} rad rho^2 (f = {info['doe_focal_length_mm']:.0f} mm), sensor "
          f"moved {info['sensor_shift_mm'] * 1e3:+.1f} um")
    print("axial colour (paraxial focus - d-line focus), um: " + ", ".join(
        f"{w:g}: {b:+.1f} -> {c:+.1f}" for w, b, c in
        zip(info["wavelengths_um"], info["focal_shift_before_um"], info["focal_shift_after_um"])))
    wls = [0.4861, 0.5876, 0.6563]
    before = rw.strehl(cooke, 0.0, wls, device=a.device)
    after = rw.strehl(hybrid, 0.0, wls, device=a.device)
    print(f"on-axis Strehl before: {before}\non-axis Strehl after:  {after}")
    rw.layout(hybrid, out / "hybrid_layout.png")
    for name, lens in (("before", cooke), ("after", hybrid)):
        m = rw.psf_map(lens, [0.0], wls, size=32, device=a.device)
        m.plot(path=out / f"psf_{name}.png")
    hybrid.save(out / "cooke_with_doe.json")
    print(f"wrote {out}/hybrid_layout.png, psf_before.png, psf_after.png, cooke_with_doe.json")


if __name__ == "__main__":
    main()
