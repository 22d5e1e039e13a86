"""Adaptive sampling plans: error estimates against finer references, growth with the scene, warnings
for undersampled explicit plans, and the cheapest plan for a target error (small thin-lens systems)."""
import warnings

import numpy as np
import pytest

import rwwarp as rw
from rwwarp import convergence as cv
from rwwarp.errors import SamplingWarning
from rwwarp.lens import Lens, Sensor, Surface
from rwwarp.plan import Plan

WL = 0.55
SIZE = 32


def thin_lens(side_mm=1.0, f=50.0, shape="circle", doe=None, doe_to_sensor_mm=None, pixel_mm=None):
    """Aperture + ideal thin lens (+ a DOE ``doe_to_sensor_mm`` before the sensor), object at infinity."""
    pixel_mm = pixel_mm or WL * 1e-3 * f / side_mm / 3
    surfs = [Surface(type="aperture", semi_diameter=side_mm / 2, shape=shape, stop=True),
             Surface(type="thin_lens", focal_length=f, semi_diameter=side_mm,
                     thickness=f if doe is None else f - doe_to_sensor_mm)]
    if doe is not None:
        surfs.append(Surface(type="doe", semi_diameter=side_mm, shape="square", thickness=doe_to_sensor_mm,
                             profile=doe))
    return Lens(surfs, Sensor(pixel_mm, (1000, 1000)), wavelengths_um=[WL])


def even_poly(a1, a2=0.0, radius=0.5):
    return {"kind": "even_poly", "norm_radius": radius, "coefficients": [a1, a2]}


def pixel_map(n, pitch_mm, seed=0):
    rng = np.random.default_rng(seed)
    return {"kind": "pixel_map", "pitch": pitch_mm, "data": rng.uniform(0, 2 * np.pi, (n, n)).tolist()}


@pytest.fixture(scope="module")
def circle():
    lens = thin_lens()
    ref, hist = cv.converged_reference(lens, 0.0, WL, SIZE, tol=1e-4, start=cv.Settings(4.0, 3.0, 2.0, 6),
                                       max_rays=2048 ** 2, max_fft=4096)
    return lens, ref, hist


def window_mm(plan):
    return plan.n_grid * plan.pitch_mm


# ---------------------------------------------------------------------------------------------- error estimates
def test_adaptive_psf_agrees_with_finer_reference_within_its_estimate(circle):
    lens, ref, hist = circle
    est = cv.estimate_error(lens, 0.0, WL, SIZE, center_mm=ref.center_mm)
    err = cv.rel_l2(est["psf"].data, ref.data)
    conv = ref.info["convergence"]
    # the reference is finer than the default plan in every knob, and its own error estimate is smaller
    assert all(conv["settings"][k] >= v for k, v in cv.Settings().to_dict().items()
               if v is not None and conv["settings"][k] is not None)
    assert conv["estimated_error"] < est["estimated_error"]
    assert 0 < err <= est["estimated_error"]
    # the refinement only ever doubles: each trial differs from its round's state in exactly one knob
    states = {e["round"]: e["settings"] for e in hist if e["role"] == "state"}
    for e in hist:
        if e["role"] == "trial":
            base = states.get(e["round"] - 1) or states[max(r for r in states if r < e["round"])]
            diff = [k for k in cv.KNOBS if e["settings"][k] != base[k]]
            assert diff == [e["knob"]] and e["settings"] == cv.Settings(**base).doubled(e["knob"]).to_dict()


def test_estimate_covers_error_with_a_doe():
    lens = thin_lens(doe=even_poly(20.0, -5.0), doe_to_sensor_mm=10.0)
    ref, _ = cv.converged_reference(lens, 0.0, WL, SIZE, tol=1e-4, start=cv.Settings(4.0, 3.0, 2.0, 6),
                                    max_rays=2048 ** 2, max_fft=4096)
    est = cv.estimate_error(lens, 0.0, WL, SIZE, center_mm=ref.center_mm)
    assert cv.rel_l2(est["psf"].data, ref.data) <= est["estimated_error"]


@pytest.mark.parametrize("doe", [even_poly(20.0, -5.0), even_poly(200.0)], ids=["weak", "strong"])
def test_adaptive_psf_agrees_with_paper_grid_within_its_estimate(doe):
    # the paper's fixed grid (whole DOE, padded 2x, 10^6 rays) is a different discretisation of the same
    # PSF: the default adaptive plan must agree with it to the error it reports for itself
    lens = thin_lens(doe=doe, doe_to_sensor_mm=10.0)
    est = cv.estimate_error(lens, 0.0, WL, SIZE)
    adaptive = est["psf"]
    with warnings.catch_warnings():
        warnings.simplefilter("error", SamplingWarning)
        paper = rw.psf(lens, 0.0, WL, size=SIZE, plan="paper", center_mm=adaptive.center_mm)
    # it is the paper's grid: the whole 2 mm DOE, 2x padding, 1000 rays across; the adaptive window is the
    # beam's footprint (~0.2 mm)
    assert paper.plan["kind"] == "paper" and paper.plan["ray_grid"] == 1000
    assert paper.plan["n_grid"] * paper.plan["pitch_mm"] == pytest.approx(2.0, abs=paper.plan["pitch_mm"])
    assert paper.plan["n_pad"] == 2 * paper.plan["n_grid"]
    assert adaptive.plan["n_grid"] * adaptive.plan["pitch_mm"] < 0.5
    assert 0 < cv.rel_l2(adaptive.data, paper.data) <= est["estimated_error"]


def test_plan_for_error_returns_cheapest_rung_meeting_target(circle):
    lens, ref, _ = circle
    target = 2e-3
    choice = cv.plan_for_error(lens, 0.0, WL, SIZE, target_error=target, reference=ref)
    plan, err, t = choice
    assert choice.met and err <= target and t > 0
    assert isinstance(plan, Plan)
    # rungs are tried cheapest first and the walk stops at the first success
    assert [r["meets"] for r in choice.ladder] == [False] * (len(choice.ladder) - 1) + [True]
    costs = [r["predicted_cost"] for r in choice.ladder]
    assert costs == sorted(costs)
    # the returned explicit plan reproduces the PSF it was measured with, without sampling warnings (bar the
    # ray-density check, which counts rays across the window while the adaptive plan spreads them over the
    # footprint)
    with warnings.catch_warnings():
        warnings.simplefilter("error", SamplingWarning)
        warnings.filterwarnings("ignore", message="ray density", category=SamplingWarning)
        p = rw.psf(lens, 0.0, WL, size=SIZE, plan=plan, center_mm=ref.center_mm,
                   gauss_nodes=choice.settings["gauss_nodes"])
    assert cv.rel_l2(p.data, ref.data) == pytest.approx(err, rel=1e-6)
    # an unreachable target returns the most accurate rung, flagged
    worst = cv.plan_for_error(lens, 0.0, WL, SIZE, target_error=1e-12, reference=ref, ladder=((1.0, 1.0), (2.0, 1.5)))
    assert not worst.met and worst.error == min(r["error"] for r in worst.ladder)


# ---------------------------------------------------------------------------------------------- the plan follows the scene
def test_bigger_aperture_gives_larger_window():
    small = cv.plan_at(thin_lens(side_mm=1.0), 0.0, WL, SIZE)
    big = cv.plan_at(thin_lens(side_mm=2.0), 0.0, WL, SIZE)
    assert window_mm(big) > 1.8 * window_mm(small)


def test_longer_doe_distance_gives_larger_window():
    near = cv.plan_at(thin_lens(doe=even_poly(20.0), doe_to_sensor_mm=10.0), 0.0, WL, SIZE)
    far = cv.plan_at(thin_lens(doe=even_poly(20.0), doe_to_sensor_mm=30.0), 0.0, WL, SIZE)
    # the converging beam's footprint on the DOE scales with the DOE-to-focus distance
    assert window_mm(far) > 2.5 * window_mm(near)


def test_finer_doe_features_give_finer_pitch():
    coarse = cv.plan_at(thin_lens(doe=pixel_map(32, 0.008), doe_to_sensor_mm=10.0), 0.0, WL, SIZE)
    fine = cv.plan_at(thin_lens(doe=pixel_map(64, 0.004), doe_to_sensor_mm=10.0), 0.0, WL, SIZE)
    assert fine.pitch_mm <= 0.002 + 1e-12 and coarse.pitch_mm <= 0.004 + 1e-12
    assert fine.pitch_mm < coarse.pitch_mm
    # steeper continuous phase (higher local frequency) -> finer pitch too
    weak = cv.plan_at(thin_lens(doe=even_poly(20.0), doe_to_sensor_mm=10.0), 0.0, WL, SIZE)
    strong = cv.plan_at(thin_lens(doe=even_poly(400.0), doe_to_sensor_mm=10.0), 0.0, WL, SIZE)
    assert strong.pitch_mm < 0.5 * weak.pitch_mm


def test_more_rays_and_padding_follow_the_knobs():
    lens = thin_lens()
    base = cv.plan_at(lens, 0.0, WL, SIZE)
    assert cv.plan_at(lens, 0.0, WL, SIZE, settings=cv.Settings(rays_per_sample=3.0)).ray_grid >= 2 * base.ray_grid - 2
    assert cv.plan_at(lens, 0.0, WL, SIZE, settings=cv.Settings(pad_factor=2.0)).n_pad >= 2 * base.n_pad
    finer = cv.plan_at(lens, 0.0, WL, SIZE, settings=cv.Settings(nyquist_safety=4.0))
    assert finer.pitch_mm == pytest.approx(base.pitch_mm / 2)


# ---------------------------------------------------------------------------------------------- undersampling is said
@pytest.mark.parametrize("criterion", ["Nyquist", "band-limit", "window", "ray density"])
def test_undersampled_explicit_plan_warns(criterion):
    lens = thin_lens(doe=even_poly(200.0), doe_to_sensor_mm=10.0)
    good = cv.plan_at(lens, 0.0, WL, SIZE)
    p, n, npad, rays = good.pitch_mm, good.n_grid, good.n_pad, good.ray_grid
    bad = {"Nyquist": Plan(4 * p, n // 4 + 2, npad // 4 + 8, rays),
           "band-limit": Plan(p, n, n, rays),
           "window": Plan(p, n // 2, npad, rays),
           "ray density": Plan(p, n, npad, rays // 3)}[criterion]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rw.psf(lens, 0.0, WL, size=SIZE, plan=bad)
    said = [str(w.message) for w in caught if issubclass(w.category, SamplingWarning)]
    assert any(m.startswith(criterion) for m in said), said


def test_adaptive_and_equivalent_explicit_plans_do_not_warn():
    lens = thin_lens(doe=even_poly(20.0), doe_to_sensor_mm=10.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error", SamplingWarning)
        a = rw.psf(lens, 0.0, WL, size=SIZE)
        b, _ = cv.psf_at(lens, 0.0, WL, SIZE, settings=cv.Settings(pad_factor=2.0), center_mm=a.center_mm)
    assert cv.rel_l2(b.data, a.data) < 1e-2
