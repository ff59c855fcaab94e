"""Image files in, model-size tensors out, with the exact pixel mapping between the two.

``matl.predict`` feeds the network square ``S x S`` images (``S`` from the checkpoint) but reports
poses in the *original* pixel coordinates of the user's files. Every file goes through one
resize-and-pad (:func:`fit_to_model`) whose matrix ``model_H_file`` is returned with the image, so
any model-frame homography can be re-expressed in file coordinates (:func:`pose_in_files`).

Convention:
    * Pixel coordinates as everywhere in matl: x right, y down, ``(0, 0)`` the *centre* of the
      top-left pixel (OpenCV), so ``cv2.warpPerspective`` with a reported ``H`` lands where
      expected.
    * Resizing uses the half-pixel rule of antialiased resizers (torch ``interpolate`` with
      ``align_corners=False``, PIL, ``cv2.INTER_AREA``): pixel centre ``x`` of the file lands at
      ``(x + 0.5) * s - 0.5`` with ``s = new_width / old_width``. This is *not*
      :func:`matl.geometry.rescale_homography`'s ``align_corners=True`` rule (corner centres fixed),
      which would be the right one only for a resize done that way; we compute the matrix of the
      resize we actually do. Padding then adds an integer translation.
    * Images are RGB in [0, 1]; transparent pixels become background 0 (RGB multiplied by alpha), as
      the foreground-segmented training images (``docs/design.md``). EXIF orientation is applied, as
      ``cv2.imread`` does, so coordinates refer to the image as displayed.

Files that cannot be used (not an image, empty, unreadable) raise :class:`ImageFileError` with a
one-line reason; folder-level callers report it and go on with the other files.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image, ImageOps, UnidentifiedImageError

from matl.utils.errors import MatlError

log = logging.getLogger(__name__)

GALLERY_SUFFIXES = (".png", ".jpg", ".jpeg")  # the `images` layout: <root>/<object>/<plane>.png (or .jpg)


class ImageFileError(MatlError):
    """One file cannot be used as an image; the message names the file and why."""


def read_rgba(path: str | Path, min_side: int = 1) -> tuple[np.ndarray, np.ndarray | None]:
    """Read an image file: RGB float32 ``(H, W, 3)`` in [0, 1] and its alpha ``(H, W)`` in [0, 1], or
    None without an alpha channel. EXIF orientation is applied; 16-bit and 32-bit grey images are
    scaled by their bit depth (:func:`_high_depth_grey`), not clipped.

    The one image reader of matl: :func:`load_image_file` (predict, score, unseen) and the
    ``images`` dataset (:mod:`matl.data.photos`) both read through it.

    Raises:
        ImageFileError: missing, empty, not an image, undecodable, or with a side below ``min_side``.
    """
    path = Path(path)
    if not path.is_file():
        raise ImageFileError(f"{path}: no such file")
    if path.stat().st_size == 0:
        raise ImageFileError(f"{path}: empty file (0 bytes)")
    try:
        with Image.open(path) as img:
            img = ImageOps.exif_transpose(img)
            if img.mode.startswith(("I", "F")):  # 16-bit / 32-bit grey: PIL's convert("RGB") would clip to white
                grey = _high_depth_grey(np.asarray(img))
                rgba = np.repeat(grey[..., None], 3, axis=-1)
                has_alpha = False
            else:
                has_alpha = img.mode in ("RGBA", "LA", "PA") or (img.mode == "P" and "transparency" in img.info)
                rgba = np.asarray(img.convert("RGBA" if has_alpha else "RGB"), dtype=np.float32) / 255.0
    except (UnidentifiedImageError, OSError, ValueError, Image.DecompressionBombError) as error:
        reason = "not an image" if isinstance(error, UnidentifiedImageError) else " ".join(str(error).split())
        raise ImageFileError(f"{path}: {reason}") from error
    if rgba.ndim != 3 or rgba.shape[0] < min_side or rgba.shape[1] < min_side:
        raise ImageFileError(f"{path}: image has no pixels")
    return (rgba[..., :3], rgba[..., 3]) if has_alpha else (rgba, None)


def load_image_file(path: str | Path) -> np.ndarray:
    """Read an image file as RGB float32 ``(H, W, 3)`` in [0, 1], transparent pixels set to 0.

    Raises:
        ImageFileError: missing, empty, not an image, or undecodable.
    """
    rgb, alpha = read_rgba(path)
    if alpha is not None:
        return np.ascontiguousarray(rgb * alpha[..., None])
    return np.ascontiguousarray(rgb)


def _high_depth_grey(values: np.ndarray) -> np.ndarray:
    """A 16-bit, 32-bit integer or float grey image as float32 in [0, 1].

    Integer images of PIL's ``I;16*`` modes are 16-bit (divide by 65535); mode ``I`` holds 16-bit PNGs
    in older PIL versions, so it is read as 8-bit only if no value exceeds 255. Float images are
    taken as [0, 1] if they fit, else as 8-bit or 16-bit ranges; NaN becomes 0.
    """
    x = np.nan_to_num(values.astype(np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    top = float(x.max()) if x.size else 0.0
    if values.dtype.kind == "u" and values.dtype.itemsize == 2:  # I;16, I;16B, I;16L (any byte order)
        scale = 65535.0
    elif values.dtype.kind == "f" and top <= 1.0:
        scale = 1.0
    else:
        scale = 255.0 if top <= 255.0 else 65535.0
    return np.clip(x / scale, 0.0, 1.0).astype(np.float32)


@dataclass(frozen=True)
class Fit:
    """How a ``height x width`` file maps into the ``size x size`` model frame.

    Attributes:
        new_height, new_width: size of the resized content (before padding).
        left, top: integer padding offsets of the content in the model frame.
        model_H_file: ``(3, 3)`` float64, file pixel centre -> model pixel centre.
    """

    new_height: int
    new_width: int
    left: int
    top: int
    model_H_file: torch.Tensor = field(repr=False)


def fit_geometry(height: int, width: int, size: int, fill: float = 1.0) -> Fit:
    """Resize keeping the aspect so the longer side spans ``fill * size`` pixels, then centre-pad.

    Args:
        height, width: file size in pixels.
        size: model image side ``S``.
        fill: fraction of the model frame the longer side takes (1: touch the border; the synthetic
            catalogs frame their canonical planes at 0.6).
    """
    if not 0.0 < fill <= 1.0:
        raise MatlError(f"fill={fill} is invalid: use a fraction in (0, 1]")
    scale = fill * size / max(height, width)
    new_w = min(size, max(1, round(width * scale)))
    new_h = min(size, max(1, round(height * scale)))
    left, top = (size - new_w) // 2, (size - new_h) // 2
    # the per-axis scales are new/old exactly (that is what interpolate(size=...) uses), not `scale`
    sx, sy = new_w / width, new_h / height
    model_H_file = torch.tensor([[sx, 0.0, 0.5 * sx - 0.5 + left],
                                 [0.0, sy, 0.5 * sy - 0.5 + top],
                                 [0.0, 0.0, 1.0]], dtype=torch.float64)
    return Fit(new_h, new_w, left, top, model_H_file)


def fit_to_model(image: np.ndarray | torch.Tensor, size: int, fill: float = 1.0) -> tuple[torch.Tensor, Fit]:
    """Resize (antialiased bilinear) and centre-pad with 0 an image to the model frame.

    Args:
        image: ``(H, W, 3)`` array or ``(3, H, W)`` tensor, RGB in [0, 1].
        size: model image side ``S``.
        fill: see :func:`fit_geometry`.
    Returns:
        ``(3, S, S)`` float32 tensor and its :class:`Fit` (``model_H_file`` maps file pixels to it).
    """
    x = torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1) if isinstance(image, np.ndarray) else image
    x = x.float()
    fit = fit_geometry(int(x.shape[1]), int(x.shape[2]), size, fill)
    resized = F.interpolate(x[None], size=(fit.new_height, fit.new_width), mode="bilinear",
                            align_corners=False, antialias=True)[0].clamp(0.0, 1.0)
    out = x.new_zeros(3, size, size)
    out[:, fit.top:fit.top + fit.new_height, fit.left:fit.left + fit.new_width] = resized
    return out, fit


def pose_in_files(query_H_canon: torch.Tensor, canon_H_gallery_file: torch.Tensor,
                  query_H_query_file: torch.Tensor) -> torch.Tensor:
    """Re-express model-frame poses in the pixel coordinates of the original files.

    Convention: the model's ``query_H_canon`` maps the canonical *model* frame to the query *model*
    frame. With ``canon_H_gallery_file`` (the gallery file's ``model_H_file``) and
    ``query_H_query_file`` (the query file's ``model_H_file``) the file-level pose is
    ``query_file_H_gallery_file = inv(query_H_query_file) @ query_H_canon @ canon_H_gallery_file``,
    so ``cv2.warpPerspective(gallery_img, H, (query_w, query_h))`` lands on the query.

    Args:
        query_H_canon, canon_H_gallery_file, query_H_query_file: ``(B, 3, 3)``.
    Returns:
        ``(B, 3, 3)`` float64 with ``H[2, 2] = 1``.
    """
    H = torch.linalg.solve(query_H_query_file.double(), query_H_canon.double() @ canon_H_gallery_file.double())
    return H / H[..., 2:3, 2:3]


def list_image_candidates(path: str | Path, recursive: bool = False) -> list[Path]:
    """The files to try as images: ``path`` itself, or the non-hidden regular files of a folder, sorted.

    Nothing is filtered by extension: every candidate is opened and a non-image is reported by the
    caller, so a misnamed file is not silently ignored.
    """
    path = Path(path).expanduser()
    if path.is_file():
        return [path]
    if not path.is_dir():
        raise MatlError(f"images={path}: no such file or folder")
    walk = path.rglob("*") if recursive else path.iterdir()
    files = [p for p in walk if p.is_file() and not any(part.startswith(".") for part in p.relative_to(path).parts)]
    return sorted(files)


@dataclass
class GalleryFiles:
    """The canonical image files of a gallery folder, one per plane, objects and planes sorted by name.

    Attributes:
        root: the gallery folder.
        paths: ``(P,)`` canonical image files.
        plane_names: ``(P,)`` file stems (``front``, ``top``, ...).
        plane_object: ``(P,)`` index into ``object_names``.
        object_names: ``(O,)`` object folder names.
        skipped: ``(path, reason)`` of files that were not used.
    """

    root: Path
    paths: list[Path]
    plane_names: list[str]
    plane_object: list[int]
    object_names: list[str]
    skipped: list[tuple[Path, str]]

    def fingerprint(self) -> list[tuple[str, int, int]]:
        """``(relative path, mtime_ns, size)`` of every candidate file, used or skipped (cache key)."""
        files = sorted({*self.paths, *(p for p, _ in self.skipped if p.is_file())})
        return [(str(p.relative_to(self.root)), p.stat().st_mtime_ns, p.stat().st_size) for p in files]


def scan_gallery(root: str | Path) -> GalleryFiles:
    """List ``<root>/<object>/<plane>.{png,jpg,jpeg}`` (the ``images`` layout, ``docs/datasets.md``).

    Other files and sub-folders are recorded in ``skipped`` with the reason (photographed-anchor
    folders ``<object>/<plane>/<k>.png`` are not used: predict makes anchors by rotation). Files are
    not opened here.
    """
    root = Path(root).expanduser()
    if not root.is_dir():
        raise MatlError(f"gallery={root}: no such folder")
    paths, planes, plane_object, objects, skipped = [], [], [], [], []
    for entry in sorted(root.iterdir()):
        if entry.name.startswith("."):
            continue  # our feature cache, .DS_Store, ...
        if not entry.is_dir():
            skipped.append((entry, "not inside an object folder (<gallery>/<object>/<plane>.png)"))
            continue
        found = []
        for f in sorted(entry.iterdir()):
            if f.name.startswith("."):
                continue
            if f.is_dir():
                skipped.append((f, "sub-folders are not used (anchors are made by in-plane rotation)"))
            elif f.suffix.lower() not in GALLERY_SUFFIXES:
                skipped.append((f, f"not a {'/'.join(GALLERY_SUFFIXES)} file"))
            else:
                found.append(f)
        if found:
            for f in found:
                paths.append(f)
                planes.append(f.stem)
                plane_object.append(len(objects))
            objects.append(entry.name)
    return GalleryFiles(root, paths, planes, plane_object, objects, skipped)
