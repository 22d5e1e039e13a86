"""Training images: a folder of images (DIV2K layout) or, offline by default, scikit-image's
bundled sample photographs; random crops and flips drawn from a ``torch.Generator`` (so a run is
reproducible and can be resumed exactly).

Folder layouts accepted for ``root`` (first match wins, for split ``"train"`` / ``"valid"``)::

    root/DIV2K_train_HR/*.png   root/DIV2K_valid_HR/*.png     (the DIV2K download, unpacked)
    root/train/*                root/valid/*                  (any image files)
    root/*                      (one folder: the last ``valid_fraction`` of the sorted files are "valid")

Pixel values are floats in [0, 1] (sRGB code values / 255, or linearised with ``linearize=True``);
grey images are repeated to three channels and an alpha channel is dropped. Nothing is downloaded:
only the sample images that ship inside the scikit-image wheel are used when ``root`` is None.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

__all__ = ["SKIMAGE_TRAIN", "SKIMAGE_VALID", "ImageSet", "load_image", "srgb_to_linear"]

# sample images bundled with scikit-image (files in skimage/data, no download)
SKIMAGE_TRAIN = ["astronaut.png", "coffee.png", "rocket.jpg", "ihc.png", "hubble_deep_field.jpg", "retina.jpg",
                 "motorcycle_left.png", "camera.png", "brick.png", "grass.png", "gravel.png", "moon.png",
                 "page.png", "text.png"]
SKIMAGE_VALID = ["chelsea.png", "motorcycle_right.png", "coins.png", "color.png"]
_EXT = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp"}


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """Inverse sRGB transfer curve (IEC 61966-2-1), values in [0, 1]."""
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def load_image(path, scale: float = 1.0, linearize: bool = False) -> np.ndarray:
    """Read an image file as float32 (H, W, 3) in [0, 1]; ``scale`` < 1 downsamples it (anti-aliased)."""
    from skimage import io, transform
    img = io.imread(str(path))
    if img.dtype == bool:
        img = img.astype(np.uint8) * 255
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    if img.shape[2] == 4:
        img = img[..., :3]
    if img.shape[2] == 1:
        img = np.repeat(img, 3, axis=2)
    maxval = 65535.0 if img.dtype == np.uint16 else (255.0 if np.issubdtype(img.dtype, np.integer) else 1.0)
    out = img.astype(np.float64) / maxval
    if scale != 1.0:
        out = transform.rescale(out, scale, channel_axis=2, anti_aliasing=scale < 1.0, order=1)
    out = np.clip(out, 0.0, 1.0)
    if linearize:
        out = srgb_to_linear(out)
    return out.astype(np.float32)


def _files_for(root: Path, split: str, valid_fraction: float):
    for name in (f"DIV2K_{split}_HR", split):
        d = root / name
        if d.is_dir():
            files = sorted(p for p in d.iterdir() if p.suffix.lower() in _EXT)
            if files:
                return files
    files = sorted(p for p in root.iterdir() if p.suffix.lower() in _EXT)
    if not files:
        raise FileNotFoundError(f"no images in {root} (looked for DIV2K_{split}_HR/, {split}/ and image files)")
    n_valid = max(1, round(valid_fraction * len(files))) if len(files) > 1 else 0
    return files[len(files) - n_valid:] if split == "valid" else files[:len(files) - n_valid] or files


class ImageSet:
    """Images of one split, held in memory, with reproducible random crops.

    Parameters
    ----------
    root : path or None
        Folder (layouts in the module docstring); None: scikit-image's bundled samples.
    split : "train" | "valid"
    crop : int
        Crop size in pixels (square).
    scale : float
        Resampling factor applied when loading (e.g. 0.5 halves DIV2K's 2K images).
    max_images : int, optional
        Use at most this many files (sorted order).
    linearize : bool
        Convert sRGB code values to linear intensity (what a sensor integrates).
    """

    def __init__(self, root=None, split: str = "train", crop: int = 64, scale: float = 1.0,
                 max_images: int | None = None, linearize: bool = False, valid_fraction: float = 0.1):
        if split not in ("train", "valid"):
            raise ValueError(f"split must be 'train' or 'valid', got {split!r}")
        if crop < 1:
            raise ValueError(f"crop must be >= 1, got {crop}")
        if root is None:
            import skimage.data
            base = Path(skimage.data.__file__).parent
            names = SKIMAGE_TRAIN if split == "train" else SKIMAGE_VALID
            files = [base / n for n in names if (base / n).exists()]
            if not files:
                raise FileNotFoundError(f"scikit-image sample images not found in {base}")
        else:
            root = Path(root)
            if not root.is_dir():
                raise FileNotFoundError(f"data root {root} is not a folder")
            files = _files_for(root, split, valid_fraction)
        if max_images is not None:
            files = files[:int(max_images)]
        self.files = files
        self.crop = int(crop)
        self.images = []
        for f in files:
            img = load_image(f, scale, linearize)
            if min(img.shape[:2]) < self.crop:
                # small images are upsampled so that one crop fits
                from skimage import transform
                s = self.crop / min(img.shape[:2])
                img = np.clip(transform.rescale(img, s * 1.0001, channel_axis=2, order=1), 0, 1).astype(np.float32)
            self.images.append(torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1))))
        # sample images in proportion to their area (every pixel equally likely)
        area = np.array([im.shape[1] * im.shape[2] for im in self.images], dtype=np.float64)
        self.prob = torch.from_numpy(area / area.sum())

    def __len__(self):
        return len(self.images)

    def __getitem__(self, i) -> torch.Tensor:
        """The whole image ``i`` as a (3, H, W) float32 tensor."""
        return self.images[i]

    def sample(self, batch_size: int, generator: torch.Generator) -> torch.Tensor:
        """``batch_size`` random crops (B, 3, crop, crop), each from an image drawn in proportion to its
        area, at a uniform random position, flipped left-right and up-down with probability 1/2 each."""
        out = torch.empty(batch_size, 3, self.crop, self.crop)
        idx = torch.multinomial(self.prob, batch_size, replacement=True, generator=generator)
        for b, i in enumerate(idx.tolist()):
            im = self.images[i]
            H, W = im.shape[1:]
            y = int(torch.randint(H - self.crop + 1, (1,), generator=generator))
            x = int(torch.randint(W - self.crop + 1, (1,), generator=generator))
            c = im[:, y:y + self.crop, x:x + self.crop]
            flips = torch.rand(2, generator=generator)
            if flips[0] < 0.5:
                c = c.flip(-1)
            if flips[1] < 0.5:
                c = c.flip(-2)
            out[b] = c
        return out

    def fixed_crops(self, n: int, seed: int = 1234) -> torch.Tensor:
        """``n`` crops that do not depend on any training state (evaluation set): a generator seeded with
        ``seed``, no flips."""
        g = torch.Generator().manual_seed(int(seed))
        out = torch.empty(n, 3, self.crop, self.crop)
        for b in range(n):
            im = self.images[b % len(self.images)]
            H, W = im.shape[1:]
            y = int(torch.randint(H - self.crop + 1, (1,), generator=g))
            x = int(torch.randint(W - self.crop + 1, (1,), generator=g))
            out[b] = im[:, y:y + self.crop, x:x + self.crop]
        return out
