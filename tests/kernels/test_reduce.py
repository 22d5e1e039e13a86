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


@pytest.mark.parametrize("scalar", [wp.float64, wp.float32], ids=["float64", "float32"])
@pytest.mark.parametrize("n", [1, 200, 256, 257, 65536, 70001], ids=lambda n: f"n{n}")
def test_power_source_sums(device, rng, n, scalar):
    """A RayWave's per-source (launched, valid) power, ``power_source_sums`` (on the CPU one launch of
    power_tree_kernel: the terms and the 256-wide tree's one, two or three levels in one thread a source):
    against math.fsum of the weights (all, and the valid rays'), relative to the sum (weights >= 0; measured on
    the CPU worst 8.2e-16; tolerance 2e-15 as above), and bit for bit the sums of ``power_sums_kernel``'s terms
    through ``source_sums`` (the launches it replaces)."""
    from rwwarp.kernels.splat import make_splat_kernels
    from rwwarp.wave.reduce import power_source_sums
    nsrc = 3
    dt = np.float64 if scalar == wp.float64 else np.float32
    w = (rng.uniform(0.0, 1.0, nsrc * n) * 10.0 ** rng.uniform(-2, 2, nsrc * n)).astype(dt)
    ok = (rng.uniform(size=nsrc * n) > 0.3).astype(np.int32)
    valid = wp.array(ok, dtype=wp.int32, device=device)
    weight = wp.array(w, dtype=scalar, device=device)
    out = power_source_sums(valid, weight, nsrc, n, scalar, device).numpy().reshape(nsrc, 4)
    w64 = w.astype(np.float64)
    err = 0.0
    for s in range(nsrc):
        sl = slice(s * n, (s + 1) * n)
        for c, ref in enumerate((math.fsum(w64[sl]), math.fsum(w64[sl] * ok[sl]))):
            err = max(err, abs(out[s, c] - ref) / max(ref, 1e-300))
    print(f"power n {n}: worst {err:.2g}")
    assert err <= 2e-15, err
    assert not out[:, 2:].any()
    K = make_splat_kernels(scalar)
    terms = wp.empty(nsrc * n, dtype=K.vec4d, device=device)
    wp.launch(K.power_sums_kernel, dim=nsrc * n, inputs=[valid, weight], outputs=[terms], device=device)
    ref = source_sums(terms, nsrc, wp.float64, device).numpy().reshape(nsrc, 4)
    assert np.array_equal(out, ref)
