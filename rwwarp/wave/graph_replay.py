"""A kept batch's device work recorded once as a CUDA graph and replayed (issue 25, "no Python on the hot path").

A :class:`~rwwarp.wave.plan_cache.PlanCache` keeps the batches of a call
(:class:`~rwwarp.wave.packed.PackedRayWave`: its tracer's arrays, the members' focal operators, DOE factors and
uploads). A repeat of the call runs the same launches on the same arrays: the trace and splat (Warp), the wave step,
DOE factor and propagation of every member (CuPy, cuBLAS, cuFFT / VkFFT, NVRTC kernels). On a GPU the Python that
issues them, not the device, bounds such a call (~20 Warp and ~10 CuPy launches a source, 2.7-4.2 ms a 64 px PSF
on an H100). This module records that sequence once as a CUDA graph on Warp's stream and replays it with one launch;
the host then copies the pixel powers and the per-source power sums back and normalises as
:meth:`PackedRayWave.result` does. The replayed kernels are the recorded ones with the same arguments, so a replay
gives the same bits as the eager run it replaces (tested on CUDA: ``tests/rwwarp/test_graph_replay.py``).

What may be recorded: a batch on a CUDA device whose run needs no host decision: the energy amplitude convention
(the paper's rescale reads the traced power on the host) and every chief ray valid (a vignetted chief ray picks
its replacement on the host). Anything else, and any failure while recording, runs eagerly; :func:`run_kept`
says which in its second return value. CuPy does not let cuBLAS run inside a capture, so a batch whose propagation
calls it (the focal method's matrix products) records its trace and splat only and propagates eagerly.

Memory: the recorded temporaries (CuPy arrays made during the recording) come from a memory pool private to the
graph, kept with it and used by nothing else, so no other work reuses the addresses the graph writes.
"""
from __future__ import annotations

import numpy as np


def replay_blocker(packed) -> str | None:
    """Why ``packed`` (a kept :class:`~rwwarp.wave.packed.PackedRayWave`) cannot be recorded, or None when it can."""
    dev = str(packed.tracer.device)
    if not dev.startswith("cuda"):
        return f"eager: device {dev} (CUDA graphs only on CUDA devices)"
    if packed.amplitude != "energy":
        return "eager: amplitude 'paper' (its rescale reads the traced power on the host)"
    if not np.all(packed.chief_ok):
        return "eager: a vignetted chief ray (its replacement is chosen on the host)"
    return None


class ReplayedBatch:
    """The device work of one kept :class:`~rwwarp.wave.packed.PackedRayWave` run (``focal_precision`` "single" or
    "double"), recorded as a CUDA graph by :meth:`record` and replayed by :meth:`run`. Build it through
    :func:`run_kept`.

    :attr:`scope` is what the graph holds: ``"whole"`` (trace, splat and every member's propagation), or
    ``"field"`` (trace and splat; the propagations then run eagerly on the same stream) where the propagation
    cannot be recorded: CuPy refuses to call cuBLAS inside a stream capture, and the focal method's products
    are cuBLAS calls. The ASM's FFTs and kernels record."""

    def __init__(self, packed, focal_precision: str):
        import cupy
        import warp as wp
        self.packed, self.focal_precision = packed, focal_precision
        self.device = wp.get_device(packed.tracer.device)
        self.stream = wp.get_stream(self.device)
        self.pool = cupy.cuda.MemoryPool()      # the graph's own temporaries: nothing else allocates from it
        self.graph = self.out = self.scope = None

    def _context(self):
        import contextlib

        import cupy
        stack = contextlib.ExitStack()
        stack.enter_context(cupy.cuda.Device(self.device.ordinal))
        stack.enter_context(cupy.cuda.ExternalStream(self.stream.cuda_stream, self.device.ordinal))
        stack.enter_context(cupy.cuda.using_allocator(self.pool.malloc))
        return stack

    def _queue(self, scope: str):
        import cupy
        if scope == "field":
            return self.packed.field_array()
        data = self.packed.device_psfs(self.focal_precision, keep_operators=True, to_host=False)
        return cupy.concatenate([cupy.asarray(d).reshape(1, *d.shape[-2:]) for d in data])

    def _capture(self, scope: str):
        import warp as wp
        wp.capture_begin(self.device, stream=self.stream)
        try:
            out = self._queue(scope)
        except BaseException:
            try:
                wp.capture_end(self.device, stream=self.stream)
            except Exception:         # the capture was already invalidated; nothing to keep
                pass
            raise
        return wp.capture_end(self.device, stream=self.stream), out

    def record(self):
        """Run the batch once eagerly on Warp's stream (kernels compiled, FFT plans and uploads made, every lazy
        set-up done), then record it as a CUDA graph: the whole run, or where the propagation cannot be recorded
        the trace and splat. Raises what the recording of the trace and splat raised."""
        with self._context():
            self._queue("whole")          # warm-up on the recording stream: every lazy set-up happens here
            try:
                self.graph, self.out = self._capture("whole")
                self.scope = "whole"
            except NotImplementedError:   # cuBLAS inside a capture (CuPy): the trace and splat alone
                self.graph, self.out = self._capture("field")
                self.scope = "field"

    @property
    def how(self) -> str:
        """``"graph"`` (the whole run replayed) or ``"graph: trace and splat"`` (its propagations eager)."""
        return "graph" if self.scope == "whole" else "graph: trace and splat"

    def run(self) -> dict:
        """Replay the recorded graph and return :meth:`PackedRayWave.run`'s result dict."""
        import cupy
        import warp as wp
        if self.graph is None:
            self.record()
        wp.capture_launch(self.graph, stream=self.stream)
        with self._context():
            if self.scope == "whole":
                data = list(cupy.asnumpy(self.out, stream=cupy.cuda.get_current_stream()))
            else:
                data = self.packed.device_psfs(self.focal_precision, keep_operators=True, u_all=self.out)
        self.packed._sums = None          # the power sums the replay wrote: read again
        return self.packed.result(data)


def run_kept(packed, focal_precision: str, graphs: bool = True):
    """Run a kept batch again: by its recorded CUDA graph where it can be recorded (recorded on the first call),
    else eagerly (:meth:`PackedRayWave.run`). Returns ``(result, how)``: the result dict and "graph" or the reason
    it ran eagerly. ``focal_precision``: "single" or "double" (resolved)."""
    why = "eager: graphs off" if not graphs else replay_blocker(packed)
    rep = getattr(packed, "_replay", None)
    if why is None and (rep is None or rep.focal_precision != focal_precision):
        if getattr(packed, "_replay_failed", None) is not None:
            why = packed._replay_failed
        else:
            rep = ReplayedBatch(packed, focal_precision)
            try:
                rep.record()
            except Exception as exc:      # not recordable on this machine: eager from now on, and say why
                packed._replay_failed = why = f"eager: recording failed ({type(exc).__name__}: {exc})"[:300]
                rep = None
            packed._replay = rep
    if why is not None:
        return packed.run(focal_precision, keep_operators=True), why
    return packed._replay.run(), packed._replay.how
