"""Fake run folders as ``matl.train`` / ``matl.eval`` leave them, for the reporting tests (nothing is trained)."""

from __future__ import annotations

import json
import os
from pathlib import Path

from omegaconf import OmegaConf

from tests.conftest import compose_config


def fake_run(folder: Path, overrides: list[str], metrics: dict | None, choices: dict | None = None,
             config_name: str = "train", failed: str | None = None) -> Path:
    """A run folder: .hydra/{config,hydra}.yaml composed from the real configs, and a result file."""
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
    """A metrics.json: corner errors 10x / 9x the pose error, pose_acc_5px half the accuracy, 1.5 ms a query."""
    no_pose = pose is None
    return {"rec_acc": rec, "pose_err": pose, "corner_err_px": None if no_pose else 10 * pose,
            "corner_err_px_median": None if no_pose else 9 * pose, "pose_acc_5px": None if no_pose else rec / 2,
            "query_ms": 1.5, "seed": seed, "N": N}


def make_sweep(tmp_path: Path) -> Path:
    """Rows a, b, f on synthetic_arc and f on synthetic_apc (scale=cpu, 3 seeds), N=2 for Fig. 4, a
    SIFT evaluation, Table 2 (c), a failed and an unfinished job, and an older duplicate of a seed.

    Folders: ``<tmp_path>/multirun``, ``<tmp_path>/old``, ``<tmp_path>/evals``; returns ``tmp_path``.
    """
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
