"""Textured trimesh models of the procedural products and their canonical planes.

Object frame (cm): x right, y away from the viewer of the front, z up; the object's centre is
the origin. A product is a list of textured parts (one per face, label or lid, each with its own
texture image) plus the canonical planes it is photographed from. UVs are the projection of each
part onto its plane's (right, up) axes, so every texture appears upright and unmirrored in its
canonical view.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import trimesh
from PIL import Image
from trimesh.visual.material import PBRMaterial
from trimesh.visual.texture import TextureVisuals

from matl.data.catalog.labels import compose
from matl.data.catalog.products import ProductSpec

CYLINDER_SIDE_ANGLES = tuple(range(0, 360, 45))


@dataclass(frozen=True)
class PlaneView:
    """A canonical plane: outward ``normal`` (3,), image ``up`` (3,) and the ``extent``
    (width, height) in cm of the object's silhouette seen along the normal."""

    name: str
    normal: np.ndarray
    up: np.ndarray
    extent: tuple[float, float]

    @property
    def right(self) -> np.ndarray:
        """Image-right axis (3,) of the view: ``up x normal``, so (right, up, normal) is right-handed."""
        return np.cross(self.up, self.normal)


@dataclass(frozen=True)
class ProductModel:
    """Textured parts of one product and its canonical planes, in order, and its object name."""

    parts: list[trimesh.Trimesh]
    planes: list[PlaneView]
    name: str = ""


def _material(image: Image.Image) -> PBRMaterial:
    # Matte, non-metallic: the print should look like ink on paper/card, not like chrome.
    return PBRMaterial(baseColorTexture=image, metallicFactor=0.0, roughnessFactor=1.0)


def textured_quad(
    centre: np.ndarray, normal: np.ndarray, up: np.ndarray, width: float, height: float, image: Image.Image
) -> trimesh.Trimesh:
    """Rectangle of ``width`` x ``height`` facing ``normal`` with ``image`` upright along ``up``.

    Returns a 4-vertex, 2-face trimesh whose UV (0, 0) is the image's bottom-left corner.
    """
    right = np.cross(up, normal)
    hw, hh = right * width / 2, up * height / 2
    vertices = np.array([centre - hw - hh, centre + hw - hh, centre + hw + hh, centre - hw + hh])
    faces = np.array([[0, 1, 2], [0, 2, 3]])  # counter-clockwise seen from outside
    uv = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    return trimesh.Trimesh(vertices, faces, visual=TextureVisuals(uv=uv, material=_material(image)), process=False)


def _texture_size(width: float, height: float, longest: int) -> tuple[int, int]:
    """Texture pixels for a face of ``width`` x ``height`` cm, ``longest`` px on its long side."""
    s = longest / max(width, height)
    return max(round(width * s), 16), max(round(height * s), 16)


BOX_FACES: tuple[tuple[str, tuple[int, int, int], tuple[int, int, int]], ...] = (
    # name, outward normal, image up
    ("front", (0, -1, 0), (0, 0, 1)),
    ("back", (0, 1, 0), (0, 0, 1)),
    ("left", (-1, 0, 0), (0, 0, 1)),
    ("right", (1, 0, 0), (0, 0, 1)),
    ("top", (0, 0, 1), (0, 1, 0)),  # seen from above with the front at the bottom of the image
    ("bottom", (0, 0, -1), (0, 1, 0)),  # seen from below, front edge also at the bottom (x mirrored)
)


def box_model(spec: ProductSpec, texture_px: int) -> ProductModel:
    """Six textured faces of a box of ``spec.dims``; planar products keep only front and back as
    canonical planes and print their thin rim plainly."""
    dims = np.asarray(spec.dims, float)
    parts: list[trimesh.Trimesh] = []
    planes: list[PlaneView] = []
    planar = spec.shape == "planar"
    for name, n, u in BOX_FACES:
        normal, up = np.asarray(n, float), np.asarray(u, float)
        right = np.cross(up, normal)
        width, height = float(np.abs(right) @ dims), float(np.abs(up) @ dims)
        is_plane = not planar or name in ("front", "back")
        role = name if is_plane else "edge"
        image = compose(spec, role, _texture_size(width, height, texture_px))
        parts.append(textured_quad(normal * dims / 2, normal, up, width, height, image))
        if is_plane:
            planes.append(PlaneView(name, normal, up, (width, height)))
    return ProductModel(parts, planes)


def cylinder_side(radius: float, height: float, image: Image.Image, segments: int) -> trimesh.Trimesh:
    """Open cylinder side around z with ``image`` wrapped once round it.

    Texture u = 0.5 faces -y (the front view) and u grows towards +x, so in the front view the
    label reads left to right; the seam (u = 0 = 1) is at the back. The seam column is duplicated
    so u can jump from 1 back to 0. Vertex normals are radial, giving smooth shading.
    """
    u = np.linspace(0.0, 1.0, segments + 1)
    phi = 2 * math.pi * u - 1.5 * math.pi
    ring = np.stack([radius * np.cos(phi), radius * np.sin(phi)], axis=1)
    bottom = np.column_stack([ring, np.full(segments + 1, -height / 2)])
    top = np.column_stack([ring, np.full(segments + 1, height / 2)])
    vertices = np.vstack([bottom, top])
    k = np.arange(segments)
    n1 = segments + 1
    faces = np.vstack([np.column_stack([k, k + 1, n1 + k + 1]), np.column_stack([k, n1 + k + 1, n1 + k])])
    uv = np.vstack([np.column_stack([u, np.zeros(n1)]), np.column_stack([u, np.ones(n1)])])
    normals = np.column_stack([np.vstack([ring, ring]) / radius, np.zeros(2 * n1)])
    mesh = trimesh.Trimesh(vertices, faces, visual=TextureVisuals(uv=uv, material=_material(image)), process=False)
    mesh.vertex_normals = normals
    return mesh


def textured_disc(
    radius: float, z: float, normal_sign: float, up: np.ndarray, image: Image.Image, segments: int
) -> trimesh.Trimesh:
    """Flat disc at height ``z`` facing ``normal_sign * z``, the square ``image`` inscribed and
    upright along ``up`` when seen from outside."""
    normal = np.array([0.0, 0.0, normal_sign])
    right = np.cross(up, normal)
    phi = np.linspace(0, 2 * math.pi, segments, endpoint=False)
    rim = np.stack([radius * np.cos(phi), radius * np.sin(phi), np.full(segments, z)], axis=1)
    vertices = np.vstack([[0.0, 0.0, z], rim])
    k = np.arange(segments)
    faces = np.column_stack([np.zeros(segments, int), 1 + k, 1 + (k + 1) % segments])
    if normal_sign < 0:
        faces = faces[:, ::-1]
    uv = 0.5 + np.column_stack([vertices[:, :2] @ right[:2], vertices[:, :2] @ up[:2]]) / (2 * radius)
    return trimesh.Trimesh(vertices, faces, visual=TextureVisuals(uv=uv, material=_material(image)), process=False)


def cylinder_model(spec: ProductSpec, texture_px: int, segments: int = 128) -> ProductModel:
    """Labelled cylinder with lids; planes are top, bottom and eight side views every 45 deg.

    ``side_{a:03d}`` looks from the front direction rotated by ``a`` degrees counter-clockwise about
    +z (seen from above), so ``side_090`` looks at the right-hand side of ``side_000``.
    """
    diameter, _, height = spec.dims
    radius = diameter / 2
    circumference = 2 * math.pi * radius
    wrap_size = _texture_size(circumference, height, 2 * texture_px)  # the label is long: twice the budget
    up_lid = np.array([0.0, 1.0, 0.0])
    parts = [
        cylinder_side(radius, height, compose(spec, "wrap", wrap_size), segments),
        textured_disc(radius, height / 2, 1.0, up_lid, compose(spec, "lid_top", (texture_px, texture_px)), segments),
        textured_disc(
            radius, -height / 2, -1.0, up_lid, compose(spec, "lid_bottom", (texture_px, texture_px)), segments
        ),
    ]
    planes = [
        PlaneView("top", np.array([0.0, 0.0, 1.0]), up_lid, (diameter, diameter)),
        PlaneView("bottom", np.array([0.0, 0.0, -1.0]), up_lid, (diameter, diameter)),
    ]
    for a in CYLINDER_SIDE_ANGLES:
        t = math.radians(a)
        planes.append(
            PlaneView(
                f"side_{a:03d}",
                np.array([math.sin(t), -math.cos(t), 0.0]),
                np.array([0.0, 0.0, 1.0]),
                (diameter, height),
            )
        )
    return ProductModel(parts, planes)
