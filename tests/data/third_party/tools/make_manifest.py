import json, hashlib, os, re
T = 'tests/data/third_party/files'
refs = json.load(open('/tmp/refs_out.json'))
REPOS = {
 'optiland': {"repo": "HarrisonKramer/optiland", "commit": "1fcb3876f977b11730149608c631d0f5a637c02f", "licence": "MIT",
              "dir": "tests/zemax_files/"},
 'ray-optics': {"repo": "mjhoptics/ray-optics", "commit": "0b1dc26c8d8e5d43a5720fa1e397805325e7f156",
                "licence": "BSD-3-Clause", "dir": None},
 'DeepLens': {"repo": "singer-yang/DeepLens", "commit": "e15add06f42c145c4be02331a573459b34541dd0",
              "licence": "Apache-2.0", "dir": "datasets/lenses/"},
}
RO_PATHS = {"ACL3026U-Zemax(ZMX).zmx": "src/rayoptics/elem/tests/", "US05331467-1.zmx": "src/rayoptics/zemax/models/PhotoPrime/"}
entries = []
for src in sorted(os.listdir(T)):
    for f in sorted(os.listdir(f"{T}/{src}")):
        p = f"{T}/{src}/{f}"
        info = dict(REPOS[src]); d = info.pop("dir")
        if src == 'ray-optics':
            d = RO_PATHS.get(f, "src/rayoptics/zemax/tests/")
        orig = d + (f.replace('__', '/') if src == 'DeepLens' else f)
        e = {"file": f"{src}/{f}", "repo": info["repo"], "path": orig, "commit": info["commit"],
             "licence": info["licence"], "sha256": hashlib.sha256(open(p, 'rb').read()).hexdigest()}
        r = refs.get(p)
        if r is not None:
            if 'error' in r:
                e["optiland_error"] = r["error"][:160]
            else:
                text = open(p, 'rb').read()
                try:
                    t = text.decode('utf-16') if text[:2] in (b'\xff\xfe', b'\xfe\xff') else text.decode('latin-1')
                except Exception:
                    t = text.decode('latin-1')
                m = re.search(r"^\s*UNIT\s+(\w+)", t, re.M)
                e["reference"] = dict(r, lens_unit=m.group(1) if m else "MM")
        entries.append(e)
out = {"about": "Third-party lens prescriptions (unchanged copies) with reference values computed once by optiland "
       "(run offline in a separate environment; only the numbers are stored). Reference lengths are in the file's "
       "lens unit (optiland keeps them); index_after_surf[k] is the index optiland used after Zemax SURF k at "
       "wavelength_um; rms_um is the RMS spot radius about the centroid, optiland 'uniform' pupil "
       "(linspace(-1, 1, 101)^2, r^2 <= 1), paraxial ray aiming, vignetting factors zeroed, image surface of the file.",
       "versions": {"optiland": "0.6.3", "rayoptics": "0.9.8", "numpy": "2.4.6"},
       "files": entries}
json.dump(out, open('tests/data/third_party/manifest.json', 'w'), indent=1)
print(len(entries), sum('reference' in e for e in entries))
