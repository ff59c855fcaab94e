"""SIFT + RANSAC baseline, Table 1 row (d) (Sec. 5.5).

OpenCV SIFT with the paper's parameters (sigma 1.6, contrast threshold 0.004, edge threshold 1000),
Lowe's ratio test against each gallery image, ``cv2.findHomography`` with RANSAC per gallery image,
and the gallery image with most inliers wins. The matching runs against the whole gallery at once
(see :mod:`matl.baselines.keypoints`) and gives the same answer as the per-image loop.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
import torch

from matl.baselines.keypoints import (
    ImageFeatures,
    RansacVotingMatcher,
    TentativeMatches,
    ratio_test_matches,
    to_gray_uint8,
)

__all__ = ["SiftRansacMatcher"]


class SiftRansacMatcher(RansacVotingMatcher):
    """SIFT + ratio test + RANSAC homography, voting for the gallery image with most inliers.

    Args:
        sigma: Gaussian sigma of the first octave (paper: 1.6).
        contrast_threshold: DoG contrast threshold (paper: 0.004; OpenCV's default is 0.04).
        edge_threshold: edge-response threshold (paper: 1000, which practically disables it).
        ratio: Lowe's ratio test threshold.
        n_octave_layers: DoG layers per octave (OpenCV's and Lowe's 3).
        max_features: keep at most this many strongest keypoints per image (0: all, OpenCV's default).
        **ransac: the RANSAC vote, :class:`~matl.baselines.keypoints.RansacVoting`'s keys
            (``ransac_reproj_threshold``, ``min_inliers``, ``top_k``, ``ransac_max_iters``,
            ``ransac_confidence``, ``ransac_method``); ``top_k`` counts ratio-test matches.
    """

    def __init__(
        self,
        sigma: float = 1.6,
        contrast_threshold: float = 0.004,
        edge_threshold: float = 1000.0,
        ratio: float = 0.8,
        n_octave_layers: int = 3,
        max_features: int = 0,
        **ransac: Any,
    ) -> None:
        super().__init__(**ransac)
        if not 0.0 < ratio <= 1.0:
            raise ValueError(f"ratio must be in (0, 1], got {ratio}")
        self.ratio = float(ratio)
        self.sigma = float(sigma)
        self.contrast_threshold = float(contrast_threshold)
        self.edge_threshold = float(edge_threshold)
        self.n_octave_layers = int(n_octave_layers)
        self.max_features = int(max_features)
        self._sift = cv2.SIFT_create(
            nfeatures=self.max_features,
            nOctaveLayers=self.n_octave_layers,
            contrastThreshold=self.contrast_threshold,
            edgeThreshold=self.edge_threshold,
            sigma=self.sigma,
        )

    def extract(self, images: torch.Tensor) -> list[ImageFeatures]:
        """SIFT keypoints ``(K, 2)`` and descriptors ``(K, 128)`` of each image ``(B, 3, H, W)``.

        Images are converted to 8-bit grey as OpenCV's SIFT expects.
        """
        out = []
        for gray in to_gray_uint8(images):
            kps, desc = self._sift.detectAndCompute(gray, None)
            pts = np.array([kp.pt for kp in kps], dtype=np.float32).reshape(-1, 2)
            if desc is None:
                desc = np.zeros((0, 128), dtype=np.float32)
            out.append(ImageFeatures(pts, torch.from_numpy(np.ascontiguousarray(desc, dtype=np.float32))))
        return out

    def tentative(self, query: ImageFeatures) -> TentativeMatches:
        """Ratio-test matches of the query with every gallery image (per-image 2-NN)."""
        return ratio_test_matches(query.descriptors, self._require_gallery(), self.ratio)
