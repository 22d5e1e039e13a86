"""The cost model of ``method="pixel"`` (rwwarp.wave.pixel_scale.pixel_cost, pixel_kirchhoff.tile_cost) against the
work the method does: its NUFFT calls are recorded (points, weight vectors, outputs) and their flops counted here
from those loop sizes, written out below (not the model's functions); memory against tracemalloc's peak."""
import math
import tracemalloc

import numpy as np
import pytest

import rwwarp as rw
import rwwarp.wave.pixel_scale as ps
from rwwarp.io import load_lens
from rwwarp.wave import pixel_kirchhoff as pk


def _nufft_work(J, K, n, spread=6, R=2):
    """Flops of a Gaussian-gridding type-1 NUFFT of J points, K weight vectors, n^2 outputs: per point, cell of the
    (2 spread)^2 footprint and vector 2 multiplies (the weight's real and imaginary parts by the Gaussian) and 2 adds;
    per point, footprint row and vector 2 multiplies (the weight by the row's Gaussian); per point 2 x 2 spread 1-D
    Gaussians (~20 flops each); per vector an (R n)^2 complex FFT (5 N log2 N) and the deconvolution (2 n^2)."""
    N = (R * n) ** 2
    return (J * K * ((2 * spread) ** 2 * 4 + 2 * spread * 2) + J * 4 * spread * 20
            + K * (5 * N * math.log2(N) + 2 * n * n))


@pytest.fixture
def nufft_calls(monkeypatch):
    calls = []
    from rwwarp.wave import nufft
    orig = nufft.nufft_type1

    def spy(tx, ty, c, n, xp=np, **kw):
        calls.append((len(tx), 1 if np.ndim(c) == 1 else np.shape(c)[0], n, kw.get("spread") or ps.NUFFT_SPREAD))
        return orig(tx, ty, c, n, xp, **kw)
    monkeypatch.setattr(nufft, "nufft_type1", spy)
    return calls


def _synthetic(J, z, seed=1):
    rng = np.random.default_rng(seed)
    rr, ph = 1.5 * np.sqrt(rng.uniform(0, 1, J)), rng.uniform(0, 2 * np.pi, J)
    P = np.stack([rr * np.cos(ph), rr * np.sin(ph), np.zeros(J)], -1)
    T = np.array([0.0, 0.0, z])
    return P, -np.linalg.norm(T - P, axis=1), rng.uniform(0.5, 1.5, J) + 0j, T


_SPREADS = {"lin": 4, "quad": 3, "amp": 3, "cub": 2}     # as group_spreads gives for eps ~0.04 (EF50 f/1.8, 10 deg)


@pytest.mark.parametrize("J,z,h,n,tile_max,grid_bytes,spreads", [(3000, 5.0, 0.0008, 48, 24, 2 * 2 ** 20, None),
                                                                 (1500, 200.0, 0.004, 160, 160, None, None),
                                                                 (3000, 5.0, 0.0008, 48, 24, 2 * 2 ** 20, _SPREADS)])
def test_kirchhoff_tile_cost_is_the_work_and_memory_of_its_loop(nufft_calls, J, z, h, n, tile_max, grid_bytes, spreads):
    P, L, amp, T = _synthetic(J, z)
    nt, t = pk.kirchhoff_tiles(P, T, 0.55e-3, 1.0, h, n, tile_max)
    tracemalloc.start()
    base = tracemalloc.get_traced_memory()[0]
    pk.kirchhoff_samples(P, L, amp, 0.55e-3, 1.0, T, np.zeros(2), h, n, True, tile_max=tile_max, grid_bytes=grid_bytes,
                         spreads=spreads)
    peak = tracemalloc.get_traced_memory()[1] - base
    tracemalloc.stop()
    model = pk.tile_cost(nt, J, True, grid_bytes, spreads=spreads)
    # every tile takes every point into 17 weight vectors: the plane waves of U and U_w in one call at the full spread,
    # the 15 corrections (quadratic rest 3 + 6, amplitude 2, cubic 4) in chunks, each group at its spread (all at
    # REST_SPREAD where spreads is None), the wider spreads first
    assert sum(c[1] for c in nufft_calls) == t * t * 17 and all(c[0] == J and c[2] == nt for c in nufft_calls)
    sp = spreads or {g: pk.REST_SPREAD for g in pk.GROUPS}
    per_tile = [(2, ps.NUFFT_SPREAD)]
    for s in sorted(set(sp.values()), reverse=True):
        k = sum({"lin": 3, "quad": 6, "amp": 2, "cub": 4}[g] for g in sp if sp[g] == s)
        per_tile += [(min(model["chunk"], k - c0), s) for c0 in range(0, k, model["chunk"])]
    assert [(c[1], c[3]) for c in nufft_calls] == per_tile * t * t
    work = sum(_nufft_work(*c) for c in nufft_calls)
    assert t * t * model["nufft_flops"] == pytest.approx(work, rel=1e-9)
    # the rest (forming the vectors, combining them) is a small share: the model's total within 25% of the NUFFTs
    assert work < t * t * model["flops"] < 1.25 * work
    # memory: the model covers the measured peak (one tile's arrays, its larger NUFFT call's) within 25% (measured 1.00-1.18
    # on points- and grid-dominated cases)
    assert peak <= model["memory_bytes"] <= 1.25 * peak


def test_plan_cost_is_the_run_debye(nufft_calls):
    lens = load_lens("a489_doe")
    pl = rw.plan_psf(lens, 0.0, 0.55, size=15, pixel_mm=0.016, method="pixel")
    assert pl.pixel_field["form"] == "debye" == pl.estimate["form"]
    rw.psf(lens, 0.0, 0.55, size=15, pixel_mm=0.016, method="pixel")
    # U and U_w ("flux"), one NUFFT each of the rays inside the pupil, per tile
    assert [c[1] for c in nufft_calls] == [1, 1] * pl.estimate["tiles"] ** 2
    work = sum(_nufft_work(*c) for c in nufft_calls)
    # the points from the pilot's share of the pupil grid: measured 1e-4 off the traced rays' count
    assert pl.estimate["nufft_flops"] == pytest.approx(work, rel=0.01)
    assert "sensor field form debye" in pl.explain()


# 5 px, KIRCHHOFF_NEAR off: tiles over the whole grid (4 x 4 of 44, the last overlapping); 15 px: 9 tiles of 38 over the spot's region (the
# pilot landings' box + 12 / B a side), the Debye form elsewhere
@pytest.mark.parametrize("size,near_only", [(5, False), (15, True)])
def test_plan_cost_is_the_run_kirchhoff(nufft_calls, monkeypatch, size, near_only):
    monkeypatch.setattr(ps, "FIELD_FORM", "kirchhoff")
    monkeypatch.setattr(ps, "KIRCHHOFF_NEAR", near_only)
    lens = load_lens("a489_doe")
    kw = dict(size=size, pixel_mm=0.016, method="pixel", rays_per_sample=0.2)     # 121 rays across: the count only
    pl = rw.plan_psf(lens, 0.0, 0.55, **kw)
    f = pl.pixel_field
    assert f["form"] == "kirchhoff" == pl.estimate["form"] and f["vectors"] == 17
    assert (f["reach_mm"] is None) == (not near_only) and f["near"] == len(f["origins"]) == (16 if size == 5 else 9)
    # the tiles lie inside the grid and, where all are Kirchhoff, cover it
    n, nt = pl.n_sensor, f["tile"]
    cover = np.zeros((n, n), bool)
    for sy, sx in f["origins"]:
        assert 0 <= sy <= n - nt and 0 <= sx <= n - nt
        cover[sy:sy + nt, sx:sx + nt] = True
    assert cover.all() == (not near_only)
    rw.psf(lens, 0.0, 0.55, **kw)
    kirch = [c for c in nufft_calls if c[2] == f["tile"]]
    debye = [c for c in nufft_calls if c[2] != f["tile"]]
    # the tiling planned from the pilot is the run's: 17 vectors of every wave-plane sample on each near tile, the
    # corrections at the planned groups' spreads; where not every tile is near, the Debye form's U and U_w on the whole
    # grid first (one tile of n_sensor)
    assert sum(c[1] for c in kirch) == 17 * f["near"]
    assert sorted({c[3] for c in kirch}) == sorted({ps.NUFFT_SPREAD, *f["spreads"].values()})
    assert [(c[1], c[2]) for c in debye] == ([] if size == 5 else [(1, pl.n_sensor)] * 2)
    assert all(c[3] == ps.DEBYE_FAR_SPREAD for c in debye)      # the Debye samples beyond the tiles: the narrower spread
    work = sum(_nufft_work(*c) for c in nufft_calls)
    assert pl.estimate["nufft_flops"] == pytest.approx(work, rel=0.01)
    ex = pl.explain()
    assert "kirchhoff sensor field" in ex and "sensor field form kirchhoff" in ex and "NUFFTs" in ex
    assert ("near the spot, Debye elsewhere" in ex) == (size == 15)
