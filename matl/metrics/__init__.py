"""Recognition and pose metrics (the binding names of docs/design.md)."""

from matl.metrics.pose import (
    METRIC_NAMES,
    POSE_METRICS,
    CornerError,
    PoseAccuracy,
    PoseError,
    RecognitionAccuracy,
    pose_metrics,
)

__all__ = [
    "METRIC_NAMES",
    "POSE_METRICS",
    "CornerError",
    "PoseAccuracy",
    "PoseError",
    "RecognitionAccuracy",
    "pose_metrics",
]
