"""The Python API: enrol products, recognise camera crops (or answer "unknown"), pose in the caller's pixels.

>>> from matl import Recognizer
>>> rec = Recognizer.from_checkpoint("outputs/train/<time>/checkpoints/best.ckpt")
>>> rec.enrol("gallery/")                       # <gallery>/<object>/<plane>.png, no retraining
>>> rec.add("tea", "front", "tea_front.png")    # one more product at run time
>>> match = rec.predict(camera_crop)            # HxWx3 uint8 RGB, HxWx4 with alpha as the mask, a path
>>> match.object, match.known, match.H          # H: gallery image pixels -> crop pixels

A :class:`Recognizer` holds one model and one gallery. Every enrolled plane keeps its canonical
image at model size, its ``N`` anchors' features (computed once, when the plane is added) and the
matrix from its gallery image's pixels to the model frame, so poses come back in the pixels of the
images the caller gave: ``cv2.warpPerspective(gallery_img, match.H, (w, h))`` lands on the query.

Verification (``verify_top_k`` > 0, models with an STN): once a pose is known the query can be
compared with the anchor pixel by pixel (:mod:`matl.inference.verify`): warped into the anchor's
frame, its zero-mean normalised cross-correlation (ZNCC) with the anchor over the anchor's plane is
near 1 when the product and the pose are right. The nearest anchor is verified first; when ``1 -
ZNCC`` exceeds ``verify_max`` the next-nearest anchors (up to ``verify_top_k``, any product, plane
or rotation, each posed by the STN and the alignment stage) are tried in turn, and the first that
verifies becomes the answer (object, plane, anchor, ``H``); when none does, the nearest stays. With
``verify_shortlist`` (default 64) the anchors among the 64 nearest whose pixels at the STN's pose look most like
the query are tried too, at a stricter bar, and the candidate that verifies closest wins: in a warehouse catalogue
the right product is often a few to tens of places down the features' order. The
query's empty pixels (all channels 0: the transparent part of an RGBA query) are not compared. With
``verify_statistic=patches`` (default) the comparison is over the part of the plane the query shows: its mask
(an RGBA alpha, the foreground step's) travels with it as its visibility, warped by the pose, and an
occluder the mask missed costs only the patches it covers; a pose that shows less than
``verify_min_visible`` of the plane does not verify. The refinement weighs the query's pixels by the same
visibility and knows how much each file was enlarged (:mod:`matl.inference.fast_refine`).

Open set: a query whose statistic exceeds :attr:`Recognizer.threshold` is answered ``known=False``
(``object`` None). The statistic (``open_set_statistic``) is ``verify`` (default): 0 when the
answer's pose verifies, else ``ratio``, so a verified answer is always known and the others are
judged by the ratio; ``verify_or_ratio``: the same values, calibrated as ``ratio`` (below);
``ratio``: the distance to the nearest anchor of the answer's product over the distance to the
nearest anchor of any *other* product (a query of an enrolled product is much closer to it than to
anything else; an unenrolled product is about as far from its two nearest products); or
``distance``: the answer's nearest-anchor distance itself. With ``threshold="auto"`` the threshold
is calibrated on the gallery alone (:func:`calibrate_open_set`): warped copies of every enrolled
plane (the training warps) are embedded (for ``verify`` also posed and verified as queries are, by
the model's poses without refinement); their statistic against the whole gallery is the *genuine*
sample, and against the gallery without their own product the *impostor* sample (what an
unenrolled product looks like). The threshold is the ``open_set_quantile`` quantile of the genuine
sample; ``score`` is the share of the impostor sample above the query's statistic. With ``verify``
the threshold is set by copies most of which verify, so it is strict on the ratio of the rest: a
query that fails verification (a camera's blur, noise or JPEG, a poor mask, a poor pose) must be
clearly nearer its product than any other; ``verify_or_ratio`` (with a lower quantile, e.g. 0.88)
keeps the ratio's own threshold for those, trading unknowns let through for known products kept.

Grey queries (``HxW`` arrays, grey files, or equal colour channels) are answered against the grey (luma)
twins of the enrolled planes, embedded and calibrated once at the first grey query: a grey crop can
only be recognised by what its product looks like in grey.

The calibration is kept: :meth:`Recognizer.save` stores its samples, and a gallery enrolled from a
folder with ``cache=True`` keeps them beside the features' cache
(:meth:`Recognizer.calibration_cache_file`), each keyed by the model, every plane's image and the
calibration options (:meth:`Recognizer.calibration_key`), so a new process answers its first query
without calibrating again.

One call at a time: the methods take a lock, so one recognizer can be shared by threads that take
turns; for parallel queries make one recognizer per thread (they share nothing global).
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import threading
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from matl.data.gallery import Gallery
from matl.data.image_files import pose_in_files
from matl.inference.calibration import (
    CALIBRATION_FORMAT,
    CALIBRATION_HIDDEN,
    CALIBRATION_PREFIX,
    OpenSetCalibration,
    calibrate_open_set,
)
from matl.inference.enrolment import GALLERY_FORMAT, READABLE_GALLERY_FORMATS, Enrolment, _Plane
from matl.inference.fast_refine import FastRefiner
from matl.inference.flow_pose import FlowPose, FlowPoses
from matl.inference.foreground import ForegroundStep, LearnedForeground, mask_query
from matl.inference.gallery import build_gallery
from matl.inference.images import (
    FLOAT_SLACK,
    LUMA,
    MIN_GALLERY_SIDE,
    _as_rgb,
    _concat,
    _grey_u8,
    _is_grey,
    _rows,
    _upscale,
)
from matl.inference.keypoint_pose import KeypointPose, KeypointPoses
from matl.inference.quantize import calibration_images, quantize_recognizer
from matl.inference.query_passes import Covering, QueryPasses
from matl.inference.recognizer_options import OPEN_SET_STATISTICS, RecognizerOptions
from matl.inference.refine import PhotometricRefiner, RefinedRecognizer
from matl.inference.runtime import runtime_path
from matl.inference.verification import VERIFY_CHUNK, Verifying
from matl.inference.verify import CandidateMemo
from matl.models.checkpoint import (
    PRETRAINED,
    PRETRAINED_FAST,
    SHIPPED,
    load_embedding_model,
    resolve_checkpoint_keyword,
    shipped_checkpoint,
)
from matl.models.prediction import Prediction
from matl.models.recognizer import TensorRecognizer, embed
from matl.models.search import ExactSearch, FaissSearch, SearchFactory
from matl.utils.errors import MatlError
from matl.utils.threads import thread_map
from matl.utils.timing import StageTimer, stage

# the shipped models' names and paths are matl.models.checkpoint's (the one resolver of ckpt=), importable here too;
# the constants and helpers of the recognizer's parts (enrolment, calibration, verification, images, options) too
__all__ = ["CALIBRATION_FORMAT", "CALIBRATION_HIDDEN", "CALIBRATION_PREFIX", "FLOAT_SLACK", "GALLERY_FORMAT", "LUMA",
           "MIN_GALLERY_SIDE", "OPEN_SET_STATISTICS", "PRETRAINED", "PRETRAINED_FAST", "READABLE_GALLERY_FORMATS",
           "SHIPPED", "VERIFY_CHUNK", "Match", "Recognizer", "RecognizerOptions", "calibrate_open_set",
           "load_embedding_model", "resolve_checkpoint_keyword", "shipped_checkpoint"]


@dataclass
class Match:
    """The answer for one query image.

    Attributes:
        object, plane: the recognised product and face; None when ``known`` is False.
        anchor: index ``k`` of the selected anchor (rotation ``k * 360 / N``) of the nearest plane.
        distance: L2 feature distance to that anchor.
        score: in [0, 1], the share of the calibration's impostor statistics above ``statistic`` (1:
            closer than any unenrolled product came in calibration); NaN without calibration.
        known: False when ``statistic`` exceeds the open-set threshold.
        H: ``(3, 3)`` float64 ``query_H_canon`` in pixels: gallery image of the plane -> the given query
            image (``H[2, 2] = 1``); None for models without an STN. Given for the nearest plane even
            when ``known`` is False.
        nearest_object, nearest_plane: the nearest plane's labels, also when ``known`` is False.
        statistic: the open-set statistic of the query (``open_set_statistic``: ``verify``, the distance
            ratio, or ``distance``), compared with the threshold.
        verification: ``1 - ZNCC`` of the query warped by ``H`` onto the answer's anchor (0: identical
            up to gain and bias per channel; 1: uncorrelated; the second look's where that verified a partly
            hidden product, ``verify_occluder_margin``); NaN without verification.
        gallery_image: the gallery file of the plane (None for a plane added as an array).
        alternatives: the next-nearest *other* products (``top_k - 1`` of them), each as a Match of its
            nearest plane (``anchor`` -1, no ``H``, ``score`` NaN).
        covered_by: a product found lying across this one (``uncover``: the crop's first answer, whose print
            verified, explained away), as a Match with its own ``H`` in the query's pixels; None otherwise.
    """

    object: str | None
    plane: str | None
    anchor: int
    distance: float
    score: float
    known: bool
    H: np.ndarray | None
    nearest_object: str
    nearest_plane: str
    gallery_image: str | None = None
    alternatives: list[Match] = field(default_factory=list)
    statistic: float = float("nan")
    verification: float = float("nan")
    covered_by: Match | None = None



class Recognizer(Enrolment, OpenSetCalibration, Verifying, QueryPasses, KeypointPoses, FlowPoses):
    """Recognition and pose of camera crops against an enrolled gallery; see the module docstring.

    Args:
        model: an embedding model (``feature_net``, ``stn``, ``anchor_choice``), e.g. from
            :func:`load_embedding_model`.
        image_size, num_anchors: the model's ``S`` and ``N``.
        model_id: identifies the weights (the checkpoint's sha256); a saved gallery of another model
            is refused.
        options: every option below at once, a :class:`~matl.inference.recognizer_options.RecognizerOptions`
            (then no keyword argument); else the keyword arguments below make one.
        device: ``cpu``, ``cuda`` or ``auto``.
        refine: photometric refinement of every pose (True: the default refiner,
            :class:`~matl.inference.fast_refine.FastRefiner` with ``conf/refiner/fast.yaml``'s settings, whose
            per-anchor data is computed once each time the gallery changes; or a configured
            ``FastRefiner`` or :class:`~matl.inference.refine.PhotometricRefiner`).
        quantize: ``none`` or ``int8`` (int8 convolutions for the query networks, float fallback).
        runtime: ``onnxruntime`` (default: ``s()``'s regressor and ``c()`` in onnxruntime, ``s()``'s warps in
            OpenCV, for CPU queries; :mod:`matl.inference.runtime`) or ``torch``. Falls back to torch, saying
            why in ``options()["runtime_fallback"]``, where it does not apply (a GPU, another model).
        search: ``exact`` (default), ``faiss`` or a search factory (:mod:`matl.models.search`).
        threshold: ``auto`` (calibrated on the gallery), a distance, or None (closed set: every
            query gets the nearest product).
        open_set_statistic: ``verify``, ``verify_or_ratio``, ``ratio`` or ``distance`` (see the module docstring).
        open_set_quantile: with ``auto``, the quantile of the genuine calibration sample used.
        calibration_warps: warped copies per plane for the calibration.
        calibration_planes: the calibration's copies are of at most this many planes, the same ones each time (those
            whose names hash lowest): a warehouse catalogue's threshold from a sample of its planes, each copy still
            compared with the whole gallery, at a bounded cost (None: every plane).
        verify_top_k: nearest anchors verified per query, until one verifies (0: no verification; then
            ``verify`` is ``ratio``). Models without an STN have no pose to verify: none.
        verify_shortlist: a query whose nearest anchor does not verify also meets the few anchors among its this
            many nearest whose pixels, warped by the STN's pose, look most like it (a warehouse catalogue's right
            product can be 3rd to 50th nearest by the features), each verifying within a stricter bar; of the
            candidates that verify the closest wins (:func:`~matl.inference.verify.verify_candidates`). 0 (or at
            most ``verify_top_k``): the ``verify_top_k`` nearest alone, the first that verifies winning.
        verify_max: the largest ``1 - ZNCC`` that verifies a pose.
        verify_blur: Gaussian smoothing of both images before the comparison, px.
        verify_refine: pose each further candidate by the fast refinement against it (``refiner.start``'s
            pose refined, :class:`~matl.inference.fast_refine.FastRefiner`: the recognizer's own with
            ``refine=`` a FastRefiner, else one with ``conf/refiner/fast.yaml``'s settings, whose per-anchor
            data is computed once per gallery when first needed) rather than by the STN and alignment stage
            alone; with ``refine=false`` the nearest anchor is posed and verified again that way when its
            own pose does not verify. A re-ranked answer then carries the refined pose.
        verify_statistic: ``patches`` (over the part of the anchor's plane the query shows, its mask warped
            by the pose: the lower of ``1 - ZNCC`` over it and a strict trimmed mean of per-patch ``1 - ZNCC``, so
            an occluder the mask missed costs only the patches it covers) or ``global`` (one ZNCC over the plane);
            :mod:`matl.inference.verify`.
        verify_min_visible: ``patches``: an answer whose pose shows less than this share of the anchor's plane
            does not verify (judged by the ratio test).
        verify_occluded_copies: ``patches``: the share of the calibration's copies with an occluder across them
            (:func:`matl.inference.calibration._occluded_copies`); 0 (default): whole copies.
        verify_occluder_margin: ``patches``: the open set's second look (:meth:`_second_look`): an answer that
            does not verify once its poses are final, of a crop with a mask, whose plane covers most of what the crop
            shows and is at least a tenth hidden, is compared again leaving out this many px (default 5) of its
            visible plane along the edges of what hides it (an occluder's drop shadow darkens the print beside it)
            and verifies if that is within ``verify_max``; the poses are chosen over the whole visible plane all
            the same. 0: no second look.
        keypoint_pose: ``unverified`` (default): an answer whose pose does not verify is matched by SIFT keypoints
            against its product's planes, then the next nearest products' (:mod:`matl.inference.keypoint_pose`), and
            takes that pose where it verifies better (another product only where it verifies); ``always``; ``none``;
            or a :class:`~matl.inference.keypoint_pose.KeypointPose` with its own settings.
        flow_pose: ``always`` (default): an answer whose verification distance is above 0.03 is warped into its
            anchor's frame, matched to the anchor by dense optical flow, and takes the homography fitted to the flow
            of its visible textured pixels where that verifies better (:mod:`matl.inference.flow_pose`);
            ``unverified`` (answers that do not verify); ``none``; or a :class:`~matl.inference.flow_pose.FlowPose`
            with its own settings.
        lookalike_ratio: a verified answer meets every other product within this factor of its feature distance,
            nearest first and up to three (look-alikes: the same layout in another flavour or colour): each one's
            best verified candidate is compared with the current answer (``lookalike_statistic``), the closer
            kept (:meth:`~matl.inference.verification.Verifying._lookalikes`); None: never.
        lookalike_statistic: how an answer and a look-alike are compared: ``difference`` (default: where their
            anchors, each warped into the crop by its pose, differ; :func:`~matl.inference.verify.difference_distances`)
            or ``global`` (one ZNCC over the whole plane).
        uncover: an RGB crop's answer whose pose verifies but whose plane covers less than this share of what the
            crop shows (another product lying across the one the crop was cut for) is erased from the crop's
            foreground and the rest answered again; the rest's answer is taken where it is another product that
            verifies, covers more of the crop or lies nearer its centre, and lies under the first
            (:mod:`matl.inference.uncover`). A masked crop's answer whose pose verifies with a margin but that was
            held unverified (another product's keypoint pose) counts as verified where its plane covers at least this
            share: it is the crop's subject. None: never.
        pose_judge: how the flow pose is judged against the answer's pose: ``both`` (default: the sum of the two
            distances below), ``explained`` (how badly the anchor, warped into the query by each pose, explains the
            query's visible foreground, over the same pixels for both poses:
            :func:`~matl.inference.verify.explained_distance`) or ``verification`` (the verification distance, in
            the anchor's frame, over the part of the plane each pose puts under the query's mask).
        refine_check: a second judge of a refined pose beside the refiner's own loss: ``judge`` (default): a refined
            answer that does not verify meets the pose the recognizer gives without
            refinement (``s()`` and the model's alignment stage) and ``pose_judge`` keeps the better, before the flow
            pose (:meth:`~matl.inference.verification.Verifying._unrefined_poses`); ``verify`` keeps the refiner's
            start where its verification distance (``verify_blur``, ``verify_statistic``, over the query's
            visibility) is lower than the refined pose's; ``none``: the refiner's loss alone.
        gallery_fill, query_fill: the fraction of the model frame an image's longer side takes
            (:func:`matl.data.image_files.fit_geometry`).
        batch_size: query images per forward pass.
        foreground: the foreground step of RGB queries without a mask (:mod:`matl.inference.foreground`):
            ``grabcut`` (default; a crop whose border is black is used as given), ``none`` (every RGB
            query used as given), ``learned`` (the visibility network; its soft probability
            ``foreground.probability(rgb)``) or a :class:`~matl.inference.foreground.GrabCutForeground` or
            :class:`~matl.inference.foreground.LearnedForeground`. An RGBA
            query always uses its alpha.
    """

    def __init__(self, model: nn.Module, image_size: int, num_anchors: int, model_id: str,
                 options: RecognizerOptions | None = None, **kwargs: Any) -> None:
        if options is not None and kwargs:
            raise MatlError(f"Recognizer: pass options=RecognizerOptions(...) or keyword arguments, not both "
                            f"(got {', '.join(kwargs)} too)")
        if options is not None and not isinstance(options, RecognizerOptions):
            raise MatlError(f"Recognizer: options={options!r} is invalid: use a RecognizerOptions (or keyword "
                            "arguments)")
        settings = options if options is not None else RecognizerOptions(**kwargs)
        self.model = model.to(settings.device).eval()
        self.image_size, self.num_anchors, self.model_id = int(image_size), int(num_anchors), str(model_id)
        self.device = torch.device(settings.device)
        self.refiner: PhotometricRefiner | FastRefiner | None = settings.refine
        self.quantize = settings.quantize
        self.runtime = settings.runtime
        self.search: SearchFactory = settings.search
        self.threshold_option = settings.threshold
        self.verify_refine = settings.verify_refine
        self.verify_statistic, self.verify_min_visible = settings.verify_statistic, settings.verify_min_visible
        self.verify_occluded_copies = settings.verify_occluded_copies
        self.verify_occluder_margin = settings.verify_occluder_margin
        self.refine_check = settings.refine_check
        self.keypoint_pose: KeypointPose = settings.keypoint_pose
        self.flow_pose: FlowPose = settings.flow_pose
        self.pose_judge = settings.pose_judge
        self.lookalike_ratio = settings.lookalike_ratio
        self.lookalike_statistic = settings.lookalike_statistic
        self.uncover = settings.uncover
        self._verify_refiner: tuple[FastRefiner, Any] | None = None  # the candidates' refiner and its anchor data
        self.open_set_statistic = settings.open_set_statistic
        self.verify_top_k, self.verify_max, self.verify_blur = (settings.verify_top_k, settings.verify_max,
                                                                settings.verify_blur)
        self.verify_shortlist = settings.verify_shortlist
        self.open_set_quantile = settings.open_set_quantile
        self.calibration_warps = settings.calibration_warps
        self.calibration_planes = settings.calibration_planes
        self.gallery_fill, self.query_fill = settings.gallery_fill, settings.query_fill
        self.batch_size = settings.batch_size
        self.foreground: ForegroundStep | None = settings.foreground
        self.quantize_fallback: str | None = None
        self.runtime_fallback: str | None = None
        self._runtime_path: Any = None  # runtime=onnxruntime's query path, built at the first query
        self._planes: list[_Plane] = []
        #: per gallery, kept while it is the same: (planes list, its length, objects, each plane's product position)
        self._product_index: tuple[list[_Plane], int, list[str], list[int], torch.Tensor] | None = None
        self._lock = threading.RLock()
        self._built: tuple[Any, Gallery] | None = None
        self._built_planes: list[_Plane] = []  # the planes self._built holds, in its order
        #: the last built gallery and its planes after a change, until the next build takes what it can of it
        self._previous_gallery: tuple[list[_Plane], Gallery] | None = None
        self._calibrated: tuple[float, torch.Tensor] | None = None  # (threshold, sorted impostor distances)
        #: samples of the open-set statistic with the key they were made under (calibration_key): from load(), the
        #: enrolment folder's cache or the last calibration
        self._stored_calibration: dict[str, Any] | None = None
        #: (folder, ids of the planes enrol() took from it): the calibration of exactly those planes is cached there
        self._calibration_folder: tuple[Path, list[int]] | None = None
        self._grey: Recognizer | None = None  # the same recognizer over its gallery's grey twins (grey queries)
        self._variant = "rgb"  # "grey" for that twin
        #: filled with each stage's milliseconds while set (:meth:`time_stages`); None: no timing, no cost
        self.stage_timer: StageTimer | None = None

    # -------------------------------------------------------------------------------- construction
    @classmethod
    def from_checkpoint(cls, path: str | Path, **options: Any) -> Recognizer:
        """A recognizer for a ``matl.train`` checkpoint (or ``pretrained`` / ``pretrained_fast``, the shipped
        models, as ``ckpt=`` names them); ``options`` as the constructor's."""
        model, size, num_anchors, sha = load_embedding_model(resolve_checkpoint_keyword(path), device="cpu")
        return cls(model, size, num_anchors, sha, **options).prepare()

    def prepare(self) -> Recognizer:
        """Make the query networks ready, whatever the gallery: the onnxruntime path exported and its sessions
        opened (``runtime=onnxruntime``; the learned foreground's too), the compiled search and refinement kernels
        loaded (numba's cache).
        Part of loading a model (:meth:`from_checkpoint`, :meth:`pretrained`), so that the first query after
        :meth:`enrol` or :meth:`load` pays only for its gallery (docs/speed.md); otherwise done at that query."""
        with self._lock:
            want_runtime = (self.runtime == "onnxruntime" and self._runtime_path is None
                            and self.runtime_fallback is None and self.device.type == "cpu")
            if want_runtime or self.search is ExactSearch:  # a one-plane gallery of zeros: the networks' shapes
                blank = build_gallery(torch.zeros(1, 3, self.image_size, self.image_size, dtype=torch.uint8), [0],
                                      ["p"], ["o"], self.num_anchors).to(self.device)
                probe = TensorRecognizer(self.model.feature_net, self.model.stn, blank, self.model.anchor_choice,
                                         search=self.search, align=getattr(self.model, "align", None))
                if want_runtime:
                    self._runtime_path, self.runtime_fallback = runtime_path(probe)
            if isinstance(self.refiner, FastRefiner) or (self._verifying() and self.verify_refine):
                from matl.inference import fast_refine_kernels

                fast_refine_kernels.warm_up()
            if isinstance(self.foreground, LearnedForeground):
                self.foreground.prepare()
        return self

    @classmethod
    def pretrained(cls, name: str = "default", **options: Any) -> Recognizer:
        """A model shipped inside the package (loaded offline): ``default`` (with its alignment stage: the best
        pose without refinement) or ``fast`` (a cheaper s() whose pose the refinement sets: ``refine`` defaults
        to True for it; docs/speed.md)."""
        if name == "fast" and options.get("options") is None:  # a RecognizerOptions given is taken as it is
            options.setdefault("refine", True)
        return cls.from_checkpoint(shipped_checkpoint(name), **options)

    # ----------------------------------------------------------------------------------- queries
    def _build(self) -> tuple[Any, Gallery]:
        """The batch recognizer over the current planes (rebuilt after any gallery change)."""
        if self._built is not None:
            return self._built
        if not self._planes:
            raise MatlError("the gallery is empty: enrol(folder) or add(object, plane, image) first")
        gallery = build_gallery(torch.stack([p.canon_u8 for p in self._planes]), self._plane_objects(),
                                [p.name for p in self._planes], self.objects, self.num_anchors,
                                self._reused_anchors()).to(self.device)
        features = torch.cat([p.features for p in self._planes]).to(self.device)
        model = self.model
        recognizer = TensorRecognizer(model.feature_net, model.stn, gallery, model.anchor_choice,
                                      gallery_features=features, search=self.search,
                                      align=getattr(model, "align", None))
        if self.quantize == "int8":
            self.quantize_fallback = quantize_recognizer(recognizer, calibration_images(gallery.images))
        if self.runtime == "onnxruntime":  # the path depends on the networks only: built once, kept across galleries
            if self._runtime_path is None and self.runtime_fallback is None:
                self._runtime_path, self.runtime_fallback = runtime_path(recognizer)
            recognizer.onnx = self._runtime_path
        check = self._pose_check if self.refine_check == "verify" else None
        predictor = RefinedRecognizer(recognizer, self.refiner, check=check) if self.refiner is not None else recognizer
        self._built = (predictor, gallery)
        self._built_planes = list(self._planes)
        self._precompute_keypoints()
        return self._built

    def _reused_anchors(self) -> torch.Tensor | None:
        """The current planes' anchor images ``(P * N, 3, S, S)``, those of the planes the last built gallery held
        taken from it and the others' warped now (an add or remove in a warehouse catalogue rebuilds in a copy,
        not in a warp of every anchor); None when there is nothing to take (then every plane is warped)."""
        previous, self._previous_gallery = self._previous_gallery, None
        if previous is None:
            return None
        planes, gallery = previous  # the old planes are held there, so their ids cannot be reused by new ones
        where = {id(p): j for j, p in enumerate(planes)}
        fresh = [i for i, p in enumerate(self._planes) if id(p) not in where]  # the planes it did not hold
        if len(fresh) == len(self._planes):
            return None
        N, old = self.num_anchors, gallery.images
        images = torch.empty((len(self._planes) * N, *old.shape[1:]), dtype=old.dtype, device=old.device)
        runs: list[list[int]] = []  # [first new plane, first old plane, planes]: kept planes in consecutive runs
        for i, p in enumerate(self._planes):
            j = where.get(id(p))
            if j is None:
                continue
            if runs and runs[-1][0] + runs[-1][2] == i and runs[-1][1] + runs[-1][2] == j:
                runs[-1][2] += 1
            else:
                runs.append([i, j, 1])
        for i, j, count in runs:  # one copy a run (an add keeps one run, a remove two)
            images[i * N:(i + count) * N] = old[j * N:(j + count) * N]
        if fresh:
            first = torch.tensor(fresh, device=old.device)[:, None] * N
            rows = (first + torch.arange(N, device=old.device)).reshape(-1)
            images[rows] = build_gallery(torch.stack([self._planes[i].canon_u8 for i in fresh]), [0] * len(fresh),
                                         ["p"] * len(fresh), ["o"], N).images.to(old.device)
        return images

    def _gallery_recognizer(self) -> TensorRecognizer:
        """The batch recognizer without its refinement wrapper (its networks and gallery features)."""
        recognizer, _ = self._build()
        return getattr(recognizer, "recognizer", recognizer)

    def _plane_distances(self, features: torch.Tensor) -> torch.Tensor:
        """``(Q, P)`` distance of each feature to the nearest anchor of every enrolled plane (the gallery
        features the search uses: int8 ones with ``quantize=int8``)."""
        d = self._gallery_recognizer().gallery_distances(features).cpu()  # (Q, G), anchors plane-major
        return d.view(len(features), len(self._planes), -1).min(2).values

    def _answered_and_other(self, by_object: torch.Tensor, plane_index: torch.Tensor
                            ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Of :meth:`_object_distances`' ``(Q, O)`` and the answered planes ``plane_index`` ``(Q,)``: each query's
        answered product (its position in :attr:`objects`), its distance to it and to the nearest other product,
        each ``(Q,)``."""
        position = self._plane_objects()
        own = torch.tensor([position[int(p)] for p in plane_index], dtype=torch.long)
        return (own, by_object.gather(1, own[:, None])[:, 0],
                by_object.scatter(1, own[:, None], float("inf")).amin(1))

    def _object_distances(self, features: torch.Tensor) -> tuple[torch.Tensor, list[str]]:
        """``(Q, O)`` distance of each feature to the nearest anchor of every product, and the products."""
        objects = self.objects
        by_plane = self._plane_distances(features)
        owner = self._products()[2]
        out = torch.full((len(features), len(objects)), float("inf"), dtype=torch.float64)
        return out.scatter_reduce(1, owner.expand(len(features), -1), by_plane, reduce="amin"), objects
    # ----------------------------------------------------------------------------- grey queries
    def _grey_twin(self) -> Recognizer:
        """This recognizer over the grey (luma) twins of its planes, for grey queries: a grey crop is compared
        with what its product looks like in grey, not with colours it cannot show. Built at the first grey
        query (its anchors' features, once) and calibrated as this one; self when every plane is grey."""
        if self._variant == "grey":
            return self
        if self._grey is None:
            if all(bool((p.canon_u8[0] == p.canon_u8[1]).all() and (p.canon_u8[1] == p.canon_u8[2]).all())
                   for p in self._planes):
                return self
            twin = copy.copy(self)
            grey = torch.stack([_grey_u8(p.canon_u8) for p in self._planes])
            features = self._embed_anchors(grey).split(self.num_anchors)
            twin._planes = [dataclasses.replace(p, canon_u8=g, features=f.clone(), calibration=None)
                            for p, g, f in zip(self._planes, grey, features, strict=True)]
            twin._variant, twin._grey = "grey", None
            twin._built = twin._calibrated = twin._verify_refiner = twin._stored_calibration = None
            twin._previous_gallery = None
            same_folder = self.calibration_cache_file() is not None
            twin._calibration_folder = ((self._calibration_folder[0], [id(p) for p in twin._planes])
                                        if same_folder else None)
            self._grey = twin
        return self._grey

    def _predict_routed(self, arrays: list[np.ndarray], top_k: int = 1
                        ) -> tuple[list[Match], Prediction, torch.Tensor]:
        """:meth:`_predict_arrays`, grey queries (equal colour channels) answered by :meth:`_grey_twin`; the
        answers in the given order (the twin's planes, anchors and objects are this gallery's, in its order)."""
        grey = [i for i, a in enumerate(arrays) if _is_grey(a)]
        twin = self._grey_twin() if grey and self._planes else self
        if twin is self:
            return self._predict_arrays(arrays, top_k)
        if len(grey) == len(arrays):
            return twin._predict_arrays(arrays, top_k)
        colour = [i for i in range(len(arrays)) if i not in set(grey)]
        first = self._predict_arrays([arrays[i] for i in colour], top_k)
        second = twin._predict_arrays([arrays[i] for i in grey], top_k)
        order = torch.argsort(torch.tensor(colour + grey))  # row i of the result: row order[i] of the concatenation
        matches = [*first[0], *second[0]]
        return ([matches[int(i)] for i in order], _rows(_concat(first[1], second[1]), order),
                _rows(_concat(first[2], second[2]), order))

    def predict_tensor(self, queries: torch.Tensor) -> Prediction:
        """The model-frame prediction for ``(B, 3, S, S)`` images already at model size (no pose in files)."""
        with self._lock:
            recognizer, _ = self._build()
            return recognizer(queries.to(self.device))

    @property
    def gallery(self) -> Gallery:
        """The model-frame gallery of every enrolled plane's ``N`` anchors (plane-major)."""
        with self._lock:
            return self._build()[1]

    def plane_at(self, index: int) -> _Plane:
        """The enrolled plane of a prediction's ``plane_index``."""
        return self._planes[index]

    def options(self) -> dict[str, Any]:
        """What the queries run with (for result files): search, refinement and its check, quantisation, runtime."""
        refiner = None
        if self.refiner is not None:
            refiner = {k: v for k, v in vars(self.refiner).items() if not k.startswith("_")}
        name = getattr(self.search, "func", self.search)
        return {"search": "faiss" if name is FaissSearch else "exact" if name is ExactSearch else str(name),
                "refine": self.refiner is not None, "refiner": refiner, "refine_check": self.refine_check,
                "keypoint_pose": self.keypoint_pose.options(),
                "flow_pose": self.flow_pose.options(), "pose_judge": self.pose_judge,
                "lookalike_ratio": self.lookalike_ratio, "lookalike_statistic": self.lookalike_statistic,
                "uncover": self.uncover,
                "quantize": self.quantize,
                "foreground": None if self.foreground is None else dataclasses.asdict(self.foreground),
                "quantize_fallback": self.quantize_fallback,
                "runtime": "torch" if self.runtime_fallback else self.runtime,
                "runtime_fallback": self.runtime_fallback}

    def time_stages(self, timer: StageTimer | None) -> None:
        """Fill ``timer`` (:class:`matl.utils.timing.StageTimer`) with the milliseconds of each stage of the calls
        that follow: ``foreground``, ``framing`` (to the model frame), ``networks``, ``search``, ``alignment``,
        ``refinement``, ``verification`` (the further candidates' networks and poses included),
        ``lookalikes`` (``lookalike_ratio``: the near products met, their candidates posed and verified),
        ``keypoints`` (``keypoint_pose``), ``uncover`` (``uncover``: everything a query answered again runs),
        ``retries`` (``foreground.retry_insets``: everything a retried query runs
        again) and ``flow`` (``flow_pose``); None stops it and leaves no cost.
        Time the stages after enrolling: a gallery changed afterwards is answered untimed inside the networks."""
        with self._lock:
            if self.stage_timer is not None:
                self.stage_timer.unwrap()
            self.stage_timer = timer
            if timer is None:
                return
            predictor, _ = self._build()
            inner = self._gallery_recognizer()
            timer.wrap(inner, "embed_queries", "networks")
            timer.wrap(inner.search, "search", "search")
            if getattr(inner, "align", None) is not None:
                timer.wrap(inner.align, "infer", "alignment")
            if predictor is not inner:
                timer.wrap(predictor, "refiner", "refinement")

    def predict_details(self, arrays: list[np.ndarray]) -> tuple[list[Match], Prediction, torch.Tensor]:
        """:meth:`predict` for float RGB ``(H, W, 3)`` or RGBA ``(H, W, 4)`` arrays in [0, 1] (alpha = mask),
        plus the model-frame prediction and the model-size query images it came from (for pictures and
        diagnostics)."""
        with self._lock:
            return self._predict_routed(arrays)

    def predict(self, images: Any, top_k: int = 1) -> Match | list[Match]:
        """Recognise one image or a batch; see :class:`Match`.

        Args:
            images: a path, an ``HxWx3`` RGB / ``HxWx4`` RGBA / ``HxW`` grey array (any size; uint8 0-255 or
                float 0-1), a ``(3|4, H, W)`` or ``(H, W)`` tensor, a list of those, or a ``(B, 3, H, W)`` tensor.
                A grey image (equal colour channels) is matched against the grey twins of the enrolled
                planes. Float pixels outside [0, 1], NaN or infinite are a one-line error.
            top_k: also return the ``top_k - 1`` next-nearest other planes in ``Match.alternatives``.
        Returns:
            One :class:`Match` for a single image, else a list in the given order.
        """
        single = not (isinstance(images, (list, tuple)) or (isinstance(images, torch.Tensor) and images.ndim == 4))
        items: Sequence[Any] = [images] if single else list(images)
        if top_k < 1:
            raise MatlError(f"top_k={top_k} is invalid: use an integer >= 1")
        matches: list[Match] = []
        with self._lock:
            for start in range(0, len(items), self.batch_size):
                chunk = [_as_rgb(x, f"image {start + i}", keep_alpha=True)
                         for i, x in enumerate(items[start:start + self.batch_size])]
                matches.extend(self._predict_routed(chunk, top_k)[0])
        return matches[0] if single else matches

    def _predict_arrays(self, arrays: list[np.ndarray], top_k: int = 1
                        ) -> tuple[list[Match], Prediction, torch.Tensor]:
        """Matches of float RGB ``(H, W, 3)`` arrays, the model-frame prediction they came from and the
        model-size queries."""
        recognizer, _ = self._build()
        with stage(self.stage_timer, "foreground"):
            # (masked, rgb, alpha found or None), the crops over torch's threads
            prepared = thread_map(functools.partial(mask_query, self.foreground), arrays)
        memo = CandidateMemo()  # the candidates verification poses, met again by the look-alike comparison
        pred, queries, query_H_file, verification, visibility = self._answer(recognizer, prepared, memo)
        covering: dict[int, Covering] = {}  # uncover: what lies across a row's answer
        taken = None  # (the features, their per-product distances): kept for the open-set answer while they hold
        if (verification is not None and pred.query_H_anchor is not None and pred.features is not None
                and self.lookalike_ratio is not None):  # a near twin compared with the answer
            taken = (pred.features, self._object_distances(pred.features))
            with stage(self.stage_timer, "lookalikes"):
                pred, verification = self._lookalikes(queries, pred, verification, visibility,
                                                      _upscale(query_H_file), taken[1][0], memo)
        if verification is not None and self.keypoint_pose.active and pred.query_H_anchor is not None:
            # before the foreground's retries: a hidden product posed by its keypoints verifies, and is not retried
            pred, verification = self._keypoint_poses(prepared, pred, query_H_file, verification)
        if verification is not None and self.uncover is not None and pred.query_H_canon is not None:
            # a verified product lying across the one the crop was cut for is explained away
            with stage(self.stage_timer, "uncover"):
                pred, queries, verification, visibility, covering = self._uncovered(
                    recognizer, prepared, pred, queries, query_H_file, verification, visibility)
                verification = self._subjects_verified(prepared, pred, queries, verification, visibility)
        if verification is not None and self.foreground is not None and self.foreground.retrying:
            with stage(self.stage_timer, "retries"):
                pred, queries, verification, visibility = self._foreground_retries(
                    recognizer, prepared, pred, queries, verification, visibility)
        if verification is not None and self.refine_check == "judge" and pred.query_H_anchor is not None:
            # a refined answer that does not verify meets its unrefined pose; the flow starts from the one judged better
            pred, verification = self._unrefined_poses(queries, pred, verification, visibility)
        if verification is not None and self.flow_pose.active and pred.query_H_anchor is not None:
            # last: from the best pose the passes above found (the keypoints' of a hidden product among them)
            pred, verification = self._flow_poses(queries, pred, verification, visibility, _upscale(query_H_file))
        if verification is not None and pred.query_H_anchor is not None:
            # the open set's second look: the final poses, the print beside what hides the plane left out
            verification = self._second_look(prepared, pred, queries, verification, visibility)
        plane = pred.plane_index.cpu()
        H = None
        if pred.query_H_canon is not None:  # the answered planes' file geometry (not the whole catalogue's)
            canon_H_file = torch.stack([self._planes[int(p)].canon_H_file for p in plane])
            H = pose_in_files(pred.query_H_canon.cpu(), canon_H_file, query_H_file)
        threshold = self.threshold
        features = pred.features  # c(s(query)), as the search used it: per-product distances
        if features is None:
            features = embed(self.model.feature_net, pred.warped)
        # the look-alike step's distances unless a foreground retry answered a query anew (new features)
        held = taken is not None and taken[0] is features
        by_object, objects = taken[1] if held else self._object_distances(features)
        own, nearest, second = self._answered_and_other(by_object, plane)
        statistic = self._statistic(nearest, second if len(objects) > 1 else nearest,
                                    None if verification is None else verification.verified)
        alternatives = self._alternatives(features, own, top_k)
        matches = []
        for i in range(len(arrays)):
            matches.append(self._match(int(plane[i]), int(pred.anchor_index[i]), float(pred.distance[i]),
                                       float(statistic[i]), None if H is None else H[i].numpy(), threshold,
                                       alternatives[i],
                                       float("nan") if verification is None else float(verification.distance[i])))
        for i, top in covering.items():  # the product lying across the answer, posed in the caller's pixels
            top_H = pose_in_files(top.query_H_canon[None], self._planes[top.plane].canon_H_file[None],
                                  query_H_file[i:i + 1])[0].numpy()
            matches[i].covered_by = self._match(top.plane, top.anchor, top.distance, 0.0, top_H, None, [],
                                                top.verification)
        return matches, pred, queries

    def _match(self, plane: int, anchor: int, distance: float, statistic: float, H: np.ndarray | None,
               threshold: float | None, alternatives: list[Match], verification: float = float("nan")) -> Match:
        p = self._planes[plane]
        known = threshold is None or statistic <= threshold
        return Match(p.object if known else None, p.name if known else None, anchor, distance,
                     self._score(statistic), known, H, p.object, p.name, p.path, alternatives, statistic,
                     verification)

    def _alternatives(self, features: torch.Tensor, own: torch.Tensor, top_k: int) -> list[list[Match]]:
        """The ``top_k - 1`` next-nearest other products of each query, each by its nearest plane (no pose)."""
        if top_k <= 1:
            return [[] for _ in range(len(own))]
        by_plane = self._plane_distances(features)
        position = self._plane_objects()
        out = []
        for i in range(len(own)):
            seen = {int(own[i])}
            matches = []
            for k in torch.argsort(by_plane[i]).tolist():
                plane = self._planes[k]
                if position[k] in seen:
                    continue
                seen.add(position[k])
                d = float(by_plane[i, k])
                matches.append(Match(plane.object, plane.name, -1, d, float("nan"), True, None, plane.object,
                                     plane.name, plane.path))
                if len(matches) == top_k - 1:
                    break
            out.append(matches)
        return out
