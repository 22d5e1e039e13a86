"""Planning time per source (ms) on the CPU, the per-source loop (``plan_batch`` once a source, as
:func:`rwwarp.wave.packed.source_plans` and :meth:`torch_bridge.HybridLens.raywaves_alone` planned before issue 25)
against :func:`rwwarp.wave.plan_sources.plan_sources` (what they call now), for two cases:

* ``a489``: the A489+DOE map of :func:`rwwarp.psf_map` (its options: ``method="auto"``, ``allow_pixel``, the CPU's
  memory budget), 10 fields 0..10 deg x 0.45 / 0.55 / 0.65 um = 30 sources, 64 px of 2 um;
* ``a489_relief``: the same with a DOE relief that wraps ~16 zones inside the aperture (``a1 = -100`` rad at the
  1.5 mm norm radius): up to 17 diffraction orders a source at 0.45 / 0.65 um (rwwarp.wave.focal_sources plans them);
* ``cooke``: the ``cooke_hybrid`` design step's 48 sources (``perf/time_plan_cooke.py``'s setup: 16 nodes x 3
  wavelengths, ``method="focal"``, common patch centres) through ``HybridLens.raywaves_alone``.

"warm": the model-error memo (:mod:`rwwarp.wave.model_error`, keyed by the lens's values) holds the estimates
(a psf_map of an unchanged lens); "miss": it is emptied before every call (the design loop, whose lens changes
every optimiser step). The new path reads and fills the same memo (under the same keys), so its warm and
miss figures differ only by the memo's hits. Old and new are called in turn ``--runs`` times; each figure is the
least process CPU time (less sensitive than wall time to other load on a shared machine; the median in brackets)
and the least wall time, ms per source, the pilot trace included. Run it with ``PYTHONPATH`` on another tree (a
copy of this file in its perf/) to time that tree's source_plans / raywaves_alone as "new".
"""
import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def a489_case(relief=None):
    """(old, new, n): callables planning the A489 map's 30 sources the old way and the new; ``relief``: the DOE's
    ``a1 rho^2`` (rad, rho = r / 1.5 mm) in place of the lens file's blank DOE (its orders then planned)."""
    import numpy as np
    import rwwarp as rw
    from rwwarp.map_run import map_args
    from rwwarp.wave.packed import source_plans
    from rwwarp.wave.raywave import RayWave
    from rwwarp.wave.pilot import trace_pilot
    lens = rw.load_lens("a489_doe")
    if relief is not None:
        from rwwarp.lens import Surface
        p = lens.wave_plane_index()
        surfs = [Surface(**{k: getattr(s, k) for k in s.__dataclass_fields__}) for s in lens.surfaces]
        surfs[p].profile = {"kind": "even_poly", "norm_radius": 1.5, "coefficients": [float(relief), 0.0, 0.0, 0.0]}
        lens = lens.replace(surfaces=surfs)
    fields = [float(f) for f in np.linspace(0.0, 10.0, 10)]
    wl = [0.45, 0.55, 0.65]
    F = [f for f in fields for _ in wl]
    W = [w for _ in fields for w in wl]
    a = map_args(lens, fields, wl, size=64, pixel_mm=0.002)
    opts = a.opts

    def old():
        # the per-source loop source_plans ran before: one RayWave (plan_batch) a source, one pilot of all
        pilot = trace_pilot(lens, F, W, opts["device"], opts["dtype"], None, own_pupils=True,
                            use_reference=opts["use_reference"])
        kw = {k: v for k, v in opts.items()}
        return [RayWave(lens, [F[k]], [W[k]], 64, 0.002, own_pupils=True, pilot=pilot.subset([k]), **kw)
                for k in range(len(F))]

    def new():
        return source_plans(lens, F, W, 64, 0.002, **opts)
    return old, new, len(F)


def cooke_case():
    """(old, new, n): the cooke_hybrid design step's 48 sources, the old per-source loop of raywaves_alone and
    the new raywaves_alone."""
    import numpy as np
    from time_plan_cooke import setup
    from rwwarp.psf import RayWave, trace_pilot
    from rwwarp.trace import Tracer
    from rwwarp.wave.batch_plan import plan_batch
    from torch_bridge.modules import bridge_state
    m, fields, ws, centres, size, pixel = setup()
    centers = np.asarray(centres, dtype=np.float64).reshape(len(fields), 2)

    def old():
        lens = m._once("lens", m.to_lens)
        opts = m._raywave_options(None)
        pilot = trace_pilot(lens, fields, ws, opts["device"], opts["dtype"], None, own_pupils=True,
                            use_reference=opts["use_reference"])
        layers, out = {}, []
        for k, (f, w) in enumerate(zip(fields, ws)):
            if w not in layers:
                layers[w] = Tracer(lens, [w], device=opts["device"], dtype=opts["dtype"])
            tr = layers[w]
            bp = plan_batch(lens, [f], [w], int(size), pixel, plan=m.plan_policy, center_mm=centers[k:k + 1],
                            method="focal", own_pupils=True, pilot=pilot.subset([k]), tracer=tr, **opts)
            rw = RayWave.from_plan(bp, requires_grad=True, tracer_on_use=True)
            bridge_state(rw)["base_table"] = tr.params_np.copy()
            out.append(rw)
        return out

    def new():
        return m.raywaves_alone(fields, ws, size, centers_mm=centres, pixel_mm=pixel, method="focal")
    return old, new, len(fields)


def cooke_estimate_case():
    """(old, new, n): the cooke_hybrid design step's 48 sources through raywaves_alone with the model-error estimate
    (``HybridLens(estimate_model_error=True)``, "old") and without it (the design configs' default, "new")."""
    from time_plan_cooke import setup
    m, fields, ws, centres, size, pixel = setup()

    def run(flag):
        m.estimate_model_error = flag
        try:
            return m.raywaves_alone(fields, ws, size, centers_mm=centres, pixel_mm=pixel, method="focal")
        finally:
            m.estimate_model_error = True
    return (lambda: run(True)), (lambda: run(False)), len(fields)


def timed(fns, runs, miss):
    """Per callable of ``fns``, called in turn (interleaved, so that other load on the machine falls on all alike)
    ``runs`` times: (min wall s, min process CPU s, median process CPU s); ``miss``: the model-error memo emptied
    before every call."""
    from rwwarp.wave import model_error
    wall, cpu = [[] for _ in fns], [[] for _ in fns]
    for _ in range(runs):
        for i, fn in enumerate(fns):
            if miss:
                model_error._MEMO.clear()
            t0, c0 = time.perf_counter(), time.process_time()
            fn()
            wall[i].append(time.perf_counter() - t0)
            cpu[i].append(time.process_time() - c0)
    return [(min(w), min(c), statistics.median(c)) for w, c in zip(wall, cpu)]


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--case", choices=("a489", "a489_relief", "cooke", "cooke_estimate", "both"), default="both",
                    help="cooke_estimate: the Cooke sources with the model-error estimate (old) and without (new)")
    args = ap.parse_args()
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    cases = [("a489", a489_case), ("a489_relief", lambda: a489_case(-100.0)), ("cooke", cooke_case),
             ("cooke_estimate", cooke_estimate_case)]
    for name, make in cases:
        if args.case != name and not (args.case == "both" and name in ("a489", "cooke")):
            continue
        old, new, n = make()
        old(), new()   # kernel builds, imports
        for miss in (False, True):
            (w_old, c_old, m_old), (w_new, c_new, m_new) = timed((old, new), args.runs, miss)
            print(f"{name} ({n} sources) {'memo miss' if miss else 'warm     '}: process CPU old {c_old / n * 1e3:.3f} "
                  f"new {c_new / n * 1e3:.3f} ms/source ({c_old / c_new:.2f}x) [medians {m_old / n * 1e3:.3f} / "
                  f"{m_new / n * 1e3:.3f}]; wall old {w_old / n * 1e3:.3f} new {w_new / n * 1e3:.3f} ms/source",
                  flush=True)


if __name__ == "__main__":
    main()
