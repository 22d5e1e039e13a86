"""Command line on bad input (issue 12): one-line error on stderr, exit status 2, no traceback (unless
--debug), wrong arity refused, no partial output files."""
import json
import os
import subprocess
import sys

import pytest

from rwwarp.cli import main

A489 = "a489_doe"


def _fails(argv, capsys):
    with pytest.raises(SystemExit) as e:
        main(argv)
    cap = capsys.readouterr()
    return e.value.code, cap.err


@pytest.mark.parametrize("argv, needle", [
    (["psf", A489, "--field", "1", "2", "3"], "--field"),
    (["psf", A489, "--size", "0"], "--size"),
    (["psf", A489, "--size", "abc"], "--size"),
    (["psf", A489, "--wavelength", "nan"], "--wavelength"),
    (["psf", A489, "--wavelength", "550", "--model", "ray"], "wavelength_um=550"),
    (["psf", A489, "--field", "inf"], "--field"),
    (["psf", A489, "--device", "gpu7", "--model", "ray"], "device='gpu7'"),
    (["psf", A489, "--model", "wave"], "--model"),
    (["info", A489, "--wavelength", "550"], "wavelength_um=550 is outside 0.2-20 um"),
    (["info", A489, "--wavelength", "0"], "wavelength_um=0 is outside"),  # not silently the default
    (["info", "/nonexistent/lens.json"], "/nonexistent/lens.json"),
    (["info", "/"], "directory"),
    (["info", "/dev/null"], "regular file"),
    (["map", A489, "--n-fields", "0"], "--n-fields"),
    (["map", A489, "--fields", "1", "--n-fields", "2"], "one or the other"),
    (["map", A489, "--batch", "-1"], "--batch"),
    (["map", A489, "--max-field", "95", "--n-fields", "2", "--size", "8", "--model", "ray"], "89.9"),
    (["bench", "../../etc/passwd"], "no benchmark"),
    (["demo", "--fields", "x"], "--fields"),
    (["nosuchcommand"], "invalid choice"),
    (["psf"], "lens"),
])
def test_bad_input_one_line_exit_2(argv, needle, capsys, tmp_path):
    code, err = _fails(argv, capsys)
    assert code == 2, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert needle in lines[0], lines[0]
    assert "Traceback" not in err


def test_bad_lens_file_in_every_format_is_one_line(tmp_path, capsys):
    for name, data in (("bad.json", b"\xff\xfe\x00{"), ("bad.zmx", b"SURF 0\nSURF 1\n  CURV nan\nSURF 2\n"),
                       ("deep.json", b"[" * 5000)):
        p = tmp_path / name
        p.write_bytes(data)
        code, err = _fails(["info", str(p)], capsys)
        assert code == 2 and str(p) in err and len(err.strip().splitlines()) == 1, err


def test_debug_shows_the_traceback(capsys):
    code, err = _fails(["--debug", "info", A489, "--wavelength", "550"], capsys)
    assert code == 2 and "Traceback" in err and "wavelength_um=550" in err.splitlines()[-1]
    code, err = _fails(["info", A489, "--wavelength", "550", "--debug"], capsys)
    assert code == 2 and "Traceback" in err


def test_failed_psf_leaves_no_output(tmp_path, capsys):
    out = tmp_path / "p.npy"
    code, _ = _fails(["psf", A489, "--model", "ray", "--size", "8", "--field", "60", "--out", str(out)], capsys)
    assert code == 2
    assert list(tmp_path.iterdir()) == []


def test_psf_output_written_atomically(tmp_path, capsys):
    out = tmp_path / "p.npz"
    main(["psf", A489, "--model", "ray", "--size", "8", "--field", "1", "--out", str(out)])
    assert out.exists() and [p.name for p in tmp_path.iterdir()] == ["p.npz"]  # no temporary left


def test_psf_out_other_than_npz_or_png_is_refused_before_computing(tmp_path, capsys):
    code, err = _fails(["psf", A489, "--model", "ray", "--size", "8", "--out", str(tmp_path / "p.npy")], capsys)
    assert code == 2 and ".npz" in err and "p.npy" in err and len(err.strip().splitlines()) == 1, err
    assert "PSF" not in capsys.readouterr().out and list(tmp_path.iterdir()) == []


def test_failed_map_writes_no_folder(tmp_path, capsys):
    out = tmp_path / "map"
    code, err = _fails(["map", A489, "--model", "ray", "--size", "8", "--n-fields", "2", "--max-field", "60",
                        "--out", str(out)], capsys)
    assert code == 2 and not out.exists(), err


def test_console_script_exit_status_and_no_traceback(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"format": "rwwarp-lens/1", "surfaces": [{"type": "standard", "radius": [1]}]}))
    r = subprocess.run([sys.executable, "-m", "rwwarp.cli", "info", str(bad)], capture_output=True, text=True,
                       env={**os.environ, "PYTHONWARNINGS": "ignore"}, timeout=300)
    assert r.returncode == 2
    assert "Traceback" not in r.stderr and "radius" in r.stderr and str(bad) in r.stderr


def test_design_binary_config_is_one_line_and_writes_nothing(tmp_path, capsys, monkeypatch):
    pytest.importorskip("torch")
    monkeypatch.chdir(tmp_path)
    cfg = tmp_path / "bad.yaml"
    cfg.write_bytes(b"\xff\xfe\x00\x01binary")
    code, err = _fails(["design", str(cfg)], capsys)
    assert code == 2 and "bad.yaml" in err and len(err.strip().splitlines()) == 1, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.yaml"]
