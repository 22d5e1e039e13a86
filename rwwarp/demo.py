"""What ``rwwarp demo`` runs: the bundled A489 asphere with a modest achromatising DOE, and PSF patches
chosen so that each PSF fits its patch.

Units: lengths in mm, wavelengths in um, field angles in degrees, DOE phase in radians.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["achromat_doe", "fitting_patch", "doe_quadratic_for_achromat"]


def _doe_index(lens) -> int:
    idx = [i for i, s in enumerate(lens.surfaces) if s.type == "doe"]
    if not idx:
        raise ValueError(f"{lens.name or 'the lens'} has no DOE surface")
    return idx[-1]


def _with_a1(lens, i, a1, refocus_to=None):
    """``lens`` with the DOE ``i``'s rho^2 coefficient set to ``a1`` (rad); with ``refocus_to`` (a reference
    lens and wavelength, um), the sensor moves with the paraxial focus so that its offset from that focus is
    the reference's."""
    from .metrics import paraxial_image_distance as v
    s = lens.surfaces[i]
    prof = dict(s.profile)
    c = [float(x) for x in prof.get("coefficients", [])] or [0.0]
    c[0] = float(a1)
    prof["coefficients"] = c
    out = lens.with_surface(i, profile=prof)
    if refocus_to is not None:
        ref, w = refocus_to
        last = len(out.surfaces) - 1
        out = out.with_surface(last, thickness=out.surfaces[last].thickness + v(out, w) - v(ref, w))
    return out


def doe_quadratic_for_achromat(lens, wavelengths_um=None) -> float:
    """The DOE's rho^2 phase coefficient (rad, at its design wavelength, over its ``norm_radius``) that brings
    the paraxial foci of the shortest and longest of ``wavelengths_um`` (default the lens's) together: a
    paraxial hybrid achromat. The DOE's power ``-lambda a1 / (pi R^2)`` grows with the wavelength and so
    cancels the glass's axial colour. Found by the secant method on the paraxial image distances."""
    from .metrics import paraxial_image_distance as v
    wls = sorted(float(w) for w in (wavelengths_um or lens.wavelengths_um))
    lo, hi = wls[0], wls[-1]
    if hi - lo < 1e-6:
        raise ValueError("an achromat needs two different wavelengths")
    i = _doe_index(lens)
    a_now = float((lens.surfaces[i].profile.get("coefficients") or [0.0])[0])

    def colour(a1):
        L = _with_a1(lens, i, a1)
        return v(L, hi) - v(L, lo)

    x0, x1 = a_now, a_now - 100.0
    f0, f1 = colour(x0), colour(x1)
    for _ in range(50):
        if f1 == f0:
            break
        x0, x1, f0 = x1, x1 - f1 * (x1 - x0) / (f1 - f0), f1
        f1 = colour(x1)
        if abs(x1 - x0) < 1e-9 * max(1.0, abs(x1)):
            break
    if not math.isfinite(x1) or abs(f1) > 1e-9:
        raise ValueError("no paraxial achromat found for this DOE (its power does not move the colour focus)")
    return float(x1)


def achromat_doe(lens, strength: float = 0.5, wavelengths_um=None, focus_wavelength_um=None):
    """``lens`` with a rotationally symmetric quadratic phase on its DOE: ``strength`` times the change that
    makes it a paraxial achromat over ``wavelengths_um`` (1: the shortest and longest wavelengths focus
    together; 0.5 halves the axial colour), the sensor moved with the paraxial focus of
    ``focus_wavelength_um`` (default the middle wavelength) so that it keeps its offset from that focus.

    Returns ``(new_lens, info)``; ``info`` holds ``a1_rad``, ``doe_focal_length_mm`` (at the design
    wavelength), ``sensor_shift_mm`` and ``focal_shift_um`` before / after (paraxial, relative to the
    middle wavelength, at each of the lens's wavelengths)."""
    from .metrics import chromatic_focal_shift
    from .paraxial import doe_power
    if not (0.0 <= float(strength) <= 1.5):
        raise ValueError(f"strength must be in 0..1.5 (1: paraxial achromat), got {strength}")
    wls = list(wavelengths_um or lens.wavelengths_um)
    wmid = float(focus_wavelength_um or sorted(wls)[len(wls) // 2])
    i = _doe_index(lens)
    a_now = float((lens.surfaces[i].profile.get("coefficients") or [0.0])[0])
    a1 = a_now + float(strength) * (doe_quadratic_for_achromat(lens, wls) - a_now)
    new = _with_a1(lens, i, a1, refocus_to=(lens, wmid))
    new.name = f"{lens.name} + achromatising DOE ({strength:g} x paraxial achromat)"
    s = new.surfaces[i]
    p = doe_power(s, s.design_wavelength_um)
    last = len(lens.surfaces) - 1
    info = {"a1_rad": a1, "doe_surface": i,
            "doe_focal_length_mm": (1.0 / p) if p else math.inf,
            "sensor_shift_mm": new.surfaces[last].thickness - lens.surfaces[last].thickness,
            "wavelengths_um": sorted(wls),
            "focal_shift_before_um": chromatic_focal_shift(lens, sorted(wls), wmid).shift_um,
            "focal_shift_after_um": chromatic_focal_shift(new, sorted(wls), wmid).shift_um}
    return new, info


def _doe_orders(lens, w, min_power):
    """Diffraction orders of the lens's DOE that carry at least ``min_power`` of the power at ``w`` um (scalar
    theory for a continuous blazed relief: ``sinc^2(m - s)``, ``s`` the wavelength remap), always order 1."""
    from .doe import wavelength_scale
    i = [k for k, s in enumerate(lens.surfaces) if s.type == "doe"]
    if not i:
        return [1]
    s = lens.surfaces[i[-1]]
    a = float(np.ravel(wavelength_scale(s.material, s.design_wavelength_um, w))[0])
    return sorted({1} | {m for m in range(-3, 6) if np.sinc(m - a) ** 2 >= min_power})


def fitting_patch(lens, fields, wavelengths_um, pixel_mm=None, airy_radii: float = 10.0, min_order_power=0.02,
                  cap: int = 512, device: str = "cpu"):
    """Patch centres and one patch size (sensor pixels) that hold every (field, wavelength) PSF.

    The centre of each field is where its chief ray lands at the middle wavelength *in the DOE's first
    diffraction order* (the library's default centre, the chief ray traced through the refractive surfaces
    only, misses the PSF by the DOE's deflection); all wavelengths of a field share it, so lateral colour
    stays visible. The size is twice the farthest ray of a 31 x 31 pupil grid from its field's centre, in
    every diffraction order that carries at least ``min_order_power`` of a wavelength's power (scalar
    theory, ``sinc^2(m - s(lambda))``: at 0.45 um a DOE blazed for 0.55 um sends 8 % into order 2 and 3 %
    into order 0), plus ``airy_radii`` Airy radii (0.61 lambda / NA) for diffraction, plus 10 %, rounded up
    to a multiple of 8 (at most ``cap``). Returns ``(centres (n_fields, 2) mm, size)``."""
    from .metrics.sampling import _image_space_rays, image_space_na
    from .trace import as_field_list, pupil_grid
    fields = as_field_list(fields)
    pixel = float(pixel_mm or lens.sensor.pixel_pitch)
    wls = sorted(float(w) for w in wavelengths_um)
    wmid = wls[len(wls) // 2]
    shape = lens.surfaces[lens.stop_index].shape
    u, v, _ = pupil_grid(31, shape, layout="edges")
    u, v = np.concatenate([[0.0], u]), np.concatenate([[0.0], v])

    def on_sensor(w, orders):
        """Sensor hits (S, N, 2) mm and validity of the rays in each diffraction order (a list)."""
        pos, d1, ok1, _, n = _image_space_rays(lens, fields, w, u, v, device=device)
        _, d0, ok0, _, _ = _image_space_rays(lens, fields, w, u, v, device=device, doe_bending="none")
        out = []
        for m in orders:
            t = n * (d0[..., :2] + m * (d1[..., :2] - d0[..., :2]))  # grating equation: tangential part linear in m
            tz2 = n * n - np.sum(t * t, -1)
            ok = ok1 & ok0 & (tz2 > 0)
            d = np.concatenate([t, np.sqrt(np.maximum(tz2, 1e-30))[..., None]], -1)
            s = (lens.sensor_z - pos[..., 2]) / d[..., 2]
            out.append((pos[..., :2] + s[..., None] * d[..., :2], ok))
        return out

    (xy, ok), = on_sensor(wmid, [1])
    centres = np.zeros((len(fields), 2))
    for k in range(len(fields)):
        centres[k] = xy[k, 0] if ok[k, 0] else xy[k, ok[k]].mean(0)
    need = 0.0
    for w in wls:
        airy = [0.61 * w * 1e-3 / max(image_space_na(lens, f, w, device=device), 1e-6) for f in fields]
        for xy, ok in on_sensor(w, _doe_orders(lens, w, min_order_power)):
            for k in range(len(fields)):
                if ok[k].sum() < 2:
                    continue
                need = max(need, float(np.max(np.abs(xy[k, ok[k]] - centres[k]))) + airy_radii * airy[k])
    n = int(math.ceil(1.1 * 2.0 * need / pixel))
    return centres, int(min(max(32, 8 * math.ceil(n / 8)), cap))


def _stack_maps(maps):
    """One :class:`rwwarp.PSFMap` (fields x wavelengths) from per-field maps of the same size and wavelengths."""
    from .psf import PSFMap
    first = maps[0]
    info = {"plan": maps[-1].info.get("plan"), "time_s": sum(m.info.get("time_s", 0.0) for m in maps),
            "valid_fraction": [v for m in maps for v in m.info["valid_fraction"]],
            "power_in_patch": np.concatenate([m.info["power_in_patch"] for m in maps], 0),
            "batches": [b for m in maps for b in m.info.get("batches", [])]}
    return PSFMap(np.concatenate([m.data for m in maps], 0), first.pixel_mm,
                  np.concatenate([m.centers_mm for m in maps], 0), [f for m in maps for f in m.fields_deg],
                  list(first.wavelengths_um), first.model, info)


def run(lens, fields, size=None, device: str = "cpu", batch=None, doe_strength: float = 0.25, progress=True):
    """The demo's computation: ``lens`` with :func:`achromat_doe` (``doe_strength``; skipped when the lens has
    no polynomial DOE or the strength is 0), a ray-wave PSF map over ``fields`` x the lens's wavelengths on
    patches from :func:`fitting_patch` (``size`` overrides the size), and the on-axis PSFs of the lens as given
    (no DOE change) on the same pixels for comparison.

    Returns a dict: ``lens`` (the demo's), ``doe`` (:func:`achromat_doe` info or None), ``map`` (PSFMap),
    ``size`` and ``auto_size`` (px), ``time_s`` (the map), ``reference`` (PSFMap of the lens as given on
    axis, or None), ``reference_time_s``."""
    import time
    import warnings

    from .errors import PatchWarning
    from .psf import psf_map
    wls = list(lens.wavelengths_um)
    doe = None
    base = lens
    has_poly_doe = any(s.type == "doe" and (s.profile or {}).get("kind") == "even_poly" for s in lens.surfaces)
    if has_poly_doe and doe_strength > 0 and max(wls) - min(wls) > 1e-6:  # an achromat needs two wavelengths
        lens, doe = achromat_doe(lens, doe_strength)
    centres, auto = fitting_patch(lens, fields, wls, device=device)
    size = int(size or auto)
    it = range(len(fields))
    bar = None
    if progress:
        from tqdm.auto import tqdm
        bar = tqdm(total=len(fields) * len(wls), desc="ray-wave PSFs", unit="PSF")
    maps = []
    t = time.perf_counter()
    for k in it:
        maps.append(psf_map(lens, [fields[k]], wls, size=size, device=device, batch=batch or len(wls),
                            center_mm=tuple(centres[k])))
        if bar is not None:
            bar.update(len(wls))
    if bar is not None:
        bar.close()
    dt = time.perf_counter() - t
    res = {"lens": lens, "doe": doe, "map": _stack_maps(maps), "size": size, "auto_size": auto, "time_s": dt,
           "reference": None, "reference_time_s": 0.0}
    if doe is not None:  # the bundled lens on axis, on the same pixels: what the DOE changes
        _, ref_size = fitting_patch(base, [fields[0]], wls, device=device)
        ref_size = min(ref_size, size)
        t = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", PatchWarning)  # its fraction in the patch is printed instead
            res["reference"] = psf_map(base, [fields[0]], wls, size=ref_size, device=device,
                                       batch=batch or len(wls), center_mm=tuple(centres[0]))
        res["reference_time_s"] = time.perf_counter() - t
    return res


def crop(a, n):
    """The central ``n`` x ``n`` samples of the last two axes (the patch centre stays at ``n // 2``)."""
    s = a.shape[-1]
    o = s // 2 - n // 2
    return a[..., o:o + n, o:o + n]


def doe_effect_figure(res, path):
    """On-axis PSFs without (the lens as given) and with the demo's DOE, one column per wavelength, log10,
    each column over the larger of its two peaks, with a colour bar; axes in um from the patch centre."""
    from .plots import _plt
    plt = _plt()
    ref, m = res["reference"], res["map"]
    n = ref.data.shape[-1]
    wls = m.wavelengths_um
    a = ref.data[0]
    b = crop(m.data[0], n)
    pix_um = m.pixel_mm * 1e3
    ext = [(-n // 2 - 0.5) * pix_um, (n - n // 2 - 0.5) * pix_um] * 2
    fig, axes = plt.subplots(2, len(wls), figsize=(2.3 * len(wls) + 0.9, 5.6), squeeze=False,
                             layout="constrained")
    for j, w in enumerate(wls):
        top = max(a[j].max(), b[j].max(), 1e-300)
        for r, (d, label) in enumerate(((a[j], "DOE as bundled (flat)"), (b[j], "demo DOE"))):
            ax = axes[r, j]
            im = ax.imshow(np.log10(np.maximum(d / top, 1e-6)), origin="lower", cmap="inferno", vmin=-6, vmax=0,
                           extent=ext)
            ax.set_title(f"{w:g} um, {label}\npeak {d.max():.3g} /px", fontsize=7)
            ax.tick_params(labelsize=6)
            ax.set_xlabel("x (um)", fontsize=7)
            if j == 0:
                ax.set_ylabel("y (um)", fontsize=7)
    cb = fig.colorbar(im, ax=axes, shrink=0.8, pad=0.02)
    cb.set_label("log10(power per pixel / larger peak of the column)", fontsize=7)
    cb.ax.tick_params(labelsize=6)
    d = res["doe"]
    fig.suptitle(f"on axis, {n} px of {pix_um:g} um: the DOE's quadratic phase a1 = {d['a1_rad']:.1f} rad "
                 f"(f = {d['doe_focal_length_mm']:.1f} mm at its design wavelength)\nper pixel: fraction of the power "
                 "entering the pupil; each column normalised to the larger of its two peaks", fontsize=8)
    fig.savefig(path, dpi=110)
    plt.close(fig)
