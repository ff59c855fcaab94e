"""load_run reads a run's row from its saved config; group_runs keeps one run per seed."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from matl.reporting.runs import find_runs, group_runs, load_run
from matl.utils.errors import MatlError
from tests.reporting.fake_runs import fake_run, metrics_for


def test_rows_are_read_from_the_config_not_the_experiment_name(tmp_path: Path) -> None:
    """experiment=table1_f N=2 is a Fig. 4 point; a run with the paper's recipe (model=matl augment=none)
    and row (g)'s settings is row (g)."""
    a = load_run(fake_run(tmp_path / "a", ["experiment=table1_f", "N=2"], metrics_for(0.5, 1.0, 0)))
    assert a.table1 is None and a.fig4 is not None and a.fig4[1] == 2
    g = load_run(fake_run(tmp_path / "g", ["model=matl", "augment=none", "lam=0"], metrics_for(0.5, 1.0, 0)))
    assert g.table1 == "g" and g.paper_column == "ARC"
    j = load_run(fake_run(tmp_path / "j", ["model=matl", "augment=none", "loss=nce", "data.batch_size=40"],
                          metrics_for(0.5, 1.0, 0)))
    assert j.table1 == "j"
    other = load_run(fake_run(tmp_path / "o", ["model=matl", "augment=none", "loss=nce", "N=6", "data.batch_size=40"],
                              metrics_for(0.5, 1.0, 0)))
    assert other.table1 is None and other.fig4 is None
    ycb_all = load_run(fake_run(tmp_path / "y", ["model=matl", "augment=none", "data=synthetic_ycb",
                                                 "data.source.subset=all"], metrics_for(0.5, 1.0, 0)))
    assert ycb_all.dataset == "synthetic_ycb/all" and ycb_all.paper_column is None  # not the paper's YCB
    t2 = load_run(fake_run(tmp_path / "t2", ["experiment=table2_b"], metrics_for(0.5, 1.0, 0)))
    assert (t2.table1, t2.table2, t2.fig4, t2.dataset) == (None, "b", None, "synthetic_ycb_table2/planar")
    # two seeds of one config share a fingerprint; another lam does not
    s1 = load_run(fake_run(tmp_path / "s1", ["model=matl", "augment=none", "seed=1"], metrics_for(0.5, 1.0, 1)))
    s0 = load_run(fake_run(tmp_path / "s0", ["model=matl", "augment=none", "seed=0"], metrics_for(0.5, 1.0, 0)))
    assert s0.fingerprint == s1.fingerprint != g.fingerprint


def test_a_baseline_is_its_row_only_with_the_papers_N(tmp_path: Path) -> None:
    def baseline(name: str, N: int):
        metrics = {**metrics_for(0.7, 0.6, 0, N=N), "evaluated": "baseline", "baseline": name}
        return load_run(fake_run(tmp_path / f"{name}{N}", [f"baseline={name}", f"N={N}"], metrics, config_name="eval"))

    assert baseline("sift", 4).table1 == "d" and baseline("superpoint", 4).table1 == "e"
    sift2 = baseline("sift", 2)
    assert sift2.table1 is None and sift2.kind == "baseline" and sift2.method == "SIFT+RANSAC [20, 13], N=2"
    assert baseline("lightglue", 4).table1 is None


def test_groups_keep_the_newest_run_of_a_seed_and_list_failures(tmp_path: Path) -> None:
    new = fake_run(tmp_path / "new", ["seed=0"], metrics_for(0.9, 0.5, 0))
    old = fake_run(tmp_path / "old", ["seed=0"], metrics_for(0.1, 9.0, 0))
    os.utime(old / "metrics.json", (1, 1))
    fake_run(tmp_path / "failed", ["seed=1"], None, failed="boom")
    fake_run(tmp_path / "started", ["seed=2"], None)
    assert find_runs([tmp_path]) == sorted(tmp_path / n for n in ("new", "old", "failed", "started"))
    (group,) = group_runs(load_run(p) for p in find_runs([tmp_path]))
    assert [r.path for r in group.runs] == [new] and group.duplicates == 1
    assert group.stat("rec_acc") == (0.9, 0.0, 1)
    assert [r.reason for r in group.failed] == ["boom"] and [r.path.name for r in group.incomplete] == ["started"]


def test_a_missing_folder_is_a_user_error(tmp_path: Path) -> None:
    with pytest.raises(MatlError, match="does not exist"):
        find_runs([tmp_path / "missing"])


def test_runs_beyond_the_papers_recipe_are_no_paper_row(tmp_path) -> None:
    """A run with camera-like positives, or the default (model=matl_camera, input_norm=channel), is not row
    (f); experiment=table1_f is."""
    from matl.reporting.configs import dataset_name
    from matl.reporting.rows import classify_training, describe
    from tests.conftest import compose_config

    camera = compose_config("train", ["augment=camera"], tmp_path)
    assert classify_training(camera, dataset_name(camera.data)) == (None, None, False)
    assert "augment=camera" in describe(camera, "train", {})
    default = compose_config("train", [], tmp_path)
    assert classify_training(default, dataset_name(default.data)) == (None, None, False)
    assert "input_norm=channel" in describe(default, "train", {})
    paper_f = compose_config("train", ["experiment=table1_f"], tmp_path)
    assert classify_training(paper_f, dataset_name(paper_f.data))[0] == "f"
