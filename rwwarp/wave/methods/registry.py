"""The propagation methods' common interface (:class:`Propagation`) and the registry that names them.

A propagation method carries the wave-plane field of a :class:`~rwwarp.wave.raywave.RayWave` batch to the
sensor's pixels. Each is a subclass of :class:`Propagation` registered by name (:func:`register`); the
planner (:class:`~rwwarp.wave.raywave.RayWave`), :func:`rwwarp.psf`, :func:`rwwarp.wave.plan.estimate_cost`,
the packed batches and :mod:`torch_bridge` look a method up by name (:func:`get`) and read its capability
flags instead of testing the name. ``"auto"`` (the cheaper of ``"focal"`` and ``"asm"``, or ``"pixel"``) and
``"two-step"`` (auto's choice with a wave step) are choices the planner makes between and around registered
methods, not methods (:data:`PLANNER_CHOICES`).

Adding a method (docs/ARCHITECTURE.md "Adding a propagation method"): one module defining and registering a
subclass, its module name in :data:`METHOD_MODULES`, one test file; differentiable through :mod:`torch_bridge`
with ``torch_path = "operator"`` and no other file. Lengths in mm.
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass, field as _field

import numpy as np

from ..sensor_grid import gauss_nodes_xy  # noqa: F401 (its home: sensor_grid; re-exported for the methods)

#: the modules (of this package) whose import registers the built-in methods; a new method adds its line
METHOD_MODULES = ("asm", "focal", "pixel", "direct")

#: the choices the planner makes between or around registered methods (not methods themselves)
PLANNER_CHOICES = ("auto", "two-step")

_REGISTRY: dict = {}
_loaded = False


@dataclass
class PlanContext:
    """What a method's :meth:`Propagation.plan` reads: the batch's pilot trace and the caller's request.

    ``lens``, ``plane`` (the wave plane's surface index), ``plan`` (the request: "auto", "paper" or a
    :class:`~rwwarp.wave.plan.Plan`); per source S: ``pos_p`` (S, R, 3) pilot rays on the plane, ``dir_s``
    (S, R, 3) their directions behind it, ``ok`` (S, R) the rays reaching the sensor, ``chief_plane`` /
    ``chief_dir`` (S, 3), ``n_after`` (S,) the index after the plane, ``lam_mm`` (S,) vacuum wavelengths (mm),
    ``wls`` (um); ``distance_mm`` plane to sensor; ``center_mm`` the caller's patch centres or None; ``size``
    (pixels a side), ``pixel`` (mm); the beam: ``width`` (mm, largest footprint side), ``pilot_cell`` (mm),
    ``lo`` / ``hi`` (S, 2) footprint corners, ``fmax`` (S,) its largest local frequency after the carrier
    (cycles/mm), ``f_doe`` / ``feature`` (the DOE's largest frequency, its feature size (mm) or None),
    ``out_width`` (mm, the patch); ``carrier`` (S, 2) cycles/mm and ``centers`` (S, 2) mm after the chief ray;
    the knobs ``rays_per_sample``, ``nyquist_safety``, ``patch_tol``, ``straight_edges`` (a square pupil),
    ``sampling_tol`` (the requested tolerance, or None);
    ``shared``: a dict the sources of one call share (per-lens and per-wavelength values a method computes once)
    or None."""
    lens: object
    plane: int
    plan: object
    pos_p: np.ndarray
    dir_s: np.ndarray
    ok: np.ndarray
    chief_plane: np.ndarray
    chief_dir: np.ndarray
    n_after: np.ndarray
    lam_mm: np.ndarray
    wls: list
    distance_mm: float
    center_mm: object
    size: int
    pixel: float
    width: float
    pilot_cell: float
    lo: np.ndarray
    hi: np.ndarray
    fmax: np.ndarray
    f_doe: object
    feature: object
    out_width: float
    carrier: np.ndarray
    centers: np.ndarray
    rays_per_sample: float
    nyquist_safety: float
    patch_tol: float = 1e-5
    straight_edges: bool = False
    #: the caller's tolerance (max |error| / peak) or None: the focal plan's sampling follows it
    #: (:func:`rwwarp.wave.plan.sampling_relax`)
    sampling_tol: float | None = None
    #: per-call constants a method may keep across the sources of one call (same lens and request), e.g. the DOE
    #: profile and its wavelength scale per wavelength (:func:`rwwarp.wave.plan_sources.plan_sources`); None: none
    shared: dict | None = None


@dataclass
class Planned:
    """A method's plan for a batch: the :class:`~rwwarp.wave.plan.Plan`, the carrier (S, 2) cycles/mm and patch
    centres (S, 2) mm it propagates with, the footprint corners ``lo`` / ``hi`` (S, 2) mm of its windows, and
    ``geo``: the method's own planned state (RayWave keeps it as ``rw.focal``; None if it has none)."""
    plan: object
    carrier: np.ndarray
    centers: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    geo: dict | None = None
    extra: dict = _field(default_factory=dict)


class Propagation:
    """A propagation method: the interface every registered method shares.

    Capability flags (class attributes; the callers read these, never the name):

    * ``forms_field``: the method propagates a splatted wave-plane field (False: it forms its own, ``pixel``).
    * ``torch_path``: the :mod:`torch_bridge` autograd path that differentiates it, ``"operator"`` (the generic
      one over :meth:`operator`: :func:`torch_bridge.operator_function.operator_propagate`, the DOE applied as
      ``exp(1j alpha phi0)`` first where ``doe_in_propagator`` is False or ``doe_separable`` True; the ASM's
      path) or ``"focal"`` (the DOE-orders factor, then the generic path over the focal operator), or None;
      ``differentiable``: it has one.
    * ``packable``: :class:`~rwwarp.wave.packed.PackedRayWave` may batch its members (one trace and splat).
    * ``doe_in_propagator``: the DOE phase ``phi0`` goes into the propagation with the field (the ASM's
      ``doe_phase``); False: the caller multiplies the field by the DOE-orders factor first (``focal``).
    * ``doe_separable``: its operator applies the planned DOE but leaves it out with ``operator(..., doe=False)``:
      :mod:`torch_bridge` then multiplies the field by ``exp(1j alpha phi0)`` itself, so the DOE phase is
      differentiated (``asm``).
    * ``spatial_tiles``: its operator evaluates a part of the patch, ``operator(..., tile=(r0, r1, c0, c1))`` (those
      pixel rows / columns, equal to the same pixels of the whole patch): :mod:`torch_bridge` propagates in spatial
      tiles to bound the output side's memory (``asm``).
    * ``per_source_distances``: its operator takes one distance per source (``distance_mm`` of shape (S,)), so the
      sources of a batch may be propagated over different distances (``asm``); else one distance for all.
    * ``fft_padded``: the plan's ``n_pad`` is a padded FFT the memory budget names.
    * ``rim_weighted``: the energy convention traces the circular pupil's rim cells by their part (``focal``).
    * ``per_source_plans``: its grids follow each source's patch: batches plan their sources alone (``focal``).
    * ``planned_beside``: planned at the end of the batch's planning beside the window plan (:meth:`consider`),
      where it is asked for or where "auto" may choose it (``allow_pixel``) (``pixel``).

    Methods: :meth:`plan` (its part of the batch's planning), :meth:`estimate` (peak memory and flops),
    :meth:`operator` (the linear map field -> complex field at the pixels' Gauss nodes, with ``forward``,
    ``adjoint``, ``distance_derivative``), :meth:`pixels` (the power per pixel for :meth:`RayWave.run`),
    :meth:`explain_grids` (its part of :meth:`~rwwarp.wave.plan.Plan.explain`) and :meth:`wave_step_sizes`
    (its grids when :mod:`rwwarp.wave.wave_step` refines the pitch)."""

    name = ""
    forms_field = True
    torch_path = None
    packable = True
    doe_in_propagator = True
    doe_separable = False
    spatial_tiles = False
    per_source_distances = False
    fft_padded = False
    rim_weighted = False
    per_source_plans = False
    planned_beside = False

    @property
    def differentiable(self) -> bool:
        """:mod:`torch_bridge` differentiates it (it names a ``torch_path``)."""
        return self.torch_path is not None

    def plan(self, ctx: PlanContext) -> Planned:
        """This method's :class:`Planned` for the batch described by ``ctx`` (:class:`PlanContext`)."""
        raise NotImplementedError(f"method {self.name!r} has no planner")

    def consider(self, rw, explicit: bool, pilot: dict, tolerance, memory_budget_bytes) -> bool:
        """(``planned_beside`` methods) Plan beside ``rw.plan`` (``rw``: the batch's
        :class:`~rwwarp.wave.batch_plan.BatchPlan` so far, not changed) and return ``(plan, switched)``: a plan switched
        to this method where it should run (always when ``explicit``, the method was asked for) and True, else a plan
        with a reason why not and False. ``pilot``: ``pos_s``,
        ``dir_s``, ``ok`` (the pilot rays at the sensor), ``carrier`` / ``centers`` (the chief rays'),
        ``beam_width_mm`` (the footprint's smaller side), ``rays_per_sample``; ``tolerance``: the model error
        accepted (of the PSF's peak) or None."""
        raise NotImplementedError(f"method {self.name!r} is not planned beside another")

    def estimate(self, plan, n_sources: int, size: int, gauss_nodes: int) -> dict:
        """``{"memory_bytes": int, "flops": float}``: the batch's peak memory (bytes) and work."""
        raise NotImplementedError(f"method {self.name!r} has no cost estimate")

    def operator(self, rw, distance_mm=None, precision: str = "double"):
        """The linear operator of the planned propagation of ``rw`` over ``distance_mm`` (mm; default the
        lens's): an object with ``forward(field)`` (wave-plane field (S, n, n), carrier removed, DOE applied as
        the method does -> complex field (S, My, Mx) at the pixels' Gauss nodes, up to a constant phase per
        source), ``adjoint(grad)`` (its conjugate transpose) and ``distance_derivative(field)`` (d forward / dz,
        per mm), in the array namespace of ``rw``'s device (numpy on the CPU and OpenCL, CuPy on CUDA); for
        ``pixel_values="flux"`` also ``forward_pair`` / ``adjoint_pair`` / ``distance_derivative_pair`` (the field
        and its direction-cosine-weighted field ``U_w``). :mod:`torch_bridge` differentiates any method through
        it (``torch_path = "operator"``)."""
        raise NotImplementedError(f"method {self.name!r} has no linear operator")

    def pixels(self, rw, field, precision: str = "double", to_host: bool = True):
        """Power per sensor pixel (S, size, size), numpy, not yet divided by the entering power, of the
        wave-plane field ``field`` ((S, n, n) of :meth:`RayWave.field_array`; None when not ``forms_field``).
        ``to_host=False``: the device array may be returned as it is (CuPy on CUDA; no copy, no wait:
        :mod:`rwwarp.wave.graph_replay` propagates a replayed field so)."""
        raise NotImplementedError(f"method {self.name!r} computes no pixels")

    def explain_grids(self, plan) -> str:
        """The grid part of :meth:`Plan.explain`'s first line."""
        return f"pitch {plan.pitch_mm * 1e3:.4g} um, grid {plan.n_grid}^2, "

    def wave_step_sizes(self, plan, rw, pitch: float, extra: int):
        """``(ray_grid, n_pad)`` of ``plan`` when the wave step refines its pitch to ``pitch`` (mm) and widens
        its window by ``extra`` samples a side: by default rays per sample are kept and a padded FFT grows
        with the window."""
        import math
        from ..propagate_setup import next_fft_size   # = plan.nice_fft_length (the registry sits below plan)
        ray_grid = max(plan.ray_grid, int(math.ceil(plan.ray_grid * plan.pitch_mm / pitch)))
        n_pad = plan.n_pad if not self.fft_padded else next_fft_size(max(plan.n_pad, int(math.ceil(
            plan.n_pad * plan.pitch_mm / pitch)) + 2 * extra))
        return ray_grid, n_pad


def register(cls):
    """Register a :class:`Propagation` subclass under its ``name`` (usable as a class decorator); a name
    registered again is replaced (a test's toy method). Returns ``cls``."""
    if not (isinstance(cls, type) and issubclass(cls, Propagation)):
        raise TypeError(f"register: {cls!r} is not a Propagation subclass")
    if not isinstance(cls.name, str) or not cls.name or cls.name in PLANNER_CHOICES:
        raise ValueError(f"register: {cls.__name__}.name must be a non-empty string other than "
                         f"{', '.join(PLANNER_CHOICES)}, got {cls.name!r}")
    _REGISTRY[cls.name] = cls()
    return cls


def unregister(name: str) -> None:
    """Remove a registered method (a test's toy method); unknown names are ignored."""
    _REGISTRY.pop(name, None)


def _load():
    global _loaded
    if not _loaded:
        _loaded = True
        for mod in METHOD_MODULES:
            importlib.import_module(f"{__package__}.{mod}")


def names() -> tuple:
    """The registered methods' names (the built-in ones first, in :data:`METHOD_MODULES` order)."""
    _load()
    return tuple(_REGISTRY)


def get(name) -> Propagation:
    """The registered method ``name``; a clear :class:`ValueError` naming the registered ones otherwise."""
    _load()
    try:
        return _REGISTRY[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown propagation method {name!r}: registered are {', '.join(map(repr, _REGISTRY))}"
                         f" (and the planner's choices {', '.join(map(repr, PLANNER_CHOICES))})") from None


def choices(*, differentiable: bool = False) -> tuple:
    """The values a ``method=`` argument accepts: the planner's choices and the registered methods
    (``differentiable``: only those :mod:`torch_bridge` differentiates)."""
    return PLANNER_CHOICES + tuple(n for n in names() if not differentiable or get(n).differentiable)


def check_method(method, where: str, *, differentiable: bool = False) -> str:
    """``method`` if :func:`choices` holds it, else a :class:`ValueError` naming ``where`` and the choices."""
    ok = choices(differentiable=differentiable)
    if not isinstance(method, str) or method not in ok:
        raise ValueError(f"{where}: method must be one of {', '.join(map(repr, ok))}, got {method!r}")
    return method
