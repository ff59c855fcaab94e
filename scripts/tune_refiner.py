"""Choosing the pose refiner's settings on validation queries (never the test split).

    python scripts/tune_refiner.py dump <run dir> <out.pt> [data.queries=rendered ...]
    python scripts/tune_refiner.py compare <out.pt> [<out2.pt> ...] --refiner fast photometric \
        [--set levels=4 loss=cauchy] [--clutter]

``dump``: the run's checkpoint on its **validation** queries (the ``val`` stream of the run's seed,
disjoint from training and test): per query the image ``(Q, 3, S, S)``, the STN's
``query_H_anchor`` and selected gallery index, the true ``query_H_canon`` and whether the
recognition is correct; plus the gallery's images and ``anchor_H_canon``. Extra arguments are
overrides of the run's saved config (``data.queries=rendered`` for rendered views).

``compare``: refines the correctly recognised queries of each dump with each refiner (``conf/refiner/<name>.yaml``,
``--set`` overrides applied to all) and prints the median corner error, ``pose_acc_5px`` among them and
the per-query refinement time (one batch of one, one thread). ``--clutter`` pastes another
query's pixels behind each query's object (the query background is 0 by construction) and
shifts its gain and bias: a cluttered, differently lit query whose true pose is unchanged.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import hydra
import torch
from omegaconf import OmegaConf

from matl.geometry import corner_error_px
from matl.models.checkpoint import build_model, load_checkpoint
from matl.utils.errors import CONF_DIR
from matl.utils.runs import load_run, resolve_checkpoint


def dump(run: str, out: str, overrides: list[str]) -> None:
    run_dir, saved = load_run(run)
    if overrides:
        saved = OmegaConf.merge(saved, OmegaConf.from_dotlist(overrides))
    checkpoint_path = resolve_checkpoint(run_dir, "best")
    ckpt = load_checkpoint(checkpoint_path)
    dm = hydra.utils.instantiate(saved.data)
    dm.setup("test")
    model = build_model(saved.model, ckpt, checkpoint_path, dm).eval()
    rec = model.build_recognizer(dm.gallery)
    params = {k: v for k, v in dm.val_set.params.items()}
    queries, H, index, true, correct = [], [], [], [], []
    n = len(next(iter(params.values())))
    with torch.no_grad():
        for start in range(0, n, 100):
            batch = dm.materialize({k: v[start:start + 100] for k, v in params.items()})
            pred = rec(batch["query"])
            queries.append(batch["query"])
            H.append(pred.query_H_anchor.double())
            index.append(pred.gallery_index)
            true.append(batch["query_H_canon"].double())
            correct.append(pred.object_index == batch["object"])
    torch.save({"queries": torch.cat(queries), "query_H_anchor": torch.cat(H), "gallery_index": torch.cat(index),
                "true_query_H_canon": torch.cat(true), "correct": torch.cat(correct),
                "anchors": dm.gallery.images, "anchor_H_canon": dm.gallery.anchor_H_canon.double()}, out)
    print(f"{out}: {n} validation queries, {int(torch.cat(correct).sum())} recognised")


def clutter(queries: torch.Tensor, seed: int = 0) -> torch.Tensor:
    """Another query behind each one's object, and a gain / bias change of the whole image."""
    g = torch.Generator().manual_seed(seed)
    background = (queries == 0).all(dim=1, keepdim=True)
    behind = queries.roll(7, dims=0).flip(-1)
    out = torch.where(background, behind, queries)
    gain = 0.7 + 0.5 * torch.rand(len(queries), 1, 1, 1, generator=g)
    bias = 0.1 * torch.rand(len(queries), 1, 1, 1, generator=g) - 0.05
    return (out * gain + bias).clamp(0, 1)


def compare(dumps: list[str], refiners: list[str], sets: list[str], with_clutter: bool, timed: int) -> None:
    torch.set_num_threads(1)
    for path in dumps:
        d = torch.load(path, weights_only=True)
        ok = d["correct"] & (d["gallery_index"] >= 0)
        q = d["queries"][ok]
        if with_clutter:
            q = clutter(q)
        idx = d["gallery_index"][ok]
        start = d["query_H_anchor"][ok]
        anchor_H_canon = d["anchor_H_canon"][idx]
        true = d["true_query_H_canon"][ok]
        size = tuple(q.shape[-2:])
        before = corner_error_px(start @ anchor_H_canon, true, size)
        print(f"{path}{' +clutter' if with_clutter else ''}: {len(q)} recognised; start median "
              f"{float(before.median()):.2f} px, acc5 {float((before < 5).float().mean()):.3f}")
        for name in refiners:
            cfg = OmegaConf.merge(OmegaConf.load(Path(CONF_DIR) / "refiner" / f"{name}.yaml"),
                                  OmegaConf.from_dotlist(sets))
            refiner = hydra.utils.instantiate(cfg)
            if hasattr(refiner, "prepare"):
                refiner.prepare(d["anchors"])
                args = (q, idx, start)
            else:
                args = (q, d["anchors"][idx], start)
            t0 = time.perf_counter()
            result = refiner(*args)
            batch_s = time.perf_counter() - t0
            after = corner_error_px(result.query_H_anchor @ anchor_H_canon, true, size)
            times = []
            for i in range(min(timed, len(q))):
                one = (args[0][i:i + 1], args[1][i:i + 1], args[2][i:i + 1])
                t0 = time.perf_counter()
                refiner(*one)
                times.append(time.perf_counter() - t0)
            ms = 1e3 * float(torch.tensor(times).median()) if times else float("nan")
            print(f"  {name} {' '.join(sets)}: median {float(after.median()):.3f} px, acc5 "
                  f"{float((after < 5).float().mean()):.3f}, mean {float(after.mean()):.2f}, accepted "
                  f"{float(result.accepted.float().mean()):.2f}, single {ms:.2f} ms, batch {batch_s:.1f} s")


def main(argv: list[str]) -> None:
    if argv and argv[0] == "dump":
        dump(argv[1], argv[2], argv[3:])
        return
    parser = argparse.ArgumentParser()
    parser.add_argument("command", choices=["compare"])
    parser.add_argument("dumps", nargs="+")
    parser.add_argument("--refiner", nargs="+", default=["fast"])
    parser.add_argument("--set", nargs="*", default=[])
    parser.add_argument("--clutter", action="store_true")
    parser.add_argument("--timed", type=int, default=30)
    a = parser.parse_args(argv)
    compare(a.dumps, a.refiner, a.set, a.clutter, a.timed)


if __name__ == "__main__":
    main(sys.argv[1:])
