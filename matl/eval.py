"""``python -m matl.eval run=<run dir> [ckpt=best|last|<path>|pretrained[_fast]] [data=<name>] [baseline=<name>]``.

Re-evaluates a checkpoint with the run's *own* saved config (``<run>/.hydra/config.yaml``; the
defaults are never re-composed, so later edits of ``conf/`` cannot change what a run means):

* the model is instantiated from the saved ``model`` node and the checkpoint's weights are loaded
  with ``torch.load(weights_only=True)``; ``ckpt=pretrained`` / ``pretrained_fast`` evaluates a shipped
  model instead (its size and N must be the run's);
* the queries are the run's test split (the saved ``data`` node, ``seed`` and ``N``), or with
  ``data=<name>`` another dataset: only that data group is composed and swapped into the saved
  config, the run's ``N``, ``seed`` and image size stay;
* ``baseline=sift|superpoint|lightglue`` evaluates a keypoint matcher instead, with the *same*
  evaluator on the *same* queries (pose = ``query_H_anchor @ anchor_H_canon`` of the matched gallery
  image); ``run=`` is then optional (``data=``, ``seed=`` and ``N=`` pick the queries).

Writes ``eval.json`` (metric names of docs/design.md plus what was evaluated) and ``per_query.csv`` into its
own run folder ``outputs/eval/<time>/``.
"""

from __future__ import annotations

from omegaconf import DictConfig

from matl.utils.cli import command


@command("eval", sweepable=True, next_step="python -m matl.report {output_dir}")
def main(cfg: DictConfig) -> None:
    from matl.evaluation.evaluate import evaluate  # torch and the models load after composition
    from matl.models.checkpoint import resolve_ckpt_option

    resolve_ckpt_option(cfg)  # ckpt=pretrained / pretrained_fast: a shipped model (best / last / a path as given)
    evaluate(cfg)


if __name__ == "__main__":
    main()
