"""rwwarp report: the folder it writes, the clear apertures of its layout, the CLI entry."""
import math

import numpy as np
import pytest

import rwwarp as rw
from rwwarp.cli import main
from rwwarp.lens import Lens, Surface
from rwwarp.report import clear_semi_diameters, write_report

PNG = b"\x89PNG\r\n\x1a\n"


def test_clear_semi_diameters_thin_lens_oracle():
    """Stop at an ideal thin lens (EPD 4 mm, f = 50 mm), a plane d = 10 mm behind it: at field theta the
    outermost ray there is at 2 (1 - d / f) + d tan(theta) (the top rim ray, pupil (0, 1))."""
    f, d = 50.0, 10.0
    s = [Surface(type="thin_lens", focal_length=f, thickness=d, stop=True),
         Surface(type="standard", radius=None, thickness=f - d)]
    lens = Lens(s, entrance_pupil_diameter=4.0)
    theta = 5.0
    h = clear_semi_diameters(lens, [0.0, theta], [0.55])
    assert h[0] == pytest.approx(2.0, abs=1e-12)
    assert h[1] == pytest.approx(2 * (1 - d / f) + d * math.tan(math.radians(theta)), abs=1e-9)


def _check_folder(out, page, expect):
    text = page.read_text()
    assert "This section failed" not in text
    for name in expect:
        p = out / name
        assert p.read_bytes()[:8] == PNG, name
        assert f"]({name})" in text, name
    return text


def test_report_cooke_ray_model(tmp_path):
    lens = rw.load_lens("cooke_triplet")
    page = write_report(lens, tmp_path, model="ray", psf_size=32, mtf_size=64, through_focus_planes=3,
                        progress=False, lens_label="cooke_triplet")
    text = _check_folder(tmp_path, page, ["layout.png", "spots.png", "psf_map.png", "mtf.png", "encircled_energy.png",
                                          "through_focus.png", "chromatic_focal_shift.png", "field_curves.png"])
    assert "| EFL at 0.587562 um | 50.021351 mm |" in text  # the README's Zemax value
    # RMS spot at 14 deg, 0.5876 um, from the report's 31-ray-across grid (README: 15.2156 um on 401x401)
    row = next(ln for ln in text.splitlines() if ln.startswith("| 14 deg |") and ln.count("|") == 5)
    assert float(row.split("|")[3]) == pytest.approx(15.2156, rel=2e-2)
    # clear apertures come from rays (the Cooke file has none): first lens 8.5 mm, not the 18 mm image height
    assert "8.5576 (rays)" in text
    # best focus inside the (extended) through-focus scan, at least half a plane step from either end
    import re
    m = re.search(r"Best focus at \d+ lp/mm: ([+-][\d.]+) um from the sensor plane, inside the scan "
                  r"\(([+-][\d.]+) \.\. ([+-][\d.]+) um, \d+ planes ([\d.]+) um apart", text)
    assert m, "best focus not reported inside its scan"
    best, lo, hi, step = map(float, m.groups())
    assert lo + 0.5 * step <= best <= hi - 0.5 * step


def test_report_cli_a489(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    assert capsys.readouterr().out.strip() == f"rwwarp {rw.__version__}"
    out = tmp_path / "rep"
    main(["report", "a489_doe", "--out", str(out), "--model", "ray", "--psf-size", "16", "--mtf-size", "32",
          "--through-focus", "0", "--fields", "0", "5", "--quiet"])
    assert "report written to" in capsys.readouterr().out
    _check_folder(out, out / "report.md", ["layout.png", "spots.png", "psf_map.png", "mtf.png", "doe.png",
                                           "field_curves.png"])
    assert not (out / "through_focus.png").exists()


def test_patch_size_for_ideal_lens():
    """An ideal lens has no geometric spread: the patch is 2 x 1.1 x 10 Airy radii (0.61 lambda / NA)."""
    from rwwarp.report import patch_size_for
    s = [Surface(type="thin_lens", focal_length=50.0, thickness=50.0, stop=True)]
    lens = Lens(s, entrance_pupil_diameter=4.0)
    na = math.sin(math.atan(2.0 / 50.0))
    n = 1.1 * 2 * 10 * 0.61 * 0.55e-3 / na / 0.001
    assert patch_size_for(lens, [0.0], [0.55], 0.001) == 8 * math.ceil(n / 8)


def test_report_a489_raywave_small(tmp_path):
    page = write_report(rw.load_lens("a489_doe"), tmp_path, fields_deg=[0.0, 5.0], psf_size=16, mtf_size=48,
                        through_focus_planes=3, progress=False)
    text = _check_folder(tmp_path, page, ["psf_map.png", "mtf.png", "through_focus.png", "doe.png"])
    assert "Strehl ratio" in text and "| 0 deg | " in text
