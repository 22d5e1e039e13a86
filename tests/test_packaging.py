"""Every data file the packages read at run time is shipped by a non-editable install: each
non-Python file under the package folders matches a ``[tool.setuptools.package-data]`` glob of
``pyproject.toml`` (a bundled config missing from the wheel broke ``rwwarp design NAME`` on a
plain install)."""
import fnmatch
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_package_data_covers_data_files():
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    dirs = {name: ROOT / cfg.get("package-dir", {}).get(name, name.replace(".", "/")) for name in cfg["packages"]}
    data = cfg["package-data"]
    missing = []
    for name in ("rwwarp", "torch_bridge", "rwwarp.kernels"):
        base = dirs[name]
        for f in base.rglob("*"):
            if not f.is_file() or f.suffix in (".py", ".pyc") or "__pycache__" in f.parts:
                continue
            # the innermost listed package that holds the file ships it
            owner = max((n for n, d in dirs.items() if d in f.parents), key=lambda n: len(str(dirs[n])))
            rel = f.relative_to(dirs[owner]).as_posix()
            if not any(fnmatch.fnmatch(rel, g) for g in data.get(owner, [])):
                missing.append(f"{f.relative_to(ROOT)} (package {owner})")
    assert not missing, "not in [tool.setuptools.package-data]: " + ", ".join(missing)
