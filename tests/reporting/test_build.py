"""build_report on fake run folders: Table 1 / Table 2 / Fig. 4 beside the paper's numbers, the methods table, CSV."""

from __future__ import annotations

import csv
import statistics
from pathlib import Path

import pytest

from matl.reporting.build import build_report, find_fig5_pair
from matl.reporting.runs import group_runs, load_run
from tests.reporting.fake_runs import fake_run, make_sweep, metrics_for


@pytest.fixture
def sweep(tmp_path: Path) -> Path:
    return make_sweep(tmp_path)


def test_report_tables_from_fake_runs(sweep: Path) -> None:
    out = sweep / "report"
    rep = build_report([sweep / "multirun", sweep / "old", sweep / "evals"], out, auto_fig5=True)
    text = (out / "report.md").read_text()
    # Table 1, one setting (scale=cpu at 100 px, 8 epochs, 1000 test queries), the paper's numbers beside ours
    assert "## Table 1 (scale=cpu, 100 px, 8 epochs, 1000 test queries)" in text
    table1 = text.split("## Table 1", 1)[1].split("\n## ", 1)[0]
    lines = {line.split(" | ")[0]: line for line in table1.splitlines() if line.startswith("| (")}
    f_line = lines["| (f)"]
    rec = statistics.mean([0.90, 0.91, 0.92]), statistics.stdev([0.90, 0.91, 0.92])
    assert f"{rec[0]:.3f} ± {rec[1]:.3f} (3)" in f_line  # the older duplicate (0.1) is not averaged
    assert "0.93 ± 0.01" in f_line and "0.66 ± 0.01" in f_line and "0.46 ± 0.01" in f_line  # paper ARC / APC
    cells = [c.strip() for c in f_line.strip("|").split("|")]
    assert cells[2].startswith("0.910") and cells[10].startswith("0.910")  # ARC and APC rec_acc
    assert cells[6] == "—"  # no YCB run
    b_cells = [c.strip() for c in lines["| (b)"].strip("|").split("|")]
    assert b_cells[2].startswith("0.860") and b_cells[4] == "n/a" and b_cells[5] == "n/a"  # TL: no pose, as the paper
    d_cells = [c.strip() for c in lines["| (d)"].strip("|").split("|")]
    assert d_cells[2] == "0.750 ± 0.000 (2)" and d_cells[3] == "0.82 ± 0.02"  # the SIFT evaluations
    # Table 2 and Fig. 4
    table2 = text.split("## Table 2", 1)[1].split("\n## ", 1)[0]
    assert "| (c) | Ours (non-planar) | 0.700 (1) | 0.81 ± 0.02 | 0.900 (1) | 0.68 ± 0.05 |" in table2
    assert "| (a) | Ours (planar) | — | 0.91 ± 0.02 | — | 0.57 ± 0.03 |" in table2
    assert (out / "fig4.png").is_file() and "![Fig. 4](fig4.png)" in text
    fig4 = [line for line in text.splitlines() if line.startswith("| synthetic_arc |")]
    assert [line.split(" | ")[1] for line in fig4] == ["1", "2", "4"]
    assert fig4[1] == "| synthetic_arc | 2 | 0.850 ± 0.000 (2) | 1.000 ± 0.000 (2) | 0.425 ± 0.000 (2) |"
    # failures and unfinished jobs are listed, not averaged; the duplicate is noted
    assert "## Failed runs" in text and "NonFiniteLossError: training loss became nan" in text
    assert "## Unfinished runs" in text
    assert "1 older run(s)" in text
    assert "Fig. 5 skipped" not in text and not (out / "fig5.png").exists()  # fake runs have no checkpoints
    # every group, with every metric column of the metric collection and query_ms
    assert ("| config | dataset | kind | runs | seeds | rec_acc | pose_err | corner_err_px | corner_err_px_median | "
            "pose_acc_5px | query_ms |") in text
    # table.csv: one row per configuration with numeric columns and its place in the paper's tables
    with (out / "table.csv").open() as f:
        rows = list(csv.DictReader(f))
    by_role = {(r["table1_row"], r["dataset"]): r for r in rows if r["table1_row"]}
    f_arc = by_role[("f", "synthetic_arc")]
    assert float(f_arc["rec_acc_mean"]) == pytest.approx(rec[0])
    assert float(f_arc["rec_acc_std"]) == pytest.approx(rec[1])
    assert float(f_arc["corner_err_px_median_mean"]) == pytest.approx(9 * statistics.mean([0.70, 0.72, 0.74]))
    assert f_arc["runs"] == "3" and f_arc["seeds"] == "0 1 2" and f_arc["fig4_N"] == "4"
    assert float(f_arc["paper_rec_acc_mean"]) == 0.93 and float(f_arc["paper_pose_err_mean"]) == 0.66
    assert by_role[("b", "synthetic_arc")]["pose_err_mean"] == ""
    assert by_role[("d", "synthetic_arc")]["kind"] == "baseline"
    table2_c = next(r for r in rows if r["table2_row"] == "c")
    assert table2_c["paper_rec_acc_mean"] == "0.81" and table2_c["paper_pose_err_std"] == "0.05"
    assert {p.name for p in rep.files} >= {"report.md", "table.csv", "fig4.png"}


def test_methods_table_names_evaluations_by_the_evaluated_runs_config(tmp_path: Path) -> None:
    """matl.eval of row (f) and row (b) checkpoints (one with refinement) and a SIFT evaluation, same queries."""
    runs = {row: fake_run(tmp_path / "train" / row, [f"experiment=table1_{row}", "seed=0"], metrics_for(0.9, 0.5, 0),
                          {"data": "synthetic_arc"}) for row in ("f", "b")}
    evals = tmp_path / "evals"
    queries = {"data": "synthetic_arc", "image_size": 100, "num_queries": 1000, "seed": 0}
    for k, (row, refine, rec, pose) in enumerate([("f", False, 0.93, 0.6), ("f", True, 0.93, 0.4),
                                                  ("b", False, 0.88, None)]):
        metrics = {**metrics_for(rec, pose, 0), **queries, "run": str(runs[row]), "evaluated": "checkpoint",
                   "refine": refine}
        fake_run(evals / str(k), [f"run={runs[row]}", f"refine={str(refine).lower()}"], metrics,
                 {"data": "synthetic_arc"}, config_name="eval")
    fake_run(evals / "sift", ["experiment=table1_d"], {**metrics_for(0.97, 0.09, 0), **queries, "evaluated": "baseline",
                                                        "baseline": "sift"}, {"baseline": "sift"}, config_name="eval")
    gone = {**metrics_for(0.5, 0.5, 0), **queries, "run": str(tmp_path / "moved"), "evaluated": "checkpoint"}
    fake_run(evals / "gone", [f"run={tmp_path / 'moved'}"], gone, {"data": "synthetic_arc"}, config_name="eval")
    build_report([evals], tmp_path / "report", auto_fig5=False)
    text = (tmp_path / "report" / "report.md").read_text()
    section = text.split("## Methods on the same test queries", 1)[1].split("\n## ", 1)[0]
    assert "synthetic_arc, split seed(s) 0, 1000 queries:" in section
    assert "| method | rec_acc | pose_err | median corner_err_px | pose_acc_5px | query_ms | seeds |" in section
    rows = {line.split(" | ")[0].lstrip("| "): [c.strip() for c in line.strip("|").split("|")]
            for line in section.splitlines() if line.startswith(("| (", "| SIFT", "| eval of"))}
    matl = "(f) Ours (multiple anchors, λ=10, N=4)"
    assert set(rows) == {matl, f"{matl} + refinement", "(b) TL [29]", "SIFT+RANSAC [20, 13]",
                         f"eval of {tmp_path / 'moved'}"}  # a run that is gone is named by its folder
    assert rows["(f) Ours (multiple anchors, λ=10, N=4) + refinement"][2] == "0.400 (1)"
    assert rows["(b) TL [29]"][2:5] == ["n/a", "n/a", "n/a"] and rows["(b) TL [29]"][1] == "0.880 (1)"
    assert rows["SIFT+RANSAC [20, 13]"][1] == "0.970 (1)" and rows["SIFT+RANSAC [20, 13]"][3] == "0.810 (1)"


def test_fig5_pair_is_a_row_a_and_a_row_f_run_of_one_seed(tmp_path: Path) -> None:
    paths = {}
    for row, seeds in (("a", (0, 1)), ("f", (1,))):
        for seed in seeds:
            run = fake_run(tmp_path / f"{row}{seed}", [f"experiment=table1_{row}", f"seed={seed}"],
                           metrics_for(0.9, 0.5, seed), {"data": "synthetic_arc"})
            (run / "checkpoints").mkdir()
            paths[(row, seed)] = run / "checkpoints" / "best.ckpt"
            paths[(row, seed)].write_bytes(b"")
    groups = group_runs(load_run(p) for p in sorted(tmp_path.iterdir()))
    assert find_fig5_pair(groups) == (paths[("a", 1)], paths[("f", 1)])  # seed 1 is in both rows
