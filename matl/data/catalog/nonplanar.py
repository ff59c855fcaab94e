"""Non-planar procedural products (paper Sec. 5.8, Table 2): bottles, mugs, spray cans, pouches, balls.

"Non-planar objects consist of not only canonical planes but also curved surfaces, projections, and
concavities." Each product here is printed with the same label machinery as the simple ones
(:func:`matl.data.catalog.labels.compose`: brand palette, fonts, pictures, barcodes) but has a shape
no single plane describes:

* ``bottle``: lathe profile with a rounded base, a body carrying the label, a shoulder that narrows
  to a neck, and a screw cap whose top is printed.
* ``flask``: the same with an elliptical cross-section (a squeeze bottle, like YCB's mustard).
* ``mug``: open cylinder with a rim, an inner wall, a printed inner bottom and a handle (concave,
  with a projection).
* ``spray``: aerosol can with a domed shoulder and a narrower cap.
* ``pouch``: gusseted bag, front and back bulging, printed side gussets, crimped seals top and bottom.
* ``ball``: lumpy, squashed sphere (a squeeze toy), its print wrapped round.

The first four take the cylinder's 10 canonical planes (top, bottom, 8 sides every 45 deg); the
last two the box's 6. Each plane's extent is the silhouette's bounding box seen along it, measured
symmetrically about the object centre (the origin, the centre of the object's bounding box), so a
mug's handle stays inside the frame of every side view while the camera axis goes through the
object's centre (``docs/design.md``).
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import trimesh
from PIL import Image, ImageDraw
from trimesh.visual.texture import TextureVisuals

from matl.data.catalog.drawing import INK, RGB, WHITE, floor_ink, mix
from matl.data.catalog.labels import compose
from matl.data.catalog.products import BRANDS, VARIANTS, ProductSpec, catalog_seed, slug
from matl.data.catalog.shapes import (
    BOX_FACES,
    CYLINDER_SIDE_ANGLES,
    PlaneView,
    ProductModel,
    _material,
    textured_disc,
)


@dataclass(frozen=True)
class NonPlanarKind:
    """A non-planar product kind: ``form`` (mesh builder), nominal bounding box (x, y, z) in cm,
    label ``style`` (chooses cap and lid prints) and ``(title, illustration, variant)`` titles."""

    form: str
    dims: tuple[float, float, float]
    style: str
    titles: tuple[tuple[str, str, str], ...]
    sizes: tuple[str, ...]


NONPLANAR_KINDS: tuple[NonPlanarKind, ...] = (
    NonPlanarKind(
        "bottle",
        (8.0, 8.0, 19.0),
        "tube",
        (
            ("Sparkling Water", "drops", "sky"),
            ("Olive Oil", "leaves", "olive"),
            ("Orange Juice", "fruit", "orange"),
            ("Herbal Shampoo", "leaves", "mint"),
            ("Tomato Ketchup", "fruit", "tomato"),
            ("Dish Soap", "drops", "lime"),
            ("Berry Smoothie", "berries", "berry"),
        ),
        ("500 ml", "750 ml", "1 l"),
    ),
    NonPlanarKind(
        "flask",
        (9.5, 5.5, 18.0),
        "tube",
        (
            ("Yellow Mustard", "grains", "lemon"),
            ("Bleach Cleanser", "drops", "sky"),
            ("Hand Lotion", "flower", "rose"),
            ("Honey Squeeze", "flower", "caramel"),
        ),
        ("250 ml", "400 g", "300 ml"),
    ),
    NonPlanarKind(
        "mug",
        (8.5, 8.5, 9.5),
        "tube",
        (
            ("Morning Mug", "cup", "cocoa"),
            ("Garden Mug", "flower", "mint"),
            ("Starry Mug", "stars", "plum"),
            ("Harbor Mug", "landscape", "sky"),
        ),
        ("350 ml", "300 ml"),
    ),
    NonPlanarKind(
        "spray",
        (7.0, 7.0, 17.0),
        "tube",
        (
            ("Air Freshener", "flower", "lime"),
            ("Glass Cleaner", "drops", "sky"),
            ("Hair Spray", "stars", "rose"),
            ("Whipped Cream", "berries", "cream"),
        ),
        ("300 ml", "250 ml", "400 ml"),
    ),
    NonPlanarKind(
        "pouch",
        (16.0, 5.0, 22.0),
        "box",
        (
            ("Potato Chips", "grains", "lemon"),
            ("Gummy Bears", "berries", "berry"),
            ("Trail Mix", "grains", "caramel"),
        ),
        ("150 g", "200 g"),
    ),
    NonPlanarKind(
        "ball",
        (8.0, 7.0, 6.5),
        "tube",
        (("Squeeze Ball", "stars", "orange"), ("Bath Bomb", "flower", "plum"), ("Dog Toy Ball", "fish", "lime")),
        ("1 pc", "2 pcs"),
    ),
)
# Objects per form in the non-planar set: 23, as the paper's non-planar YCB split (Sec. 5.8).
NONPLANAR_COMPOSITION: dict[str, int] = {"bottle": 6, "flask": 4, "mug": 4, "spray": 4, "pouch": 3, "ball": 2}
CYLINDER_FORMS = ("bottle", "flask", "mug", "spray")
BOX_FORMS = ("pouch", "ball")
PLANES_PER_FORM: dict[str, int] = {**dict.fromkeys(CYLINDER_FORMS, 10), **dict.fromkeys(BOX_FORMS, 6)}


def sample_nonplanar(seed: int) -> list[ProductSpec]:
    """The 23 non-planar products for ``seed`` (shape ``"nonplanar"``, ``kind`` = form), grouped by
    form in :data:`NONPLANAR_COMPOSITION` order.

    Brands are dealt round robin in a shuffled order as for the simple catalogs, and one brand never
    carries a title twice.
    """
    root = catalog_seed("ycb_nonplanar", seed)
    rng = np.random.default_rng(root)
    n_total = sum(NONPLANAR_COMPOSITION.values())
    brand_of = [BRANDS[i % len(BRANDS)] for i in rng.permutation(n_total)]
    children = root.spawn(n_total)
    kinds = {k.form: k for k in NONPLANAR_KINDS}
    specs: list[ProductSpec] = []
    i = 0
    for form, count in NONPLANAR_COMPOSITION.items():
        kind = kinds[form]
        titles = [kind.titles[j] for j in rng.permutation(len(kind.titles))]
        for n in range(count):
            title, art, variant = titles[n % len(titles)]
            if n >= len(titles):
                title = f"{title} {n // len(titles) + 1}"
            brand = brand_of[i]
            jitter = rng.uniform(0.88, 1.12, size=3)
            if form in ("bottle", "mug", "spray"):
                jitter[1] = jitter[0]  # round cross-section
            dims = tuple(float(round(d * j, 2)) for d, j in zip(kind.dims, jitter, strict=True))
            specs.append(
                ProductSpec(
                    name=slug(f"{brand.name} {title}"),
                    title=title,
                    subtitle=str(rng.choice(kind.sizes)),
                    brand=brand,
                    kind=form,
                    shape="nonplanar",
                    style=kind.style,
                    dims=dims,  # type: ignore[arg-type]
                    variant=VARIANTS[variant],
                    art=art,
                    seed=int(children[i].generate_state(1)[0]),
                )
            )
            i += 1
    return specs


# ------------------------------------------------------------------------------------- mesh parts


def _solid(colour: RGB) -> Image.Image:
    """A small flat texture: parts printed in one colour still carry a texture (the renderer's
    material path is the same for every part)."""
    return floor_ink(Image.new("RGB", (8, 8), colour))


def _printed(vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray, image: Image.Image) -> trimesh.Trimesh:
    """A mesh printed with ``image`` at texture coordinates ``uv``, its vertices and faces kept as given."""
    return trimesh.Trimesh(vertices, faces, visual=TextureVisuals(uv=uv, material=_material(image)), process=False)


def lathe(
    z: np.ndarray,
    r: np.ndarray,
    image: Image.Image,
    segments: int = 96,
    aspect: tuple[float, float] = (1.0, 1.0),
    inward: bool = False,
) -> trimesh.Trimesh:
    """Surface of revolution about +z of the profile ``(z, r)`` (K,), bottom to top.

    Texture u = 0.5 faces -y (the front, ``side_000``) and grows towards +x, as
    :func:`~matl.data.catalog.shapes.cylinder_side`; v runs linearly with z from the profile's
    bottom (0) to top (1). ``aspect`` scales x and y (an elliptical cross-section); ``inward``
    turns the faces to look at the axis (an inner wall). The seam column is duplicated so u can
    wrap, and its normals are averaged so the seam does not show in the shading.
    """
    z, r = np.asarray(z, float), np.asarray(r, float)
    u = np.linspace(0.0, 1.0, segments + 1)
    phi = 2 * math.pi * u - 1.5 * math.pi
    cos, sin = np.cos(phi) * aspect[0], np.sin(phi) * aspect[1]
    k_rows, n1 = len(z), segments + 1
    vertices = np.stack(
        [r[:, None] * cos[None, :], r[:, None] * sin[None, :], np.repeat(z[:, None], n1, axis=1)], axis=-1
    ).reshape(-1, 3)
    v = (z - z[0]) / max(z[-1] - z[0], 1e-9)
    uv = np.stack([np.tile(u, k_rows), np.repeat(v, n1)], axis=1)
    faces = []
    for k in range(k_rows - 1):
        a, b = k * n1, (k + 1) * n1
        j = np.arange(segments)
        faces.append(np.column_stack([a + j, a + j + 1, b + j + 1]))
        faces.append(np.column_stack([a + j, b + j + 1, b + j]))
    faces = np.vstack(faces)
    if inward:
        faces = faces[:, ::-1]
    mesh = _printed(vertices, faces, uv, image)
    normals = mesh.vertex_normals.reshape(k_rows, n1, 3).copy()
    seam = normals[:, 0] + normals[:, -1]
    seam /= np.maximum(np.linalg.norm(seam, axis=1, keepdims=True), 1e-12)
    normals[:, 0] = normals[:, -1] = seam
    mesh.vertex_normals = normals.reshape(-1, 3)
    return mesh


def _disc(radius: float, z: float, up_facing: bool, image: Image.Image, segments: int = 96,
          aspect: tuple[float, float] = (1.0, 1.0)) -> trimesh.Trimesh:
    """Printed flat disc (or ellipse, by ``aspect``) at height ``z``, upright from outside like the
    cylinder lids (image up = +y)."""
    disc = textured_disc(radius, z, 1.0 if up_facing else -1.0, np.array([0.0, 1.0, 0.0]), image, segments)
    disc.vertices[:, 0] *= aspect[0]
    disc.vertices[:, 1] *= aspect[1]
    return disc


def tube_along(path: np.ndarray, radius: tuple[float, float], image: Image.Image, sides: int = 16) -> trimesh.Trimesh:
    """A tube of elliptical cross-section (``radius`` = half-width in the path's plane, half-depth
    across it) swept along the polyline ``path`` (K, 3) lying in a plane y = const; ends left open
    (they sit against the body)."""
    tangents = np.gradient(path, axis=0)
    tangents /= np.linalg.norm(tangents, axis=1, keepdims=True)
    across = np.array([0.0, 1.0, 0.0])
    inplane = np.cross(tangents, across)
    theta = np.linspace(0.0, 2 * math.pi, sides, endpoint=False)
    ring = (np.cos(theta)[None, :, None] * radius[0] * inplane[:, None, :]
            + np.sin(theta)[None, :, None] * radius[1] * across[None, None, :])  # fmt: skip
    vertices = (path[:, None, :] + ring).reshape(-1, 3)
    faces = []
    for k in range(len(path) - 1):
        a, b = k * sides, (k + 1) * sides
        j = np.arange(sides)
        jn = (j + 1) % sides
        faces.append(np.column_stack([a + j, b + j, b + jn]))
        faces.append(np.column_stack([a + j, b + jn, a + jn]))
    uv = np.full((len(vertices), 2), 0.5)
    mesh = _printed(vertices, np.vstack(faces), uv, image)
    # The tube is open, so its volume sign means nothing: check the winding against the radial
    # direction (face centre minus its ring's path point) and flip if the faces look inward.
    ring_of_face = np.arange(len(mesh.faces)) // (2 * sides)
    radial = mesh.triangles_center - path[ring_of_face]
    if float(np.einsum("ij,ij->i", mesh.face_normals, radial).sum()) < 0:
        mesh.invert()
    return mesh


def _wrap_texture(spec: ProductSpec, circumference: float, height: float, texture_px: int) -> Image.Image:
    s = 2 * texture_px / max(circumference, height)
    return compose(spec, "wrap", (max(round(circumference * s), 32), max(round(height * s), 32)))


def _bottle_texture(
    spec: ProductSpec, body: RGB, circumference: float, height: float, band: tuple[float, float], texture_px: int
) -> Image.Image:
    """Side texture of a whole lathe: plastic ``body`` colour with the product's wrap label in the
    z band ``band`` (fractions of the height, from the bottom) and a brand-coloured collar above it."""
    label = _wrap_texture(spec, circumference, height * (band[1] - band[0]), texture_px)
    w = label.width
    h = max(round(label.height / (band[1] - band[0])), label.height + 2)
    im = Image.new("RGB", (w, h), body)
    draw = ImageDraw.Draw(im)
    # Soft vertical shading stripes make a plastic body read as round even where it is unprinted.
    for k in range(8):
        x = int((k + 0.5) * w / 8)
        draw.line((x, 0, x, h), fill=mix(body, WHITE, 0.12), width=max(1, w // 120))
    top = h - round(band[1] * h)  # image rows run top-down, v (and z) bottom-up
    im.paste(label.resize((w, round((band[1] - band[0]) * h))), (0, top))
    collar_top = top - max(2, h // 30)
    if collar_top > 0:  # a brand-coloured collar just above the label, where there is room
        draw.rectangle((0, collar_top, w, top - 1), fill=spec.brand.palette.main)
    return floor_ink(im)


def _cylinder_planes(parts: list[trimesh.Trimesh]) -> list[PlaneView]:
    """Top, bottom and 8 sides (as :func:`~matl.data.catalog.shapes.cylinder_model`) with extents
    measured on the parts."""
    up_lid = np.array([0.0, 1.0, 0.0])
    planes = [PlaneView("top", np.array([0.0, 0.0, 1.0]), up_lid, (0.0, 0.0)),
              PlaneView("bottom", np.array([0.0, 0.0, -1.0]), up_lid, (0.0, 0.0))]  # fmt: skip
    for a in CYLINDER_SIDE_ANGLES:
        t = math.radians(a)
        planes.append(PlaneView(f"side_{a:03d}", np.array([math.sin(t), -math.cos(t), 0.0]),
                                np.array([0.0, 0.0, 1.0]), (0.0, 0.0)))  # fmt: skip
    return [with_extent(p, parts) for p in planes]


def _box_planes(parts: list[trimesh.Trimesh]) -> list[PlaneView]:
    planes = [PlaneView(name, np.asarray(n, float), np.asarray(u, float), (0.0, 0.0)) for name, n, u in BOX_FACES]
    return [with_extent(p, parts) for p in planes]


def with_extent(plane: PlaneView, parts: list[trimesh.Trimesh]) -> PlaneView:
    """``plane`` with its extent set to twice the largest distance of any vertex from the centre
    along the plane's right and up axes (symmetric about the centre, so everything fits)."""
    v = np.concatenate([p.vertices for p in parts])
    width = 2.0 * float(np.abs(v @ plane.right).max())
    height = 2.0 * float(np.abs(v @ plane.up).max())
    return PlaneView(plane.name, plane.normal, plane.up, (width, height))


def _centre(parts: list[trimesh.Trimesh]) -> list[trimesh.Trimesh]:
    """Move all parts so the centre of their joint bounding box is the origin (the object centre)."""
    v = np.concatenate([p.vertices for p in parts])
    shift = -(v.min(0) + v.max(0)) / 2
    for p in parts:
        p.apply_translation(shift)
    return parts


def _smooth_step(t: np.ndarray) -> np.ndarray:
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3 - 2 * t)


def _body_colour(spec: ProductSpec, rng: np.random.Generator) -> RGB:
    p = spec.brand.palette
    options = (mix(spec.variant, WHITE, 0.35), mix(p.main, WHITE, 0.15), p.paper, mix(spec.variant, INK, 0.2))
    return options[int(rng.integers(len(options)))]


def _bottle_parts(spec: ProductSpec, texture_px: int, rng: np.random.Generator, flat: bool) -> list[trimesh.Trimesh]:
    """Bottle, or with ``flat`` a flask of elliptical cross-section (depth/width of ``spec.dims``):
    rounded base, labelled body, shoulder, neck and a knurled cap with a printed top."""
    w, d, h = spec.dims
    radius = w / 2
    asp = (1.0, d / w) if flat else (1.0, 1.0)
    neck_r = radius * float(rng.uniform(0.32, 0.45))
    shoulder = float(rng.uniform(0.58, 0.7))
    neck_z = shoulder + float(rng.uniform(0.12, 0.18))
    cap_h = float(rng.uniform(0.07, 0.1))
    body_top = 1.0 - cap_h
    zs = np.concatenate([
        [0.0], np.linspace(0.005, 0.05, 5), np.linspace(0.07, shoulder, 6),
        np.linspace(shoulder, neck_z, 12)[1:], np.linspace(neck_z, body_top, 3)[1:],
    ])  # fmt: skip
    base = 0.86 + 0.14 * np.sqrt(_smooth_step(zs / 0.05))  # rounded heel
    waist = 1.0 - 0.05 * np.exp(-(((zs - 0.35) / 0.08) ** 2)) * float(rng.integers(2))  # some have a grip waist
    taper = 1.0 - (1.0 - neck_r / radius) * _smooth_step((zs - shoulder) / (neck_z - shoulder))
    rs = radius * np.minimum(base, 1.0) * waist * taper
    body_colour = _body_colour(spec, rng)
    band = (0.12, shoulder - 0.03)
    circumference = math.pi * w if asp == (1.0, 1.0) else math.pi * (w + d) / 2
    side = _bottle_texture(spec, body_colour, circumference, h * body_top, (band[0] / body_top, band[1] / body_top),
                           texture_px)  # fmt: skip
    parts = [lathe(zs * h, rs, side, aspect=asp)]
    cap_colour = (spec.brand.palette.main, spec.variant, spec.brand.palette.second)[int(rng.integers(3))]
    cap_r = neck_r * float(rng.uniform(1.15, 1.35))
    cz = np.array([body_top - 0.01, body_top + 0.005, 1.0 - 0.01, 1.0]) * h
    cr = np.array([cap_r * 0.97, cap_r, cap_r, cap_r * 0.94])
    ridges = Image.new("RGB", (64, 16), cap_colour)
    rd = ImageDraw.Draw(ridges)
    for x in range(0, 64, 4):  # knurled cap edge
        rd.line((x, 0, x, 16), fill=mix(cap_colour, INK, 0.25))
    parts.append(lathe(cz, cr, floor_ink(ridges), aspect=asp))
    parts.append(_disc(cap_r * 0.94, h, True, compose(spec, "lid_top", (texture_px, texture_px)), aspect=asp))
    parts.append(_disc(rs[0], 0.0, False, compose(spec, "lid_bottom", (texture_px, texture_px)), aspect=asp))
    return parts


def _mug_parts(spec: ProductSpec, texture_px: int, rng: np.random.Generator) -> list[trimesh.Trimesh]:
    """Mug: printed outer wall, rim, plain inner wall, printed inner bottom, base and a handle."""
    w, _, h = spec.dims
    radius = w / 2
    wall = radius * 0.07
    colour = (spec.brand.palette.paper, mix(spec.variant, WHITE, 0.55), WHITE)[int(rng.integers(3))]
    inner_colour = mix(colour, INK, 0.12)
    zs = np.array([0.0, 0.01, 0.03, 0.06, 1.0]) * h
    rs = radius * np.array([0.9, 0.95, 0.985, 1.0, 1.0])
    print_im = _wrap_texture(spec, math.pi * w, h, texture_px)
    outer = lathe(zs, rs, print_im)
    rim = lathe(np.array([h, h + wall * 0.3, h]), np.array([radius, radius - wall / 2, radius - wall]),
                _solid(colour))  # fmt: skip
    floor = 0.09 * h
    inner = lathe(np.array([floor, h]), np.array([radius - wall, radius - wall]), _solid(inner_colour), inward=True)
    # The inside of the bottom carries a small print (brand mark), as many mugs do: it is what the
    # top view sees besides the rim and the handle.
    inside = Image.new("RGB", (texture_px, texture_px), inner_colour)
    mark = compose(spec, "lid_top", (texture_px // 2, texture_px // 2))
    inside.paste(mark, (texture_px // 4, texture_px // 4))
    floor_disc = _disc(radius - wall, floor, True, floor_ink(inside))
    base = _disc(rs[0], 0.0, False, compose(spec, "lid_bottom", (texture_px, texture_px)))
    # Handle: a C from near the top to near the bottom on the +x side.
    reach = radius * float(rng.uniform(0.45, 0.6))
    t = np.linspace(-math.pi / 2, math.pi / 2, 24)
    top_z, bottom_z = h * 0.82, h * 0.22
    mid, half_h = (top_z + bottom_z) / 2, (top_z - bottom_z) / 2
    path = np.column_stack([radius * 0.96 + reach * np.cos(t), np.zeros_like(t), mid - half_h * np.sin(t)])
    handle = tube_along(path, (radius * 0.09, radius * 0.16), _solid(mix(colour, INK, 0.05)))
    return [outer, rim, inner, floor_disc, base, handle]


def _spray_parts(spec: ProductSpec, texture_px: int, rng: np.random.Generator) -> list[trimesh.Trimesh]:
    """Aerosol can: labelled body, domed metal shoulder, valve, narrower printed cap."""
    w, _, h = spec.dims
    radius = w / 2
    body_h = float(rng.uniform(0.68, 0.74))
    dome_h = 0.07
    zs = np.concatenate([[0.0, 0.01, 0.025], np.linspace(0.04, body_h, 4)])
    rs = radius * np.array([0.9, 0.97, 1.0, 1.0, 1.0, 1.0, 1.0])
    metal = (196, 198, 204)
    side = _bottle_texture(spec, metal, math.pi * w, h * body_h, (0.05, 0.97), texture_px)
    parts = [lathe(zs * h, rs, side)]
    dz = np.linspace(body_h, body_h + dome_h, 8)
    dr = radius * np.sqrt(np.clip(1 - ((dz - body_h) / dome_h) ** 2 * 0.75, 0.0, 1.0))
    parts.append(lathe(dz * h, dr, _solid(mix(metal, WHITE, 0.2))))
    cap_r = radius * float(rng.uniform(0.8, 0.92))
    cap_colour = (spec.brand.palette.main, spec.variant, spec.brand.palette.accent)[int(rng.integers(3))]
    cz = np.array([body_h + dome_h * 0.4, body_h + dome_h * 0.45, 0.985, 1.0]) * h
    cr = np.array([cap_r, cap_r * 1.02, cap_r * 0.99, cap_r * 0.95])
    parts.append(lathe(cz, cr, _solid(cap_colour)))
    parts.append(_disc(cap_r * 0.95, h, True, compose(spec, "lid_top", (texture_px, texture_px))))
    parts.append(_disc(rs[0], 0.0, False, compose(spec, "lid_bottom", (texture_px, texture_px))))
    return parts


def _grid(nx: int, ny: int) -> np.ndarray:
    """Triangles (2 (nx-1)(ny-1), 3) of an ``nx`` x ``ny`` vertex grid, row-major."""
    i, j = np.meshgrid(np.arange(nx - 1), np.arange(ny - 1), indexing="xy")
    a = (j * nx + i).reshape(-1)
    return np.vstack([np.column_stack([a, a + 1, a + nx + 1]), np.column_stack([a, a + nx + 1, a + nx])])


def _pouch_parts(spec: ProductSpec, texture_px: int, rng: np.random.Generator) -> list[trimesh.Trimesh]:
    """Gusseted bag: front and back sheets bulging to the bag's depth, printed side gussets, and
    crimped flat seals at top and bottom where the sheets and gussets close to nothing."""
    w, d, h = spec.dims
    nx, nz, ny = 33, 45, 9
    x = np.linspace(-w / 2, w / 2, nx)
    z = np.linspace(-h / 2, h / 2, nz)
    xx, zz = np.meshgrid(x, z, indexing="xy")
    seal = 0.07
    gusset = d / 2 * 0.45  # half-depth where a sheet meets its side gusset
    across = np.clip(1 - (2 * xx / w) ** 4, 0.0, 1.0) ** 0.5
    along = _smooth_step((0.5 - np.abs(zz / h) - seal) / 0.12)
    wrinkle = 1.0 + 0.04 * np.sin(xx * float(rng.uniform(1.5, 2.5)) + zz * 0.7)  # a bag is never smooth
    bulge = (gusset + (d / 2 - gusset) * across * wrinkle) * along
    # Seals are crimped: a small zig-zag so they catch the light.
    crimp = 0.004 * h * np.sign(np.sin(xx * 6.0)) * (along == 0)

    def panel(role: str, x: np.ndarray, y: np.ndarray, zs: np.ndarray, u: np.ndarray, faces: np.ndarray,
              width: float) -> trimesh.Trimesh:
        """One printed panel on a vertex grid: its ``role``'s print, ``width`` x ``h`` cm, v up the bag."""
        k = texture_px / max(width, h)
        size = max(round(width * k), 16), max(round(h * k), 16)
        vertices = np.column_stack([x.reshape(-1), y.reshape(-1), zs.reshape(-1)])
        uv = np.column_stack([u.reshape(-1), (zs / h + 0.5).reshape(-1)])
        return _printed(vertices, faces, uv, compose(spec, role, size))

    sheet = _grid(nx, nz)
    # the back reads left-to-right from behind
    parts = [panel("front", xx, -bulge + crimp, zz, xx / w + 0.5, sheet, w),
             panel("back", xx, bulge + crimp, zz, 0.5 - xx / w, sheet[:, ::-1], w)]
    # Side gussets: strips at x = +-w/2 spanning the sheets' edges, printed like a box's sides. Seen from
    # outside (looking along -sign x) image right is +y on the left gusset, -y on the right.
    t = np.linspace(-1.0, 1.0, ny)
    tt, gz = np.meshgrid(t, z, indexing="xy")
    edge = gusset * _smooth_step((0.5 - np.abs(gz / h) - seal) / 0.12)
    strip = _grid(ny, nz)
    parts += [panel("left", np.full(tt.size, -w / 2), tt * edge, gz, (tt + 1) / 2, strip[:, ::-1], d),
              panel("right", np.full(tt.size, w / 2), tt * edge, gz, (1 - tt) / 2, strip, d)]
    return parts


def _ball_parts(spec: ProductSpec, texture_px: int, rng: np.random.Generator) -> list[trimesh.Trimesh]:
    """Lumpy squashed sphere with its print wrapped round (u = azimuth, v = height)."""
    w, d, h = spec.dims
    n_u, n_v = 97, 49
    u = np.linspace(0.0, 1.0, n_u)
    v = np.linspace(0.0, 1.0, n_v)
    uu, vv = np.meshgrid(u, v, indexing="xy")
    phi = 2 * math.pi * uu - 1.5 * math.pi
    theta = math.pi * (1 - vv)  # polar angle: v = 0 bottom, 1 top
    direction = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=-1)
    lumps = np.ones_like(uu)
    for _ in range(5):  # smooth random lumps: a few low-frequency bumps on the sphere
        centre = rng.normal(size=3)
        centre /= np.linalg.norm(centre)
        lumps += float(rng.uniform(0.04, 0.1)) * np.exp(-((1 - direction @ centre) / 0.25) ** 2)
    vertices = (direction * lumps[..., None] * np.array([w, d, h]) / 2).reshape(-1, 3)
    image = _wrap_texture(spec, math.pi * (w + d) / 2, h * 1.2, texture_px)
    faces = _grid(n_u, n_v)  # u round (counter-clockwise from above), v up: outward winding
    uv = np.column_stack([uu.reshape(-1), vv.reshape(-1)])
    mesh = _printed(vertices, faces, uv, image)
    if mesh.volume < 0:
        mesh.invert()
    return [mesh]


_PART_BUILDERS: dict[str, Callable[[ProductSpec, int, np.random.Generator], list[trimesh.Trimesh]]] = {
    "bottle": lambda s, t, r: _bottle_parts(s, t, r, flat=False),
    "flask": lambda s, t, r: _bottle_parts(s, t, r, flat=True),
    "mug": _mug_parts,
    "spray": _spray_parts,
    "pouch": _pouch_parts,
    "ball": _ball_parts,
}


def nonplanar_model(spec: ProductSpec, texture_px: int = 512) -> ProductModel:
    """Textured parts and canonical planes of a non-planar product (``spec.kind`` is its form)."""
    if spec.kind not in _PART_BUILDERS:
        raise ValueError(f"unknown non-planar form {spec.kind!r}; valid: {sorted(_PART_BUILDERS)}")
    rng = np.random.default_rng([spec.seed, zlib.crc32(b"nonplanar-geometry")])
    parts = _centre(_PART_BUILDERS[spec.kind](spec, texture_px, rng))
    planes = _cylinder_planes(parts) if spec.kind in CYLINDER_FORMS else _box_planes(parts)
    return ProductModel(parts, planes, spec.name)
