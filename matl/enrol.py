"""``python -m matl.enrol gallery=<dir> [save=<gallery.pt>] [shard=<k> shards=<K>]``.

Enrols a gallery folder (``<gallery>/<object>/<plane>.{png,jpg}``) without queries: every product's features go to
the folder's per-product cache (:mod:`matl.inference.gallery`), which predict, ``Recognizer.enrol`` and a later run
read back; ``save=`` also writes the whole gallery, with its open-set calibration, for ``Recognizer.load``. A large
catalogue is split into ``shards`` run by separate processes (Hydra's joblib launcher) or hosts (its submitit
launcher) that share the folder; a run without ``shard`` then merges them, reading every product from the cache.
Options as predict's (``conf/predict.yaml``), plus ``conf/enrol.yaml``'s.
"""

from __future__ import annotations

from typing import Any

from omegaconf import DictConfig

from matl.utils.cli import command


@command("enrol", sweepable=True)
def main(cfg: DictConfig) -> Any:
    from matl.inference.files import enrol  # torch and the models load after composition

    return enrol(cfg)["products"]  # under -m a failing shard writes failed.json and the others go on


if __name__ == "__main__":
    main()
