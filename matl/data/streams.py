"""Independent random streams: one seeded ``torch.Generator`` per (split seed, stream name).

Every random draw of the data side names its stream ("train", "val", "test", "anchors", "views",
"shuffle", "loader"), so the splits never share random numbers and adding draws to one stream
never shifts another.
"""

from __future__ import annotations

import hashlib

import torch


def stream_generator(seed: int, stream: str) -> torch.Generator:
    """An independent generator per (seed, stream), so splits never share random numbers."""
    digest = hashlib.sha256(f"{seed}/{stream}".encode()).digest()
    return torch.Generator().manual_seed(int.from_bytes(digest[:8], "little") & ((1 << 63) - 1))


def copy_generator(generator: torch.Generator) -> torch.Generator:
    """A new generator in the same state as ``generator`` (the two then draw the same numbers)."""
    copy = torch.Generator(device=generator.device)
    copy.set_state(generator.get_state())
    return copy
