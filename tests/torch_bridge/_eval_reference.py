"""The evaluation as it was before the batched image loop (torch_bridge/evaluate.py at ca62915, verbatim but for
the names; the ray model's figures, which the change left as they were, from
:func:`torch_bridge.evaluate.ray_figures`): node after node, each crop blurred alone, the noise drawn on the host (a
CUDA image copied down and back), PSNR / SSIM by scikit-image on host copies, one host read per node. The reference the batched evaluation
(:func:`torch_bridge.evaluate.evaluate`) is tested against (test_eval_batched.py) and timed against
(perf/profile_eval.py --reference). Its PSFs come from the same ``_eval_psfs`` (not changed)."""
from __future__ import annotations

import math
import time

import numpy as np
import torch

from torch_bridge.config import _depth_tag, _depth_value
from torch_bridge.evaluate import _eval_psfs, _psf_kernels, ray_figures


def _noise(image, noise: dict, gen):
    """Sensor noise drawn from the CPU generator ``gen`` (reproducible on any device)."""
    from torch_bridge.imaging import sensor_noise
    if image.device.type == "cpu":
        return sensor_noise(image, read_std=noise["read_std"], photons=noise["photons"], generator=gen)
    return sensor_noise(image.cpu(), read_std=noise["read_std"], photons=noise["photons"],
                        generator=gen).to(image.device)


def _blur_patch(images, kernels, boundary):
    """Blur each image (B, C, H, W) with its own kernel (B, C, k, k) (image orientation), FFT."""
    from torch_bridge.imaging import spatially_varying_blur
    out = [spatially_varying_blur(images[b:b + 1], kernels[b][None, None], boundary=boundary)
           for b in range(images.shape[0])]
    return torch.cat(out, 0)



def image_metrics_skimage(out: torch.Tensor, gt: torch.Tensor, lpips=None) -> dict:
    """PSNR (dB), SSIM and 1 - LPIPS of (B, 3, H, W) images in [0, 1], averaged over the batch
    (scikit-image for PSNR and SSIM; ``one_minus_lpips`` is NaN without an :class:`LPIPS`)."""
    from skimage.metrics import peak_signal_noise_ratio, structural_similarity
    a = out.detach().float().clamp(0, 1).cpu().numpy().transpose(0, 2, 3, 1).astype(np.float64)
    b = gt.detach().float().clamp(0, 1).cpu().numpy().transpose(0, 2, 3, 1).astype(np.float64)
    ps, ss = [], []
    for i in range(a.shape[0]):
        ps.append(peak_signal_noise_ratio(b[i], a[i], data_range=1.0))
        ss.append(structural_similarity(b[i], a[i], data_range=1.0, channel_axis=2, gaussian_weights=True,
                                        sigma=1.5, use_sample_covariance=False))
    ps = [p if math.isfinite(p) else 100.0 for p in ps]
    res = {"psnr": float(np.mean(ps)), "ssim": float(np.mean(ss)), "one_minus_lpips": float("nan")}
    if lpips is not None:
        res["one_minus_lpips"] = float(1.0 - lpips(out.detach().float().clamp(0, 1).cpu(), gt.float().cpu()).mean())
    return res


@torch.no_grad()
def evaluate_reference(arm, prov=None, on_progress=None) -> dict:
    """Evaluation of a trained arm with the ray-wave model (see the module docstring): per evaluation
    depth and node (the training nodes, or ``eval.grid``), PSNR (dB) / SSIM / 1-LPIPS of the raw and the
    reconstructed fixed crops; the ray-model RMS spot radius (um); EFL (mm); DOE coefficients (rad); ``timing_s``,
    the wall time (s) of its parts: ``psfs`` (field builds and PSFs), ``images`` (crops through the network,
    metrics), ``rms`` (the ray model). ``on_progress(nodes_done, nodes_total)``: called after each chunk of an
    ``eval.grid``'s PSFs."""
    from torch_bridge.imaging import spatially_varying_blur
    cfg = arm.cfg
    ev = cfg["eval"]
    depths = [_depth_value(d) for d in (ev["depths_mm"] or cfg["optics"]["depths_mm"])]
    # ray-wave PSFs of the designed lens (its refractive part is frozen now: fields may be cached)
    t0 = time.perf_counter()
    psf_by_depth, positions, fields = _eval_psfs(arm, depths, prov, on_progress)
    timing = {"psfs": time.perf_counter() - t0}    # wall s: DOE-plane field builds and PSFs of the nodes
    t0 = time.perf_counter()
    n_nodes = len(positions)
    gt_all = arm.valid_set.fixed_crops(cfg["data"]["eval_images"], seed=ev["seed"]).to(arm.device)
    g = torch.Generator().manual_seed(int(ev["seed"]))
    arm.net.eval()
    rows = []
    psf_store = {}
    for depth in depths:
        psf = psf_by_depth[depth]
        psf_store[str(depth)] = psf.cpu().numpy()
        kern = _psf_kernels(psf.float()).to(arm.device)
        node_rows = []
        if cfg["render"]["mode"] == "patch":
            for n in range(n_nodes):
                raw = _blur_patch(gt_all, kern[[n] * gt_all.shape[0]], cfg["render"]["boundary"])
                raw = _noise(raw, ev["noise"], g)
                rec = torch.cat([arm.net(raw[i:i + ev["batch_size"]]) for i in range(0, raw.shape[0],
                                                                                      ev["batch_size"])])
                m_raw = image_metrics_skimage(raw, gt_all, arm.lpips)
                m_rec = image_metrics_skimage(rec, gt_all, arm.lpips)
                node_rows.append({"node": n, "position_mm": positions[n], "field_deg": fields[n],
                                  "raw": m_raw, "rec": m_rec})
                if n == n_nodes - 1:
                    sample = (gt_all[:2].cpu(), raw[:2].cpu(), rec[:2].cpu())
        else:
            gy, gx = arm.grid
            raw = spatially_varying_blur(gt_all, kern.reshape(gy, gx, 3, arm.size, arm.size),
                                         boundary=cfg["render"]["boundary"])
            raw = _noise(raw, ev["noise"], g)
            rec = torch.cat([arm.net(raw[i:i + ev["batch_size"]]) for i in range(0, raw.shape[0], ev["batch_size"])])
            node_rows.append({"node": "all", "raw": image_metrics_skimage(raw, gt_all, arm.lpips),
                              "rec": image_metrics_skimage(rec, gt_all, arm.lpips)})
            sample = (gt_all[:2].cpu(), raw[:2].cpu(), rec[:2].cpu())

        def avg(part, key, node_rows=node_rows):
            return float(np.mean([r[part][key] for r in node_rows]))
        rows.append({"depth_mm": depth, "nodes": node_rows,
                     "raw": {k: avg("raw", k) for k in ("psnr", "ssim", "one_minus_lpips")},
                     "rec": {k: avg("rec", k) for k in ("psnr", "ssim", "one_minus_lpips")},
                     "psf_energy": psf.sum((-1, -2)).mean().item()})
        np.savez(arm.out / f"eval_sample_{_depth_tag(depth)}.npz", gt=sample[0].numpy(), raw=sample[1].numpy(),
                 rec=sample[2].numpy())
    np.savez(arm.out / "eval_psfs.npz", **psf_store)
    arm.net.train()
    res = {"depths": rows}
    timing["images"] = time.perf_counter() - t0    # blurring, noise, network and metrics of every node's crops
    t0 = time.perf_counter()
    res.update(ray_figures(arm))    # the ray model's figures: unchanged, not what this reference is for
    timing["rms"] = time.perf_counter() - t0
    res["timing_s"] = {k: round(v, 2) for k, v in timing.items()}
    return res
