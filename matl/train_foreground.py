"""``python -m matl.train_foreground [overrides]``: train the visibility network of ``foreground=learned``.

Composes ``conf/train_foreground.yaml`` and runs :func:`matl.training.foreground.train_foreground`: scenes of
the training catalog (:mod:`matl.data.scenes`), the network (:mod:`matl.models.visibility`), the best
validation IoU's checkpoint in ``<run>/checkpoints/``, ``metrics.json``; ``publish=shipped`` writes the
network into the package (``matl/weights/matl_foreground.ckpt``). Returns the validation IoU.
"""

from __future__ import annotations

from omegaconf import DictConfig

from matl.utils.cli import command


@command("train_foreground", next_step="python -m matl.predict foreground=learned foreground.weights=<published file> "
                                       "gallery=<dir> images=<dir> out=<file.jsonl>")
def main(cfg: DictConfig) -> float | None:
    from matl.training.foreground import train_foreground  # torch and Lightning load after composition

    return train_foreground(cfg).get("val_iou")


if __name__ == "__main__":
    main()
