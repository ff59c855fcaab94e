"""``python -m matl.bench [bench.quick=true] [ckpt=<path>] [overrides]``: speed, measured against a reference.

Speed is measured against a reference measured *in the same run* on the same machine
(here SIFT+RANSAC on the same queries), never against a remembered absolute time. One run writes
``bench.json`` in its folder (``outputs/bench/<time>/``) and prints a summary table:

* ``train_triplets_per_s``: the default model and datamodule (``conf/bench.yaml`` composes the same
  groups as ``train.yaml``); ``bench.train_steps`` training steps after ``bench.train_warmup`` untimed
  ones, each = loader collation + ``materialize`` (the batched warps) + ``training_step`` + backward
  + optimiser step. Lightning's loop (logging, callbacks) is not included.
* ``data_time_fraction``: the share of those steps spent in ``materialize``, timed in the same loop.
* ``query_ms``: median milliseconds per query, batch of 1, ARC-size gallery in memory (all N anchors
  of every plane of ``data``; 152 x 4 = 608 for synthetic_arc), the same ``bench.queries`` test
  queries for every method: ``matl`` (exact search), ``matl_refine`` (plus ``refine=true``),
  ``matl_faiss`` (``search=faiss``, when installed), ``matl_onnx`` (the exported query network in
  onnxruntime, when installed) and ``sift_ransac`` (``baseline``).
  Without ``ckpt=`` the MATL model is the default config's, untrained (``query_timing.weights``).
* ``speedup_vs_sift``: ``sift_ransac / matl``; ``refine_added_ms``: ``matl_refine - matl``.
* ``gallery_scaling``: ``{anchors, query_ms, search_ms, ...}`` for ``bench.scaling_anchors``. The
  search part runs on random unit embeddings of the model's dimension (queries are perturbed
  gallery entries, so each has a true nearest neighbour), plus the fixed STN + feature cost of a
  query measured once on real images (``fixed_query_ms``). With faiss, its latency, build time and
  recall@1 against exact search are listed too.
* ``render_images_per_s``: canonical renders of ``data.source`` (:func:`matl.data.render_speed.render_images_per_s`).
* ``query_ms_camera``: what a camera delivers, ``bench.camera.crops`` RGB crops without a mask (products of
  ``camera_data``, the held-out ones, on real backgrounds, with neighbours, occluders and camera effects),
  decoded once, the same for ``matl``, ``matl_refine``, ``matl_fast_refine`` (the shipped models, whatever
  ``ckpt=`` says) and ``sift_ransac``, each through the public API with the run's ``foreground`` (the foreground
  step and its retries timed), batch of 1 and ``query_ms_camera_batch`` (``bench.batch`` crops a call);
  ``speedup_camera_vs_sift[_batch]`` beside them, ``camera_timing`` how, and ``query_timing.breakdown_camera``
  where the milliseconds go (decode, foreground, networks, search, verification, refinement, retries)
  (:mod:`matl.evaluation.camera_speed`).

``bench.quick=true`` merges ``bench_quick`` over ``bench``: a smoke run of a few seconds (the tests'),
whose numbers are not measurements.
"""

from __future__ import annotations

from omegaconf import DictConfig

from matl.utils.cli import command


@command("bench")
def main(cfg: DictConfig) -> None:
    from matl.evaluation.speed import run_bench  # torch and the models load after composition

    run_bench(cfg)


if __name__ == "__main__":
    main()
