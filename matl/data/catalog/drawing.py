"""Drawing primitives for procedural product prints.

Everything here draws with PIL on RGB/RGBA canvases and takes its randomness from an explicit
``numpy.random.Generator`` so a print is a pure function of its seed. The only external assets
are fonts and sample photos that ship inside matplotlib (see ``docs/datasets.md`` for their
licences); nothing is downloaded. The held-out benchmark's photos (:data:`HELDOUT_PHOTO_FILES`,
:data:`HELDOUT_BACKGROUND_FILES`) ship inside scikit-image's wheel instead and are never trained on.
"""

from __future__ import annotations

import functools
import importlib.util
import math
from collections.abc import Sequence
from pathlib import Path

import matplotlib
import numpy as np
from PIL import Image, ImageDraw, ImageFont

from matl.utils.errors import MatlError

RGB = tuple[int, int, int]
Box = tuple[float, float, float, float]  # (left, top, right, bottom) in canvas pixels

_MPL_DATA = Path(matplotlib.get_data_path())
FONT_DIR = _MPL_DATA / "fonts" / "ttf"
PHOTO_DIR = _MPL_DATA / "sample_data"

# Only DejaVu (Bitstream Vera licence) and STIX (SIL OFL) faces; the cm*.ttf BaKoMa fonts carry a
# licence we do not want to depend on, so they are deliberately absent.
FONT_FILES: dict[str, str] = {
    "sans": "DejaVuSans.ttf",
    "sans_bold": "DejaVuSans-Bold.ttf",
    "sans_bold_oblique": "DejaVuSans-BoldOblique.ttf",
    "serif": "DejaVuSerif.ttf",
    "serif_bold": "DejaVuSerif-Bold.ttf",
    "serif_bold_italic": "DejaVuSerif-BoldItalic.ttf",
    "mono": "DejaVuSansMono.ttf",
    "mono_bold": "DejaVuSansMono-Bold.ttf",
    "stix_bold": "STIXGeneralBol.ttf",
    "stix_bold_italic": "STIXGeneralBolIta.ttf",
    "stix_italic": "STIXGeneralItalic.ttf",
}

# Photos shipped in matplotlib's sample_data. logo2.png is left out on purpose: it is the
# Matplotlib logo, and printing a project's mark on fake products is trademark use.
PHOTO_FILES: dict[str, str] = {
    "hopper": "grace_hopper.jpg",
    "present": "Minduka_Present_Blue_Pack.png",
}

# Benchmark (held-out) photos: images bundled in scikit-image's wheel (skimage/data, no download),
# each dedicated to the public domain or CC0 by its source (docs/datasets.md lists them). The training
# catalogs never print them: SyntheticCatalog(photos="skimage") does, and matl.train refuses that.
# Colour photos for the products' art ...
HELDOUT_PHOTO_FILES: dict[str, str] = {
    "astronaut": "astronaut.png",
    "chelsea": "chelsea.png",
    "coffee": "coffee.png",
    "rocket": "rocket.jpg",
}
# The catalogue benchmark's products (matl.data.catalog.lookalikes) print these and two more colour photos of the
# same package (both "no known copyright restrictions" / CC0 by their sources), never trained on either.
CATALOG_PHOTO_FILES: dict[str, str] = {**HELDOUT_PHOTO_FILES, "ihc": "ihc.png", "retina": "retina.jpg"}
# ... and other photos of the same package, only ever used as the real backgrounds of benchmark queries.
HELDOUT_BACKGROUND_FILES: dict[str, str] = {
    "brick": "brick.png",
    "grass": "grass.png",
    "gravel": "gravel.png",
    "camera": "camera.png",
    "hubble": "hubble_deep_field.jpg",
}
# data.source.photos of SyntheticCatalog: the pool its product art comes from.
PHOTO_POOLS: dict[str, dict[str, str]] = {"matplotlib": PHOTO_FILES, "skimage": HELDOUT_PHOTO_FILES}
TRAINING_PHOTO_POOL = "matplotlib"


def heldout_photo_dir() -> Path:
    """The folder of scikit-image's bundled sample images (``skimage/data``), found without importing skimage."""
    spec = importlib.util.find_spec("skimage")
    if spec is None or not spec.submodule_search_locations:
        raise MatlError("the held-out benchmark photos come from scikit-image: pip install 'scikit-image>=0.22'")
    return Path(next(iter(spec.submodule_search_locations))) / "data"


def heldout_image(name: str) -> Image.Image:
    """One of :data:`CATALOG_PHOTO_FILES` (:data:`HELDOUT_PHOTO_FILES` and two more) or
    :data:`HELDOUT_BACKGROUND_FILES` as RGB (grey files repeated)."""
    files = {**CATALOG_PHOTO_FILES, **HELDOUT_BACKGROUND_FILES}
    if name not in files:
        raise MatlError(f"unknown held-out photo {name!r}; valid: {', '.join(sorted(files))}")
    path = heldout_photo_dir() / files[name]
    if not path.is_file():
        raise MatlError(f"{path} is missing: this scikit-image wheel does not bundle it (pip install "
                        "'scikit-image>=0.22')")
    with Image.open(path) as im:
        return im.convert("RGB")


# Darkest value any printed channel may take. Canonical images use exactly 0 as background, so
# print must never reach 0 even after antialiasing against the black background.
INK_FLOOR = 28
INK: RGB = (38, 38, 42)
WHITE: RGB = (250, 250, 246)


@functools.lru_cache(maxsize=512)
def font(key: str, size: int) -> ImageFont.FreeTypeFont:
    """Load one of :data:`FONT_FILES` at ``size`` px (cached; PIL font objects are immutable)."""
    return ImageFont.truetype(str(FONT_DIR / FONT_FILES[key]), max(int(size), 4))


@functools.lru_cache(maxsize=16)
def photo(key: str) -> Image.Image:
    """One of :data:`PHOTO_FILES` (or, for the held-out catalogs, :data:`HELDOUT_PHOTO_FILES`) as RGBA
    (transparent where the file has alpha)."""
    if key not in PHOTO_FILES and key in CATALOG_PHOTO_FILES:
        return heldout_image(key).convert("RGBA")
    with Image.open(PHOTO_DIR / PHOTO_FILES[key]) as im:
        return im.convert("RGBA")


def mix(a: RGB, b: RGB, t: float) -> RGB:
    """Linear blend ``(1 - t) * a + t * b`` of two colours."""
    return tuple(round(x + (y - x) * t) for x, y in zip(a, b, strict=True))  # type: ignore[return-value]


def luminance(c: RGB) -> float:
    """Perceived brightness in [0, 1] (Rec. 601 weights), used to pick readable text colours."""
    return (0.299 * c[0] + 0.587 * c[1] + 0.114 * c[2]) / 255.0


def contrast_ink(bg: RGB, light: RGB = WHITE, dark: RGB = INK) -> RGB:
    """Text colour that reads on ``bg``: ``dark`` on light backgrounds, ``light`` on dark ones."""
    return dark if luminance(bg) > 0.6 else light


def fit_font(key: str, text: str, width: float, height: float, max_size: int | None = None) -> ImageFont.FreeTypeFont:
    """Largest font of face ``key`` whose rendering of ``text`` fits a ``width`` x ``height`` box."""
    lo, hi = 4, int(max(min(height * 1.4, max_size or 10_000), 5))
    while lo < hi:  # binary search: text extent grows monotonically with the font size
        mid = (lo + hi + 1) // 2
        left, top, right, bottom = font(key, mid).getbbox(text)
        if right - left <= width and bottom - top <= height:
            lo = mid
        else:
            hi = mid - 1
    return font(key, lo)


def draw_text(
    draw: ImageDraw.ImageDraw,
    box: Box,
    text: str,
    key: str,
    fill: RGB,
    align: str = "center",
    max_size: int | None = None,
    stroke: tuple[int, RGB] | None = None,
) -> Box:
    """Draw ``text`` as large as fits into ``box``; return the inked bounding box.

    ``align`` is "left", "center" or "right" (vertical placement is always centred).
    ``stroke`` is ``(width_px, colour)`` for an outline, as on bold packaging titles.
    """
    left, top, right, bottom = box
    sw = stroke[0] if stroke else 0
    f = fit_font(key, text, right - left - 2 * sw, bottom - top - 2 * sw, max_size)
    bl, bt, br, bb = f.getbbox(text)
    y = (top + bottom) / 2 - (bt + bb) / 2
    if align == "left":
        x = left + sw - bl
    elif align == "right":
        x = right - sw - br
    else:
        x = (left + right) / 2 - (bl + br) / 2
    kwargs = {"stroke_width": sw, "stroke_fill": stroke[1]} if stroke else {}
    draw.text((x, y), text, font=f, fill=fill, **kwargs)
    return (x + bl, y + bt, x + br, y + bb)


def draw_paragraph(
    draw: ImageDraw.ImageDraw, box: Box, words: Sequence[str], key: str, size: int, fill: RGB, spacing: float = 1.3
) -> None:
    """Flow ``words`` into ``box`` line by line at a fixed font size (small print, may be cut)."""
    left, top, right, bottom = box
    f = font(key, size)
    y = top
    line: list[str] = []
    lines: list[str] = []
    for w in words:
        trial = " ".join([*line, w])
        if line and f.getlength(trial) > right - left:
            lines.append(" ".join(line))
            line = [w]
        else:
            line.append(w)
    if line:
        lines.append(" ".join(line))
    for text in lines:
        if y + size > bottom:
            break
        draw.text((left, y), text, font=f, fill=fill)
        y += size * spacing


def linear_gradient(size: tuple[int, int], c0: RGB, c1: RGB, angle_deg: float = 90.0) -> Image.Image:
    """RGB image of ``size`` = (W, H) blending ``c0`` into ``c1`` along ``angle_deg`` (90 = top to bottom)."""
    w, h = size
    a = math.radians(angle_deg)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    t = (xx - w / 2) * math.cos(a) + (yy - h / 2) * math.sin(a)
    t = (t - t.min()) / max(float(t.max() - t.min()), 1e-6)
    arr = np.asarray(c0, np.float32) * (1 - t[..., None]) + np.asarray(c1, np.float32) * t[..., None]
    return Image.fromarray(np.clip(arr, 0, 255).astype(np.uint8), "RGB")


def radial_gradient(size: int, inner: RGB, outer: RGB, centre: tuple[float, float] = (0.5, 0.5)) -> Image.Image:
    """Square RGB image (size x size) shading ``inner`` at ``centre`` (fractions) to ``outer`` at the rim."""
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32) / max(size - 1, 1)
    t = np.clip(np.hypot(xx - centre[0], yy - centre[1]) / 0.75, 0, 1)[..., None]
    arr = np.asarray(inner, np.float32) * (1 - t) + np.asarray(outer, np.float32) * t
    return Image.fromarray(arr.astype(np.uint8), "RGB")


def disc_mask(size: int, inset: float = 0.0) -> Image.Image:
    """L-mode (size x size) mask of a centred disc, ``inset`` px in from the border."""
    m = Image.new("L", (size, size), 0)
    inset = min(inset, (size - 1) / 2)  # tiny discs: never let the box invert
    ImageDraw.Draw(m).ellipse((inset, inset, size - 1 - inset, size - 1 - inset), fill=255)
    return m


def diagonal_stripes(
    draw: ImageDraw.ImageDraw, box: Box, colours: Sequence[RGB], width: float, slope: float = 1.0
) -> None:
    """Fill ``box`` with parallel stripes cycling through ``colours`` (clipped by the caller's layering)."""
    left, top, right, bottom = box
    h = bottom - top
    x = left - h * abs(slope) - width
    i = 0
    while x < right + width:
        pts = [(x, bottom), (x + width, bottom), (x + width + h * slope, top), (x + h * slope, top)]
        draw.polygon(pts, fill=colours[i % len(colours)])
        x += width
        i += 1


def star_points(
    cx: float, cy: float, r_out: float, r_in: float, n: int, rot_deg: float = -90.0
) -> list[tuple[float, float]]:
    """Vertices of an ``n``-pointed star (or starburst) centred at (cx, cy)."""
    pts = []
    for k in range(2 * n):
        r = r_out if k % 2 == 0 else r_in
        a = math.radians(rot_deg + k * 180.0 / n)
        pts.append((cx + r * math.cos(a), cy + r * math.sin(a)))
    return pts


def regular_polygon(cx: float, cy: float, r: float, n: int, rot_deg: float = -90.0) -> list[tuple[float, float]]:
    """Vertices of a regular ``n``-gon centred at (cx, cy)."""
    return [
        (
            cx + r * math.cos(math.radians(rot_deg + 360.0 * k / n)),
            cy + r * math.sin(math.radians(rot_deg + 360.0 * k / n)),
        )
        for k in range(n)
    ]


# --- EAN-13 --------------------------------------------------------------------------------------
# Module patterns of the EAN-13 symbology: L (odd parity), G (even parity) and R codes per digit,
# and the parity sequence of the left half selected by the leading digit.
_EAN_L = ["0001101", "0011001", "0010011", "0111101", "0100011", "0110001", "0101111", "0111011", "0110111", "0001011"]
_EAN_R = ["".join("1" if b == "0" else "0" for b in code) for code in _EAN_L]
_EAN_G = [code[::-1] for code in _EAN_R]
_EAN_PARITY = ["LLLLLL", "LLGLGG", "LLGGLG", "LLGGGL", "LGLLGG", "LGGLLG", "LGGGLG", "LGGGGL", "LGLGLG", "LGLGGL"]


def ean13_digits(rng: np.random.Generator) -> str:
    """Random 13-digit EAN with a valid check digit (so the printed code is a real EAN-13)."""
    body = [int(d) for d in rng.integers(0, 10, size=12)]
    body[0] = max(body[0], 2)  # leading 0/1 are reserved prefixes; keep codes looking like goods
    s = sum(d * (3 if i % 2 else 1) for i, d in enumerate(body))
    return "".join(map(str, body)) + str((10 - s % 10) % 10)


def ean13_modules(digits: str) -> str:
    """The 95-module bar pattern ("1" = bar) of a 13-digit EAN code."""
    first, left, right = int(digits[0]), digits[1:7], digits[7:13]
    parity = _EAN_PARITY[first]
    out = "101"
    for p, d in zip(parity, left, strict=True):
        out += (_EAN_L if p == "L" else _EAN_G)[int(d)]
    out += "01010"
    for d in right:
        out += _EAN_R[int(d)]
    return out + "101"


def barcode(size: tuple[int, int], digits: str, bar: RGB = INK, paper: RGB = WHITE) -> Image.Image:
    """RGB EAN-13 label of ``size`` = (W, H): quiet zone, bars with longer guards, digits below.

    Bars are dark grey rather than 0 so the print can never be confused with background.
    """
    w, h = size
    im = Image.new("RGB", (w, h), paper)
    d = ImageDraw.Draw(im)
    mods = ean13_modules(digits)
    quiet = 9  # modules of blank margin each side, enough to fit the leading digit
    unit = w / (95 + 2 * quiet)
    text_h = h * 0.2
    bar_bottom = h - text_h - h * 0.04
    for i, m in enumerate(mods):
        if m == "1":
            x0 = (quiet + i) * unit
            is_guard = i < 3 or 45 <= i < 50 or i >= 92
            d.rectangle((x0, h * 0.05, x0 + unit - 0.01, bar_bottom + (text_h * 0.5 if is_guard else 0)), fill=bar)
    f = fit_font("mono", "0000000", 42 * unit, text_h)
    d.text((quiet * unit * 0.2, h - text_h * 1.05), digits[0], font=f, fill=bar)
    d.text(((quiet + 3 + 21) * unit, h - text_h * 1.05), digits[1:7], font=f, fill=bar, anchor="ma")
    d.text(((quiet + 50 + 21) * unit, h - text_h * 1.05), digits[7:], font=f, fill=bar, anchor="ma")
    return im


def floor_ink(im: Image.Image) -> Image.Image:
    """Raise every channel to at least :data:`INK_FLOOR` (see its comment) and return RGB."""
    arr = np.asarray(im.convert("RGB"))
    return Image.fromarray(np.maximum(arr, INK_FLOOR).astype(np.uint8), "RGB")


def text_on_circle(
    canvas: Image.Image,
    centre: tuple[float, float],
    radius: float,
    text: str,
    key: str,
    size: int,
    fill: RGB,
    start_deg: float = -90.0,
) -> None:
    """Print ``text`` clockwise along a circle, letters upright towards the outside, starting at
    ``start_deg`` (image angles: 0 = right, -90 = top), as on lids and seals."""
    f = font(key, size)
    circumference = 2 * math.pi * radius
    angle = start_deg
    for ch in text:
        adv = f.getlength(ch) + size * 0.08
        a_mid = angle + math.degrees(adv / 2 / radius)
        glyph = Image.new("RGBA", (size * 2, size * 2), (0, 0, 0, 0))
        ImageDraw.Draw(glyph).text((size, size), ch, font=f, fill=(*fill, 255), anchor="mm")
        glyph = glyph.rotate(-(a_mid + 90), resample=Image.Resampling.BICUBIC)
        x = centre[0] + radius * math.cos(math.radians(a_mid)) - size
        y = centre[1] + radius * math.sin(math.radians(a_mid)) - size
        canvas.paste(glyph, (round(x), round(y)), glyph)
        angle += math.degrees(adv / radius)
        if (angle - start_deg) / 360 * circumference > circumference * 0.97:
            break
