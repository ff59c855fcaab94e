"""``python -m matl.unseen ckpt=<path> [data=synthetic_apc] [queries=1000] [out=<dir>]``.

Recognition (and pose) of products the checkpoint never saw in training, measured through the
user-facing path, ``matl.predict`` with a gallery enrolled from image files (paper Sec. 2.1):

1. *Products*: the canonical images of ``data``'s source (default ``synthetic_apc``), rendered by the
   project's own pipeline at ``file_size`` px (default: the checkpoint's model size). Every product
   the checkpoint's training catalog also holds is dropped (:func:`seen_products`: same name, or same
   brand and title, i.e. the same product printed again); products that only share a title with
   another brand, or a brand and a kind, stay and are listed as ``related``.
2. *Gallery*: ``<out>/gallery/<object>/<plane>.png`` (the ``images`` layout of docs/datasets.md). The files are the
   catalog's full canonical frames, in which each plane spans 0.6 of the side as in training, so
   predict runs with ``gallery_fill=1.0``; with ``gallery_crop=true`` they are tight crops of the
   plane (its mask's bounding box) enrolled with ``gallery_fill=0.6``, which frames them the same way.
3. *Queries*: ``queries`` files ``<out>/queries/q<i>.png``, each a canonical image warped by a random
   homography of ``data.homography`` (the paper's ranges, scaled with the file size) with the fixed
   ``query_seed``; the ground truth (object, plane, gallery file, ``query_H_canon`` in the files'
   pixel coordinates) goes to ``<out>/truth.jsonl`` (:mod:`matl.score`'s sidecar format).
4. ``python -m matl.predict ckpt=... gallery=... images=... out=<out>/predictions.jsonl`` (a separate
   process: exactly the command a user runs), then :func:`matl.score.score_files`.

Writes ``<out>/unseen.json`` (the metrics of docs/design.md, ``plane_acc``, the products, what was excluded and
why, per-object accuracy, the most frequent confusions and the commands used) and
``<out>/per_query.csv``.
"""

from __future__ import annotations

from omegaconf import DictConfig

from matl.utils.cli import command


@command("unseen")
def main(cfg: DictConfig) -> None:
    from matl.evaluation.unseen import unseen  # torch and the models load after composition

    unseen(cfg)


if __name__ == "__main__":
    main()
