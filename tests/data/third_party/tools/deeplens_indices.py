import json, glob, math, warnings, rwwarp as rw
from rwwarp import materials
from rwwarp.io.deeplens import _material
out = {}
for p in sorted(glob.glob('tests/data/third_party/files/DeepLens/*.json')):
    try:
        d = json.load(open(p))
    except Exception:
        continue
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try: L = rw.load_lens(p)
        except Exception: continue
    if L.doe_index is not None or any(s.type == "thin_lens" for s in L.surfaces):
        continue
    wl = 0.5876
    idx = []
    for i, sd in enumerate(d["surfaces"]):
        m = _material(sd, i, p, None, materials)
        idx.append(float(materials.get_material(m).n(wl)))
    efl = L.efl(wl)
    half = 0.5 * L.sensor.pixel_pitch * math.hypot(*L.sensor.resolution)
    f1 = 0.5 * math.degrees(math.atan(half / abs(efl)))
    out[p] = {"n_after_surface": idx, "wavelength_um": wl, "fields_deg": [0.0, f1]}
json.dump(out, open('/tmp/dl_sidecar.json', 'w'), indent=1)
print(len(out), list(out)[:3])
