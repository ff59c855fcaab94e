"""``python -m matl.predict ckpt=<path> gallery=<dir> images=<dir or file> out=<file.jsonl>``.

Recognition and pose for real image files (DESIGN §5), with a gallery enrolled from canonical image
files, without retraining (paper Sec. 2.1):

1. *Enrol*: every ``<gallery>/<object>/<plane>.{png,jpg,jpeg}`` is loaded, resized with its aspect
   kept and centre-padded with 0 to the checkpoint's model size (:mod:`matl.data.image_files`),
   rotated into the checkpoint's ``N`` fixed anchors, and embedded once by ``c()``. The features are
   cached next to the gallery in ``.matl_gallery_<ckpt>_<files>.pt`` (plain tensors, loads with
   ``weights_only=True``), keyed by the checkpoint's sha256 and every file's path, mtime and size,
   so adding, removing or editing a file refreshes it.
2. *Predict*: query files of any size go through the same resize/pad, in batches; the recognizer
   returns the nearest anchor and the model-frame pose, which is re-expressed in the original pixel
   coordinates of the gallery file and of the query file.

Output: one JSON line per usable image::

    {"image": "crops/0001.jpg", "object": "cereal", "plane": "front", "anchor": 2, "distance": 0.31,
     "H": [[...], [...], [...]], "gallery_image": "gallery/cereal/front.png"}

``H`` is ``query_H_canon`` in file pixels (``null`` for models without an STN), so
``cv2.warpPerspective(cv2.imread(gallery_image), np.array(H), (query_w, query_h))`` lands on the
query. Bad files are reported in one line each and skipped.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import tempfile
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import hydra
import numpy as np
import torch
from omegaconf import DictConfig
from PIL import Image, ImageDraw
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from torch import nn

from matl.data.gallery import Gallery
from matl.data.image_files import (
    GalleryFiles,
    ImageFileError,
    fit_to_model,
    list_image_candidates,
    load_image_file,
    pose_in_files,
    scan_gallery,
)
from matl.geometry import anchor_H_canon, transfer_points, warp_image
from matl.inference.options import configure_recognizer
from matl.inference.quantize import apply_quantize_option, calibration_images, quantize_option
from matl.inference.recognizer import Prediction, Recognizer, embed
from matl.models.checkpoint import build_model, checkpoint_info, file_sha256, load_checkpoint
from matl.utils.config import validate_config
from matl.utils.errors import MatlError, exit_on_error, hydra_errors

log = logging.getLogger(__name__)

CACHE_FORMAT = 1  # bump when the cache's content or meaning changes: old files then miss the key
CACHE_PREFIX = ".matl_gallery_"


# ---------------------------------------------------------------------------------------- gallery
@dataclass
class EnrolledGallery:
    """A gallery built from canonical image files.

    Attributes:
        gallery: the ``G = P * N`` anchors at model size with labels and ``anchor_H_canon``.
        features: ``(G, D)`` ``c(anchor)``, or None if no feature net was given.
        canon_H_file: ``(P, 3, 3)`` float64, gallery-file pixel -> canonical model-frame pixel.
        file_sizes: ``(P, 2)`` int64 ``(height, width)`` of each canonical image file.
        paths: ``(P,)`` the canonical image file of each plane.
        cache_file: the feature cache used or written, if any.
    """

    gallery: Gallery
    features: torch.Tensor | None
    canon_H_file: torch.Tensor
    file_sizes: torch.Tensor
    paths: list[Path]
    cache_file: Path | None = None


def report_skipped(path: Path, reason: str) -> None:
    """One line per unusable file; the run goes on."""
    log.warning("skipped %s: %s", path, reason)


def _load_planes(files: GalleryFiles, size: int,
                 fill: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, list[int]]:
    """Load and fit every plane file; unusable files are reported and dropped.

    Returns:
        uint8 ``(P', 3, S, S)`` canonical images (quantised like the catalogs' canonical sets, so the
        cached and uncached paths see identical pixels), ``(P', 3, 3)`` ``canon_H_file``, ``(P', 2)``
        file ``(height, width)`` and the indices of the kept planes into ``files.paths``.
    """
    images, matrices, sizes, kept = [], [], [], []
    for i, path in enumerate(files.paths):
        try:
            original = load_image_file(path)
            image, fit = fit_to_model(original, size, fill)
        except ImageFileError as error:
            report_skipped(path, str(error).removeprefix(f"{path}: "))
            continue
        images.append((image * 255.0).round().to(torch.uint8))
        matrices.append(fit.model_H_file)
        sizes.append(original.shape[:2])
        kept.append(i)
    if not images:
        return (torch.zeros(0, 3, size, size, dtype=torch.uint8), torch.zeros(0, 3, 3, dtype=torch.float64),
                torch.zeros(0, 2, dtype=torch.long), [])
    return torch.stack(images), torch.stack(matrices), torch.tensor(sizes, dtype=torch.long), kept


def _cache_file(root: Path, key: dict[str, Any]) -> Path:
    key_json = json.dumps(key, sort_keys=True)
    files_digest = hashlib.sha256(key_json.encode()).hexdigest()[:16]
    return root / f"{CACHE_PREFIX}{key['checkpoint'][:16]}_{files_digest}.pt"


def _read_cache(path: Path, key: dict[str, Any]) -> dict[str, Any] | None:
    if not path.is_file():
        return None
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # a corrupt cache is never fatal: it is rebuilt
        log.warning("gallery cache %s is unreadable (%s); rebuilding it", path, " ".join(str(error).split()))
        return None
    if not isinstance(payload, dict) or payload.get("key") != json.dumps(key, sort_keys=True):
        return None
    return payload


def _write_cache(path: Path, payload: dict[str, Any]) -> None:
    """Atomic write (temp file in the same folder, then ``os.replace``); stale caches of the same
    checkpoint are removed. A read-only gallery folder only costs a warning."""
    try:
        fd, tmp = tempfile.mkstemp(prefix=f"{path.name}.", suffix=".tmp", dir=path.parent)
        try:
            with os.fdopen(fd, "wb") as f:
                torch.save(payload, f)
            umask = os.umask(0)
            os.umask(umask)
            os.chmod(tmp, 0o666 & ~umask)  # mkstemp's 0600 would hide the cache from other users of the gallery
            os.replace(tmp, path)
        except BaseException:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)
            raise
    except OSError as error:
        log.warning("cannot write the gallery cache %s (%s); features will be recomputed next time", path, error)
        return
    same_checkpoint = path.name[:len(CACHE_PREFIX) + 16]
    for old in path.parent.glob(f"{same_checkpoint}_*.pt"):
        if old != path:
            with contextlib.suppress(OSError):
                old.unlink()


def _build_gallery(canon_u8: torch.Tensor, plane_object: list[int], plane_names: list[str],
                   object_names: list[str], num_anchors: int) -> Gallery:
    """The ``P * N`` fixed anchors (DESIGN §2) of the canonical images, flattened plane-major."""
    P, N = len(canon_u8), num_anchors
    size = int(canon_u8.shape[-1])
    H = anchor_H_canon(N, (size, size), torch.float64)                    # (N, 3, 3)
    flat_H = H.repeat(P, 1, 1)                                             # (P*N, 3, 3)
    canon = canon_u8.float().div(255.0).repeat_interleave(N, dim=0)
    images = warp_image(canon, flat_H) if P else canon
    obj = torch.tensor(plane_object, dtype=torch.long)
    return Gallery(images=images, object_index=obj.repeat_interleave(N),
                   plane_index=torch.arange(P).repeat_interleave(N), anchor_index=torch.arange(N).repeat(P),
                   anchor_H_canon=flat_H, object_names=list(object_names), plane_names=list(plane_names))


def enrol_gallery(root: str | Path, feature_net: nn.Module | None, image_size: int, num_anchors: int,
                  fill: float = 1.0, cache_tag: str | None = None, batch_size: int = 256) -> EnrolledGallery:
    """Enrol ``<root>/<object>/<plane>.png`` files into a gallery, features cached when ``cache_tag`` is set.

    Args:
        root: the gallery folder.
        feature_net: ``c()`` (in eval mode), or None to skip the features.
        image_size: model side ``S`` (from the checkpoint).
        num_anchors: ``N`` (from the checkpoint).
        fill: see :func:`matl.data.image_files.fit_geometry`.
        cache_tag: the checkpoint's sha256; None disables the on-disk cache.
        batch_size: images per ``c()`` call.
    Raises:
        MatlError: no folder, or no usable image in it.
    """
    files = scan_gallery(root)
    for path, reason in files.skipped:
        report_skipped(path, reason)
    layout = f"{files.root}/<object>/<plane>.png"
    if not files.paths:
        raise MatlError(f"gallery={files.root} holds no canonical images: expected {layout}")
    key = None if cache_tag is None else {
        "format": CACHE_FORMAT, "checkpoint": cache_tag, "image_size": int(image_size),
        "num_anchors": int(num_anchors), "fill": float(fill), "anchors": "fixed", "files": files.fingerprint()}
    cache_path = None if key is None else _cache_file(files.root, key)
    payload = None if cache_path is None else _read_cache(cache_path, key)
    if payload is not None:
        log.info("gallery features loaded from %s", cache_path)
        canon_u8, canon_H_file, file_sizes = payload["images"], payload["canon_H_file"], payload["file_sizes"]
        kept = [int(i) for i in payload["kept"]]
    else:
        canon_u8, canon_H_file, file_sizes, kept = _load_planes(files, image_size, fill)
    if not kept:
        raise MatlError(f"gallery={files.root} holds no usable image (all were skipped): expected {layout}")
    # objects whose every plane was skipped disappear; the others are re-indexed densely
    used_objects = sorted({files.plane_object[i] for i in kept})
    remap = {o: j for j, o in enumerate(used_objects)}
    gallery = _build_gallery(canon_u8, [remap[files.plane_object[i]] for i in kept],
                             [files.plane_names[i] for i in kept], [files.object_names[o] for o in used_objects],
                             num_anchors)
    features = None
    if payload is not None:
        features = payload["features"]
    elif feature_net is not None:
        first = next(iter(feature_net.parameters()), None)
        device = first.device if first is not None else torch.device("cpu")
        features = embed(feature_net, gallery.images.to(device), batch_size).cpu()
        if cache_path is not None:
            _write_cache(cache_path, {"key": json.dumps(key, sort_keys=True), "images": canon_u8,
                                      "canon_H_file": canon_H_file, "file_sizes": file_sizes,
                                      "kept": torch.tensor(kept, dtype=torch.long), "features": features})
    log.info("gallery: %d objects, %d planes, %d anchors", len(gallery.object_names), len(kept), len(gallery))
    return EnrolledGallery(gallery, features, canon_H_file, file_sizes, [files.paths[i] for i in kept], cache_path)


# ---------------------------------------------------------------------------------------- queries
def _batches(items: Sequence[Path], size: int) -> Iterator[Sequence[Path]]:
    for start in range(0, len(items), size):
        yield items[start:start + size]


def prediction_records(pred: Prediction, enrolled: EnrolledGallery, paths: Sequence[Path],
                       query_H_file: torch.Tensor) -> list[dict[str, Any]]:
    """JSON records of a batch: the model-frame prediction with ``H`` in file pixels.

    Args:
        pred: the recognizer's output for ``Q`` queries.
        paths: ``(Q,)`` query files.
        query_H_file: ``(Q, 3, 3)`` each query file's ``model_H_file``.
    """
    g = enrolled.gallery
    plane = pred.plane_index.cpu()
    H = None
    if pred.query_H_canon is not None:
        H = pose_in_files(pred.query_H_canon.cpu(), enrolled.canon_H_file[plane], query_H_file)
    records = []
    for i, path in enumerate(paths):
        p = int(plane[i])
        records.append({
            "image": str(path),
            "object": g.object_names[int(pred.object_index[i])],
            "plane": g.plane_names[p],
            "anchor": int(pred.anchor_index[i]),
            "distance": float(pred.distance[i]),
            "H": None if H is None else H[i].tolist(),
            "gallery_image": str(enrolled.paths[p]),
        })
    return records


def save_visualisation(path: Path, query: np.ndarray, pred: Prediction, i: int, enrolled: EnrolledGallery,
                       record: dict[str, Any], panel: int = 256) -> None:
    """One PNG: the query with the gallery image's outline (its corners mapped by ``H``),
    ``s(query)`` and the selected anchor.

    Args:
        query: ``(h, w, 3)`` float original query image.
        pred: the batch's prediction; ``i`` the query's row in it.
        record: the query's JSON record (for ``H`` and labels).
        panel: height of each panel in pixels.
    """
    def to_pil(x: np.ndarray) -> Image.Image:
        return Image.fromarray((np.clip(x, 0.0, 1.0) * 255.0).round().astype(np.uint8))

    h, w = query.shape[:2]
    scale = panel / h
    left = to_pil(query).resize((max(1, round(w * scale)), panel), Image.Resampling.BILINEAR)
    draw = ImageDraw.Draw(left)
    if record["H"] is not None:
        gh, gw = (int(v) for v in enrolled.file_sizes[int(pred.plane_index[i])])
        corners = torch.tensor([[[0.0, 0.0], [gw - 1.0, 0.0], [gw - 1.0, gh - 1.0], [0.0, gh - 1.0]]],
                               dtype=torch.float64)
        mapped = transfer_points(torch.tensor(record["H"], dtype=torch.float64)[None], corners)[0]
        # file pixel centres -> panel pixel centres (the panel is a plain scaled copy)
        pts = [((float(x) + 0.5) * left.width / w - 0.5, (float(y) + 0.5) * scale - 0.5) for x, y in mapped]
        if all(np.isfinite(v) for pt in pts for v in pt):
            draw.line([*pts, pts[0]], fill=(0, 255, 0), width=2)
    warped = to_pil(pred.warped[i].permute(1, 2, 0).cpu().numpy()).resize((panel, panel), Image.Resampling.NEAREST)
    anchor = enrolled.gallery.images[int(pred.gallery_index[i])]
    anchor = to_pil(anchor.permute(1, 2, 0).cpu().numpy()).resize((panel, panel), Image.Resampling.NEAREST)
    gap, title = 8, 18
    canvas = Image.new("RGB", (left.width + 2 * panel + 2 * gap, panel + title), (255, 255, 255))
    labels = [(left, "query + gallery outline"), (warped, "s(query)"),
              (anchor, f"anchor {record['anchor']}: {record['object']}/{record['plane']}")]
    x = 0
    text = ImageDraw.Draw(canvas)
    for image, label in labels:
        canvas.paste(image, (x, title))
        text.text((x + 2, 2), label, fill=(0, 0, 0))
        x += image.width + gap
    canvas.save(path)


def predict_files(recognizer: Callable[[torch.Tensor], Prediction], enrolled: EnrolledGallery,
                  files: Sequence[Path], image_size: int, sink: Callable[[dict[str, Any]], None],
                  batch_size: int = 64, fill: float = 1.0, viz_dir: Path | None = None,
                  device: torch.device | str = "cpu", show_progress: bool = True) -> tuple[int, int]:
    """Recognise every file in batches; each usable one gives a record to ``sink``.

    Returns:
        ``(predicted, skipped)`` counts. Unusable files are reported (one line) and skipped.
    """
    if batch_size < 1:
        raise MatlError(f"batch_size={batch_size} is invalid: use an integer >= 1")
    if viz_dir is not None:
        viz_dir.mkdir(parents=True, exist_ok=True)
    done = skipped = 0
    viz_names: set[str] = set()  # recursive listings can repeat a file name: never overwrite a PNG
    columns = (TextColumn("[bold]predict"), BarColumn(), MofNCompleteColumn(), TextColumn("images"),
               TimeElapsedColumn())
    with Progress(*columns, disable=not show_progress or len(files) < 2) as progress:
        task = progress.add_task("predict", total=len(files))
        for chunk in _batches(files, batch_size):
            paths, originals, images, matrices = [], [], [], []
            for path in chunk:
                try:
                    original = load_image_file(path)
                except ImageFileError as error:
                    report_skipped(path, str(error).removeprefix(f"{path}: "))
                    skipped += 1
                    continue
                image, fit = fit_to_model(original, image_size, fill)
                paths.append(path)
                originals.append(original if viz_dir is not None else None)
                images.append(image)
                matrices.append(fit.model_H_file)
            if paths:
                pred = recognizer(torch.stack(images).to(device))
                records = prediction_records(pred, enrolled, paths, torch.stack(matrices))
                for i, record in enumerate(records):
                    sink(record)
                    if viz_dir is not None:
                        name, n = f"{paths[i].name}.png", 1
                        while name in viz_names:
                            n += 1
                            name = f"{paths[i].name}-{n}.png"
                        viz_names.add(name)
                        save_visualisation(viz_dir / name, originals[i], pred, i, enrolled, record)
                done += len(paths)
            progress.advance(task, len(chunk))
    return done, skipped


# ------------------------------------------------------------------------------------ entry point
def load_predictor(ckpt_path: str | Path, image_size: int | None = None,
                   device: str = "cpu") -> tuple[nn.Module, int, int, str]:
    """The checkpoint's model (eval mode, on ``device``), its image size, N and file sha256.

    The size is always the checkpoint's; ``image_size`` only asserts it.
    """
    ckpt = load_checkpoint(ckpt_path)
    size, num_anchors = checkpoint_info(ckpt, ckpt_path)
    if image_size is not None and int(image_size) != size:
        raise MatlError(f"checkpoint {ckpt_path} was trained at {size} px, not image_size={image_size}: the model "
                        "size always comes from the checkpoint (drop image_size=)")
    config = ckpt.get("matl_config")
    if not isinstance(config, dict) or "model" not in config:
        raise MatlError(f"checkpoint {ckpt_path} carries no matl_config: not written by matl.train")
    data_size = config.get("data", {}).get("image_size")
    if data_size is not None and int(data_size) != size:
        raise MatlError(f"checkpoint {ckpt_path} is inconsistent: matl_image_size={size} but its config says "
                        f"data.image_size={data_size}")
    model = build_model(config["model"], ckpt, ckpt_path)
    if not hasattr(model, "feature_net"):
        raise MatlError(f"checkpoint {ckpt_path} is a {type(model).__name__}, which cannot enrol new objects: "
                        "predict needs an embedding model (model=matl or model=tl)")
    return model.to(device), size, num_anchors, file_sha256(ckpt_path)


def predict(cfg: DictConfig) -> dict[str, Any]:
    """Run predict for a composed ``conf/predict.yaml``; returns a summary."""
    validate_config(cfg)  # batch_size, fills, device, image_size: before the checkpoint is read
    quantize_option(cfg)  # quantize=none|int8
    for key in ("ckpt", "gallery", "images", "out"):
        if cfg.get(key) in (None, ""):
            raise MatlError(f"{key}=... is required: python -m matl.predict ckpt=<path> gallery=<dir> "
                            "images=<dir or file> out=<file.jsonl>")
    device = str(cfg.device)
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    model, size, num_anchors, ckpt_hash = load_predictor(cfg.ckpt, cfg.get("image_size"), device)
    files = list_image_candidates(cfg.images, bool(cfg.get("recursive", False)))
    if not files:
        raise MatlError(f"images={cfg.images} holds no files")
    enrolled = enrol_gallery(cfg.gallery, model.feature_net, size, num_anchors, float(cfg.gallery_fill),
                             ckpt_hash if cfg.cache else None)
    gallery = enrolled.gallery.to(device)
    recognizer = Recognizer(model.feature_net, model.stn, gallery, model.anchor_choice,
                            gallery_features=enrolled.features)
    # quantize=int8: calibrated on gallery images warped by random homographies (matl/inference/quantize.py)
    quantize = apply_quantize_option(recognizer, cfg, lambda: calibration_images(gallery.images))
    recognizer, inference = configure_recognizer(recognizer, cfg)  # search=exact|faiss, refine=true
    out = Path(cfg.out).expanduser()
    out.parent.mkdir(parents=True, exist_ok=True)
    viz_dir = Path(cfg.viz_dir) if cfg.viz else None
    with open(out, "w") as f:
        def sink(record: dict[str, Any]) -> None:
            f.write(json.dumps(record) + "\n")
            f.flush()  # partial results survive an interrupted run over a large folder
        done, skipped = predict_files(recognizer, enrolled, files, size, sink, int(cfg.batch_size),
                                      float(cfg.query_fill), viz_dir, device)
    summary = {"predicted": done, "skipped": skipped, "out": str(out), "image_size": size, "N": num_anchors,
               "gallery_objects": len(gallery.object_names), "gallery_planes": len(enrolled.paths),
               "viz_dir": None if viz_dir is None else str(viz_dir), **inference, **quantize}
    log.info("predict: %s", json.dumps(summary))
    return summary


@hydra_errors  # outside hydra.main: an unknown option (data=foo) or key is one line, exit 2
@hydra.main(config_path="../conf", config_name="predict", version_base="1.3")
@exit_on_error  # inside hydra.main: a MatlError prints one line and exits 2, no Hydra traceback
def main(cfg: DictConfig) -> None:
    predict(cfg)


if __name__ == "__main__":
    main()
