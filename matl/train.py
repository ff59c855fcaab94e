"""``python -m matl.train [overrides]``: train, test the best checkpoint, write ``metrics.json``.

Composes ``conf/train.yaml`` and runs :func:`matl.training.fit.train`; under ``-m`` a failing job
writes ``failed.json`` and the sweep goes on. Returns the test value of ``optimized_metric`` for
Hydra's sweepers. Options, sweeps and resuming: docs/experiments.md.
"""

from __future__ import annotations

from omegaconf import DictConfig

from matl.utils.cli import command


@command("train", sweepable=True, next_step="python -m matl.eval run={output_dir}")
def main(cfg: DictConfig) -> float | None:
    from matl.training.fit import sweep_value, train  # torch and Lightning load after composition

    return sweep_value(train(cfg), cfg)


if __name__ == "__main__":
    main()
