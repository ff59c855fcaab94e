"""Pinhole cameras around a plane: poses, pixel projection and the homography a plane induces.

The one implementation of camera projection in matl: rendered queries and anchors
(:mod:`matl.data.view_sampler`), the canonical orthographic renders and the perspective renders
(:mod:`matl.data.catalog.rendering`) all build their cameras and pixel coordinates here.

Conventions:
    * Camera poses are camera-to-world ``(4, 4)`` matrices in the OpenGL / pyrender convention:
      the camera looks down its own -z axis, its +y is image up and +x image right.
    * Pixel coordinates as everywhere in matl (``docs/design.md``): x right, y down, ``(0, 0)``
      the *centre* of the top-left pixel; homographies map pixel coordinates, ``H[2, 2] = 1``.
    * A canonical image of a plane is the orthographic view along its normal, ``S`` pixels
      spanning ``[-half, half]`` object units along the plane's ``right`` and ``up`` axes.

Only numpy: planes and cameras are anything with the attributes of :class:`PlaneFrame` and
:class:`PinholeCamera` (e.g. ``matl.data.catalog.shapes.PlaneView`` and
``matl.data.catalog.rendering.ViewCamera``).
"""

from __future__ import annotations

import math
from typing import Protocol

import numpy as np


class PlaneFrame(Protocol):
    """A plane's axes in the object frame: outward ``normal``, image ``up`` and ``right`` (each (3,))."""

    @property
    def normal(self) -> np.ndarray: ...

    @property
    def up(self) -> np.ndarray: ...

    @property
    def right(self) -> np.ndarray: ...


class PinholeCamera(Protocol):
    """A camera-to-world ``pose`` (4, 4), ``focal_px`` and ``principal`` (cx, cy) in pixel-centre coordinates."""

    @property
    def pose(self) -> np.ndarray: ...

    @property
    def focal_px(self) -> float: ...

    @property
    def principal(self) -> tuple[float, float]: ...


def rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """(3, 3) rotation by ``angle`` radians about ``axis`` (any length > 0), right-handed (Rodrigues)."""
    x, y, z = axis / np.linalg.norm(axis)
    k = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + math.sin(angle) * k + (1.0 - math.cos(angle)) * (k @ k)


def camera_pose(right: np.ndarray, up: np.ndarray, back: np.ndarray, position: np.ndarray) -> np.ndarray:
    """(4, 4) camera-to-world pose of a camera at ``position`` whose image axes are ``right`` and
    ``up`` and which looks along ``-back`` (all (3,), object frame; the axes orthonormal)."""
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2] = right, up, back
    pose[:3, 3] = position
    return pose


def projection(pose: np.ndarray, focal_px: float, principal: tuple[float, float]) -> np.ndarray:
    """(3, 4) pixel projection ``[u, v, 1] ~ P @ [X, 1]`` of a camera with camera-to-world ``pose``
    looking down its -z with y up (OpenGL/pyrender), in our pixel-centre, y-down convention."""
    r_wc = pose[:3, :3].T
    t = -r_wc @ pose[:3, 3]
    # (X, Y, Z) camera coordinates -> u = cx + f X / (-Z), v = cy - f Y / (-Z)
    k = np.array([[focal_px, 0.0, principal[0]], [0.0, -focal_px, principal[1]], [0.0, 0.0, 1.0]])
    flip = np.diag([1.0, 1.0, -1.0])
    return k @ flip @ np.column_stack([r_wc, t])


def edge_intrinsics(focal_px: float, principal: tuple[float, float], factor: int = 1) -> tuple[float, float, float]:
    """``(f, cx, cy)`` of :func:`projection`'s camera for a renderer that renders ``factor`` times
    larger and counts pixel *edges* (pixel ``k`` spans ``[k, k + 1]``, as pyrender's
    ``IntrinsicsCamera``): a pixel-centre coordinate ``c`` is ``factor * (c + 0.5)`` there."""
    return factor * focal_px, factor * (principal[0] + 0.5), factor * (principal[1] + 0.5)


def canon_pixel_to_plane(plane: PlaneFrame, offset: float, half: float, image_size: int) -> np.ndarray:
    """(3, 3) matrix ``A`` with ``X = A @ [u, v, 1]``: canonical pixel (u, v) to the 3D point (object
    frame) on the plane ``normal . X = offset`` that the canonical (orthographic) view shows there.

    The canonical view spans ``[-half, half]`` object units across its ``S`` pixels, so a pixel
    centre ``u`` sits at ``(u - (S - 1) / 2) * 2 * half / S`` along ``right`` (and ``v`` against
    ``up``, image y pointing down).
    """
    k = image_size / (2.0 * half)
    c = (image_size - 1) / 2.0
    p0 = plane.normal * offset
    right, up = plane.right, plane.up
    return np.column_stack([right / k, -up / k, p0 - (right - up) * c / k])


def plane_homography(
    plane: PlaneFrame, offset: float, half: float, image_size: int, camera: PinholeCamera
) -> np.ndarray:
    """``query_H_canon`` (3, 3), ``H[2, 2] = 1``: the homography the plane ``normal . X = offset``
    induces from the canonical image (framed by ``half``) to the view of ``camera``."""
    P = projection(camera.pose, camera.focal_px, camera.principal)
    H = P @ np.vstack([canon_pixel_to_plane(plane, offset, half, image_size), [0.0, 0.0, 1.0]])
    return H / H[2, 2]
