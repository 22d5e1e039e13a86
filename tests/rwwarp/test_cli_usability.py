"""Command line and API usability (issue 28, "The command line and API"): PSFs and maps saved with their
metadata, the lens's own fields and wavelengths as defaults, fields outside the lens refused before computing,
one-line warnings, the knobs the errors name, help with defaults, short reprs and .plot(), print(lens)."""
import os
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

import rwwarp as rw
from rwwarp import cli
from rwwarp.cli import main

ROOT = Path(__file__).resolve().parents[2]
PNG = b"\x89PNG\r\n\x1a\n"


def _fails(argv, capsys):
    with pytest.raises(SystemExit) as e:
        main(argv)
    cap = capsys.readouterr()
    return e.value.code, cap.err


# ------------------------------------------------------------------------------------------- item 1: psf output
def test_psf_npz_holds_pitch_centre_field_and_loads_without_pickle(tmp_path, capsys):
    out = tmp_path / "p.npz"
    main(["psf", "cooke_triplet", "--field", "14", "--size", "16", "--pixel", "2.5", "--out", str(out)])
    z = np.load(out)  # allow_pickle=False: no object arrays
    assert z["psf"].shape == (16, 16) and z["pixel_mm"] == pytest.approx(0.0025)
    assert z["field_deg"].tolist() == [0.0, 14.0]
    assert z["wavelength_um"] == pytest.approx(0.5875618)  # the lens's primary (middle) wavelength, not 0.55
    assert str(z["model"]) == "ray-wave" and z["center_mm"].shape == (2,)
    assert 12.0 < z["center_mm"][1] < 13.0  # the 14 deg chief ray (EFL 50 mm)
    assert "of 2.5 um" in capsys.readouterr().out


def test_psf_pixel_changes_the_pitch(tmp_path):
    a, b = tmp_path / "a.npz", tmp_path / "b.npz"
    main(["psf", "a489_doe", "--size", "8", "--model", "ray", "--out", str(a)])
    main(["psf", "a489_doe", "--size", "8", "--model", "ray", "--pixel", "3", "--out", str(b)])
    assert np.load(a)["pixel_mm"] == pytest.approx(0.001) and np.load(b)["pixel_mm"] == pytest.approx(0.003)


def test_psf_out_png_and_plot_write_pictures(tmp_path):
    png, plot = tmp_path / "p.png", tmp_path / "q.png"
    main(["psf", "a489_doe", "--size", "8", "--model", "ray", "--out", str(png), "--plot", str(plot)])
    assert png.read_bytes()[:8] == PNG and plot.read_bytes()[:8] == PNG
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.png", "q.png"]  # not p.png.npy


def test_zemax_lens_without_pixel_says_which_sensor(tmp_path, capsys):
    zmx = ROOT / "rwwarp" / "lenses" / "cooke_triplet.zmx"
    main(["psf", str(zmx), "--size", "8", "--model", "ray"])
    err = capsys.readouterr().err
    assert "has no sensor" in err and "2000 x 2000 px of 4 um" in err and "--pixel" in err
    main(["psf", str(zmx), "--size", "8", "--model", "ray", "--pixel", "5"])
    assert "has no sensor" not in capsys.readouterr().err


def test_map_npz_loads_without_pickle_and_uses_the_lens_fields(tmp_path, capsys):
    main(["map", "cooke_triplet", "--model", "ray", "--size", "8", "--out", str(tmp_path)])
    z = np.load(tmp_path / "psf_map.npz")  # fields_deg used to be an object array
    assert z["fields_deg"].dtype == np.float64 and z["fields_deg"][:, 1].tolist() == [0.0, 14.0, 20.0]
    assert z["wavelengths_um"].tolist() == [0.4861327, 0.5875618, 0.6562725]
    assert z["psf"].shape == (3, 3, 8, 8) and str(z["model"]) == "ray"


def test_map_fields_are_angles_as_in_report_and_n_fields_spaces_them(tmp_path):
    main(["map", "a489_doe", "--model", "ray", "--size", "8", "--fields", "0", "5", "--wavelengths", "0.55",
          "--out", str(tmp_path / "a")])
    assert np.load(tmp_path / "a" / "psf_map.npz")["fields_deg"][:, 1].tolist() == [0.0, 5.0]
    main(["map", "cooke_triplet", "--model", "ray", "--size", "8", "--n-fields", "3", "--wavelengths", "0.55",
          "--out", str(tmp_path / "b")])
    assert np.load(tmp_path / "b" / "psf_map.npz")["fields_deg"][:, 1].tolist() == [0.0, 10.0, 20.0]


# ------------------------------------------------------------------------------------------- item 3: field check
def test_psf_outside_the_lens_field_is_refused_before_computing(capsys, monkeypatch):
    psf_mod = sys.modules["rwwarp.psf"]  # (rw.psf is the function)
    monkeypatch.setattr(psf_mod, "psf_map", lambda *a, **k: pytest.fail("computed a refused field"))
    code, err = _fails(["psf", "cooke_triplet", "--field", "30"], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert "20 deg" in err and "half width is 10 x 10 mm" in err and "--allow-outside" in err


def test_allow_outside_computes_and_warns_once_on_one_line(capsys):
    main(["psf", "cooke_triplet", "--field", "30", "--model", "ray", "--size", "8", "--allow-outside"])
    err = capsys.readouterr().err
    warns = [ln for ln in err.splitlines() if ln.startswith("warning: ")]
    outside = [ln for ln in warns if "past the sensor's half width 10 x 10 mm" in ln]
    assert len(outside) == 1 and "largest field 20 deg" in outside[0], err
    assert any("keep less than 95 %" in ln for ln in warns), err  # the PatchWarning, one line too
    assert "Warning:" not in err and "warnings.warn" not in err and "psf.py:" not in err, err


def test_a_warning_prints_once_as_one_line(capsys):
    shown = warnings.showwarning
    cli._setup_warnings()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("always")
            for _ in range(2):
                warnings.warn("PSF cut\n  by its patch", UserWarning)
    finally:
        warnings.showwarning = shown
    assert capsys.readouterr().err == "warning: PSF cut by its patch\n"


def test_cpu_commands_do_not_print_the_cuda_driver_warning():
    r = subprocess.run([sys.executable, "-m", "rwwarp.cli", "psf", "a489_doe", "--size", "8", "--model", "ray"],
                       capture_output=True, text=True, timeout=300, cwd=ROOT,
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 0, r.stderr
    assert "CUDA" not in r.stderr and "rwwarp psf: ray PSF" in r.stderr  # progress on stderr, results on stdout
    assert r.stdout.startswith("PSF ray")


def test_validate_reports_progress(tmp_path, capsys, monkeypatch):
    """rwwarp validate prints each step on stderr (the PSF and the ground truth stubbed: the real run is 87 s)."""
    import rwwarp.ground_truth as gt
    psf_mod = sys.modules["rwwarp.psf"]  # (rw.psf is the function)

    def fake_psf(lens, field, wl, size=64, **kw):
        return psf_mod.PSF(np.ones((size, size)), 1e-3, (0.0, 0.0), field, wl, plan={"n_grid": 1, "n_pad": 2})
    monkeypatch.setattr(psf_mod, "psf", fake_psf)
    monkeypatch.setattr(gt, "rs_thin_lens_psf", lambda *a, **k: np.ones((32, 32)))
    main(["validate", "--quick", "--out", str(tmp_path)])
    err = capsys.readouterr().err
    assert "[1/3]" in err and "[3/3]" in err and "ground truth" in err and "so far" in err, err
    assert (tmp_path / "report.md").exists()


# ------------------------------------------------------------------------------------------- item 2: help
def test_help_shows_defaults_and_bundled_lenses(capsys):
    with pytest.raises(SystemExit):
        main(["psf", "--help"])
    out = capsys.readouterr().out
    for name in ("a489_doe", "cooke_triplet", "ac254_100_a"):
        assert name in out
    assert "(default: 64)" in out and "(default: cpu)" in out and "--pixel" in out and "--rays-per-sample" in out


def test_design_help_lists_its_options(capsys):
    pytest.importorskip("torch")
    with pytest.raises(SystemExit) as e:
        main(["design", "--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert "--preset" in out and "--arm" in out and "--out" in out


def test_bench_alone_lists_the_benchmarks(capsys):
    main(["bench"])
    out = capsys.readouterr().out
    assert "trace" in out and "psf" in out and "arguments are required" not in out


# ------------------------------------------------------------------------------------------- item 5: knobs
def test_rays_per_sample_reaches_the_plan(capsys):
    main(["psf", "a489_doe", "--dry-run", "--method", "asm", "--size", "16"])
    one = capsys.readouterr().out
    main(["psf", "a489_doe", "--dry-run", "--method", "asm", "--size", "16", "--rays-per-sample", "0.5"])
    half = capsys.readouterr().out
    assert "rays: 1.0 per sample" in one and "rays: 0.5 per sample" in half


def test_memory_budget_and_batch_are_accepted_by_map(tmp_path, capsys):
    code, err = _fails(["map", "a489_doe", "--size", "8", "--fields", "0", "--memory-budget-gb", "1e-6",
                        "--batch", "1", "--out", str(tmp_path / "m")], capsys)
    assert code == 2 and "memory budget" in err and not (tmp_path / "m").exists(), err
    # the message names the options of this command that set the knobs it names
    assert "--batch N" in err and "--rays-per-sample" in err and "--memory-budget-gb" in err, err


def test_cli_knob_names_only_for_options_the_command_has():
    import argparse
    text = "split the batch (batch=...), rays_per_sample, or raise memory_budget_gb"
    psf_args = argparse.Namespace(rays_per_sample=1.0, memory_budget_gb=None)  # rwwarp psf: no --batch
    out = cli.cli_knob_names(text, psf_args)
    assert "batch=..." in out and "--batch" not in out
    assert "rays_per_sample (--rays-per-sample)" in out and "memory_budget_gb (--memory-budget-gb)" in out


# ------------------------------------------------------------------------------------------- item 6: OpenCL
def test_missing_opencl_platform_says_what_to_install(capsys):
    class LogicError(Exception):
        pass

    def boom(a):
        raise LogicError("clGetPlatformIDs failed: PLATFORM_NOT_FOUND_KHR")

    import argparse
    with pytest.raises(SystemExit) as e:
        cli._run(argparse.Namespace(cmd="psf", func=boom, device="cpu"))
    err = capsys.readouterr().err
    assert e.value.code == cli.EXIT_NO_OPENCL and "internal error" not in err and "please report" not in err
    assert "no OpenCL platform" in err and "pocl-opencl-icd" in err and len(err.strip().splitlines()) == 1


# ------------------------------------------------------------------------------------------- item 4: API
def test_dir_shows_public_names_only():
    names = dir(rw)
    assert "psf" in names and "layout" in names and "Strehl" in names
    for internal in ("raywave", "trace", "plan_psf_", "checks", "metrics_strehl", "io", "lens", "errors"):
        assert internal not in names
    assert len(names) <= len(rw.__all__)


def test_print_lens_is_a_surface_table():
    lens = rw.load_lens("cooke_triplet")
    text = str(lens)
    assert "EFL 50.021351 mm" in text and "semi-diam" in text and "STOP" in text and "N-SK16" in text
    assert "Surface(" not in text and len(repr(lens)) < 200 and "Surface(" not in repr(lens)


def test_results_have_short_reprs_and_plot(tmp_path):
    lens = rw.load_lens("a489_doe")
    m = rw.psf_map(lens, [0.0, 5.0], [0.55], model="ray", size=8)
    p = m[1, 0]
    s = rw.strehl(rw.load_lens("cooke_triplet"), 0.0, 0.5876)
    for r in (p, m, s):
        text = repr(r)
        assert len(text) < 300 and "array(" not in text and "\n" not in text, text
    assert repr(s).startswith("Strehl(ray-wave") and "psf_map" not in repr(s)
    for r, name in ((p, "p.png"), (m, "m.png"), (s, "s.png")):
        fig = r.plot(path=tmp_path / name)
        assert (tmp_path / name).read_bytes()[:8] == PNG and fig is not None
    import matplotlib
    matplotlib.use("Agg")
    ax = p.plot()
    assert hasattr(ax, "imshow")


def test_layout_is_exported(tmp_path):
    rw.layout(rw.load_lens("cooke_triplet"), tmp_path / "l.png")
    assert (tmp_path / "l.png").read_bytes()[:8] == PNG


# ------------------------------------------------------------------------------------------- item 4: examples
@pytest.mark.parametrize("script, files", [
    ("build_lens_and_add_doe.py", ["hybrid_layout.png", "psf_before.png", "psf_after.png", "cooke_with_doe.json"]),
    ("psf_map_image_simulation.py", ["scene.png", "simulated.png", "psf_map.png", "psf_map.npz"]),
])
def test_examples_run(script, files, tmp_path):
    r = subprocess.run([sys.executable, str(ROOT / "examples" / script), "--out", str(tmp_path)],
                       capture_output=True, text=True, timeout=600, cwd=ROOT,
                       env={**os.environ, "PYTHONPATH": str(ROOT), "MPLBACKEND": "Agg"})
    assert r.returncode == 0, r.stderr[-3000:]
    for f in files:
        assert (tmp_path / f).stat().st_size > 500, f
    if script.startswith("build"):
        assert rw.load_lens(tmp_path / "cooke_with_doe.json").doe_index is not None


def test_design_on_a_machine_without_the_nvidia_driver_is_quiet_too(monkeypatch, capfd):
    """rwwarp design has no --device (its config names it): Warp is initialised quietly when no NVIDIA driver
    loads at all, loudly (as Warp does) otherwise."""
    calls = []
    monkeypatch.setattr(cli, "_cuda_driver_present", lambda: False)
    import rwwarp.trace as tr
    monkeypatch.setattr(tr, "init_warp", lambda: (os.write(2, b"Warp CUDA warning: test\n"), calls.append(1)))
    cli._quiet_warp(None)
    assert calls and "Warp CUDA warning" not in capfd.readouterr().err
    monkeypatch.setattr(cli, "_cuda_driver_present", lambda: True)
    cli._quiet_warp(None)  # a driver: nothing silenced (and nothing initialised here)
    cli._quiet_warp("cuda")
    assert len(calls) == 1


def test_no_opencl_platform_end_to_end(tmp_path):
    """A machine without an OpenCL platform (the ICD loader pointed at an empty folder): rwwarp psf stops with
    one line that says what to install, exit status 3, not 'internal error ... please report it'. The ASM
    needs OpenCL on the CPU (the focal path, which method auto takes here on the CPU, runs in numpy)."""
    empty = tmp_path / "vendors"
    empty.mkdir()
    r = subprocess.run([sys.executable, "-m", "rwwarp.cli", "psf", "a489_doe", "--size", "8", "--method", "asm"],
                       capture_output=True, text=True, timeout=300, cwd=ROOT,
                       env={**os.environ, "PYTHONPATH": str(ROOT), "OCL_ICD_VENDORS": str(empty)})
    errs = [ln for ln in r.stderr.splitlines() if "error" in ln]
    assert r.returncode == cli.EXIT_NO_OPENCL, r.stderr
    assert len(errs) == 1 and "no OpenCL platform" in errs[0] and "pocl" in errs[0].lower(), r.stderr
    assert "internal error" not in r.stderr and "Traceback" not in r.stderr
