"""DDP evaluation is exact: every test query counts once, and a 2-process DDP-CPU run's test metrics
equal a single-process test of the same checkpoint.

Tolerance: the per-query records are gathered from the ranks (rank 0's queries, then rank 1's),
so means are float64 sums in another order than one process's: equal to ~1e-15; we allow 1e-9.
Counts (``rec_acc``, ``pose_acc_5px``) and the median are exactly equal.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
from omegaconf import OmegaConf, open_dict
from torch.utils.data import DistributedSampler

from matl.metrics import METRIC_NAMES
from matl.utils.distributed import UnpaddedDistributedSampler, eval_sampler
from matl.utils.instantiate import build

ROOT = Path(__file__).resolve().parents[2]
TOLERANCE = 1e-9
# float32 kernels may round a query's pose differently in another batch composition (the shards' batches
# differ from one process's); a query counted twice or dropped moves a mean over 47 queries by far more
RELATIVE = 1e-7


@pytest.mark.parametrize("n,world", [(47, 2), (48, 2), (10, 3), (2, 3)])
def test_unpadded_shards_cover_every_query_once(n: int, world: int) -> None:
    data = list(range(n))
    shards = [list(UnpaddedDistributedSampler(data, num_replicas=world, rank=r)) for r in range(world)]
    assert sorted(i for shard in shards for i in shard) == data
    for rank, shard in enumerate(shards):
        assert len(UnpaddedDistributedSampler(data, num_replicas=world, rank=rank)) == len(shard)
    # what Lightning's default would have done: pad to a multiple of the world size with repeats
    padded = [list(DistributedSampler(data, num_replicas=world, rank=r, shuffle=False)) for r in range(world)]
    assert sum(map(len, padded)) == math.ceil(n / world) * world


def test_single_process_loaders_are_unchanged() -> None:
    assert eval_sampler(list(range(5))) is None  # no process group: the sequential order, as before


def _single_process_test(run: Path, cache_dir: Path) -> dict[str, float]:
    """The run's best checkpoint tested by one process, through the same Lightning test loop."""
    import lightning as L

    cfg = OmegaConf.load(run / ".hydra" / "config.yaml")
    with open_dict(cfg):
        cfg.paths.output_dir = str(run)
        cfg.paths.cache_dir = str(cache_dir)
    datamodule, model = build(cfg)
    trainer = L.Trainer(accelerator="cpu", devices=1, logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False)
    trainer.test(model, datamodule=datamodule, ckpt_path=str(run / "checkpoints" / "best.ckpt"), weights_only=True,
                 verbose=False)
    return {name: float(model.test_results[f"test/{name}"]) for name in METRIC_NAMES}


@pytest.mark.filterwarnings("ignore:Be aware that when using `ckpt_path`")
def test_ddp_cpu_test_metrics_equal_single_process(tmp_path: Path, cache_dir: Path) -> None:
    run = tmp_path / "ddp"
    # 47 test and 31 validation queries: odd, so a padding sampler would count one query twice
    args = [sys.executable, "-m", "matl.train", "trainer=ddp_cpu", "scale=smoke", "data.test_queries=47",
            "data.val_queries=31", "logger=none", "callbacks.progress_bar=null", f"paths.cache_dir={cache_dir}",
            f"hydra.run.dir={run}"]
    done = subprocess.run(args, cwd=ROOT, env={**os.environ, "OMP_NUM_THREADS": "1"}, capture_output=True,
                          text=True, timeout=900)
    assert done.returncode == 0, done.stderr[-4000:]
    log = (run / "train.log").read_text() + done.stdout + done.stderr
    assert "MEMBER: 2/2" in log  # two processes really trained and tested
    ddp = json.loads((run / "metrics.json").read_text())
    single = _single_process_test(run, cache_dir)
    for name in METRIC_NAMES:
        if ddp[name] is None:
            assert math.isnan(single[name]), name
        else:
            assert ddp[name] == pytest.approx(single[name], rel=RELATIVE, abs=TOLERANCE), name
    # rec_acc over 47 queries is a multiple of 1/47: no query was counted twice or dropped
    assert round(ddp["rec_acc"] * 47) == pytest.approx(ddp["rec_acc"] * 47, abs=1e-9)
