"""Truths of scenes even in x and in y, evaluated on one quadrant of pixels and mirrored.

A scene that is even in x and in y (an on-axis plane wave; a square or round aperture and a DOE even in x and y,
all centred on the axis) has a PSF even in x and y about the axis. On a patch whose pixel centres are symmetric
about the axis (checked here), every pixel's truth equals that of its mirror image in the quadrant x, y >= 0:
a quarter of the cost of the direct sums, the same numbers (measured against the sums on every pixel: the
thin-lens truths of tests/rwwarp/test_focal.py, test_psf.py, test_analytic.py and test_convergence.py to 2e-14
relative, ``rs_lens_psf`` of the Cooke triplet on axis to 4e-13, the rounding of its traced rays).
"""
import numpy as np


def mirrored_truth(truth_on, x, y):
    """``truth_on(qx, qy) -> (len(qy), len(qx))`` evaluated on the pixel centres ``x, y >= 0`` (mm) only and
    mirrored to the whole patch (len(y), len(x)). Raises AssertionError when ``x`` or ``y`` is not symmetric
    about 0 (the mirror would not be exact)."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    for name, c in (("x", x), ("y", y)):
        assert np.allclose(np.sort(-c), np.sort(c), rtol=0, atol=1e-12), f"pixel centres {name} not symmetric: {c}"
    qx, qy = x[x > -1e-12], y[y > -1e-12]
    q = np.asarray(truth_on(qx, qy))
    ix = np.abs(np.abs(x)[:, None] - qx[None, :]).argmin(1)
    iy = np.abs(np.abs(y)[:, None] - qy[None, :]).argmin(1)
    return q[np.ix_(iy, ix)]


def mirrored_patch_truth(truth_patch, center_mm, size, pixel_mm):
    """As :func:`mirrored_truth` for truths computed on a square patch, ``truth_patch(center_mm, size) -> (size,
    size)`` (rows +y, columns +x, pixel centres ``center + (k - size // 2) pixel``, as
    :func:`rwwarp.ground_truth.rs_lens_psf`): evaluated on the quadrant patch of ``size / 2`` pixels and mirrored
    to the ``size`` x ``size`` patch about ``center_mm`` (``size`` a multiple of 4)."""
    assert size % 4 == 0, size
    off = (np.arange(size) - size // 2) * pixel_mm
    x, y = center_mm[0] + off, center_mm[1] + off

    def on(qx, qy):
        n = len(qx)
        assert len(qy) == n == size // 2
        return truth_patch((qx[n // 2], qy[n // 2]), n)
    return mirrored_truth(on, x, y)
