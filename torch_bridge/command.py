"""``rwwarp design``'s command line: run a config (in the foreground, detached in its own process session, or on
several processes), ``--check`` a config, and the subcommands ``status`` (a run's progress from another
process), ``pack`` (a portable checkpoint in parts) and ``fetch-data`` (a named image set). The training itself is
:mod:`torch_bridge.train`; its ``main`` hands over to :func:`main` here (the entry point stays
``torch_bridge.train:main``)."""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import torch

from torch_bridge.config import parse_overrides
from torch_bridge.report import _fmt
from torch_bridge.train import (CONFIG_DIR, ConfigError, _preflight, build_lens, load_config, run_folder,
                                train)

__all__ = ["main"]


def main(argv=None) -> int:
    """``rwwarp design CONFIG [--preset P] [--arm NAME ...] [--out DIR] [--fresh] [--check] [--table]
    [--detach] [--resume PACK] [--procs N]``, ``rwwarp design status RUN_DIR [--json]``,
    ``rwwarp design pack RUN_DIR [...]`` and ``rwwarp design fetch-data NAME [--out DIR]`` (docs/cli/design.md).
    Returns the exit status (0 success, 1 failure or a run that is not alive for ``status``, 2 bad input)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    # torch's CUDA allocator with expandable segments, unless the user set it: a design step's tiles of varying
    # sizes otherwise fragment the pool (the cooke_hybrid gpu preset's packed e2e step on an H100 at 20f0a09:
    # 27.9 GB of device memory without, 16.5 GB with). Read when CUDA is first used, so set before that.
    os.environ.setdefault("PYTORCH_CUDA_ALLOC_CONF", "expandable_segments:True")
    if argv and argv[0] in _SUBCOMMANDS:
        return _SUBCOMMANDS[argv[0]](argv[1:])
    ap = argparse.ArgumentParser(prog="rwwarp design", description="end-to-end hybrid lens design")
    ap.add_argument("config", help="YAML/TOML config (a path, or the name of a bundled config: "
                                   + ", ".join(sorted(p.stem for p in CONFIG_DIR.glob('*.yaml'))) + ")")
    ap.add_argument("--preset", default=None, help="a preset of the config (e.g. cpu, gpu)")
    ap.add_argument("--arm", action="append", default=None, help="run only this arm (repeatable)")
    ap.add_argument("--out", default=None, help="output folder")
    ap.add_argument("--fresh", action="store_true", help="ignore existing checkpoints")
    ap.add_argument("--check", action="store_true", help="validate the config and exit")
    ap.add_argument("--table", action="store_true",
                    help="train nothing: rewrite table.md/table.csv/designs.png/summary.json from the arms "
                         "finished in the output folder (e.g. after running arms in separate processes)")
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="set a config key in every arm after the preset (repeatable), e.g. --set "
                         "train.joint_steps=2000 --set data.root=data/debian-photos")
    ap.add_argument("--detach", action="store_true",
                    help="start the run in the background in its own process session and return: output in "
                         "RUN_DIR/run.log, process id in RUN_DIR/run.pid, progress in RUN_DIR/progress.json "
                         "(see: rwwarp design status RUN_DIR)")
    ap.add_argument("--resume", default=None, metavar="PACK",
                    help="first write the portable checkpoint PACK (a folder with pack.json, from rwwarp design "
                         "pack) into the run folder, then resume from it")
    ap.add_argument("--procs", type=int, default=1,
                    help="processes (ranks of torch.distributed, started through torch's launcher; gloo on the "
                         "CPU, NCCL with one GPU a rank): PSF nodes and the batch are split across them. "
                         "Under an external torchrun leave it at 1")
    a = ap.parse_args(argv)
    if a.procs < 1:
        print("rwwarp design: error: --procs must be >= 1", file=sys.stderr)
        return 2
    if a.resume and a.fresh:
        print("rwwarp design: error: --resume and --fresh contradict each other", file=sys.stderr)
        return 2
    try:
        a.overrides = parse_overrides(a.set)
    except ConfigError as e:
        print(f"rwwarp design: error: {e}", file=sys.stderr)
        return 2
    if (a.detach or a.resume) and not a.check and not a.table:
        return _detach_or_unpack(a, argv)
    if a.procs > 1 and not a.check and not a.table:
        if int(os.environ.get("WORLD_SIZE", "1") or 1) > 1:
            print("rwwarp design: error: --procs with an external launcher (WORLD_SIZE is set): use one or the "
                  "other", file=sys.stderr)
            return 2
        from rwwarp.distributed import DistributedError, launch
        rest = [x for x in (argv if argv is not None else sys.argv[1:])]
        rest = _drop_option(rest, "--procs")
        try:
            exp = load_config(a.config, a.preset, a.overrides)   # a bad config fails here, before any worker
            for arm in exp["arms"]:
                b = arm["config"]["data"]["batch_size"]
                if b % a.procs:
                    raise ConfigError(f"arm {arm['name']!r}: 'data.batch_size' {b} is not a multiple of --procs "
                                      f"{a.procs} (each rank trains on an equal slice of the batch)")
            codes = launch(_design_worker, a.procs, rest)
        except ConfigError as e:
            print(f"rwwarp design: error: {e}", file=sys.stderr)
            return 2
        except DistributedError as e:
            print(f"rwwarp design: error: {e}", file=sys.stderr)
            return 1
        return max(codes)
    try:
        if a.check:
            return _check(a.config, a.preset, a.out, a.overrides)
        _stop_on_sigterm()
        res = train(a.config, a.preset, [] if a.table else a.arm, a.out, resume=not a.fresh,
                    progress=not a.no_progress, overrides=a.overrides)
    except ConfigError as e:
        print(f"rwwarp design: error: {e}", file=sys.stderr)
        return 2
    for name, r in res.items():
        if "eval" in r:
            d = r["eval"]["depths"][0]
            print(f"{name}: raw {_fmt(d['raw'])}  rec {_fmt(d['rec'])}")
    return 0


def _detach_or_unpack(a, argv: list) -> int:
    """``--resume PACK`` (write the portable checkpoint into the run folder) and/or ``--detach`` (start
    the run in the background); without ``--detach`` the run then goes on in this process."""
    from torch_bridge.runs import detach, process_alive, unpack
    try:
        exp = load_config(a.config, a.preset, a.overrides)
        out = run_folder(exp, a.preset, a.out)
        chosen = exp["arms"] if a.arm is None else [x for x in exp["arms"] if x["name"] in set(a.arm)]
        if a.arm is not None and len(chosen) != len(set(a.arm)):
            raise ConfigError(f"unknown arm(s) {sorted(set(a.arm) - {x['name'] for x in exp['arms']})}; the config "
                              f"has {[x['name'] for x in exp['arms']]}")
        _preflight(chosen, out)
        pidf = out / "run.pid"
        if pidf.exists():
            old = json.loads(pidf.read_text())
            if process_alive(old["pid"], old.get("start_ticks")):
                raise ConfigError(f"{out}: a run is already going on there (pid {old['pid']}); see: rwwarp design "
                                  f"status {out}")
        if a.resume:
            man = unpack(a.resume, out)
            print(f"resume: wrote the pack {a.resume} ({man['bytes'] / 2 ** 20:.1f} MiB, weights {man['weights']}, "
                  f"optimizer {man['optimizer']}) into {out}: "
                  + ", ".join(f"{k} step {v['step']}{' (finished)' if v['finished'] else ''}"
                              for k, v in man["arms"].items()))
    except (ConfigError, FileNotFoundError, ValueError) as e:
        print(f"rwwarp design: error: {e}", file=sys.stderr)
        return 2
    rest = _drop_option([x for x in argv if x != "--detach"], "--resume")
    rest = _drop_option(rest, "--out") + ["--out", str(out)]
    if not a.detach:
        return main(rest)
    env = dict(__import__("os").environ, RWWARP_DESIGN_DETACHED="1")
    env.setdefault("TQDM_MININTERVAL", "30")       # progress bars in run.log: a line every 30 s
    try:
        rec = detach(rest, out, env=env)
    except RuntimeError as e:
        print(f"rwwarp design: error: {e}", file=sys.stderr)
        return 2
    print(f"started pid {rec['pid']} in its own session; log {out / 'run.log'}; progress {out / 'progress.json'}\n"
          f"  rwwarp design status {out}")
    return 0


def _check(config, preset, out_dir, overrides=None) -> int:
    """``--check``: validate the config (every arm after its preset) on this machine without a GPU:
    build each arm's lens and network (parameter count), and print the schedule, the data and the device
    of each arm; a difference of schedule between the arms of the experiment is reported."""
    from torch_bridge.network import build_network
    exp = load_config(config, preset, overrides)
    print(f"{exp['source'] or config}: valid; arms: {', '.join(x['name'] for x in exp['arms'])}")
    nets, sched = {}, set()
    for arm in exp["arms"]:
        cfg = arm["config"]
        try:
            lens = build_lens(cfg, exp["source"])
        except (ValueError, OSError) as e:
            raise ConfigError(f"arm {arm['name']!r}: the lens cannot be built: {e}") from None
        n = cfg["network"]
        key = json.dumps(n, sort_keys=True)
        if key not in nets:
            net = build_network(n["preset"], 3, width=n["width"], enc_blocks=n["enc_blocks"],
                                middle_blocks=n["middle_blocks"], dec_blocks=n["dec_blocks"], zero_init=n["zero_init"])
            nets[key] = sum(p.numel() for p in net.parameters())
        t, d = cfg["train"], cfg["data"]
        sched.add((t["joint_steps"], t["finetune_steps"], d["batch_size"], d["crop"]))
        dev = str(cfg["device"])
        here = "" if not dev.startswith("cuda") or torch.cuda.is_available() else " (no CUDA here: not run)"
        root = d["root"]
        data = "scikit-image samples" if root is None else f"{root}" + ("" if Path(root).is_dir() else " (missing here)")
        print(f"  {arm['name']}: {cfg['design']['method']}, lens {len(lens.surfaces)} surfaces, "
              f"{_n_nodes(cfg)} PSF nodes, network {n['preset']} "
              f"{nets[key] / 1e6:.2f} M parameters, {t['joint_steps']} joint + {t['finetune_steps']} fine-tune steps, "
              f"batch {d['batch_size']} x {d['crop']} px, seed {cfg['seed']}, data {data}, device {dev}{here}")
    if len(sched) > 1:
        print("  note: the arms differ in schedule (joint, fine-tune, batch, crop): " + ", ".join(map(str, sorted(sched))))
    out = run_folder(exp, preset, out_dir)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"output {str(out)!r} exists and is not a folder")
    return 0


def _n_nodes(cfg) -> str:
    """Number of PSF nodes of a config (a grid: gy x gx; a diagonal: its fractions)."""
    nd = cfg["optics"]["nodes"]
    if cfg["render"]["mode"] == "full" or nd["layout"] == "grid":
        return f"{nd['grid'][0]} x {nd['grid'][1]}"
    return str(len(nd["fractions"]))


def _cmd_status(argv: list) -> int:
    """``rwwarp design status RUN_DIR [--json]`` (:func:`torch_bridge.runs.cli_status`)."""
    from torch_bridge.runs import cli_status
    return cli_status(argv)


def _cmd_pack(argv: list) -> int:
    """``rwwarp design pack RUN_DIR [--out DIR] [--weights float32|bfloat16] [--optimizer full|bfloat16|none]
    [--part-mib M] [--arm NAME]``."""
    from torch_bridge.runs import pack
    ap = argparse.ArgumentParser(prog="rwwarp design pack",
                                 description="a portable checkpoint of a stopped run, in parts of <= --part-mib MiB")
    ap.add_argument("run_dir")
    ap.add_argument("--out", default=None, help="folder (default RUN_DIR/pack)")
    ap.add_argument("--weights", default="float32", choices=["float32", "bfloat16"],
                    help="network weights: float32 (exact) or bfloat16 (half the bytes, rounded)")
    ap.add_argument("--optimizer", default="full", choices=["full", "bfloat16", "none"],
                    help="the network's Adam moments: full (exact resume), bfloat16, or none (Adam restarts)")
    ap.add_argument("--part-mib", type=float, default=15.0, help="largest part, MiB (<= 16)")
    ap.add_argument("--arm", action="append", default=None, help="only this arm (repeatable)")
    a = ap.parse_args(argv)
    try:
        man = pack(a.run_dir, a.out, a.weights, a.optimizer, a.part_mib, a.arm)
    except (FileNotFoundError, ValueError, RuntimeError) as e:
        print(f"rwwarp design pack: error: {e}", file=sys.stderr)
        return 2
    out = Path(a.out or Path(a.run_dir) / "pack")
    print(f"{out}: {len(man['parts'])} parts + pack.json, {man['bytes'] / 2 ** 20:.2f} MiB (weights {man['weights']}, "
          f"optimizer {man['optimizer']}); arms: "
          + ", ".join(f"{k} step {v['step']}{' finished' if v['finished'] else ''}" for k, v in man["arms"].items()))
    return 0


def _cmd_fetch_data(argv: list) -> int:
    """``rwwarp design fetch-data NAME [--out DIR] [--debs FILE ...]``: a named image set into a folder."""
    from torch_bridge.data import IMAGE_SETS, fetch_image_set
    ap = argparse.ArgumentParser(prog="rwwarp design fetch-data",
                                 description="write a named image set (train/ and valid/ folders) for data.root")
    ap.add_argument("name", choices=sorted(IMAGE_SETS))
    ap.add_argument("--out", default=None, help="folder (default data/NAME)")
    ap.add_argument("--debs", nargs="+", default=None,
                    help="the Debian packages (.deb) already downloaded (default: apt-get download them)")
    a = ap.parse_args(argv)
    try:
        man = fetch_image_set(a.name, a.out or f"data/{a.name}", debs=a.debs)
    except (FileNotFoundError, ValueError, RuntimeError) as e:
        print(f"rwwarp design fetch-data: error: {e}", file=sys.stderr)
        return 2
    print(f"{man['root']}: {len(man['train'])} train + {len(man['valid'])} valid images, "
          f"{man['bytes'] / 2 ** 20:.1f} MiB")
    return 0


def _stop_on_sigterm():
    """In a detached run (``RWWARP_DESIGN_DETACHED``), SIGTERM ends the run through SystemExit(143), so that
    ``progress.json`` records ``stopped`` (the checkpoint on disk is the last one written, never a partial one)."""
    import os
    import signal
    import threading
    if os.environ.get("RWWARP_DESIGN_DETACHED") and threading.current_thread() is threading.main_thread():
        def stop(signum, frame):
            raise SystemExit(143)
        signal.signal(signal.SIGTERM, stop)


_SUBCOMMANDS = {"status": _cmd_status, "pack": _cmd_pack, "fetch-data": _cmd_fetch_data}


def _drop_option(argv: list, name: str) -> list:
    """``argv`` without ``name VALUE`` / ``name=VALUE``."""
    out, skip = [], False
    for x in argv:
        if skip:
            skip = False
        elif x == name:
            skip = True
        elif not x.startswith(name + "="):
            out.append(x)
    return out


def _design_worker(argv: list) -> int:
    """One rank of ``rwwarp design --procs N`` (started by :func:`rwwarp.distributed.launch`)."""
    return main(argv)
