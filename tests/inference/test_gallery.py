"""Enrolling a gallery folder (matl.inference.gallery): the per-product feature cache, an interrupted enrolment
resumed, a grown or shrunk gallery embedding only what changed."""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import pytest
import torch
from torch import nn

from matl.inference import gallery as gallery_module
from matl.inference.gallery import cache_gallery_shard, enrol_gallery
from matl.utils.errors import MatlError
from tests.inference.test_api import gallery_folder

SIZE, N = 32, 4


class CountingNet(nn.Module):
    """c() as the mean colour of four quadrants (12-d), counting the anchor images it embeds."""

    def __init__(self) -> None:
        super().__init__()
        self.pool = nn.AdaptiveAvgPool2d(2)
        self.seen = 0

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        self.seen += len(images)
        return self.pool(images).flatten(1)


def enrol(root: Path, net: CountingNet, cache: bool = True):
    return enrol_gallery(root, net, SIZE, N, cache_tag="0123456789abcdef" * 4 if cache else None, batch_size=8)


def cache_files(root: Path) -> list[str]:
    (folder,) = root.glob(".matl_gallery_*")
    return sorted(p.stem for p in folder.glob("*.pt"))


def test_each_product_is_cached_on_its_own_and_read_back_alike(tmp_path: Path) -> None:
    root = gallery_folder(tmp_path / "g", 5)
    net = CountingNet()
    first = enrol(root, net)
    assert net.seen == 5 * N and cache_files(root) == [f"p{k:02d}" for k in range(5)]
    assert first.cache_file is not None and first.cache_file.parent == root
    again = enrol(root, net)
    assert net.seen == 5 * N  # nothing embedded: every product read from its file
    plain = enrol(root, CountingNet(), cache=False)
    for enrolled in (again, first):
        assert torch.equal(enrolled.features, plain.features) and torch.equal(enrolled.canon_u8, plain.canon_u8)
        assert torch.equal(enrolled.gallery.images, plain.gallery.images) and enrolled.paths == plain.paths
        assert enrolled.gallery.object_names == plain.gallery.object_names


def test_an_interrupted_enrolment_resumes_where_it_stopped(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    root = gallery_folder(tmp_path / "g", 5)
    monkeypatch.setattr(gallery_module, "ENROL_PLANES", 2)  # products embedded and written two at a time
    written = gallery_module._write_cache

    def stop_after_three(path: Path, payload: dict) -> bool:
        if len(list(path.parent.glob("*.pt"))) == 3:
            raise KeyboardInterrupt  # the user's Ctrl-C after three products were written
        return written(path, payload)

    monkeypatch.setattr(gallery_module, "_write_cache", stop_after_three)
    with pytest.raises(KeyboardInterrupt):
        enrol(root, CountingNet())
    assert cache_files(root) == ["p00", "p01", "p02"]
    monkeypatch.setattr(gallery_module, "_write_cache", written)
    net = CountingNet()
    resumed = enrol(root, net)
    assert net.seen == 2 * N  # the two products left, nothing recomputed
    assert torch.equal(resumed.features, enrol(root, CountingNet(), cache=False).features)


def test_a_grown_or_shrunk_gallery_embeds_only_what_changed(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    root = gallery_folder(tmp_path / "g", 4)
    enrol(root, CountingNet())
    gallery_folder(tmp_path / "more", 6)
    shutil.copytree(tmp_path / "more" / "p05", root / "p05")  # a new product
    net = CountingNet()
    caplog.set_level(logging.INFO, logger="matl.inference.gallery")
    grown = enrol(root, net)
    assert net.seen == N and "4 products read from the cache, 1 enrolled" in caplog.text
    assert grown.gallery.object_names == ["p00", "p01", "p02", "p03", "p05"]
    shutil.rmtree(root / "p01")  # a product taken out: its file goes too
    net = CountingNet()
    shrunk = enrol(root, net)
    assert net.seen == 0 and cache_files(root) == ["p00", "p02", "p03", "p05"]
    assert torch.equal(shrunk.features, enrol(root, CountingNet(), cache=False).features)


def test_a_corrupt_or_foreign_cache_file_is_rebuilt(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    root = gallery_folder(tmp_path / "g", 3)
    enrol(root, CountingNet())
    (folder,) = root.glob(".matl_gallery_*")
    (folder / "p01.pt").write_bytes(b"not a torch file")
    shutil.copy(folder / "p00.pt", folder / "p02.pt")  # another product's file under this one's name: its key differs
    net = CountingNet()
    with caplog.at_level(logging.WARNING):
        enrolled = enrol(root, net)
    assert net.seen == 2 * N and "p01.pt is unreadable" in caplog.text
    assert torch.equal(enrolled.features, enrol(root, CountingNet(), cache=False).features)


def test_a_product_whose_every_file_is_unusable_is_skipped_and_remembered(tmp_path: Path) -> None:
    root = gallery_folder(tmp_path / "g", 3)
    (root / "p01" / "front.png").write_bytes(b"not an image")
    net = CountingNet()
    enrolled = enrol(root, net)
    assert enrolled.gallery.object_names == ["p00", "p02"] and net.seen == 2 * N
    again = enrol(root, net)
    assert again.gallery.object_names == ["p00", "p02"] and net.seen == 2 * N


def test_shards_enrolled_apart_merge_into_the_whole_gallery(tmp_path: Path) -> None:
    root = gallery_folder(tmp_path / "g", 5)
    tag = "0123456789abcdef" * 4
    seen = []
    for shard in range(2):  # e.g. two processes or hosts sharing the folder
        net = CountingNet()
        assert cache_gallery_shard(root, net, SIZE, N, 1.0, tag, shard, 2) == ((5 - shard + 1) // 2,) * 2
        seen.append(net.seen)
    assert seen == [3 * N, 2 * N] and cache_files(root) == [f"p{k:02d}" for k in range(5)]
    net = CountingNet()
    merged = enrol(root, net)
    assert net.seen == 0  # the merge reads every product from the shards' files
    assert torch.equal(merged.features, enrol(root, CountingNet(), cache=False).features)
    assert cache_gallery_shard(root, CountingNet(), SIZE, N, 1.0, tag, 1, 2) == (2, 0)  # done already
    for shard, shards in ((2, 2), (-1, 2), (0, 0)):
        with pytest.raises(MatlError, match=f"shard={shard} of shards={shards} is invalid"):
            cache_gallery_shard(root, CountingNet(), SIZE, N, 1.0, tag, shard, shards)
