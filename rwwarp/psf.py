"""Point spread functions: the public ``psf`` and ``psf_map`` calls and the three models.

* ``model="ray-wave"`` (the paper's model): coherent ray trace to the DOE plane (Warp), rays splatted
  into a complex field (Warp), DOE phase, band-limited angular spectrum to the sensor and pixel
  integration (OpenCL + VkFFT).
* ``model="ray"``: the DOE as a local grating (rays bent by the phase gradient), geometric PSF by
  binning ray power into pixels. Refuses discontinuous DOEs.
* ``model="paraxial-wave"``: the refractive part replaced by an ideal thin lens of its paraxial
  focal length at the DOE plane, then the same wave path.

Normalisation: ``PSF.data`` is the fraction of the power entering the entrance pupil that lands in
each sensor pixel (box integration of |U|^2 over the pixel). Lengths in mm, wavelengths in um.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from .wave.plan import Plan
from .trace import as_field_list
from .wave.raywave import RAYWAVE_OPTIONS, RayWave  # noqa: F401 (RayWave lived here)
from .wave.packed import PackedRayWave, packed_bytes, source_plans
from .wave.pilot import Pilot, trace_pilot  # noqa: F401 (the pilot trace of a batch, rwwarp.wave.pilot)
from .wave.methods import choices as method_choices  # the registered methods
from .map_run import MODELS, _check_tolerance, _wave_map, pack_sources, wave_members  # noqa: F401 (their home: map_run)

@dataclass
class PSF:
    """A PSF patch on the sensor's pixel grid.

    ``data``: (size, size) fraction of entering power per pixel (row = y, column = x, y up).
    ``pixel_mm``: pixel pitch, mm. ``center_mm``: sensor (x, y) of the centre pixel ``data[size//2, size//2]``.
    """

    data: np.ndarray
    pixel_mm: float
    center_mm: tuple
    field_deg: object = 0.0
    wavelength_um: float = 0.55
    model: str = "ray-wave"
    plan: dict | None = None
    info: dict = field(default_factory=dict)

    @property
    def extent_mm(self):
        """(xmin, xmax, ymin, ymax) of the patch's outer pixel edges, mm (for imshow)."""
        n = self.data.shape[0]
        h = 0.5 * n * self.pixel_mm
        return (self.center_mm[0] - h, self.center_mm[0] + h, self.center_mm[1] - h, self.center_mm[1] + h)

    def coords_mm(self):
        """Pixel-centre coordinates (x, y) of the patch columns and rows, mm."""
        n = self.data.shape[0]
        off = (np.arange(n) - n // 2) * self.pixel_mm
        return self.center_mm[0] + off, self.center_mm[1] + off

    def __repr__(self):
        from .results import psf_repr
        return psf_repr(self)

    def plot(self, path=None, ax=None, log: bool = True):
        """The patch normalised to its peak, log10 by default, axes in um from its centre (rwwarp.results); returns the Axes, or the Figure saved to ``path`` (PNG)."""
        from .results import plot_psf
        return plot_psf(self, path=path, ax=ax, log=log)


@dataclass
class PSFMap:
    """PSFs for fields x wavelengths: ``data`` (n_fields, n_wavelengths, size, size), ``centers_mm``
    (n_fields, n_wavelengths, 2)."""

    data: np.ndarray
    pixel_mm: float
    centers_mm: np.ndarray
    fields_deg: list
    wavelengths_um: list
    model: str
    info: dict = field(default_factory=dict)

    def __getitem__(self, idx) -> PSF:
        i, j = idx
        return PSF(self.data[i, j], self.pixel_mm, tuple(self.centers_mm[i, j]), self.fields_deg[i],
                   self.wavelengths_um[j], self.model)

    def __repr__(self):
        from .results import psf_map_repr
        return psf_map_repr(self)

    def plot(self, path=None, log: bool = True):
        """Fields across, wavelengths down, each tile normalised to its own peak (rwwarp.results); returns the Axes, or the Figure saved to ``path`` (PNG)."""
        from .results import plot_psf_map
        return plot_psf_map(self, path=path, log=log)


# ---------------------------------------------------------------------------------------------- API
def psf(lens, field_deg=0.0, wavelength_um: float = 0.55, model: str = "ray-wave", size: int = 64,
        device: str = "cpu", plan="auto", dtype: str = "float64", amplitude: str = "energy",
        object_distance_mm=None, rays_per_sample: float = 1.0, pixel_mm=None, center_mm=None,
        use_reference: bool = True, gauss_nodes: int | None = None, nyquist_safety: float = 2.0,
        method: str = "auto", memory_budget_gb: float | None = None, focal_patch_tol: float = 1e-5,
        focal_precision: str = "auto", deterministic: bool = False, pixel_values: str = "flux",
        tolerance: float | None = None, cache="auto", order_tol: float = 1e-4) -> PSF:
    """PSF of ``lens`` for one field point and wavelength.

    Parameters
    ----------
    field_deg : float or (float, float)
        Field angle in degrees (y, or (x, y)).
    wavelength_um : float
        Wavelength, um.
    model : "ray-wave" | "ray" | "paraxial-wave"
    size : int
        Patch size in sensor pixels (square).
    device : "cpu" | "cuda" | "cuda:N" | "opencl:P:D"
    plan : "auto" | "paper" | Plan
        Sampling plan (see :mod:`rwwarp.wave.plan`).
    dtype : "float64" | "float32"
        Ray-tracing precision (the field is accumulated in float64).
    amplitude : "energy" | "paper"
        Ray amplitude convention of the splat (:mod:`rwwarp.kernels.splat`; README "Physics notes").
    object_distance_mm : float, optional
        Overrides the lens's object distance (mm from the first vertex; inf allowed).
    rays_per_sample : float
        Rays per DOE-plane sample along each axis (adaptive plan).
    pixel_mm : float, optional
        Sensor pixel pitch (mm), default the lens's sensor.
    center_mm : (x, y), optional
        Sensor position of the patch centre (snapped to a pixel centre); default where the chief ray lands.
    gauss_nodes : int, optional
        Gauss-Legendre nodes per axis for the pixel (box) integration of the pixel values; default: the fewest
        whose error bound for the highest intensity frequency across a pixel is below 1e-7.
    nyquist_safety : float
        Adaptive plan: the DOE-plane pitch samples the highest local frequency this many times above
        its Nyquist limit of 2 samples per period (aperture-edge diffraction spreads past it; 2 keeps
        the aliased part near 1e-4).
    method : "auto" | "focal" | "asm" | "two-step" | "pixel" | "direct" | any registered method
        Wave propagation (ray-wave model). ``"focal"`` handles the wave converging to the patch
        analytically and samples only what reaches the patch (:mod:`rwwarp.wave.focal`); ``"asm"`` is the
        band-limited angular spectrum over the whole converging beam (its cost grows with footprint x NA /
        lambda; not a reference where the geometric spot is wider than the patch: docs/accuracy.md).
        ``"auto"``: both are planned from one pilot trace and the plan of fewer flops runs, on every device
        (:class:`rwwarp.wave.raywave.RayWave`'s ``auto_rule``); pixel-map DOEs and ``plan="paper"`` always use
        the ASM.
        With ``tolerance`` "auto" adds the wave step (:mod:`rwwarp.wave.wave_step`) where the model's own error
        estimate exceeds it. ``"two-step"``: the method "auto" picks, always with the wave step: the
        geometric field's edge is diffracted as a wave from the stop's image to the DOE plane before the DOE.
        ``"pixel"``: pixels many Airy radii wide (:mod:`rwwarp.wave.pixel_scale`): the sensor field as the rays'
        plane waves on a grid at the field's Nyquist rate over the patch, each pixel's box integrated exactly;
        its cost follows the patch and the aberrations, not the beam's diffraction-scale sampling. "auto" picks
        it for a lens without a DOE where the pixel spans >= 4 Airy radii, its error estimate against the full
        computation is within ``tolerance`` (default 1e-3 of the peak; a given ``tolerance`` below the model's own
        error keeps the wave step instead) and it plans fewer flops. ``"direct"``: the brute-force
        Rayleigh-Sommerfeld sum from every wave-plane sample to every pixel node (no FFT; O(N^2 M^2): a reference
        for small cases). The methods are registered by name (:mod:`rwwarp.wave.methods`).
    memory_budget_gb : float, optional
        Refuse (:class:`rwwarp.wave.plan.MemoryBudgetError`, naming the estimate and what drives it) or split a
        batch whose planned arrays would exceed this many GiB; default half the available memory.
    focal_patch_tol : float
        Focal method with a DOE off its design wavelength: a diffraction order other than the main one
        is computed only if it puts at least this fraction of the power on the patch (default 1e-5;
        the orders left out are reported in ``info``). Larger values keep fewer, defocused orders.
    focal_precision : "auto" | "single" | "double"
        Arithmetic of the focal method's matrix products (its phases are formed in float64; the rest is
        complex128). "single" halves their time and memory on the CPU and moved the Cooke triplet, AC254 and
        A489 errors against the independent truth in the third digit; "double" matches the torch bridge's
        gradients' arithmetic. "auto" (default): single on the CPU, double on CUDA (on an H200 the complex128
        products, on FP64 tensor cores, were faster: Cooke 14 deg 12.2 against 17.0 ms).
    deterministic : bool
        The same bits on every run on a GPU too (:class:`RayWave` ``deterministic``: fixed-point splat
        sums, resolution ~1e-13 of the field). The CPU is deterministic either way.
    pixel_values : "flux" | "intensity"
        What a sensor pixel records (wave models). ``"flux"`` (default): the power through it, the
        z-component of the Poynting vector (obliquity included) of the field whose flux through the wave
        plane is the traced power, so a PSF that catches all the light sums to the traced fraction.
        ``"intensity"``: ``|U|^2`` integrated over it, the convention before issue 27. The two differ by the
        Poynting vector's z-component: in scale by about the mean direction cosine of the light at the sensor
        (0.991 at 10 deg with a strong DOE 5 mm before the sensor, docs/accuracy.md), in shape, once that scale
        is removed, by ~1e-4 of the peak at 35-40 deg (docs/propagation.md "Pixel values").
    tolerance : float, optional
        The model error (max |error| over the PSF's peak) the caller accepts. The ray-wave model's own
        error (the geometric field at the DOE plane leaves out the rim's diffraction on the way there) is
        estimated from the scene (:mod:`rwwarp.wave.model_error`; in the plan and ``--explain``); above
        ``tolerance``, ``method="auto"`` adds the wave step, and an explicit ``"asm"`` / ``"focal"`` warns
        (:class:`rwwarp.wave.model_error.ModelErrorWarning`). None (default): estimate and report only. It also
        sets the focal plan's sampling: where a tenth of it (``rwwarp.wave.plan.SAMPLING_SHARE``) exceeds the
        default rules' error (~2e-4 of the peak), the ray-landing period, the rim's ray count, a lit taper's margin
        and the pixel integration relax (:func:`rwwarp.wave.plan.sampling_relax`, at most 16x) so that the sampling
        error stays within that tenth (the plan's reasons say so); None or a tolerance up to 2e-3: the default plan. A
        strongly defocused beam asks for a wave-plane grid beyond ``rwwarp.wave.plan.FOCAL_RAY_MAX_GRID`` samples; the
        plan then caps it and states the rim's estimated error (a :class:`~rwwarp.errors.SamplingWarning` above
        the tolerance, or 1e-3 without one), and with a tolerance the cap gives way to meet it (up to 16384 samples).
    cache : "auto" | rwwarp.PlanCache | None
        Keep this call's pilot trace, plan, batches and propagation operators in a
        :class:`~rwwarp.wave.plan_cache.PlanCache` and reuse them when a later call passes the same cache, lens
        values and arguments (wave models; the same bits as without it; a lens changed in place is a miss: the key
        is a digest of its values, :func:`~rwwarp.wave.plan_cache.lens_fingerprint`). ``"auto"`` (default): the
        process-wide :func:`~rwwarp.wave.plan_cache.default_cache` (at most 8 entries and 512 MiB of kept arrays;
        a call that finds it busy in another thread runs uncached). None or False: plan every call, keep nothing;
        ``RWWARP_PLAN_CACHE=0`` in the environment or ``rwwarp.wave.plan_cache.set_default_cache(None)`` turns
        the default off for the whole process. ``p.info["cache"]``: "hit", "miss", or where the default cache
        was skipped "busy" / "off".
    order_tol : float
        Multi-order phase surfaces (``Surface.diffraction_orders``, :mod:`rwwarp.phase_orders`): an order
        combination whose efficiency is below this is skipped (named in the plan's reasons); default 1e-4.
    """
    m = psf_map(lens, [field_deg], [wavelength_um], model=model, size=size, device=device, plan=plan,
                dtype=dtype, amplitude=amplitude, object_distance_mm=object_distance_mm,
                rays_per_sample=rays_per_sample, pixel_mm=pixel_mm, center_mm=center_mm,
                use_reference=use_reference, gauss_nodes=gauss_nodes, nyquist_safety=nyquist_safety,
                method=method, memory_budget_gb=memory_budget_gb, focal_patch_tol=focal_patch_tol,
                focal_precision=focal_precision, deterministic=deterministic, pixel_values=pixel_values,
                tolerance=tolerance, cache=cache, order_tol=order_tol)
    p = m[0, 0]
    p.plan = m.info.get("plan")
    p.info = {k: (v[0] if isinstance(v, (list, np.ndarray)) and len(v) == 1 else v) for k, v in m.info.items()}
    return p


def plan_psf(lens, field_deg=0.0, wavelength_um: float = 0.55, size: int = 64, device: str = "cpu",
             method: str = "auto", rays_per_sample: float = 1.0, nyquist_safety: float = 2.0, pixel_mm=None,
             object_distance_mm=None, center_mm=None, focal_patch_tol: float = 1e-5,
             tolerance: float | None = None) -> Plan:
    """The sampling plan and its cost estimate for a ray-wave PSF, without computing it (only the pilot
    trace runs). ``plan.explain()`` prints it; ``plan.estimate`` holds ``memory_bytes`` and ``flops``.
    Arguments as :func:`psf` (lengths mm, wavelengths um, field deg)."""
    from . import checks
    checks.check_choice(method, "method", method_choices())
    tolerance = _check_tolerance(tolerance)
    fields = checks.check_fields([field_deg])
    wls = checks.check_wavelengths([wavelength_um], lens)
    size = checks.check_size(size)
    pixel = float(pixel_mm or lens.sensor.pixel_pitch)
    from .phase_orders import ORDER_TOL, describe, multi_order_surfaces, order_combinations, order_lens
    multi = multi_order_surfaces(lens)
    # several orders: the design order is planned here, the others when computed (rwwarp.phase_orders)
    planned = order_lens(lens, {i: lens.surfaces[i].diffraction_order for i in multi}) if multi else lens
    rwm = RayWave(planned, as_field_list(fields), [float(w) for w in wls], size, pixel, device, "auto",
                  object_distance_mm=object_distance_mm, rays_per_sample=rays_per_sample, center_mm=center_mm,
                  nyquist_safety=nyquist_safety, method=method, focal_patch_tol=focal_patch_tol,
                  model_tolerance=tolerance, allow_pixel=True)
    if multi:
        kept, skipped = order_combinations(lens, float(wls[0]), ORDER_TOL)
        return rwm.plan.with_reasons(*describe(kept, skipped, float(wls[0]), ORDER_TOL))
    return rwm.plan


def psf_map(lens, fields, wavelengths_um, model: str = "ray-wave", size: int = 64, device: str = "cpu",
            plan="auto", dtype: str = "float64", amplitude: str = "energy", object_distance_mm=None,
            rays_per_sample: float = 1.0, pixel_mm=None, center_mm=None, use_reference: bool = True,
            gauss_nodes: int | None = None, batch: int | None = None, progress: bool = False,
            nyquist_safety: float = 2.0, method: str = "auto", memory_budget_gb: float | None = None,
            focal_patch_tol: float = 1e-5, focal_precision: str = "auto", deterministic: bool = False,
            pixel_values: str = "flux", tolerance: float | None = None, cache=None,
            order_tol: float = 1e-4) -> PSFMap:
    """PSFs for every (field, wavelength) pair, batched: one trace launch per surface for the whole
    batch. ``fields``: list of field angles (deg), ``wavelengths_um``: list (um).

    Wave models: every (field, wavelength) pair is planned on its own (one pilot trace of all of them) and
    computed on that plan whatever its batch, so each PSF is the one :func:`psf` gives (to ~1e-16 of the
    peak: the splat's float sums on CPU threads may add in another order). A batch
    (:class:`rwwarp.wave.packed.PackedRayWave`) traces and splats its members in one set of launches, in arrays
    sized to its largest member (the extra rays invalid, the extra samples zero), then propagates each by
    its own plan; batches take members of one propagation method, largest first, within the memory budget
    (:func:`pack_sources`). ``batch`` limits the number of sources per batch (default no limit but the
    budget, and on the CPU :data:`rwwarp.map_run.CPU_BATCH_BYTES` a batch); ``progress`` shows a tqdm bar. Returns :class:`PSFMap` with ``data`` of shape (n_fields,
    n_wavelengths, size, size); ``info["batches"]`` lists each batch's (field, wavelength) index pairs,
    ``plans`` (each member's plan) and ``plan`` (its last member's); ``info["plan"]`` is the last batch's
    ``plan``. ``cache`` (a :class:`~rwwarp.wave.plan_cache.PlanCache`, or ``"auto"``: the process-wide one that
    :func:`psf` uses by default; None, the default here: nothing kept): a repeated map of the same lens values
    and arguments reuses its pilot, plans, batches and operators (``info["cache"]``: "hit" or "miss"; on a hit
    ``info["replay"]``: per batch "graph: trace and splat" (replayed as a CUDA graph, :mod:`rwwarp.wave.graph_replay`) or why it ran eagerly).
    A lens with multi-order phase surfaces (``Surface.diffraction_orders``) computes each PSF as the coherent sum of
    its orders (:mod:`rwwarp.phase_orders`; ``info["orders"]``: per PSF the traced orders, weights, efficiencies).
    Other arguments as :func:`psf`.
    """
    from .map_run import finish_map, map_args, run_sources
    # arguments at the public edge (issue 12), checked and resolved where rwwarp.distributed.psf_map takes them too
    a = map_args(lens, fields, wavelengths_um, model=model, size=size, device=device, plan=plan, dtype=dtype,
                 amplitude=amplitude, object_distance_mm=object_distance_mm, rays_per_sample=rays_per_sample,
                 pixel_mm=pixel_mm, center_mm=center_mm, use_reference=use_reference, gauss_nodes=gauss_nodes,
                 batch=batch, nyquist_safety=nyquist_safety, method=method, memory_budget_gb=memory_budget_gb,
                 focal_patch_tol=focal_patch_tol, focal_precision=focal_precision, deterministic=deterministic,
                 pixel_values=pixel_values, tolerance=tolerance, order_tol=order_tol)
    from .wave.plan_cache import resolve_cache
    cache = resolve_cache(cache)   # "auto": the process-wide default cache; None / False: nothing kept
    fields, wavelengths_um, size = a.fields, a.wls, a.size
    pairs = [(i, j) for i in range(len(fields)) for j in range(len(wavelengths_um))]
    out = np.zeros((len(fields), len(wavelengths_um), size, size))
    centers = np.zeros((len(fields), len(wavelengths_um), 2))
    info = {"plan": None, "valid_fraction": np.zeros(len(pairs)), "time_s": 0.0, "batches": [],
            "dropped_rays": np.zeros(len(pairs), dtype=np.int64)}
    t0 = time.perf_counter()
    index = {pr: k for k, pr in enumerate(pairs)}
    bar = None
    if progress:
        from tqdm.auto import tqdm
        bar = tqdm(total=len(pairs), desc=f"{model} PSFs", unit="PSF")

    def store(chunk, res):
        for k, (i, j) in enumerate(chunk):
            out[i, j] = res["data"][k]
            centers[i, j] = res["centers"][k]
            info["valid_fraction"][index[(i, j)]] = res["valid_fraction"][k]
            if "dropped_rays" in res:
                info["dropped_rays"][index[(i, j)]] = int(res["dropped_rays"][k])
        info["plan"] = res.get("plan")
        info["batches"].append({"pairs": [tuple(pr) for pr in chunk], "plan": res.get("plan"),
                                "plans": res.get("plans", [res.get("plan")] * len(chunk))})
        if bar is not None:
            bar.update(len(chunk))

    # wave models: every source on its own plan (a PSF does not depend on its batch), planned alone from one pilot
    # trace, then packed into batches of at most ``batch`` sources that one set of launches traces and splats
    # (arrays sized to the batch's largest member; rwwarp.wave.packed.PackedRayWave), each propagated alone
    run_sources(lens, a, pairs, object_distance_mm, store, cache=cache, info=info)
    if bar is not None:
        bar.close()
    info["valid_fraction"] = list(info["valid_fraction"])
    info["power_in_patch"] = finish_map(a, out.sum(axis=(2, 3)), info["valid_fraction"], info["dropped_rays"],
                                        [p for b in info["batches"] for p in b["plans"]])
    info["time_s"] = time.perf_counter() - t0
    return PSFMap(out, a.pixel, centers, fields, wavelengths_um, model, info)


# ---------------------------------------------------------------------------------------------- comparison models
from .wave.paraxial_wave import paraxial_equivalent  # noqa: E402,F401  (public here for compatibility)


from .ray_model import _ray_model  # noqa: E402,F401
