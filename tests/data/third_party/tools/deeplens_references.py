"""optiland references for DeepLens lens files (run in /tmp/refvenv): the prescription is read here
independently of rwwarp (d_next / d, roc / c, k, ai with use_ai2, r); indices come from the sidecar."""
import json, math, sys, warnings
from pathlib import Path
import numpy as np
warnings.filterwarnings("ignore")
from optiland.optic import Optic
from optiland.materials import IdealMaterial
from optiland.physical_apertures import RadialAperture

side = json.load(open('/tmp/dl_sidecar.json'))
N = 101
res = {}
for p, sc in side.items():
    d = json.load(open(Path(__file__).resolve().parents[4] / p))   # p: relative to the repository root
    S = [{k: v for k, v in s.items() if not k.startswith('(')} for s in d["surfaces"]]
    if all("d_next" in s for s in S):
        z, acc = [], 0.0
        for s in S:
            z.append(acc); acc += s["d_next"]
        zs = acc
    else:
        z = [s["d"] for s in S]; zs = d["d_sensor"]
    op = Optic()
    op.add_surface(index=0, thickness=np.inf)
    stop = next((i for i, s in enumerate(S) if s["type"] in ("Aperture", "Stop")), 0)
    for i, s in enumerate(S):
        t = (z[i + 1] if i + 1 < len(S) else zs) - z[i]
        n = sc["n_after_surface"][i]
        mat = "air" if n == 1.0 else IdealMaterial(n=n)
        kw = dict(index=i + 1, thickness=t, material=mat, is_stop=(i == stop))
        if s.get("r") is not None:
            kw["aperture"] = RadialAperture(r_max=float(s["r"]))
        if s["type"] in ("Spheric", "Aspheric"):
            c = s.get("c") if s.get("roc") is None else (0.0 if s["roc"] == 0 else 1.0 / s["roc"])
            R = np.inf if c == 0 else 1.0 / c
            if s["type"] == "Aspheric":
                ai = list(s.get("ai") or [])
                coeffs = ai if s.get("use_ai2", True) else [0.0] + ai
                op.add_surface(surface_type="even_asphere", radius=R, conic=s.get("k", 0.0),
                               coefficients=coeffs, **kw)
            else:
                op.add_surface(radius=R, **kw)
        else:  # Aperture / Stop / Plane
            op.add_surface(radius=np.inf, **kw)
    op.add_surface(index=len(S) + 1)
    if d.get("enpd") is not None:
        op.set_aperture("EPD", float(d["enpd"]))
    else:
        op.set_aperture("float_by_stop_size", 2.0 * float(S[stop]["r"]))
    op.set_field_type("angle")
    for f in sc["fields_deg"]:
        op.add_field(y=f)
    op.add_wavelength(sc["wavelength_um"], is_primary=True)
    op.set_ray_aiming("paraxial")
    px = op.paraxial
    zz = [float(sf.geometry.cs.z) for sf in op.surfaces.surfaces]
    out = {"wavelength_um": sc["wavelength_um"], "n_after_surface": sc["n_after_surface"],
           "efl_mm": float(np.ravel(px.f2())[0]), "epd_mm": float(np.ravel(px.EPD())[0]), "bfl_mm": float(np.ravel(zz[-1] + px.F2() - zz[-2])[0]),
           "fields": [], "rms_um": [], "n_rays": [], "field_type": "AngleField", "lens_unit": "MM"}
    mx = max(sc["fields_deg"]) or 1.0
    for f in sc["fields_deg"]:
        rays = op.trace(0.0, f / mx, sc["wavelength_um"], N, "uniform")
        x, y, i = np.asarray(rays.x), np.asarray(rays.y), np.asarray(rays.i)
        ok = i > 0
        out["fields"].append([0.0, f]); out["n_rays"].append(int(ok.sum()))
        out["rms_um"].append(1e3 * float(np.sqrt(np.mean((x[ok] - x[ok].mean()) ** 2 + (y[ok] - y[ok].mean()) ** 2)))
                             if ok.any() else None)
    res[p] = out
json.dump(res, open('/tmp/dl_refs_out.json', 'w'), indent=1)
print(len(res))
