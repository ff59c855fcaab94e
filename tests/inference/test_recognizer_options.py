"""The recognizer's options: one dataclass, the same defaults and checks as the keyword arguments."""

from __future__ import annotations

import dataclasses

import pytest
from omegaconf import OmegaConf

from matl import Recognizer
from matl.inference.fast_refine import FastRefiner
from matl.inference.foreground import LearnedForeground
from matl.inference.recognizer_options import CONFIG_OPTIONS, RecognizerOptions, config_options, option_default
from matl.models.search import ExactSearch, FaissSearch
from matl.utils.errors import MatlError
from tests.conftest import compose_config
from tests.inference.test_api import SIZE, StubModel, exact_model_pose, stub_recognizer

SETTINGS = ("device", "refiner", "quantize", "runtime", "search", "threshold_option", "open_set_statistic",
            "open_set_quantile", "calibration_warps", "calibration_planes", "verify_top_k", "verify_shortlist",
            "verify_max", "verify_blur", "verify_refine", "verify_statistic", "verify_min_visible", "refine_check",
            "keypoint_pose", "gallery_fill", "query_fill", "batch_size", "foreground")


def test_the_defaults_are_resolved_once() -> None:
    options = RecognizerOptions()
    assert options.refine is None and options.search is ExactSearch and options.threshold == "auto"
    assert isinstance(options.foreground, LearnedForeground) and options.device == "cpu"
    assert options.verify_top_k == 8 and options.verify_statistic == "patches" and options.batch_size == 64
    refined = RecognizerOptions(refine=True, search="faiss", foreground="none", verify_max=1, gallery_fill=0.6)
    assert isinstance(refined.refine, FastRefiner) and refined.search is FaissSearch and refined.foreground is None
    assert isinstance(refined.verify_max, float) and refined.gallery_fill == 0.6
    again = dataclasses.replace(refined)  # built again from its own (resolved) values: the same options
    assert again.refine is refined.refine and again.search is FaissSearch and again.foreground is None


def test_a_recognizer_from_options_is_the_recognizer_from_keyword_arguments() -> None:
    kwargs = {"threshold": 0.5, "verify_top_k": 3, "verify_blur": 0.0, "query_fill": 0.6, "foreground": "none",
              "refine": True, "open_set_statistic": "ratio", "refine_check": "verify"}
    by_keywords = stub_recognizer(**kwargs)
    by_options = Recognizer(StubModel(exact_model_pose()), SIZE, 1, "stub-model",
                            options=RecognizerOptions(**kwargs))
    for name in SETTINGS:
        a, b = getattr(by_keywords, name), getattr(by_options, name)
        assert type(a) is type(b) and (a == b or name == "refiner"), name
    assert by_keywords.options() == by_options.options()
    with pytest.raises(MatlError, match="not both"):
        Recognizer(StubModel(exact_model_pose()), SIZE, 1, "stub-model", options=RecognizerOptions(), verify_max=0.2)
    with pytest.raises(MatlError, match="RecognizerOptions"):
        Recognizer(StubModel(exact_model_pose()), SIZE, 1, "stub-model", options={"verify_max": 0.2})


def test_bad_values_are_the_keyword_arguments_errors() -> None:
    for bad in ({"quantize": "int4"}, {"runtime": "tvm"}, {"threshold": "high"}, {"refine": "yes"},
                {"search": "annoy"}, {"open_set_statistic": "zncc"}, {"verify_top_k": True}, {"verify_shortlist": -1},
                {"verify_shortlist": 2.5}, {"verify_max": 3.0},
                {"verify_blur": -1.0}, {"verify_refine": 1}, {"verify_statistic": "median"},
                {"verify_min_visible": 1.5}, {"refine_check": "loss"}, {"foreground": "magic"},
                {"keypoint_pose": "sometimes"}, {"keypoint_pose": 3}):
        key = next(iter(bad))
        with pytest.raises(MatlError, match=key) as from_options:
            RecognizerOptions(**bad)
        with pytest.raises(MatlError, match=key) as from_keywords:
            stub_recognizer(**bad)
        assert str(from_options.value) == str(from_keywords.value)


def test_options_from_a_config_node() -> None:
    node = OmegaConf.create({"threshold": None, "verify_top_k": 0, "foreground": {"_target_": None}})
    options = RecognizerOptions.from_config(node)
    assert options.threshold is None and options.verify_top_k == 0 and options.foreground is None
    with pytest.raises(MatlError, match="verify_topk: not a Recognizer option"):
        RecognizerOptions.from_config({"verify_topk": 3})


@pytest.mark.parametrize("config", ["predict", "unseen"])
def test_the_configs_write_the_options_defaults(config: str) -> None:
    cfg = compose_config(config)
    assert {key: cfg[key] for key in CONFIG_OPTIONS} == {key: option_default(key) for key in CONFIG_OPTIONS}
    assert config_options(OmegaConf.create({})) == {key: option_default(key) for key in CONFIG_OPTIONS}
    assert config_options(OmegaConf.create({"verify_max": 0.2}))["verify_max"] == 0.2
