"""``python -m matl.predict ckpt=<path> gallery=<dir> images=<dir or file> out=<file.jsonl>``.

Recognition and pose for real image files (docs/design.md), with a gallery enrolled from canonical
image files, without retraining (paper Sec. 2.1). A thin user of the Python API
(:class:`matl.Recognizer`, :mod:`matl.inference.api`):

1. *Enrol*: every ``<gallery>/<object>/<plane>.{png,jpg,jpeg}`` is loaded, resized with its aspect
   kept and centre-padded with 0 to the checkpoint's model size (:mod:`matl.data.image_files`),
   rotated into the checkpoint's ``N`` fixed anchors, and embedded once by ``c()``. The features are
   cached next to the gallery in ``.matl_gallery_<ckpt>_<settings>/``, one file per product (plain tensors,
   loads with ``weights_only=True``), keyed by the checkpoint's sha256 and the path, mtime and size of
   its files, so adding, removing or editing a product embeds that product alone.
2. *Predict*: query files of any size go through the same resize/pad, in batches; the recognizer
   returns the nearest anchor and the model-frame pose, which is re-expressed in the original pixel
   coordinates of the gallery file and of the query file. A query farther than ``threshold`` from
   every anchor is a product that is not enrolled: ``known`` false, ``object`` and ``plane`` null
   (``threshold=auto`` calibrates it on the gallery itself; ``threshold=null`` is a closed set).

Output: one JSON line per usable image::

    {"image": "crops/0001.jpg", "object": "cereal", "plane": "front", "known": true,
     "nearest_object": "cereal", "anchor": 2, "distance": 0.31, "score": 0.97,
     "H": [[...], [...], [...]], "gallery_image": "gallery/cereal/front.png"}

``H`` is ``query_H_canon`` in file pixels (``null`` for models without an STN), so
``cv2.warpPerspective(cv2.imread(gallery_image), np.array(H), (query_w, query_h))`` lands on the
query. Bad files are reported in one line each and skipped; when no file at all can be read,
nothing is written and the command exits 2 naming the files. ``viz=true`` writes ``<stem>.png``
per query: the plane outlined on the query by ``H``, the query warped into the anchor frame by the
homography that produced ``H`` (the refined one with ``refine=true``), the anchor; an unknown
query's outline and verdict are red.

Large query sets split over processes or hosts: ``shard=<k> shards=<K>`` answers the files ``k, k + K, ...`` of the
sorted list, e.g. ``python -m matl.predict -m ... shards=4 'shard=range(4)' hydra/launcher=joblib`` (each job writes
``predictions.jsonl`` in its own folder of the sweep); ``python -m matl.score predictions=<the sweep folder>
truth=...`` scores them as one run.
"""

from __future__ import annotations

from omegaconf import DictConfig

from matl.utils.cli import command


@command("predict", sweepable=True)
def main(cfg: DictConfig) -> int:
    from matl.inference.files import predict  # torch and the models load after composition

    return predict(cfg)["predicted"]  # under -m (shards) a failing job writes failed.json and the others go on


if __name__ == "__main__":
    main()
