"""SuperPoint + RANSAC baseline, Table 1 row (e) (Sec. 5.5).

The network follows DeTone et al., "SuperPoint: Self-Supervised Interest Point Detection and
Description" (CVPRW 2018): a VGG-style shared encoder (eight 3x3 convolutions, three 2x2 max-pools,
so one cell per 8x8 pixels), a detector head giving 65 logits per cell (64 pixel positions plus a
"no keypoint" dustbin), turned into a full-resolution heatmap by a softmax and depth-to-space, and a
descriptor head giving a coarse 256-d map that is interpolated at the keypoints and L2-normalised.
Module names follow the public pretrained release (``superpoint_v1.pth``) so that its state dict
loads by name. matl neither ships nor downloads that file: the user passes its path.

Matching is mutual nearest neighbours against every gallery image, then the same RANSAC voting as
the SIFT baseline (:mod:`matl.baselines.keypoints`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from matl.baselines.keypoints import (
    ImageFeatures,
    RansacVotingMatcher,
    TentativeMatches,
    extract_in_batches,
    mutual_nn_matches,
    to_gray_float,
)

__all__ = ["SuperPointNet", "SuperPointRansacMatcher", "load_superpoint_state_dict"]

_CELL = 8  # encoder stride: three 2x2 max-pools


class SuperPointNet(nn.Module):
    """The SuperPoint network (encoder, detector head, descriptor head), without post-processing.

    Parameter names (``conv1a`` ... ``convDb``) are those of the public pretrained weights.

    Args:
        descriptor_dim: descriptor channels (256 in the release).
    """

    def __init__(self, descriptor_dim: int = 256) -> None:
        super().__init__()
        c1, c2, c3, c4, c5 = 64, 64, 128, 128, 256
        self.relu = nn.ReLU(inplace=True)
        self.pool = nn.MaxPool2d(kernel_size=2, stride=2)
        self.conv1a = nn.Conv2d(1, c1, 3, padding=1)
        self.conv1b = nn.Conv2d(c1, c1, 3, padding=1)
        self.conv2a = nn.Conv2d(c1, c2, 3, padding=1)
        self.conv2b = nn.Conv2d(c2, c2, 3, padding=1)
        self.conv3a = nn.Conv2d(c2, c3, 3, padding=1)
        self.conv3b = nn.Conv2d(c3, c3, 3, padding=1)
        self.conv4a = nn.Conv2d(c3, c4, 3, padding=1)
        self.conv4b = nn.Conv2d(c4, c4, 3, padding=1)
        self.convPa = nn.Conv2d(c4, c5, 3, padding=1)
        self.convPb = nn.Conv2d(c5, _CELL * _CELL + 1, 1)
        self.convDa = nn.Conv2d(c4, c5, 3, padding=1)
        self.convDb = nn.Conv2d(c5, descriptor_dim, 1)

    def forward(self, gray: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Run the network.

        Args:
            gray: ``(B, 1, H, W)`` grey images in [0, 1], ``H`` and ``W`` multiples of 8.

        Returns:
            ``logits (B, 65, H/8, W/8)`` of the detector head and the raw, unnormalised
            descriptor map ``(B, D, H/8, W/8)``.
        """
        x = gray
        for a, b, pool in (
            (self.conv1a, self.conv1b, True),
            (self.conv2a, self.conv2b, True),
            (self.conv3a, self.conv3b, True),
            (self.conv4a, self.conv4b, False),
        ):
            x = self.relu(b(self.relu(a(x))))
            if pool:
                x = self.pool(x)
        logits = self.convPb(self.relu(self.convPa(x)))
        desc = self.convDb(self.relu(self.convDa(x)))
        return logits, desc


def logits_to_heatmap(logits: torch.Tensor) -> torch.Tensor:
    """Detector logits ``(B, 65, Hc, Wc)`` to a keypoint probability map ``(B, 1, 8 Hc, 8 Wc)``.

    Softmax over the 65 bins, drop the dustbin, then depth-to-space: bin ``8 * dy + dx`` of cell
    ``(i, j)`` becomes pixel ``(8 i + dy, 8 j + dx)``, which is exactly ``pixel_shuffle``'s layout.
    """
    prob = logits.softmax(1)[:, :-1]
    return F.pixel_shuffle(prob, _CELL)


def nms_heatmap(heat: torch.Tensor, radius: int) -> torch.Tensor:
    """Keep only the local maxima of ``heat (B, 1, H, W)`` in a ``(2 r + 1)^2`` window (others 0)."""
    if radius <= 0:
        return heat
    local_max = F.max_pool2d(heat, kernel_size=2 * radius + 1, stride=1, padding=radius)
    return torch.where(heat == local_max, heat, torch.zeros_like(heat))


def sample_descriptors(desc: torch.Tensor, keypoints: torch.Tensor) -> torch.Tensor:
    """Interpolate a coarse descriptor map at pixel keypoints and L2-normalise.

    Cell ``(i, j)`` of the map describes pixels ``8 i .. 8 i + 7``, i.e. it sits at the pixel
    coordinate ``8 j + 3.5``; a keypoint ``x`` is therefore at cell coordinate ``(x - 3.5) / 8``.

    Args:
        desc: ``(D, Hc, Wc)`` descriptor map of one image.
        keypoints: ``(K, 2)`` pixel coordinates ``(x, y)``.

    Returns:
        ``(K, D)`` unit-norm descriptors.
    """
    d, hc, wc = desc.shape
    if keypoints.shape[0] == 0:
        return desc.new_zeros(0, d)
    cell = (keypoints - (_CELL - 1) / 2.0) / _CELL
    size = keypoints.new_tensor([max(wc - 1, 1), max(hc - 1, 1)])
    grid = (2.0 * cell / size - 1.0).view(1, 1, -1, 2)
    out = F.grid_sample(desc[None], grid.to(desc.dtype), mode="bilinear", align_corners=True)
    return F.normalize(out[0, :, 0].T, dim=1)


def load_superpoint_state_dict(path: str | Path) -> dict[str, torch.Tensor]:
    """Read a SuperPoint state dict from ``path`` without executing pickled code.

    Accepts the plain release state dict, a checkpoint that wraps it under ``state_dict`` or
    ``model_state_dict``, and names prefixed by ``module.`` (DataParallel) or ``model.``.
    """
    obj = torch.load(str(path), map_location="cpu", weights_only=True)
    if isinstance(obj, dict):
        for key in ("state_dict", "model_state_dict", "model"):
            if key in obj and isinstance(obj[key], dict):
                obj = obj[key]
                break
    if not isinstance(obj, dict):
        raise ValueError(f"{path} does not hold a state dict (got {type(obj).__name__})")
    out = {}
    for name, value in obj.items():
        for prefix in ("module.", "model."):
            if name.startswith(prefix):
                name = name[len(prefix) :]
        out[name] = value
    return out


class SuperPointRansacMatcher(RansacVotingMatcher):
    """SuperPoint features + mutual nearest neighbours + RANSAC homography voting.

    Args:
        weights: path to the pretrained ``superpoint_v1.pth`` (config key ``baseline.weights``).
            Required: matl neither ships nor downloads it.
        nms_radius: non-maximum-suppression radius in pixels (paper: 4).
        keypoint_threshold: minimum keypoint probability (paper: 0.005).
        max_keypoints: keep at most this many highest-scoring keypoints (paper: 1024; <= 0: all).
        remove_borders: drop keypoints closer than this many pixels to the image border (the release
            demo's 4), where the zero padding of the convolutions makes responses unreliable.
        max_descriptor_distance: optional L2 bound on a mutual-NN pair (unit descriptors: in [0, 2]).
        batch_size: images per network forward when indexing the gallery.
        device: torch device for the network.
        **ransac: the RANSAC vote, :class:`~matl.baselines.keypoints.RansacVoting`'s keys
            (``ransac_reproj_threshold``, ``min_inliers``, ``top_k``, ``ransac_max_iters``,
            ``ransac_confidence``, ``ransac_method``); ``top_k`` counts mutual nearest neighbours.

    Raises:
        ValueError: ``weights`` is None.
        FileNotFoundError: ``weights`` does not exist.
    """

    def __init__(
        self,
        weights: str | Path | None,
        nms_radius: int = 4,
        keypoint_threshold: float = 0.005,
        max_keypoints: int = 1024,
        remove_borders: int = 4,
        max_descriptor_distance: float | None = None,
        batch_size: int = 64,
        device: str = "cpu",
        **ransac: Any,
    ) -> None:
        super().__init__(**ransac)
        if weights is None:
            raise ValueError(
                "SuperPointRansacMatcher needs the pretrained SuperPoint weights, which matl does not ship "
                "or download: set baseline.weights=/path/to/superpoint_v1.pth (or the environment variable "
                "MATL_SUPERPOINT_WEIGHTS) to the Magic Leap release file"
            )
        path = Path(weights).expanduser()
        if not path.is_file():
            raise FileNotFoundError(
                f"SuperPoint weights not found at baseline.weights={weights}: "
                "give the path of superpoint_v1.pth"
            )
        self.nms_radius = int(nms_radius)
        self.keypoint_threshold = float(keypoint_threshold)
        self.max_keypoints = int(max_keypoints)
        self.remove_borders = int(remove_borders)
        self.max_descriptor_distance = max_descriptor_distance
        self.batch_size = int(batch_size)
        self.device = torch.device(device)
        self.net = SuperPointNet()
        state = load_superpoint_state_dict(path)
        missing, unexpected = self.net.load_state_dict(state, strict=False)
        if missing or unexpected:
            raise ValueError(
                f"{path} is not a SuperPoint state dict: "
                f"missing {sorted(missing)}, unexpected {sorted(unexpected)}"
            )
        self.net.eval().to(self.device)

    @torch.no_grad()
    def extract(self, images: torch.Tensor) -> list[ImageFeatures]:
        """SuperPoint keypoints ``(K, 2)`` and unit descriptors ``(K, 256)`` of images ``(B, 3, H, W)``."""
        return extract_in_batches(self._extract_batch, images, self.batch_size)

    def _extract_batch(self, images: torch.Tensor) -> list[ImageFeatures]:
        h, w = images.shape[-2:]
        gray = to_gray_float(images.float()).to(self.device)
        # pad bottom/right to a multiple of the cell size so every pixel has a detector bin; the
        # padding is black like the background, and the heatmap is cropped back before NMS
        pad_h, pad_w = (-h) % _CELL, (-w) % _CELL
        gray = F.pad(gray, (0, pad_w, 0, pad_h))
        logits, desc = self.net(gray)
        heat = logits_to_heatmap(logits)[..., :h, :w]
        heat = nms_heatmap(heat, self.nms_radius)
        b = self.remove_borders
        if b > 0:
            border = torch.zeros_like(heat, dtype=torch.bool)
            border[..., b : h - b, b : w - b] = True
            heat = heat * border
        feats = []
        for i in range(heat.shape[0]):
            ys, xs = torch.nonzero(heat[i, 0] > self.keypoint_threshold, as_tuple=True)
            scores = heat[i, 0, ys, xs]
            if 0 < self.max_keypoints < scores.numel():
                # stable sort keeps equal scores in raster order, so the cut is deterministic
                keep = torch.sort(scores, descending=True, stable=True).indices[: self.max_keypoints]
                keep = keep.sort().values
                ys, xs = ys[keep], xs[keep]
            kpts = torch.stack([xs, ys], 1).to(desc.dtype)
            descriptors = sample_descriptors(desc[i], kpts)
            feats.append(ImageFeatures(kpts.cpu().numpy().astype(np.float32), descriptors.float().cpu()))
        return feats

    def tentative(self, query: ImageFeatures) -> TentativeMatches:
        """Mutual nearest-neighbour matches of the query with every gallery image."""
        return mutual_nn_matches(query.descriptors, self._require_gallery(), self.max_descriptor_distance)
