"""Design configs: the schema, defaults, loading and validation (``load_config``), the lens a config
describes (``build_lens``) and the checks made before anything is written (``_preflight``).

A config is a YAML or TOML file (or a dict) validated before anything runs; errors
(:class:`ConfigError`) name the key (``arms[1].train.lr_network``) and the file. The keys and what
they do are described in :mod:`torch_bridge.train`.
"""
from __future__ import annotations

import copy
import math
import warnings
from pathlib import Path

import numpy as np
from rwwarp.wave.methods import choices as method_choices

__all__ = ["CONFIG_DIR", "parse_overrides", "DEFAULTS", "SCHEMA", "ConfigError", "build_lens", "load_config", "resolve_config",
           "validate_config"]

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
          ("curvature", "thickness", "conic", "aspheric", "doe", "phase")}
_LR = {q: _num(0, lo_open=False) for q in ("curvature", "thickness", "conic", "aspheric", "doe", "phase")}
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
        # kept live focal plans (torch_bridge.live.LiveProvider): live_replan_every 1 (default) plans every source
        # afresh every call. Above 1: rule "drift" (default) keeps a plan while the lens's wavefront drift since it
        # (torch_bridge.replan, waves) is <= live_replan_drift (default 1.0), at most live_replan_every optimiser
        # steps, spreading due re-plans (at most ceil(n_sources / live_replan_spread) a call, default 3; one more
        # call past due, never past live_replan_drift_hard, default null = 2 x live_replan_drift); rule "calls"
        # (the rule before) plans again every live_replan_every calls.
        "live_replan_every": _num(1, integer=True),
        "live_replan_rule": _choice("calls", "drift"),
        "live_replan_drift": _num(0, lo_open=True),
        "live_replan_drift_hard": _num(0, lo_open=True, none=True),
        "live_replan_spread": _num(1, integer=True),
        "live_pack": _bool(),
        # a packed tile's members are stacked into one focal operator while padding grows their work by at most
        # this factor (LiveProvider.pack_waste, rwwarp.wave.focal_packed.focal_groups): larger, fewer groups (fewer
        # operator calls and launches a step, issue 25) and more padded work; the PSFs agree to rounding
        "live_pack_waste": _num(1),
        "memory_budget_gb": _num(0, lo_open=True, none=True),
        "cache_precision": _choice("double", "single"),
        "cache_device": _choice("device", "host"),
        "propagation": _choice(*method_choices(differentiable=True)),   # rwwarp.wave.methods
        "focal_patch_tol": _num(0, 1),
        "deterministic": _bool(),
        "pixel_values": _choice("flux", "intensity"),
        "model_error_estimate": _bool(),
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
        # replay the network's forward, loss, backward and training PSNR as one CUDA graph (torch_bridge.graph_step;
        # CUDA and one process only: ignored with one warning on the CPU and under DDP, where the step runs eager)
        "cuda_graph": _bool(),
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
        "grid": _list(_num(1, integer=True), 2, 2, none=True),
        "node_chunk": _num(1, integer=True),
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
               "check_sampling_every": 10, "live_replan_every": 1, "live_replan_rule": "drift",
               "live_replan_drift": 1.0, "live_replan_drift_hard": None, "live_replan_spread": 3, "live_pack": True,
               "live_pack_waste": 1.5,
               "memory_budget_gb": None, "cache_precision": "double", "cache_device": "device", "propagation": "auto",
               "focal_patch_tol": 1e-5, "deterministic": False, "pixel_values": "flux", "model_error_estimate": False},
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
              "checkpoint_every": 25, "stop_after": None, "cuda_graph": False},
    "design": {"method": "e2e", "init": None, "efl_mm": None, "efl_weight": 0.0,
               "rms": {"steps": 100, "grid": 31, "lr": {"doe": 1.0}, "wavelengths_um": None}},
    "eval": {"depths_mm": None, "noise": {"read_std": 0.01, "photons": None}, "seed": 1234,
             "rms_fractions": [0.0, 0.25, 0.5, 0.75, 0.9], "rms_grid": 41, "batch_size": 8, "grid": None,
             "node_chunk": 16},
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


def load_config(source, preset: str | None = None, overrides: dict | None = None) -> dict:
    """Read (YAML ``.yaml``/``.yml`` or TOML ``.toml``) or take a dict, apply ``preset`` (a key of its
    ``presets`` section), validate every arm and return the resolved experiment::

        {"experiment": ..., "base": <merged config>, "arms": [{"name": ..., "config": <merged>}, ...],
         "source": path or None, "preset": preset}

    Raises :class:`ConfigError` naming the key and the file for unknown keys, wrong types,
    impossible values, a missing preset, a lens file that cannot be read, or learning quantities
    that the lens or the chosen model cannot learn. Nothing is trained before this passes.

    ``overrides`` (a nested mapping, e.g. from ``--set train.joint_steps=2000``): merged last, after the
    preset and each arm's own keys, into every arm (the same budget for every arm); checked like the file.
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
    if overrides:
        if not isinstance(overrides, dict):
            raise ConfigError("--set: overrides must be a mapping")
        _check(overrides, SCHEMA, f"{where} [--set]")
        base = _merge(base, overrides)
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
        if overrides:
            cfg = _merge(cfg, overrides)
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
                if q == "phase" and not (isinstance(e, list) and lens.surfaces[i].phase is not None):
                    raise ConfigError(f"{where}: 'optics.learn.phase' entries are [surface, k] pairs on a surface "
                                      f"with a diffractive phase (Surface.phase; k = 0 for A_1), got {e!r}")
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
    if cfg["eval"]["grid"] is not None and cfg["render"]["mode"] != "patch":
        raise ConfigError(f"{where}: 'eval.grid' needs render.mode 'patch' (the full-image rendering evaluates on "
                          "the training node grid)")
    if cfg["render"]["mode"] == "patch" and cfg["data"]["crop"] < cfg["optics"]["psf_size"] // 2:
        raise ConfigError(f"{where}: 'data.crop' {cfg['data']['crop']} is smaller than half of "
                          f"'optics.psf_size' {cfg['optics']['psf_size']}")
    hard = cfg["optics"]["live_replan_drift_hard"]
    if hard is not None and hard < cfg["optics"]["live_replan_drift"]:
        raise ConfigError(f"{where}: 'optics.live_replan_drift_hard' {hard} is below 'optics.live_replan_drift' "
                          f"{cfg['optics']['live_replan_drift']} (waves)")
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


def _learn_dict(learn: dict) -> dict:
    out = {}
    for q, spec in learn.items():
        out[q] = "all" if spec == "all" else [tuple(e) if isinstance(e, list) else int(e) for e in spec]
    return out


def _feature_mm(optics: dict):
    """``optics.min_feature_um`` in mm, None when unset."""
    f = optics.get("min_feature_um")
    return None if f is None else float(f) * 1e-3


def _depth_tag(d):
    return "default" if d is None else ("inf" if math.isinf(d) else f"{d:g}mm")


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, float) and not math.isfinite(o):
        return None
    return str(o)


def _preflight(arms, out: Path) -> None:
    """Check what each arm needs before anything is written: its data folder (a directory, when set),
    its device (CUDA present when asked for) and the output path (not a file). Raises ConfigError."""
    import torch
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


def parse_overrides(items) -> dict:
    """``["train.joint_steps=2000", "data.root=data/debian-photos"]`` -> a nested mapping for
    :func:`load_config`; each VALUE is read as YAML (numbers, ``null``, ``true``, lists ``[1, 2]``).
    Raises :class:`ConfigError` for an item without ``=`` or with an empty key."""
    import yaml
    out = {}
    for it in items or []:
        if "=" not in it:
            raise ConfigError(f"--set {it!r}: expected KEY=VALUE (e.g. train.joint_steps=2000)")
        key, val = it.split("=", 1)
        keys = key.strip().split(".")
        if not all(keys):
            raise ConfigError(f"--set {it!r}: empty key")
        try:
            v = yaml.safe_load(val)
        except yaml.YAMLError as e:
            raise ConfigError(f"--set {it!r}: the value is not YAML ({e})") from None
        d = out
        for k in keys[:-1]:
            d = d.setdefault(k, {})
            if not isinstance(d, dict):
                raise ConfigError(f"--set {it!r}: {k!r} is set both as a value and as a section")
        d[keys[-1]] = v
    return out
