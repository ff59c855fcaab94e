"""Sweep jobs: a failing job writes failed.json and the sweep goes on; resume=auto; DDP inside -m."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from omegaconf import OmegaConf, open_dict

from matl.utils import sweep
from matl.utils.errors import MatlError
from tests.conftest import TINY, compose_config

ROOT = Path(__file__).resolve().parents[2]


def _cfg(tmp_path: Path, extra: list[str] | None = None):
    return compose_config("train", [*TINY, *(extra or [])], tmp_path / "run")


def test_auto_resume_picks_what_the_folder_holds(tmp_path: Path) -> None:
    cfg = _cfg(tmp_path, ["resume=auto"])
    run = Path(cfg.paths.output_dir)
    assert sweep.auto_resume(cfg) == (None, None)  # empty folder: a fresh start
    last = run / "checkpoints" / "last.ckpt"
    last.parent.mkdir(parents=True)
    last.write_bytes(b"")
    assert sweep.auto_resume(cfg) == (str(last), None)
    (run / "metrics.json").write_text(json.dumps({"rec_acc": 0.5}))
    assert sweep.auto_resume(cfg) == (None, {"rec_acc": 0.5})  # complete: not trained again
    assert sweep.auto_resume(_cfg(tmp_path)) == (None, None)  # resume=null changes nothing
    with pytest.raises(MatlError, match="resume=sometimes"):
        sweep.auto_resume(_cfg(tmp_path, ["resume=sometimes"]))
    with pytest.raises(MatlError, match="both set"):
        sweep.auto_resume(_cfg(tmp_path, ["resume=auto", f"ckpt_path={last}"]))


def test_run_sweep_job_records_the_failure(tmp_path: Path) -> None:
    cfg = _cfg(tmp_path)

    def job(_):
        raise RuntimeError("CUDA out of memory.\nTried to allocate 2 GiB")

    result, error = sweep.run_sweep_job(job, cfg)
    assert result is None and isinstance(error, RuntimeError)
    failed = json.loads((Path(cfg.paths.output_dir) / "failed.json").read_text())
    assert failed["reason"] == "RuntimeError: CUDA out of memory." and failed["type"] == "RuntimeError"
    assert sweep.run_sweep_job(lambda c: {"rec_acc": 1.0}, cfg) == ({"rec_acc": 1.0}, None)
    with pytest.raises(KeyboardInterrupt):  # Ctrl-C still ends the sweep
        sweep.run_sweep_job(lambda c: (_ for _ in ()).throw(KeyboardInterrupt()), cfg)


def test_sweep_value_is_the_test_side_of_the_selection_score(tmp_path: Path) -> None:
    from matl.training.fit import sweep_value

    results = {"rec_acc": 0.9, "pose_err": 0.5, "pose_acc_5px": 0.25}
    assert sweep_value(results, _cfg(tmp_path)) == pytest.approx(1.15)  # default score: rec_acc + pose_acc_5px
    weighted = _cfg(tmp_path, ["model.score_weights.rec_acc=2", "model.score_weights.pose_acc_5px=-1"])
    assert sweep_value(results, weighted) == pytest.approx(1.55)
    assert sweep_value({"rec_acc": 0.8, "pose_acc_5px": None}, _cfg(tmp_path)) == pytest.approx(0.8)  # TL: no pose
    assert sweep_value(results, _cfg(tmp_path, ["optimized_metric=val/rec_acc"])) == 0.9


def test_eval_multirun_continues_past_failing_jobs(tmp_path: Path) -> None:
    sweep_dir = tmp_path / "sweep"
    args = [sys.executable, "-m", "matl.eval", "-m", f"run={tmp_path}/missing_a,{tmp_path}/missing_b",
            f"hydra.sweep.dir={sweep_dir}"]
    done = subprocess.run(args, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    for job, name in ((0, "missing_a"), (1, "missing_b")):  # the first failure did not end the sweep
        failed = json.loads((sweep_dir / str(job) / "failed.json").read_text())
        assert failed["reason"] == f"MatlError: run={tmp_path}/{name}: no such folder"
    assert "2 job(s) failed" in done.stdout + done.stderr


def test_local_ddp_inside_a_multirun_is_refused(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    for key in ("SLURM_NTASKS", "TORCHELASTIC_RUN_ID", "LOCAL_RANK"):
        monkeypatch.delenv(key, raising=False)
    ddp = _cfg(tmp_path, ["trainer=ddp_cpu"])
    sweep.check_distributed_launch(ddp)  # a single run: Lightning re-runs the command line, fine
    monkeypatch.setattr(sweep, "is_multirun", lambda: True)
    with pytest.raises(MatlError, match="hydra/launcher=slurm"):
        sweep.check_distributed_launch(ddp)
    sweep.check_distributed_launch(_cfg(tmp_path))  # one process: fine in a sweep
    with open_dict(ddp):
        ddp.trainer.devices = 1
    sweep.check_distributed_launch(ddp)
    with open_dict(ddp):
        ddp.trainer.devices = 2
    monkeypatch.setenv("SLURM_NTASKS", "2")  # SLURM started the processes
    sweep.check_distributed_launch(ddp)


def test_multirun_continues_past_a_failing_job_and_resumes(tmp_path: Path, cache_dir: Path) -> None:
    """CLI: job 0 fails (N=0), job 1 trains; the sweep exits 0. Re-run with resume=auto: job 1 is skipped."""
    sweep_dir = tmp_path / "sweep"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    args = [sys.executable, "-m", "matl.train", "-m", "N=0,1", "scale=smoke", "logger=none",
            "callbacks.progress_bar=null", f"paths.cache_dir={cache_dir}", f"hydra.sweep.dir={sweep_dir}"]
    first = subprocess.run(args, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert first.returncode == 0, first.stderr[-3000:]
    failed = json.loads((sweep_dir / "0" / "failed.json").read_text())
    assert failed["reason"].startswith("ConfigError: N=0 is invalid") and "N=0" in failed["overrides"]
    assert not (sweep_dir / "0" / "metrics.json").exists()
    metrics = json.loads((sweep_dir / "1" / "metrics.json").read_text())
    assert metrics["N"] == 1 and 0 <= metrics["rec_acc"] <= 1
    assert "1 job(s) failed" in first.stdout + first.stderr  # the sweep summary callback
    # the same sweep folder again with resume=auto: the finished job is not trained again
    stamp = (sweep_dir / "1" / "metrics.json").stat().st_mtime_ns
    second = subprocess.run([*args, "resume=auto"], cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert second.returncode == 0, second.stderr[-3000:]
    assert (sweep_dir / "1" / "metrics.json").stat().st_mtime_ns == stamp
    assert "the run is complete" in (sweep_dir / "1" / "train.log").read_text()
    saved = OmegaConf.load(sweep_dir / "1" / ".hydra" / "config.yaml")
    assert saved.resume == "auto"
