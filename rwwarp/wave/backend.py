"""Compute backends of the wave stage: OpenCL (pyopencl + pyvkfft) and CUDA (CuPy + NVRTC).

One kernel source, two builds. The propagation kernels are OpenCL C files in
``kernels/opencl/`` (installed as ``rwwarp.kernels``). :class:`OpenCLBackend` builds them with
pyopencl for any OpenCL device (PoCL on the CPU for tests and laptops, AMD/Intel GPUs) and does
FFTs with pyvkfft's OpenCL backend. :class:`CudaBackend` prepends ``cuda_compat.h`` to the same
source and compiles it with NVRTC through ``cupy.RawModule``; FFTs go through pyvkfft's CUDA backend
when it is installed, else through ``cupy.fft`` (cuFFT). Both builds take the precision from
``-D REAL=double|float`` (complex128 / complex64) and form phases in double whenever the device has
it (``-D RW_HAVE_FP64=1``).

Every backend offers the same small interface, used by :mod:`rwwarp.wave.propagate`:
``to_device``, ``to_host``, ``empty``, ``zeros``, ``fft2`` / ``fft1`` (in place, batched over the
other axes),
``launch`` (a named kernel of a named source, built once per (context, dtype)), ``workspace``
(reused scratch arrays, one per tag), ``cache`` (a byte-bounded LRU cache of device arrays),
``synchronize`` and ``allocated_bytes`` / ``memory_report`` (what is held between calls). FFT plans
are an LRU bounded by count and bytes.
Work is queued asynchronously on one in-order queue (OpenCL) or on CuPy's current stream (CUDA);
nothing comes back to the host until ``to_host``.

FFT convention (numpy's): the forward transform is unnormalised, ``exp(-2 pi i k n / N)``; the
inverse has ``exp(+2 pi i k n / N)`` and divides by ``N`` per transformed axis.
"""

from __future__ import annotations

import atexit
import functools
import gc
import sys
import re
import threading
from collections import OrderedDict

import numpy as np

from .kernel_source import _kernel_signatures, kernel_source

__all__ = [
    "Backend",
    "CudaBackend",
    "OpenCLBackend",
    "complex_dtype",
    "get_backend",
    "kernel_source",
    "real_dtype",
    "release_warp_pool",
]

_COMPLEX_TO_REAL = {
    np.dtype(np.complex128): np.dtype(np.float64),
    np.dtype(np.complex64): np.dtype(np.float32),
}


def complex_dtype(dtype) -> np.dtype:
    """The complex dtype named by ``dtype`` (complex64 or complex128); a real dtype maps to its
    complex counterpart (float32 -> complex64, float64 -> complex128)."""
    dt = np.dtype(dtype)
    if dt in _COMPLEX_TO_REAL:
        return dt
    if dt == np.float32:
        return np.dtype(np.complex64)
    if dt == np.float64:
        return np.dtype(np.complex128)
    raise TypeError(f"unsupported dtype {dt}: use complex64 or complex128")


def real_dtype(dtype) -> np.dtype:
    """The real dtype of the same precision as the complex ``dtype``."""
    return _COMPLEX_TO_REAL[complex_dtype(dtype)]


def _round_up(n: int, m: int) -> int:
    return -(-int(n) // int(m)) * int(m)


class DeviceCache:
    """Least-recently-used cache of device arrays bounded by their total size in bytes."""

    def __init__(self, max_bytes: int = 512 * 2**20):
        self.max_bytes = int(max_bytes)
        self._items: OrderedDict = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()

    def get(self, key, factory):
        """The cached value for ``key``, else ``factory()`` (an array with ``nbytes``) stored."""
        with self._lock:
            if key in self._items:
                self._items.move_to_end(key)
                return self._items[key]
        value = factory()
        nbytes = int(getattr(value, "nbytes", 0))
        with self._lock:
            if nbytes <= self.max_bytes:
                self._items[key] = value
                self._bytes += nbytes
                while self._bytes > self.max_bytes and self._items:
                    _, old = self._items.popitem(last=False)
                    self._bytes -= int(getattr(old, "nbytes", 0))
        return value

    def clear(self):
        """Drop every entry."""
        with self._lock:
            self._items.clear()
            self._bytes = 0

    @property
    def nbytes(self) -> int:
        """Bytes held by the cached arrays."""
        return self._bytes

    def __len__(self):
        return len(self._items)


class Backend:
    """Common interface of the compute backends (see the module docstring).

    Attributes: ``device`` (the string it was made from), ``kind`` ('opencl' or 'cuda'),
    ``has_fp64`` (double precision available), ``phase_dtype`` (float64 if ``has_fp64`` else
    float32: dtype of phases, frequencies and coordinates handed to kernels), ``cache``
    (:class:`DeviceCache` for transfer functions and the like).
    """

    kind = "abstract"

    #: FFT plans kept (least recently used dropped first), and the byte budget of their temporary buffers.
    #: Plans without a temporary buffer hold next to no device memory but cost a kernel build (NVRTC on
    #: CUDA) to remake, so the count bound is generous: a map's batches and a design step's wavelength-depth
    #: entries can all keep theirs (session 24, H200: the a489_edof gpu step, 27 entries drawn a few a step, had built
    #: 76 plans after 12 steps, 12 of them dropped by a bound of 64, and was still building 1-13 a step at ~0.2-0.7
    #: s each). A plan the bound dropped and built again is counted (:attr:`fft_plans_rebuilt`) and warned about once.
    max_fft_plans = 512
    max_fft_plan_bytes = 512 * 2**20

    #: True where :meth:`gemm` runs the batched complex matrix products of the matrix DFTs through the vendor's
    #: BLAS (CUDA: cuBLAS, whose FP64 GEMMs use the tensor cores); False: the OpenCL C kernels of
    #: ``angular_spectrum.cl`` (``cgemm_batched_kernel``, ``cgemm_cpu_kernel``). An instance may set it False
    #: to run the kernels instead; the CUDA GEMM test checks both against numpy.
    vendor_gemm = False

    def gemm(self, a, b, c, m, n, k, **kw) -> None:  # pragma: no cover - overridden where vendor_gemm
        """Batched ``c = op(a) op(b)`` through the vendor BLAS (arguments of :func:`strided_gemm`)."""
        raise NotImplementedError(f"{type(self).__name__} has no vendor GEMM (vendor_gemm is False)")

    def __init__(self, device: str):
        self.device = device
        self.cache = DeviceCache()
        self._workspace: dict = {}  # (tag, dtype) -> (flat device array, {shape: view}), grown on demand
        self._plans: OrderedDict = OrderedDict()  # key -> (plan, estimated bytes), LRU order
        self._plan_bytes = 0
        #: FFT plans built since the backend was made (each a VkFFT kernel build: NVRTC on CUDA), and those of them
        #: dropped by the count or byte bound (:attr:`max_fft_plans`, :attr:`max_fft_plan_bytes`): a plan dropped and
        #: needed again is built again, so a growing count over kept plans shows plans cycling
        self.fft_plans_built = 0
        self.fft_plans_dropped = 0
        #: plans built again after the bound dropped them (the working set exceeds the bound: warned once)
        self.fft_plans_rebuilt = 0
        self._dropped_keys: OrderedDict = OrderedDict()  # keys the bound dropped (the last 4096), for the count above
        self._cycling_warned = False  # the cycling warning is given once (again after clear_caches)
        self._programs: dict = {}
        self._lock = threading.Lock()
        self._release_hooks: list = []  # callables that free device memory held by other allocators

    # -- arrays ---------------------------------------------------------------------------
    def is_device_array(self, arr) -> bool:  # pragma: no cover - overridden
        raise NotImplementedError

    def to_device(self, arr, dtype=None):  # pragma: no cover - overridden
        raise NotImplementedError

    def to_host(self, arr) -> np.ndarray:  # pragma: no cover - overridden
        raise NotImplementedError

    def empty(self, shape, dtype):  # pragma: no cover - overridden
        raise NotImplementedError

    def zeros(self, shape, dtype):  # pragma: no cover - overridden
        raise NotImplementedError

    def synchronize(self):  # pragma: no cover - overridden
        raise NotImplementedError

    def workspace(self, tag: str, shape, dtype):
        """A scratch device array of ``shape`` and ``dtype`` for ``tag``, reused across calls.

        One buffer per (tag, dtype): a request no larger than the tag's buffer gets a C-contiguous view of its
        start (zero offset), a larger one replaces it (the old one is released, so a PSF map whose
        batches have many shapes holds one buffer per tag, as big as the largest request, never one
        per shape). Valid until the next request for the same tag, whatever its shape; never
        returned to users. Work on one queue / stream at a time when using it."""
        shape = tuple(int(s) for s in shape)
        dt = np.dtype(dtype)
        count = int(np.prod(shape, dtype=np.int64))
        key = (tag, dt.str)
        with self._lock:
            entry = self._workspace.get(key)
            if entry is None or entry[0].size < count:
                if entry is not None:
                    del self._workspace[key]  # released when the last queued use ends
                entry = (self._empty_unpooled(max(count, 1), dt), {})
                self._workspace[key] = entry
            buf, views = entry
            view = views.get(shape)
            if view is None:
                if len(views) >= 16:  # views are cheap to remake; keep the dict small
                    views.clear()
                view = views[shape] = buf[:count].reshape(shape)
        return view

    def _empty_unpooled(self, count: int, dtype):
        """A 1-D device array allocated outside the memory pool (freed to the device when dropped)."""
        return self.empty((count,), dtype)

    def add_release_hook(self, fn):
        """Register ``fn()``, called when a device allocation fails, before one retry: it should give
        back memory that another allocator on the same device caches (torch_bridge registers
        ``torch.cuda.empty_cache``). Registering the same callable twice has no effect."""
        with self._lock:
            if fn not in self._release_hooks:
                self._release_hooks.append(fn)

    def _is_out_of_memory(self, exc: BaseException) -> bool:
        """Whether ``exc`` is this device's out-of-memory error."""
        return isinstance(exc, MemoryError)

    def _allocate(self, alloc):
        """``alloc()``; on out-of-memory, free what can be freed (the transfer-function cache, the scratch
        workspaces -- a buffer still viewed by a running call stays alive through its views --, the pool's
        unused blocks, the release hooks' allocators) and try once more."""
        try:
            return alloc()
        except Exception as exc:
            if not self._is_out_of_memory(exc):
                raise
            self.cache.clear()
            with self._lock:
                self._workspace.clear()
            self._release_pool()
            for fn in list(self._release_hooks):
                fn()
            return alloc()

    def _release_pool(self):
        """Give the allocator's unused blocks back to the device (no-op by default)."""

    def _plan(self, key, nbytes, factory):
        """The cached FFT plan for ``key``, else ``factory()`` stored; least recently used plans beyond
        :attr:`max_fft_plans` or :attr:`max_fft_plan_bytes` are dropped. A plan's bytes are VkFFT's
        temporary buffer (``tmp_buffer_nbytes``) where pyvkfft reports it, else ``nbytes`` (an upper bound)."""
        with self._lock:
            entry = self._plans.get(key)
            if entry is not None:
                self._plans.move_to_end(key)
                return entry[0]
        plan = factory()
        nbytes = int(getattr(plan, "tmp_buffer_nbytes", nbytes))
        with self._lock:
            self._plans[key] = (plan, int(nbytes))
            self._plan_bytes += int(nbytes)
            self.fft_plans_built += 1
            cycling = self._dropped_keys.pop(key, None) is not None
            if cycling:
                self.fft_plans_rebuilt += 1
            while len(self._plans) > 1 and (len(self._plans) > self.max_fft_plans
                                            or self._plan_bytes > self.max_fft_plan_bytes):
                old_key, (_, old) = self._plans.popitem(last=False)
                self._plan_bytes -= old
                self.fft_plans_dropped += 1
                self._dropped_keys[old_key] = True
                while len(self._dropped_keys) > 4096:
                    self._dropped_keys.popitem(last=False)
        if cycling and not self._cycling_warned:
            self._cycling_warned = True
            import warnings
            from rwwarp.errors import PerformanceWarning
            warnings.warn(f"FFT plans are cycling on {self.device}: a plan the cache dropped (bounds: "
                          f"max_fft_plans={self.max_fft_plans}, max_fft_plan_bytes={self.max_fft_plan_bytes}) is "
                          "built again; each build compiles a VkFFT kernel (~0.7 s on CUDA). The work's plans do "
                          "not fit the bounds: raise them on the backend (rwwarp.wave.backend.get_backend(...))",
                          PerformanceWarning, stacklevel=3)
        return plan

    def allocated_bytes(self) -> int:
        """Bytes the backend keeps between calls: workspaces + cached transfer functions + FFT plans'
        temporary buffers. Excludes compiled programs and memory a pool holds for reuse. See
        :meth:`memory_report` for the parts."""
        r = self.memory_report()
        return r["workspace_bytes"] + r["cache_bytes"] + r["fft_plan_bytes"]

    def memory_report(self) -> dict:
        """Bookkeeping of held device memory, bytes: ``workspace_bytes`` (per tag in
        ``workspaces``), ``cache_bytes`` (transfer functions and the like, ``cache_entries``),
        ``fft_plan_bytes`` (VkFFT temporary buffers) and ``fft_plans`` (count); ``fft_plans_built`` and
        ``fft_plans_dropped``, ``fft_plans_rebuilt`` (dropped, then needed again): counts since the backend was made."""
        with self._lock:
            ws = {f"{tag}:{dt}": int(e[0].nbytes) for (tag, dt), e in self._workspace.items()}
            return {"workspace_bytes": sum(ws.values()), "workspaces": ws, "cache_bytes": self.cache.nbytes,
                    "cache_entries": len(self.cache), "fft_plan_bytes": self._plan_bytes,
                    "fft_plans": len(self._plans), "fft_plans_built": self.fft_plans_built,
                    "fft_plans_dropped": self.fft_plans_dropped, "fft_plans_rebuilt": self.fft_plans_rebuilt}

    def clear_caches(self):
        """Release cached workspaces, FFT plans and transfer functions (compiled programs stay), and
        the memory pool's unused blocks."""
        with self._lock:
            self._workspace.clear()
            self._plans.clear()
            self._dropped_keys.clear()
            self._cycling_warned = False
            self._plan_bytes = 0
        self.cache.clear()
        self._release_pool()

    # -- kernels --------------------------------------------------------------------------
    def _build_options(self, dtype, defines=()) -> list[str]:
        dt = complex_dtype(dtype)
        opts = (
            ["-DREAL=double", "-DREAL_IS_DOUBLE=1"]
            if dt == np.complex128
            else ["-DREAL=float", "-DREAL_IS_DOUBLE=0"]
        )
        if self.has_fp64:
            opts.append("-DRW_HAVE_FP64=1")
        opts += [f"-D{d}" for d in defines]
        return opts

    def _scalar(self, kind: str, value, dtype):
        if kind == "int":
            return np.int32(value)
        if kind == "idx_t":
            return np.int64(value)
        if kind == "real_t":
            return real_dtype(dtype).type(value)
        if kind == "phase_t":
            return self.phase_dtype.type(value)
        raise TypeError(f"unsupported kernel scalar type {kind!r}")

    def launch(self, source: str, name: str, dtype, global_size, local_size, *args, defines=()):
        """Queue kernel ``name`` of ``kernels/opencl/<source>`` built for ``dtype`` (complex64 or
        complex128). ``global_size``/``local_size``: up to 3 ints, axis 0 fastest; the global size
        is rounded up to whole work-groups (kernels check their bounds). ``args``: device arrays
        for pointer parameters, Python numbers for scalars (converted to the declared type).
        ``defines``: extra ``NAME=VALUE`` macros (e.g. tile sizes); each distinct set is one more
        build of the source, cached like the others."""
        raise NotImplementedError  # pragma: no cover

    def _signature(self, source: str, name: str):
        sigs = _kernel_signatures(source)
        if name not in sigs:
            raise KeyError(f"no __kernel {name!r} in {source}")
        return sigs[name]

    # -- FFT ------------------------------------------------------------------------------
    def fft2(self, arr, inverse: bool = False):
        """In-place 2-D FFT over the last two axes of a C-contiguous complex device array,
        batched over the leading axes; returns ``arr``. Forward unnormalised, inverse divided by
        ``ny * nx`` (numpy convention). Plans are built once per (shape, dtype, axes) and cached."""
        if arr.ndim < 2:
            raise ValueError("fft2 needs at least 2 dimensions")
        return self._fft(arr, (-2, -1), inverse)

    def fft1(self, arr, axis: int = -1, inverse: bool = False):
        """In-place 1-D FFT along ``axis`` (-1 or -2) of a C-contiguous complex device array,
        batched over all other axes; returns ``arr``. Same conventions and plan cache as
        :meth:`fft2` (the inverse divides by the transform length)."""
        if axis not in (-1, -2):
            raise ValueError("fft1 transforms axis -1 or -2")
        return self._fft(arr, (int(axis),), inverse)

    def _fft(self, arr, axes, inverse):  # pragma: no cover - overridden
        raise NotImplementedError

    def __repr__(self):
        return f"<{type(self).__name__} {self.device!r}: {self.name}>"


class OpenCLBackend(Backend):
    """pyopencl context + in-order queue on one OpenCL device, pyvkfft OpenCL FFTs.

    Device arrays are ``pyopencl.array.Array`` (C-contiguous, zero offset) allocated from a
    memory pool. Programs are built once per (context, dtype) with ``-D REAL=...``.
    """

    kind = "opencl"

    def __init__(self, cl_device, device: str):
        import pyopencl as cl
        import pyopencl.tools

        super().__init__(device)
        self._cl = cl
        self.cl_device = cl_device
        self.name = f"{cl_device.platform.name.strip()} / {cl_device.name.strip()}"
        self.context = cl.Context([cl_device])
        self.queue = cl.CommandQueue(self.context)
        self._immediate = cl.tools.ImmediateAllocator(self.queue)
        self.allocator = cl.tools.MemoryPool(self._immediate)
        self.has_fp64 = "cl_khr_fp64" in cl_device.extensions or cl_device.double_fp_config != 0
        self.phase_dtype = np.dtype(np.float64 if self.has_fp64 else np.float32)
        self.is_cpu = bool(cl_device.type & cl.device_type.CPU)
        self.max_work_group_size = int(cl_device.max_work_group_size)
        self.compute_units = int(cl_device.max_compute_units)

    # arrays
    def is_device_array(self, arr) -> bool:
        import pyopencl.array as cla

        return isinstance(arr, cla.Array)

    def to_device(self, arr, dtype=None):
        """A device copy of a numpy array (or the device array itself, cast to ``dtype`` if
        needed, made C-contiguous with zero offset)."""
        import pyopencl.array as cla

        if isinstance(arr, cla.Array):
            if not arr.flags.c_contiguous:
                raise ValueError("device arrays handed to rwwarp must be C-contiguous")
            if dtype is not None and arr.dtype != np.dtype(dtype):
                arr = arr.astype(dtype)
            if arr.offset != 0:
                arr = arr.copy()
            return arr
        host = np.ascontiguousarray(np.asarray(arr, dtype=dtype))
        return cla.to_device(self.queue, host, allocator=self.allocator)

    def wrap_host(self, arr: np.ndarray):
        """A device array that uses the memory of a C-contiguous numpy array (no copy) when the
        device is a CPU (zero-copy host pointer); a plain copy on other devices. The numpy array
        must outlive the device array and not be touched while kernels use it."""
        import pyopencl.array as cla

        cl = self._cl
        arr = np.ascontiguousarray(arr)
        if not self.is_cpu:
            return self.to_device(arr)
        buf = cl.Buffer(self.context, cl.mem_flags.READ_WRITE | cl.mem_flags.USE_HOST_PTR, hostbuf=arr)
        return cla.Array(self.queue, arr.shape, arr.dtype, data=buf)

    def to_host(self, arr) -> np.ndarray:
        """Copy a device array to a new numpy array (waits for the queued work)."""
        if isinstance(arr, np.ndarray):
            return arr
        return arr.get(queue=self.queue)

    def empty(self, shape, dtype):
        """Uninitialised device array."""
        import pyopencl.array as cla

        return cla.empty(self.queue, tuple(int(s) for s in shape), np.dtype(dtype), allocator=self.allocator)

    def _empty_unpooled(self, count, dtype):
        import pyopencl.array as cla

        return cla.empty(self.queue, (int(count),), np.dtype(dtype), allocator=self._immediate)

    def zeros(self, shape, dtype):
        """Zero-filled device array."""
        arr = self.empty(shape, dtype)
        if arr.nbytes:
            self._cl.enqueue_fill_buffer(self.queue, arr.data, np.uint8(0), 0, arr.nbytes)
        return arr

    def synchronize(self):
        """Wait for all queued work."""
        self.queue.finish()

    def _release_pool(self):
        """Free the memory pool's held (unused) blocks; buffers still queued stay alive (OpenCL
        reference counting)."""
        self.allocator.free_held()

    # kernels
    def _program(self, source: str, dtype, defines=()):
        key = (source, complex_dtype(dtype).str, tuple(defines))
        with self._lock:
            entry = self._programs.get(key)
            if entry is None:
                prg = self._cl.Program(self.context, kernel_source(source)).build(
                    options=self._build_options(dtype, defines)
                )
                entry = (prg, {})
                self._programs[key] = entry
        return entry

    def launch(self, source, name, dtype, global_size, local_size, *args, defines=()):
        prg, kernels = self._program(source, dtype, defines)
        sig = self._signature(source, name)
        if len(sig) != len(args):
            raise TypeError(f"{name}: expected {len(sig)} arguments, got {len(args)}")
        knl = kernels.get(name)
        if knl is None:
            knl = getattr(prg, name)
            kernels[name] = knl
        import pyopencl.array as cla

        cargs = []
        for kind, a in zip(sig, args):
            if kind == "buf":
                cargs.append(a.data if isinstance(a, cla.Array) else a)
            else:
                cargs.append(self._scalar(kind, a, dtype))
        lsize = tuple(int(v) for v in local_size)
        gsize = tuple(_round_up(max(int(g), 1), l) for g, l in zip(global_size, lsize))
        knl(self.queue, gsize, lsize, *cargs)

    # FFT
    def _fft(self, arr, axes, inverse):
        from pyvkfft.opencl import VkFFTApp

        key = (tuple(arr.shape), arr.dtype.str, axes)
        app = self._plan(key, arr.nbytes,
                         lambda: VkFFTApp(arr.shape, arr.dtype, self.queue, axes=axes, inplace=True, norm=1))
        if inverse:
            app.ifft(arr, queue=self.queue)
        else:
            app.fft(arr, queue=self.queue)
        return arr


#: cuFFT plans CuPy keeps per GPU for the focal propagation's FFTs, and the bytes of their work areas
CUFFT_PLAN_CACHE = 128
CUFFT_PLAN_CACHE_BYTES = 1 << 30


def ensure_cufft_plan_cache():
    """Raise CuPy's cuFFT plan cache on the current device to :data:`CUFFT_PLAN_CACHE` plans (at most
    :data:`CUFFT_PLAN_CACHE_BYTES` of work areas) where it is smaller. A design step plans each focal
    source on its own grid (dozens of FFT shapes), which CuPy's default cache of 16 plans cycles through
    without a hit (0.23 s of host time a step of the Cooke hybrid on an H100). CuPy keeps one cache per thread
    and device, and torch runs a backward pass on a device thread of its own: call it in the thread that runs
    the FFTs (:class:`rwwarp.wave.focal.FocalPropagator` does, before each; it costs a few microseconds)."""
    import cupy
    cache = cupy.fft.config.get_plan_cache()
    if cache.get_size() < CUFFT_PLAN_CACHE:
        cache.set_size(CUFFT_PLAN_CACHE)
        cache.set_memsize(CUFFT_PLAN_CACHE_BYTES)


class CudaBackend(Backend):
    """CuPy arrays on one NVIDIA GPU; the OpenCL C kernels compiled by NVRTC after
    ``cuda_compat.h``; FFTs by pyvkfft's CUDA backend (if importable) or ``cupy.fft``.

    Work is queued on CuPy's current stream (use ``cupy.cuda.ExternalStream`` around calls to
    share torch's stream). Device arrays are ``cupy.ndarray``; ``to_device`` wraps objects that
    expose ``__cuda_array_interface__`` (torch, Warp) without copying.
    """

    kind = "cuda"
    # cuBLAS for the matrix DFTs: on an H200 the a489_aberration e2e_doe step (48 ASM sources, complex128)
    # spent 2.86 of its 3.47 s of device time in the OpenCL C kernel cgemm_batched_kernel (NVRTC),
    # ~5 ms a product (perf/results/session20_h200x4/)
    vendor_gemm = True

    def gemm(self, a, b, c, m, n, k, **kw) -> None:
        """Batched ``c = op(a) op(b)`` by cuBLAS on the current stream (:func:`strided_gemm` with CuPy)."""
        from .blas import strided_gemm
        with self.cuda_device:
            strided_gemm(self.cp, a, b, c, m, n, k, **kw)

    def __init__(self, index: int, device: str):
        try:
            import cupy
        except ImportError as exc:  # pragma: no cover - depends on the machine
            raise RuntimeError(
                f"device {device!r} needs CuPy: install rwwarp[cuda] (cupy-cuda12x) on a machine with an "
                "NVIDIA GPU, or use device='cpu' / 'opencl:P:D'"
            ) from exc
        super().__init__(device)
        self.cp = cupy
        self.index = int(index)
        self.cuda_device = cupy.cuda.Device(self.index)
        props = cupy.cuda.runtime.getDeviceProperties(self.index)
        name = props.get("name", b"cuda")
        self.name = name.decode() if isinstance(name, bytes) else str(name)
        self.has_fp64 = True
        self.phase_dtype = np.dtype(np.float64)
        self.compute_units = int(props.get("multiProcessorCount", 1))
        self.is_cpu = False
        with self.cuda_device:
            ensure_cufft_plan_cache()
        try:
            from pyvkfft.cuda import VkFFTApp  # noqa: F401

            self._vkfft = True
        except (ImportError, OSError, RuntimeError):  # no CuPy/PyCUDA or no _vkfft_cuda library
            self._vkfft = False

    def is_device_array(self, arr) -> bool:
        return isinstance(arr, self.cp.ndarray)

    def to_device(self, arr, dtype=None):
        """A CuPy array for ``arr`` on this GPU: numpy arrays are copied, CUDA arrays (CuPy,
        torch, Warp: ``__cuda_array_interface__``) are used in place unless a cast or a
        contiguous copy is needed."""
        with self.cuda_device:
            out = self.cp.asarray(arr, dtype=dtype)
            return self.cp.ascontiguousarray(out)

    def to_host(self, arr) -> np.ndarray:
        """Copy to a new numpy array (synchronises the current stream)."""
        if isinstance(arr, np.ndarray):
            return arr
        with self.cuda_device:
            return self.cp.asnumpy(arr)

    def empty(self, shape, dtype):
        with self.cuda_device:
            return self._allocate(lambda: self.cp.empty(tuple(int(s) for s in shape), dtype=np.dtype(dtype)))

    def zeros(self, shape, dtype):
        with self.cuda_device:
            return self._allocate(lambda: self.cp.zeros(tuple(int(s) for s in shape), dtype=np.dtype(dtype)))

    def _is_out_of_memory(self, exc):
        cp = self.cp
        if isinstance(exc, (MemoryError, cp.cuda.memory.OutOfMemoryError)):
            return True
        if isinstance(exc, cp.cuda.runtime.CUDARuntimeError):
            return "out of memory" in str(exc).lower()
        return isinstance(exc, RuntimeError) and str(exc).startswith("Failed to allocate")  # Warp

    def _empty_unpooled(self, count, dtype):
        cp = self.cp
        dt = np.dtype(dtype)
        with self.cuda_device:
            mem = self._allocate(lambda: cp.cuda.Memory(max(int(count) * dt.itemsize, 1)))
            return cp.ndarray((int(count),), dtype=dt, memptr=cp.cuda.MemoryPointer(mem, 0))

    def synchronize(self):
        with self.cuda_device:
            self.cp.cuda.get_current_stream().synchronize()

    def _release_pool(self):
        """Free CuPy's unused pool blocks (``cudaFree`` waits for the device) and the unused blocks of
        Warp's memory pool on the same device (the ray buffers of the trace stage)."""
        with self.cuda_device:
            self.cp.get_default_memory_pool().free_all_blocks()
        release_warp_pool(f"cuda:{self.index}")

    def _module(self, source: str, dtype, defines=()):
        key = (source, complex_dtype(dtype).str, tuple(defines))
        with self._lock:
            entry = self._programs.get(key)
            if entry is None:
                code = kernel_source("cuda_compat.h") + "\n" + kernel_source(source)
                opts = tuple(["-DRW_CUDA=1", "--std=c++17"] + self._build_options(dtype, defines))
                with self.cuda_device:
                    mod = self.cp.RawModule(code=code, options=opts)
                entry = (mod, {})
                self._programs[key] = entry
        return entry

    def launch(self, source, name, dtype, global_size, local_size, *args, defines=()):
        mod, kernels = self._module(source, dtype, defines)
        sig = self._signature(source, name)
        if len(sig) != len(args):
            raise TypeError(f"{name}: expected {len(sig)} arguments, got {len(args)}")
        with self.cuda_device:
            knl = kernels.get(name)
            if knl is None:
                knl = mod.get_function(name)
                kernels[name] = knl
            cargs = tuple(a if kind == "buf" else self._scalar(kind, a, dtype) for kind, a in zip(sig, args))
            lsize = tuple(int(v) for v in local_size) + (1,) * (3 - len(local_size))
            gsize = tuple(int(v) for v in global_size) + (1,) * (3 - len(global_size))
            grid = tuple(max(1, -(-g // l)) for g, l in zip(gsize, lsize))
            knl(grid, lsize, cargs)

    def _fft(self, arr, axes, inverse):
        with self.cuda_device:
            if self._vkfft:
                from pyvkfft.cuda import VkFFTApp

                stream = self.cp.cuda.get_current_stream()
                key = (tuple(arr.shape), arr.dtype.str, axes, int(stream.ptr))
                app = self._plan(key, arr.nbytes,
                                 lambda: VkFFTApp(arr.shape, arr.dtype, axes=axes, inplace=True, stream=stream,
                                                  norm=1))
                if inverse:
                    app.ifft(arr)
                else:
                    app.fft(arr)
                return arr
            fn = self.cp.fft.ifftn if inverse else self.cp.fft.fftn
            arr[...] = fn(arr, axes=axes)
            return arr


_DEVICE_RE = re.compile(r"^(cpu|opencl(?::(\d+):(\d+))?|cuda(?::(\d+))?)$")


def _find_cpu_device():
    import pyopencl as cl

    try:
        platforms = cl.get_platforms()
    except cl.Error as e:  # no ICD / no platform: say what to install (README, Install)
        raise RuntimeError(f"no OpenCL platform found ({e}): rwwarp's wave propagation runs on OpenCL; install "
                           "PoCL for the CPU (Debian/Ubuntu: apt-get install pocl-opencl-icd; conda: conda install "
                           "-c conda-forge pocl) or a GPU vendor's OpenCL driver") from e
    for platform in platforms:
        try:
            devices = platform.get_devices(device_type=cl.device_type.CPU)
        except cl.Error:
            continue
        if devices:
            return devices[0]
    raise RuntimeError("no OpenCL CPU device found (install PoCL: pip install pocl-binary-distribution)")


_MADE: list = []   # every backend made, in order (release_all)


def release_all() -> None:
    """Wait for every backend made, release its caches and collect garbage while CuPy, torch and Warp are alive. Run
    at exit (left to the teardown they ended a GPU design command with SIGSEGV). Safe at any time (caches refill)."""
    for b in list(_MADE):
        try:
            b.synchronize()
            b.clear_caches()
        except Exception as exc:   # an exit after a device error: say so, release the rest
            print(f"rwwarp: releasing {b!r} at exit failed: {exc}", file=sys.stderr)
    gc.collect()


atexit.register(release_all)


@functools.cache
def _make_backend(device: str) -> Backend:
    _MADE.append(_new_backend(device))
    return _MADE[-1]


def _new_backend(device: str) -> Backend:
    m = _DEVICE_RE.match(device)
    if m is None:
        raise ValueError(f"unknown device {device!r}: use 'cpu', 'opencl:P:D', 'cuda' or 'cuda:N'")
    if device == "cpu":
        return OpenCLBackend(_find_cpu_device(), device)
    if device.startswith("opencl"):
        import pyopencl as cl

        p = int(m.group(2) or 0)
        d = int(m.group(3) or 0)
        platforms = cl.get_platforms()
        if p >= len(platforms):
            raise RuntimeError(f"device {device!r}: only {len(platforms)} OpenCL platform(s)")
        devs = platforms[p].get_devices()
        if d >= len(devs):
            raise RuntimeError(f"device {device!r}: platform {p} has only {len(devs)} device(s)")
        return OpenCLBackend(devs[d], device)
    return CudaBackend(int(m.group(4) or 0), device)


def release_warp_pool(device) -> None:
    """Hand the unused blocks of Warp's CUDA memory pool on ``device`` back to the driver (so torch,
    CuPy and the next Warp allocations can use them): the pool's release threshold is set to 0 for
    one device synchronisation, then restored. No-op on the CPU or without a memory pool."""
    import warp as wp  # the trace stage's library; only its pool is touched here

    dev = wp.get_device(str(device))
    if not dev.is_cuda:
        return
    if not getattr(dev, "is_mempool_enabled", False):
        wp.synchronize_device(dev)
        return
    keep = wp.get_mempool_release_threshold(dev)
    try:
        wp.set_mempool_release_threshold(dev, 0)
        wp.synchronize_device(dev)
    finally:
        wp.set_mempool_release_threshold(dev, keep)


def get_backend(device: str = "cpu") -> Backend:
    """The (memoised) backend for ``device``: ``"cpu"`` = the first OpenCL CPU device (PoCL),
    ``"opencl"`` / ``"opencl:P:D"`` = OpenCL platform P, device D, ``"cuda"`` / ``"cuda:N"`` =
    NVIDIA GPU N through CuPy (RuntimeError if CuPy is missing). The same string always gives the
    same object (same context/queue, compiled programs, FFT plans and caches)."""
    if isinstance(device, Backend):
        return device
    dev = str(device).strip().lower()
    if dev == "opencl":
        dev = "opencl:0:0"
    if dev == "cuda":
        dev = "cuda:0"
    return _make_backend(dev)
