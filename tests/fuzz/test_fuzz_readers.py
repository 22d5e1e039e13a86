"""Fuzzing the three lens readers (issue 12): whatever the bytes, ``rw.load_lens`` raises a LensError
naming the file or returns a lens that traces to finite numbers (see fuzz_strategies.check_file)."""
import pytest

pytest.importorskip("hypothesis")
from hypothesis import given, settings  # noqa: E402

from fuzz_strategies import check_file, deeplens_files, native_files, zmx_files  # noqa: E402

N = settings.default.max_examples


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return tmp_path_factory.mktemp("fuzz")


@settings(max_examples=N * 2)
@given(data=native_files())
def test_native_json(folder, data):
    check_file(folder / "lens.json", data)


@settings(max_examples=N * 2)
@given(data=zmx_files())
def test_zemax(folder, data):
    check_file(folder / "lens.zmx", data)


@settings(max_examples=N)
@given(data=deeplens_files())
def test_deeplens_json(folder, data):
    check_file(folder / "lens.json", data)
