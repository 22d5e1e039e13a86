"""Short reprs and ``.plot()`` for the result classes (:class:`~rwwarp.psf.PSF`, :class:`~rwwarp.psf.PSFMap`,
:class:`~rwwarp.metrics.MTF`, :class:`~rwwarp.metrics.ThroughFocusMTF`, :class:`~rwwarp.metrics.energy.EnergyCurve`,
:class:`~rwwarp.metrics.strehl.Strehl`, :class:`~rwwarp.metrics.curves.ChromaticFocalShift`,
:class:`~rwwarp.metrics.curves.FieldCurves`).

A repr names the shape, the sampling and a few numbers, never the arrays themselves (``repr(strehl)`` used to
embed a whole PSF map). Every ``plot(path=None, ax=None)``: draws into ``ax`` (a matplotlib Axes) or a new
figure; with ``path`` it saves a PNG there (a backend-free Figure when no ``ax`` is given, so nothing opens
on screen) and returns the Figure; otherwise it returns the Axes. Lengths in mm (patch axes in um),
wavelengths in um, fields in deg, frequencies in lp/mm.
"""
from __future__ import annotations

import numpy as np

from .plots import field_label


def _nums(a, digits=4, limit=8) -> str:
    """A short text of an array: its values when few, else shape and range."""
    a = np.asarray(a, dtype=float)
    if a.size <= limit:
        return np.array2string(a, precision=digits, separator=", ", suppress_small=False).replace("\n", "")
    return f"<{'x'.join(map(str, a.shape))} array, {np.nanmin(a):.{digits}g}..{np.nanmax(a):.{digits}g}>"


def _fields(fields) -> str:
    fields = list(fields) if np.ndim(fields) else [fields]
    if len(fields) > 6:
        return f"[{field_label(fields[0])} .. {field_label(fields[-1])}, {len(fields)} fields]"
    return "[" + ", ".join(field_label(f) for f in fields) + "]"


def _wls(wls) -> str:
    wls = list(np.atleast_1d(wls))
    return "[" + ", ".join(f"{float(w):g}" for w in wls) + "] um"


def _figure(path, ax, nrows=1, ncols=1, size=(5.0, 4.0)):
    """(figure, axes array, made_here): ``ax`` given, else a backend-free Figure (``path``) or pyplot's."""
    if ax is not None:
        axes = np.atleast_1d(ax)
        return axes.flat[0].figure, axes.reshape(-1), False
    if path is not None:
        from matplotlib.figure import Figure
        fig = Figure(figsize=size, layout="constrained")
        axes = fig.subplots(nrows, ncols, squeeze=False)
    else:
        import matplotlib.pyplot as plt
        fig, axes = plt.subplots(nrows, ncols, squeeze=False, figsize=size, layout="constrained")
    return fig, axes.reshape(-1), True


def _done(fig, axes, path, dpi=110):
    if path is not None:
        fig.savefig(path, dpi=dpi, format="png")
        return fig
    return axes[0] if len(axes) == 1 else axes


# ---------------------------------------------------------------------------------------------- PSF
def psf_repr(p) -> str:
    n = p.data.shape[0]
    return (f"PSF({p.model}, field {field_label(p.field_deg)}, {float(p.wavelength_um):g} um: {n}x{n} px of "
            f"{p.pixel_mm * 1e3:.4g} um, centre ({p.center_mm[0]:.5f}, {p.center_mm[1]:.5f}) mm, "
            f"sum {float(p.data.sum()):.6g}, peak {float(p.data.max()):.4g})")


def _patch_image(ax, data, pixel_mm, log, title):
    n = data.shape[-1]
    pu = pixel_mm * 1e3
    ext = [(-(n // 2) - 0.5) * pu, (n - n // 2 - 0.5) * pu] * 2
    peak = max(float(data.max()), 1e-300)
    if log:
        im = ax.imshow(np.log10(np.maximum(data / peak, 1e-6)), origin="lower", cmap="inferno", vmin=-6, vmax=0,
                       extent=ext)
    else:
        im = ax.imshow(data / peak, origin="lower", cmap="inferno", vmin=0, vmax=1, extent=ext)
    ax.set_xlabel("x from the patch centre (um)", fontsize=8)
    ax.set_ylabel("y (um)", fontsize=8)
    ax.set_title(title, fontsize=8)
    ax.tick_params(labelsize=7)
    return im


def plot_psf(p, path=None, ax=None, log: bool = True):
    """Picture of a PSF patch normalised to its peak (log10 over 6 decades by default)."""
    fig, axes, made = _figure(path, ax, size=(5.0, 4.2))
    im = _patch_image(axes[0], p.data, p.pixel_mm, log,
                      f"{p.model} PSF, {field_label(p.field_deg)}, {float(p.wavelength_um):g} um\n"
                      f"{p.data.shape[0]} px of {p.pixel_mm * 1e3:.3g} um, centre ({p.center_mm[0]:.4f}, "
                      f"{p.center_mm[1]:.4f}) mm, peak {float(p.data.max()):.3g}")
    if made:
        fig.colorbar(im, ax=axes[0], label="log10(power / peak)" if log else "power / peak")
    return _done(fig, axes, path)


def psf_map_repr(m) -> str:
    nf, nw, n = m.data.shape[0], m.data.shape[1], m.data.shape[-1]
    return (f"PSFMap({m.model}, {nf} fields {_fields(m.fields_deg)} x {nw} wavelengths {_wls(m.wavelengths_um)}: "
            f"{n}x{n} px of {m.pixel_mm * 1e3:.4g} um)")


def plot_psf_map(m, path=None, log: bool = True):
    """Grid of the map's PSFs (fields across, wavelengths down), each normalised to its own peak."""
    nf, nw = m.data.shape[:2]
    fig, axes, _ = _figure(path, None, nrows=nw, ncols=nf, size=(2.3 * nf + 1.0, 2.2 * nw + 0.6))
    axes = axes.reshape(nw, nf)
    im = None
    for i in range(nf):
        for j in range(nw):
            im = _patch_image(axes[j, i], m.data[i, j], m.pixel_mm, log,
                              f"{field_label(m.fields_deg[i])}, {float(m.wavelengths_um[j]):g} um")
    fig.colorbar(im, ax=axes, shrink=0.85, label="log10(power / tile peak)" if log else "power / tile peak")
    return _done(fig, axes.reshape(-1), path)


# ---------------------------------------------------------------------------------------------- MTF
def _per_field(a, nf):
    a = np.asarray(a, float)
    return a.reshape(nf, -1) if a.ndim > 1 or nf == 1 else a.reshape(1, -1)


def mtf_repr(m) -> str:
    f = np.asarray(m.frequencies_lp_mm, float)
    return (f"MTF({m.model}, fields {_fields(m.fields_deg)}, {_wls(m.wavelengths_um)}: {f.size} frequencies "
            f"{f.min():g}..{f.max():g} lp/mm, cutoff {float(m.cutoff_lp_mm):.4g} lp/mm, tangential "
            f"{_nums(m.tangential, 3)}, sagittal {_nums(m.sagittal, 3)})")


def plot_mtf(m, path=None, ax=None):
    """Tangential (solid) and sagittal (dashed) MTF per field against frequency."""
    fig, axes, _ = _figure(path, ax)
    fields = list(m.fields_deg) if np.ndim(m.fields_deg) else [m.fields_deg]
    t, s = _per_field(m.tangential, len(fields)), _per_field(m.sagittal, len(fields))
    a = axes[0]
    for i, f in enumerate(fields):
        line, = a.plot(m.frequencies_lp_mm, t[i], label=f"{field_label(f)} T")
        a.plot(m.frequencies_lp_mm, s[i], "--", color=line.get_color(), label=f"{field_label(f)} S")
    a.set_xlabel("spatial frequency (lp/mm)")
    a.set_ylabel("MTF")
    a.set_ylim(0, 1.02)
    a.set_title(f"{m.model} MTF, {_wls(m.wavelengths_um)}", fontsize=9)
    a.legend(fontsize=7)
    return _done(fig, axes, path)


def through_focus_repr(m) -> str:
    z = np.asarray(m.focus_mm, float)
    return (f"ThroughFocusMTF({m.model}, fields {_fields(m.fields_deg)}, {_wls(m.wavelengths_um)}: {z.size} planes "
            f"{z.min() * 1e3:+.4g}..{z.max() * 1e3:+.4g} um, {np.size(m.frequencies_lp_mm)} frequencies)")


def plot_through_focus(m, path=None, ax=None):
    """Tangential / sagittal MTF at the first frequency against sensor shift (um), per field."""
    fig, axes, _ = _figure(path, ax)
    fields = list(m.fields_deg) if np.ndim(m.fields_deg) else [m.fields_deg]
    t = np.asarray(m.tangential, float).reshape(len(fields), np.size(m.focus_mm), -1)
    s = np.asarray(m.sagittal, float).reshape(len(fields), np.size(m.focus_mm), -1)
    a = axes[0]
    z = np.asarray(m.focus_mm) * 1e3
    for i, f in enumerate(fields):
        line, = a.plot(z, t[i, :, 0], label=f"{field_label(f)} T")
        a.plot(z, s[i, :, 0], "--", color=line.get_color(), label=f"{field_label(f)} S")
    a.set_xlabel("sensor shift (um, + away from the lens)")
    a.set_ylabel(f"MTF at {float(np.atleast_1d(m.frequencies_lp_mm)[0]):g} lp/mm")
    a.set_ylim(0, 1.02)
    a.legend(fontsize=7)
    return _done(fig, axes, path)


# ---------------------------------------------------------------------------------------------- energy, Strehl
def energy_repr(e) -> str:
    r = np.asarray(e.size_um, float)
    return (f"EnergyCurve({e.kind}, {e.model}, fields {_fields(e.fields_deg)}, {_wls(e.wavelengths_um)}: "
            f"{r.size} sizes {r.min():g}..{r.max():g} um, fraction {_nums(e.fraction, 3)})")


def plot_energy(e, path=None, ax=None):
    """Encircled / ensquared energy against radius / half width (um), per field."""
    fig, axes, _ = _figure(path, ax)
    fields = list(e.fields_deg) if np.ndim(e.fields_deg) else [e.fields_deg]
    fr = _per_field(e.fraction, len(fields))
    for i, f in enumerate(fields):
        axes[0].plot(e.size_um, fr[i], label=field_label(f))
    axes[0].set_xlabel("radius (um)" if e.kind == "encircled" else "half width (um)")
    axes[0].set_ylabel(f"{e.kind} energy (fraction)")
    axes[0].set_ylim(0, 1.02)
    axes[0].legend(fontsize=7)
    return _done(fig, axes, path)


def strehl_repr(s) -> str:
    return (f"Strehl({s.model}, fields {_fields(s.fields_deg)}, {_wls(s.wavelengths_um)}: ratio "
            f"{_nums(s.ratio)})")


def plot_strehl(s, path=None, ax=None):
    """Strehl ratio against field, one line per wavelength."""
    fig, axes, _ = _figure(path, ax)
    fields = list(s.fields_deg) if np.ndim(s.fields_deg) else [s.fields_deg]
    wls = list(np.atleast_1d(s.wavelengths_um))
    r = np.asarray(s.ratio, float).reshape(len(fields), len(wls))
    y = [np.hypot(*f) if np.ndim(f) else float(f) for f in fields]
    for j, w in enumerate(wls):
        axes[0].plot(y, r[:, j], "o-", label=f"{float(w):g} um")
    axes[0].set_xlabel("field (deg)")
    axes[0].set_ylabel("Strehl ratio")
    axes[0].set_ylim(0, 1.05)
    axes[0].legend(fontsize=7)
    return _done(fig, axes, path)


# ---------------------------------------------------------------------------------------------- ray curves
def focal_shift_repr(c) -> str:
    sh = np.asarray(c.shift_um, float)
    return (f"ChromaticFocalShift({np.size(c.wavelengths_um)} wavelengths {np.min(c.wavelengths_um):g}.."
            f"{np.max(c.wavelengths_um):g} um, reference {float(c.reference_um):g} um: shift {sh.min():+.4g}.."
            f"{sh.max():+.4g} um)")


def plot_focal_shift(c, path=None, ax=None):
    """Paraxial focal shift (um) against wavelength (um)."""
    fig, axes, _ = _figure(path, ax)
    axes[0].plot(c.shift_um, c.wavelengths_um)
    axes[0].set_xlabel("focal shift (um, + away from the lens)")
    axes[0].set_ylabel("wavelength (um)")
    return _done(fig, axes, path)


def field_curves_repr(c) -> str:
    f = np.asarray(c.fields_deg, float)
    return (f"FieldCurves({f.size} fields {f.min():g}..{f.max():g} deg, {float(c.wavelength_um):g} um: distortion "
            f"{np.nanmin(c.distortion_percent):+.3g}..{np.nanmax(c.distortion_percent):+.3g} %)")


def plot_field_curves(c, path=None, ax=None):
    """Field curvature (tangential, sagittal; um) and distortion (%) against field (deg), side by side."""
    fig, axes, made = _figure(path, ax, ncols=2, size=(8.0, 3.8))
    axes[0].plot(np.asarray(c.tangential_mm) * 1e3, c.fields_deg, label="tangential")
    axes[0].plot(np.asarray(c.sagittal_mm) * 1e3, c.fields_deg, "--", label="sagittal")
    axes[0].set_xlabel("focus from the sensor (um)")
    axes[0].set_ylabel("field (deg)")
    axes[0].legend(fontsize=7)
    if len(axes) > 1:
        axes[1].plot(c.distortion_percent, c.fields_deg)
        axes[1].set_xlabel("distortion (%)")
    return _done(fig, axes, path)
