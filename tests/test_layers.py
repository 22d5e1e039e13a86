"""The layers hold: no import circle among rwwarp modules, no arrow up the layers.

The layers, bottom to top: ``rwwarp.kernels`` (the ``kernels/`` folder) -> ``rwwarp`` -> ``torch_bridge``.
Every import statement is read with ``ast`` -- at module level and inside functions alike (a lazy import
is still an arrow; it only hides it from the interpreter's start-up) -- and resolved to the module it
names. The graph among rwwarp modules must be acyclic, ``rwwarp.kernels`` must not import the rest of
rwwarp, and nothing under ``rwwarp/`` or ``kernels/`` may import ``torch`` or ``torch_bridge``
(``rwwarp design`` finds torch_bridge through the ``rwwarp.commands`` entry point group instead).
"""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# package name -> folder, as pyproject's [tool.setuptools.package-dir] maps them
PACKAGES = {"rwwarp": ROOT / "rwwarp", "rwwarp.kernels": ROOT / "kernels"}
UPPER = ("torch", "torch_bridge")     # nothing in rwwarp/ or kernels/ may import these
# The one documented exception (while it exists): rwwarp.distributed shards a PSF map over the ranks of a
# torch.distributed job and imports torch only inside the functions that run in one (a single-process psf_map
# never imports torch); it uses torch.distributed as a process-group library, not torch_bridge's autograd
# layer. A module-level import of torch there still fails.
OPTIONAL = {"rwwarp.distributed": "torch"}


def _modules() -> dict[str, Path]:
    """Every rwwarp module: dotted name -> file."""
    out = {}
    for pkg, folder in PACKAGES.items():
        for f in sorted(folder.rglob("*.py")):
            rel = f.relative_to(folder).with_suffix("")
            parts = list(rel.parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            name = ".".join([pkg, *parts])
            if pkg == "rwwarp" and name.startswith("rwwarp.kernels"):
                continue
            out[name] = f
    return out


def _imports(name: str, path: Path, known: set[str]) -> list[tuple[str, int]]:
    """(imported module, line, lazy) for every import in ``path`` (module ``name``); lazy: inside a function."""
    tree = ast.parse(path.read_text(), filename=str(path))
    is_pkg = path.name == "__init__.py"
    package = name if is_pkg else name.rpartition(".")[0]
    found = []
    in_function = {id(n) for f in ast.walk(tree) if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef))
                   for n in ast.walk(f)}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [((a.name, node.lineno), id(node)) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module
            subs = [f"{mod}.{a.name}" for a in node.names if f"{mod}.{a.name}" in known]
            found += [((s, node.lineno), id(node)) for s in subs]   # `from pkg import submodule`: the submodule
            if len(subs) < len(node.names):             # (a parent package is always imported first
                found.append(((mod, node.lineno), id(node)))   # anyway: not an arrow of its own)
    return [(t, line, id_ in in_function) for (t, line), id_ in found]


def _graph():
    mods = _modules()
    known = set(mods)
    edges, upward = {m: set() for m in mods}, []
    for m, path in mods.items():
        for target, line, lazy in _imports(m, path, known):
            top = target.split(".")[0]
            optional = lazy and m in OPTIONAL and (target + ".").startswith(OPTIONAL[m] + ".")
            if top in UPPER and not optional:
                upward.append(f"{path.relative_to(ROOT)}:{line} imports {target}")
            if target in known and target != m:
                edges[m].add(target)
            elif top == "rwwarp" and target not in known:
                # `import rwwarp.x.y` where y is a name: the nearest known module
                parts = target.split(".")
                while parts and ".".join(parts) not in known:
                    parts.pop()
                if parts and ".".join(parts) != m:
                    edges[m].add(".".join(parts))
    return mods, edges, upward


def _cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []
    counter = [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(edges[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return out


def test_graph_sees_the_modules():
    mods, edges, _ = _graph()
    assert "rwwarp.lens" in mods and "rwwarp.kernels.trace" in mods
    assert "rwwarp.kernels.trace" in edges["rwwarp.trace"]   # `from .kernels import trace as ktrace`


def test_no_import_cycle():
    _, edges, _ = _graph()
    cycles = _cycles(edges)
    assert not cycles, "import circles among rwwarp modules:\n" + "\n".join(
        " <-> ".join(c) for c in cycles)


def test_kernels_import_nothing_above():
    mods, edges, _ = _graph()
    bad = [f"{m} -> {t}" for m in mods if m.startswith("rwwarp.kernels")
           for t in edges[m] if not t.startswith("rwwarp.kernels")]
    assert not bad, "rwwarp.kernels imports the layer above:\n" + "\n".join(bad)


def test_no_torch_in_rwwarp():
    _, _, upward = _graph()
    assert not upward, "arrows up the layers:\n" + "\n".join(upward)


def test_design_command_is_an_entry_point():
    """``rwwarp design`` reaches torch_bridge through the ``rwwarp.commands`` entry point group (written to the
    installed metadata by ``pip install -e .``, which ``.ci/setup`` runs whenever pyproject.toml changes)."""
    from importlib.metadata import entry_points

    import tomllib

    declared = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["entry-points"]["rwwarp.commands"]
    installed = {ep.name: ep.value for ep in entry_points(group="rwwarp.commands")}
    assert declared == {"design": "torch_bridge.train:main"}
    assert installed.get("design") == declared["design"], "reinstall: pip install -e '.[torch]' (bash .ci/setup)"


def test_torch_bridge_reaches_rwwarp_through_its_host_modules():
    """torch_bridge imports rwwarp's host modules, never the device code (``rwwarp.kernels``) or a private
    name of another package (``from rwwarp.x import _y``): the surface table's columns come from
    ``rwwarp.trace.COLUMNS``."""
    bad = []
    for f in sorted((ROOT / "torch_bridge").glob("*.py")):
        tree = ast.parse(f.read_text(), filename=str(f))
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and not node.level and (node.module or "").startswith("rwwarp"):
                if node.module.startswith("rwwarp.kernels") or "kernels" in {a.name for a in node.names}:
                    bad.append(f"{f.name}:{node.lineno} imports {node.module}")
                bad += [f"{f.name}:{node.lineno} imports {node.module}.{a.name}" for a in node.names
                        if a.name.startswith("_")]
            elif isinstance(node, ast.Import):
                bad += [f"{f.name}:{node.lineno} imports {a.name}" for a in node.names
                        if a.name.startswith("rwwarp.kernels")]
    assert not bad, "torch_bridge reaches past rwwarp's public host modules:\n" + "\n".join(bad)
