"""Generate ``rwwarp/data/glasses_extra.json``: the glasses real lens files name that the makers'
current catalogues (``glasses.json``, see ``make_glass_table.py``) do not hold.

This script documents how the table was made; rwwarp never imports it. Run it in a throwaway
environment that has a copy of the refractiveindex.info database (public domain, CC0 1.0; the copy
used is the one shipped inside optiland 0.6.3, ``optiland/database/data-nk``)::

    python -m venv /tmp/refvenv && /tmp/refvenv/bin/pip install optiland==0.6.3 pyyaml
    /tmp/refvenv/bin/python perf/tools/make_extra_glass_table.py \\
        /tmp/refvenv/lib/python3.*/site-packages/optiland/database/data-nk rwwarp/data/glasses_extra.json

Sources
-------
* refractiveindex.info database (M. Polyanskiy, CC0): the makers' Zemax catalogues and data sheets it
  transcribes -- HIKARI (Nikon), SUMITA, OHARA, CDGM, HOYA (glasses the current spreadsheets no longer
  list), SCHOTT legacy glasses (F5, K7, LF5, LAFN7, ...), LZOS, and optical plastics (ZEONEX E48R,
  OPTOREZ 1330, polystyrene, ... with the fits of Sultanova et al. 2009). Formula entries are copied
  unchanged as the database's own formulas (``RII1``, ``RII2``, ``RII3`` in :mod:`rwwarp.materials`);
  glasses given only as tabulated indices (SCHOTT B 270 data sheet, LZOS) get a least-squares fit of the
  Schott power series n^2 = A0 + A1 l^2 + A2 l^-2 + A3 l^-4 + A4 l^-6 + A5 l^-8 to the maker's points
  (the largest residual is stored as ``fit_residual``).
* OKP4, OKP4HT (Osaka Gas Chemicals), COC (TOPAS), POLYSTYR: the Schott power-series coefficients of the
  Zemax MISC catalogue as listed in DeepLens's material table (``deeplens/optics/materials.py``,
  Apache-2.0) -- numbers, not code.
* ZEONEX E48R: the only published fit (2 terms) misses vd by 4, so the maker's data-sheet nd / vd
  (1.531 / 56.0) as a model glass.

Names: the makers' names (file stems). A name the shipped table already has keeps its shipped entry;
a name that two catalogues share is stored as ``"CATALOG:NAME"`` after the first; LZOS glasses only as
``"LZOS:NAME"`` (Russian names clash with SCHOTT's).
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import yaml

CATALOGS = [("hikari", "HIKARI"), ("sumita", "SUMITA"), ("ohara", "OHARA"), ("cdgm", "CDGM"), ("hoya", "HOYA"),
            ("schott", "SCHOTT"), ("schott/obsolete", "SCHOTT"), ("schott/misc", "SCHOTT"), ("lzos", "LZOS")]
PLASTICS = {  # folder under other/commercial plastics or organic -> (name, aliases)
    "other/commercial plastics/Optorez1330/Sultanova.yml": ("OZ1330", ["OPTOREZ1330", "OPTOREZ-1330"]),
}
MISC = {
    # Schott power series A0..A5 (Zemax MISC catalogue, as listed in DeepLens's material table)
    "OKP4": [2.49230, -1.46713e-3, 3.04056e-2, -2.31960e-4, 3.62928e-4, -1.89103e-5],
    "OKP4HT": [2.55219, 6.51282e-5, 3.57452e-2, 8.49831e-4, 8.47777e-5, 1.58990e-5],
    "COC": [2.28449, 1.02952e-2, 3.73494e-2, -9.28410e-3, 1.73290e-3, -1.15203e-4],
    "POLYSTYR": [2.44598, 2.21429e-5, 2.72989e-2, 3.01211e-4, 8.88934e-5, -1.75708e-6],
}
MISC_ALIASES = {"POLYSTYR": ["PS", "POLYSTYRENE"], "COC": ["TOPAS"]}
#: the maker's own dispersion formula where the database holds only tabulated points over a narrower range:
#: name -> (formula, coefficients, range_um, source); replaces the entry the database gives (issue 28)
MAKER_FORMULAS = {
    # SCHOTT's Zemax catalogue "schott glasses preferred and special" (June 2025 B.AGF): "NM B270 1 1 1.523080
    # 58.571369" (formula 1 = Schott power series A0..A5), "CD 2.286575 -8.7334582E-3 1.1742884E-2 2.9041756E-4
    # -1.2506695E-5 9.2646253E-7"; they give its nd 1.523080 and vd 58.571369 to all printed digits. Range
    # 0.334-2.5 um: the validity issue 28 gives for the maker's formula (the database's points: 0.436-0.656 um).
    "B270": ("Schott", [2.286575, -8.7334582e-3, 1.1742884e-2, 2.9041756e-4, -1.2506695e-5, 9.2646253e-7],
             [0.334, 2.5], "SCHOTT Zemax catalogue (schott glasses preferred and special, June 2025 B.AGF), "
             "NM B270 formula 1 (Schott), nd 1.523080, vd 58.571369"),
}
#: plastics whose published fits are poor (2-term, vd off by 4): the maker's data-sheet nd / vd as a model glass
MODEL = {"E48R": (1.5310, 56.0, ["ZEONEX", "ZEONEX-E48R", "ZEONEX_E48R", "ZEONEXE48R", "COP"],
                  "ZEON ZEONEX E48R data sheet: nd 1.531, vd 56.0 (model glass)")}
RII_FORMULA = {1: "RII1", 2: "RII2", 3: "RII3"}
#: catalogues whose names clash with other makers' glasses of different composition (LZOS "BK10" is not
#: SCHOTT's BK10): stored only as "CATALOG:NAME"
QUALIFIED_ONLY = {"LZOS"}


def _entry(doc):
    for d in doc.get("DATA", []):
        t = d["type"].strip()
        if t.startswith("formula"):
            num = int(t.split()[1])
            if num not in RII_FORMULA:
                return None
            coeffs = [float(c) for c in str(d["coefficients"]).split()]
            rng = [float(v) for v in str(d["wavelength_range"]).split()]
            return {"formula": RII_FORMULA[num], "coefficients": coeffs, "range_um": rng}
    for d in doc.get("DATA", []):
        if d["type"].strip() in ("tabulated n", "tabulated nk"):
            rows = np.array([[float(v) for v in line.split()[:2]] for line in d["data"].strip().splitlines()])
            lam, n = rows[:, 0], rows[:, 1]
            keep = (lam >= 0.36) & (lam <= 1.1)
            lam, n = lam[keep], n[keep]
            if len(lam) < 8:
                return None
            A = np.stack([np.ones_like(lam), lam ** 2, lam ** -2, lam ** -4, lam ** -6, lam ** -8], 1)
            c, *_ = np.linalg.lstsq(A, n * n, rcond=None)
            res = float(np.max(np.abs(np.sqrt(A @ c) - n)))
            return {"formula": "Schott", "coefficients": [float(v) for v in c],
                    "range_um": [float(lam.min()), float(lam.max())], "fit_residual": res}
    return None


def main(root, out):
    root = Path(root)
    shipped = json.loads((Path(__file__).resolve().parents[2] / "rwwarp" / "data" / "glasses.json").read_text())
    taken = {k.lower() for k in shipped["glasses"]}
    for e in shipped["glasses"].values():
        taken |= {a.lower() for a in e.get("aliases", ())}
    glasses = {}

    def add(name, entry, catalog, source, aliases=()):
        key = name if name.lower() not in taken and catalog not in QUALIFIED_ONLY else f"{catalog}:{name}"
        if key.lower() in taken:
            return
        if name in MAKER_FORMULAS:
            formula, coeffs, rng, source = MAKER_FORMULAS[name]
            entry = {"formula": formula, "coefficients": coeffs, "range_um": rng}
        entry = dict(entry, catalog=catalog, nd=None, vd=None, source=source)
        if aliases:
            entry["aliases"] = [a for a in aliases if a.lower() not in taken]
            taken.update(a.lower() for a in entry["aliases"])
        glasses[key] = entry
        taken.add(key.lower())

    for folder, catalog in CATALOGS:
        for f in sorted((root / "glass" / folder).glob("*.yml")):
            doc = yaml.safe_load(f.read_text())
            e = _entry(doc)
            if e is None:
                continue
            add(f.stem, e, catalog, f"refractiveindex.info database (CC0), glass/{folder}/{f.name}")
    for rel, (name, aliases) in PLASTICS.items():
        doc = yaml.safe_load((root / rel).read_text())
        add(name, _entry(doc), "MISC", f"refractiveindex.info database (CC0), {rel}", aliases)
    for name, c in MISC.items():
        add(name, {"formula": "Schott", "coefficients": c, "range_um": [0.4, 0.8]}, "MISC",
            "Zemax MISC catalogue Schott power series, as listed in DeepLens deeplens/optics/materials.py",
            MISC_ALIASES.get(name, ()))
    fs = shipped["glasses"]["fused_silica"]
    add("C79-80", {k: fs[k] for k in ("formula", "coefficients", "range_um")}, "CORNING",
        "Corning HPFS 7980 (Zemax name C79-80) is synthetic fused silica: Malitson 1965, as fused_silica",
        ["CORNING7980", "HPFS7980", "7980"])
    for name, (nd, vd, aliases, src) in MODEL.items():
        add(name, {"formula": "Model", "coefficients": [nd, vd], "range_um": [0.4, 1.1]}, "MISC", src, aliases)
    table = {"format": "rwwarp-glasses/1",
             "notes": "glasses beyond the makers' current catalogues; generated by perf/tools/make_extra_glass_table.py",
             "catalogs": {}, "glasses": glasses}
    lines = [f" {json.dumps(k)}: {json.dumps(v, separators=(',', ':'))}" for k, v in glasses.items()]
    head = json.dumps({k: v for k, v in table.items() if k != "glasses"}, separators=(",", ":"))[:-1]
    Path(out).write_text(head + ',"glasses":{\n' + ",\n".join(lines) + "\n}}\n")
    print(f"{len(glasses)} glasses -> {out}")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
