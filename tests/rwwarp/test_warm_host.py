"""Host work of a warm (repeated) PSF call (issue 25): what every call does again, checked against an independent
reference. ``Plan.to_dict`` (every result carries its plans as dicts) against the standard library's
``dataclasses.asdict``, on real plans of each method, and its dict is the caller's own (changing it changes no plan)."""
import dataclasses
import warnings

import numpy as np
import pytest

import rwwarp as rw
from rwwarp.wave.plan import Plan

from test_map import doe_lens


def _asdict_reference(plan):
    """The dict ``Plan.to_dict`` gave before (the standard library's recursion, ``reasons`` as a list)."""
    d = dataclasses.asdict(plan)
    d["reasons"] = list(d["reasons"])
    return d


def _same_tree(a, b):
    """Equal values and equal container types at every level (a tuple stays a tuple, a list a list)."""
    assert type(a) is type(b), (type(a), type(b))
    if isinstance(a, dict):
        assert list(a) == list(b)
        for k in a:
            _same_tree(a[k], b[k])
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b)
        for x, y in zip(a, b):
            _same_tree(x, y)
    elif isinstance(a, np.ndarray):
        assert np.array_equal(a, b) and a.dtype == b.dtype
    else:
        assert a == b or (a != a and b != b), (a, b)


def _plans():
    warnings.simplefilter("ignore")
    lens = doe_lens()
    out = [rw.plan_psf(lens, 0.0, 0.55, size=16, method=m) for m in ("asm", "focal")]
    out.append(rw.plan_psf(lens, 0.3, 0.55, size=16, method="focal", tolerance=1e-3))   # model error, reasons
    out.append(rw.plan_psf(rw.load_lens("cooke_triplet"), 14.0, 0.55, size=8, rays_per_sample=0.1))
    return out


def test_to_dict_is_what_asdict_gives():
    plans = _plans()
    assert any(p.model_error for p in plans) and any(p.estimate for p in plans)   # nested dicts are exercised
    for p in plans:
        _same_tree(p.to_dict(), _asdict_reference(p))
    # nested containers of every kind, an array and a dataclass inside a dict field
    @dataclasses.dataclass
    class Inner:
        a: float
        b: list

    p = Plan(0.01, 8, 16, 5, reasons=("x", "y"), estimate={"memory_bytes": 10, "flops": 2.5,
                                                            "parts": [1, (2, 3.0), {"k": None}],
                                                            "arr": np.arange(3.0), "inner": Inner(1.0, [2])})
    _same_tree(p.to_dict(), _asdict_reference(p))


def test_to_dict_is_a_copy():
    """Changing the returned dict (a nested list, a nested dict, an array in place) leaves the plan as it was."""
    p = Plan(0.01, 8, 16, 5, reasons=("x",), estimate={"flops": 1.0, "parts": [1, 2], "arr": np.zeros(2)},
             model_error={"estimate": 1e-3})
    before = _asdict_reference(p)
    d = p.to_dict()
    d["reasons"].append("z")
    d["estimate"]["parts"].append(3)
    d["estimate"]["arr"][0] = 5.0
    d["model_error"]["estimate"] = 1.0
    _same_tree(_asdict_reference(p), before)
