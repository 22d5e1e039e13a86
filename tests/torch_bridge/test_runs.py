"""Runs that survive interruption (torch_bridge.runs, rwwarp design --detach / status / pack / --resume):
a tiny design started in the background is killed after its first checkpoint and resumed from the
portable checkpoint on a "fresh machine" (another folder); the resumed run must equal an uninterrupted
one bit for bit with the full state. Also: pack parts and their checks, resuming without the Adam state,
--check of the bundled GPU presets, and the named image set read from Debian packages."""
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import tarfile
import time
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")
yaml = pytest.importorskip("yaml")

from test_train import _rows, tiny  # noqa: E402  (the tiny design of test_train.py)
from torch_bridge.runs import pack, process_alive, status, unpack  # noqa: E402
from torch_bridge.train import main, train  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
# 4 joint steps (the optics update at every one) + 1 fine-tune step, a checkpoint after every step
TOTAL = 5
OVER = {"train.joint_steps": 4, "train.finetune_steps": 1, "train.checkpoint_every": 1, "train.image_every": 0,
        "train.optics_every": 1}
KEYS = ("loss", "mse", "perceptual", "psnr_train", "optics_step")


def _design(*args, **kw):
    """``python -m torch_bridge.train ARGS`` in another process."""
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.run([sys.executable, "-m", "torch_bridge.train", *map(str, args)], capture_output=True,
                          text=True, env=env, timeout=120, **kw)


def _rwwarp_status(*args):
    """``rwwarp design status ARGS`` in another process (the command line's fast path: it reads the run's
    files without importing torch, a few seconds less than ``python -m torch_bridge.train status``)."""
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    code = "import sys, rwwarp.cli as c\nsys.exit(c.main(sys.argv[1:]))\n"
    return subprocess.run([sys.executable, "-c", code, "design", "status", *map(str, args)], capture_output=True,
                          text=True, env=env, timeout=120)


def test_detached_run_killed_and_resumed_from_the_pack_equals_an_uninterrupted_run(tmp_path):
    cfg = tmp_path / "tiny.yaml"
    cfg.write_text(yaml.safe_dump(tiny(**OVER)))
    run = tmp_path / "run"
    r = _design(cfg, "--out", run, "--detach")
    assert r.returncode == 0, r.stderr
    pid = json.loads((run / "run.pid").read_text())
    ck = run / "e2e" / "checkpoint.pt"
    deadline = time.time() + 90
    while time.time() < deadline:            # a checkpoint after a training step (step 0 is the design stage)
        if ck.exists() and torch.load(ck, weights_only=False)["step"] >= 1:
            break
        time.sleep(0.1)
    st = _rwwarp_status(run)                   # from another process
    assert st.returncode == 0 and "ALIVE" in st.stdout, st.stdout + st.stderr
    assert json.loads((run / "progress.json").read_text())["arm"] == "e2e"
    os.kill(pid["pid"], signal.SIGKILL)        # a machine taken back: no handler runs
    for _ in range(100):
        if not process_alive(pid["pid"], pid["start_ticks"]):
            break
        time.sleep(0.05)
    st = _rwwarp_status(run, "--json")
    rec = json.loads(st.stdout)
    assert st.returncode == 1 and not rec["alive"] and rec["state"] == "dead", st.stdout
    step = torch.load(ck, weights_only=False)["step"]
    assert 1 <= step < TOTAL, "the detached run finished before it was killed"
    # the uninterrupted reference, in this process
    straight = train(tiny(**OVER), out_dir=tmp_path / "straight")["e2e"]
    # pack: parts of <= 0.25 MiB (several parts), each checked on the way back
    man = pack(run, tmp_path / "pack", part_mib=0.25)
    assert len(man["parts"]) >= 2
    assert all((tmp_path / "pack" / p["file"]).stat().st_size <= 0.25 * 2 ** 20 for p in man["parts"])
    bad = tmp_path / "bad"
    bad.mkdir()
    for f in (tmp_path / "pack").iterdir():
        (bad / f.name).write_bytes(f.read_bytes())
    b = bytearray((bad / "pack.part001").read_bytes())
    b[10] ^= 1
    (bad / "pack.part001").write_bytes(bytes(b))
    with pytest.raises(ValueError, match="pack.part001"):
        unpack(bad, tmp_path / "nowhere")
    (bad / "pack.part001").unlink()
    with pytest.raises(FileNotFoundError, match="pack.part001 is missing"):
        unpack(bad, tmp_path / "nowhere")
    # a fresh machine: only the pack travels; --resume writes it into a new run folder and goes on
    assert main([str(cfg), "--out", str(tmp_path / "fresh"), "--resume", str(tmp_path / "pack"), "--no-progress"]) == 0
    resumed = _rows(tmp_path / "fresh" / "e2e" / "metrics.csv")
    ref = _rows(tmp_path / "straight" / "e2e" / "metrics.csv")
    assert [int(x["step"]) for x in resumed] == list(range(TOTAL))
    for k in range(TOTAL):                         # bit-equal: before the kill (carried over) and after it
        for key in KEYS:
            assert float(resumed[k][key]) == float(ref[k][key]), (k, key)
    res = json.loads((tmp_path / "fresh" / "e2e" / "result.json").read_text())
    for part in ("raw", "rec"):
        for m in ("psnr", "ssim"):
            assert res["eval"]["depths"][0][part][m] == straight["eval"]["depths"][0][part][m], (part, m)
    segs = res["run"]["segments"]
    assert [s["start_step"] for s in segs] == [0, step] and segs[-1]["end_step"] == TOTAL
    assert res["run"]["steps_done"] == TOTAL and res["run"]["wall_s_total"] > 0
    s = json.loads((tmp_path / "fresh" / "progress.json").read_text())
    assert s["state"] == "done" and s["step"] == TOTAL
    # a second run of the finished experiment keeps the arm (no training, no new evaluation)
    mtime = (tmp_path / "fresh" / "e2e" / "result.json").stat().st_mtime_ns
    assert main([str(cfg), "--out", str(tmp_path / "fresh"), "--no-progress"]) == 0
    assert (tmp_path / "fresh" / "e2e" / "result.json").stat().st_mtime_ns == mtime
    # the finished run packed and moved once more: the experiment runs again there (it redraws the table's
    # figure from the evaluation's PSFs and crops, which travel with a finished arm) and keeps the arm
    pack(tmp_path / "fresh", tmp_path / "pack2")
    assert main([str(cfg), "--out", str(tmp_path / "moved"), "--resume", str(tmp_path / "pack2"),
                 "--no-progress"]) == 0
    for f in ("eval_psfs.npz", "result.json"):
        assert (tmp_path / "moved" / "e2e" / f).read_bytes() == (tmp_path / "fresh" / "e2e" / f).read_bytes(), f
    assert (tmp_path / "moved" / "designs.png").exists()


def test_resume_without_adam_state_and_bf16_weights(tmp_path):
    """The small portable form (bfloat16 weights, no Adam moments) resumes and finishes; it is not the
    uninterrupted run (Adam restarts, weights rounded to 8 bits of mantissa), and says so."""
    # 2 joint steps and 1 fine-tune step, stopped after the first: the network's Adam state exists from the
    # first step on, and the resumed run goes on through an optics step and a fine-tune step (5 steps
    # stopped after 3 before: the same paths, 2 steps more)
    over = dict(OVER, **{"train.checkpoint_every": 0, "train.joint_steps": 2, "train.finetune_steps": 1})
    total = 3
    train(tiny(**over, **{"train.stop_after": 1}), out_dir=tmp_path / "run")
    full = pack(tmp_path / "run", tmp_path / "p_full")
    small = pack(tmp_path / "run", tmp_path / "p_small", weights="bfloat16", optimizer="none")
    assert small["bytes"] < full["bytes"]
    unpack(tmp_path / "p_small", tmp_path / "res")
    ck = torch.load(tmp_path / "res" / "e2e" / "checkpoint.pt", weights_only=False)
    ref = torch.load(tmp_path / "run" / "e2e" / "checkpoint.pt", weights_only=False)
    assert ck["opt_net"] is None and ck["step"] == ref["step"] == 1
    assert ref["opt_net"]["state"]                  # there was an Adam state to leave out
    for k, v in ref["net"].items():            # bfloat16 round trip: relative error <= 2^-8
        assert ck["net"][k].dtype == torch.float32
        assert torch.allclose(ck["net"][k], v, rtol=2 ** -8, atol=0), k
    assert torch.equal(ck["module"]["doe"], ref["module"]["doe"])     # the optics state is exact
    res = train(tiny(**over), out_dir=tmp_path / "res")["e2e"]
    assert res["steps_done"] == total and res["run"]["resumed_without_optimizer"]
    assert any("without the network's Adam state" in n for n in res["notes"])


@pytest.mark.parametrize("name", ["cooke_hybrid", "a489_aberration", "a489_edof"])
def test_gpu_presets_check_on_the_cpu(name, capsys):
    """``rwwarp design NAME --preset gpu --check``: every arm's lens and the paper-size network build on
    the CPU; the same schedule for every arm."""
    assert main([name, "--preset", "gpu", "--check"]) == 0
    out = capsys.readouterr().out
    assert "valid" in out and "17.1" in out and "differ in schedule" not in out, out
    # --set reaches every arm after the preset; a misspelt key is refused, naming it
    assert main([name, "--preset", "gpu", "--check", "--set", "train.joint_steps=2000"]) == 0
    out = capsys.readouterr().out
    assert out.count("2000 joint") == out.count("\n  ") and "2000 joint" in out, out
    assert main([name, "--preset", "gpu", "--check", "--set", "train.joint_stesp=2000"]) == 2
    assert "'train.joint_stesp'" in capsys.readouterr().err


def _deb(path: Path, files: dict, links: dict = ()):
    """A minimal Debian package (ar archive with data.tar.gz) holding ``files`` and symbolic ``links``."""
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tf:
        for name, b in files.items():
            ti = tarfile.TarInfo("./" + name)
            ti.size = len(b)
            tf.addfile(ti, io.BytesIO(b))
        for name, target in dict(links).items():
            ti = tarfile.TarInfo("./" + name)
            ti.type, ti.linkname = tarfile.SYMTYPE, target
            tf.addfile(ti)
    members = [("debian-binary", b"2.0\n"), ("control.tar.gz", b""), ("data.tar.gz", buf.getvalue())]
    out = b"!<arch>\n"
    for n, b in members:
        out += f"{n:<16}{0:<12}{0:<6}{0:<6}{100644:<8}{len(b):<10}`\n".encode() + b + (b"\n" if len(b) % 2 else b"")
    path.write_bytes(out)


def test_named_image_set_from_debian_packages(tmp_path):
    import hashlib

    import numpy as np
    from skimage import io as skio

    from torch_bridge.data import IMAGE_SETS, ImageSet, fetch_image_set
    spec = IMAGE_SETS["debian-photos"]
    assert len(spec["images"]) == 22 and sum(r[7] == "valid" for r in spec["images"]) == 4
    assert len({r[0] for r in spec["images"]}) == 22
    rng = np.random.default_rng(0)
    blobs = {}
    for k in range(4):
        p = tmp_path / f"im{k}.png"
        skio.imsave(p, rng.integers(0, 255, (40 + k, 50, 3), dtype=np.uint8), check_contrast=False)
        blobs[k] = p.read_bytes()
    sha = {k: hashlib.sha256(b).hexdigest() for k, b in blobs.items()}
    table = {"packages": {"pkga": "1", "pkgb": "2"}, "images": [
        ("a0", "pkga", "usr/share/a/0.png", sha[0], len(blobs[0]), "GPL-2+", "x", "train"),
        ("a1", "pkga", "usr/share/a/link.png", sha[1], len(blobs[1]), "GPL-2+", "x", "valid"),
        ("b2", "pkgb", "usr/share/b/2.png", sha[2], len(blobs[2]), "LGPL-3", "y", "train"),
        ("b3", "pkgb", "usr/share/b/3.png", sha[3], len(blobs[3]), "LGPL-3", "y", "train")]}
    _deb(tmp_path / "pkga_1_all.deb", {"usr/share/a/0.png": blobs[0], "usr/share/a/1.png": blobs[1]},
         {"usr/share/a/link.png": "1.png"})
    _deb(tmp_path / "pkgb_2_all.deb", {"usr/share/b/2.png": blobs[2], "usr/share/b/3.png": blobs[3]})
    debs = [tmp_path / "pkga_1_all.deb", tmp_path / "pkgb_2_all.deb"]
    man = fetch_image_set("toy", tmp_path / "set", debs=debs, table=table)
    assert man["train"] == ["train/a0.png", "train/b2.png", "train/b3.png"] and man["valid"] == ["valid/a1.png"]
    assert (tmp_path / "set" / "valid" / "a1.png").read_bytes() == blobs[1]            # through the link
    tr, va = ImageSet(tmp_path / "set", "train", 16), ImageSet(tmp_path / "set", "valid", 16)
    assert len(tr) == 3 and len(va) == 1 and tuple(va[0].shape) == (3, 41, 50)
    g1, g2 = torch.Generator().manual_seed(5), torch.Generator().manual_seed(5)
    assert torch.equal(tr.sample(3, g1), tr.sample(3, g2))
    (tmp_path / "set" / "train" / "b3.png").unlink()
    with pytest.raises(FileNotFoundError, match="train/b3.png"):
        ImageSet(tmp_path / "set", "train", 16)
    bad = dict(table, images=[table["images"][0][:3] + ("0" * 64,) + table["images"][0][4:]])
    with pytest.raises(ValueError, match="'a0'.*differs"):
        fetch_image_set("toy", tmp_path / "set2", debs=debs, table=bad)
    assert not (tmp_path / "set2").exists()            # nothing written on failure
    with pytest.raises(FileNotFoundError, match="pkgb"):
        fetch_image_set("toy", tmp_path / "set3", debs=debs[:1], table=table)
    # a destination whose parent folders do not exist yet (the documented `--out data/debian-photos` on a
    # fresh checkout): the parents are made, and the set lands complete
    man4 = fetch_image_set("toy", tmp_path / "new" / "data" / "set", debs=debs, table=table)
    assert man4["train"] == man["train"]
    assert (tmp_path / "new" / "data" / "set" / "train" / "b3.png").read_bytes() == blobs[3]


def test_dense_evaluation_grid_equals_the_training_grid_and_is_chunked(tmp_path, monkeypatch):
    """``eval.grid`` evaluates on its own node grid, in chunks of ``eval.node_chunk`` nodes: the training
    grid in one chunk gives the default evaluation's numbers; one node a chunk plans each node's sampling
    alone, which moves the metrics by the sampling error only (here <= 0.05 dB at nyquist_safety 1). The
    progress file follows the grid's chunks (nodes done of the grid, after each chunk)."""
    import numpy as np

    from torch_bridge.design import node_positions_mm
    from torch_bridge.runs import ProgressFile
    seen = []
    update = ProgressFile.update

    def spy(self, **kw):
        if "eval_nodes_done" in kw:
            seen.append((kw["eval_nodes_done"], kw["eval_nodes"], self.rec.get("phase", kw.get("phase"))))
        update(self, **kw)
    monkeypatch.setattr(ProgressFile, "update", spy)
    from torch_bridge.design import CachedProvider
    released, release = [], CachedProvider.release

    def spy_release(self):
        released.append(len(self._cache))           # entries held when let go
        release(self)
    monkeypatch.setattr(CachedProvider, "release", spy_release)
    base = {"optics.nodes": {"layout": "grid", "grid": [2, 2], "region": "quadrant", "half_size_mm": 1.5},
            "train.joint_steps": 1, "train.finetune_steps": 1, "train.image_every": 0,
            "arms": [{"name": "fixed", "design": {"method": "fixed"}}], "data.eval_images": 2}
    ref = train(tiny(**base), out_dir=tmp_path / "ref")["fixed"]["eval"]["depths"][0]
    assert not released                             # no eval.grid: the training nodes' fields are what it evaluates
    for chunk, tol_db in ((4, 1e-9), (1, 0.05)):
        # the same trained arm evaluated on the eval grid: the reference's final checkpoint (its network
        # and optics bit for bit, as the resume tests show) resumes at its last step, so the run only
        # evaluates: the property is the evaluation's, training it again would give the same state
        (tmp_path / f"g{chunk}" / "fixed").mkdir(parents=True)
        shutil.copy(tmp_path / "ref" / "fixed" / "checkpoint.pt", tmp_path / f"g{chunk}" / "fixed" / "checkpoint.pt")
        res = train(tiny(**base, **{"eval.grid": [2, 2], "eval.node_chunk": chunk}), out_dir=tmp_path / f"g{chunk}")
        ev = res["fixed"]["eval"]["depths"][0]
        assert res["fixed"]["run"]["segments"][-1]["start_step"] == 2        # resumed finished: no training
        # the training nodes' fields are let go before the grid's chunks build theirs (not held beside them)
        assert released and released[0] > 0, released
        released.clear()
        timing = res["fixed"]["eval"]["timing_s"]     # the evaluation's parts, wall s
        assert set(timing) == {"psfs", "images", "rms", "training_nodes", "objective"}
        assert all(v >= 0 for v in timing.values()) and timing["psfs"] > 0
        assert len(ev["nodes"]) == 4
        for a, b in zip(ev["nodes"], ref["nodes"]):
            assert np.allclose(a["position_mm"], b["position_mm"], rtol=0, atol=1e-12)
            for part in ("raw", "rec"):
                assert abs(a[part]["psnr"] - b[part]["psnr"]) <= tol_db, (chunk, part, a[part], b[part])
        want = node_positions_mm("grid", 1.5, [2, 2], None, "quadrant")
        assert [tuple(n["position_mm"]) for n in ev["nodes"]] == [tuple(p) for p in want]
        assert [s[:2] for s in seen] == [(min(d + chunk, 4), 4) for d in range(0, 4, chunk)], seen
        assert all(s[2] == "eval" for s in seen)
        seen.clear()
    bad = tiny(**base, **{"eval.grid": [2, 2], "render.mode": "full"})
    from torch_bridge.train import ConfigError
    with pytest.raises(ConfigError, match="eval.grid"):
        train(bad, out_dir=tmp_path / "bad")


def test_rwwarp_design_status_reads_a_run_without_importing_torch(tmp_path):
    """``rwwarp design status`` from another process: alive while the recorded process runs (here: this
    test's process, same host), not alive for a finished run; torch is never imported for it."""
    import socket
    from torch_bridge.runs import write_json_atomic
    run = tmp_path / "run"
    run.mkdir()
    code = ("import sys, rwwarp.cli as c\n"
            "try:\n    c.main(['design', 'status', sys.argv[1]])\n"
            "except SystemExit as e:\n    print('torch' in sys.modules, e.code)\n")
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))

    def status_rc():
        r = subprocess.run([sys.executable, "-c", code, str(run)], capture_output=True, text=True, env=env,
                           timeout=60)
        return r.stdout.strip().splitlines()
    write_json_atomic(run / "progress.json", {"pid": os.getpid(), "host": socket.gethostname(), "state": "running",
                                              "arm": "e2e", "step": 3, "steps_total": 10})
    out = status_rc()
    assert "ALIVE" in out[0] and out[-1] == "False 0", out
    write_json_atomic(run / "progress.json", {"pid": os.getpid(), "host": socket.gethostname(), "state": "done"})
    out = status_rc()
    assert "not running" in out[0] and out[-1] == "False 1", out
    assert status(run)["state"] == "done"


def test_git_commit_of_a_copied_tree_comes_from_rwwarp_commit(monkeypatch, tmp_path):
    """A run on a machine that got a copy of the tree (no ``.git``) records ``$RWWARP_COMMIT``; without the
    variable, a folder outside any repository records None, and this checkout its HEAD as git prints it."""
    import subprocess
    from torch_bridge.runs import git_commit
    monkeypatch.setenv("RWWARP_COMMIT", "0123abc")
    assert git_commit(tmp_path) == {"commit": "0123abc", "dirty": None}
    monkeypatch.delenv("RWWARP_COMMIT")
    assert git_commit(tmp_path)["commit"] is None
    root = Path(__file__).resolve().parents[2]
    head = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True)
    if head.returncode == 0:
        assert git_commit(root)["commit"] == head.stdout.strip()


def test_memory_over_the_budget_is_warned_once_and_recorded(tmp_path):
    """The design loop compares the memory in use it measures after each step (here the process's peak RSS,
    hundreds of MB) with ``optics.memory_budget_gb``: under a 1 MB budget it warns once per arm, naming the budget,
    and ``progress.json`` keeps the message; under a budget above the measured memory, or none, nothing is said."""
    import warnings
    small = tiny(**{**OVER, "optics.memory_budget_gb": 0.001})
    with warnings.catch_warnings(record=True) as got:
        warnings.resetwarnings()                              # as outside pytest: Python's default filters
        warnings.simplefilter("ignore", ResourceWarning)      # hide this category (and deprecations)
        train(small, out_dir=tmp_path / "small", progress=False)
    over = [w for w in got if issubclass(w.category, RuntimeWarning) and "memory_budget_gb" in str(w.message)]
    assert len(over) == 1 and "over the memory budget of 0.001 GB" in str(over[0].message)
    rss_gb = float(str(over[0].message).split(": ")[1].split(" GB")[0])
    assert rss_gb > 0.001                                     # what was measured, not the budget
    assert "memory_budget_gb" in json.loads((tmp_path / "small" / "progress.json").read_text())["memory_over_budget"]
    from torch_bridge.budget import over_budget
    assert over_budget(rss_gb, 1000, "x") is None and over_budget(rss_gb, None, "x") is None   # under / no budget
    assert over_budget(rss_gb, 0.5 * rss_gb, "x") is not None
