"""The OpenCL C sources of ``kernels/opencl`` (imported as ``rwwarp.kernels``): their text with the ``#include``
lines expanded, as both compilers take it (OpenCL, and NVRTC after ``cuda_compat.h``), and each kernel's argument
kinds, from which the backends pack a launch's arguments (:mod:`rwwarp.wave.backend`)."""
from __future__ import annotations

import functools
import importlib.util
import re
from pathlib import Path

__all__ = ["kernel_source"]


def _kernel_dir() -> Path:
    """Folder of the OpenCL C sources: ``rwwarp.kernels/opencl`` when installed, else the
    repository's ``kernels/opencl``."""
    try:
        spec = importlib.util.find_spec("rwwarp.kernels")
    except (ImportError, ValueError):
        spec = None
    if spec is not None and spec.submodule_search_locations:
        for loc in spec.submodule_search_locations:
            cand = Path(loc) / "opencl"
            if cand.is_dir():
                return cand
    cand = Path(__file__).resolve().parents[2] / "kernels" / "opencl"
    if cand.is_dir():
        return cand
    raise FileNotFoundError("cannot find the OpenCL kernel sources (kernels/opencl)")


_INCLUDE_RE = re.compile(r'^[ \t]*#[ \t]*include[ \t]*"([^"]+)"[ \t]*$', re.MULTILINE)


@functools.cache
def kernel_source(name: str) -> str:
    """Text of ``kernels/opencl/<name>`` with its ``#include "..."`` lines expanded in place
    (each header once), so that both compilers get one self-contained source."""
    folder = _kernel_dir()
    seen: set[str] = set()

    def expand(fname: str) -> str:
        if fname in seen:
            return ""
        seen.add(fname)
        text = (folder / fname).read_text()
        return _INCLUDE_RE.sub(lambda m: expand(m.group(1)), text)

    return expand(name)


_KERNEL_RE = re.compile(r"__kernel\s+void\s+(\w+)\s*\(([^)]*)\)", re.MULTILINE)


@functools.cache
def _kernel_signatures(name: str) -> dict:
    """Argument kinds of each ``__kernel`` in a source: 'buf' for pointers, else the scalar type
    name (int, real_t, phase_t, idx_t)."""
    src = re.sub(r"/\*.*?\*/", "", kernel_source(name), flags=re.DOTALL)
    out = {}
    for kname, args in _KERNEL_RE.findall(src):
        kinds = []
        for arg in args.split(","):
            arg = arg.strip()
            if "*" in arg:
                kinds.append("buf")
                continue
            toks = arg.replace("const", "").split()
            kinds.append(toks[0])
        out[kname] = tuple(kinds)
    return out
