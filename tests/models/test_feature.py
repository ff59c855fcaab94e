"""The feature network c()."""

from __future__ import annotations

import torch

from matl.models.feature import FeatureNet

S = 32


def test_feature_net_shape_and_norm() -> None:
    emb = FeatureNet()(torch.rand(3, 3, S, S))
    assert emb.shape == (3, 128)
    assert torch.allclose(emb.norm(dim=1), torch.ones(3), atol=1e-5)


def test_channel_input_norm_cancels_gain_bias_and_white_balance() -> None:
    import pytest

    from matl.models.feature import ChannelStandardize, input_normalization
    from matl.models.stn import HomographyRegressor

    torch.manual_seed(0)
    x = torch.rand(2, 3, S, S, dtype=torch.float64)
    z = ChannelStandardize()(x)
    var = x.var(dim=(-2, -1), unbiased=False, keepdim=True)
    assert torch.allclose(z.mean(dim=(-2, -1)), torch.zeros(2, 3, dtype=torch.float64), atol=1e-12)
    assert torch.allclose(z.var(dim=(-2, -1), unbiased=False, keepdim=True), var / (var + 0.02 ** 2))
    flat = ChannelStandardize()(torch.full((1, 3, S, S), 0.7))
    assert flat.abs().max() < 1e-4  # a flat channel stays flat (mean rounding only), not blown up to noise
    camera = x * torch.tensor([1.3, 0.8, 1.1], dtype=torch.float64).view(1, 3, 1, 1) + 0.05
    net = FeatureNet(input_norm="channel").double()
    plain = FeatureNet().double()
    assert torch.allclose(net(camera), net(x), atol=1e-3)  # up to eps relative to each channel's spread
    assert not torch.allclose(plain(camera), plain(x), atol=1e-3)
    assert torch.allclose(net.forward_graph(x), net(x), atol=1e-12)
    single = FeatureNet(input_norm="channel")
    assert torch.allclose(single.infer(x.float()), single(x.float()), atol=1e-5)
    reg = HomographyRegressor(image_size=S, input_norm="channel").double()
    torch.nn.init.normal_(reg.fc2.weight, std=0.1)
    assert torch.allclose(reg(camera), reg(x), atol=1e-3)
    assert isinstance(input_normalization("none"), torch.nn.Identity)
    with pytest.raises(ValueError, match=r"input_norm='batch'.*none, channel"):
        FeatureNet(input_norm="batch")
