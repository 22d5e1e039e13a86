"""Batched complex matrix products through an array module's BLAS (numpy, or CuPy: cuBLAS), with the argument
layout of the OpenCL C kernel ``cgemm_batched_kernel`` (``kernels/opencl/angular_spectrum.cl``), so that
:func:`rwwarp.wave.propagate_stages._gemm` can hand a product to the vendor BLAS where the backend has one
(``Backend.vendor_gemm``: CUDA) and to the kernel elsewhere."""
from __future__ import annotations

__all__ = ["strided_gemm"]


def strided_gemm(xp, a, b, c, m: int, n: int, k: int, *, batch: int, lda: int, ldb: int, ldc: int, sa: int, sb: int,
                 sc: int, ta: int = 0, ca: int = 0, tb: int = 0, cb: int = 0) -> None:
    """``c[i] = op(a[i]) @ op(b[i])`` for ``i < batch`` through the array module ``xp`` (numpy, or CuPy:
    cuBLAS's strided batched GEMM), with the arguments of the OpenCL kernel ``cgemm_batched_kernel``
    (``kernels/opencl/angular_spectrum.cl``): ``a``, ``b``, ``c`` contiguous complex arrays read as flat
    buffers of row-major matrices; ``op(a)`` is ``m x k`` (stored ``k x m`` when ``ta``; conjugated when
    ``ca``), ``op(b)`` is ``k x n`` (``tb``, ``cb`` likewise); ``lda``/``ldb``/``ldc`` the row strides and
    ``sa``/``sb``/``sc`` the batch strides, in elements (a batch stride of 0 shares one matrix over the batch).
    Written in place into ``c``; a view that would reach past a buffer is a ValueError (no out-of-bounds read)."""
    as_strided = xp.lib.stride_tricks.as_strided

    def view(x, rows, cols, ld, stride, name):
        flat = x.reshape(-1)
        last = (batch - 1) * stride + (rows - 1) * ld + cols
        if ld < cols or stride < 0 or last > flat.size:
            raise ValueError(f"strided_gemm: {name} ({rows} x {cols}, ld {ld}, batch stride {stride}, batch {batch}) "
                             f"does not fit its buffer of {flat.size} elements")
        isz = flat.itemsize
        return as_strided(flat, (batch, rows, cols), (stride * isz, ld * isz, isz))

    op_a = view(a, k, m, lda, sa, "a").swapaxes(1, 2) if ta else view(a, m, k, lda, sa, "a")
    op_b = view(b, n, k, ldb, sb, "b").swapaxes(1, 2) if tb else view(b, k, n, ldb, sb, "b")
    out = view(c, m, n, ldc, sc, "c")
    op_a, op_b = (op_a.conj() if ca else op_a), (op_b.conj() if cb else op_b)
    if ldc == n and (sc == m * n or batch == 1):
        xp.matmul(op_a, op_b, out=out)   # c's rows are contiguous: the product lands in place
    else:
        out[...] = xp.matmul(op_a, op_b)
