"""What the settings of an optional pose stage share (:class:`~matl.inference.keypoint_pose.KeypointPose`,
:class:`~matl.inference.flow_pose.FlowPose`): a ``mode``, the dataclass fields as the options written to result
files, and per-thread OpenCV workers (a SIFT detector, a DIS flow object) that copies and pickles leave out."""

from __future__ import annotations

import dataclasses
import threading
from typing import Any

__all__ = ["StageSettings"]


class StageSettings:
    """A base of the settings dataclasses of the pose stages; each thread keeps its own workers in ``_local``
    (recognizers may share one settings object across threads)."""

    mode: str

    def _new_workers(self) -> None:
        self._local = threading.local()

    def __getstate__(self) -> dict[str, Any]:  # copies and pickles carry the settings, not the workers
        return {k: v for k, v in self.__dict__.items() if k != "_local"}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._new_workers()

    @property
    def active(self) -> bool:
        return self.mode != "none"

    def options(self) -> dict[str, Any]:
        """The settings, for result files."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}  # type: ignore[arg-type]
