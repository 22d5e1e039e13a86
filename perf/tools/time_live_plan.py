"""Host time of :class:`torch_bridge.live.LiveProvider`'s planning in a design step, on the CPU: the ``cooke_hybrid``
gpu preset's e2e arm (``perf/time_plan_cooke.py``'s setup: the paraxial achromat start) with ``--nodes`` of its 16
field nodes x one wavelength per colour channel, ``--size`` px of 4 um, chunks of ``--tile`` sources, every source
planned again every call (``replan_every=1``: the steady state of a step whose plans are all made again; the
drift rule makes ~30 of 48 again). Per call (no gradients): the wall time of ``psfs`` (s), the provider's planning
seconds (:attr:`~torch_bridge.live.LiveProvider.plan_seconds`, host), the host seconds spent in ``LiveProvider._chunks``
(planning and packed tiles, without the tiles' runs), the pilot traces made
(:func:`rwwarp.wave.pilot.pilot_from_tracer` calls) and the ``raywaves_alone`` calls. The first call (kernel builds,
first plans) is reported apart. Compare trees by alternating ``PYTHONPATH=TREE python perf/tools/time_live_plan.py``.
"""
import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--nodes", type=int, default=4)
    ap.add_argument("--size", type=int, default=15)
    ap.add_argument("--tile", type=int, default=3)
    ap.add_argument("--runs", type=int, default=5)
    a = ap.parse_args()
    import torch
    from time_plan_cooke import setup
    import rwwarp.wave.pilot as P
    import rwwarp.wave.plan_sources as PS
    import torch_bridge.modules as TM
    from torch_bridge.live import LiveProvider
    m, fields, ws, centres, size, pixel = setup()
    nodes = list(dict.fromkeys(tuple(f) if hasattr(f, "__len__") else (f,) for f in fields))[:a.nodes]
    wls = sorted(set(ws), reverse=True)
    count = {"pilot": 0, "alone": 0}

    def counted(name, fn):
        def wrap(*args, **kw):
            count[name] += 1
            return fn(*args, **kw)
        return wrap
    PS.pilot_from_tracer = counted("pilot", P.pilot_from_tracer)   # plan_sources' pilot (imported by name)
    P.pilot_from_tracer = PS.pilot_from_tracer
    TM.HybridLens.raywaves_alone = counted("alone", TM.HybridLens.raywaves_alone)
    spent = [0.0]   # host seconds inside LiveProvider._chunks (planning, packed tiles; not the tiles' runs)
    chunks = LiveProvider._chunks

    def timed(self, *args):
        it = chunks(self, *args)
        while True:
            t0 = time.perf_counter()
            try:
                c = next(it)
            except StopIteration:
                spent[0] += time.perf_counter() - t0
                return
            spent[0] += time.perf_counter() - t0
            yield c
    LiveProvider._chunks = timed
    prov = LiveProvider(m, nodes, a.size, pixel, wavelength_ref_um=0.55, tile=a.tile)
    with torch.no_grad():
        t0 = time.perf_counter()
        prov.psfs(wls)
        print(f"first call {time.perf_counter() - t0:.2f} s ({len(nodes) * len(wls)} sources, tile {a.tile})")
        wall, plan, chk = [], [], []
        for _ in range(a.runs):
            c0, p0, s0 = dict(count), prov.plan_seconds, spent[0]
            t0 = time.perf_counter()
            prov.psfs(wls)
            wall.append(time.perf_counter() - t0)
            plan.append(prov.plan_seconds - p0)
            chk.append(spent[0] - s0)
            print(f"call: {wall[-1]:.3f} s, planning {plan[-1]:.3f} s, _chunks {chk[-1]:.3f} s, pilot traces {count['pilot'] - c0['pilot']}, "
                  f"raywaves_alone calls {count['alone'] - c0['alone']}")
    print(f"median: call {statistics.median(wall):.3f} s, planning {statistics.median(plan):.3f} s, "
          f"_chunks {statistics.median(chk):.3f} s")


if __name__ == "__main__":
    main()
