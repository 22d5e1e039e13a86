"""Fuzzing the argument space of the public calls (issue 12): an invalid argument raises an
ArgumentError naming it (and its range); valid arguments give finite results or a LensError; inputs are
not mutated."""
import copy
import math

import numpy as np
import pytest

pytest.importorskip("hypothesis")
from hypothesis import given, settings, strategies as st  # noqa: E402

import rwwarp as rw  # noqa: E402
from rwwarp import paraxial  # noqa: E402
from rwwarp.errors import ArgumentError, LensError  # noqa: E402

import fuzz_strategies as fs  # noqa: E402

N = settings.default.max_examples


@pytest.fixture(scope="module")
def lenses():
    return {n: rw.load_lens(n) for n in ("a489_doe", "thin_lens_doe", "cooke_triplet")}


def _expect(call, bad_names, what):
    """Run ``call``; with bad arguments it must raise an ArgumentError naming one of them."""
    fs.STATS["arg_cases"] += 1
    try:
        with fs.time_limit():
            out = call()
    except ArgumentError as e:
        fs.STATS["arg_refused"] += 1
        assert bad_names, f"{what}: valid arguments refused: {e}"
        assert any(n in str(e) for n in bad_names), f"{what}: message names none of {bad_names}: {e}"
        return None
    except LensError as e:  # e.g. a vignetted field: documented, and it names the field or the file
        fs.STATS["refusals"] += 1
        assert not bad_names, f"{what}: bad {bad_names} not refused as such but as {type(e).__name__}: {e}"
        assert e.file or e.field is not None or e.surface is not None, e
        return None
    except fs.Hang:
        fs.STATS["hangs"] += 1
        raise
    except Exception:
        fs.STATS["crashes"] += 1
        raise
    assert not bad_names, f"{what}: bad {bad_names} accepted"
    fs.STATS["arg_ok"] += 1
    return out


def _names(*args):
    return [n for _, n in args if n is not None]


@settings(max_examples=N)
@given(lens=st.sampled_from(["a489_doe", "thin_lens_doe"]), data=st.data())
def test_psf_arguments(lenses, lens, data):
    L = lenses[lens]
    before = copy.deepcopy(L.to_dict())
    a, bad = fs.pick(data, {"field": fs.field_arg, "wl": fs.wavelength_arg, "size": fs.size_arg,
                            "device": fs.device_arg, "od": fs.object_distance_arg, "pixel": fs.pixel_arg,
                            "nyq": fs.factor_args["nyquist_safety"], "rps": fs.factor_args["rays_per_sample"],
                            "center": fs.center_arg})
    snapshot = repr(a)
    p = _expect(lambda: rw.psf(L, a["field"], a["wl"], model="ray", size=a["size"], device=a["device"],
                               object_distance_mm=a["od"], pixel_mm=a["pixel"], nyquist_safety=a["nyq"],
                               rays_per_sample=a["rps"], center_mm=a["center"]), bad, "psf")
    if p is not None:
        fs._finite(p.data, "psf")
        fs._finite(p.center_mm, "psf centre")
        assert p.data.shape == (a["size"], a["size"]) and p.data.sum() <= 1 + 1e-6
    assert L.to_dict() == before and repr(a) == snapshot  # nothing mutated


@settings(max_examples=N)
@given(fields=st.lists(fs.either(fs.field_arg), min_size=0, max_size=3),
       wls=st.lists(fs.either(fs.wavelength_arg), min_size=0, max_size=3), batch=fs.either(fs.batch_arg))
def test_psf_map_lists(lenses, fields, wls, batch):
    L = lenses["thin_lens_doe"]
    f_in, w_in = [f for f, _ in fields], [w for w, _ in wls]
    f_copy, w_copy = repr(f_in), repr(w_in)
    bad = _names(*fields, *wls, batch)
    if not f_in:
        bad.append("fields")
    if not w_in:
        bad.append("wavelengths_um")
    m = _expect(lambda: rw.psf_map(L, f_in, w_in, model="ray", size=8, batch=batch[0]), bad, "psf_map")
    if m is not None:
        fs._finite(m.data, "psf_map")
        assert m.data.shape == (len(f_in), len(w_in), 8, 8)
        assert np.all(m.data.sum(axis=(2, 3)) <= 1 + 1e-6)
    assert repr(f_in) == f_copy and repr(w_in) == w_copy  # not mutated (repr: NaN-safe)


@settings(max_examples=N)
@given(lens=st.sampled_from(["a489_doe", "thin_lens_doe", "cooke_triplet"]), data=st.data())
def test_spot_and_paraxial_arguments(lenses, lens, data):
    L = lenses[lens]
    a, bad = fs.pick(data, {"field": fs.field_arg, "wl": fs.wavelength_arg, "grid": fs.grid_arg,
                            "reference": fs.reference_arg})
    v = _expect(lambda: rw.spot_rms(L, a["field"], a["wl"], grid=a["grid"], reference=a["reference"]), bad,
                "spot_rms")
    if v is not None:
        assert fs._finite(v, "spot_rms") >= 0
    wl_bad = ["wavelength"] if "wavelength" in bad else []
    for fn in (L.efl, L.bfl, lambda w: paraxial.pupils(L, w).entrance_radius,
               lambda w: paraxial.f_number(L, w)):
        out = _expect(lambda: fn(a["wl"]), wl_bad, "paraxial")
        if out is not None:
            fs._finite(out, "paraxial")
