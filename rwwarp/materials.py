"""Optical materials: dispersion formulas, the shipped glass table, Zemax AGF catalogues, model glasses.

Units: wavelengths in micrometres. Indices are relative to air and air has n = 1 exactly, as in
the Zemax glass catalogues.

Dispersion formulas (``lam`` = wavelength in um, ``c`` = coefficients in Zemax AGF ``CD`` order):

====  ============  ==========================================================================
AGF   name          formula
====  ============  ==========================================================================
1     Schott        n^2 = c0 + c1 lam^2 + c2 lam^-2 + c3 lam^-4 + c4 lam^-6 + c5 lam^-8
2     Sellmeier1    n^2 - 1 = sum_{i=0..2} c_{2i} lam^2 / (lam^2 - c_{2i+1})
3     Herzberger    n = c0 + c1 L + c2 L^2 + c3 lam^2 + c4 lam^4 + c5 lam^6,  L = 1/(lam^2 - 0.028)
4     Sellmeier2    n^2 - 1 = c0 + c1 lam^2 / (lam^2 - c2^2) + c3 / (lam^2 - c4^2)
5     Conrady       n = c0 + c1 / lam + c2 / lam^3.5
6     Sellmeier3    n^2 - 1 = sum_{i=0..3} c_{2i} lam^2 / (lam^2 - c_{2i+1})
7     Handbook1     n^2 = c0 + c1 / (lam^2 - c2) - c3 lam^2          (Handbook of Optics 1)
8     Handbook2     n^2 = c0 + c1 lam^2 / (lam^2 - c2) - c3 lam^2    (Handbook of Optics 2)
9     Sellmeier4    n^2 = c0 + c1 lam^2 / (lam^2 - c2) + c3 lam^2 / (lam^2 - c4)
10    Extended      n^2 = c0 + c1 lam^2 + c2 lam^-2 + c3 lam^-4 + ... + c7 lam^-12
11    Sellmeier5    n^2 - 1 = sum_{i=0..4} c_{2i} lam^2 / (lam^2 - c_{2i+1})
12    Extended2     n^2 = c0 + c1 lam^2 + c2 lam^-2 + c3 lam^-4 + c4 lam^-6 + c5 lam^-8
                          + c6 lam^4 + c7 lam^6
13    Extended3     n^2 = c0 + c1 lam^2 + c2 lam^4 + c3 lam^-2 + c4 lam^-4 + c5 lam^-6
                          + c6 lam^-8 + c7 lam^-10 + c8 lam^-12
-     Constant      n = c0                                            (air, vacuum)
-     Model         n = nd + (nd - 1)/vd * (lam^-2 - lam_d^-2) / (lam_F^-2 - lam_C^-2),  c = (nd, vd)
-     ModelLines    the Model law with its own lines, c = (nd, vd, lam_d, lam_F, lam_C)
-     RII1          n^2 - 1 = c0 + sum_i c_{2i-1} lam^2 / (lam^2 - c_{2i}^2)      (refractiveindex.info 1)
-     RII2          n^2 - 1 = c0 + sum_i c_{2i-1} lam^2 / (lam^2 - c_{2i})        (refractiveindex.info 2)
-     RII3          n^2 = c0 + sum_i c_{2i-1} lam^c_{2i}                        (refractiveindex.info 3)
====  ============  ==========================================================================

The ``Model`` formula is the two-term Cauchy law n = A + B / lam^2 through (nd, vd) (as in
Ditteon, "Modern Geometrical Optics", eqs. 1.37-1.39, and DeepLens' "n/V" materials, here with
the exact d, F, C wavelengths); written around nd it returns nd bit-exactly at the d line.

Names: :func:`get_material` looks names up case-insensitively; glasses added by
:func:`register_catalog` take precedence (latest first) over the shipped table
``rwwarp/data/glasses.json`` (SCHOTT, OHARA, HOYA, CDGM catalogues, fused silica, PMMA,
polycarbonate; ``perf/tools/make_glass_table.py`` documents its sources). Every catalogue glass
can also be named ``"CATALOG:NAME"`` (e.g. ``"CDGM:F2"``, ``"SCHOTT:N-BK7"``). ``"nd/vd"`` and
``"nd,vd"`` strings give model glasses.
"""
from __future__ import annotations

import codecs
import difflib
import functools
import json
import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import GlassError, LensFileError

__all__ = ["Material", "get_material", "resolve_glass", "GlassSubstitutionWarning", "model_glass", "load_agf", "register_catalog", "reset_catalogs",
           "available_materials", "WAVELENGTH_D_UM", "WAVELENGTH_F_UM", "WAVELENGTH_C_UM"]

WAVELENGTH_D_UM = 0.5875618  # helium d line
WAVELENGTH_F_UM = 0.4861327  # hydrogen F line
WAVELENGTH_C_UM = 0.6562725  # hydrogen C line

_TABLE_PATH = Path(__file__).resolve().parent / "data" / "glasses.json"
_EXTRA_PATH = Path(__file__).resolve().parent / "data" / "glasses_extra.json"
_DEEPLENS_PATH = Path(__file__).resolve().parent / "data" / "deeplens_materials.json"


class GlassSubstitutionWarning(UserWarning):
    """A lens file names a glass the tables do not hold and another material stands in for it (a SCHOTT
    lead-free successor, or a model glass from the nd/Vd the file lists); the message names both."""


# ---------------------------------------------------------------------------------------------
# dispersion formulas: each maps (wavelength_um array, coefficient tuple) -> index array
# ---------------------------------------------------------------------------------------------
def _schott(lam, c):
    l2 = lam * lam
    il2 = 1.0 / l2
    return np.sqrt(c[0] + c[1] * l2 + il2 * (c[2] + il2 * (c[3] + il2 * (c[4] + il2 * c[5]))))


def _make_sellmeier(terms):
    def sellmeier(lam, c):
        l2 = lam * lam
        n2 = 1.0
        for i in range(terms):
            n2 = n2 + c[2 * i] * l2 / (l2 - c[2 * i + 1])
        return np.sqrt(n2)
    return sellmeier


def _herzberger(lam, c):
    l2 = lam * lam
    big_l = 1.0 / (l2 - 0.028)
    return c[0] + big_l * (c[1] + big_l * c[2]) + l2 * (c[3] + l2 * (c[4] + l2 * c[5]))


def _sellmeier2(lam, c):
    l2 = lam * lam
    return np.sqrt(1.0 + c[0] + c[1] * l2 / (l2 - c[2] * c[2]) + c[3] / (l2 - c[4] * c[4]))


def _conrady(lam, c):
    return c[0] + c[1] / lam + c[2] / lam ** 3.5


def _handbook1(lam, c):
    l2 = lam * lam
    return np.sqrt(c[0] + c[1] / (l2 - c[2]) - c[3] * l2)


def _handbook2(lam, c):
    l2 = lam * lam
    return np.sqrt(c[0] + c[1] * l2 / (l2 - c[2]) - c[3] * l2)


def _sellmeier4(lam, c):
    l2 = lam * lam
    return np.sqrt(c[0] + c[1] * l2 / (l2 - c[2]) + c[3] * l2 / (l2 - c[4]))


def _inverse_powers(l2, coeffs):
    """sum_k coeffs[k] * l2^-(k+1), Horner form."""
    il2 = 1.0 / l2
    acc = 0.0
    for ck in reversed(coeffs):
        acc = (acc + ck) * il2
    return acc


def _extended(lam, c):
    l2 = lam * lam
    return np.sqrt(c[0] + c[1] * l2 + _inverse_powers(l2, c[2:8]))


def _extended2(lam, c):
    l2 = lam * lam
    return np.sqrt(c[0] + l2 * (c[1] + l2 * (c[6] + l2 * c[7])) + _inverse_powers(l2, c[2:6]))


def _extended3(lam, c):
    l2 = lam * lam
    return np.sqrt(c[0] + l2 * (c[1] + l2 * c[2]) + _inverse_powers(l2, c[3:9]))


def _constant(lam, c):
    return np.full(np.shape(lam), c[0], dtype=np.float64)


_INV_D2 = 1.0 / (WAVELENGTH_D_UM * WAVELENGTH_D_UM)
_INV_F2_MINUS_C2 = 1.0 / (WAVELENGTH_F_UM * WAVELENGTH_F_UM) - 1.0 / (WAVELENGTH_C_UM * WAVELENGTH_C_UM)


def _model(lam, c):
    nd, vd = c[0], c[1]
    return nd + (nd - 1.0) / vd * (1.0 / (lam * lam) - _INV_D2) / _INV_F2_MINUS_C2


def _model_lines(lam, c):
    nd, vd, ld, lf, lc = c[0], c[1], c[2], c[3], c[4]
    return nd + (nd - 1.0) / vd * (1.0 / (lam * lam) - 1.0 / (ld * ld)) / (1.0 / (lf * lf) - 1.0 / (lc * lc))


def _rii1(lam, c):
    l2 = lam * lam
    n2 = 1.0 + c[0]
    for i in range(1, len(c) - 1, 2):
        if c[i] != 0.0:
            n2 = n2 + c[i] * l2 / (l2 - c[i + 1] * c[i + 1])
    return np.sqrt(n2)


def _rii2(lam, c):
    l2 = lam * lam
    n2 = 1.0 + c[0]
    for i in range(1, len(c) - 1, 2):
        if c[i] != 0.0:
            n2 = n2 + c[i] * l2 / (l2 - c[i + 1])
    return np.sqrt(n2)


def _rii3(lam, c):
    n2 = c[0] + 0.0 * lam
    for i in range(1, len(c) - 1, 2):
        if c[i] != 0.0:
            n2 = n2 + c[i] * lam ** c[i + 1]
    return np.sqrt(n2)


# name -> (Zemax AGF formula number or None, number of coefficients, evaluator)
_FORMULAS = {
    "Schott": (1, 6, _schott),
    "Sellmeier1": (2, 6, _make_sellmeier(3)),
    "Herzberger": (3, 6, _herzberger),
    "Sellmeier2": (4, 5, _sellmeier2),
    "Conrady": (5, 3, _conrady),
    "Sellmeier3": (6, 8, _make_sellmeier(4)),
    "Handbook1": (7, 4, _handbook1),
    "Handbook2": (8, 4, _handbook2),
    "Sellmeier4": (9, 5, _sellmeier4),
    "Extended": (10, 8, _extended),
    "Sellmeier5": (11, 10, _make_sellmeier(5)),
    "Extended2": (12, 8, _extended2),
    "Extended3": (13, 9, _extended3),
    "Constant": (None, 1, _constant),
    "Model": (None, 2, _model),
    "ModelLines": (None, 5, _model_lines),
    "RII1": (None, 17, _rii1),
    "RII2": (None, 17, _rii2),
    "RII3": (None, 17, _rii3),
}
_FORMULA_BY_NUMBER = {v[0]: k for k, v in _FORMULAS.items() if v[0] is not None}
_FORMULA_BY_KEY = {k.lower(): k for k in _FORMULAS}
_FORMULA_BY_KEY.update({"handbookofoptics1": "Handbook1", "handbookofoptics2": "Handbook2",
                        "extended1": "Extended", "sellmeier": "Sellmeier1", "cauchy": "Model"})


def _canonical_formula(formula) -> str:
    """Canonical formula name for a name ("Sellmeier 1", "handbook of optics 2") or AGF number."""
    if isinstance(formula, (int, np.integer)) and not isinstance(formula, bool):
        if int(formula) in _FORMULA_BY_NUMBER:
            return _FORMULA_BY_NUMBER[int(formula)]
    elif isinstance(formula, str):
        key = re.sub(r"[\s_\-]", "", formula).lower()
        if key in _FORMULA_BY_KEY:
            return _FORMULA_BY_KEY[key]
        if key.isdigit() and int(key) in _FORMULA_BY_NUMBER:
            return _FORMULA_BY_NUMBER[int(key)]
    raise GlassError(f"unsupported dispersion formula {formula!r} (known: {', '.join(_FORMULAS)}, "
                     f"or Zemax AGF formula numbers 1-13)")


# ---------------------------------------------------------------------------------------------
# Material
# ---------------------------------------------------------------------------------------------
# refractive indices at scalar wavelengths, keyed by (formula, coefficients, wavelength): a PSF asks for
# the same few dozen values many times (surface tables, pupils, DOE scale)
_N_CACHE: dict = {}
_N_CACHE_MAX = 4096


@dataclass(frozen=True)
class Material:
    """An optical material: a dispersion formula and its coefficients (immutable).

    Attributes:
        name: lookup name (as in the table, e.g. ``"N-SK16"``, ``"CDGM:F2"``, ``"1.5168/64.17"``).
        formula: dispersion formula name (Zemax name, see the module docstring), e.g. ``"Sellmeier1"``.
        coefficients: formula coefficients in Zemax AGF ``CD`` order (wavelengths in um); padded
            with zeros / cut to the formula's count, as Zemax reads a ``CD`` line.
        wavelength_range_um: ``(lo, hi)`` in um where the maker's data (formula fit or AGF ``LD``
            line) is valid, or ``None`` if unknown. Informative: :meth:`n` does not enforce it.
        catalog: catalogue the glass comes from (``"SCHOTT"``, ``"CDGM"``, an AGF file's stem...).
        catalog_nd, catalog_vd: the maker's published nd and Abbe number vd, if any (for checks;
            the properties :attr:`nd` and :attr:`vd` are always computed from the formula).
        source: where the data comes from (citation or file).
    """

    name: str
    formula: str
    coefficients: tuple
    wavelength_range_um: tuple | None = None
    catalog: str | None = None
    catalog_nd: float | None = None
    catalog_vd: float | None = None
    source: str | None = None

    def __post_init__(self):
        formula = _canonical_formula(self.formula)
        count = _FORMULAS[formula][1]
        try:
            coeffs = [float(c) for c in self.coefficients]
        except (TypeError, ValueError):
            raise GlassError(f"glass {self.name!r}: coefficients must be numbers, got {self.coefficients!r}")
        if not all(math.isfinite(c) for c in coeffs):
            raise GlassError(f"glass {self.name!r}: non-finite dispersion coefficient in {coeffs}")
        rng = self.wavelength_range_um
        if rng is not None:
            rng = (float(rng[0]), float(rng[1]))
        object.__setattr__(self, "formula", formula)
        object.__setattr__(self, "coefficients", tuple((coeffs + [0.0] * count)[:count]))
        object.__setattr__(self, "wavelength_range_um", rng)
        for attr in ("catalog_nd", "catalog_vd"):
            v = getattr(self, attr)
            object.__setattr__(self, attr, None if v is None else float(v))

    @property
    def agf_formula_number(self) -> int | None:
        """Zemax AGF formula number (1-13), or None for ``Constant`` and ``Model``."""
        return _FORMULAS[self.formula][0]

    def n(self, wavelength_um):
        """Refractive index (relative to air) at ``wavelength_um``.

        Args:
            wavelength_um: wavelength(s) in micrometres, float or array-like, > 0.

        Returns:
            float64 index of the same shape (a numpy float64 scalar for a scalar input).
        """
        if isinstance(wavelength_um, (float, int, np.floating)) and not isinstance(wavelength_um, bool):
            key = (self.formula, self.coefficients, float(wavelength_um))
            hit = _N_CACHE.get(key)
            if hit is None:
                hit = self._n(wavelength_um)
                if len(_N_CACHE) >= _N_CACHE_MAX:
                    _N_CACHE.clear()
                _N_CACHE[key] = hit
            return hit
        return self._n(wavelength_um)

    def _n(self, wavelength_um):
        lam = np.asarray(wavelength_um, dtype=np.float64)
        if not np.all(lam > 0.0) or not np.all(np.isfinite(lam)):
            raise ValueError(f"{self.name}: wavelength_um must be positive and finite, got {wavelength_um!r}")
        out = np.asarray(_FORMULAS[self.formula][2](lam, self.coefficients), dtype=np.float64)
        if out.shape != lam.shape:
            out = np.broadcast_to(out, lam.shape).copy()
        return out[()] if out.ndim == 0 else out

    @property
    def nd(self) -> float:
        """Index at the helium d line (0.5875618 um), from the formula."""
        return float(self.n(WAVELENGTH_D_UM))

    @property
    def vd(self) -> float:
        """Abbe number (nd - 1) / (nF - nC), F = 0.4861327 um, C = 0.6562725 um; inf if non-dispersive."""
        n_d, n_f, n_c = self.n(np.array([WAVELENGTH_D_UM, WAVELENGTH_F_UM, WAVELENGTH_C_UM]))
        dn = n_f - n_c
        return math.inf if dn == 0.0 else float((n_d - 1.0) / dn)

    def __repr__(self):
        cat = f", catalog={self.catalog!r}" if self.catalog else ""
        return f"Material({self.name!r}, formula={self.formula!r}{cat})"


_AIR = Material("air", "Constant", (1.0,), catalog="MISC", source="n = 1 (catalogue indices are relative to air)")
_VACUUM = Material("vacuum", "Constant", (1.0,), catalog="MISC", source="n = 1")


def model_glass(nd: float, vd: float, lines_um=None) -> Material:
    """Model glass through (nd, vd), like Zemax's MODEL glass (without partial dispersion).

    Dispersion: two-term Cauchy n(lam) = A + B / lam^2 with A, B set so that n(lam_d) = nd and
    (nd - 1) / (n(lam_F) - n(lam_C)) = vd, evaluated as
    n = nd + (nd - 1) / vd * (lam^-2 - lam_d^-2) / (lam_F^-2 - lam_C^-2), lam in um
    (lam_d = 0.5875618, lam_F = 0.4861327, lam_C = 0.6562725). Gives nd exactly at the d line
    and vd to rounding (~1e-12).

    Args:
        nd: index at the d line (dimensionless, > 0).
        vd: Abbe number (dimensionless, non-zero; ``inf`` gives a non-dispersive material).
        lines_um: optional ``(d, F, C)`` wavelengths (um) that define nd and vd in the source format
            (DeepLens: 0.5876, 0.4861, 0.6563); default the exact helium d / hydrogen F, C lines.

    Returns:
        the :class:`Material` named ``"nd/vd"`` (``"nd/vd@d,F,C"`` with ``lines_um``).
    """
    nd, vd = float(nd), float(vd)
    if not (math.isfinite(nd) and nd > 0.0) or math.isnan(vd) or vd == 0.0:
        raise GlassError(f"model glass needs a finite nd > 0 and a non-zero vd, got nd={nd!r}, vd={vd!r}")
    if lines_um is not None:
        ld, lf, lc = (float(v) for v in lines_um)
        if not (0.0 < lf < ld < lc):
            raise GlassError(f"model glass lines must satisfy 0 < F < d < C (um), got {lines_um!r}")
        return Material(f"{nd!r}/{vd!r}@{ld!r},{lf!r},{lc!r}", "ModelLines", (nd, vd, ld, lf, lc), catalog="MODEL",
                        catalog_nd=nd, catalog_vd=vd, source="model glass (Cauchy through nd, vd at the given lines)")
    return Material(f"{nd!r}/{vd!r}", "Model", (nd, vd), catalog="MODEL", catalog_nd=nd, catalog_vd=vd,
                    source="model glass (Cauchy through nd, vd)")


# ---------------------------------------------------------------------------------------------
# Zemax AGF catalogues
# ---------------------------------------------------------------------------------------------
def _decode(data: bytes, path) -> str:
    """Text of an AGF file: UTF-16 (with or without BOM), UTF-8 (with or without BOM), else Latin-1."""
    try:
        if data.startswith(codecs.BOM_UTF16_LE) or data.startswith(codecs.BOM_UTF16_BE):
            return data.decode("utf-16")
        if data.startswith(codecs.BOM_UTF8):
            return data[len(codecs.BOM_UTF8):].decode("utf-8")
        head = data[:200]
        if len(head) >= 2 and head[1::2].count(0) > len(head) // 4:
            return data.decode("utf-16-le")
        if len(head) >= 2 and head[0::2].count(0) > len(head) // 4:
            return data.decode("utf-16-be")
    except UnicodeDecodeError as e:
        raise LensFileError(f"cannot decode AGF catalogue as UTF-16: {e}", file=str(path)) from None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        return data.decode("latin-1")


def _floats(parts, path, lineno, what):
    try:
        return [float(p) for p in parts]
    except ValueError:
        raise LensFileError(f"line {lineno}: {what}: expected numbers, got {' '.join(parts)!r}",
                            file=str(path)) from None


def load_agf(path) -> dict:
    """Read a Zemax ``.AGF`` glass catalogue.

    Reads ``NM`` (name, formula number, MIL code, nd, vd, ...), ``CD`` (dispersion coefficients)
    and ``LD`` (valid wavelength range, um) records; the other records (CC, GC, ED, TD, OD, IT,
    ...) are skipped. ASCII/UTF-8 or UTF-16 (with BOM), LF or CRLF line ends.

    Args:
        path: file path.

    Returns:
        dict glass name -> :class:`Material`, in file order; ``catalog`` is the file's stem in
        upper case, ``catalog_nd``/``catalog_vd`` come from the NM line.

    Raises:
        LensFileError: unreadable file or a bad line (the message names the file and line number).
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as e:
        raise LensFileError(f"cannot read AGF catalogue: {e}", file=str(path)) from None
    catalog = path.stem.upper()
    out: dict = {}
    cur = None  # the glass being read

    def finish():
        if cur is None:
            return
        if cur["cd"] is None:
            raise LensFileError(f"line {cur['line']}: glass {cur['name']} has no CD (dispersion "
                                f"coefficients) record", file=str(path))
        out[cur["name"]] = Material(cur["name"], cur["formula"], cur["cd"], wavelength_range_um=cur["ld"],
                                    catalog=catalog, catalog_nd=cur["nd"], catalog_vd=cur["vd"],
                                    source=str(path))

    for lineno, line in enumerate(_decode(data, path).splitlines(), start=1):
        parts = line.split()
        if not parts:
            continue
        key = parts[0]
        if key == "NM":
            finish()
            if len(parts) < 3:
                raise LensFileError(f"line {lineno}: NM record needs at least a name and a formula number",
                                    file=str(path))
            name = parts[1]
            try:
                number = float(parts[2])
            except ValueError:
                number = math.nan
            if not (number.is_integer() and int(number) in _FORMULA_BY_NUMBER):
                raise LensFileError(f"line {lineno}: glass {name}: unsupported dispersion formula {parts[2]!r} "
                                    f"(Zemax AGF formulas are 1-13)", file=str(path))
            nd_vd = _floats(parts[4:6], path, lineno, f"glass {name} nd/vd")
            cur = {"name": name, "formula": _FORMULA_BY_NUMBER[int(number)], "line": lineno, "cd": None,
                   "ld": None, "nd": nd_vd[0] if len(nd_vd) > 0 else None,
                   "vd": nd_vd[1] if len(nd_vd) > 1 else None}
        elif key == "CD":
            if cur is None:
                raise LensFileError(f"line {lineno}: CD record before any NM record", file=str(path))
            cd = _floats(parts[1:], path, lineno, f"glass {cur['name']} CD")
            if not all(math.isfinite(c) for c in cd):
                raise LensFileError(f"line {lineno}: glass {cur['name']}: non-finite CD coefficient",
                                    file=str(path))
            cur["cd"] = cd
        elif key == "LD":
            if cur is None:
                raise LensFileError(f"line {lineno}: LD record before any NM record", file=str(path))
            ld = _floats(parts[1:], path, lineno, f"glass {cur['name']} LD")
            if len(ld) < 2 or not (0.0 < ld[0] < ld[1]):
                raise LensFileError(f"line {lineno}: glass {cur['name']}: LD needs 0 < min < max wavelength "
                                    f"in um, got {' '.join(parts[1:])!r}", file=str(path))
            cur["ld"] = (ld[0], ld[1])
        elif not re.fullmatch(r"[A-Z]{2}", key):
            raise LensFileError(f"line {lineno}: not an AGF record (expected a two-letter keyword such as "
                                f"NM, CD, LD): {line.strip()[:60]!r}", file=str(path))
    finish()
    return out


# ---------------------------------------------------------------------------------------------
# lookup: shipped table + registered catalogues
# ---------------------------------------------------------------------------------------------
_REGISTERED: list = []  # dicts name -> Material, in registration order


def _material_from_entry(key: str, entry: dict) -> Material:
    """Material from a glasses.json entry."""
    try:
        return Material(key, entry["formula"], tuple(entry["coefficients"]),
                        wavelength_range_um=entry.get("range_um"), catalog=entry.get("catalog"),
                        catalog_nd=entry.get("nd"), catalog_vd=entry.get("vd"), source=entry.get("source"))
    except (KeyError, TypeError) as e:
        raise GlassError(f"glass table entry {key!r} is malformed ({e!r})") from None


def _load_table_json(path) -> tuple:
    """(dict name -> Material, dict alias -> name) from a file in the glasses.json format."""
    with open(path, encoding="utf-8") as f:
        table = json.load(f)
    materials, aliases = {}, {}
    for key, entry in table["glasses"].items():
        materials[key] = _material_from_entry(key, entry)
        for alias in entry.get("aliases", ()):
            aliases[alias] = key
    return materials, aliases


@functools.lru_cache(maxsize=1)
def _shipped():
    return _load_table_json(_TABLE_PATH)


@functools.lru_cache(maxsize=1)
def _deeplens():
    """DeepLens's own material names as DeepLens defines them (``data/deeplens_materials.json``), only as
    ``"DEEPLENS:<name>"`` (the DeepLens reader looks there first)."""
    return _load_table_json(_DEEPLENS_PATH)


@functools.lru_cache(maxsize=1)
def _extra():
    """Glasses beyond the makers' current catalogues (``data/glasses_extra.json``: HIKARI, SUMITA,
    older OHARA/CDGM/HOYA/SCHOTT glasses, B 270, optical plastics); looked up after the shipped table."""
    return _load_table_json(_EXTRA_PATH)


def _plain_name(m: Material) -> str:
    return m.name.split(":", 1)[1] if ":" in m.name else m.name


@functools.lru_cache(maxsize=1)
def _index() -> dict:
    """lower-case name -> Material. Precedence, lowest first: shipped aliases, shipped names,
    registered catalogues in registration order; "air" and "vacuum" always mean n = 1."""
    shipped, aliases = _shipped()
    extra, extra_aliases = _extra()
    index = {key.lower(): m for key, m in _deeplens()[0].items()}
    index.update({alias.lower(): extra[key] for alias, key in extra_aliases.items()})
    for key, m in extra.items():
        index[key.lower()] = m
        if m.catalog and ":" not in key:
            index[f"{m.catalog}:{key}".lower()] = m
    index.update({alias.lower(): shipped[key] for alias, key in aliases.items()})
    # an extra entry stored as "CATALOG:NAME" because its name clashes with a shipped glass is the maker's
    # other data set (e.g. CDGM's Zemax-catalogue D-ZK3, valid 0.302-2.325 um, beside its spreadsheet's
    # 0.365-1.014 um): the shipped entry keeps "CATALOG:NAME", this one is "CATALOG-AGF:NAME"
    for key, m in extra.items():
        if ":" in key:
            cat, plain = key.split(":", 1)
            index[f"{cat}-agf:{plain}".lower()] = m
    for layer in [shipped] + list(_REGISTERED):
        for key, m in layer.items():
            if m.catalog:
                index[f"{m.catalog}:{_plain_name(m)}".lower()] = m
            index[key.lower()] = m
    index.update({"air": _AIR, "vacuum": _VACUUM})
    return index


_NUMBER = r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?"
_MODEL_RE = re.compile(rf"^\s*({_NUMBER})\s*[/,]\s*({_NUMBER}|[+]?inf)\s*$", re.IGNORECASE)
# "nd/vd@d,F,C": a model glass defined at its own d, F, C lines (um), e.g. DeepLens's 587.6/486.1/656.3 nm
_MODEL_LINES_RE = re.compile(rf"^\s*({_NUMBER})\s*/\s*({_NUMBER}|[+]?inf)\s*@\s*({_NUMBER})\s*,\s*({_NUMBER})"
                             rf"\s*,\s*({_NUMBER})\s*$", re.IGNORECASE)


@functools.lru_cache(maxsize=None)
def get_material(name: str) -> Material:
    """Material by name (case-insensitive).

    Args:
        name: ``"air"``/``"vacuum"`` (n = 1); a catalogue glass (``"N-BK7"``, ``"F2"``, ``"H-K51"``,
            ``"S-LAH79"``, ``"FC5"``), optionally qualified ``"CATALOG:NAME"``; ``"fused_silica"``
            (aliases ``"F_SILICA"``, ``"SILICA"``, ``"FUSEDSILICA"``, ``"fused silica"``);
            ``"PMMA"``; ``"PC"``/``"polycarbonate"``; a model glass ``"nd/vd"`` or ``"nd,vd"``
            (e.g. ``"1.5168/64.17"``, see :func:`model_glass`); or a glass added by
            :func:`register_catalog`.

    Returns:
        the (cached, immutable) :class:`Material`.

    Raises:
        GlassError: unknown name (the message names it and suggests close matches).
    """
    if not isinstance(name, str) or not name.strip():
        raise GlassError(f"material name must be a non-empty string, got {name!r}")
    key = name.strip().lower()
    index = _index()
    if key in index:
        return index[key]
    match = _MODEL_RE.match(key)
    if match:
        return model_glass(float(match.group(1)), float(match.group(2)))
    match = _MODEL_LINES_RE.match(key)
    if match:
        lines = tuple(float(match.group(i)) for i in (3, 4, 5))
        return model_glass(float(match.group(1)), float(match.group(2)), lines_um=lines)
    key_compact = re.sub(r"\s+", "", key)
    if key_compact in index:
        return index[key_compact]
    close = difflib.get_close_matches(key, list(index), n=5, cutoff=0.6)
    display = [index[c].name if index[c].name.lower() == c else c for c in close]
    hint = (f"; did you mean {', '.join(repr(d) for d in display)}?" if close else
            "; give 'nd/vd' for a model glass or add a catalogue with register_catalog()")
    raise GlassError(f"unknown glass {name.strip()!r}{hint}")


def _successor(name: str):
    """SCHOTT's lead-free successor of a legacy glass name ("SK16" -> "N-SK16"), or None."""
    base = name.strip().upper()
    if base.startswith("SCHOTT:"):
        base = base[7:]
    if base.startswith(("N-", "P-", "H-")):
        return None
    cand = f"N-{base}"
    try:
        m = get_material(cand)
    except GlassError:
        return None
    return m if (m.catalog or "").upper() == "SCHOTT" else None


def _plausible(nd, vd) -> bool:
    """nd / vd that describe a glass: not Zemax's placeholders (0 / 0, and the 1.5 / 40 it writes for a
    catalogue glass whose data it looks up)."""
    return nd is not None and vd is not None and math.isfinite(nd) and math.isfinite(vd) and 1.0 < nd < 4.5 \
        and 0.0 < vd < 200.0 and (nd, vd) != (1.5, 40.0)


def _moulding_base(name: str):
    """The base glass name of a maker's moulding-grade variant, or None: OHARA ``<base>_MOLD``
    ("L-TIM28_MOLD"), CDGM ``D-<base>M`` ("D-ZK3M": CDGM's D- glasses are its low-Tg moulding glasses, the
    trailing M the moulded grade), optionally catalogue-qualified."""
    n = name.strip()
    base = re.sub(r"_MOLD$", "", n, flags=re.IGNORECASE)
    if base != n:
        return base
    plain = n.split(":", 1)[-1]
    if re.match(r"^D-[A-Z0-9]+[0-9A-Z]M$", plain, flags=re.IGNORECASE) and len(plain) > 4:
        return n[:-1]
    return None


def resolve_glass(name: str, nd=None, vd=None, lines_um=None):
    """The material a lens file's glass name stands for: ``(material name, note)``.

    ``note`` is None when ``name`` is in the tables. Otherwise a substitute is chosen and ``note`` says
    which (the caller warns with :class:`GlassSubstitutionWarning`, naming the surface):

    * a maker's moulding-grade variant (OHARA ``..._MOLD``, CDGM ``D-...M``) whose base glass is in the
      tables: the base glass, whatever nd / vd the file lists;
    * a legacy SCHOTT name whose lead-free successor ``N-<name>`` is in the SCHOTT catalogue
      ("BK7", "SK16", "LAK9"), when the file's nd / vd (if any) agree with it (1e-3 / 0.5);
    * else, where the file lists a plausible nd and vd (not Zemax's 0 placeholders), a model glass
      through them (:func:`model_glass`; with ``lines_um = (d, F, C)`` the format's own defining lines).

    Raises :class:`~rwwarp.errors.GlassError` (the lookup's own message, with close matches) when
    there is no substitute.
    """
    try:
        get_material(name)
        return name, None
    except GlassError as e:
        err = e
    nd = None if nd is None else float(nd)
    vd = None if vd is None else float(vd)
    base = _moulding_base(name)
    if base is not None:
        # a maker's moulding-grade variant (OHARA "L-TIM28_MOLD", CDGM "D-ZK3M"): the base glass's data (the
        # moulded index differs by the annealing shift, ~1e-3), before the file's nd / vd, which for these
        # names are often stale (Thorlabs' D-ZK3M: nd 1.601, vd 50.3 against D-ZK3's 1.589, 61.2)
        try:
            m = get_material(base)
        except GlassError:
            m = None
        if m is not None:
            use = m.name
            # the maker's other data set for the same glass where it covers more wavelengths (CDGM's Zemax
            # catalogue D-ZK3 reaches 2.325 um, its spreadsheet's 1.014 um; they agree to 2e-5 in between)
            other = _extra()[0].get(f"{m.catalog}:{_plain_name(m)}") if m.catalog else None
            if other is not None and m.wavelength_range_um is not None and other.wavelength_range_um is not None \
                    and other.wavelength_range_um[1] - other.wavelength_range_um[0] > \
                    m.wavelength_range_um[1] - m.wavelength_range_um[0]:
                use = f"{m.catalog}-AGF:{_plain_name(m)}"
            return use, (f"glass {name.strip()!r} is not in the tables: the base glass {use!r} stands in "
                         "(a moulding variant; moulded glasses differ by their annealing shift)")
    succ = _successor(name)
    if succ is not None and (not _plausible(nd, vd) or (abs(succ.nd - nd) < 1e-3 and abs(succ.vd - vd) < 0.5)):
        return succ.name, (f"glass {name.strip()!r} is not in the tables: SCHOTT's lead-free successor "
                           f"{succ.name!r} (nd {succ.nd:.5f}, vd {succ.vd:.2f}) stands in")
    if _plausible(nd, vd):
        if lines_um is None:
            sub = f"{nd!r}/{vd!r}"
        else:
            sub = f"{nd!r}/{vd!r}@" + ",".join(repr(float(v)) for v in lines_um)
        return sub, (f"glass {name.strip()!r} is not in the tables: a model glass from the file's nd {nd:g}, "
                     f"vd {vd:g} stands in (no partial dispersion)")
    raise err


def register_catalog(path_or_dict, catalog: str | None = None) -> dict:
    """Add glasses to the lookup of :func:`get_material`; they take precedence over the table.

    Args:
        path_or_dict: a Zemax ``.AGF`` file path, a ``.json`` file in the ``glasses.json`` format,
            or a dict name -> :class:`Material` (or name -> table entry dict with ``formula``,
            ``coefficients`` and optional ``range_um`` (um), ``catalog``, ``nd``, ``vd``, ``source``).
        catalog: catalogue name given to dict entries that have none (for ``"CATALOG:NAME"`` lookups).

    Returns:
        dict name -> :class:`Material` of the glasses added.

    Raises:
        LensFileError: unreadable or malformed file. GlassError: malformed dict entry.
    """
    if isinstance(path_or_dict, dict):
        added = {}
        for key, value in path_or_dict.items():
            if isinstance(value, Material):
                m = value
                if catalog is not None and m.catalog is None:
                    m = Material(m.name, m.formula, m.coefficients, m.wavelength_range_um, catalog,
                                 m.catalog_nd, m.catalog_vd, m.source)
            else:
                entry = dict(value)
                if entry.get("catalog") is None:
                    entry["catalog"] = catalog
                m = _material_from_entry(str(key), entry)
            added[str(key)] = m
    else:
        path = Path(path_or_dict)
        if path.suffix.lower() == ".json":
            try:
                added = _load_table_json(path)[0]
            except (OSError, ValueError, KeyError, AttributeError) as e:
                raise LensFileError(f"cannot read glass table: {e!r}", file=str(path)) from None
        else:
            added = load_agf(path)
    _REGISTERED.append(added)
    _index.cache_clear()
    get_material.cache_clear()
    return added


def reset_catalogs() -> None:
    """Forget every catalogue added by :func:`register_catalog` (the shipped table stays)."""
    _REGISTERED.clear()
    _index.cache_clear()
    get_material.cache_clear()


def available_materials(catalog: str | None = None) -> list:
    """Names of the shipped and registered materials (one name per material, no aliases).

    Args:
        catalog: only glasses of this catalogue (``"SCHOTT"``, ``"OHARA"``, ``"HOYA"``, ``"CDGM"``,
            ``"MISC"``, an AGF file's stem...), case-insensitive; ``None`` for all.

    Returns:
        sorted list of names accepted by :func:`get_material`.
    """
    names = set()
    for layer in [_shipped()[0]] + list(_REGISTERED):
        for key, m in layer.items():
            if catalog is None or (m.catalog or "").lower() == catalog.lower():
                names.add(key)
    return sorted(names)
