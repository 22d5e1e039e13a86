"""Counters the launch-bound tests share (issue 25: on a GPU each aten operation and each Warp copy or memset is a
launch): :class:`OpCounter` counts the aten operations dispatched in a block (forward and backward, views included),
:func:`count_warp_copies` counts Warp's copies and memsets through pytest's ``monkeypatch``."""
import collections


class OpCounter:
    """Counts the aten operations dispatched inside the ``with`` block (``n``), through a TorchDispatchMode."""

    def __init__(self):
        from torch.utils._python_dispatch import TorchDispatchMode
        outer = self

        class Mode(TorchDispatchMode):
            def __torch_dispatch__(self, func, types, args=(), kwargs=None):
                outer.n += 1
                return func(*args, **(kwargs or {}))
        self.n, self._mode = 0, Mode()

    def __enter__(self):
        self._mode.__enter__()
        return self

    def __exit__(self, *exc):
        return self._mode.__exit__(*exc)


def count_warp_copies(monkeypatch) -> collections.Counter:
    """Patch ``wp.copy``, ``wp.array.zero_`` and ``wp.array.fill_`` to count their calls in the returned Counter (keys
    ``copy``, ``zero_``, ``fill_``) until ``monkeypatch.undo()``."""
    import warp as wp
    c = collections.Counter()
    for owner, name in ((wp, "copy"), (wp.array, "zero_"), (wp.array, "fill_")):
        def counted(*a, _orig=getattr(owner, name), _name=name, **k):
            c[_name] += 1
            return _orig(*a, **k)
        monkeypatch.setattr(owner, name, counted)
    return c
