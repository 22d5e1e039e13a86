"""Image simulation: a point source reproduces its PSF, a flat scene stays flat with its energy,
the blending has no seams, RGB channel mixing, noise statistics, and gradients."""
import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from torch_bridge import imaging


def gauss(k, sigma, dx=0.0, dy=0.0):
    y, x = np.mgrid[:k, :k] - k // 2
    g = np.exp(-((x - dx) ** 2 + (y - dy) ** 2) / (2 * sigma * sigma))
    return g / g.sum()


def varying_map(g=3, k=15):
    """PSFs whose width and centroid change from node to node (normalised to 1)."""
    return torch.tensor(np.array([[gauss(k, 0.8 + 0.4 * (r + c), 0.3 * c - 0.3, 0.2 * r) for c in range(g)]
                                  for r in range(g)]))


def test_blend_weights_are_a_smooth_partition_of_unity():
    w = imaging.blend_weights(4, 100)
    np.testing.assert_allclose(w.sum(0).numpy(), 1.0, atol=1e-15)
    assert torch.all(w >= 0)
    # C1: second differences stay small (no kinks from the windows)
    assert np.abs(np.diff(w.numpy(), 2, axis=1)).max() < 4 * (math.pi / 2 / 25) ** 2


def test_point_source_on_a_node_reproduces_its_psf():
    psfs = varying_map()
    nodes = imaging.node_positions(3, 99)  # 16, 49, 82: integer pixels
    for r, c in [(1, 1), (0, 2), (2, 0)]:
        y, x = int(nodes[r]), int(nodes[c])
        img = torch.zeros(1, 99, 99, dtype=torch.float64)
        img[0, y, x] = 1.0
        out = imaging.spatially_varying_blur(img, psfs)[0]
        k = 15
        patch = out[y - k // 2:y + k // 2 + 1, x - k // 2:x + k // 2 + 1]
        np.testing.assert_allclose(patch.numpy(), psfs[r, c].numpy(), atol=1e-15)
        assert out.sum().item() == pytest.approx(1.0, abs=1e-13)


def test_point_source_between_nodes_keeps_its_energy():
    img = torch.zeros(1, 99, 99, dtype=torch.float64)
    img[0, 30, 61] = 2.5
    out = imaging.spatially_varying_blur(img, varying_map())
    assert out.sum().item() == pytest.approx(2.5, rel=1e-13)
    assert out.min().item() > -1e-15


def test_flat_scene_stays_flat_and_keeps_energy():
    k = 15
    same = torch.tensor(gauss(k, 1.7, 0.4, -0.2))[None, None].expand(4, 3, k, k)
    img = torch.zeros(2, 96, 90, dtype=torch.float64)
    img[:, 12:84, 12:78] = torch.tensor([1.0, 3.0], dtype=torch.float64)[:, None, None]  # dark margin > k / 2
    out = imaging.spatially_varying_blur(img, same)
    np.testing.assert_allclose(out.sum(dim=(1, 2)).numpy(), img.sum(dim=(1, 2)).numpy(), rtol=1e-13)
    inner = out[:, 12 + k:84 - k, 12 + k:78 - k]
    np.testing.assert_allclose(inner[0].numpy(), 1.0, atol=1e-13)
    np.testing.assert_allclose(inner[1].numpy(), 3.0, atol=1e-13)
    # the whole frame, continued beyond its edges
    flat = torch.ones(1, 64, 64, dtype=torch.float64)
    np.testing.assert_allclose(imaging.spatially_varying_blur(flat, same, boundary="reflect").numpy(), 1.0,
                               atol=1e-13)


def test_uniform_scene_with_a_varying_map_has_no_seams():
    out = imaging.spatially_varying_blur(torch.ones(1, 99, 99, dtype=torch.float64), varying_map(),
                                         boundary="replicate")[0].numpy()
    dev = np.abs(out - 1.0).max()
    assert dev < 0.05  # normalised PSFs: only their centroid shifts move light around
    # a seam (a jump between patches) would show as a second difference of the order of the
    # deviation itself; blending leaves a smooth field
    d2 = max(np.abs(np.diff(out, 2, axis=0)).max(), np.abs(np.diff(out, 2, axis=1)).max())
    assert d2 < 0.1 * dev, (d2, dev)


def test_blur_gradcheck():
    torch.manual_seed(0)
    img = torch.rand(2, 12, 14, dtype=torch.float64, requires_grad=True)
    psfs = torch.rand(2, 3, 2, 5, 4, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b: imaging.spatially_varying_blur(a, b, boundary="reflect"),
                                    (img, psfs), fast_mode=True)


def test_rgb_channels_mean_and_random():
    psfs = torch.rand(2, 2, 6, 5, 5, dtype=torch.float64)
    ch = [[0, 1], [2, 3], [4, 5]]
    mean = imaging.channel_psfs(psfs, ch, mode="mean")
    np.testing.assert_allclose(mean[:, :, 1].numpy(), 0.5 * (psfs[:, :, 2] + psfs[:, :, 3]).numpy())
    g = torch.Generator().manual_seed(3)
    picks = set()
    for _ in range(20):
        rnd = imaging.channel_psfs(psfs, ch, mode="random", generator=g)
        k = [j for j in ch[0] if torch.equal(rnd[:, :, 0], psfs[:, :, j])]
        assert len(k) == 1
        picks.add(k[0])
    assert picks == {0, 1}
    img = torch.rand(3, 20, 20, dtype=torch.float64)
    assert imaging.render_rgb(img, psfs, ch).shape == (3, 20, 20)


def test_sensor_noise_statistics_and_gradient():
    g = torch.Generator().manual_seed(0)
    x = torch.full((200_000,), 0.25, dtype=torch.float64, requires_grad=True)
    y = imaging.sensor_noise(x, read_std=0.01, photons=1000.0, generator=g)
    assert y.mean().item() == pytest.approx(0.25, abs=1e-4)
    assert y.var().item() == pytest.approx(0.25 / 1000 + 0.01 ** 2, rel=0.02)
    y.sum().backward()
    assert torch.all(torch.isfinite(x.grad))


def test_psf_grid_of_a_hybrid_lens_feeds_the_blur_with_gradients():
    import torch_bridge as tb
    from rwwarp.lens import Lens, Sensor, Surface
    prof = {"kind": "even_poly", "norm_radius": 0.3, "coefficients": [-2.0, 1.0]}
    surfs = [Surface(type="aperture", semi_diameter=0.3, shape="circle", stop=True, thickness=0.2),
             Surface(type="standard", radius=12.0, material="N-BK7", semi_diameter=1.0, thickness=1.0),
             Surface(type="standard", radius=-40.0, semi_diameter=1.0, thickness=0.5),
             Surface(type="doe", semi_diameter=0.6, shape="square", thickness=17.5, profile=prof)]
    hl = tb.HybridLens(Lens(surfs, Sensor(0.004, (1000, 1000)), wavelengths_um=[0.55]), learn={"doe": "all"})
    grid = imaging.psf_grid(hl, (24, 40), (1, 2), [0.55], 9)
    assert grid.shape == (1, 2, 1, 9, 9)
    # node (0, 1) is right of the axis at mid height: field (+x, 0); rows flipped to image order
    x_mm = (imaging.node_positions(2, 40)[1] + 0.5 - 20) * 0.004
    ref = hl.psf((math.degrees(math.atan(x_mm / hl.to_lens().efl(0.55))), 0.0), 0.55, 9)
    np.testing.assert_allclose(grid[0, 1, 0].detach().numpy(), ref.detach().numpy()[::-1], atol=1e-14)
    img = torch.rand(1, 24, 40, dtype=torch.float64)
    imaging.spatially_varying_blur(img, grid[:, :, 0]).sum().backward()
    assert torch.any(hl.doe.grad != 0)
