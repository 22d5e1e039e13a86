"""The GPU smoke's arm selection (``perf/smoke_presets.py --arms``), which ``perf/gpu_suite.sh smoke-parallel`` uses
to give one arm of a preset a GPU of its own: the three gpu presets' arms (names from the bundled configs) against
the selection each form of ``--arms`` must make."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "perf"))
import smoke_presets  # noqa: E402

ARMS = {"cooke_hybrid": ["paraxial", "rms_spot", "e2e", "e2e_from_rms"],
        "a489_aberration": ["blank_doe", "e2e_doe"],
        "a489_edof": ["paraxial_doe", "raywave_doe"]}


def _selected(arms):
    return {c: [a for a in names if smoke_presets.wanted(c, a, arms)] for c, names in ARMS.items()}


def test_the_bundled_presets_have_these_arms():
    from torch_bridge.train import load_config
    for config, names in ARMS.items():
        assert [a["name"] for a in load_config(config, "gpu")["arms"]] == names


def test_arm_selection():
    assert _selected(None) == ARMS
    # CONFIG:ARM picks that arm of that config; the configs not named keep every arm
    assert _selected(["a489_edof:raywave_doe"]) == {**ARMS, "a489_edof": ["raywave_doe"]}
    assert _selected(["a489_edof:paraxial_doe", "cooke_hybrid:e2e"]) == \
        {**ARMS, "a489_edof": ["paraxial_doe"], "cooke_hybrid": ["e2e"]}
    # a plain ARM picks that arm wherever it is, and nothing else
    assert _selected(["e2e_doe"]) == {"cooke_hybrid": [], "a489_aberration": ["e2e_doe"], "a489_edof": []}
