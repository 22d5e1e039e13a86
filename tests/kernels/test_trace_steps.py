"""The CPU's trace through several surfaces in one launch (``kernels/trace_steps.py``, issue 25).

* against numpy written from the equations (Snell's law, the reflection law, the aperture and the ideal
  thin lens's equal path; :mod:`test_trace_kernels`' references) for a chain of surfaces;
* the same bits as the per-surface launches it replaces (``intersect_kernel`` + ``surface_kernel`` a surface),
  rays lost on the way (aperture, total internal reflection) and invalid on entry included, in float64 and
  float32, and through :class:`rwwarp.trace.Tracer` on the shipped lenses (which on the CPU now traces so).
"""
import numpy as np
import pytest

wp = pytest.importorskip("warp")

from rwwarp.kernels import trace as kt  # noqa: E402
from rwwarp.kernels.trace_steps import make_trace_steps_kernel  # noqa: E402
from test_trace_kernels import SURFACES, _params, _rays, _refract_np  # noqa: E402

DEV = "cpu"


def _chain():
    """(rows, kinds, n_in, n_out) of a chain: sphere into glass, asphere out of it, an aperture plane (clips),
    an ideal thin lens (f = 60 mm), a concave mirror; indices at two wavelengths."""
    s1, s2 = SURFACES["sphere"], SURFACES["asphere"]
    rows = [_params(z=s1["z"], c=s1["c"]),
            _params(z=s1["z"] + 3.0, c=-s2["c"], k=s2["k"], asph=s2["asph"], a2=s2["a2"]),
            _params(z=8.0, sd=3.2),
            _params(z=9.0, power=1.0 / 60.0, v=60.0),
            _params(z=30.0, c=-1 / 40.0)]
    kinds = [kt.KIND_REFRACT, kt.KIND_REFRACT, kt.KIND_PLANE, kt.KIND_THIN, kt.KIND_REFLECT]
    glass = [1.5168, 1.5225]
    n_in = [[1.0, 1.0], glass, [1.0, 1.0], [1.0, 1.0], [1.0, 1.0]]
    n_out = [glass, [1.0, 1.0], [1.0, 1.0], [1.0, 1.0], [1.0, 1.0]]
    return np.array(rows), np.array(kinds, np.int32), np.array(n_in), np.array(n_out)


def _state(pos, d, opl, valid, wl, scalar):
    K = kt.make_trace_kernels(scalar)
    dt = np.float64 if scalar == wp.float64 else np.float32
    return (wp.array(pos.astype(dt), dtype=K.vec3, device=DEV), wp.array(d.astype(dt), dtype=K.vec3, device=DEV),
            wp.array(opl.astype(dt), dtype=scalar, device=DEV), wp.array(valid.astype(np.int32), device=DEV),
            wp.array(wl.astype(np.int32), device=DEV))


def _out(n, scalar):
    K = kt.make_trace_kernels(scalar)
    return [wp.zeros(n, dtype=K.vec3, device=DEV), wp.zeros(n, dtype=K.vec3, device=DEV),
            wp.zeros(n, dtype=scalar, device=DEV), wp.zeros(n, dtype=wp.int32, device=DEV)]


def _fused(state, tabs, scalar):
    rows, kinds, n_in, n_out = tabs
    dt = np.float64 if scalar == wp.float64 else np.float32
    n = state[0].shape[0]
    out = _out(n, scalar)
    wp.launch(make_trace_steps_kernel(scalar), dim=n,
              inputs=[*state, wp.array(rows.astype(dt), dtype=scalar, device=DEV), wp.array(kinds, device=DEV),
                      wp.array(n_in.astype(dt), dtype=scalar, device=DEV),
                      wp.array(n_out.astype(dt), dtype=scalar, device=DEV), len(kinds)], outputs=out, device=DEV)
    return [o.numpy() for o in out]


def _per_surface(state, tabs, scalar):
    """The launches Tracer._trace_range makes without the fused kernel: per surface, intersect_kernel on a
    curved one, then surface_kernel."""
    K = kt.make_trace_kernels(scalar)
    rows, kinds, n_in, n_out = tabs
    dt = np.float64 if scalar == wp.float64 else np.float32
    n = state[0].shape[0]
    cur, wl = state[:4], state[4]
    for s in range(len(kinds)):
        row = wp.array(rows[s:s + 1].astype(dt), dtype=scalar, device=DEV)
        t = wp.zeros(n, dtype=scalar, device=DEV)
        if kinds[s] in (kt.KIND_REFRACT, kt.KIND_REFLECT):
            wp.launch(K.intersect_kernel, dim=n, inputs=[cur[0], cur[1], cur[3], row, 0], outputs=[t], device=DEV)
        out = _out(n, scalar)
        wp.launch(K.surface_kernel, dim=n, inputs=[*cur, wl, row, 0, wp.array(n_in[s].astype(dt), dtype=scalar,
                                                                               device=DEV),
                                                   wp.array(n_out[s].astype(dt), dtype=scalar, device=DEV),
                                                   int(kinds[s]), t], outputs=out, device=DEV)
        cur = out
    return [o.numpy() for o in cur]


def test_chain_matches_snell(rng):
    """Sphere into glass and an asphere out of it: the fused kernel's rays against numpy's Snell chain
    (:func:`test_trace_kernels._refract_np` twice); tolerance 5e-14 mm as that file's single surface (measured
    here: 1.8e-15 mm hit, 5.6e-16 direction, 3.6e-15 mm OPL)."""
    rows, kinds, n_in, n_out = _chain()
    pos, d, opl = _rays(rng, 120, h=4.0, max_tan=0.1)
    n = len(pos)
    st = _state(pos, d, opl, np.ones(n), np.zeros(n), wp.float64)
    p_k, d_k, o_k, v_k = _fused(st, (rows[:2], kinds[:2], n_in[:2], n_out[:2]), wp.float64)
    s1, s2 = SURFACES["sphere"], SURFACES["asphere"]
    p_r, d_r, o_r = _refract_np(pos, d, opl, s1, 1.0, 1.5168)
    back = dict(z=s1["z"] + 3.0, c=-s2["c"], k=s2["k"], asph=s2["asph"], a2=s2["a2"], odd=())
    p_r, d_r, o_r = _refract_np(p_r, d_r, o_r, back, 1.5168, 1.0)
    assert v_k.all()
    np.testing.assert_allclose(p_k, p_r, rtol=0, atol=5e-14)
    np.testing.assert_allclose(d_k, d_r, rtol=0, atol=5e-14)
    np.testing.assert_allclose(o_k, o_r, rtol=0, atol=5e-14)


def test_thin_lens_and_mirror_in_the_chain(rng):
    """After the aperture (semi-diameter 3.2 mm at z = 8: rays beyond it lost, keeping the state they had before
    it, as a surface's launch leaves a lost ray) the
    ideal thin lens sends a collimated beam through its focus (z = 9 + 60 mm; measured miss 4.4e-16 mm,
    tolerance 1e-14) with equal optical paths there (Fermat; measured spread 2.8e-14 mm, tolerance 5e-13), and
    the mirror reverses the beam (d_z < 0)."""
    rows, kinds, n_in, n_out = _chain()
    n = 200
    xy = rng.uniform(-4.0, 4.0, (n, 2))
    pos = np.column_stack([xy, np.full(n, 7.0)])
    d = np.tile([0.0, 0.0, 1.0], (n, 1))
    st = _state(pos, d, np.zeros(n), np.ones(n), np.zeros(n), wp.float64)
    p_k, d_k, o_k, v_k = _fused(st, (rows[2:4], kinds[2:4], n_in[2:4], n_out[2:4]), wp.float64)
    inside = np.hypot(xy[:, 0], xy[:, 1]) <= 3.2
    assert 0 < inside.sum() < n
    np.testing.assert_array_equal(v_k.astype(bool), inside)
    np.testing.assert_array_equal(p_k[~inside], pos[~inside])
    np.testing.assert_array_equal(d_k[~inside], d[~inside])
    # the valid rays meet the focus: their line through the lens passes (0, 0, 69)
    t = (69.0 - p_k[inside, 2]) / d_k[inside, 2]
    at_focus = p_k[inside, :2] + t[:, None] * d_k[inside, :2]
    np.testing.assert_allclose(at_focus, 0.0, atol=1e-14)
    total = o_k[inside] + t * np.linalg.norm(d_k[inside], axis=1)
    assert np.ptp(total) < 5e-13
    p_m, d_m, o_m, v_m = _fused(st, (rows[2:], kinds[2:], n_in[2:], n_out[2:]), wp.float64)
    assert (d_m[v_m == 1, 2] < 0).all()


@pytest.mark.parametrize("scalar", [wp.float64, wp.float32], ids=["float64", "float32"])
def test_same_bits_as_per_surface_launches(rng, scalar):
    """The whole chain (refraction, an aperture that clips, a thin lens, a mirror) on rays of both wavelengths,
    some invalid on entry and some lost to total internal reflection inside the glass (steep rays): every
    output array equal, bit for bit, to the per-surface launches'."""
    rows, kinds, n_in, n_out = _chain()
    pos, d, opl = _rays(rng, 400, h=5.0, max_tan=1.2)
    n = len(pos)
    valid = (rng.uniform(size=n) > 0.1).astype(np.int32)
    wl = rng.integers(0, 2, n)
    st = _state(pos, d, opl, valid, wl, scalar)
    fused = _fused(st, (rows, kinds, n_in, n_out), scalar)
    ref = _per_surface(st, (rows, kinds, n_in, n_out), scalar)
    assert 0 < fused[3].sum() < valid.sum()   # some rays lost on the way, some through
    for a, b in zip(fused, ref):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("name", ["a489_doe", "cooke_triplet", "thin_lens_doe"])
def test_tracer_same_bits(monkeypatch, name):
    """Tracer._run on the CPU (fused) against the same call with the fused kernel switched off (per-surface
    launches): the traced rays at the sensor of three shipped lenses (off axis, 7 deg), equal bit for bit."""
    import rwwarp as rw
    from rwwarp.trace import Tracer
    lens = rw.load_lens(name)
    tr = Tracer(lens, [0.55], device=DEV)

    def trace():
        rays = tr.trace([(0.0, 7.0), (3.0, -2.0)], grid=24)
        return [np.array(a.numpy()) for a in (rays.pos, rays.dir, rays.opl, rays.valid)]
    calls = []
    orig = Tracer._fused_steps
    monkeypatch.setattr(Tracer, "_fused_steps", lambda self, steps: calls.append(1) or orig(self, steps))
    new = trace()
    assert calls
    monkeypatch.setattr(Tracer, "_fused_steps", lambda self, steps: None)
    old = trace()
    assert new[3].any()
    for a, b in zip(new, old):
        np.testing.assert_array_equal(a, b)
