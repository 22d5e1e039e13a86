"""A kept batch's device work recorded once as a CUDA graph and replayed (issue 25, "no Python on the hot path").

A :class:`~rwwarp.wave.plan_cache.PlanCache` keeps the batches of a call
(:class:`~rwwarp.wave.packed.PackedRayWave`: its tracer's arrays, the members' focal operators, DOE factors and
uploads). A repeat of the call runs the same launches on the same arrays: the trace and splat (Warp), the wave step,
DOE factor and propagation of every member (CuPy, cuBLAS, cuFFT / VkFFT, NVRTC kernels). On a GPU the Python that
issues them, not the device, bounds such a call (~20 Warp and ~10 CuPy launches a source, 2.7-4.2 ms a 64 px PSF
on an H100). This module records the trace and splat (every Warp launch of the call, with their uploads and
power sums) once as a CUDA graph on Warp's stream and replays it with one launch; the propagations follow eagerly
on the same stream (:class:`ReplayedBatch` says why), and the host normalises as :meth:`PackedRayWave.result`
does. The replayed kernels are the recorded ones with the same arguments, so a replay gives the same bits as the
eager run it replaces (tested on CUDA: ``tests/rwwarp/test_graph_replay.py``).

What may be recorded: a batch on a CUDA device whose run needs no host decision: the energy amplitude convention
(the paper's rescale reads the traced power on the host) and every chief ray valid (a vignetted chief ray picks
its replacement on the host). Anything else, and any failure while recording, runs eagerly; :func:`run_kept`
says which in its second return value.

Memory: the graph reads and writes only arrays that outlive it: the kept batch's tracer tables and work arrays
(``Tracer.pool``), and the small uploads of its per-source constants, which the :class:`ReplayedBatch` holds
(:class:`rwwarp.device_upload.recording_uploads`: the upload cache may drop its entries). CuPy arrays made during
the recording come from a memory pool private to the graph, kept with it and used by nothing else.
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
    """The trace and splat of one kept :class:`~rwwarp.wave.packed.PackedRayWave` (``focal_precision`` "single" or
    "double" for its propagations), recorded as a CUDA graph by :meth:`record` and replayed by :meth:`run`; the
    members' propagations then run eagerly on the same stream. Build it through :func:`run_kept`.

    Why not the propagations too (measured on an H100, CuPy 13): CuPy refuses to call cuBLAS inside a stream
    capture (the focal method's products are cuBLAS calls), and the ASM's set-up uploads its per-call parameters
    from pageable host memory, which a capture does not permit."""

    def __init__(self, packed, focal_precision: str):
        import cupy
        import warp as wp
        self.packed, self.focal_precision = packed, focal_precision
        self.device = wp.get_device(packed.tracer.device)
        self.stream = wp.get_stream(self.device)
        self.pool = cupy.cuda.MemoryPool()      # the graph's own temporaries: nothing else allocates from it
        self.graph = self.field = None
        self.inputs = []        # the uploads the graph reads (held here: the upload cache may drop them)

    def _context(self, private_pool: bool = False):
        import contextlib

        import cupy
        stack = contextlib.ExitStack()
        stack.enter_context(cupy.cuda.Device(self.device.ordinal))
        stack.enter_context(cupy.cuda.ExternalStream(self.stream.cuda_stream, self.device.ordinal))
        if private_pool:
            stack.enter_context(cupy.cuda.using_allocator(self.pool.malloc))
        return stack

    def record(self):
        """Run the batch once eagerly on Warp's stream (kernels compiled, FFT plans and uploads made, every lazy
        set-up done), then record its trace and splat as a CUDA graph. Raises what the recording raised (the
        capture is ended and dropped first)."""
        import warp as wp

        from ..device_upload import recording_uploads
        with self._context():
            self.packed.device_psfs(self.focal_precision, keep_operators=True, to_host=False)   # warm-up
        with self._context(private_pool=True), recording_uploads(self.inputs):
            wp.capture_begin(self.device, stream=self.stream)
            try:
                field = self.packed.field_array()
            except BaseException:
                try:
                    wp.capture_end(self.device, stream=self.stream)
                except Exception:         # the capture was already invalidated; nothing to keep
                    pass
                raise
            self.graph, self.field = wp.capture_end(self.device, stream=self.stream), field

    def run(self) -> dict:
        """Replay the recorded trace and splat, propagate every member eagerly on the same stream, and return
        :meth:`PackedRayWave.run`'s result dict."""
        import warp as wp
        if self.graph is None:
            self.record()
        wp.capture_launch(self.graph, stream=self.stream)
        with self._context():
            data = self.packed.device_psfs(self.focal_precision, keep_operators=True, u_all=self.field)
        self.packed._sums = None          # the power sums the replay wrote: read again
        return self.packed.result(data)


def run_kept(packed, focal_precision: str, graphs: bool = True):
    """Run a kept batch again: by its recorded CUDA graph where it can be recorded (recorded on the first call),
    else eagerly (:meth:`PackedRayWave.run`). Returns ``(result, how)``: the result dict and "graph: trace and splat" or the reason
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
                import traceback
                packed._replay_error = traceback.format_exc()
                packed._replay_failed = why = f"eager: recording failed ({type(exc).__name__}: {exc})"[:300]
                rep = None
            packed._replay = rep
    if why is not None:
        return packed.run(focal_precision, keep_operators=True), why
    return packed._replay.run(), "graph: trace and splat"
