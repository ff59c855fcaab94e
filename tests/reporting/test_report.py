"""matl.report on fake run folders (metrics.json / eval.json + .hydra/ written here), and the figures."""

from __future__ import annotations

import csv
import json
import math
import os
import statistics
from pathlib import Path

import hydra
import pytest
import torch
from omegaconf import OmegaConf

from matl import report
from matl.reporting.figures import appearance_vs_rotation, fig5_panels, local_minima, plot_fig5
from tests.conftest import TINY, compose_config


def fake_run(folder: Path, overrides: list[str], metrics: dict | None, choices: dict | None = None,
             config_name: str = "train", failed: str | None = None) -> Path:
    """A run folder as matl.train / matl.eval leaves it: .hydra/{config,hydra}.yaml and a result file."""
    cfg = compose_config(config_name, overrides, folder)
    (folder / ".hydra").mkdir(parents=True, exist_ok=True)
    OmegaConf.save(cfg, folder / ".hydra" / "config.yaml")
    hydra_cfg = OmegaConf.create({"hydra": {"runtime": {"choices": choices or {}}}})
    OmegaConf.save(hydra_cfg, folder / ".hydra" / "hydra.yaml")
    if metrics is not None:
        name = "eval.json" if config_name == "eval" else "metrics.json"
        (folder / name).write_text(json.dumps(metrics))
    if failed is not None:
        (folder / "failed.json").write_text(json.dumps({"reason": failed}))
    return folder


def metrics_for(rec: float, pose: float | None, seed: int, N: int = 4) -> dict:
    no_pose = pose is None
    return {"rec_acc": rec, "pose_err": pose, "corner_err_px": None if no_pose else 10 * pose,
            "corner_err_px_median": None if no_pose else 9 * pose, "pose_acc_5px": None if no_pose else rec / 2,
            "query_ms": 1.5, "seed": seed, "N": N}


@pytest.fixture
def sweep(tmp_path: Path) -> Path:
    """Rows a, b, f on synthetic_arc and f on synthetic_apc (scale=cpu, 3 seeds), N=2 for Fig. 4, a
    SIFT evaluation, Table 2 (a), a failed and an unfinished job, and an older duplicate of a seed."""
    root = tmp_path / "multirun"
    values = {"table1_a": (0.80, 1.80), "table1_b": (0.85, None), "table1_f": (0.90, 0.70)}
    k = 0
    for data in ("synthetic_arc", "synthetic_apc"):
        for row, (rec, pose) in values.items():
            if data == "synthetic_apc" and row != "table1_f":
                continue
            for seed in range(3):
                fake_run(root / str(k), [f"experiment={row}", "scale=cpu", f"data={data}", f"seed={seed}"],
                         metrics_for(rec + 0.01 * seed, None if pose is None else pose + 0.02 * seed, seed),
                         {"data": data, "scale": "cpu", "experiment": row})
                k += 1
    for seed in range(2):  # Fig. 4: N=2 (N=1 and N=4 are rows a and f)
        fake_run(root / str(k), ["experiment=table1_f", "N=2", "scale=cpu", f"seed={seed}"],
                 metrics_for(0.85, 1.0, seed, N=2), {"data": "synthetic_arc", "scale": "cpu"})
        k += 1
    fake_run(root / str(k), ["experiment=table2_c", "scale=cpu", "seed=0"], metrics_for(0.7, 0.9, 0),
             {"data": "synthetic_ycb_table2", "scale": "cpu"})
    k += 1
    fake_run(root / str(k), ["experiment=table1_g", "scale=cpu", "seed=0"], None, {"data": "synthetic_arc",
                                                                                    "scale": "cpu"},
             failed="NonFiniteLossError: training loss became nan")
    k += 1
    fake_run(root / str(k), ["experiment=table1_h", "scale=cpu", "seed=0"], None, {"data": "synthetic_arc",
                                                                                    "scale": "cpu"})
    k += 1
    # an older run of row f / seed 0 with other numbers: the newest run of a seed wins
    old = fake_run(tmp_path / "old" / "0", ["experiment=table1_f", "scale=cpu", "seed=0"], metrics_for(0.1, 9.0, 0),
                   {"data": "synthetic_arc", "scale": "cpu"})
    os.utime(old / "metrics.json", (1, 1))
    evals = tmp_path / "evals"
    for seed in range(2):
        fake_run(evals / str(seed), ["experiment=table1_d", "data=synthetic_arc", f"seed={seed}"],
                 {**metrics_for(0.75, 0.65, seed), "evaluated": "baseline", "baseline": "sift", "data": "synthetic_arc",
                  "image_size": 100, "num_queries": 1000}, {"data": "synthetic_arc", "baseline": "sift"},
                 config_name="eval")
    return tmp_path


def test_report_tables_from_fake_runs(sweep: Path) -> None:
    out = sweep / "report"
    rep = report.build_report([sweep / "multirun", sweep / "old", sweep / "evals"], out, auto_fig5=True)
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
    assert "## Table 2" in text and "0.700 (1)" in text
    assert (out / "fig4.png").is_file() and "![Fig. 4](fig4.png)" in text
    fig4 = [line for line in text.splitlines() if line.startswith("| synthetic_arc |")]
    assert [line.split(" | ")[1] for line in fig4] == ["1", "2", "4"]
    # failures and unfinished jobs are listed, not averaged; the duplicate is noted
    assert "## Failed runs" in text and "NonFiniteLossError: training loss became nan" in text
    assert "## Unfinished runs" in text
    assert "1 older run(s)" in text
    assert "Fig. 5 skipped" not in text and not (out / "fig5.png").exists()  # fake runs have no checkpoints
    # table.csv: one row per configuration with numeric columns and its place in the paper's tables
    with (out / "table.csv").open() as f:
        rows = list(csv.DictReader(f))
    by_role = {(r["table1_row"], r["dataset"]): r for r in rows if r["table1_row"]}
    f_arc = by_role[("f", "synthetic_arc")]
    assert float(f_arc["rec_acc_mean"]) == pytest.approx(rec[0])
    assert float(f_arc["rec_acc_std"]) == pytest.approx(rec[1])
    assert f_arc["runs"] == "3" and f_arc["seeds"] == "0 1 2" and f_arc["fig4_N"] == "4"
    assert float(f_arc["paper_rec_acc_mean"]) == 0.93 and float(f_arc["paper_pose_err_mean"]) == 0.66
    assert by_role[("b", "synthetic_arc")]["pose_err_mean"] == ""
    assert by_role[("d", "synthetic_arc")]["kind"] == "baseline"
    assert any(r["table2_row"] == "c" for r in rows)
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
    report.build_report([evals], tmp_path / "report", auto_fig5=False)
    text = (tmp_path / "report" / "report.md").read_text()
    section = text.split("## Methods on the same test queries", 1)[1].split("\n## ", 1)[0]
    assert "synthetic_arc, split seed(s) 0, 1000 queries:" in section
    rows = {line.split(" | ")[0].lstrip("| "): [c.strip() for c in line.strip("|").split("|")]
            for line in section.splitlines() if line.startswith("| (") or line.startswith("| SIFT")}
    matl = "(f) Ours (multiple anchors, λ=10, N=4)"
    assert set(rows) == {matl, f"{matl} + refinement", "(b) TL [29]", "SIFT+RANSAC [20, 13]"}
    assert rows["(f) Ours (multiple anchors, λ=10, N=4) + refinement"][2] == "0.400 (1)"
    assert rows["(b) TL [29]"][2:5] == ["n/a", "n/a", "n/a"] and rows["(b) TL [29]"][1] == "0.880 (1)"
    assert rows["SIFT+RANSAC [20, 13]"][1] == "0.970 (1)" and rows["SIFT+RANSAC [20, 13]"][3] == "0.810 (1)"


def test_rows_are_read_from_the_config_not_the_experiment_name(tmp_path: Path) -> None:
    """experiment=table1_f N=2 is a Fig. 4 point; a plain run with the same settings as row (g) is row (g)."""
    a = report.load_run(fake_run(tmp_path / "a", ["experiment=table1_f", "N=2"], metrics_for(0.5, 1.0, 0)))
    assert a.table1 is None and a.fig4 is not None and a.fig4[1] == 2
    g = report.load_run(fake_run(tmp_path / "g", ["lam=0"], metrics_for(0.5, 1.0, 0)))
    assert g.table1 == "g" and g.paper_column == "ARC"
    j = report.load_run(fake_run(tmp_path / "j", ["loss=nce", "data.batch_size=40"], metrics_for(0.5, 1.0, 0)))
    assert j.table1 == "j"
    other = report.load_run(fake_run(tmp_path / "o", ["loss=nce", "N=6", "data.batch_size=40"],
                                     metrics_for(0.5, 1.0, 0)))
    assert other.table1 is None and other.fig4 is None
    ycb_all = report.load_run(fake_run(tmp_path / "y", ["data=synthetic_ycb", "data.source.subset=all"],
                                       metrics_for(0.5, 1.0, 0)))
    assert ycb_all.dataset == "synthetic_ycb/all" and ycb_all.paper_column is None  # not the paper's YCB
    # two seeds of one config share a fingerprint; another lam does not
    s1 = report.load_run(fake_run(tmp_path / "s1", ["seed=1"], metrics_for(0.5, 1.0, 1)))
    s0 = report.load_run(fake_run(tmp_path / "s0", ["seed=0"], metrics_for(0.5, 1.0, 0)))
    assert s0.fingerprint == s1.fingerprint != g.fingerprint


def test_cli(sweep: Path, capsys: pytest.CaptureFixture) -> None:
    assert report.main([str(sweep / "multirun"), "--out", str(sweep / "cli"), "--no-fig5"]) == 0
    assert "## Table 1" in capsys.readouterr().out and (sweep / "cli" / "table.csv").is_file()
    empty = sweep / "empty"
    empty.mkdir()
    assert report.main([str(empty)]) == 2
    assert report.main([str(sweep / "missing")]) == 2


# ------------------------------------------------------------------------------------ figures
def test_fig2_curve_has_minima_at_0_and_180() -> None:
    """A label-like image (a 2:1 rectangle with an off-centre mark): rotated by 180 deg its silhouette
    matches again, so the loss has a poor local minimum there, as Fig. 2 shows for a book."""
    image = torch.zeros(3, 32, 32)
    image[:, 10:22, 4:28] = 0.6
    image[0, 12:16, 6:12] = 1.0
    angles = torch.arange(-180.0, 181.0, 5.0, dtype=torch.float64)
    values = appearance_vs_rotation(image, angles)
    assert values[angles == 0].item() == pytest.approx(0.0, abs=1e-6)
    minima = dict(local_minima(angles.tolist(), values.tolist()))
    assert 0.0 in minima and -180.0 in minima and 180.0 in minima
    assert values[angles == 180].item() < values[angles == 90].item()


def test_fig2_from_a_tiny_catalog(tmp_path: Path, cache_dir: Path) -> None:
    path, caption = report.write_fig2(tmp_path / "fig2.png", "synthetic_apc", None, 32, str(cache_dir))
    assert path.is_file() and path.stat().st_size > 0 and "Local minima" in caption
    with (tmp_path / "fig2.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 181 and float(rows[90]["rotation_deg"]) == 0.0
    assert float(rows[90]["appearance_loss"]) < 1e-6 < min(float(r["appearance_loss"]) for r in rows[:80])


def _fake_checkpoint(path: Path, overrides: list[str], cache_dir: Path) -> Path:
    """A matl.train-style checkpoint of a freshly initialised model (no training needed for the figure)."""
    cfg = compose_config("train", [*TINY, f"paths.cache_dir={cache_dir}", *overrides], path.parent)
    config = OmegaConf.to_container(cfg, resolve=True)
    model = hydra.utils.instantiate(cfg.model)
    torch.save({"state_dict": model.state_dict(), "matl_config": config, "matl_image_size": 32,
                "matl_num_anchors": cfg.N, "epoch": 0, "global_step": 0}, path)
    return path


def test_fig5_from_two_checkpoints(tmp_path: Path, cache_dir: Path) -> None:
    single = _fake_checkpoint(tmp_path / "single.ckpt", ["N=1"], cache_dir)
    matl = _fake_checkpoint(tmp_path / "matl.ckpt", ["N=4", "seed=1"], cache_dir)
    panels = fig5_panels(single, matl, rows=3, pool=40)
    assert panels.query.shape == panels.single.shape == panels.matl.shape == panels.anchor.shape == (3, 3, 32, 32)
    assert len(panels.labels) == 3 and all("rotation" in label for label in panels.labels)
    rotations = [abs(float(label.rsplit(" ", 1)[-1].rstrip("°"))) for label in panels.labels]
    assert rotations == sorted(rotations)  # from small to large in-plane rotation
    assert plot_fig5(panels, tmp_path / "fig5.png").is_file()
    # through the report, with the checkpoints given on the command line
    rep = report.build_report([], tmp_path / "rep", fig5=[single, matl])
    assert (tmp_path / "rep" / "fig5.png").is_file() and "![Fig. 5](fig5.png)" in (rep.out / "report.md").read_text()
    assert not math.isnan(float(panels.matl.mean()))


def test_configs_that_resolve_alike_group_together() -> None:
    from matl.report import config_container, fingerprint

    def run(t_max: object, seed: int) -> str:
        trainer = {"max_epochs": 8, "default_root_dir": "${hydra:runtime.output_dir}"}  # unresolvable here
        cfg = OmegaConf.create({"seed": seed, "trainer": trainer, "data": {"seed": "${seed}"},
                                "model": {"scheduler": {"T_max": t_max}}})
        return fingerprint(config_container(cfg))

    assert run(8, 0) == run("${trainer.max_epochs}", 1) == run("${trainer.max_epochs}", 2)  # seeds of one setting
    assert run(4, 0) != run(8, 0)
