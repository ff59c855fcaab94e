"""``python -m matl.export ckpt=<path>|pretrained|pretrained_fast out=<dir> [format=torchscript|export|onnx]``.

The inference path without matl. Writes self-contained networks and a description into ``out``:

* ``gallery_net.<ext>``: ``c()``, ``(B, 3, S, S) -> (B, D)`` embeddings of gallery anchors (enrol once).
* ``query_net.<ext>``: ``s()`` then ``c()`` on queries, ``(B, 3, S, S) -> (embedding (B, D),
  query_H_anchor (B, 3, 3) pixel homography, degenerate (B,) bool, warped (B, 3, S, S))``.
* ``align_net.<ext>`` (a checkpoint with an alignment stage, ``model.align``, as the shipped default
  model): ``(images, anchors, stn_query_H_anchor, warped) -> query_H_anchor``, run after the search
  against the anchor found (:class:`matl.inference.export.AlignGraph`); its ``query_H_anchor`` is the
  pose ``matl.predict`` and ``matl.Recognizer`` give without refinement.
* ``foreground_net.<ext>`` (``foreground_net=shipped``, the default; ``null``: none): ``foreground=learned``'s
  visibility network, ``(B, 3, F, F)`` RGB crops without a mask at its working size ``F`` -> logits ``(B, 1, F,
  F)``, the probability that a pixel shows the visible print of the crop's target product (the mask a camera's
  crop needs before the query network).
* ``export.json``: image size, N, embedding size, the checkpoint's sha256, the largest difference
  between exported and eager outputs (per network and per output) measured right after export, and
  what a user of the files alone needs: input layout, outputs, recognition, pose, the anchors'
  matrices and the mapping to the original image's pixels.

Recognition is then ``argmin_g ||gallery_emb[g] - query_emb||`` and the pose
``query_H_canon = query_H_anchor @ anchor_H_canon[g]`` (docs/design.md), a few lines in any runtime;
``scripts/onnx_predict_example.py`` is that path with numpy, OpenCV and onnxruntime alone (docs/usage.md).

The files are written into a temporary folder and moved into ``out`` once every check has passed; an
earlier export's files in ``out`` are replaced only with ``overwrite=true`` (checked before any work).

Formats: ``torchscript`` (default; ``.pt``, ``torch.jit.load`` in Python or libtorch in C++, no matl or
kornia needed), ``export`` (``torch.export``, ``.pt2`` files loaded with ``torch.export.load``) or
``onnx`` (``.onnx``, opset 17, checked in onnxruntime's CPUExecutionProvider; both dependencies of matl).
Every format has a dynamic batch axis. The query network re-expresses the STN's forward pass with
plain torch ops (``grid_sample`` on a precomputed grid, the degeneracy guard as ``torch.where``;
:class:`matl.models.recognizer.QueryGraph`) so that tracing records no Python branch; for ONNX, which
has no SVD, the guard's singular values are computed in closed form
(:func:`matl.inference.export.svdvals_3x3`). The export is checked against the eager model on every
export (tolerance ``tolerance``).
"""

from __future__ import annotations

from omegaconf import DictConfig

from matl.utils.cli import command


@command("export")
def main(cfg: DictConfig) -> None:
    from matl.inference.export import export  # torch and the models load after composition

    export(cfg)


if __name__ == "__main__":
    main()
