"""Fuzz suite (issue 12): every test here carries the ``fuzz`` marker; the counts of cases, refusals,
crashes, hangs and NaN escapes are printed at the end of the session.

Hypothesis profiles are registered in tests/conftest.py: ``ci`` (default: derandomised, a few hundred
examples in all) and ``long`` (``pytest -m fuzz --hypothesis-profile long``).
"""
import pytest


def pytest_collection_modifyitems(config, items):
    for item in items:
        if "/tests/fuzz/" in str(item.fspath).replace("\\", "/"):
            item.add_marker(pytest.mark.fuzz)


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    try:
        from fuzz_strategies import STATS
    except ImportError:
        return
    if STATS:
        from hypothesis import settings
        keys = ["cases", "files_loaded", "files_refused", "psfs", "arg_cases", "arg_refused", "arg_ok",
                "refusals", "crashes", "hangs", "nan_escapes"]
        terminalreporter.write_line(f"fuzz (profile {settings._current_profile}): " +
                                    ", ".join(f"{k} {STATS.get(k, 0)}" for k in keys))
