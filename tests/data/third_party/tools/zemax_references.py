"""Reference values for tests/data/third_party (run once in /tmp/refvenv; only the numbers are kept)."""
import hashlib, json, sys, warnings, importlib.metadata as md
import numpy as np
warnings.filterwarnings("ignore")
from optiland.fileio import load_zemax_file

N = 101  # optiland 'uniform' distribution: linspace(-1, 1, N)^2 masked to r^2 <= 1


def refs(path):
    op = load_zemax_file(path)
    if op.aperture.ap_type == "float_by_stop_size":
        # optiland 0.6.3's reader (fileio/zemax/reader/converter.py) passes the stop's DIAM, which a Zemax
        # file holds as a semi-diameter, as the stop's diameter: give it the diameter (the pupil then agrees
        # with the same lens built from DeepLens's JSON with float_by_stop_size 2 r)
        op.set_aperture("float_by_stop_size", 2.0 * float(np.ravel(op.aperture.value)[0]))
    op.set_ray_aiming("paraxial")
    # no vignetting factors (rwwarp ignores them): the whole paraxial pupil, as rwwarp traces it
    for f in op.fields.fields:
        for a in ("vx", "vy"):
            if hasattr(f, a):
                setattr(f, a, 0.0)
    wl = float(op.primary_wavelength)
    px = op.paraxial
    zs = [float(s.geometry.cs.z) for s in op.surfaces.surfaces]
    idx = [float(np.real(np.asarray(sf.material_post.n(wl)).reshape(-1)[0])) for sf in op.surfaces.surfaces]
    def scalar(v):  # optiland returns 0-d or 1-element arrays depending on the aperture type (FLOA: arrays)
        return float(np.ravel(v)[0])
    out = {"index_after_surf": idx, "wavelength_um": wl, "efl_mm": scalar(px.f2()), "epd_mm": scalar(px.EPD()),
           "bfl_mm": scalar(zs[-1] + px.F2() - zs[-2]), "fields": [], "rms_um": []}
    ys = [float(f.y) for f in op.fields.fields]
    xs = [float(f.x) for f in op.fields.fields]
    mx = float(op.fields.max_field) or 1.0
    for fx, fy in zip(xs, ys):
        rays = op.trace(fx / mx, fy / mx, wl, N, "uniform")
        x, y, i = np.asarray(rays.x), np.asarray(rays.y), np.asarray(rays.i)
        ok = i > 0
        cx, cy = x[ok].mean(), y[ok].mean()
        out["fields"].append([fx, fy])
        out["rms_um"].append(1e3 * float(np.sqrt(np.mean((x[ok] - cx) ** 2 + (y[ok] - cy) ** 2))))
        out.setdefault("n_rays", []).append(int(ok.sum()))
    out["field_type"] = type(op.fields.field_definition).__name__
    return out


if __name__ == "__main__":
    res = {}
    for p in sys.argv[1:]:
        try:
            res[p] = refs(p)
        except Exception as e:
            res[p] = {"error": f"{type(e).__name__}: {e}"[:300]}
    res["_versions"] = {}
    for pkg in ("optiland", "rayoptics", "numpy"):  # rayoptics: installed beside optiland in the first run
        try:
            res["_versions"][pkg] = md.version(pkg)
        except md.PackageNotFoundError:
            pass
    import os
    open(os.environ.get("REFS_OUT", "/tmp/refs_out.json"), "w").write(json.dumps(res, indent=1))
