"""Images given to the :class:`~matl.inference.api.Recognizer` and the rows of its batches.

Query and gallery images in any accepted form become float32 ``(H, W, 3|4)`` arrays in [0, 1] (:func:`_as_rgb`),
names of products and planes are checked, grey images found and made (:data:`LUMA`), and a query's mask becomes its
visibility ``(B, 1, S, S)`` in the model frame (:func:`_query_visibility`). Batches of per-query tensors
(:class:`~matl.models.prediction.Prediction`, :class:`~matl.inference.verify.Verification`) are joined, indexed and
patched row by row.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import torch

from matl.data.image_files import fit_to_model, load_image_file, read_rgba
from matl.utils.errors import MatlError

#: px: a gallery image whose shorter side is below this carries too little of the product to match
MIN_GALLERY_SIDE = 8
#: ITU-R BT.601 luma weights (OpenCV's and PIL's RGB -> grey): a grey query is matched against its gallery's grey
LUMA = (0.299, 0.587, 0.114)

#: how far outside [0, 1] float pixels may stray (rounding of the caller's arithmetic) before it is a scale error
FLOAT_SLACK = 1.0 / 512.0  # half a step of 8 bits


def _as_rgb(image: Any, what: str, keep_alpha: bool = False) -> np.ndarray:
    """A query or gallery image as float32 ``(H, W, 3)`` RGB in [0, 1], transparent pixels set to 0; with
    ``keep_alpha`` an image with an alpha channel stays ``(H, W, 4)`` RGBA (alpha = mask).

    Arrays: ``HxWx3`` RGB, ``HxWx4`` RGBA, or grey ``HxW`` / ``HxWx1`` (replicated to 3 channels, as a grey
    file is); tensors: ``(3|4, H, W)``, or grey ``(H, W)`` / ``(1, H, W)``. ``uint8`` pixels are 0-255, float
    pixels 0-1: a float image with values above 1 (0-255 floats), below 0, NaN or infinite is refused in
    one line, never clipped into another picture.
    """
    if isinstance(image, (str, Path)):
        if keep_alpha:
            rgb, alpha = read_rgba(image)
            return rgb if alpha is None else np.ascontiguousarray(np.concatenate([rgb, alpha[..., None]], -1))
        return load_image_file(image)
    if image is None:
        raise MatlError(f"{what}: got None instead of an image (a path, an HxWx3 uint8 array or a tensor)")
    if isinstance(image, torch.Tensor):
        image = image.detach().cpu()
        if image.ndim == 3 and image.shape[0] == 1:
            image = image[0]
        if image.ndim == 3 and image.shape[0] in (3, 4):
            image = image.permute(1, 2, 0)
        elif image.ndim != 2:
            raise MatlError(f"{what}: a tensor image must be (3, H, W), (4, H, W) or grey (H, W), got "
                            f"{tuple(image.shape)}")
        image = image.numpy()
    array = np.asarray(image)
    if array.ndim == 3 and array.shape[-1] == 1:
        array = array[..., 0]
    if array.ndim == 2:
        array = np.repeat(array[..., None], 3, axis=-1)
    if array.ndim != 3 or array.shape[-1] not in (3, 4) or array.shape[0] == 0 or array.shape[1] == 0:
        raise MatlError(f"{what}: expected an HxWx3 RGB, HxWx4 RGBA or HxW grey image, got shape {array.shape}")
    if array.dtype == np.uint8:
        x = array.astype(np.float32) / 255.0
    elif array.dtype.kind == "f":
        x = array.astype(np.float32)
        if not np.isfinite(x).all():
            raise MatlError(f"{what}: {int((~np.isfinite(x)).sum())} pixel value(s) are NaN or infinite: "
                            "replace them (e.g. np.nan_to_num) before passing the image")
        low, high = float(x.min()), float(x.max())
        if high > 1.0 + FLOAT_SLACK or low < -FLOAT_SLACK:
            hint = "divide by 255 (or pass uint8)" if high > 1.0 + FLOAT_SLACK else "rescale them into [0, 1]"
            raise MatlError(f"{what}: float pixels must be in [0, 1], these span [{low:g}, {high:g}]: {hint}")
        x = np.clip(x, 0.0, 1.0)
    else:
        raise MatlError(f"{what}: expected uint8 (0-255) or float (0-1) pixels, got {array.dtype}")
    if x.shape[-1] == 4 and not keep_alpha:  # alpha is the segmentation mask: background becomes 0, as in training
        x = x[..., :3] * x[..., 3:4]
    return np.ascontiguousarray(x)


def _check_name(value: Any, kind: str, call: str) -> str:
    """``value`` if it is a usable object or plane name (it stands for a folder or file of a gallery folder)."""
    if (not isinstance(value, str) or not value.strip() or "/" in value or "\\" in value or ".." in value
            or any(ord(c) < 32 for c in value)):
        raise MatlError(f"{call}: {kind}={value!r} is not a name: use a non-empty string without '/', '\\', '..' or "
                        f"control characters, e.g. {'tea' if kind == 'object' else 'front'!r}")
    return value


def _gallery_image_problem(file_size: tuple[int, int], canon_u8: torch.Tensor) -> str | None:
    """Why a canonical image cannot be enrolled (too small, or nothing but background), or None."""
    if min(file_size) < MIN_GALLERY_SIDE:
        return (f"is {file_size[1]}x{file_size[0]} px: a gallery image needs at least {MIN_GALLERY_SIDE} px a side "
                "(a top-down photo or render of the face)")
    if not bool(canon_u8.any()):
        return "is empty (every pixel is 0, the background): nothing to recognise"
    return None


def _is_grey(image: np.ndarray) -> bool:
    """Whether an ``(H, W, 3|4)`` image's colour channels are equal everywhere (a grey image); a subsample first,
    so a colour image costs a few microseconds."""
    step = max(1, min(image.shape[:2]) // 16)
    few = image[::step, ::step]
    if not (np.array_equal(few[..., 0], few[..., 1]) and np.array_equal(few[..., 1], few[..., 2])):
        return False
    return bool(np.array_equal(image[..., 0], image[..., 1]) and np.array_equal(image[..., 1], image[..., 2]))


def _grey_u8(canon_u8: torch.Tensor) -> torch.Tensor:
    """``(3, S, S)`` uint8 canonical image -> its luma (:data:`LUMA`) in all three channels."""
    weights = torch.tensor(LUMA, dtype=torch.float32)[:, None, None]
    luma = (canon_u8.float() * weights).sum(0).round().clamp(0, 255).to(torch.uint8)
    return luma.expand(3, -1, -1).clone()


def _concat(a: Any, b: Any) -> Any:
    """Two tensors, or dataclasses of per-query tensors (:class:`Prediction`), one after the other (None stays)."""
    if isinstance(a, torch.Tensor):
        return torch.cat([a, b.to(a.device, a.dtype)])
    return dataclasses.replace(a, **{f.name: _concat(getattr(a, f.name), getattr(b, f.name))
                                     for f in dataclasses.fields(a) if getattr(a, f.name) is not None})


def _rows(value: Any, index: torch.Tensor) -> Any:
    """The rows ``index`` of a tensor or of each tensor of a dataclass of per-query tensors."""
    if isinstance(value, torch.Tensor):
        return value[index.to(value.device)]
    return dataclasses.replace(value, **{f.name: _rows(getattr(value, f.name), index)
                                         for f in dataclasses.fields(value) if getattr(value, f.name) is not None})


def _with_rows(value: Any, rows: list[int], source: Any, source_rows: list[int]) -> Any:
    """``value`` (a tensor, or a dataclass of per-query tensors such as :class:`Prediction`) with its rows ``rows``
    replaced by ``source``'s rows ``source_rows``; new tensors, fields that are None stay None."""
    if isinstance(value, torch.Tensor):
        out = value.clone()
        out[rows] = source[source_rows].to(out.device, out.dtype)
        return out
    return dataclasses.replace(value, **{
        f.name: _with_rows(getattr(value, f.name), rows, getattr(source, f.name), source_rows)
        for f in dataclasses.fields(value) if getattr(value, f.name) is not None})


def _upscale(query_H_file: torch.Tensor) -> torch.Tensor:
    """``(B,)`` how many times each query's file was enlarged to the model's size (model px per file px) from its
    framing ``model_H_file`` ``(B, 3, 3)`` (a scale and a shift)."""
    return (query_H_file[:, 0, 0] * query_H_file[:, 1, 1]).sqrt()


def _query_visibility(prepared: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]], size: int, fill: float,
                      device: torch.device) -> torch.Tensor | None:
    """``(B, 1, S, S)`` float in [0, 1]: the mask each query prepared by :func:`mask_query` was multiplied by (the
    foreground step's, or an RGBA query's alpha read back from its pixels), framed as the query is (0 where the
    frame holds no file pixel); None when no query has a mask."""
    masks: list[np.ndarray | None] = []
    for masked, rgb, found in prepared:
        if found is not None:
            masks.append(found)
        elif masked is rgb:  # used as given: no mask
            masks.append(None)
        else:  # masked = rgb * alpha; where a pixel is black its alpha is unknown (and it holds no data: 0)
            peak = rgb.max(-1)
            masks.append(np.where(peak > 0, masked.max(-1) / np.maximum(peak, 1e-12), 0.0).astype(np.float32))
    if all(m is None for m in masks):
        return None
    framed = [fit_to_model(torch.from_numpy(np.ones(rgb.shape[:2], np.float32) if m is None else
                                            np.clip(m, 0.0, 1.0).astype(np.float32))[None], size, fill)[0][:1]
              for m, (_, rgb, _) in zip(masks, prepared, strict=True)]
    return torch.stack(framed).to(device)
