"""scripts/reproduce_cpu.sh: its commands (printed by DRY_RUN=1) compose, job by job, as Hydra would."""

from __future__ import annotations

import os
import re
import shlex
import subprocess
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from tests.conftest import CONF_DIR

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "scripts" / "reproduce_cpu.sh"


def dry_run(out: Path, **env: str) -> list[list[str]]:
    done = subprocess.run(["bash", str(SCRIPT), str(out)], cwd=ROOT, capture_output=True, text=True, timeout=60,
                          env={**os.environ, "DRY_RUN": "1", **env})
    assert done.returncode == 0, done.stderr
    return [shlex.split(line[2:]) for line in done.stdout.splitlines() if line.startswith("+ ")]


def first_job(args: list[str]) -> list[str]:
    """The overrides of a multirun's first job: every swept ``key=a,b`` takes its first value."""
    out = []
    for arg in args:
        key, _, value = arg.partition("=")
        if "," in value and not re.search(r"[\[\]{}()]", value):
            value = value.split(",")[0]
        out.append(f"{key}={value}")
    return out


@pytest.mark.parametrize("scale", ["cpu", "smoke"])
def test_every_command_composes(scale: str, tmp_path: Path) -> None:
    commands = dry_run(tmp_path / "out", SCALE=scale, SEEDS="0,1", JOBS="2")
    apps = [c[2] for c in commands]
    assert apps.count("matl.train") == 3 * 2 + 1 and apps.count("matl.eval") == 3 and apps[-1] == "matl.report"
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        for command in commands:
            app, args = command[2], [a for a in command[3:] if a != "-m"]
            if app == "matl.report":
                assert "--fig2" in args and str(tmp_path / "out" / "report") in args
                continue
            cfg = compose(app.split(".")[1], first_job(args), return_hydra_config=True)
            if app == "matl.train":
                assert cfg.resume == "auto" and cfg.hydra.sweep.dir.startswith(str(tmp_path / "out"))
                assert cfg.data.image_size == (100 if scale == "cpu" else 32)
                assert cfg.hydra.runtime.choices["hydra/launcher"] == "joblib"
            if app == "matl.eval":  # the baseline's queries are the trained runs' test split
                assert cfg.baseline._target_.endswith("SiftRansacMatcher") and cfg.N == 4
                assert cfg.data.test_queries == (1000 if scale == "cpu" else 48)


def test_superpoint_only_with_weights_and_one_job(tmp_path: Path) -> None:
    commands = dry_run(tmp_path / "out", JOBS="1", DATASETS="synthetic_apc", MATL_SUPERPOINT_WEIGHTS="/w.pth")
    evals = [c for c in commands if c[2] == "matl.eval"]
    assert [next(a for a in c if a.startswith("experiment=")) for c in evals] == ["experiment=table1_d",
                                                                                   "experiment=table1_e"]
    assert not any(a.startswith("hydra/launcher") for c in commands for a in c)


def test_unknown_scale_is_refused(tmp_path: Path) -> None:
    done = subprocess.run(["bash", str(SCRIPT), str(tmp_path)], cwd=ROOT, capture_output=True, text=True,
                          env={**os.environ, "DRY_RUN": "1", "SCALE": "paper"}, timeout=60)
    assert done.returncode == 2 and "GPUs" in done.stderr


def test_compare_methods_evaluates_every_run_and_baseline_on_the_run_queries(tmp_path: Path) -> None:
    runs = []
    for name in ("n4", "n1", "tl"):
        (tmp_path / name / ".hydra").mkdir(parents=True)
        (tmp_path / name / ".hydra" / "config.yaml").write_text("task_name: train\n")
        runs.append(str(tmp_path / name))
    script = ROOT / "scripts" / "compare_methods.sh"
    env = {k: v for k, v in os.environ.items() if k != "MATL_SUPERPOINT_WEIGHTS"}
    done = subprocess.run(["bash", str(script), str(tmp_path / "out"), *runs], cwd=ROOT, capture_output=True,
                          text=True, timeout=60, env={**env, "DRY_RUN": "1", "BASELINES": "sift lightglue"})
    assert done.returncode == 0, done.stderr
    commands = [line[2:] for line in done.stdout.splitlines() if line.startswith("+ ")]
    evals = [c for c in commands if c.startswith("python -m matl.eval")]
    assert [c.split()[3] for c in evals[:3]] == [f"run={r}" for r in runs]
    assert f"run={runs[0]} refine=true" in evals[3]
    assert [c.split()[4] for c in evals[4:]] == ["baseline=sift", "baseline=lightglue"]
    assert all(f"run={runs[0]}" in c for c in evals[4:])  # the baselines see RUN_N4's gallery and queries
    assert len({c.rsplit("hydra.run.dir=", 1)[1] for c in evals}) == len(evals)  # one folder each
    assert commands[-1].startswith("python -m matl.report")
    assert [c.rsplit("hydra.run.dir=", 1)[1] for c in evals] == [
        str(tmp_path / "out" / name) for name in ("n4", "n1", "tl", "n4_refine", "baseline_sift", "baseline_lightglue")]
    (tmp_path / "out" / "baseline_sift").mkdir(parents=True)
    (tmp_path / "out" / "baseline_sift" / "eval.json").write_text("{}")  # finished before: skipped
    again = subprocess.run(["bash", str(script), str(tmp_path / "out"), *runs], cwd=ROOT, capture_output=True,
                           text=True, timeout=60, env={**env, "DRY_RUN": "1", "BASELINES": "sift lightglue"})
    assert "skip:" in again.stdout and "baseline=sift" not in again.stdout and "baseline=lightglue" in again.stdout
    bad = subprocess.run(["bash", str(script), str(tmp_path / "out"), str(tmp_path / "missing")], cwd=ROOT,
                         capture_output=True, text=True, timeout=60, env={**env, "DRY_RUN": "1"})
    assert bad.returncode == 2 and "not a matl.train run folder" in bad.stderr
