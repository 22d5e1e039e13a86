"""Throughput at scale: PSF maps of the A489 + DOE lens (N x N fields x 3 wavelengths), PSFs per second,
peak memory, and the distance from the memory-bandwidth floor; DeepLens's ``psf_map`` loop timed in the
same run when ``deeplens-core`` is importable.

Fields follow DeepLens's ``point_source_grid(grid=(N, N), center=True)``: normalised sensor positions
``u = linspace(-1 + h, 1 - h, N)``, ``h = 1 / (2 (N - 1))``, turned into field angles with the pinhole
scale (``tan(theta) = u * sensor_half / f``, DeepLens's ``calc_scale`` when it is importable, else the
paraxial EFL), object at 10 m, wavelengths 0.45 / 0.55 / 0.65 um, 64 x 64 px patches (``--size``).

Memory: a sampler thread polls every 5 ms during each measured block (rwwarp: the cold and the timed
map at one batch size; DeepLens: its loop): host RSS (psutil) and, on CUDA, the device's used memory
(``cudaMemGetInfo``: everything the process holds, allocator caches included); reported as the peak
above the level at the start of the block, after rwwarp's caches and CuPy's / torch's pools were given
back (Warp's mempool releases at once: threshold 0). DeepLens's torch peak (``max_memory_allocated``)
is reported besides.

Bandwidth floor (a model, stated in the JSON): the bytes each PSF's work must move at least once, over the
copy bandwidth measured on the device (``wp.copy``, read + write):

* trace: each pupil ray read and written once per surface launch up to the DOE plane (124 B) plus
  its generation (60 B), as in ``perf/bench_trace.py``;
* rays to field: the ray record (pos, dir, opl, valid, weight: 68 B) read by the tube-area and
  splat kernels, the tube area written and read (24 B), 4 complex atomic adds per ray (64 B); the
  field accumulators zeroed, read and written as one complex field (48 B per sample);
* propagation (the pruned band-limited ASM of ``rwwarp.wave.propagate``): field and DOE phase read
  (24 B per sample), padded rows written, x-FFT read + write (one pass), band columns gathered, y-FFT
  read + write, transfer function and band read, band written, the two GEMMs' operands and
  results, the node field read by the pixel reduction, the PSF written.

DeepLens's floor by the same rules: its rays (spp x the same per-ray trace bytes, 3 launches + the DOE
plane), its 3000^2 field splat, the 6000^2 padded complex128 field through a forward and an inverse
2-D FFT (one read + write each), the transfer-function multiply, |U|^2 and the crop.

    python perf/bench_map.py --quick                  # CPU, 3x3 fields x 3 wavelengths
    python perf/bench_map.py --grid 10 --size 32      # CPU, 10x10 x 3 at 32 px
    python perf/bench_map.py --device cuda            # GPU, 10x10 x 3 at batches 6, 15, 30; DeepLens when importable
"""
import argparse
import ctypes
import gc
import json
import math
import os
import threading
import time
import traceback

import numpy as np
from _common import RESULTS, device_name, git_commit, save, sync_fn

import rwwarp as rw
from rwwarp.wave import propagate as prop
from rwwarp.trace import as_field_list

WLS = [0.45, 0.55, 0.65]
SIZE = 64
DEPTH = 10000.0


# ------------------------------------------------------------------------------------------- memory sampler
class PeakSampler:
    """Polls host RSS (and device used memory on CUDA) in a thread; ``peak_*`` relative to the start."""

    def __init__(self, device, interval=0.005):
        import psutil
        self.proc = psutil.Process()
        self.cuda = device.startswith("cuda")
        self.device = device
        self.interval = interval

    def _dev_used(self):
        if not self.cuda:
            return 0
        import cupy
        free, total = cupy.cuda.runtime.memGetInfo()
        return total - free

    def release(self):
        """Give cached blocks back (rwwarp's backend caches, CuPy's and torch's pools, malloc) so that the
        peak above the start counts what the measured block allocates."""
        gc.collect()
        try:
            from rwwarp.wave import backend as bk
            bk.get_backend(self.device).clear_caches()
        except Exception:
            pass
        if self.cuda:
            import cupy
            cupy.cuda.runtime.deviceSynchronize()
            cupy.get_default_memory_pool().free_all_blocks()
            try:
                import torch
                torch.cuda.empty_cache()
            except Exception:
                pass
        try:
            ctypes.CDLL("libc.so.6").malloc_trim(0)
        except OSError:
            pass

    def __enter__(self):
        self.release()
        self.base_rss = self.proc.memory_info().rss
        self.base_dev = self._dev_used()
        self.peak_rss, self.peak_dev = self.base_rss, self.base_dev
        self._stop = threading.Event()

        def loop():
            while not self._stop.is_set():
                self.peak_rss = max(self.peak_rss, self.proc.memory_info().rss)
                if self.cuda:
                    self.peak_dev = max(self.peak_dev, self._dev_used())
                time.sleep(self.interval)
        self._t = threading.Thread(target=loop, daemon=True)
        self._t.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._t.join()
        self.peak_rss = max(self.peak_rss, self.proc.memory_info().rss)
        if self.cuda:
            self.peak_dev = max(self.peak_dev, self._dev_used())

    def report(self):
        out = {"host_rss_peak_bytes": self.peak_rss, "host_rss_increase_bytes": self.peak_rss - self.base_rss}
        if self.cuda:
            out.update({"device_used_peak_bytes": self.peak_dev, "device_used_increase_bytes": self.peak_dev - self.base_dev})
        return out


def copy_bandwidth(device):
    """Read + write bytes per second of a device copy (``wp.copy``; 256 MB on CUDA, 64 MB on CPU)."""
    import warp as wp
    from _common import timed
    dev = "cuda:0" if device == "cuda" else ("cpu" if not device.startswith("cuda") else device)
    n = (32 if dev.startswith("cuda") else 8) * 1_000_000
    x = wp.zeros(n, dtype=wp.float64, device=dev)
    y = wp.zeros(n, dtype=wp.float64, device=dev)
    t = timed(lambda: wp.copy(y, x), lambda: wp.synchronize_device(dev), 5)
    return 2 * 8 * n / t


# ------------------------------------------------------------------------------------------- fields
def field_grid(n, lens, scale=None):
    """DeepLens's centre-of-patch grid of normalised sensor positions -> (x, y) field angles (deg), rows from
    +y to -y as DeepLens orders them. ``scale``: object height per image height (DeepLens's calc_scale)."""
    if n == 1:
        us = np.array([0.0])
    else:
        h = 1.0 / (2.0 * (n - 1))
        us = np.linspace(-1 + h, 1 - h, n)
    half = 0.5 * lens.sensor.pixel_pitch * lens.sensor.resolution[0]
    if scale is None:
        scale = DEPTH / lens.efl(0.55)
    ang = lambda u: math.degrees(math.atan(u * half * scale / DEPTH))
    return [(ang(ux), ang(uy)) for uy in us[::-1] for ux in us], [(float(ux), float(uy)) for uy in us[::-1] for ux in us]


# ------------------------------------------------------------------------------------------- bytes model
def _band_widths(rwm):
    """Band columns / rows (kx, ky) of each source, as rwwarp.wave.propagate sets them up."""
    g = rwm.sensor_geometry()
    pitch, origin, wl_um, z, px, py = (g.pitch_mm, g.origin_mm, g.wavelength_um, g.distance_mm,
                                       g.pixel_centers_x_mm, g.pixel_centers_y_mm)
    n = rwm.plan.n_grid
    npad = rwm.plan.n_pad
    lam = np.asarray(wl_um) * 1e-3
    lp = pitch * npad
    in_center = origin + 0.5 * (n - 1) * pitch
    out_center = np.stack([0.5 * (px[:, 0] + px[:, -1]), 0.5 * (py[:, 0] + py[:, -1])], axis=1)
    shift = out_center - in_center
    # the distance is per source ((S,) since the map's sources each carry their own): a column for the two axes
    zc = np.broadcast_to(np.asarray(z, dtype=float).reshape(-1, 1), (len(lam), 1))
    lo, hi = prop.band_limits(lam[:, None], zc, np.full((len(lam), 2), lp), shift)
    carrier = rwm.carrier
    qmin, qmax = -(npad // 2), (npad - 1) // 2
    with np.errstate(invalid="ignore", over="ignore"):
        q_lo = np.where(np.isfinite(lo), np.ceil((lo - carrier) * lp) - 1.0, qmin)
        q_hi = np.where(np.isfinite(hi), np.floor((hi - carrier) * lp) + 1.0, qmax)
    kb = np.maximum(np.clip(q_hi, qmin - 1, qmax) - np.clip(q_lo, qmin, qmax + 1) + 1.0, 0.0)
    kx = min(npad, int(math.ceil(max(kb[:, 0].max(), 1) / 64.0) * 64))
    ky = max(int(kb[:, 1].max()), 1)
    return kx, ky


def rwwarp_bytes(rwm, gauss_nodes=3):
    """Minimum bytes moved per stage for one batch (RayWave instance), summed over its sources."""
    pl, S = rwm.plan, rwm.nsrc
    rays = pl.ray_grid ** 2
    launches = rwm.plane + 1
    n, npad = pl.n_grid, pl.n_pad
    m = SIZE * gauss_nodes
    c = 16  # complex128
    trace = rays * (124 * launches + 60)
    to_field = rays * (68 * 2 + 24 + 64) + n * n * 48
    if pl.method == "focal":
        # rwwarp.wave.focal: field (and the DOE orders' factor) read, the two separable kernel matrices
        # (n_sensor x n_grid) read, the intermediate (n_sensor x n_grid) written and read, the sensor-side
        # field (n_sensor^2) written, its padded FFT (n_sensor_fft^2, read + write, forward and inverse),
        # the output DFT's factors and result, the PSF written
        ns, nf = pl.n_sensor, pl.n_sensor_fft
        propagation = (2 * n * n * c + 2 * ns * n * c + 2 * ns * n * c + ns * ns * c
                       + 2 * 2 * nf * nf * c + (2 * nf * m + m * m) * c + SIZE * SIZE * 8)
        return {"trace": S * trace, "rays_to_field": S * to_field, "propagation": S * propagation}
    kx, ky = _band_widths(rwm)
    has_phase = rwm.doe_phase()[0] is not None
    propagation = (n * n * (c + (8 if has_phase else 0)) + n * npad * c  # pad + modulate
                   + 2 * n * npad * c                                     # x-FFT
                   + n * kx * c + npad * kx * c                           # column gather
                   + 2 * npad * kx * c                                    # y-FFT
                   + 3 * ky * kx * c                                      # transfer x band
                   + (ky * kx + kx * m + 2 * ky * m + m * ky + m * m) * c  # GEMMs (band, factors, tmp, out)
                   + m * m * c + SIZE * SIZE * 8)                         # pixel reduction
    return {"trace": S * trace, "rays_to_field": S * to_field, "propagation": S * propagation}


def deeplens_bytes(spp, n_doe=3000, launches=4):
    npad = 2 * n_doe
    c = 16
    field = n_doe * n_doe * 2 * c
    waves = (npad * npad * c            # pad
             + 2 * 2 * npad * npad * c  # forward + inverse 2-D FFT, one read + write each
             + 3 * npad * npad * c      # transfer function multiply
             + npad * npad * (c + 8)    # |U|^2
             + SIZE * SIZE * 8)
    return {"trace": spp * (124 * launches + 60), "rays_to_field": spp * (68 + 64) + field, "propagation": waves}


# ------------------------------------------------------------------------------------------- runs
def bench_rwwarp(lens, fields, device, batch, bandwidth, log, method="auto"):
    s = sync_fn(device)
    pairs = [(i, j) for i in range(len(fields)) for j in range(len(WLS))]
    with PeakSampler(device) as mem:   # over the cold run (FFT plans, transfer functions) and the timed one
        t0 = time.perf_counter()
        rw.psf_map(lens, fields, WLS, size=SIZE, device=device, batch=batch, method=method)
        s()
        cold = time.perf_counter() - t0
        t0 = time.perf_counter()
        m = rw.psf_map(lens, fields, WLS, size=SIZE, device=device, batch=batch, method=method)
        s()
        warm = time.perf_counter() - t0
    # bytes model of the plans psf_map ran: every source on its own plan (rwwarp.wave.packed.source_plans, pilot
    # traces only; packed batches pad the trace and splat to their largest member, not counted here)
    from rwwarp.wave.plan import default_memory_budget_bytes
    from rwwarp.wave.packed import source_plans
    tot = {"trace": 0, "rays_to_field": 0, "propagation": 0}
    order = [pr for b in m.info["batches"] for pr in b["pairs"]]
    members = source_plans(lens, as_field_list([fields[i] for i, _ in order]), [WLS[j] for _, j in order], SIZE,
                           lens.sensor.pixel_pitch, device, method=method,
                           memory_budget_bytes=default_memory_budget_bytes(device))
    for rwm in members:
        for k, v in rwwarp_bytes(rwm).items():
            tot[k] += v
    plans, at = [], 0
    for b in m.info["batches"]:
        grp = members[at:at + len(b["pairs"])]
        at += len(b["pairs"])
        plans.append({"sources": len(grp), "method": [r.plan.method for r in grp],
                      "pitch_um": [r.plan.pitch_mm * 1e3 for r in grp], "n_grid": [r.plan.n_grid for r in grp],
                      "n_pad": [r.plan.n_pad for r in grp], "ray_grid": [r.plan.ray_grid for r in grp]})
    nb = sum(tot.values())
    floor = nb / bandwidth
    out = {"batch": batch, "method": method, "n_batches": len(m.info["batches"]), "n_psfs": len(pairs), "cold_s": cold, "time_s": warm, "psfs_per_s": len(pairs) / warm,
           "ms_per_psf": 1e3 * warm / len(pairs), **mem.report(), "bytes_model": tot, "bytes_total": nb,
           "floor_s": floor, "fraction_of_floor": floor / warm,
           "floor_by_stage_s": {k: v / bandwidth for k, v in tot.items()}, "plans": plans,
           "patch_power_mean": float(m.data.sum(axis=(2, 3)).mean())}
    log(f"rwwarp batch {batch}, method {method}: {warm:.2f} s (cold {cold:.2f} s) for {len(pairs)} PSFs = {out['psfs_per_s']:.2f} PSF/s, "
        f"floor {floor:.3f} s ({100 * out['fraction_of_floor']:.1f}% of the floor), "
        f"peak +{out.get('device_used_increase_bytes', out['host_rss_increase_bytes']) / 2 ** 30:.2f} GiB")
    return out, m


def deeplens_lens(device):
    """DeepLens's HybridLens of the A489 + flat DOE (perf/_deeplens.py)."""
    import _deeplens
    return _deeplens.a489_hybridlens("cuda" if device.startswith("cuda") else "cpu")


def bench_deeplens(n, device, bandwidth, log, spp_loop=1_000_000):
    import torch
    dev = "cuda" if device.startswith("cuda") else "cpu"
    lens = deeplens_lens(device)
    sync = (lambda: torch.cuda.synchronize()) if dev == "cuda" else (lambda: None)
    out = {"scale": float(lens.calc_scale(-DEPTH))}
    # warm-up (one PSF)
    with torch.no_grad():
        lens.psf(points=[0.0, 0.0, -DEPTH], ks=SIZE, wvln=0.55)
    sync()

    def map_default():
        res = []
        for w in WLS:
            try:
                res.append(lens.psf_map(grid=(n, n), wvln=w, depth=-DEPTH, ks=SIZE))
            except TypeError:
                res.append(lens.psf_map(grid=(n, n), wvln=w, depth=-DEPTH, ks=SIZE, spp=None))
        return res

    def loop_spp():
        _, pts = field_grid(n, rw.load_lens("a489_doe"), out["scale"])
        for ux, uy in pts:
            for w in WLS:
                lens.psf(points=[ux, uy, -DEPTH], ks=SIZE, wvln=w, spp=spp_loop)

    for name, fn, spp in (("psf_map_default_spp", map_default, 16_777_216), (f"loop_{spp_loop}_spp", loop_spp, spp_loop)):
        if dev == "cuda":
            torch.cuda.empty_cache()
            torch.cuda.reset_peak_memory_stats()
        try:
            with PeakSampler(device) as mem, torch.no_grad():
                t0 = time.perf_counter()
                fn()
                sync()
                t = time.perf_counter() - t0
        except Exception as e:
            traceback.print_exc()
            out[name] = {"error": f"{type(e).__name__}: {e}"}
            continue
        npsf = n * n * len(WLS)
        nb = deeplens_bytes(spp)
        floor = npsf * sum(nb.values()) / bandwidth
        r = {"time_s": t, "n_psfs": npsf, "psfs_per_s": npsf / t, "ms_per_psf": 1e3 * t / npsf, **mem.report(),
             "spp": spp, "bytes_model_per_psf": nb, "floor_s": floor, "fraction_of_floor": floor / t}
        if dev == "cuda":
            r["torch_peak_allocated_bytes"] = torch.cuda.max_memory_allocated()
        out[name] = r
        log(f"DeepLens {name}: {t:.2f} s = {r['psfs_per_s']:.2f} PSF/s, floor {floor:.3f} s "
            f"({100 * r['fraction_of_floor']:.1f}%)")
    return out


def deeplens_importable():
    try:
        import _deeplens
        return _deeplens.deeplens_importable()   # stubs a torchvision that cannot load (image writing only)
    except Exception:
        return False


def main():
    global SIZE
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--grid", type=int, default=None, help="fields per axis (default 10; --quick: 3)")
    ap.add_argument("--quick", action="store_true", help="3x3 fields (unless --grid) x 3 wavelengths")
    ap.add_argument("--size", type=int, default=SIZE, help=f"patch size, px (default {SIZE})")
    ap.add_argument("--batch", type=int, nargs="+", default=None,
                    help="sources per launch, one run each, 0: psf_map's default (no limit but the memory "
                         "budget) (default CPU 9 30, GPU 3 6 15 30 0)")
    ap.add_argument("--method", default="auto", choices=("auto", "focal", "asm"),
                    help="rw.psf_map's method (default auto: each source's own choice, as rw.psf makes it)")
    ap.add_argument("--no-deeplens", action="store_true")
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    SIZE = a.size
    gpu = a.device.startswith("cuda")
    n = a.grid or (3 if a.quick else 10)
    # CPU: no default-budget run (half the available memory, shared with whatever else runs there)
    batch_list = [b or None for b in (a.batch or ([3, 6, 15, 30, 0] if gpu else [9, 30]))]

    def log(msg):
        print(msg, flush=True)

    lens = rw.load_lens("a489_doe")
    if gpu:
        import warp as wp
        wp.init()
        wp.set_mempool_release_threshold("cuda:0" if a.device == "cuda" else a.device, 0)  # measurable peaks
    have_dl = not a.no_deeplens and deeplens_importable()
    t0 = time.perf_counter()
    rw.psf(lens, 0.0, 0.55, size=SIZE, device=a.device)
    first = time.perf_counter() - t0
    bw = copy_bandwidth(a.device)
    scale = None
    if have_dl:
        try:
            scale = float(deeplens_lens(a.device).calc_scale(-DEPTH))   # the same field points as DeepLens's grid
        except Exception:
            traceback.print_exc()
            have_dl = False
    fields, norm = field_grid(n, lens, scale)
    res = {"benchmark": "psf_map", "lens": "a489_doe (flat DOE), object at 10 m", "device": a.device,
           "device_name": device_name(a.device), "commit": git_commit(), "grid": [n, n], "wavelengths_um": WLS,
           "size_px": SIZE, "n_psfs": n * n * len(WLS), "fields_deg": fields, "fields_normalised": norm,
           "first_call_s": first, "copy_bandwidth_GBps": bw / 1e9, "load_average_start": os.getloadavg(),
           "floor_model": "bytes each stage must move at least once / measured copy bandwidth (see the script's "
                          "docstring); fraction_of_floor = floor_s / time_s",
           "memory": "peak above the start of each measured block (rwwarp: cold + timed map; DeepLens: its loop), "
                     "caches and pools released first; sampled every 5 ms",
           "rwwarp": []}
    log(f"{n}x{n} fields x {len(WLS)} wavelengths on {res['device_name']}; copy bandwidth {bw / 1e9:.1f} GB/s")
    for b in batch_list:
        r, _ = bench_rwwarp(lens, fields, a.device, b, bw, log, a.method)
        res["rwwarp"].append(r)
    if have_dl:
        try:
            res["deeplens"] = bench_deeplens(n, a.device, bw, log)
            key = "device_used_increase_bytes" if gpu else "host_rss_increase_bytes"
            ratios = {}
            for name, dl in res["deeplens"].items():
                if not isinstance(dl, dict) or "psfs_per_s" not in dl:
                    continue
                ratios[name] = [{"rwwarp_batch": r["batch"], "throughput_ratio": r["psfs_per_s"] / dl["psfs_per_s"],
                                 "peak_memory_ratio": r[key] / max(dl[key], 1)} for r in res["rwwarp"]]
            res["ratios"] = ratios
            log("ratios: " + json.dumps(ratios))
        except Exception as e:
            traceback.print_exc()
            res["deeplens_error"] = f"{type(e).__name__}: {e}"
    elif a.no_deeplens:
        res["deeplens"] = "not run (--no-deeplens): on 2 CPU cores its default 16.7M-ray psf_map takes ~8 min per PSF; timed on the GPU run"
    else:
        res["deeplens"] = "not importable on this machine (deeplens-core); timed on the GPU run"
    res["load_average_end"] = os.getloadavg()
    tag = "gpu" if gpu else "cpu"
    if a.method != "auto":
        tag += f"_{a.method}"
    log(f"-> {save(f'bench_map_{tag}', res, a.out or os.environ.get('RWWARP_RESULTS', str(RESULTS)))}")


if __name__ == "__main__":
    main()
