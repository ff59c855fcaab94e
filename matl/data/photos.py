"""``data=images``: canonical images from the user's photos (or renders) of each plane.

Layout (``docs/datasets.md``)::

    <root>/<object>/<plane>.png            one canonical photo per plane (any image format)
    <root>/<object>/<plane>/<k>.png        N photographed anchors of a plane

Every non-hidden file inside an object folder must be an image: a corrupt or non-image file, or an
object folder without images, is a one-line error naming it. Files directly in ``<root>`` (a
manifest, a README) are ignored.

**Foreground.** An image with an alpha channel is cut out by its alpha (> 0.5). Without alpha the
object is segmented from a *uniform* background (:func:`segment_foreground`): the background
colour is the median of a thin frame along the image border; pixels farther than a threshold from
it (Euclidean RGB distance, threshold = max(``min_threshold``, median + 4 robust sigmas of the
frame's own distances)) are foreground; a 3x3 opening removes speckle, the largest connected
component is kept and its holes are filled (print in the background's colour inside the object
stays foreground). Then, as the synthetic catalog frames its renders, the object's bounding box is
scaled so its larger side spans ``fill`` of the image and centred; the background is set to 0.

**Photographed anchors.** A plane folder's images are its N anchors, in numeric/name order; the
first (or the one named ``0``) is also the plane's canonical image. Their ``anchor_H_canon`` is
not measured, so:

* ``anchor_names: angle``: files are named by the in-plane rotation in degrees of that photo
  relative to the canonical one (``000.png``, ``090.png``...), as with a turntable;
  ``anchor_H_canon`` is that rotation about the image centre, so poses are relative to the
  canonical image as for rotated anchors. Each anchor photo keeps the canonical photo's scale (mask
  area matched) and its object centre is put where the rotation sends the canonical's.
* ``anchor_names: index`` (default): ``anchor_H_canon`` is the identity for every anchor. A
  predicted pose is then relative to *the selected anchor's own frame*: ``query_H_canon`` reads
  "query from anchor k's photo", not from the canonical image. Use it for recognition, or for poses
  when you know which anchor was chosen (``predict`` reports it).

Anchors come from :class:`matl.data.anchors.PhotoAnchors` (the ``images`` data config selects
it); planes without a plane folder get the ``fallback`` acquisition (the top-level ``anchors``,
fixed rotations by default). Files are read by :func:`matl.data.image_files.read_rgba`, the reader
``matl.predict`` uses too (16-bit grey images included).
"""

from __future__ import annotations

import hashlib
import logging
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image
from scipy import ndimage

from matl.data.anchors import PhotoAnchors  # noqa: F401  (the _target_ of run configs saved before it moved)
from matl.data.canonical import CanonicalSet, ProgressFn
from matl.data.image_files import ImageFileError, read_rgba
from matl.data.meshes.manifest import Manifest
from matl.geometry import centre_rotation
from matl.utils.errors import MatlError

log = logging.getLogger(__name__)

PHOTO_SOURCE_VERSION = 1
ANCHOR_NAMES = ("index", "angle")


@dataclass(frozen=True)
class Segmentation:
    """Uniform-background segmentation settings (see the module docstring).

    Attributes:
        border: width of the frame sampled for the background colour, fraction of the shorter side.
        min_threshold: smallest RGB distance (0-1 scale, max sqrt(3)) that counts as foreground.
        sigmas: robust standard deviations of the frame's distances added above their median.
        min_area: smallest foreground, as a fraction of the image, below which it is an error.
    """

    border: float = 0.03
    min_threshold: float = 0.12
    sigmas: float = 4.0
    min_area: float = 0.002


def segment_foreground(rgb: np.ndarray, settings: Segmentation | None = None) -> np.ndarray:
    """Foreground mask (H, W) bool of an object photographed on a uniform background, ``rgb`` (H, W, 3)."""
    s = settings or Segmentation()
    h, w = rgb.shape[:2]
    b = max(1, round(min(h, w) * s.border))
    frame = np.concatenate([rgb[:b].reshape(-1, 3), rgb[-b:].reshape(-1, 3),
                            rgb[:, :b].reshape(-1, 3), rgb[:, -b:].reshape(-1, 3)])  # fmt: skip
    background = np.median(frame, axis=0)
    frame_d = np.linalg.norm(frame - background, axis=1)
    mad = float(np.median(np.abs(frame_d - np.median(frame_d))))
    threshold = max(s.min_threshold, float(np.median(frame_d)) + s.sigmas * 1.4826 * mad)
    mask = np.linalg.norm(rgb - background, axis=2) > threshold
    mask = ndimage.binary_opening(mask, structure=np.ones((3, 3), bool))
    labels, n = ndimage.label(mask, structure=np.ones((3, 3), int))
    if n == 0:
        return mask
    sizes = ndimage.sum_labels(mask, labels, index=np.arange(1, n + 1))
    mask = labels == (1 + int(np.argmax(sizes)))
    return ndimage.binary_fill_holes(mask)


def object_mask(path: Path, rgb: np.ndarray, alpha: np.ndarray | None, settings: Segmentation) -> np.ndarray:
    """The object's mask from alpha, or segmented; raises if nothing is found."""
    mask = alpha > 0.5 if alpha is not None else segment_foreground(rgb, settings)
    if mask.mean() < settings.min_area:
        how = "alpha channel (almost) empty" if alpha is not None else "no object found against a uniform background"
        raise ImageFileError(f"{path}: {how}")
    return mask


def frame_object(
    rgb: np.ndarray, mask: np.ndarray, size: int, scale: float, point: tuple[float, float],
    target: tuple[float, float],
) -> tuple[np.ndarray, np.ndarray]:
    """Scale the masked object by ``scale`` and move its pixel ``point`` (x, y) to ``target`` in an
    ``size`` x ``size`` black image.

    Returns the (S, S, 3) uint8 image (foreground floored at 1 so it never reads as background) and
    its (S, S) bool mask.
    """
    ys, xs = np.nonzero(mask)
    x0, x1, y0, y1 = xs.min(), xs.max() + 1, ys.min(), ys.max() + 1
    crop = rgb[y0:y1, x0:x1] * mask[y0:y1, x0:x1, None]  # premultiplied: edges fade to black
    cw, ch = max(1, round((x1 - x0) * scale)), max(1, round((y1 - y0) * scale))
    img = Image.fromarray(np.rint(crop * 255).astype(np.uint8)).resize((cw, ch), Image.Resampling.LANCZOS)
    msk = Image.fromarray((mask[y0:y1, x0:x1] * 255).astype(np.uint8)).resize((cw, ch), Image.Resampling.BOX)
    # top-left so that `point` lands on `target`: pixel centre x maps to (x - x0 + 0.5) * scale - 0.5
    left = round(target[0] - ((point[0] - x0 + 0.5) * scale - 0.5))
    top = round(target[1] - ((point[1] - y0 + 0.5) * scale - 0.5))
    out = Image.new("RGB", (size, size))
    out.paste(img, (left, top))
    out_mask = Image.new("L", (size, size))
    out_mask.paste(msk, (left, top))
    image, m = np.asarray(out).copy(), np.asarray(out_mask) > 127
    image[~m] = 0
    image[m] = np.maximum(image[m], 1)
    return image, m


def _natural_key(p: Path) -> tuple:
    return tuple(int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", p.stem))


@dataclass
class PlaneFiles:
    """One plane's files: ``canonical`` and, for a plane folder, its anchor photos in order."""

    object: str
    plane: str
    canonical: Path
    anchors: list[Path]


class ImageFolderSource:
    """``data=images``: canonical images (and optionally photographed anchors) from image files.

    Args:
        root: the folder of object folders.
        fill: fraction of the image width covered by each object's larger side (as the catalog).
        manifest: optional YAML/CSV manifest of the objects' shape types (else: 2 planes planar,
            up to 6 rectangular, more cylindrical).
        anchor_names: "index" or "angle": how photographed-anchor files are named (module docstring).
        segmentation: :class:`Segmentation` settings (a mapping from the config).
    """

    def __init__(self, root: str | Path, fill: float = 0.6, manifest: str | Path | None = None,
                 anchor_names: str = "index", segmentation: Segmentation | dict | None = None) -> None:
        if root is None or str(root) in ("", "???"):
            raise MatlError("data.source.root is not set: pass data.source.root=<folder of object folders>")
        self.root = Path(root).expanduser()
        if not self.root.is_dir():
            raise MatlError(f"data.source.root={self.root}: no such folder")
        if not 0.0 < fill <= 1.0:
            raise MatlError(f"data.source.fill={fill} is invalid: use a fraction in (0, 1]")
        if anchor_names not in ANCHOR_NAMES:
            raise MatlError(f"data.source.anchor_names={anchor_names!r} is invalid; valid: {list(ANCHOR_NAMES)}")
        self.fill = float(fill)
        self.manifest = Manifest.load(manifest) if manifest else Manifest.empty()
        self.anchor_names = anchor_names
        if segmentation is not None and not isinstance(segmentation, Segmentation):
            segmentation = Segmentation(**{k: float(v) for k, v in dict(segmentation).items()})
        self.segmentation = segmentation or Segmentation()
        self._planes: list[PlaneFiles] | None = None

    def __repr__(self) -> str:
        return f"ImageFolderSource(root={str(self.root)!r}, fill={self.fill}, anchor_names={self.anchor_names!r})"

    # ------------------------------------------------------------------------------------ files
    def planes(self) -> list[PlaneFiles]:
        """Every plane's files, objects and planes in natural name order."""
        if self._planes is not None:
            return self._planes
        planes: list[PlaneFiles] = []
        objects = sorted((d for d in self.root.iterdir() if d.is_dir() and not d.name.startswith(".")),
                         key=_natural_key)  # fmt: skip
        if not objects:
            raise MatlError(f"data.source.root={self.root}: no object folders (expected <root>/<object>/<plane>.png)")
        for obj in objects:
            entries = sorted((e for e in obj.iterdir() if not e.name.startswith(".")), key=_natural_key)
            if not entries:
                raise MatlError(f"{obj}: empty object folder (expected <plane>.png files or <plane>/ folders)")
            for e in entries:
                if e.is_dir():
                    files = sorted((f for f in e.iterdir() if f.is_file() and not f.name.startswith(".")),
                                   key=_natural_key)  # fmt: skip
                    if not files:
                        raise MatlError(f"{e}: empty plane folder (expected anchor photos <k>.png)")
                    if self.anchor_names == "angle":
                        for f in files:
                            self._angle(f)
                        zero = [f for f in files if self._angle(f) % 360 == 0]
                        canonical = zero[0] if zero else files[0]
                    else:
                        canonical = files[0]
                    planes.append(PlaneFiles(obj.name, e.name, canonical, files))
                else:
                    planes.append(PlaneFiles(obj.name, e.stem, e, []))
        self._planes = planes
        return planes

    @staticmethod
    def _angle(path: Path) -> float:
        try:
            return float(path.stem)
        except ValueError:
            raise MatlError(f"{path}: anchor_names=angle needs files named by their angle in degrees "
                            "(e.g. 090.png)") from None  # fmt: skip

    def _fingerprint(self) -> str:
        rows = []
        for p in self.planes():
            for f in [p.canonical, *p.anchors]:
                st = f.stat()
                rows.append((str(f.relative_to(self.root)), st.st_size, st.st_mtime_ns))
        return hashlib.sha1(repr(sorted(set(rows))).encode()).hexdigest()

    def cache_key(self) -> dict[str, Any]:
        manifest = hashlib.sha1(self.manifest.path.read_bytes()).hexdigest() if self.manifest.path else None
        return {"type": "image_folder", "version": PHOTO_SOURCE_VERSION, "root": str(self.root.resolve()),
                "files": self._fingerprint(), "fill": self.fill, "anchor_names": self.anchor_names,
                "segmentation": vars(self.segmentation), "manifest": manifest}  # fmt: skip

    # ------------------------------------------------------------------------------------ images
    def _load(self, path: Path) -> tuple[np.ndarray, np.ndarray]:
        rgb, alpha = read_rgba(path, min_side=2)
        return rgb, object_mask(path, rgb, alpha, self.segmentation)

    def _canonical(self, path: Path, size: int) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
        rgb, mask = self._load(path)
        ys, xs = np.nonzero(mask)
        scale = self.fill * size / max(xs.max() - xs.min() + 1, ys.max() - ys.min() + 1)
        centre = ((xs.min() + xs.max()) / 2, (ys.min() + ys.max()) / 2)
        c = (size - 1) / 2
        image, m = frame_object(rgb, mask, size, scale, centre, (c, c))
        # what anchors of this plane need to keep the canonical's scale and placement
        info = {"scale": scale, "area": float(mask.sum()), "centroid": (xs.mean(), ys.mean())}
        info["target"] = ((info["centroid"][0] - centre[0]) * scale + c, (info["centroid"][1] - centre[1]) * scale + c)
        return image, m, info

    def _shape(self, name: str, n_planes: int) -> str:
        entry = self.manifest.lookup(name)
        if entry is not None:
            return entry.shape
        return "planar" if n_planes <= 2 else "rectangular" if n_planes <= 6 else "cylindrical"

    def build(self, image_size: int, progress: ProgressFn | None = None) -> CanonicalSet:
        """Load, segment and frame every plane's canonical image at ``image_size`` px."""
        planes = self.planes()
        objects = list(dict.fromkeys(p.object for p in planes))
        images, masks = [], []
        for i, p in enumerate(planes):
            image, mask, _ = self._canonical(p.canonical, image_size)
            images.append(image)
            masks.append(mask)
            if progress is not None:
                progress(i + 1, len(planes))
        plane_object = np.array([objects.index(p.object) for p in planes], dtype=np.int64)
        shapes = [self._shape(o, int((plane_object == k).sum())) for k, o in enumerate(objects)]
        return CanonicalSet(np.stack(images), np.stack(masks), plane_object, [p.plane for p in planes], objects, shapes)

    def anchor_photos(self, image_size: int) -> list[tuple[np.ndarray, np.ndarray] | None]:
        """Per plane (canonical-set order): None, or the photographed anchors' images (K, S, S, 3)
        uint8 and their ``anchor_H_canon`` (K, 3, 3) float64 (module docstring)."""
        out: list[tuple[np.ndarray, np.ndarray] | None] = []
        c = (image_size - 1) / 2
        for p in self.planes():
            if not p.anchors:
                out.append(None)
                continue
            canon_img, _, info = self._canonical(p.canonical, image_size)
            images, Hs = [], []
            for f in p.anchors:
                angle = self._angle(f) if self.anchor_names == "angle" else 0.0
                H = centre_rotation(torch.tensor(angle, dtype=torch.float64), (image_size, image_size)).numpy()
                if f == p.canonical:
                    images.append(canon_img)
                else:
                    rgb, mask = self._load(f)
                    ys, xs = np.nonzero(mask)
                    scale = info["scale"] * float(np.sqrt(info["area"] / mask.sum()))  # same object size
                    # The canonical's object centre, where this anchor's rotation sends it.
                    tx, ty, tw = H @ np.array([*info["target"], 1.0])
                    target = (tx / tw, ty / tw) if self.anchor_names == "angle" else (c, c)
                    images.append(frame_object(rgb, mask, image_size, scale, (xs.mean(), ys.mean()), target)[0])
                Hs.append(H)
            out.append((np.stack(images), np.stack(Hs)))
        return out
