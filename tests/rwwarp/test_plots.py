"""Pictures (issue 28): what the layout drawing, the spot diagrams and the report's MTF / best focus show,
against independent references (paraxial pupils, field directions, traced source points, numpy)."""
import math

import matplotlib
import numpy as np
import pytest

import rwwarp as rw
from rwwarp import paraxial
from rwwarp.plots import layout_figure, layout_rays
from rwwarp.trace import field_direction

LENS1 = "tests/data/third_party/files/optiland/lens1.zmx"


def _drawn_lines(monkeypatch, tmp_path, fn):
    """Run ``fn(path)`` (a figure writer) with plt.close disabled; return the Line2D data of its axes."""
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    plt.close("all")
    monkeypatch.setattr(plt, "close", lambda *a, **k: None)
    fn(tmp_path / "fig.png")
    figs = [plt.figure(n) for n in plt.get_fignums()]
    assert len(figs) == 1
    lines = [(np.asarray(ln.get_xdata(), float), np.asarray(ln.get_ydata(), float), ln)
             for ax in figs[0].axes for ln in ax.get_lines()]
    monkeypatch.undo()
    plt.close("all")
    return figs[0], lines


@pytest.mark.parametrize("name, field", [("cooke_triplet", 0.0), ("cooke_triplet", 20.0), (LENS1, 0.0),
                                         (LENS1, 12.0)])
def test_layout_rays_start_on_the_source_rays(name, field):
    """Object at infinity: in front of the first surface every drawn ray is a straight segment along the
    field direction (slope tan(field), 0 on axis: parallel), the fan lying across the paraxial entrance pupil
    (on its plane the rays are at y = r_EP v, the chief ray at 0), and the segment ends on the traced point
    of the first surface. Before the fix the Cooke marginal ray on axis was drawn at slope -0.089 from
    y = 5.58 mm (its in-glass direction extended back); now 0 and 5.00 mm to 1e-12 (measured 0 / 4e-15)."""
    lens = rw.load_lens(name)
    wl = lens.wavelengths_um[len(lens.wavelengths_um) // 2]
    assert math.isinf(lens.object_distance)
    rays = 9
    paths, ok = layout_rays(lens, field, wl, rays)
    assert ok.all()
    pup = paraxial.pupils(lens, wl)
    d = field_direction(field)  # object-space direction of the source rays (independent of the layout)
    seg = paths[:, 1] - paths[:, 0]
    assert paths[:, 0, 2] == pytest.approx(np.full(rays, paths[0, 0, 2]))
    assert paths[0, 0, 2] < lens.vertex_z[0]  # the rays start in front of the lens
    # along the source direction: cross product with it vanishes (measured < 1e-14 mm)
    assert np.max(np.abs(np.cross(seg / np.linalg.norm(seg, axis=1)[:, None], d))) < 1e-12
    slope = seg[:, 1] / seg[:, 2]
    assert slope == pytest.approx(np.full(rays, math.tan(math.radians(field))), abs=1e-12)
    # on the entrance-pupil plane the fan spans the paraxial pupil: y = r_EP v + the chief ray's height 0
    t = (pup.entrance_z - paths[:, 0, 2]) / seg[:, 2]
    y_ep = paths[:, 0, 1] + t * seg[:, 1]
    assert y_ep == pytest.approx(pup.entrance_radius * np.linspace(-1, 1, rays), abs=1e-9)
    # the second point is the traced first-surface intersection: on the surface's sag
    s0 = lens.surfaces[0]
    r = np.hypot(paths[:, 1, 0], paths[:, 1, 1])
    assert paths[:, 1, 2] == pytest.approx(lens.vertex_z[0] + s0.sag(r), abs=1e-9)


def test_layout_figure_draws_those_rays(monkeypatch, tmp_path):
    """What layout_figure puts on the axes are the layout_rays paths (y against z), e.g. the Cooke triplet's
    on-axis marginal ray: parallel at y = 5.00 mm in front of the lens."""
    lens = rw.load_lens("cooke_triplet")
    wl = lens.wavelengths_um[1]
    _, lines = _drawn_lines(monkeypatch, tmp_path, lambda p: layout_figure(lens, p, [0.0], wl, rays=9))
    paths, _ = layout_rays(lens, 0.0, wl, 9)
    for j in (0, 8):
        hit = [ln for ln in lines if len(ln[0]) == paths.shape[1] and np.allclose(ln[0], paths[j, :, 2])
               and np.allclose(ln[1], paths[j, :, 1])]
        assert len(hit) == 1
        z, y, _ = hit[0]
        assert abs(y[0]) == pytest.approx(5.0, abs=1e-9) and y[1] == pytest.approx(y[0], abs=1e-9)


def test_best_focus_is_inside_the_scan_and_at_a_fine_scans_peak():
    """Cooke triplet on axis, ray-wave, 0.5876 um, MTF at a quarter of the cutoff (85 lp/mm). The report's first
    scan (+-4 lambda F#^2 = +-58.27 um) peaked on its last plane (+58.27 um, what the report used to print);
    best_focus extends it (here from 5 planes 29.1 um apart to +116.5 um) and puts the peak at +85.4 um with a
    plane on each side (margin >= half a step). Independent check: a brute-force scan 3 um apart over +-12 um
    about it peaks at +83.4 um (its own parabola: +83.8 um); measured difference 1.6-2.0 um, bound 5 um."""
    from rwwarp import metrics as M
    lens = rw.load_lens("cooke_triplet")
    wl = lens.wavelengths_um[1]
    na = M.image_space_na(lens, 0.0, wl)
    f = 0.25 * 2 * na / (wl * 1e-3)
    dz = 4 * wl * 1e-3 / (2 * na) ** 2
    pix = M.default_sampling_mm(lens, [0.0], [wl])
    b = M.best_focus(lens, 0.0, wl, f, focus_mm=np.linspace(-dz, dz, 5), size=128, pixel_mm=pix)
    z = b.scan.focus_mm
    assert b.interior and z[-1] > dz + 1e-9  # the scan had to grow past its first end
    assert z[0] + 0.5 * b.step_mm <= b.focus_mm <= z[-1] - 0.5 * b.step_mm
    fine = b.focus_mm + np.arange(-12, 13, 3) * 1e-3
    t = M.through_focus_mtf(lens, 0.0, wl, frequencies_lp_mm=[f], focus_mm=fine, size=128, pixel_mm=pix)
    m = 0.5 * (t.tangential[:, 0] + t.sagittal[:, 0])
    k = int(np.argmax(m))
    assert 0 < k < len(fine) - 1  # the fine scan's own peak is inside it
    assert abs(b.focus_mm - fine[k]) < 5e-3


def test_polychromatic_diffraction_limit_is_the_weighted_mean():
    """Cooke (NA 0.1004; 0.4861 / 0.5876 / 0.6563 um): at 300 lp/mm the equal-weight diffraction limit is 0.073
    (the issue's figure), not the shortest wavelength's 0.165 the report drew. Checked against a numpy pupil
    autocorrelation (overlap of two discs on a 1201 x 1201 grid, per wavelength; its staircase edge: 1e-3)."""
    from rwwarp.report import polychromatic_diffraction_mtf
    na, wls = 0.10041620811148178, [0.486133, 0.587562, 0.656273]
    fc = [2 * na / (w * 1e-3) for w in wls]
    x = np.linspace(-1, 1, 1201)
    X, Y = np.meshgrid(x, x)
    disc = X * X + Y * Y <= 1.0

    def overlap(v):  # discs of radius 1 shifted by 2 v (v = f / cutoff) along y
        s = int(round(2 * v / (x[1] - x[0])))
        return np.logical_and(disc[s:], disc[:disc.shape[0] - s]).sum() / disc.sum() if s < len(x) else 0.0

    num = np.mean([overlap(300.0 / c) for c in fc])
    got = polychromatic_diffraction_mtf([300.0], fc)[0]
    assert got == pytest.approx(num, abs=3e-3)
    assert got == pytest.approx(0.073, abs=1e-3)
    assert polychromatic_diffraction_mtf([300.0], fc[:1])[0] == pytest.approx(0.165, abs=1e-3)
    assert polychromatic_diffraction_mtf([300.0], fc, [0, 0, 1])[0] == pytest.approx(
        polychromatic_diffraction_mtf([300.0], fc[2:])[0], abs=1e-15)


def test_report_mtf_figure_limit_and_axis(monkeypatch, tmp_path):
    """The report's MTF figure: its diffraction-limit curve is the equal-weight limit of the lens's wavelengths,
    its axis stops at 1.2 x the sensor Nyquist (Cooke: 5 um pixels, 100 lp/mm; the cutoff 413 lp/mm is far
    beyond), where a line marks the Nyquist frequency."""
    from rwwarp import report as R
    from rwwarp.psf import psf_map
    lens = rw.load_lens("cooke_triplet")
    wls = list(lens.wavelengths_um)
    got = {}
    real = R._line_fig
    monkeypatch.setattr(R, "_line_fig", lambda path, *a, **k: (got.setdefault(path.name, (a, k)), real(path, *a, **k)))
    R._section("mtf", lens, [0.0], [0.0], wls, wls[1], "ray", 32, 64, 3, "cpu", tmp_path, psf_map)
    (title, xl, yl, curves), kw = got["mtf.png"]
    f, dl, style = curves[0]
    assert "diffraction limit" in style["label"]
    nyq = 0.5 / lens.sensor.pixel_pitch
    assert f[-1] == pytest.approx(1.2 * nyq) and kw["xlim"][1] == pytest.approx(1.2 * nyq)
    na = rw.metrics.image_space_na(lens, 0.0, min(wls))
    ref = np.mean([rw.metrics.diffraction_mtf_circular(f, 2 * na / (w * 1e-3)) for w in wls], axis=0)
    assert np.max(np.abs(dl - ref)) < 1e-12
    assert any(np.array_equal(c[0], [nyq, nyq]) and "Nyquist" in c[2].get("label", "") for c in curves)


def test_spot_diagrams_common_scale_airy_circle_and_order(monkeypatch, tmp_path):
    """Spot diagrams (Cooke, 0 / 14 / 20 deg): every panel on the same scale, holding every ray; the Airy circle
    drawn with radius 1.22 lambda F#_w: against the paraxial F/# 5.0021 (0.5876 um: 3.586 um) within 1 % on axis
    (measured 3.57 um from the traced cone's NA, -0.4 %); the tightest wavelength drawn last (on top)."""
    from rwwarp import paraxial
    from rwwarp.report import _spots, spot_data
    lens = rw.load_lens("cooke_triplet")
    wls, fields = list(lens.wavelengths_um), [0.0, 14.0, 20.0]
    fig, _ = _drawn_lines(monkeypatch, tmp_path, lambda p: _spots(lens, fields, wls, p, "cpu"))
    xy, rms, airy = spot_data(lens, fields, wls)
    axes = fig.axes
    assert len({ax.get_xlim() for ax in axes}) == 1 and len({ax.get_ylim() for ax in axes}) == 1
    half = axes[0].get_xlim()[1]
    assert all(np.max(np.abs(d)) <= half for row in xy for d in row)
    assert airy[0] == pytest.approx(1.22 * wls[1] * paraxial.f_number(lens, wls[1]), rel=1e-2)
    for i, ax in enumerate(axes):
        circ = [ln for ln in ax.get_lines() if ln.get_color() == "k"]
        r = np.hypot(circ[0].get_xdata(), circ[0].get_ydata())
        assert r == pytest.approx(np.full(len(r), airy[i]), rel=1e-12)
        drawn = [c.get_label() for c in ax.collections]
        assert drawn[-1] == f"{wls[int(np.argmin(rms[i]))]:g} um"  # the tightest on top
        assert sorted(drawn) == sorted(f"{w:g} um" for w in wls)  # every wavelength drawn


def test_demo_layout_title_fits_the_figure(monkeypatch, tmp_path):
    """The demo's lens has an 86-character name (A489 + achromatising DOE): the layout's title (drawn on two
    lines now) lies inside the saved figure, measured with the renderer (it ran off both sides before)."""
    from rwwarp.demo import achromat_doe
    lens, _ = achromat_doe(rw.load_lens("a489_doe"), 0.25)
    assert len(lens.name) > 80
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    plt.close("all")
    monkeypatch.setattr(plt, "close", lambda *a, **k: None)
    layout_figure(lens, tmp_path / "layout.png", [0.0, 7.0, 14.0], 0.55)
    fig = plt.figure(plt.get_fignums()[0])
    box, page = fig.axes[0].title.get_window_extent(fig.canvas.get_renderer()), fig.bbox
    monkeypatch.undo()
    plt.close("all")
    assert box.x0 >= page.x0 and box.x1 <= page.x1 and box.y1 <= page.y1


def test_layout_rays_of_a_near_object_start_at_the_object_point():
    """Object 100 mm in front of an ideal thin lens (stop at the lens, EPD 4 mm): every drawn ray of a field
    starts at that field's object point, (0, -100 tan(theta), -100) mm for the pupil at z = 0, and its first
    segment reaches the lens at y = 2 v (the pupil height), the traced first-surface point."""
    from rwwarp.lens import Lens, Surface
    s = [Surface(type="thin_lens", focal_length=50.0, thickness=100.0, stop=True)]
    lens = Lens(s, entrance_pupil_diameter=4.0, object_distance=100.0)
    for field in (0.0, 3.0):
        paths, ok = layout_rays(lens, field, 0.55, 5)
        assert ok.all()
        obj = np.array([0.0, -100.0 * math.tan(math.radians(field)), -100.0])
        assert np.max(np.abs(paths[:, 0] - obj)) < 1e-12
        assert paths[:, 1, 1] == pytest.approx(2.0 * np.linspace(-1, 1, 5), abs=1e-9)
        assert paths[:, 1, 2] == pytest.approx(np.zeros(5), abs=1e-12)
