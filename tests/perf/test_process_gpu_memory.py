"""The smoke's per-process GPU memory (``perf/_common.py`` ``ProcessGpuMemory``): the sum of the driver's
per-process figures over a process and its descendants, other processes left out. No GPU here: a stand-in
``nvidia-smi`` on the PATH prints the rows the driver would (``pid, MiB`` of ``--query-compute-apps``), for a real
process tree started by the test."""
import os
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "perf"))
from _common import ProcessGpuMemory, process_tree  # noqa: E402


def _fake_smi(tmp_path, rows_file):
    b = tmp_path / "bin"
    b.mkdir()
    (b / "nvidia-smi").write_text(f"#!/bin/sh\ncat {rows_file}\n")
    (b / "nvidia-smi").chmod(0o755)
    return str(b)


def test_the_tree_of_a_process_and_its_memory(tmp_path, monkeypatch):
    # a parent (sh) with a child (sleep): the tree holds both; an unrelated process is not in it
    parent = subprocess.Popen(["sh", "-c", "sleep 30 & wait"])
    other = subprocess.Popen(["sleep", "30"])
    child = None
    try:
        for _ in range(100):
            tree = process_tree(parent.pid)
            if len(tree) == 2:
                break
            time.sleep(0.02)
        assert parent.pid in tree and len(tree) == 2 and other.pid not in tree
        child = (tree - {parent.pid}).pop()
        rows = tmp_path / "rows.csv"
        monkeypatch.setenv("PATH", _fake_smi(tmp_path, rows) + os.pathsep + os.environ["PATH"])
        m = ProcessGpuMemory(parent.pid)
        rows.write_text(f"{other.pid}, 9000\n")                 # only another process on the GPU
        assert m.sample() == 0 and not m.matched
        rows.write_text(f"{other.pid}, 9000\n{child}, 1500\n{parent.pid}, 300\n")
        assert m.sample() == 1800 and m.matched                  # the tree's two rows, not the other's
        rows.write_text("No running processes found\n")         # what nvidia-smi prints with no compute process
        assert m.sample() == 0
        # the sampler thread keeps the peak and when it was first seen
        rows.write_text(f"{child}, 2500\n")
        with ProcessGpuMemory(parent.pid, period=0.01) as s:
            time.sleep(0.3)
        assert s.peak == 2500 and s.matched and s.peak_at_s is not None
    finally:
        if child is not None:
            os.kill(child, 9)
        for p in (parent, other):
            p.kill()
            p.wait()
    # a process that has gone: its tree is itself alone (nothing to read under /proc)
    assert process_tree(parent.pid) == {parent.pid}
