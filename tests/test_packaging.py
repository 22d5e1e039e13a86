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


def test_every_package_folder_is_installed():
    """Every folder of Python modules under rwwarp/ and torch_bridge/ is listed in ``packages`` (a new sub-package
    missing from the list is absent from a non-editable install: rwwarp.wave.methods was, and the GPU machine's
    install failed to import rwwarp while every CPU test, run from the source tree, passed)."""
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    listed = {(ROOT / cfg.get("package-dir", {}).get(n, n.replace(".", "/"))).resolve() for n in cfg["packages"]}
    missing = []
    for top in ("rwwarp", "torch_bridge"):
        for init in (ROOT / top).rglob("__init__.py"):
            if "__pycache__" in init.parts:
                continue
            if init.parent.resolve() not in listed:
                missing.append(init.parent.relative_to(ROOT).as_posix())
    assert not missing, "packages missing from pyproject.toml [tool.setuptools] packages: " + ", ".join(missing)


def test_ci_pins_lie_inside_the_declared_ranges_and_setup_uses_them():
    """pyproject.toml declares ranges (a research environment's numpy/torch/warp need not match CI's); the
    exact tested versions live in .ci/constraints.txt, which .ci/setup installs with, and each pin must be
    one that the declared range accepts."""
    from packaging.requirements import Requirement

    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    reqs = [Requirement(r) for r in cfg["dependencies"] + sum(cfg["optional-dependencies"].values(), [])]
    pins = {}
    for line in (ROOT / ".ci" / "constraints.txt").read_text().splitlines():
        line = line.split("#")[0].strip()
        if line:
            name, ver = line.split("==")
            pins[name.lower()] = ver
    for r in reqs:
        if r.name == "cupy-cuda12x":
            continue
        assert r.name.lower() in pins, f"{r.name} has no tested pin in .ci/constraints.txt"
        assert r.specifier.contains(pins[r.name.lower()]), f"{r.name}=={pins[r.name.lower()]} outside {r.specifier}"
        assert not any(s.operator == "==" for s in r.specifier), f"{r.name}: pinned in pyproject ({r.specifier})"
    setup = (ROOT / ".ci" / "setup").read_text()
    assert "constraints.txt" in setup and setup.count('-c "$cons"') >= 3
