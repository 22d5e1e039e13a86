"""From a field-varying PSF map to a simulated image.

The A489 hybrid lens (bundled) images a synthetic scene (a star chart and bars, in RGB). A ray-wave
:func:`rwwarp.psf_map` is computed at ``--n-fields`` fields from 0 to the sensor's half height along +y, at
the lens's three wavelengths. The image is a vertical strip of the sensor (``--width`` x the full height, in
sensor pixels): each colour channel is convolved with the PSF of every field, and the results are blended
with hat weights in image height (linear interpolation of the PSF between neighbouring fields, the usual
space-variant convolution by PSF interpolation). Below the axis the PSF is the one of the mirrored field
(the lens is rotationally symmetric): flipped in y. Each wavelength's PSF is shifted by the offset of its
chief ray from the middle wavelength's, so lateral colour shows. Written to ``--out``: ``scene.png``,
``simulated.png`` (both sRGB-ish, gamma 1/2.2), ``psf_map.png`` and ``psf_map.npz``.

    python examples/psf_map_image_simulation.py [--out out/examples/psf_map_image_simulation] [--device cpu]

Units: lengths in mm (pixel pitch 1 um), wavelengths in um, fields in deg. About 15 s on 2 CPU cores.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy.signal import fftconvolve

import rwwarp as rw


def scene(ny: int, nx: int) -> np.ndarray:
    """(ny, nx, 3) test scene in [0, 1]: a star chart every 400 px along y and coloured bars between."""
    y, x = np.mgrid[0:ny, 0:nx].astype(float)
    img = np.zeros((ny, nx, 3))
    for cy in np.arange(200, ny, 400):
        r = np.hypot(x - nx / 2, y - cy)
        star = (np.sin(24 * np.arctan2(y - cy, x - nx / 2)) > 0) & (r < 0.45 * nx)
        img[star] = 1.0
        band = (np.abs(y - cy - 200) < 60)
        bars = band & ((x // 12) % 2 == 0)
        img[bars] = [1.0, 0.3, 0.1] if (cy // 400) % 2 else [0.2, 0.5, 1.0]
    return img


def blend_weights(y_mm, centres_mm):
    """Hat weights (n_fields, len(y_mm)) in |y| over the sorted field centres (sum 1 at every height)."""
    c = np.asarray(centres_mm, float)
    w = np.zeros((len(c), len(y_mm)))
    ay = np.clip(np.abs(y_mm), c[0], c[-1])
    k = np.clip(np.searchsorted(c, ay) - 1, 0, len(c) - 2)
    t = (ay - c[k]) / (c[k + 1] - c[k])
    w[k, np.arange(len(ay))] = 1 - t
    w[k + 1, np.arange(len(ay))] += t
    return w


def simulate(img, m, pixel_mm):
    """Space-variant blur of ``img`` (ny, nx, 3; rows = +y downwards as an image, row 0 at the top) by the PSF map
    ``m`` (fields along +y, three wavelengths; channel c <- wavelength index 2 - c, red = longest)."""
    ny, nx, _ = img.shape
    y_mm = (ny / 2 - 0.5 - np.arange(ny)) * pixel_mm  # row centres, + up
    ref = m.centers_mm[:, 1, 1]  # middle wavelength's chief-ray heights, mm
    w = blend_weights(y_mm, ref)
    out = np.zeros_like(img)
    for c in range(3):
        j = 2 - c
        for i in range(len(ref)):
            k = m.data[i, j][::-1]  # rows as the image's: +y at the top
            shift = int(round((m.centers_mm[i, j, 1] - ref[i]) / pixel_mm))  # lateral colour, px (+ up)
            k = np.pad(k, ((max(-shift, 0) * 2, max(shift, 0) * 2), (0, 0)))  # keeps the centre where the PSF is
            up = fftconvolve(img[..., c], k, mode="same")
            down = fftconvolve(img[..., c], k[::-1], mode="same")  # the mirrored field below the axis
            out[..., c] += w[i][:, None] * np.where((y_mm >= 0)[:, None], up, down)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/examples/psf_map_image_simulation", help="output folder")
    ap.add_argument("--device", default="cpu", help="cpu or cuda")
    ap.add_argument("--n-fields", type=int, default=4, help="fields from 0 to the sensor's half height")
    ap.add_argument("--width", type=int, default=256, help="strip width, sensor pixels")
    ap.add_argument("--size", type=int, default=128, help="PSF patch, sensor pixels (128 holds >= 95 % of each)")
    a = ap.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)

    lens = rw.load_lens("a489_doe")
    pixel = lens.sensor.pixel_pitch
    half_h = lens.sensor.half_size[1]
    wl = lens.wavelengths_um
    fmax = float(np.degrees(np.arctan(half_h / lens.efl(wl[1]))))
    fields = list(np.round(np.linspace(0.0, fmax, a.n_fields), 3))
    m = rw.psf_map(lens, fields, wl, size=a.size, device=a.device)
    print(m)
    m.plot(path=out / "psf_map.png")
    np.savez(out / "psf_map.npz", psf=m.data, centers_mm=m.centers_mm, pixel_mm=m.pixel_mm,
             fields_deg=np.asarray(fields, float), wavelengths_um=np.asarray(wl, float))

    ny = lens.sensor.resolution[1]
    img = scene(ny, a.width)
    sim = simulate(img, m, pixel)
    # a ray-wave PSF holds the power that reaches the patch (< 1): the image keeps that loss
    print(f"scene {img.shape[1]} x {img.shape[0]} px of {pixel * 1e3:g} um; power kept per channel (R, G, B): "
          + ", ".join(f"{sim[..., c].sum() / img[..., c].sum():.3f}" for c in range(3)))
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    for name, im in (("scene", img), ("simulated", sim)):
        plt.imsave(out / f"{name}.png", np.clip(im, 0, 1) ** (1 / 2.2))
    print(f"wrote {out}/scene.png, simulated.png, psf_map.png, psf_map.npz")


if __name__ == "__main__":
    main()
