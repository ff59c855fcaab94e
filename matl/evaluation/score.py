"""Scoring a predictions JSONL file against a truth JSONL file in file pixels.

The library side of ``python -m matl.score`` (the command and its options: :mod:`matl.score`).
"""

from __future__ import annotations

import json
import logging
import math
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig
from PIL import Image, UnidentifiedImageError

from matl.data.image_files import fit_geometry
from matl.geometry import corner_error_px, frobenius_pose_error
from matl.metrics import pose_metrics
from matl.utils.config import validate_config
from matl.utils.errors import MatlError
from matl.utils.io import write_csv

log = logging.getLogger(__name__)

METRICS = ("rec_acc", "plane_acc", "pose_err", "corner_err_px", "corner_err_px_median", "pose_acc_5px")
EXIF_ORIENTATION = 0x0112  # values 5-8 swap width and height (as predict's exif_transpose)


@dataclass
class Truth:
    """One labelled query file."""

    image: Path
    object: str
    plane: str | None
    gallery_image: Path | None
    H: np.ndarray | None  # (3, 3) query_file_H_gallery_file


def _resolve(value: str, base: Path) -> Path:
    path = Path(value).expanduser()
    return path if path.is_absolute() else base / path


def _matrix(value: Any, where: str) -> np.ndarray | None:
    if value is None:
        return None
    try:
        H = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise MatlError(f"{where}: H is not a 3x3 matrix of numbers") from None
    if H.shape != (3, 3):
        raise MatlError(f"{where}: H has shape {H.shape}, expected 3x3")
    return H


def _read_jsonl(path: Path, what: str) -> list[tuple[int, dict[str, Any]]]:
    if not path.is_file():
        raise MatlError(f"{what}={path}: no such file")
    rows = []
    with open(path) as f:
        for number, line in enumerate(f, 1):
            if not line.strip():
                continue
            try:
                row = json.loads(line)
            except json.JSONDecodeError as error:
                raise MatlError(f"{path}:{number}: not a JSON line ({error.msg})") from None
            if not isinstance(row, dict):
                raise MatlError(f"{path}:{number}: expected a JSON object")
            rows.append((number, row))
    return rows


def read_predictions(path: str | Path) -> list[dict[str, Any]]:
    """predict's JSON lines: one file, or every ``*.jsonl`` under a folder (the shards of ``matl.predict
    shard=<k> shards=<K>``, each one's ``out=``), merged; an image answered in two files is a one-line error (shards
    that overlap, or a folder holding two runs)."""
    path = Path(path).expanduser()
    files = sorted(p for p in path.rglob("*.jsonl") if p.is_file()) if path.is_dir() else [path]
    if not files:
        raise MatlError(f"predictions={path}: the folder holds no .jsonl file (give predict's out= file, or the "
                        "folder of its shards' files)")
    records: list[dict[str, Any]] = []
    first: dict[str, Path] = {}
    for file in files:
        for _, row in _read_jsonl(file, "predictions"):
            image = str(row.get("image", ""))
            if image in first:
                raise MatlError(f"predictions={path}: {image} is answered in both {first[image]} and {file}: give "
                                "the files of one run's shards (each file answered once)")
            first[image] = file
            records.append(row)
    return records


def read_truth(path: str | Path) -> list[Truth]:
    """The ground-truth sidecar (see the module docstring); paths resolved against its folder."""
    path = Path(path).expanduser()
    base = path.parent
    truth = []
    for number, row in _read_jsonl(path, "truth"):
        where = f"{path}:{number}"
        for key in ("image", "object"):
            if not isinstance(row.get(key), str) or not row[key]:
                raise MatlError(f"{where}: '{key}' is required (a string)")
        H = _matrix(row.get("H"), where)
        gallery = row.get("gallery_image")
        if H is not None and not gallery:
            raise MatlError(f"{where}: H needs 'gallery_image' (the canonical image file H starts from)")
        truth.append(Truth(_resolve(row["image"], base).resolve(), row["object"], row.get("plane"),
                           None if not gallery else _resolve(gallery, base).resolve(), H))
    if not truth:
        raise MatlError(f"truth={path} holds no queries")
    if len({t.image for t in truth}) != len(truth):
        raise MatlError(f"truth={path} lists a query file twice")
    return truth


def match_predictions(truth: list[Truth], predictions: list[dict[str, Any]], truth_base: Path,
                      cwd: Path | None = None) -> list[dict[str, Any] | None]:
    """The prediction record of each truth query (None if predict gave none)."""
    cwd = cwd or Path.cwd()
    by_path: dict[Path, dict[str, Any]] = {}
    by_name: dict[str, list[dict[str, Any]]] = {}
    for record in predictions:
        image = Path(str(record.get("image", ""))).expanduser()
        for base in (cwd, truth_base):
            by_path.setdefault((image if image.is_absolute() else base / image).resolve(), record)
        by_name.setdefault(image.name, []).append(record)
    names = Counter(t.image.name for t in truth)
    matched = []
    for t in truth:
        record = by_path.get(t.image)
        if record is None and names[t.image.name] == 1 and len(by_name.get(t.image.name, [])) == 1:
            record = by_name[t.image.name][0]
        matched.append(record)
    return matched


def image_size_of(path: Path, cache: dict[Path, tuple[int, int]]) -> tuple[int, int]:
    """``(height, width)`` of an image file as predict sees it (EXIF orientation applied); header only."""
    if path not in cache:
        try:
            with Image.open(path) as img:
                width, height = img.size
                if img.getexif().get(EXIF_ORIENTATION, 1) in (5, 6, 7, 8):
                    width, height = height, width
        except (OSError, UnidentifiedImageError) as error:
            raise MatlError(f"{path}: cannot read the image size ({' '.join(str(error).split())})") from None
        cache[path] = (height, width)
    return cache[path]


def to_model_frame(H: np.ndarray, gallery_file: Path, query_file: Path, image_size: int, gallery_fill: float,
                   query_fill: float, sizes: dict[Path, tuple[int, int]]) -> torch.Tensor:
    """A file-pixel ``query_file_H_gallery_file`` as the model-frame ``query_H_canon`` (``H[2,2] = 1``)."""
    gallery_fit = fit_geometry(*image_size_of(gallery_file, sizes), image_size, gallery_fill)
    query_fit = fit_geometry(*image_size_of(query_file, sizes), image_size, query_fill)
    model = query_fit.model_H_file @ torch.as_tensor(H, dtype=torch.float64) @ torch.linalg.inv(
        gallery_fit.model_H_file)
    return model / model[2, 2]


def _gallery_file(value: str, truth: Truth, truth_base: Path | None) -> Path:
    """A prediction's ``gallery_image``: as written (absolute or relative to the current folder), else
    relative to the sidecar's folder, else ``<object>/<plane file>`` in the truth's gallery folder."""
    path = Path(value).expanduser()
    candidates = [path] if path.is_absolute() else [Path.cwd() / path]
    if not path.is_absolute() and truth_base is not None:
        candidates.append(truth_base / path)
    if truth.gallery_image is not None and len(path.parts) >= 2:
        candidates.append(truth.gallery_image.parent.parent / path.parts[-2] / path.parts[-1])
    for candidate in candidates:
        if candidate.is_file():
            return candidate.resolve()
    raise MatlError(f"prediction for {truth.image}: gallery_image {value} not found (run the scorer from the folder "
                    "predict ran in, or keep the gallery where it was)")


def _number(value: torch.Tensor | float) -> float | None:
    value = float(value)
    return value if math.isfinite(value) else None


def score(truth: list[Truth], predictions: list[dict[str, Any] | None], image_size: int,
          gallery_fill: float = 1.0, query_fill: float = 1.0, truth_base: Path | None = None,
          top_confusions: int = 10) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """the metrics of docs/design.md of matched predictions (see :func:`match_predictions`).

    Args:
        truth_base: the sidecar's folder (to find a relative ``gallery_image`` of a prediction).
    Returns:
        ``(summary, per_query_rows)``; pose metrics are None when no pose can be compared (a truth
        or a prediction without ``H``, e.g. a TL model) or no query is recognised.
    """
    named = {p["object"] for p in predictions if p and p.get("object") is not None}  # null: answered unknown
    objects = sorted({t.object for t in truth} | named)
    index = {name: i for i, name in enumerate(objects)}
    sizes: dict[Path, tuple[int, int]] = {}
    # a query answered with no product (unknown, or a keypoint baseline that matched nothing) may come without H
    pose_known = all(t.H is not None for t in truth) and all(
        p.get("H") is not None and p.get("gallery_image") for p in predictions
        if p is not None and p.get("object") is not None)
    pred_obj, true_obj, est_H, true_H, rows = [], [], [], [], []
    plane_ok = 0
    for t, p in zip(truth, predictions, strict=True):
        obj = p.get("object") if p else None
        plane = p.get("plane") if p else None
        correct = obj == t.object
        plane_ok += int(correct and plane == t.plane)
        pred_obj.append(index.get(obj, -1) if obj is not None else -1)
        true_obj.append(index[t.object])
        row: dict[str, Any] = {"image": str(t.image), "true_object": t.object, "true_plane": t.plane,
                               "pred_object": obj, "pred_plane": plane, "distance": p.get("distance") if p else None,
                               "correct": int(correct), "plane_correct": int(correct and plane == t.plane)}
        if pose_known:
            true_model = to_model_frame(t.H, t.gallery_image, t.image, image_size, gallery_fill, query_fill, sizes)
            est_model = torch.eye(3, dtype=torch.float64)  # no prediction: not recognised, the pose is not used
            if p is not None and p.get("H") is not None and p.get("gallery_image"):
                gallery = _gallery_file(str(p["gallery_image"]), t, truth_base)
                est_model = to_model_frame(_matrix(p["H"], f"prediction for {t.image}"), gallery, t.image,
                                           image_size, gallery_fill, query_fill, sizes)
            true_H.append(true_model)
            est_H.append(est_model)
            size = (image_size, image_size)
            row["corner_err_px"] = float(corner_error_px(est_model[None], true_model[None], size)[0])
            row["frobenius_err"] = float(frobenius_pose_error(est_model[None], true_model[None], size)[0])
        rows.append(row)
    metrics = pose_metrics(image_size)
    metrics.update(torch.tensor(pred_obj), torch.tensor(true_obj),
                   torch.stack(est_H) if pose_known else None,
                   torch.stack(true_H) if pose_known else torch.eye(3, dtype=torch.float64).expand(len(truth), 3, 3))
    values = {k: _number(v) for k, v in metrics.compute().items()}
    values["plane_acc"] = plane_ok / len(truth)

    per_object: dict[str, dict[str, Any]] = {}
    confusions: Counter[tuple[str, str]] = Counter()
    for row in rows:
        entry = per_object.setdefault(row["true_object"], {"queries": 0, "correct": 0})
        entry["queries"] += 1
        entry["correct"] += row["correct"]
        if not row["correct"]:
            confusions[(row["true_object"], str(row["pred_object"]))] += 1
    for entry in per_object.values():
        entry["rec_acc"] = entry["correct"] / entry["queries"]
    summary = {
        **{k: values.get(k) for k in METRICS},
        "num_queries": len(truth),
        "missing_predictions": sum(p is None for p in predictions),
        "num_objects": len({t.object for t in truth}),
        "num_planes": len({(t.object, t.plane) for t in truth}),
        "image_size": int(image_size), "gallery_fill": float(gallery_fill), "query_fill": float(query_fill),
        "pose_threshold_px": 5.0 * image_size / 100.0,
        "per_object": dict(sorted(per_object.items())),
        "confusions": [{"true": a, "predicted": b, "count": n} for (a, b), n in confusions.most_common(top_confusions)],
    }
    return summary, rows


def write_rows(path: Path, rows: list[dict[str, Any]]) -> None:
    """``per_query.csv``: one row per truth query (nothing is written for no rows)."""
    if rows:
        write_csv(path, rows)


def model_size(cfg: DictConfig) -> int:
    """The model side ``S``: from ``ckpt=`` (which must agree with ``image_size=`` if both are given)."""
    size = cfg.get("image_size")
    if cfg.get("ckpt") not in (None, ""):
        from matl.models.checkpoint import checkpoint_info, load_checkpoint

        ckpt_size, _ = checkpoint_info(load_checkpoint(cfg.ckpt), cfg.ckpt)
        if size is not None and int(size) != ckpt_size:
            raise MatlError(f"image_size={size} differs from the checkpoint's {ckpt_size} px: drop image_size=")
        return ckpt_size
    if size is None:
        raise MatlError("the model size is needed to compare poses at model resolution: pass ckpt=<the checkpoint "
                        "predict used> or image_size=<S>")
    return int(size)


def score_files(predictions: str | Path, truth: str | Path, image_size: int, gallery_fill: float = 1.0,
                query_fill: float = 1.0) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """Read a predict JSONL and a truth sidecar and :func:`score` them."""
    truth_path = Path(truth).expanduser()
    labelled = read_truth(truth_path)
    records = read_predictions(predictions)
    matched = match_predictions(labelled, records, truth_path.parent.resolve())
    summary, rows = score(labelled, matched, image_size, gallery_fill, query_fill, truth_path.parent.resolve())
    summary.update(predictions=str(predictions), truth=str(truth))
    return summary, rows


def run(cfg: DictConfig) -> dict[str, Any]:
    """Score for a composed ``conf/score.yaml``; writes ``score.json`` and ``per_query.csv`` in ``out``."""
    validate_config(cfg)
    for key in ("predictions", "truth"):
        if cfg.get(key) in (None, ""):
            raise MatlError(f"{key}=... is required: python -m matl.score predictions=<file.jsonl> "
                            "truth=<file.jsonl> ckpt=<path>")
    summary, rows = score_files(cfg.predictions, cfg.truth, model_size(cfg), float(cfg.gallery_fill),
                                float(cfg.query_fill))
    out = Path(cfg.out).expanduser()
    out.mkdir(parents=True, exist_ok=True)
    from matl.utils.io import write_json

    write_json(out / "score.json", summary)
    write_rows(out / "per_query.csv", rows)
    log.info("score: %s", json.dumps({k: summary[k] for k in (*METRICS, "num_queries", "missing_predictions")}))
    return summary
