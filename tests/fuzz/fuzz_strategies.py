"""Hypothesis strategies and contract checks of the fuzz suite (issue 12).

Three lens formats (native rwwarp JSON, Zemax .zmx, DeepLens JSON) are fuzzed by mutating real files:
values replaced by hostile ones (NaN/inf as literals and strings, overflowing magnitudes, wrong types,
deep nesting), keys deleted or added, lines deleted/duplicated/inserted, then the bytes re-encoded
(UTF-8, UTF-16 with and without a BOM, Latin-1) and optionally truncated or corrupted.

The contract (:func:`check_file`): ``rw.load_lens`` raises a LensError naming the file, or returns a
lens whose paraxial numbers, RMS spot and (DOE lenses) ray-model PSF are finite or refused with a
LensError; PSF sums <= 1; nothing mutated; no call runs past :data:`HANG_S` seconds.

``STATS`` counts what happened (printed at the end of the session by tests/fuzz/conftest.py).
"""
from __future__ import annotations

import copy
import json
import math
import signal
from collections import Counter
from contextlib import contextmanager
from pathlib import Path

import numpy as np
from hypothesis import strategies as st

import rwwarp as rw
from rwwarp.errors import ArgumentError, LensError

STATS = Counter()
HANG_S = 60
LENSES = Path(rw.__file__).parent / "lenses"

NATIVE_BASES = [json.loads((LENSES / n).read_text()) for n in ("a489_doe.json", "thin_lens_doe.json",
                                                                  "cooke_triplet.json")]
ZMX_BASES = [
    (LENSES / "cooke_triplet.zmx").read_bytes().decode("utf-16").replace("\r\n", "\n"),
    """MODE SEQ
UNIT MM
ENPD 4
FTYP 0 0 2 1
YFLN 0 2
WAVM 1 0.55 1
PWAV 1
SURF 0
  DISZ INFINITY
SURF 1
  STOP
  TYPE PARAXIAL
  PARM 1 50
  DISZ 1
SURF 2
  TYPE BINARY_2
  PARM 0 1
  XDAT 1 2 0 9 0 0
  XDAT 2 2.0 0 9 0 0
  XDAT 3 -10.0 0 9 0 0
  XDAT 4 1.0 0 9 0 0
  DIAM 2 1 0 0 1 ""
  DISZ 49
SURF 3
""",
    """MODE SEQ
UNIT MM
FNUM 4
WAVM 1 0.4861327 1
WAVM 2 0.5875618 1
PWAV 2
SURF 0
  DISZ 1000
SURF 1
  TYPE EVENASPH
  CURV 0.02
  CONI -1
  PARM 2 1e-6
  PARM 3 -1e-9
  GLAS N-BK7
  DISZ 5
  CLAP 0 10
  STOP
SURF 2
  CURV -0.005
  DISZ 45
  SQAP 8 8 0 0 0
SURF 3
""",
]
DEEPLENS_BASES = [
    {"info": "hybrid", "r_sensor": 2.1213, "sensor_res": [3000, 3000],
     "surfaces": [
         {"type": "Aperture", "r": 1.0, "mat2": "air", "is_square": False, "d_next": 0.1},
         {"type": "Aspheric", "r": 6.35, "roc": 4.7531, "k": -1.2051,
          "ai": [0.0, 5.33e-4, 1.12e-05, -3.75e-07, -7.63e-09, 1.36e-10], "mat2": "H-K51", "d_next": 7.5},
         {"type": "Spheric", "r": 6.35, "roc": -15.65, "mat2": "air", "d_next": 3.657}],
     "DOE": {"type": "DOE", "d": 8.3098, "res": [3000, 3000], "fab_ps": 0.001, "is_square": True,
             "param_model": "binary2", "order2": -40.0, "order4": 3.0, "order6": 0.0, "order8": 0.0}},
    {"r_sensor": 2.0, "sensor_res": [100, 100], "enpd": 3.0,
     "surfaces": [{"type": "Stop", "r": 2.0, "d_next": 1.0},
                  {"type": "ThinLens", "f": 50.0, "r": 2.0, "mat2": "air", "d_next": 50.0},
                  {"type": "Plane", "r": 3.0, "mat2": "N-BK7", "d_next": 1.0},
                  {"type": "Plane", "r": 3.0, "mat2": "air", "d_next": 1.0}],
     "DOE": {"type": "Fresnel", "d": 1.5, "res": 2000, "fab_ps": 0.001, "f0": 400.0, "fab_step": 8}},
]

# ------------------------------------------------------------------------------------------ values
HOSTILE_FLOATS = [math.nan, math.inf, -math.inf, 0.0, -0.0, 1e308, -1e308, 1e-300, -1e-300, 5e-324, 1e16,
                  -1.0, 1e6, 1e-6, 1e9, 2.5]
HOSTILE_STRINGS = ["nan", "NaN", "inf", "-inf", "Infinity", "1e999", "", " ", "air", "H-K51", "fused_silica",
                   "square", "doe", "even_poly", "\x00", "\ud800", "é" * 3, "x" * 300]
numbers = st.one_of(st.sampled_from(HOSTILE_FLOATS),
                    st.floats(allow_nan=True, allow_infinity=True),
                    st.integers(min_value=-(10 ** 20), max_value=10 ** 20),
                    st.sampled_from([2 ** 63, 10 ** 400, -1, 0, 1, 2, 16, 10 ** 8]))
scalars = st.one_of(numbers, st.text(max_size=6), st.sampled_from(HOSTILE_STRINGS), st.booleans(), st.none())
values = st.recursive(scalars, lambda c: st.one_of(st.lists(c, max_size=4),
                                                   st.dictionaries(st.text(max_size=6), c, max_size=3)),
                      max_leaves=6)


def _paths(obj, prefix=()):
    """Every path (tuple of keys/indices) into a nested JSON value, the root excluded."""
    out = []
    if isinstance(obj, dict):
        for k, v in obj.items():
            out.append(prefix + (k,))
            out.extend(_paths(v, prefix + (k,)))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            out.append(prefix + (i,))
            out.extend(_paths(v, prefix + (i,)))
    return out


def _is_num(v):
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _parent(obj, path):
    for k in path[:-1]:
        obj = obj[k]
    return obj


@st.composite
def mutated_json(draw, bases):
    """A JSON document (as a Python value) mutated from one of ``bases`` by 1-3 edits."""
    d = copy.deepcopy(draw(st.sampled_from(bases)))
    for _ in range(draw(st.integers(1, 3))):
        paths = _paths(d)
        if not paths:
            break
        action = draw(st.sampled_from(["number", "number", "number", "scale", "replace", "replace", "delete",
                                       "add", "nest"]))
        numeric = [p for p in paths if _is_num(_parent(d, p)[p[-1]])]
        if action in ("number", "scale") and numeric:
            path = draw(st.sampled_from(numeric))
        else:
            path = draw(st.sampled_from(paths))
        parent = _parent(d, path)
        key = path[-1]
        if action == "number":
            parent[key] = draw(st.one_of(st.sampled_from(HOSTILE_FLOATS), numbers,
                                         st.sampled_from(["nan", "inf", "1e999", [1.0], {"v": 1}, None, True])))
        elif action == "replace":
            parent[key] = draw(values)
        elif action == "scale" and isinstance(parent[key], (int, float)) and not isinstance(parent[key], bool):
            f = draw(st.sampled_from([1e300, 1e-300, -1.0, 1e6, 1e-6, 0.0, math.inf, math.nan]))
            with np.errstate(all="ignore"):
                try:
                    parent[key] = float(np.float64(parent[key]) * f)
                except OverflowError:  # an int past float range
                    parent[key] = math.inf
        elif action == "delete":
            del parent[key]
        elif action == "add" and isinstance(parent, dict):
            parent[draw(st.sampled_from(["unknown", "radius", "stop", "levels", "DOE", "(x)", "fields_deg", "a2"]))] = \
                draw(values)
        elif action == "nest":
            depth = draw(st.sampled_from([2, 50, 70, 200]))
            v = parent[key]
            for _ in range(depth):
                v = [v]
            parent[key] = v
    return d


@st.composite
def encoded(draw, text: str):
    """``text`` as bytes in a drawn encoding, optionally truncated, corrupted or padded."""
    enc = draw(st.sampled_from(["utf-8", "utf-8", "utf-8-sig", "utf-16", "utf-16-le", "utf-16-be", "latin-1",
                                "utf-32"]))
    raw = text.encode(enc, errors="surrogatepass" if enc.startswith("utf") else "replace")
    op = draw(st.sampled_from(["none", "none", "none", "truncate", "flip", "insert", "odd"]))
    if op == "truncate" and raw:
        raw = raw[:draw(st.integers(0, len(raw) - 1))]
    elif op == "flip" and raw:
        i = draw(st.integers(0, len(raw) - 1))
        raw = raw[:i] + bytes([raw[i] ^ draw(st.integers(1, 255))]) + raw[i + 1:]
    elif op == "insert":
        i = draw(st.integers(0, len(raw)))
        raw = raw[:i] + draw(st.binary(min_size=1, max_size=8)) + raw[i:]
    elif op == "odd":
        raw = raw + b"\x00"
    return raw


@st.composite
def native_files(draw):
    return draw(encoded(json.dumps(draw(mutated_json(NATIVE_BASES)), allow_nan=True)))


@st.composite
def deeplens_files(draw):
    return draw(encoded(json.dumps(draw(mutated_json(DEEPLENS_BASES)), allow_nan=True)))


ZMX_TOKENS = ["nan", "NaN", "inf", "-inf", "INFINITY", "1e308", "-1e308", "1e-300", "0", "-0", "abc", "1e8",
              "99999999999999999999", "-5", "2.5", "1E+400", "0x10"]
ZMX_LINES = ["TYPE BINARY_2", "TYPE EVENASPH", "TYPE PARAXIAL", "TYPE TOROIDAL", "XDAT 1 1e8 0 9 0 0",
             "XDAT 1 1e300", "XDAT 2 0", "XDAT 3 1e12", "PARM 1 0", "PARM 0 1e300", "UNIT FOO", "UNIT METER",
             "CLAP 0 1e308", "CLAP 1 2", "SQAP 1 2 0", "GLAS MIRROR", "GLAS ___BLANK 1 0 nan 60", "STOP",
             "FLOA", "FNUM 0", "FNUM 1e-300", "WAVM 1 550 1", "WAVM 1 nan 1", "PWAV 99", "FTYP 0 0 99999 99999",
             "SURF 99", "DIAM 1e308 1", "CURV 1e308", "DISZ 1e308", "DISZ INFINITY", "CONI -1e300", "ENPD 0",
             "ENPD 1e308", "XFLN 0 1e308", "YFLN nan", "MODE NSC", "NAME \x00\x01"]


@st.composite
def zmx_files(draw):
    lines = draw(st.sampled_from(ZMX_BASES)).split("\n")
    for _ in range(draw(st.integers(1, 3))):
        i = draw(st.integers(0, len(lines) - 1))
        action = draw(st.sampled_from(["token", "token", "delete", "duplicate", "insert"]))
        if action == "token":
            toks = lines[i].split()
            if len(toks) > 1:
                j = draw(st.integers(1, len(toks) - 1))
                toks[j] = draw(st.sampled_from(ZMX_TOKENS))
                lines[i] = "  " + " ".join(toks)
        elif action == "delete":
            del lines[i]
        elif action == "duplicate":
            lines.insert(i, lines[i])
        else:
            lines.insert(i, "  " + draw(st.sampled_from(ZMX_LINES)))
        if not lines:
            lines = [""]
    return draw(encoded("\n".join(lines)))


# ------------------------------------------------------------------------------------------ contract
class Hang(Exception):
    """A call ran past HANG_S seconds."""


@contextmanager
def time_limit(seconds=HANG_S):
    def _alarm(signum, frame):
        raise Hang(f"call ran past {seconds} s")
    old = signal.signal(signal.SIGALRM, _alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


def _finite(v, what):
    a = np.asarray(v, dtype=np.float64)
    if not np.all(np.isfinite(a)):
        STATS["nan_escapes"] += 1
        raise AssertionError(f"{what} returned a non-finite number: {v!r}")
    return a


def guarded(fn, what):
    """Run ``fn``: a LensError is a refusal (returned), any other exception a crash (re-raised), a run
    past HANG_S a hang."""
    try:
        with time_limit():
            return fn(), None
    except LensError as e:
        STATS["refusals"] += 1
        return None, e
    except Hang:
        STATS["hangs"] += 1
        raise
    except Exception:
        STATS["crashes"] += 1
        raise


def check_file(path: Path, data: bytes, *, psf: bool = True):
    """The reader contract for one file's bytes (see the module docstring)."""
    STATS["cases"] += 1
    path.write_bytes(data)
    lens, err = guarded(lambda: rw.load_lens(path), "load_lens")
    if err is not None:
        assert str(path) in str(err), f"the message does not name the file: {err}"
        if "cannot interpret the file (" in str(err):  # load_lens's last line of defence caught a crash
            STATS["crashes"] += 1
            raise AssertionError(f"a reader crashed (caught by load_lens's safety net): {err}")
        STATS["files_refused"] += 1
        return
    STATS["files_loaded"] += 1
    check_lens(lens, psf=psf)


def check_lens(lens, *, psf: bool = True):
    """A loaded lens traces to finite numbers or refuses with a LensError; nothing is mutated."""
    before = copy.deepcopy(lens.to_dict())
    w0 = lens.wavelengths_um[0]
    for w in lens.wavelengths_um[:2]:
        for name in ("efl", "bfl"):
            v, err = guarded(lambda: getattr(lens, name)(w), name)
            if err is None:
                _finite(v, f"lens.{name}({w})")
    v, err = guarded(lambda: rw.spot_rms(lens, 0.0, w0, grid=7), "spot_rms")
    if err is None:
        assert _finite(v, "spot_rms") >= 0
    if psf and lens.doe_index is not None:
        p, err = guarded(lambda: rw.psf(lens, 0.0, w0, model="ray", size=8), "psf")
        if err is None:
            _finite(p.data, "psf data")
            _finite(p.center_mm, "psf center")
            assert p.data.min() >= 0 and p.data.sum() <= 1 + 1e-6, p.data.sum()
            STATS["psfs"] += 1
    assert lens.to_dict() == before, "the lens was mutated"


# ------------------------------------------------------------------------------------------ arguments
def pick(data, strategies: dict, max_bad: int = 2):
    """Draw every argument of ``strategies`` (name -> one_of(good, bad) strategy, as built below): at most
    ``max_bad`` of them from their bad branch. Returns ({name: value}, [names of the bad ones])."""
    names = sorted(strategies)
    bad_set = data.draw(st.sets(st.sampled_from(names), max_size=max_bad), label="bad arguments")
    out, bad_names = {}, []
    for n in names:
        good_s, bad_s = strategies[n]
        v, label = data.draw(bad_s if n in bad_set else good_s, label=n)
        out[n] = v
        if label is not None:
            bad_names.append(label)
    return out, bad_names


def bad(strategy, name):
    """An invalid value of argument ``name``: (value, name)."""
    return strategy.map(lambda v: (v, name))


def good(strategy):
    return strategy.map(lambda v: (v, None))


NOT_NUMBERS = st.one_of(st.text(max_size=4), st.none(), st.lists(st.floats(0.5, 0.6), max_size=2),
                        st.dictionaries(st.text(max_size=2), st.integers(), max_size=1), st.booleans())
NON_FINITE = st.sampled_from([math.nan, math.inf, -math.inf])

wavelength_arg = (
    good(st.floats(0.42, 0.9)),
    bad(st.one_of(st.floats(200, 20000), NON_FINITE, st.floats(-10, 0.199), st.floats(20.01, 1e300),
                  NOT_NUMBERS), "wavelength"),
)
field_arg = (
    st.one_of(good(st.floats(-3, 3)), good(st.tuples(st.floats(-2, 2), st.floats(-2, 2)))),
    bad(st.one_of(NON_FINITE, st.floats(90, 1e300), st.floats(-1e300, -90),
                  NOT_NUMBERS.filter(lambda v: not isinstance(v, list)),  # a list is a list of fields
        st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1))), "field"),
)
size_arg = (good(st.integers(1, 24)),
                     bad(st.one_of(st.integers(-10, 0), st.integers(8193, 10 ** 12), st.floats(1.5, 7.5),
                                   NON_FINITE, st.text(max_size=3), st.none()), "size"))
device_arg = (good(st.just("cpu")),
                       bad(st.one_of(st.text(max_size=8).filter(lambda s: s != "cpu"),
                                     st.sampled_from(["cuda", "cuda:0", "cuda:7", "gpu", "CPU", "cpu:0"]),
                                     st.integers(), st.none()), "device"))
object_distance_arg = (st.one_of(good(st.sampled_from([None, math.inf])), good(st.floats(500, 1e7))),
                                bad(st.one_of(st.floats(-1e300, 0), st.just(math.nan), st.just(-math.inf),
                                              st.floats(1e13, 1e300), NOT_NUMBERS.filter(lambda v: v is not None)),
                                    "object_distance_mm"))
pixel_arg = (good(st.sampled_from([None, 0.001, 0.004])),
                      bad(st.one_of(st.floats(-1, 0), NON_FINITE, st.floats(11, 1e300),
                                    st.text(max_size=2)), "pixel_mm"))
factor_args = {
    "nyquist_safety": (good(st.floats(1.0, 3.0)),
                                bad(st.one_of(st.floats(-5, 0.4), NON_FINITE, st.floats(17, 1e300)), "nyquist_safety")),
    "rays_per_sample": (good(st.floats(0.5, 2.0)),
                                 bad(st.one_of(st.floats(-5, 0.09), NON_FINITE), "rays_per_sample")),
}
batch_arg = (good(st.sampled_from([None, 1, 2])),
                      bad(st.one_of(st.integers(-5, 0), st.floats(0.5, 1.5), st.text(max_size=2)), "batch"))
center_arg = (good(st.just(None)),
                       bad(st.one_of(st.tuples(NON_FINITE, st.floats(-1, 1)), st.just((1.0, 2.0, 3.0)),
                                     st.just([]), st.text(max_size=2)), "center_mm"))
grid_arg = (good(st.integers(1, 15).filter(lambda g: g != 2)),  # 2x2 "edges" grid: no sample in a circle
            bad(st.one_of(st.integers(-3, 0), st.integers(4002, 10 ** 9), st.floats(1.5, 2.5), st.text(max_size=2)),
                "grid"))
reference_arg = (good(st.sampled_from(["centroid", "chief"])),
                 bad(st.text(max_size=5).filter(lambda t: t not in ("centroid", "chief")), "reference"))


def either(arg):
    """Good or bad value of one argument (as a one_of strategy of (value, bad name or None))."""
    return st.one_of(arg[0], arg[0], arg[1])
