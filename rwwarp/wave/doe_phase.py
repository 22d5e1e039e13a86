"""A DOE's phase written once for every array namespace (numpy, CuPy or torch, chosen from the arrays or
passed as ``xp``; rwwarp never imports torch): the profiles' phase and gradient at the design wavelength
(radial polynomials, Fresnel lens, cubic, Zernike, pixel map; rad and rad/mm; :func:`profile_phase` and
:func:`profile_gradient` dispatch on the kind), and the relief it becomes: the phase wrapped to [0, 2 pi)
and quantised to ``levels`` levels (:func:`wrap_phase`, :func:`quantize`, :func:`relief_phase`), its wrap
zones and a zone's relief remapped to another wavelength (:func:`wrap_zone`, :func:`zone_relief_phase`).
:mod:`rwwarp.doe`'s profile classes, the wave stage (numpy / CuPy) and torch_bridge's DOE (learnable values,
the straight-through gradient of the quantiser, the ray model's grating, the focal orders) all call these."""
from __future__ import annotations

import functools
import math
import sys

import numpy as np

from ..errors import LensError

TWO_PI = 2.0 * math.pi


def array_namespace(*arrays):
    """The array module of the arguments: ``torch`` or ``cupy`` for the first torch tensor or CuPy array
    among them (looked up in ``sys.modules``: rwwarp never imports either), else numpy (numpy arrays,
    lists, Python numbers)."""
    for a in arrays:
        mod = type(a).__module__.split(".", 1)[0]
        if mod in ("torch", "cupy"):
            return sys.modules[mod]
    return np

def _real(a, xp):
    """``a`` as an array of ``xp``: numpy inputs become float64 (as every numpy entry point always did);
    torch / CuPy arrays keep their dtype and device."""
    if xp is np:
        return np.asarray(a, dtype=np.float64)
    return a if type(a).__module__.split(".", 1)[0] == xp.__name__ else xp.asarray(a)

def _as_index(a, xp):
    """Integer index array of ``a`` (whole-valued floats) in ``xp``."""
    return a.long() if xp.__name__ == "torch" else a.astype(xp.intp)

def _polyval_ascending(coeffs, u, xp=np):
    """sum_k coeffs[k] * u**k by Horner's rule (coeffs ascending)."""
    out = xp.zeros_like(u)
    for c in reversed(coeffs):
        out = out * u + c
    return out

def radial_phase(kind: str, coefficients, norm_radius: float, r2, xp=None):
    """Phase phi0 (rad) of an ``even_poly`` or ``poly`` DOE at ``r2 = x^2 + y^2`` (mm^2).

    * even_poly ``phi0 = sum_i a_i u^i`` (i = 1, 2, ...), ``u = r^2 / R^2``;
    * poly ``phi0 = sum_k c_k rho^k`` (k = 1, 2, ...), ``rho = r / R``.

    ``coefficients`` (rad): a sequence of numbers or a 1-D array of ``xp`` (a torch tensor of learnable
    values: differentiable); ``norm_radius`` R in mm; ``r2`` an array of ``xp`` (any shape; the result has
    its shape). Horner's rule ``phi = (... ((a_n) v + a_(n-1)) v ... + a_1) v`` in ``v = u`` or ``rho``. The
    one home of this evaluation: :class:`EvenPolyProfile`, :class:`PolyProfile` and
    ``torch_bridge.HybridLens.doe_phase`` call it."""
    xp = array_namespace(r2, coefficients) if xp is None else xp
    r2 = _real(r2, xp)
    R = float(norm_radius)
    if kind == "even_poly":
        v = r2 / (R * R)
    elif kind == "poly":
        v = xp.sqrt(r2) / R
    else:
        raise ValueError(f"radial_phase handles 'even_poly' and 'poly' DOEs, got {kind!r}")
    phi = xp.zeros_like(v)
    for i in range(len(coefficients) - 1, -1, -1):     # Horner, ascending coefficients times v
        phi = (phi + coefficients[i]) * v
    return phi

def fresnel_quadratic(focal_length, design_wavelength_um: float):
    """``q = -pi / (lambda0 f)`` (rad/mm^2) of an ideal diffractive lens of focal length ``focal_length`` (mm;
    a number or a 0-d array: differentiable) at ``design_wavelength_um`` (um): ``phi0 = q r^2``."""
    return -math.pi / (float(design_wavelength_um) * 1e-3 * focal_length)

def fresnel_phase(focal_length, design_wavelength_um: float, r2, xp=None):
    """Phase phi0 (rad) of a ``fresnel`` DOE at ``r2 = x^2 + y^2`` (mm^2): ``(-pi / (lambda0 f)) r^2``
    (:func:`fresnel_quadratic`; ``f`` in mm, possibly a 0-d torch tensor, lambda0 in um)."""
    xp = array_namespace(r2, focal_length) if xp is None else xp
    return fresnel_quadratic(focal_length, design_wavelength_um) * _real(r2, xp)

def cubic_phase(alpha, norm_radius: float, x_mm, y_mm, xp=None):
    """Phase phi0 (rad) of a ``cubic`` DOE: ``alpha ((x/R)^3 + (y/R)^3)``; ``alpha`` in rad (a number or a
    0-d array: differentiable), R = ``norm_radius`` in mm, ``x_mm``, ``y_mm`` broadcastable arrays (mm).
    The cubes are products (``t t t``), so every namespace gives the same floating-point result."""
    xp = array_namespace(x_mm, y_mm, alpha) if xp is None else xp
    R = float(norm_radius)
    x, y = _real(x_mm, xp) / R, _real(y_mm, xp) / R
    return alpha * (x * x * x + y * y * y)

def fresnel_gradient(focal_length, design_wavelength_um: float, x_mm, y_mm, xp=None):
    """``(dphi0/dx, dphi0/dy) = 2 q (x, y)`` (rad/mm) of a ``fresnel`` DOE, ``q`` of
    :func:`fresnel_quadratic` (``f`` in mm, a number or a 0-d array: differentiable; lambda0 in um), at
    broadcastable ``x_mm``, ``y_mm`` (mm)."""
    xp = array_namespace(x_mm, y_mm, focal_length) if xp is None else xp
    q2 = 2.0 * fresnel_quadratic(focal_length, design_wavelength_um)
    return q2 * _real(x_mm, xp), q2 * _real(y_mm, xp)

def cubic_gradient(alpha, norm_radius: float, x_mm, y_mm, xp=None):
    """``(dphi0/dx, dphi0/dy) = (3 alpha / R^3) (x^2, y^2)`` (rad/mm) of a ``cubic`` DOE (``alpha`` in rad, a
    number or a 0-d array: differentiable; R = ``norm_radius`` in mm) at broadcastable ``x_mm``, ``y_mm``."""
    xp = array_namespace(x_mm, y_mm, alpha) if xp is None else xp
    R = float(norm_radius)
    x, y = _real(x_mm, xp), _real(y_mm, xp)
    k = 3.0 * alpha / R ** 3
    return k * x * x, k * y * y

def radial_gradient_over_r(kind: str, coefficients, norm_radius: float, r2, xp=np):
    """``(1 / r) d phi0 / dr`` (rad/mm^2) of an ``even_poly`` or ``poly`` DOE at ``r2 = x^2 + y^2`` (mm^2),
    so that ``grad phi0 = g (x, y)``. ``coefficients``: a sequence or a 1-D array of the array namespace
    ``xp`` (numpy or torch: differentiable in torch), ``norm_radius`` in mm. The one home of this
    derivative: :class:`EvenPolyProfile`, :class:`PolyProfile` and the ray model's DOE grating in
    ``torch_bridge`` use it.

    * even_poly ``phi0 = sum_i a_i u^(i+1)``, ``u = r^2 / R^2``: ``g = (2 / R^2) sum_i (i + 1) a_i u^i``;
    * poly ``phi0 = sum_k c_k rho^k``, ``rho = r / R``: ``g = sum_(k>=2) k c_k rho^(k-2) / R^2 + c_1 / (R r)``
      (the cone term's gradient is undefined on the axis and taken as 0 there)."""
    R = float(norm_radius)
    n = len(coefficients)
    if kind == "even_poly":
        u = r2 / (R * R)
        d = u * 0.0
        for i in range(n - 1, -1, -1):                # Horner
            d = d * u + (i + 1) * coefficients[i]
        return (2.0 / (R * R)) * d
    if kind == "poly":
        r = xp.sqrt(r2)
        rho = r / R
        d = rho * 0.0
        for k in range(n, 1, -1):                     # Horner over k >= 2
            d = d * rho + k * coefficients[k - 1]
        g = d / (R * R)
        if n:
            g = g + xp.where(r > 0, coefficients[0] / (R * xp.where(r > 0, r, 1.0)), 0.0)
        return g
    raise ValueError(f"radial_gradient_over_r handles 'even_poly' and 'poly' DOEs, got {kind!r}")

def noll_to_nm(j: int):
    """Noll index j (1-based) -> (n, m); m > 0 cosine, m < 0 sine, m = 0 rotationally symmetric."""
    if j < 1:
        raise ValueError(f"Noll index must be >= 1, got {j}")
    n = 0
    while (n + 1) * (n + 2) // 2 < j:
        n += 1
    p = j - n * (n + 1) // 2 - 1  # position within the row, 0..n
    abs_m = [m for m in range(n % 2, n + 1, 2) for _ in ((0,) if m == 0 else (0, 1))][p]
    if abs_m == 0:
        return n, 0
    return n, (abs_m if j % 2 == 0 else -abs_m)

@functools.lru_cache(maxsize=None)
def _zernike_radial_q(n: int, m: int):
    """Coefficients (ascending in u = rho^2) of Q with R_n^m(rho) = rho^m Q(rho^2)."""
    m = abs(m)
    q = [0.0] * ((n - m) // 2 + 1)
    for s in range((n - m) // 2 + 1):
        c = (-1) ** s * math.factorial(n - s) / (
            math.factorial(s) * math.factorial((n + m) // 2 - s) * math.factorial((n - m) // 2 - s))
        q[(n - m) // 2 - s] += c
    return tuple(q)

def zernike_phase(coefficients, norm_radius: float, x_mm, y_mm, xp=None, gradient: bool = False):
    """Phase phi0 (rad) of a ``zernike`` DOE, ``sum_j z_j Z_j`` (Noll-ordered, Noll-normalised, see
    :class:`ZernikeProfile`), at broadcastable ``x_mm``, ``y_mm`` (mm); with ``gradient`` also
    ``(dphi0/dx, dphi0/dy)`` in rad/mm: returns ``(phi0, gx, gy)``.

    ``coefficients`` (rad): a sequence of numbers (terms equal to 0 are skipped) or of 0-d arrays / a 1-D
    array of ``xp`` (a torch tensor: every term is kept, differentiable). Evaluated in Cartesian form with
    real arithmetic only (``rho^m cos(m theta) = Re((x + i y)^m) / R^m``, the powers by repeated
    multiplication), so values and gradients have no singularity and every namespace gives the same
    floating-point result."""
    xp = array_namespace(x_mm, y_mm, coefficients) if xp is None else xp
    R = float(norm_radius)
    x, y = _real(x_mm, xp) / R, _real(y_mm, xp) / R
    u = x * x + y * y
    val = xp.zeros_like(u)
    gx, gy = xp.zeros_like(u), xp.zeros_like(u)
    powers = [None, (x, y)]                             # (Re, Im) of (x + i y)^k, k >= 1

    def power(k):
        while len(powers) <= k:
            a, b = powers[-1]
            powers.append((a * x - b * y, a * y + b * x))
        return powers[k]

    for j in range(1, len(coefficients) + 1):
        c = coefficients[j - 1]
        if isinstance(c, (int, float)) and c == 0.0:
            continue
        n, m = noll_to_nm(j)
        cn = c * (math.sqrt(n + 1) if m == 0 else math.sqrt(2 * (n + 1)))
        q = _zernike_radial_q(n, m)
        am = abs(m)
        Q = _polyval_ascending(q, u, xp)
        ang = None if am == 0 else power(am)[0 if m > 0 else 1]
        val = val + (cn * Q if ang is None else cn * Q * ang)
        if gradient:
            dq = [k * a for k, a in enumerate(q)][1:]
            dQ = _polyval_ascending(dq, u, xp) if dq else xp.zeros_like(u)
            if am == 0:
                gx = gx + cn * (2.0 * x * dQ)
                gy = gy + cn * (2.0 * y * dQ)
                continue
            # d/dx (x + i y)^m = m (x + i y)^(m-1), d/dy = i m (x + i y)^(m-1)
            if am == 1:
                pr, pi_ = 1.0, 0.0
            else:
                pr, pi_ = power(am - 1)
            pr, pi_ = am * pr, am * pi_
            dax, day = (pr, -pi_) if m > 0 else (pi_, pr)
            gx = gx + cn * (2.0 * x * dQ * ang + Q * dax)
            gy = gy + cn * (2.0 * y * dQ * ang + Q * day)
    return (val, gx / R, gy / R) if gradient else val

def pixel_map_indices(pitch: float, shape, x_mm, y_mm, xp=None):
    """Nearest-pixel ``(row, col, inside)`` of a pixel map of ``shape`` (ny, nx) and ``pitch`` mm, centred on
    the axis, row 0 at +y and column 0 at -x: ``col = floor(x / pitch + nx / 2)``,
    ``row = floor(ny / 2 - y / pitch)``. ``x_mm``, ``y_mm``: broadcastable arrays of ``xp`` (mm). Indices are
    integer arrays of ``xp`` (0 outside the map), ``inside`` a boolean mask."""
    xp = array_namespace(x_mm, y_mm) if xp is None else xp
    ny, nx = shape
    pitch = float(pitch)
    col = xp.floor(_real(x_mm, xp) / pitch + nx / 2.0)
    row = xp.floor(ny / 2.0 - _real(y_mm, xp) / pitch)
    inside = (col >= 0) & (col < nx) & (row >= 0) & (row < ny)
    return _as_index(xp.where(inside, row, 0.0), xp), _as_index(xp.where(inside, col, 0.0), xp), inside

def pixel_map_phase(data, row, col, inside, xp=None):
    """Phase phi0 (rad) of a pixel map ``data`` (ny, nx; an array of ``xp``, differentiable in torch) at the
    indices of :func:`pixel_map_indices`: ``data[row, col]`` inside the map, 0 outside."""
    xp = array_namespace(data) if xp is None else xp
    return xp.where(inside, data[row, col], 0.0)

# ====================================================================== any smooth kind by name
SMOOTH_KINDS = ("even_poly", "poly", "fresnel", "zernike", "cubic")

def _check_kind(kind, norm_radius):
    if kind not in SMOOTH_KINDS:
        raise ValueError(f"a smooth DOE profile kind is one of {SMOOTH_KINDS}, got {kind!r} (a pixel map: "
                         "pixel_map_indices / pixel_map_phase)")
    if kind != "fresnel" and (norm_radius is None or not float(norm_radius) > 0):
        raise ValueError(f"a {kind!r} DOE profile needs norm_radius > 0 (mm), got {norm_radius!r}")

def profile_phase(kind: str, values, x_mm, y_mm, *, norm_radius=None, design_wavelength_um: float = 0.55,
                  xp=None):
    """Phase phi0 (rad) of a smooth DOE profile of ``kind`` at broadcastable ``x_mm``, ``y_mm`` (mm): the one
    dispatch over the kinds that :mod:`rwwarp.doe`'s profile classes and ``torch_bridge`` (learnable values)
    share. ``values``: the profile's learnable numbers, a sequence or a 1-D array of ``xp`` (a torch tensor:
    differentiable): the coefficients (rad) of ``even_poly`` / ``poly`` / ``zernike``, ``[focal_length]`` (mm)
    of ``fresnel``, ``[alpha]`` (rad) of ``cubic``. ``norm_radius`` (mm): all kinds but ``fresnel``;
    ``design_wavelength_um`` (um): ``fresnel``'s lambda0."""
    _check_kind(kind, norm_radius)
    xp = array_namespace(x_mm, y_mm, values) if xp is None else xp
    if kind in ("even_poly", "poly"):
        x, y = _real(x_mm, xp), _real(y_mm, xp)
        return radial_phase(kind, values, norm_radius, x * x + y * y, xp)
    if kind == "fresnel":
        x, y = _real(x_mm, xp), _real(y_mm, xp)
        return fresnel_phase(values[0], design_wavelength_um, x * x + y * y, xp)
    if kind == "cubic":
        return cubic_phase(values[0], norm_radius, x_mm, y_mm, xp)
    return zernike_phase(values, norm_radius, x_mm, y_mm, xp)

def profile_gradient(kind: str, values, x_mm, y_mm, *, norm_radius=None, design_wavelength_um: float = 0.55,
                     xp=None):
    """``(dphi0/dx, dphi0/dy)`` (rad/mm) of a smooth DOE profile of ``kind`` at ``x_mm``, ``y_mm`` (mm); the
    arguments as :func:`profile_phase` (differentiable in torch ``values`` and coordinates). The one home of
    the gradient: :meth:`rwwarp.doe.Profile.gradient` (plans, the ray model) and torch_bridge's ray model
    (``RaySpot``) call it."""
    _check_kind(kind, norm_radius)
    xp = array_namespace(x_mm, y_mm, values) if xp is None else xp
    if kind in ("even_poly", "poly"):
        x, y = _real(x_mm, xp), _real(y_mm, xp)
        k = radial_gradient_over_r(kind, values, norm_radius, x * x + y * y, xp)
        return k * x, k * y
    if kind == "fresnel":
        return fresnel_gradient(values[0], design_wavelength_um, x_mm, y_mm, xp)
    if kind == "cubic":
        return cubic_gradient(values[0], norm_radius, x_mm, y_mm, xp)
    _, gx, gy = zernike_phase(values, norm_radius, x_mm, y_mm, xp, gradient=True)
    return gx, gy

def profile_quadratic(kind: str, values, *, norm_radius=None, design_wavelength_um: float = 0.55):
    """The rotationally symmetric ``r^2`` coefficient ``q`` (rad/mm^2) of a smooth DOE's phase near the axis
    (``phi0 ~ q r^2``: the paraxial power hook, :func:`rwwarp.paraxial.diffractive_power`), from its learnable
    ``values`` as :func:`profile_phase` takes them (numbers, or a 1-D torch tensor: differentiable):
    ``a_1 / R^2`` (even_poly), ``c_2 / R^2`` (poly), ``-pi / (lambda0 f)`` (fresnel), the ``rho^2`` terms of
    the rotationally symmetric Zernike polynomials over ``R^2`` (zernike), 0 (cubic)."""
    _check_kind(kind, norm_radius)
    n = len(values)
    if kind == "fresnel":
        return fresnel_quadratic(values[0], design_wavelength_um)
    if kind == "cubic" or (kind == "even_poly" and n < 1) or (kind == "poly" and n < 2):
        return 0.0
    R = float(norm_radius)
    if kind in ("even_poly", "poly"):
        return values[0 if kind == "even_poly" else 1] / R ** 2
    total = 0.0                                         # the r^2 terms of the rotationally symmetric Z_j
    for j in range(1, n + 1):
        nn, m = noll_to_nm(j)
        q = _zernike_radial_q(nn, m)
        if m == 0 and len(q) > 1:
            total += values[j - 1] * math.sqrt(nn + 1) * q[1]
    return total / R ** 2

# ====================================================================== phase operations
def wrap_phase(phi, xp=None):
    """Phase ``phi`` (rad) wrapped to [0, 2 pi): ``phi - 2 pi floor(phi / 2 pi)``, a value that rounds to
    exactly 2 pi (or below 0) becoming 0. ``xp``: the array namespace (default that of ``phi``); numpy
    results are float64, torch / CuPy keep the input's dtype and device."""
    xp = array_namespace(phi) if xp is None else xp
    phi = _real(phi, xp)
    w = phi - TWO_PI * xp.floor(phi * (1.0 / TWO_PI))  # 4x faster than np.mod on large grids
    return xp.where((w >= TWO_PI) | (w < 0.0), 0.0, w)  # rounding can give exactly 2 pi

def quantize(phi, levels: int, xp=None):
    """Wrap ``phi`` (radians) to [0, 2 pi) and round to the nearest of ``levels`` equally spaced levels
    ``k 2 pi / levels`` (k = 0 .. levels-1; a value that rounds to 2 pi becomes 0; ties to the even k).
    ``xp``: the array namespace (default that of ``phi``).

    Gradient convention (the autograd glue is ``torch_bridge.QuantizeSTE``, whose forward is this
    function): straight-through, i.e. the backward pass treats quantisation as the identity,
    ``d quantize(phi) / d phi = 1``; the wrap is also passed straight through (its derivative is 1
    almost everywhere).
    """
    levels = int(levels)
    if levels < 2:
        raise LensError(f"levels must be >= 2, got {levels}")
    xp = array_namespace(phi) if xp is None else xp
    step = TWO_PI / levels
    k = xp.round(wrap_phase(phi, xp) / step)
    return xp.where(k >= levels, 0.0, k * step)

def relief_phase(phi, levels=None, xp=None):
    """The relief phase of an unwrapped DOE phase ``phi`` (rad): :func:`wrap_phase` when ``levels`` is
    None, else :func:`quantize` to ``levels`` levels. The forward of ``torch_bridge.QuantizeSTE``."""
    return wrap_phase(phi, xp) if levels is None else quantize(phi, levels, xp)

def wrap_zone(phi, xp=None):
    """The wrap zone ``k = floor(phi / 2 pi)`` of an unwrapped DOE phase ``phi`` (rad), a float array of ``xp``
    (default that of ``phi``): inside zone ``k`` the relief phase is ``phi - 2 pi k``. The one zone index of the
    focal method's exact chief-ray zone (:func:`rwwarp.wave.focal.doe_order_series`, torch_bridge's packed
    tiles) and of the plan's chief-ray zone (:func:`rwwarp.wave.doe_sampling.chief_zone`)."""
    xp = array_namespace(phi) if xp is None else xp
    return xp.floor(phi / TWO_PI)

def zone_relief_phase(phi, zone, scale):
    """The relief phase of zone ``zone`` (:func:`wrap_zone`) at another wavelength: ``scale (phi - 2 pi zone)``
    (rad), ``scale`` the wavelength remap ``s(lambda)`` of :func:`rwwarp.doe.wavelength_scale` (a number or an
    array broadcasting with ``phi``, e.g. one per source). Equal to ``scale * wrap_phase(phi)`` where
    ``wrap_zone(phi) == zone`` (without the wrap's discontinuity: smooth in ``phi``)."""
    return scale * (phi - TWO_PI * zone)
