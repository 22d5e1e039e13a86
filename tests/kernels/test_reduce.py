"""The deterministic per-source sums (kernels/reduce.py, rwwarp.wave.reduce.source_sums) against numpy's
math.fsum (exactly rounded), their run-to-run bits, and their gradient under wp.Tape (the adjoint of a sum
hands every term the sum's gradient)."""
import math

import numpy as np
import pytest

wp = pytest.importorskip("warp")

from rwwarp.wave.reduce import source_sums

V4 = wp.types.vector(4, wp.float64)


@pytest.mark.parametrize("grad", [False, True], ids=["wide", "tree16"])
@pytest.mark.parametrize("n", [1, 16, 17, 257, 4099, 65537], ids=lambda n: f"n{n}")
def test_sums_match_exactly_rounded_sums(device, rng, n, grad):
    """Sources of n terms (one pass, partial runs, several levels): every component of every source's sum
    against math.fsum, relative to the sum of magnitudes. Terms of mixed sign and magnitude (1e-3 .. 1e3).
    Both paths: the 16-wide tree (with gradients) and the 256-wide passes (without). Measured on the CPU:
    worst 2.3e-16 (wide, n = 257) and 2e-16 (tree, n = 16), the others 8e-18 .. 1.3e-16; tolerance 2e-15
    (sqrt(256) x the float64 epsilon, the typical error growth of 256 sequential additions)."""
    nsrc = 3
    vals = rng.normal(0, 1, (nsrc * n, 4)) * 10.0 ** rng.uniform(-3, 3, (nsrc * n, 4))
    out = source_sums(wp.array(vals, dtype=V4, device=device), nsrc, wp.float64, device,
                      requires_grad=grad).numpy().reshape(nsrc, 4)
    err = 0.0
    for s in range(nsrc):
        for c in range(4):
            ref = math.fsum(vals[s * n:(s + 1) * n, c])
            scale = math.fsum(np.abs(vals[s * n:(s + 1) * n, c]))
            err = max(err, abs(out[s, c] - ref) / scale)
    print(f"n {n} grad {grad}: worst {err:.2g}")
    assert err <= 2e-15


def test_same_bits_every_run(device, rng):
    """A fixed summation tree: the same inputs give the same bits (the atomics it replaces add in arrival
    order on a GPU)."""
    vals = wp.array(rng.normal(0, 1, (5 * 100_003, 4)), dtype=V4, device=device)
    first = source_sums(vals, 5, wp.float64, device).numpy()
    for _ in range(3):
        assert np.array_equal(source_sums(vals, 5, wp.float64, device).numpy(), first)


def test_gradient_under_tape(device, rng):
    """d(sum_c w_c S_c[s]) / d(term) = w_c for every term of source s: exact (no rounding in the adjoint)."""
    nsrc, n = 2, 300
    vals = wp.array(rng.normal(0, 1, (nsrc * n, 4)), dtype=V4, device=device, requires_grad=True)
    tape = wp.Tape()
    with tape:
        out = source_sums(vals, nsrc, wp.float64, device, requires_grad=True)
    w = np.array([[1.0, -2.0, 0.5, 3.0], [0.25, 4.0, -1.0, 2.0]])
    tape.backward(grads={out: wp.array(w.reshape(nsrc, 1, 4), dtype=V4, device=device).reshape((nsrc, 1))})
    g = vals.grad.numpy().reshape(nsrc, n, 4)
    assert np.array_equal(g, np.broadcast_to(w[:, None, :], g.shape))


def test_bad_split_is_refused(device):
    with pytest.raises(ValueError, match="do not split"):
        source_sums(wp.zeros(10, dtype=V4, device=device), 3, wp.float64, device)
