"""torch_bridge.report: the titles of designs.png (issue 28)."""
import math


def test_designs_png_titles_name_the_node_fields_and_the_object():
    """designs.png titles: the node's field angles from result.json and the object distance, not
    "PSF node 0 (None)" (the npz key of the lens's own distance)."""
    from torch_bridge.report import _node_fields, _object_label
    res = {"eval": {"depths": [{"depth_mm": None, "nodes": [{"node": 0, "field_deg": [0.0, 0.0]},
                                                            {"node": 1, "field_deg": [6.458, 6.458]}]}]}}
    assert _node_fields(res, "None") == [[0.0, 0.0], [6.458, 6.458]]
    assert _node_fields({}, "None") == []
    assert _object_label("None", math.inf) == "object at infinity"
    assert _object_label("None", 1000.0) == "object at 1000 mm"
    assert _object_label("500.0") == "object at 500 mm"
    assert "None" not in _object_label("None")


def test_psf_mosaic_places_each_node_by_its_field():
    """A 10 x 10 evaluation grid is drawn as one mosaic (the gpu presets' designs.png was one row of 100 tiles,
    20,600 px wide): each tile lands where its field angles put it (largest y at the top), and a set of nodes that
    is not a full grid gets no mosaic."""
    import numpy as np
    from torch_bridge.report import _grid_layout, psf_mosaic
    k, gap = 5, 2
    xs, ys = [0.5, 1.5, 2.5], [0.5, 1.5]
    fields = [[x, y] for y in ys for x in xs]                 # node n: column n % 3, y row n // 3 (from the bottom)
    psfs = np.zeros((6, 3, k, k))
    for n in range(6):
        psfs[n, n % 3, 0, 0] = 1.0 + n                         # node n lights one pixel in colour channel n % 3
    img, nr, nc = psf_mosaic(psfs, fields, gap=gap)
    assert (nr, nc) == (2, 3) and img.shape == (2 * k + gap, 3 * k + 2 * gap, 3)
    for n in range(6):
        r, c = 1 - n // 3, n % 3                               # y = 1.5 is the top row
        tile = img[r * (k + gap):r * (k + gap) + k, c * (k + gap):c * (k + gap) + k]
        # _rgb_psf flips rows (image orientation): pixel (0, 0) of the PSF is the tile's bottom-left, at 1.0
        assert tile[k - 1, 0, n % 3] == 1.0 and tile.sum() == 1.0, n
    assert img[k:k + gap].min() == 1.0                         # white gap between the rows
    assert _grid_layout(fields[:5]) is None and psf_mosaic(psfs[:5], fields[:5]) is None
    assert _grid_layout([None] * 6) is None
