"""The host side of building a stacked focal operator (rwwarp.wave.focal_packed.PackedFocalPropagator): the members'
tapers and FFT frequencies formed at once equal each member's own (rwwarp.wave.focal.sensor_taper, numpy.fft.fftfreq)
bit for bit; the small host arrays go to the device in one copy (rwwarp.device_upload.upload_arrays: the same values,
dtypes and shapes), so a build makes 2 host-to-device copies and another distance 1 (counted with a numpy-backed
namespace), and a build through the packed copies equals the numpy build bit for bit."""
import numpy as np
import pytest

import rwwarp as rw
import rwwarp.device_upload as DU
from rwwarp.device_upload import upload_arrays
from rwwarp.wave.focal import sensor_taper
from rwwarp.wave.focal_packed import PackedFocalPropagator, _fft_freqs
from rwwarp.wave.packed import source_plans


class _Counting:
    """numpy, counting the host arrays given to ``asarray`` (the host-to-device copies on a device namespace)."""

    def __init__(self):
        self.copies = 0

    def asarray(self, a, *args, **kw):
        if isinstance(a, np.ndarray):
            self.copies += 1
        return np.asarray(a, *args, **kw)

    def __getattr__(self, name):
        return getattr(np, name)


def test_upload_arrays_keeps_values_dtypes_and_shapes_in_one_copy():
    rng = np.random.default_rng(0)
    arrays = [np.arange(7, dtype=np.int64), rng.random((7, 33)) < 0.5, rng.random((7, 5, 2)),
              (rng.random((3, 9)) + 1j * rng.random((3, 9))).astype(np.complex64),
              rng.random((2, 3)) + 1j * rng.random((2, 3)), np.zeros((0, 4)), np.float64(2.5),
              rng.random((4, 6))[:, ::2]]          # not contiguous
    before = [a.copy() for a in arrays]
    c = _Counting()
    out = upload_arrays(c, arrays)
    assert c.copies == 1
    for a, b in zip(arrays, out):
        assert b.dtype == np.asarray(a).dtype and b.shape == np.shape(a) and np.array_equal(a, b)
    for a, b in zip(arrays, before):
        assert np.array_equal(a, b)          # inputs not changed
    same = upload_arrays(np, arrays)
    assert all(np.array_equal(a, b) for a, b in zip(arrays, same))


def test_member_tapers_and_fft_frequencies_equal_each_members_own():
    """7 members of sensor-side grids of 150-400 points (their own last point ends each taper), FFT lengths 170-500:
    the batched forms equal the per-member numpy calls bit for bit; 1 (taper) and 0 (frequency) past a member's
    own points."""
    rng = np.random.default_rng(1)
    S, NS = 7, 400
    n_own = rng.integers(150, NS + 1, S)
    pitch = rng.uniform(2e-3, 4e-3, S)
    p = rng.uniform(-1, 1, (S, 1)) + np.arange(NS)[None, :] * pitch[:, None]
    lo = p[:, 0] + 0.3 * n_own * pitch
    hi = p[:, 0] + 0.7 * n_own * pitch
    got = sensor_taper(p, lo, hi, n_own=n_own)
    for k in range(S):
        m = int(n_own[k])
        own = sensor_taper(p[k:k + 1, :m], lo[k:k + 1], hi[k:k + 1])[0]
        assert np.array_equal(got[k, :m], own) and np.all(got[k, m:] == 1.0)
        assert own.min() < 1e-3 and own.max() == 1.0      # the taper falls to ~0 at both ends
        # the window written out from its definition: 1 - e(t) / (e(t) + e(1 - t)), e(t) = exp(-1 / t), t from
        # lo / hi (0) to the member's own first / last point (1)
        x = p[k, :m]
        t = np.clip(np.where(x < lo[k], (lo[k] - x) / (lo[k] - x[0]), np.where(x > hi[k], (x - hi[k]) / (x[-1] - hi[k]),
                                                                             0.0)), 0.0, 1.0)
        with np.errstate(divide="ignore"):
            e = lambda v: np.where(v > 0, np.exp(-1.0 / v), 0.0)
            want = 1.0 - e(t) / (e(t) + e(1.0 - t))
        assert np.max(np.abs(got[k, :m] - want)) < 1e-15   # measured 0 (the same operations)
    n_fft = n_own + rng.integers(20, 100, S)
    nu = _fft_freqs(n_fft, pitch, int(n_fft.max()))
    for k in range(S):
        n = int(n_fft[k])
        assert np.array_equal(nu[k, :n], np.fft.fftfreq(n, d=float(pitch[k]))) and np.all(nu[k, n:] == 0.0)


@pytest.fixture(scope="module")
def members():
    lens = rw.load_lens("a489_doe")
    ms = source_plans(lens, [(0.0, 0.0), (3.0, 7.0), (0.0, 10.0)], [0.45, 0.55, 0.65], 16, lens.sensor.pixel_pitch,
                      method="focal")
    return ms, float(ms[0].z_sensor - ms[0].z_plane)


def _factors(op):
    return [*op._E, op._W, op._HR, op._c, op._rem, op._Fx, op._Fy, *op._band.values(), *op._geo.values()]


def test_a_build_makes_two_copies_and_another_distance_one(members):
    ms, z = members
    c = _Counting()
    op = PackedFocalPropagator.from_members(ms, z, xp=c)
    assert c.copies == 2
    op.at_distance(1.01 * z)
    assert c.copies == 3


@pytest.mark.parametrize("precision", ["double", "single"])
def test_a_build_through_packed_copies_equals_the_numpy_build(members, monkeypatch, precision):
    ms, z = members
    ref = PackedFocalPropagator.from_members(ms, z, precision)
    ref2 = ref.at_distance(1.01 * z)
    orig = DU.upload_arrays
    monkeypatch.setattr(DU, "upload_arrays", lambda xp, arrays, pack=None: orig(xp, arrays, pack=True))
    op = PackedFocalPropagator.from_members(ms, z, precision)
    op2 = op.at_distance(1.01 * z)
    for a, b in zip(_factors(ref) + _factors(ref2), _factors(op) + _factors(op2)):
        assert a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b)
    assert not np.array_equal(ref2._HR, ref._HR)      # the distance changes the factors compared
