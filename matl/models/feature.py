"""The feature network c() (paper Sec. 5.2): 2 conv, 1 max pool, global max pool, 128-d."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class FeatureNet(nn.Module):
    """``c()``: ``(B, 3, H, W) -> (B, embedding_dim)``.

    conv -> ReLU -> max pool -> conv -> ReLU -> global max pool, as in the paper. Strides are ours
    (the paper gives none): a stride-2 first layer keeps a CPU step cheap at 100 px while the
    5x5 kernels still see print detail.

    Args:
        channels: output channels of the two convolutions; the second is the embedding size.
        kernel_sizes: kernel of each convolution.
        strides: stride of each convolution.
        pool: kernel (= stride) of the max pool between the convolutions.
        normalize: L2-normalise the embedding (distances then live in [0, 2]).
    """

    def __init__(self, channels: tuple[int, int] = (32, 128), kernel_sizes: tuple[int, int] = (5, 5),
                 strides: tuple[int, int] = (2, 1), pool: int = 2, normalize: bool = True,
                 in_channels: int = 3) -> None:
        super().__init__()
        c1, c2 = channels
        k1, k2 = kernel_sizes
        s1, s2 = strides
        self.conv1 = nn.Conv2d(in_channels, c1, k1, stride=s1, padding=k1 // 2)
        self.pool = nn.MaxPool2d(pool)
        self.conv2 = nn.Conv2d(c1, c2, k2, stride=s2, padding=k2 // 2)
        self.normalize = normalize
        self.embedding_dim = c2

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        x = self.pool(F.relu(self.conv1(images)))
        x = F.relu(self.conv2(x))
        # max (one index per channel) rather than amax: amax's backward, which splits the gradient
        # among ties, cost ~15% of a training step on the CPU; the values are identical
        x = x.flatten(2).max(dim=-1).values
        return F.normalize(x, dim=-1) if self.normalize else x
