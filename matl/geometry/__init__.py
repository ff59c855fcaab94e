"""Planar geometry: homography frames, the degeneracy rule, warps, the random homography sampler and pose errors.

``homography``: frames, pixel <-> normalised, composition, the degeneracy rule, errors; ``warp``: the
normalised grid and the grid sampler; ``sampler``: random homographies. Nothing here imports from
outside ``matl.geometry``.
"""

from matl.geometry.homography import (
    anchor_H_canon,
    centre_rotation,
    check_homographies,
    check_images,
    compose_query_H_canon,
    corner_error_px,
    degenerate_homographies,
    degenerate_matrix,
    frobenius_pose_error,
    guard_homographies,
    image_corners,
    normalisation_matrices,
    normalised_to_pixel,
    pixel_to_normalised,
    rescale_homography,
    scale_to_unit,
    transfer_points,
)
from matl.geometry.sampler import HomographySampler
from matl.geometry.warp import (
    normalised_grid,
    sample_by_normalised,
    sample_by_normalised_kornia,
    sample_by_pixels,
    warp_image,
)

__all__ = [
    "HomographySampler",
    "anchor_H_canon",
    "centre_rotation",
    "check_homographies",
    "check_images",
    "compose_query_H_canon",
    "corner_error_px",
    "degenerate_homographies",
    "degenerate_matrix",
    "frobenius_pose_error",
    "guard_homographies",
    "image_corners",
    "normalisation_matrices",
    "normalised_grid",
    "normalised_to_pixel",
    "pixel_to_normalised",
    "rescale_homography",
    "sample_by_normalised",
    "sample_by_normalised_kornia",
    "sample_by_pixels",
    "scale_to_unit",
    "transfer_points",
    "warp_image",
]
