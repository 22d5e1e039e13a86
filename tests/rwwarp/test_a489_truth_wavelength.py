"""The A489 truth's wavelength (``_a489_truth.A489(lam_mm=...)``, issue 27): the glass's and the DOE substrate's
indices against rwwarp's material table, the DOE's relief off its design wavelength against diffraction theory
(the wrapped relief's main-order efficiency ``sinc^2(s - 1)``) and the project's remap, the design wavelength's
phase unchanged, and the truth at 0.45 / 0.65 um against geometric optics where the stop has no edge."""
import numpy as np
import pytest

from _a489_truth import A489, catalogue_index, measured_error, truth_and_model


@pytest.mark.parametrize("w_um", [0.45, 0.55, 0.65])
def test_the_indices_are_the_material_tables(w_um):
    # H-K51 (Schott formula) and fused silica (Sellmeier1) written in _a489_truth from the catalogue's coefficients,
    # against rwwarp.materials' evaluation of the same data: equal to rounding (measured 0 and 1e-16)
    from rwwarp import doe, materials
    lens = A489(a_mm=1.0, lam_mm=w_um * 1e-3)
    assert lens.n == pytest.approx(float(materials.get_material("H-K51").n(w_um)), abs=1e-13)
    assert catalogue_index("fused_silica", w_um * 1e-3) == pytest.approx(
        float(materials.get_material("fused_silica").n(w_um)), abs=1e-13)
    # the relief's scale is the project's remap (rwwarp.doe.wavelength_scale), exactly 1 at the design wavelength
    assert lens.doe_scale == pytest.approx(doe.wavelength_scale("fused_silica", 0.55, w_um), abs=1e-13)
    # and H-K51 disperses normally: a wrong wavelength unit (um for mm) or formula would not give 1.52-1.54
    assert 1.52 < lens.n < 1.54


def test_at_the_design_wavelength_the_doe_phase_is_the_unwrapped_polynomial():
    # the old call (0.55 um, the DOE's design wavelength): phi0 = 600 rho^2 + 200 rho^4 itself, bit for bit
    x = np.linspace(-1.4, 1.4, 101)
    y = 0.3 * x[::-1]
    rho2 = (x * x + y * y) / 1.5 ** 2
    for lens in (A489(coeffs=(600.0, 200.0)), A489(coeffs=(600.0, 200.0), lam_mm=0.55e-3)):
        assert lens.doe_scale == 1.0
        np.testing.assert_array_equal(lens.doe_phase(x, y), 600.0 * rho2 + 200.0 * rho2 ** 2)


@pytest.mark.parametrize("w_um", [0.45, 0.65])
def test_off_its_design_wavelength_the_relief_keeps_sinc2_in_its_main_order(w_um):
    # a wrapped relief of depth s * 2 pi puts |<exp(i (s wrap(phi0) - phi0))>|^2 = sinc^2(s - 1) into the order whose
    # phase is phi0 (scalar diffraction theory of a blazed grating; 0.828 at 0.45 um, 0.919 at 0.65 um). phi0 =
    # 200 pi rho^2 sampled uniformly in rho^2 spans exactly 100 zones; 1e6 samples: measured to 2e-9. The relief
    # scaled unwrapped (s phi0) would read 1, the main order alone (phi0) 1 too
    lens = A489(coeffs=(2 * np.pi * 100, 0.0), lam_mm=w_um * 1e-3)
    rho2 = (np.arange(1_000_000) + 0.5) / 1e6
    x = 1.5 * np.sqrt(rho2)
    eta = abs(np.mean(np.exp(1j * (lens.doe_phase(x, 0 * x) - 2 * np.pi * 100 * rho2)))) ** 2
    assert eta == pytest.approx(np.sinc(lens.doe_scale - 1.0) ** 2, abs=1e-6)
    assert eta < 0.95


@pytest.mark.parametrize("w_um, bound", [(0.45, 4e-2), (0.65, 6e-2)])
def test_without_an_edge_the_truth_is_geometric_optics_at_other_wavelengths(w_um, bound):
    # the reduced case (F/8, axis, the 1.5 um grid) with the stop's amplitude a cos^2 over its radius: the wave and
    # the traced field, through the same wrapped relief, differ by 2.0e-2 (0.45 um) and 3.0e-2 (0.65 um) of the
    # peak (7.8e-3 at 0.55 um; bounds 2x); power kept to 1.5e-5. A wavelength taken by one path and not the other
    # (transfer functions, index, carrier, source phase) shows as a difference of order 1
    lens = A489(a_mm=0.5, coeffs=(600.0, 200.0), lam_mm=w_um * 1e-3)
    T, M, info = truth_and_model(lens, 0.0, h=1.5e-3, dz=1e-3, front="wave", soft=1.0)
    assert np.isfinite(T).all() and np.isfinite(M).all()
    assert measured_error(T, M) < bound
    assert info["power_doe_truth"] / info["power_stop"] == pytest.approx(1.0, abs=1e-4)


def test_a_wavelength_outside_the_catalogue_is_refused():
    with pytest.raises(ValueError, match="H-K51"):
        A489(lam_mm=2.0e-3)
    with pytest.raises(ValueError, match="lam_mm"):
        A489(lam_mm=-1.0)
