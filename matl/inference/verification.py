"""Verification and re-ranking of a :class:`~matl.inference.api.Recognizer`'s answers.

Once a pose is known the query is compared with the anchor pixel by pixel (:mod:`matl.inference.verify`); the
nearest anchors are tried in turn (up to ``verify_top_k``, each posed by the STN and the alignment stage, or by the
fast refinement with ``verify_refine``) and the first that verifies becomes the answer (:meth:`Verifying._reranked`).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import torch

from matl.geometry import compose_query_H_canon
from matl.inference.fast_refine import FastRefiner
from matl.inference.images import _with_rows
from matl.inference.verify import (
    DIFFERENCE_OVERLAP,
    SECOND_LOOK_HIDDEN,
    CandidateMemo,
    CandidatePose,
    Verification,
    candidate_distances,
    difference_distances,
    explained_distance,
    hidden_share,
    memo_poses,
    verification_distance,
    verify_candidates,
)
from matl.models.prediction import Prediction
from matl.utils.timing import stage

VERIFY_CHUNK = 32  # queries verified together (each with up to verify_top_k candidates in one batch)
#: ``lookalike_ratio``: most other products within the ratio a verified answer meets, nearest first (a look-alike
#: family of up to 4)
LOOKALIKE_RIVALS = 3


def _posed_rows(pose: CandidatePose, queries: torch.Tensor, index: torch.Tensor, stn_H: torch.Tensor,
                warped: torch.Tensor, visibility: torch.Tensor | None, upscale: torch.Tensor | None, rows: list[int]
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """``pose`` (a :data:`~matl.inference.verify.CandidatePose`) of the rows ``rows`` of its arguments."""
    return pose(queries[rows], index[rows], stn_H[rows], warped[rows], None if visibility is None else visibility[rows],
                None if upscale is None else upscale[rows])


class Verifying:
    """The verification side of :class:`~matl.inference.api.Recognizer`; a mixin of it, using its gallery
    recognizer, refiner and ``verify_*`` options."""

    def _verifying(self) -> bool:
        """Whether answers are verified (``verify_top_k`` > 0 and a model with an STN to give a pose)."""
        return self.verify_top_k > 0 and getattr(self.model, "stn", None) is not None

    def _verify(self, queries: torch.Tensor, first: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None,
                exclude_object: torch.Tensor | None = None, visibility: torch.Tensor | None = None,
                upscale: torch.Tensor | None = None,
                embedded: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None,
                memo: CandidateMemo | None = None, keys: list[int] | None = None) -> Verification:
        """:func:`~matl.inference.verify.verify_candidates` with this recognizer's settings, in chunks; the
        queries' empty (all-zero: transparent) pixels are left out of the comparison, and ``verify_statistic=patches``
        weighs the rest by the queries' ``visibility`` ``(Q, 1, S, S)`` (None: ones); ``upscale`` ``(Q,)``: each file's
        enlargement to the model's size, for the candidates' refinement; ``embedded``, ``memo`` and ``keys`` as
        ``verify_candidates``' (the queries' STN poses, warps and gallery distances already computed; candidates
        already posed)."""
        inner, chunks, step = self._gallery_recognizer(), [], VERIFY_CHUNK
        pose = self._candidate_pose() if self.verify_refine else None
        first_refined = first is not None and self.refiner is not None
        for i in range(0, len(queries), step):
            part = None if first is None else tuple(t[i:i + step] for t in first)
            given = None if embedded is None else tuple(t[i:i + step] for t in embedded)
            chunks.append(verify_candidates(inner, queries[i:i + step], self.verify_top_k, self.verify_max,
                                            self.verify_blur, part,
                                            None if exclude_object is None else exclude_object[i:i + step],
                                            skip_empty=True, candidate_pose=pose, first_refined=first_refined,
                                            visibility=None if visibility is None else visibility[i:i + step],
                                            upscale=None if upscale is None else upscale[i:i + step],
                                            statistic=self.verify_statistic, min_visible=self.verify_min_visible,
                                            shortlist=self.verify_shortlist, embedded=given, memo=memo,
                                            keys=None if keys is None else keys[i:i + step]))
        return Verification(*(torch.cat([getattr(c, f.name) for c in chunks])
                              for f in dataclasses.fields(Verification)))

    def _pose_check(self, queries: torch.Tensor, query_H_anchor: torch.Tensor, gallery_index: torch.Tensor,
                    visibility: torch.Tensor | None) -> torch.Tensor:
        """``refine_check=verify``: the verification distance ``(T,)`` of each pose ``(T, 3, 3)`` of ``(T, 3, S, S)``
        queries against gallery anchor ``gallery_index`` ``(T,)`` (lower is better), with this recognizer's
        ``verify_*`` settings."""
        _, gallery = self._build()
        return verification_distance(queries, query_H_anchor, gallery.images[gallery_index.to(gallery.images.device)],
                                     self.verify_blur, skip_empty=True, visibility=visibility,
                                     statistic=self.verify_statistic, min_visible=self.verify_min_visible)

    def _verified_past_occluders(self, queries: torch.Tensor, gallery_index: torch.Tensor,
                                 query_H_anchor: torch.Tensor, verification: Verification,
                                 visibility: torch.Tensor | None, rows: list[int] | None = None,
                                 within: list[float] | None = None) -> Verification:
        """The open set's second look (``verify_occluder_margin``): the answers of rows ``rows`` (None: every one that
        does not verify), posed ``query_H_anchor`` ``(B, 3, 3)`` against gallery anchors ``gallery_index`` ``(B,)``,
        are compared again leaving out the visible plane's ``verify_occluder_margin`` px along the edges of what
        hides it, where at least :data:`~matl.inference.verify.SECOND_LOOK_HIDDEN` of the plane is hidden (a whole
        product has no occluder's edge: what the margin would leave out there is the mask's and the pose's misfit);
        one within ``within`` (one distance per row; None: ``verify_max``) verifies, with that distance.
        The poses stay as they are: they were chosen over the whole visible plane, whose print along an occluder's
        edge tells a pose a few px off from the right one. ``queries`` ``(B, 3, S, S)`` and ``visibility``
        ``(B, 1, S, S)`` (None: nothing hidden, nothing to do) as verification saw them."""
        if self.verify_occluder_margin == 0 or visibility is None or self.verify_statistic != "patches":
            return verification
        if rows is None:
            rows = torch.nonzero(~verification.verified).flatten().tolist()
        if not rows:
            return verification
        at = torch.as_tensor(rows, dtype=torch.long)
        limit = torch.full((len(at),), self.verify_max, dtype=torch.float64) if within is None else torch.as_tensor(
            within, dtype=torch.float64)
        images = self._build()[1].images
        index = gallery_index[at.to(gallery_index.device)]
        shown, poses = queries[at.to(queries.device)], query_H_anchor[at.to(query_H_anchor.device)]
        anchors, seen = images[index.to(images.device)], visibility[at.to(visibility.device)]
        hidden = hidden_share(shown, poses, anchors, seen) >= SECOND_LOOK_HIDDEN  # whole planes: not compared again
        if not bool(hidden.any()):
            return verification
        keep = torch.nonzero(hidden).flatten()
        distance = verification_distance(shown[keep.to(shown.device)], poses[keep.to(poses.device)],
                                         anchors[keep.to(anchors.device)], self.verify_blur, skip_empty=True,
                                         visibility=seen[keep.to(seen.device)], statistic="patches",
                                         min_visible=self.verify_min_visible,
                                         occluder_margin=self.verify_occluder_margin)
        now = distance <= limit[keep].to(distance)
        if not bool(now.any()):
            return verification
        at = at[keep]
        take = at[now]
        verified, kept = verification.verified.clone(), verification.distance.clone()
        verified[take] = True
        kept[take] = distance[now].to(kept)
        return dataclasses.replace(verification, verified=verified, distance=kept)

    def _verified_copies(self, images: torch.Tensor, visibility: torch.Tensor | None,
                         exclude_object: torch.Tensor | None = None) -> torch.Tensor:
        """Which of the calibration's copies ``images`` ``(M, 3, S, S)`` verify (``(M,)`` bool), as queries do: the
        candidates (without ``exclude_object``'s, the impostors'), then the second look
        (:meth:`_verified_past_occluders`) of those with ``visibility`` (an occluder across them; each copy is its
        plane's subject, the plane covering it whole)."""
        verification = self._verify(images, None, exclude_object, visibility=visibility)
        return self._verified_past_occluders(images, verification.gallery_index, verification.query_H_anchor,
                                             verification, visibility).verified

    def _unrefined_poses(self, queries: torch.Tensor, pred: Prediction, verification: Verification,
                         visibility: torch.Tensor | None) -> tuple[Prediction, Verification]:
        """``refine_check=judge``: each refined answer that does not verify meets the pose the recognizer gives without
        refinement (``s()``'s, then the model's alignment stage, which the refinement skips) against the same anchor;
        ``pose_judge`` (:meth:`_judged`) keeps the lower, and the flow stage starts from it. Such a pose that verifies
        within ``verify_max`` counts as verified, as it does for the unrefined recognizer. A refined answer that
        verifies is left as it is (on validation meeting the unrefined pose moved none of them, docs/decisions.md).
        ``queries`` ``(B, 3, S, S)`` and ``visibility`` ``(B, 1, S, S)`` (or None) as verification saw them."""
        if self.refiner is None:  # the answers' poses are the unrefined ones already
            return pred, verification
        rows = [i for i in range(len(queries)) if not bool(verification.verified[i])]
        if not rows:
            return pred, verification
        with stage(self.stage_timer, "alignment"):
            inner, images = self._gallery_recognizer(), self._build()[1].images
            shown = queries[rows]
            _, poses, _, warped = inner.embed_queries(shown)
            align = getattr(inner, "align", None)
            if align is not None:
                anchors = images[pred.gallery_index[rows].to(images.device)]
                poses = align.infer(shown, anchors, poses, warped).query_H_anchor
            return self._take_judged_better(queries, pred, verification, rows, poses.double().cpu(), visibility,
                                            self.verify_max)

    def _take_judged_better(self, queries: torch.Tensor, pred: Prediction, verification: Verification,
                            rows: list[int], poses: torch.Tensor, visibility: torch.Tensor | None,
                            verifies: float | None) -> tuple[Prediction, Verification]:
        """``pred`` and ``verification`` with rows ``rows`` posed by ``poses`` ``(R, 3, 3)`` (float64 pixel
        ``query_H_anchor`` against each row's answered anchor) where ``pose_judge`` (:meth:`_judged`) rates that pose
        better than the row's own; its verification distance goes with it, and an answer it brings within
        ``verifies`` counts as verified (None: ``verified`` stays as it was). ``queries`` ``(B, 3, S, S)`` and
        ``visibility`` ``(B, 1, S, S)`` (or None) as verification saw them."""
        index = pred.gallery_index[rows].cpu()
        shown, seen = queries[rows], None if visibility is None else visibility[rows]
        distance = self._pose_check(shown, poses, index, seen)
        offered = self._judged(shown, poses, index, seen, distance)
        own = self._judged(shown, pred.query_H_anchor[rows].double().cpu(), index, seen, verification.distance[rows])
        better = [j for j in range(len(rows)) if float(offered[j]) < float(own[j])]
        if not better:
            return pred, verification
        take = [rows[j] for j in better]
        pred = self._answered(pred, take, index[better], poses[better], pred.distance[take])
        kept = distance[better].to(verification.distance)
        answer = {"query_H_anchor": poses[better], "distance": kept}
        if verifies is not None:
            answer["verified"] = verification.verified[take] | (kept <= verifies).to(verification.verified)
        source = list(range(len(take)))
        return pred, dataclasses.replace(verification, **{
            name: _with_rows(getattr(verification, name), take, value, source) for name, value in answer.items()})

    def _judged(self, queries: torch.Tensor, query_H_anchor: torch.Tensor, gallery_index: torch.Tensor,
                visibility: torch.Tensor | None, distance: torch.Tensor) -> torch.Tensor:
        """``pose_judge``'s value ``(T,)`` of each pose ``(T, 3, 3)`` of ``(T, 3, S, S)`` queries against gallery anchor
        ``gallery_index`` ``(T,)`` whose verification distance is ``distance`` ``(T,)`` (lower is better): that
        distance (``verification``), :func:`~matl.inference.verify.explained_distance` (``explained``) or their sum
        (``both``)."""
        if self.pose_judge == "verification":
            return distance.double().cpu()
        images = self._build()[1].images
        explained = explained_distance(queries, query_H_anchor, images[gallery_index.to(images.device)], visibility)
        return explained + distance.double().cpu() if self.pose_judge == "both" else explained

    def _candidate_refiner(self) -> tuple[FastRefiner, Any]:
        """The refiner of ``verify_refine``'s candidates and its per-anchor data, built when a candidate first needs
        it (once per gallery): a query whose nearest anchor verifies never waits for it."""
        if self._verify_refiner is None:
            recognizer, gallery = self._build()
            refiner = self.refiner if isinstance(self.refiner, FastRefiner) else FastRefiner()
            templates = getattr(recognizer, "templates", None) if refiner is self.refiner else None
            if templates is None:
                templates = refiner.anchor_templates(gallery.images)  # once per gallery
            self._verify_refiner = (refiner, templates)
        return self._verify_refiner

    def _candidate_pose(self) -> CandidatePose:
        """``verify_refine``'s poses of candidates: verified after the fast refinement against each (from
        ``refiner.start``'s pose); an answer carries that pose with ``refine=`` set, else the networks' own."""
        inner = self._gallery_recognizer()

        refined_answers = self.refiner is not None
        align = getattr(inner, "align", None)

        def pose(queries: torch.Tensor, index: torch.Tensor, stn_H: torch.Tensor, warped: torch.Tensor,
                 visibility: torch.Tensor | None = None, upscale: torch.Tensor | None = None
                 ) -> tuple[torch.Tensor, torch.Tensor]:
            refiner, templates = self._candidate_refiner()
            network = stn_H  # the pose the recognizer gives without refinement: s(), then the alignment stage
            compare = refiner.compare_align and refiner.start == "stn"  # the stage's pose kept where its loss is lower
            if align is not None and (refiner.start == "align" or not refined_answers or compare):
                network = align.infer(queries, inner.gallery.images[index], stn_H, warped).query_H_anchor
            start = network if refiner.start == "align" else stn_H
            others = network.double()[:, None] if compare and network is not stn_H else None
            refined = refiner(queries, index, start.double(), templates, visibility=visibility, upscale=upscale,
                              alternatives=others).query_H_anchor.to(stn_H.dtype)
            return refined, refined if refined_answers else network

        return pose

    def _lookalikes(self, queries: torch.Tensor, pred: Prediction, verification: Verification,
                    visibility: torch.Tensor | None, upscale: torch.Tensor | None, by_object: torch.Tensor,
                    memo: CandidateMemo | None = None) -> tuple[Prediction, Verification]:
        """``lookalike_ratio``: each verified answer meets the other products within ``lookalike_ratio`` times its own
        feature distance (look-alikes: the same layout in another flavour, colour band, size or badge), nearest
        first, at most :data:`LOOKALIKE_RIVALS` of them: each one's best candidate that verifies (:meth:`_verify` from
        that product's nearest anchor, without the current answer's product) is compared with the current answer, and
        the closer one is the answer, still verified. ``lookalike_statistic`` says how: ``difference`` (the default)
        where the two anchors, each warped into the crop by its pose, differ (:func:`difference_distances`: the flavour
        text or the colour band decides, not the shared layout; a rival whose plane overlaps the answer's by less than
        :data:`~matl.inference.verify.DIFFERENCE_OVERLAP` lies elsewhere and is no twin: the answer stays), or one
        ZNCC over the whole plane (``global``, and where the two do not differ on what the crop shows), never the
        verification's patches, which keep the best half. ``queries`` ``(B, 3, S, S)``, ``visibility``
        ``(B, 1, S, S)`` (or None) and ``upscale`` ``(B,)`` (or None) as verification saw them; ``by_object``
        ``(B, O)`` the queries' :meth:`_object_distances`; ``memo``: the candidates verification already posed for
        these queries, each by its row (:class:`~matl.inference.verify.CandidateMemo`; None: a new one). Each
        rival's candidates are posed once however many rivals meet them."""
        ratio = self.lookalike_ratio
        if ratio is None or len(self.objects) < 2:
            return pred, verification
        own, mine, _ = self._answered_and_other(by_object, pred.plane_index.cpu())
        rivals: dict[int, list[int]] = {}  # query -> the other products within the ratio, nearest first
        for i in range(len(queries)):
            if bool(verification.verified[i]):
                # the products within the ratio, found over the whole row at once (a catalogue holds thousands)
                within = by_object[i] <= ratio * float(mine[i])
                within[int(own[i])] = False
                close = torch.nonzero(within).flatten()
                if len(close):  # nearest first; ties in product order, as a stable sort of the whole row gives
                    order = torch.argsort(by_object[i, close], stable=True)[:LOOKALIKE_RIVALS]
                    rivals[i] = close[order].tolist()
        if not rivals:
            return pred, verification
        tied = list(rivals)
        inner, images = self._gallery_recognizer(), self._build()[1].images
        _, stn_H, warped, d = candidate_distances(inner, queries[tied], None)
        objects = inner.gallery.object_index.to(d.device)
        pose = self._candidate_pose() if self.verify_refine else None
        memo = CandidateMemo() if memo is None else memo  # a query's rivals meet much the same candidates
        for rank in range(LOOKALIKE_RIVALS):
            at = [j for j, i in enumerate(tied) if rank < len(rivals[i])]
            if not at:
                break
            rows = [tied[j] for j in at]
            target = torch.tensor([rivals[i][rank] for i in rows], device=d.device)
            nearest_d, nearest = d[at].masked_fill(objects[None, :] != target[:, None], float("inf")).min(1)
            seen = None if visibility is None else visibility[rows]
            factor = None if upscale is None else torch.as_tensor(upscale)[rows]
            # posed as the answers' further candidates are (not by the alignment stage, which a refined recognizer
            # skips), then verification's candidates without the current answer's product
            posed = stn_H[at] if pose is None else memo_poses(memo, rows, nearest, stn_H[at], functools.partial(
                _posed_rows, pose, queries[rows], nearest, stn_H[at], warped[at], seen, factor))
            rival = self._verify(queries[rows], first=(nearest, posed, nearest_d),
                                 exclude_object=pred.object_index[rows].cpu(), visibility=seen, upscale=factor,
                                 embedded=(stn_H[at], warped[at], d[at]), memo=memo, keys=rows)
            answer_H, rival_H = pred.query_H_anchor[rows].double().cpu(), rival.query_H_anchor.double().cpu()
            answer_g, rival_g = pred.gallery_index[rows].cpu(), rival.gallery_index.cpu()
            n = len(rows)
            pair_g = torch.stack([answer_g, rival_g], 1).to(images.device)  # (n, 2): the answer's, the rival's
            # each pair's distances (n, 2): where the two anchors differ, or one ZNCC over the whole plane (also
            # where the two do not differ on what the crop shows)
            apart = torch.full((n, 2), float("nan"), dtype=torch.float64)
            elsewhere = torch.zeros(n, dtype=torch.bool)  # a rival whose plane lies elsewhere in the crop: no twin
            if self.lookalike_statistic == "difference":
                apart, overlap = difference_distances(queries[rows], torch.stack([answer_H, rival_H], 1),
                                                      images[pair_g], seen, self.verify_blur)
                elsewhere = overlap < DIFFERENCE_OVERLAP
            whole = apart.isnan().any(1) & ~elsewhere
            if bool(whole.any()):
                at_whole = whole.nonzero().flatten()
                apart[at_whole] = verification_distance(
                    queries[rows][at_whole].repeat(2, 1, 1, 1), torch.cat([answer_H[at_whole], rival_H[at_whole]]),
                    images[pair_g[at_whole].T.flatten()], self.verify_blur, skip_empty=True,
                    statistic="global").view(2, -1).T
            better = [j for j in range(n) if bool(rival.verified[j]) and not bool(elsewhere[j])
                      and float(apart[j, 1]) < float(apart[j, 0])]
            if not better:
                continue
            take = [rows[j] for j in better]
            pred = self._answered(pred, take, rival.gallery_index[better], rival.query_H_anchor[better],
                                  rival.feature_distance[better].to(pred.distance))
            source = list(range(len(take)))
            verification = dataclasses.replace(verification, **{
                name: _with_rows(getattr(verification, name), take, getattr(rival, name)[better], source)
                for name in ("gallery_index", "query_H_anchor", "feature_distance", "distance", "verified")})
        return pred, verification

    def _reranked(self, pred: Prediction, verification: Verification) -> Prediction:
        """``pred`` with the verified answer where it differs from the nearest anchor (other rows unchanged)."""
        changed = (verification.gallery_index.to(pred.gallery_index.device) != pred.gallery_index)
        rows = changed.nonzero()[:, 0].tolist()
        if not rows:
            return pred
        return self._answered(pred, rows, verification.gallery_index[rows], verification.query_H_anchor[rows],
                              verification.feature_distance[rows])

    def _answered(self, pred: Prediction, rows: list[int], gallery_index: torch.Tensor, query_H_anchor: torch.Tensor,
                  distance: torch.Tensor) -> Prediction:
        """``pred`` with rows ``rows`` answered by gallery anchors ``gallery_index`` ``(R,)`` at pixel poses
        ``query_H_anchor`` ``(R, 3, 3)`` (kept in ``pred``'s dtype), ``distance`` ``(R,)`` their feature distances;
        the object, plane, anchor and ``query_H_canon`` follow from them."""
        g = self.gallery
        index = gallery_index.to(g.anchor_H_canon.device)
        H = query_H_anchor.to(index.device, pred.query_H_anchor.dtype)
        answer = {"gallery_index": index, "object_index": g.object_index[index], "plane_index": g.plane_index[index],
                  "anchor_index": g.anchor_index[index], "distance": distance, "query_H_anchor": H,
                  "query_H_canon": compose_query_H_canon(H.double(), g.anchor_H_canon64()[index])}
        source = list(range(len(rows)))
        return dataclasses.replace(pred, **{name: _with_rows(getattr(pred, name), rows, value, source)
                                            for name, value in answer.items()})
