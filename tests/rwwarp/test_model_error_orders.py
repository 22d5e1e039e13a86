"""The model-error estimate's other DOE orders (rwwarp.wave.model_error, "Other orders":
``rwwarp.wave.edge_wave.edge_wave_orders_error``; ``other_orders_error`` beside the scalar law): a wrapped relief used
away from its design wavelength sends light into its other orders, defocused on the sensor; their fields and edge
waves add to the main order's on the patch, the rim's diffraction (which the one-step model leaves out) turning each
order's edge wave by its own Fresnel phase, and the error is over the peak of all of them. Checked against the independent Gauss-Hankel truth
(``_wave_truth.radial_truth`` with the wrapped transmission ``exp(1j alpha (phi0 mod 2 pi))``, every order) and
against the one-step vs wave-path difference on the stored Cooke design off its design wavelength (the case
docs/accuracy.md reported the main-order estimate missing by 20x / 4x). No constant of this part is fitted.
"""
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

import rwwarp as rw
from rwwarp.lens import Lens, Sensor, Surface
from rwwarp.wave import model_error as me

from _wave_truth import radial_truth

ROOT = Path(__file__).resolve().parents[2]
#: the thin lens of the truth (f 50 mm, stop 2.5 mm), a DOE 20 mm before its focus with -40 rho^2 rad (wrapping
#: 6 times over the beam): the DOE's main order focuses Z2 behind it (1 / Z2 = 1 / 20 + 0.55e-3 40 / (pi 1^2))
A_MM, D2, COEFFS, Z2 = 2.5, 20.0, (-40.0, 0.0), 17.54


def wrapped_scene(design_wavelength_um):
    rb = A_MM * D2 / 50.0
    surfs = [Surface(type="aperture", semi_diameter=A_MM, shape="circle", stop=True),
             Surface(type="thin_lens", focal_length=50.0, semi_diameter=1.2 * A_MM, thickness=50.0 - D2),
             Surface(type="doe", semi_diameter=1.5 * rb, thickness=Z2, material="1.5/1e9",
                     design_wavelength_um=design_wavelength_um,
                     profile={"kind": "even_poly", "coefficients": list(COEFFS), "norm_radius": rb})]
    return Lens(surfs, Sensor(0.5e-3, (4000, 4000)), wavelengths_um=[0.55])


@pytest.mark.parametrize("design_um", [0.5, 0.62])
def test_the_other_orders_against_the_truth_of_a_wrapped_doe(design_um):
    # at 0.55 um a dispersion-free relief designed for 0.5 / 0.62 um scales its phase by alpha = 0.909 / 1.127:
    # 0.7 % / 1.6 % of the light in orders 0 and 2 (and +-2 beyond)
    alpha = design_um / 0.55
    rho = np.linspace(0.0, 0.04, 161)
    truth, model = radial_truth(A_MM, D2, COEFFS, rho, alpha=alpha, sensor_mm=Z2)
    measured = float(np.max(np.abs(model - truth)) / truth.max())
    p = rw.plan_psf(wrapped_scene(design_um), 0.0, 0.55, size=48, pixel_mm=0.5e-3, method="auto")
    e = p.model_error
    print(f"alpha {alpha:.4f}: truth {measured:.3g}, estimate {e['estimate']:.3g} (main {e['main_estimate']:.3g}, "
          f"orders {e['orders_estimate']:.3g})")
    # measured: truth 4.65e-3 / 2.16e-3 (6.9e-4 at alpha = 1, one order), estimate 4.49e-3 / 2.37e-3: 0.97x /
    # 1.10x (the on-axis orders' term before: 4.61e-3 / 3.52e-3, 0.99x / 1.63x); within the factor 2 the estimate
    # is held to
    assert 0.5 < e["estimate"] / measured < 2.0
    # the main order's estimate alone (4.9e-4: the rim's edge waves, rwwarp.wave.edge_wave; 0.71x the one-order
    # truth's 6.9e-4) misses it, 0.10x / 0.23x: the orders' term is what the test checks
    assert e["main_estimate"] < 0.3 * measured
    assert e["estimate"] == pytest.approx(e["main_estimate"] + e["orders_estimate"])


def test_a_wrapped_doe_at_its_design_wavelength_has_no_other_orders():
    # a continuous relief at its design wavelength transmits its main order only (c_m = sinc(1 - m) = 0): the
    # estimate is the main order's
    p = rw.plan_psf(wrapped_scene(0.55), 0.0, 0.55, size=48, pixel_mm=0.5e-3, method="auto")
    assert p.model_error["orders_estimate"] == 0.0
    assert p.model_error["estimate"] == p.model_error["main_estimate"] > 0.0


def test_formulas_refuse_bad_input_and_vanish_without_light():
    assert me.other_orders_error(100.0, 50.0, 0.0) == 0.0
    assert me.other_orders_error(float("inf"), 50.0, 0.1) == 0.0
    # E_m = 8 sqrt(eta ratio) |sin(S^2 / (8 pi N_F))| / S, from its definition
    assert me.other_orders_error(100.0, 50.0, 0.04) == pytest.approx(8 * 0.2 * abs(np.sin(2500 / (800 * np.pi))) / 50)
    for bad in [(0.0, 1.0, 0.1), (10.0, float("nan"), 0.1), (10.0, 1.0, -0.1)]:
        with pytest.raises(ValueError, match="Fresnel number"):
            me.other_orders_error(*bad)


COOKE_DESIGN = ROOT / "perf" / "results" / "design" / "cooke_hybrid_cpu_long" / "e2e" / "lens.json"


@pytest.mark.skipif(not COOKE_DESIGN.exists(), reason="the stored Cooke design is not in this checkout")
@pytest.mark.filterwarnings("ignore::UserWarning")
@pytest.mark.parametrize("wl", [0.47, 0.63])
def test_the_cooke_design_off_its_design_wavelength(wl):
    # perf/model_vs_wave_path.py's case (its gpu preset: 63 px of 4 um), on axis: the one-step vs wave-path
    # difference sits on the axis (the orders' edge waves), 1.06e-2 / 1.11e-2 (measured); the main-order estimate
    # read 2.9e-3 / 5.5e-4 of it
    sys.path.insert(0, str(ROOT / "perf"))
    import model_vs_wave_path as mvw
    cfg, _ = mvw.experiment_config("cooke_hybrid")
    o = cfg["optics"]
    kw = dict(size=int(o["psf_size"]), pixel_mm=float(o["pixel_um"]) * 1e-3, nyquist_safety=o["nyquist_safety"],
              rays_per_sample=o["rays_per_sample"], focal_patch_tol=o["focal_patch_tol"], pixel_values=o["pixel_values"])
    lens = rw.load_lens(COOKE_DESIGN)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        row = mvw.one_psf(lens, (0.0, 0.0), wl, None, kw)
    measured = row["max_diff_over_peak"]
    a, b = row["psf_one"], row["psf_two"]
    i = np.unravel_index(np.argmax(np.abs(a - b)), a.shape)
    assert max(abs(i[0] - a.shape[0] // 2), abs(i[1] - a.shape[1] // 2)) <= 1      # on the axis
    e = rw.plan_psf(lens, (0.0, 0.0), wl, size=kw["size"], pixel_mm=kw["pixel_mm"], method="auto",
                    rays_per_sample=kw["rays_per_sample"], nyquist_safety=kw["nyquist_safety"],
                    focal_patch_tol=kw["focal_patch_tol"]).model_error
    # measured: estimate 1.89e-2 / 1.27e-2, 1.78x / 1.15x the difference (the on-axis orders' term before: 1.84e-2 /
    # 1.42e-2; main order 3.6e-3 / 8.1e-4: 0.34x / 0.07x); within the factor 2 (2.5 for the wave path's own error of
    # ~2e-4 .. 5e-4 against the truth on top)
    assert 0.5 < e["estimate"] / measured < 2.5
    assert e["main_estimate"] < 0.5 * measured          # 0.34x / 0.07x measured (comment above)
