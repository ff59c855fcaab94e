"""``python -m matl.export ckpt=<path> out=<dir> [format=torchscript|export]``: the inference path without matl.

Writes two self-contained modules and a description into ``out``:

* ``gallery_net.pt``: ``c()``, ``(B, 3, S, S) -> (B, D)`` embeddings of gallery anchors (enrol once).
* ``query_net.pt``: ``s()`` then ``c()`` on queries, ``(B, 3, S, S) -> (embedding (B, D),
  query_H_anchor (B, 3, 3) pixel homography, degenerate (B,) bool, warped (B, 3, S, S))``.
* ``export.json``: image size, N, embedding size, the conventions, the checkpoint's sha256, and the
  largest difference between exported and eager outputs measured right after export.

Recognition is then ``argmin_g ||gallery_emb[g] - query_emb||`` and the pose
``query_H_canon = query_H_anchor @ anchor_H_canon[g]`` (docs/design.md, "Homographies and their
frames"), a few lines in any runtime.

Formats: ``torchscript`` (default; ``torch.jit.load`` in Python or libtorch in C++, no matl or kornia
needed) or ``export`` (``torch.export``, ``.pt2`` files loaded with ``torch.export.load``; dynamic batch).
The query module re-expresses the STN's forward pass with plain torch ops (``grid_sample`` on a
precomputed grid, the degeneracy guard as ``torch.where``; :class:`matl.inference.recognizer.QueryGraph`)
so that tracing records no Python branch; the export is checked against the eager model on every
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
