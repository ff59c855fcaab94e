"""The prints of cylinders (cans, tubes, jars): the label wrapped round the side and the top and bottom lids, for
:func:`matl.data.catalog.labels.compose`.
"""

from __future__ import annotations

import math

import numpy as np
from PIL import Image, ImageDraw

from matl.data.catalog.art import logo
from matl.data.catalog.drawing import (
    INK,
    WHITE,
    contrast_ink,
    draw_text,
    mix,
    radial_gradient,
    text_on_circle,
)
from matl.data.catalog.panels import (
    art_for,
    barcode_panel,
    brand_row,
    front_panel,
    nutrition_panel,
    paste_art,
    recycle_mark,
    sub_box,
    text_panel,
)
from matl.data.catalog.products import ProductSpec


def wrap_label(spec: ProductSpec, w: int, h: int, rng: np.random.Generator) -> Image.Image:
    """Label wrapped round a cylinder; u = 0.5 faces the front view (side_000), the seam is at the back.

    Panels around the circumference differ (barcode, nutrition, front, story, brand spine) so the
    eight side views see different prints.
    """
    p = spec.brand.palette
    glass = spec.style == "jar"
    full = (0.0, 0.0, float(w), float(h))
    im = Image.new("RGB", (w, h), p.paper)
    draw = ImageDraw.Draw(im)
    if glass:  # contents seen through the glass above and below the paper label
        contents = mix(spec.variant, INK, 0.35)
        draw.rectangle(full, fill=contents)
        for _ in range(40):
            x, y, r = rng.uniform(0, w), rng.uniform(0, h), h * rng.uniform(0.01, 0.03)
            draw.ellipse((x - r, y - r, x + r, y + r), fill=mix(contents, WHITE, rng.uniform(0.05, 0.2)))
        label = sub_box(full, 0, 0.18, 1, 0.86)
    else:
        label = full
    draw.rectangle(label, fill=p.paper)
    band_h = 0.1
    draw.rectangle(sub_box(label, 0, 0, 1, band_h), fill=p.main)
    draw.rectangle(sub_box(label, 0, 1 - band_h, 1, 1), fill=p.main)
    draw.rectangle(sub_box(label, 0, band_h, 1, band_h + 0.025), fill=spec.variant)
    inner = sub_box(label, 0, band_h + 0.04, 1, 1 - band_h - 0.02)
    front_panel(im, sub_box(inner, 0.34, -0.04, 0.66, 1.0), spec, rng)
    # Half the products carry the panels round the other way, so side views of two products
    # do not line up panel for panel.
    mirrored = bool(rng.integers(2))

    def span(a: float, b: float) -> tuple[float, float]:
        return (1 - b, 1 - a) if mirrored else (a, b)

    nx0, nx1 = span(0.14, 0.31)
    nutrition_panel(im, sub_box(inner, nx0, 0.04, nx1, 0.96), spec, rng)
    sx0, sx1 = span(0.69, 0.86)
    text_panel(im, sub_box(inner, sx0, 0.02, sx1, 0.62), spec, rng, "Our story", p.ink,
               mix(p.paper, spec.variant, 0.15))
    art_box = sub_box(inner, sx0 + 0.01, 0.66, sx1 - 0.01, 0.98)
    paste_art(im, art_box, art_for(spec, art_box, rng))
    bx0, bx1 = span(0.885, 0.99)
    barcode_panel(im, sub_box(inner, bx0, 0.45, bx1, 0.95), rng)
    # Brand spine: composed lying down, turned to run up the label.
    spine = _spine(spec, int(inner[3] - inner[1]), int(w * 0.1)).transpose(Image.Transpose.ROTATE_90)
    im.paste(spine, (int(w * span(0.015, 0.115)[0]), int(inner[1])))
    brand_row(im, sub_box(label, 0.2, 0.0, 0.45, band_h), spec, contrast_ink(p.main), logo_first=False)
    brand_row(im, sub_box(label, 0.55, 1 - band_h, 0.8, 1.0), spec, contrast_ink(p.main), logo_first=False)
    return im


def _spine(spec: ProductSpec, w: int, h: int) -> Image.Image:
    p = spec.brand.palette
    im = Image.new("RGB", (w, h), spec.variant)
    draw = ImageDraw.Draw(im)
    draw_text(
        draw,
        (w * 0.04, h * 0.1, w * 0.96, h * 0.9),
        f"{spec.brand.name} {spec.title}",
        spec.brand.font,
        contrast_ink(spec.variant),
    )
    draw.rectangle((0, 0, w, h * 0.06), fill=p.main)
    return im


def lid_top(spec: ProductSpec, s: int, rng: np.random.Generator) -> Image.Image:
    """Top lid (square texture, the disc inscribed): metal with a pull tab for cans, a printed
    plastic cap for tubes and jars. Tint, pattern and print vary per product so two lids of one
    brand still differ."""
    p = spec.brand.palette
    c = s / 2
    if spec.style == "can":
        silver = (200, 200, 206)
        metal = (silver, (214, 186, 120), mix(silver, p.main, 0.35), mix(silver, spec.variant, 0.35))[
            int(rng.integers(4))
        ]
        im = radial_gradient(s, mix(metal, WHITE, 0.4), mix(metal, INK, 0.2), centre=(0.35, 0.3))
        draw = ImageDraw.Draw(im)
        # Printed lacquer ring in the brand colour carrying brand and product name, edged in the
        # variant colour: two brands' "Tuna Chunks" lids must not look alike.
        draw.ellipse((c - s * 0.43, c - s * 0.43, c + s * 0.43, c + s * 0.43), fill=spec.variant)
        draw.ellipse((c - s * 0.4, c - s * 0.4, c + s * 0.4, c + s * 0.4), fill=p.main)
        draw.ellipse((c - s * 0.3, c - s * 0.3, c + s * 0.3, c + s * 0.3), fill=mix(metal, WHITE, 0.2))
        ring_text = f"{spec.brand.name} \u2022 {spec.title.upper()} \u2022 "
        text_on_circle(
            im, (c, c), s * 0.33, ring_text, "sans_bold", int(s * 0.065), contrast_ink(p.main), start_deg=-200
        )
        for r, col in ((0.48, mix(metal, INK, 0.35)), (0.45, mix(metal, WHITE, 0.3))):
            draw.ellipse((c - s * r, c - s * r, c + s * r, c + s * r), outline=col, width=max(2, s // 90))
        # Pull tab towards the bottom of the view, its finger hole below the rivet.
        draw.rounded_rectangle(
            (c - s * 0.1, c + s * 0.02, c + s * 0.1, c + s * 0.29),
            radius=s * 0.05,
            fill=mix(metal, WHITE, 0.5),
            outline=mix(metal, INK, 0.4),
            width=max(2, s // 120),
        )
        draw.ellipse((c - s * 0.06, c + s * 0.13, c + s * 0.06, c + s * 0.25), fill=mix(metal, INK, 0.45))
        draw.ellipse((c - s * 0.03, c - s * 0.01, c + s * 0.03, c + s * 0.05), fill=mix(metal, INK, 0.3))
        weight_ink = mix(spec.variant, INK, 0.3)
        draw_text(
            draw,
            (c - s * 0.22, c - s * 0.25, c + s * 0.22, c - s * 0.07),
            spec.subtitle or "OPEN",
            "sans_bold",
            weight_ink,
        )
        return im
    options = (p.main, spec.variant, p.second, mix(p.main, spec.variant, 0.5))
    cap = options[int(rng.integers(len(options)))]
    trim = spec.variant if cap != spec.variant else p.main
    im = radial_gradient(s, mix(cap, WHITE, 0.25), mix(cap, INK, 0.2), centre=(0.4, 0.35))
    draw = ImageDraw.Draw(im)
    pattern = int(rng.integers(3))
    if pattern == 0:  # sunburst of alternating wedges
        for k in range(0, 24, 2):
            draw.pieslice((0, 0, s - 1, s - 1), k * 15, k * 15 + 15, fill=mix(cap, WHITE, 0.18))
    elif pattern == 1:  # band across the lower part of the cap
        band = Image.new("RGB", (s, s), trim)
        mask = Image.new("L", (s, s), 0)
        ImageDraw.Draw(mask).rectangle((0, s * 0.68, s, s * 0.84), fill=255)
        im.paste(band, (0, 0), mask)
    else:  # dotted ring
        for k in range(20):
            a = math.radians(k * 18)
            x, y, r = c + s * 0.42 * math.cos(a), c + s * 0.42 * math.sin(a), s * 0.025
            draw.ellipse((x - r, y - r, x + r, y + r), fill=trim)
    draw.ellipse((s * 0.02, s * 0.02, s * 0.98, s * 0.98), outline=mix(cap, INK, 0.35), width=max(3, s // 50))
    if spec.style == "jar":
        draw.ellipse(
            (c - s * 0.36, c - s * 0.36, c + s * 0.36, c + s * 0.36), fill=p.paper, outline=trim, width=max(3, s // 60)
        )
        text_on_circle(
            im,
            (c, c),
            s * 0.285,
            f"{spec.title.upper()} \u2022 {spec.brand.tagline.upper()} \u2022 ",
            "sans_bold",
            int(s * 0.05),
            p.ink,
            start_deg=-180,
        )
        txt_fill = p.ink
    else:
        txt_fill = contrast_ink(cap)
    mark_s = int(s * 0.26)
    mark = logo(mark_s, spec.brand.logo, trim, p.accent, spec.brand.name[0], spec.brand.font)
    im.paste(mark, (int(c - mark_s / 2), int(c - s * 0.3)), mark)
    brand_box = (c - s * 0.24, c - s * 0.03, c + s * 0.24, c + s * 0.08)
    draw_text(draw, brand_box, spec.brand.name, spec.brand.font, txt_fill)
    # Product name on a ribbon across the cap, the part that tells one product's cap from the next.
    ribbon = (c - s * 0.4, c + s * 0.11, c + s * 0.4, c + s * 0.27)
    draw.rectangle(ribbon, fill=trim)
    draw_text(draw, sub_box(ribbon, 0.04, 0.1, 0.96, 0.9), spec.title, "sans_bold", contrast_ink(trim))
    return im


def lid_bottom(spec: ProductSpec, s: int, rng: np.random.Generator) -> Image.Image:
    """Bottom (square texture, disc inscribed). Cans: metal with dot-matrix codes and a printed
    ring. Tubes (cardboard) and jars (glass over a paper sticker): a big barcode, which is also
    what tells two otherwise similar bases apart."""
    p = spec.brand.palette
    c = s / 2
    if spec.style == "can":
        base = mix((180, 180, 186), (p.second, spec.variant, p.main)[int(rng.integers(3))], 0.3)
        im = radial_gradient(s, mix(base, WHITE, 0.3), mix(base, INK, 0.15), centre=(0.4, 0.35))
        ring = mix(base, INK, 0.35)
    elif spec.style == "tube":
        # Cardboard, tin or a plastic base in the brand colour.
        options = (mix((196, 170, 130), p.paper, float(rng.uniform(0, 0.5))), (188, 190, 196), p.main)
        base = options[int(rng.integers(len(options)))]
        im = radial_gradient(s, mix(base, WHITE, 0.15), mix(base, INK, 0.1), centre=(0.4, 0.35))
        ring = mix(base, INK, 0.3)
    else:
        base = mix(spec.variant, INK, 0.35)
        im = radial_gradient(s, mix(base, WHITE, 0.15), base)
        ring = mix(base, WHITE, 0.35)
    draw = ImageDraw.Draw(im)
    draw.ellipse((c - s * 0.47, c - s * 0.47, c + s * 0.47, c + s * 0.47), outline=ring, width=max(2, s // 100))
    ink = contrast_ink(base)
    text_on_circle(
        im,
        (c, c),
        s * 0.4,
        f"{spec.brand.name.upper()} \u2022 {spec.kind.upper()} \u2022 RECYCLE ME \u2022 ",
        "sans_bold",
        int(s * 0.045),
        ink,
        start_deg=-160,
    )
    lot = f"L{int(rng.integers(1000, 9999))} {int(rng.integers(1, 12)):02d}/{int(rng.integers(2026, 2029))}"
    if spec.style == "can":
        draw.ellipse(
            (c - s * 0.34, c - s * 0.34, c + s * 0.34, c + s * 0.34), outline=spec.variant, width=max(4, s // 30)
        )
        draw_text(draw, (c - s * 0.24, c - s * 0.24, c + s * 0.24, c - s * 0.14), "BEST BEFORE", "mono_bold", ink)
        draw_text(draw, (c - s * 0.26, c - s * 0.12, c + s * 0.26, c - s * 0.02), lot, "mono_bold", ink)
        mark_s = int(s * 0.2)
        mark = logo(mark_s, spec.brand.logo, spec.variant, p.main, spec.brand.name[0], spec.brand.font)
        im.paste(mark, (int(c - mark_s * 0.9), int(c + s * 0.04)), mark)
        recycle_mark(draw, (c + s * 0.06, c + s * 0.06, c + s * 0.22, c + s * 0.22), ink)
        return im
    # Printed ring in the product's colour, then a sticker in the brand colour round a white
    # barcode field, with the product name under it.
    draw.ellipse((c - s * 0.35, c - s * 0.35, c + s * 0.35, c + s * 0.35), outline=spec.variant, width=max(4, s // 22))
    sticker = (c - s * 0.33, c - s * 0.26, c + s * 0.33, c + s * 0.2)
    draw.rectangle(sticker, fill=p.main, outline=spec.variant, width=max(3, s // 60))
    draw_text(draw, sub_box(sticker, 0.06, 0.04, 0.94, 0.22), f"{lot}  {spec.subtitle}", "mono_bold",
              contrast_ink(p.main))
    barcode_panel(im, sub_box(sticker, 0.08, 0.26, 0.92, 0.94), rng)
    draw_text(draw, (c - s * 0.26, c + s * 0.22, c + s * 0.26, c + s * 0.3), spec.title, "sans_bold", ink)
    return im


