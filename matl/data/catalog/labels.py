"""Composed product prints: one texture image per face (box/plate) or per label and lid (cylinder).

A print is a pure function of ``(spec, role, size)``: its random details come from a generator
seeded by ``(spec.seed, role)``. Faces of one product share the brand palette, variant colour and
typeface, but each role has its own layout (front: brand + name + picture; back: text + barcode;
sides: nutrition table or brand spine; top/bottom: opening tab, codes), so the planes of one
object are related but distinct. Brand names and titles are printed big because the canonical
images are only ~100 px wide.

This module lays out the faces of boxes and plates and dispatches every role (:func:`compose`); the panels they
are built from are in :mod:`matl.data.catalog.panels`, the planar styles' fronts and backs in
:mod:`matl.data.catalog.planar_prints`, the cylinders' labels and lids in :mod:`matl.data.catalog.cylinder_prints`.
"""

from __future__ import annotations

import numpy as np
from PIL import Image

from matl.data.catalog.art import drop_shadow
from matl.data.catalog.cylinder_prints import lid_bottom, lid_top, wrap_label
from matl.data.catalog.drawing import (
    INK,
    WHITE,
    contrast_ink,
    disc_mask,
    draw_text,
    floor_ink,
    linear_gradient,
    mix,
)
from matl.data.catalog.panels import (
    FaceLayout,
    art_for,
    barcode_panel,
    brand_row,
    face_canvas,
    front_panel,
    nutrition_panel,
    paste_art,
    recycle_mark,
    sub_box,
    text_panel,
    title_lines,
    turned_when_tall,
)
from matl.data.catalog.planar_prints import PLANAR_STYLES
from matl.data.catalog.products import ProductSpec

ROLES = ("front", "back", "left", "right", "top", "bottom", "edge", "wrap", "lid_top", "lid_bottom")


def _rng(spec: ProductSpec, role: str) -> np.random.Generator:
    return np.random.default_rng([spec.seed, ROLES.index(role)])


def _box_back(spec: ProductSpec, w: int, h: int, rng: np.random.Generator) -> Image.Image:
    p = spec.brand.palette
    im, draw, full = face_canvas(Image.new("RGB", (w, h), p.paper))
    portrait = h >= 0.75 * w
    draw.rectangle(sub_box(full, 0, 0, 1, 0.16), fill=p.main)
    brand_row(im, sub_box(full, 0.04, 0.02, 0.7, 0.14), spec, contrast_ink(p.main))
    draw.rectangle(sub_box(full, 0, 0.16, 1, 0.19), fill=spec.variant)
    if portrait:
        title_lines(draw, sub_box(full, 0.05, 0.21, 0.95, 0.33), spec.title, spec.brand.font, p.ink)
        art_box = sub_box(full, 0.55, 0.36, 0.95, 0.62)
        text_panel(im, sub_box(full, 0.05, 0.36, 0.52, 0.78), spec, rng, "Ingredients", p.ink, p.paper)
        barcode_panel(im, sub_box(full, 0.52, 0.8, 0.96, 0.96), rng)
        recycle_mark(draw, sub_box(full, 0.06, 0.82, 0.2, 0.95), p.ink)
    else:
        title_lines(draw, sub_box(full, 0.04, 0.22, 0.6, 0.42), spec.title, spec.brand.font, p.ink)
        art_box = sub_box(full, 0.64, 0.22, 0.95, 0.55)
        text_panel(im, sub_box(full, 0.04, 0.45, 0.6, 0.97), spec, rng, "Ingredients", p.ink, p.paper)
        barcode_panel(im, sub_box(full, 0.64, 0.62, 0.96, 0.95), rng)
    paste_art(im, art_box, art_for(spec, art_box, rng))
    return im


@turned_when_tall(3.2)
def _box_left(spec: ProductSpec, w: int, h: int, rng: np.random.Generator) -> Image.Image:
    p = spec.brand.palette
    im, draw, full = face_canvas(Image.new("RGB", (w, h), mix(spec.variant, p.paper, 0.5)))
    draw.rectangle(sub_box(full, 0, 0, 1, 0.14), fill=spec.variant)
    draw_text(draw, sub_box(full, 0.05, 0.02, 0.95, 0.12), spec.title, "sans_bold", contrast_ink(spec.variant))
    if w > 1.6 * h:  # wide low side: table left, brand mark right
        nutrition_panel(im, sub_box(full, 0.04, 0.18, 0.6, 0.96), spec, rng)
        brand_row(im, sub_box(full, 0.64, 0.35, 0.97, 0.7), spec, p.main, logo_first=False)
    else:
        nutrition_panel(im, sub_box(full, 0.06, 0.18, 0.94, 0.84), spec, rng)
        brand_row(im, sub_box(full, 0.1, 0.86, 0.9, 0.97), spec, p.main)
    return im


@turned_when_tall(1.6)
def _box_right(spec: ProductSpec, w: int, h: int, rng: np.random.Generator) -> Image.Image:
    p = spec.brand.palette
    im, draw, full = face_canvas(Image.new("RGB", (w, h), p.main))
    draw.polygon([sub_box(full, 0, 0.62, 0, 0)[:2], sub_box(full, 1, 0.45, 0, 0)[:2], (w, h), (0, h)],
                 fill=spec.variant)
    brand_row(im, sub_box(full, 0.05, 0.08, 0.95, 0.42), spec, contrast_ink(p.main))
    draw_text(draw, sub_box(full, 0.06, 0.44, 0.94, 0.56), spec.brand.tagline, spec.brand.font, contrast_ink(p.main))
    art_box = sub_box(full, 0.3, 0.6, 0.7, 0.97)
    paste_art(im, art_box, drop_shadow(art_for(spec, art_box, rng), 3))
    draw_text(
        draw,
        sub_box(full, 0.72, 0.8, 0.97, 0.96),
        spec.subtitle or spec.kind,
        "sans_bold",
        contrast_ink(spec.variant),
        align="right",
    )
    return im


@turned_when_tall(1.6)
def _box_top(spec: ProductSpec, w: int, h: int, rng: np.random.Generator) -> Image.Image:
    p = spec.brand.palette
    im, draw, full = face_canvas(linear_gradient((w, h), p.main, mix(p.main, spec.variant, 0.6), angle_deg=0))
    brand_row(im, sub_box(full, 0.05, 0.08, 0.7, 0.5), spec, contrast_ink(p.main))
    draw_text(draw, sub_box(full, 0.05, 0.55, 0.7, 0.85), spec.title, "sans_bold", contrast_ink(p.main), align="left")
    # Tear-off tab: dashed outline with an arrow pointing to it (an up direction for the face).
    tab = sub_box(full, 0.74, 0.15, 0.95, 0.85)
    dash = max(int(min(w, h) * 0.04), 3)
    x = tab[0]
    while x < tab[2]:
        draw.line([(x, tab[1]), (min(x + dash, tab[2]), tab[1])], fill=p.paper, width=max(2, dash // 3))
        draw.line([(x, tab[3]), (min(x + dash, tab[2]), tab[3])], fill=p.paper, width=max(2, dash // 3))
        x += 2 * dash
    cx = (tab[0] + tab[2]) / 2
    draw.polygon(
        [
            (cx, tab[1] + (tab[3] - tab[1]) * 0.2),
            (tab[0] + 4, tab[1] + (tab[3] - tab[1]) * 0.55),
            (tab[2] - 4, tab[1] + (tab[3] - tab[1]) * 0.55),
        ],
        fill=p.paper,
    )
    draw_text(draw, sub_box(tab, 0.05, 0.62, 0.95, 0.9), "OPEN", "sans_bold", p.paper)
    return im


@turned_when_tall(1.6)
def _box_bottom(spec: ProductSpec, w: int, h: int, rng: np.random.Generator) -> Image.Image:
    p = spec.brand.palette
    im, draw, full = face_canvas(Image.new("RGB", (w, h), mix(p.paper, p.second, 0.25)))
    draw.rectangle(sub_box(full, 0, 0.0, 1, 0.08), fill=p.main)
    draw.rectangle(sub_box(full, 0, 0.82, 1, 1), fill=spec.variant)
    draw_text(
        draw, sub_box(full, 0.05, 0.84, 0.95, 0.98), spec.title, "sans_bold", contrast_ink(spec.variant), align="left"
    )
    barcode_panel(im, sub_box(full, 0.05, 0.14, 0.5, 0.78), rng)
    day, month, year = int(rng.integers(1, 28)), int(rng.integers(1, 12)), int(rng.integers(2026, 2029))
    lot = f"L{int(rng.integers(1000, 9999))}  {day:02d}.{month:02d}.{year}"
    draw_text(draw, sub_box(full, 0.55, 0.14, 0.96, 0.3), "BEST BEFORE", "sans_bold", p.ink, align="left")
    draw_text(draw, sub_box(full, 0.55, 0.34, 0.96, 0.48), lot, "mono_bold", p.ink, align="left")
    draw_text(draw, sub_box(full, 0.55, 0.54, 0.8, 0.76), spec.brand.name, spec.brand.font, p.main, align="left")
    recycle_mark(draw, sub_box(full, 0.82, 0.52, 0.96, 0.78), p.ink)
    return im


def _edge(spec: ProductSpec, w: int, h: int, rng: np.random.Generator) -> Image.Image:
    """Rim of a planar item: page block for books, plain stock otherwise (never a canonical plane)."""
    p = spec.brand.palette
    if spec.style == "book":
        arr = np.full((h, w, 3), mix(p.paper, WHITE, 0.5), np.uint8)
        arr[:: max(h // 60, 2)] = mix(p.paper, INK, 0.15)  # hint of stacked pages
        return Image.fromarray(arr)
    return Image.new("RGB", (w, h), mix(p.main, p.paper, 0.3))


def _box_front(spec: ProductSpec, w: int, h: int, rng: np.random.Generator) -> Image.Image:
    im = Image.new("RGB", (w, h), spec.brand.palette.paper)
    front_panel(im, (0.0, 0.0, float(w), float(h)), spec, rng)
    return im


_BOX: dict[str, FaceLayout] = {
    "front": _box_front,
    "back": _box_back,
    "left": _box_left,
    "right": _box_right,
    "top": _box_top,
    "bottom": _box_bottom,
    "edge": _edge,
}


def compose(spec: ProductSpec, role: str, size: tuple[int, int]) -> Image.Image:
    """The print of one face or label of ``spec`` as an RGB image of ``size`` = (W, H).

    ``role`` is one of :data:`ROLES`. Box/plate faces are viewed from outside with the product's up
    at the top; cylinder lids are square with the disc inscribed; the wrap label runs round the
    side with the front at its horizontal centre. Every channel is floored at ``INK_FLOOR`` so the
    print never reaches the 0 reserved for background.
    """
    if role not in ROLES:
        raise ValueError(f"unknown role {role!r}; valid: {ROLES}")
    w, h = int(size[0]), int(size[1])
    rng = _rng(spec, role)
    if role == "wrap":
        im = wrap_label(spec, w, h, rng)
    elif role == "lid_top":
        im = lid_top(spec, w, rng)
    elif role == "lid_bottom":
        im = lid_bottom(spec, w, rng)
    elif spec.style in PLANAR_STYLES and role in ("front", "back"):
        im = PLANAR_STYLES[spec.style][role == "back"](spec, w, h, rng)
    else:
        im = _BOX[role](spec, w, h, rng)
    if role in ("lid_top", "lid_bottom"):
        # Outside the inscribed disc the texture is never sampled; paint it flat so mipmaps at the
        # rim do not bleed stray colour in.
        flat = Image.new("RGB", im.size, im.getpixel((w // 2, int(w * 0.03))))
        flat.paste(im, (0, 0), disc_mask(w))
        im = flat
    return floor_ink(im)
