"""End-to-end design: a tiny design runs end to end and improves its objective over its own starting
point; resuming from a checkpoint gives the same next step as an uninterrupted run; bad configs fail
before any training with the key named. Plus the pieces: the ray model (RMS spot against rwwarp's
spot_rms, gradients against finite differences), the paraxial achromat (focal shift cancelled), the
cached-field PSFs against rwwarp's own ray-wave PSFs, the NAFNet, the data set and the losses."""
import copy
import csv
import math
import warnings

import numpy as np
import pytest

torch = pytest.importorskip("torch")

import rwwarp as rw
import torch_bridge as tb
from torch_bridge import design as dz
from torch_bridge.train import ConfigError, build_lens, load_config, main, train

# a tiny design: the bundled A489 asphere + 16-level DOE, one wavelength per colour channel, two
# PSF nodes, 32 px crops, the tiny NAFNet
TINY = {
    "experiment": "tiny",
    "seed": 3,
    "lens": {"file": "a489_doe", "doe_levels": 16},
    "optics": {"learn": {"doe": "all"}, "psf_size": 15, "pixel_um": 3.0,
               "nodes": {"layout": "diagonal", "fractions": [0.0, 0.6], "half_size_mm": 1.5},
               "wavelengths_um": [[0.63], [0.55], [0.47]], "nyquist_safety": 1.0, "rays_per_sample": 1.2,
               "doe_budget_cpmm": 10},
    "data": {"crop": 32, "batch_size": 2, "eval_images": 2},
    "network": {"preset": "tiny"},
    "loss": {"alpha": 0.1, "perceptual": "ssim"},
    "train": {"joint_steps": 8, "finetune_steps": 2, "lr_network": 1e-3, "lr_optics": {"doe": 0.5},
              "log_every": 1, "image_every": 5, "checkpoint_every": 0},
    "eval": {"rms_fractions": [0.0, 0.6], "rms_grid": 15, "batch_size": 2},
    "progress": False,
    "arms": [{"name": "e2e", "design": {"method": "e2e"}}],
}


def tiny(**over):
    cfg = copy.deepcopy(TINY)
    for dotted, v in over.items():
        d = cfg
        keys = dotted.split(".")
        for k in keys[:-1]:
            d = d.setdefault(k, {})
        d[keys[-1]] = v
    return cfg


def _rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


# ---------------------------------------------------------------------------------------------- end to end
def test_tiny_design_end_to_end(tmp_path):
    res = train(tiny(), out_dir=tmp_path)["e2e"]
    assert res["steps_done"] == 10
    # the design improves its objective (MSE + alpha (1 - SSIM) on fixed validation crops) over its
    # starting point: the initial DOE (blank) with the untrained (identity) network
    assert res["objective_final"]["loss"] < res["objective_initial"]["loss"]
    assert any(abs(c) > 1e-3 for c in res["eval"]["doe_coefficients"])       # the DOE learned
    d = res["eval"]["depths"][0]
    assert 0.0 < d["psf_energy"] <= 1.0 + 1e-9                               # fraction of entering power
    for part in ("raw", "rec"):
        assert math.isfinite(d[part]["psnr"]) and 0.0 < d[part]["ssim"] <= 1.0
    out = tmp_path / "e2e"
    for f in ("metrics.csv", "checkpoint.pt", "lens.json", "network.pt", "result.json", "step_000000.png",
              "step_000005.png"):
        assert (out / f).exists(), f
    assert (tmp_path / "table.md").exists() and (tmp_path / "designs.png").exists()
    rows = _rows(out / "metrics.csv")
    assert [int(r["step"]) for r in rows] == list(range(10))
    assert {r["phase"] for r in rows} == {"joint", "finetune"}
    # the wave backend's FFT plan builds, counted since the process started: whole, never decreasing, and every
    # plan the first step needed built by then
    built = [int(r["fft_plans_built"]) for r in rows]
    assert built[0] >= 1 and built == sorted(built)
    assert all(r["torch_gb"] == "" and r["torch_peak_gb"] == "" for r in rows)   # CUDA's allocator only
    # what the (cached) provider keeps: its fields, built before step 0, the same at every step; no live units
    held = {r["provider_held_gb"] for r in rows}
    assert len(held) == 1 and float(held.pop()) > 0 and all(r["live_unit_gb"] == "" for r in rows)
    # the designed lens file loads and keeps the quantised DOE
    lens = rw.load_lens(out / "lens.json")
    assert lens.surfaces[lens.doe_index].levels == 16
    # --table rebuilds the table from the finished arm without training
    import yaml
    (tmp_path / "table.md").unlink()
    p = tmp_path / "tiny.yaml"
    p.write_text(yaml.safe_dump(tiny()))
    assert main([str(p), "--table", "--out", str(tmp_path)]) == 0
    assert "| e2e |" in (tmp_path / "table.md").read_text()
    assert len(_rows(out / "metrics.csv")) == 10


def test_resume_gives_the_same_next_step(tmp_path):
    """The optics update every 2nd step; interrupted after step 0 (an optics step), resumed for steps 1-4:
    step 1 (no optics update: the network sees the PSFs of step 0, restored from the checkpoint), step 2
    (an optics step: the optics' Adam moments of step 0 restored from the checkpoint), step 3 (PSFs of
    step 2 again) and step 4 (the first fine-tune step: frozen optics, sensor noise drawn from the
    restored generator); every resumed step equals the uninterrupted run bit for bit.

    One run covers what were two cases (optics_every 1 resumed onto an optics step at step 3, and
    optics_every 2 resumed at step 3 onto a step that reuses restored PSFs, then a fine-tune step): both
    kinds of step follow the resume here, and a resume landing directly on an optics step (optics every
    step) is also checked bit for bit by test_runs.py's killed-and-resumed detached run."""
    # 6 steps in all, both runs stopped after 5: no final evaluation (not what is tested here)
    over = {"train.joint_steps": 4, "train.finetune_steps": 2, "train.image_every": 0, "train.optics_every": 2}
    stop = 5
    cfg = tiny(**over, **{"train.stop_after": stop})
    train(cfg, out_dir=tmp_path / "straight")
    straight = _rows(tmp_path / "straight" / "e2e" / "metrics.csv")
    train(tiny(**over, **{"train.stop_after": 1}), out_dir=tmp_path / "resumed")
    assert len(_rows(tmp_path / "resumed" / "e2e" / "metrics.csv")) == 1
    train(cfg, out_dir=tmp_path / "resumed")
    resumed = _rows(tmp_path / "resumed" / "e2e" / "metrics.csv")
    assert [int(r["step"]) for r in resumed] == list(range(stop))
    assert [r["phase"] for r in resumed] == ["joint"] * 4 + ["finetune"]
    assert [int(float(r["optics_step"])) for r in resumed] == [1, 0, 1, 0, 0]
    for k in range(1, stop):
        for key in ("loss", "mse", "perceptual", "psnr_train", "optics_step"):
            assert float(resumed[k][key]) == float(straight[k][key]), (k, key)
    a = torch.load(tmp_path / "straight" / "e2e" / "checkpoint.pt", weights_only=False)
    b = torch.load(tmp_path / "resumed" / "e2e" / "checkpoint.pt", weights_only=False)
    assert a["step"] == b["step"] == stop
    assert torch.equal(a["module"]["doe"], b["module"]["doe"])
    for k in a["net"]:
        assert torch.equal(a["net"][k], b["net"][k]), k


@pytest.mark.parametrize("over,key", [
    ({"trian": {"joint_steps": 3}}, "trian"),
    ({"train.lr_netwrok": 1e-3}, "train.lr_netwrok"),
    ({"train.joint_steps": -5}, "train.joint_steps"),
    ({"train.lr_network": 0.0}, "train.lr_network"),
    ({"optics.psf_size": 0}, "optics.psf_size"),
    ({"optics.psf_size": 16}, "optics.psf_size"),
    ({"optics.wavelengths_um": [[0.63], [0.55]]}, "optics.wavelengths_um"),
    ({"optics.wavelengths_um": [[0.63], [0.55], [5.0]]}, "optics.wavelengths_um"),
    ({"optics.model": "wave"}, "optics.model"),
    ({"optics.learn": {"doe": [7]}}, "optics.learn.doe"),
    ({"optics.learn": {"curvature": [0]}}, "optics.learn.curvature"),
    ({"data.batch_size": "four"}, "data.batch_size"),
    ({"lens.file": "no_such_lens.json"}, "lens"),
    ({"lens.doe_distance_mm": 50.0}, "lens"),
    ({"network.preset": "huge"}, "network.preset"),
    ({"loss.fallback_alpha": -0.1}, "loss.fallback_alpha"),
    ({"optics.nodes.fractions": [0.0, 1.5]}, "optics.nodes.fractions"),
    ({"eval.depths_mm": [300, -200]}, "eval.depths_mm"),
    ({"train.optics_every": 0}, "train.optics_every"),
    ({"optics.live_pack_waste": 0.5}, "optics.live_pack_waste"),
    ({"train.lr_optics": {"curvature": 1e-5}}, "train.lr_optics"),
])
def test_bad_config_fails_before_training_naming_the_key(tmp_path, over, key):
    cfg = tiny()
    for dotted, v in over.items():
        d = cfg
        ks = dotted.split(".")
        for k in ks[:-1]:
            d = d.setdefault(k, {})
        d[ks[-1]] = v
    with pytest.raises(ConfigError) as e:
        train(cfg, out_dir=tmp_path)
    assert f"'{key}" in str(e.value)
    assert not any(tmp_path.rglob("metrics.csv")) and not any(tmp_path.rglob("checkpoint.pt"))


def test_bad_config_in_an_arm_or_preset(tmp_path):
    cfg = tiny()
    cfg["arms"] = [{"name": "a", "design": {"method": "e2e"}}, {"name": "b", "design": {"methd": "rms"}}]
    with pytest.raises(ConfigError, match=r"arms\[1\].*'design.methd'"):
        train(cfg, out_dir=tmp_path)
    assert not (tmp_path / "a" / "metrics.csv").exists()   # arm a did not start either
    cfg = tiny()
    cfg["presets"] = {"cpu": {"train": {"finetune_steps": -1}}}
    with pytest.raises(ConfigError, match=r"presets.cpu.*'train.finetune_steps'"):
        load_config(cfg, "cpu")
    with pytest.raises(ConfigError, match="unknown preset 'gpu'"):
        load_config(cfg, "gpu")
    cfg = tiny(**{"optics.model": "paraxial-wave"})
    cfg["optics"]["learn"] = {"doe": "all", "curvature": [1]}
    with pytest.raises(ConfigError, match="'optics.model' paraxial-wave"):
        load_config(cfg)
    cfg = tiny()
    cfg["arms"] = [{"name": "f", "design": {"method": "fixed", "init": "rms"}}]
    with pytest.raises(ConfigError, match=r"arms\[0\].*'design.init' rms"):
        load_config(cfg)


def test_e2e_can_start_from_the_rms_spot_design(tmp_path):
    # design.init rms: the paraxial achromat, then the RMS-spot stage, then (not run here) end to end
    from torch_bridge.design import RaySpot
    from torch_bridge.train import Arm
    cfg = load_config(tiny(**{"design.rms": {"steps": 4, "grid": 9, "lr": {"doe": 2.0}}}))["arms"][0]["config"]
    cfg["design"]["init"] = "rms"
    arm = Arm("e2e", cfg, None, tmp_path, progress=False)
    start = arm.module.value("doe").detach().clone()
    assert abs(float(start[0])) > 1.0                              # the achromat's quadratic term
    wls = [c[0] for c in arm.wls]
    before = float(RaySpot(arm.module, arm.fields, wls, grid=9).rms().detach().mean())
    arm.run_design()
    assert len(arm.rms_log) == 4 and arm.design_done
    assert not torch.equal(arm.module.value("doe").detach(), start)
    assert float(RaySpot(arm.module, arm.fields, wls, grid=9).rms().detach().mean()) < before


def test_cli_reports_config_errors(tmp_path, capsys):
    p = tmp_path / "bad.yaml"
    p.write_text("experiment: x\nlens: {file: a489_doe}\ntrain: {joint_stepz: 3}\n")
    assert main([str(p), "--check"]) == 2
    assert "'train.joint_stepz'" in capsys.readouterr().err
    p = tmp_path / "bad.toml"
    p.write_text('experiment = "x"\n[lens]\nfile = "a489_doe"\n[optics]\npsf_size = -3\n')
    assert main([str(p), "--check"]) == 2
    assert "'optics.psf_size'" in capsys.readouterr().err


@pytest.mark.parametrize("name", ["cooke_hybrid", "a489_aberration", "a489_edof"])
def test_bundled_configs_are_valid(name):
    for preset in ("cpu", "gpu"):
        exp = load_config(name, preset)
        assert len(exp["arms"]) >= 2


def test_cooke_lens_matches_the_paper_specification():
    """f = 47 mm and F/4 are the hybrid's: the refractive part with its paraxial achromatic DOE (the
    DOE carries part of the power), measured by a paraxial trace through the DOE's quadratic phase."""
    exp = load_config("cooke_hybrid", None)
    refr = build_lens(exp["base"], exp["source"])
    from rwwarp import paraxial
    d = refr.doe_index
    a1, dist = dz.paraxial_achromat(refr, [0.47, 0.55, 0.63])
    prof = refr.surfaces[d].profile
    lens = refr.with_surface(d, profile={**prof, "coefficients": [a1] + [0.0] * (len(prof["coefficients"]) - 1)},
                             thickness=dist)
    assert refr.efl(0.55) > 50.0                 # the refractive part alone is weaker
    assert lens.efl(0.55) == pytest.approx(47.0, abs=0.2)
    assert paraxial.f_number(lens, 0.55) == pytest.approx(4.0, abs=0.05)
    # a ~20 mm DOE-to-sensor distance and a total length in the paper's range (~75 mm)
    assert 18.0 < dist < 22.0
    assert 55.0 < sum(x.thickness for x in lens.surfaces) < 80.0
    s = lens.surfaces[lens.doe_index]
    assert s.semi_diameter == 4.0 and s.shape == "square" and s.profile["kind"] == "even_poly"
    assert len(s.profile["coefficients"]) == 4
    assert lens.sensor.resolution[0] * lens.sensor.pixel_pitch == pytest.approx(8.0)
    # 14 deg diagonal: the sensor corner (5.66 mm) is at 7 deg
    assert math.degrees(math.atan(4.0 * math.sqrt(2) / lens.efl(0.55))) == pytest.approx(7.0, abs=0.2)


# ---------------------------------------------------------------------------------------------- optics pieces
def _cooke():
    exp = load_config("cooke_hybrid", None)
    return build_lens(exp["base"], exp["source"])


def test_ray_model_rms_equals_rwwarp_spot_rms_without_doe():
    lens = _cooke()
    m = tb.HybridLens(lens)
    fields = [(0.0, 0.0), (2.0, 2.0), (3.5, 3.5)]
    for w in (0.47, 0.63):
        ours = dz.RaySpot(m, fields, [w], grid=41).rms().detach().numpy() * 1e3
        ref = [rw.spot_rms(lens, f, w, grid=41, layout="centers") for f in fields]
        np.testing.assert_allclose(ours, ref, rtol=1e-10)


def test_ray_model_gradients_match_finite_differences():
    lens = _cooke()
    d = lens.doe_index
    lens = lens.with_surface(d, profile={**lens.surfaces[d].profile, "coefficients": [-300.0, 20.0, 5.0, 0.0]})
    m = tb.HybridLens(lens, learn={"curvature": [2], "doe": [1], "thickness": [d]})
    fields = [(0.0, 0.0), (3.0, 3.0)]

    def f():
        return dz.RaySpot(m, fields, [0.47, 0.55, 0.63], grid=21).rms().sum()
    f().backward()
    for q, h in (("curvature", 1e-6), ("doe", 1e-3), ("thickness", 1e-5)):
        p = getattr(m, q)
        g = float(p.grad[0])
        with torch.no_grad():
            p[0] += h
            fp = float(f())
            p[0] -= 2 * h
            fm = float(f())
            p[0] += h
        assert g == pytest.approx((fp - fm) / (2 * h), rel=1e-5), q


@pytest.mark.parametrize("profile,k,h", [
    ({"kind": "fresnel", "focal_length": 2000.0}, 0, 0.1),
    ({"kind": "zernike", "norm_radius": 4.0, "coefficients": [0.0, 0.0, 0.0, -40.0, 5.0, 0.0, 3.0]}, 3, 1e-3),
    ({"kind": "cubic", "norm_radius": 4.0, "alpha": 20.0}, 0, 1e-3)], ids=["fresnel", "zernike", "cubic"])
def test_ray_model_takes_every_smooth_doe_kind(profile, k, h):
    """RaySpot's grating is rwwarp.doe.profile_gradient in torch for every smooth kind (it took only the radial
    polynomials before): the RMS radius's gradient in one DOE value against central differences. Measured
    3.3e-11 relative (Zernike, cubic) and 2.5e-9 (the Fresnel focal length: the truncation (h / f)^2 at
    h = 0.1 mm); tolerance 1e-8."""
    lens = _cooke()
    lens = lens.with_surface(lens.doe_index, profile=profile)
    m = tb.HybridLens(lens, learn={"doe": [k]})
    fields = [(0.0, 0.0), (3.0, 3.0)]

    def f():
        return dz.RaySpot(m, fields, [0.47, 0.63], grid=15).rms().sum()
    f().backward()
    g = float(m.doe.grad[0])
    with torch.no_grad():
        m.doe[0] += h
        fp = float(f())
        m.doe[0] -= 2 * h
        fm = float(f())
        m.doe[0] += h
    assert g != 0.0 and g == pytest.approx((fp - fm) / (2 * h), rel=1e-8)


@pytest.mark.parametrize("kind", ["fresnel", "zernike", "cubic"])
def test_paraxial_efl_of_a_lone_doe_by_hand(kind):
    """paraxial_efl (rwwarp.doe.profile_quadratic and rwwarp.paraxial.diffractive_power in torch) of a stop and
    one DOE, against the hand formulas: a Fresnel lens of focal length f at lambda0 has EFL ``f lambda0 / lambda``
    (d/df = lambda0 / lambda); a Zernike DOE ``q = (2 sqrt(3) z4 - 6 sqrt(5) z11) / R^2``, ``EFL = -pi / (lambda q)``,
    ``d EFL / d z4 = pi / (lambda q^2) 2 sqrt(3) / R^2``; a cubic plate has no power (no finite EFL). Measured
    <= 4.4e-16 relative (2 ulp); tolerance 1e-14."""
    from rwwarp.lens import Lens, Sensor, Surface
    R, lam0 = 2.0, 0.55
    prof = {"fresnel": {"kind": "fresnel", "focal_length": 50.0},
            "zernike": {"kind": "zernike", "norm_radius": R, "coefficients": [0, 0, 0, -30.0] + [0.0] * 6 + [4.0]},
            "cubic": {"kind": "cubic", "norm_radius": R, "alpha": 9.0}}[kind]
    lens = Lens([Surface(type="aperture", semi_diameter=1.0, shape="circle", stop=True, thickness=0.5),
                 Surface(type="doe", semi_diameter=1.0, thickness=50.0, profile=prof, design_wavelength_um=lam0)],
                Sensor(0.004, (100, 100)), wavelengths_um=[0.45, 0.55])
    m = tb.HybridLens(lens, learn={"doe": "all"})
    for lam in (0.45, 0.55):
        m.zero_grad()
        efl = dz.paraxial_efl(m, lam)
        if kind == "cubic":
            assert not math.isfinite(float(efl.detach()))
            continue
        efl.backward()
        if kind == "fresnel":
            ref, dref, i = 50.0 * lam0 / lam, lam0 / lam, 0
        else:
            q = (2 * math.sqrt(3) * -30.0 - 6 * math.sqrt(5) * 4.0) / R ** 2
            ref, dref, i = -math.pi / (lam * 1e-3 * q), math.pi / (lam * 1e-3 * q * q) * 2 * math.sqrt(3) / R ** 2, 3
        assert float(efl.detach()) == pytest.approx(ref, rel=1e-14)
        assert float(m.doe.grad[i]) == pytest.approx(dref, rel=1e-14)


def test_paraxial_achromat_cancels_the_focal_shift():
    lens = _cooke()
    d = lens.doe_index
    wls = [0.47, 0.55, 0.63]
    a1, dist = dz.paraxial_achromat(lens, wls)
    hyb = lens.with_surface(d, profile={**lens.surfaces[d].profile, "coefficients": [a1, 0, 0, 0]}, thickness=dist)
    before = np.ptp([lens.bfl(w) for w in wls])
    after = np.ptp([hyb.bfl(w) for w in wls])
    # the linear (primary) focal shift is gone: the end wavelengths focus together; what is left is
    # the secondary spectrum of a crown + diffractive achromat (curvature in lambda, ~8 % here)
    assert after < 0.1 * before
    assert abs(hyb.bfl(0.47) - hyb.bfl(0.63)) < 0.02 * before
    # the sensor sits at the mean paraxial focus
    assert np.mean([hyb.bfl(w) for w in wls]) == pytest.approx(dist, abs=0.05 * before)
    m = tb.HybridLens(hyb)
    assert float(dz.paraxial_efl(m, 0.55)) == pytest.approx(hyb.efl(0.55), rel=1e-12)


def test_cached_psfs_equal_rwwarp_raywave_psfs():
    """Caching the DOE-plane fields and applying the DOE in torch reproduces rwwarp's ray-wave PSF
    (same plan and centres) to round-off."""
    lens = rw.load_lens("a489_doe")
    d = lens.doe_index
    lens = lens.with_surface(d, profile={**lens.surfaces[d].profile, "coefficients": [-20.0, 8.0, 3.0, -1.0]})
    m = tb.HybridLens(lens, learn={"doe": "all"}, nyquist_safety=1.0, rays_per_sample=1.2)
    fields = dz.field_angles(lens, [(0.0, 0.0), (0.8, 0.8)], 0.55)
    prov = dz.CachedProvider(m, fields, 21, 0.003, wavelength_ref_um=0.55)
    psf = prov.psfs([0.63, 0.47]).detach().numpy()                      # (2 nodes, 2 wavelengths, 21, 21)
    for j, w in enumerate([0.63, 0.47]):
        rec = prov.plans[prov._key(w, None)]
        plan = rw.Plan(rec["pitch_mm"], rec["n_grid"], rec["n_pad"], rec["ray_grid"], "explicit")
        for i, f in enumerate(fields):
            ref = rw.psf(lens, f, w, size=21, pixel_mm=0.003, plan=plan, center_mm=rec["centers"][i],
                         rays_per_sample=1.2, nyquist_safety=1.0, gauss_nodes=m.gauss_nodes)
            np.testing.assert_allclose(psf[i, j], ref.data, rtol=0, atol=1e-9 * ref.data.max())
    # the DOE gradient of a weighted PSF sum at the design wavelength along a random direction against a
    # 4-point central difference; measured 1.4e-10 (h = 0.01 rad), tolerance 1e-9. (Off the design wavelength
    # the wrapped phase sampled on the grid jumps as its zone edges cross samples: no derivative to compare.)
    from _gradcheck import directional_error
    w = torch.from_numpy(np.random.default_rng(3).random((2, 1, 21, 21)))
    assert directional_error(lambda: (prov.psfs([0.55]) * w).sum(), m.doe, 0.01) < 1e-9


def test_paraxial_wave_provider_is_aberration_free_off_axis():
    """The paraxial-wave model idealises the lens: its off-axis PSF is as compact as on axis, the
    ray-wave one is not (the A489 has off-axis aberrations)."""
    lens = rw.load_lens("a489_doe")
    m = tb.HybridLens(lens, nyquist_safety=1.0, rays_per_sample=1.2)
    fields = dz.field_angles(lens, [(0.0, 0.0), (1.2, 1.2)], 0.55)

    def second_moment(p):
        y, x = np.mgrid[:p.shape[0], :p.shape[1]]
        s = p.sum()
        cy, cx = (p * y).sum() / s, (p * x).sum() / s
        return ((p * ((y - cy) ** 2 + (x - cx) ** 2)).sum() / s) ** 0.5
    par = dz.CachedProvider(m, fields, 31, 0.003, model="paraxial-wave").psfs([0.55]).detach().numpy()[:, 0]
    ray = dz.CachedProvider(m, fields, 31, 0.003, model="ray-wave").psfs([0.55]).detach().numpy()[:, 0]
    assert second_moment(par[1]) < 1.5 * second_moment(par[0])
    assert second_moment(ray[1]) > 2.0 * second_moment(par[1])


# ---------------------------------------------------------------------------------------------- network, data, losses
def test_nafnet_presets_shapes_and_identity_start():
    from torch_bridge.network import PRESETS, build_network
    x = torch.rand(2, 3, 37, 50)
    for p in PRESETS:
        if p == "paper":
            continue
        net = build_network(p)
        y = net(x)
        assert y.shape == x.shape
        assert torch.equal(y, x)                 # zero-initialised output convolution: the identity
    net = build_network("tiny", zero_init=False)
    assert not torch.equal(net(x), x)
    n_paper = sum(q.numel() for q in build_network("paper").parameters())
    assert 15e6 < n_paper < 20e6                 # NAFNet-width32 (GoPro) has 17.1 M parameters


def test_image_set_folder_layout_and_reproducible_crops(tmp_path):
    from skimage import io

    from torch_bridge.data import ImageSet
    rng = np.random.default_rng(0)
    for split, n in (("DIV2K_train_HR", 3), ("DIV2K_valid_HR", 1)):
        (tmp_path / split).mkdir()
        for i in range(n):
            io.imsave(tmp_path / split / f"{i:04d}.png", (rng.random((40, 50, 3)) * 255).astype(np.uint8),
                      check_contrast=False)
    tr = ImageSet(tmp_path, "train", crop=16)
    va = ImageSet(tmp_path, "valid", crop=16)
    assert len(tr) == 3 and len(va) == 1
    a = tr.sample(5, torch.Generator().manual_seed(1))
    b = tr.sample(5, torch.Generator().manual_seed(1))
    assert a.shape == (5, 3, 16, 16) and torch.equal(a, b) and 0.0 <= float(a.min()) and float(a.max()) <= 1.0
    assert torch.equal(va.fixed_crops(2), va.fixed_crops(2))
    # the crops are the images' pixels cut and flipped as the docstring says (the same draws, torch's flip)
    g = torch.Generator().manual_seed(1)
    idx = torch.multinomial(tr.prob, 5, replacement=True, generator=g)
    for k, i in enumerate(idx.tolist()):
        y = int(torch.randint(40 - 16 + 1, (1,), generator=g))
        x = int(torch.randint(50 - 16 + 1, (1,), generator=g))
        c = tr.images[i][:, y:y + 16, x:x + 16]
        f = torch.rand(2, generator=g)
        c = c.flip(-1) if f[0] < 0.5 else c
        c = c.flip(-2) if f[1] < 0.5 else c
        assert torch.equal(a[k], c)
    # offline default: scikit-image's bundled samples
    d = ImageSet(None, "valid", crop=32)
    assert len(d) >= 3


def test_losses_fallback_warns_and_vgg_loads_from_a_file(tmp_path):
    from torch_bridge.losses import ReconstructionLoss, VGG16Features, image_metrics, psnr, ssim_torch
    x = torch.rand(2, 3, 32, 32)
    y = (x + 0.05 * torch.randn_like(x)).clamp(0, 1)
    with pytest.warns(UserWarning, match="no VGG16 weights"):
        L = ReconstructionLoss(0.1, "vgg", None, "ssim")
    assert L.perceptual.active_kind == "ssim"
    total, parts = L(y, x)
    assert float(total) == pytest.approx(parts["mse"] + 0.1 * parts["perceptual"], rel=1e-6)
    # the fallback has its own weight (the SSIM term's scale is not the VGG term's); an explicitly
    # chosen weight-free term keeps alpha
    with pytest.warns(UserWarning, match="no VGG16 weights"):
        Lf = ReconstructionLoss(0.1, "vgg", None, "ssim", fallback_alpha=0.01)
    total, parts = Lf(y, x)
    assert Lf.alpha == 0.01
    assert float(total) == pytest.approx(parts["mse"] + 0.01 * parts["perceptual"], rel=1e-6)
    assert ReconstructionLoss(0.1, "ssim", None, "ssim", fallback_alpha=0.01).alpha == 0.1
    assert float(ssim_torch(x, x)) == pytest.approx(1.0, abs=1e-6)
    # a torchvision-layout state dict loads (random weights here: the layout is what is tested)
    v = VGG16Features()
    torch.save({"features." + k: t for k, t in v.features.state_dict().items()}, tmp_path / "vgg16.pth")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        L2 = ReconstructionLoss(0.1, "vgg", tmp_path / "vgg16.pth")
    assert L2.perceptual.active_kind == "vgg"
    assert float(L2(y, x)[0]) > float(L2(x, x)[0])
    m = image_metrics(y, x)
    from skimage.metrics import peak_signal_noise_ratio
    ref = np.mean([peak_signal_noise_ratio(x[i].numpy().transpose(1, 2, 0), y[i].numpy().transpose(1, 2, 0),
                                           data_range=1.0) for i in range(2)])
    assert m["psnr"] == pytest.approx(ref, rel=1e-6)
    assert m["psnr"] == pytest.approx(psnr(y, x), rel=1e-4)
    assert math.isnan(m["one_minus_lpips"])


def test_resume_rewrites_an_older_metrics_csv_with_the_current_columns(tmp_path):
    """A metrics.csv written before a column was added (memory_gb) is truncated at the resume step and
    rewritten with every current column, so the rows appended after it line up with the header."""
    from torch_bridge.train import _CSV_FIELDS, _truncate_csv
    p = tmp_path / "metrics.csv"
    old = [f for f in _CSV_FIELDS if f != "memory_gb"]
    p.write_text(",".join(old) + "\n" + "\n".join(",".join([str(k)] + ["1"] * (len(old) - 1)) for k in range(5)) + "\n")
    _truncate_csv(p, 3, _CSV_FIELDS)
    rows = _rows(p)
    assert [int(r["step"]) for r in rows] == [0, 1, 2]
    assert list(rows[0].keys()) == _CSV_FIELDS and rows[0]["memory_gb"] == ""


def test_design_checks_data_device_and_output_before_writing(tmp_path):
    """A missing data folder, an absent CUDA device or an output path that is a file stop the run
    before anything is written (no folder, no config_resolved.json)."""
    import copy
    from torch_bridge.train import ConfigError, _preflight, load_config, train as run
    exp = load_config("a489_aberration", "cpu")
    out = tmp_path / "run"
    bad = copy.deepcopy(exp)
    for a in bad["arms"]:
        a["config"]["data"]["root"] = str(tmp_path / "missing")
    with pytest.raises(ConfigError, match="data.root"):
        _preflight(bad["arms"], out)
    if not torch.cuda.is_available():
        bad = copy.deepcopy(exp)
        for a in bad["arms"]:
            a["config"]["device"] = "cuda"
        with pytest.raises(ConfigError, match="not available"):
            _preflight(bad["arms"], out)
    f = tmp_path / "afile"
    f.write_text("x")
    with pytest.raises(ConfigError, match="not a folder"):
        run("a489_aberration", "cpu", out_dir=f)
    assert f.read_text() == "x" and not out.exists()


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_ray_spot_on_cuda_equals_the_cpu():
    """RaySpot traces on the module's device: on CUDA (Warp's CUDA trace with its tape, torch's arithmetic on the
    GPU) the RMS radii and their gradients in every learning quantity equal the CPU's (both float64: rounding
    in another order, expected ~1e-14 relative; tolerance 1e-10, the issue's CUDA-vs-CPU bound). On the CPU
    this spot's design took 1.3 s a step where the host's cores were shared (the gpu preset's 300-step
    RMS design did not finish in 520 s)."""
    lens = _cooke()
    learn = {"curvature": "all", "doe": "all", "thickness": "all"}
    fields = [(0.0, 0.0), (2.0, 2.0), (3.5, 3.5)]
    out = {}
    for dev in ("cpu", "cuda"):
        m = tb.HybridLens(lens, learn=learn).to(dev)
        r = dz.RaySpot(m, fields, [0.47, 0.55, 0.63], grid=21).rms()
        assert r.device.type == dev
        r.sum().backward()
        out[dev] = (r.detach().cpu().numpy(), {q: getattr(m, q).grad.detach().cpu().numpy() for q in learn})
    (rc, gc), (rg, gg) = out["cpu"], out["cuda"]
    assert np.all(rc > 0) and np.max(np.abs(rg - rc) / rc) < 1e-10
    for q in learn:
        scale = np.max(np.abs(gc[q]))
        assert scale > 0 and np.max(np.abs(gg[q] - gc[q])) < 1e-10 * scale, q
