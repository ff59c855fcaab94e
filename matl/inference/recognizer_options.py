"""The :class:`~matl.inference.api.Recognizer`'s options: one typed dataclass, built once and checked.

:class:`RecognizerOptions` holds every keyword argument of ``Recognizer(...)`` (and of
:meth:`~matl.inference.api.Recognizer.from_checkpoint` / :meth:`~matl.inference.api.Recognizer.pretrained`), with
the same defaults; building one checks every value (a bad one is a one-line :class:`~matl.utils.errors.MatlError`)
and resolves ``refine`` to a refiner or None, ``search`` to a search factory, ``foreground`` to a foreground step
or None and ``device="auto"`` to the device present. Building it again from its own values gives the same options.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import torch

from matl.inference.fast_refine import FastRefiner
from matl.inference.flow_pose import FlowPose
from matl.inference.foreground import ForegroundStep, foreground_option
from matl.inference.keypoint_pose import KeypointPose
from matl.inference.refine import PhotometricRefiner
from matl.inference.runtime import RUNTIMES
from matl.inference.verify import LOOKALIKE_STATISTICS, VERIFY_STATISTICS
from matl.models.search import ExactSearch, FaissSearch, SearchFactory
from matl.utils.config import is_int, is_number
from matl.utils.errors import MatlError

__all__ = ["CONFIG_OPTIONS", "OPEN_SET_STATISTICS", "POSE_JUDGES", "REFINE_CHECKS", "RecognizerOptions",
           "config_options", "option_default"]

OPEN_SET_STATISTICS = ("verify", "verify_or_ratio", "ratio", "distance")
#: second judges of a refined pose (Recognizer's ``refine_check``)
REFINE_CHECKS = ("none", "verify", "judge")
#: how the flow pose is judged against the answer's pose (Recognizer's ``pose_judge``)
POSE_JUDGES = ("both", "explained", "verification")


def _search_factory(search: str | SearchFactory | None) -> SearchFactory:
    if search is None or search == "exact":
        return ExactSearch
    if search == "faiss":
        return FaissSearch
    if callable(search):
        return search
    raise MatlError(f"search={search!r} is invalid: use 'exact', 'faiss' or a search factory")


def _refiner(refine: bool | PhotometricRefiner | FastRefiner | None) -> PhotometricRefiner | FastRefiner | None:
    if refine is None or refine is False:
        return None
    if refine is True:
        return FastRefiner()  # conf/refiner/fast.yaml's defaults
    if isinstance(refine, (PhotometricRefiner, FastRefiner)):
        return refine
    raise MatlError(f"refine={refine!r} is invalid: use true, false, a PhotometricRefiner or a FastRefiner")


def _stage(value: Any, settings: type, name: str) -> Any:
    """A pose stage's option (``keypoint_pose``, ``flow_pose``): a mode's name as the stage's settings with their
    defaults, or the settings given."""
    if isinstance(value, str):
        return settings(mode=value)
    if not isinstance(value, settings):
        raise MatlError(f"{name}={value!r} is invalid: use none, unverified, always or a {settings.__name__}")
    return value


@dataclass
class RecognizerOptions:
    """What a :class:`~matl.inference.api.Recognizer` runs with; the fields are its keyword arguments, documented
    there. After construction ``refine`` is a refiner or None, ``search`` a search factory, ``foreground`` a
    foreground step or None and ``device`` ``cpu`` or ``cuda`` (``auto``: the GPU when there is one).

    Raises:
        MatlError: one line naming the first bad value and what to use instead.
    """

    device: str = "cpu"
    refine: bool | PhotometricRefiner | FastRefiner | None = False
    quantize: str = "none"
    runtime: str = "onnxruntime"
    search: str | SearchFactory | None = "exact"
    threshold: float | str | None = "auto"
    open_set_statistic: str = "verify"
    open_set_quantile: float = 0.94
    calibration_warps: int = 8
    calibration_planes: int | None = 2000
    verify_top_k: int = 8
    verify_shortlist: int = 64
    verify_max: float = 0.1
    verify_blur: float = 1.0
    verify_refine: bool = True
    verify_statistic: str = "patches"
    verify_min_visible: float = 0.3
    verify_occluded_copies: float = 0.0
    verify_occluder_margin: int = 5
    refine_check: str = "judge"
    keypoint_pose: str | KeypointPose = "unverified"
    flow_pose: str | FlowPose = "always"
    pose_judge: str = "both"
    lookalike_ratio: float | None = 1.1
    lookalike_statistic: str = "difference"
    uncover: float | None = 0.7
    gallery_fill: float = 1.0
    query_fill: float = 1.0
    batch_size: int = 64
    foreground: str | ForegroundStep | None = "learned"

    def __post_init__(self) -> None:
        if self.quantize not in ("none", "int8"):
            raise MatlError(f"quantize={self.quantize!r} is invalid: use none or int8")
        if self.runtime not in RUNTIMES:
            raise MatlError(f"runtime={self.runtime!r} is invalid: use {' or '.join(RUNTIMES)}")
        threshold = self.threshold
        if not (threshold is None or threshold == "auto" or isinstance(threshold, (int, float))):
            raise MatlError(f"threshold={threshold!r} is invalid: use auto, a distance or None (closed set)")
        if self.device == "auto":
            self.device = "cuda" if torch.cuda.is_available() else "cpu"
        self.refine = _refiner(self.refine)
        self.search = _search_factory(self.search)
        if self.open_set_statistic not in OPEN_SET_STATISTICS:
            raise MatlError(f"open_set_statistic={self.open_set_statistic!r} is invalid: use verify, verify_or_ratio, "
                            "ratio or distance")
        top_k = self.verify_top_k
        if isinstance(top_k, bool) or not isinstance(top_k, int) or top_k < 0:
            raise MatlError(f"verify_top_k={top_k!r} is invalid: use an integer >= 0 (0: no verification)")
        if not is_int(self.verify_shortlist) or int(self.verify_shortlist) < 0:
            raise MatlError(f"verify_shortlist={self.verify_shortlist!r} is invalid: use a number of anchors >= 0 "
                            "(e.g. 64; at most verify_top_k: no shortlist)")
        self.verify_shortlist = int(self.verify_shortlist)
        if not is_number(self.verify_max) or not 0.0 <= self.verify_max <= 2.0:
            raise MatlError(f"verify_max={self.verify_max!r} is invalid: use a 1 - ZNCC level in [0, 2] (e.g. 0.1)")
        if not is_number(self.verify_blur) or not 0.0 <= self.verify_blur <= 10.0:
            raise MatlError(f"verify_blur={self.verify_blur!r} is invalid: use a Gaussian sigma in px in [0, 10]")
        if not isinstance(self.verify_refine, bool):
            raise MatlError(f"verify_refine={self.verify_refine!r} is invalid: use true or false")
        if self.verify_statistic not in VERIFY_STATISTICS:
            raise MatlError(f"verify_statistic={self.verify_statistic!r} is invalid: use "
                            f"{' or '.join(VERIFY_STATISTICS)}")
        if not is_number(self.verify_min_visible) or not 0.0 <= self.verify_min_visible <= 1.0:
            raise MatlError(f"verify_min_visible={self.verify_min_visible!r} is invalid: use a share of the plane in "
                            "[0, 1] (e.g. 0.3)")
        if not is_number(self.verify_occluded_copies) or not 0.0 <= self.verify_occluded_copies <= 1.0:
            raise MatlError(f"verify_occluded_copies={self.verify_occluded_copies!r} is invalid: use a share of the "
                            "calibration's copies in [0, 1] (0: whole copies)")
        self.verify_occluded_copies = float(self.verify_occluded_copies)
        margin = self.verify_occluder_margin
        if not is_int(margin) or not 0 <= margin <= 16:
            raise MatlError(f"verify_occluder_margin={margin!r} is invalid: use px in 0-16 (0: no second look)")
        if self.refine_check not in REFINE_CHECKS:
            raise MatlError(f"refine_check={self.refine_check!r} is invalid: use {' or '.join(REFINE_CHECKS)}")
        self.keypoint_pose = _stage(self.keypoint_pose, KeypointPose, "keypoint_pose")
        self.flow_pose = _stage(self.flow_pose, FlowPose, "flow_pose")
        if self.lookalike_ratio is not None:
            if not is_number(self.lookalike_ratio) or self.lookalike_ratio < 1.0:
                raise MatlError(f"lookalike_ratio={self.lookalike_ratio!r} is invalid: use a factor >= 1 (e.g. 1.1) or "
                                "None (no look-alike comparison)")
            self.lookalike_ratio = float(self.lookalike_ratio)
        if self.lookalike_statistic not in LOOKALIKE_STATISTICS:
            raise MatlError(f"lookalike_statistic={self.lookalike_statistic!r} is invalid: use "
                            f"{' or '.join(LOOKALIKE_STATISTICS)}")
        if self.uncover is not None:
            if not is_number(self.uncover) or not 0.0 < self.uncover <= 1.0:
                raise MatlError(f"uncover={self.uncover!r} is invalid: use a share of the crop in (0, 1] (e.g. 0.7) or "
                                "None (never)")
            self.uncover = float(self.uncover)
        if self.pose_judge not in POSE_JUDGES:
            raise MatlError(f"pose_judge={self.pose_judge!r} is invalid: use {' or '.join(POSE_JUDGES)}")
        self.verify_top_k, self.verify_max = int(top_k), float(self.verify_max)
        self.verify_blur, self.verify_min_visible = float(self.verify_blur), float(self.verify_min_visible)
        self.open_set_quantile = float(self.open_set_quantile)
        self.calibration_warps = int(self.calibration_warps)
        if self.calibration_planes is not None:
            if not is_int(self.calibration_planes) or int(self.calibration_planes) < 1:
                raise MatlError(f"calibration_planes={self.calibration_planes!r} is invalid: use a number of planes "
                                ">= 1 (e.g. 2000), or None (every plane)")
            self.calibration_planes = int(self.calibration_planes)
        self.gallery_fill, self.query_fill = float(self.gallery_fill), float(self.query_fill)
        self.batch_size = int(self.batch_size)
        self.foreground = foreground_option(self.foreground)

    @classmethod
    def from_config(cls, node: Mapping[str, Any]) -> RecognizerOptions:
        """The options of a mapping (e.g. a Hydra config node) of keyword arguments; a key that is not an option is
        a one-line error naming the options."""
        names = [f.name for f in dataclasses.fields(cls)]
        unknown = [str(k) for k in node if k not in names]
        if unknown:
            raise MatlError(f"{', '.join(unknown)}: not a Recognizer option; use {', '.join(names)}")
        return cls(**{str(k): v for k, v in node.items()})


#: the keys of predict's config (and matl.unseen's) passed to the Recognizer under their own name: the open set,
#: verification and the pose stages; a key a config leaves out takes :class:`RecognizerOptions`' default, the one
#: place the defaults are written in code (conf/predict.yaml and conf/unseen.yaml write the same values)
CONFIG_OPTIONS = ("open_set_statistic", "open_set_quantile", "calibration_planes", "verify_top_k", "verify_shortlist",
                  "verify_max",
                  "verify_blur", "verify_refine", "verify_statistic", "verify_min_visible", "verify_occluded_copies",
                  "verify_occluder_margin", "refine_check",
                  "keypoint_pose", "flow_pose", "pose_judge", "lookalike_ratio", "lookalike_statistic",
                  "uncover")


def option_default(name: str) -> Any:
    """:class:`RecognizerOptions`' default of option ``name``."""
    return {f.name: f.default for f in dataclasses.fields(RecognizerOptions)}[name]


def config_options(cfg: Mapping[str, Any]) -> dict[str, Any]:
    """The :data:`CONFIG_OPTIONS` of a config (e.g. predict's), each missing one at its default."""
    return {key: cfg.get(key, option_default(key)) for key in CONFIG_OPTIONS}
