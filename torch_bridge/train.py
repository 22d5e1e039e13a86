"""End-to-end hybrid lens design: joint optimisation of lens, DOE and reconstruction network.

``train(config)`` runs an experiment (one or more *arms*, each a lens design method followed by
network training and evaluation) and writes its table; ``main(argv)`` is the ``rwwarp design
CONFIG`` command line. A config is a YAML or TOML file (or a dict) validated before anything
runs (:func:`load_config`); errors name the key (``arms[1].train.lr_network``) and the file.

Per arm:

1. **Design stage** (``design.method``): ``fixed`` (the lens as loaded, e.g. a blank DOE),
   ``paraxial_achromat`` (analytic Fresnel-phase DOE and refocus, :func:`design.paraxial_achromat`),
   ``rms`` (the "Zemax" arm: the learning quantities minimise the polychromatic RMS spot radius of
   the ray model, :class:`design.RaySpot`), or ``e2e`` (the optics learn with the network below).
   ``design.init`` may first set the DOE to the paraxial achromat (``paraxial_achromat``) or run the
   RMS-spot design from it (``rms``: an e2e design that starts where the "Zemax" arm ends).
2. **Joint phase** (``train.joint_steps``): each step draws image crops and, per colour channel, one
   of its wavelengths (and one depth); computes the RGB PSFs of the nodes (ray-wave, or the
   paraxial-wave model), converts them to float32 (:class:`MixedPrecision`), blurs the crops,
   reconstructs them with the NAFNet and minimises ``MSE + alpha * perceptual``; the optics
   (``e2e`` only) and the network have their own Adam optimisers and learning rates.
3. **Fine-tune phase** (``train.finetune_steps``): the optics are frozen; the network is trained on
   images with sensor noise (``train.noise``).
4. **Evaluation**: ray-wave PSFs with the three wavelengths of each channel averaged, fixed
   validation crops with seeded noise, PSNR / SSIM / 1-LPIPS of the raw and reconstructed images
   per depth and node; the ray-model RMS spot radius on axis, at the outer node and averaged.

Fabrication limit (``optics.min_feature_um``, default none): after every optics update the DOE is
scaled onto its smallest allowed feature (the narrowest quantisation step over the aperture,
:meth:`HybridLens.limit_doe_feature`; counted in ``result.json`` as ``feature_projections``), and
cached plans sample that limit, so a DOE growing up to it never forces a replan.

Rendering (``render.mode``): ``patch`` (each crop is a patch of the sensor at one PSF node,
blurred by that node's PSF at the native pixel pitch: cheap, and the blur has its real size) or
``full`` (the crop covers the node grid's region and is blurred with a spatially varying PSF,
:func:`torch_bridge.imaging.spatially_varying_blur`).

Outputs in ``out_dir/<arm>/``: ``metrics.csv`` (one row per logged step), ``step_XXXXXX.png``
(PSF map, DOE phase, raw and reconstructed crops), ``checkpoint.pt`` (everything needed to resume:
step, optics and network weights, optimiser states, every RNG state, the cached sampling plans),
``lens.json`` (the designed lens), ``network.pt``, ``result.json``; in ``out_dir``: ``table.md``,
``table.csv``, ``summary.json`` and ``designs.png``.
Resuming (the default when a checkpoint exists) continues exactly where the run stopped: the next
step is the same as in an uninterrupted run.
"""
from __future__ import annotations

import argparse
import copy
import csv
import json
import math
import random
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch

__all__ = [
    "DEFAULTS",
    "ConfigError",
    "load_config",
    "main",
    "resolve_config",
    "train",
    "train_arm",
    "validate_config",
]

CONFIG_DIR = Path(__file__).resolve().parent / "configs"


class ConfigError(ValueError):
    """A design config is invalid; the message names the key and the file."""


# ============================================================================================== schema
class _Spec:
    """A leaf of the config schema: a check function with a description of what is allowed."""

    def __init__(self, check, what):
        self.check, self.what = check, what


def _num(lo=None, hi=None, lo_open=False, integer=False, none=False):
    def check(v):
        if v is None:
            return none
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            return False
        if integer and not float(v).is_integer():
            return False
        if not math.isfinite(float(v)):
            return False
        if lo is not None and (v <= lo if lo_open else v < lo):
            return False
        return hi is None or v <= hi
    rng = []
    if lo is not None:
        rng.append(f"{'>' if lo_open else '>='} {lo}")
    if hi is not None:
        rng.append(f"<= {hi}")
    what = ("an integer" if integer else "a number") + (" " + " and ".join(rng) if rng else "") + \
           (" or null" if none else "")
    return _Spec(check, what)


def _choice(*opts, none=False):
    return _Spec(lambda v: (v is None and none) or v in opts,
                 "one of " + ", ".join(repr(o) for o in opts) + (" or null" if none else ""))


def _str(none=False):
    return _Spec(lambda v: (v is None and none) or isinstance(v, str), "a string" + (" or null" if none else ""))


def _bool():
    return _Spec(lambda v: isinstance(v, bool), "true or false")


def _depth(v):
    return v is None or v == "inf" or (isinstance(v, (int, float)) and not isinstance(v, bool) and v > 0)


def _list(item: _Spec, min_len=0, max_len=None, none=False, what=None):
    def check(v):
        if v is None:
            return none
        if not isinstance(v, (list, tuple)) or len(v) < min_len or (max_len is not None and len(v) > max_len):
            return False
        return all(item.check(x) for x in v)
    n = f"{min_len}" if max_len == min_len else f"{min_len}..{max_len if max_len is not None else ''}"
    return _Spec(check, what or f"a list of {n} items, each {item.what}" + (" or null" if none else ""))


def _learn_entry(v):
    return v == "all" or (isinstance(v, list) and all(isinstance(e, int) or (isinstance(e, list) and len(e) == 2 and
                                                                              all(isinstance(x, int) for x in e))
                                                      for e in v))


_LEARN = {q: _Spec(_learn_entry, "'all' or a list of indices") for q in
          ("curvature", "thickness", "conic", "aspheric", "doe")}
_LR = {q: _num(0, lo_open=False) for q in ("curvature", "thickness", "conic", "aspheric", "doe")}
_WLS = _Spec(lambda v: isinstance(v, list) and len(v) >= 1 and all(
    isinstance(c, list) and len(c) >= 1 and all(isinstance(w, (int, float)) and not isinstance(w, bool) and
                                               0.2 < w < 2.0 for w in c) for c in v),
    "a list of colour channels, each a list of wavelengths in um (0.2 .. 2.0)")
_NOISE = {"read_std": _num(0), "photons": _num(0, lo_open=True, none=True)}

SCHEMA = {
    "experiment": _str(),
    "description": _str(none=True),
    "seed": _num(0, integer=True),
    "device": _Spec(lambda v: isinstance(v, str) and (v == "cpu" or v.startswith("cuda")), "'cpu' or 'cuda[:N]'"),
    "out_dir": _str(none=True),
    "lens": {
        "file": _str(),
        "entrance_pupil_diameter": _num(0, lo_open=True, none=True),
        "f_number": _num(0, lo_open=True, none=True),
        "doe_levels": _num(2, integer=True, none=True),
        "doe_profile": _Spec(lambda v: v is None or isinstance(v, dict), "a DOE profile mapping or null"),
        "doe_distance_mm": _num(0, lo_open=True, none=True),
        "focus_mm": _Spec(lambda v: v is None or _depth(v), "an object distance in mm (> 0), 'inf' or null"),
        "object_distance_mm": _Spec(lambda v: v is None or _depth(v), "an object distance in mm (> 0), 'inf' or null"),
    },
    "optics": {
        "model": _choice("ray-wave", "paraxial-wave"),
        "cache_fields": _choice("auto", True, False),
        "learn": _LEARN,
        "psf_size": _num(3, integer=True),
        "pixel_um": _num(0, lo_open=True, none=True),
        "nodes": {
            "layout": _choice("grid", "diagonal"),
            "grid": _list(_num(1, integer=True), 2, 2),
            "fractions": _list(_num(0, 1), 1),
            "region": _choice("quadrant", "full"),
            "half_size_mm": _num(0, lo_open=True, none=True),
        },
        "wavelengths_um": _WLS,
        "depths_mm": _list(_Spec(_depth, "a depth in mm (> 0), 'inf' or null"), 1),
        "nyquist_safety": _num(0.5),
        "rays_per_sample": _num(0.5),
        "doe_budget_cpmm": _num(0),
        "min_feature_um": _num(0, lo_open=True, none=True),
        "check_sampling_every": _num(0, integer=True),
        "memory_budget_gb": _num(0, lo_open=True, none=True),
    },
    "render": {
        "mode": _choice("patch", "full"),
        "boundary": _choice("reflect", "replicate", "zero"),
    },
    "data": {
        "root": _str(none=True),
        "crop": _num(16, integer=True),
        "scale": _num(0, lo_open=True),
        "batch_size": _num(1, integer=True),
        "eval_images": _num(1, integer=True),
        "max_images": _num(1, integer=True, none=True),
        "linearize": _bool(),
    },
    "network": {
        "preset": _choice("tiny", "small", "paper"),
        "width": _num(1, integer=True, none=True),
        "enc_blocks": _list(_num(0, integer=True), 1, none=True),
        "middle_blocks": _num(0, integer=True, none=True),
        "dec_blocks": _list(_num(0, integer=True), 1, none=True),
        "zero_init": _bool(),
    },
    "loss": {
        "alpha": _num(0),
        "perceptual": _choice("vgg", "ssim", "gradient", "none"),
        "fallback": _choice("ssim", "gradient", "none"),
        "fallback_alpha": _num(0, none=True),
        "vgg_weights": _str(none=True),
        "lpips_weights": _str(none=True),
    },
    "train": {
        "joint_steps": _num(0, integer=True),
        "finetune_steps": _num(0, integer=True),
        "lr_network": _num(0, lo_open=True),
        "lr_optics": _LR,
        "lr_decay": _choice("cosine", "none"),
        "optics_every": _num(1, integer=True),
        "noise": _NOISE,
        "noise_in_joint": _bool(),
        "grad_clip": _num(0, lo_open=True, none=True),
        "log_every": _num(1, integer=True),
        "image_every": _num(0, integer=True),
        "checkpoint_every": _num(0, integer=True),
        "stop_after": _num(0, integer=True, none=True),
    },
    "design": {
        "method": _choice("fixed", "paraxial_achromat", "rms", "e2e"),
        "init": _choice("paraxial_achromat", "rms", none=True),
        "efl_mm": _num(0, lo_open=True, none=True),
        "efl_weight": _num(0),
        "rms": {
            "steps": _num(0, integer=True),
            "grid": _num(3, integer=True),
            "lr": _LR,
            "wavelengths_um": _list(_num(0.2, 2.0), 1, none=True),
        },
    },
    "eval": {
        "depths_mm": _list(_Spec(_depth, "a depth in mm (> 0), 'inf' or null"), 1, none=True),
        "noise": _NOISE,
        "seed": _num(0, integer=True),
        "rms_fractions": _list(_num(0, 1), 1),
        "rms_grid": _num(3, integer=True),
        "batch_size": _num(1, integer=True),
    },
    "progress": _bool(),
}

DEFAULTS = {
    "experiment": "design", "description": None, "seed": 0, "device": "cpu", "out_dir": None,
    "lens": {"file": "a489_doe", "entrance_pupil_diameter": None, "f_number": None, "doe_levels": None,
             "doe_profile": None, "doe_distance_mm": None, "focus_mm": None, "object_distance_mm": None},
    "optics": {"model": "ray-wave", "cache_fields": "auto", "learn": {"doe": "all"}, "psf_size": 31,
               "pixel_um": None,
               "nodes": {"layout": "grid", "grid": [2, 2], "fractions": [0.0, 0.5, 0.9], "region": "quadrant",
                         "half_size_mm": None},
               "wavelengths_um": [[0.60, 0.63, 0.66], [0.52, 0.55, 0.58], [0.45, 0.47, 0.49]],
               "depths_mm": [None], "nyquist_safety": 1.0, "rays_per_sample": 1.2, "doe_budget_cpmm": 0.0,
               "min_feature_um": None,
               "check_sampling_every": 10, "memory_budget_gb": None},
    "render": {"mode": "patch", "boundary": "reflect"},
    "data": {"root": None, "crop": 64, "scale": 1.0, "batch_size": 4, "eval_images": 8, "max_images": None,
             "linearize": False},
    "network": {"preset": "tiny", "width": None, "enc_blocks": None, "middle_blocks": None, "dec_blocks": None,
                "zero_init": True},
    "loss": {"alpha": 0.1, "perceptual": "vgg", "fallback": "ssim", "fallback_alpha": 0.01, "vgg_weights": None,
             "lpips_weights": None},
    "train": {"joint_steps": 100, "finetune_steps": 50, "lr_network": 1e-3, "lr_optics": {"doe": 0.5},
              "lr_decay": "cosine", "optics_every": 1, "noise": {"read_std": 0.01, "photons": None},
              "noise_in_joint": False, "grad_clip": 1.0, "log_every": 5, "image_every": 50,
              "checkpoint_every": 25, "stop_after": None},
    "design": {"method": "e2e", "init": None, "efl_mm": None, "efl_weight": 0.0,
               "rms": {"steps": 100, "grid": 31, "lr": {"doe": 1.0}, "wavelengths_um": None}},
    "eval": {"depths_mm": None, "noise": {"read_std": 0.01, "photons": None}, "seed": 1234,
             "rms_fractions": [0.0, 0.25, 0.5, 0.75, 0.9], "rms_grid": 41, "batch_size": 8},
    "progress": True,
}

_TOP_ONLY = {"presets", "arms"}


def _check(cfg: dict, schema: dict, where: str, path: str = ""):
    for k, v in cfg.items():
        key = f"{path}{k}"
        if k not in schema:
            near = [s for s in schema if s.lower().replace("_", "") == str(k).lower().replace("_", "")]
            hint = f" (did you mean {near[0]!r}?)" if near else f" (allowed: {', '.join(sorted(schema))})"
            raise ConfigError(f"{where}: unknown key '{key}'{hint}")
        spec = schema[k]
        if isinstance(spec, dict):
            if not isinstance(v, dict):
                raise ConfigError(f"{where}: '{key}' must be a mapping, got {v!r}")
            _check(v, spec, where, key + ".")
        elif not spec.check(v):
            raise ConfigError(f"{where}: '{key}' must be {spec.what}, got {v!r}")


def _merge(base: dict, over: dict) -> dict:
    out = copy.deepcopy(base)
    for k, v in (over or {}).items():
        if isinstance(v, dict) and isinstance(out.get(k), dict) and k not in ("learn", "lr", "lr_optics",
                                                                               "doe_profile"):
            out[k] = _merge(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


def _read(path: Path) -> dict:
    if not path.is_file():
        raise ConfigError(f"config file {path} does not exist")
    text = path.read_text()
    try:
        if path.suffix.lower() == ".toml":
            import tomllib
            data = tomllib.loads(text)
        else:
            import yaml
            data = yaml.safe_load(text)
    except Exception as e:
        raise ConfigError(f"{path}: cannot parse ({e})") from e
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: the top level must be a mapping")
    return data


def load_config(source, preset: str | None = None) -> dict:
    """Read (YAML ``.yaml``/``.yml`` or TOML ``.toml``) or take a dict, apply ``preset`` (a key of its
    ``presets`` section), validate every arm and return the resolved experiment::

        {"experiment": ..., "base": <merged config>, "arms": [{"name": ..., "config": <merged>}, ...],
         "source": path or None, "preset": preset}

    Raises :class:`ConfigError` naming the key and the file for unknown keys, wrong types,
    impossible values, a missing preset, a lens file that cannot be read, or learning quantities
    that the lens or the chosen model cannot learn. Nothing is trained before this passes.
    """
    if isinstance(source, dict):
        raw, where, path = copy.deepcopy(source), "config", None
    else:
        path = Path(source)
        if not path.exists() and (CONFIG_DIR / path).exists():
            path = CONFIG_DIR / path
        if not path.exists() and (CONFIG_DIR / (str(source) + ".yaml")).exists():
            path = CONFIG_DIR / (str(source) + ".yaml")
        raw, where = _read(path), str(path)
    presets = raw.pop("presets", {}) or {}
    arms = raw.pop("arms", None)
    if not isinstance(presets, dict):
        raise ConfigError(f"{where}: 'presets' must be a mapping of name -> overrides")
    _check(raw, SCHEMA, where)
    base = _merge(DEFAULTS, raw)
    if preset is not None:
        if preset not in presets:
            raise ConfigError(f"{where}: unknown preset {preset!r} (available: {', '.join(sorted(presets)) or 'none'})")
        over = presets[preset] or {}
        if not isinstance(over, dict):
            raise ConfigError(f"{where}: 'presets.{preset}' must be a mapping")
        over = dict(over)
        arm_over = over.pop("arms", None)
        _check(over, SCHEMA, f"{where} [presets.{preset}]")
        base = _merge(base, over)
    else:
        arm_over = None
    if arms is None:
        arms = [{"name": base["design"]["method"]}]
    if not isinstance(arms, list) or not arms:
        raise ConfigError(f"{where}: 'arms' must be a non-empty list")
    out_arms = []
    names = set()
    for i, a in enumerate(arms):
        if not isinstance(a, dict) or "name" not in a or not isinstance(a["name"], str):
            raise ConfigError(f"{where}: 'arms[{i}]' must be a mapping with a 'name'")
        a = dict(a)
        name = a.pop("name")
        if name in names or not name.replace("_", "").replace("-", "").isalnum():
            raise ConfigError(f"{where}: 'arms[{i}].name' {name!r} must be unique and alphanumeric (_ and - allowed)")
        names.add(name)
        _check(a, SCHEMA, f"{where} [arms[{i}] {name}]")
        cfg = _merge(base, a)
        if arm_over and name in arm_over:
            _check(arm_over[name], SCHEMA, f"{where} [presets.{preset}.arms.{name}]")
            cfg = _merge(cfg, arm_over[name])
        _semantic(cfg, f"{where} [arms[{i}] {name}]", path)
        out_arms.append({"name": name, "config": cfg})
    if arm_over:
        unknown = set(arm_over) - names
        if unknown:
            raise ConfigError(f"{where}: 'presets.{preset}.arms' names unknown arms {sorted(unknown)}")
    return {"experiment": base["experiment"], "base": base, "arms": out_arms, "source": None if path is None
            else str(path), "preset": preset}


def validate_config(source, preset: str | None = None) -> dict:
    """Same as :func:`load_config` (the name says what it is for)."""
    return load_config(source, preset)


def _lens_path(cfg, source):
    f = cfg["lens"]["file"]
    p = Path(f)
    if not p.is_absolute():
        for base in ([Path(source).parent] if source else []) + [CONFIG_DIR, Path.cwd()]:
            if (base / p).exists():
                return base / p
    return p if p.exists() else f


def _semantic(cfg: dict, where: str, source):
    """Checks that need the lens or several keys together."""
    from rwwarp.errors import LensError
    try:
        lens = build_lens(cfg, source)
    except (LensError, OSError, ValueError) as e:
        raise ConfigError(f"{where}: 'lens' cannot be built: {e}") from e
    if lens.doe_index is None:
        raise ConfigError(f"{where}: 'lens.file' has no DOE surface (end-to-end design needs one)")
    ns = len(lens.surfaces)
    learn = cfg["optics"]["learn"]
    for q, spec in learn.items():
        if isinstance(spec, list):
            for e in spec:
                i = e[0] if isinstance(e, list) else e
                lim = len(lens.surfaces[lens.doe_index].profile.get("coefficients", [])) if q == "doe" else ns
                if not 0 <= i < lim:
                    raise ConfigError(f"{where}: 'optics.learn.{q}' index {i} is outside 0..{lim - 1}")
                if q in ("curvature", "conic", "aspheric") and lens.surfaces[i].type != "standard":
                    raise ConfigError(f"{where}: 'optics.learn.{q}' index {i} is not a refracting ('standard') surface")
    refr = [q for q in learn if q != "doe"]
    method = cfg["design"]["method"]
    live = method in ("e2e", "rms") and _refractive_learns(_learn_dict(learn), lens)
    if cfg["optics"]["model"] == "paraxial-wave" and live:
        raise ConfigError(f"{where}: 'optics.model' paraxial-wave keeps the refractive part frozen; "
                          f"'optics.learn' may only hold 'doe' and the DOE-to-sensor thickness (got {sorted(learn)})")
    if cfg["optics"]["cache_fields"] is True and live:
        raise ConfigError(f"{where}: 'optics.cache_fields' true needs a frozen refractive part, but "
                          f"'optics.learn' has {sorted(refr)}")
    if method == "rms":
        kind = lens.surfaces[lens.doe_index].profile.get("kind")
        if kind not in ("even_poly", "poly"):
            raise ConfigError(f"{where}: 'design.method' rms needs an even_poly or poly DOE, got {kind!r}")
    if cfg["design"]["init"] == "rms" and method not in ("e2e", "rms"):
        raise ConfigError(f"{where}: 'design.init' rms needs 'design.method' e2e (the optics learn after it)")
    # every learning quantity needs its learning rate (checked here, not when the arm reaches it)
    if method == "rms" or cfg["design"]["init"] == "rms":
        missing = sorted(q for q in learn if q not in cfg["design"]["rms"]["lr"])
        if missing:
            raise ConfigError(f"{where}: 'design.rms.lr' has no learning rate for {missing} ('optics.learn')")
    if method == "e2e":
        missing = sorted(q for q in learn if q not in cfg["train"]["lr_optics"])
        if missing:
            raise ConfigError(f"{where}: 'train.lr_optics' has no learning rate for {missing} ('optics.learn')")
    if cfg["design"]["init"] in ("paraxial_achromat", "rms") or method == "paraxial_achromat":
        kind = lens.surfaces[lens.doe_index].profile.get("kind")
        if kind not in ("even_poly", "poly"):
            raise ConfigError(f"{where}: 'design.method' paraxial_achromat needs an even_poly or poly DOE")
    if cfg["render"]["mode"] == "patch" and cfg["data"]["crop"] < cfg["optics"]["psf_size"] // 2:
        raise ConfigError(f"{where}: 'data.crop' {cfg['data']['crop']} is smaller than half of "
                          f"'optics.psf_size' {cfg['optics']['psf_size']}")
    if cfg["optics"]["psf_size"] % 2 == 0:
        raise ConfigError(f"{where}: 'optics.psf_size' must be odd (the PSF centre is a pixel), got "
                          f"{cfg['optics']['psf_size']}")
    for w in cfg["optics"]["wavelengths_um"]:
        if len(w) != len(cfg["optics"]["wavelengths_um"][0]):
            raise ConfigError(f"{where}: 'optics.wavelengths_um' channels need the same number of wavelengths")
    if len(cfg["optics"]["wavelengths_um"]) != 3:
        raise ConfigError(f"{where}: 'optics.wavelengths_um' needs 3 colour channels (R, G, B), got "
                          f"{len(cfg['optics']['wavelengths_um'])}")
    if cfg["loss"]["vgg_weights"] and not Path(cfg["loss"]["vgg_weights"]).is_file():
        warnings.warn(f"{where}: 'loss.vgg_weights' {cfg['loss']['vgg_weights']} does not exist; the perceptual "
                      f"loss will fall back to '{cfg['loss']['fallback']}'", UserWarning, stacklevel=3)
    if cfg["train"]["joint_steps"] + cfg["train"]["finetune_steps"] == 0 and method == "e2e":
        raise ConfigError(f"{where}: 'train.joint_steps' is 0: an e2e design needs joint steps")


def _refractive_learns(learn: dict, lens) -> bool:
    """True when a learning quantity changes the field on the DOE plane (anything but the DOE and the
    DOE-to-sensor distance): then the DOE-plane fields cannot be cached."""
    plane = lens.doe_index
    for q, spec in learn.items():
        if q == "doe":
            continue
        if q == "thickness":
            idx = range(len(lens.surfaces)) if spec == "all" else [int(e) for e in spec]
            if any(i < plane for i in idx):
                return True
            continue
        return True
    return False


def _budget_bytes(optics: dict):
    """``optics.memory_budget_gb`` in bytes (1 GB = 1e9 bytes), None when unset (the device default)."""
    gb = optics.get("memory_budget_gb")
    return None if not gb else int(float(gb) * 1e9)


def _depth_value(v):
    return math.inf if v == "inf" else (None if v is None else float(v))


def build_lens(cfg: dict, source=None):
    """The lens of a config: ``lens.file`` (relative to the config file, the configs folder, or a
    bundled name) with the overrides of the ``lens`` section applied:

    * ``entrance_pupil_diameter`` / ``f_number`` (mm / EFL over EPD at 0.55 um): a floating stop of
      that diameter (or, for a lens with an aperture surface as stop, its semi-diameter scaled);
    * ``doe_profile`` (a DOE profile mapping), ``doe_levels`` (quantisation levels);
    * ``doe_distance_mm``: the DOE moved to this distance in front of the sensor (the surface before
      it shortened, the sensor kept);
    * ``object_distance_mm``: the lens's object distance;
    * ``focus_mm``: the sensor moved to the paraxial focus (0.55 um) of an object at this distance.
    """
    import rwwarp as rw
    from rwwarp import paraxial
    p = _lens_path(cfg, source)
    lens = rw.load_lens(p)
    L = cfg["lens"]
    d = lens.doe_index
    if L.get("object_distance_mm") is not None:
        lens = lens.replace(object_distance=_depth_value(L["object_distance_mm"]))
    if d is not None and L.get("doe_profile") is not None:
        lens = lens.with_surface(d, profile=dict(L["doe_profile"]))
    if d is not None and L.get("doe_levels") is not None:
        lens = lens.with_surface(d, levels=int(L["doe_levels"]))
    if d is not None and L.get("doe_distance_mm") is not None:
        if d == 0:
            raise ValueError("the DOE is the first surface: it cannot be moved")
        total = lens.surfaces[d - 1].thickness + lens.surfaces[d].thickness
        new = float(L["doe_distance_mm"])
        if new >= total:
            raise ValueError(f"lens.doe_distance_mm {new} is not inside the gap of {total:.4g} mm before the sensor")
        lens = lens.with_surface(d - 1, thickness=total - new).with_surface(d, thickness=new)
    epd = L.get("entrance_pupil_diameter")
    if L.get("f_number") is not None:
        epd = lens.efl(0.55) / float(L["f_number"])
    if epd is not None:
        stop = lens.stop_index
        s = lens.surfaces[stop]
        if lens.entrance_pupil_diameter is not None or s.type != "aperture":
            lens = lens.replace(entrance_pupil_diameter=float(epd))
        else:
            cur = paraxial.pupils(lens, 0.55).entrance_radius * 2.0
            lens = lens.with_surface(stop, semi_diameter=s.semi_diameter * float(epd) / cur)
    if L.get("focus_mm") is not None:
        u = _depth_value(L["focus_mm"])
        last = len(lens.surfaces) - 1
        if math.isinf(u):
            lens = lens.with_surface(last, thickness=lens.bfl(0.55))
        else:
            slope = 1e-3
            ys, nus = paraxial.ynu_trace(lens, 0.55, u * slope, slope)
            n = lens.indices(0.55)[-1]
            lens = lens.with_surface(last, thickness=float(-ys[-1] * n / nus[-1]))
    return lens


def resolve_config(source, preset=None) -> dict:
    """Alias of :func:`load_config`."""
    return load_config(source, preset)


# ============================================================================================== helpers
def _seed_all(seed: int):
    random.seed(seed)
    np.random.seed(seed % (2 ** 32))
    torch.manual_seed(seed)


def _rng_state(gen):
    return {"python": random.getstate(), "numpy": np.random.get_state(), "torch": torch.get_rng_state(),
            "gen": gen.get_state(), "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None}


def _set_rng_state(st, gen):
    random.setstate(st["python"])
    np.random.set_state(st["numpy"])
    torch.set_rng_state(st["torch"])
    gen.set_state(st["gen"])
    if st.get("cuda") is not None and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(st["cuda"])


def _lr_factor(kind, step, total):
    if kind == "none" or total <= 1:
        return 1.0
    return 0.5 * (1.0 + math.cos(math.pi * min(step, total) / total)) * 0.9 + 0.1


def _learn_dict(learn: dict) -> dict:
    out = {}
    for q, spec in learn.items():
        out[q] = "all" if spec == "all" else [tuple(e) if isinstance(e, list) else int(e) for e in spec]
    return out


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


# ============================================================================================== one arm
class Arm:
    """State of one arm (lens module, provider, network, optimisers) built from a resolved config."""

    def __init__(self, name: str, cfg: dict, source, out_dir: Path, progress: bool = True):
        import torch_bridge as tb
        from torch_bridge import design as dz
        from torch_bridge.data import ImageSet
        from torch_bridge.losses import LPIPS, ReconstructionLoss
        from torch_bridge.network import build_network
        self.name, self.cfg, self.out = name, cfg, out_dir
        self.progress = progress and cfg["progress"]
        self.device = torch.device(cfg["device"])
        o = cfg["optics"]
        self.lens0 = build_lens(cfg, source)
        method = cfg["design"]["method"]
        self.method = method
        learn = _learn_dict(o["learn"]) if method in ("e2e", "rms") else {}
        self.learn = learn
        self.live = _refractive_learns(learn, self.lens0)
        lens = self.lens0
        if cfg["design"]["init"] in ("paraxial_achromat", "rms") or method == "paraxial_achromat":
            lens = self._achromat(lens)
        self.lens_init = lens
        self.module = tb.HybridLens(lens, learn=learn, nyquist_safety=o["nyquist_safety"],
                                    rays_per_sample=o["rays_per_sample"]).to(self.device)
        self.pixel_mm = (o["pixel_um"] * 1e-3) if o["pixel_um"] else lens.sensor.pixel_pitch
        self.size = int(o["psf_size"])
        self.wls = [[float(w) for w in c] for c in o["wavelengths_um"]]
        self.wl_ref = self.wls[len(self.wls) // 2][len(self.wls[0]) // 2]
        self.depths = [_depth_value(d) for d in o["depths_mm"]]
        nd = o["nodes"]
        half = nd["half_size_mm"] or [0.5 * lens.sensor.resolution[0] * lens.sensor.pixel_pitch,
                                      0.5 * lens.sensor.resolution[1] * lens.sensor.pixel_pitch]
        if cfg["render"]["mode"] == "full":
            from torch_bridge.imaging import node_positions
            H = W = cfg["data"]["crop"]
            gy, gx = nd["grid"]
            cy, cx = (H / 2.0, W / 2.0) if nd["region"] == "full" else (float(H), 0.0)
            self.positions = [((c + 0.5 - cx) * self.pixel_mm, (cy - r - 0.5) * self.pixel_mm)
                              for r in node_positions(gy, H) for c in node_positions(gx, W)]
            self.grid = (gy, gx)
        else:
            self.positions = dz.node_positions_mm(nd["layout"], half, nd["grid"], nd["fractions"], nd["region"])
            self.grid = None
        self.fields = dz.field_angles(lens, self.positions, self.wl_ref)
        self.provider = self._provider(o["model"])
        # data, network, losses
        d = cfg["data"]
        self.train_set = ImageSet(d["root"], "train", d["crop"], d["scale"], d["max_images"], d["linearize"])
        self.valid_set = ImageSet(d["root"], "valid", d["crop"], d["scale"], d["max_images"], d["linearize"])
        n = cfg["network"]
        self.net = build_network(n["preset"], 3, width=n["width"], enc_blocks=n["enc_blocks"],
                                 middle_blocks=n["middle_blocks"], dec_blocks=n["dec_blocks"],
                                 zero_init=n["zero_init"]).to(self.device)
        lo = cfg["loss"]
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            self.criterion = ReconstructionLoss(lo["alpha"], lo["perceptual"], lo["vgg_weights"], lo["fallback"],
                                                lo["fallback_alpha"])
        self.notes = [str(w.message) for w in caught]
        if self.criterion.perceptual.active_kind != lo["perceptual"]:
            self.notes.append(f"perceptual term: {self.criterion.perceptual.active_kind} with weight "
                              f"{self.criterion.alpha:g} (loss.fallback_alpha)")
        for w in caught:
            warnings.warn(w.message, UserWarning, stacklevel=2)
        self.criterion.to(self.device)
        self.lpips = None
        if lo["lpips_weights"] and lo["vgg_weights"] and Path(lo["lpips_weights"]).is_file() \
                and Path(lo["vgg_weights"]).is_file():
            self.lpips = LPIPS(lo["vgg_weights"], lo["lpips_weights"])
        t = cfg["train"]
        self.opt_net = torch.optim.Adam(self.net.parameters(), lr=t["lr_network"])
        groups = [{"params": [getattr(self.module, q)], "lr": float(t["lr_optics"].get(q, 0.0)), "name": q}
                  for q in learn if q in t["lr_optics"]] if method == "e2e" else []
        missing = [q for q in learn if q not in t["lr_optics"]] if method == "e2e" else []
        if missing:
            raise ConfigError(f"arm {name}: 'train.lr_optics' has no learning rate for {missing}")
        self.opt_optics = torch.optim.Adam(groups) if groups else None
        self.gen = torch.Generator().manual_seed(int(cfg["seed"]))
        self.step = 0
        self.design_done = False
        self.rms_log = []
        self.feature_projections = 0
        self.objective_initial = None
        self.last_psf = None

    # ------------------------------------------------------------------ optics
    def _achromat(self, lens):
        from torch_bridge.design import paraxial_achromat
        d = lens.doe_index
        s = lens.surfaces[d]
        allw = [w for c in self.cfg["optics"]["wavelengths_um"] for w in c]
        a, dist = paraxial_achromat(lens, allw)
        coeffs = [0.0] * len(s.profile["coefficients"])
        coeffs[0 if s.profile["kind"] == "even_poly" else 1] = a
        lens = lens.with_surface(d, profile={**s.profile, "coefficients": coeffs})
        if d == len(lens.surfaces) - 1:
            lens = lens.with_surface(d, thickness=dist)
        return lens

    def _provider(self, model, module=None):
        from torch_bridge import design as dz
        o = self.cfg["optics"]
        module = module or self.module
        cache = o["cache_fields"]
        if cache == "auto" or self.method != "e2e":
            # frozen refractive part during training (every method but e2e with lens quantities)
            cache = not (self.method == "e2e" and self.live)
        if model == "paraxial-wave" or cache:
            return dz.CachedProvider(module, self.fields, self.size, self.pixel_mm, model=model,
                                     wavelength_ref_um=self.wl_ref, doe_budget_cpmm=o["doe_budget_cpmm"],
                                     memory_budget_bytes=_budget_bytes(o), min_feature_mm=_feature_mm(o))
        tile = None
        if o["memory_budget_gb"]:
            tile = max(1, int(o["memory_budget_gb"] * 1e9 // max(1, module.bytes_per_source(
                module.raywave(self.fields[-1:], [self.wls[-1][0]], self.size, pixel_mm=self.pixel_mm)))))
        return dz.LiveProvider(module, self.fields, self.size, self.pixel_mm, wavelength_ref_um=self.wl_ref,
                               tile=tile)

    def limit_feature(self) -> float:
        """After an optics update: project the DOE onto ``optics.min_feature_um`` (a learning DOE only;
        :meth:`HybridLens.limit_doe_feature`). Counts the projections in :attr:`feature_projections`;
        returns the scale applied (1.0: none needed or no limit)."""
        mf = _feature_mm(self.cfg["optics"])
        if mf is None or "doe" not in self.learn:
            return 1.0
        c = self.module.limit_doe_feature(mf)
        if c < 1.0:
            self.feature_projections += 1
        return c

    def optics_learn(self) -> bool:
        return self.method == "e2e" and self.opt_optics is not None

    def psfs(self, wls, depth, grad: bool):
        """(n_nodes, 3, k, k) float64 PSFs (sensor orientation)."""
        if grad:
            return self.provider.psfs(wls, depth)
        with torch.no_grad():
            return self.provider.psfs(wls, depth)

    # ------------------------------------------------------------------ design stage
    def run_design(self):
        """RMS-spot optimisation (``design.method: rms``, or ``design.init: rms`` before an e2e design:
        the paraxial achromat, then the RMS-spot design, then end to end); nothing otherwise."""
        if (self.method != "rms" and self.cfg["design"]["init"] != "rms") or self.design_done:
            self.design_done = True
            return
        from torch_bridge.design import RaySpot, paraxial_efl
        r = self.cfg["design"]["rms"]
        lrs = r["lr"]
        missing = [q for q in self.learn if q not in lrs]
        if missing:
            raise ConfigError(f"arm {self.name}: 'design.rms.lr' has no learning rate for {missing}")
        opt = torch.optim.Adam([{"params": [getattr(self.module, q)], "lr": float(lrs[q])} for q in self.learn])
        wls = r["wavelengths_um"] or [c[len(c) // 2] for c in self.wls]
        spot = RaySpot(self.module, self.fields, wls, grid=r["grid"])
        efl_mm, efl_w = self.cfg["design"]["efl_mm"], self.cfg["design"]["efl_weight"]
        it = range(r["steps"])
        if self.progress:
            from tqdm.auto import tqdm
            it = tqdm(it, desc=f"{self.name}: RMS spot", unit="step", leave=False)
        for k in it:
            opt.zero_grad()
            rms = spot.rms()
            loss = (rms ** 2).mean() * 1e6  # um^2
            if efl_mm and efl_w:
                loss = loss + efl_w * (paraxial_efl(self.module, self.wl_ref) - efl_mm) ** 2
            loss.backward()
            opt.step()
            self.limit_feature()
            self.rms_log.append({"step": k, "rms_um": float(rms.detach().mean() * 1e3), "loss": float(loss.detach())})
        self.provider = self._provider(self.cfg["optics"]["model"])
        self.design_done = True

    # ------------------------------------------------------------------ checkpoint
    def state(self) -> dict:
        return {"step": self.step, "design_done": self.design_done, "module": self.module.state_dict(),
                "net": self.net.state_dict(), "opt_net": self.opt_net.state_dict(),
                "opt_optics": None if self.opt_optics is None else self.opt_optics.state_dict(),
                "rng": _rng_state(self.gen), "rms_log": self.rms_log,
                "feature_projections": self.feature_projections, "objective_initial": self.objective_initial,
                "last_psf": self.last_psf,
                "plans": {f"{k[0]}|{k[1]}": v for k, v in getattr(self.provider, "plans", {}).items()}}

    def save(self, path: Path):
        tmp = path.with_suffix(".tmp")
        torch.save(self.state(), tmp)
        tmp.replace(path)

    def load(self, path: Path):
        st = torch.load(path, map_location="cpu", weights_only=False)
        self.step = int(st["step"])
        self.design_done = bool(st["design_done"])
        self.module.load_state_dict(st["module"])
        self.net.load_state_dict(st["net"])
        self.opt_net.load_state_dict(st["opt_net"])
        if self.opt_optics is not None and st["opt_optics"] is not None:
            self.opt_optics.load_state_dict(st["opt_optics"])
        self.rms_log = st.get("rms_log", [])
        self.feature_projections = st.get("feature_projections", 0)
        self.objective_initial = st.get("objective_initial")
        self.last_psf = None if st.get("last_psf") is None else st["last_psf"].to(self.module.thickness_base.device)
        self.provider = self._provider(self.cfg["optics"]["model"])
        plans = st.get("plans") or {}
        if plans and hasattr(self.provider, "load_plans"):
            def key(s):
                w, d = s.split("|")
                return (float(w), None if d == "None" else float(d))
            self.provider.load_plans({key(k): v for k, v in plans.items()})
        _set_rng_state(st["rng"], self.gen)


def _psf_kernels(psfs):
    """Sensor-orientation PSFs (..., k, k) -> image-orientation convolution kernels (row 0 at +y)."""
    return psfs.flip(-2)


def train_arm(name: str, cfg: dict, source=None, out_dir=None, resume: bool = True, progress: bool = True) -> dict:
    """Run one arm (design stage, joint phase, fine-tune phase, evaluation); returns its result dict
    (also written to ``out_dir/result.json``). ``resume``: continue from ``out_dir/checkpoint.pt``."""
    from torch_bridge.functions import mixed_precision
    from torch_bridge.imaging import spatially_varying_blur
    from torch_bridge.losses import psnr
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    _seed_all(int(cfg["seed"]))
    arm = Arm(name, cfg, source, out, progress)
    ck = out / "checkpoint.pt"
    csv_path = out / "metrics.csv"
    t_cfg = cfg["train"]
    total = t_cfg["joint_steps"] + t_cfg["finetune_steps"]
    if resume and ck.exists():
        arm.load(ck)
        _truncate_csv(csv_path, arm.step, _CSV_FIELDS)
    else:
        for f in out.glob("step_*.png"):
            f.unlink()
        if csv_path.exists():
            csv_path.unlink()
    t0 = time.perf_counter()
    if not arm.design_done:
        arm.run_design()
        if isinstance(arm.provider, __import__("torch_bridge.design", fromlist=["CachedProvider"]).CachedProvider):
            arm.provider.prepare(sorted({w for c in arm.wls for w in c}), arm.depths, progress=arm.progress)
        arm.objective_initial = objective(arm, _eval_provider(arm))
        arm.save(ck)
    if isinstance(arm.provider, __import__("torch_bridge.design", fromlist=["CachedProvider"]).CachedProvider):
        allw = sorted({w for c in arm.wls for w in c})
        arm.provider.prepare(allw, arm.depths, progress=arm.progress)
    new_csv = not csv_path.exists()
    fcsv = open(csv_path, "a", newline="")
    writer = csv.DictWriter(fcsv, fieldnames=_CSV_FIELDS)
    if new_csv:
        writer.writeheader()
    B = cfg["data"]["batch_size"]
    n_nodes = len(arm.fields)
    stop_after = t_cfg["stop_after"]
    psf_cache = {}
    it = range(arm.step, total)
    if arm.progress:
        from tqdm.auto import tqdm
        it = tqdm(it, desc=f"{name}", unit="step", initial=arm.step, total=total)
    last = None
    try:
        for step in it:
            phase = "joint" if step < t_cfg["joint_steps"] else "finetune"
            # ---- draws (all from the arm's generator, in a fixed order)
            choice = [int(torch.randint(len(c), (1,), generator=arm.gen)) for c in arm.wls]
            wls = [c[k] for c, k in zip(arm.wls, choice)]
            depth = arm.depths[int(torch.randint(len(arm.depths), (1,), generator=arm.gen))]
            gt = arm.train_set.sample(B, arm.gen).to(arm.device)
            perm = torch.randperm(n_nodes, generator=arm.gen)
            nodes = [int(perm[b % n_nodes]) for b in range(B)]
            noisy = phase == "finetune" or t_cfg["noise_in_joint"]
            # ---- optics
            optics_step = phase == "joint" and arm.optics_learn() and step % t_cfg["optics_every"] == 0
            if optics_step:
                psf = arm.psfs(wls, depth, grad=True)
                psf_cache.clear()
                arm.last_psf = psf.detach()
            elif phase == "joint" and arm.optics_learn() and arm.last_psf is not None:
                # between optics updates the network sees the PSFs of the last update (no extra forward)
                psf = arm.last_psf
            else:
                # frozen optics: single-wavelength PSFs cached, a channel combination is a stack of them
                per = []
                for w in wls:
                    if (w, depth) not in psf_cache:
                        psf_cache[(w, depth)] = arm.psfs([w], depth, grad=False)[:, 0]
                    per.append(psf_cache[(w, depth)])
                psf = torch.stack(per, 1)
            kern = _psf_kernels(mixed_precision(psf) if psf.dtype == torch.float64 else psf).to(arm.device)
            if cfg["render"]["mode"] == "patch":
                raw = _blur_patch(gt, kern[nodes], cfg["render"]["boundary"])
            else:
                gy, gx = arm.grid
                raw = spatially_varying_blur(gt, kern.reshape(gy, gx, 3, arm.size, arm.size),
                                             boundary=cfg["render"]["boundary"])
            if noisy:
                raw = _noise(raw, t_cfg["noise"], arm.gen)
            # ---- network and loss
            f = _lr_factor(t_cfg["lr_decay"], step, total)
            for g in arm.opt_net.param_groups:
                g["lr"] = t_cfg["lr_network"] * f
            arm.opt_net.zero_grad(set_to_none=True)
            if arm.opt_optics is not None:
                arm.opt_optics.zero_grad(set_to_none=True)
            rec = arm.net(raw)
            loss, parts = arm.criterion(rec, gt)
            if optics_step and cfg["design"]["efl_mm"] and cfg["design"]["efl_weight"]:
                from torch_bridge.design import paraxial_efl
                loss = loss + cfg["design"]["efl_weight"] * (paraxial_efl(arm.module, arm.wl_ref).float() -
                                                             cfg["design"]["efl_mm"]) ** 2
            loss.backward()
            if t_cfg["grad_clip"]:
                torch.nn.utils.clip_grad_norm_(arm.net.parameters(), t_cfg["grad_clip"])
            arm.opt_net.step()
            if optics_step:
                for g in arm.opt_optics.param_groups:
                    g["lr"] = float(t_cfg["lr_optics"][g["name"]]) * _lr_factor(t_cfg["lr_decay"], step,
                                                                               t_cfg["joint_steps"])
                arm.opt_optics.step()
                arm.limit_feature()
                ev = cfg["optics"]["check_sampling_every"]
                if ev and hasattr(arm.provider, "check_sampling") and (step // t_cfg["optics_every"]) % ev == 0:
                    arm.provider.check_sampling()
            arm.step = step + 1
            last = {"step": step, "phase": phase, "loss": float(loss.detach()), "mse": parts["mse"],
                    "perceptual": parts["perceptual"], "psnr_train": psnr(rec.detach(), gt),
                    "lr_network": t_cfg["lr_network"] * f, "optics_step": int(optics_step),
                    "wall_s": time.perf_counter() - t0, "replans": getattr(arm.provider, "replans", 0),
                    "memory_gb": _memory_gb(arm.device)}
            if step % t_cfg["log_every"] == 0 or arm.step == total:
                writer.writerow(last)
                fcsv.flush()
            if arm.progress:
                it.set_postfix(loss=f"{last['loss']:.4f}", psnr=f"{last['psnr_train']:.2f}", phase=phase)
            if t_cfg["image_every"] and (step % t_cfg["image_every"] == 0 or arm.step == total):
                _snapshot(arm, out / f"step_{step:06d}.png", psf, gt, raw, rec, step, phase)
            boundary = arm.step == t_cfg["joint_steps"] or arm.step == total
            if (t_cfg["checkpoint_every"] and arm.step % t_cfg["checkpoint_every"] == 0) or boundary:
                arm.save(ck)
            if stop_after is not None and arm.step >= stop_after:
                arm.save(ck)
                break
    finally:
        fcsv.close()
    result = {"arm": name, "method": arm.method, "steps_done": arm.step, "steps_total": total,
              "train_wall_s": time.perf_counter() - t0, "last": last, "notes": arm.notes,
              "replans": getattr(arm.provider, "replans", 0),
              "feature_projections": arm.feature_projections,
              "replan_log": getattr(arm.provider, "replan_log", []),
              "field_build": getattr(arm.provider, "build_log", []),
              "step_log": getattr(arm.provider, "step_log", [])[-8:]}
    if arm.step < total:
        result["stopped_early"] = True
        return result
    arm.module.save_lens(out / "lens.json")
    torch.save(arm.net.state_dict(), out / "network.pt")
    t1 = time.perf_counter()
    prov = _eval_provider(arm)
    result["eval"] = evaluate(arm, prov)
    result["objective_initial"] = arm.objective_initial
    result["objective_final"] = objective(arm, prov)
    result["eval_wall_s"] = time.perf_counter() - t1
    result["rms_design_log"] = arm.rms_log[-1:] if arm.rms_log else []
    (out / "result.json").write_text(json.dumps(result, indent=1, default=_json_default))
    return result


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, float) and not math.isfinite(o):
        return None
    return str(o)


def _memory_gb(device) -> float:
    """Memory in use (GB = 1e9 bytes) after a step: on CUDA the whole device's used memory (total - free,
    so torch, Warp and CuPy pools all count), on the CPU the process's peak resident set size."""
    dev = torch.device(device)
    if dev.type == "cuda":
        free, total = torch.cuda.mem_get_info(dev)
        return round((total - free) / 1e9, 3)
    import resource
    import sys
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss          # kB on Linux, bytes on macOS
    return round(rss * (1 if sys.platform == "darwin" else 1024) / 1e9, 3)


def _feature_mm(optics: dict):
    """``optics.min_feature_um`` in mm, None when unset."""
    f = optics.get("min_feature_um")
    return None if f is None else float(f) * 1e-3


_CSV_FIELDS = ["step", "phase", "loss", "mse", "perceptual", "psnr_train", "lr_network", "optics_step", "wall_s",
               "replans", "memory_gb"]


def _truncate_csv(path: Path, step: int, fields=None):
    """Drop rows at or after ``step`` (a resumed run rewrites them). With ``fields``, the file is
    rewritten with those columns (a CSV of an older version gets the new ones, empty in old rows)."""
    if not path.exists():
        return
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
        old = list(rows[0].keys()) if rows else None
    if old is None:
        return
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(fields or old), restval="", extrasaction="ignore")
        w.writeheader()
        for r in rows:
            if int(r["step"]) < step:
                w.writerow(r)


# ============================================================================================== evaluation
def _eval_provider(arm: Arm):
    """A ray-wave provider for the current lens: the training one when it caches ray-wave fields of
    this lens (checked for sampling and centring first), else a new one."""
    from torch_bridge import design as dz
    p = arm.provider
    if isinstance(p, dz.CachedProvider) and p.model == "ray-wave":
        p.check_sampling()
        return p
    prov = dz.CachedProvider(arm.module, arm.fields, arm.size, arm.pixel_mm, model="ray-wave",
                             wavelength_ref_um=arm.wl_ref, memory_budget_bytes=_budget_bytes(arm.cfg["optics"]),
                             min_feature_mm=_feature_mm(arm.cfg["optics"]))
    ev = arm.cfg["eval"]["depths_mm"] or arm.cfg["optics"]["depths_mm"]
    prov.prepare(sorted({w for c in arm.wls for w in c}), [_depth_value(d) for d in ev], progress=False)
    return prov


@torch.no_grad()
def objective(arm: Arm, prov=None) -> dict:
    """The training objective (``MSE + alpha * perceptual``) on the fixed evaluation crops: ray-wave PSFs
    of the current lens (the wavelengths of each channel averaged) at the first evaluation depth, every
    node, seeded noise, the current network. Used to compare a design with its own starting point."""
    from torch_bridge.imaging import spatially_varying_blur
    cfg = arm.cfg
    ev = cfg["eval"]
    depth = _depth_value((ev["depths_mm"] or cfg["optics"]["depths_mm"])[0])
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
            raw = _blur_patch(gt, kern[[v] * gt.shape[0]], cfg["render"]["boundary"])
        raw = _noise(raw, ev["noise"], g)
        rec = arm.net(raw)
        loss, parts = arm.criterion(rec, gt)
        tot += float(loss)
        mse += parts["mse"]
        n += 1
    arm.net.train()
    return {"loss": tot / n, "mse": mse / n}


@torch.no_grad()
def evaluate(arm: Arm, prov=None) -> dict:
    """Evaluation of a trained arm with the ray-wave model (see the module docstring)."""
    from torch_bridge.imaging import spatially_varying_blur
    from torch_bridge.losses import image_metrics
    cfg = arm.cfg
    ev = cfg["eval"]
    depths = [_depth_value(d) for d in (ev["depths_mm"] or cfg["optics"]["depths_mm"])]
    # ray-wave provider on the designed lens (its refractive part is frozen now: fields may be cached)
    from torch_bridge import design as dz
    prov = prov or _eval_provider(arm)
    gt_all = arm.valid_set.fixed_crops(cfg["data"]["eval_images"], seed=ev["seed"]).to(arm.device)
    g = torch.Generator().manual_seed(int(ev["seed"]))
    arm.net.eval()
    rows = []
    psf_store = {}
    for depth in depths:
        per_wl = []
        for j in range(len(arm.wls[0])):
            per_wl.append(prov.psfs([c[j] for c in arm.wls], depth))
        psf = torch.stack(per_wl, 0).mean(0)                              # (nodes, 3, k, k): mean per channel
        psf_store[str(depth)] = psf.cpu().numpy()
        kern = _psf_kernels(psf.float()).to(arm.device)
        node_rows = []
        if cfg["render"]["mode"] == "patch":
            for n in range(len(arm.fields)):
                raw = _blur_patch(gt_all, kern[[n] * gt_all.shape[0]], cfg["render"]["boundary"])
                raw = _noise(raw, ev["noise"], g)
                rec = torch.cat([arm.net(raw[i:i + ev["batch_size"]]) for i in range(0, raw.shape[0],
                                                                                      ev["batch_size"])])
                m_raw = image_metrics(raw, gt_all, arm.lpips)
                m_rec = image_metrics(rec, gt_all, arm.lpips)
                node_rows.append({"node": n, "position_mm": arm.positions[n], "field_deg": arm.fields[n],
                                  "raw": m_raw, "rec": m_rec})
                if n == len(arm.fields) - 1:
                    sample = (gt_all[:2].cpu(), raw[:2].cpu(), rec[:2].cpu())
        else:
            gy, gx = arm.grid
            raw = spatially_varying_blur(gt_all, kern.reshape(gy, gx, 3, arm.size, arm.size),
                                         boundary=cfg["render"]["boundary"])
            raw = _noise(raw, ev["noise"], g)
            rec = torch.cat([arm.net(raw[i:i + ev["batch_size"]]) for i in range(0, raw.shape[0], ev["batch_size"])])
            node_rows.append({"node": "all", "raw": image_metrics(raw, gt_all, arm.lpips),
                              "rec": image_metrics(rec, gt_all, arm.lpips)})
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


def _depth_tag(d):
    return "default" if d is None else ("inf" if math.isinf(d) else f"{d:g}mm")


# ============================================================================================== figures
def _doe_phase_image(lens, n: int = 256):
    from rwwarp import doe as rdoe
    s = lens.surfaces[lens.doe_index]
    prof = rdoe.profile_from_dict(s.profile)
    h = s.semi_diameter or 1.0
    g = np.linspace(-h, h, n)
    x, y = np.meshgrid(g, g[::-1])
    return rdoe.design_phase(prof, x, y, s.design_wavelength_um, s.levels), h


def _rgb_psf(p):
    """(3, k, k) -> (k, k, 3) display image (sqrt, per-image max), image orientation."""
    a = np.clip(p, 0, None)
    a = np.sqrt(a / max(a.max(), 1e-30))
    return a.transpose(1, 2, 0)[::-1]


def _snapshot(arm, path, psf, gt, raw, rec, step, phase):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    p = psf.detach().float().cpu().numpy()
    nn_ = p.shape[0]
    ncol = max(nn_, 4)
    fig, ax = plt.subplots(2, ncol, figsize=(2.2 * ncol, 4.6))
    for j in range(ncol):
        for r in range(2):
            ax[r, j].axis("off")
    for j in range(nn_):
        ax[0, j].imshow(_rgb_psf(p[j]))
        f = arm.fields[j]
        ax[0, j].set_title(f"PSF ({f[0]:.1f}, {f[1]:.1f}) deg", fontsize=7)
    ph, h = _doe_phase_image(arm.module.to_lens())
    ax[1, 0].imshow(ph, cmap="twilight", extent=(-h, h, -h, h))
    ax[1, 0].set_title("DOE phase (rad, wrapped)", fontsize=7)
    ax[1, 0].axis("on")
    ax[1, 0].tick_params(labelsize=6)
    for j, (img, t) in enumerate(((gt, "ground truth"), (raw, "raw"), (rec, "reconstructed"))):
        ax[1, j + 1].imshow(img[0].detach().float().clamp(0, 1).cpu().numpy().transpose(1, 2, 0))
        ax[1, j + 1].set_title(t, fontsize=7)
    fig.suptitle(f"{arm.name}: step {step} ({phase})", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _designs_figure(results: dict, out: Path):
    """One row per arm: DOE phase, evaluation PSFs (RGB, sqrt scale) of the nodes, raw / rec crop."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    import rwwarp as rw
    arms = [a for a in results if (out / a / "lens.json").exists()]
    if not arms:
        return
    psfs = {a: np.load(out / a / "eval_psfs.npz") for a in arms}
    first = psfs[arms[0]]
    key0 = next(iter(first.keys()))
    nn_ = first[key0].shape[0]
    ncol = 1 + nn_ + 2
    fig, ax = plt.subplots(len(arms), ncol, figsize=(2.0 * ncol, 2.1 * len(arms)), squeeze=False)
    for i, a in enumerate(arms):
        for j in range(ncol):
            ax[i, j].axis("off")
        lens = rw.load_lens(out / a / "lens.json")
        ph, h = _doe_phase_image(lens)
        ax[i, 0].imshow(ph, cmap="twilight", extent=(-h, h, -h, h))
        ax[i, 0].set_title(f"{a}: DOE phase", fontsize=7)
        p = psfs[a][key0]
        for j in range(nn_):
            ax[i, 1 + j].imshow(_rgb_psf(p[j]))
            ax[i, 1 + j].set_title(f"PSF node {j} ({key0})", fontsize=6)
        smp = sorted((out / a).glob("eval_sample_*.npz"))
        if smp:
            s = np.load(smp[0])
            ax[i, ncol - 2].imshow(np.clip(s["raw"][0].transpose(1, 2, 0), 0, 1))
            ax[i, ncol - 2].set_title("raw (outer node)", fontsize=7)
            ax[i, ncol - 1].imshow(np.clip(s["rec"][0].transpose(1, 2, 0), 0, 1))
            ax[i, ncol - 1].set_title("reconstructed", fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "designs.png", dpi=100)
    plt.close(fig)


def _fmt(m):
    lp = m.get("one_minus_lpips")
    lp_s = "-" if lp is None or (isinstance(lp, float) and not math.isfinite(lp)) else f"{lp:.3f}"
    return f"{m['psnr']:.2f}/{m['ssim']:.3f}/{lp_s}"


def write_table(results: dict, out: Path, title: str = "", preset=None):
    """``table.md`` and ``table.csv`` of an experiment from its arms' results (numbers as measured)."""
    lines = [f"# {title}" + (f" (preset {preset})" if preset else ""), "",
             ("| design | depth | RMS radius um (on/off-axis/avg) | PSNR/SSIM/1-LPIPS raw | PSNR/SSIM/1-LPIPS rec | "
              "EFL mm |"), "|---|---|---|---|---|---|"]
    rows = []
    for a, r in results.items():
        if "eval" not in r:
            continue
        e = r["eval"]
        rms = e.get("rms_um", {})
        rms_s = f"{rms['on_axis']:.1f}/{rms['off_axis']:.1f}/{rms['avg']:.1f}" if "on_axis" in rms else "-"
        for d in e["depths"]:
            dep = _depth_tag(d["depth_mm"])
            lines.append(f"| {a} | {dep} | {rms_s} | {_fmt(d['raw'])} | {_fmt(d['rec'])} | {e['efl_mm']:.2f} |")
            rows.append({"design": a, "depth": dep, "rms_on_um": rms.get("on_axis"), "rms_off_um": rms.get("off_axis"),
                         "rms_avg_um": rms.get("avg"), "psnr_raw": d["raw"]["psnr"], "ssim_raw": d["raw"]["ssim"],
                         "one_minus_lpips_raw": d["raw"]["one_minus_lpips"], "psnr_rec": d["rec"]["psnr"],
                         "ssim_rec": d["rec"]["ssim"], "one_minus_lpips_rec": d["rec"]["one_minus_lpips"],
                         "efl_mm": e["efl_mm"], "train_wall_s": r.get("train_wall_s")})
    lines.append("")
    lines.append("Per node (PSNR raw / rec, dB; node positions on the sensor in mm):")
    lines.append("")
    for a, r in results.items():
        if "eval" in r:
            for d in r["eval"]["depths"]:
                lines.append(f"- {a}, depth {_depth_tag(d['depth_mm'])}: " + ", ".join(
                    f"node {n['node']}" + (f" {tuple(round(v, 2) for v in n['position_mm'])}" if 'position_mm' in n
                                           else "") + f": {n['raw']['psnr']:.2f} / {n['rec']['psnr']:.2f}"
                    for n in d["nodes"]))
    lines.append("")
    lines.append("Objective (MSE + alpha * perceptual on the evaluation crops, first evaluation depth; initial = "
                 "the arm's starting lens with the untrained network) and wall time:")
    lines.append("")
    for a, r in results.items():
        if "eval" in r:
            oi, of = r.get("objective_initial") or {}, r.get("objective_final") or {}
            obj = f"{oi['loss']:.5f} -> {of['loss']:.5f}" if "loss" in oi and "loss" in of else "-"
            lines.append(f"- {a}: objective {obj}; training {r.get('train_wall_s', float('nan')):.0f} s, "
                         f"evaluation {r.get('eval_wall_s', float('nan')):.0f} s")
    (out / "table.md").write_text("\n".join(lines) + "\n")
    if rows:
        with open(out / "table.csv", "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)


# ============================================================================================== experiment
def _preflight(arms, out: Path) -> None:
    """Check what each arm needs before anything is written: its data folder (a directory, when set),
    its device (CUDA present when asked for) and the output path (not a file). Raises ConfigError."""
    for a in arms:
        cfg = a["config"]
        root = (cfg.get("data") or {}).get("root")
        if root is not None and not Path(root).is_dir():
            raise ConfigError(f"arm {a['name']!r}: data.root {root!r} is not a directory")
        dev = str(cfg.get("device", "cpu"))
        if dev.startswith("cuda"):
            idx = int(dev.split(":")[1]) if ":" in dev else 0
            if not torch.cuda.is_available() or idx >= torch.cuda.device_count():
                raise ConfigError(f"arm {a['name']!r}: device {dev!r} is not available on this machine "
                                  f"({torch.cuda.device_count() if torch.cuda.is_available() else 0} CUDA devices); "
                                  "use --preset cpu or device: cpu")
    if out.exists() and not out.is_dir():
        raise ConfigError(f"output {str(out)!r} exists and is not a folder")


def train(config, preset: str | None = None, arms=None, out_dir=None, resume: bool = True,
          progress: bool | None = None) -> dict:
    """Run an experiment: validate the config (``config``: path or dict, ``preset``: a key of its
    ``presets``), then every arm (or those named in ``arms``) in order, then write the table and the
    comparison figure. Returns ``{arm: result}``. ``out_dir`` overrides the config's; default
    ``out/design/<experiment>[_<preset>]``."""
    exp = load_config(config, preset)
    base = exp["base"]
    out = Path(out_dir or base["out_dir"] or f"out/design/{exp['experiment']}" + (f"_{preset}" if preset else ""))
    chosen = exp["arms"] if arms is None else [a for a in exp["arms"] if a["name"] in set(arms)]
    if arms is not None and len(chosen) != len(set(arms)):
        known = [a["name"] for a in exp["arms"]]
        raise ConfigError(f"unknown arm(s) {sorted(set(arms) - set(known))}; the config has {known}")
    _preflight(chosen, out)  # nothing is written before the data, the device and the output folder check out
    out.mkdir(parents=True, exist_ok=True)
    (out / "config_resolved.json").write_text(json.dumps(exp, indent=1, default=_json_default))
    results = {}
    for a in chosen:
        cfg = copy.deepcopy(a["config"])
        if progress is not None:
            cfg["progress"] = bool(progress)
        results[a["name"]] = train_arm(a["name"], cfg, exp["source"], out / a["name"], resume=resume,
                                       progress=cfg["progress"])
    # include arms finished earlier (other invocations) in the table
    for a in exp["arms"]:
        if a["name"] not in results and (out / a["name"] / "result.json").exists():
            results[a["name"]] = json.loads((out / a["name"] / "result.json").read_text())
    order = [a["name"] for a in exp["arms"] if a["name"] in results]
    results = {k: results[k] for k in order}
    if any("eval" in r for r in results.values()):
        write_table(results, out, base["description"] or exp["experiment"], preset)
        _designs_figure(results, out)
    (out / "summary.json").write_text(json.dumps(results, indent=1, default=_json_default))
    return results


def main(argv=None) -> int:
    """``rwwarp design CONFIG [--preset P] [--arm NAME ...] [--out DIR] [--fresh] [--check] [--table]``."""
    ap = argparse.ArgumentParser(prog="rwwarp design", description="end-to-end hybrid lens design")
    ap.add_argument("config", help="YAML/TOML config (a path, or the name of a bundled config: "
                                   + ", ".join(sorted(p.stem for p in CONFIG_DIR.glob('*.yaml'))) + ")")
    ap.add_argument("--preset", default=None, help="a preset of the config (e.g. cpu, gpu)")
    ap.add_argument("--arm", action="append", default=None, help="run only this arm (repeatable)")
    ap.add_argument("--out", default=None, help="output folder")
    ap.add_argument("--fresh", action="store_true", help="ignore existing checkpoints")
    ap.add_argument("--check", action="store_true", help="validate the config and exit")
    ap.add_argument("--table", action="store_true",
                    help="train nothing: rewrite table.md/table.csv/designs.png/summary.json from the arms "
                         "finished in the output folder (e.g. after running arms in separate processes)")
    ap.add_argument("--no-progress", action="store_true")
    a = ap.parse_args(argv)
    try:
        if a.check:
            exp = load_config(a.config, a.preset)
            print(f"{exp['source'] or a.config}: valid; arms: {', '.join(x['name'] for x in exp['arms'])}")
            return 0
        res = train(a.config, a.preset, [] if a.table else a.arm, a.out, resume=not a.fresh,
                    progress=not a.no_progress)
    except ConfigError as e:
        print(f"rwwarp design: error: {e}", file=sys.stderr)
        return 2
    for name, r in res.items():
        if "eval" in r:
            d = r["eval"]["depths"][0]
            print(f"{name}: raw {_fmt(d['raw'])}  rec {_fmt(d['rec'])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
