"""A pose from dense optical flow: the crop matched to its answer's anchor pixel by pixel.

Under an occluder the networks' pose of a partly hidden product is typically 10-20 px off at the model's 100 px, and
the photometric refinement converges only from a few px (its loss, a sum over the anchor's plane, also gains where
the visible print is stretched over the hidden part). Dense optical flow reaches that far: the crop, warped into the
answer's anchor frame by the answer's pose, is matched to the anchor by OpenCV's DIS optical flow (coarse to fine,
with its variational refinement), both brought to ``scale`` times the model's size first, where a 100 px product's
print has enough detail. A homography is fitted by MAGSAC to the flow of the anchor's textured foreground pixels that
the query shows (its visibility warped by the same pose): the occluder's and the background's flow are outliers. The
fit, composed with the answer's pose, is the flow pose. DIS reaches a start that far only in part, so for an answer
that still does not verify the match is made again from the pose it found (up to ``rounds`` rounds).

It is tried for every answer whose verification distance is above ``above`` (``mode=always``, the default) or for
those that do not verify (``unverified``), and replaces the answer's pose where it is judged better (the
Recognizer's ``pose_judge``: by default the sum of its verification distance,
:func:`~matl.inference.verify.verification_distance` over the query's visibility, and of
:func:`~matl.inference.verify.explained_distance`, which compares both poses over the query's own visible pixels,
so neither a pose that shrinks the plane onto a few well-matching pixels nor one that stretches it over the mask
wins by that alone): it never changes the product or the plane. An answer whose pose failed verification and that
the flow pose brings within ``verifies`` counts as verified (a partly hidden product the networks posed far off);
one held unverified below ``verify_max`` for another reason stays so. It is not refined afterwards: from a flow
pose under an occluder the refinement moves the pose away more often than closer.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import torch

from matl.geometry import corner_error_px
from matl.inference.stage_settings import StageSettings
from matl.inference.verify import Verification
from matl.models.prediction import Prediction
from matl.utils.config import is_int, is_number
from matl.utils.errors import MatlError
from matl.utils.threads import thread_map
from matl.utils.timing import stage

__all__ = ["FLOW_POSE_MODES", "FLOW_PRESETS", "FlowPose", "FlowPoses"]

#: when the flow pose is tried: never, for answers that do not verify, for every answer
FLOW_POSE_MODES = ("none", "unverified", "always")
#: a flow round that moves the plane's corners (at the model's size) by less than this many px ends the rounds
SETTLED_PX = 0.1
#: OpenCV's DIS presets by name
FLOW_PRESETS = {"ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST, "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
                "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM}


def _integer(value: Any, low: int, high: int) -> bool:
    return is_int(value) and low <= value <= high


def _luminance_u8(image: torch.Tensor, side: int) -> np.ndarray:
    """``image`` ``(3, S, S)`` float in [0, 1] as ``(side, side)`` uint8 luminance (cubic resampling)."""
    rgb = (image.detach().float().cpu().clamp(0, 1).permute(1, 2, 0).numpy() * 255.0).astype(np.uint8)
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    if grey.shape[0] == side:
        return grey
    return cv2.resize(grey, (side, side), interpolation=cv2.INTER_CUBIC)


@dataclass
class FlowPose(StageSettings):
    """The flow pose's settings (Recognizer's ``flow_pose`` option).

    Args:
        mode: ``always`` (every answer whose verification distance is above ``above``; the Recognizer's default),
            ``unverified`` (answers whose pose does not verify) or ``none``.
        above: ``always``: the answers whose verification distance (``1 - ZNCC``) is at most this are left as they
            are (a pose that close is as good as the flow's; 0: every answer). On validation 0.03 skips about half
            of the whole products' queries and loses none of the flow's gains (docs/decisions.md).
        scale: the crop and the anchor are matched at this many times the model's size.
        preset: OpenCV's DIS preset (``ultrafast``, ``fast``, ``medium``): patch size, stride and iterations.
        finest_scale: DIS's finest pyramid level (0: full resolution).
        variational_iterations: DIS's variational refinement iterations per level (0: none).
        reproj_threshold: MAGSAC's inlier threshold, model px.
        max_points: most flow vectors the homography is fitted to (the textured visible pixels, evenly thinned).
        min_points: fewest such pixels for a fit.
        texture: a pixel is textured where the anchor's Sobel gradient magnitude (luminance 0-255 at the matching
            size) exceeds this: flat print carries no flow.
        dark: anchor pixels of at most this luminance (0-255) are left out: the background (0 by convention) and the
            darkest print, which the black of a query's masked-out pixels cannot be told from.
        verifies: an answer whose pose did not verify (verification distance above the Recognizer's ``verify_max``)
            and that the flow pose brings to at most this counts as verified by the open set (a partly hidden
            product posed right by the flow is known); an answer held unverified for another reason (another
            product's keypoint pose, which can be a product lying across an unenrolled one) stays unverified. None:
            the flow pose never makes an answer count as verified (docs/decisions.md).
        rounds: the flow is matched again from the pose of the round before, up to this many rounds (fewer when a
            round fits no homography, settles or stops converging: :meth:`pose`); each round's pose is judged
            against the best so far (``pose_judge``), so a start 10-20 px off is reached in steps and a round that
            drifts is not kept. In a Recognizer the rounds after the first go on only for the answers that still do not
            verify (verification distance above ``verify_max``): a pose that verifies is left to the first round.
            3 (default): on validation more partly hidden products posed within 5 px and answered known than with 1,
            as many as with 5 (docs/decisions.md); 1: one match.
        max_upscale: a query whose file was enlarged more than this many times to the model's size is left as it is
            (its print is too blurred against the sharp anchor: on validation 40 px crops lost 0.03 of their refined
            ``pose_acc_5px`` to the flow pose); None: every query.
    """

    mode: str = "none"
    above: float = 0.03
    scale: int = 2
    preset: str = "fast"
    finest_scale: int = 0
    variational_iterations: int = 5
    reproj_threshold: float = 1.0
    max_points: int = 800
    min_points: int = 12
    texture: float = 20.0
    dark: float = 8.0
    verifies: float | None = 0.08
    max_upscale: float | None = 1.5
    rounds: int = 3

    def __post_init__(self) -> None:
        if self.mode not in FLOW_POSE_MODES:
            raise MatlError(f"flow_pose={self.mode!r} is invalid: use {', '.join(FLOW_POSE_MODES)}")
        if not is_number(self.above) or not 0.0 <= self.above <= 2.0:
            raise MatlError(f"FlowPose above={self.above!r} is invalid: use a verification distance in [0, 2] (0: "
                            "every answer)")
        if not _integer(self.scale, 1, 8):
            raise MatlError(f"FlowPose scale={self.scale!r} is invalid: use an integer factor in [1, 8] (e.g. 2)")
        if self.preset not in FLOW_PRESETS:
            raise MatlError(f"FlowPose preset={self.preset!r} is invalid: use {', '.join(FLOW_PRESETS)}")
        if not _integer(self.finest_scale, 0, 6):
            raise MatlError(f"FlowPose finest_scale={self.finest_scale!r} is invalid: use a pyramid level in [0, 6] "
                            "(0: full resolution)")
        if not _integer(self.variational_iterations, 0, 100):
            raise MatlError(f"FlowPose variational_iterations={self.variational_iterations!r} is invalid: use an "
                            "integer in [0, 100]")
        if not is_number(self.reproj_threshold) or not self.reproj_threshold > 0:
            raise MatlError(f"FlowPose reproj_threshold={self.reproj_threshold!r} is invalid: use a distance in "
                            "model px > 0")
        if not _integer(self.min_points, 4, 1_000_000) or not _integer(self.max_points, self.min_points, 1_000_000):
            raise MatlError(f"FlowPose min_points={self.min_points!r}, max_points={self.max_points!r} are invalid: "
                            "use integers with 4 <= min_points <= max_points (a homography needs 4)")
        if not is_number(self.texture) or self.texture < 0:
            raise MatlError(f"FlowPose texture={self.texture!r} is invalid: use a gradient magnitude >= 0")
        if not is_number(self.dark) or not 0 <= self.dark < 255:
            raise MatlError(f"FlowPose dark={self.dark!r} is invalid: use a luminance in [0, 255) (e.g. 8)")
        self.reproj_threshold, self.texture, self.dark = float(self.reproj_threshold), float(self.texture), float(
            self.dark)
        self.above = float(self.above)
        if self.max_upscale is not None and (not is_number(self.max_upscale) or not self.max_upscale >= 1.0):
            raise MatlError(f"FlowPose max_upscale={self.max_upscale!r} is invalid: use a factor >= 1 or None (every "
                            "query)")
        if not _integer(self.rounds, 1, 20):
            raise MatlError(f"FlowPose rounds={self.rounds!r} is invalid: use an integer in [1, 20] (1: one flow from "
                            "the answer's pose)")
        if self.verifies is not None and (not is_number(self.verifies) or not 0.0 <= self.verifies <= 2.0):
            raise MatlError(f"FlowPose verifies={self.verifies!r} is invalid: use a verification distance in [0, 2] "
                            "or None (the flow pose never makes an answer count as verified)")
        self._new_workers()  # each thread its own DIS object

    def _flow(self) -> Any:
        dis = getattr(self._local, "dis", None)
        if dis is None:
            dis = cv2.DISOpticalFlow_create(FLOW_PRESETS[self.preset])
            dis.setFinestScale(self.finest_scale)
            dis.setVariationalRefinementIterations(self.variational_iterations)
            self._local.dis = dis
        return dis

    def pose(self, query: torch.Tensor, anchor: torch.Tensor, query_H_anchor: torch.Tensor,
             visibility: torch.Tensor | None = None) -> torch.Tensor | None:
        """The flow pose of one query: up to ``rounds`` rounds of :meth:`matched`, each from the one before; they end
        when a round fits no homography, moves the plane's corners by less than :data:`SETTLED_PX` (settled) or by no
        less than the round before (not converging: that round is left out). Arguments and result as
        :meth:`matched`'s; None: the first round fits nothing."""
        pose, last_move = None, float("inf")
        for _ in range(self.rounds):
            step = self.step(query, anchor, query_H_anchor if pose is None else pose, visibility, last_move)
            if step is None:
                break
            pose, last_move = step
            if last_move < SETTLED_PX:
                break
        return pose

    def step(self, query: torch.Tensor, anchor: torch.Tensor, query_H_anchor: torch.Tensor,
             visibility: torch.Tensor | None, last_move: float) -> tuple[torch.Tensor, float] | None:
        """One round of :meth:`pose` from ``query_H_anchor``: its pose and how far it moved the plane's corners
        (px at the model's size); None where it fits no homography or moves them by no less than ``last_move`` (the
        round before's move; inf for the first round)."""
        found = self.matched(query, anchor, query_H_anchor, visibility)
        if found is None:
            return None
        moved = float(corner_error_px(found[None], query_H_anchor.detach().double().cpu()[None],
                                      tuple(query.shape[-2:]))[0])
        return (found, moved) if moved < last_move else None

    def matched(self, query: torch.Tensor, anchor: torch.Tensor, query_H_anchor: torch.Tensor,
                visibility: torch.Tensor | None = None) -> torch.Tensor | None:
        """One round of the flow pose of one query: the crop warped by the pose, matched to the anchor, the fit.

        Args:
            query: ``(3, S, S)`` the model-size query in [0, 1]; anchor: ``(3, S, S)`` its answer's anchor.
            query_H_anchor: ``(3, 3)`` the answer's pixel pose (anchor -> query), where the flow starts.
            visibility: ``(1, S, S)`` or ``(S, S)`` the query's visibility in [0, 1] (None: all of it).
        Returns:
            ``(3, 3)`` float64 pixel ``query_H_anchor``, or None where too few textured pixels are shown or no
            homography fits.
        """
        size = int(query.shape[-1])
        if query.shape[-2:] != anchor.shape[-2:] or query_H_anchor.shape != (3, 3):
            raise MatlError(f"FlowPose.pose: query {tuple(query.shape)} and anchor {tuple(anchor.shape)} must be "
                            f"(3, S, S) alike and query_H_anchor (3, 3), got {tuple(query_H_anchor.shape)}")
        side = size * self.scale
        up = np.diag([float(self.scale), float(self.scale), 1.0])
        start = query_H_anchor.detach().double().cpu().numpy()
        if not np.isfinite(start).all():
            return None
        at_side = up @ start @ np.linalg.inv(up)  # the same pose between the enlarged images
        inverse = cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR
        warped = cv2.warpPerspective(_luminance_u8(query, side), at_side, (side, side), flags=inverse)
        target = _luminance_u8(anchor, side)
        usable = target > self.dark  # the plane, less its darkest print (a masked-out query pixel is black too)
        if visibility is not None:
            seen = visibility.detach().float().cpu().reshape(size, size).numpy()
            seen = cv2.resize(seen, (side, side), interpolation=cv2.INTER_LINEAR)
            usable &= cv2.warpPerspective(seen, at_side, (side, side), flags=inverse) > 0.5
        gx = cv2.Sobel(target, cv2.CV_32F, 1, 0)
        gy = cv2.Sobel(target, cv2.CV_32F, 0, 1)
        usable &= np.hypot(gx, gy) > self.texture
        ys, xs = np.nonzero(usable)
        if len(xs) < self.min_points:
            return None
        step = max(1, len(xs) // self.max_points)
        xs, ys = xs[::step], ys[::step]
        flow = self._flow().calc(target, warped, None)  # anchor -> warped query, px of the enlarged images
        src = np.stack([xs, ys], 1).astype(np.float32)
        dst = src + flow[ys, xs]
        correction, _ = cv2.findHomography(src, dst, cv2.USAC_MAGSAC, self.reproj_threshold * self.scale)
        if correction is None or not np.isfinite(correction).all() or np.linalg.det(correction) <= 0:
            return None
        pose = start @ np.linalg.inv(up) @ correction @ up
        if abs(pose[2, 2]) < 1e-12:  # the plane's origin sent to infinity: no usable pose
            return None
        return torch.from_numpy(pose / pose[2, 2])


class FlowPoses:
    """The flow side of :class:`~matl.inference.api.Recognizer`; a mixin of it, using its gallery, verification
    options and ``flow_pose`` settings."""

    def _flow_poses(self, queries: torch.Tensor, pred: Prediction, verification: Verification,
                    visibility: torch.Tensor | None, upscale: torch.Tensor | None = None
                    ) -> tuple[Prediction, Verification]:
        """``pred`` and ``verification`` with the flow pose of each answer it applies to (``flow_pose``: those that do
        not verify, or all whose verification distance is above ``above``; not those enlarged more than
        ``max_upscale``) where it is judged better than the answer's pose (``pose_judge``, :meth:`_judged`: by
        default the verification distance plus how badly the anchor, warped into the query, explains its visible
        foreground); ``queries`` ``(B, 3, S, S)`` and ``visibility`` ``(B, 1, S, S)`` (or None) as verification saw
        them, ``upscale`` ``(B,)`` each file's enlargement to the model's size (None: not known, every query)."""
        settings: FlowPose = self.flow_pose
        rows = [i for i in range(len(queries)) if (not bool(verification.verified[i]) or (
            settings.mode == "always" and float(verification.distance[i]) > settings.above)) and (
            upscale is None or settings.max_upscale is None or float(upscale[i]) <= settings.max_upscale)]
        if not rows:
            return pred, verification
        with stage(self.stage_timer, "flow"):
            images = self._build()[1].images
            # an answer whose pose failed the statistic (above verify_max) may be made to verify by the flow pose
            # (within ``verifies``); one held unverified below it (another product's keypoint pose) stays so
            failed = [i for i in rows if float(verification.distance[i]) > self.verify_max]
            going = {i: (pred.query_H_anchor[i], float("inf")) for i in rows}  # each row's start and last move
            for _ in range(settings.rounds):
                calls = [(queries[i], images[int(pred.gallery_index[i])], start,
                          None if visibility is None else visibility[i], last_move)
                         for i, (start, last_move) in going.items()]
                found_steps = thread_map(lambda call: settings.step(*call), calls)  # the rows over torch's threads
                steps = {i: found for i, found in zip(going, found_steps, strict=True) if found is not None}
                if not steps:
                    break
                at = list(steps)  # each round's pose judged against the best so far
                pred, verification = self._take_judged_better(queries, pred, verification, at,
                                                              torch.stack([steps[i][0] for i in at]), visibility, None)
                # the next round: the rows neither settled nor verifying now
                going = {i: found for i, found in steps.items()
                         if found[1] >= SETTLED_PX and float(verification.distance[i]) > self.verify_max}
            if settings.verifies is None:
                return pred, verification
            made = [i for i in failed if float(verification.distance[i]) <= settings.verifies]
            if not made:
                return pred, verification
            verified = verification.verified.clone()
            verified[made] = True
            return pred, dataclasses.replace(verification, verified=verified)
