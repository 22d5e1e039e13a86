"""method="auto" chooses between the band-limited ASM and the focal propagation from the two plans of
one pilot trace: the cheaper in work, the ASM while its plan is small, and never a plan over the memory
budget when the other fits."""
from pathlib import Path

import pytest

import rwwarp as rw
from rwwarp.wave.plan import MemoryBudgetError
from rwwarp.wave.raywave import RayWave

COOKE = Path(__file__).resolve().parents[2] / "torch_bridge" / "configs" / "lenses" / "cooke_hybrid.json"


def _cooke_hybrid():
    """The F/4 Cooke hybrid with a DOE of strong power (the achromat's first coefficient and distance)."""
    lens = rw.load_lens(str(COOKE))
    d = len(lens.surfaces) - 1
    return lens.with_surface(d, profile={**lens.surfaces[d].profile, "coefficients": [-664.9, 0, 0, 0]},
                             thickness=19.9843)


def test_auto_takes_the_plan_that_fits_the_budget():
    """0.47 um, 3 deg (measured planner estimates). focal_patch_tol 1e-4: focal 190 GFLOP / 1.6 GiB against
    ASM 795 GFLOP / 12.7 GiB, so auto takes the focal plan, and keeps it under a 3 GiB budget; at 1e-5 the
    focal plan keeps more DOE orders (1.29 TFLOP / 9.0 GiB): without a budget the ASM does less work and is
    chosen; under 10 GiB only the focal plan fits and auto takes it instead of refusing; under 8 GiB
    neither fits: refused, naming the estimate."""
    lens = _cooke_hybrid()
    cheap = RayWave(lens, [(0.0, 3.0)], [0.47], 64, 0.004, method="auto", focal_patch_tol=1e-4)
    assert cheap.plan.method == "focal"
    assert cheap.plan.estimate["flops"] < 0.5 * 795e9
    kept = RayWave(lens, [(0.0, 3.0)], [0.47], 64, 0.004, method="auto", focal_patch_tol=1e-4,
                   memory_budget_bytes=3 * 2 ** 30)
    assert kept.plan.method == "focal" and kept.plan.estimate["memory_bytes"] <= 3 * 2 ** 30
    kw = dict(method="auto", focal_patch_tol=1e-5)
    free = RayWave(lens, [(0.0, 3.0)], [0.47], 64, 0.004, **kw)
    assert free.plan.method == "asm"
    asm_bytes = free.plan.estimate["memory_bytes"]
    budget = 10 * 2 ** 30
    fitted = RayWave(lens, [(0.0, 3.0)], [0.47], 64, 0.004, memory_budget_bytes=budget, **kw)
    assert fitted.plan.method == "focal" and fitted.plan.estimate["memory_bytes"] <= budget < asm_bytes
    with pytest.raises(MemoryBudgetError, match="needs an estimated"):
        RayWave(lens, [(0.0, 3.0)], [0.47], 64, 0.004, memory_budget_bytes=8 * 2 ** 30, **kw)
