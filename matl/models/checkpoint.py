"""Loading ``matl.train`` checkpoints safely and rebuilding their models (shared by eval and predict),
and writing them atomically during training (:class:`AtomicModelCheckpoint`).

Checkpoints are read with ``torch.load(weights_only=True)``: they hold plain containers only
(``state_dict``, ``matl_config`` = the run's resolved config as a dict, ``matl_image_size``,
``matl_num_anchors``, and for classifiers ``matl_class_names``), so nothing is unpickled.

``ckpt=`` of every command (predict, unseen, bench, export, score, eval) and ``Recognizer.pretrained``
name a checkpoint the same way, through :func:`resolve_checkpoint_keyword`: ``pretrained`` and
``pretrained_fast`` are the models shipped inside the package (:data:`SHIPPED`), anything else a path.
A file that is not a matl checkpoint is one line naming the file and the fix, never torch's own advice
(which suggests ``weights_only=False``, i.e. running the file's code).
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import random as _py_random
import shutil
import warnings
from pathlib import Path
from typing import Any
from weakref import proxy

import hydra
import lightning as L
import numpy as np
import torch
from lightning.fabric.utilities.cloud_io import _is_local_file_protocol
from lightning.pytorch.callbacks import ModelCheckpoint
from omegaconf import DictConfig, OmegaConf

from matl.utils.errors import MatlError


def _is_global_zero() -> bool:
    """Rank 0 (or no distributed run): the process that writes files."""
    import torch.distributed as dist

    return not (dist.is_available() and dist.is_initialized()) or dist.get_rank() == 0


# ------------------------------------------------------------------------------ naming checkpoints
WEIGHTS_DIR = Path(__file__).resolve().parents[1] / "weights"
#: the shipped default model (experiment=pretrained_occluded: matl_camera, alignment stage, trained with occluders)
PRETRAINED = WEIGHTS_DIR / "matl_default.ckpt"
#: the shipped fast model (experiment=pretrained_fast: a cheaper s(), no alignment stage; meant for refine=True)
PRETRAINED_FAST = WEIGHTS_DIR / "matl_fast.ckpt"
#: the ``ckpt=`` keywords of the command line that name the shipped models -> ``Recognizer.pretrained``'s names
SHIPPED = {"pretrained": "default", "pretrained_fast": "fast"}
#: what every checkpoint error suggests
CKPT_FIX = ("pass a checkpoint written by python -m matl.train (<run>/checkpoints/best.ckpt), ckpt=pretrained or "
            "ckpt=pretrained_fast")


def shipped_checkpoint(name: str = "default") -> Path:
    """The path of a model shipped inside the package, ``default`` or ``fast``; a one-line error when this install
    lacks it."""
    paths = {"default": PRETRAINED, "fast": PRETRAINED_FAST}
    if name not in paths:
        raise MatlError(f"no shipped model is called {name!r}: use one of {', '.join(paths)}")
    if not paths[name].is_file():
        raise MatlError(f"no pretrained model ships with this version of matl ({paths[name]} is missing): "
                        "train one with python -m matl.train and use "
                        "Recognizer.from_checkpoint(<run>/checkpoints/best.ckpt)")
    return paths[name]


def resolve_checkpoint_keyword(ckpt: Any) -> Any:
    """``pretrained`` / ``pretrained_fast`` -> the shipped model's path (a string); any other value as it is.

    The one resolver of ``ckpt=``: every command that takes a checkpoint calls it (directly or through
    :func:`resolve_ckpt_option`) before it reads the file."""
    return str(shipped_checkpoint(SHIPPED[ckpt])) if isinstance(ckpt, str) and ckpt in SHIPPED else ckpt


def resolve_ckpt_option(cfg: Any, key: str = "ckpt") -> Any:
    """A command's ``cfg.<key>`` with a shipped model's keyword replaced by its path, in place; returns the value
    (None or empty left as they are: the command decides what a missing checkpoint means)."""
    from omegaconf import open_dict

    value = cfg.get(key)
    resolved = resolve_checkpoint_keyword(str(value)) if value not in (None, "") else value
    if resolved != value:
        with open_dict(cfg):
            cfg[key] = resolved
    return resolved


def _read_failure(path: Path, error: BaseException) -> str:
    """Why ``torch.load(weights_only=True)`` refused a file, in our words (torch's own message advises
    ``weights_only=False``, which would run whatever code the file holds)."""
    text = " ".join(str(error).split())
    if "TorchScript" in text:
        return "a TorchScript file (matl.export's output is for deployment, not a training checkpoint)"
    if "Unsupported global" in text or "not an allowed global" in text:
        return "it holds pickled Python objects beyond tensors and plain containers, which are never unpickled"
    with open(path, "rb") as f:
        zipped = f.read(4) == b"PK\x03\x04"  # torch.save's archive
    if isinstance(error, EOFError) or any(s in text for s in ("central directory", "failed reading", "truncated")) or (
            zipped and isinstance(error, OSError)):
        return "the file is truncated or corrupt"
    return "not a torch checkpoint file"


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """Read a checkpoint with ``weights_only=True`` onto the CPU; one-line :class:`MatlError` on failure."""
    path = Path(str(path)).expanduser()
    if path.is_dir():
        raise MatlError(f"checkpoint {path} is a folder: {CKPT_FIX}")
    if not path.is_file():
        raise MatlError(f"checkpoint {path} not found: {CKPT_FIX}")
    try:
        with warnings.catch_warnings():  # torch warns about pickle protocols of files it then refuses anyway
            warnings.simplefilter("ignore")
            ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # any failure to parse the file is the file's, not a bug
        raise MatlError(f"checkpoint {path} cannot be read safely (weights_only=True): {_read_failure(path, error)}; "
                        f"{CKPT_FIX}") from None
    if not isinstance(ckpt, dict) or not isinstance(ckpt.get("state_dict"), dict):
        raise MatlError(f"checkpoint {path} has no state_dict: not a Lightning checkpoint; {CKPT_FIX}")
    if not all(isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in ckpt["state_dict"].items()):
        raise MatlError(f"checkpoint {path} has a state_dict that is not a table of named tensors; {CKPT_FIX}")
    return ckpt


def checkpoint_info(ckpt: dict[str, Any], path: str | Path) -> tuple[int, int]:
    """``(image_size, num_anchors)`` recorded by ``MATLModule.on_save_checkpoint``."""
    if "matl_image_size" not in ckpt or "matl_num_anchors" not in ckpt:
        raise MatlError(f"checkpoint {path} has no matl_image_size / matl_num_anchors: not written by matl.train; "
                        f"{CKPT_FIX}")
    values = ckpt["matl_image_size"], ckpt["matl_num_anchors"]
    if not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in values):
        raise MatlError(f"checkpoint {path} records matl_image_size={values[0]!r}, matl_num_anchors={values[1]!r}, "
                        f"not positive integers: not written by matl.train; {CKPT_FIX}")
    return int(values[0]), int(values[1])


#: what a published (slim) checkpoint keeps: the weights and what rebuilds the model
PUBLISHED_KEYS = ("state_dict", "matl_config", "matl_image_size", "matl_num_anchors", "matl_class_names",
                  "matl_degenerate_count", "pytorch-lightning_version")


def publish_checkpoint(src: str | Path, dst: str | Path, metrics: dict[str, Any] | None = None) -> Path:
    """Write ``src``'s model as a slim checkpoint ``dst`` (no optimiser, loop or callback state):
    what ``matl.predict ckpt=``, ``matl.eval`` and ``matl.Recognizer`` load, a fraction of the size.

    ``metrics`` (e.g. the run's test metrics) are kept as ``matl_metrics``. Written atomically.
    """
    ckpt = load_checkpoint(src)
    slim = {k: ckpt[k] for k in PUBLISHED_KEYS if k in ckpt}
    slim["state_dict"] = {k: v.contiguous().clone() for k, v in ckpt["state_dict"].items()
                          if not k.startswith("recognizer.")}
    if metrics is not None:
        slim["matl_metrics"] = {k: v for k, v in metrics.items() if isinstance(v, (int, float, str, type(None)))}
    dst = Path(dst).expanduser()
    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = dst.with_name(f".{dst.name}.tmp")
    torch.save(slim, tmp)
    os.replace(tmp, dst)
    return dst


def file_sha256(path: str | Path, chunk: int = 1 << 20) -> str:
    """Hex sha256 of a file's bytes (keys the gallery-feature cache of ``matl.predict``)."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            digest.update(block)
    return digest.hexdigest()


SAFE_TARGET_PREFIXES = ("matl.", "torch.")


def _targets(node: Any) -> list[str]:
    """Every ``_target_`` in a (nested) config."""
    if isinstance(node, dict):
        own = [str(node["_target_"])] if "_target_" in node else []
        return own + [t for value in node.values() for t in _targets(value)]
    if isinstance(node, (list, tuple)):
        return [t for value in node for t in _targets(value)]
    return []


def check_model_targets(model_cfg: DictConfig | dict[str, Any], path: str | Path) -> None:
    """Refuse to instantiate anything but network, loss, optimiser and scheduler classes of matl and torch.

    ``weights_only=True`` stops *pickled* code, but a checkpoint's ``matl_config`` (and a run folder's
    ``.hydra/config.yaml``) are instantiated by Hydra, and a crafted ``_target_: os.system`` (or any
    function with side effects, e.g. one that writes files) would run it. Each target must lie in
    :data:`SAFE_TARGET_PREFIXES` and resolve to a subclass of ``nn.Module``, ``Optimizer`` or ``LRScheduler``.
    """
    from torch import nn
    from torch.optim.lr_scheduler import LRScheduler

    container = OmegaConf.to_container(model_cfg, resolve=False) if isinstance(model_cfg, DictConfig) else model_cfg
    for target in _targets(container):
        allowed = target.startswith(SAFE_TARGET_PREFIXES)
        if allowed:
            try:
                obj = hydra.utils.get_class(target)
            except Exception:  # not a class (a function), or not importable
                obj = None
            allowed = isinstance(obj, type) and issubclass(obj, (nn.Module, torch.optim.Optimizer, LRScheduler))
        if not allowed:
            raise MatlError(f"the config of checkpoint {path} asks to build {target!r}, not a matl/torch network, "
                            "loss, optimiser or scheduler class: refused (an untrusted file could run code this way)")


def build_model(model_cfg: DictConfig | dict[str, Any], ckpt: dict[str, Any], path: str | Path,
                datamodule: L.LightningDataModule | None = None) -> L.LightningModule:
    """Instantiate ``model_cfg`` and load the checkpoint's weights into it (strict), in eval mode.

    Models whose output size depends on the data (the STN classifier's number of classes) expose
    ``attach_data(datamodule)``; it is called before the weights are loaded, as Lightning's ``setup``
    hook does in training.
    """
    cfg = OmegaConf.create(model_cfg) if isinstance(model_cfg, dict) else model_cfg
    check_model_targets(cfg, path)  # the config came with the checkpoint (or run folder): it names code to run
    try:
        model = hydra.utils.instantiate(cfg)
    except MatlError:
        raise
    except Exception as error:  # a config this version cannot build is the file's, not a bug
        first = " ".join(str(error).split())[:200] or type(error).__name__
        raise MatlError(f"checkpoint {path}: its model config cannot be built by this version of matl ({first}); "
                        f"{CKPT_FIX}") from None
    if not isinstance(model, L.LightningModule):
        raise MatlError(f"checkpoint {path}: its model config builds a {type(model).__name__}, not a matl model; "
                        f"{CKPT_FIX}")
    if hasattr(model, "attach_data"):
        class_names = ckpt.get("matl_class_names")
        if datamodule is not None:
            names = list(datamodule.gallery.object_names)
            if class_names is not None and list(class_names) != names:
                raise MatlError(f"checkpoint {path} classifies the {len(class_names)} objects it was trained on; "
                                f"this data has {len(names)} other objects (a classifier cannot enrol new ones)")
            model.attach_data(datamodule)
        elif class_names is not None:
            model.attach_classes(list(class_names))
    # A recognizer assigned as a module attribute during validation is saved as a duplicate of the
    # feature net / STN weights under "recognizer."; a fresh model has none, so those keys are dropped.
    state = {k: v for k, v in ckpt["state_dict"].items() if not k.startswith("recognizer.")}
    try:
        model.load_state_dict(state)
    except RuntimeError as error:
        first = str(error).strip().splitlines()[0]
        raise MatlError(f"checkpoint {path} does not fit the model of its config: {first}") from error
    model.eval()
    return model


# ------------------------------------------------------------------------------ writing checkpoints
def _fsync_file(path: str) -> None:
    with open(path, "rb") as f:
        os.fsync(f.fileno())


def _fsync_dir(path: str) -> None:
    # makes the rename itself durable; not possible (nor needed) on every platform
    with contextlib.suppress(OSError):
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def atomic_copy(src: str | Path, dst: str | Path) -> None:
    """Copy ``src`` to ``dst`` through a temporary file in ``dst``'s folder and ``os.replace``."""
    dst = Path(dst)
    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = dst.with_name(f".{dst.name}.partial")
    shutil.copyfile(src, tmp)
    _fsync_file(str(tmp))
    os.replace(tmp, dst)
    _fsync_dir(str(dst.parent))


def capture_rng_state() -> dict[str, Any]:
    """The global RNG states (torch, CUDA, numpy, random) as tensors and plain containers.

    Plain data only, so a checkpoint holding it still loads with ``torch.load(weights_only=True)``.
    """
    state: dict[str, Any] = {"torch": torch.get_rng_state(), "python": list(_py_random.getstate())}
    kind, keys, pos, has_gauss, cached = np.random.get_state()
    state["numpy"] = [str(kind), torch.from_numpy(np.asarray(keys, dtype=np.int64)), int(pos), int(has_gauss),
                      float(cached)]
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def restore_rng_state(state: dict[str, Any]) -> None:
    """Inverse of :func:`capture_rng_state` (missing parts are left alone)."""
    if "torch" in state:
        torch.set_rng_state(state["torch"])
    if "python" in state:
        version, internal, gauss = state["python"]
        _py_random.setstate((version, tuple(internal), gauss))
    if "numpy" in state:
        kind, keys, pos, has_gauss, cached = state["numpy"]
        np.random.set_state((kind, np.asarray(keys, dtype=np.uint32), pos, has_gauss, cached))
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


class AtomicModelCheckpoint(ModelCheckpoint):
    """Lightning's ``ModelCheckpoint`` that never leaves a truncated file, saves ``last.ckpt`` within
    epochs, and makes a resumed run continue exactly.

    * **Atomic writes.** Lightning writes through fsspec, whose local "transaction" stages the file
      in the system temp folder and moves it: on another filesystem that move is a copy, and a
      kill during it leaves a truncated ``last.ckpt``. Here every checkpoint is written to
      ``.<name>.partial`` in its own folder, fsync'ed and ``os.replace``'d: a kill at any instant
      leaves the previous complete file or the new one.
    * **Mid-epoch saves.** ``last_every_n_train_steps=K`` (> 0) rewrites ``last.ckpt`` every ``K``
      optimiser steps, so a crash loses at most ``K`` steps. These saves do not count as "saved
      at this step" for the parent's logic, so the epoch-end best/last saves still happen.
    * **last.ckpt at every epoch end.** Lightning 2.6 refreshes ``last.ckpt`` only when a top-k
      checkpoint was written in the same step; here it is refreshed after every validation (or
      training epoch end when there is no validation) regardless of improvement.
    * **RNG.** The global RNG states are saved with the callback's state and restored just before
      the first training batch of a resumed run (random NCE negatives continue as uninterrupted).
    * **Resuming into a new run folder** (Hydra makes one per run): the best checkpoint of the old
      folder is *copied* into the new one and its score kept, so checkpoint selection continues and
      the old run's files are never touched (the parent would forget the best, or delete it later).

    Args:
        last_every_n_train_steps: ``K`` above; 0 disables mid-epoch saves.
        *args, **kwargs: as :class:`lightning.pytorch.callbacks.ModelCheckpoint`.
    """

    def __init__(self, *args: Any, last_every_n_train_steps: int = 0, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        if int(last_every_n_train_steps) < 0:
            raise ValueError(f"last_every_n_train_steps must be >= 0, got {last_every_n_train_steps}")
        self.last_every_n_train_steps = int(last_every_n_train_steps)
        self._last_saves = 0                       # how many times last.ckpt was written (this process)
        self._pending_rng: dict[str, Any] | None = None

    # ------------------------------------------------------------------------------- writing
    def _save_checkpoint(self, trainer: L.Trainer, filepath: str) -> None:
        if not _is_local_file_protocol(filepath):  # object stores: fsspec's transaction is atomic there
            super()._save_checkpoint(trainer, filepath)
            return
        tmp = os.path.join(os.path.dirname(filepath), f".{os.path.basename(filepath)}.partial")
        trainer.save_checkpoint(tmp, self.save_weights_only)  # every rank calls it; rank 0 writes
        if trainer.is_global_zero:
            _fsync_file(tmp)
            os.replace(tmp, filepath)
            _fsync_dir(os.path.dirname(filepath))
        trainer.strategy.barrier("AtomicModelCheckpoint._save_checkpoint")
        self._last_global_step_saved = trainer.global_step
        self._last_checkpoint_saved = filepath
        if trainer.is_global_zero:
            for logger in trainer.loggers:
                logger.after_save_checkpoint(proxy(self))

    def _save_last_checkpoint(self, trainer: L.Trainer, monitor_candidates: dict[str, torch.Tensor]) -> None:
        super()._save_last_checkpoint(trainer, monitor_candidates)
        if self.save_last:
            self._last_saves += 1

    def _may_save(self, trainer: L.Trainer) -> bool:
        from lightning.pytorch.trainer.states import TrainerFn

        return (not trainer.fast_dev_run and trainer.state.fn == TrainerFn.FITTING and not trainer.sanity_checking
                and trainer.global_step > 0)

    def on_train_batch_start(self, trainer: L.Trainer, pl_module: L.LightningModule, batch: Any,
                             batch_idx: int) -> None:
        if self._pending_rng is not None:  # the first batch after a resume: continue the saved RNG streams
            restore_rng_state(self._pending_rng)
            self._pending_rng = None

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any,
                           batch_idx: int) -> None:
        super().on_train_batch_end(trainer, pl_module, outputs, batch, batch_idx)
        K = self.last_every_n_train_steps
        if K and self.save_last and trainer.global_step % K == 0 and self._may_save(trainer):
            saved_step = self._last_global_step_saved
            self._save_last_checkpoint(trainer, self._monitor_candidates(trainer))
            # a periodic last.ckpt must not make the parent skip this step's epoch-end best/last save
            self._last_global_step_saved = saved_step

    def _refresh_last(self, trainer: L.Trainer, saves_before: int) -> None:
        if self.save_last and self._last_saves == saves_before and self._may_save(trainer):
            self._save_last_checkpoint(trainer, self._monitor_candidates(trainer))

    def on_validation_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        before = self._last_saves
        super().on_validation_end(trainer, pl_module)
        if not self._should_save_on_train_epoch_end(trainer) and not trainer.sanity_checking:
            self._refresh_last(trainer, before)

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        before = self._last_saves
        super().on_train_epoch_end(trainer, pl_module)
        if self._should_save_on_train_epoch_end(trainer):
            self._refresh_last(trainer, before)

    # ------------------------------------------------------------------------------- state
    def state_dict(self) -> dict[str, Any]:
        state = super().state_dict()
        state["rng"] = capture_rng_state()
        return state

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        state = dict(state_dict)
        self._pending_rng = state.pop("rng", None)
        old_dir = state.get("dirpath")
        if old_dir is None or self.dirpath is None or os.path.realpath(old_dir) == os.path.realpath(self.dirpath):
            super().load_state_dict(state)
            return
        # a new run folder: adopt the old best checkpoints as copies (never move or delete the old run's files)
        moved: dict[str, str] = {}
        for old in [*state.get("best_k_models", {}), state.get("best_model_path") or ""]:
            if old and old not in moved and os.path.isfile(old):
                new = os.path.join(self.dirpath, os.path.basename(old))
                if os.path.realpath(new) != os.path.realpath(old) and _is_global_zero():
                    atomic_copy(old, new)
                moved[old] = new
        self.best_k_models = {moved[k]: v for k, v in state.get("best_k_models", {}).items() if k in moved}
        self.best_model_path = moved.get(state.get("best_model_path") or "", "")
        self.best_model_score = state.get("best_model_score") if self.best_model_path else None
        self.kth_best_model_path = moved.get(state.get("kth_best_model_path") or "", "")
        if self.kth_best_model_path and state.get("kth_value") is not None:
            self.kth_value = state["kth_value"]
        self.last_model_path = ""  # the old last.ckpt stays where it is, untouched


def load_embedding_model(ckpt_path: str | Path, image_size: int | None = None,
                         device: str = "cpu") -> tuple[torch.nn.Module, int, int, str]:
    """The checkpoint's model (eval mode, on ``device``), its image size, N and file sha256.

    The size is always the checkpoint's; ``image_size`` only asserts it.

    Raises:
        MatlError: not a matl checkpoint, inconsistent, or a model that cannot enrol new products.
    """
    ckpt = load_checkpoint(ckpt_path)
    size, num_anchors = checkpoint_info(ckpt, ckpt_path)
    if image_size is not None and int(image_size) != size:
        raise MatlError(f"checkpoint {ckpt_path} was trained at {size} px, not image_size={image_size}: the model "
                        "size always comes from the checkpoint (drop image_size=)")
    config = ckpt.get("matl_config")
    if not isinstance(config, dict) or not isinstance(config.get("model"), dict):
        raise MatlError(f"checkpoint {ckpt_path} carries no matl_config: not written by matl.train; {CKPT_FIX}")
    data = config.get("data") if isinstance(config.get("data"), dict) else {}
    data_size = data.get("image_size")
    if data_size is not None and str(data_size) != str(size):
        raise MatlError(f"checkpoint {ckpt_path} is inconsistent: matl_image_size={size} but its config says "
                        f"data.image_size={data_size}")
    model = build_model(config["model"], ckpt, ckpt_path)
    if not hasattr(model, "feature_net"):
        raise MatlError(f"checkpoint {ckpt_path} is a {type(model).__name__}, which cannot enrol new objects: "
                        "predict needs an embedding model (model=matl or model=tl)")
    model.eval()
    model.homography_config = data.get("homography")  # the training warps, for calibration
    return model.to(device), size, num_anchors, file_sha256(ckpt_path)
