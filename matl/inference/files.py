"""Recognition and pose for image files: enrol a gallery folder, predict query files, write JSON lines.

The library side of ``python -m matl.predict`` (the command, its options and output format:
:mod:`matl.predict`), a thin user of the Python API :class:`matl.inference.api.Recognizer`.
"""

from __future__ import annotations

import contextlib
import json
import logging
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from omegaconf import DictConfig
from PIL import Image, ImageDraw
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from matl.data.image_files import ImageFileError, list_image_candidates, read_rgba
from matl.geometry import transfer_points, warp_image
from matl.inference.api import Match, Recognizer
from matl.inference.gallery import report_skipped
from matl.inference.quantize import quantize_option
from matl.inference.recognizer_options import config_options
from matl.inference.runtime import runtime_option
from matl.models.prediction import Prediction
from matl.utils.config import is_int, validate_config
from matl.utils.errors import MatlError
from matl.utils.instantiate import instantiate_node
from matl.utils.io import write_json

log = logging.getLogger(__name__)


def _batches(items: Sequence[Path], size: int) -> Iterator[Sequence[Path]]:
    for start in range(0, len(items), size):
        yield items[start:start + size]


def _finite(value: float) -> float | None:
    return None if value != value else value  # NaN -> null (JSON has no NaN)


def record_of(path: Path, match: Match) -> dict[str, Any]:
    """The JSON line of one query file (``object`` / ``plane`` null when the product is not enrolled)."""
    return {
        "image": str(path),
        "object": match.object,
        "plane": match.plane,
        "known": match.known,
        "nearest_object": match.nearest_object,
        "anchor": match.anchor,
        "distance": _finite(match.distance),  # a keypoint baseline has no feature distance: null
        "score": _finite(match.score),  # NaN (no calibration) -> null
        "statistic": _finite(match.statistic),
        "verification": _finite(match.verification),  # 1 - ZNCC of the answer's pose (null: not verified)
        "H": None if match.H is None else match.H.tolist(),
        "gallery_image": match.gallery_image,
        # uncover: a product found lying across this one, with its own pose in the file (null: none)
        "covered_by": None if match.covered_by is None else {
            "object": match.covered_by.object, "plane": match.covered_by.plane,
            "verification": _finite(match.covered_by.verification),
            "H": None if match.covered_by.H is None else match.covered_by.H.tolist()},
    }


def plane_outline(canon_u8: torch.Tensor, canon_H_file: torch.Tensor) -> np.ndarray:
    """``(K, 2)`` the outline of a plane's foreground in its gallery image's pixels (the whole frame if empty)."""
    mask = (canon_u8.amax(0) > 0).numpy().astype(np.uint8)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    if contours:
        points = max(contours, key=cv2.contourArea)[:, 0, :].astype(np.float64)
    else:
        s = mask.shape[0] - 1.0
        points = np.array([[0.0, 0.0], [s, 0.0], [s, s], [0.0, s]])
    file_H_canon = torch.linalg.inv(canon_H_file.double())
    return transfer_points(file_H_canon[None], torch.from_numpy(points)[None])[0].numpy()


def save_visualisation(path: Path, query: np.ndarray, match: Match, warped: np.ndarray, anchor: np.ndarray,
                       outline: np.ndarray | None, panel: int = 256) -> None:
    """One PNG: the query with the product's plane outlined by ``H``; the query warped into the anchor
    frame by the homography that produced ``H`` (the refined one with ``refine=true``); the anchor.

    Args:
        query: ``(h, w, 3)`` float original query image.
        warped, anchor: ``(S, S, 3)`` float model-frame images.
        outline: ``(K, 2)`` the plane's outline in gallery-image pixels (None: no pose).
    """
    def to_pil(x: np.ndarray) -> Image.Image:
        return Image.fromarray((np.clip(x, 0.0, 1.0) * 255.0).round().astype(np.uint8))

    h, w = query.shape[:2]
    scale = panel / h
    left = to_pil(query).resize((max(1, round(w * scale)), panel), Image.Resampling.BILINEAR)
    draw = ImageDraw.Draw(left)
    colour = (0, 255, 0) if match.known else (255, 0, 0)
    if match.H is not None and outline is not None:
        mapped = transfer_points(torch.from_numpy(match.H)[None], torch.from_numpy(outline)[None])[0].numpy()
        # file pixel centres -> panel pixel centres (the panel is a plain scaled copy)
        pts = [((float(x) + 0.5) * left.width / w - 0.5, (float(y) + 0.5) * scale - 0.5) for x, y in mapped]
        if all(np.isfinite(v) for pt in pts for v in pt):
            draw.line([*pts, pts[0]], fill=colour, width=2)
    gap, title = 8, 18
    canvas = Image.new("RGB", (left.width + 2 * panel + 2 * gap, panel + title), (255, 255, 255))
    name = f"{match.nearest_object}/{match.nearest_plane}"
    verdict = f"{name}" if match.known else f"UNKNOWN (nearest {name})"
    labels = [(left, f"query: {verdict}"), (to_pil(warped).resize((panel, panel), Image.Resampling.NEAREST),
                                              "query in the anchor frame"),
              (to_pil(anchor).resize((panel, panel), Image.Resampling.NEAREST), f"anchor {match.anchor}, "
                                                                               f"d={match.distance:.3f}")]
    x = 0
    text = ImageDraw.Draw(canvas)
    for image, label in labels:
        canvas.paste(image, (x, title))
        text.text((x + 2, 2), label, fill=colour if x == 0 else (0, 0, 0))
        x += image.width + gap
    canvas.save(path)


def _viz_name(path: Path, used: set[str]) -> str:
    """``<stem>.png``, numbered when a recursive listing repeats a stem (never overwrite a picture)."""
    name, n = f"{path.stem}.png", 1
    while name in used:
        n += 1
        name = f"{path.stem}-{n}.png"
    used.add(name)
    return name


def _visualise(recognizer: Recognizer, viz_dir: Path, paths: Sequence[Path], originals: list[np.ndarray],
               matches: list[Match], pred: Prediction, queries: torch.Tensor, used: set[str]) -> None:
    gallery = recognizer.gallery
    for i, match in enumerate(matches):
        g = int(pred.gallery_index[i])
        anchor = gallery.images[g].permute(1, 2, 0).cpu().numpy()
        if pred.query_H_anchor is not None:  # the final homography (refined when refine=true)
            anchor_H_query = torch.linalg.inv(pred.query_H_anchor[i:i + 1].double().cpu())
            warped = warp_image(queries[i:i + 1].cpu(), anchor_H_query)[0]
        else:
            warped = queries[i].cpu()
        plane = recognizer.plane_at(int(pred.plane_index[i]))
        outline = plane_outline(plane.canon_u8, plane.canon_H_file) if match.H is not None else None
        save_visualisation(viz_dir / _viz_name(paths[i], used), originals[i], match,
                           warped.permute(1, 2, 0).numpy(), anchor, outline)


def predict_files(recognizer: Recognizer, files: Sequence[Path], sink: Callable[[dict[str, Any]], None],
                  viz_dir: Path | None = None, show_progress: bool = True) -> tuple[int, list[Path]]:
    """Recognise every file in batches of ``recognizer.batch_size``; each usable one gives a record to ``sink``.

    Returns:
        How many files were predicted, and the files that could not be read (each reported in one line).
    """
    if viz_dir is not None:
        viz_dir.mkdir(parents=True, exist_ok=True)
    done, bad = 0, []
    used: set[str] = set()
    columns = (TextColumn("[bold]predict"), BarColumn(), MofNCompleteColumn(), TextColumn("images"),
               TimeElapsedColumn())
    with Progress(*columns, disable=not show_progress or len(files) < 2) as progress:
        task = progress.add_task("predict", total=len(files))
        for chunk in _batches(files, recognizer.batch_size):
            paths, originals, inputs = [], [], []
            for path in chunk:
                try:
                    rgb, alpha = read_rgba(path)
                except ImageFileError as error:
                    report_skipped(path, str(error).removeprefix(f"{path}: "))
                    bad.append(path)
                    continue
                paths.append(path)
                originals.append(rgb if alpha is None else rgb * alpha[..., None])
                inputs.append(rgb if alpha is None else np.concatenate([rgb, alpha[..., None]], -1))  # alpha = mask
            if paths:
                matches, pred, queries = recognizer.predict_details(inputs)
                for path, match in zip(paths, matches, strict=True):
                    sink(record_of(path, match))
                if viz_dir is not None:
                    _visualise(recognizer, viz_dir, paths, originals, matches, pred, queries, used)
                done += len(paths)
            progress.advance(task, len(chunk))
    return done, bad


def _threshold(cfg: DictConfig) -> float | str | None:
    value = cfg.get("threshold", "auto")
    if value is None or value == "auto" or (isinstance(value, (int, float)) and not isinstance(value, bool)):
        return value
    raise MatlError(f"threshold={value} is invalid: use auto (calibrated on the gallery), a distance, or null "
                    "(closed set: every query gets its nearest product)")


def recognizer_from_config(cfg: DictConfig) -> Recognizer:
    """The :class:`Recognizer` a predict config asks for (checkpoint, device, search, refine, quantize, runtime,
    open set)."""
    refine = cfg.get("refine", False)
    if refine not in (True, False):
        raise MatlError(f"refine={refine} is invalid: use true or false")
    refiner = instantiate_node(cfg.refiner, "refiner") if refine else None
    search = instantiate_node(cfg.search, "search") if cfg.get("search") is not None else "exact"
    recognizer = Recognizer.from_checkpoint(
        cfg.ckpt, device=str(cfg.device), refine=refiner, quantize=quantize_option(cfg),
        runtime=runtime_option(cfg), search=search,
        threshold=_threshold(cfg), **config_options(cfg), gallery_fill=float(cfg.gallery_fill),
        query_fill=float(cfg.query_fill), batch_size=int(cfg.batch_size),
        foreground=cfg.get("foreground"))
    if cfg.get("image_size") is not None and int(cfg.image_size) != recognizer.image_size:
        raise MatlError(f"checkpoint {cfg.ckpt} was trained at {recognizer.image_size} px, not "
                        f"image_size={cfg.image_size}: the model size always comes from the checkpoint "
                        "(drop image_size=)")
    return recognizer


def _resolve_model(cfg: DictConfig) -> None:
    """``cfg.ckpt`` made a checkpoint path: null is the model shipped in the package, ``pretrained`` /
    ``pretrained_fast`` a shipped model by name."""
    from omegaconf import open_dict

    from matl.models import checkpoint

    if cfg.get("ckpt") in (None, ""):
        if not checkpoint.PRETRAINED.is_file():
            raise MatlError(f"ckpt=... is required: no pretrained model ships with this install "
                            f"({checkpoint.PRETRAINED} is missing); train one (python -m matl.train) and pass its "
                            "checkpoints/best.ckpt")
        with open_dict(cfg):
            cfg.ckpt = str(checkpoint.PRETRAINED)
    else:
        checkpoint.resolve_ckpt_option(cfg)


def _shard_option(cfg: DictConfig, whole: str) -> tuple[int | None, int]:
    """``(shard or None, shards)`` of a config, checked (``whole``: what a run without ``shard`` takes)."""
    shard, shards = cfg.get("shard"), cfg.get("shards", 1)
    if not is_int(shards) or shards < 1:
        raise MatlError(f"shards={shards} is invalid: use an integer >= 1 (the number of shards)")
    if shard is not None and (not is_int(shard) or not 0 <= shard < shards):
        raise MatlError(f"shard={shard} is invalid: use an integer in [0, shards={shards}) or null (the whole "
                        f"{whole})")
    return shard, shards


def enrol(cfg: DictConfig) -> dict[str, Any]:
    """Run enrol for a composed ``conf/enrol.yaml``: the gallery folder's per-product feature cache filled (one
    shard of its products with ``shard``), and with ``save`` the whole gallery written for ``Recognizer.load``;
    returns a summary.

    Raises:
        MatlError: a bad option (checked before any work), no usable gallery, or a cache that cannot be written.
    """
    from matl.utils.io import check_output_file, overwrite_option

    validate_config(cfg)
    quantize_option(cfg)
    runtime_option(cfg)
    _threshold(cfg)
    overwrite = overwrite_option(cfg)
    if cfg.get("gallery") in (None, ""):
        raise MatlError("gallery=... is required: python -m matl.enrol gallery=<dir> [save=<gallery.pt>] "
                        "[shard=<k> shards=<K>]")
    if not Path(str(cfg.gallery)).expanduser().is_dir():
        raise MatlError(f"gallery={cfg.gallery}: no such folder")
    shard, shards = _shard_option(cfg, "gallery")
    if shard is not None and (cfg.get("save") or not cfg.cache):
        raise MatlError("shard= fills the gallery's cache only: drop save= and cache=false, and save from a run "
                        "without shard= once every shard is done")
    save = check_output_file(cfg.save, "save", overwrite, example="gallery.pt") if cfg.get("save") else None
    _resolve_model(cfg)
    recognizer = recognizer_from_config(cfg)
    if shard is not None:
        products, embedded = recognizer.enrol_shard(cfg.gallery, int(shard), int(shards))
        summary = {"gallery": str(cfg.gallery), "shard": int(shard), "shards": int(shards), "products": products,
                   "embedded": embedded}
    else:
        recognizer.enrol(cfg.gallery, cache=bool(cfg.cache))
        if save is not None:
            recognizer.save(save)
        summary = {"gallery": str(cfg.gallery), "products": len(recognizer.objects),
                   "planes": len(recognizer.planes), "saved": None if save is None else str(save)}
    log.info("enrol: %s", json.dumps(summary))
    folder = cfg.get("paths", {}).get("output_dir") if isinstance(cfg.get("paths"), DictConfig) else None
    if folder:  # the run's record (a sweep of shards counts these)
        write_json(Path(str(folder)) / "enrol.json", summary)
    return summary


def predict(cfg: DictConfig, baseline_name: str | None = None) -> dict[str, Any]:
    """Run predict for a composed ``conf/predict.yaml``; returns a summary.

    ``baseline_name`` names the baseline whose node ``cfg.baseline`` is, for a config built in Python (e.g. by
    :mod:`matl.evaluation.unseen_methods`); None: the command line's ``baseline=`` choice.

    Every option, the model, the query files and the outputs (``out``, ``viz_dir``: writable, and an
    existing file replaced only with ``overwrite=true``) are checked before the gallery is enrolled.
    ``out`` is written to a temporary file beside it and renamed over it when every query is answered
    (:func:`matl.utils.io.atomic_write`): an interrupted run leaves an earlier ``out`` as it was.

    Raises:
        MatlError: a bad option, no usable gallery, or no readable query image at all (then nothing
            is written; with some readable images the others are reported and the run succeeds).
    """
    from matl.utils.io import atomic_write, check_output_file, check_output_folder, overwrite_option

    validate_config(cfg)  # batch_size, fills, device, image_size: before the checkpoint is read
    quantize_option(cfg)  # quantize=none|int8
    runtime_option(cfg)  # runtime=torch|onnxruntime
    _threshold(cfg)
    overwrite = overwrite_option(cfg)
    shard, shards = _shard_option(cfg, "set of query files")
    for key in ("gallery", "images", "out"):
        if cfg.get(key) in (None, ""):
            raise MatlError(f"{key}=... is required: python -m matl.predict gallery=<dir> images=<dir or file> "
                            "out=<file.jsonl> [ckpt=<path>]")
    out = check_output_file(cfg.out, "out", overwrite)  # before any work: nothing of the user's is replaced
    viz_dir = check_output_folder(cfg.viz_dir, ["*.png"], "viz_dir", overwrite) if cfg.viz else None
    if not Path(str(cfg.gallery)).expanduser().is_dir():
        raise MatlError(f"gallery={cfg.gallery}: no such folder")
    files = list_image_candidates(cfg.images, bool(cfg.get("recursive", False)))
    if not files:
        raise MatlError(f"images={cfg.images} holds no files")
    if shard is not None:  # files k, k + K, ... of the sorted list: shards together answer every file once
        files = files[shard::shards]
        if not files:
            raise MatlError(f"shard={shard} of shards={shards} holds no file: images={cfg.images} has fewer files "
                            "than shards; use shards=<at most the number of files>")
    _resolve_model(cfg)
    baseline = None
    if cfg.get("baseline") is not None:  # a keypoint baseline on the same files, framed the same way
        from matl.inference.baseline_files import baseline_recognizer_from_config
        from matl.utils.runs import hydra_choice

        baseline = baseline_name or hydra_choice("baseline") or str(cfg.baseline._target_).rsplit(".", 1)[-1]
        recognizer: Any = baseline_recognizer_from_config(cfg, baseline)
    else:
        recognizer = recognizer_from_config(cfg)
    recognizer.enrol(cfg.gallery, cache=bool(cfg.cache))
    unknown = 0
    with contextlib.ExitStack() as stack:
        handle = None

        def sink(record: dict[str, Any]) -> None:
            nonlocal handle, unknown
            unknown += not record["known"]
            if handle is None:  # opened on the first answer: a run with no readable image writes no file
                handle = stack.enter_context(atomic_write(out))
            handle.write(json.dumps(record) + "\n")

        done, bad = predict_files(recognizer, files, sink, viz_dir)
        if done == 0:
            names = ", ".join(str(p) for p in bad[:5]) + (f" and {len(bad) - 5} more" if len(bad) > 5 else "")
            raise MatlError(f"images={cfg.images}: no readable image among {len(bad)} file(s) ({names}); "
                            f"nothing was written to {out}")
    gallery = recognizer.gallery
    summary = {"predicted": done, "skipped": len(bad), "skipped_files": [str(p) for p in bad], "out": str(out),
               "image_size": recognizer.image_size, "N": recognizer.num_anchors,
               "gallery_objects": len(gallery.object_names), "gallery_planes": len(recognizer.planes),
               "unknown": unknown, "threshold": recognizer.threshold,
               "viz_dir": None if viz_dir is None else str(viz_dir), "shard": shard, "shards": shards,
               **recognizer.options()}
    log.info("predict: %s", json.dumps(summary))
    return summary
