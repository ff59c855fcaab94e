"""Every tensor-level recognizer is a QueryRecognizer: ``recognizer(queries) -> Prediction`` against its gallery."""

from __future__ import annotations

import torch

from matl.baselines.recognizer import BaselineRecognizer
from matl.baselines.sift import SiftRansacMatcher
from matl.data.gallery import Gallery
from matl.geometry import anchor_H_canon, warp_image
from matl.inference.refine import PhotometricRefiner, RefinedRecognizer
from matl.models.feature import FeatureNet
from matl.models.prediction import Prediction, QueryRecognizer
from matl.models.recognizer import TensorRecognizer
from matl.models.stn import HomographyRegressor, SpatialTransformer
from matl.models.stn_classifier import ClassifierRecognizer, STNClassifierModule

S, N, P = 32, 2, 3


def tiny_gallery() -> Gallery:
    g = torch.Generator().manual_seed(0)
    canon = torch.zeros(P, 3, S, S)
    canon[:, :, 6:26, 8:24] = torch.rand(P, 3, 20, 16, generator=g)
    rot = anchor_H_canon(N, (S, S), torch.float64)
    anchors = torch.stack([warp_image(canon, rot[k].expand(P, 3, 3)) for k in range(N)], 1)
    return Gallery(anchors.reshape(P * N, 3, S, S), torch.arange(P).repeat_interleave(N),
                   torch.arange(P).repeat_interleave(N), torch.arange(N).repeat(P), rot.repeat(P, 1, 1),
                   [f"o{i}" for i in range(P)], [f"p{i}" for i in range(P)])


def stn() -> SpatialTransformer:
    return SpatialTransformer(HomographyRegressor(image_size=S), image_size=S).eval()


def test_every_recognizer_answers_a_query_batch_against_its_gallery() -> None:
    torch.manual_seed(0)
    gallery = tiny_gallery()
    classifier = STNClassifierModule(stn(), FeatureNet(), hidden=8, num_classes=P, num_anchors=N, image_size=S).eval()
    matl = TensorRecognizer(FeatureNet().eval(), stn(), gallery)
    recognizers = {
        "matl": matl,
        "tl": TensorRecognizer(FeatureNet().eval(), None, gallery),
        "classifier": ClassifierRecognizer(classifier, gallery),
        "sift": BaselineRecognizer(SiftRansacMatcher(), gallery),
        "refined": RefinedRecognizer(matl, PhotometricRefiner(iterations=2)),
    }
    queries = gallery.images[[1, 4]]
    for name, recognizer in recognizers.items():
        assert isinstance(recognizer, QueryRecognizer), name
        assert recognizer.gallery.images.shape == gallery.images.shape, name
        pred = recognizer(queries)
        assert isinstance(pred, Prediction), name
        assert pred.gallery_index.shape == pred.object_index.shape == pred.distance.shape == (2,), name
        assert pred.warped.shape == queries.shape, name
        if pred.query_H_canon is not None:
            assert pred.query_H_canon.shape == (2, 3, 3), name


def test_a_callable_without_a_gallery_is_not_a_query_recognizer() -> None:
    assert not isinstance(lambda queries: None, QueryRecognizer)
