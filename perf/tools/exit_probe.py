"""Where a design command crashes at exit (a GPU diagnostic): runs ``torch_bridge.train``'s command line in this
process, then reports the live threads, re-installs the fault handler (a library may have replaced its SIGSEGV
handler) and prints markers at each stage of the interpreter's exit, so a crash after the work is placed: in the
atexit handlers, in the modules' teardown (the fault handler prints the Python stack there), or after Python
(no marker missing, no stack: a native library's static destructors).

    python perf/tools/exit_probe.py [--cleanup] -- <rwwarp design arguments>

``--cleanup``: before exiting, wait for the device and release rwwarp's backend caches and torch's cached blocks
(what an orderly shutdown would do), to see whether that avoids the crash.
"""
import atexit
import faulthandler
import gc
import os
import sys
import threading


def _say(msg):
    os.write(2, f"PROBE: {msg}\n".encode())


def main():
    argv = sys.argv[1:]
    cleanup = "--cleanup" in argv[:argv.index("--")] if "--" in argv else False
    args = argv[argv.index("--") + 1:] if "--" in argv else argv
    atexit.register(_say, "the last atexit handler ran: interpreter teardown next")   # first registered, last run
    from torch_bridge.train import main as train_main
    rc = train_main(args)
    _say(f"main returned {rc}")
    _say("threads: " + ", ".join(f"{t.name}{' (daemon)' if t.daemon else ''}" for t in threading.enumerate()))
    faulthandler.enable(all_threads=True)
    if cleanup:
        import torch

        from rwwarp.wave import backend as be
        for dev in ("cuda:0",):
            b = be.get_backend(dev)
            b.synchronize()
            b.clear_caches()
        gc.collect()
        torch.cuda.synchronize()
        torch.cuda.empty_cache()
        _say("cleanup done")
    atexit.register(_say, "the first atexit handler ran")
    sys.exit(rc)


if __name__ == "__main__":
    main()
