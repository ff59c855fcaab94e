"""Model pieces: inference with an oracle STN, the checkpoint score (STN: test_stn.py, c(): test_feature.py)."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

from matl.data.gallery import Gallery
from matl.geometry import anchor_H_canon, corner_error_px, pixel_to_normalised, warp_image
from matl.losses import TripletLoss
from matl.models.feature import FeatureNet
from matl.models.module import MATLModule
from matl.models.recognizer import TensorRecognizer
from matl.models.search import nearest
from matl.models.stn import HomographyRegressor, SpatialTransformer, STNOutput

S = 32


class OracleSTN(nn.Module):
    """Returns given query_H_anchor matrices (pixel), warping like the real STN."""

    def __init__(self, query_H_anchor: torch.Tensor) -> None:
        super().__init__()
        self.H = query_H_anchor

    def forward(self, images: torch.Tensor) -> STNOutput:
        warped = warp_image(images, torch.linalg.inv(self.H).float())
        return STNOutput(warped, self.H, torch.zeros(len(images), dtype=torch.bool))


def test_recognizer_composes_pose_with_selected_anchor() -> None:
    torch.manual_seed(0)
    N, P = 4, 3
    canon = torch.zeros(P, 3, S, S)
    canon[:, :, 8:24, 10:22] = torch.rand(P, 3, 16, 12)
    rot = anchor_H_canon(N, (S, S), torch.float64)
    anchors = torch.stack([warp_image(canon, rot[k].expand(P, 3, 3)) for k in range(N)], 1)
    gallery = Gallery(anchors.reshape(P * N, 3, S, S), torch.arange(P).repeat_interleave(N),
                      torch.arange(P).repeat_interleave(N), torch.arange(N).repeat(P), rot.repeat(P, 1, 1),
                      [f"o{i}" for i in range(P)], [f"p{i}" for i in range(P)])
    # the query is plane 1 seen as anchor 2 shifted by (2, 1): query_H_anchor is that shift
    shift = torch.tensor([[1.0, 0, 2.0], [0, 1.0, 1.0], [0, 0, 1.0]], dtype=torch.float64)[None]
    query = warp_image(anchors[1:2, 2], shift.float())
    rec = TensorRecognizer(FeatureNet(), OracleSTN(shift), gallery)
    # make the feature net an exact matcher: features of the warped query equal its anchor's
    rec.gallery_features = rec.feature_net(gallery.images)
    pred = rec(query)
    assert int(pred.object_index) == 1 and int(pred.anchor_index) == 2
    true_pose = shift @ rot[2][None]
    assert float(corner_error_px(pred.query_H_canon, true_pose, (S, S))) < 1e-6
    assert pixel_to_normalised(pred.query_H_canon, (S, S))[0, 2, 2] == 1


def test_nearest_is_exact_and_chunked() -> None:
    g = torch.Generator().manual_seed(1)
    q, gal = torch.randn(5, 8, generator=g), torch.randn(300, 8, generator=g)
    idx, dist = nearest(q, gal, chunk=64)
    ref = torch.cdist(q, gal).min(1)
    assert torch.equal(idx, ref.indices) and torch.allclose(dist, ref.values, atol=1e-5)


class _FixedMetrics:
    """A metrics collection that computes given values (what ``_log_metrics`` reads)."""

    def __init__(self, values: dict[str, float]) -> None:
        self.values = values

    def compute(self) -> dict[str, torch.Tensor]:
        return {k: torch.tensor(v) for k, v in self.values.items()}

    def reset(self) -> None:
        pass


def test_checkpoint_score_weighs_recognition_and_pose_alike() -> None:
    from matl.models.evaluation import PoseEvaluationModule

    def scorer(weights: dict[str, float] | None):
        module = PoseEvaluationModule(image_size=32, num_anchors=4, score_weights=weights)
        module.log_dict = lambda *args, **kwargs: None  # no trainer: nothing to log into
        return lambda rec, pose: module._log_metrics(
            _FixedMetrics({"val/rec_acc": rec, "val/pose_acc_5px": pose}), "val/")["val/score"]

    score = scorer(None)
    assert score(0.5, 0.2) == pytest.approx(0.7)
    assert score(0.9, 0.0) > score(0.1, 0.0)             # all pose_acc 0 (an untrained pose): recognition decides
    # a default run: epoch 4 (rec 0.950, pose 0.130) beats epoch 7 (0.890, 0.133)
    assert score(0.950, 0.130) > score(0.890, 0.133)
    assert score(0.7, math.nan) == pytest.approx(0.7)    # no pose (TL): rec_acc alone
    pose_only = scorer({"pose_acc_5px": 1.0})
    assert pose_only(0.1, 0.3) == pytest.approx(0.3)
    with pytest.raises(ValueError, match="score_weights"):
        PoseEvaluationModule(image_size=32, num_anchors=4, score_weights={"accuracy": 1.0})


def _occlusion_model() -> tuple[MATLModule, dict[str, torch.Tensor]]:
    torch.manual_seed(0)
    stn = SpatialTransformer(HomographyRegressor(image_size=S), image_size=S, iterations=2)
    with torch.no_grad():
        stn.regressor.fc2.bias.copy_(torch.tensor([0.05, -0.03, 0.04, 0.02, -0.04, -0.05, 0.01, -0.02]))
    model = MATLModule(FeatureNet(), stn, TripletLoss(), image_size=S, appearance="symmetric")
    g = torch.Generator().manual_seed(1)
    batch = {"anchors": torch.rand(4, 4, 3, S, S, generator=g), "positive": torch.rand(4, 3, S, S, generator=g),
             "negative": torch.rand(4, 3, S, S, generator=g), "object": torch.arange(4),
             "neg_object": torch.arange(4) + 4}
    return model, batch


def test_warp_target_is_the_stns_own_warp() -> None:
    model, batch = _occlusion_model()
    out = model.stn(batch["positive"])
    assert torch.allclose(model.warp_target(batch["positive"], out.query_H_anchor), out.warped, atol=1e-5)


def test_appearance_is_taken_on_the_whole_positive_when_it_is_occluded() -> None:
    """``positive_target`` (data.occlude): the pose is regressed from the occluded positive, the appearance loss
    judges it on the whole one; a target equal to the positive is the plain loss."""
    model, batch = _occlusion_model()
    plain = model.training_loss(batch)
    same = model.training_loss({**batch, "positive_target": batch["positive"].clone()})
    assert torch.allclose(plain, same, atol=1e-6)
    holed = batch["positive"].clone()
    holed[:, :, : S // 2] = 0.0
    occluded = model.training_loss({**batch, "positive": holed, "positive_target": batch["positive"]})
    unaware = model.training_loss({**batch, "positive": holed})
    assert torch.isfinite(occluded) and not torch.allclose(occluded, unaware)
