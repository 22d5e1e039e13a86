"""A/B of the bridge's parameter-table load on one machine, through perf/profile_step.py:

    python perf/ab_table_load.py A --config cooke_hybrid --preset gpu --device cuda --steps 14 --out DIR
    python perf/ab_table_load.py B ...   (the same, the table loaded from its host copy)

A: as the library does it (device to device, ``RayWave.load_params(device_table=)``); B: the host table
uploaded instead (the path before). The remaining arguments go to profile_step.py.
"""
import runpy
import sys
from pathlib import Path

mode = sys.argv.pop(1)
if mode not in ("A", "B"):
    raise SystemExit(f"first argument: A (device to device) or B (host table), got {mode!r}")
if mode == "B":
    import torch_bridge.functions as f
    orig = f.load_table
    f.load_table = lambda rw, table, table_host=None: orig(rw, table_host if table_host is not None else table)
runpy.run_path(str(Path(__file__).resolve().parent / "profile_step.py"), run_name="__main__")
