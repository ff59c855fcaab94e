"""The feature network c()."""

from __future__ import annotations

import torch

from matl.models.feature import FeatureNet

S = 32


def test_feature_net_shape_and_norm() -> None:
    emb = FeatureNet()(torch.rand(3, 3, S, S))
    assert emb.shape == (3, 128)
    assert torch.allclose(emb.norm(dim=1), torch.ones(3), atol=1e-5)
