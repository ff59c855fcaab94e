"""Camera projection: hand-computed pixels, plane-induced homographies and their round trip."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from matl.geometry.camera import (
    camera_pose,
    canon_pixel_to_plane,
    edge_intrinsics,
    plane_homography,
    projection,
    rotation,
)


@dataclass(frozen=True)
class Plane:
    normal: np.ndarray
    up: np.ndarray

    @property
    def right(self) -> np.ndarray:
        return np.cross(self.up, self.normal)


@dataclass(frozen=True)
class Camera:
    pose: np.ndarray
    focal_px: float
    principal: tuple[float, float]


TOP = Plane(np.array([0.0, 0.0, 1.0]), np.array([0.0, 1.0, 0.0]))  # right = +x


def project(P: np.ndarray, X: np.ndarray) -> np.ndarray:
    uvw = P @ np.append(X, 1.0)
    return uvw[:2] / uvw[2]


def test_rotation_and_pose() -> None:
    R = rotation(np.array([0.0, 0.0, 2.0]), math.pi / 2)  # the axis need not be unit length
    assert np.allclose(R @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]) and np.isclose(np.linalg.det(R), 1.0)
    pose = camera_pose(np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), np.array([0, 0, 1.0]), np.array([1.0, 2, 3]))
    assert np.array_equal(pose, [[1, 0, 0, 1], [0, 1, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]])


def test_projection_of_a_hand_computed_point() -> None:
    # Camera 10 units above the origin looking down -z, f = 100 px, principal point (50, 50):
    # (1, 2, 0) is 10 units in front, 1 right and 2 up: u = 50 + 100 * 1 / 10, v = 50 - 100 * 2 / 10.
    pose = camera_pose(np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), np.array([0, 0, 1.0]), np.array([0, 0, 10.0]))
    P = projection(pose, 100.0, (50.0, 50.0))
    assert np.allclose(project(P, np.array([1.0, 2.0, 0.0])), [60.0, 30.0])
    assert np.allclose(project(P, np.zeros(3)), [50.0, 50.0])
    # a renderer at twice the size counting pixel edges sees the same point at 2 * (c + 0.5)
    assert edge_intrinsics(100.0, (50.0, 50.0), 2) == (200.0, 101.0, 101.0)


def test_canonical_pixels_on_the_plane() -> None:
    # S = 4 px spanning [-2, 2]: 1 unit per pixel, pixel centres at -1.5, -0.5, 0.5, 1.5; image y is -up.
    A = canon_pixel_to_plane(TOP, 0.5, 2.0, 4)
    assert np.allclose(A @ [0.0, 0.0, 1.0], [-1.5, 1.5, 0.5])
    assert np.allclose(A @ [1.5, 1.5, 1.0], [0.0, 0.0, 0.5])
    assert np.allclose(A @ [3.0, 0.0, 1.0], [1.5, 1.5, 0.5])


def test_fronto_parallel_view_is_the_identity_and_round_trip() -> None:
    size, half, offset = 64, 5.0, 1.5
    focal = float(size)
    distance = focal * 2.0 * half / size  # the plane appears at its canonical size
    c = (size - 1) / 2.0
    front = camera_pose(TOP.right, TOP.up, TOP.normal, TOP.normal * (offset + distance))
    H = plane_homography(TOP, offset, half, size, Camera(front, focal, (c, c)))
    assert np.allclose(H, np.eye(3), atol=1e-12)

    # A tilted, rolled, off-centre camera: every canonical pixel goes to the plane point it shows
    # and on through the camera exactly where H sends it, and H's inverse brings it back.
    R = rotation(np.array([1.0, 1.0, 0.0]), math.radians(25)) @ rotation(TOP.normal, math.radians(40))
    cam = Camera(camera_pose(R[:, 0], R[:, 1], R[:, 2], TOP.normal * offset + 12.0 * R[:, 2]), 70.0, (30.0, 35.0))
    H = plane_homography(TOP, offset, half, size, cam)
    assert math.isclose(H[2, 2], 1.0) and np.abs(H[2, :2]).max() > 1e-4  # a tilt is not affine
    P, A = projection(cam.pose, cam.focal_px, cam.principal), canon_pixel_to_plane(TOP, offset, half, size)
    rng = np.random.default_rng(0)
    for u, v in rng.uniform(0, size - 1, (20, 2)):
        X = A @ [u, v, 1.0]
        assert math.isclose(float(TOP.normal @ X), offset)
        q = H @ [u, v, 1.0]
        assert np.allclose(q[:2] / q[2], project(P, X))
        back = np.linalg.solve(H, q)
        assert np.allclose(back[:2] / back[2], [u, v])
