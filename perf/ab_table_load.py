"""A/B of the bridge's parameter-table load on one machine: device-to-device (A) against the host table (B)."""
import runpy
import sys

mode = sys.argv.pop(1)
if mode == "B":
    import torch_bridge.functions as f
    orig = f.load_table
    f.load_table = lambda rw, table, table_host=None: orig(rw, table_host if table_host is not None else table)
runpy.run_path(sys.argv[0] if False else "profile_step.py", run_name="__main__")
