"""The unseen-products benchmark: gallery and query files of products a checkpoint never saw, predicted and scored.

The library side of ``python -m matl.unseen`` (the command and its options: :mod:`matl.unseen`). Every
condition (:mod:`matl.evaluation.conditions`) is written from the same products and query poses into
``<out>/<condition>/`` and predicted by every method through ``python -m matl.predict`` (MATL, MATL with
refinement, and the keypoint baselines with ``baseline=``, on the same files framed the same way), scored
by :func:`score_condition` (:mod:`matl.evaluation.score`'s metrics) and timed in this process on the same queries.
"""

from __future__ import annotations

import itertools
import json
import logging
import os
import re
import shlex
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import hydra
import numpy as np
import torch
from omegaconf import DictConfig, ListConfig, OmegaConf
from PIL import Image

from matl.data.canonical import CanonicalSet, load_canonical, require_models
from matl.data.occluders import Occluders
from matl.evaluation.conditions import (
    CONDITIONS,
    Clutter,
    DarkFloor,
    ImperfectMask,
    Photometric,
    composite,
    condition_rng,
    heldout_backgrounds,
    other_plane,
    sample_poses,
    scale_pixels,
    to_uint8,
    warp_planes,
)
from matl.evaluation.open_set import open_set_summary, plot_open_set
from matl.evaluation.score import METRICS, match_predictions, read_truth, score, write_rows
from matl.geometry import HomographySampler
from matl.inference.runtime import runtime_option
from matl.models.checkpoint import checkpoint_info, load_checkpoint
from matl.utils.config import validate_config
from matl.utils.errors import MatlError

log = logging.getLogger(__name__)

REPO = Path(__file__).resolve().parents[2]
SYNTHETIC = "matl.data.catalog.SyntheticCatalog"
SHELVES = "matl.data.catalog.shelves.ShelfCatalog"
CROP_FILL = 0.6  # the catalogs frame each plane's longer side at 0.6 of the image (data.source.fill)
WARP_BATCH = 250
METHODS = ("matl", "matl_refine", "sift", "sift_ecc", "lightglue", "xfeat", "xfeat_lighterglue")


# ------------------------------------------------------------------------------------ never seen
def _catalog_products(source: dict[str, Any]) -> list[Any]:
    """The product specs of a procedural catalog's config (``SyntheticCatalog``, ``ShelfCatalog``): the
    catalog is built from its own config, which renders nothing until asked."""
    return hydra.utils.instantiate(source).products()


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
    if source.get("_target_") not in (SYNTHETIC, SHELVES) or not hasattr(test_source, "products"):
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
    what = (f"ShelfCatalog(shelves={source.get('shelves')}, first_seed={source.get('first_seed')})"
            if source.get("_target_") == SHELVES else
            f"SyntheticCatalog(catalog={source.get('catalog')!r}, seed={source.get('seed')})")
    return seen, related, f"product specs compared with the training catalog {what}"


# ---------------------------------------------------------------------------------------- files
def _write_png(path: Path, image: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(image).save(path)


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


def _record(path: Path, out: Path, cs: CanonicalSet, p: int, gallery_files: list[Path], H_file: torch.Tensor,
            **extra: Any) -> dict[str, Any]:
    """One ground-truth line (:mod:`matl.score`'s sidecar): ``H`` = ``query_H_canon`` gallery file -> query file."""
    H_file = H_file.double()
    return {"image": str(path.relative_to(out)), "object": cs.object_names[int(cs.plane_object[p])],
            "plane": cs.plane_names[p], "gallery_image": str(gallery_files[p].relative_to(out)),
            "H": (H_file / H_file[2, 2]).tolist(), **extra}


def _query_name(root: Path, i: int, n: int, suffix: str = ".png") -> Path:
    return root / f"q{i:0{max(4, len(str(n - 1)))}d}{suffix}"


def write_true_mask(out: Path, query: Path, coverage: np.ndarray) -> str:
    """The target product's true visible mask of a query, ``<out>/masks/<query stem>.png`` (uint8 0/255: coverage
    ``(H, W)`` above 0.5), to score a foreground step's mask; returns its path relative to ``out`` (``mask_file``)."""
    path = out / "masks" / f"{query.stem}.png"
    _write_png(path, np.where(coverage > 0.5, 255, 0).astype(np.uint8))
    return str(path.relative_to(out))


def write_queries(cs: CanonicalSet, sampler: HomographySampler, n: int, seed: int, root: Path,
                  gallery_files: list[Path], canon_H_file: torch.Tensor, out: Path) -> list[dict[str, Any]]:
    """``n`` warped query files ``<root>/q<i>.png`` (the ``clean`` condition) and their ground-truth records.

    Each query draws a plane uniformly and a homography from ``sampler`` (object kept in the frame,
    as the training queries). ``H`` is ``query_H_canon`` in file pixels: gallery file -> query file.
    """
    plane, query_H_canon = sample_poses(cs, sampler, n, seed)
    return write_clean(cs, plane, query_H_canon, root, gallery_files, canon_H_file, out)


def write_clean(cs: CanonicalSet, plane: torch.Tensor, query_H_canon: torch.Tensor, root: Path,
                gallery_files: list[Path], canon_H_file: torch.Tensor, out: Path) -> list[dict[str, Any]]:
    """The planes ``(n,)`` warped by their poses ``(n, 3, 3)``, one PNG each; returns the truth records."""
    n = len(plane)
    root.mkdir(parents=True, exist_ok=True)
    truth = []
    for start in range(0, n, WARP_BATCH):
        idx, H = plane[start:start + WARP_BATCH], query_H_canon[start:start + WARP_BATCH]
        images, _ = warp_planes(cs, idx, H)
        for j, image in enumerate(images):
            i, p = start + j, int(idx[j])
            path = _query_name(root, i, n)
            _write_png(path, to_uint8(image))
            truth.append(_record(path, out, cs, p, gallery_files, H[j] @ canon_H_file[p]))
    return truth


@dataclass
class Queries:
    """What every condition starts from: the held-out products and the queries' planes and poses.

    Attributes:
        cs: the products' canonical set at ``file_size``.
        plane: ``(n,)`` int64 plane of each query; query_H_canon: ``(n, 3, 3)`` float64 its pose.
        seed: ``query_seed``.
        source: the instantiated data source; source_objects: the source's object index of each of
            ``cs``'s objects (to take the same products from the source's other renders).
        cfg: the composed ``conf/unseen.yaml``.
    """

    cs: CanonicalSet
    plane: torch.Tensor
    query_H_canon: torch.Tensor
    seed: int
    source: Any
    source_objects: list[int]
    cfg: DictConfig

    def at_size(self, size: int) -> CanonicalSet:
        """The same products rendered at ``size`` px (cached like every canonical set)."""
        if size == self.cs.image_size:
            return self.cs
        return load_canonical(self.source, size, self.cfg.paths.cache_dir).subset_objects(self.source_objects)


def _node(cfg: DictConfig, key: str) -> dict[str, Any]:
    return {k: tuple(v) if isinstance(v, (list, ListConfig)) else v
            for k, v in OmegaConf.to_container(cfg[key], resolve=True).items()}


def write_photometric(q: Queries, root: Path, gallery_files: list[Path], canon_H_file: torch.Tensor,
                      out: Path) -> list[dict[str, Any]]:
    """The clean warps through :class:`~matl.evaluation.conditions.Photometric`, saved as JPEG files."""
    camera = Photometric(**_node(q.cfg, "photometric"))
    images, _ = warp_planes(q.cs, q.plane, q.query_H_canon)
    root.mkdir(parents=True, exist_ok=True)
    truth = []
    for i, image in enumerate(images):
        p = int(q.plane[i])
        data, params = camera.apply(image, condition_rng(q.seed, "photometric", i))
        path = _query_name(root, i, len(images), ".jpg")
        path.write_bytes(data)
        truth.append(_record(path, out, q.cs, p, gallery_files, q.query_H_canon[i] @ canon_H_file[p],
                             photometric=params))
    return truth


def write_mask(q: Queries, root: Path, gallery_files: list[Path], canon_H_file: torch.Tensor,
               out: Path) -> list[dict[str, Any]]:
    """RGBA files: the warp composited on a real background, alpha an :class:`ImperfectMask` of the true one."""
    segmenter = ImperfectMask(**_node(q.cfg, "mask"))
    backgrounds = heldout_backgrounds(tuple(q.cfg.backgrounds.crop))
    images, masks = warp_planes(q.cs, q.plane, q.query_H_canon)
    truth = []
    for i, (image, mask) in enumerate(zip(images, masks, strict=True)):
        p, rng = int(q.plane[i]), condition_rng(q.seed, "mask", i)
        rgb = composite(backgrounds.sample(q.cs.image_size, rng), image, mask)
        alpha, params = segmenter.apply(mask > 0.5, rng)
        path = _query_name(root, i, len(images))
        _write_png(path, np.concatenate([to_uint8(rgb), alpha[..., None].astype(np.uint8) * 255], axis=-1))
        truth.append(_record(path, out, q.cs, p, gallery_files, q.query_H_canon[i] @ canon_H_file[p], mask=params,
                             mask_file=write_true_mask(out, path, mask)))
    return truth


def write_clutter(q: Queries, root: Path, gallery_files: list[Path], canon_H_file: torch.Tensor,
                  out: Path) -> list[dict[str, Any]]:
    """RGB files: a real background, a neighbouring product cut by the crop's edge, the product on top."""
    clutter = Clutter(**_node(q.cfg, "clutter"))
    backgrounds = heldout_backgrounds(tuple(q.cfg.backgrounds.crop))
    sampler = hydra.utils.instantiate(q.cfg.data.homography)
    images, masks = warp_planes(q.cs, q.plane, q.query_H_canon)
    size = q.cs.image_size
    truth = []
    for i, (image, mask) in enumerate(zip(images, masks, strict=True)):
        p, rng = int(q.plane[i]), condition_rng(q.seed, "clutter", i)
        other = other_plane(q.cs, p, rng)
        g = torch.Generator().manual_seed(int(rng.integers(2**62)))
        own_H = sampler.sample(1, (size, size), g)[0]
        neighbour, neighbour_mask = warp_planes(q.cs, torch.tensor([other]),
                                                clutter.neighbour_H(own_H, size, rng)[None])
        scene = composite(composite(backgrounds.sample(size, rng), neighbour[0], neighbour_mask[0]), image, mask)
        path = _query_name(root, i, len(images))
        _write_png(path, to_uint8(scene))
        truth.append(_record(path, out, q.cs, p, gallery_files, q.query_H_canon[i] @ canon_H_file[p],
                             neighbour={"object": q.cs.object_names[int(q.cs.plane_object[other])],
                                        "plane": q.cs.plane_names[other]},
                             mask_file=write_true_mask(out, path, mask)))  # the product lies on top: all of it
    return truth


def _weighted(weights: dict[str, float], rng: np.random.Generator) -> str:
    """One name of ``weights`` (name -> weight >= 0, some > 0), drawn in proportion."""
    names = list(weights)
    p = np.array([float(weights[n]) for n in names])
    return names[int(rng.choice(len(names), p=p / p.sum()))]


def write_occluded(q: Queries, root: Path, gallery_files: list[Path], canon_H_file: torch.Tensor,
                   out: Path) -> list[dict[str, Any]]:
    """The product in a picking bin, partly hidden (:class:`~matl.data.occluders.Occluders`).

    Each query: a floor (dark, :class:`DarkFloor`, or a held-out background photo, by ``occluded.floors``), the
    product on it, then one occluder hiding a fraction drawn in ``occluded.hidden``; the ``product`` occluders
    are the other held-out products' prints, the bin wall's texture another background crop. A share
    ``occluded.rgba_share`` of the files is RGBA with alpha the visible part of the product; the rest is RGB.
    The truth adds ``hidden_fraction``, ``occluder``, ``floor``, ``rgba`` and ``mask_file`` (the visible mask).
    """
    node = q.cfg.occluded
    occluders = Occluders(dict(node.kinds), tuple(node.hidden))
    floors = {str(k): float(v) for k, v in node.floors.items()}
    dark, rgba_share = DarkFloor(**_node(node, "dark_floor")), float(node.rgba_share)
    backgrounds = heldout_backgrounds(tuple(q.cfg.backgrounds.crop))
    cs, size = q.cs, q.cs.image_size
    if occluders.kinds.get("product", 0.0) > 0 and cs.num_objects < 2:
        raise MatlError("condition=occluded lays other products on the query's: it needs at least two products, or "
                        "occluded.kinds.product=0")
    prints = [(cs.images[j].astype(np.float64) / 255.0, cs.masks[j].astype(np.float64)) for j in range(cs.num_planes)]
    images, masks = warp_planes(cs, q.plane, q.query_H_canon)
    root.mkdir(parents=True, exist_ok=True)
    truth = []
    for i, (image, mask) in enumerate(zip(images, masks, strict=True)):
        p, rng = int(q.plane[i]), condition_rng(q.seed, "occluded", i)
        floor_kind = _weighted(floors, rng)
        floor = dark.sample(size, rng) if floor_kind == "dark" else backgrounds.sample(size, rng)
        others = np.flatnonzero(cs.plane_object != cs.plane_object[p])
        wall = backgrounds.sample(size, rng)
        scene, visible, info = occluders.apply(composite(floor, image, mask), mask, rng,
                                               [prints[j] for j in others], floor=wall)
        if "product_index" in info:  # the occluding print: a plane of another held-out product
            j = int(others[info.pop("product_index")])
            info["product"] = {"object": cs.object_names[int(cs.plane_object[j])], "plane": cs.plane_names[j]}
        rgba = bool(rng.random() < rgba_share)
        path = _query_name(root, i, len(images))
        pixels = to_uint8(scene)
        if rgba:
            pixels = np.concatenate([pixels, np.where(visible > 0.5, 255, 0).astype(np.uint8)[..., None]], axis=-1)
        _write_png(path, pixels)
        truth.append(_record(path, out, cs, p, gallery_files, q.query_H_canon[i] @ canon_H_file[p],
                             hidden_fraction=info["hidden_fraction"], occluder=info["occluder"], floor=floor_kind,
                             rgba=rgba, mask_file=write_true_mask(out, path, visible),
                             occlusion={k: v for k, v in info.items() if k not in ("occluder", "hidden_fraction")}))
    return truth


def write_view(q: Queries, root: Path, gallery_files: list[Path], canon_H_file: torch.Tensor,
               out: Path) -> list[dict[str, Any]]:
    """Views rendered from 3D camera poses (:class:`matl.data.view_sampler.ViewSampler`), the same planes
    as the other conditions; ``H`` the plane-induced homography of each view."""
    from matl.data.view_pool import load_view_pool
    from matl.data.view_sampler import ViewSampler

    source = require_models(q.source, "condition=view")
    counts = torch.bincount(q.plane, minlength=q.cs.num_planes)
    sampler = ViewSampler(**_node(q.cfg.view, "sampler"))
    pool = load_view_pool(source, q.cs.image_size, max(1, int(counts.max())), sampler, int(q.cfg.view.seed),
                          q.cfg.paths.cache_dir).subset_objects(q.source_objects)
    pool.check_matches(q.cs)
    used = np.zeros(q.cs.num_planes, dtype=np.int64)
    truth = []
    for i in range(len(q.plane)):
        p = int(q.plane[i])
        k, used[p] = int(used[p]), used[p] + 1
        path = _query_name(root, i, len(q.plane))
        _write_png(path, pool.images[p, k])
        H = torch.from_numpy(pool.query_H_canon[p, k]).double()
        truth.append(_record(path, out, q.cs, p, gallery_files, H @ canon_H_file[p], view=k))
    return truth


def write_sizes(q: Queries, root: Path, gallery_files: list[Path], canon_H_file: torch.Tensor,
                out: Path) -> list[dict[str, Any]]:
    """The clean poses at ``sizes.query`` px, rendered at that size (the gallery is written at ``sizes.gallery``).

    A pose at the file size ``f`` becomes ``M H M^-1`` at ``s`` px (``M`` the pixel scaling by ``s / f``); the
    truth maps the ``g`` px gallery file to the query file: ``H_s @ scale(s / g) @ canon_H_file``.
    """
    f, s, g = q.cs.image_size, int(q.cfg.sizes.query), int(q.cfg.sizes.gallery)
    cs_query = q.at_size(s)
    M = scale_pixels(s / f)
    H = M @ q.query_H_canon.double() @ torch.linalg.inv(M)
    root.mkdir(parents=True, exist_ok=True)
    truth = []
    images, _ = warp_planes(cs_query, q.plane, H)
    canon_H_gallery = scale_pixels(s / g)
    for i, image in enumerate(images):
        p = int(q.plane[i])
        path = _query_name(root, i, len(images))
        _write_png(path, to_uint8(image))
        truth.append(_record(path, out, q.cs, p, gallery_files, H[i] @ canon_H_gallery @ canon_H_file[p]))
    return truth


def _write_clean_condition(q: Queries, root: Path, gallery_files: list[Path], canon_H_file: torch.Tensor,
                           out: Path) -> list[dict[str, Any]]:
    return write_clean(q.cs, q.plane, q.query_H_canon, root, gallery_files, canon_H_file, out)


WRITERS = {"clean": _write_clean_condition, "photometric": write_photometric, "mask": write_mask,
           "clutter": write_clutter, "occluded": write_occluded, "view": write_view, "sizes": write_sizes}


OPEN_SET_KEYS = {"open_set_statistic": "verify", "verify_top_k": 8, "verify_max": 0.1, "verify_blur": 1.0,
                 "verify_refine": True}


def open_set_args(cfg: DictConfig) -> list[str]:
    """predict's open-set statistic and verification overrides, from the same keys here."""
    return [_arg(key, cfg.get(key, default)) for key, default in OPEN_SET_KEYS.items()]


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


def run_predict(args: list[str], out: Path, log_name: str = "predict.log") -> None:
    """``python -m matl.predict <args>`` in a separate process; its one-line error becomes ours."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), *filter(None, [env.get("PYTHONPATH")])])
    proc = subprocess.run([sys.executable, "-m", "matl.predict", *args], cwd=out, env=env, capture_output=True,
                          text=True)
    (out / log_name).write_text(proc.stdout + proc.stderr)
    if proc.returncode != 0:
        errors = [line for line in proc.stderr.splitlines() if line.startswith("error: ")]
        reason = errors[-1].removeprefix("error: ") if errors else f"exit status {proc.returncode}"
        raise MatlError(f"matl.predict failed ({reason}); its output is in {out / log_name}")


def _task_overrides() -> list[str]:
    try:
        from hydra.core.hydra_config import HydraConfig

        return list(HydraConfig.get().overrides.task)
    except ValueError:  # called as a function, not from the command line
        return []


def _own_command() -> str:
    overrides = _task_overrides()
    return shlex.join(["python", "-m", "matl.unseen", *overrides]) if overrides else ""


def method_overrides(method: str) -> list[str]:
    """The user's own overrides of a method's settings, as predict's keys: ``foreground.*`` for matl and
    matl_refine, ``refiner=<choice>`` and ``refiner.*`` for matl_refine, ``baselines.<name>.*`` (here) ->
    ``baseline.*`` (predict) for a keypoint baseline."""
    overrides = _task_overrides()
    if method in ("matl", "matl_refine"):  # foreground=<choice> is passed on by predict_args
        keys = ("foreground.", "refiner.", "refiner=") if method == "matl_refine" else ("foreground.",)
        return [o for o in overrides if o.lstrip("+~").startswith(keys)]
    prefix = f"baselines.{method}."
    return [o.replace(prefix, "baseline.", 1) for o in overrides if o.lstrip("+~").startswith(prefix)]


def predict_args(method: str, common: list[str], foreground: str = "grabcut", runtime: str = "onnxruntime"
                 ) -> list[str]:
    """predict's overrides for one method on the files of ``common`` (ckpt, gallery, images, fills, ...);
    ``foreground`` is the choice of the ``foreground`` group and ``runtime`` the query networks' runtime for matl
    and matl_refine."""
    if method in ("matl", "matl_refine"):
        return [*common, _arg("refine", method == "matl_refine"), _arg("foreground", foreground),
                _arg("runtime", runtime), *method_overrides(method)]
    return [*[a for a in common if not a.startswith("threshold=")], _arg("baseline", method), _arg("threshold", "null"),
            *method_overrides(method)]


def foreground_choice(cfg: DictConfig) -> str:
    """The ``foreground`` group's choice (``grabcut`` or ``none``) of an unseen config, for predict."""
    from matl.utils.runs import hydra_choice

    choice = hydra_choice("foreground")
    if choice is not None:
        return choice
    node = cfg.get("foreground")
    return "none" if node is None or node.get("_target_") is None else "grabcut"


# ------------------------------------------------------------------------------------------ timing
def method_recognizer(method: str, cfg: DictConfig, ckpt: Path, threshold: Any, gallery_fill: float,
                      query_fill: float) -> Any:
    """The in-memory recognizer of one method, built as ``matl.predict`` builds it (batch of 1)."""
    from matl.inference.files import recognizer_from_config

    if method in ("matl", "matl_refine"):
        node = OmegaConf.create({"ckpt": str(ckpt), "device": cfg.device, "refine": method == "matl_refine",
                                 "threshold": threshold, "open_set_quantile": cfg.get("open_set_quantile", 0.94),
                                 **{key: cfg.get(key, default) for key, default in OPEN_SET_KEYS.items()},
                                 "gallery_fill": gallery_fill, "query_fill": query_fill, "batch_size": 1,
                                 "quantize": "none", "runtime": runtime_option(cfg)})
        node.refiner = cfg.refiner
        node.foreground = cfg.get("foreground")
        return recognizer_from_config(node)
    from matl.baselines.recognizer import build_baseline
    from matl.inference.baseline_files import KeypointFileRecognizer

    size, num_anchors = checkpoint_info(load_checkpoint(ckpt), ckpt)
    return KeypointFileRecognizer(build_baseline(cfg.baselines[method], method), method, size, num_anchors,
                                  gallery_fill=gallery_fill, query_fill=query_fill, batch_size=1)


def time_methods(recognizers: dict[str, Any], files: list[Path], warmup: int, threads: int) -> dict[str, float]:
    """``query_ms`` of each enrolled recognizer on the same query files: the median of single-query calls
    (file already decoded; framing, recognition, pose and pose-in-files timed), after ``warmup`` untimed
    calls, with ``threads`` torch and OpenCV threads for every method."""
    from matl.data.image_files import read_rgba
    from matl.utils.timing import median_query_ms

    arrays = [rgb if alpha is None else np.concatenate([rgb, alpha[..., None]], -1)  # RGBA: alpha = mask
              for rgb, alpha in map(read_rgba, files)]
    shapes = {a.shape for a in arrays}
    if len(shapes) != 1:
        raise MatlError(f"timing needs query files of one size, got {sorted(shapes)}")
    queries = torch.from_numpy(np.stack(arrays))  # (Q, H, W, 3 or 4)
    # median_query_ms sets torch's and OpenCV's threads alike (matl.utils.timing.compute_threads)
    return {name: median_query_ms(lambda x, r=rec: r.predict_details([x[0].numpy()]), queries, warmup,
                                  threads=int(threads)) for name, rec in recognizers.items()}


# ------------------------------------------------------------------------------------ entry point
def _names(value: Any, valid: tuple[str, ...], key: str, allow_all: bool) -> list[str]:
    """A single name, ``all`` or a list, checked against ``valid`` (one-line error naming them)."""
    items = list(value) if isinstance(value, (list, tuple, ListConfig)) else [value]
    if allow_all and items == ["all"]:
        return list(valid)
    options = ", ".join(valid) + (" or all" if allow_all else "")
    bad = [v for v in items if not isinstance(v, str) or v not in valid]
    if bad or not items or len(set(items)) != len(items):
        shown = value if not isinstance(value, ListConfig) else OmegaConf.to_container(value)
        raise MatlError(f"{key}={shown} is invalid: use {'one or a list' if allow_all else 'a list'} of {options}")
    return [str(v) for v in items]


def _ranges(cfg: DictConfig, keys: list[str]) -> None:
    for key in keys:
        value = OmegaConf.select(cfg, key)
        ok = isinstance(value, (list, ListConfig)) and len(value) == 2 and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) for v in value) and value[0] <= value[1]
        if not ok:
            raise MatlError(f"{key}={value} is invalid: use [low, high] with low <= high")


def _check_occluded(cfg: DictConfig) -> None:
    """``occluded.*``: the occluders' kinds and range, the floors' weights, the RGBA share, the bins."""
    node = cfg.occluded
    kinds = OmegaConf.to_container(node.kinds) if isinstance(node.kinds, DictConfig) else node.kinds
    try:
        Occluders(kinds, tuple(node.hidden))
    except MatlError as error:
        raise MatlError(f"occluded: {error}") from None
    floors = OmegaConf.to_container(node.floors) if isinstance(node.floors, DictConfig) else node.floors
    if not isinstance(floors, dict) or not floors or not set(floors) <= {"dark", "texture"} or not all(
            isinstance(w, (int, float)) and not isinstance(w, bool) and w >= 0 for w in floors.values()) \
            or sum(floors.values()) <= 0:
        raise MatlError(f"occluded.floors={floors} is invalid: use weights >= 0 of dark and texture, not all 0, "
                        "e.g. {dark: 0.5, texture: 0.5}")
    share = node.rgba_share
    if not isinstance(share, (int, float)) or isinstance(share, bool) or not 0.0 <= share <= 1.0:
        raise MatlError(f"occluded.rgba_share={share} is invalid: use a fraction in [0, 1] of RGBA query files")
    bins = node.bins
    if not isinstance(bins, (list, ListConfig)) or not bins or not all(
            isinstance(b, (int, float)) and not isinstance(b, bool) and 0.0 < b < 1.0 for b in bins) \
            or any(a >= b for a, b in itertools.pairwise(bins)):
        shown = OmegaConf.to_container(bins) if isinstance(bins, ListConfig) else bins
        raise MatlError(f"occluded.bins={shown} is invalid: use increasing upper edges in (0, 1) of the "
                        "hidden-fraction bins, e.g. [0.2, 0.35, 0.5]")


def _check(cfg: DictConfig) -> tuple[list[str], list[str]]:
    """Validate a composed ``conf/unseen.yaml``; returns the conditions and the methods."""
    validate_config(cfg)
    runtime_option(cfg)  # runtime=torch|onnxruntime
    if cfg.get("ckpt") in (None, ""):
        raise MatlError("ckpt=... is required: python -m matl.unseen ckpt=<checkpoint> [condition=all] "
                        "[data=heldout] [out=<dir>]")
    conditions = _names(cfg.get("condition"), CONDITIONS, "condition", allow_all=True)
    methods = _names(cfg.get("methods"), METHODS, "methods", allow_all=False)
    for key, low in (("queries", 1), ("query_seed", 0), ("file_size", 16), ("sizes.gallery", 16), ("sizes.query", 16),
                     ("timing.queries", 0), ("timing.warmup", 0), ("timing.threads", 1), ("view.seed", 0)):
        value = OmegaConf.select(cfg, key)
        if value is None and key == "file_size":
            continue
        if not isinstance(value, int) or isinstance(value, bool) or value < low:
            raise MatlError(f"{key}={value} is invalid: use an integer >= {low}")
    _ranges(cfg, [f"photometric.{k}" for k in cfg.photometric] + ["mask.offset_px", "mask.ragged_px",
                                                                   "clutter.distance", "backgrounds.crop"]
            + ["occluded.hidden"] + [f"occluded.dark_floor.{k}" for k in ("level", "noise", "vignetting")])
    _check_occluded(cfg)
    leave_out = cfg.get("leave_out", 0.0)
    if not isinstance(leave_out, (int, float)) or isinstance(leave_out, bool) or not 0.0 <= leave_out < 1.0:
        raise MatlError(f"leave_out={leave_out} is invalid: use a fraction in [0, 1) of the products kept out of "
                        "the gallery (open set)")
    for key in ("exclude_seen", "gallery_crop"):
        if not isinstance(cfg.get(key), bool):
            raise MatlError(f"{key}={cfg.get(key)} is invalid: use true or false")
    return conditions, methods


def primary_method(methods: list[str]) -> str:
    """The method whose metrics are ``unseen.json``'s top level: MATL's (plain first), else the first."""
    return next((m for m in ("matl", "matl_refine") if m in methods), methods[0])


def _products(cfg: DictConfig, train_data: dict[str, Any], file_size: int) -> tuple[Queries, dict[str, Any]]:
    """The held-out products (seen ones dropped) and the queries' planes and poses; plus what was checked."""
    from matl.data.prepare import instantiate_source

    source = instantiate_source(cfg)
    sampler = hydra.utils.instantiate(cfg.data.homography)
    cs = load_canonical(source, file_size, cfg.paths.cache_dir)
    objects = OmegaConf.select(cfg, "data.objects")
    source_objects = list(range(cs.num_objects)) if objects is None else [int(o) for o in objects]
    if objects is not None:
        cs = cs.subset_objects(source_objects)
    seen, related, how = seen_products(train_data, source, cs.object_names)
    if not cfg.exclude_seen:
        seen = {}
    keep = [i for i, name in enumerate(cs.object_names) if name not in seen]
    if not keep:
        raise MatlError(f"every product of {source!r} is in the checkpoint's training catalog: pick another "
                        "data= (e.g. heldout) or data.source.seed=")
    cs = cs.subset_objects(keep)
    log.info("unseen: %d products (%d planes), %d excluded as seen: %s", cs.num_objects, cs.num_planes, len(seen),
             sorted(seen))
    plane, query_H_canon = sample_poses(cs, sampler, int(cfg.queries), int(cfg.query_seed))
    queries = Queries(cs, plane, query_H_canon, int(cfg.query_seed), source, [source_objects[i] for i in keep], cfg)
    return queries, {"seen": seen, "related": related, "how": how}


def _settings(cfg: DictConfig, condition: str) -> dict[str, Any] | None:
    """The config values a condition was made with (for unseen.json)."""
    keys = {"photometric": ["photometric"], "mask": ["mask", "backgrounds"], "clutter": ["clutter", "backgrounds"],
            "occluded": ["occluded", "backgrounds"], "view": ["view"], "sizes": ["sizes"]}.get(condition)
    if keys is None:
        return None
    return {k: OmegaConf.to_container(cfg[k], resolve=True) for k in keys}


def run_condition(condition: str, q: Queries, cfg: DictConfig, methods: list[str], ckpt_path: Path, size: int,
                  num_anchors: int, checked: dict[str, Any], train_data: dict[str, Any], out: Path) -> dict[str, Any]:
    """Write one condition's gallery and queries into ``out``, predict and score them with every method;
    returns what ``<out>/unseen.json`` holds."""
    from matl.utils.io import write_json

    for sub in ("gallery", "queries"):
        if (out / sub).exists() and any((out / sub).iterdir()):
            raise MatlError(f"out={out} already holds {sub}/ from an earlier run: use a new out= folder")
    out.mkdir(parents=True, exist_ok=True)
    crop = bool(cfg.gallery_crop)
    gallery_fill = float(cfg.gallery_fill if cfg.gallery_fill is not None else (CROP_FILL if crop else 1.0))
    query_fill = float(cfg.query_fill)
    gallery_cs = q.at_size(int(cfg.sizes.gallery)) if condition == "sizes" else q.cs
    gallery_files, canon_H_file = write_gallery(gallery_cs, out / "gallery", crop)
    truth = WRITERS[condition](q, out / "queries", gallery_files, canon_H_file, out)
    cs = q.cs
    left_out = left_out_products(cs.object_names, float(cfg.leave_out), int(cfg.query_seed))
    for name in left_out:  # their gallery files move out of the gallery: predict never sees them
        (out / "gallery" / name).rename(_left_out_dir(out, name))
    for t in truth:
        t["enrolled"] = t["object"] not in left_out
        if not t["enrolled"]:
            t["gallery_image"] = str(Path("left_out") / Path(t["gallery_image"]).relative_to("gallery"))
    enrolled = [t for t in truth if t["enrolled"]]
    truth_path = out / "truth.jsonl"
    truth_path.write_text("".join(json.dumps(t) + "\n" for t in enrolled))
    headline = headline_queries(enrolled)
    headline_path = truth_path  # the queries of the headline numbers (all, or the RGB ones of a mixed condition)
    if len(headline) < len(enrolled):
        headline_path = out / "truth_rgb.jsonl"
        headline_path.write_text("".join(json.dumps(enrolled[i]) + "\n" for i in headline))
    groups = breakdown_groups(enrolled, headline, [float(e) for e in cfg.occluded.bins])
    if left_out:
        (out / "truth_left_out.jsonl").write_text("".join(json.dumps(t) + "\n" for t in truth if not t["enrolled"]))

    threshold = cfg.get("threshold", "auto") if left_out else None  # leave_out=0: the closed-set benchmark
    common = [_arg("ckpt", ckpt_path), _arg("gallery", out / "gallery"), _arg("images", out / "queries"),
              _arg("gallery_fill", gallery_fill), _arg("query_fill", query_fill), _arg("batch_size", cfg.batch_size),
              _arg("device", cfg.device), _arg("threshold", "null" if threshold is None else threshold),
              _arg("open_set_quantile", cfg.get("open_set_quantile", 0.94)), *open_set_args(cfg)]
    primary = primary_method(methods)
    per_method: dict[str, dict[str, Any]] = {}
    rows_of: dict[str, list[dict[str, Any]]] = {}
    scored_groups: dict[str, dict[str, dict[str, dict[str, Any]]]] = {}
    for method in methods:
        pred_path = out / ("predictions.jsonl" if method == primary else f"predictions_{method}.jsonl")
        args = [*predict_args(method, common, foreground_choice(cfg), runtime_option(cfg)), _arg("out", pred_path)]
        log.info("unseen: %s: predicting %d queries with %s", condition, len(truth), method)
        run_predict([*args, _arg("hydra.run.dir", out / f"predict_{method}")], out, f"predict_{method}.log")
        summary, rows, scored_groups[method] = score_condition(pred_path, truth_path, headline, groups, size,
                                                               gallery_fill, query_fill)
        summary["truth"] = str(headline_path)
        for row, t in zip(rows, enrolled, strict=True):  # a mixed condition's own fields, per query
            row.update({k: t[k] for k in QUERY_FIELDS if k in t})
        score_args = [_arg("predictions", pred_path), _arg("truth", headline_path), _arg("ckpt", ckpt_path),
                      _arg("gallery_fill", gallery_fill), _arg("query_fill", query_fill),
                      _arg("out", out / f"score_{method}")]
        per_method[method] = {**{k: summary[k] for k in METRICS}, "query_ms": None, "summary": summary,
                              "predictions": pred_path.name,
                              "per_query": "per_query.csv" if method == primary else f"per_query_{method}.csv",
                              "commands": {"predict": shlex.join(["python", "-m", "matl.predict", *args]),
                                           "score": shlex.join(["python", "-m", "matl.score", *score_args])}}
        rows_of[method] = rows

    timing = None
    if int(cfg.timing.queries) > 0:
        rgba = {t["image"] for t in truth if t.get("rgba")} if len(headline) < len(enrolled) else set()
        files = [f for f in sorted((out / "queries").iterdir()) if str(f.relative_to(out)) not in rgba]  # headline's
        files = files[: int(cfg.timing.queries) + int(cfg.timing.warmup)]
        warmup = min(int(cfg.timing.warmup), max(len(files) - 1, 0))
        recognizers = {m: method_recognizer(m, cfg, ckpt_path, threshold, gallery_fill, query_fill).enrol(
            out / "gallery") for m in methods}
        for method, ms in time_methods(recognizers, files, warmup, int(cfg.timing.threads)).items():
            per_method[method]["query_ms"] = ms
        timing = {"queries": len(files) - warmup, "warmup": warmup, "threads": int(cfg.timing.threads),
                  "statistic": "median over single-query calls (batch of 1), gallery in memory, file decoded"}

    open_set = None
    if left_out and primary in ("matl", "matl_refine"):
        pred_path = out / per_method[primary]["predictions"]
        predictions = {str(Path(r["image"]).relative_to(out)) if Path(r["image"]).is_absolute() else r["image"]: r
                       for r in map(json.loads, pred_path.read_text().splitlines())}
        open_set = open_set_summary(truth, predictions)
        write_json(out / "open_set.json", {**open_set, "left_out": left_out})
        plot_open_set(open_set, out / "open_set.png")
        open_set = {k: v for k, v in open_set.items() if k != "curve"}
        log.info("unseen: open set %s", json.dumps(open_set))

    summary, rows = per_method[primary]["summary"], [rows_of[primary][i] for i in headline]
    related = checked["related"]
    unrelated = [r for r in rows if r["true_object"] not in related]
    result = {
        **{k: summary[k] for k in METRICS},
        "rec_acc_unrelated": sum(r["correct"] for r in unrelated) / len(unrelated) if unrelated else None,
        "num_queries_unrelated": len(unrelated),
        "num_queries": summary["num_queries"], "missing_predictions": summary["missing_predictions"],
        "num_queries_all": len(enrolled), "headline": "all" if len(headline) == len(enrolled) else "rgb",
        "num_objects": cs.num_objects, "num_planes": cs.num_planes,
        "condition": condition, "condition_settings": _settings(cfg, condition), "method": primary,
        "foreground": foreground_choice(cfg),
        "methods": {m: {k: v for k, v in r.items() if k != "summary"} for m, r in per_method.items()},
        "timing": timing,
        "checkpoint": str(ckpt_path), "image_size": size, "N": num_anchors,
        "data": OmegaConf.to_container(cfg.data.source, resolve=True), "products": list(cs.object_names),
        "excluded_seen": checked["seen"], "related": related, "seen_check": checked["how"],
        "train_data": train_data.get("source"),
        "query_seed": int(cfg.query_seed), "file_size": cs.image_size, "gallery_crop": crop,
        "gallery_fill": gallery_fill, "query_fill": query_fill, "refine": primary == "matl_refine",
        "homography": OmegaConf.to_container(cfg.data.homography, resolve=True),
        "pose_threshold_px": summary["pose_threshold_px"],
        "per_object": summary["per_object"], "confusions": summary["confusions"],
        "commands": {"unseen": _own_command(), **per_method[primary]["commands"]},
        "files": {"gallery": "gallery", "queries": "queries", "truth": truth_path.name,
                  "predictions": per_method[primary]["predictions"], "per_query": "per_query.csv",
                  **({"truth_headline": headline_path.name} if headline_path != truth_path else {}),
                  **({"masks": "masks"} if (out / "masks").is_dir() else {})},
    }
    if groups:
        result["breakdown"] = breakdown_result(groups, scored_groups, [float(e) for e in cfg.occluded.bins],
                                               result["headline"])
    if open_set is not None:
        result["open_set"] = {**open_set, "left_out": left_out, "curve": "open_set.json", "figure": "open_set.png"}
    write_json(out / "unseen.json", result)
    for method, method_rows in rows_of.items():
        write_rows(out / per_method[method]["per_query"], method_rows)
    log.info("unseen: %s: %s", condition, json.dumps({m: {k: r[k] for k in TABLE_METRICS}
                                                      for m, r in per_method.items()}))
    return result


# -------------------------------------------------------------------------------------- breakdown
BREAKDOWN_METRICS = ("rec_acc", "corner_err_px_median", "pose_acc_5px")
BREAKDOWN_GROUPS = ("hidden_fraction", "occluder", "floor", "input")
QUERY_FIELDS = ("hidden_fraction", "occluder", "floor", "rgba")  # copied from the truth into per_query.csv


def headline_queries(truth: list[dict[str, Any]]) -> list[int]:
    """Indices of the truth records whose metrics are a condition's headline (its row of the table): the RGB
    queries of a condition that mixes RGB and RGBA files (``occluded``; ``rgba`` true in the truth), else all."""
    rgb = [i for i, t in enumerate(truth) if not t.get("rgba", False)]
    return rgb if rgb else list(range(len(truth)))


def bin_labels(edges: list[float]) -> list[str]:
    """Labels of the hidden-fraction bins with upper ``edges`` (increasing), and of the one beyond the last:
    ``[0.2, 0.35, 0.5]`` -> ``<=0.20``, ``0.20-0.35``, ``0.35-0.50``, ``>0.50``."""
    return ([f"<={edges[0]:.2f}"] + [f"{a:.2f}-{b:.2f}" for a, b in itertools.pairwise(edges)]
            + [f">{edges[-1]:.2f}"])


def hidden_bin(fraction: float, edges: list[float]) -> str:
    """The label of the bin (:func:`bin_labels`) a hidden fraction falls in; an upper edge belongs to its bin."""
    labels = bin_labels(edges)
    return next((label for edge, label in zip(edges, labels, strict=False) if fraction <= edge), labels[-1])


def breakdown_groups(truth: list[dict[str, Any]], headline: list[int], edges: list[float]
                     ) -> dict[str, dict[str, list[int]]]:
    """The breakdown of a condition whose truth records carry ``hidden_fraction`` (``occluded``; else ``{}``): the
    headline queries by hidden-fraction bin (every bin up to the last edge listed, empty or not), occluder kind and
    floor; every query by input (``rgb``, ``rgba``). Values: indices into ``truth``."""
    if not any("hidden_fraction" in t for t in truth):
        return {}
    from matl.data.occluders import OCCLUDER_KINDS

    by_bin: dict[str, list[int]] = {label: [] for label in bin_labels(edges)[:-1]}
    by_kind: dict[str, list[int]] = {}
    by_floor: dict[str, list[int]] = {}
    for i in headline:
        by_bin.setdefault(hidden_bin(float(truth[i]["hidden_fraction"]), edges), []).append(i)
        by_kind.setdefault(str(truth[i]["occluder"]), []).append(i)
        by_floor.setdefault(str(truth[i]["floor"]), []).append(i)
    by_input: dict[str, list[int]] = {"rgb": [], "rgba": []}
    for i, t in enumerate(truth):
        by_input["rgba" if t.get("rgba") else "rgb"].append(i)
    kinds = sorted(by_kind, key=lambda k: OCCLUDER_KINDS.index(k) if k in OCCLUDER_KINDS else len(OCCLUDER_KINDS))
    return {"hidden_fraction": by_bin, "occluder": {k: by_kind[k] for k in kinds},
            "floor": dict(sorted(by_floor.items())), "input": by_input}


def _read_predictions(path: Path) -> list[dict[str, Any]]:
    try:
        return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    except (OSError, json.JSONDecodeError) as error:
        raise MatlError(f"predictions={path} cannot be read: {' '.join(str(error).split())}") from None


def score_condition(predictions: Path, truth: Path, headline: list[int], groups: dict[str, dict[str, list[int]]],
                    image_size: int, gallery_fill: float = 1.0, query_fill: float = 1.0
                    ) -> tuple[dict[str, Any], list[dict[str, Any]], dict[str, dict[str, dict[str, Any]]]]:
    """Score one method's predictions of a condition (:func:`matl.evaluation.score.score`, its metrics).

    Returns:
        ``(summary, rows, groups)``: the summary of the ``headline`` queries (indices into ``truth``'s lines), the
        per-query rows of every query, and per group and label of ``groups`` its ``num_queries`` and
        :data:`BREAKDOWN_METRICS` (None for an empty label).
    """
    labelled = read_truth(truth)
    base = Path(truth).expanduser().parent.resolve()
    matched = match_predictions(labelled, _read_predictions(Path(predictions)), base)

    def scored(indices: list[int]) -> tuple[dict[str, Any], list[dict[str, Any]]]:
        return score([labelled[i] for i in indices], [matched[i] for i in indices], image_size, gallery_fill,
                     query_fill, base)

    every, rows = score(labelled, matched, image_size, gallery_fill, query_fill, base)
    summary = every if len(headline) == len(labelled) else scored(headline)[0]
    summary.update(predictions=str(predictions), truth=str(truth))
    by_group: dict[str, dict[str, dict[str, Any]]] = {}
    for group, labels in groups.items():
        by_group[group] = {}
        for label, indices in labels.items():
            metrics = scored(indices)[0] if indices else {}
            by_group[group][label] = {"num_queries": len(indices), **{k: metrics.get(k) for k in BREAKDOWN_METRICS}}
    return summary, rows, by_group


def breakdown_result(groups: dict[str, dict[str, list[int]]], scored: dict[str, dict[str, dict[str, dict]]],
                     edges: list[float], headline: str) -> dict[str, Any]:
    """``unseen.json``'s ``breakdown``: per group and label, ``num_queries`` and each method's metrics."""
    out: dict[str, Any] = {
        "queries": (f"hidden_fraction, occluder and floor: the headline ({headline}) queries; input: every query"),
        "hidden_fraction_bins": edges, "metrics": list(BREAKDOWN_METRICS)}
    for group, labels in groups.items():
        out[group] = {label: {"num_queries": len(indices),
                              "methods": {m: {k: s[group][label][k] for k in BREAKDOWN_METRICS}
                                          for m, s in scored.items()}}
                      for label, indices in labels.items()}
    return out


# ------------------------------------------------------------------------------------------ table
TABLE_METRICS = ("rec_acc", "corner_err_px_median", "pose_acc_5px", "query_ms")


def _cell(metrics: dict[str, Any]) -> str:
    def fmt(value: Any, digits: int) -> str:
        return "-" if value is None else f"{float(value):.{digits}f}"

    return " / ".join([fmt(metrics.get("rec_acc"), 3), fmt(metrics.get("corner_err_px_median"), 1),
                       fmt(metrics.get("pose_acc_5px"), 3), fmt(metrics.get("query_ms"), 1)])


def benchmark_table(results: dict[str, dict[str, Any]], methods: list[str], command: str) -> tuple[dict, str]:
    """``benchmark.json``'s content and ``benchmark.md``: one row per condition, one column per method,
    each cell ``rec_acc / median corner_err_px / pose_acc_5px / query_ms``."""
    table = {c: {m: {k: r["methods"][m].get(k) for k in TABLE_METRICS} for m in methods} for c, r in results.items()}
    first = next(iter(results.values()))
    data = {"command": command, "conditions": list(results), "methods": methods, "table": table,
            "columns": list(TABLE_METRICS), "num_queries": {c: r["num_queries"] for c, r in results.items()},
            "num_objects": first["num_objects"], "num_planes": first["num_planes"], "image_size": first["image_size"],
            "checkpoint": first["checkpoint"], "data": first["data"], "query_seed": first["query_seed"],
            "timing": first["timing"]}
    lines = [f"Never-seen products: {first['num_objects']} products, {first['num_planes']} planes, "
             f"checkpoint `{first['checkpoint']}`.", "",
             f"`{command}`" if command else "(called as a function)", "",
             "Each cell: rec_acc / median corner_err_px (at the model's "
             f"{first['image_size']} px) / pose_acc_5px / query_ms (batch of 1).", "",
             "| condition | queries | " + " | ".join(methods) + " |",
             "|---|---|" + "---|" * len(methods)]
    for condition, row in table.items():
        lines.append(f"| {condition} | {results[condition]['num_queries']} | "
                     + " | ".join(_cell(row[m]) for m in methods) + " |")
    headlines = {c: r.get("headline") for c, r in results.items() if r.get("headline") not in (None, "all")}
    if headlines:
        lines += ["", "Rows of " + ", ".join(f"{c} count its {h.upper()} queries only" for c, h in headlines.items())
                  + " (the breakdown below has the others)."]
    for condition, result in results.items():
        breakdown = result.get("breakdown")
        if not breakdown:
            continue
        data.setdefault("breakdown", {})[condition] = breakdown
        lines += ["", f"{condition} broken down ({breakdown['queries']}); each cell: rec_acc / median corner_err_px / "
                  "pose_acc_5px.", "", "| group | queries | " + " | ".join(methods) + " |",
                  "|---|---|" + "---|" * len(methods)]
        for group in BREAKDOWN_GROUPS:
            for label, entry in breakdown.get(group, {}).items():
                cells = (_cell({**entry["methods"].get(m, {}), "query_ms": None}).rsplit(" / ", 1)[0] for m in methods)
                lines.append(f"| {group} {label} | {entry['num_queries']} | " + " | ".join(cells) + " |")
    return data, "\n".join(lines) + "\n"


def write_speed_accuracy(data: dict[str, Any], folders: dict[str, Path], out: Path) -> dict[str, str]:
    """``speed_accuracy.png`` and ``methods.md`` (:mod:`matl.reporting.speed_accuracy`) beside each condition's
    ``unseen.json`` whose methods were timed; returns their paths relative to ``out`` per condition."""
    from matl.reporting.speed_accuracy import methods_table, plot_speed_accuracy, timed_methods

    written = {}
    timing = data.get("timing") or {}
    for condition, table in data["table"].items():
        if not timed_methods(table):
            continue
        n = data["num_queries"][condition]
        title = (f"{data['num_objects']} never-seen products, condition {condition}, {n} queries; query_ms: median "
                 f"of {timing.get('queries')} single queries at {timing.get('threads')} thread(s)")
        png = plot_speed_accuracy(table, folders[condition] / "speed_accuracy.png", title)
        (folders[condition] / "methods.md").write_text(methods_table(table, n))
        written[condition] = str(png.relative_to(out))
    return written


def unseen(cfg: DictConfig) -> dict[str, Any]:
    """Run the benchmark for a composed ``conf/unseen.yaml``.

    Each condition writes ``<out>/<condition>/`` (gallery, queries, truth, predictions per method,
    ``unseen.json``, ``per_query.csv``), or ``<out>/`` itself when ``condition`` names one condition;
    ``<out>/benchmark.json`` and ``benchmark.md`` hold the table.

    Returns:
        The last condition's ``unseen.json`` content, with ``benchmark`` (``benchmark.json``'s content).
    """
    from matl.utils.io import write_json

    conditions, methods = _check(cfg)
    from matl.inference.api import resolve_checkpoint_keyword

    ckpt_path = Path(resolve_checkpoint_keyword(str(cfg.ckpt))).expanduser().resolve()  # pretrained[_fast]: shipped
    ckpt = load_checkpoint(ckpt_path)
    size, num_anchors = checkpoint_info(ckpt, ckpt_path)
    train_data = (ckpt.get("matl_config") or {}).get("data") or {}
    del ckpt
    out = Path(cfg.out).expanduser().resolve()
    # one condition by name: its files straight into out/; all or a list: out/<condition>/ each
    flat = isinstance(cfg.condition, str) and cfg.condition != "all"
    folders = {c: out if flat else out / c for c in conditions}
    for folder in folders.values():
        for sub in ("gallery", "queries"):
            if (folder / sub).exists() and any((folder / sub).iterdir()):
                raise MatlError(f"out={out} already holds {folder.relative_to(out) / sub}/ from an earlier run: use a "
                                "new out= folder")
    if "view" in conditions:
        from matl.data.prepare import instantiate_source

        require_models(instantiate_source(cfg), "condition=view")
    q, checked = _products(cfg, train_data, int(cfg.file_size or size))
    results = {}
    for condition in conditions:
        results[condition] = run_condition(condition, q, cfg, methods, ckpt_path, size, num_anchors, checked,
                                           train_data, folders[condition])
    data, text = benchmark_table(results, methods, _own_command())
    data["files"] = {c: str((folders[c] / "unseen.json").relative_to(out)) for c in conditions}
    data["speed_accuracy"] = write_speed_accuracy(data, folders, out)
    write_json(out / "benchmark.json", data)
    (out / "benchmark.md").write_text(text)
    log.info("unseen: benchmark -> %s\n%s", out / "benchmark.md", text)
    return {**results[conditions[-1]], "benchmark": data}
