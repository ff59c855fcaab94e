"""Offscreen rendering of canonical planes with pyrender (EGL; Mesa's software renderer on CPU).

Each plane is rendered with an orthographic camera on its normal through the object's centre,
at ``supersample`` times the target size, then area-averaged down. Lighting is dominated by an
ambient term so the print keeps its colours; a weak light from the camera adds the gentle
fall-off that makes a cylinder read as round. The mask comes from the depth buffer, never from
colour. :class:`ViewRenderer` renders the same scenes from perspective cameras (rendered queries
and anchors). Camera poses and the pixel convention are :mod:`matl.geometry.camera`'s.
"""

from __future__ import annotations

import logging
import os

# pyrender picks its GL platform at import time; EGL works headless (no X server).
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
# PyOpenGL logs at INFO, on import, that its optional C accelerator is missing: harmless noise.
logging.getLogger("OpenGL.acceleratesupport").setLevel(logging.WARNING)

import math  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from types import TracebackType  # noqa: E402

import numpy as np  # noqa: E402
import pyrender  # noqa: E402
import trimesh  # noqa: E402
from trimesh.visual.texture import TextureVisuals  # noqa: E402

from matl.data.catalog.shapes import PlaneView, ProductModel  # noqa: E402
from matl.geometry.camera import camera_pose, edge_intrinsics  # noqa: E402

# In linear light: flat faces get AMBIENT + DIRECT = 1 (the texture's own colour); a cylinder's
# flanks, seen at grazing angles, fall to AMBIENT.
AMBIENT = 0.72
DIRECT = 0.28


def _camera_pose(plane: PlaneView, distance: float) -> np.ndarray:
    """4x4 camera-to-world pose looking along -normal with image up = ``plane.up``."""
    return camera_pose(plane.right, plane.up, plane.normal, plane.normal * distance)


def area_downsample(color: np.ndarray, depth: np.ndarray, factor: int) -> tuple[np.ndarray, np.ndarray]:
    """Antialias a supersampled render.

    ``color`` (F*S, F*S, 3) uint8 and ``depth`` (F*S, F*S) float with 0 = background. Returns the
    (S, S, 3) uint8 image (box-filtered over F x F blocks, exactly 0 outside the mask) and the
    (S, S) bool mask (covered fraction > 0.5).
    """
    hi = color.shape[0]
    s = hi // factor
    covered = (depth > 0).reshape(s, factor, s, factor).mean(axis=(1, 3))
    mask = covered > 0.5
    # Background pixels are 0, so the block mean is the print composited over black: edge pixels
    # darken smoothly instead of staircasing.
    img = color.reshape(s, factor, s, factor, 3).astype(np.float32).mean(axis=(1, 3))
    img = np.rint(img).astype(np.uint8)
    img[~mask] = 0
    return img, mask


def plane_half_width(plane: PlaneView, fill: float) -> float:
    """Half-width (object units) of the square a canonical image of ``plane`` shows: its larger
    extent covers ``fill`` of the image width. Canonical and rendered views share it, so their
    pixel frames agree."""
    return max(plane.extent) / (2.0 * fill)


def part_primitives(part: trimesh.Trimesh) -> list[pyrender.Primitive]:
    """pyrender primitives of one part: textured (PBR or simple material) or vertex-coloured.

    Every material is matte (metallic 0, roughness 1) and opaque, because BLEND (trimesh's default
    for materials with alpha) would skip the depth writes the mask is made from.
    """
    visual = part.visual
    if isinstance(visual, TextureVisuals) and visual.uv is not None:
        mat = visual.material
        image = getattr(mat, "baseColorTexture", None)
        if image is None:
            image = getattr(mat, "image", None)
        if image is not None:
            material = pyrender.MetallicRoughnessMaterial(
                baseColorTexture=image, metallicFactor=0.0, roughnessFactor=1.0, alphaMode="OPAQUE"
            )
            return list(pyrender.Mesh.from_trimesh(part, material=material, smooth=True).primitives)
    # Vertex or face colours (e.g. coloured PLY scans): pyrender reads them from the visual when no
    # material is passed; a white matte material keeps them as they are.
    material = pyrender.MetallicRoughnessMaterial(
        baseColorFactor=np.ones(4), metallicFactor=0.0, roughnessFactor=1.0, alphaMode="OPAQUE"
    )
    return list(pyrender.Mesh.from_trimesh(part, material=material, smooth=True).primitives)


def model_radius(model: ProductModel) -> float:
    """Largest distance (object units) of any vertex from the object's centre (the origin)."""
    return float(np.linalg.norm(np.concatenate([p.vertices for p in model.parts]), axis=1).max())


def model_scene(model: ProductModel, ambient: float = AMBIENT) -> pyrender.Scene:
    """A scene holding all parts of ``model`` as one mesh, black background, grey ambient light."""
    scene = pyrender.Scene(bg_color=np.zeros(4), ambient_light=np.full(3, ambient))
    primitives = []
    for part in model.parts:
        primitives.extend(part_primitives(part))
    scene.add(pyrender.Mesh(primitives))
    return scene


def directional_intensity(direct: float) -> float:
    """pyrender light intensity that adds ``direct`` to a matte face lit head-on (linear light)."""
    # Diffuse response of roughness-1 dielectric in pyrender's BRDF is ~0.92/pi per unit radiance.
    return direct * math.pi / 0.92


def ortho_depth(depth: np.ndarray, znear: float, zfar: float) -> np.ndarray:
    """True distance along the view axis from pyrender's depth of an *orthographic* render.

    pyrender linearises every depth buffer as if the camera were perspective; for an orthographic
    camera that is wrong, so undo it: back to window depth, then linear in [znear, zfar]. ``depth``
    (H, W), 0 = background (kept 0).
    """
    d = np.asarray(depth, dtype=np.float64)
    out = np.zeros_like(d)
    hit = d > 0
    z_ndc = (zfar + znear - 2.0 * znear * zfar / d[hit]) / (zfar - znear)
    out[hit] = (z_ndc + 1.0) / 2.0 * (zfar - znear) + znear
    return out


def render_canonical(
    renderer: pyrender.OffscreenRenderer, model: ProductModel, fill: float, supersample: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Canonical images (P, S, S, 3) uint8, masks (P, S, S) bool and plane offsets (P,) of every
    plane of ``model`` with ``renderer`` (of size ``supersample * S``); see
    :meth:`CanonicalRenderer.render_planes`."""
    scene = model_scene(model)
    radius = model_radius(model)
    distance = 3.0 * radius
    znear, zfar = radius * 0.5, radius * 5.0
    camera = pyrender.OrthographicCamera(xmag=1.0, ymag=1.0, znear=znear, zfar=zfar)
    cam_node = scene.add(camera)
    light = pyrender.DirectionalLight(color=np.ones(3), intensity=directional_intensity(DIRECT))
    light_node = scene.add(light)

    images, masks, offsets = [], [], []
    for plane in model.planes:
        camera.xmag = camera.ymag = plane_half_width(plane, fill)
        pose = _camera_pose(plane, distance)
        scene.set_pose(cam_node, pose)
        scene.set_pose(light_node, pose)  # light from the viewer: no cast shadows in view
        color, depth = renderer.render(scene)
        img, mask = area_downsample(color, depth, supersample)
        images.append(img)
        masks.append(mask)
        hit = depth > 0
        offsets.append(float(distance - ortho_depth(depth, znear, zfar)[hit].mean()) if hit.any() else 0.0)
    return np.stack(images), np.stack(masks), np.asarray(offsets, dtype=np.float64)


class CanonicalRenderer:
    """Renders every canonical plane of product models into ``image_size`` px images.

    One OpenGL context serves all renders (creating one per image is slow); use as a context
    manager or call :meth:`close`.
    """

    def __init__(self, image_size: int, supersample: int = 2, fill: float = 0.6) -> None:
        if image_size < 8:
            raise ValueError(f"image_size must be >= 8, got {image_size}")
        if supersample < 1:
            raise ValueError(f"supersample must be >= 1, got {supersample}")
        if not 0.0 < fill <= 1.0:
            raise ValueError(f"fill must be in (0, 1], got {fill}")
        self.image_size = int(image_size)
        self.supersample = int(supersample)
        self.fill = float(fill)
        size = self.image_size * self.supersample
        self._renderer: pyrender.OffscreenRenderer | None = pyrender.OffscreenRenderer(size, size)

    def render(self, model: ProductModel) -> tuple[np.ndarray, np.ndarray]:
        """All planes of ``model``: images (P, S, S, 3) uint8 and masks (P, S, S) bool, in
        ``model.planes`` order.

        Each plane is scaled so its larger extent spans ``fill`` of the image width, centred.
        """
        images, masks, _ = self.render_planes(model)
        return images, masks

    def render_planes(self, model: ProductModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """As :meth:`render`, plus each plane's *offset* (P,) float64: the mean height, along the
        plane's normal from the object's centre, of the surface seen in its canonical view.

        The offset places the plane whose homography best explains the visible surface (a box
        face: exactly the face; a cylinder side: about pi/4 of the radius); rendered views use it
        for their ground-truth ``query_H_canon``.
        """
        if self._renderer is None:
            raise RuntimeError("renderer is closed")
        return render_canonical(self._renderer, model, self.fill, self.supersample)

    def close(self) -> None:
        """Release the GL context (idempotent)."""
        if self._renderer is not None:
            self._renderer.delete()
            self._renderer = None

    def __enter__(self) -> CanonicalRenderer:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


@dataclass(frozen=True)
class ViewCamera:
    """One perspective view of a model, with its lighting.

    Attributes:
        pose: (4, 4) camera-to-world (object frame); the camera looks down its own -z, y up.
        focal_px: focal length in pixels at the target size ``S``.
        principal: (cx, cy) principal point in pixel-centre coordinates at size ``S`` (x right,
            y down, (0, 0) the centre of the top-left pixel).
        znear, zfar: clipping distances (object units).
        ambient: grey ambient light level (linear).
        direct: strength of the directional light, as added to a face it hits head-on.
        light_pose: (4, 4) pose of the directional light (it shines along its own -z).
        light_colour: (3,) RGB multiplier of the directional light (a slight tint).
    """

    pose: np.ndarray
    focal_px: float
    principal: tuple[float, float]
    znear: float
    zfar: float
    ambient: float = AMBIENT
    direct: float = DIRECT
    light_pose: np.ndarray | None = None
    light_colour: tuple[float, float, float] = (1.0, 1.0, 1.0)


class ViewRenderer:
    """Renders models from arbitrary perspective cameras (rendered queries and anchors).

    Same scene, materials, supersampling and mask rule as :class:`CanonicalRenderer`, so a view
    with no tilt, no roll and unit scale looks like the canonical image up to perspective. One GL
    context for all renders; use as a context manager or call :meth:`close`. Never keep two
    renderers open at once: pyrender's EGL platform terminates the display shared by all contexts
    when one is deleted, so the other could no longer be released.
    """

    def __init__(self, image_size: int, supersample: int = 2) -> None:
        if image_size < 8:
            raise ValueError(f"image_size must be >= 8, got {image_size}")
        if supersample < 1:
            raise ValueError(f"supersample must be >= 1, got {supersample}")
        self.image_size = int(image_size)
        self.supersample = int(supersample)
        size = self.image_size * self.supersample
        self._renderer: pyrender.OffscreenRenderer | None = pyrender.OffscreenRenderer(size, size)

    def canonical(self, model: ProductModel, fill: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Canonical images, masks and plane offsets of ``model`` framed by ``fill``, exactly as
        :meth:`CanonicalRenderer.render_planes`, but with this renderer's context."""
        if self._renderer is None:
            raise RuntimeError("renderer is closed")
        return render_canonical(self._renderer, model, fill, self.supersample)

    def plane_offsets(self, model: ProductModel, fill: float) -> np.ndarray:
        """(P,) offset of each canonical plane of ``model`` (see :meth:`CanonicalRenderer.render_planes`)."""
        return self.canonical(model, fill)[2]

    def render(self, model: ProductModel, cameras: list[ViewCamera]) -> tuple[np.ndarray, np.ndarray]:
        """Images (V, S, S, 3) uint8 and masks (V, S, S) bool of ``model`` seen by ``cameras``."""
        if self._renderer is None:
            raise RuntimeError("renderer is closed")
        scene = model_scene(model)
        f = self.supersample
        camera = pyrender.IntrinsicsCamera(fx=1.0, fy=1.0, cx=0.0, cy=0.0)
        cam_node = scene.add(camera)
        light = pyrender.DirectionalLight(color=np.ones(3), intensity=directional_intensity(DIRECT))
        light_node = scene.add(light)
        images = np.zeros((len(cameras), self.image_size, self.image_size, 3), np.uint8)
        masks = np.zeros((len(cameras), self.image_size, self.image_size), bool)
        for i, cam in enumerate(cameras):
            # pyrender's cx, cy are edge-based (pixel k spans [k, k+1]) at the supersampled size.
            camera.fx, camera.cx, camera.cy = edge_intrinsics(cam.focal_px, cam.principal, f)
            camera.fy = camera.fx
            camera.znear, camera.zfar = cam.znear, cam.zfar
            scene.set_pose(cam_node, cam.pose)
            scene.ambient_light = np.full(3, cam.ambient)
            light.color = np.asarray(cam.light_colour, dtype=np.float64)
            light.intensity = directional_intensity(cam.direct)
            scene.set_pose(light_node, cam.pose if cam.light_pose is None else cam.light_pose)
            color, depth = self._renderer.render(scene)
            images[i], masks[i] = area_downsample(color, depth, f)
        return images, masks

    def close(self) -> None:
        """Release the GL context (idempotent)."""
        if self._renderer is not None:
            self._renderer.delete()
            self._renderer = None

    def __enter__(self) -> ViewRenderer:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()
