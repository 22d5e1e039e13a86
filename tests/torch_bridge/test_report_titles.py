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
