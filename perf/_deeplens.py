"""DeepLens (``deeplens-core`` 2.5.6) for the benchmarks only: import, the A489 + DOE lens in its JSON
format, and the registration of its PSF patches onto ours. Never a dependency of rwwarp.

Install (benchmarks only): ``pip install --no-deps deeplens_core-2.5.6-py3-none-any.whl`` (the wheel says
Python >= 3.12; it runs on 3.11 with ``--ignore-requires-python``), then ``einops opencv-python-headless
scikit-image`` with ``torch==2.13.0`` pinned so that pip keeps the installed torch, and ``lpips`` with
``--no-deps`` (it requires torchvision).
DeepLens imports ``torchvision`` at module level but only calls ``torchvision.utils.save_image`` /
``make_grid`` (image writing); ``lpips`` imports ``torchvision.models``. PyPI's torchvision wheels are
CUDA builds that do not load with the CPU torch (``operator torchvision::nms does not exist``), so where
the real torchvision cannot be imported, :func:`import_deeplens` puts a stub in ``sys.modules`` whose
image writers raise; nothing on DeepLens's PSF path touches it.

Conventions of ``HybridLens.psf`` (read from its source, checked against rwwarp in ``speed_accuracy.py``):
the point is ``[x, y, z]`` with x, y normalised to the sensor half-size at the object plane
(``y = depth tan(field) / (scale * h / 2)`` puts the object on the y axis at ``depth tan(field)``, depth
from the first vertex, the same source as rwwarp's ``field_deg`` at ``object_distance`` 10 m); rays are
sampled uniformly at random over the entrance pupil (at least 10^6, it asserts), each splatted
bilinearly onto the DOE's fixed grid (here 3000^2 at 1 um over the whole 3 mm DOE) with amplitude
``sqrt(|d_z|)`` and its full phase; the grid is padded 2x, propagated by the ASM to the sensor and
``|U|^2`` taken at the grid points (point samples at the pixel centres, no pixel integration), flipped
(image rows top-down, x and y mirrored), cropped around the chief ray rounded to a pixel, and normalised
to sum 1 over the patch, in float32.
"""
from __future__ import annotations

import json
import math
import os
import sys
import tempfile
import types

import numpy as np

# the DOE grid of the DeepLens lens below: 3000^2 samples of 1 um over the whole 3 mm DOE
DOE_RES = 3000
DOE_PITCH_MM = 0.001


def _stub_torchvision():
    """Put a minimal ``torchvision`` in ``sys.modules`` (image writers that raise, an empty ``models``)."""
    for k in [k for k in sys.modules if k == "torchvision" or k.startswith("torchvision.")]:
        del sys.modules[k]

    def unavailable(*a, **k):
        raise NotImplementedError("torchvision is stubbed for the DeepLens benchmarks (CPU torch, CUDA-only "
                                  "torchvision wheels); image writing is not available")
    tv = types.ModuleType("torchvision")
    tv.__path__ = []
    tv.__stub__ = True
    utils = types.ModuleType("torchvision.utils")
    utils.save_image = utils.make_grid = unavailable
    models = types.ModuleType("torchvision.models")
    tv.utils, tv.models = utils, models
    sys.modules.update({"torchvision": tv, "torchvision.utils": utils, "torchvision.models": models})


def import_deeplens():
    """Import ``deeplens`` (stubbing torchvision where the real one does not load). Returns the module;
    raises ImportError where deeplens-core is not installed."""
    try:
        import torchvision  # noqa: F401
    except Exception:
        _stub_torchvision()
    import deeplens
    return deeplens


def deeplens_importable() -> bool:
    try:
        import_deeplens()
        return True
    except Exception:
        return False


def deeplens_json(path):
    """The A489 + flat DOE lens (``a489_doe``) in DeepLens's JSON format. ``ai`` is DeepLens's legacy
    aspheric list (ai[0] the r^2 term, then r^4 ... r^12: the same coefficients as rwwarp's r^4 ...)."""
    d = {"info": "A489 + flat DOE (rwwarp benchmark)", "d_sensor": 11.257, "sensor_size": [3.0, 3.0],
         "sensor_res": [3000, 3000],
         "surfaces": [
             {"type": "Aperture", "r": 1.0, "d": 0.0, "mat2": "air", "is_square": False, "diffraction": False,
              "d_next": 0.1},
             {"type": "Aspheric", "r": 6.35, "roc": 4.7531, "d": 0.1, "k": -1.2051,
              "ai": [0.0, 5.33e-4, 1.12e-5, -3.75e-7, -7.63e-9, 1.36e-10], "mat2": "h-k51", "d_next": 7.5},
             {"type": "Spheric", "r": 6.35, "roc": -15.65, "d": 7.6, "mat2": "air", "d_next": 3.657}],
         "DOE": {"type": "binary2", "d": 8.3098, "res": [DOE_RES, DOE_RES], "fab_ps": DOE_PITCH_MM,
                 "is_square": True, "mat": "fused_silica", "wvln0": 0.55}}
    with open(path, "w") as f:
        json.dump(d, f)


def a489_hybridlens(device="cpu"):
    """DeepLens ``HybridLens`` of the A489 + flat DOE (its Binary2 coefficients zeroed), float64."""
    import torch
    import_deeplens()
    torch.set_default_dtype(torch.float64)
    from deeplens.hybridlens import HybridLens
    path = os.path.join(tempfile.mkdtemp(), "a489_doe_deeplens.json")
    deeplens_json(path)
    lens = HybridLens(filename=path, device=device)
    for k in ("alpha2", "alpha4", "alpha6", "alpha8", "alpha10"):
        if hasattr(lens.doe, k):
            setattr(lens.doe, k, torch.zeros(1, device=device, dtype=torch.float64))
    return lens


def point_for_field(lens, field_deg, depth_mm=10000.0):
    """DeepLens's ``points`` argument for a source at ``depth_mm`` from the first vertex on the y axis at
    ``field_deg`` (object height ``depth tan(field)``), rwwarp's ``field_deg`` at that object distance."""
    scale = float(lens.calc_scale(-depth_mm))
    half = float(lens.sensor_size[1]) / 2.0
    return [0.0, depth_mm * math.tan(math.radians(field_deg)) / (scale * half), -depth_mm]


def chief_ray_mm(lens, point):
    """Where DeepLens puts its patch centre: its chief ray on the sensor (mm, in its mirrored frame)."""
    import torch
    g = lens.geolens
    p = torch.as_tensor([point], dtype=torch.float64, device=lens.device)
    p[:, 0] = p[:, 0] * float(g.calc_scale(point[2])) * g.sensor_size[0] / 2
    p[:, 1] = p[:, 1] * float(g.calc_scale(point[2])) * g.sensor_size[1] / 2
    with torch.no_grad():
        c = g.psf_center(p, method="chief_ray")[0]
    return [float(c[0]), float(c[1])]


def rel_l2(a, b):
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


def register(big, ref):
    """Best match of a DeepLens patch ``big`` (m x m, m >= n, centred like ``ref``) to the n x n reference
    over the four flips and every n x n crop of it (integer shifts up to (m - n) / 2 px each way), after
    scaling the crop to the reference's patch power (DeepLens normalises to sum 1 over its own patch).
    Cropping a larger patch instead of shifting in zeros leaves no empty rows where the PSF overflows.
    Returns (aligned n x n array, description with ``at_edge``: the best shift is on the search border)."""
    n, m = ref.shape[0], big.shape[0]
    half = (m - n) // 2
    best = None
    for fy in (False, True):
        for fx in (False, True):
            a = big[::-1] if fy else big
            a = a[:, ::-1] if fx else a
            for oy in range(m - n + 1):
                for ox in range(m - n + 1):
                    b = a[oy:oy + n, ox:ox + n]
                    b = b * (ref.sum() / max(b.sum(), 1e-300))
                    e = rel_l2(b, ref)
                    if best is None or e < best[0]:
                        best = (e, b, {"flip_y": fy, "flip_x": fx, "shift_px": [ox - half, oy - half]})
    how = best[2]
    how["at_edge"] = bool(max(abs(s) for s in how["shift_px"]) >= half)
    return best[1], how
