"""Sweeps on real launchers: failing jobs, resumable jobs, DDP inside sweeps, a summary at the end.

* :func:`run_sweep_job`: under ``-m`` (multirun) one job's exception must not end the sweep.
  Hydra's sweepers re-raise a failed job's exception after its batch, which stops every later
  batch (and exits non-zero even when 29 of 30 jobs finished). The job logs the traceback (into
  its ``<job dir>/train.log``), writes ``failed.json`` with the one-line reason in its job dir and
  returns NaN, which the basic sweeper ignores and Optuna records as a failed trial.
* :func:`auto_resume`: ``resume=auto`` continues a job in its own folder: ``metrics.json`` present
  -> the job is complete and is skipped; ``checkpoints/last.ckpt`` present -> training resumes
  from it (exact resume: :class:`matl.models.checkpoint.AtomicModelCheckpoint`); else
  it starts fresh. Re-running a sweep with the same ``hydra.sweep.dir`` gives each job the same
  folder (``<sweep dir>/<job num>``), so an interrupted sweep finishes only what is missing; a
  SLURM job requeued after a timeout does the same.
* :func:`check_distributed_launch`: Lightning starts the extra DDP processes of a local run by
  re-running the command line, which under ``-m`` would re-run the whole sweep in every process.
  Refused with a one-line error unless the processes come from SLURM or torchrun.
* :class:`SweepSummary`: a Hydra callback that lists the failed jobs when a multirun ends.

Only light imports at module level: ``matl.train`` imports this before validating a config.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from matl.utils.distributed import is_global_zero
from matl.utils.errors import MatlError

log = logging.getLogger(__name__)

FAILED_FILE = "failed.json"
METRICS_FILE = "metrics.json"


def is_multirun() -> bool:
    """True inside a job of a Hydra multirun (``-m``); False for single runs and plain function calls."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    if not HydraConfig.initialized():
        return False
    return HydraConfig.get().mode == RunMode.MULTIRUN


def _job_overrides() -> list[str]:
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return []
    return list(HydraConfig.get().overrides.task)


def one_line(error: BaseException) -> str:
    """``Type: message`` on one line (the first line of a multi-line message)."""
    text = " ".join(str(error).strip().splitlines()[0].split()) if str(error).strip() else ""
    return f"{type(error).__name__}: {text}" if text else type(error).__name__


def write_failed(output_dir: Path, error: BaseException) -> Path:
    """``<output_dir>/failed.json``: the one-line reason, the exception type and the job's overrides."""
    from matl.utils.io import write_json

    output_dir.mkdir(parents=True, exist_ok=True)
    path = output_dir / FAILED_FILE
    write_json(path, {"reason": one_line(error), "type": type(error).__name__, "overrides": _job_overrides(),
                      "log": "the full traceback is in this folder's *.log"})
    return path


def run_sweep_job(job: Callable[[DictConfig], Any], cfg: DictConfig) -> tuple[Any, BaseException | None]:
    """``job(cfg)``, or ``(None, error)`` after recording a failure (see the module docstring).

    Only ``Exception`` is caught: Ctrl-C (``KeyboardInterrupt``) and ``SystemExit`` still stop the sweep.
    """
    output_dir = Path(str(cfg.paths.output_dir))
    try:
        return job(cfg), None
    except Exception as error:  # any failure of a job is reported, instead of ending the sweep
        log.exception("job failed (the sweep continues): %s", one_line(error))
        if is_global_zero():
            path = write_failed(output_dir, error)
            log.error("wrote %s", path)
        return None, error


def clear_failed(output_dir: Path) -> None:
    """Remove a stale ``failed.json`` once the job has completed (e.g. after a resume)."""
    path = output_dir / FAILED_FILE
    if path.is_file() and is_global_zero():
        path.unlink()


# ------------------------------------------------------------------------------------- resume
def checkpoint_dir(cfg: DictConfig) -> Path:
    """Where the run's checkpoints go (``callbacks.model_checkpoint.dirpath``, else ``<output_dir>/checkpoints``)."""
    dirpath = OmegaConf.select(cfg, "callbacks.model_checkpoint.dirpath", default=None)
    return Path(str(dirpath)) if dirpath else Path(str(cfg.paths.output_dir)) / "checkpoints"


def auto_resume(cfg: DictConfig) -> tuple[str | None, dict[str, Any] | None]:
    """Apply ``resume``: returns ``(checkpoint to resume from or None, finished metrics or None)``.

    ``resume=null`` changes nothing. ``resume=auto``: finished metrics when ``metrics.json`` is
    already in the run folder (the caller returns them without training), else ``last.ckpt`` of
    the run's checkpoint folder when present, else nothing (a fresh start). Explicit
    ``ckpt_path=`` together with ``resume=auto`` is ambiguous and refused.
    """
    mode = cfg.get("resume")
    if mode in (None, "", False):
        return None, None
    if mode != "auto":
        raise MatlError(f"resume={mode} is invalid: use resume=auto (continue this run folder) or "
                        "ckpt_path=<file> (resume from a given checkpoint)")
    if cfg.get("ckpt_path"):
        raise MatlError("resume=auto and ckpt_path= are both set: resume=auto picks <run>/checkpoints/last.ckpt "
                        "itself; drop one of them")
    output_dir = Path(str(cfg.paths.output_dir))
    metrics = output_dir / METRICS_FILE
    if metrics.is_file() and cfg.get("test", True):
        log.info("resume=auto: %s exists, the run is complete; not training again", metrics)
        return None, json.loads(metrics.read_text())
    last = checkpoint_dir(cfg) / "last.ckpt"
    if last.is_file():
        log.info("resume=auto: resuming from %s", last)
        return str(last), None
    log.info("resume=auto: no %s yet, starting fresh", last)
    return None, None


# ------------------------------------------------------------------------------------ DDP in sweeps
def _process_count(trainer: DictConfig) -> int | None:
    """Processes a trainer config asks for (devices x nodes), None when it cannot tell (``auto``, -1)."""
    devices, nodes = trainer.get("devices", 1), trainer.get("num_nodes", 1) or 1
    if isinstance(devices, (list, tuple)) or OmegaConf.is_list(devices):
        count = len(devices)
    elif isinstance(devices, int) and devices >= 1:
        count = devices
    elif isinstance(devices, str) and devices.isdigit():
        count = int(devices)
    else:
        return None
    return count * int(nodes)


def _strategy_name(trainer: DictConfig) -> str:
    strategy = trainer.get("strategy")
    if isinstance(strategy, DictConfig):
        return str(strategy.get("_target_", "")).lower()
    return str(strategy or "").lower()


def externally_launched() -> bool:
    """The DDP processes are started by a cluster launcher (SLURM tasks, torchrun), not by Lightning."""
    ntasks = os.environ.get("SLURM_NTASKS", "")
    return (ntasks.isdigit() and int(ntasks) > 1) or "TORCHELASTIC_RUN_ID" in os.environ


def check_distributed_launch(cfg: DictConfig) -> None:
    """Refuse a local multi-process DDP job inside a multirun (see the module docstring)."""
    trainer = cfg.get("trainer")
    if not isinstance(trainer, DictConfig) or not is_multirun():
        return
    strategy = _strategy_name(trainer)
    if "ddp" not in strategy or "spawn" in strategy:
        return
    count = _process_count(trainer)
    if count == 1 or externally_launched() or "LOCAL_RANK" in os.environ:
        return
    raise MatlError("a multi-process DDP trainer inside a local multirun (-m) is not supported: Lightning starts "
                    "the other processes by re-running the command line, i.e. the whole sweep. Run DDP jobs one "
                    "at a time (python -m matl.train trainer=ddp ...), or sweep with hydra/launcher=slurm, where "
                    "SLURM starts one task per device")


# ------------------------------------------------------------------------------------ summary
try:
    from hydra.experimental.callback import Callback as _HydraCallback
except ImportError:  # pragma: no cover - hydra < 1.1
    _HydraCallback = object  # type: ignore[assignment,misc]


class SweepSummary(_HydraCallback):  # type: ignore[misc]
    """Hydra callback: at the end of a multirun, log how many jobs failed and where their reasons are."""

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        sweep_dir = Path(str(config.hydra.sweep.dir))
        failed = sorted(sweep_dir.glob(f"*/{FAILED_FILE}")) if sweep_dir.is_dir() else []
        done = [*sorted(sweep_dir.glob(f"*/{METRICS_FILE}")), *sorted(sweep_dir.glob("*/eval.json")),
                *sorted(sweep_dir.glob("*/enrol.json")), *sorted(sweep_dir.glob("*/predictions.jsonl"))]
        if not failed:
            log.info("sweep %s: %d job(s) with results, none failed", sweep_dir, len(done))
            return
        log.warning("sweep %s: %d job(s) failed, %d with results", sweep_dir, len(failed), len(done))
        for path in failed:
            try:
                reason = json.loads(path.read_text()).get("reason", "?")
            except (OSError, ValueError):
                reason = "?"
            log.warning("  %s: %s", path.parent, reason)

