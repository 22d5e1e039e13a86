"""Several small host arrays uploaded to a Warp device in one copy (:func:`upload_packed`), with a small LRU of
recent packs (surface tables of a lens, a source's inputs, the pilot pupil); and to an array namespace's device
(CuPy) in one copy (:func:`upload_arrays`)."""
from __future__ import annotations

import threading
from collections import OrderedDict

import numpy as np
import warp as wp

__all__ = ["upload_packed", "recording_uploads", "upload_arrays"]


_UPLOADS: OrderedDict = OrderedDict()  # packed bytes -> views, for upload_packed(..., cache=True)
_UPLOADS_MAX = 64
_UPLOADS_MAX_BYTES = 1 << 16
_UPLOADS_LOCK = threading.RLock()   # re-entrant: a cache hit calls _recorded under it
_RECORDERS: list = []   # lists that collect every upload returned while they are registered (recording_uploads)


class recording_uploads:
    """``with recording_uploads(keep):`` appends every array :func:`upload_packed` returns inside the block (cached
    or new) to the list ``keep``: a CUDA graph recorded in the block reads them, so its owner holds them (an upload
    cache entry may be evicted and freed; :mod:`rwwarp.wave.graph_replay`)."""

    def __init__(self, keep: list):
        self.keep = keep

    def __enter__(self):
        with _UPLOADS_LOCK:
            _RECORDERS.append(self.keep)
        return self.keep

    def __exit__(self, *exc):
        with _UPLOADS_LOCK:
            _RECORDERS.remove(self.keep)
        return False


def _recorded(out):
    with _UPLOADS_LOCK:
        for keep in _RECORDERS:
            keep.extend(out)
    return out


def upload_packed(parts, device: str, cache: bool = False):
    """Several small host arrays to ``device`` in one copy.

    ``parts``: ``(array, numpy dtype, warp dtype)`` triples (vector warp dtypes take ``(n, k)`` arrays).
    The arrays are packed into one byte buffer (each part 16-byte aligned), uploaded once, and returned
    as typed Warp views into it, in order (each view keeps the buffer alive). Read-only inputs only.
    ``cache``: reuse the views of an earlier upload with the same bytes, types and device (a small LRU
    of packs up to 64 KiB: surface tables of a lens, a source's inputs, the pilot pupil)."""
    host = [np.ascontiguousarray(a, dtype=dt) for a, dt, _ in parts]
    offsets, total = [], 0
    for h in host:
        offsets.append(total)
        total += -(-max(h.nbytes, 1) // 16) * 16
    buf = np.zeros(total, dtype=np.uint8)
    for h, off in zip(host, offsets):
        buf[off:off + h.nbytes] = h.reshape(-1).view(np.uint8)
    key = None
    if cache and total <= _UPLOADS_MAX_BYTES:
        key = (str(device), buf.tobytes(), tuple((h.shape, wdt) for h, (_, _, wdt) in zip(host, parts)))
        with _UPLOADS_LOCK:
            hit = _UPLOADS.get(key)
            if hit is not None:
                _UPLOADS.move_to_end(key)
        if hit is not None:  # recorded outside the lock (it takes the lock itself)
            return _recorded(list(hit))
    base = wp.array(buf, dtype=wp.uint8, device=device)
    out = []
    for h, off, (_, _, wdt) in zip(host, offsets, parts):
        length = h.shape[0] if h.ndim else 1
        a = wp.array(ptr=base.ptr + off, dtype=wdt, shape=(length,), device=device)
        a._rw_base = base  # the views do not own the memory
        out.append(a)
    if key is not None:
        with _UPLOADS_LOCK:
            _UPLOADS[key] = tuple(out)
            while len(_UPLOADS) > _UPLOADS_MAX:
                _UPLOADS.popitem(last=False)
    return _recorded(out)


def upload_arrays(xp, arrays, pack: bool | None = None) -> list:
    """Host arrays ``arrays`` (numpy, any dtypes and shapes) as arrays of the namespace ``xp`` (numpy, CuPy), the
    same values, dtypes and shapes, in order. On a device (``xp`` not numpy) they go in one host-to-device copy:
    packed into one byte buffer (each part 16-byte aligned), uploaded once and returned as typed views into it
    (each view keeps the buffer alive: upload arrays that live and die together) instead of one copy, and one
    host wait, each. With numpy they are returned as they are (``np.asarray``) unless ``pack`` is True (the
    packed path on the host, for tests); ``pack`` False: one ``xp.asarray`` each."""
    host = [np.asarray(a, order="C") for a in arrays]
    if pack is None:
        pack = xp is not np
    if not pack:
        return [xp.asarray(h) for h in host]
    offsets, total = [], 0
    for h in host:
        offsets.append(total)
        total += -(-max(h.nbytes, 1) // 16) * 16
    buf = np.zeros(max(total, 16), dtype=np.uint8)
    for h, off in zip(host, offsets):
        buf[off:off + h.nbytes] = h.reshape(-1).view(np.uint8)
    dev = xp.asarray(buf)
    return [dev[off:off + h.nbytes].view(h.dtype).reshape(h.shape) for h, off in zip(host, offsets)]
