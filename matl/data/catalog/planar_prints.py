"""The fronts and backs of planar products (books, cards, envelopes, notebooks, magazines), one style each
(:data:`PLANAR_STYLES`); :func:`matl.data.catalog.labels.compose` draws a planar product's two faces with them.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from PIL import Image, ImageDraw

from matl.data.catalog.art import drop_shadow, illustration, logo
from matl.data.catalog.drawing import (
    INK,
    WHITE,
    contrast_ink,
    diagonal_stripes,
    draw_paragraph,
    draw_text,
    linear_gradient,
    mix,
)
from matl.data.catalog.panels import (
    art_for,
    barcode_panel,
    brand_row,
    face_canvas,
    int_box,
    paste_art,
    small_print,
    sub_box,
    title_lines,
)
from matl.data.catalog.products import ProductSpec


def _book_front(spec: ProductSpec, w: int, h: int, rng: np.random.Generator) -> Image.Image:
    p = spec.brand.palette
    im, draw, full = face_canvas(linear_gradient((w, h), spec.variant, mix(spec.variant, p.ink, 0.55), angle_deg=100))
    title_lines(draw, sub_box(full, 0.07, 0.05, 0.93, 0.3), spec.title, "serif_bold", WHITE)
    draw.rectangle(sub_box(full, 0.3, 0.315, 0.7, 0.325), fill=mix(WHITE, spec.variant, 0.3))
    art_box = sub_box(full, 0.1, 0.36, 0.9, 0.8)
    if spec.art.startswith("photo_"):
        draw.rectangle(sub_box(art_box, -0.02, -0.02, 1.02, 1.02), fill=WHITE)
    paste_art(im, art_box, art_for(spec, art_box, rng))
    draw_text(draw, sub_box(full, 0.1, 0.82, 0.9, 0.9), spec.subtitle, "serif_bold_italic", WHITE)
    brand_row(im, sub_box(full, 0.3, 0.91, 0.7, 0.98), spec, mix(WHITE, spec.variant, 0.2))
    return im


def _book_back(spec: ProductSpec, w: int, h: int, rng: np.random.Generator) -> Image.Image:
    p = spec.brand.palette
    dark = mix(spec.variant, p.ink, 0.55)
    im, draw, full = face_canvas(Image.new("RGB", (w, h), dark))
    draw_text(draw, sub_box(full, 0.08, 0.04, 0.92, 0.14), f"\u201c{spec.title}\u201d", "serif_bold_italic", WHITE)
    draw.rectangle(sub_box(full, 0.08, 0.17, 0.92, 0.62), fill=mix(dark, WHITE, 0.85))
    draw_paragraph(draw, sub_box(full, 0.11, 0.19, 0.89, 0.6), small_print(rng, 140), "serif", max(int(w * 0.04), 7),
                   p.ink)
    draw_text(draw, sub_box(full, 0.08, 0.66, 0.6, 0.74), f"by {spec.subtitle}", "serif_bold", WHITE, align="left")
    brand_row(im, sub_box(full, 0.08, 0.8, 0.45, 0.9), spec, WHITE)
    barcode_panel(im, sub_box(full, 0.52, 0.76, 0.94, 0.95), rng)
    draw_text(draw, sub_box(full, 0.62, 0.66, 0.92, 0.73), f"${rng.uniform(9, 30):.2f}", "sans_bold", WHITE,
              align="right")
    return im


def _card_front(spec: ProductSpec, w: int, h: int, rng: np.random.Generator) -> Image.Image:
    p = spec.brand.palette
    im, draw, full = face_canvas(Image.new("RGB", (w, h), mix(spec.variant, WHITE, 0.75)))
    art_box = sub_box(full, 0.52, 0.08, 0.96, 0.92)
    paste_art(im, art_box, art_for(spec, art_box, rng))
    draw.rectangle(sub_box(full, 0, 0.58, 0.56, 0.86), fill=spec.variant)
    title_lines(
        draw, sub_box(full, 0.04, 0.12, 0.52, 0.56), spec.title, "stix_bold_italic", mix(spec.variant, p.ink, 0.6)
    )
    draw_text(draw, sub_box(full, 0.04, 0.62, 0.52, 0.82), spec.brand.name, spec.brand.font, contrast_ink(spec.variant))
    for k in range(3):  # scattered confetti dots
        r = min(w, h) * 0.03
        x, y = rng.uniform(0.05, 0.45) * w, rng.uniform(0.88, 0.96) * h
        draw.ellipse((x - r, y - r, x + r, y + r), fill=(p.main, p.accent, p.second)[k])
    return im


def _card_back(spec: ProductSpec, w: int, h: int, rng: np.random.Generator) -> Image.Image:
    p = spec.brand.palette
    im, draw, full = face_canvas(Image.new("RGB", (w, h), mix(WHITE, spec.variant, 0.12)))
    draw.line([sub_box(full, 0.55, 0.1, 0, 0)[:2], sub_box(full, 0.55, 0.9, 0, 0)[:2]], fill=p.ink,
              width=max(2, w // 200))
    stamp = sub_box(full, 0.8, 0.07, 0.95, 0.35)
    draw.rectangle(stamp, outline=spec.variant, width=max(2, w // 150))
    draw_text(draw, sub_box(stamp, 0.1, 0.2, 0.9, 0.8), "STAMP", "sans_bold", spec.variant)
    for k in range(4):
        y = h * (0.5 + 0.1 * k)
        draw.line([(w * 0.6, y), (w * 0.95, y)], fill=mix(p.ink, WHITE, 0.4), width=max(1, w // 300))
    draw_paragraph(draw, sub_box(full, 0.05, 0.08, 0.5, 0.5), small_print(rng, 40), "stix_italic",
                   max(int(h * 0.05), 8), p.ink)
    draw.rectangle(sub_box(full, 0.0, 0.56, 0.5, 0.72), fill=spec.variant)
    draw_text(draw, sub_box(full, 0.04, 0.58, 0.48, 0.7), spec.title, "stix_bold_italic", contrast_ink(spec.variant))
    brand_row(im, sub_box(full, 0.05, 0.76, 0.3, 0.9), spec, p.main)
    barcode_panel(im, sub_box(full, 0.32, 0.76, 0.52, 0.94), rng)
    return im


def _envelope_front(spec: ProductSpec, w: int, h: int, rng: np.random.Generator) -> Image.Image:
    p = spec.brand.palette
    kraft = mix((226, 200, 160), p.paper, 0.3)
    im, draw, full = face_canvas(Image.new("RGB", (w, h), kraft))
    # Stamp: photo patch inside a white perforated frame, top right.
    stamp = sub_box(full, 0.8, 0.06, 0.95, 0.46)
    sx0, sy0, sx1, sy1 = stamp
    draw.rectangle(stamp, fill=WHITE)
    r = (sx1 - sx0) * 0.04
    for t in np.linspace(0, 1, 9):
        for cx_, cy_ in (
            (sx0 + t * (sx1 - sx0), sy0),
            (sx0 + t * (sx1 - sx0), sy1),
            (sx0, sy0 + t * (sy1 - sy0)),
            (sx1, sy0 + t * (sy1 - sy0)),
        ):
            draw.ellipse((cx_ - r, cy_ - r, cx_ + r, cy_ + r), fill=kraft)
    inner = sub_box(stamp, 0.1, 0.08, 0.9, 0.78)
    paste_art(im, inner, art_for(spec, inner, rng, tone=None))
    draw_text(draw, sub_box(stamp, 0.1, 0.8, 0.9, 0.95), f"{int(rng.integers(1, 9)) * 10}c", "sans_bold", spec.variant)
    for k in range(4):  # postmark waves over the stamp's left edge
        y0 = sy0 + (sy1 - sy0) * (0.25 + 0.12 * k)
        pts = [(sx0 - w * 0.15 + t * w * 0.2, y0 + math.sin(t * 12) * h * 0.01) for t in np.linspace(0, 1, 30)]
        draw.line(pts, fill=mix(p.ink, kraft, 0.3), width=max(2, w // 300))
    brand_row(im, sub_box(full, 0.04, 0.06, 0.4, 0.2), spec, p.ink)
    draw_paragraph(draw, sub_box(full, 0.04, 0.22, 0.4, 0.4), small_print(rng, 12), "sans", max(int(h * 0.04), 7),
                   p.ink)
    draw_paragraph(draw, sub_box(full, 0.45, 0.55, 0.9, 0.85), small_print(rng, 18), "mono_bold",
                   max(int(h * 0.06), 8), p.ink)
    draw.rectangle(sub_box(full, 0.04, 0.62, 0.4, 0.82), fill=spec.variant)
    draw_text(draw, sub_box(full, 0.06, 0.64, 0.38, 0.8), spec.title.upper(), "sans_bold", contrast_ink(spec.variant))
    return im


def _envelope_back(spec: ProductSpec, w: int, h: int, rng: np.random.Generator) -> Image.Image:
    p = spec.brand.palette
    kraft = mix((226, 200, 160), p.paper, 0.3)
    im = Image.new("RGB", (w, h), kraft)
    draw = ImageDraw.Draw(im)
    shade = mix(kraft, p.ink, 0.25)
    # Flap printed with a security tint in the product's colour, as mailers are.
    flap = [(0, 0), (w, 0), (w * 0.5, h * 0.62)]
    tint = Image.new("RGB", (w, h), mix(kraft, WHITE, 0.15))
    diagonal_stripes(
        ImageDraw.Draw(tint),
        (0, 0, w, h),
        [mix(kraft, spec.variant, 0.6), mix(kraft, WHITE, 0.15)],
        w * 0.02,
        slope=-1.0,
    )
    mask = Image.new("L", (w, h), 0)
    ImageDraw.Draw(mask).polygon(flap, fill=255)
    im.paste(tint, (0, 0), mask)
    draw.polygon(flap, outline=shade)
    draw.line([(0, h), (w * 0.42, h * 0.5)], fill=shade, width=max(2, w // 250))
    draw.line([(w, h), (w * 0.58, h * 0.5)], fill=shade, width=max(2, w // 250))
    seal = int(h * 0.3)
    mark = logo(seal, spec.brand.logo, spec.variant, spec.brand.palette.main, spec.brand.name[0], spec.brand.font)
    im.paste(mark, (int(w * 0.5 - seal / 2), int(h * 0.5 - seal / 2)), mark)
    draw_text(
        draw,
        (w * 0.06, h * 0.78, w * 0.7, h * 0.95),
        f"{spec.brand.name} \u2022 {spec.title}",
        "sans_bold",
        p.ink,
        align="left",
    )
    return im


def _notebook_front(spec: ProductSpec, w: int, h: int, rng: np.random.Generator) -> Image.Image:
    p = spec.brand.palette
    im, draw, full = face_canvas(Image.new("RGB", (w, h), p.main))
    diagonal_stripes(draw, sub_box(full, 0, 0.0, 1, 0.08), [p.main, mix(p.main, WHITE, 0.15)], w * 0.03)
    draw.rectangle(sub_box(full, 0.86, 0, 0.92, 1), fill=spec.variant)  # elastic band
    label = sub_box(full, 0.12, 0.18, 0.78, 0.48)
    draw.rounded_rectangle(label, radius=w * 0.03, fill=p.paper, outline=spec.variant, width=max(3, w // 80))
    title_lines(draw, sub_box(label, 0.06, 0.08, 0.94, 0.62), spec.title, "sans_bold", p.ink)
    for k in range(2):
        y = label[1] + (label[3] - label[1]) * (0.72 + 0.14 * k)
        draw.line([(label[0] + w * 0.04, y), (label[2] - w * 0.04, y)], fill=mix(p.ink, WHITE, 0.5), width=2)
    art_box = sub_box(full, 0.2, 0.55, 0.7, 0.82)
    paste_art(im, art_box, art_for(spec, art_box, rng))
    brand_row(im, sub_box(full, 0.12, 0.86, 0.8, 0.96), spec, contrast_ink(p.main))
    return im


def _notebook_back(spec: ProductSpec, w: int, h: int, rng: np.random.Generator) -> Image.Image:
    p = spec.brand.palette
    im, draw, full = face_canvas(Image.new("RGB", (w, h), mix(p.main, INK, 0.15)))
    step = w / 14
    grid = mix(p.main, WHITE, 0.25)
    for k in range(1, 14):
        draw.line([(k * step, 0), (k * step, h * 0.6)], fill=grid, width=1)
    for k in range(1, int(h * 0.6 / step)):
        draw.line([(0, k * step), (w, k * step)], fill=grid, width=1)
    draw.rectangle(sub_box(full, 0.08, 0.02, 0.08 + 0.04, 0.6), fill=spec.variant)
    draw.rectangle(sub_box(full, 0.0, 0.62, 1.0, 0.75), fill=spec.variant)
    draw_text(
        draw,
        sub_box(full, 0.06, 0.63, 0.94, 0.74),
        f"{spec.title} \u2022 {int(rng.integers(4, 12)) * 16} pages",
        "sans_bold",
        contrast_ink(spec.variant),
        align="left",
    )
    barcode_panel(im, sub_box(full, 0.5, 0.78, 0.94, 0.95), rng)
    brand_row(im, sub_box(full, 0.08, 0.8, 0.45, 0.9), spec, WHITE)
    return im


def _magazine_front(spec: ProductSpec, w: int, h: int, rng: np.random.Generator) -> Image.Image:
    p = spec.brand.palette
    im, draw, full = face_canvas(Image.new("RGB", (w, h), mix(spec.variant, WHITE, 0.7)))
    art_box = sub_box(full, 0.0, 0.2, 1.0, 1.0)
    art = art_for(spec, art_box, rng)
    im.paste(art, int_box(art_box)[:2], art)
    draw.rectangle(sub_box(full, 0, 0, 1, 0.2), fill=p.main)
    draw_text(draw, sub_box(full, 0.03, 0.01, 0.97, 0.19), spec.title, "serif_bold", contrast_ink(p.main))
    for k in range(3):
        box = sub_box(full, 0.04, 0.3 + 0.12 * k, 0.5, 0.38 + 0.12 * k)
        draw.rectangle(box, fill=(spec.variant, p.accent, WHITE)[k])
        draw_text(
            draw, sub_box(box, 0.04, 0.1, 0.96, 0.9), " ".join(small_print(rng, 2)).upper(), "sans_bold", INK,
            align="left"
        )
    draw.rectangle(sub_box(full, 0.04, 0.86, 0.42, 0.96), fill=WHITE)
    draw_text(
        draw, sub_box(full, 0.06, 0.87, 0.4,
                      0.95), f"{spec.brand.name} No.{int(rng.integers(1, 52))}", "sans_bold", p.ink
    )
    return im


def _magazine_back(spec: ProductSpec, w: int, h: int, rng: np.random.Generator) -> Image.Image:
    p = spec.brand.palette
    im, draw, full = face_canvas(linear_gradient((w, h), p.second, p.main, angle_deg=80))
    title_lines(
        draw, sub_box(full, 0.06, 0.05, 0.94, 0.25), spec.brand.tagline, spec.brand.font, WHITE, stroke=(2, p.ink)
    )
    art_box = sub_box(full, 0.15, 0.3, 0.85, 0.72)
    paste_art(
        im,
        art_box,
        drop_shadow(
            illustration(
                (int(w * 0.7), int(h * 0.42)), "fruit" if spec.art != "fruit" else "cup", spec.variant, p.accent, rng
            ),
            4,
        ),
    )
    brand_row(im, sub_box(full, 0.2, 0.76, 0.8, 0.86), spec, WHITE)
    barcode_panel(im, sub_box(full, 0.62, 0.88, 0.96, 0.98), rng)
    return im


PLANAR_STYLES: dict[str, tuple[Callable[..., Image.Image], Callable[..., Image.Image]]] = {
    "book": (_book_front, _book_back),
    "card": (_card_front, _card_back),
    "envelope": (_envelope_front, _envelope_back),
    "notebook": (_notebook_front, _notebook_back),
    "magazine": (_magazine_front, _magazine_back),
}


