"""``python -m matl.score predictions=<file.jsonl> truth=<file.jsonl> (ckpt=<path> | image_size=<S>)``.

Scores the JSON lines of ``matl.predict`` (one file, or a folder of them: every ``*.jsonl`` under it, as
``matl.predict shard=<k> shards=<K>`` writes its shards) against a ground-truth sidecar with the metrics of
docs/design.md, for any gallery and query folder: the synthetic never-seen-products measurement of ``matl.unseen``
writes such a sidecar, and so can a robotics engineer who knows what is in their own camera crops.

Ground truth: one JSON line per query file::

    {"image": "queries/q0000.png", "object": "cereal", "plane": "front",
     "gallery_image": "gallery/cereal/front.png", "H": [[...], [...], [...]]}

``H`` is the true ``query_H_canon`` in the *files'* pixel coordinates (gallery file -> query file,
OpenCV convention, the same meaning as predict's ``H``); ``H`` and ``gallery_image`` may be left out
(or null) for recognition only. Relative paths are relative to the sidecar's folder. Predictions are
matched to the truth by file (``image`` resolved against the current folder, else against the
sidecar's folder, else by a unique file name); a query without a prediction (a file predict skipped)
counts as not recognised.

Metrics (docs/design.md): ``rec_acc`` (object correct), ``plane_acc`` (object and plane correct), and on
the recognised queries ``pose_err``, ``corner_err_px`` (mean), ``corner_err_px_median``, plus
``pose_acc_5px`` over all queries. Poses are compared at *model* resolution, as docs/design.md defines
them: both file-pixel ``H`` are taken into the model frame with the resize-and-pad predict applies
(:func:`matl.data.image_files.fit_geometry` with ``gallery_fill`` / ``query_fill``, which must be the
values predict ran with), ``model_H = query_model_H_file @ H @ inv(gallery_model_H_file)``. Writes
``score.json`` (metrics, per-object accuracy and the most frequent confusions) and
``per_query.csv``.

``ckpt=`` takes a path or a shipped model's name (``pretrained``, ``pretrained_fast``); ``out`` is checked
before the scoring (a ``score.json`` or ``per_query.csv`` already there is replaced only with
``overwrite=true``).
"""

from __future__ import annotations

from omegaconf import DictConfig

from matl.utils.cli import command

OUTPUTS = ("score.json", "per_query.csv")


def score(cfg: DictConfig) -> dict:
    """``matl.score``'s work: ``ckpt=`` resolved (:func:`matl.models.checkpoint.resolve_ckpt_option`) and ``out``
    checked first, then :func:`matl.evaluation.score.run`."""
    from matl.evaluation.score import run  # torch and the models load after composition
    from matl.models.checkpoint import resolve_ckpt_option
    from matl.utils.io import check_output_folder, overwrite_option

    resolve_ckpt_option(cfg)
    check_output_folder(cfg.out, OUTPUTS, "out", overwrite_option(cfg))
    return run(cfg)


@command("score")
def main(cfg: DictConfig) -> None:
    score(cfg)


if __name__ == "__main__":
    main()
