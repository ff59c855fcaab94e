"""Non-planar procedural products (Sec. 5.8, Table 2) and the catalog's planar / non-planar subsets."""

from __future__ import annotations

import numpy as np
import pytest

from matl.data.canonical import CanonicalSet
from matl.data.catalog import SyntheticCatalog
from matl.data.catalog.nonplanar import NONPLANAR_COMPOSITION, nonplanar_model, sample_nonplanar
from tests.conftest import compose_config

SIZE = 32
TEXTURE_PX = 64


@pytest.fixture(scope="module")
def nonplanar() -> CanonicalSet:
    return SyntheticCatalog("ycb", subset="nonplanar", texture_px=TEXTURE_PX).build(SIZE)


@pytest.mark.parametrize(
    "catalog,subset,objects,planes",
    [
        ("ycb", "planar", 34, 240),
        ("ycb", "nonplanar", 23, 210),
        ("ycb", "all", 57, 450),
        ("ycb_table2", "all", 34, 284),
        ("ycb_table2", "planar", 11, 74),
        ("ycb_table2", "nonplanar", 23, 210),
        ("arc", "all", 34, 152),
    ],
)
def test_subset_counts(catalog: str, subset: str, objects: int, planes: int) -> None:
    cat = SyntheticCatalog(catalog, subset=subset)
    assert (cat.num_objects, cat.num_planes) == (objects, planes)
    specs = cat.products()
    assert len(specs) == objects and len({s.name for s in specs}) == objects


def test_default_keeps_the_design_set_and_its_cache_key() -> None:
    cat = SyntheticCatalog("ycb")
    assert (cat.num_objects, cat.num_planes) == (34, 240)
    assert "subset" not in cat.cache_key() and "nonplanar" not in cat.cache_key()
    assert SyntheticCatalog("ycb", subset="all").cache_key() != cat.cache_key()
    cfg = compose_config("train", ["data=synthetic_ycb"])
    assert cfg.data.source.subset == "planar"
    t2 = compose_config("train", ["data=synthetic_ycb_table2", "data.source.subset=nonplanar"])
    assert t2.data.source.catalog == "ycb_table2" and t2.data.source.subset == "nonplanar"


def test_table2_simple_objects_are_those_of_synthetic_ycb() -> None:
    ycb = {s.name: s for s in SyntheticCatalog("ycb").products()}
    simple = SyntheticCatalog("ycb_table2", subset="planar").products()
    assert [s.shape for s in simple] == ["planar"] * 2 + ["rectangular"] * 5 + ["cylindrical"] * 4
    assert all(ycb[s.name] == s for s in simple)
    assert SyntheticCatalog("ycb_table2", subset="nonplanar").products() == sample_nonplanar(0)


def test_invalid_subsets_are_named() -> None:
    with pytest.raises(ValueError, match="no non-planar"):
        SyntheticCatalog("arc", subset="nonplanar")
    with pytest.raises(ValueError, match=r"subset='curved'.*planar"):
        SyntheticCatalog("ycb", subset="curved")


def test_nonplanar_plane_layouts(nonplanar: CanonicalSet) -> None:
    cyl = ["top", "bottom"] + [f"side_{a:03d}" for a in range(0, 360, 45)]
    box = ["front", "back", "left", "right", "top", "bottom"]
    specs = sample_nonplanar(0)
    assert [s.kind for s in specs] == [f for f, n in NONPLANAR_COMPOSITION.items() for _ in range(n)]
    for o, spec in enumerate(specs):
        names = [nonplanar.plane_names[p] for p in np.flatnonzero(nonplanar.plane_object == o)]
        assert names == (box if spec.kind in ("pouch", "ball") else cyl), spec.kind
    assert set(nonplanar.object_shapes) == {"nonplanar"}


def test_nonplanar_renders_fit_and_differ(nonplanar: CanonicalSet) -> None:
    cs = nonplanar
    assert not cs.images[~cs.masks].any()
    assert cs.masks.reshape(cs.num_planes, -1).sum(1).min() > 20  # every plane shows a real object
    border = cs.masks[:, 0].any(1) | cs.masks[:, -1].any(1) | cs.masks[:, :, 0].any(1) | cs.masks[:, :, -1].any(1)
    assert not border.any()
    for p in range(cs.num_planes):  # the larger extent is at most `fill` of the width (handles included)
        ys, xs = np.nonzero(cs.masks[p])
        assert max(xs.max() - xs.min() + 1, ys.max() - ys.min() + 1) <= 0.6 * SIZE + 1.5, cs.plane_label(p)
    # Different objects' planes differ: mean absolute difference over the union of the two
    # foregrounds, 0-255 scale (as the simple catalogs' test).
    img = cs.images.astype(np.int16)
    worst = (np.inf, -1, -1)
    for p in range(cs.num_planes):
        other = np.flatnonzero(cs.plane_object != cs.plane_object[p])
        union = cs.masks[p][None] | cs.masks[other]
        d = (np.abs(img[p][None] - img[other]).mean(-1) * union).sum((1, 2)) / union.sum((1, 2))
        if d.min() < worst[0]:
            worst = (float(d.min()), p, int(other[d.argmin()]))
    assert worst[0] > 5.0, f"{cs.plane_label(worst[1])} ~ {cs.plane_label(worst[2])}: {worst[0]:.2f}"


def test_mug_is_concave_with_a_handle() -> None:
    mug = next(s for s in sample_nonplanar(0) if s.kind == "mug")
    model = nonplanar_model(mug, TEXTURE_PX)
    v = np.concatenate([p.vertices for p in model.parts])
    # the handle sticks out along x: the object is wider along x than across it
    assert np.ptp(v[:, 0]) > 1.15 * np.ptp(v[:, 1])
    side_090 = next(p for p in model.planes if p.name == "side_090")
    side_000 = next(p for p in model.planes if p.name == "side_000")
    assert side_000.extent[0] > side_090.extent[0]  # seen from the front the handle widens the silhouette
