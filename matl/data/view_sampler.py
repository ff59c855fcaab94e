"""Random cameras and lighting around a canonical plane: the views of rendered queries and anchors.

The paper makes positives and test queries by warping a canonical image with a random homography
(Sec. 5.1). Rendered views instead show the 3D object from a perspective camera placed at random
around one of its planes (tilt, in-plane roll, distance, off-centre framing, changed lighting).
The ground truth ``query_H_canon`` of a view is the homography its plane induces between the
canonical image and the view (:func:`matl.geometry.camera.plane_homography`): exact for a planar
face, the best planar approximation for a curved or irregular surface (the plane sits at the mean
height of the surface seen in the canonical view, see
:meth:`matl.data.catalog.rendering.CanonicalRenderer.render_planes`).

:class:`ViewSampler` only draws cameras; :mod:`matl.data.view_pool` renders and caches them.
Pixel convention as everywhere (``docs/design.md``): x right, y down, (0, 0) the centre of the
top-left pixel; homographies map pixel coordinates, ``H[2, 2] = 1``.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from matl.geometry.camera import camera_pose, plane_homography, projection, rotation
from matl.utils.errors import MatlError

if TYPE_CHECKING:  # imported lazily at run time: pyrender sets up OpenGL on import
    from matl.data.catalog.rendering import ViewCamera
    from matl.data.catalog.shapes import PlaneView, ProductModel


def bounding_box_corners(model: ProductModel) -> np.ndarray:
    """(8, 3) corners of the axis-aligned (object frame) bounding box of all parts of ``model``."""
    vertices = np.concatenate([p.vertices for p in model.parts])
    lo, hi = vertices.min(0), vertices.max(0)
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])


@dataclass
class ViewSampler:
    """Random camera and lighting around one plane (rendered queries and anchors).

    The camera looks at the plane's centre (the object centre projected onto the plane) from the
    direction of the plane's normal tilted by ``tilt_deg`` towards a uniformly random azimuth,
    rolled about its axis by ``rotation_deg``, at the distance where the plane appears ``scale``
    times its canonical size, with a pinhole of focal length ``focal`` image widths. The object is
    then framed off-centre by shifting the principal point by ``translation`` x image size per axis
    (a crop of a wider photo). Lighting: grey ambient ``ambient``, plus a directional light of
    strength ``direct`` from within ``light_cone_deg`` of the camera, tinted per channel by up to
    ``tint``. Ranges are ``[low, high]``, uniform.

    ``keep_inside`` draws ``max_tries`` candidates per view and keeps the first whose object
    bounding box (8 corners) projects inside the frame, else the one that leaves it least.

    Defaults mirror the warped positives (``docs/design.md``): +-180 deg roll, scale [0.8, 1.2],
    +-25 % translation, tilt up to 30 deg (the warps' +-0.5 rad per axis).
    """

    tilt_deg: tuple[float, float] = (0.0, 30.0)
    rotation_deg: tuple[float, float] = (-180.0, 180.0)
    scale: tuple[float, float] = (0.8, 1.2)
    translation: tuple[float, float] = (-0.25, 0.25)
    focal: float = 1.0
    ambient: tuple[float, float] = (0.55, 0.85)
    direct: tuple[float, float] = (0.1, 0.45)
    light_cone_deg: float = 40.0
    tint: float = 0.08
    keep_inside: bool = True
    max_tries: int = 16

    def __post_init__(self) -> None:
        for name in ("tilt_deg", "rotation_deg", "scale", "translation", "ambient", "direct"):
            low, high = (float(v) for v in getattr(self, name))
            if low > high:
                raise MatlError(f"views.{name} must be [low, high] with low <= high, got [{low}, {high}]")
            setattr(self, name, (low, high))
        if not (self.tilt_deg[0] >= 0.0 and self.tilt_deg[1] < 85.0):
            raise MatlError(f"views.tilt_deg must lie in [0, 85), got {list(self.tilt_deg)}")
        if self.scale[0] <= 0 or self.focal <= 0:
            raise MatlError(f"views.scale and views.focal must be > 0, got {list(self.scale)}, {self.focal}")
        if self.max_tries < 1:
            raise MatlError(f"views.max_tries must be >= 1, got {self.max_tries}")

    def key(self) -> dict[str, Any]:
        """JSON-serialisable parameters (part of the view cache key)."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    def _candidate(
        self, plane: PlaneView, offset: float, half: float, radius: float, size: int, rng: np.random.Generator
    ) -> ViewCamera:
        from matl.data.catalog.rendering import ViewCamera

        u = rng.random(9)
        tilt = math.radians(self.tilt_deg[0] + u[0] * (self.tilt_deg[1] - self.tilt_deg[0]))
        azimuth = 2.0 * math.pi * u[1]
        roll = math.radians(self.rotation_deg[0] + u[2] * (self.rotation_deg[1] - self.rotation_deg[0]))
        scale = self.scale[0] + u[3] * (self.scale[1] - self.scale[0])
        tx, ty = (self.translation[0] + u[4:6] * (self.translation[1] - self.translation[0])) * size
        focal_px = self.focal * size
        # Fronto-parallel, a plane point at x units from the centre lands scale * x * S / (2 half) px away.
        distance = focal_px * 2.0 * half / (scale * size)
        right, up, normal = plane.right, plane.up, plane.normal
        tilt_rot = rotation(math.cos(azimuth) * right + math.sin(azimuth) * up, tilt)
        x_axis, y_axis, z_axis = tilt_rot @ right, tilt_rot @ up, tilt_rot @ normal
        c, s = math.cos(roll), math.sin(roll)
        x_axis, y_axis = c * x_axis - s * y_axis, s * x_axis + c * y_axis
        pose = camera_pose(x_axis, y_axis, z_axis, normal * offset + distance * z_axis)
        dist_centre = float(np.linalg.norm(pose[:3, 3]))
        # The light comes from near the camera: its axis turned off the view axis within the cone.
        cone = math.radians(self.light_cone_deg) * math.sqrt(u[6])
        spin = 2.0 * math.pi * u[7]
        light_rot = rotation(math.cos(spin) * x_axis + math.sin(spin) * y_axis, cone)
        light_pose = np.eye(4)
        light_pose[:3, :3] = light_rot @ pose[:3, :3]
        tint = 1.0 + self.tint * (2.0 * rng.random(3) - 1.0)
        return ViewCamera(
            pose=pose,
            focal_px=focal_px,
            principal=((size - 1) / 2.0 + float(tx), (size - 1) / 2.0 + float(ty)),
            znear=max(dist_centre - 1.5 * radius, 1e-3 * dist_centre),
            zfar=dist_centre + 1.5 * radius,
            ambient=self.ambient[0] + u[8] * (self.ambient[1] - self.ambient[0]),
            direct=float(self.direct[0] + rng.random() * (self.direct[1] - self.direct[0])),
            light_pose=light_pose,
            light_colour=(float(tint[0]), float(tint[1]), float(tint[2])),
        )

    def sample(
        self,
        plane: PlaneView,
        offset: float,
        half: float,
        box: np.ndarray,
        size: int,
        n: int,
        rng: np.random.Generator,
    ) -> tuple[list[ViewCamera], np.ndarray]:
        """``n`` cameras around ``plane`` and their ``query_H_canon`` (n, 3, 3) float64.

        Args:
            plane, offset: the plane (normal . X = offset, object frame).
            half: half-width of its canonical view (:func:`matl.data.catalog.rendering.plane_half_width`).
            box: (8, 3) corners of the object's bounding box (:func:`bounding_box_corners`), kept in
                the frame by ``keep_inside``.
            size: image side ``S`` in pixels.
            rng: all randomness comes from it.
        """
        radius = float(np.linalg.norm(box, axis=1).max())
        corners = np.column_stack([box, np.ones(len(box))])
        cameras, Hs = [], []
        for _ in range(n):
            best, best_violation = None, math.inf
            for _try in range(self.max_tries if self.keep_inside else 1):
                cam = self._candidate(plane, offset, half, radius, size, rng)
                if not self.keep_inside:
                    best = cam
                    break
                proj = corners @ projection(cam.pose, cam.focal_px, cam.principal).T
                w = proj[:, 2]
                if (w <= 1e-9).any():  # a corner behind the camera: never acceptable
                    continue
                uv = proj[:, :2] / w[:, None]
                violation = float(np.clip(-uv, 0, None).sum() + np.clip(uv - (size - 1), 0, None).sum())
                if violation < best_violation:
                    best, best_violation = cam, violation
                if violation == 0.0:
                    break
            if best is None:  # every candidate had a corner behind the camera (absurd ranges)
                best = self._candidate(plane, offset, half, radius, size, rng)
            cameras.append(best)
            Hs.append(plane_homography(plane, offset, half, size, best))
        return cameras, np.stack(Hs) if Hs else np.zeros((0, 3, 3))
