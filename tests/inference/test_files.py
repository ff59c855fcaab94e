"""``matl.predict``'s library: gallery folders and query files to JSON lines, H in the files' pixels."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import torch.nn.functional as F
from torch import nn

from matl.data.image_files import fit_geometry, fit_to_model, load_image_file, pose_in_files
from matl.geometry import warp_image
from matl.inference.api import Recognizer
from matl.inference.files import predict, predict_files
from matl.inference.gallery import enrol_gallery
from matl.utils.errors import MatlError
from tests.conftest import compose_config
from tests.predict_helpers import (
    COLOURS,
    GALLERY_HW,
    QUERY_HW,
    RECORD_KEYS,
    REPO,
    FixedSTN,
    MeanColour,
    make_files,
    predict_cfg,
    smooth_texture,
    tiny_run,  # noqa: F401 - a module fixture
    write_png,
)


def test_predict_files_reports_H_in_original_file_pixels(tmp_path: Path) -> None:
    """With an STN that outputs the exact model-frame pose, predict's H is the true file-to-file H."""
    size = 48
    gallery_dir, queries_dir, H_true = make_files(tmp_path)
    gallery_fit = fit_geometry(*GALLERY_HW, size).model_H_file
    query_fit = fit_geometry(*QUERY_HW, size).model_H_file
    # the pose a perfect STN would give at model resolution (N = 1: anchor = canonical image)
    model_H = query_fit @ torch.from_numpy(H_true) @ torch.linalg.inv(gallery_fit)

    enrolled = enrol_gallery(gallery_dir, MeanColour(), size, num_anchors=1)
    assert enrolled.gallery.object_names == sorted(COLOURS)
    # that model-frame pose really aligns the model-size images (the fit matrices describe the pixels)
    canon = enrolled.gallery.images[0:1]  # blue_card/front
    query, _ = fit_to_model(load_image_file(queries_dir / "blue_card.png"), size)
    warped = warp_image(canon, model_H[None].float())
    inside = warp_image(torch.ones_like(canon), model_H[None].float())[0, 0] > 0.999
    inside = -F.max_pool2d(-inside[None].float(), 5, 1, 2)[0] > 0.5  # away from the resampled border
    assert inside.sum() > 100
    assert (warped[0] - query).abs()[:, inside].mean() < 0.02

    model = nn.Module()
    model.feature_net, model.stn, model.anchor_choice = MeanColour(), FixedSTN(model_H), "feature"
    recognizer = Recognizer(model, size, 1, "stub", threshold=None, batch_size=2).enrol(gallery_dir, cache=False)
    records: list[dict] = []
    (queries_dir / "notes.txt").write_text("not an image")
    files = sorted(queries_dir.iterdir())
    done, bad = predict_files(recognizer, files, records.append, viz_dir=tmp_path / "viz", show_progress=False)
    assert (done, bad) == (3, [queries_dir / "notes.txt"])
    assert sorted(p.name for p in (tmp_path / "viz").iterdir()) == ["blue_card.png", "green_can.png", "red_box.png"]
    for record in records:
        assert set(record) == RECORD_KEYS
        assert record["object"] == Path(record["image"]).stem and record["anchor"] == 0 and record["known"]
        np.testing.assert_allclose(np.array(record["H"]), H_true, rtol=1e-9, atol=1e-9)
        # the promise of docs/design.md: cv2.warpPerspective of the gallery file with H lands on the query file
        g = cv2.imread(record["gallery_image"]).astype(np.float32)
        q = cv2.imread(record["image"]).astype(np.float32)
        back = cv2.warpPerspective(g, np.array(record["H"]), (QUERY_HW[1], QUERY_HW[0]), flags=cv2.INTER_LINEAR)
        assert np.abs(back - q).max() <= 1.0
    # the bookkeeping function alone, batched
    H = pose_in_files(model_H[None].repeat(2, 1, 1), gallery_fit[None].repeat(2, 1, 1),
                      query_fit[None].repeat(2, 1, 1))
    np.testing.assert_allclose(H.numpy(), np.stack([H_true, H_true]), rtol=1e-9, atol=1e-9)


def test_predict_end_to_end_with_tiny_checkpoint(tiny_run: Path, tmp_path: Path,
                                                 caplog: pytest.LogCaptureFixture) -> None:
    ckpt = tiny_run / "checkpoints" / "best.ckpt"
    gallery, queries, _ = make_files(tmp_path)
    # a second plane of another size, with alpha, a JPEG plane and files that must be skipped
    alpha = np.zeros((70, 50))
    alpha[5:65, 5:45] = 1.0
    write_png(gallery / "red_box" / "top.png", smooth_texture(70, 50, (1, 0.2, 0.1), 7), alpha)
    jpg = (smooth_texture(40, 90, (0.2, 0.9, 0.3), 8) * 255).astype(np.uint8)
    cv2.imwrite(str(gallery / "green_can" / "side.jpg"), jpg[..., ::-1])
    (gallery / "notes.txt").write_text("not an object folder")
    (gallery / "blue_card" / "notes.md").write_text("not a plane")
    (queries / "broken.png").write_text("not an image")
    (queries / "empty.jpg").write_bytes(b"")

    with caplog.at_level(logging.WARNING):
        summary = predict(predict_cfg(tmp_path, ckpt, gallery, queries, ["viz=true", "batch_size=2"]))
    assert summary["predicted"] == 3 and summary["skipped"] == 2
    assert summary["gallery_planes"] == 5 and summary["gallery_objects"] == 3
    skipped = [r.getMessage() for r in caplog.records if r.getMessage().startswith("skipped")]
    assert any("broken.png: not an image" in m for m in skipped) and any("empty.jpg: empty file" in m for m in skipped)
    assert any("notes.txt" in m for m in skipped) and any("notes.md" in m for m in skipped)
    assert all("\n" not in m for m in skipped)

    lines = (tmp_path / "out" / "pred.jsonl").read_text().splitlines()
    assert len(lines) == 3
    for line in lines:
        record = json.loads(line)
        assert set(record) == RECORD_KEYS
        assert record["nearest_object"] in COLOURS and 0 <= record["anchor"] < 4
        assert record["object"] == (record["nearest_object"] if record["known"] else None)
        assert np.isfinite(record["distance"]) and np.array(record["H"]).shape == (3, 3)
        assert record["H"][2][2] == pytest.approx(1.0)
    assert len(list((tmp_path / "run" / "viz").glob("*.png"))) == 3

    # features cached next to the gallery, one file per product, loadable safely; reused, and a product whose file
    # changed enrolled again alone
    folders = list(gallery.glob(".matl_gallery_*"))
    assert len(folders) == 1 and folders[0].is_dir()
    caches = sorted(folders[0].glob("*.pt"))
    assert [c.stem for c in caches] == sorted(p.name for p in gallery.iterdir() if p.is_dir() and p.name in COLOURS)
    payloads = {c.stem: torch.load(c, weights_only=True) for c in caches}
    assert sum(p["features"].shape[0] for p in payloads.values()) == 5 * 4
    caplog.clear()
    with caplog.at_level(logging.INFO):
        predict(predict_cfg(tmp_path, ckpt, gallery, queries, ["batch_size=2", "overwrite=true"]))
    assert any(f"{len(caches)} products read from the cache, 0 enrolled" in r.getMessage() for r in caplog.records)
    assert any("open-set calibration loaded from" in r.getMessage() for r in caplog.records)  # kept, not redone
    # same answers from the cached features
    assert (tmp_path / "out" / "pred.jsonl").read_text().splitlines() == lines
    stat = (gallery / "red_box" / "front.png").stat()
    os.utime(gallery / "red_box" / "front.png", ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))
    written = {c.stem: c.stat().st_mtime_ns for c in caches}
    caplog.clear()
    with caplog.at_level(logging.INFO):
        predict(predict_cfg(tmp_path, ckpt, gallery, queries, ["overwrite=true"]))
    assert any(f"{len(caches) - 1} products read from the cache, 1 enrolled" in r.getMessage()
               for r in caplog.records)
    assert [c.stem for c in caches if c.stat().st_mtime_ns != written[c.stem]] == ["red_box"]

    # a single file works too
    single = predict(predict_cfg(tmp_path, ckpt, gallery, queries / "red_box.png", ["cache=false", "overwrite=true"]))
    assert single["predicted"] == 1


def test_predict_user_errors(tiny_run: Path, tmp_path: Path) -> None:
    ckpt = tiny_run / "checkpoints" / "best.ckpt"
    gallery, queries, _ = make_files(tmp_path)
    with pytest.raises(MatlError, match="not found"):
        predict(predict_cfg(tmp_path, tmp_path / "missing.ckpt", gallery, queries))
    (tmp_path / "empty_gallery").mkdir()
    with pytest.raises(MatlError, match="holds no canonical images"):
        predict(predict_cfg(tmp_path, ckpt, tmp_path / "empty_gallery", queries))
    (tmp_path / "bad_gallery" / "obj").mkdir(parents=True)
    (tmp_path / "bad_gallery" / "obj" / "front.png").write_text("not a png")
    with pytest.raises(MatlError, match="no usable image"):
        predict(predict_cfg(tmp_path, ckpt, tmp_path / "bad_gallery", queries))
    with pytest.raises(MatlError, match="trained at 32 px"):
        predict(predict_cfg(tmp_path, ckpt, gallery, queries, ["image_size=48"]))
    with pytest.raises(MatlError, match="no such file or folder"):
        predict(predict_cfg(tmp_path, ckpt, gallery, tmp_path / "nothing_here"))
    with pytest.raises(MatlError, match="required"):
        predict(compose_config("predict", [f"ckpt={ckpt}"], tmp_path / "run"))
    (tmp_path / "not_a_ckpt.ckpt").write_text("garbage")
    with pytest.raises(MatlError, match="cannot be read"):
        predict(predict_cfg(tmp_path, tmp_path / "not_a_ckpt.ckpt", gallery, queries))


@pytest.mark.parametrize("module,args", [
    ("matl.eval", ["run=/nonexistent/run"]),
    ("matl.predict", ["ckpt=/nonexistent.ckpt", "gallery=/nonexistent", "images=/nonexistent"]),
])
def test_cli_prints_one_line_and_exits_2(module: str, args: list[str], tmp_path: Path) -> None:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(REPO)}
    proc = subprocess.run([sys.executable, "-m", module, *args, f"hydra.run.dir={tmp_path / 'h'}"],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr + proc.stdout
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error: ")]
    assert len(errors) == 1 and "/nonexistent" in errors[0]


def test_predict_exit_codes_when_inputs_are_bad(tiny_run: Path, tmp_path: Path) -> None:
    """All bad: one line naming the files, exit 2, nothing written; some bad: the rest predicted, exit 0."""
    ckpt = tiny_run / "checkpoints" / "best.ckpt"
    gallery, queries, _ = make_files(tmp_path)
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "notes.txt").write_text("not an image")
    (bad / "empty.png").write_bytes(b"")
    out = tmp_path / "out" / "pred.jsonl"
    message = r"no readable image among 2 file\(s\).*empty.png.*notes.txt.*nothing was written"
    with pytest.raises(MatlError, match=message):
        predict(predict_cfg(tmp_path, ckpt, gallery, bad))
    assert not out.exists()
    with pytest.raises(MatlError, match="no readable image among 1 file"):
        predict(predict_cfg(tmp_path, ckpt, gallery, bad / "notes.txt"))
    assert not out.exists()
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(REPO)}
    args = [sys.executable, "-m", "matl.predict", f"ckpt={ckpt}", f"gallery={gallery}", f"out={out}",
            f"hydra.run.dir={tmp_path / 'h'}"]
    proc = subprocess.run([*args, f"images={bad}"], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2 and not out.exists()
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error: ")]
    assert len(errors) == 1 and "notes.txt" in errors[0]
    (queries / "notes.txt").write_text("not an image")
    proc = subprocess.run([*args, f"images={queries}"], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert len(out.read_text().splitlines()) == 3 and "skipped" in proc.stderr + proc.stdout


def test_a_rerun_never_loses_an_earlier_result(tiny_run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """out= is checked before any work and written whole: an existing file needs overwrite=true, and a run that
    is interrupted leaves the earlier, complete file as it was (no truncation, no temporary file left)."""
    ckpt = tiny_run / "checkpoints" / "best.ckpt"
    gallery, queries, _ = make_files(tmp_path)
    out = tmp_path / "out" / "pred.jsonl"
    predict(predict_cfg(tmp_path, ckpt, gallery, queries, ["cache=false", "threshold=null"]))
    earlier = out.read_text()
    assert len(earlier.splitlines()) == 3

    def never(*args, **kwargs):
        raise AssertionError("the gallery was enrolled before the outputs were checked")

    with monkeypatch.context() as patch:
        patch.setattr(Recognizer, "enrol", never)
        with pytest.raises(MatlError, match=r"out=.*pred\.jsonl already exists: pass overwrite=true"):
            predict(predict_cfg(tmp_path, ckpt, gallery, queries, ["cache=false"]))
        (tmp_path / "a_file").write_text("")
        for target, message in ((tmp_path / "out", "is a folder: name a file in it"),
                                (tmp_path / "a_file" / "p.jsonl", r"cannot be created: .*a_file is a file, not a")):
            cfg = predict_cfg(tmp_path, ckpt, gallery, queries)
            cfg.out = str(target)
            with pytest.raises(MatlError, match=message):
                predict(cfg)
    assert out.read_text() == earlier

    answered = Recognizer.predict_details

    def interrupted(self: Recognizer, arrays: list[np.ndarray]):
        if interrupted.calls == 1:
            raise KeyboardInterrupt  # killed after the first answer was written
        interrupted.calls += 1
        return answered(self, arrays)

    interrupted.calls = 0
    with monkeypatch.context() as patch:
        patch.setattr(Recognizer, "predict_details", interrupted)
        with pytest.raises(KeyboardInterrupt):
            predict(predict_cfg(tmp_path, ckpt, gallery, queries, ["cache=false", "threshold=null", "batch_size=1",
                                                                    "overwrite=true"]))
    assert out.read_text() == earlier and sorted(p.name for p in out.parent.iterdir()) == ["pred.jsonl"]
    predict(predict_cfg(tmp_path, ckpt, gallery, queries / "red_box.png", ["cache=false", "threshold=null",
                                                                           "overwrite=true"]))
    assert len(out.read_text().splitlines()) == 1  # replaced, once complete


def test_enrol_in_shards_then_merge_and_save(tiny_run: Path, tmp_path: Path) -> None:
    """python -m matl.enrol: two shards fill the gallery's cache (as separate processes would), a run without shard
    reads every product from it and saves the gallery, which a Recognizer loads and answers with as predict does."""
    from matl.inference.files import enrol

    ckpt = tiny_run / "checkpoints" / "best.ckpt"
    gallery, queries, _ = make_files(tmp_path)

    def run(*extra: str) -> dict:
        return enrol(compose_config("enrol", [f"ckpt={ckpt}", f"gallery={gallery}", *extra], tmp_path / "run"))

    shards = [run(f"shard={k}", "shards=2") for k in range(2)]
    assert [s["products"] for s in shards] == [2, 1] and [s["embedded"] for s in shards] == [2, 1]
    assert json.loads((tmp_path / "run" / "enrol.json").read_text())["shard"] == 1
    merged = run(f"save={tmp_path / 'gallery.pt'}")
    assert merged["products"] == 3 and merged["saved"] == str(tmp_path / "gallery.pt")
    loaded = Recognizer.from_checkpoint(ckpt).load(tmp_path / "gallery.pt")
    enrolled = Recognizer.from_checkpoint(ckpt).enrol(gallery, cache=False)
    query = str(queries / "red_box.png")
    a, b = loaded.predict(query), enrolled.predict(query)
    assert (a.object, a.known, a.distance) == (b.object, b.known, b.distance)


def test_predict_in_shards_answers_every_file_once_as_one_run_does(tiny_run: Path, tmp_path: Path) -> None:
    """predict shard=k shards=K: files k, k + K, ... of the sorted list; the shards' files together are one run's."""
    from matl.evaluation.score import read_predictions

    ckpt = tiny_run / "checkpoints" / "best.ckpt"
    gallery, queries, _ = make_files(tmp_path)

    def run(out: Path, *extra: str) -> dict:
        return predict(compose_config("predict", [f"ckpt={ckpt}", f"gallery={gallery}", f"images={queries}",
                                                  f"out={out}", "threshold=null", *extra], tmp_path / "run"))

    whole = run(tmp_path / "all.jsonl")
    parts = [run(tmp_path / "shards" / f"{k}.jsonl", f"shard={k}", "shards=2") for k in range(2)]
    assert [p["predicted"] for p in parts] == [2, 1] and whole["predicted"] == 3
    assert (parts[1]["shard"], parts[1]["shards"], whole["shard"]) == (1, 2, None)
    by_image = {r["image"]: r for r in read_predictions(tmp_path / "all.jsonl")}
    merged = read_predictions(tmp_path / "shards")
    assert sorted(r["image"] for r in merged) == sorted(by_image)
    for record in merged:  # the same answer as in the one run
        one = by_image[record["image"]]
        assert (record["object"], record["plane"]) == (one["object"], one["plane"])
        np.testing.assert_allclose(record["H"], one["H"], rtol=1e-5, atol=1e-4)  # float32 batches of 3 and 2
    with pytest.raises(MatlError, match="shard=3 of shards=4 holds no file"):
        run(tmp_path / "none.jsonl", "shard=3", "shards=4")
    with pytest.raises(MatlError, match=r"shard=2 is invalid: use an integer in \[0, shards=2\)"):
        run(tmp_path / "bad.jsonl", "shard=2", "shards=2")
