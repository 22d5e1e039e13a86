"""When a kept focal plan of :class:`torch_bridge.live.LiveProvider` is stale: the wavefront drift of the lens
since the plan was made (:func:`wavefront_drift_waves`), and which of the plans due in one call are made
again now and which are kept one more call (:func:`choose_replans`).

Why a wavefront measure. A kept plan (:class:`rwwarp.psf.RayWave`: grids, pitch, kept DOE orders, fitted
transfer) is traced and propagated with the current values, so its PSF is exact except for how well the
plan still samples the field: the error grows with how much the wave on the wave plane changed since the
plan was made, i.e. with the change of the optical path across the beam. A lateral move of the patch is
followed exactly (:meth:`rwwarp.psf.RayWave.recentre`) and rays leaving the window are caught by the window
check, so what is left is the change of the wavefront's shape. The learning values themselves are a poor
measure: a relative change is unbounded for a value near 0 (a weak surface, a DOE coefficient that starts at
0: the Cooke hybrid's second curvature is -2e-3 /mm and three of its four DOE coefficients are 0), and a
curvature, a distance and a DOE coefficient of the same relative change move the wave by very different
amounts. The measure here is first-order and host-only (no trace): the optical path change each learning
value makes over the source's beam, summed over surfaces (an upper bound for the change at any point of the
pupil), in waves of the source's wavelength:

* a refracting surface: ``|n' - n| max_{r <= h} |sag_now(r) - sag_plan(r)|`` (curvature, conic, aspheres),
  ``h`` the beam's paraxial extent on the surface at the source's field (marginal + chief ray height);
* a DOE: ``max |phi_now - phi_plan| / 2 pi`` over the disc ``r <= h`` at the source's wavelength
  (:func:`rwwarp.doe.wavelength_scale`); a phase surface the same in its diffraction order;
* a thin lens: ``h^2 / 2 |1/f_now - 1/f_plan|``;
* a distance (thickness ``t`` of the gap after a surface, index ``n``): the defocus it makes,
  ``n |dt| u^2 / 2`` with ``u`` the paraxial marginal ray's angle in the gap (a change of the axial
  position without defocus moves the patch, followed exactly).

Measured (``perf/replan_study.py``, the Cooke hybrid of ``configs/cooke_hybrid.yaml`` at 31 px and the ``gpu``
preset's sampling: curvatures, DOE and sensor distance moved by 0.1, 0.3 and 1 Adam step of ``lr_optics`` in
one direction; 2 corner-ward nodes x 0.45 / 0.55 / 0.66 um): a kept plan's PSF error against a fresh plan,
max |kept - fresh| / peak, is at most 4.1e-4 where the drift is <= 1 wave (12 cases, 0.15-0.95 waves; the
largest off the DOE's design wavelength, 0.66 um: the kept DOE orders and their fitted transfers), 1.5e-3 and
2.3e-3 at 1.96 and 2.37 waves; at 0.55 um <= 3.7e-5 up to 2.7 waves. One full Adam step is 1.4-3.2 waves
there. On the Cooke triplet (no DOE) the error is linear in the drift, 6.6e-5 a wave at 10 deg
(``tests/torch_bridge/test_live_drift.py``). Hence the ``gpu`` preset's tolerance of 1 wave (errors <= ~4e-4)
and its hard bound of 2 waves (a due plan kept one more call by the spreading: <= ~1.5e-3).

Units: mm, um for wavelengths, degrees for fields; drifts in waves."""
from __future__ import annotations

import math

import numpy as np

#: radial samples (sags, phase surfaces) in [0, 1] and points of the unit disc (DOE) the drift is evaluated on,
#: scaled by the beam's extent on each surface
_R01 = np.linspace(0.0, 1.0, 33)
_G = np.linspace(-1.0, 1.0, 17)
_X01, _Y01 = (a[a ** 2 + b ** 2 <= 1.0 + 1e-12] for a, b in (np.meshgrid(_G, _G), np.meshgrid(_G, _G)[::-1]))


def beam_extents(lens, wavelength_um: float, field_deg) -> tuple[np.ndarray, np.ndarray]:
    """Paraxial beam of a source at ``field_deg`` (deg, y or (x, y)) and ``wavelength_um`` (um), object at
    infinity: ``(h, u)``, ``h`` (n_surfaces,) the largest ray height on each surface (|marginal| + |chief|,
    mm) and ``u`` (n_surfaces,) the marginal ray's angle (rad, paraxial) in the gap after each surface."""
    from rwwarp import paraxial
    f = np.atleast_1d(np.asarray(field_deg, dtype=np.float64))
    tan = math.tan(math.radians(float(np.hypot(*f)) if f.size == 2 else abs(float(f[0]))))
    p = paraxial.pupils(lens, wavelength_um)
    ym, num = paraxial.ynu_trace(lens, wavelength_um, p.entrance_radius, 0.0)
    yc, _ = paraxial.ynu_trace(lens, wavelength_um, -p.entrance_z * tan, tan)
    n = paraxial.signed_indices(lens, wavelength_um)
    return np.abs(ym) + np.abs(yc), np.abs(num / n)


def source_geometry(lens, wavelength_um: float, field_deg) -> tuple:
    """What :func:`wavefront_drift_waves` needs of the plan's lens for one source, kept by a caller that judges
    the same plan again: ``(h, u, n, n_before)``: :func:`beam_extents` and the indices after and before each
    surface at ``wavelength_um`` (um)."""
    h, u = beam_extents(lens, wavelength_um, field_deg)
    n = lens.indices(wavelength_um)
    return h, u, n, np.concatenate([[1.0], n[:-1]])


def _same_shape(s, t) -> bool:
    return (s.radius == t.radius and s.conic == t.conic and list(s.aspheric) == list(t.aspheric) and s.a2 == t.a2
            and list(s.odd_aspheric) == list(t.odd_aspheric))


def wavefront_drift_waves(lens_plan, lens_now, wavelength_um: float, field_deg=0.0, extents=None) -> float:
    """First-order bound on the change of the optical path across the beam of a source (``field_deg``
    deg, ``wavelength_um`` um) between the lens a plan was made from (``lens_plan``) and the lens now
    (``lens_now``: the same surfaces, other values), in waves of ``wavelength_um``: the sum over surfaces of
    the terms in the module docstring. 0 for equal lenses. Raises ValueError when the lenses do not have
    the same surfaces (types, materials). ``extents``: :func:`source_geometry` of ``lens_plan`` for this source,
    when the caller keeps it (it depends on the plan's lens only)."""
    from rwwarp import doe
    from rwwarp import phase_surface as ph
    a, b = lens_plan.surfaces, lens_now.surfaces
    if len(a) != len(b) or any(s.type != t.type or s.material != t.material for s, t in zip(a, b)):
        raise ValueError("wavefront_drift_waves: the two lenses do not have the same surfaces (types, materials)")
    wl_mm = float(wavelength_um) * 1e-3
    h, u, n, n_before = source_geometry(lens_plan, wavelength_um, field_deg) if extents is None else extents
    opl = 0.0     # mm
    phase = 0.0   # rad
    for i, (s, t) in enumerate(zip(a, b)):
        if s.thickness != t.thickness:
            opl += abs(n[i]) * abs(t.thickness - s.thickness) * 0.5 * u[i] ** 2
        if s.type == "standard":
            if not _same_shape(s, t):
                ds = np.abs(t.sag(_R01 * h[i]) - s.sag(_R01 * h[i]))
                d = float(np.max(ds)) if np.all(np.isfinite(ds)) else math.inf
                opl += abs(n[i] - n_before[i]) * d
            if (s.phase is not None or t.phase is not None) and s.phase != t.phase:
                if (s.phase is None) != (t.phase is None):
                    return math.inf
                rho = _R01 * h[i]
                d = 0.0
                for q, sign in ((s, -1.0), (t, 1.0)):
                    rn, co = ph.phase_profile(q)
                    d = d + sign * float(q.diffraction_order) * sum(c * (rho / rn) ** (2 * k + 2) for k, c in enumerate(co))
                phase += float(np.max(np.abs(d)))
        elif s.type == "thin_lens" and s.focal_length != t.focal_length:
            opl += 0.5 * h[i] ** 2 * abs(1.0 / t.focal_length - 1.0 / s.focal_length)
        elif s.type == "doe" and s.profile != t.profile:
            x, y = _X01 * h[i], _Y01 * h[i]
            src = getattr(lens_plan, "source", None)
            d = doe.get_profile(t, src).phase(x, y, t.design_wavelength_um) - \
                doe.get_profile(s, src).phase(x, y, s.design_wavelength_um)
            scale = doe.wavelength_scale(s.material, s.design_wavelength_um, wavelength_um)
            phase += abs(scale) * float(np.max(np.abs(d)))
    out = opl / wl_mm + phase / (2.0 * math.pi)
    return float(out) if np.isfinite(out) else math.inf


def choose_replans(status: dict, quota: int) -> set:
    """Which kept plans to make again in one call. ``status``: key -> ``(forced, due, staleness)``: ``forced``
    plans are made again whatever the quota (rays left the window, the age bound, the hard drift bound, or
    already kept once past due); ``due`` plans (past the drift tolerance or the age) take what is left of
    ``quota`` (re-plans this call), the stalest (largest ``staleness``) first, the rest are kept one more
    call. Returns the set of keys to plan again."""
    out = {k for k, (forced, _, _) in status.items() if forced}
    due = sorted((k for k, (forced, d, _) in status.items() if d and not forced), key=lambda k: -status[k][2])
    room = max(0, int(quota) - len(out))
    out.update(due[:room])
    return out
