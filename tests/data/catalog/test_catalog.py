"""The embedded procedural catalog and the canonical-image cache."""

from __future__ import annotations

import os
import subprocess
import sys
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from matl.data.canonical import CanonicalSet, CanonicalSource, cache_path, load_canonical
from matl.data.catalog import CATALOG_COMPOSITIONS, PLANES_PER_SHAPE, SyntheticCatalog, contact_sheet

SIZE = 32  # small renders keep the module fast; the layout is resolution independent
TEXTURE_PX = 128
EXPECTED = {"arc": (34, 152), "ycb": (34, 240), "apc": (17, 90)}
ROOT = Path(__file__).resolve().parents[3]


@pytest.fixture(scope="module")
def built() -> dict[str, CanonicalSet]:
    """Every catalog rendered once at SIZE px."""
    return {name: SyntheticCatalog(name, texture_px=TEXTURE_PX).build(SIZE) for name in CATALOG_COMPOSITIONS}


def _masked_diff(a: np.ndarray, b: np.ndarray, ma: np.ndarray, mb: np.ndarray) -> np.ndarray:
    """Mean absolute difference (0-255 scale) over the union of foregrounds.

    a: (S, S, 3), b: (K, S, S, 3), masks (S, S) / (K, S, S). Returns (K,).
    """
    union = ma[None] | mb
    d = np.abs(a[None].astype(np.int16) - b.astype(np.int16)).mean(-1)
    return (d * union).sum((1, 2)) / union.sum((1, 2))


class FakeSource:
    """Tiny random source that counts its builds (and can be made to fail)."""

    def __init__(self, fail: bool = False) -> None:
        self.builds = 0
        self.fail = fail

    def cache_key(self) -> dict[str, Any]:
        return {"type": "fake", "v": 1}

    def build(self, image_size: int) -> CanonicalSet:
        self.builds += 1
        if self.fail:
            raise RuntimeError("builder failed")
        rng = np.random.default_rng(0)
        masks = np.zeros((3, image_size, image_size), bool)
        masks[:, 4:-4, 4:-4] = True
        images = rng.integers(1, 256, (3, image_size, image_size, 3), dtype=np.uint8) * masks[..., None]
        return CanonicalSet(
            images=images.astype(np.uint8),
            masks=masks,
            plane_object=np.array([0, 0, 1], np.int64),
            plane_names=["front", "back", "top"],
            object_names=["a", "b"],
            object_shapes=["planar", "cylindrical"],
        )


# --- composition -----------------------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_counts_match_the_paper(name: str, built: dict[str, CanonicalSet]) -> None:
    cs = built[name]
    n_obj, n_planes = EXPECTED[name]
    assert (cs.num_objects, cs.num_planes) == (n_obj, n_planes)
    cat = SyntheticCatalog(name)
    assert (cat.num_objects, cat.num_planes) == (n_obj, n_planes)
    for shape, n in CATALOG_COMPOSITIONS[name].items():
        assert cs.object_shapes.count(shape) == n
        assert sum(cs.object_shapes[o] == shape for o in cs.plane_object) == n * PLANES_PER_SHAPE[shape]
    assert len(set(cs.object_names)) == n_obj


def test_plane_names_per_shape(built: dict[str, CanonicalSet]) -> None:
    expected = {
        "planar": ["front", "back"],
        "rectangular": ["front", "back", "left", "right", "top", "bottom"],
        "cylindrical": ["top", "bottom"] + [f"side_{a:03d}" for a in range(0, 360, 45)],
    }
    cs = built["ycb"]
    for o, shape in enumerate(cs.object_shapes):
        names = [cs.plane_names[p] for p in np.flatnonzero(cs.plane_object == o)]
        assert names == expected[shape], cs.object_names[o]


def test_unknown_catalog_names_the_valid_ones() -> None:
    with pytest.raises(ValueError, match=r"arc.*apc|apc.*arc") as e:
        SyntheticCatalog("coco")
    assert "ycb" in str(e.value)


def test_products_differ_between_catalogs_and_seeds() -> None:
    arc = [p.name for p in SyntheticCatalog("arc").products()]
    assert arc == [p.name for p in SyntheticCatalog("arc").products()]
    assert arc != [p.name for p in SyntheticCatalog("arc", seed=1).products()]
    assert arc[:6] != [p.name for p in SyntheticCatalog("apc").products()][:6]


# --- images ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_background_mask_and_framing(name: str, built: dict[str, CanonicalSet]) -> None:
    cs = built[name]
    assert cs.images.shape == (cs.num_planes, SIZE, SIZE, 3) and cs.images.dtype == np.uint8
    assert cs.masks.dtype == np.bool_
    # Background exactly 0, and print never reaches 0, so the mask is exactly the non-zero pixels.
    assert not cs.images[~cs.masks].any()
    assert np.array_equal(cs.masks, cs.images.max(-1) > 0)
    assert cs.masks.reshape(cs.num_planes, -1).any(1).all()
    border = cs.masks[:, 0].any(1) | cs.masks[:, -1].any(1) | cs.masks[:, :, 0].any(1) | cs.masks[:, :, -1].any(1)
    assert not border.any()
    # Scale decision: each plane's larger extent covers `fill` (0.6) of the width, centred.
    for p in range(cs.num_planes):
        ys, xs = np.nonzero(cs.masks[p])
        extent = max(xs.max() - xs.min() + 1, ys.max() - ys.min() + 1)
        assert abs(extent - 0.6 * SIZE) <= 1.5, cs.plane_label(p)
        centre = ((xs.min() + xs.max()) / 2, (ys.min() + ys.max()) / 2)
        assert np.allclose(centre, (SIZE - 1) / 2, atol=1.0), cs.plane_label(p)


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_distinct_planes_differ(name: str, built: dict[str, CanonicalSet]) -> None:
    cs = built[name]
    worst = (np.inf, -1, -1)
    for i in range(cs.num_planes - 1):
        d = _masked_diff(cs.images[i], cs.images[i + 1 :], cs.masks[i], cs.masks[i + 1 :])
        j = int(d.argmin())
        if d[j] < worst[0]:
            worst = (float(d[j]), i, i + 1 + j)
    assert worst[0] > 5.0, f"{cs.plane_label(worst[1])} ~ {cs.plane_label(worst[2])}: {worst[0]:.2f}"


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_prints_have_an_up_direction(name: str, built: dict[str, CanonicalSet]) -> None:
    """No canonical image looks the same turned by 180 deg (pose would be ambiguous)."""
    cs = built[name]
    turned, turned_masks = cs.images[:, ::-1, ::-1], cs.masks[:, ::-1, ::-1]
    for p in range(cs.num_planes):
        d = _masked_diff(cs.images[p], turned[p : p + 1], cs.masks[p], turned_masks[p : p + 1])[0]
        assert d > 8.0, f"{cs.plane_label(p)} is nearly 180-degree symmetric ({d:.2f})"


def test_deterministic_and_cached_round_trip(built: dict[str, CanonicalSet], tmp_path: Path) -> None:
    source = SyntheticCatalog("apc", texture_px=TEXTURE_PX)
    again = load_canonical(source, SIZE, tmp_path)  # builds afresh, then caches
    ref = built["apc"]
    assert again.images.tobytes() == ref.images.tobytes()
    assert np.array_equal(again.masks, ref.masks)
    assert again.plane_names == ref.plane_names and again.object_names == ref.object_names
    assert cache_path(source, SIZE, tmp_path).exists()

    def no_build(*args: Any, **kwargs: Any) -> CanonicalSet:
        raise AssertionError("should have loaded from the cache")

    source.build = no_build  # type: ignore[method-assign]
    loaded = load_canonical(source, SIZE, tmp_path)
    assert loaded.images.tobytes() == ref.images.tobytes()
    assert np.array_equal(loaded.plane_object, ref.plane_object) and loaded.plane_object.dtype == np.int64
    assert loaded.object_shapes == ref.object_shapes


def test_cache_key_tracks_parameters(tmp_path: Path) -> None:
    paths = {
        cache_path(SyntheticCatalog(**kw), size, tmp_path)
        for kw, size in [({}, 100), ({}, 64), ({"seed": 1}, 100), ({"fill": 0.5}, 100), ({"catalog": "ycb"}, 100)]
    }
    assert len(paths) == 5
    assert cache_path(SyntheticCatalog(), 100, tmp_path) == cache_path(SyntheticCatalog("arc", 0), 100, tmp_path)


# --- cache -----------------------------------------------------------------------------------------


def test_cache_loads_without_rebuilding(tmp_path: Path) -> None:
    src = FakeSource()
    first = load_canonical(src, 16, tmp_path)
    second = load_canonical(src, 16, tmp_path)
    assert src.builds == 1
    assert np.array_equal(first.images, second.images) and second.plane_names == ["front", "back", "top"]
    assert isinstance(src, CanonicalSource)


@pytest.mark.parametrize("damage", ["garbage", "truncated", "missing_arrays"])
def test_corrupt_cache_is_rebuilt(tmp_path: Path, damage: str) -> None:
    src = FakeSource()
    good = load_canonical(src, 16, tmp_path)
    path = cache_path(src, 16, tmp_path)
    if damage == "garbage":
        path.write_bytes(b"not an npz at all")
    elif damage == "truncated":
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    else:
        with open(path, "wb") as f:
            np.savez(f, images=good.images)
    with pytest.warns(RuntimeWarning, match="rebuilding"):
        rebuilt = load_canonical(src, 16, tmp_path)
    assert src.builds == 2
    assert np.array_equal(rebuilt.images, good.images)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the rewritten file is healthy again
        load_canonical(src, 16, tmp_path)
    assert src.builds == 2


def test_failed_build_leaves_no_file(tmp_path: Path) -> None:
    with pytest.raises(RuntimeError, match="builder failed"):
        load_canonical(FakeSource(fail=True), 16, tmp_path / "cache")
    assert not (tmp_path / "cache").exists() or not any((tmp_path / "cache").iterdir())


def test_interrupted_write_is_atomic(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A crash halfway through writing leaves neither a partial cache nor a temp file."""
    src = FakeSource()

    def half_write(file: Any, **arrays: Any) -> None:
        file.write(b"PK\x03\x04 half an archive")
        raise KeyboardInterrupt

    monkeypatch.setattr(np, "savez_compressed", half_write)
    with pytest.raises(KeyboardInterrupt):
        load_canonical(src, 16, tmp_path)
    assert list(tmp_path.iterdir()) == []


# --- CanonicalSet ----------------------------------------------------------------------------------


def test_subset_objects_reindexes() -> None:
    cs = FakeSource().build(16)
    sub = cs.subset_objects([1, 0])
    assert sub.object_names == ["b", "a"] and sub.object_shapes == ["cylindrical", "planar"]
    assert sub.plane_names == ["top", "front", "back"]
    assert sub.plane_object.tolist() == [0, 1, 1] and sub.plane_object.dtype == np.int64
    assert np.array_equal(sub.images[0], cs.images[2])
    only = cs.subset_objects(np.array([1]))
    assert (only.num_objects, only.num_planes) == (1, 1)
    with pytest.raises(ValueError):
        cs.subset_objects([0, 0])
    with pytest.raises(IndexError):
        cs.subset_objects([2])


def test_canonical_set_validates_shapes() -> None:
    cs = FakeSource().build(16)
    with pytest.raises(ValueError):
        CanonicalSet(cs.images, cs.masks[:2], cs.plane_object, cs.plane_names, cs.object_names, cs.object_shapes)
    with pytest.raises(ValueError):
        CanonicalSet(cs.images, cs.masks, cs.plane_object, cs.plane_names, cs.object_names, ["planar", "sphere"])


# --- entry point -----------------------------------------------------------------------------------


def test_contact_sheet_shows_every_plane(tmp_path: Path) -> None:
    # 23 planes of 5 objects, each plane a unique solid colour (not used by the sheet's chrome).
    n, size = 23, 20
    masks = np.zeros((n, size, size), bool)
    masks[:, 5:15, 3:17] = True
    colours = np.stack([np.arange(n) * 9 + 20, np.full(n, 7), np.full(n, 201)], 1).astype(np.uint8)
    cs = CanonicalSet(
        images=(masks[..., None] * colours[:, None, None, :]).astype(np.uint8),
        masks=masks,
        plane_object=np.repeat(np.arange(5), [2, 6, 10, 3, 2]).astype(np.int64),
        plane_names=[f"p{i}" for i in range(n)],
        object_names=[f"object_{o}" for o in range(5)],
        object_shapes=["planar", "rectangular", "cylindrical", "nonplanar", "planar"],
    )
    sheet = contact_sheet(cs, tmp_path / "sheet.png", cell=size, max_cols=8)
    assert (tmp_path / "sheet.png").exists() and sheet.mode == "RGB"
    pixels = np.asarray(sheet).reshape(-1, 3)
    for c in colours:  # every plane drawn once, unscaled
        assert (pixels == c).all(1).sum() == masks[0].sum()


def test_render_cli(tmp_path: Path) -> None:
    """``python -m matl.render data=synthetic_apc`` builds the cache and writes gallery.png."""
    run_dir, cache = tmp_path / "run", tmp_path / "cache"
    cmd = [
        sys.executable, "-m", "matl.render", "data=synthetic_apc", "data.image_size=24",
        "+data.source.texture_px=64", f"paths.cache_dir={cache}", f"hydra.run.dir={run_dir}",
    ]  # fmt: skip
    env = {**os.environ, "PYOPENGL_PLATFORM": os.environ.get("PYOPENGL_PLATFORM", "egl")}
    out = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    assert (run_dir / "gallery.png").exists()
    assert len(list(cache.glob("canonical_*.npz"))) == 1
    assert "90" in out.stdout and "17" in out.stdout and "cylindrical" in out.stdout
