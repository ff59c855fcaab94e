"""``python -m matl.unseen ckpt=<path> [condition=clean|photometric|mask|clutter|view|sizes|all] [data=heldout]``.

``condition=catalog`` (alone) is the catalogue benchmark instead: galleries of ``catalog_sizes`` held-out
products, a quarter in look-alike families, against gallery size (:mod:`matl.evaluation.catalog`,
docs/catalog.md); it writes ``<out>/catalog.json``, ``catalog.md`` and ``catalog.png``.

The benchmark of products the checkpoint never saw in training, measured through the user-facing
path, ``matl.predict`` with a gallery enrolled from image files (paper Sec. 2.1):

1. *Products*: the canonical images of ``data``'s source (default ``heldout``: a procedural catalog
   whose art comes from scikit-image's bundled photos, a pool no training catalog uses;
   ``data=synthetic_apc`` is the earlier default), rendered at ``file_size`` px (default: the
   checkpoint's model size). Every product the checkpoint's training catalog also holds is dropped
   (:func:`~matl.evaluation.unseen.seen_products`: same name, or same brand and title); products that
   only share a title with another brand, or a brand and a kind, stay and are listed as ``related``.
2. *Gallery*: ``gallery/<object>/<plane>.png`` (the ``images`` layout of docs/datasets.md), full
   canonical frames enrolled with ``gallery_fill=1.0`` (``gallery_crop=true``: tight crops, 0.6).
3. *Queries*: ``queries`` files per condition, the same planes and poses (``data.homography``, fixed
   ``query_seed``) in every condition that has poses (:mod:`matl.evaluation.conditions`): ``clean``
   warps, ``photometric`` camera effects (JPEG files), ``mask`` RGBA files on real backgrounds with an
   imperfect alpha, ``clutter`` real backgrounds and a neighbouring product cut by the edge, ``view``
   pyrender views from 3D cameras (the plane-induced homography as truth), ``sizes`` other file sizes.
   The truth (object, plane, gallery file, ``query_H_canon`` in file pixels) goes to ``truth.jsonl``.
4. *Methods* (``methods``): predict's code (:func:`matl.inference.files.predict`, what ``python -m
   matl.predict`` runs) once per method on the same files, in this process
   (:mod:`matl.evaluation.unseen_methods`): ``matl``, ``matl_refine`` (``refine=true``), ``sift``,
   ``sift_ecc``, ``lightglue``, ``xfeat`` and ``xfeat_lighterglue`` (``baseline=<name>``, read and framed
   by the same code); scored by :func:`matl.evaluation.score.score_files`; ``query_ms`` of every method timed here on
   the same queries (``timing.*``: batch of 1, gallery in memory, warm-up, the same thread count).

Writes per condition ``unseen.json`` (the metrics of docs/design.md and ``plane_acc`` of the first
MATL method at the top level, every method's under ``methods``, the products, what was excluded and
why, per-object accuracy, confusions, the commands used) and ``per_query.csv``, into ``<out>/`` for
one named condition or ``<out>/<condition>/`` for ``all`` or a list; then ``<out>/benchmark.json`` and
``<out>/benchmark.md``, one row per condition and one column per method.
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
