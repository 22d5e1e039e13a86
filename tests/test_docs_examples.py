"""The command-line examples of ``docs/cli/*.md`` run as written (each page's ``bash`` blocks in order, in an
empty folder, ``.venv/bin/`` read as this interpreter's folder), and write what they name (84 s for the six
pages on 2 cores shared with other jobs; the report page's example reports two fields to keep it near 20 s).
The design and validate pages run for minutes each and are left out of CI: the design page's commands
(detach, status, pack, resume) are tested on a smaller config by tests/torch_bridge/test_runs.py;
``validate --quick`` itself is not run in CI."""
from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = sorted(p for p in (ROOT / "docs" / "cli").glob("*.md") if p.stem not in ("README", "design", "validate"))


def _bash_blocks(text: str) -> list[str]:
    return re.findall(r"^```bash\n(.*?)^```", text, flags=re.S | re.M)


@pytest.mark.parametrize("page", PAGES, ids=[p.stem for p in PAGES])
def test_cli_page_examples_run_as_written(page, tmp_path):
    blocks = _bash_blocks(page.read_text())
    assert blocks, f"{page.name} has no bash example"
    (tmp_path / "docs").symlink_to(ROOT / "docs")
    bin_dir = str(Path(sys.executable).parent) + "/"
    script = "set -e\n" + "\n".join(b.replace(".venv/bin/", bin_dir) for b in blocks)
    env = dict(os.environ, MPLBACKEND="Agg")
    p = subprocess.run(["bash", "-c", script], cwd=tmp_path, capture_output=True, text=True, timeout=300, env=env)
    assert p.returncode == 0, (p.stdout[-1500:], p.stderr[-3000:])
    named = set(re.findall(r"out/[\w./-]+\.(?:png|npz|json|md)", "\n".join(blocks)))
    for f in named:
        assert (tmp_path / f).exists(), f"{page.name}: {f} was not written"
    written = list((tmp_path / "out").rglob("*"))
    assert any(w.is_file() and w.stat().st_size > 0 for w in written), f"{page.name} wrote nothing under out/"
