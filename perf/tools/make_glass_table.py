"""Generate ``rwwarp/data/glasses.json``, the glass table shipped with rwwarp.

This script documents how the table was made; rwwarp itself never imports it and does not depend
on the ``opticalglass`` package. Run it in a throwaway environment::

    python -m venv /tmp/ogvenv && /tmp/ogvenv/bin/pip install opticalglass==1.1.1
    /tmp/ogvenv/bin/python perf/tools/make_glass_table.py rwwarp/data/glasses.json

Sources
-------
Catalogue glasses: the vendors' own catalogue spreadsheets as shipped inside the ``opticalglass``
package (M. J. Hayford, https://github.com/mjhoptics/opticalglass, version 1.1.1, ``data/``):

- ``SCHOTT.xls``  SCHOTT optical glass data sheet, status 2018-06-01 (Sellmeier, B1..B3, C1..C3)
- ``OHARA.xlsx``  OHARA glass catalogue (Sellmeier, A1..A3 numerators, B1..B3 in um^2)
- ``HOYA.xlsx``   HOYA glass catalogue (Schott power series A0..A5, given as mantissa + exponent)
- ``CDGM.xls``    CDGM (Chengdu Guangming) glass catalogue (Schott power series A0..A5)

The coefficients are copied unchanged (the spreadsheets store the makers' printed decimals, which
round-trip through float64; HOYA's mantissa/exponent pairs are joined as decimal strings before
conversion so no binary rounding is added). ``nd`` and ``vd`` are the makers' published values
(the spreadsheet columns nd and vd). ``range_um`` is the span of wavelengths at which the maker
tabulates refractive indices for that glass (the range the formula was fitted to).

Coefficient order is the Zemax AGF ``CD`` order: Sellmeier1 ``[K1, L1, K2, L2, K3, L3]``
(n^2 - 1 = sum K_i lambda^2 / (lambda^2 - L_i), L in um^2); Schott ``[A0, A1, A2, A3, A4, A5]``
(n^2 = A0 + A1 lambda^2 + A2 lambda^-2 + A3 lambda^-4 + A4 lambda^-6 + A5 lambda^-8).

Names: the makers' spellings, stripped of blanks inside OHARA names ("S-BSL 7" -> "S-BSL7", as in
OHARA's own AGF files). Lookups in rwwarp are case-insensitive. Where two catalogues use the same
name (case-insensitively) the first catalogue in ``CATALOG_ORDER`` keeps the plain name and the
other entry is stored as ``"CATALOG:NAME"`` (e.g. ``"CDGM:F2"``); every glass can also be asked
for as ``"CATALOG:NAME"``.

Non-catalogue materials (hand-entered below, each with its citation in "source"):

- fused silica: I. H. Malitson, "Interspecimen comparison of the refractive index of fused
  silica", J. Opt. Soc. Am. 55, 1205-1209 (1965), 3-term Sellmeier, 0.21-3.71 um. Malitson
  publishes resonance wavelengths lambda_i; the table stores L_i = lambda_i^2.
- PMMA: G. Beadie, M. Brindza, R. A. Flynn, A. Rosenberg, J. S. Shirk, "Refractive index
  measurements of poly(methyl methacrylate) (PMMA) from 0.4-1.6 um", Appl. Opt. 54, F139-F143
  (2015), 20.1 degC, absolute accuracy < 2e-4. Their fit is a Laurent series in lambda^2 that is
  exactly Zemax's "Extended 3" form. (The one-term Sellmeier fit of Sultanova et al. 2009 was not
  used: it gives vd = 53, against vd = 59.2 measured by the same authors and 57-59 on datasheets.)
- polycarbonate: N. Sultanova, S. Kasarova, I. Nikolov, "Dispersion properties of optical
  polymers", Acta Physica Polonica A 116, 585-587 (2009), one-term Sellmeier fit by
  M. Polyanskiy (refractiveindex.info), 0.4368-1.052 um, 20 degC.
These have no maker-published nd/vd, so those fields are null.
"""
import json
import math
import sys
import warnings

CATALOG_ORDER = ("SCHOTT", "OHARA", "HOYA", "CDGM")

# Spectral lines used by the spreadsheets' column headers, wavelength in nm.
LINES_NM = {
    "t": 1013.98, "s": 852.11, "A'": 768.195, "r": 706.5188, "C": 656.2725, "C'": 643.8469,
    "He-Ne": 632.8, "D": 589.2938, "d": 587.5618, "e": 546.074, "F": 486.1327, "F'": 479.9914,
    "He-Cd": 441.57, "g": 435.8343, "h": 404.6561, "i": 365.014,
}

SPECIAL = {
    "fused_silica": {
        "formula": "Sellmeier1",
        "coefficients": [0.6961663, 0.0684043 ** 2, 0.4079426, 0.1162414 ** 2, 0.8974794, 9.896161 ** 2],
        "range_um": [0.21, 3.71], "catalog": "MISC", "nd": None, "vd": None,
        "aliases": ["F_SILICA", "SILICA", "FUSEDSILICA", "fused silica", "FUSED_SILICA", "SiO2"],
        "source": "I. H. Malitson, J. Opt. Soc. Am. 55, 1205-1209 (1965); L_i = lambda_i^2",
    },
    "PMMA": {
        "formula": "Extended3",
        "coefficients": [2.1778, 6.1209e-3, -1.5004e-3, 2.3678e-2, -4.2137e-3, 7.3417e-4, -4.5042e-5,
                         0.0, 0.0],
        "range_um": [0.42, 1.62], "catalog": "MISC", "nd": None, "vd": None,
        "aliases": ["ACRYLIC", "poly(methyl methacrylate)"],
        "source": "G. Beadie, M. Brindza, R. A. Flynn, A. Rosenberg, J. S. Shirk, Appl. Opt. 54, "
                  "F139-F143 (2015), 20.1 degC",
    },
    "PC": {
        "formula": "Sellmeier1",
        "coefficients": [1.4182, 0.021304, 0.0, 0.0, 0.0, 0.0],
        "range_um": [0.4368, 1.052], "catalog": "MISC", "nd": None, "vd": None,
        "aliases": ["POLYCARBONATE", "POLYCARB"],
        "source": "N. Sultanova, S. Kasarova, I. Nikolov, Acta Physica Polonica A 116, 585-587 (2009); "
                  "Sellmeier fit by M. Polyanskiy (refractiveindex.info), 20 degC",
    },
}

CATALOG_META = {
    "SCHOTT": {"source": "SCHOTT optical glass data sheet (SCHOTT.xls, status 2018-06-01), "
                         "as shipped in opticalglass 1.1.1"},
    "OHARA": {"source": "OHARA optical glass catalogue (OHARA.xlsx), as shipped in opticalglass 1.1.1"},
    "HOYA": {"source": "HOYA optical glass catalogue (HOYA.xlsx), as shipped in opticalglass 1.1.1"},
    "CDGM": {"source": "CDGM optical glass catalogue (CDGM.xls), as shipped in opticalglass 1.1.1"},
    "MISC": {"source": "published dispersion fits, see each glass's 'source'"},
}


def _wavelength_nm(label):
    """Wavelength in nm of a spreadsheet index column header (number or spectral line letter)."""
    if isinstance(label, (int, float)):
        return float(label)
    label = str(label).strip()
    if label in LINES_NM:
        return LINES_NM[label]
    return float(label)


def _range_um(row_indices):
    """[lo, hi] in um over the wavelengths at which a refractive index is tabulated."""
    wl = []
    for label, value in row_indices.items():
        try:
            v = float(value)
        except (TypeError, ValueError):
            continue
        if math.isfinite(v) and v > 1.0:
            wl.append(_wavelength_nm(label))
    return [round(min(wl) / 1000.0, 6), round(max(wl) / 1000.0, 6)]


def _catalog_rows():
    """Yield (catalog, name, formula, coefficients, nd, vd, range_um) for every vendor glass."""
    from opticalglass import cdgm, hoya, ohara, schott

    cats = {"SCHOTT": schott.SchottCatalog, "OHARA": ohara.OharaCatalog,
            "HOYA": hoya.HoyaCatalog, "CDGM": cdgm.CDGMCatalog}
    for catname in CATALOG_ORDER:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            df = cats[catname]().df
        coef = df["dispersion coefficients"]
        for gname in df.index:
            row = df.loc[gname]
            name = str(gname).strip()
            if catname == "OHARA":
                name = name.replace(" ", "")
            if catname in ("SCHOTT", "OHARA"):
                c = [float(x) for x in coef.loc[gname].tolist()]  # B1 B2 B3 C1 C2 C3 / A1 A2 A3 B1 B2 B3
                formula, coefficients = "Sellmeier1", [c[0], c[3], c[1], c[4], c[2], c[5]]
            elif catname == "HOYA":
                c = coef.loc[gname].tolist()  # A0 A0pow A1 A1pow ...
                coefficients = [float(f"{float(c[2 * k])!r}e{int(c[2 * k + 1])}") for k in range(6)]
                formula = "Schott"
            else:
                formula, coefficients = "Schott", [float(x) for x in coef.loc[gname].tolist()]
            nd = float(row[("refractive indices", "d")])
            vd = float(row[("abbe number", "vd")])
            yield catname, name, formula, coefficients, nd, vd, _range_um(row["refractive indices"])


def build_table():
    """Return the table dict ``{"format", "catalogs", "glasses"}``."""
    glasses, seen = {}, {}
    for catname, name, formula, coefficients, nd, vd, rng in _catalog_rows():
        entry = {"formula": formula, "coefficients": coefficients, "range_um": rng, "catalog": catname,
                 "nd": nd, "vd": vd}
        key = name if name.lower() not in seen else f"{catname}:{name}"
        if key.lower() in seen:
            raise RuntimeError(f"duplicate glass {key} in {catname}")
        seen[key.lower()] = key
        glasses[key] = entry
    for key, entry in SPECIAL.items():
        if key.lower() in seen:
            raise RuntimeError(f"special material {key} collides with a catalogue glass")
        glasses[key] = dict(entry)
    return {"format": "rwwarp-glasses/1",
            "notes": "coefficients in Zemax AGF CD order; wavelengths in um; indices relative to air; "
                     "nd/vd are the makers' published values (null where none); generated by "
                     "perf/tools/make_glass_table.py",
            "catalogs": CATALOG_META, "glasses": glasses}


def dump(table, path):
    """Write the table as JSON with one glass per line."""
    lines = ["{", f'"format": {json.dumps(table["format"])},', f'"notes": {json.dumps(table["notes"])},',
             f'"catalogs": {json.dumps(table["catalogs"])},', '"glasses": {']
    items = list(table["glasses"].items())
    for i, (k, v) in enumerate(items):
        lines.append(f"{json.dumps(k)}: {json.dumps(v)}" + ("," if i < len(items) - 1 else ""))
    lines += ["}", "}"]
    with open(path, "w", encoding="utf-8") as f:
        f.write("\n".join(lines) + "\n")


if __name__ == "__main__":
    out = sys.argv[1] if len(sys.argv) > 1 else "rwwarp/data/glasses.json"
    table = build_table()
    dump(table, out)
    json.load(open(out, encoding="utf-8"))  # round-trip check
