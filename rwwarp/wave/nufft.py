"""The type-1 non-uniform FFT of the pixel method (:mod:`rwwarp.wave.pixel_scale`, :mod:`rwwarp.wave.pixel_kirchhoff`):
weights at scattered frequencies summed onto a uniform grid by Gaussian gridding, an oversampled FFT and a
deconvolution, and its operation count. Angles in rad a sample, grids in samples."""
from __future__ import annotations

import math

import numpy as np

#: oversampling and half-width (grid cells) of the Gaussian gridding of :func:`nufft_type1` (~1e-6 relative)
NUFFT_OVERSAMPLE = 2
NUFFT_SPREAD = 6


def nufft_type1(theta_x, theta_y, c, n: int, xp=np, oversample: int | None = None, spread: int | None = None):
    """``U[my, mx] = sum_j c_j exp(i (mx theta_x,j + my theta_y,j))`` for ``mx, my = -n/2 .. n/2 - 1`` (array
    index ``m + n/2``), the points' phases ``theta`` (rad) in ``[-pi, pi)`` (1-D arrays, ``c`` complex).

    Gaussian gridding (the Greengard-Lee form of the type-1 non-uniform DFT): each point is spread with
    ``g(t) = exp(-t^2 / (4 tau))`` onto the ``M = oversample n`` periodic grid ``t_l = 2 pi l / M`` over
    ``2 spread`` cells per axis, ``tau = pi spread / (n^2 R (R - 1/2))`` (``R = oversample``); the grid's
    inverse FFT is ``sum_j c_j ghat(m) exp(i m theta_j) / (2 pi) M``-scaled, and dividing by the Gaussian's
    transform ``sqrt(4 pi tau) exp(-m^2 tau)`` gives ``U``. Relative error ~1e-6 with the defaults (the
    spread Gaussian's tail at its cut, ``exp(-spread pi / 4)`` per axis at R = 2, and its aliases). Returns a
    complex128 ``(n, n)`` array in ``xp``; ``c`` (K, J): K weight vectors on the same points, ``(K, n, n)``. ``oversample`` / ``spread`` None: the module's ``NUFFT_OVERSAMPLE`` /
    ``NUFFT_SPREAD`` at call time."""
    n = int(n)
    R = int(NUFFT_OVERSAMPLE if oversample is None else oversample)
    spread = int(NUFFT_SPREAD if spread is None else spread)
    M = R * n
    tau = math.pi * spread / (n * n * R * (R - 0.5))
    tx = xp.asarray(theta_x, dtype=xp.float64)
    ty = xp.asarray(theta_y, dtype=xp.float64)
    c = xp.asarray(c, dtype=xp.complex128)
    one = c.ndim == 1          # c (K, J): K weight vectors on the same points, one (n, n) result each
    c = c[None] if one else c
    K = c.shape[0]
    step = 2.0 * math.pi / M
    lx0 = xp.floor(tx / step).astype(xp.int64)
    ly0 = xp.floor(ty / step).astype(xp.int64)
    ks = xp.asarray(np.arange(-spread + 1, spread + 1))[:, None]
    gx = xp.exp(-((lx0[None] + ks) * step - tx[None]) ** 2 / (4.0 * tau))      # (2 spread, J)
    gy = xp.exp(-((ly0[None] + ks) * step - ty[None]) ** 2 / (4.0 * tau))
    ix = (lx0[None] + ks) % M
    grid_re = xp.zeros((K, M * M))           # contiguous accumulators (a complex array's .real is strided: slower)
    grid_im = xp.zeros((K, M * M))
    for a in range(2 * spread):
        idx = ((((ly0 + int(ks[a, 0])) % M) * M)[None] + ix).ravel()
        for q in range(K):
            grid_re[q] += xp.bincount(idx, weights=(gx * (c[q].real * gy[a])[None]).ravel(), minlength=M * M)
            grid_im[q] += xp.bincount(idx, weights=(gx * (c[q].imag * gy[a])[None]).ravel(), minlength=M * M)
        del idx
    grid = xp.empty((K, M * M), dtype=xp.complex128)
    grid.real, grid.imag = grid_re, grid_im
    del grid_re, grid_im
    spec = xp.fft.ifft2(grid.reshape(K, M, M), axes=(-2, -1))     # sum_l F_l exp(+2 pi i m l / M) / M^2
    del grid
    spec *= M * M
    m = np.arange(-n // 2, n // 2)
    sel = xp.asarray(m % M)
    spec = spec[:, sel][:, :, sel]
    dec = xp.asarray(np.exp(m.astype(float) ** 2 * tau) * (step / math.sqrt(4.0 * math.pi * tau)))
    out = spec * dec[:, None] * dec[None, :]
    return out[0] if one else out


def nufft_flops(points: int, vectors: int, n: int, spread: int | None = None) -> float:
    """Work (flops) of one :func:`nufft_type1` call: ``points`` points, ``vectors`` weight vectors, ``n^2`` outputs.
    Per point, spread cell (``(2 spread)^2``, None: ``NUFFT_SPREAD``) and vector: the two products of the weight's
    parts with the 2-D Gaussian and two accumulations (4); per point, cell row and vector the weight times the row's
    Gaussian (2); per point the 2 x 2 spread Gaussians (~20 each); per vector the ``M^2`` FFT (``5 M^2 log2 M^2``,
    ``M = NUFFT_OVERSAMPLE n``) and the deconvolution (2 ``n^2``)."""
    spread = NUFFT_SPREAD if spread is None else int(spread)
    cells = (2 * spread) ** 2
    M = NUFFT_OVERSAMPLE * int(n)
    return float(points * (vectors * (4.0 * cells + 2.0 * 2 * spread) + 80.0 * spread)
                 + vectors * (5.0 * M * M * math.log2(M * M) + 2.0 * n * n))
