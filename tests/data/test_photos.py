"""``data=images``: photos of planes, uniform-background segmentation, photographed anchors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image, ImageDraw

from matl.data.anchors import PhotoAnchors
from matl.data.datamodule import TripletDataModule
from matl.data.image_files import ImageFileError
from matl.data.photos import ImageFolderSource, Segmentation, segment_foreground
from matl.geometry import centre_rotation
from matl.utils.errors import MatlError
from tests.conftest import compose_config

SIZE = 32


def photo(size: tuple[int, int] = (160, 120), box: tuple[int, int, int, int] = (40, 30, 110, 95), seed: int = 0,
          background: tuple[int, int, int] = (200, 205, 210), angle: float = 0.0) -> tuple[Image.Image, np.ndarray]:
    """A product-like card on a uniform, slightly noisy background; returns the image and the true mask.

    The card carries a stripe in the *background* colour (a hole the segmentation must fill) and a
    letter; ``angle`` turns the whole card (counter-clockwise on screen) about the image centre.
    """
    rng = np.random.default_rng(seed)
    card = Image.new("RGBA", size, (0, 0, 0, 0))
    d = ImageDraw.Draw(card)
    colour = tuple(int(c) for c in rng.integers(30, 160, 3))
    d.rectangle(box, fill=(*colour, 255))
    d.rectangle((box[0] + 10, box[1] + 15, box[2] - 10, box[1] + 22), fill=(*background, 255))
    d.rectangle((box[0] + 8, box[3] - 20, box[0] + 30, box[3] - 8), fill=(250, 220, 40, 255))
    card = card.rotate(angle, resample=Image.Resampling.BICUBIC)
    base = np.asarray(Image.new("RGB", size, background)).astype(np.float32)
    base += rng.normal(0, 3, base.shape)
    alpha = np.asarray(card)[..., 3:4] / 255.0
    out = base * (1 - alpha) + np.asarray(card)[..., :3] * alpha
    return Image.fromarray(np.clip(out, 0, 255).astype(np.uint8)), alpha[..., 0] > 0.5


def test_segmentation_of_a_uniform_background() -> None:
    image, truth = photo()
    mask = segment_foreground(np.asarray(image, np.float32) / 255)
    iou = (mask & truth).sum() / (mask | truth).sum()
    assert iou > 0.97  # the background-coloured stripe inside is filled


def test_segmentation_keeps_the_largest_component_only() -> None:
    image, truth = photo()
    ImageDraw.Draw(image).rectangle((2, 2 + 10, 6, 16), fill=(10, 10, 10))  # a speck of dirt off the object
    mask = segment_foreground(np.asarray(image, np.float32) / 255, Segmentation(border=0.01))
    assert not mask[:20, :10].any() and (mask & truth).sum() / truth.sum() > 0.97


def make_root(tmp_path: Path) -> Path:
    root = tmp_path / "photos"
    (root / "box_a").mkdir(parents=True)
    photo(seed=1)[0].save(root / "box_a" / "front.jpg", quality=95)
    photo(seed=2)[0].save(root / "box_a" / "back.png")
    # a transparent render: the alpha is the mask
    rgba = Image.new("RGBA", (90, 90), (0, 0, 0, 0))
    ImageDraw.Draw(rgba).ellipse((10, 20, 80, 70), fill=(20, 120, 200, 255))
    ImageDraw.Draw(rgba).text((30, 35), "Hi", fill=(250, 250, 250, 255))
    (root / "can_b").mkdir()
    rgba.save(root / "can_b" / "top.png")
    (root / "can_b" / "side").mkdir()
    for angle in (0, 90, 180, 270):
        photo(seed=3, angle=angle)[0].save(root / "can_b" / "side" / f"{angle:03d}.png")
    (root / "README.txt").write_text("files directly in the root are ignored")
    return root


def test_image_folder_source_builds_framed_canonical_images(tmp_path: Path) -> None:
    source = ImageFolderSource(make_root(tmp_path), anchor_names="angle")
    cs = source.build(SIZE)
    assert cs.object_names == ["box_a", "can_b"] and cs.plane_names == ["back", "front", "side", "top"]
    assert cs.object_shapes == ["planar", "planar"]
    assert not cs.images[~cs.masks].any() and (cs.images[cs.masks] > 0).all()
    for p in range(cs.num_planes):  # catalog framing: larger side covers fill, centred
        ys, xs = np.nonzero(cs.masks[p])
        assert abs(max(np.ptp(xs), np.ptp(ys)) + 1 - 0.6 * SIZE) <= 1.5, cs.plane_label(p)
        assert np.allclose(((xs.min() + xs.max()) / 2, (ys.min() + ys.max()) / 2), (SIZE - 1) / 2, atol=1.0)


def test_photographed_anchors_by_angle(tmp_path: Path) -> None:
    source = ImageFolderSource(make_root(tmp_path), anchor_names="angle")
    dm = TripletDataModule(source, image_size=SIZE, num_anchors=4, train_triplets=16, val_queries=4, test_queries=8,
                           batch_size=4, eval_batch_size=4, cache_dir=tmp_path / "cache",
                           anchors=PhotoAnchors())  # fmt: skip
    dm.setup()
    side = dm.canonical.plane_names.index("side")
    expected = centre_rotation(torch.tensor([0.0, 90.0, 180.0, 270.0], dtype=torch.float64), (SIZE, SIZE))
    assert torch.allclose(dm.anchor_H_canon[side], expected)
    # each anchor is its photo, and agrees with the canonical image turned by its angle
    canon = dm.canon_images[side][None].repeat(4, 1, 1, 1)
    from matl.geometry import warp_image

    turned = warp_image(canon, expected.float())
    anchor_masks = dm.anchor_images[side].amax(1) > 0
    turned_masks = turned.amax(1) > 0.5
    iou = (anchor_masks & turned_masks).flatten(1).sum(1) / (anchor_masks | turned_masks).flatten(1).sum(1)
    assert (iou > 0.8).all(), iou
    # planes without a plane folder keep the fallback: fixed rotations of their canonical image
    front = dm.canonical.plane_names.index("front")
    assert torch.allclose(dm.anchor_H_canon[front], expected)
    assert torch.allclose(dm.anchor_images[front, 0], dm.canon_images[front], atol=1e-5)
    with pytest.raises(MatlError, match=r"can_b/side has 4 photographed anchors but N=3"):
        TripletDataModule(source, image_size=SIZE, num_anchors=3, cache_dir=tmp_path / "cache",
                          anchors=PhotoAnchors()).setup()  # fmt: skip


def test_photographed_anchors_by_index_are_identity(tmp_path: Path) -> None:
    root = make_root(tmp_path)
    for f in sorted((root / "can_b" / "side").iterdir()):
        f.rename(f.with_name(f"{int(f.stem) // 90}.png"))
    source = ImageFolderSource(root)
    photos = source.anchor_photos(SIZE)
    side = [p.plane for p in source.planes()].index("side")
    images, H = photos[side]
    assert images.shape == (4, SIZE, SIZE, 3) and np.allclose(H, np.eye(3))
    assert photos[0] is None


def test_bad_files_are_one_line_errors(tmp_path: Path) -> None:
    root = make_root(tmp_path)
    (root / "box_a" / "notes.png").write_text("not really a png")
    with pytest.raises(ImageFileError, match=r"notes\.png: not an image"):
        ImageFolderSource(root).build(SIZE)
    (root / "box_a" / "notes.png").unlink()
    (root / "empty_c").mkdir()
    with pytest.raises(MatlError, match=r"empty_c: empty object folder"):
        ImageFolderSource(root).build(SIZE)
    (root / "empty_c").rmdir()
    Image.new("RGB", (50, 50), (90, 90, 90)).save(root / "box_a" / "blank.png")
    with pytest.raises(ImageFileError, match=r"blank\.png: no object found"):
        ImageFolderSource(root).build(SIZE)
    with pytest.raises(MatlError, match="anchor_names"):
        ImageFolderSource(root, anchor_names="sorted")


def test_images_config_uses_photo_anchors(tmp_path: Path) -> None:
    cfg = compose_config("train", ["data=images", f"data.source.root={make_root(tmp_path)}"])
    assert cfg.data.anchors._target_ == "matl.data.anchors.PhotoAnchors"
    assert cfg.data.anchors.fallback._target_ == "matl.data.anchors.FixedAnchors"


def test_16_bit_grey_photos_keep_their_levels(tmp_path: Path) -> None:
    """A 16-bit grey PNG is scaled by 65535 (PIL's own conversion to RGB would clip it to white)."""
    rng = np.random.default_rng(0)
    grey = np.full((120, 160), 20000.0) + rng.normal(0, 150, (120, 160))  # background at 0.31 of full scale
    grey[30:95, 40:110] = 50000.0  # the object at 0.76
    grey[45:52, 50:100] = 20000.0  # a background-coloured stripe inside it (a hole the segmentation fills)
    (tmp_path / "photos" / "card").mkdir(parents=True)
    Image.fromarray(np.clip(grey, 0, 65535).astype(np.uint16)).save(tmp_path / "photos" / "card" / "front.png")
    assert Image.open(tmp_path / "photos" / "card" / "front.png").mode.startswith("I")
    cs = ImageFolderSource(tmp_path / "photos").build(SIZE)
    inside = cs.images[0][cs.masks[0]].astype(float)
    assert 0.28 < cs.masks[0].mean() < 0.4  # the 70 x 65 px card framed to 0.6 of the image: 19 x 18 of 32 x 32
    assert np.allclose(np.median(inside, axis=0), 50000 / 65535 * 255, atol=3)  # grey, not clipped to 255
    assert not cs.images[0][~cs.masks[0]].any()
