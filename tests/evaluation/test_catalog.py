"""The catalogue benchmark (matl.evaluation.catalog, ``python -m matl.unseen condition=catalog``): its options,
the files of one gallery size, the scores on made-up predictions, the table and plot, and the whole path once
with the shipped checkpoint (slow)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from omegaconf import open_dict

from matl.data.catalog.lookalikes import LookalikeCatalog
from matl.evaluation.catalog import (
    ROW_KEYS,
    catalog_table,
    check_catalog,
    family_of_enrolled,
    plot_catalog,
    score_method,
    write_size,
)
from matl.evaluation.unseen import _check, unseen
from matl.evaluation.unseen_methods import MethodRun
from matl.utils.errors import MatlError
from tests.conftest import compose_config


def _cfg(tmp_path: Path, *overrides: str):
    return compose_config("unseen", ["ckpt=unused.ckpt", "condition=catalog", *overrides], tmp_path / "run")


def test_the_default_options_are_valid(tmp_path: Path) -> None:
    cfg = _cfg(tmp_path, "catalog_sizes=[2000,20,200]")
    assert check_catalog(cfg) == [20, 200, 2000] and _check(cfg)[0] == ["catalog"]
    assert check_catalog(_cfg(tmp_path)) == [20, 200, 2000]
    assert check_catalog(_cfg(tmp_path, "catalog_sizes=[10000]")) == [10000]


@pytest.mark.parametrize("override,match", [
    ("catalog_sizes=foo", "catalog_sizes=foo is invalid: use a list of distinct gallery sizes"),
    ("catalog_sizes=[]", "catalog_sizes=[] is invalid"),
    ("catalog_sizes=[1,20]", "integers >= 2"),
    ("catalog_sizes=[20,20]", "distinct"),
    ("catalog_sizes=[2.5]", "integers >= 2"),
    ("catalog_sizes=[20,20000]", "at most 10000 products; drop 20000"),
    ("catalog.leave_out=0", "catalog.leave_out=0 is invalid"),
    ("catalog.leave_out=1.5", "catalog.leave_out=1.5 is invalid"),
    ("catalog.methods=[sift]", "catalog.methods=['sift'] is invalid: use a list of matl"),
    ("catalog.methods=[matl,foo]", "catalog.methods"),
    ("catalog.planes=3", "catalog.planes=3 is invalid"),
    ("catalog.family_size=[1,3]", "catalog.family_size=[1, 3] is invalid"),
    ("catalog.lookalike_share=1.0", "catalog.lookalike_share=1.0 is invalid"),
    ("catalog.keypoint_max_products=-1", "catalog.keypoint_max_products=-1 is invalid"),
    ("catalog.texture_px=8", "catalog.texture_px=8 is invalid"),
    ("catalog.calibrate_max_products=1", "catalog.calibrate_max_products=1 is invalid"),
])
def test_bad_catalog_options_are_one_line_errors(tmp_path: Path, override: str, match: str) -> None:
    with pytest.raises(MatlError, match=match.replace("[", r"\[").replace("]", r"\]")) as error:
        check_catalog(_cfg(tmp_path, override))
    assert "\n" not in str(error.value)


def test_the_catalogue_runs_alone_and_its_options_are_checked_for_every_condition(tmp_path: Path) -> None:
    with pytest.raises(MatlError, match="condition=catalog runs alone"):
        _check(_cfg(tmp_path, "condition=[catalog,clean]"))
    with pytest.raises(MatlError, match="catalog_sizes=foo"):
        _check(_cfg(tmp_path, "condition=clean", "catalog_sizes=foo"))
    assert _check(_cfg(tmp_path, "condition=all"))[0][0] == "clean"  # all: the conditions, not the catalogue


def test_families_count_only_with_an_enrolled_twin() -> None:
    products = LookalikeCatalog(200).products()
    k = next(i for i, p in enumerate(products) if p.family is not None)  # the first family's first member
    assert family_of_enrolled(products, k + 1) == {}  # alone in the gallery: no twin yet
    twins = family_of_enrolled(products, k + 2)
    assert twins == {products[k].spec.name: products[k].family, products[k + 1].spec.name: products[k].family}
    assert len(family_of_enrolled(products, 200)) == sum(
        1 for p in products if p.family is not None and sum(q.family == p.family for q in products) > 1)


def _size(tmp_path: Path, n: int = 12, queries: int = 24):
    cfg = _cfg(tmp_path, f"queries={queries}", "catalog.leave_out=0.25")
    catalog = LookalikeCatalog(n + 3, lookalike_share=0.5)
    cs, products = catalog.build(32), catalog.products()
    out = tmp_path / f"n{n}"
    truth, left_out = write_size(cfg, cs, products, n, out)
    return cfg, products, truth, left_out, out


def test_one_size_writes_the_first_n_products_and_leaves_the_next_out(tmp_path: Path) -> None:
    _, products, truth, left_out, out = _size(tmp_path)
    assert left_out == [p.spec.name for p in products[12:15]]  # round(0.25 * 12)
    assert sorted(d.name for d in (out / "gallery").iterdir()) == sorted(p.spec.name for p in products[:12])
    assert sorted(d.name for d in (out / "left_out").iterdir()) == sorted(left_out)
    assert len(truth) == 24 and len(list((out / "queries").glob("*.jpg"))) == 24  # the photometric camera
    enrolled = [json.loads(line) for line in (out / "truth.jsonl").read_text().splitlines()]
    assert enrolled == [t for t in truth if t["enrolled"]] and len(enrolled) < 24
    for t in truth:
        assert t["enrolled"] == (t["object"] not in left_out) and "photometric" in t
        assert (out / t["gallery_image"]).is_file() and (out / t["image"]).is_file()
        assert t["family"] == family_of_enrolled(products, 12).get(t["object"])
    assert any(t["family"] for t in truth)
    with pytest.raises(MatlError, match="already holds"):
        from matl.evaluation.catalog import run_catalog

        run_catalog(_cfg(tmp_path, "catalog_sizes=[12]"), Path("unused.ckpt"), 32, tmp_path)


def _answers(truth: list[dict], wrong: set[str] = frozenset()) -> list[dict]:
    """predict's lines: every enrolled query right (or the first other product for those in ``wrong``), every
    left-out one answered unknown."""
    lines = []
    for t in truth:
        obj = next(u["object"] for u in truth if u["object"] != t["object"]) if t["object"] in wrong else t["object"]
        known = t["enrolled"]
        lines.append({"image": t["image"], "object": obj if known else None, "nearest_object": obj,
                      "plane": t["plane"], "known": known, "statistic": 0.0 if known else 1.0,
                      "H": t["H"], "gallery_image": t["gallery_image"]})
    return lines


def test_scores_on_made_up_predictions(tmp_path: Path) -> None:
    _, _, truth, _, out = _size(tmp_path)
    path = out / "predictions_matl_refine.jsonl"
    run = MethodRun("matl_refine", {"out": path}, {})
    path.write_text("".join(json.dumps(r) + "\n" for r in _answers(truth)))
    perfect = score_method(run, truth, out, 32)
    assert perfect["rec_acc"] == perfect["lookalike_rec_acc"] == perfect["unknown_rejected"] == 1.0
    assert perfect["pose_acc_5px"] == 1.0 and perfect["rec_acc_closed"] == 1.0
    assert perfect["lookalike_queries"] == sum(1 for t in truth if t["enrolled"] and t["family"])
    # the look-alikes' queries answered with another product: only they are wrong
    twins = {t["object"] for t in truth if t["enrolled"] and t["family"]}
    path.write_text("".join(json.dumps(r) + "\n" for r in _answers(truth, twins)))
    confused = score_method(run, truth, out, 32)
    enrolled = [t for t in truth if t["enrolled"]]
    assert confused["lookalike_rec_acc"] == 0.0 and confused["unknown_rejected"] == 1.0
    assert confused["rec_acc"] == pytest.approx(sum(t["family"] is None for t in enrolled) / len(enrolled))
    # a keypoint baseline answers a closed set: no unknown_rejected
    assert score_method(MethodRun("sift", {"out": path}, {}), truth, out, 32)["unknown_rejected"] is None


def test_table_and_plot(tmp_path: Path) -> None:
    rows = [{"products": n, "rec_acc": 0.9, "lookalike_rec_acc": 0.7, "unknown_rejected": 0.5,
             "refine_pose_acc_5px": 0.8, "query_ms": q, "enrol_s": 1.0, "method": "matl_refine",
             "methods": {"matl_refine": {"query_ms": q},
                         "sift": {"query_ms": 10 * q, "rec_acc": 0.6 if n < 100 else None}}}
            for n, q in ((20, 30.0), (2000, 60.0))]
    table = catalog_table(rows, "python -m matl.unseen condition=catalog")
    assert "| products | rec_acc | lookalike_rec_acc | unknown_rejected | refine_pose_acc_5px | query_ms |" in table
    assert "| 20 | 0.900 | 0.700 | 0.500 | 0.800 | 30.0 | 1.0 | 0.600 | 300.0 |" in table
    assert "| 2000 | 0.900 | 0.700 | 0.500 | 0.800 | 60.0 | 1.0 | - | 600.0 |" in table
    png = plot_catalog(rows, tmp_path / "catalog.png", "title")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # catalog.timing_queries=0: no method timed, the time panel says so (a log axis of nothing was an error)
    untimed = [{**r, "query_ms": None, "methods": {m: {**v, "query_ms": None} for m, v in r["methods"].items()}}
               for r in rows]
    assert plot_catalog(untimed, tmp_path / "untimed.png", "title").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.slow
def test_catalog_end_to_end(tmp_path: Path, cache_dir: Path) -> None:
    out = tmp_path / "catalog"
    cfg = compose_config("unseen", ["ckpt=pretrained", "condition=catalog", "catalog_sizes=[6,3]", "queries=10",
                                    "catalog.methods=[matl,sift]", "catalog.keypoint_max_products=3",
                                    "catalog.timing_queries=1", "timing.warmup=1", "catalog.leave_out=0.5",
                                    "catalog.calibrate_max_products=3",
                                    f"out={out}", f"paths.cache_dir={cache_dir}"], tmp_path / "run")
    data = unseen(cfg)
    saved = json.loads((out / "catalog.json").read_text())
    assert saved["rows"] == json.loads(json.dumps(data["rows"])) and [r["products"] for r in saved["rows"]] == [3, 6]
    for row in saved["rows"]:
        assert set(ROW_KEYS) <= set(row) and row["refine_pose_acc_5px"] is None  # matl_refine did not run
        assert 0.0 <= row["rec_acc"] <= row["rec_acc_closed"] <= 1.0
        assert row["query_ms"] > 0 and row["enrol_s"] > 0 and row["methods"]["sift"]["query_ms"] > 0
        assert row["queries"] + row["left_out_queries"] == 10
        folder = out / row["folder"]
        products = [d for d in (folder / "gallery").iterdir() if d.is_dir() and not d.name.startswith(".")]
        assert len(products) == row["products"]  # the features' cache folder aside
        assert len(list((folder / "left_out").iterdir())) == row["left_out_products"] == round(0.5 * row["products"])
    small, large = saved["rows"]
    # above calibrate_max_products the closed set: no calibration, nothing answered unknown
    assert small["threshold_option"] == "auto" and small["threshold"] is not None
    assert 0.0 <= small["unknown_rejected"] <= 1.0
    assert large["threshold_option"] is None and large["unknown_rejected"] is None
    assert "rec_acc" in small["methods"]["sift"] and "skipped" in large["methods"]["sift"]
    assert (out / "catalog.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "| 6 |" in (out / "catalog.md").read_text()
    with open_dict(cfg):
        cfg.catalog_sizes = [3]
    with pytest.raises(MatlError, match="already holds n3/gallery"):
        unseen(cfg)
