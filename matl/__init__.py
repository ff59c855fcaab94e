"""matl: joint object recognition and planar pose estimation of retail products (MATL).

The Python API is :class:`Recognizer` (enrol products, recognise camera crops, poses in the caller's
pixels) and its answer :class:`Match`; see :mod:`matl.inference.api`. The command-line tools are the
modules ``python -m matl.<command>`` (README.md).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from matl.inference.api import Match, Recognizer

__all__ = ["Match", "Recognizer"]


def __getattr__(name: str) -> Any:
    # imported on first use: `python -m matl.<command>` must not load torch before its config is checked
    if name in __all__:
        from matl.inference import api

        return getattr(api, name)
    raise AttributeError(f"module 'matl' has no attribute {name!r}")
