"""Reliability of training: numerical guards, metrics without NaN, atomic and resumable checkpoints, determinism,
checkpoint loading safety. The bad-input table is tests/test_bad_inputs.py.

Tolerances (also in docs/reliability.md):
* determinism: two runs of the same seed on the same CPU and thread count give metrics within 1e-9
  (measured: identical);
* resume: a run SIGKILLed mid-epoch and resumed from last.ckpt ends with test metrics within 1e-9 and
  weights within 1e-9 of the uninterrupted run (measured: identical, max weight difference 0.0).
"""

from __future__ import annotations

import ast
import json
import math
import os
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import lightning as L
import numpy as np
import pytest
import torch
from omegaconf import open_dict
from torch.utils.data import DataLoader

from matl.data.resumable import ResumableShuffleSampler, resume_position
from matl.data.streams import stream_generator
from matl.metrics import METRIC_NAMES
from matl.models.checkpoint import AtomicModelCheckpoint, capture_rng_state, restore_rng_state
from matl.models.stn import HomographyRegressor, SpatialTransformer
from matl.training.fit import null_reasons, train
from matl.utils.errors import MatlError, NonFiniteLossError
from matl.utils.instantiate import build
from matl.utils.io import write_json
from tests.conftest import TINY, compose_config

REPO = Path(__file__).resolve().parents[2]
TOLERANCE = 1e-9  # determinism and resume: metrics and weights agree to this (absolute); measured 0.0
TIMING_KEYS = {"train_seconds", "query_ms"}  # wall-clock values, never compared


def env() -> dict[str, str]:
    return {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(REPO)}


# --------------------------------------------------------------------------------- STN guard
def bad_rows(H: torch.Tensor) -> torch.Tensor:
    """Rows 0..2 of a regressor's output made NaN, singular and ill-conditioned; row 3+ untouched."""
    H = H.clone()
    H[0] = torch.nan
    H[1] = torch.tensor([[1.0, 2.0, 0.0], [2.0, 4.0, 0.0], [0.0, 0.0, 1.0]])  # rank 2
    H[2] = torch.diag(torch.tensor([1.0, 1e-7, 1.0]))                           # condition number 1e7
    return H


def test_stn_guard_replaces_nan_and_singular_predictions(monkeypatch: pytest.MonkeyPatch) -> None:
    stn = SpatialTransformer(HomographyRegressor(image_size=32), image_size=32)
    original = stn.regressor.forward
    monkeypatch.setattr(stn.regressor, "forward", lambda x: bad_rows(original(x)))
    images = torch.rand(5, 3, 32, 32)
    out = stn(images)
    assert out.degenerate.tolist() == [True, True, True, False, False]
    assert torch.isfinite(out.warped).all() and torch.isfinite(out.query_H_anchor).all()
    # a degenerate row is warped by identity: the query comes out unchanged
    assert torch.allclose(out.warped[:3], images[:3], atol=1e-5)
    assert torch.allclose(out.query_H_anchor[:3], torch.eye(3, dtype=out.query_H_anchor.dtype).expand(3, 3, 3),
                          atol=1e-6)


def tiny_model_and_data(tmp_path: Path, cache_dir: Path, extra: list[str] | None = None):
    cfg = compose_config("train", [*TINY, f"paths.cache_dir={cache_dir}", "logger=none", *(extra or [])], tmp_path)
    L.seed_everything(0)
    return build(cfg)


def quiet_trainer(**kwargs) -> L.Trainer:
    return L.Trainer(accelerator="cpu", devices=1, logger=False, enable_checkpointing=False,
                     enable_progress_bar=False, enable_model_summary=False, **kwargs)


def test_degenerate_stn_is_counted_and_logged(tmp_path: Path, cache_dir: Path,
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    datamodule, model = tiny_model_and_data(tmp_path, cache_dir)
    flagged = {"train": 0, "eval": 0}

    def half_nan(regress):
        def regress_half_nan(x: torch.Tensor) -> torch.Tensor:
            H = regress(x).clone()
            H[::2] = torch.nan  # every other row
            return H
        return regress_half_nan

    def counting(run):  # what the guard flagged, by phase, independently of the module
        def run_and_count(images: torch.Tensor):
            out = run(images)
            flagged["train" if model.training else "eval"] += int(out.degenerate.sum())
            assert torch.isfinite(out.warped).all() and torch.isfinite(out.query_H_anchor).all()
            return out
        return run_and_count

    # training uses forward; evaluation the inference path (infer), so both are patched
    for name in ("forward", "infer"):
        monkeypatch.setattr(model.stn.regressor, name, half_nan(getattr(model.stn.regressor, name)))
        monkeypatch.setattr(model.stn, name, counting(getattr(model.stn, name)))
    trainer = quiet_trainer(max_epochs=1, limit_train_batches=2, limit_val_batches=1, num_sanity_val_steps=0)
    trainer.fit(model, datamodule=datamodule)
    assert flagged["train"] >= 2 * 8 and flagged["eval"] >= 16  # at least half of 2 x 16 positives, 32 queries
    assert model.degenerate_count == flagged["train"]
    assert trainer.callback_metrics["train/degenerate_stn"].item() == flagged["train"]
    assert trainer.callback_metrics["val/degenerate_stn"].item() == flagged["eval"]
    for name in ("train/loss", "val/rec_acc"):
        assert math.isfinite(trainer.callback_metrics[name].item()), name  # the warp stayed defined


def test_nan_loss_raises_a_clear_error(tmp_path: Path, cache_dir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    datamodule, model = tiny_model_and_data(tmp_path, cache_dir)
    monkeypatch.setattr(model.feature_net, "forward", lambda x: torch.full((len(x), 128), torch.nan))
    trainer = quiet_trainer(max_epochs=1, limit_train_batches=2, limit_val_batches=0)
    with pytest.raises(NonFiniteLossError, match=r"training loss became nan .*lower model\.optimizer\.lr") as error:
        trainer.fit(model, datamodule=datamodule)
    assert isinstance(error.value, MatlError) and "\n" not in str(error.value)
    assert trainer.global_step == 0  # stopped at the first bad step, no update was made with it


def test_nan_during_training_cli_one_line_and_last_checkpoint_kept(tmp_path: Path, cache_dir: Path) -> None:
    """Weights poisoned with NaN at step 3: one `error:` line, exit 2, and last.ckpt (step 2) intact and finite."""
    run = tmp_path / "run"
    proc = subprocess.run(
        [sys.executable, "-m", "matl.train", *TINY, f"paths.cache_dir={cache_dir}", "logger=none",
         "~callbacks.progress_bar", "callbacks.model_checkpoint.last_every_n_train_steps=1",
         "+callbacks.poison._target_=tests.crash_helpers.PoisonWeights", "+callbacks.poison.step=2",
         f"hydra.run.dir={run}"],
        cwd=tmp_path, env=env(), capture_output=True, text=True, timeout=600)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "Traceback" not in proc.stdout + proc.stderr
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error: ")]
    assert len(errors) == 1 and "training loss became nan" in errors[0], proc.stderr[-2000:]
    last = torch.load(run / "checkpoints" / "last.ckpt", weights_only=True)
    assert last["global_step"] == 2
    assert all(torch.isfinite(v).all() for v in last["state_dict"].values() if v.is_floating_point())
    assert not (run / "metrics.json").exists()


# --------------------------------------------------------------------------- metrics.json
def test_metrics_json_never_holds_nan(tmp_path: Path) -> None:
    path = tmp_path / "metrics.json"
    write_json(path, {"pose_err": math.nan, "nested": {"x": [1.0, math.inf]}, "t": torch.tensor(math.nan)})
    text = path.read_text()
    assert "NaN" not in text and "Infinity" not in text
    assert json.loads(text) == {"pose_err": None, "nested": {"x": [1.0, None]}, "t": None}


def test_null_metrics_come_with_a_reason() -> None:
    class NoSTN:
        stn = None

    class WithSTN:
        stn = object()

    tl = null_reasons({"rec_acc": 0.5, "pose_err": None, "corner_err_px": None, "query_ms": 1.0}, NoSTN())
    assert set(tl) == {"pose_err", "corner_err_px"} and "no STN" in tl["pose_err"]
    lost = null_reasons({"rec_acc": 0.0, "pose_err": None, "query_ms": None}, WithSTN())
    assert "recognised" in lost["pose_err"] and "time" in lost["query_ms"]
    assert "NaN" in null_reasons({"rec_acc": None, "query_ms": 1.0}, WithSTN())["rec_acc"]


# --------------------------------------------------------------------- resumable data order
def test_resumable_sampler_gives_the_dataloader_shuffle() -> None:
    """Uninterrupted runs see exactly the batches DataLoader(shuffle=True, generator=g) gave before."""
    data = list(range(37))
    loader = DataLoader(data, batch_size=5, shuffle=True, drop_last=True, generator=stream_generator(3, "shuffle"))
    sampler = ResumableShuffleSampler(len(data), lambda: stream_generator(3, "shuffle"))
    for epoch in range(3):
        expected = torch.cat(list(loader)).tolist()
        sampler.set_epoch(epoch)
        assert sampler.permutation(epoch)[:35].tolist() == expected
        assert list(sampler)[:35] == expected
    sampler.resume_at(2, 10)  # a run killed after 2 batches of epoch 2
    assert list(sampler) == sampler.permutation(2)[10:].tolist()
    assert list(sampler) == sampler.permutation(2).tolist()  # the skip applies to one iteration only
    assert len(sampler) == 37


class StubTrainer:
    def __init__(self, global_step: int, current_epoch: int, accumulate: int = 1, limit: float | int = 1.0) -> None:
        self.global_step, self.current_epoch = global_step, current_epoch
        self.accumulate_grad_batches, self.limit_train_batches = accumulate, limit


@pytest.mark.parametrize("trainer,expected", [
    (None, (0, 0)),
    (StubTrainer(0, 0), (0, 0)),
    (StubTrainer(11, 1), (1, 3)),          # 8 batches per epoch: 3 batches into epoch 1
    (StubTrainer(16, 1), (2, 0)),          # epoch 1 trained, counter not yet moved on
    (StubTrainer(16, 2), (2, 0)),
    (StubTrainer(5, 1, accumulate=2), (1, 2)),      # 2 batches per step
    (StubTrainer(20, 1), (2, 4)),          # an inconsistent epoch counter: the step count wins
    (StubTrainer(5, 1, limit=4), (1, 1)),
])
def test_resume_position(trainer: StubTrainer | None, expected: tuple[int, int]) -> None:
    assert resume_position(trainer, 8) == expected


def test_rng_state_round_trip_is_plain_data(tmp_path: Path) -> None:
    state = capture_rng_state()
    expected = (torch.rand(3), np.random.rand(3), __import__("random").random())
    torch.save({"rng": state}, tmp_path / "s.pt")
    restore_rng_state(torch.load(tmp_path / "s.pt", weights_only=True)["rng"])
    again = (torch.rand(3), np.random.rand(3), __import__("random").random())
    assert torch.equal(expected[0], again[0]) and np.array_equal(expected[1], again[1]) and expected[2] == again[2]


# -------------------------------------------------------------------------- atomic saving
def test_kill_during_checkpoint_write_keeps_the_previous_last_ckpt(tmp_path: Path, cache_dir: Path) -> None:
    """The 2nd save is SIGKILLed half-way through its file: last.ckpt is still the complete 1st one."""
    run = tmp_path / "run"
    proc = subprocess.run(
        [sys.executable, "-m", "matl.train", *TINY, f"paths.cache_dir={cache_dir}", "logger=none",
         "~callbacks.progress_bar", "callbacks.model_checkpoint.last_every_n_train_steps=1",
         "+callbacks.crash._target_=tests.crash_helpers.KillDuringSave", "+callbacks.crash.nth=2",
         f"hydra.run.dir={run}"],
        cwd=tmp_path, env=env(), capture_output=True, text=True, timeout=600)
    assert proc.returncode == -signal.SIGKILL, proc.stderr[-2000:]
    assert (run / "checkpoints" / ".last.ckpt.partial").is_file()  # the torn write went to the side file
    last = torch.load(run / "checkpoints" / "last.ckpt", weights_only=True)
    assert last["global_step"] == 1 and "optimizer_states" in last


def test_atomic_checkpoint_in_process(tmp_path: Path, cache_dir: Path) -> None:
    """last.ckpt refreshed every K steps and at every epoch end; no partial file left; best kept."""
    datamodule, model = tiny_model_and_data(tmp_path, cache_dir, ["data.train_triplets=96"])  # 6 steps / epoch
    saved_steps: list[int] = []

    class Recorder(AtomicModelCheckpoint):
        def _save_checkpoint(self, trainer: L.Trainer, filepath: str) -> None:
            super()._save_checkpoint(trainer, filepath)
            if filepath.endswith("last.ckpt"):
                saved_steps.append(trainer.global_step)

    ckpt = Recorder(dirpath=tmp_path / "ck", filename="best", monitor="val/score", mode="max", save_last=True,
                    last_every_n_train_steps=5, enable_version_counter=False)
    trainer = L.Trainer(accelerator="cpu", logger=False, enable_progress_bar=False, enable_model_summary=False,
                        max_epochs=2, callbacks=[ckpt])
    trainer.fit(model, datamodule=datamodule)
    assert saved_steps == [5, 6, 10, 12]  # periodic at 5 and 10, epoch ends at 6 and 12
    assert sorted(p.name for p in (tmp_path / "ck").iterdir()) == ["best.ckpt", "last.ckpt"]
    assert torch.load(tmp_path / "ck" / "last.ckpt", weights_only=True)["global_step"] == 12


# ------------------------------------------------------------------------------ determinism
def comparable(metrics: dict) -> dict:
    return {k: v for k, v in metrics.items() if k not in TIMING_KEYS}


def assert_same_metrics(a: dict, b: dict) -> None:
    a, b = comparable(a), comparable(b)
    assert a.keys() == b.keys()
    for key in a:
        if isinstance(a[key], float) and isinstance(b[key], float):
            assert math.isclose(a[key], b[key], rel_tol=0.0, abs_tol=TOLERANCE), (key, a[key], b[key])
        else:
            assert a[key] == b[key], (key, a[key], b[key])


def max_weight_difference(a: Path, b: Path) -> float:
    sa = torch.load(a, weights_only=True)["state_dict"]
    sb = torch.load(b, weights_only=True)["state_dict"]
    assert sa.keys() == sb.keys()
    return max((sa[k].double() - sb[k].double()).abs().max().item() for k in sa if sa[k].numel())


def test_same_seed_same_metrics(tiny_train_cfg) -> None:
    first = train(tiny_train_cfg(["logger=none"], run="a"))
    second = train(tiny_train_cfg(["logger=none"], run="b"))
    assert_same_metrics(first, second)
    assert all(first[name] is not None for name in METRIC_NAMES)


# ---------------------------------------------------------------------------------- resume
RESUME = [*TINY, "data.train_triplets=128", "trainer.max_epochs=2", "logger=none", "~callbacks.progress_bar",
          "callbacks.model_checkpoint.last_every_n_train_steps=3", "loss=nce", "loss.num_negatives=4"]
STEPS_PER_EPOCH = 128 // 16


def run_train(args: list[str], run: Path, cwd: Path) -> subprocess.CompletedProcess:
    proc = subprocess.run([sys.executable, "-m", "matl.train", *args, f"hydra.run.dir={run}"], cwd=cwd, env=env(),
                          capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc


@pytest.mark.slow
def test_resume_after_sigkill_mid_epoch_matches_uninterrupted(tmp_path: Path, cache_dir: Path) -> None:
    """kill -9 in the middle of epoch 2 (after a periodic last.ckpt), resume with ckpt_path=: same metrics.

    NCE with random negatives, so the saved RNG state matters as well as the data order; epoch 2, so
    the best checkpoint of epoch 1 must be carried into the resumed run's folder.
    """
    args = [*RESUME, f"paths.cache_dir={cache_dir}"]
    run_train(args, tmp_path / "uninterrupted", tmp_path)

    killed = tmp_path / "killed"
    proc = subprocess.Popen([sys.executable, "-m", "matl.train", *args, f"hydra.run.dir={killed}",
                             "+callbacks.slow._target_=tests.crash_helpers.SlowSteps", "+callbacks.slow.seconds=0.25"],
                            cwd=tmp_path, env=env(), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    last = killed / "checkpoints" / "last.ckpt"
    step, deadline = -1, time.monotonic() + 600
    try:
        while proc.poll() is None and time.monotonic() < deadline:
            if last.is_file():
                step = int(torch.load(last, weights_only=True)["global_step"])  # atomic: never a torn file
                if step > STEPS_PER_EPOCH:  # a periodic save inside epoch 2
                    os.kill(proc.pid, signal.SIGKILL)
                    break
            time.sleep(0.05)
    finally:
        if proc.poll() is None and step <= STEPS_PER_EPOCH:
            proc.kill()
        proc.wait()
    assert proc.returncode == -signal.SIGKILL and STEPS_PER_EPOCH < step < 2 * STEPS_PER_EPOCH, step
    assert step % STEPS_PER_EPOCH != 0  # really mid-epoch
    assert not (killed / "metrics.json").exists()

    run_train([*args, f"ckpt_path={last}"], tmp_path / "resumed", tmp_path)
    done = json.loads((tmp_path / "uninterrupted" / "metrics.json").read_text())
    resumed = json.loads((tmp_path / "resumed" / "metrics.json").read_text())
    assert_same_metrics(done, resumed)
    difference = max_weight_difference(tmp_path / "uninterrupted" / "checkpoints" / "last.ckpt",
                                       tmp_path / "resumed" / "checkpoints" / "last.ckpt")
    assert difference <= TOLERANCE, difference
    assert resumed["checkpoint"] == "checkpoints/best.ckpt"  # the best of epoch 1 was carried over (copied)
    assert (killed / "checkpoints" / "best.ckpt").is_file() and last.is_file()  # the killed run is untouched


# ----------------------------------------------------------------------- checkpoint safety
def torch_load_calls(tree: ast.AST) -> list[ast.Call]:
    return [node for node in ast.walk(tree) if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
            and node.func.attr == "load" and isinstance(node.func.value, ast.Name) and node.func.value.id == "torch"]


def test_every_checkpoint_load_in_matl_is_weights_only() -> None:
    """Static check: every torch.load, trainer.fit and trainer.test in matl/ passes weights_only=True."""
    calls = 0
    for path in sorted((REPO / "matl").rglob("*.py")):
        tree = ast.parse(path.read_text())
        for call in torch_load_calls(tree):
            calls += 1
            keywords = {k.arg: k.value for k in call.keywords}
            value = keywords.get("weights_only")
            assert isinstance(value, ast.Constant) and value.value is True, f"{path}:{call.lineno}"
        for node in ast.walk(tree):
            if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                    and node.func.attr in ("fit", "test", "validate") and isinstance(node.func.value, ast.Name)
                    and node.func.value.id == "trainer"
                    and any(k.arg == "ckpt_path" for k in node.keywords)):
                value = {k.arg: k.value for k in node.keywords}.get("weights_only")
                assert isinstance(value, ast.Constant) and value.value is True, f"{path}:{node.lineno}"
    assert calls >= 2


def test_resume_option_is_validated_before_training(tiny_train_cfg, tmp_path: Path) -> None:
    cfg = tiny_train_cfg()
    with open_dict(cfg):
        cfg.ckpt_path = str(tmp_path / "nothing.ckpt")
    with pytest.raises(MatlError, match="no such checkpoint file"):
        train(cfg)


# ------------------------------------------------------------------- dataset cache atomicity
KILLED_CACHE_WRITE = """
import os, signal, sys
import numpy as np
import matl.data.canonical as canonical

class TinySource:  # as tests.test_bad_inputs.TinySource (same cache key), without importing torch
    def cache_key(self):
        return {"tiny": 1}

    def build(self, image_size):
        images = np.zeros((2, image_size, image_size, 3), np.uint8)
        return canonical.CanonicalSet(images, images[..., 0] > 0, np.array([0, 1]), ["front", "front"], ["a", "b"],
                                      ["planar", "planar"])

def torn_savez(f, **arrays):  # half an archive, then the process dies mid-write
    f.write(b"PK\\x03\\x04" + b"\\0" * 4096)
    f.flush()
    os.kill(os.getpid(), signal.SIGKILL)

canonical.np.savez_compressed = torn_savez
canonical.load_canonical(TinySource(), 16, sys.argv[1])
"""


def test_dataset_cache_write_is_atomic(tmp_path: Path) -> None:
    """A build killed while writing its cache leaves no cache file (only a hidden temp), and the next run builds it."""
    from matl.data.canonical import cache_path, load_canonical
    from tests.test_bad_inputs import TinySource

    proc = subprocess.run([sys.executable, "-c", KILLED_CACHE_WRITE, str(tmp_path)], cwd=REPO, env=env(),
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    target = cache_path(TinySource(), 16, tmp_path)
    assert not target.exists()
    assert [p.name.startswith(".") for p in tmp_path.iterdir()] == [True]  # the torn temp file only
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a clean build: no "unreadable cache" warning
        assert load_canonical(TinySource(), 16, tmp_path).num_planes == 2
    assert target.is_file()
