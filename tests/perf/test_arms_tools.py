"""The shell tools that move design runs to and from the GPU machines (``perf/tools/pack_out.sh``,
``perf/tools/arms_gpu.sh start``), on the two faults that cost session 23 a resumed run: a pack laid out in calls
too big to carry beside the tree (the device tool refuses a call over 64 MiB: tree + carried folders), and a run
started from step 0 when its pack folder arrived incomplete."""
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
MIB = 1048576
LIMIT = 64 * MIB                      # what the device tool carries a call: the tree plus the carried folders
PART = 15 * MIB                       # `rwwarp design pack` writes parts of <= 15 MiB

pytestmark = pytest.mark.skipif(shutil.which("git") is None or shutil.which("bash") is None,
                                reason="needs git and bash")


def _repo(tmp_path: Path, tree_mib: int, parts: int) -> Path:
    """A git checkout whose tree is ``tree_mib`` MiB, with a pack of ``parts`` 15 MiB parts in out/pack/run."""
    repo = tmp_path / "repo"
    (repo / "out" / "pack" / "run").mkdir(parents=True)
    subprocess.run(["git", "init", "-q", str(repo)], check=True)
    (repo / ".gitignore").write_text("out/\n.device/\n")
    with open(repo / "big.bin", "wb") as f:          # the tracked tree: sparse, only its size matters
        f.truncate(tree_mib * MIB)
    pack = repo / "out" / "pack" / "run"
    (pack / "pack.json").write_text("{}")
    for i in range(parts):
        with open(pack / f"pack.part{i:03d}", "wb") as f:
            f.truncate(PART)
    return repo


def _folder_bytes(d: Path) -> int:
    return sum(f.stat().st_size for f in d.iterdir())


@pytest.mark.parametrize("tree_mib", [1, 20, 34])
def test_pack_out_calls_fit_beside_the_tree(tmp_path, tree_mib):
    repo = _repo(tmp_path, tree_mib, parts=7)
    out = subprocess.run(["bash", str(ROOT / "perf" / "tools" / "pack_out.sh"), "run"], cwd=repo,
                         capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    tree = (repo / "big.bin").stat().st_size + (repo / ".gitignore").stat().st_size
    folders = sorted((repo / ".device").iterdir())
    got = []
    for d in folders:
        assert tree + _folder_bytes(d) <= LIMIT, (d.name, tree + _folder_bytes(d))
        got += [f.name for f in d.iterdir() if f.name.startswith("pack.part")]
    assert sorted(got) == [f"pack.part{i:03d}" for i in range(7)]       # every part goes, once
    assert (folders[0] / "pack.json").exists()
    # as many parts a call as fit with 4 MiB to spare: 3 beside a 1 MiB tree, 2 beside 20 MiB, 1 beside 34 MiB
    per = (LIMIT - tree - 4 * MIB) // PART
    assert max(len(list(d.glob("pack.part*"))) for d in folders) == per == {1: 3, 20: 2, 34: 1}[tree_mib]


def test_pack_out_refuses_when_no_part_fits(tmp_path):
    repo = _repo(tmp_path, 50, parts=2)
    out = subprocess.run(["bash", str(ROOT / "perf" / "tools" / "pack_out.sh"), "run"], cwd=repo,
                         capture_output=True, text=True)
    assert out.returncode == 2 and "no room for one part" in out.stderr
    assert not (repo / ".device").exists()


def test_start_refuses_an_incomplete_pack(tmp_path):
    """A pack folder without pack.json is a trip cut short: ``start`` must stop with exit 2 and say so, not start the
    run from step 0 (what it did before)."""
    (tmp_path / "data" / "debian-photos").mkdir(parents=True)
    (tmp_path / "data" / "debian-photos" / "MANIFEST.json").write_text("{}")
    pack = tmp_path / "out" / "pack" / "a489_aberration_gpu_s1_e2e_doe"
    pack.mkdir(parents=True)
    (pack / "pack.part006").write_bytes(b"x")
    bindir = tmp_path / "bin"
    bindir.mkdir()
    wrapper = bindir / "python3"                               # the script's python3: this interpreter (a venv's
    wrapper.write_text(f'#!/bin/sh\nexec "{sys.executable}" "$@"\n')   # python found through a link loses the venv)
    wrapper.chmod(0o755)
    env = {**os.environ, "PATH": f"{bindir}{os.pathsep}{os.environ['PATH']}", "ARMS_NGPU": "1",
           "ARMS_PRESET": "cpu", "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    out = subprocess.run(["bash", str(ROOT / "perf" / "tools" / "arms_gpu.sh"), "start", "a489_aberration",
                          "1:e2e_doe"], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 2, (out.stdout, out.stderr)
    assert "no pack.json" in out.stderr
    assert not (tmp_path / "out" / "design").exists()        # nothing was started
