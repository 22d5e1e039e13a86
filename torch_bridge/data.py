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

Named image sets (:data:`IMAGE_SETS`) are written into a folder by :func:`fetch_image_set`
(``rwwarp design fetch-data NAME``) with the ``root/train``, ``root/valid`` layout and a
``MANIFEST.json`` (sources, licences, sha256); ``data.root`` then names that folder, and
:class:`ImageSet` checks that every file of the manifest's split is there. ``debian-photos``: 22
photographs (1280 x 1024 to 2560 x 1920 px) from two Debian packages, ``mate-backgrounds`` (GPL-2+)
and ``plasma-workspace-wallpapers`` (LGPL-3), fixed split 18 train / 4 valid, 12.6 MB of JPEG.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

__all__ = ["IMAGE_SETS", "SKIMAGE_TRAIN", "SKIMAGE_VALID", "ImageSet", "fetch_image_set", "load_image",
           "srgb_to_linear"]

# sample images bundled with scikit-image (files in skimage/data, no download)
SKIMAGE_TRAIN = ["astronaut.png", "coffee.png", "rocket.jpg", "ihc.png", "hubble_deep_field.jpg", "retina.jpg",
                 "motorcycle_left.png", "camera.png", "brick.png", "grass.png", "gravel.png", "moon.png",
                 "page.png", "text.png"]
SKIMAGE_VALID = ["chelsea.png", "motorcycle_right.png", "coins.png", "color.png"]
# Named image sets obtainable from package registries. Per image: (name, package, path in the package,
# sha256, bytes, licence, author, split). The split is fixed here (the valid images are chosen to span
# the subjects: landscape, macro, evening scene, forest); the sha256 pins the package versions below.
_MATE = "usr/share/backgrounds/mate/nature/"
_KDE = "usr/share/wallpapers/{}/contents/images/2560x1600.jpg"
IMAGE_SETS = {
    "debian-photos": {
        "description": "photographs from Debian's mate-backgrounds (GPL-2+) and plasma-workspace-wallpapers "
                       "(LGPL-3) packages",
        "packages": {"mate-backgrounds": "1.26.0-1", "plasma-workspace-wallpapers": "4:5.27.5-2"},
        "images": [
            ("Aqua", "mate-backgrounds", _MATE + "Aqua.jpg",
             "5c30118205982da441bf7e6a1ada636a8a0be879408140b3148280c665ed6bce", 200353, "GPL-2+", "Charles Barbin", "train"),
            ("Blinds", "mate-backgrounds", _MATE + "Blinds.jpg",
             "f7aac0dcc2e06d0491643e84df3da1d9db7c4610f58806a880d56e074799f600", 1157513, "GPL-2+",
             "Lennart Poettering, Andrea Cimitan", "train"),
            ("Dune", "mate-backgrounds", _MATE + "Dune.jpg",
             "8a67c2cb0be8c46b70c237311a4fa4d2b4ac7d39568135384787801fa5cc9a91", 1021283, "GPL-2+",
             "Marco Cogoni, Hylke Bons", "train"),
            ("FreshFlower", "mate-backgrounds", _MATE + "FreshFlower.jpg",
             "972b0a0c4e5e3fa93f4f244fc84bc64b121a5eac3aaa5856f1308c1f38a02f8e", 80905, "GPL-2+", "Jens Ansorg", "train"),
            ("Garden", "mate-backgrounds", _MATE + "Garden.jpg",
             "d3095ee09d425ef23d27155412136cf14fc3c9af76ca58b452f55e23da324e78", 264831, "GPL-2+", "Charles Barbin", "train"),
            ("GreenMeadow", "mate-backgrounds", _MATE + "GreenMeadow.jpg",
             "8fa0de0aa4089f7319c9fb7a6d006d4cab6023e8c8853731557cff53567b4832", 183377, "GPL-2+",
             "Timothy Schellhase, Lapo Calamandrei", "train"),
            ("LadyBird", "mate-backgrounds", _MATE + "LadyBird.jpg",
             "e35a9a4126ef969c90b29c038058c5a575a20eadd84106a37bf1fa9931e7b61d", 351588, "GPL-2+", "Charles Barbin", "valid"),
            ("RainDrops", "mate-backgrounds", _MATE + "RainDrops.jpg",
             "3e4ea9671c28c90a86cf67b3db9daf18c4741587c596333a7529ca589aaa0c16", 1242241, "GPL-2+", "blackcombwhistler07",
             "train"),
            ("Storm", "mate-backgrounds", _MATE + "Storm.jpg",
             "77ca53077831d3237f73393a91fc879158abc046d852941c26e90de336356957", 695070, "GPL-2+", "Sergey Nazarov", "valid"),
            ("TwoWings", "mate-backgrounds", _MATE + "TwoWings.jpg",
             "665e5abf8a5399070a91a9a8e455fe071e5b61697ff78fdeda4e9843ef545aeb", 881400, "GPL-2+", "Charles Barbin", "train"),
            ("Wood", "mate-backgrounds", _MATE + "Wood.jpg",
             "19c78500ac00a622e19907ab9cc7d06d46fe08c4a6142759a84195696150ec07", 525520, "GPL-2+",
             "Jean-Francois Fortin Tam", "train"),
            ("YellowFlower", "mate-backgrounds", _MATE + "YellowFlower.jpg",
             "254da96256acb7add685679775a04d1e4a5bc8cd13e5a5a3d61351ce198a5306", 267440, "GPL-2+", "Charles Barbin", "train"),
            ("BytheWater", "plasma-workspace-wallpapers", _KDE.format("BytheWater"),
             "c272434ef39f2abf1ed48a15a8910088020f3165329a5092f3940ec9464bc05f", 494563, "LGPL-3", "Maciej Wiklo", "train"),
            ("ColdRipple", "plasma-workspace-wallpapers", _KDE.format("ColdRipple"),
             "05bef6722fc0ed81292cceb3ed026c38d17e510f3c84be7d68610c2b1a723c3f", 526600, "LGPL-3", "Risto Saukonpaa", "train"),
            ("ColorfulCups", "plasma-workspace-wallpapers", _KDE.format("ColorfulCups"),
             "6e0f3a72feb5a4a9fec191b77e34874c3c69e2d93040deb3f07773e73385023d", 698472, "LGPL-3", "Dmitri Popov", "train"),
            ("DarkestHour", "plasma-workspace-wallpapers", _KDE.format("DarkestHour"),
             "8e3703fae3a3c217b1fc2b399b706cd3720584268d071ba153e4809daa55f1ce", 318080, "LGPL-3", "Risto Saukonpaa", "train"),
            ("EveningGlow", "plasma-workspace-wallpapers", _KDE.format("EveningGlow"),
             "586682dcb362b9f620068f10138f87d0d3649939aef238adc5807cb951976a7a", 632699, "LGPL-3", "Ian Hex", "valid"),
            ("FallenLeaf", "plasma-workspace-wallpapers", _KDE.format("FallenLeaf"),
             "95603a6560c7e8d50e0e03b3f4adbe39c5258c72528e74e4ecaea1daf4e499de", 543137, "LGPL-3", "Martin Klapetek", "train"),
            ("Grey", "plasma-workspace-wallpapers", _KDE.format("Grey"),
             "88c31d8944b7e6935d1b9a296654c692f0772cb512491713eb30a972a604c0ed", 234512, "LGPL-3", "Sigi Sagi", "train"),
            ("OneStandsOut", "plasma-workspace-wallpapers", _KDE.format("OneStandsOut"),
             "cb507baf1dafdcae362264f3aba9483ed4be5f6c9fdd770f0ec0920c6d9e80fd", 892075, "LGPL-3", "Risto Saukonpaa", "train"),
            ("Path", "plasma-workspace-wallpapers", _KDE.format("Path"),
             "7477457d7f17b736259f1b021864778ad4ba802cf3214e6728181ff29126bba8", 910087, "LGPL-3", "Risto Saukonpaa", "valid"),
            ("summer_1am", "plasma-workspace-wallpapers", _KDE.format("summer_1am"),
             "c868b50789591dd42910153c768053f1ba0a98cb36bbfc2b7a96a1045d0477f8", 442791, "LGPL-3", "Risto Saukonpaa", "train"),
        ],
    },
}
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
            if (root / "MANIFEST.json").exists():
                import json
                man = json.loads((root / "MANIFEST.json").read_text())
                _check_manifest(root, man, split)
                files = sorted(root / f for f in man[split])
            else:
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
        # the crops are cut and flipped as numpy views and copied once (torch's CPU flip of a strided view costs
        # ~10-50 ms a 256 px crop, numpy's reversed slice ~1 ms: 0.23 s of an H100 design step went here); the
        # generator's draws and the values are those of cutting and flipping with torch
        out = np.empty((batch_size, 3, self.crop, self.crop), dtype=np.float32)
        idx = torch.multinomial(self.prob, batch_size, replacement=True, generator=generator)
        for b, i in enumerate(idx.tolist()):
            im = self.images[i].numpy()
            H, W = im.shape[1:]
            y = int(torch.randint(H - self.crop + 1, (1,), generator=generator))
            x = int(torch.randint(W - self.crop + 1, (1,), generator=generator))
            c = im[:, y:y + self.crop, x:x + self.crop]
            flips = torch.rand(2, generator=generator)
            if flips[0] < 0.5:
                c = c[:, :, ::-1]
            if flips[1] < 0.5:
                c = c[:, ::-1, :]
            out[b] = c
        return torch.from_numpy(out)

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


# ============================================================================================== named sets
def _deb_members(deb: Path, wanted: set) -> dict:
    """Bytes of the files ``wanted`` (paths without a leading ``./``) in the data archive of the Debian
    package ``deb`` (an ``ar`` archive holding ``data.tar.{xz,gz,zst,bz2,}``; symbolic links inside
    it are followed). Read in Python: no dpkg needed. ValueError when ``deb`` is not a Debian package."""
    import io
    import posixpath
    import tarfile
    raw = Path(deb).read_bytes()
    if not raw.startswith(b"!<arch>\n"):
        raise ValueError(f"{deb}: not a Debian package (no ar header)")
    pos, data = 8, None
    while pos + 60 <= len(raw):
        name = raw[pos:pos + 16].decode().strip().rstrip("/")
        size = int(raw[pos + 48:pos + 58].decode().strip())
        body = raw[pos + 60:pos + 60 + size]
        if name.startswith("data.tar"):
            data = (name, body)
            break
        pos += 60 + size + (size % 2)
    if data is None:
        raise ValueError(f"{deb}: no data.tar member")
    name, body = data
    if name.endswith(".zst"):
        try:
            import zstandard
        except ImportError:
            raise ValueError(f"{deb}: its data is zstd-compressed; install the 'zstandard' package") from None
        body = zstandard.ZstdDecompressor().stream_reader(io.BytesIO(body)).read()
    tf = tarfile.open(fileobj=io.BytesIO(body), mode="r:*")
    members = {m.name.lstrip("./"): m for m in tf.getmembers()}
    out = {}
    for w in wanted:
        m, hops = members.get(w), 0
        while m is not None and m.issym() and hops < 8:
            target = posixpath.normpath(posixpath.join(posixpath.dirname(m.name.lstrip("./")), m.linkname))
            m, hops = members.get(target.lstrip("./")), hops + 1
        if m is not None and m.isfile():
            out[w] = tf.extractfile(m).read()
    return out


def fetch_image_set(name: str, dest, debs=None, table: dict | None = None) -> dict:
    """Write the named image set ``name`` (a key of :data:`IMAGE_SETS`) into the folder ``dest``:
    ``dest/train/<image>.jpg``, ``dest/valid/<image>.jpg`` and ``dest/MANIFEST.json`` (package versions,
    per image its source path, licence, author, sha256, bytes and split). Returns the manifest.

    ``debs``: paths of the set's Debian packages already downloaded; default: ``apt-get download
    PACKAGE=VERSION`` into a temporary folder (needs a Debian/Ubuntu machine with network; the GPU
    machines have none: fetch here and send the folder, ~13 MB). Every image's sha256 must match the
    table (ValueError naming the image and package otherwise). Written atomically: ``dest`` appears
    complete or not at all; an existing ``dest`` with the same manifest is kept as it is.
    ``table``: another set description of the same form (tests)."""
    import hashlib
    import json
    import shutil
    import subprocess
    import tempfile
    spec = table or IMAGE_SETS.get(name)
    if spec is None:
        raise ValueError(f"no image set {name!r}; known: {sorted(IMAGE_SETS)}")
    dest = Path(dest)
    man_path = dest / "MANIFEST.json"
    if man_path.exists():
        old = json.loads(man_path.read_text())
        if old.get("name") == name and old.get("packages") == spec["packages"]:
            _check_manifest(dest, old)
            return old
        raise ValueError(f"{dest} holds another image set ({old.get('name')!r}); choose another folder")
    if dest.exists() and any(dest.iterdir()):
        raise ValueError(f"{dest} exists and is not empty; choose another folder")
    with tempfile.TemporaryDirectory(prefix="rwwarp-fetch-") as tmp:
        if debs is None:
            if shutil.which("apt-get") is None:
                raise RuntimeError("apt-get is not available here: download the packages "
                                   f"{sorted(spec['packages'])} on a Debian machine and pass them with --debs")
            debs = []
            for pkg, ver in spec["packages"].items():
                r = subprocess.run(["apt-get", "download", f"{pkg}={ver}"], cwd=tmp, capture_output=True, text=True)
                if r.returncode != 0:
                    raise RuntimeError(f"apt-get download {pkg}={ver} failed: {r.stderr.strip()[-400:]}")
            debs = sorted(Path(tmp).glob("*.deb"))
        by_pkg = {}
        for d in debs:
            d = Path(d)
            if not d.is_file():
                raise FileNotFoundError(f"--debs: {d} is not a file")
            pkg = d.name.split("_")[0]
            if pkg in spec["packages"]:
                by_pkg[pkg] = d
        missing = sorted(set(spec["packages"]) - set(by_pkg))
        if missing:
            raise FileNotFoundError(f"image set {name!r}: no .deb given for {missing} (given: {[str(d) for d in debs]})")
        # staged beside ``dest`` (same file system: the final rename is atomic); its parents are made here
        dest.parent.mkdir(parents=True, exist_ok=True)
        stage = Path(tempfile.mkdtemp(prefix=f".{dest.name}.", dir=dest.parent))
        try:
            for sub in ("train", "valid"):
                (stage / sub).mkdir()
            rows, total = [], 0
            for pkg, deb in by_pkg.items():
                imgs = [r for r in spec["images"] if r[1] == pkg]
                got = _deb_members(deb, {r[2] for r in imgs})
                for (iname, _, path, sha, size, lic, author, split) in imgs:
                    b = got.get(path)
                    if b is None:
                        raise ValueError(f"{deb.name}: has no {path} (image {iname!r}; expected package version "
                                         f"{spec['packages'][pkg]})")
                    if hashlib.sha256(b).hexdigest() != sha or len(b) != size:
                        raise ValueError(f"{deb.name}: image {iname!r} ({path}) differs from the pinned one "
                                         f"(sha256; expected package {pkg} {spec['packages'][pkg]})")
                    ext = Path(path).suffix.lower()
                    (stage / split / f"{iname}{ext}").write_bytes(b)
                    rows.append({"image": iname, "file": f"{split}/{iname}{ext}", "package": pkg, "path": path,
                                 "sha256": sha, "bytes": size, "licence": lic, "author": author, "split": split})
                    total += size
            man = {"name": name, "description": spec.get("description", ""), "packages": spec["packages"],
                   "bytes": total, "images": rows,
                   "train": [r["file"] for r in rows if r["split"] == "train"],
                   "valid": [r["file"] for r in rows if r["split"] == "valid"]}
            (stage / "MANIFEST.json").write_text(json.dumps(man, indent=1))
            if dest.exists():
                dest.rmdir()
            stage.replace(dest)
        except BaseException:
            shutil.rmtree(stage, ignore_errors=True)
            raise
    man["root"] = str(dest)
    return man


def _check_manifest(root: Path, man: dict, split: str | None = None) -> None:
    """FileNotFoundError naming the first file of ``man`` (of ``split``, or all) missing under ``root``
    or of the wrong size."""
    for r in man.get("images", []):
        if split is not None and r["split"] != split:
            continue
        f = root / r["file"]
        if not f.is_file() or f.stat().st_size != r["bytes"]:
            raise FileNotFoundError(f"image set {man.get('name')!r} in {root}: {r['file']} is missing or incomplete "
                                    f"(fetch it again: rwwarp design fetch-data {man.get('name')} --out <new folder>)")
