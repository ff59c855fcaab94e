"""The building blocks of the product prints (:mod:`matl.data.catalog.labels`): boxes, pictures, titles, the brand
row, and the panels a face is laid out from (front, nutrition table, small print, barcode).

Each takes the generator of the print it draws into (seeded by the product and the face), so a print stays a
pure function of ``(spec, role, size)``.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import numpy as np
from PIL import Image, ImageDraw

from matl.data.catalog.art import drop_shadow, illustration, logo
from matl.data.catalog.drawing import (
    RGB,
    WHITE,
    Box,
    barcode,
    contrast_ink,
    diagonal_stripes,
    draw_paragraph,
    draw_text,
    ean13_digits,
    fit_font,
    linear_gradient,
    mix,
)
from matl.data.catalog.products import ProductSpec

# Vocabulary of the small print (ingredients, storage advice); only its texture matters at 100 px.
_SMALL_PRINT = (
    "wheat flour sugar salt water sunflower oil cocoa butter milk powder natural flavour yeast barley "
    "malt extract honey oats rice corn starch vitamin iron calcium store in a cool dry place once "
    "opened keep refrigerated and consume within days best served with fresh fruit may contain traces "
    "of nuts soy sesame recyclable packaging please dispose of responsibly quality guaranteed"
)
_WORDS = tuple(_SMALL_PRINT.split())
_NUTRIENTS = ("Energy", "Fat", "of which saturates", "Carbohydrate", "of which sugars", "Fibre", "Protein", "Salt")


def small_print(rng: np.random.Generator, n: int) -> list[str]:
    return [str(w) for w in rng.choice(_WORDS, size=n)]


def sub_box(box: Box, fx0: float, fy0: float, fx1: float, fy1: float) -> Box:
    """Sub-box of ``box`` given by fractions of its width and height."""
    x0, y0, x1, y1 = box
    w, h = x1 - x0, y1 - y0
    return (x0 + fx0 * w, y0 + fy0 * h, x0 + fx1 * w, y0 + fy1 * h)


def int_box(box: Box) -> tuple[int, int, int, int]:
    return tuple(round(v) for v in box)  # type: ignore[return-value]


def paste_art(canvas: Image.Image, box: Box, art: Image.Image) -> None:
    """Paste RGBA ``art`` scaled to fit ``box`` (aspect kept), centred."""
    x0, y0, x1, y1 = box
    s = min((x1 - x0) / art.width, (y1 - y0) / art.height)
    w, h = max(int(art.width * s), 1), max(int(art.height * s), 1)
    art = art.resize((w, h), Image.Resampling.LANCZOS)
    canvas.paste(art, (int((x0 + x1 - w) / 2), int((y0 + y1 - h) / 2)), art)


def art_for(spec: ProductSpec, box: Box, rng: np.random.Generator, tone: tuple[RGB, RGB] | None = None) -> Image.Image:
    w, h = max(int(box[2] - box[0]), 8), max(int(box[3] - box[1]), 8)
    return illustration((w, h), spec.art, spec.variant, spec.brand.palette.second, rng, tone)


def title_lines(
    draw: ImageDraw.ImageDraw, box: Box, text: str, key: str, fill: RGB, stroke: tuple[int, RGB] | None = None
) -> None:
    """Draw ``text`` on one line or split over two, whichever allows the larger letters."""
    x0, y0, x1, y1 = box
    words = text.split()
    one = fit_font(key, text, x1 - x0, y1 - y0).size
    best: tuple[int, int] = (one, 0)
    for cut in range(1, len(words)):
        a, b = " ".join(words[:cut]), " ".join(words[cut:])
        size = min(fit_font(key, a, x1 - x0, (y1 - y0) * 0.48).size, fit_font(key, b, x1 - x0, (y1 - y0) * 0.48).size)
        if size > best[0] * 1.08:
            best = (size, cut)
    if best[1] == 0:
        draw_text(draw, box, text, key, fill, stroke=stroke)
        return
    mid = (y0 + y1) / 2
    draw_text(draw, (x0, y0, x1, mid), " ".join(words[: best[1]]), key, fill, max_size=best[0], stroke=stroke)
    draw_text(draw, (x0, mid, x1, y1), " ".join(words[best[1] :]), key, fill, max_size=best[0], stroke=stroke)


def brand_row(canvas: Image.Image, box: Box, spec: ProductSpec, text_fill: RGB, logo_first: bool = True) -> None:
    """Logo followed by the brand name, filling ``box``."""
    b = spec.brand
    x0, y0, x1, y1 = box
    h = y1 - y0
    mark = logo(max(int(h), 8), b.logo, b.palette.main, b.palette.accent, b.name[0], b.font)
    draw = ImageDraw.Draw(canvas)
    if logo_first and (x1 - x0) > 2.5 * h:
        canvas.paste(mark, (int(x0), int(y0)), mark)
        draw_text(draw, (x0 + h * 1.1, y0 + h * 0.05, x1, y1 - h * 0.05), b.name, b.font, text_fill, align="left")
    else:
        draw_text(draw, (x0, y0 + h * 0.05, x1, y1 - h * 0.05), b.name, b.font, text_fill)


def recycle_mark(draw: ImageDraw.ImageDraw, box: Box, colour: RGB) -> None:
    """Three-arrow triangle (a recycling mark), pointing up."""
    x0, y0, x1, y1 = box
    s = min(x1 - x0, y1 - y0)
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    pts = [(cx, cy - s * 0.45), (cx + s * 0.45, cy + s * 0.35), (cx - s * 0.45, cy + s * 0.35)]
    draw.polygon(pts, outline=colour, width=max(2, int(s / 10)))
    draw.polygon(
        [(cx - s * 0.12, cy - s * 0.32), (cx + s * 0.05, cy - s * 0.45), (cx + s * 0.02, cy - s * 0.22)], fill=colour
    )


# --- reusable panels -------------------------------------------------------------------------------


def front_panel(canvas: Image.Image, box: Box, spec: ProductSpec, rng: np.random.Generator) -> None:
    """Main display panel: brand, product name, picture and size, in one of three templates.

    The template is drawn from the product's seed, so products of one brand do not all share the
    same arrangement, as on a real shelf.
    """
    p = spec.brand.palette
    draw = ImageDraw.Draw(canvas)
    x0, y0, x1, y1 = box
    w, h = x1 - x0, y1 - y0
    portrait = h >= 0.75 * w
    template = int(rng.integers(3))
    if portrait:
        s_brand, s_art, s_title, s_foot = (
            (0.04, 0.02, 0.96, 0.2),
            (0.08, 0.24, 0.92, 0.66),
            (0.05, 0.68, 0.95, 0.85),
            (0.06, 0.87, 0.94, 0.97),
        )
    else:
        s_brand, s_title, s_foot, s_art = (
            (0.04, 0.06, 0.6, 0.36),
            (0.04, 0.4, 0.6, 0.74),
            (0.04, 0.78, 0.6, 0.94),
            (0.63, 0.06, 0.97, 0.94),
        )
    brand_box, art_box, title_box, foot_box = (sub_box(box, *s) for s in (s_brand, s_art, s_title, s_foot))

    if template == 0:  # light ground, solid brand band on top, title on a variant ribbon
        canvas.paste(
            linear_gradient((int(w) + 1, int(h) + 1), p.paper, mix(p.paper, spec.variant, 0.35)), int_box(box)[:2]
        )
        band = (x0, y0, x1, brand_box[3] + h * 0.01) if portrait else (x0, y0, x1, y0 + h * 0.05)
        draw.rectangle(band, fill=p.main)
        if not portrait:
            draw.rectangle((x0, y1 - h * 0.05, x1, y1), fill=p.main)
            draw.rectangle((x0, brand_box[1], brand_box[2], brand_box[3]), fill=p.main)
        draw.rectangle(title_box, fill=spec.variant)
        brand_row(canvas, brand_box, spec, contrast_ink(p.main))
        title_lines(draw, sub_box(title_box, 0.03, 0.08, 0.97, 0.92), spec.title, "sans_bold",
                    contrast_ink(spec.variant))
        foot_ink = p.ink
    elif template == 1:  # saturated ground crossed by diagonal stripes, outlined title
        draw.rectangle(box, fill=p.main)
        stripe = sub_box(box, 0, 0.55, 1, 0.9) if portrait else sub_box(box, 0, 0.0, 1, 1.0)
        layer = Image.new("RGB", canvas.size, p.main)
        diagonal_stripes(
            ImageDraw.Draw(layer),
            stripe,
            [spec.variant, p.main, mix(spec.variant, p.main, 0.5), p.main],
            max(w, h) * 0.07,
            slope=0.6,
        )
        mask = Image.new("L", canvas.size, 0)
        ImageDraw.Draw(mask).rectangle(
            sub_box(stripe, 0, 0.3, 1, 0.75) if portrait else sub_box(stripe, 0.62, 0, 1, 1), fill=255
        )
        canvas.paste(layer, (0, 0), mask)
        brand_row(canvas, brand_box, spec, contrast_ink(p.main))
        title_lines(draw, title_box, spec.title, "sans_bold", WHITE, stroke=(max(2, int(h * 0.012)), p.ink))
        foot_ink = contrast_ink(p.main)
    else:  # second-colour ground, picture in a rounded white window, side bar
        draw.rectangle(box, fill=mix(p.second, p.paper, 0.55))
        draw.rectangle((x0, y0, x0 + w * 0.035, y1), fill=p.main)
        draw.rectangle((x1 - w * 0.035, y0, x1, y1), fill=spec.variant)
        draw.rounded_rectangle(
            sub_box(art_box, -0.03, -0.03, 1.03, 1.03),
            radius=min(w, h) * 0.05,
            fill=WHITE,
            outline=p.main,
            width=max(2, int(min(w, h) * 0.012)),
        )
        brand_row(canvas, brand_box, spec, p.main)
        title_lines(draw, title_box, spec.title, spec.brand.font, p.ink)
        foot_ink = p.ink
    tone = (p.ink, mix(spec.variant, WHITE, 0.6)) if template == 1 and spec.art.startswith("photo_") else None
    art = art_for(spec, art_box, rng, tone)
    paste_art(canvas, art_box, drop_shadow(art, max(2, int(min(w, h) * 0.012))) if template != 2 else art)
    if spec.subtitle:
        draw_text(draw, sub_box(foot_box, 0.55, 0, 1, 1), spec.subtitle, "sans_bold", foot_ink, align="right")
    draw_text(draw, sub_box(foot_box, 0, 0.15, 0.52, 0.85), spec.brand.tagline, "sans", foot_ink, align="left")


def nutrition_panel(canvas: Image.Image, box: Box, spec: ProductSpec, rng: np.random.Generator) -> None:
    """White panel with a bold heading and a ruled nutrition table."""
    p = spec.brand.palette
    draw = ImageDraw.Draw(canvas)
    x0, y0, x1, y1 = box
    w, h = x1 - x0, y1 - y0
    draw.rectangle(box, fill=WHITE, outline=p.ink, width=max(2, int(min(w, h) * 0.015)))
    draw_text(draw, sub_box(box, 0.06, 0.02, 0.94, 0.16), "Nutrition Facts", "sans_bold", p.ink, align="left")
    draw.rectangle(sub_box(box, 0.06, 0.17, 0.94, 0.19), fill=p.ink)
    rows = len(_NUTRIENTS)
    row_h = 0.7 / rows
    for k, name in enumerate(_NUTRIENTS):
        top = 0.21 + k * row_h
        value = f"{rng.uniform(0.1, 60):.1f} g" if k else f"{int(rng.integers(300, 2000))} kJ"
        key = "sans_bold" if not name.startswith("of") else "sans"
        draw_text(
            draw,
            sub_box(box, 0.08 if key == "sans_bold" else 0.16, top, 0.66, top + row_h * 0.8),
            name,
            key,
            p.ink,
            align="left",
        )
        draw_text(draw, sub_box(box, 0.68, top, 0.94, top + row_h * 0.8), value, "sans", p.ink, align="right")
        draw.line(
            [sub_box(box, 0.06, top + row_h * 0.92, 0.94, 0)[:2], sub_box(box, 0.94, top + row_h * 0.92, 0, 0)[:2]],
            fill=mix(p.ink, WHITE, 0.5),
            width=1,
        )


def text_panel(
    canvas: Image.Image, box: Box, spec: ProductSpec, rng: np.random.Generator, heading: str, fill: RGB, ground: RGB
) -> None:
    """Heading plus a paragraph of small print on ``ground``."""
    draw = ImageDraw.Draw(canvas)
    x0, y0, x1, y1 = box
    draw.rectangle(box, fill=ground)
    draw_text(draw, sub_box(box, 0.05, 0.03, 0.95, 0.17), heading, "sans_bold", fill, align="left")
    size = max(int(min(x1 - x0, (y1 - y0) * 1.2) * 0.06), 7)
    draw_paragraph(draw, sub_box(box, 0.05, 0.22, 0.95, 0.97), small_print(rng, 120), "sans", size, fill)


def barcode_panel(canvas: Image.Image, box: Box, rng: np.random.Generator) -> None:
    """EAN-13 on a white ground (the quiet zone is part of the symbol)."""
    x0, y0, x1, y1 = box
    code = barcode((max(int(x1 - x0), 40), max(int(y1 - y0), 20)), ean13_digits(rng))
    canvas.paste(code, (int(x0), int(y0)))


# --- face layouts ------------------------------------------------------------------------------------


def face_canvas(im: Image.Image) -> tuple[Image.Image, ImageDraw.ImageDraw, Box]:
    """A face layout's ground ``im`` with its draw handle and its full box (0, 0, W, H)."""
    return im, ImageDraw.Draw(im), (0.0, 0.0, float(im.width), float(im.height))


FaceLayout = Callable[[ProductSpec, int, int, np.random.Generator], Image.Image]


def turned_when_tall(ratio: float) -> Callable[[FaceLayout], FaceLayout]:
    """Lay a face out on a landscape canvas and turn it when it is more than ``ratio`` times taller
    than wide, so its text runs up the face as on the spine of a real box."""

    def decorate(layout: FaceLayout) -> FaceLayout:
        @functools.wraps(layout)
        def face(spec: ProductSpec, w: int, h: int, rng: np.random.Generator) -> Image.Image:
            if h > ratio * w:
                return layout(spec, h, w, rng).transpose(Image.Transpose.ROTATE_90)
            return layout(spec, w, h, rng)

        return face

    return decorate


