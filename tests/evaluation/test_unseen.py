"""matl.score (predictions against a ground-truth sidecar) and matl.unseen (never-seen products via predict).

The scorer is checked on made-up predictions (perfect ones score 1 and 0 px, wrong ones 0), the
benchmark's options and held-out sources, and the whole unseen path once with a tiny checkpoint (32 px,
one epoch). Each condition's files: test_condition_writers.py; each method's run: test_unseen_methods.py;
the scores and the table: test_unseen_results.py.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from omegaconf import open_dict

from matl.data.catalog import SyntheticCatalog
from matl.data.catalog.drawing import HELDOUT_BACKGROUND_FILES, HELDOUT_PHOTO_FILES, PHOTO_FILES
from matl.evaluation.conditions import CONDITIONS, sample_poses
from matl.evaluation.score import read_truth, score, score_files
from matl.evaluation.score import run as score_run
from matl.evaluation.unseen import _check, seen_products, unseen
from matl.geometry import HomographySampler
from matl.training.fit import check_training_photos, train
from matl.utils.errors import MatlError
from tests.conftest import TINY, compose_config
from tests.evaluation.test_condition_writers import tiny_set, write_case

REPO = Path(__file__).resolve().parents[2]


def _cfg(tmp_path: Path, *overrides: str):
    return compose_config("unseen", ["ckpt=unused.ckpt", *overrides], tmp_path / "run")


def write_predictions(path: Path, records: list[dict]) -> Path:
    path.write_text("".join(json.dumps(r) + "\n" for r in records))
    return path



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


def test_a_folder_of_shard_files_scores_as_their_one_file(tmp_path: Path) -> None:
    truth_path, truth = write_case(tmp_path)
    records = [{"image": r["image"], "object": r["object"], "plane": r["plane"], "H": r["H"],
                "gallery_image": r["gallery_image"]} for r in truth]
    whole = write_predictions(tmp_path / "all.jsonl", records)
    shards = tmp_path / "shards"
    for k in range(3):  # as predict shard=k shards=3 writes them, one sub-folder per job of a sweep
        (shards / str(k)).mkdir(parents=True)
        write_predictions(shards / str(k) / "predictions.jsonl", records[k::3])
    merged, _ = score_files(shards, truth_path, 40)
    single, _ = score_files(whole, truth_path, 40)
    assert {k: v for k, v in merged.items() if k != "predictions"} == {k: v for k, v in single.items()
                                                                       if k != "predictions"}
    assert merged["num_queries"] == 12 and merged["missing_predictions"] == 0
    write_predictions(shards / "again.jsonl", records[:1])  # an image answered twice: overlapping shards
    with pytest.raises(MatlError, match="is answered in both"):
        score_files(shards, truth_path, 40)
    (tmp_path / "empty").mkdir()
    with pytest.raises(MatlError, match=r"holds no \.jsonl file"):
        score_files(tmp_path / "empty", truth_path, 40)


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


# ----------------------------------------------------------------------------- held-out sources
def test_heldout_catalog_prints_only_heldout_photos() -> None:
    default, heldout = SyntheticCatalog("apc", 1), SyntheticCatalog("apc", 1, photos="skimage")
    assert default.cache_key() == SyntheticCatalog("apc", 1, photos="matplotlib").cache_key()
    assert "photos" not in default.cache_key() and heldout.cache_key()["photos"].startswith("skimage-")
    assert heldout.cache_key() != default.cache_key()
    arts = {p.art for p in heldout.products()}
    assert arts <= {f"photo_{k}" for k in HELDOUT_PHOTO_FILES} and len(arts) == len(HELDOUT_PHOTO_FILES)
    assert not {p.art for p in default.products()} & arts  # the training catalogs never print them
    assert [p.name for p in heldout.products()] == [p.name for p in default.products()]
    assert not set(HELDOUT_PHOTO_FILES) & set(HELDOUT_BACKGROUND_FILES) and not set(HELDOUT_PHOTO_FILES) & set(
        PHOTO_FILES)
    with pytest.raises(ValueError, match="photos"):
        SyntheticCatalog("apc", 1, photos="flickr")


def test_training_refuses_the_heldout_photos(tmp_path: Path) -> None:
    check_training_photos(compose_config("train", [], tmp_path))
    with pytest.raises(MatlError, match="held-out"):
        check_training_photos(compose_config("train", ["data=heldout"], tmp_path))


# ------------------------------------------------------------------------------ options and table
@pytest.mark.parametrize("override,match", [
    ("condition=foggy", "condition=foggy is invalid: use one or a list of clean, photometric, mask, clutter, "
                        "occluded, view, sizes or all"),
    ("methods=[matl,orb]", r"methods=\['matl', 'orb'\] is invalid: use a list of matl, matl_refine, sift, sift_ecc, "
                           "lightglue, xfeat, xfeat_lighterglue$"),
    ("methods=[]", "methods=.* is invalid"),
    ("sizes.query=8", "sizes.query=8 is invalid"),
    ("photometric.gain=[2.0,1.0]", r"photometric.gain=\[2.0, 1.0\] is invalid: use \[low, high\]"),
    ("occluded.hidden=[0.5,0.1]", r"occluded.hidden=\[0.5, 0.1\] is invalid: use \[low, high\]"),
    ("occluded.hidden=[0.1,1.0]", r"occluded: occluder hidden=\[0.1, 1.0\] is invalid: use \[low, high\] with 0 <= "),
    ("+occluded.kinds.hand=1", "occluded: occluder kind 'hand' is unknown: use product, gripper, suction or edge"),
    ("occluded.kinds.edge=-1", "occluded: occluder kind weight edge=-1 is invalid: use a number >= 0"),
    ("occluded.floors.dark=0", None),
    ("+occluded.floors.carpet=1", r"occluded.floors=\{.*\} is invalid: use weights >= 0 of dark and texture"),
    ("occluded.rgba_share=1.5", r"occluded.rgba_share=1.5 is invalid: use a fraction in \[0, 1\]"),
    ("occluded.bins=[0.35,0.2]", r"occluded.bins=\[0.35, 0.2\] is invalid: use increasing upper edges in \(0, 1\)"),
    ("occluded.dark_floor.level=[0.1,0.0]", r"occluded.dark_floor.level=\[0.1, 0.0\] is invalid"),
])
def test_bad_options_are_one_line_errors(tmp_path: Path, override: str, match: str | None) -> None:
    if match is None:  # a valid setting
        _check(_cfg(tmp_path, override))
        return
    with pytest.raises(MatlError, match=match) as error:
        _check(_cfg(tmp_path, override))
    assert "\n" not in str(error.value)


def test_condition_and_method_lists(tmp_path: Path) -> None:
    assert _check(_cfg(tmp_path, "condition=all"))[0] == list(CONDITIONS)
    assert _check(_cfg(tmp_path, "condition=[view,clean]", "methods=[sift]")) == (["view", "clean"], ["sift"])
    assert _check(_cfg(tmp_path, "methods=[matl,lightglue,xfeat,xfeat_lighterglue]"))[1] == [
        "matl", "lightglue", "xfeat", "xfeat_lighterglue"]


def test_cfg_helper_keeps_the_defaults(tmp_path: Path) -> None:
    cfg = _cfg(tmp_path)
    assert cfg.condition == "clean" and list(cfg.methods) == ["matl", "matl_refine", "sift", "sift_ecc"]
    assert cfg.data.source.photos == "skimage" and cfg.baselines.sift_ecc._target_.endswith("SiftEccMatcher")
    with open_dict(cfg):
        cfg.timing.queries = 0
    assert _check(cfg)[1] == ["matl", "matl_refine", "sift", "sift_ecc"]
    plane, query_H_canon = sample_poses(tiny_set(), HomographySampler(), 3, 0)
    assert plane.shape == (3,) and query_H_canon.shape == (3, 3, 3)


@pytest.mark.parametrize("override,match", [
    ("open_set_statistic=foo", r"^matl: open_set_statistic='foo' is invalid: use verify, verify_or_ratio, ratio or "
                               "distance$"),
    ("baselines.sift.ratio=2", r"^sift: baseline=sift cannot be built: ratio must be in \(0, 1\], got 2"),
    ("verify_max=-1", r"^matl: verify_max=-1 is invalid"),
])
def test_a_methods_mistake_stops_the_benchmark_before_any_file(tmp_path: Path, override: str, match: str) -> None:
    """Every method's predict options, model and matcher are checked before a condition is written."""
    out = tmp_path / "bench"
    cfg = compose_config("unseen", ["ckpt=pretrained", "methods=[matl,sift]", f"out={out}", override],
                         tmp_path / "run")
    with pytest.raises(MatlError, match=match):
        unseen(cfg)
    assert not out.exists()


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
