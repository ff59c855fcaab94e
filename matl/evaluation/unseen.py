"""The unseen-products benchmark: gallery and query files of products a checkpoint never saw, predicted and scored.

The library side of ``python -m matl.unseen`` (the command and its options: :mod:`matl.unseen`).
"""

from __future__ import annotations

import json
import logging
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path
from typing import Any

import hydra
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from PIL import Image

from matl.data.canonical import CanonicalSet, load_canonical
from matl.data.datamodule import footprints_from_masks
from matl.evaluation.open_set import open_set_summary, plot_open_set
from matl.evaluation.score import METRICS, score_files, write_rows
from matl.geometry import HomographySampler, warp_image
from matl.models.checkpoint import checkpoint_info, load_checkpoint
from matl.utils.config import validate_config
from matl.utils.errors import MatlError

log = logging.getLogger(__name__)

REPO = Path(__file__).resolve().parents[2]
SYNTHETIC = "matl.data.catalog.SyntheticCatalog"
CROP_FILL = 0.6  # the catalogs frame each plane's longer side at 0.6 of the image (data.source.fill)
WARP_BATCH = 250


# ------------------------------------------------------------------------------------ never seen
def _catalog_products(source: dict[str, Any]) -> list[Any]:
    """The product specs of a ``SyntheticCatalog`` config, built without Hydra (no rendering)."""
    from matl.data.catalog import SyntheticCatalog

    keys = ("catalog", "seed", "subset")
    return SyntheticCatalog(**{k: source[k] for k in keys if k in source}).products()


def seen_products(train_data: dict[str, Any], test_source: Any,
                  test_names: list[str]) -> tuple[dict[str, str], dict[str, list[str]], str]:
    """Which test products the training catalog holds, and which are only related to one.

    Args:
        train_data: the checkpoint's ``data`` config (``matl_config["data"]``).
        test_source: the instantiated source of the test products.
        test_names: the test set's object names.
    Returns:
        ``(seen, related, how)``: ``seen`` maps a test product to the reason it counts as seen (same
        name, or same brand and title); ``related`` lists looser kinships kept in the test (same
        title under another brand, same brand and kind); ``how`` says what was compared.
    """
    source = train_data.get("source") or {}
    objects = train_data.get("objects")
    if source.get("_target_") != SYNTHETIC or not hasattr(test_source, "products"):
        kind = source.get("_target_", "?")
        return {}, {}, f"not verified: the training source is {kind}, not a procedural catalog"
    train = _catalog_products(source)
    if objects is not None:
        train = [train[int(i)] for i in objects]
    by_name = {p.name: p for p in train}
    by_title = {(p.brand.name, p.title): p for p in train}
    seen: dict[str, str] = {}
    related: dict[str, list[str]] = {}
    for p in test_source.products():
        if p.name not in test_names:
            continue
        if p.name in by_name:
            seen[p.name] = f"same name as training product {p.name}"
        elif (p.brand.name, p.title) in by_title:
            seen[p.name] = f"same brand and title as training product {by_title[(p.brand.name, p.title)].name}"
        else:
            kin = [f"same title as {q.name}" for q in train if q.title == p.title]
            kin += [f"same brand and kind as {q.name}" for q in train
                    if (q.brand.name, q.kind) == (p.brand.name, p.kind)]
            if kin:
                related[p.name] = kin
    what = f"SyntheticCatalog(catalog={source.get('catalog')!r}, seed={source.get('seed')})"
    return seen, related, f"product specs compared with the training catalog {what}"


# ---------------------------------------------------------------------------------------- files
def _write_png(path: Path, image: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(image).save(path)


def _to_uint8(images: torch.Tensor) -> np.ndarray:
    return (images.clamp(0.0, 1.0) * 255.0).round().to(torch.uint8).permute(0, 2, 3, 1).numpy()


def write_gallery(cs: CanonicalSet, root: Path, crop: bool = False) -> tuple[list[Path], torch.Tensor]:
    """``<root>/<object>/<plane>.png`` per plane; returns the files and ``canon_H_file`` ``(P, 3, 3)``
    (file pixel -> canonical-image pixel: identity, or the crop's offset)."""
    paths, offsets = [], []
    for p in range(cs.num_planes):
        image, x0, y0 = cs.images[p], 0, 0
        if crop and cs.masks[p].any():
            rows, cols = np.flatnonzero(cs.masks[p].any(1)), np.flatnonzero(cs.masks[p].any(0))
            y0, x0 = int(rows[0]), int(cols[0])
            image = image[y0:int(rows[-1]) + 1, x0:int(cols[-1]) + 1]
        path = root / cs.object_names[int(cs.plane_object[p])] / f"{cs.plane_names[p]}.png"
        if path.exists():
            raise MatlError(f"{path}: two planes of one object share the name {cs.plane_names[p]!r}")
        _write_png(path, np.ascontiguousarray(image))
        paths.append(path)
        offsets.append(torch.tensor([[1.0, 0.0, x0], [0.0, 1.0, y0], [0.0, 0.0, 1.0]], dtype=torch.float64))
    return paths, torch.stack(offsets)


def write_queries(cs: CanonicalSet, sampler: HomographySampler, n: int, seed: int, root: Path,
                  gallery_files: list[Path], canon_H_file: torch.Tensor, out: Path) -> list[dict[str, Any]]:
    """``n`` warped query files ``<root>/q<i>.png`` and their ground-truth records.

    Each query draws a plane uniformly and a homography from ``sampler`` (object kept in the frame,
    as the training queries). ``H`` is ``query_H_canon`` in file pixels: gallery file -> query file.
    """
    size = (cs.image_size, cs.image_size)
    g = torch.Generator().manual_seed(int(seed))
    plane = torch.randint(cs.num_planes, (n,), generator=g)
    footprints = footprints_from_masks(torch.from_numpy(cs.masks))
    query_H_canon = sampler.sample(n, size, g, footprints[plane])
    canon = torch.from_numpy(cs.images).permute(0, 3, 1, 2)
    root.mkdir(parents=True, exist_ok=True)
    width = max(4, len(str(n - 1)))
    truth = []
    for start in range(0, n, WARP_BATCH):
        idx = plane[start:start + WARP_BATCH]
        H = query_H_canon[start:start + WARP_BATCH]
        images = _to_uint8(warp_image(canon[idx].double().div(255.0), H))
        for j, image in enumerate(images):
            i, p = start + j, int(idx[j])
            path = root / f"q{i:0{width}d}.png"
            _write_png(path, image)
            H_file = H[j] @ canon_H_file[p]
            truth.append({"image": str(path.relative_to(out)), "object": cs.object_names[int(cs.plane_object[p])],
                          "plane": cs.plane_names[p], "gallery_image": str(gallery_files[p].relative_to(out)),
                          "H": (H_file / H_file[2, 2]).tolist()})
    return truth


def left_out_products(names: list[str], fraction: float, seed: int) -> list[str]:
    """``round(fraction * len(names))`` products drawn with ``seed``, kept out of the gallery (open set)."""
    count = round(fraction * len(names))
    order = torch.randperm(len(names), generator=torch.Generator().manual_seed(int(seed) + 1)).tolist()
    return sorted(names[i] for i in order[:count])


def _left_out_dir(out: Path, name: str) -> Path:
    (out / "left_out").mkdir(exist_ok=True)
    return out / "left_out" / name


# -------------------------------------------------------------------------------------- commands
def _arg(key: str, value: Any) -> str:
    """A Hydra override ``key=value``, the value quoted when Hydra's grammar would not take it bare."""
    text = str(value).lower() if isinstance(value, bool) else str(value)
    if re.fullmatch(r"[\w./:+@-]+", text):
        return f"{key}={text}"
    return f"{key}='{text.replace(chr(92), chr(92) * 2).replace(chr(39), chr(92) + chr(39))}'"


def run_predict(args: list[str], out: Path) -> None:
    """``python -m matl.predict <args>`` in a separate process; its one-line error becomes ours."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), *filter(None, [env.get("PYTHONPATH")])])
    proc = subprocess.run([sys.executable, "-m", "matl.predict", *args], cwd=out, env=env, capture_output=True,
                          text=True)
    (out / "predict.log").write_text(proc.stdout + proc.stderr)
    if proc.returncode != 0:
        errors = [line for line in proc.stderr.splitlines() if line.startswith("error: ")]
        reason = errors[-1].removeprefix("error: ") if errors else f"exit status {proc.returncode}"
        raise MatlError(f"matl.predict failed ({reason}); its output is in {out / 'predict.log'}")


def _own_command() -> str:
    try:
        from hydra.core.hydra_config import HydraConfig

        overrides = list(HydraConfig.get().overrides.task)
    except ValueError:  # called as a function, not from the command line
        return ""
    return shlex.join(["python", "-m", "matl.unseen", *overrides])


# ------------------------------------------------------------------------------------ entry point
def _check(cfg: DictConfig) -> None:
    validate_config(cfg)
    if cfg.get("ckpt") in (None, ""):
        raise MatlError("ckpt=... is required: python -m matl.unseen ckpt=<checkpoint> [data=synthetic_apc] "
                        "[out=<dir>]")
    for key, low in (("queries", 1), ("query_seed", 0), ("file_size", 16)):
        value = cfg.get(key)
        if value is None and key == "file_size":
            continue
        if not isinstance(value, int) or isinstance(value, bool) or value < low:
            raise MatlError(f"{key}={value} is invalid: use an integer >= {low}")
    leave_out = cfg.get("leave_out", 0.0)
    if not isinstance(leave_out, (int, float)) or isinstance(leave_out, bool) or not 0.0 <= leave_out < 1.0:
        raise MatlError(f"leave_out={leave_out} is invalid: use a fraction in [0, 1) of the products kept out of "
                        "the gallery (open set)")
    for key in ("exclude_seen", "gallery_crop", "refine"):
        if not isinstance(cfg.get(key), bool):
            raise MatlError(f"{key}={cfg.get(key)} is invalid: use true or false")


def unseen(cfg: DictConfig) -> dict[str, Any]:
    """Run the measurement for a composed ``conf/unseen.yaml``; returns what ``unseen.json`` holds."""
    from matl.data.prepare import instantiate_source
    from matl.utils.io import write_json

    _check(cfg)
    ckpt_path = Path(cfg.ckpt).expanduser().resolve()
    ckpt = load_checkpoint(ckpt_path)
    size, num_anchors = checkpoint_info(ckpt, ckpt_path)
    train_data = (ckpt.get("matl_config") or {}).get("data") or {}
    del ckpt
    out = Path(cfg.out).expanduser().resolve()
    for sub in ("gallery", "queries"):
        if (out / sub).exists() and any((out / sub).iterdir()):
            raise MatlError(f"out={out} already holds {sub}/ from an earlier run: use a new out= folder")
    out.mkdir(parents=True, exist_ok=True)

    file_size = int(cfg.file_size or size)
    source = instantiate_source(cfg)
    sampler = hydra.utils.instantiate(cfg.data.homography)
    cs = load_canonical(source, file_size, cfg.paths.cache_dir)
    objects = OmegaConf.select(cfg, "data.objects")
    if objects is not None:
        cs = cs.subset_objects(list(objects))
    seen, related, how = seen_products(train_data, source, cs.object_names)
    if not cfg.exclude_seen:
        seen = {}
    keep = [i for i, name in enumerate(cs.object_names) if name not in seen]
    if not keep:
        raise MatlError(f"every product of {source!r} is in the checkpoint's training catalog: pick another "
                        "data= (e.g. synthetic_apc) or data.source.seed=")
    cs = cs.subset_objects(keep)
    log.info("unseen: %d products (%d planes), %d excluded as seen: %s", cs.num_objects, cs.num_planes, len(seen),
             sorted(seen))

    crop = bool(cfg.gallery_crop)
    gallery_fill = float(cfg.gallery_fill if cfg.gallery_fill is not None else (CROP_FILL if crop else 1.0))
    query_fill = float(cfg.query_fill)
    gallery_files, canon_H_file = write_gallery(cs, out / "gallery", crop)
    truth = write_queries(cs, sampler, int(cfg.queries), int(cfg.query_seed), out / "queries", gallery_files,
                          canon_H_file, out)
    left_out = left_out_products(cs.object_names, float(cfg.leave_out), int(cfg.query_seed))
    for name in left_out:  # their gallery files move out of the gallery: predict never sees them
        (out / "gallery" / name).rename(_left_out_dir(out, name))
    for t in truth:
        t["enrolled"] = t["object"] not in left_out
        if not t["enrolled"]:
            t["gallery_image"] = str(Path("left_out") / Path(t["gallery_image"]).relative_to("gallery"))
    truth_path, pred_path = out / "truth.jsonl", out / "predictions.jsonl"
    truth_path.write_text("".join(json.dumps(t) + "\n" for t in truth if t["enrolled"]))
    if left_out:
        (out / "truth_left_out.jsonl").write_text("".join(json.dumps(t) + "\n" for t in truth if not t["enrolled"]))

    threshold = cfg.get("threshold", "auto") if left_out else None  # leave_out=0: the closed-set benchmark
    predict_args = [_arg("ckpt", ckpt_path), _arg("gallery", out / "gallery"), _arg("images", out / "queries"),
                    _arg("out", pred_path), _arg("gallery_fill", gallery_fill), _arg("query_fill", query_fill),
                    _arg("batch_size", cfg.batch_size), _arg("device", cfg.device), _arg("refine", cfg.refine),
                    _arg("threshold", "null" if threshold is None else threshold),
                    _arg("open_set_quantile", cfg.get("open_set_quantile", 0.94))]
    run_predict([*predict_args, _arg("hydra.run.dir", out / "predict")], out)
    open_set = None
    if left_out:
        predictions = {str(Path(r["image"]).relative_to(out)) if Path(r["image"]).is_absolute() else r["image"]: r
                       for r in map(json.loads, pred_path.read_text().splitlines())}
        open_set = open_set_summary(truth, predictions)
        write_json(out / "open_set.json", {**open_set, "left_out": left_out})
        plot_open_set(open_set, out / "open_set.png")
        open_set = {k: v for k, v in open_set.items() if k != "curve"}
        log.info("unseen: open set %s", json.dumps(open_set))
    summary, rows = score_files(pred_path, truth_path, size, gallery_fill, query_fill)
    score_args = [_arg("predictions", pred_path), _arg("truth", truth_path), _arg("ckpt", ckpt_path),
                  _arg("gallery_fill", gallery_fill), _arg("query_fill", query_fill), _arg("out", out / "score")]

    unrelated = [r for r in rows if r["true_object"] not in related]
    result = {
        **{k: summary[k] for k in METRICS},
        "rec_acc_unrelated": sum(r["correct"] for r in unrelated) / len(unrelated) if unrelated else None,
        "num_queries_unrelated": len(unrelated),
        "num_queries": summary["num_queries"], "missing_predictions": summary["missing_predictions"],
        "num_objects": cs.num_objects, "num_planes": cs.num_planes,
        "checkpoint": str(ckpt_path), "image_size": size, "N": num_anchors,
        "data": OmegaConf.to_container(cfg.data.source, resolve=True), "products": list(cs.object_names),
        "excluded_seen": seen, "related": related, "seen_check": how,
        "train_data": train_data.get("source"),
        "query_seed": int(cfg.query_seed), "file_size": file_size, "gallery_crop": crop,
        "gallery_fill": gallery_fill, "query_fill": query_fill, "refine": bool(cfg.refine),
        "homography": OmegaConf.to_container(cfg.data.homography, resolve=True),
        "pose_threshold_px": summary["pose_threshold_px"],
        "per_object": summary["per_object"], "confusions": summary["confusions"],
        "commands": {"unseen": _own_command(),
                     "predict": shlex.join(["python", "-m", "matl.predict", *predict_args]),
                     "score": shlex.join(["python", "-m", "matl.score", *score_args])},
        "files": {"gallery": "gallery", "queries": "queries", "truth": truth_path.name,
                  "predictions": pred_path.name, "per_query": "per_query.csv"},
    }
    if open_set is not None:
        result["open_set"] = {**open_set, "left_out": left_out, "curve": "open_set.json", "figure": "open_set.png"}
    write_json(out / "unseen.json", result)
    write_rows(out / "per_query.csv", rows)
    log.info("unseen: %s", json.dumps({k: result[k] for k in (*METRICS, "num_queries", "num_objects")}))
    return result
