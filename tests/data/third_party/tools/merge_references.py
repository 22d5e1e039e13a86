"""Merge reference outputs of zemax_references.py / deeplens_references.py into manifest.json (issue 28:
files added or newly loadable after make_manifest.py ran). Usage, from the repository root:

    python3 tests/data/third_party/tools/merge_references.py OUT.json [OUT.json ...]

Entries are matched by path; a file not yet in the manifest needs its source in NEW below. Lens units are
read from the file (UNIT), as make_manifest.py does; optiland's paraxial trace ignores the even asphere's
r^2 term, so DeepLens entries with a nonzero use_ai2 ai[0] are flagged paraxial_ignores_r2_term."""
import hashlib, json, re, sys

T = "tests/data/third_party/"
NEW = {
    "synthetic/water_image_space.zmx": {
        "repo": "this repository (written for the project)",
        "path": "tests/data/third_party/synthetic/water_image_space.zmx",
        "commit": "n/a", "licence": "MIT (this project's; written from scratch for rwwarp)"},
    "synthetic/ef35mm_f2.0_stop_diam.zmx": {
        "repo": "singer-yang/DeepLens (modified here, issue 28)", "path": "datasets/lenses/camera/ef35mm_f2.0.zmx",
        "commit": "e15add06f42c145c4be02331a573459b34541dd0",
        "licence": "Apache-2.0; changed: the stop (SURF 6) given DIAM 9.8795 1 (the r of the DeepLens JSON's "
                   "aperture) and WAVL written as WAVM lines (optiland 0.6.3 reads no PWAV for WAVL)"},
}


def text(p):
    raw = open(p, "rb").read()
    return raw.decode("utf-16") if raw[:2] in (b"\xff\xfe", b"\xfe\xff") else raw.decode("latin-1")


def r2_term(p):
    d = json.load(open(p))
    return any(s.get("type") == "Aspheric" and s.get("use_ai2", True) and (s.get("ai") or [0.0])[0] != 0
               for s in d["surfaces"])


man = json.load(open(T + "manifest.json"))
by_file = {e["file"]: e for e in man["files"]}
for out in sys.argv[1:]:
    res = json.load(open(out))
    for p, ref in res.items():
        if p.startswith("_") or "error" in ref:
            continue
        rel = p.split(T, 1)[1]
        key = rel[len("files/"):] if rel.startswith("files/") else "../" + rel
        ref = dict(ref)
        if p.endswith(".json"):
            if r2_term(p):
                ref["paraxial_ignores_r2_term"] = True
        else:
            m = re.search(r"^\s*UNIT\s+(\w+)", text(p), re.M)
            ref["lens_unit"] = m.group(1) if m else "MM"
        e = by_file.get(key)
        if e is None:
            e = dict({"file": key}, **NEW[rel])
            man["files"].append(e)
            by_file[key] = e
        e["sha256"] = hashlib.sha256(open(p, "rb").read()).hexdigest()
        e["reference"] = ref
        if "_versions" in res:  # this entry's tool versions (the manifest's "versions": the first run's)
            e["reference_versions"] = res["_versions"]
json.dump(man, open(T + "manifest.json", "w"), indent=1)
print(len(man["files"]), sum("reference" in e for e in man["files"]))
