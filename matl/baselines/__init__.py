"""Keypoint baselines: SIFT+RANSAC, SuperPoint+RANSAC (Table 1 (d), (e)), SIFT+RANSAC+ECC, ALIKED/DISK+LightGlue."""

from matl.baselines.ecc import SiftEccMatcher
from matl.baselines.keypoints import KeypointMatcher, MatchResult, measure_query_ms
from matl.baselines.lightglue import LightGlueRansacMatcher
from matl.baselines.sift import SiftRansacMatcher
from matl.baselines.superpoint import SuperPointRansacMatcher

__all__ = [
    "KeypointMatcher",
    "LightGlueRansacMatcher",
    "MatchResult",
    "SiftEccMatcher",
    "SiftRansacMatcher",
    "SuperPointRansacMatcher",
    "measure_query_ms",
]
