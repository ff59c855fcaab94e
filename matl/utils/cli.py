"""The one wrapper every ``python -m matl.<command>`` uses: Hydra main, one-line errors, sweeps, a last line.

An entry point is a module at the top of the package whose ``main`` is::

    @command("eval", sweepable=True, next_step="python -m matl.report {output_dir}")
    def main(cfg: DictConfig) -> Any:
        return evaluate(cfg)

which composes ``conf/<config_name>.yaml`` with the command line's overrides and then

* turns Hydra's own composition errors (``data=foo``, an unknown key) into ``error: <one line>``,
  exit status 2 (:func:`matl.utils.errors.hydra_errors`);
* turns a :class:`matl.utils.errors.MatlError` raised by the task into the same (exit 2);
* under ``-m`` (``sweepable=True``) keeps one failing job from ending the sweep: the job writes
  ``failed.json`` and returns NaN (:func:`matl.utils.sweep.run_sweep_job`);
* ends a finished run with its folder and the next command to try, so a user never has to look
  for where the outputs went.
"""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Callable
from typing import Any

import hydra
from omegaconf import DictConfig

from matl.utils.errors import hydra_errors, user_errors
from matl.utils.sweep import is_multirun, run_sweep_job

log = logging.getLogger("matl")

Task = Callable[[DictConfig], Any]


def _run_folder(cfg: DictConfig) -> str | None:
    from hydra.core.hydra_config import HydraConfig

    folder = cfg.get("paths", {}).get("output_dir") if isinstance(cfg.get("paths"), DictConfig) else None
    if folder is None and HydraConfig.initialized():
        folder = HydraConfig.get().runtime.output_dir
    return None if folder is None else str(folder)


def command(config_name: str, sweepable: bool = False,
            next_step: str | None = None) -> Callable[[Task], Callable[[], Any]]:
    """Decorate ``main(cfg)`` of an entry point; see the module docstring.

    ``next_step`` is a command shown after a successful run; ``{output_dir}`` in it becomes the run
    folder. The task's return value is what a Hydra sweeper optimises.
    """

    def decorate(task: Task) -> Callable[[], Any]:
        @functools.wraps(task)
        def job(cfg: DictConfig) -> Any:
            with user_errors():
                if sweepable and is_multirun():
                    value, error = run_sweep_job(task, cfg)
                    if error is not None:
                        return math.nan
                else:
                    value = task(cfg)
            folder = _run_folder(cfg)
            if folder is not None:
                log.info("run folder: %s", folder)
                if next_step:
                    log.info("next: %s", next_step.format(output_dir=folder))
            return value

        return hydra_errors(hydra.main(config_path="../conf", config_name=config_name, version_base="1.3")(job))

    return decorate
