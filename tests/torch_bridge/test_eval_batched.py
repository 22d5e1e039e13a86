"""The batched evaluation image loop (torch_bridge.evaluate._patch_nodes): every crop of a node blurred in one FFT
convolution, the noise's draws uploaded instead of the image going down and back (CUDA), PSNR / SSIM per crop in
torch on the device with one host read for the grid. Checked against independent references: the metrics against
scikit-image's own functions, the noise against torch_bridge.imaging.sensor_noise with the same generator, and the
whole evaluation against the node-by-node loop it replaced (kept verbatim in _eval_reference.py), node by node."""
import math
import sys
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from test_train import tiny  # noqa: E402  (the tiny design of test_train.py)

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _eval_reference import evaluate_reference  # noqa: E402


def _pair(shape, seed):
    """A smooth image in [0, 1] and a noisy, partly clipped copy (values past [0, 1] exercise the clipping)."""
    g = torch.Generator().manual_seed(seed)
    gt = torch.nn.functional.avg_pool2d(torch.rand(shape, generator=g), 5, 1, 2)
    out = gt + 0.05 * torch.randn(shape, generator=g) + 0.02
    return out.clamp(-0.1, 1.1), gt


def test_metrics_per_image_equal_scikit_image():
    """Torch PSNR / SSIM per image (the method a GPU runs) against scikit-image's functions called here, on
    non-square crops, one pair equal (PSNR infinite -> 100 dB, as image_metrics reports it) and a float64 input.
    Measured on this machine: |dSSIM| <= 7.8e-16, |dPSNR| = 0 here and <= 3.6e-15 dB on 16 crops of 256 x 256 px
    (the sums' order: banded matrix products against scipy's correlate1d); tolerances 4x that, 3e-15 and 1.5e-14 dB."""
    from skimage.metrics import peak_signal_noise_ratio, structural_similarity

    from torch_bridge.losses import image_metrics, image_metrics_per_image
    out, gt = _pair((6, 3, 40, 52), 0)
    out[2] = gt[2]
    for o, t in ((out, gt), (out.double(), gt)):
        p, s = image_metrics_per_image(o, t, method="torch")
        assert p.dtype == s.dtype == torch.float64 and p.shape == s.shape == (6,)
        a = o.float().clamp(0, 1).numpy().transpose(0, 2, 3, 1).astype(np.float64)
        b = t.float().clamp(0, 1).numpy().transpose(0, 2, 3, 1).astype(np.float64)
        with np.errstate(divide="ignore"):
            pr = [peak_signal_noise_ratio(b[i], a[i], data_range=1.0) for i in range(6)]
        pr = [x if math.isfinite(x) else 100.0 for x in pr]
        sr = [structural_similarity(b[i], a[i], data_range=1.0, channel_axis=2, gaussian_weights=True, sigma=1.5,
                                    use_sample_covariance=False) for i in range(6)]
        assert p[2] == 100.0 and s[2] == pytest.approx(1.0, abs=1e-15)
        assert np.max(np.abs(p.numpy() - pr)) <= 1.5e-14, np.abs(p.numpy() - pr)
        assert np.max(np.abs(s.numpy() - sr)) <= 3e-15, np.abs(s.numpy() - sr)
        # the host path ("auto" on the CPU) is scikit-image's: the same figures
        with np.errstate(divide="ignore"):
            p2, s2 = image_metrics_per_image(o, t)
            m = image_metrics(o, t)
        assert np.max(np.abs(p2.numpy() - pr)) == 0.0 and np.max(np.abs(s2.numpy() - sr)) == 0.0
        assert m["psnr"] == pytest.approx(np.mean(pr), abs=1e-14) and m["ssim"] == pytest.approx(np.mean(sr), abs=3e-15)
        assert math.isnan(m["one_minus_lpips"])
    with pytest.raises(ValueError, match="same shape|one shape"):
        image_metrics_per_image(out, gt[:2])
    with pytest.raises(ValueError, match="SSIM window"):
        image_metrics_per_image(out[..., :8, :8], gt[..., :8, :8])
    with pytest.raises(ValueError, match="method"):
        image_metrics_per_image(out, gt, method="numpy")


@pytest.mark.parametrize("noise", [{"read_std": 0.01, "photons": None}, {"read_std": 0.02, "photons": 800.0},
                                   {"read_std": 0.0, "photons": 500.0}, {"read_std": 0.0, "photons": None}])
def test_noise_from_uploaded_draws_equals_sensor_noise(noise):
    """The CUDA evaluation's noise (the draws made on the host, the formula applied where the image is) equals
    sensor_noise with the same generator bit for bit (same values, same operations; run here on the CPU), and leaves
    the generator where sensor_noise leaves it (the next node's noise is unchanged)."""
    from torch_bridge.evaluate import _noise_draws, _noise_from_draws
    from torch_bridge.imaging import sensor_noise
    img = _pair((3, 3, 17, 23), 1)[0]
    g1, g2 = torch.Generator().manual_seed(7), torch.Generator().manual_seed(7)
    want = sensor_noise(img, read_std=noise["read_std"], photons=noise["photons"], generator=g1)
    got = _noise_from_draws(img, _noise_draws(img.shape, img.dtype, noise, g2), noise)
    assert torch.equal(got, want)
    assert torch.equal(torch.randn(5, generator=g1), torch.randn(5, generator=g2))


def test_blur_one_equals_blur_patch():
    """FFT convolutions of several crops with one kernel (all of them, or chunks of 3) equal the crop-by-crop blur
    with that kernel repeated.
    Measured: equal bit for bit on this CPU (torch's CPU FFT transforms each image alike in a batch); the tolerance
    is float32 rounding (1e-6 of the image's scale) for FFT libraries that round batches differently."""
    from torch_bridge.evaluate import _blur_one, _blur_patch
    imgs = _pair((4, 3, 33, 29), 2)[1]
    g = torch.Generator().manual_seed(3)
    k = torch.rand(3, 9, 9, generator=g)
    k = k / k.sum((-1, -2), keepdim=True)
    for boundary, chunk in (("reflect", 8), ("zero", 8), ("reflect", 3)):
        a = _blur_one(imgs, k, boundary, chunk=chunk)
        b = _blur_patch(imgs, k[None].expand(4, -1, -1, -1), boundary)
        assert a.shape == imgs.shape
        assert float((a - b).abs().max()) <= 1e-6, float((a - b).abs().max())


def test_batched_patch_blur_equals_direct_convolution_per_image():
    """The training's and evaluation's patch blur (each crop with its own kernel; on a GPU one batched FFT
    convolution, ``spatially_varying_blur(per_image=True)``) against a direct 'same' convolution written here (numpy, float64,
    the scene extended as each boundary says), with a different kernel for each crop and a (3, k, k) kernel shared
    by the channels too; and against the crop-by-crop calls it replaced.
    Measured on this CPU: 1.5-1.6e-7 of the image's scale against the direct sum (float32 FFT rounding; tolerance
    1e-6), 0 / 0 / 3e-8 against the crop-by-crop calls (zero / reflect / replicate; the same tolerance, for FFT
    libraries that round the images of a batch differently)."""
    from torch_bridge.evaluate import _blur_patch
    from torch_bridge.imaging import spatially_varying_blur
    imgs = _pair((3, 3, 21, 26), 5)[1]
    g = torch.Generator().manual_seed(8)
    k = torch.rand(3, 3, 7, 5, generator=g)
    k = k / k.sum((-1, -2), keepdim=True)
    modes = {"zero": "constant", "reflect": "reflect", "replicate": "edge"}
    for boundary, np_mode in modes.items():
        batched = spatially_varying_blur(imgs, k, boundary=boundary, per_image=True)   # the GPU's form
        loop = torch.cat([spatially_varying_blur(imgs[b:b + 1], k[b][None, None], boundary=boundary)
                          for b in range(3)])
        assert float((batched - loop).abs().max()) <= 1e-6
        assert torch.equal(_blur_patch(imgs, k, boundary), loop)          # the CPU's form: those very calls
        x, kk = imgs.double().numpy(), k.double().numpy()
        kh, kw = kk.shape[-2:]
        # 'same' convolution: output (y, x) = sum_ij K[i, j] I[y + kh//2 - i, x + kw//2 - j]
        ext = np.pad(x, ((0, 0), (0, 0), (kh // 2, kh - 1 - kh // 2), (kw // 2, kw - 1 - kw // 2)), mode=np_mode)
        want = np.zeros_like(x)
        H, W = x.shape[-2:]
        for i in range(kh):
            for j in range(kw):
                want += kk[:, :, i, j][..., None, None] * ext[:, :, kh - 1 - i:kh - 1 - i + H, kw - 1 - j:kw - 1 - j + W]
        err = np.abs(batched.double().numpy() - want).max()
        assert err <= 1e-6, (boundary, err)
    with pytest.raises(ValueError, match="per_image"):
        spatially_varying_blur(imgs, k[:2], per_image=True)


def _arm(tmp_path):
    """The tiny design's fixed arm with a 2 x 3 evaluation grid, 3 crops, its network's weights perturbed (the
    untrained network starts as the identity: the reconstructed crops would equal the raw ones)."""
    from torch_bridge.train import Arm, _seed_all, load_config
    cfg = tiny(**{"arms": [{"name": "fixed", "design": {"method": "fixed"}}], "data.eval_images": 3,
                  "optics.nodes": {"layout": "grid", "grid": [2, 2], "region": "quadrant", "half_size_mm": 1.5},
                  "eval.grid": [2, 3], "eval.node_chunk": 4, "eval.noise": {"read_std": 0.01, "photons": 2000.0}})
    exp = load_config(cfg)
    a = exp["arms"][0]
    _seed_all(0)
    arm = Arm(a["name"], a["config"], exp["source"], tmp_path, progress=False)
    g = torch.Generator().manual_seed(5)
    with torch.no_grad():
        for p in arm.net.parameters():
            p.add_(0.05 * torch.randn(p.shape, generator=g, dtype=p.dtype))
    return arm


def test_batched_evaluation_equals_the_node_by_node_reference(tmp_path, monkeypatch):
    """The evaluation (batched image loop) against the loop it replaced, on the same arm and PSFs: per node the
    raw and reconstructed PSNR / SSIM, the averages, the saved sample crops. On the CPU the metrics are scikit-image's
    in both, so they agree bit for bit (measured: 0); then again with the torch metrics a GPU runs (forced here):
    measured |dPSNR| <= 3.6e-15 dB, |dSSIM| <= 1.3e-15 (22 x 22 px SSIM maps: fewer terms average the rounding
    less than in the metric test); tolerances 4x that, 1.5e-14 dB and 5e-15."""
    import torch_bridge.losses as L
    arm = _arm(tmp_path)
    ref = evaluate_reference(arm)["depths"][0]
    sample_ref = dict(np.load(next(tmp_path.glob("eval_sample_*.npz"))))
    assert len(ref["nodes"]) == 6
    for method, tol_db, tol_ssim in (("auto", 0.0, 0.0), ("torch", 1.5e-14, 5e-15)):
        if method == "torch":
            real = L.image_metrics_per_image
            monkeypatch.setattr(L, "image_metrics_per_image", lambda o, t, method="torch", chunk=16: real(o, t, "torch"))
        from torch_bridge.evaluate import evaluate
        res = evaluate(arm)
        arm_eval = res["depths"][0]
        assert set(res["timing_s"]) == {"psfs", "images", "rms"}
        assert len(arm_eval["nodes"]) == 6
        worst = {"psnr": 0.0, "ssim": 0.0}
        for a, b in zip(arm_eval["nodes"], ref["nodes"]):
            assert a["node"] == b["node"] and a["position_mm"] == b["position_mm"] and a["field_deg"] == b["field_deg"]
            for part in ("raw", "rec"):
                assert list(a[part]) == ["psnr", "ssim", "one_minus_lpips"]
                assert math.isnan(a[part]["one_minus_lpips"]) and math.isnan(b[part]["one_minus_lpips"])
                for m in ("psnr", "ssim"):
                    worst[m] = max(worst[m], abs(a[part][m] - b[part][m]))
        assert worst["psnr"] <= tol_db and worst["ssim"] <= tol_ssim, (method, worst)
        # the network changed the crops (the comparison covers the reconstructed pass, not a copy of the raw one)
        assert any(abs(n["raw"]["psnr"] - n["rec"]["psnr"]) > 0.01 for n in arm_eval["nodes"])
        for part in ("raw", "rec"):
            for m in ("psnr", "ssim"):
                assert abs(arm_eval[part][m] - ref[part][m]) <= max(tol_db, tol_ssim) + 1e-15
        sample = dict(np.load(next(tmp_path.glob("eval_sample_*.npz"))))
        for k in ("gt", "raw", "rec"):
            assert np.array_equal(sample[k], sample_ref[k]), k


CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


@pytest.mark.gpu
@CUDA
def test_cuda_noise_and_metrics_equal_the_host_ones():
    """On a CUDA device: the evaluation's noise (draws uploaded from page-locked memory, the formula on the device)
    equals the host round trip it replaced (_noise: the image down, sensor_noise, back up) to float32 rounding
    (IEEE add / multiply / divide / sqrt are correctly rounded on both: expected equal; 2 ulp of values <= 1.2 allowed),
    and the device's PSNR / SSIM equal scikit-image's to the CPU test's tolerances (cuBLAS sums in another order)."""
    from skimage.metrics import structural_similarity

    from torch_bridge.evaluate import _device_noise, _noise
    from torch_bridge.losses import image_metrics_per_image
    img = _pair((4, 3, 48, 40), 4)[0].cuda()
    for noise in ({"read_std": 0.01, "photons": None}, {"read_std": 0.02, "photons": 800.0}):
        g1, g2 = torch.Generator().manual_seed(9), torch.Generator().manual_seed(9)
        a = _device_noise(img, noise, g1)
        b = _noise(img, noise, g2)
        assert a.device == img.device and b.device == img.device
        assert float((a - b).abs().max()) <= 2.5e-7
    out, gt = _pair((5, 3, 40, 52), 6)
    p, s = image_metrics_per_image(out.cuda(), gt.cuda())
    assert p.device.type == "cuda"
    a = out.float().clamp(0, 1).numpy().transpose(0, 2, 3, 1).astype(np.float64)
    b = gt.float().clamp(0, 1).numpy().transpose(0, 2, 3, 1).astype(np.float64)
    sr = [structural_similarity(b[i], a[i], data_range=1.0, channel_axis=2, gaussian_weights=True, sigma=1.5,
                                use_sample_covariance=False) for i in range(5)]
    pr = [10 * np.log10(1.0 / np.mean((b[i] - a[i]) ** 2)) for i in range(5)]
    assert np.max(np.abs(s.cpu().numpy() - sr)) <= 3e-15
    assert np.max(np.abs(p.cpu().numpy() - pr)) <= 1.5e-14
