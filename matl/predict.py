"""``python -m matl.predict ckpt=<path> gallery=<dir> images=<dir or file> out=<file.jsonl>``.

Recognition and pose for real image files (DESIGN §5), with a gallery enrolled from canonical image
files, without retraining (paper Sec. 2.1):

1. *Enrol*: every ``<gallery>/<object>/<plane>.{png,jpg,jpeg}`` is loaded, resized with its aspect
   kept and centre-padded with 0 to the checkpoint's model size (:mod:`matl.data.image_files`),
   rotated into the checkpoint's ``N`` fixed anchors, and embedded once by ``c()``. The features are
   cached next to the gallery in ``.matl_gallery_<ckpt>_<files>.pt`` (plain tensors, loads with
   ``weights_only=True``), keyed by the checkpoint's sha256 and every file's path, mtime and size,
   so adding, removing or editing a file refreshes it.
2. *Predict*: query files of any size go through the same resize/pad, in batches; the recognizer
   returns the nearest anchor and the model-frame pose, which is re-expressed in the original pixel
   coordinates of the gallery file and of the query file.

Output: one JSON line per usable image::

    {"image": "crops/0001.jpg", "object": "cereal", "plane": "front", "anchor": 2, "distance": 0.31,
     "H": [[...], [...], [...]], "gallery_image": "gallery/cereal/front.png"}

``H`` is ``query_H_canon`` in file pixels (``null`` for models without an STN), so
``cv2.warpPerspective(cv2.imread(gallery_image), np.array(H), (query_w, query_h))`` lands on the
query. Bad files are reported in one line each and skipped.
"""

from __future__ import annotations

from omegaconf import DictConfig

from matl.utils.cli import command


@command("predict")
def main(cfg: DictConfig) -> None:
    from matl.inference.files import predict  # torch and the models load after composition

    predict(cfg)


if __name__ == "__main__":
    main()
