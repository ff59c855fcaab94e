"""Recognition and pose for image files: enrol a gallery folder, predict query files, write JSON lines.

The library side of ``python -m matl.predict`` (the command, its options and output format:
:mod:`matl.predict`). Gallery enrolment: :mod:`matl.inference.gallery`.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig
from PIL import Image, ImageDraw
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from torch import nn

from matl.data.image_files import (
    ImageFileError,
    fit_to_model,
    list_image_candidates,
    load_image_file,
    pose_in_files,
)
from matl.geometry import transfer_points
from matl.inference.gallery import EnrolledGallery, enrol_gallery, report_skipped
from matl.inference.options import configure_recognizer
from matl.inference.quantize import apply_quantize_option, calibration_images, quantize_option
from matl.inference.recognizer import Prediction, Recognizer
from matl.models.checkpoint import build_model, checkpoint_info, file_sha256, load_checkpoint
from matl.utils.config import validate_config
from matl.utils.errors import MatlError

log = logging.getLogger(__name__)


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
