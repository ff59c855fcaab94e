"""The passes of a :class:`~matl.inference.api.Recognizer`'s query: framing, foreground passes and retries.

A query prepared by :func:`~matl.inference.foreground.mask_query` is framed at model size, answered (its mask
tightened by its answered plane's outline for ``foreground.passes``), verified and re-ranked
(:meth:`QueryPasses._answer`); one whose answer does not verify is masked again and answered again
(``foreground.retry_insets``, :meth:`QueryPasses._foreground_retries`); an answer lying across the product the
crop was cut for is explained away and the rest answered again (``uncover``, :meth:`QueryPasses._uncovered`), and an
answer held unverified that covers the masked crop is its subject (:meth:`QueryPasses._subjects_verified`).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, NamedTuple

import numpy as np
import torch

from matl.data.image_files import fit_to_model
from matl.geometry import warp_image
from matl.inference.foreground import pose_mask
from matl.inference.images import _query_visibility, _upscale, _with_rows
from matl.inference.recognizer_options import option_default
from matl.inference.refine import RefinedRecognizer
from matl.inference.uncover import (
    SUBJECT_MARGIN,
    centre_offset,
    erased_alpha,
    lies_on_top,
    plane_in_query,
)
from matl.inference.verify import CandidateMemo, Verification, covered_share, shown_pixels
from matl.models.prediction import Prediction
from matl.utils.threads import thread_map
from matl.utils.timing import stage


class Covering(NamedTuple):
    """A product found lying across a query's answer (``uncover``): the first answer, explained away."""

    plane: int                    # its enrolled plane
    anchor: int                   # its anchor's rotation index
    distance: float               # its feature distance
    query_H_canon: torch.Tensor   # (3, 3) float64 its pixel pose in the query's model frame
    verification: float           # its verification distance


class QueryPasses:
    """The query side of :class:`~matl.inference.api.Recognizer` between the foreground step and the answer; a mixin
    of it, using its networks, verification and foreground step."""

    def _answer(self, recognizer: Any, prepared: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]],
                memo: CandidateMemo | None = None
                ) -> tuple[Prediction, torch.Tensor, torch.Tensor, Verification | None, torch.Tensor | None]:
        """The verified model-frame answer of queries prepared by :func:`mask_query`: the prediction (re-ranked
        by verification), the model-size queries ``(B, 3, S, S)`` of the last foreground pass, ``model_H_file``
        ``(B, 3, 3)``, the verification (None without one) and the queries' visibility ``(B, 1, S, S)`` (None: no
        query has a mask). ``memo``: where verification keeps the candidates it posed, each query by its row, for
        later passes over the same queries (the look-alike comparison)."""
        with stage(self.stage_timer, "framing"):
            fitted = [fit_to_model(masked, self.image_size, self.query_fill) for masked, _, _ in prepared]
            queries = torch.stack([f[0] for f in fitted]).to(self.device)
        query_H_file = torch.stack([f[1].model_H_file for f in fitted])
        visibility = _query_visibility(prepared, self.image_size, self.query_fill, self.device)
        upscale = _upscale(query_H_file)
        pred, queries = self._foreground_passes(recognizer, queries, [p[1] for p in prepared],
                                                [p[2] for p in prepared], visibility, upscale)
        verification = None
        if self._verifying() and pred.query_H_anchor is not None:
            with stage(self.stage_timer, "verification"):
                verification = self._verify(queries, (pred.gallery_index, pred.query_H_anchor, pred.distance),
                                            visibility=visibility, upscale=upscale, memo=memo,
                                            keys=None if memo is None else list(range(len(queries))))
                pred = self._reranked(pred, verification)
        return pred, queries, query_H_file, verification, visibility

    def _foreground_retries(self, recognizer: Any, prepared: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]],
                            pred: Prediction, queries: torch.Tensor, verification: Verification,
                            visibility: torch.Tensor | None
                            ) -> tuple[Prediction, torch.Tensor, Verification, torch.Tensor | None]:
        """Retries: each query masked by the foreground step whose answer does not verify is masked again (GrabCut
        from wider insets, :meth:`GrabCutForeground.retries`; ``foreground=learned``: at other thresholds,
        ``retry_thresholds``, and by GrabCut from ``retry_insets``, :meth:`LearnedForeground.retries`) and answered
        again; it keeps an answer that verifies over one that does not, then the
        one whose verification distance is lowest (its first one on a tie). The file frame does not change (a mask
        keeps the crop's size). Returns the prediction, queries, verification and visibility with the retried rows'
        answers taken where better."""
        retried: list[int] = []
        again: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]] = []
        rows = [i for i, (_, _, found) in enumerate(prepared)
                if found is not None and not bool(verification.verified[i])]
        with stage(self.stage_timer, "foreground"):  # the crops over torch's threads
            found_masks = thread_map(self.foreground.retries, [prepared[i][1] for i in rows])
        for i, masks in zip(rows, found_masks, strict=True):
            rgb = prepared[i][1]
            for mask in masks:
                retried.append(i)
                again.append((np.ascontiguousarray(rgb * mask[..., None]), rgb, mask))
        if not again:
            return pred, queries, verification, visibility
        alt_pred, alt_queries, _, alt_verification, alt_visibility = self._answer(recognizer, again)
        # an answer that verifies first, then the lowest distance (an answer keypoint_pose took from another product
        # can be closer and still not count as verified)
        best = {i: (not bool(verification.verified[i]), float(verification.distance[i])) for i in set(retried)}
        take: dict[int, int] = {}
        for j, i in enumerate(retried):
            candidate = (not bool(alt_verification.verified[j]), float(alt_verification.distance[j]))
            if candidate < best[i]:
                best[i], take[i] = candidate, j
        if not take:
            return pred, queries, verification, visibility
        rows, source = list(take), list(take.values())
        if visibility is not None:  # a retry always has a mask
            visibility = _with_rows(visibility, rows, alt_visibility, source)
        return (_with_rows(pred, rows, alt_pred, source), _with_rows(queries, rows, alt_queries, source),
                _with_rows(verification, rows, alt_verification, source), visibility)

    def _uncovered(self, recognizer: Any, prepared: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]],
                   pred: Prediction, queries: torch.Tensor, query_H_file: torch.Tensor, verification: Verification,
                   visibility: torch.Tensor | None
                   ) -> tuple[Prediction, torch.Tensor, Verification, torch.Tensor | None, dict[int, Covering]]:
        """``uncover`` (:mod:`matl.inference.uncover`): each query with a found foreground (an RGB crop) whose answer's
        pose verifies (distance within ``verify_max``, counted as verified or not) but whose plane covers less than
        ``uncover`` of the crop's shown pixels is answered again with that plane erased from its foreground (the
        networks, verification and, where on, the keypoint pose); the new answer is taken where it is another
        product, its pose verifies over what is left, its plane covers more of the crop or lies nearer its centre, and
        the first answer lies on top of it where their planes overlap (counted as verified; planes apart: a
        neighbour, the answer stands). Returns the prediction, queries, verification and visibility with the taken
        rows replaced (the file frame does not change), and each taken row's first answer (:class:`Covering`: the
        product lying across it)."""
        S = self.image_size
        rows = [i for i, (_, _, found) in enumerate(prepared)
                if found is not None and float(verification.distance[i]) <= self.verify_max]
        if not rows:
            return pred, queries, verification, visibility, {}
        shown = self._shown(prepared, queries, visibility, rows)
        plane = self._answered_planes(pred, rows)
        share = covered_share(plane, shown)
        small = [j for j in range(len(rows)) if float(share[j]) < self.uncover]
        if not small:
            return pred, queries, verification, visibility, {}
        again = []
        for j in small:
            i = rows[j]
            _, rgb, found = prepared[i]
            kept = erased_alpha(found, plane[j].cpu().numpy(), query_H_file[i].double().numpy())
            again.append((np.ascontiguousarray(rgb * kept[..., None]), rgb, kept))
        alt_pred, alt_queries, alt_H_file, alt_verification, alt_visibility = self._answer(recognizer, again)
        if self.keypoint_pose.active and alt_pred.query_H_anchor is not None:
            alt_pred, alt_verification = self._keypoint_poses(again, alt_pred, alt_H_file, alt_verification)
        alt_plane = self._answered_planes(alt_pred, list(range(len(small))))
        alt_share = covered_share(alt_plane, shown[small])
        images = self._build()[1].images
        take, source = [], []
        for k, j in enumerate(small):
            i = rows[j]
            if (int(alt_pred.object_index[k]) == int(pred.object_index[i])
                    or float(alt_verification.distance[k]) > self.verify_max):
                continue
            nearer = self._centre_offset(alt_pred, k) < self._centre_offset(pred, i)
            if float(alt_share[k]) <= float(share[j]) and not nearer:
                continue  # no more the crop's subject than the first answer
            anchors = images[torch.stack([pred.gallery_index[i], alt_pred.gallery_index[k]]).to(images.device)]
            poses = torch.stack([pred.query_H_anchor[i].double(), alt_pred.query_H_anchor[k].double()])
            top, under = warp_image(anchors, poses.to(anchors.device), (S, S))
            raw = fit_to_model(prepared[i][1], S, self.query_fill)[0].to(top.device)
            if lies_on_top(raw, top, under, (plane[j] & alt_plane[k] & shown[j]).to(top.device)):  # None: apart
                take.append(i)
                source.append(k)
        if not take:
            return pred, queries, verification, visibility, {}
        covering = {i: Covering(int(pred.plane_index[i]), int(pred.anchor_index[i]), float(pred.distance[i]),
                                pred.query_H_canon[i].double().cpu(), float(verification.distance[i])) for i in take}
        alt_verification = dataclasses.replace(alt_verification, verified=torch.ones_like(alt_verification.verified))
        if visibility is not None:  # an RGB crop with a found foreground always has a visibility
            visibility = _with_rows(visibility, take, alt_visibility, source)
        return (_with_rows(pred, take, alt_pred, source), _with_rows(queries, take, alt_queries, source),
                _with_rows(verification, take, alt_verification, source), visibility, covering)

    def _subjects_verified(self, prepared: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]], pred: Prediction,
                           queries: torch.Tensor, verification: Verification, visibility: torch.Tensor | None
                           ) -> Verification:
        """``verification`` with each answer held unverified although its pose verifies (distance within
        ``verify_max``: another product's keypoint pose, held because it might lie across the crop's subject) counted
        as verified where the crop has a mask (the foreground step's, an RGBA alpha), its distance is within
        :data:`~matl.inference.uncover.SUBJECT_MARGIN` of ``verify_max`` and the answer's plane covers at least
        ``uncover`` of the pixels the crop shows: then it is the crop's subject, not a product lying across a part of
        it (:meth:`_uncovered` explains those away). A crop without a mask stays the open-set statistic's to judge."""
        subject = self._masked_subjects(prepared, pred, queries, visibility, [
            i for i in range(len(prepared)) if not bool(verification.verified[i])
            and float(verification.distance[i]) <= SUBJECT_MARGIN * self.verify_max])
        if not subject:
            return verification
        verified = verification.verified.clone()
        verified[subject] = True
        return dataclasses.replace(verification, verified=verified)

    def _second_look(self, prepared: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]], pred: Prediction,
                     queries: torch.Tensor, verification: Verification, visibility: torch.Tensor | None
                     ) -> Verification:
        """The open set's second look (:meth:`_verified_past_occluders`, ``verify_occluder_margin``) at the answers
        that do not verify once posed, of crops with a mask, where the answer is the crop's subject
        (:meth:`_masked_subjects`), partly hidden. A product lying across the subject covers less of the crop; its
        print along the subject's edges is not left out for it. An answer held unverified although its distance is
        within ``verify_max`` (another product's keypoint pose; a flow pose above ``FlowPose.verifies``) must come
        within :data:`~matl.inference.uncover.SUBJECT_MARGIN` of it, as :meth:`_subjects_verified` asks; the others
        within ``verify_max``."""
        if self.verify_occluder_margin == 0 or visibility is None:
            return verification
        subject = self._masked_subjects(prepared, pred, queries, visibility, [
            i for i in range(len(prepared)) if not bool(verification.verified[i])])
        if not subject:
            return verification
        within = [SUBJECT_MARGIN * self.verify_max if float(verification.distance[i]) <= self.verify_max
                  else self.verify_max for i in subject]
        return self._verified_past_occluders(queries, pred.gallery_index, pred.query_H_anchor, verification,
                                             visibility, subject, within)

    def _masked_subjects(self, prepared: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]], pred: Prediction,
                         queries: torch.Tensor, visibility: torch.Tensor | None, rows: list[int]) -> list[int]:
        """Of rows ``rows``, those whose crop has a mask (the foreground step's, an RGBA alpha) and whose answered
        plane covers at least ``uncover`` (off: ``uncover``'s default) of the pixels the crop shows: the crop's
        subject, its hidden part included, where a product lying across it covers less."""
        # prepared[i] is (masked, rgb, found): a mask the foreground step found, or the query's own alpha
        rows = [i for i in rows if prepared[i][2] is not None or prepared[i][0] is not prepared[i][1]]
        if not rows:
            return []
        least = option_default("uncover") if self.uncover is None else self.uncover
        share = covered_share(self._answered_planes(pred, rows), self._shown(prepared, queries, visibility, rows))
        return [i for i, covered in zip(rows, share.tolist(), strict=True) if covered >= least]

    def _shown(self, prepared: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]], queries: torch.Tensor,
               visibility: torch.Tensor | None, rows: list[int]) -> torch.Tensor:
        """``(R, S, S)`` bool: the pixels the crops of rows ``rows`` show
        (:func:`~matl.inference.verify.shown_pixels`), as the foreground step masked them (with ``foreground.passes``
        the answered plane masked the queries too: the step's mask alone)."""
        if self.foreground is None or int(self.foreground.passes) == 0:
            framed = queries[rows]
        else:
            framed = torch.stack([fit_to_model(prepared[i][0], self.image_size, self.query_fill)[0] for i in rows])
        return shown_pixels(framed, None if visibility is None else visibility[rows]).cpu()

    def _centre_offset(self, pred: Prediction, row: int) -> float:
        """How far from its query's centre row ``row``'s answered plane lies
        (:func:`~matl.inference.uncover.centre_offset`)."""
        return centre_offset(self._plane_foreground(int(pred.plane_index[row])),
                             pred.query_H_canon[row].double().cpu().numpy(), self.image_size)

    def _answered_planes(self, pred: Prediction, rows: list[int]) -> torch.Tensor:
        """``(R, S, S)`` bool: the answered planes of rows ``rows`` warped into their queries' model frame by the
        answers' poses."""
        S = self.image_size
        return torch.from_numpy(np.stack([
            plane_in_query(self._plane_foreground(int(pred.plane_index[i])),
                           pred.query_H_canon[i].double().cpu().numpy(), S) for i in rows]))

    def _plane_foreground(self, plane: int) -> np.ndarray:
        """``(S, S)`` bool: enrolled plane ``plane``'s foreground in its canonical frame (its non-zero pixels)."""
        return self._planes[plane].canon_u8.amax(0).numpy() > 0

    def _foreground_passes(self, recognizer: Any, queries: torch.Tensor, rgbs: list[np.ndarray],
                           found: list[np.ndarray | None], visibility: torch.Tensor | None = None,
                           upscale: torch.Tensor | None = None) -> tuple[Prediction, torch.Tensor]:
        """The prediction of ``(B, 3, S, S)`` queries after the foreground step's pose passes, and the queries
        of the last pass: a query whose alpha came from the foreground step (``found[i]`` ``(H, W)``, None
        otherwise) is masked again by its answered plane warped by its pose, within that alpha
        (:mod:`matl.inference.foreground`). Earlier passes skip the refinement, which weighs the query's pixels by
        ``visibility`` ``(B, 1, S, S)`` and takes each file's enlargement ``upscale`` ``(B,)``."""
        if isinstance(recognizer, RefinedRecognizer):
            recognizer = functools.partial(recognizer, visibility=visibility, upscale=upscale)
        passes = 0 if self.foreground is None or all(f is None for f in found) else int(self.foreground.passes)
        if passes == 0:
            return recognizer(queries), queries
        redo = torch.tensor([f is not None for f in found], device=queries.device)[:, None, None, None]
        raw = torch.stack([fit_to_model(rgb, self.image_size, self.query_fill)[0] for rgb in rgbs])
        ones = [np.ones(rgb.shape[:2], np.float32) if f is None else f for rgb, f in zip(rgbs, found, strict=True)]
        alpha = torch.stack([fit_to_model(np.repeat(a[..., None], 3, -1), self.image_size, self.query_fill)[0][:1]
                             for a in ones])
        within = (raw * alpha).to(queries.device)  # (B, 3, S, S): the query inside the foreground step's alpha
        inner = self._gallery_recognizer()
        for _ in range(passes):
            pred = inner(queries)
            if pred.query_H_canon is None:  # a model without a pose: the foreground step's alpha alone
                break
            canon = torch.stack([self._planes[int(p)].canon_u8 for p in pred.plane_index]).to(queries.device)
            outline = pose_mask(canon, pred.query_H_canon.to(queries.device), self.image_size)
            queries = torch.where(redo, within * outline, queries)
        return recognizer(queries), queries
