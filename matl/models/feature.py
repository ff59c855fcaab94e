"""The feature network c() (paper Sec. 5.2): 2 conv, 1 max pool, global max pool, 128-d."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class ChannelStandardize(nn.Module):
    """Each image's channels to zero mean and unit variance: ``(B, C, H, W) -> (B, C, H, W)``.

    Beyond the paper. A network behind it sees the same input whatever the exposure gain, black
    level or white balance (per-channel gain) of the camera, up to clipping and 8 bits: the affine
    part of a camera's photometric change cancels. ``eps`` (in the input's units, images in [0, 1])
    keeps a flat channel from being blown up to noise.
    """

    def __init__(self, eps: float = 0.02) -> None:
        super().__init__()
        self.eps = float(eps)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        centred = images - images.mean(dim=(-2, -1), keepdim=True)
        var = centred.square().mean(dim=(-2, -1), keepdim=True)
        return centred * torch.rsqrt(var + self.eps ** 2)


#: values of the networks' ``input_norm`` option
INPUT_NORMS = ("none", "channel")


def input_normalization(kind: str) -> nn.Module:
    """The module for ``input_norm``: ``none`` (the paper: raw [0, 1] pixels) or ``channel``
    (:class:`ChannelStandardize`)."""
    if kind == "none":
        return nn.Identity()
    if kind == "channel":
        return ChannelStandardize()
    raise ValueError(f"input_norm={kind!r} is not a known input normalisation; use one of {', '.join(INPUT_NORMS)}")


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
        input_norm: ``none`` (paper) or ``channel``: each image standardised per channel first
            (:class:`ChannelStandardize`, docs/decisions.md).
    """

    def __init__(self, channels: tuple[int, int] = (32, 128), kernel_sizes: tuple[int, int] = (5, 5),
                 strides: tuple[int, int] = (2, 1), pool: int = 2, normalize: bool = True,
                 in_channels: int = 3, input_norm: str = "none") -> None:
        super().__init__()
        self.input_norm = input_normalization(input_norm)
        c1, c2 = channels
        k1, k2 = kernel_sizes
        s1, s2 = strides
        self.conv1 = nn.Conv2d(in_channels, c1, k1, stride=s1, padding=k1 // 2)
        self.pool = nn.MaxPool2d(pool)
        self.conv2 = nn.Conv2d(c1, c2, k2, stride=s2, padding=k2 // 2)
        self.normalize = normalize
        self.embedding_dim = c2

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        x = self.pool(F.relu(self.conv1(self.input_norm(images))))
        x = F.relu(self.conv2(x))
        # max (one index per channel) rather than amax: amax's backward, which splits the gradient
        # among ties, cost ~15% of a training step on the CPU; the values are identical
        x = x.flatten(2).max(dim=-1).values
        return F.normalize(x, dim=-1) if self.normalize else x

    def forward_graph(self, images: torch.Tensor) -> torch.Tensor:
        """``forward`` for a traced inference graph (:class:`matl.models.recognizer.QueryGraph`): the same
        ops, except the global max pool as ``amax``, the same values without the index search (4x
        faster on the dense map a frozen TorchScript graph hands it; no backward is needed there)."""
        x = self.pool(F.relu(self.conv1(self.input_norm(images))))
        x = F.relu(self.conv2(x))
        x = torch.amax(x, dim=(-2, -1))
        return F.normalize(x, dim=-1) if self.normalize else x

    @torch.no_grad()
    def infer(self, images: torch.Tensor) -> torch.Tensor:
        """``forward`` for inference (no gradient), the same embedding up to float rounding.

        On the CPU: channels-last tensors (vectorised max pool) and oneDNN for both convolutions.
        torch picks its slow im2col path for the second convolution of a single query (a 3x3 kernel on
        an input under 20,480 values), twice as slow as oneDNN here; the global max pool reads the
        channels-last map as ``(B, H*W, C)`` rows.
        """
        if images.device.type != "cpu" or images.dtype != torch.float32 or not torch.backends.mkldnn.is_available():
            return self.forward(images)
        x = self.input_norm(images).contiguous(memory_format=torch.channels_last)
        x = self.pool(conv_infer(self.conv1, x).relu_())
        x = conv_infer(self.conv2, x).relu_()
        x = x.permute(0, 2, 3, 1).flatten(1, 2).amax(dim=1)  # channels-last: a plain (B, H*W, C) view
        return F.normalize(x, dim=-1) if self.normalize else x


def conv_infer(conv: nn.Conv2d, x: torch.Tensor) -> torch.Tensor:
    """``conv(x)`` through oneDNN whatever the batch size, for CPU float32 inference (no gradient).

    ``F.conv2d`` sends a single small input with a 3x3 kernel (under 20,480 values) to torch's im2col
    path, twice as slow as oneDNN on it here; a channels-last input gives a channels-last output.
    Padding modes other than zeros, and string paddings, go through the module.
    """
    if conv.padding_mode != "zeros" or isinstance(conv.padding, str):
        return conv(x)
    return torch.mkldnn_convolution(x, conv.weight, conv.bias, conv.padding, conv.stride, conv.dilation, conv.groups)
