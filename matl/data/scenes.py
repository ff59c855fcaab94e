"""Training scenes of the visibility network: camera-like crops of a target product and its visible mask.

A robot's crop of a product (a detector's box) comes without a mask. :class:`SceneMaker` makes such
crops from a *training* catalog, with the truth of which pixels show the target's visible print
(``python -m matl.train_foreground``, :mod:`matl.models.visibility`):

1. the target: a canonical plane warped by the query homography sampler
   (:class:`matl.geometry.HomographySampler`, the training warps, object kept in the frame) with its
   warped mask (bilinear: an edge pixel is partly covered);
2. a background: exactly black a share of the time (``black_p``: the training convention), a dark
   bin floor (``floor_p``: a dark smooth field with sensor-like grain and a bin wall's edge), else a
   background of :class:`matl.data.augment.CameraAugment`'s bank (smooth fields, stripes and checks,
   crops of matplotlib's sample photos, shelves of the catalog's own products, and with its
   ``neighbour_p`` a catalog product beside the centre);
3. ``neighbours`` more catalog products of other objects, each under its own random pose and moved
   off-centre by ``neighbour_distance`` x the crop's side, so the crop's edge cuts them; behind the target;
4. the target composited on top: its coverage is the visible mask so far;
5. with probability ``occluded_p``, occluders in front of the target (``occluders``, e.g.
   :class:`matl.data.occluders.Occluders`: ``apply(image, visible, rng, products, floor)`` returns the
   image with them and the visible mask without what they hide);
6. a camera's photometric changes (:class:`matl.data.augment.Photometric`: gain, bias, gamma, tint, blur,
   noise, JPEG), which move no pixel, so the mask stays the truth; then 8 bits, as a camera's file.

The truth is exact: a pixel outside the target's warped mask is 0, a hidden pixel 0. Everything is
drawn from ``(seed, index)``: a scene is the same whoever asks for it, in any order.

:class:`SceneDataModule` holds the scenes a run trains and validates on at the network's working size:
training scenes of the training catalog (``synthetic_arc`` by default) and validation scenes of another
catalog (``synthetic_ycb``: products the network never saw). Nothing here reads the held-out benchmark's
sources (``matl.unseen``'s products, photos and background pool).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset

from matl.data.augment import CameraAugment, Photometric
from matl.data.canonical import CanonicalSet, CanonicalSource, load_canonical
from matl.data.datamodule import footprints_from_masks
from matl.geometry import HomographySampler, sample_by_pixels
from matl.utils.errors import MatlError

__all__ = ["Scene", "SceneDataModule", "SceneMaker", "SceneSet", "bin_floor", "make_scene_set"]

log = logging.getLogger(__name__)


@dataclass
class Scene:
    """One crop and its truth.

    Attributes:
        image: ``(S, S, 3)`` float32 RGB in [0, 1], multiples of 1/255.
        visible: ``(S, S)`` float32 in [0, 1]: the coverage of each pixel by the target's visible print.
        plane: the target's plane index in the catalog.
        query_H_canon: ``(3, 3)`` float64, the target's pose (canonical pixels -> crop pixels).
        info: what was drawn (background kind, neighbours, occluders' ``hidden_fraction``).
        covered: ``(S, S)`` float32 in [0, 1]: the target's coverage before any occluder (``covered - visible``:
            what an occluder hides of it); None: as ``visible``.
    """

    image: np.ndarray
    visible: np.ndarray
    plane: int
    query_H_canon: np.ndarray
    info: dict[str, Any] = field(default_factory=dict)
    covered: np.ndarray | None = None


def bin_floor(size: int, rng: np.random.Generator) -> np.ndarray:
    """A dark bin floor ``(size, size, 3)`` float32 in [0, 1]: a dark tinted smooth field, sensor-like grain,
    and half the time a bin wall (a straight edge beyond which the level changes)."""
    level = rng.uniform(0.02, 0.25)
    tint = 1.0 + rng.uniform(-0.25, 0.25, 3)
    cells = int(rng.integers(2, 6))
    low = cv2.resize(rng.random((cells, cells, 3)).astype(np.float32), (size, size), interpolation=cv2.INTER_CUBIC)
    floor = level * tint * (0.7 + 0.6 * low)
    floor = floor + rng.normal(0.0, rng.uniform(0.0, 0.03), (size, size, 3))
    if rng.random() < 0.5:  # a wall: the points beyond a line at a random angle and offset
        angle = rng.uniform(0.0, 2.0 * math.pi)
        v, u = np.mgrid[0:size, 0:size].astype(np.float32) / size - 0.5
        beyond = (u * math.cos(angle) + v * math.sin(angle)) > rng.uniform(0.2, 0.45)
        floor = np.where(beyond[..., None], floor * rng.uniform(0.4, 2.5), floor)
    return np.clip(floor, 0.0, 1.0).astype(np.float32)


@dataclass
class SceneMaker:
    """Camera-like crops of a catalog's products with the truth of the target's visible print (module docstring).

    Args:
        homography: the target's and the neighbours' poses (a :class:`HomographySampler` or its settings).
        augment: the background bank and its neighbour beside the centre (a :class:`CameraAugment` or its
            settings; its framings are not used); its ``photometric`` is not used either.
        photometric: the camera's changes (a :class:`Photometric` or its settings).
        black_p: share of scenes on an exactly black background.
        floor_p: share of scenes on a dark bin floor (:func:`bin_floor`).
        neighbours: ``[low, high]`` number of further products behind the target, cut by the crop's edge.
        neighbour_distance: ``[low, high]`` offset of a neighbour's centre, a fraction of the crop's side.
        occluded_p: share of scenes given occluders (needs ``occluders``).
        occluders: what puts occluders in front of the target (``apply(image, visible, rng, products, floor)``),
            or None (no occluders).
        occluder_products: how many canonical images of other products ``occluders`` may draw from per scene.
        seed: with a scene's index, seeds everything drawn for it.
    """

    homography: Any = field(default_factory=HomographySampler)
    augment: Any = field(default_factory=CameraAugment)
    photometric: Any = field(default_factory=Photometric)
    black_p: float = 0.15
    floor_p: float = 0.15
    neighbours: tuple[int, int] = (0, 2)
    neighbour_distance: tuple[float, float] = (0.5, 0.8)
    occluded_p: float = 0.5
    occluders: Any = None
    occluder_products: int = 4
    seed: int = 0

    def __post_init__(self) -> None:
        if not isinstance(self.homography, HomographySampler):
            self.homography = HomographySampler(**_settings(self.homography))
        if not isinstance(self.augment, CameraAugment):
            self.augment = CameraAugment(**_settings(self.augment))
        if not isinstance(self.photometric, Photometric):
            self.photometric = Photometric(**_settings(self.photometric))
        lo, hi = (int(v) for v in self.neighbours)
        d_lo, d_hi = (float(v) for v in self.neighbour_distance)
        if (not 0.0 <= float(self.black_p) <= 1.0 or not 0.0 <= float(self.floor_p) <= 1.0
                or float(self.black_p) + float(self.floor_p) > 1.0 or not 0 <= lo <= hi
                or not 0.0 <= d_lo <= d_hi or not 0.0 <= float(self.occluded_p) <= 1.0
                or int(self.occluder_products) < 1):
            raise MatlError(f"scenes: black_p={self.black_p}, floor_p={self.floor_p}, neighbours={[lo, hi]}, "
                            f"neighbour_distance={[d_lo, d_hi]}, occluded_p={self.occluded_p}, occluder_products="
                            f"{self.occluder_products}: use black_p, floor_p in [0, 1] with a sum <= 1, neighbours "
                            "[low, high] with 0 <= low <= high, distances 0 <= low <= high, occluded_p in [0, 1] "
                            "and occluder_products >= 1")
        if self.occluders is not None and not callable(getattr(self.occluders, "apply", None)):
            raise MatlError(f"scenes.occluders={self.occluders!r} has no apply(image, visible, rng, products, floor)")
        self.neighbours, self.neighbour_distance = (lo, hi), (d_lo, d_hi)
        self._canonical: CanonicalSet | None = None

    # -------------------------------------------------------------------------------- catalog
    def setup(self, canonical: CanonicalSet) -> SceneMaker:
        """Take the catalog ``canonical`` (its images, masks and objects) and build the background bank from it."""
        if canonical.num_planes < 1:
            raise MatlError("scenes: the catalog has no planes")
        self._canonical = canonical
        self._images = canonical.images.astype(np.float32) / 255.0        # (P, S, S, 3)
        self._masks = canonical.masks.astype(np.float32)                   # (P, S, S)
        self._footprints = footprints_from_masks(torch.from_numpy(canonical.masks))  # (P, 4, 2)
        canon = torch.from_numpy(self._images).permute(0, 3, 1, 2).contiguous()
        self.augment.setup(canon, torch.from_numpy(self._masks)[:, None])
        return self

    @property
    def size(self) -> int:
        """The scenes' side ``S`` (the catalog's image size)."""
        return self._catalog().image_size

    def _catalog(self) -> CanonicalSet:
        if self._canonical is None:
            raise RuntimeError("SceneMaker.setup(canonical) must run before scenes are made")
        return self._canonical

    def _other_plane(self, plane: int, rng: np.random.Generator) -> int:
        """A random plane of another object than ``plane``'s (any plane when the catalog has one object)."""
        owner = self._catalog().plane_object
        others = np.flatnonzero(owner != owner[plane])
        pool = others if len(others) else np.arange(len(owner))
        return int(pool[int(rng.integers(len(pool)))])

    def _warp(self, plane: int, query_H_canon: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The plane's image ``(S, S, 3)`` (0 outside it) and mask ``(S, S)`` warped by ``query_H_canon``."""
        S = self.size
        canon_H_query = np.linalg.inv(query_H_canon)
        image = sample_by_pixels(self._images[plane], canon_H_query, (S, S))
        mask = sample_by_pixels(self._masks[plane], canon_H_query, (S, S))
        return np.clip(image, 0.0, 1.0), np.clip(mask, 0.0, 1.0)

    # -------------------------------------------------------------------------------- scenes
    def __call__(self, index: int) -> Scene:
        """The scene of ``index`` (the same for the same seed, catalog and settings)."""
        cs = self._catalog()
        S = self.size
        rng = np.random.default_rng([int(self.seed), int(index)])
        g = torch.Generator().manual_seed(int(rng.integers(2**62)))
        plane = int(rng.integers(cs.num_planes))
        query_H_canon = self.homography.sample(1, (S, S), g, self._footprints[plane:plane + 1])[0].numpy()
        target, visible = self._warp(plane, query_H_canon)
        covered = visible.copy()

        draw = rng.random()
        kind = "black" if draw < self.black_p else "floor" if draw < self.black_p + self.floor_p else "bank"
        if kind == "black":
            scene = np.zeros((S, S, 3), np.float32)
        elif kind == "floor":
            scene = bin_floor(S, rng)
        else:
            scene = self.augment.backgrounds(1, torch.device("cpu"), g)[0].permute(1, 2, 0).numpy().copy()
        floor = None if kind == "black" else scene.copy()

        count = int(rng.integers(self.neighbours[0], self.neighbours[1] + 1))
        for _ in range(count):  # behind the target: another product under its own pose, moved off-centre
            other = self._other_plane(plane, rng)
            angle = rng.uniform(0.0, 2.0 * math.pi)
            d = rng.uniform(*self.neighbour_distance) * S
            moved_H_query = np.array([[1.0, 0.0, d * math.cos(angle)], [0.0, 1.0, d * math.sin(angle)],
                                      [0.0, 0.0, 1.0]])
            own_H_canon = self.homography.sample(1, (S, S), g)[0].numpy()  # its own pose, centred
            image, mask = self._warp(other, moved_H_query @ own_H_canon)
            scene = image + (1.0 - mask[..., None]) * scene
        scene = target + (1.0 - visible[..., None]) * scene  # the target on top: its coverage is visible

        info: dict[str, Any] = {"background": kind, "neighbours": count, "hidden_fraction": 0.0}
        if self.occluders is not None and rng.random() < self.occluded_p:
            products = [(self._images[q].astype(np.float64), self._masks[q].astype(np.float64))
                        for q in (self._other_plane(plane, rng) for _ in range(int(self.occluder_products)))]
            image, hidden, drawn = self.occluders.apply(scene.astype(np.float64), visible.astype(np.float64), rng,
                                                        products, floor=floor)
            # what an occluder hides is out; nothing it does can make a pixel outside the target visible
            scene, visible = np.asarray(image, np.float32), np.minimum(np.asarray(hidden, np.float32), visible)
            info.update({k: v for k, v in dict(drawn).items() if isinstance(v, (int, float, str, bool))})

        shot = self.photometric(torch.from_numpy(np.ascontiguousarray(scene.transpose(2, 0, 1)))[None].float(), g)
        image = np.round(shot[0].permute(1, 2, 0).numpy() * 255.0) / 255.0  # 8 bits, as a camera's file
        return Scene(np.ascontiguousarray(image, dtype=np.float32), visible.astype(np.float32), plane, query_H_canon,
                     info, covered.astype(np.float32))


def _settings(node: Any) -> dict[str, Any]:
    """A config mapping's settings without ``_target_``; list values as tuples."""
    if node is None:
        return {}
    return {k: tuple(v) if isinstance(v, (list, tuple)) else v for k, v in dict(node).items() if k != "_target_"}


# ------------------------------------------------------------------------------------------ data sets
@dataclass
class SceneSet:
    """Scenes at the network's working size, kept in memory as bytes.

    Attributes:
        images: ``(n, 3, W, W)`` uint8, each scene resized to the working size ``W`` (area averaging, as
            :class:`matl.inference.foreground.LearnedForeground` resizes a crop).
        visible: ``(n, 1, W, W)`` uint8, the visible coverage resized alike, x 255.
        hidden: ``(n,)`` float32, the share of the target the occluders hid.
        background: ``(n,)`` the background kind of each scene.
        covered: ``(n, 1, W, W)`` uint8, the target's coverage before any occluder resized alike, x 255.
    """

    images: torch.Tensor
    visible: torch.Tensor
    hidden: torch.Tensor
    background: list[str]
    covered: torch.Tensor


def _resized_bytes(x: np.ndarray, size: int) -> np.ndarray:
    """An image ``(S, S[, C])`` in [0, 1] at the working size ``W`` (area averaging), uint8 x 255, ``(W, W[, C])``."""
    resized = cv2.resize(x, (size, size), interpolation=cv2.INTER_AREA)
    return (np.clip(resized, 0, 1) * 255.0).round().astype(np.uint8)


def _coverage_bytes(coverage: np.ndarray, size: int) -> np.ndarray:
    """A coverage ``(S, S)`` in [0, 1] at the working size ``W``, ``(1, W, W)`` uint8 x 255."""
    return _resized_bytes(coverage, size)[None]


def resize_scene(scene: Scene, size: int) -> tuple[np.ndarray, np.ndarray]:
    """A scene's image ``(3, W, W)`` uint8 and visible coverage ``(1, W, W)`` uint8 at the working size ``W``."""
    return _resized_bytes(scene.image, size).transpose(2, 0, 1), _coverage_bytes(scene.visible, size)


def make_scene_set(maker: SceneMaker, indices: Sequence[int], size: int,
                   progress: Callable[[int, int], None] | None = None) -> SceneSet:
    """The scenes of ``indices`` at the working size ``size`` (see :class:`SceneSet`)."""
    n = len(indices)
    images = np.zeros((n, 3, size, size), np.uint8)
    visible = np.zeros((n, 1, size, size), np.uint8)
    covered = np.zeros((n, 1, size, size), np.uint8)
    hidden = np.zeros(n, np.float32)
    background = []
    for j, index in enumerate(indices):
        scene = maker(int(index))
        images[j], visible[j] = resize_scene(scene, size)
        covered[j] = _coverage_bytes(scene.visible if scene.covered is None else scene.covered, size)
        hidden[j] = float(scene.info.get("hidden_fraction", 0.0))
        background.append(str(scene.info.get("background")))
        if progress is not None and (j + 1) % 1000 == 0:
            progress(j + 1, n)
    return SceneSet(torch.from_numpy(images), torch.from_numpy(visible), torch.from_numpy(hidden), background,
                    torch.from_numpy(covered))


class _Batches(Dataset):
    """A :class:`SceneSet` as float items ``{"image": (3, W, W), "visible": (1, W, W), "covered": (1, W, W)}`` in
    [0, 1]."""

    def __init__(self, scenes: SceneSet) -> None:
        self.scenes = scenes

    def __len__(self) -> int:
        return len(self.scenes.images)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        return {"image": self.scenes.images[index].float().div(255.0),
                "visible": self.scenes.visible[index].float().div(255.0),
                "covered": self.scenes.covered[index].float().div(255.0)}


class SceneDataModule(L.LightningDataModule):
    """Training scenes of one catalog and validation scenes of another, at the working size.

    Args:
        train_source, val_source: the catalogs (:class:`~matl.data.canonical.CanonicalSource`, e.g.
            ``SyntheticCatalog(catalog="arc")`` and ``"ycb"``), rendered at ``image_size``.
        scenes: the :class:`SceneMaker` (or its settings); the validation scenes use a copy with seed
            ``seed + 1`` and the validation catalog.
        image_size: the catalogs' image size, the scenes' side ``S`` (the model's 100 px crops).
        working_size: the network's input size ``W``.
        train_scenes, val_scenes: how many of each.
        batch_size: training batch size (validation: 4x).
        seed: the loader's shuffle seed.
        cache_dir: the canonical-image cache.
    """

    def __init__(self, train_source: CanonicalSource, val_source: CanonicalSource, scenes: Any = None,
                 image_size: int = 100, working_size: int = 64, train_scenes: int = 20000, val_scenes: int = 500,
                 batch_size: int = 64, seed: int = 0, cache_dir: str | Path = ".cache/matl") -> None:
        super().__init__()
        self.train_source, self.val_source = train_source, val_source
        self.scenes = scenes if isinstance(scenes, SceneMaker) else SceneMaker(**_settings(scenes))
        self.image_size, self.working_size = int(image_size), int(working_size)
        self.train_scenes, self.val_scenes = int(train_scenes), int(val_scenes)
        self.batch_size, self.seed, self.cache_dir = int(batch_size), int(seed), Path(cache_dir)
        if self.train_scenes < self.batch_size or self.val_scenes < 1:
            raise MatlError(f"train_scenes={self.train_scenes}, val_scenes={self.val_scenes}: use at least one "
                            f"batch ({self.batch_size}) of training scenes and one validation scene")
        self.train_set: SceneSet | None = None
        self.val_set: SceneSet | None = None

    def validation_maker(self) -> SceneMaker:
        """The validation scenes' maker: the training settings, seed + 1, the validation catalog."""
        import copy

        maker = copy.deepcopy(self.scenes)
        maker.seed = int(self.scenes.seed) + 1
        maker.augment.seed = int(self.scenes.augment.seed) + 1
        return maker

    def setup(self, stage: str | None = None) -> None:
        if self.train_set is not None:
            return

        def progress(done: int, total: int) -> None:
            log.info("scenes: %d / %d", done, total)

        train = load_canonical(self.train_source, self.image_size, self.cache_dir)
        val = load_canonical(self.val_source, self.image_size, self.cache_dir)
        self.scenes.setup(train)
        self._val_maker = self.validation_maker().setup(val)
        log.info("making %d training scenes (%d planes) and %d validation scenes (%d planes) at %d px",
                 self.train_scenes, train.num_planes, self.val_scenes, val.num_planes, self.working_size)
        self.train_set = make_scene_set(self.scenes, range(self.train_scenes), self.working_size, progress)
        self.val_set = make_scene_set(self._val_maker, range(self.val_scenes), self.working_size)

    def timing_crops(self, n: int) -> list[np.ndarray]:
        """The first ``n`` validation scenes' crops ``(S, S, 3)`` float32 at the catalog's size (for timing)."""
        return [self._val_maker(i).image for i in range(int(n))]

    def train_dataloader(self) -> DataLoader:
        return DataLoader(_Batches(self.train_set), batch_size=self.batch_size, shuffle=True, drop_last=True,
                          generator=torch.Generator().manual_seed(self.seed))

    def val_dataloader(self) -> DataLoader:
        return DataLoader(_Batches(self.val_set), batch_size=4 * self.batch_size)
