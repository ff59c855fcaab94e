"""A pose from keypoints for answers that do not verify: the crop matched against its answered product's planes.

Under an occluder the networks' pose of a partly hidden product is often far off (s() regresses one homography from
the whole crop, the hidden part included), and the photometric refinement cannot reach the truth from there. Local
features do not need the whole product: SIFT keypoints of the crop are matched (Lowe's ratio test) with those of
every enrolled plane of the answered product, and RANSAC finds the homography of the plane with most inliers
(:mod:`matl.baselines.keypoints`, the SIFT baseline's matching). Both images are brought to one working size first
(``size`` px on the longer side), where SIFT finds enough keypoints on a small crop.

The keypoint pose (refined from there when the recognizer refines) replaces the answer's pose only where its
verification distance is lower (:func:`~matl.inference.verify.verification_distance`, over the query's visibility):
it can change which plane of the product is answered, never the product, and it can make an answer verify (so a
partly hidden known product is answered known) but never make the kept pose worse by that criterion.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np
import torch

from matl.baselines.keypoints import (
    RANSAC_METHODS,
    GalleryDescriptors,
    ImageFeatures,
    ratio_test_matches,
    vote_by_ransac,
)
from matl.baselines.sift import SiftRansacMatcher
from matl.data.image_files import fit_to_model
from matl.inference.images import _query_visibility, _with_rows
from matl.inference.stage_settings import StageSettings
from matl.inference.verify import Verification
from matl.models.prediction import Prediction
from matl.utils.errors import MatlError
from matl.utils.threads import thread_map
from matl.utils.timing import stage

__all__ = ["KEYPOINT_POSE_MODES", "KeypointPose", "KeypointPoses"]

#: when the keypoint pose is tried: never, for answers that do not verify, for every answer
KEYPOINT_POSE_MODES = ("none", "unverified", "always")


def _scaled(rgb: np.ndarray, size: int) -> tuple[np.ndarray, float]:
    """``rgb`` ``(H, W, 3)`` float in [0, 1] resized so its longer side is ``size`` px, and the factor (new px per
    old px)."""
    factor = size / max(rgb.shape[:2])
    if abs(factor - 1.0) < 1e-9:
        return rgb, 1.0
    shape = (max(1, round(rgb.shape[1] * factor)), max(1, round(rgb.shape[0] * factor)))
    interpolation = cv2.INTER_LINEAR if factor > 1 else cv2.INTER_AREA
    return cv2.resize(np.ascontiguousarray(rgb, dtype=np.float32), shape, interpolation=interpolation), factor


@dataclass
class KeypointPose(StageSettings):
    """The keypoint pose's settings (Recognizer's ``keypoint_pose*`` options).

    Args:
        mode: ``unverified`` (answers whose pose does not verify; the Recognizer's default), ``always`` or ``none``.
        size: the working size, px on the longer side, of the crop and of the planes' canonical images.
        min_inliers: fewest RANSAC inliers of a keypoint pose.
        ratio: Lowe's ratio test.
        reproj_threshold: RANSAC's inlier threshold in model pixels (the query's file pixels scaled to the model's
            size).
        method: a ``cv2.findHomography`` method of :data:`~matl.baselines.keypoints.RANSAC_METHODS`.
        products: the nearest products tried in turn while the answer does not verify: the answered one, then the
            next nearest (by the embedding), whose keypoint pose becomes the answer only where it verifies; such an
            answer is not counted as verified by the open set (the crop may show an enrolled product lying across
            the one it was cut for: its keypoints match and verify too), which judges it by its statistic.
        contrast_threshold: SIFT's DoG contrast threshold (OpenCV's default; the paper's baseline takes 0.004, ten
            times the keypoints and the time).
        max_features: the strongest keypoints kept per image.
        switch_margin: an answer that verifies at none of the ``products`` tried becomes the one of them whose
            planes have most keypoint inliers (at least ``min_inliers``) where that product has at least this many
            more than the answered one (which counts 0 without a keypoint pose); still not verified, so the open
            set judges it by its statistic. None: the answer stays the nearest product's.
        precompute: a gallery of at most this many planes gets every plane's keypoints when it is built (at
            enrolment, and for the planes an add brings), so that no query waits for them; a larger one computes a
            plane's at the first query that needs them (about 14 ms a plane at one thread, and up to 256 kB held).
    """

    mode: str = "none"
    size: int = 250
    min_inliers: int = 8
    ratio: float = 0.85
    reproj_threshold: float = 3.0
    method: str = "usac_magsac"
    products: int = 5
    contrast_threshold: float = 0.04
    max_features: int = 500
    switch_margin: int | None = 3
    precompute: int = 1024

    def __post_init__(self) -> None:
        if self.mode not in KEYPOINT_POSE_MODES:
            raise MatlError(f"keypoint_pose={self.mode!r} is invalid: use {', '.join(KEYPOINT_POSE_MODES)}")
        if isinstance(self.size, bool) or not isinstance(self.size, int) or not 32 <= self.size <= 2048:
            raise MatlError(f"KeypointPose size={self.size!r} is invalid: use an integer number of px in [32, 2048]")
        if isinstance(self.min_inliers, bool) or not isinstance(self.min_inliers, int) or self.min_inliers < 4:
            raise MatlError(f"KeypointPose min_inliers={self.min_inliers!r} is invalid: use an integer >= 4 (a "
                            "homography needs 4)")
        if isinstance(self.ratio, bool) or not isinstance(self.ratio, (int, float)) or not 0.0 < self.ratio <= 1.0:
            raise MatlError(f"KeypointPose ratio={self.ratio!r} is invalid: use Lowe's ratio in (0, 1] (e.g. 0.85)")
        threshold = self.reproj_threshold
        if isinstance(threshold, bool) or not isinstance(threshold, (int, float)) or not threshold > 0:
            raise MatlError(f"KeypointPose reproj_threshold={threshold!r} is invalid: use a distance in model px > 0")
        if isinstance(self.products, bool) or not isinstance(self.products, int) or self.products < 1:
            raise MatlError(f"KeypointPose products={self.products!r} is invalid: use an integer >= 1 (1: the "
                            "answered product alone)")
        margin = self.switch_margin
        if margin is not None and (isinstance(margin, bool) or not isinstance(margin, int) or margin < 0):
            raise MatlError(f"KeypointPose switch_margin={margin!r} is invalid: use an integer number of inliers >= 0, "
                            "or None to keep the nearest product")
        if isinstance(self.precompute, bool) or not isinstance(self.precompute, int) or self.precompute < 0:
            raise MatlError(f"KeypointPose precompute={self.precompute!r} is invalid: use an integer number of planes "
                            ">= 0 (0: every plane's keypoints at their first need)")
        if self.method not in RANSAC_METHODS:
            raise MatlError(f"KeypointPose method={self.method!r} is invalid: use {', '.join(RANSAC_METHODS)}")
        self.ratio, self.reproj_threshold = float(self.ratio), float(threshold)
        self._new_workers()  # each thread its own SIFT detector

    def _extract(self, rgb: np.ndarray) -> ImageFeatures:
        """SIFT features of ``rgb`` ``(H, W, 3)`` float in [0, 1] at the working size, keypoints in ``rgb``'s own
        pixels (pixel centres at integers)."""
        sift = getattr(self._local, "sift", None)
        if sift is None:
            sift = self._local.sift = SiftRansacMatcher(contrast_threshold=self.contrast_threshold,
                                                        edge_threshold=10.0, ratio=self.ratio,
                                                        max_features=self.max_features)
        scaled, factor = _scaled(rgb, self.size)
        features = sift.extract(torch.from_numpy(np.ascontiguousarray(scaled)).permute(2, 0, 1)[None])[0]
        return ImageFeatures((features.keypoints + 0.5) / factor - 0.5, features.descriptors)

    def plane_features(self, canon_u8: torch.Tensor) -> ImageFeatures:
        """The features of a plane's canonical image ``(3, S, S)`` uint8, keypoints in model pixels."""
        return self._extract(canon_u8.permute(1, 2, 0).numpy().astype(np.float32) / 255.0)

    def query_features(self, rgb: np.ndarray) -> ImageFeatures:
        """The features of a crop ``(H, W, 3)`` float in [0, 1], keypoints in its pixels."""
        return self._extract(rgb)

    def match(self, query: ImageFeatures, planes: list[ImageFeatures], model_px: float
              ) -> tuple[int, np.ndarray, int]:
        """The plane of ``planes`` with most RANSAC inliers against ``query`` (``model_px``: the query's file px per
        model px, which scales the inlier threshold): ``(index, file_H_canon (3, 3) float64, inliers)``, or
        ``(-1, identity, 0)`` when none reaches ``min_inliers``."""
        if len(query) < 4 or not any(len(p) >= 4 for p in planes):
            return -1, np.eye(3), 0
        matches = ratio_test_matches(query.descriptors, GalleryDescriptors(planes), self.ratio)
        return vote_by_ransac(query.keypoints, [p.keypoints for p in planes], matches,
                              reproj_threshold=self.reproj_threshold * model_px, min_inliers=self.min_inliers,
                              method=RANSAC_METHODS[self.method])


def _smallest_rotation(query_H_canon: torch.Tensor, anchor_H_canon: torch.Tensor) -> tuple[int, torch.Tensor]:
    """Of a plane's ``N`` anchors ``(N, 3, 3)``, the one whose ``query_H_anchor`` turns least (the anchor the STN
    would pick for this pose) and that pose ``(3, 3)`` float64."""
    poses = query_H_canon.double()[None] @ torch.linalg.inv(anchor_H_canon.double())
    poses = poses / poses[:, 2:, 2:]
    angles = torch.atan2(poses[:, 1, 0] - poses[:, 0, 1], poses[:, 0, 0] + poses[:, 1, 1]).abs()
    k = int(torch.argmin(angles))
    return k, poses[k]


class _Candidate(NamedTuple):
    """A keypoint pose of one query row against one product's planes."""

    row: int                      # the query's row in the prediction
    gallery_index: int            # the anchor (plane * N + k) whose frame the pose is in
    query_H_anchor: torch.Tensor  # (3, 3) float64, model frame
    model_px: float               # model px per file px of the query
    inliers: int                  # RANSAC inliers of the plane matched


class KeypointPoses:
    """The keypoint side of :class:`~matl.inference.api.Recognizer`; a mixin of it, using its planes, gallery,
    refiner, verification options and ``keypoint_pose`` settings."""

    def _precompute_keypoints(self) -> None:
        """Every enrolled plane's keypoints that are not computed yet, when the keypoint pose is on and the gallery
        has at most ``keypoint_pose.precompute`` planes (the planes over torch's threads)."""
        settings: KeypointPose = self.keypoint_pose
        if not settings.active or len(self._planes) > settings.precompute:
            return
        missing = [i for i, p in enumerate(self._planes) if p.keypoints is None]
        for i, features in zip(missing, thread_map(lambda i: settings.plane_features(self._planes[i].canon_u8),
                                                   missing), strict=True):
            self._planes[i].keypoints = features

    def _plane_keypoints(self, plane: int) -> ImageFeatures:
        """Enrolled plane ``plane``'s keypoints, computed at its first need and kept with the plane."""
        p = self._planes[plane]
        if p.keypoints is None:
            p.keypoints = self.keypoint_pose.plane_features(p.canon_u8)
        return p.keypoints

    def _keypoint_poses(self, prepared: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]], pred: Prediction,
                        query_H_file: torch.Tensor, verification: Verification) -> tuple[Prediction, Verification]:
        """``pred`` and ``verification`` with the keypoint pose of each answer it applies to (``keypoint_pose``:
        those that do not verify, or all) where its verification distance is lower than the answer's."""
        settings: KeypointPose = self.keypoint_pose
        rows = [i for i in range(len(prepared)) if settings.mode == "always" or not bool(verification.verified[i])]
        if not rows:
            return pred, verification
        with stage(self.stage_timer, "keypoints"):
            return self._keypoint_rows(prepared, pred, query_H_file, verification, rows)

    def _keypoint_rows(self, prepared: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]], pred: Prediction,
                       query_H_file: torch.Tensor, verification: Verification, rows: list[int]
                       ) -> tuple[Prediction, Verification]:
        settings: KeypointPose = self.keypoint_pose
        by_object: dict[int, list[int]] = {}
        for p, o in enumerate(self._plane_objects()):
            by_object.setdefault(o, []).append(p)
        ranked = {i: [int(pred.object_index[i])] for i in rows}  # the answered product, then the next nearest
        if settings.products > 1 and pred.features is not None and len(by_object) > 1:
            distances = self._object_distances(pred.features[rows])[0]
            for j, i in enumerate(rows):
                order = [o for o in torch.argsort(distances[j]).tolist() if o != ranked[i][0]]
                ranked[i] += order[:settings.products - 1]
        # the crops at the model's size as the networks saw them before any pose pass, and their visibility: once
        sub = [prepared[i] for i in rows]
        queries = torch.stack([fit_to_model(masked, self.image_size, self.query_fill)[0] for masked, _, _ in sub])
        framed = (queries.to(self.device), _query_visibility(sub, self.image_size, self.query_fill, self.device),
                  {i: j for j, i in enumerate(rows)})
        features: dict[int, ImageFeatures] = {}
        tried: dict[int, list[_Candidate | None]] = {i: [] for i in rows}
        for rank in range(settings.products):
            todo = [i for i in rows if rank < len(ranked[i]) and (rank == 0 or not bool(verification.verified[i]))]
            found = []
            calls = [(prepared[i], query_H_file[i], i, by_object[ranked[i][rank]], features) for i in todo]
            # the rows over torch's threads (each writes its own entry of features)
            candidates = thread_map(lambda call: self._keypoint_candidate(*call), calls)
            for i, candidate in zip(todo, candidates, strict=True):
                tried[i].append(candidate)
                if candidate is not None:
                    found.append(candidate)
            if found:
                pred, verification = self._keep_better(pred, verification, found, framed, rank > 0)
        if settings.switch_margin is not None:  # verified nowhere: the product whose keypoints match clearly most
            switch = []
            for i in rows:
                if bool(verification.verified[i]) or len(tried[i]) < 2:
                    continue
                answered = tried[i][0].inliers if tried[i][0] is not None else 0
                best = max((c for c in tried[i][1:] if c is not None), key=lambda c: c.inliers, default=None)
                if best is not None and best.inliers >= answered + settings.switch_margin:
                    switch.append(best)
            if switch:
                pred, verification = self._keep_better(pred, verification, switch, framed, True, force=True)
        return pred, verification

    def _keypoint_candidate(self, prepared: tuple[np.ndarray, np.ndarray, np.ndarray | None],
                            model_H_file: torch.Tensor, row: int, planes: list[int],
                            features: dict[int, ImageFeatures]) -> _Candidate | None:
        """Query ``row``'s keypoint pose against the enrolled planes ``planes`` (one product's), that of the plane
        with most inliers, or None (``features``: each row's query features, computed at the first need)."""
        settings: KeypointPose = self.keypoint_pose
        masked, rgb, alpha = prepared
        model_H_file = model_H_file.double()
        model_px = float(torch.sqrt(torch.det(model_H_file[:2, :2]).abs()))  # model px per file px
        if not math.isfinite(model_px) or model_px <= 0:
            return None
        if row not in features:  # a foreground step's crop whole; a given alpha applied
            features[row] = settings.query_features(rgb if alpha is not None else masked)
        index, file_H_canon, inliers = settings.match(features[row], [self._plane_keypoints(p) for p in planes],
                                                1.0 / model_px)
        if index < 0:
            return None
        plane, N = planes[index], self.num_anchors
        query_H_canon = model_H_file @ torch.from_numpy(file_H_canon)
        anchor_H_canon = self._build()[1].anchor_H_canon64()[plane * N:(plane + 1) * N]
        k, query_H_anchor = _smallest_rotation(query_H_canon, anchor_H_canon)
        return _Candidate(row, plane * N + k, query_H_anchor, model_px, inliers)

    def _keep_better(self, pred: Prediction, verification: Verification,
                     found: list[_Candidate],
                     framed: tuple[torch.Tensor, torch.Tensor | None, dict[int, int]],
                     other_product: bool = False, force: bool = False) -> tuple[Prediction, Verification]:
        """The keypoint poses ``found`` (refined when the recognizer refines) where their verification distance is
        lower than the answer's (``other_product``: they are another product's, taken only where they verify;
        ``force``: taken in any case, the keypoint match having decided); ``framed``: the model-size queries,
        their visibility (or None) and each row's position in them."""
        rows = [f.row for f in found]
        index = torch.tensor([f.gallery_index for f in found])
        start = torch.stack([f.query_H_anchor for f in found])
        at = [framed[2][i] for i in rows]
        queries, visibility = framed[0][at], None if framed[1] is None else framed[1][at]
        query_H_anchor, distance = start, self._pose_check(queries, start, index, visibility)
        if self.refiner is not None or self.verify_refine:  # refined from there, kept where it verifies better
            refiner, templates = self._candidate_refiner()
            upscale = torch.tensor([f.model_px for f in found], dtype=torch.float64)
            refined = refiner(queries, index, start, templates, visibility=visibility,
                              upscale=upscale).query_H_anchor.double()
            refined_distance = self._pose_check(queries, refined, index, visibility)
            closer = (refined_distance < distance)[:, None, None]
            query_H_anchor = torch.where(closer, refined, start)
            distance = torch.minimum(refined_distance, distance)
        better = [j for j, i in enumerate(rows) if force or (float(distance[j]) < float(verification.distance[i])
                  and (not other_product or float(distance[j]) <= self.verify_max))]
        if not better:
            return pred, verification
        take, g, new_H = [rows[j] for j in better], index[better], query_H_anchor[better]
        feature_distance = verification.distance.new_full((len(better),), float("nan"))
        gallery_features = getattr(self._gallery_recognizer(), "gallery_features", None)
        if pred.features is not None and gallery_features is not None:
            feature_distance = (pred.features[take].float() - gallery_features[g.to(pred.features.device)].float()
                                ).norm(dim=1).to(feature_distance)
        pred = self._answered(pred, take, g, new_H, feature_distance)
        kept = distance[better].to(verification.distance)
        # another product's pose verifies: the nearest product changes, but known stays the open-set statistic's to
        # judge (the crop may show an enrolled product lying across the one it was cut for)
        verified = verification.verified[take] if other_product else kept <= self.verify_max
        source = list(range(len(take)))
        answer = {"gallery_index": g, "query_H_anchor": new_H, "feature_distance": feature_distance, "distance": kept,
                  "verified": verified}
        return pred, dataclasses.replace(verification, **{name: _with_rows(getattr(verification, name), take, value,
                                                                           source) for name, value in answer.items()})
