"""Occluders over a product crop: another product on top, a gripper's finger or bar, a suction cup, a bin wall.

In a picking bin the product a robot is after is seldom whole: another product lies across it, the
gripper or the suction cup is in view, the bin wall or the crop's edge cuts it. :class:`Occluders`
draws one such occluder over a scene in which the target product is already composited, and returns
the occluded scene with the target's new visible coverage:

* ``product``: another product's print (its canonical image) under its own rotation, scale and a
  slight perspective, lying on top of the target, with a soft drop shadow on what lies below;
* ``gripper``: a parallel-jaw finger (rounded tip) or a gripper bar (flat end) entering from a
  random side, grey (matte) or metallic (a specular streak), shaded by a linear gradient, with a shadow;
* ``suction``: a suction cup (an ellipse: the cup seen at a slant, a lighter rim, a darker centre) on its
  shaft, a bar reaching the crop's edge, shaded like the gripper, with a shadow;
* ``edge``: the crop's edge or the bin wall: a band from one side of the frame, straight or slightly
  slanted, dark (a wall in its own shadow, or a crop beyond the camera's image) or the wall's texture.

Placement: the hidden fraction of the target is drawn uniformly in ``hidden``; the occluder's shape
and look are drawn first, then its *reach* (how far it comes over the product) is found by bisection
so that the realised fraction is close to the drawn one, growing the occluder (up to
:data:`GROWTH_STEPS` times) when even its full reach hides too little; the closest placement is kept.
The occluder always comes over the product (it enters along a line through a point of the product).

Images are ``(H, W, 3)`` float RGB in [0, 1]; coverages ``(H, W)`` float in [0, 1]; pixel coordinates
as docs/design.md (x right, y down, pixel centres at integers). Everything random comes from the
generator given to :meth:`Occluders.apply`, in a fixed order, so a generator state gives one result.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from matl.utils.errors import MatlError

OCCLUDER_KINDS = ("product", "gripper", "suction", "edge")
GROWTH = 1.4          # the occluder's size factor grows by this when its full reach hides too little
GROWTH_STEPS = 5      # size factors tried: 1, 1.4, ..., 1.4 ** 4
BISECTION_STEPS = 14  # halvings of the reach per size factor
TOLERANCE = 0.004     # a placement this close to the drawn fraction ends the search


# ------------------------------------------------------------------------------------------ shapes
def _grid(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-centre coordinates ``x``, ``y`` of an ``(H, W)`` frame, each ``(H, W)`` float64."""
    ys, xs = np.mgrid[0:shape[0], 0:shape[1]]
    return xs.astype(np.float64), ys.astype(np.float64)


def _soft(signed_distance: np.ndarray) -> np.ndarray:
    """Coverage ``(H, W)`` in [0, 1] of a region from its signed distance (px, < 0 inside): a 1 px ramp."""
    return np.clip(0.5 - signed_distance, 0.0, 1.0)


def capsule_alpha(xs: np.ndarray, ys: np.ndarray, a: np.ndarray, b: np.ndarray, half_width: float,
                  round_end: bool) -> np.ndarray:
    """Coverage ``(H, W)`` of a bar of ``half_width`` px from point ``a`` to point ``b`` (each ``(2,)``, x, y).

    ``round_end``: the end at ``b`` is a half disc (a finger's tip); else it is cut square (a bar's end).
    The end at ``a`` is square too; callers put ``a`` far outside the frame.
    """
    d = b - a
    length = max(float(np.hypot(*d)), 1e-9)
    u = d / length
    along = (xs - a[0]) * u[0] + (ys - a[1]) * u[1]
    across = np.abs(-(xs - a[0]) * u[1] + (ys - a[1]) * u[0])
    if round_end:
        beyond = np.maximum(along - length, 0.0)
        return _soft(np.hypot(beyond, across) - half_width) * _soft(-along)
    return _soft(across - half_width) * _soft(along - length) * _soft(-along)


def ellipse_alpha(xs: np.ndarray, ys: np.ndarray, centre: np.ndarray, semi_axes: tuple[float, float],
                  angle: float) -> tuple[np.ndarray, np.ndarray]:
    """Coverage ``(H, W)`` of an ellipse and each pixel's normalised radius ``(H, W)`` (1 on its outline).

    ``semi_axes``: ``(a, b)`` px along the directions ``angle`` (radians, x towards y) and ``angle + 90``
    deg. The signed distance is the normalised radius's first-order one, ``(r - 1) / |grad r|``.
    """
    c, s = math.cos(angle), math.sin(angle)
    dx, dy = xs - centre[0], ys - centre[1]
    p, q = (dx * c + dy * s) / semi_axes[0], (-dx * s + dy * c) / semi_axes[1]
    radius = np.hypot(p, q)
    grad = np.hypot(p / semi_axes[0], q / semi_axes[1]) / np.maximum(radius, 1e-9)
    return _soft((radius - 1.0) / np.maximum(grad, 1e-9)), radius


def halfplane_alpha(xs: np.ndarray, ys: np.ndarray, normal: np.ndarray, offset: float) -> np.ndarray:
    """Coverage ``(H, W)`` of the half plane ``normal . (x, y) < offset`` (``normal`` a unit ``(2,)``)."""
    return _soft(xs * normal[0] + ys * normal[1] - offset)


def hidden_fraction(visible: np.ndarray, alpha: np.ndarray) -> float:
    """The share of the coverage ``visible`` ``(H, W)`` that an occluder of coverage ``alpha`` ``(H, W)`` hides."""
    return float((visible * alpha).sum() / visible.sum())


# ------------------------------------------------------------------------------------------- target
@dataclass
class _Approach:
    """Where an occluder comes from: along the unit ``u`` ``(2,)`` through the point ``p`` ``(2,)`` of the product;
    ``v`` is ``u`` turned by +90 deg. ``s_min, s_max`` and ``t_min, t_max``: the product's extent (px) along
    ``u`` and ``v``, measured from ``p``."""

    p: np.ndarray
    u: np.ndarray
    v: np.ndarray
    s_min: float
    s_max: float
    t_min: float
    t_max: float

    @property
    def across(self) -> float:
        """The product's width across the approach, px."""
        return self.t_max - self.t_min


def _approach(visible: np.ndarray, angle: float, rng: np.random.Generator) -> _Approach:
    """An approach along ``angle`` (radians) through a random point of the product (coverage ``visible`` ``(H, W)``):
    half way at most from the coverage's centroid to a pixel drawn by its coverage, so it lies well inside."""
    xs, ys = _grid(visible.shape)
    weights = visible.ravel() / visible.sum()
    centroid = np.array([(xs.ravel() * weights).sum(), (ys.ravel() * weights).sum()])
    k = int(rng.choice(visible.size, p=weights))
    pixel = np.array([xs.ravel()[k], ys.ravel()[k]])
    p = centroid + rng.uniform(0.0, 0.5) * (pixel - centroid)
    u = np.array([math.cos(angle), math.sin(angle)])
    v = np.array([-u[1], u[0]])
    inside = visible > 0.05
    if not inside.any():
        inside = visible > 0
    s = (xs[inside] - p[0]) * u[0] + (ys[inside] - p[1]) * u[1]
    t = (xs[inside] - p[0]) * v[0] + (ys[inside] - p[1]) * v[1]
    return _Approach(p, u, v, float(s.min()) - 0.5, float(s.max()) + 0.5, float(t.min()) - 0.5, float(t.max()) + 0.5)


# ------------------------------------------------------------------------------------------ looks
def _metal(xs: np.ndarray, ys: np.ndarray, origin: np.ndarray, u: np.ndarray, half_width: float,
           look: dict[str, Any]) -> np.ndarray:
    """Colour ``(H, W, 3)`` of a grey or metallic part along ``u`` (``(2,)``) through ``origin``: a linear gradient
    across it and, when metallic, a specular streak along it (``look`` from :func:`_draw_metal`)."""
    across = (-(xs - origin[0]) * u[1] + (ys - origin[1]) * u[0]) / max(half_width, 1e-9)  # -1..1 on the part
    along = ((xs - origin[0]) * u[0] + (ys - origin[1]) * u[1]) / max(half_width, 1e-9)
    shade = 1.0 + look["gradient"] * np.clip(across, -1.5, 1.5) + look["falloff"] * np.tanh(along / 8.0)
    streak = look["specular"] * np.exp(-(((across - look["streak_at"]) / look["streak_width"]) ** 2))
    colour = look["grey"] * np.asarray(look["tint"]) * shade[..., None] + streak[..., None]
    return np.clip(colour, 0.0, 1.0)


def _draw_metal(rng: np.random.Generator) -> dict[str, Any]:
    """A grey (matte) or metallic part's look: base grey, tint, gradient, specular streak."""
    metallic = bool(rng.random() < 0.6)
    return {"metallic": metallic, "grey": float(rng.uniform(0.3, 0.75)),
            "tint": (1.0 + rng.uniform(-0.04, 0.04, 3)).tolist(), "gradient": float(rng.uniform(-0.35, 0.35)),
            "falloff": float(rng.uniform(-0.1, 0.1)), "specular": float(rng.uniform(0.2, 0.5)) if metallic else 0.0,
            "streak_at": float(rng.uniform(-0.6, 0.6)), "streak_width": float(rng.uniform(0.1, 0.25))}


def _shadow(scene: np.ndarray, alpha: np.ndarray, offset: np.ndarray, sigma: float, strength: float) -> np.ndarray:
    """``scene`` ``(H, W, 3)`` darkened by an occluder's soft drop shadow: its coverage ``alpha`` ``(H, W)`` moved by
    ``offset`` ``(2,)`` px, blurred by ``sigma`` px, at most ``strength`` darker."""
    h, w = alpha.shape
    shift = np.float64([[1.0, 0.0, offset[0]], [0.0, 1.0, offset[1]]])
    moved = cv2.warpAffine(alpha, shift, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    if sigma > 0.0:
        moved = cv2.GaussianBlur(moved, (0, 0), sigma, borderType=cv2.BORDER_REPLICATE)
    return scene * (1.0 - strength * np.clip(moved, 0.0, 1.0))[..., None]


# ---------------------------------------------------------------------------------------- occluders
class _Occluder:
    """One drawn occluder: its coverage at a size factor and a reach in [0, 1] (0: just off the product,
    1: as far over it as it goes), and its colour there. Subclasses draw their shape and look in ``__init__``."""

    kind = ""

    def alpha(self, factor: float, reach: float) -> np.ndarray:
        """Coverage ``(H, W)`` in [0, 1]."""
        raise NotImplementedError

    def colour(self, factor: float, reach: float) -> np.ndarray:
        """Colour ``(H, W, 3)`` in [0, 1] where the coverage is > 0 (anything elsewhere)."""
        raise NotImplementedError

    def info(self) -> dict[str, Any]:
        """What was drawn (JSON values)."""
        return {}


class _Gripper(_Occluder):
    """A finger (rounded tip, narrow) or a bar (square end, wide) from outside the frame, over the product."""

    kind = "gripper"

    def __init__(self, visible: np.ndarray, rng: np.random.Generator) -> None:
        self.xs, self.ys = _grid(visible.shape)
        self.angle = float(rng.uniform(0.0, 2.0 * math.pi))
        self.at = _approach(visible, self.angle, rng)
        self.variant = "finger" if rng.random() < 0.5 else "bar"
        width = rng.uniform(0.25, 0.45) if self.variant == "finger" else rng.uniform(0.45, 0.8)
        self.half_width = 0.5 * float(width) * self.at.across
        self.look = _draw_metal(rng)
        self.far = 4.0 * float(sum(visible.shape))  # the square end, outside the frame

    def _ends(self, factor: float, reach: float) -> tuple[np.ndarray, np.ndarray, float]:
        hw = self.half_width * factor
        tip = hw if self.variant == "finger" else 0.0  # a round tip reaches hw beyond its end point
        s = self.at.s_min - tip + reach * (self.at.s_max - self.at.s_min + 2.0 * tip)
        return self.at.p - self.far * self.at.u, self.at.p + s * self.at.u, hw

    def alpha(self, factor: float, reach: float) -> np.ndarray:
        a, b, hw = self._ends(factor, reach)
        return capsule_alpha(self.xs, self.ys, a, b, hw, self.variant == "finger")

    def colour(self, factor: float, reach: float) -> np.ndarray:
        _, b, hw = self._ends(factor, reach)
        return _metal(self.xs, self.ys, b, self.at.u, hw, self.look)

    def info(self) -> dict[str, Any]:
        return {"variant": self.variant, "metallic": self.look["metallic"], "direction_deg": math.degrees(self.angle)}


class _Suction(_Occluder):
    """A suction cup (an ellipse, its short axis along the approach: the cup seen at a slant) on a shaft from the
    crop's edge; reach 1 puts the cup's centre on the chosen point of the product."""

    kind = "suction"

    def __init__(self, visible: np.ndarray, rng: np.random.Generator) -> None:
        self.xs, self.ys = _grid(visible.shape)
        self.angle = float(rng.uniform(0.0, 2.0 * math.pi))
        self.at = _approach(visible, self.angle, rng)
        self.radius = float(rng.uniform(0.2, 0.35)) * self.at.across  # across the approach
        self.slant = float(rng.uniform(0.6, 0.95))                  # along it, relative
        self.shaft = float(rng.uniform(0.3, 0.5))                   # the shaft's half width, relative
        self.look = _draw_metal(rng)
        self.rubber = float(rng.uniform(0.12, 0.5))                 # the cup's grey
        self.rim = float(rng.uniform(0.4, 1.0))                     # the rim this much lighter, relative
        self.far = 4.0 * float(sum(visible.shape))

    def _parts(self, factor: float, reach: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The cup's coverage, its normalised radius, the shaft's coverage (each ``(H, W)``) and the cup's centre."""
        r = self.radius * factor
        start = self.at.s_min - r * self.slant  # the cup just off the product
        centre = self.at.p + (1.0 - reach) * start * self.at.u
        cup, radius = ellipse_alpha(self.xs, self.ys, centre, (r * self.slant, r), self.angle)
        shaft = capsule_alpha(self.xs, self.ys, centre - self.far * self.at.u, centre, r * self.shaft, False)
        return cup, radius, shaft, centre

    def alpha(self, factor: float, reach: float) -> np.ndarray:
        cup, _, shaft, _ = self._parts(factor, reach)
        return np.maximum(cup, shaft)

    def colour(self, factor: float, reach: float) -> np.ndarray:
        cup, radius, _, centre = self._parts(factor, reach)
        r = self.radius * factor
        shaft = _metal(self.xs, self.ys, centre, self.at.u, r * self.shaft, self.look)
        grey = self.rubber * (1.0 + self.rim * (radius > 0.75)) * np.where(radius < 0.45, 0.35, 1.0)  # dark centre
        shade = 1.0 + 0.25 * np.clip(-((self.xs - centre[0]) * self.at.v[0] + (self.ys - centre[1]) * self.at.v[1])
                                     / max(r, 1e-9), -1.0, 1.0)
        rubber = np.clip(grey * shade, 0.0, 1.0)[..., None] * np.asarray(self.look["tint"])
        return np.where((cup > 0)[..., None], rubber, shaft)

    def info(self) -> dict[str, Any]:
        return {"metallic": self.look["metallic"], "direction_deg": math.degrees(self.angle)}


class _Edge(_Occluder):
    """A band from one side of the frame (the crop's edge or the bin wall), its boundary straight or slanted up to
    12 deg; dark or the wall's texture (``floor``)."""

    kind = "edge"

    def __init__(self, visible: np.ndarray, rng: np.random.Generator, floor: np.ndarray | None) -> None:
        self.xs, self.ys = _grid(visible.shape)
        side = int(rng.integers(4))  # 0 left, 1 top, 2 right, 3 bottom: the band comes from there
        slant = float(rng.uniform(-12.0, 12.0)) if rng.random() < 0.5 else 0.0
        self.angle = math.radians(90.0 * side + slant)  # the inward normal of the side, turned by the slant
        self.at = _approach(visible, self.angle, rng)
        self.variant = "texture" if floor is not None and rng.random() < 0.5 else "dark"
        if self.variant == "texture":
            self.wall = np.clip(floor * rng.uniform(0.45, 0.8), 0.0, 1.0)
        else:
            level = rng.uniform(0.02, 0.12)
            ramp = (self.xs * self.at.v[0] + self.ys * self.at.v[1]) / max(visible.shape)
            noise = rng.normal(0.0, 0.01, visible.shape)
            self.wall = np.repeat(np.clip(level * (1.0 + 0.3 * ramp) + noise, 0.0, 1.0)[..., None], 3, axis=-1)
        self.slant = slant

    def alpha(self, factor: float, reach: float) -> np.ndarray:
        offset = float(self.at.p @ self.at.u) + self.at.s_min + reach * (self.at.s_max - self.at.s_min)
        return halfplane_alpha(self.xs, self.ys, self.at.u, offset)

    def colour(self, factor: float, reach: float) -> np.ndarray:
        return self.wall

    def info(self) -> dict[str, Any]:
        return {"variant": self.variant, "slant_deg": self.slant, "direction_deg": math.degrees(self.angle)}


class _Product(_Occluder):
    """Another product's print (``rgb`` ``(h, w, 3)``, ``mask`` ``(h, w)``) rotated, scaled about the target's size and
    slightly in perspective, sliding along the approach until its centre is on the chosen point (reach 1)."""

    kind = "product"

    def __init__(self, visible: np.ndarray, rng: np.random.Generator,
                 products: Sequence[tuple[np.ndarray, np.ndarray]]) -> None:
        self.shape = visible.shape
        self.index = int(rng.integers(len(products)))
        rgb, mask = products[self.index]
        self.rgb, self.mask = np.asarray(rgb, np.float64), np.asarray(mask, np.float64)
        self.angle = float(rng.uniform(0.0, 2.0 * math.pi))
        self.at = _approach(visible, self.angle, rng)
        rows, cols = np.flatnonzero(self.mask.max(1) > 0.5), np.flatnonzero(self.mask.max(0) > 0.5)
        if len(rows) == 0:
            raise MatlError(f"occluder product {self.index} has an empty mask: pass products with their masks")
        # its own frame: the mask's bounding-box centre at the origin, turned, slightly in perspective
        self.centre = np.array([(cols[0] + cols[-1]) / 2.0, (rows[0] + rows[-1]) / 2.0])
        corners = np.float32([[cols[0], rows[0]], [cols[-1], rows[0]], [cols[-1], rows[-1]], [cols[0], rows[-1]]])
        jitter = rng.uniform(-0.08, 0.08, (4, 2)) * np.array([cols[-1] - cols[0] + 1, rows[-1] - rows[0] + 1])
        self.tilt = cv2.getPerspectiveTransform(corners, (corners + jitter).astype(np.float32))
        self.turn = float(rng.uniform(0.0, 2.0 * math.pi))
        scale = math.sqrt(visible.sum() / max(self.mask.sum(), 1e-9)) * rng.uniform(0.7, 1.1)
        self.scale = float(scale)
        self.brightness = float(rng.uniform(0.85, 1.15))
        radius = float(np.hypot(*(corners + jitter - self.centre).T).max())  # its reach from its centre, canonical px
        self.radius = radius

    def _H(self, factor: float, reach: float) -> np.ndarray:
        """``(3, 3)`` frame_H_canon of the occluding print."""
        scale = self.scale * factor
        start = self.at.s_min - self.radius * scale  # the print just off the product
        centre = self.at.p + (1.0 - reach) * start * self.at.u
        c, s = math.cos(self.turn), math.sin(self.turn)
        move = np.array([[1.0, 0.0, centre[0]], [0.0, 1.0, centre[1]], [0.0, 0.0, 1.0]])
        turn = np.array([[scale * c, -scale * s, 0.0], [scale * s, scale * c, 0.0], [0.0, 0.0, 1.0]])
        back = np.array([[1.0, 0.0, -self.centre[0]], [0.0, 1.0, -self.centre[1]], [0.0, 0.0, 1.0]])
        return move @ turn @ back @ self.tilt

    def _warp(self, image: np.ndarray, factor: float, reach: float) -> np.ndarray:
        return cv2.warpPerspective(image, self._H(factor, reach), (self.shape[1], self.shape[0]),
                                   flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    def alpha(self, factor: float, reach: float) -> np.ndarray:
        return np.clip(self._warp(self.mask, factor, reach), 0.0, 1.0)

    def colour(self, factor: float, reach: float) -> np.ndarray:
        premultiplied = self._warp(self.rgb * self.mask[..., None], factor, reach)
        alpha = self.alpha(factor, reach)
        return np.clip(premultiplied / np.maximum(alpha, 1e-6)[..., None] * self.brightness, 0.0, 1.0)

    def info(self) -> dict[str, Any]:
        return {"product_index": self.index, "direction_deg": math.degrees(self.angle)}


# ---------------------------------------------------------------------------------------- placement
def place(occluder: _Occluder, visible: np.ndarray, target: float) -> tuple[float, float, np.ndarray, float]:
    """The size factor and reach whose hidden fraction of ``visible`` ``(H, W)`` is closest to ``target``.

    For each size factor (1, then grown by :data:`GROWTH`) the full reach is tried; if it hides at least
    ``target``, the reach is bisected (the invariant: too little at ``lo``, enough at ``hi``) and the search
    ends; else the next factor. Returns ``(factor, reach, alpha (H, W), realised fraction)``.
    """
    best: tuple[float, float, np.ndarray, float] | None = None

    def consider(factor: float, reach: float) -> float:
        nonlocal best
        alpha = occluder.alpha(factor, reach)
        realised = hidden_fraction(visible, alpha)
        if best is None or abs(realised - target) < abs(best[3] - target):
            best = (factor, reach, alpha, realised)
        return realised

    for step in range(GROWTH_STEPS):
        factor = GROWTH ** step
        if consider(factor, 1.0) < target:
            continue
        lo, hi = 0.0, 1.0
        for _ in range(BISECTION_STEPS):
            mid = 0.5 * (lo + hi)
            realised = consider(factor, mid)
            if abs(realised - target) <= TOLERANCE:
                break
            lo, hi = (mid, hi) if realised < target else (lo, mid)
        break
    assert best is not None
    return best


# ------------------------------------------------------------------------------------------ public
def _check_kinds(kinds: Any) -> dict[str, float]:
    if not isinstance(kinds, Mapping) or not kinds:
        raise MatlError(f"occluder kinds={kinds} is invalid: use weights of {', '.join(OCCLUDER_KINDS)}, "
                        "e.g. {product: 1, edge: 1}")
    weights = {}
    for name, weight in kinds.items():
        if name not in OCCLUDER_KINDS:
            raise MatlError(f"occluder kind {name!r} is unknown: use {', '.join(OCCLUDER_KINDS[:-1])} or "
                            f"{OCCLUDER_KINDS[-1]}")
        if not isinstance(weight, (int, float)) or isinstance(weight, bool) or not math.isfinite(weight) or weight < 0:
            raise MatlError(f"occluder kind weight {name}={weight} is invalid: use a number >= 0")
        weights[str(name)] = float(weight)
    if sum(weights.values()) <= 0:
        raise MatlError(f"occluder kinds all have weight 0: give at least one of {', '.join(OCCLUDER_KINDS)} a "
                        "weight > 0")
    return weights


@dataclass
class Occluders:
    """Random occluders over a product crop (``occluded.*`` of conf/unseen.yaml; the module docstring).

    Args:
        kinds: weights of the kinds ``product``, ``gripper``, ``suction``, ``edge`` (drawn in proportion;
            a kind left out has weight 0).
        hidden: the target hidden fraction of the product, uniform in ``[low, high]``, ``0 <= low <= high < 1``.
    """

    kinds: dict[str, float]
    hidden: tuple[float, float] = (0.1, 0.5)

    def __post_init__(self) -> None:
        self.kinds = _check_kinds(self.kinds)
        bounds = tuple(self.hidden) if isinstance(self.hidden, Sequence) else ()
        if len(bounds) != 2 or not all(isinstance(b, (int, float)) and not isinstance(b, bool) for b in bounds) \
                or not 0.0 <= bounds[0] <= bounds[1] < 1.0:
            raise MatlError(f"occluder hidden={list(self.hidden) if bounds else self.hidden} is invalid: use "
                            "[low, high] with 0 <= low <= high < 1")
        self.hidden = (float(bounds[0]), float(bounds[1]))

    def _check_inputs(self, image: np.ndarray, visible: np.ndarray,
                      products: Sequence[tuple[np.ndarray, np.ndarray]], floor: np.ndarray | None) -> None:
        if image.ndim != 3 or image.shape[2] != 3:
            raise MatlError(f"occluders take an (H, W, 3) image, got shape {image.shape}")
        if visible.shape != image.shape[:2]:
            raise MatlError(f"the visible coverage has shape {visible.shape}, the image {image.shape[:2]}: pass the "
                            "target's (H, W) mask")
        if not visible.sum() > 0:
            raise MatlError("the target product has no visible pixel: nothing to occlude")
        if floor is not None and floor.shape != image.shape:
            raise MatlError(f"the floor has shape {floor.shape}, the image {image.shape}: pass a floor of the image's "
                            "size")
        if self.kinds.get("product", 0.0) > 0 and not products:
            raise MatlError("occluder kind 'product' needs other products: pass products=[(rgb, mask), ...] or give "
                            "'product' weight 0")

    def draw_kind(self, rng: np.random.Generator) -> str:
        """One kind, drawn by weight."""
        names = list(self.kinds)
        weights = np.array([self.kinds[n] for n in names])
        return names[int(rng.choice(len(names), p=weights / weights.sum()))]

    def apply(self, image: np.ndarray, visible: np.ndarray, rng: np.random.Generator,
              products: Sequence[tuple[np.ndarray, np.ndarray]] = (), floor: np.ndarray | None = None,
              ) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
        """Draw one occluder over the scene.

        Args:
            image: ``(H, W, 3)`` float in [0, 1], the scene with the target product composited on its background.
            visible: ``(H, W)`` float in [0, 1], the target product's coverage (its warped mask).
            rng: all the randomness (kind, hidden fraction, shape, look, shadow).
            products: ``(rgb (h, w, 3) float in [0, 1], mask (h, w) float)`` canonical images of *other* products,
                the ``product`` kind's occluders.
            floor: optional ``(H, W, 3)`` texture of the bin wall (``edge``); without it the wall is dark.
        Returns:
            ``(occluded (H, W, 3) float64 in [0, 1], visible (H, W) float64, info)``: the new coverage is the old one
            times the occluder's complement (so within it, soft at the occluder's edge); ``info`` holds
            ``occluder`` (the kind), ``hidden_fraction`` (``1 - sum(new) / sum(old)``), ``target_fraction`` (the
            drawn one), ``shadow`` (its strength) and what the kind drew.
        """
        image, visible = np.asarray(image, np.float64), np.asarray(visible, np.float64)
        floor = None if floor is None else np.asarray(floor, np.float64)
        self._check_inputs(image, visible, products, floor)
        kind = self.draw_kind(rng)
        low, high = self.hidden
        target = float(rng.uniform(low, high)) if high > low else low
        if kind == "product":
            occluder: _Occluder = _Product(visible, rng, products)
        elif kind == "gripper":
            occluder = _Gripper(visible, rng)
        elif kind == "suction":
            occluder = _Suction(visible, rng)
        else:
            occluder = _Edge(visible, rng, floor)
        side = float(max(visible.shape))
        if kind == "edge":  # a wall's shadow falls inwards, away from its side
            offset = occluder.at.u * rng.uniform(0.01, 0.04) * side
        else:
            light = rng.uniform(0.0, 2.0 * math.pi)
            offset = np.array([math.cos(light), math.sin(light)]) * rng.uniform(0.02, 0.06) * side
        sigma, strength = float(rng.uniform(0.015, 0.04) * side), float(rng.uniform(0.25, 0.55))
        factor, reach, alpha, _ = place(occluder, visible, target)
        shadowed = _shadow(image, alpha, offset, sigma, strength)
        colour = occluder.colour(factor, reach)
        out = np.clip(colour * alpha[..., None] + (1.0 - alpha[..., None]) * shadowed, 0.0, 1.0)
        new_visible = visible * (1.0 - alpha)
        info = {"occluder": kind, "hidden_fraction": 1.0 - float(new_visible.sum() / visible.sum()),
                "target_fraction": target, "shadow": strength, "size_factor": factor, "reach": reach,
                **occluder.info()}
        return out, new_visible, info
