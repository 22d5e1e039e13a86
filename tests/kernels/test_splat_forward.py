"""The separable forward splat (``kernels/splat_forward.py``, the CPU's energy splat off the tape) against the
closed-form box integrals of ``test_splat_kernels._splat_np`` (numpy from the equations), and against the per-cell
``splat_kernel`` it replaces: boxes of a few cells (the factored path) and boxes wider than ``MAX_CELLS`` cells (the
per-cell fallback), a packed layout (windows of their own sides in larger slots), rays dropped off the window."""
import numpy as np
import pytest

wp = pytest.importorskip("warp")

from rwwarp.kernels import splat as ks
from rwwarp.kernels.splat_forward import MAX_CELLS, make_splat_forward_kernel

from test_splat_kernels import F64, V3, _a, _ph, _random_case, _splat_np


def _sums(device, rays, src, n_grid, use_reference, forward, grid_src=None, stride=None):
    """The splat's sums (n_src, stride, stride) complex and the dropped counts, by the forward kernel or by
    ``splat_kernel``; ``grid_src``: each source's window side in slots of ``stride`` (a packed batch)."""
    K = ks.make_splat_kernels(F64)
    nsrc = len(src["pitch"])
    n = len(rays["pos"])
    side = n_grid if stride is None else stride
    s_re = wp.zeros(nsrc * side * side, dtype=F64, device=device)
    s_im = wp.zeros_like(s_re)
    dropped = wp.zeros(nsrc, dtype=wp.int32, device=device)
    gs = _ph(device) if grid_src is None else _a(np.asarray(grid_src, np.int32), wp.int32, device)
    ins = [_a(rays["pos"], V3, device), _a(rays["dir"], V3, device), _a(rays["opl"], F64, device),
           _a(rays["valid"].astype(np.int32), wp.int32, device), _a(rays["weight"], F64, device),
           _a(rays["area"], F64, device), _a(rays["half"], wp.vec2d, device),
           _a(src["origin"], wp.vec2d, device), _a(src["pitch"], F64, device), _a(src["chief"], wp.vec3d, device),
           _a(src["target"], wp.vec3d, device), _a(src["index"], F64, device),
           _a(src["opl_chief"], F64, device), _a(src["k"], F64, device), use_reference, 1,
           n_grid if grid_src is None else -side, n // nsrc, _a(np.array([[1.0, 0.0, 0.0]]), wp.vec3d, device), 0,
           gs, 0]
    if forward:
        wp.launch(make_splat_forward_kernel(F64), dim=n, inputs=ins + [0], outputs=[s_re, s_im, dropped],
                  device=device)
    else:
        na = wp.zeros(1, dtype=wp.int64, device=device)
        nv = wp.zeros(1, dtype=K.vec4d, device=device)
        wp.launch(K.splat_kernel, dim=n, inputs=ins + [0, 0, wp.zeros((1, 1), dtype=K.vec4d, device=device)],
                  outputs=[s_re, s_im, dropped, na, na, nv], device=device)
    S = (s_re.numpy() + 1j * s_im.numpy()).reshape(nsrc, side, side)
    return S, dropped.numpy()


@pytest.mark.parametrize("use_reference", [0, 1], ids=["plain", "reference"])
@pytest.mark.parametrize("box", ["cells", "wide"])
def test_forward_splat_matches_box_integral(device, rng, use_reference, box):
    """Random rays, phases and boxes of 0.3-1.2 cells (``cells``: the factored path) or 9-12 cells half-width
    (``wide``: more than MAX_CELLS = 16 cells across, the per-cell fallback), on a 40-sample window: the sums
    against the closed-form box integrals, and against ``splat_kernel``. Measured on the CPU: 2.4e-15 (cells)
    and 2.9e-15 (wide) of the largest sample from the integrals (``splat_kernel``'s own: the same), 2.1e-16 / 0
    from ``splat_kernel``; tolerance 2e-14, that of ``splat_kernel`` against the integrals (test_splat_kernels)."""
    n_grid, h = 40, 0.01
    rays, src, n = _random_case(rng, npup=40, n_grid=n_grid, h=h)
    if box == "wide":
        rays["half"] = rng.uniform(9 * h, 12 * h, rays["half"].shape)
        rays["area"] = 4.0 * rays["half"][:, 0] * rays["half"][:, 1]
        assert 2 * rays["half"].min() / h > MAX_CELLS
    S, dropped = _sums(device, rays, src, n, use_reference, forward=True)
    S_np, _ = _splat_np(rays, src, n, energy=1, use_reference=use_reference)
    S_cell, dropped_cell = _sums(device, rays, src, n, use_reference, forward=False)
    assert (dropped == 0).all() and (dropped_cell == 0).all()
    peak = np.abs(S_np).max()
    assert np.abs(S - S_np).max() < 2e-14 * peak
    assert np.abs(S - S_cell).max() < 2e-14 * peak


def test_forward_splat_packed_windows_and_dropped_rays(device, rng):
    """A packed layout (source 0's window 16 samples in slots of 24, source 1's 24) with rays whose boxes stick
    out of their own window: the same sums and dropped counts as ``splat_kernel`` (measured 3.8e-16 of the
    largest sample; tolerance 2e-14), nothing written outside a source's own window."""
    rays, src, n = _random_case(rng, npup=60, n_grid=16)
    rays["valid"][:] = True
    rays["pos"][3, 0] = src["origin"][0, 0] + 15.6 * src["pitch"][0]     # source 0: out on the right of its 16
    S, dropped = _sums(device, rays, src, 16, 1, forward=True, grid_src=[16, 24], stride=24)
    S_cell, dropped_cell = _sums(device, rays, src, 16, 1, forward=False, grid_src=[16, 24], stride=24)
    assert dropped[0] >= 1 and np.array_equal(dropped, dropped_cell)
    assert np.abs(S - S_cell).max() < 2e-14 * np.abs(S_cell).max()
    assert not np.any(S[0, 16:, :]) and not np.any(S[0, :, 16:])
