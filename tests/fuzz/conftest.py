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


KEYS = ["cases", "files_loaded", "files_refused", "psfs", "arg_cases", "arg_refused", "arg_ok",
        "refusals", "crashes", "hangs", "nan_escapes"]


def _stats():
    """(profile name, this process's counts) or None when no fuzz test ran here."""
    try:
        from fuzz_strategies import STATS
    except ImportError:
        return None
    if not STATS:
        return None
    from hypothesis import settings
    return settings._current_profile, dict(STATS)


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    got = _stats()
    if got:
        profile, stats = got
        terminalreporter.write_line(f"fuzz (profile {profile}): " +
                                    ", ".join(f"{k} {stats.get(k, 0)}" for k in KEYS))


def pytest_sessionfinish(session):
    """Under pytest-xdist: this worker's counts go to the controller, which sums and prints them
    (tests/conftest.py; the controller runs no test, so it has none of its own)."""
    out = getattr(session.config, "workeroutput", None)
    got = _stats()
    if out is not None and got:
        out["fuzz_stats"] = {"profile": got[0], "keys": KEYS, "counts": got[1]}
