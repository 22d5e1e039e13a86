"""Phase surfaces (rwwarp.phase_surface: a DOE on any surface) in HybridLens (torch_bridge.phase_params): the
module's PSF equals rwwarp's, the PSF's gradient in the phase coefficients (and the refracting part of the same
surface) against central finite differences, the thin-lens conjugates and the paraxial EFL against rwwarp's
numpy paraxial trace, to_lens / state_dict round trips, and the learn-spec errors."""
import copy
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

import rwwarp as rw
import torch_bridge as tb
from rwwarp.kernels import trace as ktrace
from rwwarp.lens import Lens, Sensor, Surface

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "rwwarp"))
from test_phase_surface import singlet as front_phase_singlet  # noqa: E402  (the builders of the rwwarp tests)
from test_phase_surface import two_does  # noqa: E402
from test_modules import fd_errors as _fd_errors  # noqa: E402  (4-point central differences)

FIELD = (0.05, 0.4)  # off-axis in x and y: no symmetry
REAR = {"kind": "even_poly", "norm_radius": 5.0, "coefficients": [-120.0, 8.0]}


def small(lens):
    """``lens`` stopped down to a 3 mm entrance pupil (its first surface is the stop) with the sensor at the paraxial
    focus at 0.55 um: a few-px PSF, ~200^2 rays (fast on the CPU)."""
    from rwwarp import paraxial
    lens = lens.with_surface(0, semi_diameter=1.5)
    return lens.with_surface(len(lens.surfaces) - 1, thickness=paraxial.bfl(lens, 0.55))


def rear_phase_singlet():
    """test_phase_surface's diffractive-asphere singlet (N-BK7, f ~ 49 mm) with its BINARY_2 phase moved from the
    front to the curved rear face (R = -150 mm), order 1; the stop stays at the front (:func:`small`)."""
    lens = front_phase_singlet()
    return small(lens.with_surface(0, phase=None).with_surface(1, phase=copy.deepcopy(REAR)))


def phase_and_doe(gap=2.0):
    """The rear-phase singlet with a flat wave-plane DOE (even_poly, R = 1 mm) ``gap`` mm in front of the sensor."""
    lens = rear_phase_singlet()
    surfs = copy.deepcopy(lens.surfaces)
    surfs[1].thickness -= gap
    surfs.append(Surface(type="doe", semi_diameter=1.5, shape="square", thickness=gap,
                         profile={"kind": "even_poly", "norm_radius": 1.0, "coefficients": [-0.5, 0.3]}))
    return Lens(surfs, lens.sensor, wavelengths_um=lens.wavelengths_um)


def small_two_does():
    """test_phase_surface's two phases (an even_poly on a lens's curved front, a fresnel in air in order 2)."""
    return small(two_does())


def _ref_psf(lens, size, method="focal"):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")   # PatchWarning: small patches on purpose (fast tests)
        return rw.psf(lens, FIELD, 0.55, size=size, method=method, focal_precision="double")


@pytest.mark.parametrize("method", ["focal", "asm"])
@pytest.mark.parametrize("make", [rear_phase_singlet, small_two_does, phase_and_doe], ids=["rear", "two_does", "doe"])
def test_psf_equals_rwwarp_psf(make, method):
    """The module's PSF (float64) equals rw.psf of the same lens (focal in double precision, or the ASM): measured
    0 (focal: the same table and kernels) and 1e-16 (asm); tolerance 1e-13 of the peak, as test_modules' DOE lens."""
    lens = make()
    ref = _ref_psf(lens, 12, method=method)
    hl = tb.HybridLens(lens, method=method, learn={"phase": "all"})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        p = hl.psf(FIELD, 0.55, 12)
    assert p.requires_grad
    np.testing.assert_allclose(p.detach().numpy(), ref.data, rtol=0, atol=1e-13 * ref.data.max())


def test_psf_gradient_in_phase_coefficients_against_finite_differences():
    """d(weighted PSF sum)/dA_1, dA_2 of the rear phase (rad), d/dA_3 (a term the surface did not carry, 0 at
    start), and d/d(curvature) of the same surface, on a frozen plan, against 4-point central differences. Steps
    where the differences' rounding and truncation balance (scanned h = 0.01 .. 4 rad: the higher terms weigh
    rho^4, rho^6 <= 1e-3 on this 3 mm beam, so their differences need larger steps): h = 0.2, 1, 4 rad and
    1e-6 / mm. Measured relative errors: A_1 5.7e-9, A_2 5.3e-9, A_3 3.1e-8, curvature 4.5e-9; tolerance 1e-7."""
    hl = tb.HybridLens(rear_phase_singlet(), method="focal", replan=False,
                       learn={"phase": [(1, 0), (1, 1), (1, 2)], "curvature": [1]})
    assert hl.phase_index.tolist() == [8, 9, 10]
    weights = torch.from_numpy(np.random.default_rng(3).random((12, 12)))

    def loss():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return (hl.psf(FIELD, 0.55, 12) * weights).sum()

    errs = _fd_errors(hl, loss, [("phase", 0, 0.2), ("phase", 1, 1.0), ("phase", 2, 4.0), ("curvature", 0, 1e-6)])
    assert all(e < 1e-7 for e in errs.values()), errs
    assert hl.phase.grad.abs().min() > 0     # every term moves the PSF


def test_to_lens_round_trips_learned_coefficients():
    """Changed coefficients go to to_lens (even_poly with the surface's R; a changed fresnel phase as even_poly with
    R = 1 mm, an unchanged one kept as it was) and rw.psf of the exported lens equals the module's PSF (measured
    0; tolerance 1e-13 of the peak); state_dict round-trips exactly, and one written before ``phase`` existed
    loads with the lens's own coefficients."""
    lens = small_two_does()
    hl = tb.HybridLens(lens, method="focal", learn={"phase": [(0, 0), (0, 3), (2, 0)]})
    a1_fresnel = -np.pi / (0.55e-3 * 400.0)
    np.testing.assert_allclose(hl.value("phase")[2, 0].item(), a1_fresnel, rtol=1e-15)
    out = hl.to_lens()
    assert out.surfaces[0].phase == lens.surfaces[0].phase and out.surfaces[2].phase == lens.surfaces[2].phase
    with torch.no_grad():
        hl.phase += torch.tensor([-4.0, 0.3, 2.0], dtype=torch.float64)
    out = hl.to_lens()
    assert out.surfaces[0].phase == {"kind": "even_poly", "norm_radius": 5.0, "coefficients": [-84.0, 5.0, 0.0, 0.3]}
    assert out.surfaces[2].phase == {"kind": "even_poly", "norm_radius": 1.0, "coefficients": [a1_fresnel + 2.0]}
    assert out.surfaces[2].diffraction_order == 2
    assert lens.surfaces[0].phase["coefficients"] == [-80.0, 5.0]          # the input lens is not touched
    ref = _ref_psf(out, 12)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        p = hl.psf(FIELD, 0.55, 12).detach().numpy()
    np.testing.assert_allclose(p, ref.data, rtol=0, atol=1e-13 * ref.data.max())
    # the exported lens's own module reads the same values back
    np.testing.assert_allclose(tb.HybridLens(out).value("phase").numpy(), hl.value("phase").detach().numpy(),
                               rtol=1e-15, atol=0)
    b = tb.HybridLens(lens, learn={"phase": [(0, 0), (0, 3), (2, 0)]})
    b.load_state_dict(copy.deepcopy(hl.state_dict()))
    assert torch.equal(b.value("phase"), hl.value("phase"))
    old = {k: v for k, v in hl.state_dict().items() if not k.startswith("phase")}
    c = tb.HybridLens(lens)
    c.load_state_dict(old)
    np.testing.assert_array_equal(c.value("phase").numpy()[0, :2], [-80.0, 5.0])


@pytest.mark.parametrize("method,gap,steps,tol", [
    ("asm", 2.0, {"phase": 0.2, "doe": 0.02}, 1e-7),
    ("focal", 25.0, {"phase": 1e-3, "doe": 1e-3, "curvature": 1e-8}, 1e-6)])
def test_psf_gradient_with_a_wave_plane_doe_behind_the_phase(method, gap, steps, tol):
    """A phase surface and the wave-plane DOE (``gap`` mm before the sensor) learn together: d/dA_1, d/d(DOE
    coefficients) and (focal) d/d(curvature of the phase surface) against 4-point central differences.
    Measured: ASM 8.4e-9 (A_1), 1.1e-12, 2.2e-12 (DOE), tolerance 1e-7; focal 1.4e-7 (A_1), 4e-12, 3e-12 (DOE),
    4.6e-8 (curvature), tolerance 1e-6.
    Not the phase's doing, hence the 25 mm gap on the focal path: with the DOE 2 mm before a sharp focus (a ~0.1 mm
    footprint) the focal path's refractive gradients agree only to ~1e-3 (A_1 and curvature here: 8e-4, not
    converging with h from 1e-9 to 1e-7 / mm; the same singlet without any phase, in focus: 3e-3; without a DOE, a
    flat dummy wave plane 2 mm before focus: 2e-4), at 10 mm to 7e-6; the ASM is exact there (above). Likely the
    splat's kinks (rays crossing cells) on a near-focus plane, not a missing gradient term: not investigated further."""
    hl = tb.HybridLens(phase_and_doe(gap), method=method, replan=False,
                       learn={"phase": [(1, 0)], "doe": "all", "curvature": [1] if "curvature" in steps else None})
    weights = torch.from_numpy(np.random.default_rng(4).random((12, 12)))

    def loss():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return (hl.psf(FIELD, 0.55, 12) * weights).sum()
    entries = [("phase", 0, steps["phase"]), ("doe", 0, steps["doe"]), ("doe", 1, steps["doe"])]
    if "curvature" in steps:
        entries.append(("curvature", 0, steps["curvature"]))
    errs = _fd_errors(hl, loss, entries)
    assert all(e < tol for e in errs.values()), errs


def thin_lens_after_phase():
    """The rear-phase singlet, an ideal thin lens (f = 200 mm) 2 mm behind it, object at 800 mm (so the thin lens's
    conjugates depend on the phase's power)."""
    lens = rear_phase_singlet()
    surfs = copy.deepcopy(lens.surfaces) + [Surface(type="thin_lens", focal_length=200.0, semi_diameter=6.0,
                                                    thickness=40.0)]
    surfs[1].thickness = 2.0
    out = Lens(surfs, Sensor(0.004, (1000, 1000)), wavelengths_um=lens.wavelengths_um)
    out.object_distance = 800.0
    return out


def test_thin_lens_conjugates_and_efl_include_the_phase_power():
    """The torch paraxial trace of a thin lens behind a phase surface (its power, 1/u and v) reproduces the tracer's
    table (rwwarp.paraxial.thin_lens_conjugates, numpy, which adds -m lambda A_1 / (pi R^2)): agree to 1e-14
    relative, as test_modules' thin lens. paraxial_efl (torch) equals rwwarp.paraxial.efl (numpy) to 1e-13 before
    and after a change of A_1, and its autograd derivative in A_1 the central difference of the numpy EFL."""
    from rwwarp import paraxial
    from torch_bridge.design import paraxial_efl
    lens = thin_lens_after_phase()
    hl = tb.HybridLens(lens, learn={"phase": [(1, 0)], "focal_length": "all"})
    rwv = hl.raywave([FIELD], [0.55], 8)
    got = hl.param_table(rwv).detach().numpy()
    base = tb.functions.bridge_state(rwv)["base_table"]
    for c in (ktrace.P_POWER, ktrace.P_UINV, ktrace.P_V):
        np.testing.assert_allclose(got[:, c], base[:, c], rtol=1e-14, atol=1e-17)
    # without the phase's power the thin lens's 1/u would differ: the check above can fail
    blank = paraxial.thin_lens_conjugates(lens.with_surface(1, phase=None), 0.55, 2)
    assert abs(blank[0] - base[2, ktrace.P_UINV]) > 1e-6 * abs(base[2, ktrace.P_UINV])
    wl = 0.55
    e0 = paraxial_efl(hl, wl)
    assert e0.item() == pytest.approx(paraxial.efl(lens, wl), rel=1e-13)
    with torch.no_grad():
        hl.phase += 3.0
    e1 = paraxial_efl(hl, wl)
    e1.backward()
    assert e1.item() == pytest.approx(paraxial.efl(hl.to_lens(), wl), rel=1e-13)
    assert abs(e1.item() - e0.item()) > 1e-4 * abs(e0.item())          # the phase's power moves the EFL

    def efl(a1):
        return paraxial.efl(lens.with_surface(1, phase={**REAR, "coefficients": [a1, 8.0]}), wl)
    # central difference of the numpy EFL, truncation O(h^2): measured 1.5e-10 (h = 0.05 rad; 1.6e-8 at
    # h = 0.5); tolerance 1e-9
    h = 0.05
    fd = (efl(-117.0 + h) - efl(-117.0 - h)) / (2 * h)
    assert hl.phase.grad.item() == pytest.approx(fd, rel=1e-9)


@pytest.mark.parametrize("make,surface,h", [(rear_phase_singlet, 1, 0.003), (small_two_does, 0, 0.01)],
                         ids=["rear", "two_does"])
def test_ray_spot_gradient_in_phase_against_finite_differences(make, surface, h):
    """The ray model (RaySpot: the Warp trace through the phase surfaces to the last surface, then to the sensor)
    differentiates A_1: d(sum of the RMS radii at 0 and 1 deg)/dA_1 against 4-point central differences
    (h = 0.003 / 0.01 rad; the RMS near focus bends fast: at h = 0.1 the truncation is 2e-4). Measured 1.2e-10
    (rear), 3.1e-11 (two_does); tolerance 1e-9."""
    from torch_bridge.design import RaySpot
    hl = tb.HybridLens(make(), learn={"phase": [(surface, 0)]})

    def loss():
        return RaySpot(hl, [0.0, 1.0], [0.55], grid=15).rms().sum()
    errs = _fd_errors(hl, loss, [("phase", 0, h)])
    assert errs[("phase", 0)] < 1e-9, errs


def test_learn_phase_is_validated():
    lens = rear_phase_singlet()
    with pytest.raises(ValueError, match="carries no diffractive phase"):
        tb.HybridLens(lens, learn={"phase": [(0, 0)]})
    with pytest.raises(ValueError, match=r"\(surface, k\) pairs"):
        tb.HybridLens(lens, learn={"phase": [1]})
    with pytest.raises(ValueError, match="outside"):
        tb.HybridLens(lens, learn={"phase": [(1, 8)]})
    hl = tb.HybridLens(lens, learn={"phase": "all", "curvature": "all"})
    assert hl.phase_index.tolist() == list(range(8, 16)) and hl.curvature.numel() == 2
    assert dict(hl.named_parameters())["phase"].shape == (8,)
    with pytest.raises(ValueError, match="phase surfaces are not limited"):   # the fabrication limit: wave-plane DOE only
        hl.limit_doe_feature(0.01)
    # lenses without phase surfaces: nothing to learn, an all-zero table
    plain = tb.HybridLens(lens.with_surface(1, phase=None), learn={"phase": "all"})
    assert plain.phase.numel() == 0 and not plain.value("phase").any()


def test_design_config_learns_phase(tmp_path):
    """A design config may learn ``phase`` ([surface, k] pairs on a phase surface, with its learning rate); an entry
    on a surface without a phase is refused before any training, naming the key."""
    from torch_bridge.config import ConfigError, load_config
    phase_and_doe().save(tmp_path / "phase_doe.json")
    cfg = {"experiment": "phase", "lens": {"file": str(tmp_path / "phase_doe.json")},
           "optics": {"learn": {"doe": "all", "phase": [[1, 0]]}, "psf_size": 15,
                      "wavelengths_um": [[0.63], [0.55], [0.47]]},
           "train": {"lr_optics": {"doe": 0.5, "phase": 0.1}}, "arms": [{"name": "e2e", "design": {"method": "e2e"}}]}
    out = load_config(copy.deepcopy(cfg))
    assert out["arms"][0]["config"]["optics"]["learn"]["phase"] == [[1, 0]]
    cfg["optics"]["learn"]["phase"] = [[0, 0]]
    with pytest.raises(ConfigError, match="'optics.learn.phase'"):
        load_config(cfg)
