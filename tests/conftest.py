"""Shared pytest fixtures.

* ``cl_backend``: the OpenCL backend the tests run on: PoCL (the first OpenCL CPU device) by
  default; the environment variable ``PYOPENCL_TEST`` selects another, in pyopencl's format
  ``PLATFORM[:DEVICE]`` (case-insensitive substrings of the platform and device names, or their
  indices), e.g. ``PYOPENCL_TEST=portable:cpu`` or ``PYOPENCL_TEST=0:0``.
* ``dtype``: parametrises a test over complex128 and complex64.

Under pytest-xdist (``pytest -n N``, what ``.ci/test`` runs) each worker process gets its share of the
cores for its thread pools (OpenMP/BLAS/torch, PoCL's pthread device): ``cores // N`` threads each (at
least 1), unless the environment already sets the variable. Set here, before numpy, torch or pyopencl
are imported in the worker, and inherited by the subprocesses the tests start.
"""

import os

if os.environ.get("PYTEST_XDIST_WORKER"):  # a pytest-xdist worker: N of these share the cores
    try:
        _cores = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        _cores = os.cpu_count() or 1
    _threads = str(max(1, _cores // max(1, int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")))))
    for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                 "POCL_MAX_PTHREAD_COUNT", "POCL_CPU_MAX_CU_COUNT"):  # PoCL 3 / PoCL >= 4 name
        os.environ.setdefault(_var, _threads)

import numpy as np  # noqa: E402 (after the thread counts above)
import pytest  # noqa: E402

try:  # hypothesis profiles of the fuzz suite (tests/fuzz): ``ci`` by default, ``long`` on request
    from hypothesis import HealthCheck, settings

    _quiet = [HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much,
              HealthCheck.function_scoped_fixture]
    settings.register_profile("ci", derandomize=True, max_examples=100, deadline=None, database=None,
                              print_blob=True, suppress_health_check=_quiet)
    settings.register_profile("long", derandomize=False, max_examples=1500, deadline=None, database=None,
                              print_blob=True, suppress_health_check=_quiet)
    settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))  # --hypothesis-profile overrides
except ImportError:  # hypothesis is a test extra; tests/fuzz skips without it
    pass


def _select_opencl_device(spec: str) -> str:
    """rwwarp device string 'opencl:P:D' for a PYOPENCL_TEST-style 'platform[:device]' spec."""
    import pyopencl as cl

    plat_spec, _, dev_spec = spec.partition(":")
    platforms = cl.get_platforms()
    for p_idx, platform in enumerate(platforms):
        if plat_spec and not (plat_spec == str(p_idx) or plat_spec.lower() in platform.name.lower()):
            continue
        for d_idx, dev in enumerate(platform.get_devices()):
            if dev_spec and not (dev_spec == str(d_idx) or dev_spec.lower() in dev.name.lower()):
                continue
            return f"opencl:{p_idx}:{d_idx}"
    raise RuntimeError(f"PYOPENCL_TEST={spec!r} matches no OpenCL device")


@pytest.fixture(scope="session")
def cl_backend():
    """rwwarp OpenCL backend for the tests (PoCL unless PYOPENCL_TEST says otherwise)."""
    pytest.importorskip("pyopencl")
    from rwwarp.wave.backend import get_backend

    spec = os.environ.get("PYOPENCL_TEST", "").strip()
    try:
        return get_backend(_select_opencl_device(spec) if spec else "cpu")
    except RuntimeError as exc:
        pytest.skip(f"no OpenCL device: {exc}")


@pytest.fixture(params=[np.complex128, np.complex64], ids=["c128", "c64"])
def dtype(request):
    """Complex dtype under test: complex128 and complex64."""
    return np.dtype(request.param)


# pytest-xdist: the fuzz suite's counts (tests/fuzz/conftest.py) are counted in the workers; the controller
# sums what each worker reports when it finishes and prints the line the serial run prints.
@pytest.hookimpl(optionalhook=True)
def pytest_testnodedown(node, error):
    got = getattr(node, "workeroutput", {}).get("fuzz_stats")
    if got:
        total = node.config.stash.setdefault(_FUZZ_STATS, {"profile": got["profile"], "keys": got["keys"],
                                                            "counts": {}})
        for k, v in got["counts"].items():
            total["counts"][k] = total["counts"].get(k, 0) + v


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    total = config.stash.get(_FUZZ_STATS, None)
    if total:
        terminalreporter.write_line(f"fuzz (profile {total['profile']}, all workers): " +
                                    ", ".join(f"{k} {total['counts'].get(k, 0)}" for k in total["keys"]))


_FUZZ_STATS = pytest.StashKey[dict]()


@pytest.fixture(autouse=True)
def _fresh_default_plan_cache():
    """``rw.psf`` keeps its plans in a process-wide cache by default (rwwarp.wave.plan_cache.default_cache): it is
    emptied before every test, so that no test is served what another one computed (a test that changes a module
    setting the cache key does not cover, e.g. rwwarp.wave.pixel_scale.FIELD_FORM, sees its own calls only)."""
    import sys
    pc = sys.modules.get("rwwarp.wave.plan_cache")
    if pc is not None and pc._DEFAULT is not None:
        pc._DEFAULT.clear()
    yield
