"""The files of the unseen-products benchmark's conditions: a gallery folder, query files and their ground truth.

Each writer (:data:`WRITERS`, one per condition of :mod:`matl.evaluation.conditions`) turns the held-out
products and the queries' planes and poses (:class:`Queries`) into query files under ``root`` and returns their
ground-truth records (:mod:`matl.score`'s sidecar: object, plane, gallery file and ``H`` = ``query_H_canon``
from the gallery file's pixels to the query file's), with the condition's own fields (its drawn parameters,
``mask_file`` the true visible mask). :func:`write_gallery` writes the gallery the truth refers to.
:mod:`matl.evaluation.unseen` runs them and predicts the files.
"""

from __future__ import annotations

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
from matl.geometry import HomographySampler
from matl.utils.errors import MatlError

WARP_BATCH = 250  # clean warps computed at a time


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


# condition -> its writer: (queries, root, gallery files, canon_H_file, out) -> the truth records of its files
WRITERS = {"clean": _write_clean_condition, "photometric": write_photometric, "mask": write_mask,
           "clutter": write_clutter, "occluded": write_occluded, "view": write_view, "sizes": write_sizes}
