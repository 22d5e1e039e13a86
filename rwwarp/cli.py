"""Command line: ``rwwarp info | psf | map | validate | demo | design | bench``.

Run ``rwwarp <command> --help`` for the options of each. Lengths in mm, wavelengths in um,
fields in degrees.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from .lens import surface_table  # rwwarp info's table (its home: lens)
from .lenses import bundled_lenses  # re-exported: the names the lens argument takes

# ---------------------------------------------------------------- bad input: one line, exit 2 (issue 12)
EXIT_BAD_INPUT = 2


class _Parser(argparse.ArgumentParser):
    """argparse with a one-line error (``rwwarp psf: error: ...``) and exit status 2."""

    def error(self, message):
        sys.stderr.write(f"{self.prog}: error: {_one_line(message)} (see {self.prog} --help)\n")
        sys.exit(EXIT_BAD_INPUT)


def _one_line(msg) -> str:
    return " ".join(str(msg).split())


def _finite(text):
    """argparse type: a finite float."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not np.isfinite(v):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
    return v


def _positive_int(text):
    """argparse type: an integer >= 1."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"{text} must be >= 1")
    return v


def _atomic(path, write):
    """Write ``path`` by ``write(tmp_path)`` to a temporary name in the same folder, then rename: a failure
    leaves no partial file. Returns the path."""
    import os

    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"output {path} is a directory")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp{os.getpid()}{path.suffix}")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def _lens(path):
    from .io import load_lens
    return load_lens(path)



def _lens_help() -> str:
    return ("a bundled lens (" + ", ".join(bundled_lenses()) + "), or a lens file: rwwarp JSON, DeepLens JSON or "
            "Zemax .zmx")


def _default_wavelength(lens) -> float:
    """The lens's primary wavelength (Zemax PWAV), else the middle of its wavelengths, um."""
    if lens.primary_wavelength_um is not None:
        return float(lens.primary_wavelength_um)
    wls = list(lens.wavelengths_um)
    return float(wls[len(wls) // 2])


def _field_xy(f):
    """A field (y, or (x, y), deg) as (x, y)."""
    if isinstance(f, (list, tuple, np.ndarray)):
        return float(f[0]), float(f[1])
    return 0.0, float(f)


def lens_max_field(lens, wavelength_um=None):
    """(largest field angle in deg, where it comes from): the lens file's largest field, else the angle whose
    paraxial chief ray (EFL tan theta) reaches the sensor's half diagonal."""
    if lens.fields_deg:
        return max(float(np.hypot(*_field_xy(f))) for f in lens.fields_deg), "the lens file's largest field"
    wl = wavelength_um or _default_wavelength(lens)
    hx, hy = lens.sensor.half_size
    return (float(np.degrees(np.arctan(np.hypot(hx, hy) / abs(lens.efl(wl))))),
            "the sensor corner through the EFL (the lens file lists no fields)")


def check_field_inside(lens, fields, wavelength_um, pixel_mm=None, allow_outside=False, label="lens"):
    """Refuse (ValueError) a field beyond the lens's largest field (:func:`lens_max_field`) before anything is
    computed, unless ``allow_outside``; return warnings (strings) for fields whose paraxial chief ray
    (EFL tan theta) lands past the sensor's half width. Fields in deg, wavelength um, pixel mm."""
    from . import checks
    checks.check_fields(list(fields))
    fmax, why = lens_max_field(lens, wavelength_um)
    pitch = float(pixel_mm or lens.sensor.pixel_pitch)
    half = (0.5 * pitch * lens.sensor.resolution[0], 0.5 * pitch * lens.sensor.resolution[1])
    try:
        efl = abs(lens.efl(wavelength_um))
    except Exception:  # noqa: BLE001 - an afocal lens: no paraxial landing point to state
        efl = float("nan")
    notes = []
    for f in fields:
        x, y = _field_xy(f)
        ang = float(np.hypot(x, y))
        lx, ly = efl * np.tan(np.radians(x)), efl * np.tan(np.radians(y))
        if ang > fmax * (1 + 1e-6) + 1e-9 and not allow_outside:
            raise ValueError(
                f"field {ang:g} deg is outside {label}'s field: its largest is {fmax:.4g} deg ({why}); the chief "
                f"ray would land near (x, y) = ({lx:.3g}, {ly:.3g}) mm (paraxial), the sensor's half width is "
                f"{half[0]:.4g} x {half[1]:.4g} mm. Nothing computed; pass --allow-outside to compute it anyway")
        if abs(lx) > half[0] or abs(ly) > half[1]:
            notes.append(f"field {ang:g} deg lands near (x, y) = ({lx:.3g}, {ly:.3g}) mm (paraxial), past the "
                         f"sensor's half width {half[0]:.4g} x {half[1]:.4g} mm of {label} (largest field "
                         f"{fmax:.4g} deg, {why})")
    return notes


def _sensor_note(lens, pixel_um):
    """A note when a Zemax lens (no sensor in the file) runs on the default sensor without --pixel."""
    if pixel_um is None and str(lens.source or "").lower().endswith(".zmx"):
        s = lens.sensor
        return (f"{Path(lens.source).name} has no sensor (a .zmx file holds none): using the default "
                f"{s.resolution[0]} x {s.resolution[1]} px of {s.pixel_pitch * 1e3:g} um; --pixel UM sets the pitch")
    return None


def _pixel_mm(a):
    if getattr(a, "pixel", None) is None:
        return None
    if not a.pixel > 0:
        raise ValueError(f"--pixel {a.pixel:g}: the pixel pitch must be > 0 um")
    return a.pixel * 1e-3


def _say(msg):
    """Progress and notes: stderr, so that stdout keeps the results."""
    sys.stderr.write(msg + "\n")
    sys.stderr.flush()


def _warn(msg):
    import warnings
    warnings.warn(msg, UserWarning, stacklevel=2)


def _save_psf(p, out):
    """A PSF as ``.npz`` (psf, pixel_mm, center_mm, field_deg (x, y), wavelength_um, model) or a ``.png``
    picture; another suffix is refused. Written under a temporary name, renamed on success."""
    out = Path(out)
    suffix = out.suffix.lower()
    if suffix == ".png":
        _atomic(out, lambda tmp: p.plot(path=tmp))
        return out
    if suffix != ".npz":
        raise ValueError(f"--out {out}: use a .npz path (the PSF with its pixel pitch and centre) or .png "
                         "(a picture)")

    def _npz(tmp):
        with open(tmp, "wb") as fh:
            np.savez(fh, psf=p.data, pixel_mm=np.float64(p.pixel_mm), center_mm=np.asarray(p.center_mm, float),
                     field_deg=np.asarray(_field_xy(p.field_deg), float), wavelength_um=np.float64(p.wavelength_um),
                     model=np.str_(p.model))
    _atomic(out, _npz)
    return out



def cmd_info(a):
    from . import paraxial
    lens = _lens(a.lens)
    wl = a.wavelength if a.wavelength is not None else _default_wavelength(lens)
    p = paraxial.pupils(lens, wl)
    print(f"{lens.name or a.lens}: {len(lens.surfaces)} surfaces, sensor {lens.sensor.resolution[0]}x"
          f"{lens.sensor.resolution[1]} px of {lens.sensor.pixel_pitch * 1e3:.4g} um")
    print(f"  at {wl} um:  EFL {lens.efl(wl):.6f} mm   BFL {lens.bfl(wl):.6f} mm   F/# {paraxial.f_number(lens, wl):.4f}")
    print(f"  entrance pupil z {p.entrance_z:.4f} mm radius {p.entrance_radius:.4f} mm;"
          f" exit pupil z {p.exit_z:.4f} mm radius {p.exit_radius:.4f} mm; stop surface {lens.stop_index}")
    for line in surface_table(lens):
        print("  " + line)
    if a.plot:
        from .plots import layout
        _atomic(a.plot, lambda tmp: layout(lens, tmp))
        print(f"  layout written to {a.plot}")


def cmd_psf(a):
    from .psf import psf
    lens = _lens(a.lens)
    if len(a.field) not in (1, 2):
        raise ValueError(f"--field takes one angle (y) or two (x y) in degrees, got {len(a.field)} values")
    field = tuple(a.field) if len(a.field) == 2 else a.field[0]
    wl = a.wavelength if a.wavelength is not None else _default_wavelength(lens)
    pixel_mm = _pixel_mm(a)
    for o in (a.out, a.plot):  # refuse a bad output name before computing
        if o is not None and Path(o).is_dir():
            raise ValueError(f"output {o} is a directory")
    if a.out is not None and Path(a.out).suffix.lower() not in (".npz", ".png"):
        raise ValueError(f"--out {a.out}: use a .npz path (the PSF with its pixel pitch and centre) or .png (a picture)")
    from . import checks
    checks.check_wavelengths([wl], lens)
    checks.check_device(a.device)
    for note in check_field_inside(lens, [field], wl, pixel_mm, a.allow_outside, label=a.lens):
        _warn(note)
    note = _sensor_note(lens, a.pixel)
    if note:
        _say("note: " + note)
    kw = dict(size=a.size, device=a.device, method=a.method, pixel_mm=pixel_mm, rays_per_sample=a.rays_per_sample,
              nyquist_safety=a.nyquist_safety, tolerance=a.tolerance)
    if a.dry_run:
        if a.model != "ray-wave":
            raise ValueError("--dry-run plans the ray-wave model only (--model ray-wave)")
        from .psf import plan_psf
        pl = plan_psf(lens, field, wl, **kw)
        print(pl.explain())
        return
    _say(f"rwwarp psf: {a.model} PSF of {a.lens}, field {field} deg, {wl:g} um, {a.size} px on {a.device} ...")
    p = psf(lens, field, wl, model=a.model, dtype=a.dtype, memory_budget_gb=a.memory_budget_gb,
            deterministic=a.deterministic, **kw)
    if a.explain and p.plan:
        from .wave.plan import Plan
        print(Plan(**p.plan).explain())
    print(f"PSF {a.model} field {field} deg, {wl:g} um: {a.size} px of {p.pixel_mm * 1e3:g} um, sum "
          f"{p.data.sum():.6f}, peak {p.data.max():.4g}, centre ({p.center_mm[0]:.5f}, {p.center_mm[1]:.5f}) mm, "
          f"{p.info.get('time_s', 0):.2f} s")
    if not np.all(np.isfinite(p.data)):
        raise FloatingPointError("the PSF has non-finite values; nothing written")
    if a.out:
        print(f"  saved {_save_psf(p, a.out)}")
    if a.plot:
        _atomic(a.plot, lambda tmp: p.plot(path=tmp))
        print(f"  picture written to {a.plot}")


def _map(lens, fields, wls, a, out: Path, title):
    from .psf import psf_map
    t = time.perf_counter()
    m = psf_map(lens, fields, wls, model=a.model, size=a.size, device=a.device, progress=True,
                batch=getattr(a, "batch", None) or len(wls), pixel_mm=_pixel_mm(a),
                rays_per_sample=getattr(a, "rays_per_sample", 1.0), memory_budget_gb=getattr(a, "memory_budget_gb", None),
                nyquist_safety=getattr(a, "nyquist_safety", 2.0))
    dt = time.perf_counter() - t
    _save_map(m, fields, wls, out, title)
    return m, dt


def _save_map(m, fields, wls, out: Path, title):
    """``title.npz``, ``title_log.png`` and (three wavelengths) ``title_rgb.png`` of a map in ``out``.

    The ``.npz`` holds plain arrays (``np.load`` without ``allow_pickle``): ``psf`` (n_fields, n_wavelengths,
    size, size), ``centers_mm`` (n_fields, n_wavelengths, 2), ``pixel_mm``, ``fields_deg`` (n_fields, 2: x, y
    in deg), ``wavelengths_um`` and ``model``."""
    from .plots import psf_map_figure, rgb_psf_map
    if not np.all(np.isfinite(m.data)):
        raise FloatingPointError("the PSF map has non-finite values; nothing written")

    def _npz(tmp):
        with open(tmp, "wb") as fh:
            np.savez(fh, psf=m.data, centers_mm=m.centers_mm, pixel_mm=m.pixel_mm,
                     fields_deg=np.array([_field_xy(f) for f in fields], dtype=float),
                     wavelengths_um=np.array(wls, dtype=float), model=np.str_(m.model))
    _atomic(out / f"{title}.npz", _npz)
    _atomic(out / f"{title}_log.png", lambda tmp: psf_map_figure(m, tmp))
    if len(wls) == 3:
        _atomic(out / f"{title}_rgb.png", lambda tmp: rgb_psf_map(m, tmp))


def cmd_map(a):
    import os
    from . import checks
    lens = _lens(a.lens)
    wls = a.wavelengths or lens.wavelengths_um
    checks.check_wavelengths(list(wls), lens)
    checks.check_device(a.device)
    fields = _map_fields(lens, a, _default_wavelength(lens))
    for note in check_field_inside(lens, fields, _default_wavelength(lens), _pixel_mm(a), a.allow_outside,
                                   label=a.lens):
        _warn(note)
    note = _sensor_note(lens, a.pixel)
    if note:
        _say("note: " + note)
    _say(f"rwwarp map: {len(fields)} fields ({', '.join(f'{_field_xy(f)[1]:g}' for f in fields)} deg) x "
         f"{len(wls)} wavelengths ({', '.join(f'{w:g}' for w in wls)} um) of {a.lens} on {a.device} ...")
    procs = getattr(a, "procs", 1)
    if procs > 1 or int(os.environ.get("WORLD_SIZE", "1") or 1) > 1:
        # several processes (rwwarp.distributed): started here through torch's launcher, or already
        # started by an external torchrun (WORLD_SIZE set: this process is one rank)
        from .distributed import DistributedError, launch
        spec = {"lens": a.lens, "fields": fields, "wls": list(wls), "model": a.model, "size": a.size,
                "device": a.device, "batch": a.batch, "out": str(a.out), "pixel_mm": _pixel_mm(a),
                "rays_per_sample": a.rays_per_sample, "memory_budget_gb": a.memory_budget_gb,
                "nyquist_safety": a.nyquist_safety}
        if int(os.environ.get("WORLD_SIZE", "1") or 1) > 1:
            if procs > 1:
                raise ValueError("--procs with an external launcher (WORLD_SIZE is set): use one or the other")
            res = _map_worker(spec)
            if res is None:
                return
        else:
            try:
                res = launch(_map_worker, procs, spec)[0]
            except DistributedError as e:
                sys.stderr.write(f"rwwarp map: error: {_one_line(e)}\n")
                sys.exit(1)
        n, dt, ranks = res
        print(f"{n} PSFs on {len(ranks)} processes in {dt:.2f} s ({n / dt:.2f} PSF/s; per rank: "
              + ", ".join(f"{r['psfs']} PSFs in {r['work_s']:.1f} s" for r in ranks) + f"); written to {a.out}/")
        return
    m, dt = _map(lens, fields, wls, a, Path(a.out), "psf_map")
    print(f"{m.data.shape[0]} fields x {m.data.shape[1]} wavelengths in {dt:.2f} s "
          f"({m.data.shape[0] * m.data.shape[1] / dt:.2f} PSF/s); written to {a.out}/")


def _map_fields(lens, a, wl):
    """The fields of ``rwwarp map``/``demo`` as (x, y) deg: ``--fields`` (angles), else ``--n-fields`` evenly
    from 0 to ``--max-field`` (default the lens's largest field), else the lens file's own fields, else 0, 0.7
    and 1 x the sensor's half height through the EFL."""
    if a.fields is not None and (a.n_fields is not None or a.max_field is not None):
        raise ValueError("--fields lists the angles; --n-fields/--max-field space them evenly: use one or the other")
    if a.fields is not None:
        return [(0.0, float(f)) for f in a.fields]
    if a.n_fields is not None or a.max_field is not None:
        top = a.max_field if a.max_field is not None else lens_max_field(lens, wl)[0]
        n = a.n_fields if a.n_fields is not None else 3
        return [(0.0, float(f)) for f in np.linspace(0.0, top, n)]
    from .report import _default_fields
    return [_field_xy(f) for f in _default_fields(lens, wl)]


def _map_worker(spec):
    """One rank of ``rwwarp map --procs N``: the sharded map (rwwarp.distributed.psf_map), written by
    rank 0, which returns (PSFs, seconds, per-rank info); None on the other ranks."""
    from .distributed import psf_map
    _quiet_warp(spec["device"])  # each rank is its own process
    t = time.perf_counter()
    m = psf_map(_lens(spec["lens"]), spec["fields"], spec["wls"], model=spec["model"], size=spec["size"],
                device=spec["device"], batch=spec["batch"] or len(spec["wls"]), progress=True,
                pixel_mm=spec.get("pixel_mm"), rays_per_sample=spec.get("rays_per_sample", 1.0),
                memory_budget_gb=spec.get("memory_budget_gb"), nyquist_safety=spec.get("nyquist_safety", 2.0))
    if m is None:
        return None
    dt = time.perf_counter() - t
    _save_map(m, spec["fields"], spec["wls"], Path(spec["out"]), "psf_map")
    return m.data.shape[0] * m.data.shape[1], dt, m.info["ranks"]


def cmd_demo(a):
    """The main job on a bundled lens: paraxial data, layout, the A489 with a modest achromatising DOE (what it
    changes on axis, against the DOE as bundled) and an RGB multi-field ray-wave PSF map on patches that fit."""
    from . import paraxial
    from .demo import doe_effect_figure, run
    from .io import load_lens
    from .plots import layout
    lens = load_lens(a.lens)
    out = Path(a.out)
    wl = 0.55
    t0 = time.perf_counter()
    print(f"rwwarp demo: {lens.name} ({a.lens}) on device {a.device}")
    print(f"  EFL {lens.efl(wl):.4f} mm, BFL {lens.bfl(wl):.4f} mm, F/# {paraxial.f_number(lens, wl):.3f} at {wl} um")
    if a.fields is None and a.n_fields is None and a.max_field is None:
        a.n_fields, a.max_field = 3, 14.0  # the A489: 14 deg is the sensor corner
    fields = _map_fields(lens, a, wl)
    fmax = max(f[1] for f in fields)
    r = run(lens, fields, size=a.size, device=a.device, batch=a.batch, doe_strength=a.doe_strength)
    lens, m, d = r["lens"], r["map"], r["doe"]
    wls = list(lens.wavelengths_um)
    if d is not None:
        print(f"  DOE (surface {d['doe_surface']}): {a.doe_strength:g} x the paraxial achromat's phase, a1 = "
              f"{d['a1_rad']:.2f} rad rho^2 (f = {d['doe_focal_length_mm']:.1f} mm at its design wavelength); "
              f"sensor moved {d['sensor_shift_mm'] * 1e3:+.1f} um with the {wl} um focus")
        print("  axial colour (paraxial focus - at 0.55 um), um: "
              + ", ".join(f"{w:g}: {b:+.1f} -> {c:+.1f}" for w, b, c in
                          zip(d["wavelengths_um"], d["focal_shift_before_um"], d["focal_shift_after_um"])))
    _save_map(m, fields, wls, out, "psf_map")
    _atomic(out / "layout.png", lambda tmp: layout(lens, tmp, fields_deg=[0.0, fmax / 2, fmax]))
    written = ["layout.png", "psf_map_log.png"] + (["psf_map_rgb.png"] if len(wls) == 3 else []) + ["psf_map.npz"]
    how = "--size" if a.size else "fits every PSF: farthest ray of each DOE order carrying >= 2 % + 10 Airy radii"
    print(f"  ray-wave PSF map: {len(fields)} fields x {len(wls)} wavelengths, {r['size']}^2 px of "
          f"{m.pixel_mm * 1e3:g} um ({how}), {r['time_s']:.1f} s ({m.data.shape[0] * m.data.shape[1] / r['time_s']:.2f} PSF/s)")
    inside = m.info["power_in_patch"]
    print("    power inside the patch (of the traced power), " + " / ".join(f"{w:g}" for w in wls) + " um:")
    for i, f in enumerate(fields):
        print(f"    field {f[1]:5.2f} deg: " + " ".join(f"{v:.3f}" for v in inside[i])
              + f"   centre y {m.centers_mm[i, 0, 1]:.4f} mm")
    if r["reference"] is not None:
        ref = r["reference"]
        from .demo import crop
        n = ref.data.shape[-1]
        pk_ref = ref.data[0].max(axis=(1, 2))
        pk = crop(m.data[0], n).max(axis=(1, 2))
        print(f"  on axis, peak per pixel with the demo DOE / the DOE as bundled (flat; {r['reference_time_s']:.1f} s): "
              + ", ".join(f"{w:g} um {p / q:.2f}x" for w, p, q in zip(wls, pk, pk_ref)))
        _atomic(out / "doe_effect.png", lambda tmp: doe_effect_figure(r, tmp))
        written.insert(1, "doe_effect.png")
    print(f"  wrote {out}/" + ", ".join(written) + f" ({time.perf_counter() - t0:.1f} s in all)")


def cmd_validate(a):
    from .validate import run_validation
    rep = run_validation(Path(a.out), device=a.device, quick=a.quick, progress=_say)
    print(rep)


def _plugin_command(name: str):
    """The callable registered as ``name`` in the ``rwwarp.commands`` entry point group (``pip install -e .``
    writes the group from pyproject.toml; ImportError when nothing registers it or it cannot be imported)."""
    from importlib.metadata import entry_points

    found = entry_points(group="rwwarp.commands", name=name)
    if not found:
        raise ImportError(f"no {name!r} command in the entry point group 'rwwarp.commands' (is rwwarp installed "
                          "with pip install -e '.[torch]'?)")
    return next(iter(found)).load()


def _design_status_fast():
    """``torch_bridge.runs.cli_status`` loaded from its file alone (standard library only, no torch, no
    package import), or None when torch_bridge is not found."""
    import importlib.util
    spec = importlib.util.find_spec("torch_bridge")
    if spec is None or not spec.submodule_search_locations:
        return None
    path = Path(list(spec.submodule_search_locations)[0]) / "runs.py"
    if not path.exists():
        return None
    mspec = importlib.util.spec_from_file_location("_rwwarp_design_runs", path)
    mod = importlib.util.module_from_spec(mspec)
    mspec.loader.exec_module(mod)
    return mod.cli_status


def cmd_design(a):
    """End-to-end design from a YAML/TOML config (torch_bridge; needs torch). torch_bridge is a layer above
    rwwarp: the command is found through the ``rwwarp.commands`` entry point group (pyproject.toml), not
    imported here."""
    if a.config == "status":
        # read from another process while a run goes on: without importing torch (seconds) when possible
        fast = _design_status_fast()
        if fast is not None:
            sys.exit(fast(a.rest))
    try:
        train_main = _plugin_command("design")
    except ImportError as e:
        sys.exit(f"rwwarp design needs torch and torch_bridge ({e}); install with: pip install 'rwwarp[torch]'")
    try:
        code = train_main([a.config] + a.rest)
    except UnicodeError as e:
        raise ValueError(f"config {a.config}: not a UTF-8 text file ({e.reason} at byte {getattr(e, 'start', '?')})") from None
    sys.exit(code)


def cmd_bench(a):
    import subprocess
    import re
    if a.what is None:
        names = _benchmarks()
        print("rwwarp bench NAME [options]: the benchmarks in perf/: " + (", ".join(names) if names else
              "none found (they live in perf/ of the source checkout)"))
        return
    if not re.fullmatch(r"[A-Za-z0-9_]+", a.what):
        raise ValueError(f"no benchmark {a.what!r} (a name such as trace, psf, map, bridge)")
    script = Path(__file__).resolve().parents[1] / "perf" / f"bench_{a.what}.py"
    if not script.exists():
        raise ValueError(f"no benchmark {script} (benchmarks live in perf/ of the source checkout)")
    sys.exit(subprocess.call([sys.executable, str(script)] + a.rest))


def cmd_report(a):
    """A lens report: PNG figures and report.md in a folder (rwwarp.report)."""
    from .report import write_report
    out = Path(a.out or Path("out/report") / Path(a.lens).stem)
    page = write_report(_lens(a.lens), out, fields_deg=a.fields, model=a.model, psf_size=a.psf_size,
                        mtf_size=a.mtf_size, through_focus_planes=a.through_focus, device=a.device,
                        progress=not a.quiet, lens_label=a.lens)
    print(f"report written to {page}")


class _Help(argparse.ArgumentDefaultsHelpFormatter):
    """--help with each option's default (none shown where it has none)."""

    def _get_help_string(self, action):
        h = action.help or ""
        if action.default in (None, False, argparse.SUPPRESS) or "default" in h or not action.option_strings:
            return h
        return h + " (default: %(default)s)"


def _add_knobs(p, batch=True):
    """The knobs that the memory and sampling errors name (batch=, rays_per_sample, memory_budget_gb)."""
    p.add_argument("--pixel", type=_finite, default=None, metavar="UM",
                   help="sensor pixel pitch, um (default: the lens's sensor; a .zmx file has none: 4 um)")
    p.add_argument("--rays-per-sample", type=_finite, default=1.0,
                   help="rays per wave-plane sample along each axis (fewer: less memory and time, coarser)")
    p.add_argument("--memory-budget-gb", type=_finite, default=None,
                   help="refuse plans estimated above this many GiB (default: half the available memory)")
    p.add_argument("--nyquist-safety", type=_finite, default=2.0,
                   help="wave-plane samples per Nyquist limit of the highest local frequency (lower: coarser, cheaper)")
    if batch:
        p.add_argument("--batch", type=_positive_int, default=None,
                       help="(field, wavelength) sources per launch (default: the wavelengths of one field)")
    p.add_argument("--allow-outside", action="store_true",
                   help="compute fields beyond the lens's largest field (refused by default)")


_MODEL_HELP = ("ray-wave (the paper's model), ray (geometric; the DOE as a local grating) or paraxial-wave (an ideal "
               "thin lens + the wave path)")


def _build_parser():
    lens_help = _lens_help()
    ap = _Parser(prog="rwwarp", description=__doc__.splitlines()[0] + " Bundled lenses: "
                 + ", ".join(bundled_lenses()) + ".", formatter_class=_Help)
    ap.add_argument("--debug", action="store_true", help="show the Python traceback of an error")
    from . import __version__
    ap.add_argument("--version", action="version", version=f"rwwarp {__version__}")
    sub = ap.add_subparsers(dest="cmd", required=True, parser_class=_Parser)

    def add(name, **kw):
        return sub.add_parser(name, formatter_class=_Help, **kw)

    p = add("info", help="paraxial data and surface table; --plot writes a layout PNG")
    p.add_argument("lens", help=lens_help)
    p.add_argument("--wavelength", type=_finite, default=None,
                   help="um (default: the lens's primary wavelength, else the middle of its wavelengths)")
    p.add_argument("--plot", default=None, help="layout PNG path")
    p.set_defaults(func=cmd_info)

    p = add("psf", help="one PSF (.npz with its pitch and centre, or a PNG)")
    p.add_argument("lens", help=lens_help)
    p.add_argument("--field", type=_finite, nargs="+", default=[0.0], help="deg: y, or x y")
    p.add_argument("--wavelength", type=_finite, default=None,
                   help="um (default: the lens's primary wavelength, else the middle of its wavelengths)")
    p.add_argument("--model", default="ray-wave", choices=["ray-wave", "ray", "paraxial-wave"], help=_MODEL_HELP)
    p.add_argument("--size", type=_positive_int, default=64, help="patch side, sensor pixels")
    p.add_argument("--device", default="cpu", help="cpu, cuda, cuda:N or opencl:P:D")
    p.add_argument("--dtype", default="float64", choices=["float64", "float32"], help="ray-tracing precision")
    p.add_argument("--explain", action="store_true", help="print the sampling plan and why")
    p.add_argument("--dry-run", action="store_true", help="print the plan and its memory/work estimate, compute nothing")
    from .wave.methods import choices as method_choices   # the registered methods (rwwarp.wave.methods)
    p.add_argument("--method", default="auto", choices=list(method_choices()), help="wave propagation: focal (follows the patch), asm (whole beam), auto, two-step (auto + wave step), pixel (pixels many Airy radii wide), direct (Rayleigh-Sommerfeld sum, small cases)")
    p.add_argument("--tolerance", type=_finite, default=None, help="error accepted (of the peak): auto adds the wave step above it, picks pixel below it")
    p.add_argument("--deterministic", action="store_true",
                   help="the same bits on every run on a GPU too (fixed-point splat sums)")
    _add_knobs(p, batch=False)
    p.add_argument("--out", default=None, help="FILE.npz (psf, pixel_mm, center_mm, field_deg, wavelength_um, "
                                               "model) or FILE.png (a picture)")
    p.add_argument("--plot", default=None, help="PNG picture of the PSF (log scale, axes in um)")
    p.set_defaults(func=cmd_psf)

    for name, fn, helptext in (("map", cmd_map, "multi-field RGB PSF map (PNG + .npz)"),
                               ("demo", cmd_demo, "the main job on a bundled lens (CPU by default)")):
        p = add(name, help=helptext)
        if name == "map":
            p.add_argument("lens", help=lens_help)
            p.add_argument("--wavelengths", type=_finite, nargs="+", default=None,
                           help="um (default: the lens's wavelengths)")
            p.add_argument("--model", default="ray-wave", choices=["ray-wave", "ray", "paraxial-wave"], help=_MODEL_HELP)
        else:
            p.add_argument("--lens", default="a489_doe", help=lens_help)
            p.add_argument("--doe-strength", type=_finite, default=0.25,
                           help="DOE phase as a fraction of the paraxial achromat's (0: the lens's DOE as it is)")
        p.add_argument("--fields", type=_finite, nargs="+", default=None,
                       help="y field angles, deg (as rwwarp report --fields); default: "
                            + ("the lens's own fields, else 0, 0.7 and 1 x the sensor half height" if name == "map"
                               else "3 fields from 0 to 14 deg (the A489's sensor corner)"))
        p.add_argument("--n-fields", type=_positive_int, default=None,
                       help="instead of --fields: this many fields evenly from 0 to --max-field (default 3)")
        p.add_argument("--max-field", type=_finite, default=None,
                       help="deg, with --n-fields (default: the lens's largest field)")
        p.add_argument("--size", type=_positive_int, default=64 if name == "map" else None,
                       help="patch, sensor pixels" + ("" if name == "map" else " (default: one that fits every PSF)"))
        p.add_argument("--device", default="cpu", help="cpu, cuda, cuda:N or opencl:P:D")
        if name == "map":
            _add_knobs(p)
            p.add_argument("--procs", type=_positive_int, default=1,
                           help="processes (torch.distributed ranks, started through torch's launcher; each on "
                                "its own device: cuda:LOCAL_RANK or the CPU); sources balanced by estimated work")
        else:
            p.add_argument("--batch", type=_positive_int, default=None, help="sources per launch")
        p.add_argument("--out", default="out/" + name, help="folder")
        p.set_defaults(func=fn)

    p = add("validate", help="ray-wave vs scalar-diffraction ground truth (report + PNG)")
    p.add_argument("--out", default="out/validate", help="folder")
    p.add_argument("--device", default="cpu", help="cpu, cuda, cuda:N or opencl:P:D")
    p.add_argument("--quick", action="store_true", help="smaller sizes")
    p.set_defaults(func=cmd_validate)

    p = add("design", help="end-to-end lens + DOE + network design from a YAML/TOML config "
                           "(rwwarp design --help lists its options)", add_help=False)
    p.add_argument("config")
    p.add_argument("rest", nargs=argparse.REMAINDER, help="options passed to torch_bridge.train")
    p.set_defaults(func=cmd_design)

    p = add("report", help="lens report: layout, spots, PSFs, MTF, through focus, encircled energy, "
                           "colour, field curves, DOE (PNGs + report.md)")
    p.add_argument("lens", help=lens_help)
    p.add_argument("--out", default=None, help="folder (default out/report/<lens>)")
    p.add_argument("--fields", type=_finite, nargs="+", default=None,
                   help="y field angles, deg (default: the lens's own fields, else 0, 0.7 and 1 x the sensor half height)")
    p.add_argument("--model", default="ray-wave", choices=["ray-wave", "ray", "paraxial-wave"], help=_MODEL_HELP)
    p.add_argument("--psf-size", type=_positive_int, default=None, help="PSF tile, sensor pixels (default: fits)")
    p.add_argument("--mtf-size", type=_positive_int, default=None,
                   help="finely sampled PSF for MTF/EE, samples (default: fits, at most 256)")
    p.add_argument("--through-focus", type=int, default=9, help="planes (0: skip)")
    p.add_argument("--device", default="cpu", help="cpu, cuda, cuda:N or opencl:P:D")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_report)

    p = add("bench", help="run a benchmark from perf/ (" + ", ".join(_benchmarks()) + "); "
                          "rwwarp bench alone lists them")
    p.add_argument("what", nargs="?", default=None, help="benchmark name")
    p.add_argument("rest", nargs=argparse.REMAINDER, help="options passed to the benchmark script")
    p.set_defaults(func=cmd_bench)

    for name, sp in sub.choices.items():
        if name not in ("design", "bench"):  # those pass their remaining options on
            sp.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                            help="show the Python traceback of an error")
    return ap


def _benchmarks() -> list:
    d = Path(__file__).resolve().parents[1] / "perf"
    return sorted(p.stem[len("bench_"):] for p in d.glob("bench_*.py")) if d.is_dir() else []


def main(argv=None):
    argv = list(sys.argv[1:] if argv is None else argv)
    cmd_at = next((i for i, v in enumerate(argv) if not v.startswith("-")), None)
    if cmd_at is not None and argv[cmd_at] == "design" and (len(argv) == cmd_at + 1
                                                              or argv[cmd_at + 1] in ("-h", "--help")):
        # the options live in torch_bridge.train (found through the rwwarp.commands entry point)
        try:
            train_main = _plugin_command("design")
        except ImportError as e:
            sys.exit(f"rwwarp design needs torch and torch_bridge ({e}); install with: pip install 'rwwarp[torch]'")
        sys.exit(train_main(["--help"]))
    import warnings
    shown = warnings.showwarning
    _setup_warnings()
    try:
        a = _build_parser().parse_args(argv)
        return _run(a, debug=a.debug)
    finally:
        warnings.showwarning = shown


_SEEN_WARNINGS: set = set()


def _show_warning(message, category, filename, lineno, file=None, line=None):
    """A warning as one line ``warning: ...`` on stderr, each text once per command."""
    text = _one_line(message)
    if text in _SEEN_WARNINGS:
        return
    _SEEN_WARNINGS.add(text)
    (file or sys.stderr).write(f"warning: {text}\n")


def _setup_warnings():
    import warnings
    _SEEN_WARNINGS.clear()
    warnings.showwarning = _show_warning


def _cuda_driver_present() -> bool:
    """Whether the NVIDIA driver library loads (then Warp has no CUDA warning to print)."""
    import ctypes
    for name in ("libcuda.so.1", "libcuda.so", "nvcuda.dll"):
        try:
            ctypes.CDLL(name)
            return True
        except OSError:
            continue
    return False


def _quiet_warp(device):
    """Initialise Warp with its native 'Warp CUDA warning: Could not find or load the NVIDIA CUDA driver' kept
    off stderr when no GPU is asked for (``device`` not cuda), or, for a command without a device option
    (``rwwarp design``: the config names it), when there is no NVIDIA driver at all."""
    import os
    if device is not None and str(device).startswith("cuda"):
        return
    if device is None and _cuda_driver_present():  # rwwarp design: its config may ask for a GPU
        return
    try:
        from .trace import init_warp
    except ImportError:
        return
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
            try:
                init_warp()
            finally:
                os.dup2(saved, 2)
    finally:
        os.close(saved)


def _run(a, debug=False):
    """Run a parsed command: bad input prints one line and exits 2; no OpenCL platform says what to install
    and exits 3; --debug adds the traceback."""
    import traceback

    from .errors import LensError
    prog = f"rwwarp {a.cmd}"
    try:
        if a.cmd not in ("bench", "info") and getattr(a, "config", None) != "status":  # status: no imports
            _quiet_warp(getattr(a, "device", None))
        return a.func(a)
    except KeyboardInterrupt:
        sys.stderr.write(f"{prog}: interrupted\n")
        sys.exit(130)
    except SystemExit:
        raise
    except Exception as e:  # noqa: BLE001 - each kind gets its one line
        if debug:
            traceback.print_exc()
        if _no_opencl(e):
            sys.stderr.write(f"{prog}: error: {OPENCL_MISSING} ({type(e).__name__}: {_one_line(e)})\n")
            sys.exit(EXIT_NO_OPENCL)
        if isinstance(e, (LensError, ValueError, TypeError, OSError, FloatingPointError, MemoryError, ImportError)):
            what = "" if isinstance(e, (LensError, ValueError)) else f"{type(e).__name__}: "
            text = _one_line(e)
            if isinstance(e, MemoryError) or "rays_per_sample" in text:
                text = cli_knob_names(text, a)
            sys.stderr.write(f"{prog}: error: {what}{text}\n")
            sys.exit(EXIT_BAD_INPUT)
        # a bug, not bad input: still one line without --debug
        sys.stderr.write(f"{prog}: internal error: {type(e).__name__}: {_one_line(e)} "
                         "(run with --debug for the traceback and please report it)\n")
        sys.exit(1)


#: the API knobs that error messages name -> the command-line option that sets each
_KNOBS = (("batch=...", "--batch N"), ("memory_budget_gb", "--memory-budget-gb"),
          ("rays_per_sample", "--rays-per-sample"), ("nyquist_safety", "--nyquist-safety"),
          ("size (patch pixels)", "--size (patch pixels)"))


def cli_knob_names(text: str, a=None) -> str:
    """An API error message with each knob it names followed by the option of this command that sets it
    (``rays_per_sample`` -> ``rays_per_sample (--rays-per-sample)``); knobs the command lacks stay as they are."""
    import re
    for api, flag in _KNOBS:
        opt = flag.split()[0]
        if a is not None and not hasattr(a, opt[2:].replace("-", "_")):
            continue
        if api.startswith(("size", "batch")):
            text = text.replace(api, flag)
        else:
            text = re.sub(rf"(?<![\w-]){re.escape(api)}(?![\w(])", f"{api} ({flag})", text)
    return text


#: what a machine without an OpenCL platform lacks (README, Install)
OPENCL_MISSING = ("no OpenCL platform found: rwwarp's wave propagation runs on OpenCL. Install one: on the CPU "
                  "PoCL (Debian/Ubuntu: sudo apt-get install pocl-opencl-icd ocl-icd-libopencl1; conda: conda "
                  "install -c conda-forge pocl; or pip install pocl-binary-distribution), or your GPU vendor's "
                  "OpenCL driver; check with: python -c \"import pyopencl as cl; print(cl.get_platforms())\"")
EXIT_NO_OPENCL = 3


def _no_opencl(e) -> bool:
    """True for pyopencl's 'no platform' error (clGetPlatformIDs failed / PLATFORM_NOT_FOUND_KHR)."""
    text = f"{type(e).__name__} {e}"
    return ("clGetPlatformIDs" in text or "PLATFORM_NOT_FOUND" in text or "no OpenCL platform" in text
            or "no OpenCL CPU device" in text)


if __name__ == "__main__":
    main()
