"""Tiled PSF maps: tiles with checkpointing give the same values and gradients as one batch, and
peak memory stays flat as the map grows (and under a given budget)."""
import ctypes
import gc
import os
import threading
import time

import numpy as np
import pytest

torch = pytest.importorskip("torch")

import torch_bridge as tb
from rwwarp.lens import Lens, Sensor, Surface

EVEN = {"kind": "even_poly", "norm_radius": 0.3, "coefficients": [-2.0, 1.0, 0.5]}


def singlet():
    surfs = [Surface(type="aperture", semi_diameter=0.3, shape="circle", stop=True, thickness=0.2),
             Surface(type="standard", radius=12.0, conic=-0.8, aspheric=[1e-4, 2e-6], material="N-BK7",
                     semi_diameter=1.0, thickness=1.0),
             Surface(type="standard", radius=-40.0, semi_diameter=1.0, thickness=0.5),
             Surface(type="doe", semi_diameter=0.6, shape="square", thickness=17.5, profile=EVEN)]
    return Lens(surfs, Sensor(0.004, (1000, 1000)), wavelengths_um=[0.45, 0.55])


FIELDS = [(0.05 * i + 0.013, 0.4 - 0.1 * i) for i in range(8)]


def test_tiles_give_the_same_values_and_gradients():
    hl = tb.HybridLens(singlet(), learn={"doe": "all", "curvature": [1], "thickness": [3]}, replan=False)
    w = torch.from_numpy(np.random.default_rng(0).random((3, 2, 8, 8)))
    grads, maps = [], []
    for tile in (None, 1, 4):
        hl.zero_grad()
        m = hl.psf_map(FIELDS[:3], [0.45, 0.55], 8, tile=tile)
        (m * w).sum().backward()
        maps.append(m.detach().numpy())
        grads.append(torch.cat([p.grad for p in hl.parameters() if p.numel()]).numpy())
    for k in (1, 2):
        np.testing.assert_allclose(maps[k], maps[0], rtol=0, atol=1e-13 * maps[0].max())
        np.testing.assert_allclose(grads[k], grads[0], rtol=1e-10, atol=0)


# --------------------------------------------------------------------------------------- memory
_PAGE = os.sysconf("SC_PAGE_SIZE")


def _rss():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * _PAGE


class PeakRSS:
    """Peak resident memory above the starting point while the block runs (sampled every ms;
    Warp, PoCL and torch allocations all count)."""

    def __enter__(self):
        gc.collect()
        try:
            ctypes.CDLL("libc.so.6").malloc_trim(0)
        except OSError:
            pass
        self.base = self.peak = _rss()
        self._stop = False

        def sample():
            while not self._stop:
                self.peak = max(self.peak, _rss())
                time.sleep(0.001)
        self._t = threading.Thread(target=sample, daemon=True)
        self._t.start()
        return self

    def __exit__(self, *exc):
        self._stop = True
        self._t.join()
        self.peak = max(self.peak, _rss())

    @property
    def bytes(self):
        return self.peak - self.base


@pytest.mark.skipif(not os.path.exists("/proc/self/statm"), reason="needs /proc (Linux) for RSS")
def test_peak_memory_is_flat_in_the_map_size_and_under_the_budget():
    hl = tb.HybridLens(singlet(), learn={"doe": "all", "curvature": [1]}, rays_per_sample=3.0)

    def peak(n_fields, **kw):
        hl.zero_grad()
        with PeakRSS() as p:
            m = hl.psf_map(FIELDS[:n_fields], [0.55], 16, **kw)
            m.sum().backward()
            del m
        return p.bytes

    peak(1, tile=1)  # warm-up: kernel builds, FFT plans
    per_source = hl.bytes_per_source(hl.raywave(FIELDS, [0.55] * 8, 16))
    p2 = peak(2, tile=1)
    p8 = peak(8, tile=1)
    whole = peak(8, tile=8, checkpoint=False)
    # tiles of one source: 4x the fields, about the same peak (slack: allocator noise)
    assert p8 < 1.3 * p2 + 16 * 2**20, (p2, p8)
    # the un-tiled map keeps every source's tape: the test can see growth
    assert whole > p8 + 2 * per_source / 2 / 2, (whole, p8, per_source)
    budget = int(2.2 * per_source)  # room for two sources
    assert peak(8, memory_budget_bytes=budget) < budget


# --------------------------------------------------------------------------------------- spatial tiles
@pytest.mark.parametrize("tile_px", [5, 8])
def test_spatial_tiles_of_the_propagation_equal_untiled(tile_px):
    """The sensor patch evaluated in spatial tiles (ragged for 5 px), each tile checkpointed: the same
    PSF and the same gradients (lens, DOE, distance) as one untiled propagation, to 1e-12."""
    hl = tb.HybridLens(singlet(), learn={"doe": "all", "curvature": [1], "thickness": [2, 3]}, replan=False)
    w = torch.from_numpy(np.random.default_rng(3).random((16, 16)))
    out = []
    for st in (None, tile_px):
        hl.zero_grad()
        p = hl.psf(FIELDS[1], 0.55, 16, spatial_tile=st)
        (p * w).sum().backward()
        out.append((p.detach().numpy(), torch.cat([q.grad for q in hl.parameters() if q.numel()]).numpy()))
    (p0, g0), (p1, g1) = out
    np.testing.assert_allclose(p1, p0, rtol=0, atol=1e-12 * p0.max())
    np.testing.assert_allclose(g1, g0, rtol=1e-12, atol=1e-12 * np.abs(g0).max())


def test_spatial_tiles_field_phase_and_distance_gradients():
    """At the Function level (the ASM's operator path, each tile a checkpoint): a random complex field, DOE phase
    and distance; every gradient of the tiled propagation equals the untiled one to 1e-12, and the values are
    bit-compatible to 1e-12."""
    import warnings

    from torch_bridge.operator_function import operator_propagate

    def propagate(f, p, d, rw, t):
        return operator_propagate(f, d, rw, phi0=p, tile_px=t)
    hl = tb.HybridLens(singlet(), learn={"doe": "all"})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rw = hl.raywave(FIELDS[:2], [0.55, 0.45], 12)
    n = rw.plan.n_grid
    g = torch.Generator().manual_seed(0)
    f0 = torch.randn(2, n, n, dtype=torch.complex128, generator=g)
    p0 = torch.rand(2, n, n, dtype=torch.float64, generator=g) * 6.0
    d0 = torch.full((2,), rw.z_sensor - rw.z_plane, dtype=torch.float64)
    w = torch.rand(2, 12, 12, dtype=torch.float64, generator=g)
    res = []
    for t in (None, 5):
        f, p, d = (x.clone().requires_grad_() for x in (f0, p0, d0))
        out = propagate(f, p, d, rw, t)
        (out * w).sum().backward()
        res.append([out.detach(), f.grad, p.grad, d.grad])
    for a, b in zip(res[1], res[0]):
        scale = b.abs().max()
        assert float((a - b).abs().max()) <= 1e-12 * float(scale), (float((a - b).abs().max()), float(scale))
    with torch.no_grad():
        np.testing.assert_allclose(propagate(f0, p0, d0, rw, 5).numpy(), res[0][0].numpy(), rtol=0,
                                   atol=1e-12 * float(res[0][0].abs().max()))


def test_memory_budget_chooses_spatial_tiles_for_large_patches():
    hl = tb.HybridLens(singlet(), learn={"doe": "all"})
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rw = hl.raywave([FIELDS[0]], [0.55], 64)
    whole = hl.output_bytes_per_source(rw)
    assert hl.spatial_tile_for(rw, 8 * whole) is None
    t = hl.spatial_tile_for(rw, 8 * whole // 3)
    assert t is not None and 8 <= t < 64 and hl.output_bytes_per_source(rw, t) <= whole // 3
