"""Zeroed gradient buffers for many Warp arrays from one allocation.

A tracer that records its trace on a ``wp.Tape`` (:class:`rwwarp.trace.Tracer` with ``requires_grad``) makes, for
every surface, a ray state (positions, directions, path lengths) and the parameter-row copies the rays read, each
with a gradient buffer that must start at zero. Made one by one, each buffer is zeroed on its own: on a GPU one
memset each, in a design step bound by its launches (issue 25). :class:`GradBlock` hands out the buffers as views
of one array zeroed once: the same zeros, one memset for the whole trace.
"""
from __future__ import annotations

import warp as wp

__all__ = ["GradBlock"]


class GradBlock:
    """``count`` scalars of Warp type ``scalar`` (``wp.float32`` / ``wp.float64``) on ``device``, zeroed once by
    ``alloc(count)`` (default ``wp.zeros``; a caller's wrapper may retry after freeing memory), handed out in order
    as gradient buffers by :meth:`attach`. Every view keeps the block alive."""

    def __init__(self, device, scalar, count: int, alloc=None):
        count = max(int(count), 1)
        self.block = alloc(count) if alloc is not None else wp.zeros(count, dtype=scalar, device=device)
        self.scalar = scalar
        self.used = 0

    def attach(self, arr):
        """Give ``arr`` (a contiguous Warp array of ``scalar`` or a vector of it, made without a gradient) a zeroed
        gradient buffer, the block's next ``arr.size x length`` scalars, and return ``arr`` (now
        ``requires_grad``). ValueError when the block has no room left or the types differ."""
        if getattr(arr.dtype, "_wp_scalar_type_", arr.dtype) != self.scalar:
            raise ValueError(f"GradBlock of {self.scalar.__name__}: cannot hold a gradient of {arr.dtype}")
        if not arr.is_contiguous:
            raise ValueError("GradBlock: the array must be contiguous")
        size = self.block.strides[0]                               # bytes a scalar
        need = int(arr.size) * arr.strides[-1] // size             # scalars the (contiguous) array's elements take
        if self.used + need > self.block.shape[0]:
            raise ValueError(f"GradBlock: {need} scalars asked, {self.block.shape[0] - self.used} left")
        view = wp.array(ptr=self.block.ptr + self.used * size, dtype=arr.dtype, shape=arr.shape,
                        device=self.block.device)
        view._ref = self.block            # the block lives as long as a view does
        self.used += need
        arr.grad = view
        return arr
