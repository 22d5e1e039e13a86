"""method="auto" chooses between the band-limited ASM and the focal propagation from the two plans of
one pilot trace: the cheaper in work, the ASM while its plan is small, and never a plan over the memory
budget when the other fits."""
from pathlib import Path

import pytest

import rwwarp as rw
from rwwarp.plan import MemoryBudgetError
from rwwarp.raywave import RayWave

COOKE = Path(__file__).resolve().parents[2] / "torch_bridge" / "configs" / "lenses" / "cooke_hybrid.json"


def _cooke_hybrid():
    """The F/4 Cooke hybrid with a DOE of strong power (the achromat's first coefficient and distance)."""
    lens = rw.load_lens(str(COOKE))
    d = len(lens.surfaces) - 1
    return lens.with_surface(d, profile={**lens.surfaces[d].profile, "coefficients": [-664.9, 0, 0, 0]},
                             thickness=19.9843)


def test_auto_takes_the_plan_that_fits_the_budget():
    """0.47 um, 3 deg, focal_patch_tol 1e-4 (measured planner estimates: focal 1.7 TFLOP / 6.9 GiB, ASM
    0.8 TFLOP / 12.7 GiB). Without a budget the ASM does less work and is chosen; under a 10 GiB budget
    only the focal plan fits, and auto takes it instead of refusing; under 4 GiB neither fits: refused,
    naming the estimate."""
    lens = _cooke_hybrid()
    kw = dict(method="auto", focal_patch_tol=1e-4)
    free = RayWave(lens, [(0.0, 3.0)], [0.47], 64, 0.004, **kw)
    assert free.plan.method == "asm"
    asm_bytes = free.plan.estimate["memory_bytes"]
    fitted = RayWave(lens, [(0.0, 3.0)], [0.47], 64, 0.004, memory_budget_bytes=10 * 2 ** 30, **kw)
    assert fitted.plan.method == "focal" and fitted.plan.estimate["memory_bytes"] <= 10 * 2 ** 30 < asm_bytes
    with pytest.raises(MemoryBudgetError, match="needs an estimated"):
        RayWave(lens, [(0.0, 3.0)], [0.47], 64, 0.004, memory_budget_bytes=4 * 2 ** 30, **kw)
