"""Kept live focal plans of the cooke_hybrid ``gpu`` design step on the CPU: the replanning rule by calls
(``optics.live_replan_rule: calls``, the rule before) against the rule by wavefront drift (``drift``,
:mod:`torch_bridge.replan`), on a stand-in of the step's optics.

    python perf/replan_study.py [--calls 30] [--size 7] [--out perf/results/replan_study_<commit>_cpu.json]

The stand-in: the real lens (``configs/cooke_hybrid.yaml``, ``gpu`` preset: the paraxial achromat start,
curvatures + DOE + sensor distance learning, F/4) and its 16 field nodes, 3 colour channels, each call one
random wavelength per channel (as ``torch_bridge.train`` draws them), the PSFs at ``--size`` px (63 in the
preset) and a coarser sampling (``--nyquist`` 0.7, ``--rays-per-sample`` 0.3; the preset's 1.5 / 1.2) so a
call takes seconds on 2 CPU cores; a coarser plan has less margin, so a kept plan's error here is an upper
estimate of the preset's. Between calls every learning value takes an optimiser-sized step: the preset's
``train.lr_optics`` (curvature 1e-5 /mm, DOE 2 rad, thickness 5e-3 mm; an Adam step is about the learning rate
per entry) in a fixed random direction (the drift grows linearly, the worst case for kept plans).

Two parts:
* ``calibration``: 9 sources (nodes 0, 5, 15 x 0.45 / 0.55 / 0.66 um) planned once, then the lens moved by
  k steps (all values, or one quantity alone): the kept plans' PSF error against fresh plans (max over the
  sources of max |kept - fresh| / peak(fresh)) against the drift :func:`torch_bridge.replan.wavefront_drift_waves`
  gives: where the default tolerance comes from;
* ``run``: ``--calls`` calls of the 48 sources with the rule by calls (``replan_every`` 3, the preset before) and
  the rule by drift (the preset's new keys): plans made per call (mean, max), host planning seconds per call,
  and the kept plans' PSF error against fresh plans made at every call.
"""
from __future__ import annotations

import argparse
import json
import platform
import subprocess
import time
from pathlib import Path

import numpy as np
import torch


def _standin(size, nyquist, rps):
    import torch_bridge as tb
    from torch_bridge import design as dz
    from torch_bridge.config import _learn_dict, build_lens, load_config
    from torch_bridge.ray_spot import with_paraxial_achromat
    exp = load_config(str(Path(tb.__file__).resolve().parent / "configs" / "cooke_hybrid.yaml"), preset="gpu")
    cfg = next(x for x in exp["arms"] if x["name"] == "e2e")["config"]
    o = cfg["optics"]
    wls = [[float(w) for w in c] for c in o["wavelengths_um"]]
    lens = with_paraxial_achromat(build_lens(cfg, exp["source"]), [w for c in wls for w in c])
    m = tb.HybridLens(lens, learn=_learn_dict(o["learn"]), nyquist_safety=nyquist, rays_per_sample=rps,
                      method=o["propagation"], focal_patch_tol=o["focal_patch_tol"], pixel_values=o["pixel_values"])
    wl_ref = wls[len(wls) // 2][len(wls[0]) // 2]
    nd = o["nodes"]
    pos = dz.node_positions_mm(nd["layout"], nd["half_size_mm"], nd["grid"], nd["fractions"], nd["region"])
    fields = dz.field_angles(lens, pos, wl_ref)
    return cfg, m, fields, wls, wl_ref, o["pixel_um"] * 1e-3


def _direction(m, lrs, seed):
    """{quantity: step tensor}: lr x a fixed random sign per learning entry."""
    g = np.random.default_rng(seed)
    return {q: torch.as_tensor(lrs[q] * g.choice([-1.0, 1.0], size=tuple(getattr(m, q).shape)))
            for q in lrs if getattr(m, q).numel()}


def _step(m, d, k=1.0, only=None):
    with torch.no_grad():
        for q, s in d.items():
            if only is None or q == only:
                getattr(m, q).add_(k * s)


def _err(kept, fresh):
    """max over sources of max |kept - fresh| / peak(fresh); kept, fresh (n, c, s, s)."""
    k = kept.reshape(-1, *kept.shape[-2:])
    f = fresh.reshape(-1, *fresh.shape[-2:])
    peak = f.abs().amax((1, 2))
    return (((k - f).abs().amax((1, 2))) / peak)


def calibration(m, fields, wls, wl_ref, pix, size, d,
                steps=((None, (0.1, 0.3, 1.0)),)):
    from torch_bridge import design as dz
    from torch_bridge.replan import wavefront_drift_waves
    sel = [fields[i] for i in (0, 5)]
    wl = [0.45, 0.55, 0.66]
    base = {q: getattr(m, q).detach().clone() for q in d}
    out = []
    for only, ks in steps:
        for k in ks:
            with torch.no_grad():
                for q in d:
                    getattr(m, q).copy_(base[q])
            prov = dz.LiveProvider(m, sel, size, pix, wavelength_ref_um=wl_ref, replan_every=10 ** 6)
            with torch.no_grad():
                for w in wl:
                    prov.psfs([w])
                plans = {key: e[0] for key, e in prov._focal_rws.items()}
                _step(m, d, k, only)
                lens_now = m.to_lens()
                for w in wl:
                    kept = prov.psfs([w])
                    fresh = dz.LiveProvider(m, sel, size, pix, wavelength_ref_um=wl_ref).psfs([w])
                    e = _err(kept, fresh)
                    for i, f in enumerate(sel):
                        key = (tuple(np.ravel(f)), w, None)
                        dr = wavefront_drift_waves(plans[key].lens, lens_now, w, key[0])
                        win = bool(prov._focal_rws[key][3])   # more rays left its window than at its first use
                        out.append({"quantity": only or "all", "steps": k, "field_deg": list(key[0]), "wavelength_um": w,
                                    "drift_waves": dr, "err_peak": float(e[i]), "window_flag": win})
                        print(f"calib {only or 'all'} k={k} f={np.round(key[0], 2)} wl={w}: drift {dr:.3f} waves "
                              f"err {float(e[i]):.2e} window {win}", flush=True)
            assert prov.plans_made == 3 * len(sel)
    with torch.no_grad():
        for q in d:
            getattr(m, q).copy_(base[q])
    return out


def run(m, fields, wls, wl_ref, pix, size, d, calls, rules, seed=0, scale=1.0, save=None, fresh_every=1):
    from torch_bridge import design as dz
    provs = {name: dz.LiveProvider(m, fields, size, pix, wavelength_ref_um=wl_ref, **kw) for name, kw in rules.items()}
    fresh = dz.LiveProvider(m, fields, size, pix, wavelength_ref_um=wl_ref)
    gen = torch.Generator().manual_seed(seed)
    rec = {name: [] for name in rules}
    for c in range(calls):
        w = [ch[int(torch.randint(len(ch), (1,), generator=gen))] for ch in wls]
        with torch.no_grad():
            t = time.perf_counter()
            ref = fresh.psfs(w) if c % fresh_every == 0 else None
            t_ref = time.perf_counter() - t
            for name, p in provs.items():
                made, ps, ds = p.plans_made, p.plan_seconds, p.drift_seconds
                t = time.perf_counter()
                out = p.psfs(w)
                wall = time.perf_counter() - t
                e = _err(out, ref) if ref is not None else torch.full((1,), float("nan"))
                # sources whose patch holds >= 1 % of the entering power (at --size 7 px a red or blue corner node's
                # patch can hold 1e-4 of it: a peak of ~1e-6, against which any difference is large)
                lit = (ref.reshape(-1, *ref.shape[-2:]).sum((1, 2)) >= 1e-2) if ref is not None else None
                e_lit = float(e[lit].max()) if lit is not None and bool(lit.any()) else float("nan")
                rec[name].append({"call": c, "wavelengths_um": w, "plans_made": p.plans_made - made,
                                  "plan_s": p.plan_seconds - ps, "judge_s": p.drift_seconds - ds, "wall_s": wall,
                                  "err_peak_max": float(e.max()), "err_peak_max_lit": e_lit,
                                  "deferred_total": p.replans_deferred,
                                  "replans_total": dict(p.replans)})
                r = rec[name][-1]
                print(f"call {c} {name}: plans {r['plans_made']} plan {r['plan_s']:.2f} s judge {r['judge_s']:.3f} s "
                      f"wall {wall:.1f} s err {r['err_peak_max']:.2e} (fresh {t_ref:.1f} s)", flush=True)
        _step(m, d, scale)
        if save is not None:
            save({"calls": rec})
    return {"calls": rec, "summary": summarise(rec)}


def summarise(rec: dict) -> dict:
    """Per rule: plans made per call (mean, max; the first call, which plans every source under both rules, left
    out), host planning and judging seconds per call, the kept plans' PSF error against fresh plans."""
    summ = {}
    for name, rs in rec.items():
        later = rs[1:]   # the first call plans every source under both rules
        pm = [r["plans_made"] for r in later]
        summ[name] = {"plans_per_call_mean": float(np.mean(pm)), "plans_per_call_max": int(np.max(pm)),
                      "plan_s_per_call_mean": float(np.mean([r["plan_s"] for r in later])),
                      "judge_s_per_call_mean": float(np.mean([r["judge_s"] for r in later])),
                      "err_peak_max": float(np.nanmax([r["err_peak_max"] for r in rs])),
                      "err_peak_median_of_calls": float(np.nanmedian([r["err_peak_max"] for r in rs])),
                      "err_peak_max_lit": float(np.nanmax([r.get("err_peak_max_lit", np.nan) for r in rs])),
                      "plans_per_call_steady_mean": float(np.mean([r["plans_made"] for r in rs[4:]])) if len(rs) > 4 else None,
                      "plans_per_call_steady_max": int(np.max([r["plans_made"] for r in rs[4:]])) if len(rs) > 4 else None,
                      "plan_s_per_call_steady_mean": float(np.mean([r["plan_s"] for r in rs[4:]])) if len(rs) > 4 else None,
                      "replans": rs[-1]["replans_total"], "deferred": rs[-1]["deferred_total"], "n_calls": len(rs)}
    return summ


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--calls", type=int, default=30)
    ap.add_argument("--size", type=int, default=7)
    ap.add_argument("--nyquist", type=float, default=1.0)
    ap.add_argument("--rays-per-sample", type=float, default=0.5)
    ap.add_argument("--parts", default="calibration,run")
    ap.add_argument("--drift", type=float, default=None, help="the drift rule's tolerance (waves; default the config's)")
    ap.add_argument("--step-scale", type=float, default=1.0,
                    help="the step between calls in learning rates (1: a full Adam step of every value, same direction)")
    ap.add_argument("--calib-size", type=int, default=31)
    ap.add_argument("--calib-nyquist", type=float, default=1.5)
    ap.add_argument("--calib-rays-per-sample", type=float, default=1.2)
    ap.add_argument("--out", default=None)
    ap.add_argument("--fresh-every", type=int, default=1, help="fresh reference plans every this many calls")
    ap.add_argument("--summarise", default=None, help="only summarise the calls of this JSON (a run cut short)")
    a = ap.parse_args()
    if a.summarise:
        res = json.loads(Path(a.summarise).read_text())
        res["run"]["summary"] = summarise(res["run"]["calls"])
        Path(a.out or a.summarise).write_text(json.dumps(res, indent=1))
        print(json.dumps(res["run"]["summary"], indent=1))
        return
    torch.set_num_threads(2)
    cfg, m, fields, wls, wl_ref, pix = _standin(a.size, a.nyquist, a.rays_per_sample)
    lrs = {q: float(v) for q, v in cfg["train"]["lr_optics"].items()}
    d = _direction(m, lrs, 1)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=Path(__file__).parent).stdout.strip()
    o = cfg["optics"]
    res = {"commit": commit, "machine": f"development CPU, 2 cores shared with other jobs ({platform.processor() or platform.machine()})",
           "standin": {"psf_size": a.size, "nyquist_safety": a.nyquist, "rays_per_sample": a.rays_per_sample,
                       "n_fields": len(fields), "wavelengths_um": wls, "lr_step": lrs, "pixel_mm": pix}}
    out = Path(a.out or Path(__file__).parent / "results" / f"replan_study_{commit}_cpu.json")
    if "calibration" in a.parts:
        # at the preset's sampling (a coarse plan is far more sensitive to its age: at 7 px, nyquist_safety 1.0,
        # rays_per_sample 0.5 the blue corner node's error is ~200x that at 31 px, 1.5, 1.2)
        _, mc, fc, _, _, _ = _standin(a.calib_size, a.calib_nyquist, a.calib_rays_per_sample)
        res["calibration_standin"] = {"psf_size": a.calib_size, "nyquist_safety": a.calib_nyquist,
                                      "rays_per_sample": a.calib_rays_per_sample, "fields_deg": [list(np.ravel(fc[i])) for i in (0, 5)]}
        res["calibration"] = calibration(mc, fc, wls, wl_ref, pix, a.calib_size, _direction(mc, lrs, 1))
        out.write_text(json.dumps(res, indent=1))
    if "run" in a.parts:
        tol = a.drift if a.drift is not None else o["live_replan_drift"]
        rules = {"calls_every3": dict(replan_every=3, replan_rule="calls"),
                 "drift": dict(replan_every=o["live_replan_every"], replan_rule="drift", replan_drift=tol,
                               replan_drift_hard=o["live_replan_drift_hard"], replan_spread=o["live_replan_spread"])}
        res["rules"] = rules
        res["step_scale"] = a.step_scale
        res["fresh_every"] = a.fresh_every

        def save(part):
            res["run"] = part
            out.write_text(json.dumps(res, indent=1))
        res["run"] = run(m, fields, wls, wl_ref, pix, a.size, d, a.calls, rules, scale=a.step_scale, save=save,
                         fresh_every=a.fresh_every)
        out.write_text(json.dumps(res, indent=1))
        print(json.dumps(res["run"]["summary"], indent=1))
    print("wrote", out)


if __name__ == "__main__":
    main()
