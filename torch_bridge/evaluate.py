"""Evaluation of a trained arm (:func:`evaluate`: ray-wave PSFs, PSNR / SSIM / 1-LPIPS per depth and
node, RMS spot radius; :func:`objective`: the training objective on the fixed evaluation crops) and
the rendering helpers the training loop shares with it (sensor noise, per-patch blur, kernels).

``arm`` arguments are :class:`torch_bridge.train.Arm` objects (not imported here: train imports this module)."""
from __future__ import annotations

import json
import time

import numpy as np
import torch

from torch_bridge.config import _budget_bytes, _depth_tag, _depth_value, _feature_mm

__all__ = ["eval_nodes", "evaluate", "objective"]


def _noise(image, noise: dict, gen):
    """Sensor noise drawn from the CPU generator ``gen`` (reproducible on any device)."""
    from torch_bridge.imaging import sensor_noise
    if image.device.type == "cpu":
        return sensor_noise(image, read_std=noise["read_std"], photons=noise["photons"], generator=gen)
    return sensor_noise(image.cpu(), read_std=noise["read_std"], photons=noise["photons"],
                        generator=gen).to(image.device)


def _noise_draws(shape, dtype, noise: dict, gen, pin: bool = False) -> list:
    """The standard normal draws :func:`~torch_bridge.imaging.sensor_noise` makes for an image of ``shape`` and
    ``dtype`` with ``noise``, in its order (shot noise, then read noise), from the CPU generator ``gen``: the same
    values. ``pin``: into page-locked host memory (an asynchronous upload that does not wait for the device)."""
    out = []
    for on in (noise["photons"] is not None, bool(noise["read_std"])):
        if on:
            t = torch.empty(shape, dtype=dtype, pin_memory=pin)
            out.append(t.normal_(generator=gen))
    return out


def _noise_from_draws(image, draws: list, noise: dict):
    """:func:`~torch_bridge.imaging.sensor_noise`'s formula with its draws given (:func:`_noise_draws`, on the
    image's device): ``image + sqrt(max(image, 0) / photons + 1e-2 / photons^2) n1 + read_std n2``."""
    out, k = image, 0
    if noise["photons"] is not None:
        photons = float(noise["photons"])
        var = torch.clamp(image, min=0.0) / photons
        out = out + torch.sqrt(var + 1e-2 / photons ** 2) * draws[k]
        k += 1
    if noise["read_std"]:
        out = out + float(noise["read_std"]) * draws[k]
    return out


def _device_noise(image, noise: dict, gen, batch: int | None = None, rows: slice | None = None):
    """Sensor noise: :func:`_noise`'s values (the CPU generator ``gen``'s draws), but on a CUDA device only the
    draws go up (from page-locked memory, asynchronously) and the image stays there: no copy of the image to the
    host and back, no wait for the device.

    ``batch``, ``rows``: ``image`` is the rows ``rows`` of a batch of ``batch`` images (a rank's share of a
    distributed step): the draws are made for the whole batch (the generator moves as there) and the rows' are
    used, so the share gets the values the whole batch's noise has there."""
    if batch is None:
        if image.device.type != "cuda":
            return _noise(image, noise, gen)
        batch, rows = image.shape[0], slice(None)
    pin = image.device.type == "cuda"
    draws = [d[rows].to(image.device, non_blocking=True)
             for d in _noise_draws((batch,) + tuple(image.shape[1:]), image.dtype, noise, gen, pin=pin)]
    return _noise_from_draws(image, draws, noise)


def _blur_one(images, kernel, boundary, chunk: int = 8):
    """Blur every image (B, C, H, W) with the one kernel (C, k, k) (image orientation): :func:`_blur_patch` with
    that kernel for every image, in FFT convolutions of ``chunk`` images each instead of one an image (on a GPU the
    per-image calls were bound by their launches; on the CPU larger batches were slower: 64 crops of 256^2 px in
    one call took 2-5x the time of 8 calls of 8, their work arrays out of cache, perf/profile_eval.py --parts)."""
    from torch_bridge.imaging import spatially_varying_blur
    return torch.cat([spatially_varying_blur(images[i:i + chunk], kernel[None, None], boundary=boundary)
                      for i in range(0, images.shape[0], int(chunk))])


def _blur_patch(images, kernels, boundary):
    """Blur each image (B, C, H, W) with its own kernel (B, C, k, k) (image orientation, pixels): on a GPU in one
    batched FFT convolution (:func:`~torch_bridge.imaging.spatially_varying_blur` with ``per_image``: one set of
    launches, not one an image), on the CPU one image a call (8 crops of 256^2 px with 63 px kernels: 0.17-0.31 s
    one a call, 0.38-0.44 s batched on one core, the batch's work arrays out of cache). The same values either way."""
    from torch_bridge.imaging import spatially_varying_blur
    step = images.shape[0] if images.device.type == "cuda" else 1
    return torch.cat([spatially_varying_blur(images[b:b + step], kernels[b:b + step], boundary=boundary, per_image=True)
                      for b in range(0, images.shape[0], step)])


def _psf_kernels(psfs):
    """Sensor-orientation PSFs (..., k, k) -> image-orientation convolution kernels (row 0 at +y)."""
    return psfs.flip(-2)


def _eval_provider(arm):
    """A ray-wave provider for the current lens: the training one when it caches ray-wave fields of
    this lens (checked for sampling and centring first), else a new one, built after the training
    provider's caches are released (the two sets of fields are never held at once; the training one
    rebuilds its entries on their recorded plans when it needs them again)."""
    from torch_bridge import design as dz
    p = arm.provider
    if isinstance(p, dz.CachedProvider) and p.model == "ray-wave":
        p.check_sampling()
        return p
    if hasattr(p, "release"):
        p.release()
    prov = dz.CachedProvider(arm.module, arm.fields, arm.size, arm.pixel_mm, model="ray-wave",
                             wavelength_ref_um=arm.wl_ref, memory_budget_bytes=_budget_bytes(arm.cfg["optics"]),
                             min_feature_mm=_feature_mm(arm.cfg["optics"]),
                             cache_precision=arm.cfg["optics"]["cache_precision"],
                             cache_device=arm.cfg["optics"]["cache_device"])
    prov.prepare(sorted({w for c in arm.wls for w in c}), eval_depths(arm.cfg), progress=False)
    return prov


@torch.no_grad()
def objective(arm, prov=None) -> dict:
    """The training objective (``MSE + alpha * perceptual``) on the fixed evaluation crops: ray-wave PSFs
    of the current lens (the wavelengths of each channel averaged) at the first evaluation depth, every
    node, seeded noise, the current network. Used to compare a design with its own starting point."""
    from torch_bridge.imaging import spatially_varying_blur
    cfg = arm.cfg
    ev = cfg["eval"]
    depth = eval_depths(cfg)[0]
    prov = prov or _eval_provider(arm)
    psf = torch.stack([prov.psfs([c[j] for c in arm.wls], depth) for j in range(len(arm.wls[0]))], 0).mean(0)
    kern = _psf_kernels(psf.float()).to(arm.device)
    gt = arm.valid_set.fixed_crops(cfg["data"]["eval_images"], seed=ev["seed"]).to(arm.device)
    g = torch.Generator().manual_seed(int(ev["seed"]) + 1)
    arm.net.eval()
    tot, mse, n = 0.0, 0.0, 0
    views = range(len(arm.fields)) if cfg["render"]["mode"] == "patch" else [None]
    for v in views:
        if v is None:
            gy, gx = arm.grid
            raw = spatially_varying_blur(gt, kern.reshape(gy, gx, 3, arm.size, arm.size),
                                         boundary=cfg["render"]["boundary"])
        else:
            raw = _blur_one(gt, kern[v], cfg["render"]["boundary"])
        raw = _device_noise(raw, ev["noise"], g)
        rec = arm.net(raw)
        loss, parts = arm.criterion(rec, gt)
        tot += float(loss)
        mse += parts["mse"]
        n += 1
    arm.net.train()
    return {"loss": tot / n, "mse": mse / n}


def eval_nodes(arm):
    """The evaluation nodes of ``arm``: ``(positions_mm, fields)`` of ``eval.grid`` (``gy x gx`` cell
    centres over the training nodes' region and half size, row-major from the top row), or None when
    ``eval.grid`` is not set (the training nodes are evaluated)."""
    from torch_bridge import design as dz
    cfg = arm.cfg
    grid = cfg["eval"]["grid"]
    if grid is None:
        return None
    nd = cfg["optics"]["nodes"]
    lens = arm.module.to_lens()
    half = nd["half_size_mm"] or [0.5 * lens.sensor.resolution[0] * lens.sensor.pixel_pitch,
                                  0.5 * lens.sensor.resolution[1] * lens.sensor.pixel_pitch]
    pos = dz.node_positions_mm("grid", half, grid, nd["fractions"], nd["region"])
    return pos, dz.field_angles(lens, pos, arm.wl_ref)


def _eval_psfs(arm, depths, prov=None, on_progress=None, group=None) -> tuple:
    """Per evaluation depth the (nodes, 3, k, k) ray-wave PSFs with the wavelengths of each channel
    averaged, the node positions (mm) and field angles (deg). On the training nodes (``prov`` or :func:`_eval_provider`), or,
    with ``eval.grid``, on that grid in chunks of ``eval.node_chunk`` nodes, each chunk's DOE-plane
    fields cached only while its PSFs are made (memory follows the chunk, not the grid). ``on_progress``:
    called as ``on_progress(nodes_done, nodes_total)`` after each chunk of the grid (the run's progress file).

    ``group`` (:class:`torch_bridge.distributed.Group`, an ``eval.grid`` only): every rank calls this; the grid's
    chunks are dealt out round robin (chunk ``j`` on rank ``j mod ranks``), each rank computes its own, and the
    PSFs are all-gathered: every rank returns the whole grid's. The chunks are the single process's, so the PSFs are
    too (a chunk's plan is shared by its nodes: the chunking, not the rank, decides it)."""
    from torch_bridge import design as dz
    dense = eval_nodes(arm)

    def mean_psf(p, depth):
        per_wl = [p.psfs([c[j] for c in arm.wls], depth) for j in range(len(arm.wls[0]))]
        return torch.stack(per_wl, 0).mean(0)                              # (nodes, 3, k, k): mean per channel

    if dense is None:
        prov = prov or _eval_provider(arm)
        return {d: mean_psf(prov, d) for d in depths}, list(arm.positions), list(arm.fields)
    pos, fields = dense
    k = int(arm.cfg["eval"]["node_chunk"])
    out = {d: [] for d in depths}
    allw = sorted({w for c in arm.wls for w in c})
    starts = list(range(0, len(fields), k))
    ranks, rank = (1, 0) if group is None else (group.size, group.rank)
    chunks = starts[rank::ranks]
    if arm.progress:
        from tqdm.auto import tqdm
        chunks = tqdm(chunks, desc=f"{arm.name}: eval grid {arm.cfg['eval']['grid']}", unit="chunk", leave=False)
    for j, i in enumerate(chunks):
        p = dz.CachedProvider(arm.module, fields[i:i + k], arm.size, arm.pixel_mm, model="ray-wave",
                              wavelength_ref_um=arm.wl_ref, doe_budget_cpmm=arm.cfg["optics"]["doe_budget_cpmm"],
                              memory_budget_bytes=_budget_bytes(arm.cfg["optics"]),
                              min_feature_mm=_feature_mm(arm.cfg["optics"]),
                              cache_precision=arm.cfg["optics"]["cache_precision"],
                              cache_device=arm.cfg["optics"]["cache_device"])
        p.prepare(allw, depths, progress=False)
        with torch.no_grad():
            for d in depths:
                out[d].append(mean_psf(p, d))
        del p
        if on_progress is not None:   # this rank's chunks, the others' taken to keep pace
            on_progress(min((j + 1) * k * ranks, len(fields)), len(fields))
    if group is not None:
        empty = torch.zeros((0, len(arm.wls), arm.size, arm.size), dtype=torch.float64, device=arm.device)
        return ({d: _gather_chunks(group, v or [empty], starts, len(fields), k) for d, v in out.items()},
                list(pos), list(fields))
    return {d: torch.cat(v, 0) for d, v in out.items()}, list(pos), list(fields)


def _gather_chunks(group, mine: list, starts: list, n_nodes: int, k: int):
    """The grid's (n_nodes, ...) PSFs from every rank's chunks (``mine``: this rank's tensors in order, at least one,
    possibly with no nodes; chunk ``j`` of ``starts`` was computed by rank ``j mod ranks``): each rank's chunks
    padded to ``ceil(chunks / ranks) k`` nodes for one all-gather (NCCL needs equal shapes), then put back in grid
    order."""
    per = -(-len(starts) // group.size) * k
    parts = group.gather_psfs(torch.cat(mine, 0), per * group.size, per)
    parts = parts.reshape(group.size, per, *parts.shape[1:])
    out = []
    for j, i in enumerate(starts):
        r, q = j % group.size, j // group.size
        out.append(parts[r, q * k:q * k + min(k, n_nodes - i)])
    return torch.cat(out, 0)


def _patch_nodes(arm, kern, gt_all, gen, positions, fields) -> tuple:
    """The evaluation rows of patch rendering at one depth: for each node ``n`` (in order), the fixed crops
    ``gt_all`` (B, 3, H, W) blurred by the node's kernel ``kern[n]`` (:func:`_blur_one`: 8 crops an FFT convolution), seeded
    noise (``gen``, drawn node after node as before), the network in ``eval.batch_size`` batches, PSNR / SSIM per
    crop on the device (:func:`~torch_bridge.losses.image_metrics_per_image`; 1 - LPIPS on the host when the arm
    has an LPIPS). The per-crop figures stay on the device until every node is done: one host read for the grid,
    not one (or more) a node. Returns ``(node_rows, sample)``: rows as :func:`image_metrics` averages them (mean
    over the crops), and the last node's first two crops (gt, raw, rec) on the host."""
    from torch_bridge.losses import image_metrics_per_image
    cfg = arm.cfg
    ev = cfg["eval"]
    bs = ev["batch_size"]
    per, lp = [], []
    sample = None
    for n in range(kern.shape[0]):
        raw = _blur_one(gt_all, kern[n], cfg["render"]["boundary"])
        raw = _device_noise(raw, ev["noise"], gen)
        rec = torch.cat([arm.net(raw[i:i + bs]) for i in range(0, raw.shape[0], bs)])
        per.append(torch.stack([*image_metrics_per_image(raw, gt_all), *image_metrics_per_image(rec, gt_all)]))
        if arm.lpips is not None:
            lp.append([float(1.0 - arm.lpips(x.detach().float().clamp(0, 1).cpu(), gt_all.float().cpu()).mean())
                       for x in (raw, rec)])
        if n == kern.shape[0] - 1:
            sample = (gt_all[:2].cpu(), raw[:2].cpu(), rec[:2].cpu())
    vals = torch.stack(per).cpu().numpy()               # (nodes, 4 [psnr raw, ssim raw, psnr rec, ssim rec], B)
    rows = []
    for n in range(kern.shape[0]):
        m = {part: {"psnr": float(np.mean(vals[n, 2 * j])), "ssim": float(np.mean(vals[n, 2 * j + 1])),
                    "one_minus_lpips": lp[n][j] if lp else float("nan")} for j, part in enumerate(("raw", "rec"))}
        rows.append({"node": n, "position_mm": positions[n], "field_deg": fields[n], **m})
    return rows, sample


@torch.no_grad()
def evaluate(arm, prov=None, on_progress=None, group=None) -> dict:
    """Evaluation of a trained arm with the ray-wave model (see the module docstring): per evaluation
    depth and node (the training nodes, or ``eval.grid``), PSNR (dB) / SSIM / 1-LPIPS of the raw and the
    reconstructed fixed crops; the ray-model RMS spot radius (um); EFL (mm); DOE coefficients (rad); ``timing_s``,
    the wall time (s) of its parts: ``psfs`` (field builds and PSFs), ``images`` (crops through the network,
    metrics), ``rms`` (the ray model). ``on_progress(nodes_done, nodes_total)``: called after each chunk of an
    ``eval.grid``'s PSFs. ``group`` (a distributed run's, on its lead rank; the other ranks call
    :func:`eval_share`): the grid's PSFs are computed by every rank (:func:`_eval_psfs`), the rest by this one."""
    from torch_bridge.imaging import spatially_varying_blur
    from torch_bridge.losses import image_metrics
    cfg = arm.cfg
    ev = cfg["eval"]
    depths = eval_depths(cfg)
    # ray-wave PSFs of the designed lens (its refractive part is frozen now: fields may be cached)
    t0 = time.perf_counter()
    psf_by_depth, positions, fields = _eval_psfs(arm, depths, prov, on_progress,
                                                 group if eval_nodes(arm) is not None else None)
    timing = {"psfs": time.perf_counter() - t0}    # wall s: DOE-plane field builds and PSFs of the nodes
    t0 = time.perf_counter()
    gt_all = arm.valid_set.fixed_crops(cfg["data"]["eval_images"], seed=ev["seed"]).to(arm.device)
    g = torch.Generator().manual_seed(int(ev["seed"]))
    arm.net.eval()
    rows = []
    psf_store = {}
    for depth in depths:
        psf = psf_by_depth[depth]
        psf_store[str(depth)] = psf.cpu().numpy()
        kern = _psf_kernels(psf.float()).to(arm.device)
        if cfg["render"]["mode"] == "patch":
            node_rows, sample = _patch_nodes(arm, kern, gt_all, g, positions, fields)
        else:
            gy, gx = arm.grid
            raw = spatially_varying_blur(gt_all, kern.reshape(gy, gx, 3, arm.size, arm.size),
                                         boundary=cfg["render"]["boundary"])
            raw = _noise(raw, ev["noise"], g)
            rec = torch.cat([arm.net(raw[i:i + ev["batch_size"]]) for i in range(0, raw.shape[0], ev["batch_size"])])
            node_rows = [{"node": "all", "raw": image_metrics(raw, gt_all, arm.lpips),
                          "rec": image_metrics(rec, gt_all, arm.lpips)}]
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
    res.update(ray_figures(arm))
    timing["rms"] = time.perf_counter() - t0
    res["timing_s"] = {k: round(v, 2) for k, v in timing.items()}
    return res


def ray_figures(arm) -> dict:
    """The designed lens's ray-model figures of an evaluation: ``rms_um``, the RMS spot radius (um) at
    ``eval.rms_fractions`` of the nodes' half size on the diagonal (on axis, outermost, average; for an even or
    general polynomial DOE only; a vignetted field gives ``{"error": ...}``), ``efl_mm`` (mm, at the reference
    wavelength), ``doe_coefficients`` (rad) and ``sensor_distance_mm`` (mm, the last gap)."""
    from torch_bridge import design as dz
    cfg = arm.cfg
    ev = cfg["eval"]
    res = {}
    # ray-model RMS spot radius (um): on axis, outermost, average over the diagonal fractions
    lens = arm.module.to_lens()
    kind = lens.surfaces[lens.doe_index].profile.get("kind")
    if kind in ("even_poly", "poly"):
        nd = cfg["optics"]["nodes"]
        half = nd["half_size_mm"] or [0.5 * lens.sensor.resolution[0] * lens.sensor.pixel_pitch,
                                      0.5 * lens.sensor.resolution[1] * lens.sensor.pixel_pitch]
        hx, hy = (half, half) if np.ndim(half) == 0 else half
        fr = ev["rms_fractions"]
        pos = [(f * hx, f * hy) for f in fr]
        fl = dz.field_angles(lens, pos, arm.wl_ref)
        wls = cfg["design"]["rms"]["wavelengths_um"] or [c[len(c) // 2] for c in arm.wls]
        try:
            with torch.enable_grad():
                r = dz.RaySpot(arm.module, fl, wls, grid=ev["rms_grid"]).rms().detach().cpu().numpy() * 1e3
            res["rms_um"] = {"fractions": list(fr), "per_field": r.tolist(), "on_axis": float(r[0]),
                             "off_axis": float(r[-1]), "avg": float(np.mean(r))}
        except Exception as e:  # noqa: BLE001 - a vignetted field must not lose the evaluation
            res["rms_um"] = {"error": str(e)}
    res["efl_mm"] = float(lens.efl(arm.wl_ref))
    res["doe_coefficients"] = arm.module.value("doe").detach().cpu().tolist()
    res["sensor_distance_mm"] = float(lens.surfaces[-1].thickness)
    return res


def eval_depths(cfg) -> list:
    """The object distances (mm; None: at infinity) an arm is evaluated at: ``eval.depths_mm``, else the training's
    ``optics.depths_mm``."""
    return [_depth_value(d) for d in (cfg["eval"]["depths_mm"] or cfg["optics"]["depths_mm"])]


@torch.no_grad()
def eval_share(arm, group) -> None:
    """A distributed run's rank other than the lead at the end of a finished arm: its share of the ``eval.grid``'s
    PSFs (:func:`_eval_psfs`), gathered by the lead's :func:`evaluate`; nothing without an ``eval.grid`` (the lead
    evaluates the training nodes alone). The training provider's fields are let go first, as on the lead."""
    if eval_nodes(arm) is None:
        return
    if hasattr(arm.provider, "release"):
        arm.provider.release()
    _eval_psfs(arm, eval_depths(arm.cfg), group=group)


def evaluate_arm(arm, result: dict, out, report, default=None, group=None) -> dict:
    """The end of a finished arm: its lens (``lens.json``) and network (``network.pt``) saved in ``out``, the final
    objective on the training nodes (:func:`objective`, beside ``arm.objective_initial``), :func:`evaluate` (on the
    training nodes or the ``eval.grid``: the training nodes' fields are let go first, so the grid's chunks build
    theirs under the memory budget alone), the run's times, and ``result.json`` written atomically (``default``:
    the JSON encoder's fallback). ``report(state, phase, **kw)`` writes the run's progress file; the grid's chunks
    report their progress and ETA through it. ``group``: a distributed run's, on its lead rank (the grid's PSFs are
    shared out: the other ranks call :func:`eval_share`). Updates and returns ``result``."""
    from torch_bridge.runs import _utc
    arm.module.save_lens(out / "lens.json")
    torch.save(arm.net.state_dict(), out / "network.pt")
    t1 = time.perf_counter()
    prov = _eval_provider(arm)
    t_prov = time.perf_counter() - t1

    def eval_progress(done, n_nodes, t_eval=time.perf_counter()):
        # the grid's PSFs are most of an evaluation's time since the crops' metrics moved to the device (the A489's
        # 10 x 10 grid at F/2.2: 9 minutes on an H200 before, ~2/3 of it the crops' SSIM on the host; PROTOCOL.md)
        el = time.perf_counter() - t_eval
        report("evaluating", "eval", eval_nodes_done=done, eval_nodes=n_nodes,
               eval_eta_s=round(el * (n_nodes - done) / max(done, 1), 1))
    result["objective_initial"] = arm.objective_initial
    t2 = time.perf_counter()
    result["objective_final"] = objective(arm, prov)
    t_obj = time.perf_counter() - t2
    if eval_nodes(arm) is not None:
        prov.release()   # the training nodes' fields (9.5 GB for the A489 at F/2.2) are not held beside the grid's
    result["eval"] = evaluate(arm, prov, on_progress=eval_progress, group=group)
    # wall s of the evaluation's parts besides evaluate()'s own: the training nodes' fields, the objective
    result["eval"]["timing_s"].update(training_nodes=round(t_prov, 2), objective=round(t_obj, 2))
    result["eval_wall_s"] = time.perf_counter() - t1
    result["rms_design_log"] = arm.rms_log[-1:] if arm.rms_log else []
    result["run"]["wall_s_total"] = round(arm.wall_total(), 3)
    result["run"]["segments"] = arm.segments()
    result["run"]["finished_utc"] = _utc()
    tmp = out / ".result.json.tmp"
    tmp.write_text(json.dumps(result, indent=1, default=default))
    tmp.replace(out / "result.json")
    return result
