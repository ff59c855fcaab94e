"""Training positives and negatives that look like a camera's crops (``data.augment``; beyond the paper).

The paper trains on canonical images warped onto a black background. A robot camera sees other
light, a blurred and noisy sensor, JPEG, an imperfect segmentation mask, or no mask at all with a
shelf behind the product. :class:`CameraAugment` turns a batch of clean warped images (and their
warped foreground masks) into such crops, per image, in one of three framings:

* ``clean``: the warp as it is (black background), photometric changes on the product only;
* ``masked``: the product in front of a background, then cut out by an *imperfect* mask (the true
  mask dilated or eroded by up to ``mask_error_px`` px, with a ragged edge), as ``matl.predict``
  cuts out an RGBA query by its alpha: some background shows, some product is lost;
* ``clutter``: the product in front of a background, no mask (a detector's box).

Backgrounds come from a bank built once per run (:meth:`CameraAugment.setup`) from training
sources only: smooth colour fields, stripes and checks, crops of matplotlib's sample photos and
terrain data, shelves of the training catalog's own products, and (``textures``, off by default)
procedural natural-looking textures; ``grey_p`` of them turned grey; with probability
``neighbour_p`` a neighbouring product of the catalog is put beside the product, cut by the frame.
Then the photometric changes of :class:`Photometric` (gain, bias, gamma, tint, blur, noise, JPEG).
The anchors (gallery images) are never augmented.

Randomness: each call takes a generator; the datamodule seeds it per batch from the triplets'
``aug_seed`` column, so a batch looks the same whenever it is made (resumes included).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from kornia.filters import gaussian_blur2d

from matl.utils.errors import MatlError

MODES = ("clean", "masked", "clutter")


def _uniform(n: int, low_high: tuple[float, float], g: torch.Generator) -> torch.Tensor:
    low, high = float(low_high[0]), float(low_high[1])
    return low + (high - low) * torch.rand(n, generator=g)


@dataclass
class Photometric:
    """Per-image photometric changes of a camera, each drawn independently.

    ``out = clamp(gain * tint_c * x + bias, 0, 1) ** gamma``, then with probability ``blur_p`` a
    Gaussian blur (sigma in ``blur_sigma`` px), Gaussian sensor noise of std in ``noise_std``, and
    with probability ``jpeg_p`` a JPEG round trip at a quality in ``jpeg_quality``. ``p`` is the
    probability that an image gets any of it.
    """

    p: float = 0.8
    gain: tuple[float, float] = (0.6, 1.4)
    bias: tuple[float, float] = (-0.08, 0.08)
    gamma: tuple[float, float] = (0.7, 1.5)
    tint: float = 0.12
    blur_p: float = 0.4
    blur_sigma: tuple[float, float] = (0.3, 1.3)
    noise_std: tuple[float, float] = (0.0, 0.03)
    jpeg_p: float = 0.3
    jpeg_quality: tuple[int, int] = (30, 90)

    def __call__(self, images: torch.Tensor, g: torch.Generator) -> torch.Tensor:
        """``(B, 3, H, W)`` in [0, 1] -> the same shape, changed per image."""
        B = images.shape[0]
        on = torch.rand(B, generator=g) < self.p
        gain = torch.where(on, _uniform(B, self.gain, g), torch.ones(B))
        tint = 1.0 + self.tint * (2.0 * torch.rand(B, 3, generator=g) - 1.0)
        tint = torch.where(on[:, None], tint, torch.ones(B, 3))
        bias = torch.where(on, _uniform(B, self.bias, g), torch.zeros(B))
        # log-uniform gamma, so darkening and brightening are equally likely
        lo, hi = math.log(self.gamma[0]), math.log(self.gamma[1])
        gamma = torch.where(on, torch.exp(_uniform(B, (lo, hi), g)), torch.ones(B))
        dev = images.device
        scale = (gain[:, None] * tint)[:, :, None, None].to(dev)
        out = (images * scale + bias[:, None, None, None].to(dev)).clamp(0.0, 1.0)
        out = out.clamp_min(1e-6) ** gamma[:, None, None, None].to(dev)
        blur = on & (torch.rand(B, generator=g) < self.blur_p)
        sigma = _uniform(B, self.blur_sigma, g)
        if blur.any():
            idx = blur.nonzero().squeeze(1).to(dev)
            s = sigma[blur].to(dev, out.dtype)
            out[idx] = gaussian_blur2d(out[idx], (7, 7), torch.stack([s, s], 1))
        std = torch.where(on, _uniform(B, self.noise_std, g), torch.zeros(B))
        noise = torch.randn(out.shape, generator=g).to(dev, out.dtype)
        out = (out + noise * std[:, None, None, None].to(dev, out.dtype)).clamp(0.0, 1.0)
        jpeg = on & (torch.rand(B, generator=g) < self.jpeg_p)
        quality = torch.randint(int(self.jpeg_quality[0]), int(self.jpeg_quality[1]) + 1, (B,), generator=g)
        for i in jpeg.nonzero().squeeze(1).tolist():
            out[i] = jpeg_round_trip(out[i], int(quality[i]))
        return out


def jpeg_round_trip(image: torch.Tensor, quality: int) -> torch.Tensor:
    """``(3, H, W)`` in [0, 1] encoded as JPEG at ``quality`` (OpenCV) and decoded again."""
    rgb = (image.detach().cpu().clamp(0, 1) * 255.0).round().to(torch.uint8).permute(1, 2, 0).numpy()
    ok, data = cv2.imencode(".jpg", np.ascontiguousarray(rgb[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        return image
    back = cv2.imdecode(data, cv2.IMREAD_COLOR)[..., ::-1].copy()
    return torch.from_numpy(back).permute(2, 0, 1).to(image.device, image.dtype).div(255.0)


def imperfect_masks(masks: torch.Tensor, max_px: int, ragged: float, g: torch.Generator) -> torch.Tensor:
    """A segmentation's errors: ``(B, 1, H, W)`` {0, 1} masks dilated or eroded by ``-max_px..max_px`` px
    (drawn per mask) and, with ``ragged > 0``, an edge moved in and out by smooth noise of that amplitude
    (in px). Returns float {0, 1} masks of the same shape."""
    B, _, H, W = masks.shape
    radius = torch.randint(-int(max_px), int(max_px) + 1, (B,), generator=g)
    out = masks.float().clone()
    for r in radius.unique().tolist():
        if r == 0:
            continue
        idx = (radius == r).nonzero().squeeze(1).to(masks.device)
        k = 2 * abs(r) + 1
        m = out[idx]
        out[idx] = F.max_pool2d(m, k, 1, abs(r)) if r > 0 else -F.max_pool2d(-m, k, 1, abs(r))
    if ragged > 0:
        noise = torch.rand(B, 1, max(2, H // 12), max(2, W // 12), generator=g).to(masks.device)
        noise = F.interpolate(noise, size=(H, W), mode="bicubic", align_corners=False)
        # a soft edge (distance-like ramp of ~ragged px) thresholded at a noisy level
        k = 2 * max(1, round(ragged)) + 1
        soft = F.avg_pool2d(out, k, 1, k // 2, count_include_pad=False)
        out = (soft > 0.25 + 0.5 * noise).float()
    return out


# ------------------------------------------------------------------------------- backgrounds
def _smooth_fields(n: int, size: int, g: torch.Generator) -> torch.Tensor:
    cells = torch.randint(2, 9, (1,), generator=g).item()
    low = torch.rand(n, 3, cells, cells, generator=g)
    fine = torch.rand(n, 3, size // 4, size // 4, generator=g)
    field_ = F.interpolate(low, size=(size, size), mode="bicubic", align_corners=False)
    field_ = field_ + 0.15 * (F.interpolate(fine, size=(size, size), mode="bilinear", align_corners=False) - 0.5)
    return field_.clamp(0.0, 1.0)


def _patterns(n: int, size: int, g: torch.Generator) -> torch.Tensor:
    v, u = torch.meshgrid(torch.arange(size, dtype=torch.float32), torch.arange(size, dtype=torch.float32),
                          indexing="ij")
    out = []
    for _ in range(n):
        angle = float(torch.rand(1, generator=g)) * math.pi
        period = 4.0 + 28.0 * float(torch.rand(1, generator=g))
        a, b = torch.rand(3, 1, 1, generator=g), torch.rand(3, 1, 1, generator=g)
        t = (u * math.cos(angle) + v * math.sin(angle)) / period
        if float(torch.rand(1, generator=g)) < 0.5:  # stripes
            w = (torch.sin(2 * math.pi * t) > 0).float()
        else:  # checks
            s = (-u * math.sin(angle) + v * math.cos(angle)) / period
            w = ((torch.floor(t) + torch.floor(s)) % 2).float()
        out.append(a * w + b * (1 - w))
    return torch.stack(out)


def _matplotlib_pictures() -> list[np.ndarray]:
    """matplotlib's sample photos and terrain data as ``(H, W, 3)`` float images in [0, 1]."""
    import matplotlib
    from matplotlib import colormaps

    root = Path(matplotlib.get_data_path()) / "sample_data"
    pictures = []
    for name in ("grace_hopper.jpg", "Minduka_Present_Blue_Pack.png"):
        image = cv2.imread(str(root / name), cv2.IMREAD_COLOR)
        if image is not None:
            pictures.append(image[..., ::-1].astype(np.float32) / 255.0)
    for name, key, cmap in (("jacksboro_fault_dem.npz", "elevation", "gist_earth"),
                            ("topobathy.npz", "topo", "terrain")):
        try:
            with np.load(root / name) as data:
                z = data[key].astype(np.float64)
        except (OSError, KeyError):
            continue
        z = (z - z.min()) / max(float(z.max() - z.min()), 1e-9)
        pictures.append(colormaps[cmap](z)[..., :3].astype(np.float32))
    return pictures


def _picture_crops(n: int, size: int, g: torch.Generator) -> torch.Tensor:
    pictures = _matplotlib_pictures()
    if not pictures:
        return _smooth_fields(n, size, g)
    out = []
    for _ in range(n):
        pic = pictures[int(torch.randint(len(pictures), (1,), generator=g))]
        h, w = pic.shape[:2]
        side = int(min(h, w) * (0.2 + 0.6 * float(torch.rand(1, generator=g))))
        y = int(torch.randint(h - side + 1, (1,), generator=g))
        x = int(torch.randint(w - side + 1, (1,), generator=g))
        crop = cv2.resize(pic[y:y + side, x:x + side], (size, size), interpolation=cv2.INTER_AREA)
        out.append(torch.from_numpy(np.ascontiguousarray(crop)).permute(2, 0, 1))
    return torch.stack(out).clamp(0.0, 1.0)


def _shelves(n: int, size: int, canon: torch.Tensor, masks: torch.Tensor, g: torch.Generator) -> torch.Tensor:
    """Products of the catalog side by side (2 x 2 or 3 x 3 tight crops) over a smooth field."""
    out = _smooth_fields(n, size, g)
    for i in range(n):
        cells = int(torch.randint(2, 4, (1,), generator=g))
        cell = size // cells
        for r in range(cells):
            for c in range(cells):
                p = int(torch.randint(len(canon), (1,), generator=g))
                m = masks[p, 0] > 0.5
                if not m.any():
                    continue
                rows, cols = m.any(1).nonzero().squeeze(1), m.any(0).nonzero().squeeze(1)
                crop = canon[p, :, int(rows[0]):int(rows[-1]) + 1, int(cols[0]):int(cols[-1]) + 1]
                crop_m = masks[p, :, int(rows[0]):int(rows[-1]) + 1, int(cols[0]):int(cols[-1]) + 1]
                crop = F.interpolate(crop[None], size=(cell, cell), mode="bilinear", align_corners=False)[0]
                crop_m = F.interpolate(crop_m[None], size=(cell, cell), mode="nearest")[0]
                tile = out[i, :, r * cell:(r + 1) * cell, c * cell:(c + 1) * cell]
                out[i, :, r * cell:(r + 1) * cell, c * cell:(c + 1) * cell] = crop * crop_m + tile * (1 - crop_m)
    return out


def _fractal(rng: np.random.Generator, size: int, roughness: float) -> np.ndarray:
    """``(size, size)`` float noise in [0, 1]: octaves of random grids, each halving the cell and weighted by
    ``roughness`` ** octave (near 0: smooth blotches; near 1: fine grain)."""
    out, weight, total, cells = np.zeros((size, size), np.float32), 1.0, 0.0, 2
    while cells <= size:
        grid = rng.random((cells, cells), dtype=np.float32)
        out += weight * cv2.resize(grid, (size, size), interpolation=cv2.INTER_CUBIC)
        total, weight, cells = total + weight, weight * roughness, cells * 2
    out /= total
    return (out - out.min()) / max(float(out.max() - out.min()), 1e-6)


def _pebbles(rng: np.random.Generator, size: int) -> np.ndarray:
    """``(size, size)`` float grey levels in [0, 1]: overlapping shaded stones (ellipses lit from one side)."""
    image = np.full((size, size), rng.uniform(0.1, 0.5), np.float32)
    radius = rng.uniform(0.03, 0.12) * size
    light = rng.uniform(0, 2 * math.pi)
    for _ in range(int(3.0 * (size / radius) ** 2)):
        cx, cy = rng.uniform(-radius, size + radius, 2)
        axes = (max(1, int(radius * rng.uniform(0.5, 1.3))), max(1, int(radius * rng.uniform(0.4, 1.0))))
        tone = float(np.clip(rng.normal(0.5, 0.18), 0.05, 0.95))
        stone = np.zeros((size, size), np.uint8)
        cv2.ellipse(stone, (int(cx), int(cy)), axes, float(rng.uniform(0, 180)), 0, 360, 1, -1)
        inside = stone > 0
        if not inside.any():
            continue
        v, u = np.nonzero(inside)
        shade = ((u - cx) * math.cos(light) + (v - cy) * math.sin(light)) / max(axes)
        image[v, u] = np.clip(tone * (1.0 + 0.35 * shade), 0.0, 1.0)
    return image


def _fibres(rng: np.random.Generator, size: int) -> np.ndarray:
    """``(size, size)`` float grey levels in [0, 1]: short strokes around one direction (grass, hair, fabric)."""
    image = np.full((size, size), rng.uniform(0.1, 0.6), np.float32)
    angle, spread = rng.uniform(0, math.pi), rng.uniform(0.1, 1.2)
    length = rng.uniform(0.05, 0.3) * size
    for _ in range(int(rng.uniform(4, 12) * size)):
        a = angle + rng.normal(0.0, spread)
        x, y = rng.uniform(0, size, 2)
        end = (int(x + length * math.cos(a)), int(y + length * math.sin(a)))
        cv2.line(image, (int(x), int(y)), end, float(rng.uniform(0.0, 1.0)), 1, cv2.LINE_AA)
    return image


def _grain(rng: np.random.Generator, size: int) -> np.ndarray:
    """``(size, size)`` float levels in [0, 1]: bands bent by noise (wood, marble, strata)."""
    v, u = np.mgrid[0:size, 0:size].astype(np.float32) / size
    angle = rng.uniform(0, math.pi)
    t = u * math.cos(angle) + v * math.sin(angle)
    bend = _fractal(rng, size, rng.uniform(0.3, 0.6))
    return 0.5 + 0.5 * np.sin(2 * math.pi * (rng.uniform(3, 15) * t + rng.uniform(0.5, 4.0) * bend))


def _textures(n: int, size: int, g: torch.Generator) -> torch.Tensor:
    """``(n, 3, size, size)`` natural-looking textures: fractal noise, stones, strokes and bent bands, in grey
    or between two random colours, with fine grain."""
    rng = np.random.default_rng(int(torch.randint(2**31, (1,), generator=g)))
    makers = (lambda: _fractal(rng, size, rng.uniform(0.3, 0.9)), lambda: _pebbles(rng, size),
              lambda: _fibres(rng, size), lambda: _grain(rng, size))
    out = []
    for i in range(n):
        level = makers[i % len(makers)]()
        if rng.random() < 0.5:  # grey, with its own contrast
            low, high = sorted(rng.uniform(0.0, 1.0, 2))
            colours = np.stack([np.full(3, low), np.full(3, high)])
        else:
            colours = rng.uniform(0.0, 1.0, (2, 3))
        image = colours[0] + level[..., None] * (colours[1] - colours[0])
        image = image + rng.uniform(0.0, 0.06) * (rng.random((size, size, 1)) - 0.5)
        out.append(torch.from_numpy(np.clip(image, 0.0, 1.0).astype(np.float32)).permute(2, 0, 1))
    return torch.stack(out)


def _greyed(images: torch.Tensor, p: float, g: torch.Generator) -> torch.Tensor:
    """``images`` ``(N, 3, H, W)`` with each turned grey (its luminance in every channel) with probability ``p``."""
    grey = torch.rand(len(images), generator=g) < p
    if grey.any():
        luma = (0.299 * images[grey, 0] + 0.587 * images[grey, 1] + 0.114 * images[grey, 2])[:, None]
        images[grey] = luma.expand(-1, 3, -1, -1)
    return images


def _shifted(image: torch.Tensor, dx: int, dy: int) -> torch.Tensor:
    """``(C, H, W)`` moved by whole pixels (``dx`` right, ``dy`` down), zeros where it left the frame."""
    _, H, W = image.shape
    out = torch.zeros_like(image)
    if abs(dx) >= W or abs(dy) >= H:
        return out
    out[:, max(dy, 0):H + min(dy, 0), max(dx, 0):W + min(dx, 0)] = \
        image[:, max(-dy, 0):H - max(dy, 0), max(-dx, 0):W - max(dx, 0)]
    return out


@dataclass
class CameraAugment:
    """Camera-like positives and negatives (see the module docstring).

    Args:
        modes: probability of each framing (``clean``, ``masked``, ``clutter``); normalised.
        photometric: :class:`Photometric` settings (a mapping or the object).
        mask_error_px: largest dilation / erosion of the ``masked`` framing's mask, px at the model size.
        ragged: amplitude in px of the mask edge's ragged noise (0: a clean edge).
        neighbour_p: probability that a neighbouring product is put beside the product.
        bank: number of background images built per run: ``textures`` of them natural-looking textures
            (:func:`_textures`), the rest a quarter of each of the other kinds.
        textures: share of the bank that is textures (fractal noise, stones, strokes, bent bands; 0: none).
        grey_p: probability that a bank image is turned grey (many real backgrounds have no colour).
        seed: seeds the background bank.
    """

    modes: dict[str, float] = field(default_factory=lambda: {"clean": 0.2, "masked": 0.4, "clutter": 0.4})
    photometric: Any = field(default_factory=Photometric)
    mask_error_px: int = 3
    ragged: float = 1.5
    neighbour_p: float = 0.5
    bank: int = 256
    textures: float = 0.0
    grey_p: float = 0.0
    seed: int = 0

    def __post_init__(self) -> None:
        if isinstance(self.photometric, Mapping):
            self.photometric = Photometric(**{k: v for k, v in self.photometric.items() if k != "_target_"})
        unknown = sorted(set(self.modes) - set(MODES))
        if unknown or not self.modes or any(float(v) < 0 for v in self.modes.values()) \
                or sum(float(v) for v in self.modes.values()) <= 0:
            raise MatlError(f"data.augment.modes={dict(self.modes)} is invalid: give non-negative weights of "
                            f"{list(MODES)} with a positive sum")
        if int(self.mask_error_px) < 0 or self.ragged < 0 or not 0 <= self.neighbour_p <= 1 or int(self.bank) < 4:
            raise MatlError("data.augment: mask_error_px and ragged must be >= 0, neighbour_p in [0, 1], bank >= 4")
        if not 0.0 <= float(self.textures) < 1.0 or not 0.0 <= float(self.grey_p) <= 1.0:
            raise MatlError(f"data.augment: textures={self.textures}, grey_p={self.grey_p}: use a share of the bank in "
                            "[0, 1) and a probability in [0, 1] (0: none)")
        self._bank: torch.Tensor | None = None

    def setup(self, canon_images: torch.Tensor, canon_masks: torch.Tensor) -> None:
        """Build the background bank from the training catalog's ``(P, 3, S, S)`` images and
        ``(P, 1, S, S)`` masks (float {0, 1}), and keep them for neighbouring products."""
        g = torch.Generator().manual_seed(int(self.seed))
        size = canon_images.shape[-1]
        n_textures = round(int(self.bank) * float(self.textures))
        rest = int(self.bank) - n_textures
        k = rest // 4
        kinds = [_smooth_fields(k, size, g), _patterns(k, size, g), _picture_crops(k, size, g),
                 _shelves(rest - 3 * k, size, canon_images, canon_masks, g)]
        if n_textures:
            kinds.append(_textures(n_textures, size, g))
        bank = torch.cat(kinds).float()
        self._bank = (_greyed(bank, float(self.grey_p), g) if self.grey_p > 0 else bank).contiguous()
        self._canon, self._masks = canon_images.float(), canon_masks.float()
        self._device_cache: dict[torch.device, tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = {}

    def _on(self, device: torch.device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        if device not in self._device_cache:
            self._device_cache[device] = (self._bank.to(device), self._canon.to(device), self._masks.to(device))
        return self._device_cache[device]

    def backgrounds(self, n: int, device: torch.device, g: torch.Generator) -> torch.Tensor:
        """``(n, 3, S, S)`` backgrounds: a bank image flipped / rotated by 90 degree steps, and with
        probability ``neighbour_p`` a catalog product beside the centre, cut by the frame."""
        if self._bank is None:
            raise RuntimeError("CameraAugment.setup() must run before it is called")
        bank, canon, masks = self._on(device)
        size = bank.shape[-1]
        out = bank[torch.randint(len(bank), (n,), generator=g).to(device)].clone()
        turns = torch.randint(4, (n,), generator=g)
        for t in range(1, 4):
            idx = (turns == t).nonzero().squeeze(1).to(device)
            if len(idx):
                out[idx] = torch.rot90(out[idx], t, dims=(2, 3))
        near = torch.rand(n, generator=g) < self.neighbour_p
        for i in near.nonzero().squeeze(1).tolist():  # a neighbour: a product turned by 90 degree steps, shifted
            p = int(torch.randint(len(canon), (1,), generator=g))
            turn = int(torch.randint(4, (1,), generator=g))
            img, msk = torch.rot90(canon[p], turn, dims=(1, 2)), torch.rot90(masks[p], turn, dims=(1, 2))
            reach = int(size * (0.45 + 0.3 * float(torch.rand(1, generator=g))))
            along = int(size * 0.25 * (2 * float(torch.rand(1, generator=g)) - 1))
            side = int(torch.randint(4, (1,), generator=g))
            dx, dy = [(reach, along), (-reach, along), (along, reach), (along, -reach)][side]
            img, msk = _shifted(img, dx, dy), _shifted(msk, dx, dy)
            out[i] = img * msk + out[i] * (1 - msk)
        return out

    def __call__(self, images: torch.Tensor, masks: torch.Tensor, g: torch.Generator) -> torch.Tensor:
        """``(B, 3, S, S)`` clean warps (background 0) and their ``(B, 1, S, S)`` {0, 1} masks -> camera-like
        crops of the same shape, each in a framing drawn from ``modes``."""
        if images.ndim != 4 or masks.shape != (images.shape[0], 1, *images.shape[2:]):
            raise ValueError(f"images must be (B, 3, S, S) and masks (B, 1, S, S), got {tuple(images.shape)} and "
                             f"{tuple(masks.shape)}")
        B, device = images.shape[0], images.device
        weights = torch.tensor([float(self.modes.get(m, 0.0)) for m in MODES])
        mode = torch.multinomial(weights / weights.sum(), B, replacement=True, generator=g).to(device)
        masks = masks.float()
        scene = images * masks + self.backgrounds(B, device, g) * (1 - masks)
        cut = imperfect_masks(masks, int(self.mask_error_px), float(self.ragged), g)
        framed = torch.where((mode == 0)[:, None, None, None], images, scene)
        shot = self.photometric(framed, g)
        keep = torch.where((mode == 0)[:, None, None, None], masks,
                           torch.where((mode == 1)[:, None, None, None], cut, torch.ones_like(masks)))
        return shot * keep
