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


from .lens import surface_table  # noqa: E402  (rwwarp info's table; its home: lens)


def cmd_info(a):
    from . import paraxial
    lens = _lens(a.lens)
    wl = a.wavelength if a.wavelength is not None else lens.wavelengths_um[len(lens.wavelengths_um) // 2]
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
    if a.dry_run:
        if a.model != "ray-wave":
            raise ValueError("--dry-run plans the ray-wave model only (--model ray-wave)")
        from .psf import plan_psf
        pl = plan_psf(lens, field, a.wavelength, size=a.size, device=a.device, method=a.method)
        print(pl.explain())
        return
    p = psf(lens, field, a.wavelength, model=a.model, size=a.size, device=a.device, dtype=a.dtype,
            method=a.method, memory_budget_gb=a.memory_budget_gb, deterministic=a.deterministic)
    if a.explain and p.plan:
        from .plan import Plan
        print(Plan(**p.plan).explain())
    print(f"PSF {a.model} field {field} deg, {a.wavelength} um: sum {p.data.sum():.6f}, peak {p.data.max():.4g}, "
          f"centre ({p.center_mm[0]:.5f}, {p.center_mm[1]:.5f}) mm, {p.info.get('time_s', 0):.2f} s")
    if a.out:
        out = a.out if str(a.out).endswith(".npy") else str(a.out) + ".npy"  # as numpy.save names it

        def _save(tmp):
            with open(tmp, "wb") as fh:
                np.save(fh, p.data)
        _atomic(out, _save)
        print(f"  saved {out}")


def _map(lens, fields, wls, a, out: Path, title):
    from .psf import psf_map
    t = time.perf_counter()
    m = psf_map(lens, fields, wls, model=a.model, size=a.size, device=a.device, progress=True,
                batch=getattr(a, "batch", None) or len(wls))
    dt = time.perf_counter() - t
    _save_map(m, fields, wls, out, title)
    return m, dt


def _save_map(m, fields, wls, out: Path, title):
    """``title.npz``, ``title_log.png`` and (three wavelengths) ``title_rgb.png`` of a map in ``out``."""
    from .plots import psf_map_figure, rgb_psf_map
    if not np.all(np.isfinite(m.data)):
        raise FloatingPointError("the PSF map has non-finite values; nothing written")

    def _npz(tmp):
        with open(tmp, "wb") as fh:
            np.savez(fh, psf=m.data, centers_mm=m.centers_mm, pixel_mm=m.pixel_mm,
                     fields_deg=np.array(fields, dtype=object), wavelengths_um=np.array(wls))
    _atomic(out / f"{title}.npz", _npz)
    _atomic(out / f"{title}_log.png", lambda tmp: psf_map_figure(m, tmp))
    if len(wls) == 3:
        _atomic(out / f"{title}_rgb.png", lambda tmp: rgb_psf_map(m, tmp))


def cmd_map(a):
    import os
    lens = _lens(a.lens)
    fields = [(0.0, f) for f in np.linspace(0, a.max_field, a.fields)]
    wls = a.wavelengths or lens.wavelengths_um
    procs = getattr(a, "procs", 1)
    if procs > 1 or int(os.environ.get("WORLD_SIZE", "1") or 1) > 1:
        # several processes (rwwarp.distributed): started here through torch's launcher, or already
        # started by an external torchrun (WORLD_SIZE set: this process is one rank)
        from .distributed import DistributedError, launch
        spec = {"lens": a.lens, "fields": fields, "wls": list(wls), "model": a.model, "size": a.size,
                "device": a.device, "batch": a.batch, "out": str(a.out)}
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


def _map_worker(spec):
    """One rank of ``rwwarp map --procs N``: the sharded map (rwwarp.distributed.psf_map), written by
    rank 0, which returns (PSFs, seconds, per-rank info); None on the other ranks."""
    from .distributed import psf_map
    t = time.perf_counter()
    m = psf_map(_lens(spec["lens"]), spec["fields"], spec["wls"], model=spec["model"], size=spec["size"],
                device=spec["device"], batch=spec["batch"] or len(spec["wls"]), progress=True)
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
    fields = [(0.0, f) for f in np.linspace(0.0, a.max_field, a.fields)]
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
    _atomic(out / "layout.png", lambda tmp: layout(lens, tmp, fields_deg=[0.0, a.max_field / 2, a.max_field]))
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
    rep = run_validation(Path(a.out), device=a.device, quick=a.quick)
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


def main(argv=None):
    ap = _Parser(prog="rwwarp", description=__doc__.splitlines()[0])
    ap.add_argument("--debug", action="store_true", help="show the Python traceback of an error")
    from . import __version__
    ap.add_argument("--version", action="version", version=f"rwwarp {__version__}")
    sub = ap.add_subparsers(dest="cmd", required=True)

    p = sub.add_parser("info", help="paraxial data and surface table; --plot writes a layout PNG")
    p.add_argument("lens")
    p.add_argument("--wavelength", type=_finite, default=None, help="um")
    p.add_argument("--plot", default=None, help="layout PNG path")
    p.set_defaults(func=cmd_info)

    p = sub.add_parser("psf", help="one PSF")
    p.add_argument("lens")
    p.add_argument("--field", type=_finite, nargs="+", default=[0.0], help="deg: y, or x y")
    p.add_argument("--wavelength", type=_finite, default=0.55, help="um")
    p.add_argument("--model", default="ray-wave", choices=["ray-wave", "ray", "paraxial-wave"])
    p.add_argument("--size", type=_positive_int, default=64)
    p.add_argument("--device", default="cpu")
    p.add_argument("--dtype", default="float64", choices=["float64", "float32"])
    p.add_argument("--explain", action="store_true", help="print the sampling plan and why")
    p.add_argument("--dry-run", action="store_true",
                   help="print the plan and its memory/work estimate, compute nothing")
    p.add_argument("--method", default="auto", choices=["auto", "focal", "asm"],
                   help="wave propagation: focal (follows the patch), asm (whole beam), auto")
    p.add_argument("--memory-budget-gb", type=_finite, default=None,
                   help="refuse plans estimated above this (default: half the available memory)")
    p.add_argument("--deterministic", action="store_true",
                   help="the same bits on every run on a GPU too (fixed-point splat sums)")
    p.add_argument("--out", default=None, help=".npy path")
    p.set_defaults(func=cmd_psf)

    for name, fn, helptext in (("map", cmd_map, "multi-field RGB PSF map (PNG + .npz)"),
                               ("demo", cmd_demo, "the main job on a bundled lens (CPU by default)")):
        p = sub.add_parser(name, help=helptext)
        if name == "map":
            p.add_argument("lens")
            p.add_argument("--wavelengths", type=_finite, nargs="+", default=None, help="um")
            p.add_argument("--model", default="ray-wave", choices=["ray-wave", "ray", "paraxial-wave"])
            p.add_argument("--max-field", type=_finite, default=14.0, help="deg")
            p.add_argument("--fields", type=_positive_int, default=5)
        else:
            p.add_argument("--lens", default="a489_doe")
            p.add_argument("--max-field", type=_finite, default=14.0, help="deg (A489: 14 deg is the sensor corner)")
            p.add_argument("--fields", type=_positive_int, default=3)
            p.add_argument("--doe-strength", type=_finite, default=0.25,
                           help="DOE phase as a fraction of the paraxial achromat's (0: the lens's DOE as it is)")
        p.add_argument("--size", type=_positive_int, default=64 if name == "map" else None,
                       help="patch, sensor pixels" + ("" if name == "map" else " (default: one that fits every PSF)"))
        p.add_argument("--device", default="cpu")
        p.add_argument("--batch", type=_positive_int, default=None, help="sources per launch")
        if name == "map":
            p.add_argument("--procs", type=_positive_int, default=1,
                           help="processes (torch.distributed ranks, started through torch's launcher; each on "
                                "its own device: cuda:LOCAL_RANK or the CPU); sources balanced by estimated work")
        p.add_argument("--out", default="out/" + name)
        p.set_defaults(func=fn)

    p = sub.add_parser("validate", help="ray-wave vs scalar-diffraction ground truth (report + PNG)")
    p.add_argument("--out", default="out/validate")
    p.add_argument("--device", default="cpu")
    p.add_argument("--quick", action="store_true", help="smaller sizes")
    p.set_defaults(func=cmd_validate)

    p = sub.add_parser("design", help="end-to-end lens + DOE + network design from a YAML/TOML config")
    p.add_argument("config")
    p.add_argument("rest", nargs=argparse.REMAINDER, help="options passed to torch_bridge.train")
    p.set_defaults(func=cmd_design)

    p = sub.add_parser("report", help="lens report: layout, spots, PSFs, MTF, through focus, encircled energy, "
                                      "colour, field curves, DOE (PNGs + report.md)")
    p.add_argument("lens")
    p.add_argument("--out", default=None, help="folder (default out/report/<lens>)")
    p.add_argument("--fields", type=_finite, nargs="+", default=None, help="y field angles, deg")
    p.add_argument("--model", default="ray-wave", choices=["ray-wave", "ray", "paraxial-wave"])
    p.add_argument("--psf-size", type=_positive_int, default=None, help="PSF tile, sensor pixels (default: fits)")
    p.add_argument("--mtf-size", type=_positive_int, default=None,
                   help="finely sampled PSF for MTF/EE, samples (default: fits, at most 256)")
    p.add_argument("--through-focus", type=int, default=9, help="planes (0: skip)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_report)

    p = sub.add_parser("bench", help="run a benchmark from perf/ (trace, psf, map, bridge)")
    p.add_argument("what")
    p.add_argument("rest", nargs=argparse.REMAINDER)
    p.set_defaults(func=cmd_bench)

    for name, sp in sub.choices.items():
        if name not in ("design", "bench"):  # those pass their remaining options on
            sp.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                            help="show the Python traceback of an error")
    argv = list(sys.argv[1:] if argv is None else argv)
    a = ap.parse_args(argv)
    return _run(a, debug=a.debug)


def _run(a, debug=False):
    """Run a parsed command: bad input prints one line and exits 2; --debug adds the traceback."""
    import traceback

    from .errors import LensError
    prog = f"rwwarp {a.cmd}"
    try:
        return a.func(a)
    except KeyboardInterrupt:
        sys.stderr.write(f"{prog}: interrupted\n")
        sys.exit(130)
    except SystemExit:
        raise
    except (LensError, ValueError, TypeError, OSError, FloatingPointError, MemoryError, ImportError) as e:
        if debug:
            traceback.print_exc()
        what = "" if isinstance(e, (LensError, ValueError)) else f"{type(e).__name__}: "
        sys.stderr.write(f"{prog}: error: {what}{_one_line(e)}\n")
        sys.exit(EXIT_BAD_INPUT)
    except Exception as e:  # noqa: BLE001 - a bug, not bad input: still one line without --debug
        if debug:
            traceback.print_exc()
        sys.stderr.write(f"{prog}: internal error: {type(e).__name__}: {_one_line(e)} "
                         "(run with --debug for the traceback and please report it)\n")
        sys.exit(1)


if __name__ == "__main__":
    main()
