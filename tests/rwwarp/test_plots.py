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
