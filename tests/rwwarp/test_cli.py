"""The command line: info with a layout picture, psf --explain, clear errors for bad input."""
import json

import pytest

from rwwarp.cli import main


def test_info_prints_paraxial_data_and_writes_layout(tmp_path, capsys):
    png = tmp_path / "layout.png"
    main(["info", "cooke_triplet", "--wavelength", "0.5875618", "--plot", str(png)])
    out = capsys.readouterr().out
    assert "EFL 50.021351 mm" in out and "BFL 42.436440 mm" in out
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000


def test_psf_explain_prints_the_plan(capsys, tmp_path):
    npy = tmp_path / "p.npy"
    main(["psf", "a489_doe", "--size", "16", "--explain", "--out", str(npy)])
    out = capsys.readouterr().out
    assert "plan auto (asm): pitch" in out and "estimate: peak memory" in out and "method auto" in out
    assert npy.exists()


def test_psf_dry_run_prints_the_plan_and_computes_nothing(capsys, tmp_path):
    npy = tmp_path / "p.npy"
    main(["psf", "cooke_triplet", "--dry-run", "--method", "asm", "--out", str(npy)])
    out = capsys.readouterr().out
    # the ASM plan of the full-aperture Cooke triplet: ~13 GiB planned, refused by nothing, computed by nothing
    assert "plan auto (asm)" in out and "GiB" in out and "Nyquist" in out
    assert not npy.exists()


def test_bad_lens_file_exits_with_the_place_named(tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"format": "rwwarp-lens/1", "surfaces": [{"type": "toroid", "thickness": 1.0}]}))
    with pytest.raises(SystemExit) as e:
        main(["info", str(bad)])
    assert e.value.code == 2
    msg = capsys.readouterr().err
    assert "bad.json" in msg and "surface 0" in msg and "toroid" in msg
