"""matl.score (predictions against a ground-truth sidecar) and matl.unseen (never-seen products via predict).

The scorer is checked on made-up predictions (perfect ones score 1 and 0 px, wrong ones 0), the
written ground truth against cv2 (the gallery file warped by the true H *is* the query file), and
the whole unseen path once with a tiny checkpoint (32 px, one epoch).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from omegaconf import open_dict

from matl.data.canonical import CanonicalSet
from matl.evaluation.score import read_truth, score, score_files
from matl.evaluation.score import run as score_run
from matl.evaluation.unseen import (
    benchmark_table,
    bin_labels,
    breakdown_groups,
    breakdown_result,
    headline_queries,
    hidden_bin,
    score_condition,
    seen_products,
    unseen,
    write_gallery,
    write_queries,
)
from matl.geometry import HomographySampler
from matl.training.fit import train
from matl.utils.errors import MatlError
from tests.conftest import TINY, compose_config

REPO = Path(__file__).resolve().parents[2]


def tiny_set(size: int = 40, objects: int = 3) -> CanonicalSet:
    """``objects`` two-plane objects: smooth coloured rectangles of different shapes on black, in memory."""
    rng = np.random.default_rng(0)
    images, masks, plane_object, names = [], [], [], []
    y, x = np.mgrid[0:size, 0:size]
    for o in range(objects):
        for p, plane in enumerate(("front", "back")):
            h, w = int(size * (0.3 + 0.1 * p)), int(size * (0.6 - 0.05 * o))
            top, left = (size - h) // 2, (size - w) // 2
            mask = (y >= top) & (y < top + h) & (x >= left) & (x < left + w)
            colour = rng.uniform(0.2, 1.0, 3)
            shade = 0.6 + 0.4 * np.sin(x / (3.0 + o) + p)[..., None]
            images.append((mask[..., None] * colour * shade * 255).round().astype(np.uint8))
            masks.append(mask)
            plane_object.append(o)
            names.append(plane)
    return CanonicalSet(np.stack(images), np.stack(masks), np.array(plane_object, dtype=np.int64), names,
                        [f"obj_{o}" for o in range(objects)], ["planar"] * objects)


def write_case(root: Path, crop: bool = False, n: int = 12) -> tuple[Path, list[dict]]:
    cs = tiny_set()
    gallery, offsets = write_gallery(cs, root / "gallery", crop)
    truth = write_queries(cs, HomographySampler(), n, 7, root / "queries", gallery, offsets, root)
    (root / "truth.jsonl").write_text("".join(json.dumps(t) + "\n" for t in truth))
    return root / "truth.jsonl", truth


def write_predictions(path: Path, records: list[dict]) -> Path:
    path.write_text("".join(json.dumps(r) + "\n" for r in records))
    return path


@pytest.mark.parametrize("crop", [False, True])
def test_truth_is_what_the_files_show(tmp_path: Path, crop: bool) -> None:
    """cv2.warpPerspective(gallery file, H) reproduces the query file: H is in the files' pixels."""
    truth_path, truth = write_case(tmp_path, crop)
    for record in truth:
        query = cv2.imread(str(tmp_path / record["image"])).astype(np.float64)
        gallery = cv2.imread(str(tmp_path / record["gallery_image"]))
        warped = cv2.warpPerspective(gallery, np.array(record["H"]), (query.shape[1], query.shape[0]))
        assert np.abs(warped.astype(np.float64) - query).mean() < 1.0
    if crop:  # tight crops: smaller than the frame
        assert any(cv2.imread(str(tmp_path / r["gallery_image"])).shape[0] < 40 for r in truth)
    assert [t.object for t in read_truth(truth_path)] == [r["object"] for r in truth]


@pytest.mark.parametrize("crop,gallery_fill,size", [(False, 1.0, 40), (False, 1.0, 20), (True, 0.6, 40)])
def test_perfect_predictions_score_one_and_wrong_ones_zero(tmp_path: Path, crop: bool, gallery_fill: float,
                                                           size: int) -> None:
    truth_path, truth = write_case(tmp_path, crop)
    # predict writes paths as it was given them: here relative to the sidecar's folder, from another cwd
    perfect = write_predictions(tmp_path / "perfect.jsonl", [
        {"image": r["image"], "object": r["object"], "plane": r["plane"], "anchor": 0, "distance": 0.0,
         "H": r["H"], "gallery_image": r["gallery_image"]} for r in truth])
    summary, rows = score_files(perfect, truth_path, size, gallery_fill)
    assert summary["rec_acc"] == summary["plane_acc"] == summary["pose_acc_5px"] == 1.0
    assert summary["corner_err_px"] == pytest.approx(0.0, abs=1e-6)
    assert summary["pose_err"] == pytest.approx(0.0, abs=1e-9)
    assert summary["num_queries"] == len(rows) == 12 and summary["missing_predictions"] == 0
    assert summary["confusions"] == []

    objects = sorted({r["object"] for r in truth})
    wrong = write_predictions(tmp_path / "wrong.jsonl", [
        {**json.loads(line), "object": objects[(objects.index(r["object"]) + 1) % len(objects)]}
        for line, r in zip(perfect.read_text().splitlines(), truth, strict=True)])
    summary, _ = score_files(wrong, truth_path, size, gallery_fill)
    assert summary["rec_acc"] == summary["plane_acc"] == summary["pose_acc_5px"] == 0.0
    assert summary["pose_err"] is None and summary["corner_err_px"] is None
    assert sum(c["count"] for c in summary["confusions"]) == 12


def test_pose_error_and_missing_predictions(tmp_path: Path) -> None:
    truth_path, truth = write_case(tmp_path)
    shift = np.array([[1.0, 0, 4.0], [0, 1.0, -3.0], [0, 0, 1.0]])  # the estimate is 5 px off at the query
    records = [{"image": str((tmp_path / r["image"]).resolve()), "object": r["object"], "plane": r["plane"],
                "H": (shift @ np.array(r["H"])).tolist(), "gallery_image": r["gallery_image"]} for r in truth[:-1]]
    labelled = read_truth(truth_path)
    summary, rows = score(labelled, [*records, None], 40, truth_base=tmp_path)
    assert summary["missing_predictions"] == 1 and summary["rec_acc"] == pytest.approx(11 / 12)
    assert summary["corner_err_px"] == pytest.approx(5.0) and summary["corner_err_px_median"] == pytest.approx(5.0)
    assert summary["pose_acc_5px"] == 0.0  # the 5 px threshold at 100 px is 2 px at 40 px
    assert rows[-1]["correct"] == 0 and rows[-1]["pred_object"] is None
    # at model size 100 the same 5 px query-file error is 12.5 px
    summary, _ = score(labelled, [*records, None], 100, truth_base=tmp_path)
    assert summary["corner_err_px"] == pytest.approx(12.5)


def test_score_user_errors(tmp_path: Path) -> None:
    truth_path, _ = write_case(tmp_path)
    with pytest.raises(MatlError, match="no such file"):
        score_files(tmp_path / "nope.jsonl", truth_path, 40)
    bad = tmp_path / "bad.jsonl"
    bad.write_text('{"image": "a.png"}\n')
    with pytest.raises(MatlError, match="'object' is required"):
        read_truth(bad)
    cfg = compose_config("score", [f"predictions={truth_path}", f"truth={truth_path}"], tmp_path / "s")
    with pytest.raises(MatlError, match="model size"):
        score_run(cfg)


def test_hidden_fraction_bins() -> None:
    edges = [0.2, 0.35, 0.5]
    assert bin_labels(edges) == ["<=0.20", "0.20-0.35", "0.35-0.50", ">0.50"]
    assert [hidden_bin(h, edges) for h in (0.1, 0.2, 0.2001, 0.35, 0.49, 0.5, 0.51)] == [
        "<=0.20", "<=0.20", "0.20-0.35", "0.20-0.35", "0.35-0.50", "0.35-0.50", ">0.50"]


def test_a_mixed_condition_is_scored_on_its_rgb_queries_and_broken_down(tmp_path: Path) -> None:
    """Occluded-like truth (hidden fraction, occluder, floor, rgba per query): the headline is the RGB queries,
    each bin and kind is scored on its own queries, the RGBA ones under input only."""
    _, truth = write_case(tmp_path, n=12)
    hidden = [0.12, 0.18, 0.25, 0.3, 0.34, 0.4, 0.45, 0.49, 0.15, 0.22, 0.38, 0.55]
    for i, t in enumerate(truth):
        t.update(hidden_fraction=hidden[i], occluder=("edge", "product", "gripper")[i % 3], floor="dark",
                 rgba=i >= 9)
    truth_path = tmp_path / "truth.jsonl"
    truth_path.write_text("".join(json.dumps(t) + "\n" for t in truth))
    right = {0, 2, 3, 5, 9}  # every other query answered with another product
    objects = sorted({t["object"] for t in truth})
    predictions = write_predictions(tmp_path / "p.jsonl", [
        {"image": t["image"], "object": t["object"] if i in right else objects[(objects.index(t["object"]) + 1) % 3],
         "plane": t["plane"], "H": t["H"], "gallery_image": t["gallery_image"]} for i, t in enumerate(truth)])
    headline = headline_queries(truth)
    assert headline == list(range(9)) and headline_queries([{"rgba": True}]) == [0]
    groups = breakdown_groups(truth, headline, [0.2, 0.35, 0.5])
    assert groups["hidden_fraction"] == {"<=0.20": [0, 1, 8], "0.20-0.35": [2, 3, 4], "0.35-0.50": [5, 6, 7]}
    assert groups["occluder"] == {"product": [1, 4, 7], "gripper": [2, 5, 8], "edge": [0, 3, 6]}
    assert groups["input"] == {"rgb": list(range(9)), "rgba": [9, 10, 11]}
    summary, rows, scored = score_condition(predictions, truth_path, headline, groups, 40)
    assert summary["num_queries"] == 9 and summary["rec_acc"] == pytest.approx(4 / 9) and len(rows) == 12
    assert summary["corner_err_px_median"] == pytest.approx(0.0, abs=1e-6)
    assert scored["hidden_fraction"]["<=0.20"] == {"num_queries": 3, "rec_acc": pytest.approx(1 / 3),
                                                   "corner_err_px_median": pytest.approx(0.0, abs=1e-6),
                                                   "pose_acc_5px": pytest.approx(1 / 3)}
    assert scored["hidden_fraction"]["0.35-0.50"]["rec_acc"] == pytest.approx(1 / 3)
    assert scored["occluder"]["edge"]["rec_acc"] == pytest.approx(2 / 3)
    assert scored["input"]["rgba"]["rec_acc"] == pytest.approx(1 / 3)
    assert breakdown_groups([{"image": "a"}], [0], [0.2]) == {}  # other conditions have none

    result = breakdown_result(groups, {"matl": scored}, [0.2, 0.35, 0.5], "rgb")
    assert result["occluder"]["gripper"] == {"num_queries": 3, "methods": {"matl": {
        "rec_acc": pytest.approx(2 / 3), "corner_err_px_median": pytest.approx(0.0, abs=1e-6),
        "pose_acc_5px": pytest.approx(2 / 3)}}}
    row = {"num_queries": 9, "num_objects": 3, "num_planes": 6, "image_size": 40, "checkpoint": "c", "data": {},
           "query_seed": 7, "timing": None, "headline": "rgb", "breakdown": result,
           "methods": {"matl": {"rec_acc": 4 / 9, "corner_err_px_median": 0.0, "pose_acc_5px": 4 / 9,
                                "query_ms": None}}}
    data, text = benchmark_table({"occluded": row}, ["matl"], "")
    assert "| occluded | 9 | 0.444 / 0.0 / 0.444 / - |" in text and "occluded count its RGB queries only" in text
    assert "| hidden_fraction <=0.20 | 3 | 0.333 / 0.0 / 0.333 |" in text and "| input rgba | 3 |" in text
    assert data["breakdown"]["occluded"]["hidden_fraction"]["0.20-0.35"]["num_queries"] == 3


# ------------------------------------------------------------------------------- whole path
@pytest.fixture(scope="module")
def tiny_ckpt(tmp_path_factory: pytest.TempPathFactory, cache_dir: Path) -> Path:
    run_dir = tmp_path_factory.mktemp("unseen_run")
    train(compose_config("train", [*TINY, f"paths.cache_dir={cache_dir}", "logger=none"], run_dir))
    return run_dir / "checkpoints" / "best.ckpt"


@pytest.mark.slow
def test_unseen_end_to_end(tiny_ckpt: Path, tmp_path: Path, cache_dir: Path) -> None:
    out = tmp_path / "unseen"
    cfg = compose_config("unseen", [f"ckpt={tiny_ckpt}", "data=synthetic_apc", "queries=10", f"out={out}",
                                    "methods=[matl,sift]", "timing.queries=2", "timing.warmup=1",
                                    f"paths.cache_dir={cache_dir}"], tmp_path / "run")
    result = unseen(cfg)
    # synthetic_apc (seed 0) prints one product of the arc training catalog again: it is left out
    assert set(result["excluded_seen"]) == {"sorrel_milk_hazelnut"}
    assert "sorrel_milk_hazelnut" not in result["products"] and result["num_objects"] == 16
    assert not (out / "gallery" / "sorrel_milk_hazelnut").exists()
    assert len(list((out / "gallery").glob("*/*.png"))) == result["num_planes"] == 88
    assert result["num_queries"] == 10 and result["missing_predictions"] == 0 and result["file_size"] == 32
    for key in ("rec_acc", "plane_acc", "pose_acc_5px"):
        assert 0.0 <= result[key] <= 1.0
    assert result["plane_acc"] <= result["rec_acc"]
    # rec_acc is exactly the share of predict's lines naming the true object
    truth = {r["image"]: r for r in map(json.loads, (out / "truth.jsonl").read_text().splitlines())}
    lines = [json.loads(line) for line in (out / "predictions.jsonl").read_text().splitlines()]
    hits = [r["object"] == truth[str(Path(r["image"]).relative_to(out))]["object"] for r in lines]
    assert len(lines) == 10 and result["rec_acc"] == pytest.approx(sum(hits) / 10)
    assert "python -m matl.predict" in result["commands"]["predict"]
    saved = json.loads((out / "unseen.json").read_text())
    assert saved["rec_acc"] == result["rec_acc"] and (out / "per_query.csv").is_file()
    # the keypoint baseline answered the same files through predict baseline=sift, and both were timed
    sift = saved["methods"]["sift"]
    assert sift["predictions"] == "predictions_sift.jsonl" and (out / "per_query_sift.csv").is_file()
    assert len((out / sift["predictions"]).read_text().splitlines()) == 10 and "baseline=sift" in sift["commands"][
        "predict"]
    assert 0.0 <= sift["rec_acc"] <= 1.0 and sift["query_ms"] > 0 and saved["methods"]["matl"]["query_ms"] > 0
    assert saved["methods"]["matl"]["rec_acc"] == result["rec_acc"] and result["condition"] == "clean"
    table = (out / "benchmark.md").read_text()
    assert "| condition | queries | matl | sift |" in table and "| clean | 10 |" in table
    assert json.loads((out / "benchmark.json").read_text())["conditions"] == ["clean"]
    # the timed methods on the speed x accuracy plane, and their table
    assert json.loads((out / "benchmark.json").read_text())["speed_accuracy"] == {"clean": "speed_accuracy.png"}
    assert (out / "speed_accuracy.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "| SIFT+RANSAC (`sift`) |" in (out / "methods.md").read_text()

    # the recorded score command gives the same numbers
    args = result["commands"]["score"].split()[3:]
    cfg = compose_config("score", [a for a in args if not a.startswith("out=")], tmp_path / "score")
    with open_dict(cfg):
        cfg.out = str(tmp_path / "score")
    again = score_run(cfg)
    assert again["rec_acc"] == result["rec_acc"] and again["corner_err_px"] == result["corner_err_px"]

    with pytest.raises(MatlError, match="already holds"):
        unseen(compose_config("unseen", [f"ckpt={tiny_ckpt}", "data=synthetic_apc", "queries=2", f"out={out}",
                                         f"paths.cache_dir={cache_dir}"], tmp_path / "run"))
    # the training catalog itself has nothing unseen
    with pytest.raises(MatlError, match="training catalog"):
        unseen(compose_config("unseen", [f"ckpt={tiny_ckpt}", "data=synthetic_arc", "queries=2", "methods=[matl]",
                                         f"out={tmp_path / 'arc'}", f"paths.cache_dir={cache_dir}"], tmp_path / "r"))


@pytest.mark.slow
def test_unseen_occluded_end_to_end(tiny_ckpt: Path, tmp_path: Path, cache_dir: Path) -> None:
    out = tmp_path / "occluded"
    cfg = compose_config("unseen", [f"ckpt={tiny_ckpt}", "data=synthetic_apc", "queries=12", f"out={out}",
                                    "condition=[occluded]", "methods=[matl,sift]", "occluded.rgba_share=0.4",
                                    "timing.queries=2", "timing.warmup=1", f"paths.cache_dir={cache_dir}"],
                         tmp_path / "run")
    result = unseen(cfg)
    folder = out / "occluded"
    truth = [json.loads(line) for line in (folder / "truth.jsonl").read_text().splitlines()]
    rgb = [t for t in truth if not t["rgba"]]
    assert len(truth) == 12 and 0 < len(rgb) < 12 and result["headline"] == "rgb"
    assert result["num_queries"] == len(rgb) and result["num_queries_all"] == 12
    assert [json.loads(line) for line in (folder / "truth_rgb.jsonl").read_text().splitlines()] == rgb
    assert all((folder / t["mask_file"]).is_file() for t in truth) and result["files"]["masks"] == "masks"
    for method in ("matl", "sift"):  # the headline is the RGB queries' score, the breakdown adds up to it
        entry = result["methods"][method]
        bins = result["breakdown"]["hidden_fraction"]
        assert sum(b["num_queries"] for b in bins.values()) == len(rgb)
        hits = sum(b["num_queries"] * b["methods"][method]["rec_acc"] for b in bins.values() if b["num_queries"])
        assert entry["rec_acc"] == pytest.approx(hits / len(rgb))
        assert f"truth={folder / 'truth_rgb.jsonl'}" in entry["commands"]["score"]
        assert entry["query_ms"] > 0
    assert set(result["breakdown"]["occluder"]) <= {"product", "gripper", "suction", "edge"}
    assert result["breakdown"]["input"]["rgba"]["num_queries"] == 12 - len(rgb)
    rows = (folder / "per_query.csv").read_text().splitlines()
    assert len(rows) == 13 and "hidden_fraction" in rows[0] and "occluder" in rows[0]
    table = (out / "benchmark.md").read_text()
    assert f"| occluded | {len(rgb)} |" in table and "| hidden_fraction <=0.20 |" in table


def test_seen_products_of_the_catalogs() -> None:
    from matl.data.catalog import SyntheticCatalog

    train = {"source": {"_target_": "matl.data.catalog.SyntheticCatalog", "catalog": "arc", "seed": 0}}
    ycb = SyntheticCatalog("ycb", 0)
    seen, related, how = seen_products(train, ycb, [p.name for p in ycb.products()])
    assert seen == {} and related and "arc" in how
    arc = SyntheticCatalog("arc", 0)
    seen, _, _ = seen_products(train, arc, [p.name for p in arc.products()])
    assert len(seen) == 34
    seen, _, how = seen_products({"source": {"_target_": "matl.data.meshes.X"}}, arc, [])
    assert seen == {} and how.startswith("not verified")
    # the shelves catalog is compared too: its generated brands share no product with the named catalogs,
    # and a shelf product is seen by a model trained on its shelves
    from matl.data.catalog.shelves import ShelfCatalog

    shelves = {"source": {"_target_": "matl.data.catalog.shelves.ShelfCatalog", "shelves": 1, "first_seed": 100}}
    seen, _, how = seen_products(shelves, arc, [p.name for p in arc.products()])
    assert seen == {} and how.startswith("product specs compared") and "ShelfCatalog" in how
    shelf = ShelfCatalog(shelves=1, first_seed=100)
    seen, _, _ = seen_products(shelves, shelf, [p.name for p in shelf.products()])
    assert len(seen) == 34


@pytest.mark.parametrize("module,args", [("matl.unseen", []), ("matl.score", ["predictions=/nonexistent.jsonl",
                                                                             "truth=/nonexistent.jsonl",
                                                                             "image_size=32"])])
def test_cli_one_line_errors(module: str, args: list[str], tmp_path: Path) -> None:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(REPO)}
    proc = subprocess.run([sys.executable, "-m", module, *args, f"hydra.run.dir={tmp_path / 'h'}"],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2, proc.stderr
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error: ")]
    assert len(errors) == 1 and "Traceback" not in proc.stderr
