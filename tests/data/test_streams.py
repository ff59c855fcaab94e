"""Random streams: independent per name and seed; a copied generator draws the same numbers."""

from __future__ import annotations

import torch

from matl.data.streams import copy_generator, stream_generator


def test_stream_generators_independent() -> None:
    x = torch.rand(4, generator=stream_generator(0, "train"))
    y = torch.rand(4, generator=stream_generator(0, "test"))
    z = torch.rand(4, generator=stream_generator(1, "train"))
    assert not torch.equal(x, y) and not torch.equal(x, z)
    assert torch.equal(x, torch.rand(4, generator=stream_generator(0, "train")))


def test_copy_generator_draws_the_same_numbers() -> None:
    g = stream_generator(0, "train")
    torch.rand(3, generator=g)
    copy = copy_generator(g)
    assert torch.equal(torch.rand(5, generator=copy), torch.rand(5, generator=g))
