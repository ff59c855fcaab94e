"""The methods of the unseen-products benchmark: each one's run of predict on a condition's files, and its timing.

Every method answers the same files through predict's library function (:func:`matl.inference.files.predict`,
what ``python -m matl.predict`` runs), in this process: :class:`MethodRun` holds the method's predict options
as values and its config groups as nodes of the benchmark's own config, builds predict's config from them
(:meth:`MethodRun.config`) and records the shell command that runs the same (:attr:`MethodRun.command`, for
``unseen.json``; it is not what runs). :func:`time_methods` times the methods' recognizers, built from the
same configs, here too.
"""

from __future__ import annotations

import re
import shlex
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf, open_dict

from matl.inference.recognizer_options import CONFIG_OPTIONS, option_default
from matl.inference.runtime import runtime_option
from matl.utils.errors import CONF_DIR, MatlError

METHODS = ("matl", "matl_refine", "sift", "sift_ecc", "lightglue", "xfeat", "xfeat_lighterglue")
MATL_METHODS = ("matl", "matl_refine")  # the checkpoint's model; the others are keypoint baselines
# predict's open-set, verification and pose-stage keys but the quantile (shared_options writes it first), the same
# keys in conf/unseen.yaml (values: their defaults)
OPEN_SET_KEYS = {key: option_default(key) for key in CONFIG_OPTIONS if key != "open_set_quantile"}


# -------------------------------------------------------------------------------------- commands
def _arg(key: str, value: Any) -> str:
    """A Hydra override ``key=value``, the value quoted when Hydra's grammar would not take it bare."""
    text = str(value).lower() if isinstance(value, bool) else str(value)
    if re.fullmatch(r"[\w./:+@-]+", text):
        return f"{key}={text}"
    return f"{key}='{text.replace(chr(92), chr(92) * 2).replace(chr(39), chr(92) + chr(39))}'"


def _task_overrides() -> list[str]:
    try:
        from hydra.core.hydra_config import HydraConfig

        return list(HydraConfig.get().overrides.task)
    except ValueError:  # called as a function, not from the command line
        return []


def own_command() -> str:
    """``python -m matl.unseen <the command line's overrides>`` ("" when called as a function)."""
    overrides = _task_overrides()
    return shlex.join(["python", "-m", "matl.unseen", *overrides]) if overrides else ""


def method_overrides(method: str) -> list[str]:
    """The user's own overrides of a method's settings, as predict's keys: ``foreground.*`` for matl and
    matl_refine, ``refiner=<choice>`` and ``refiner.*`` for matl_refine, ``baselines.<name>.*`` (here) ->
    ``baseline.*`` (predict) for a keypoint baseline. For the recorded command only: the nodes a
    :class:`MethodRun` passes on already hold them."""
    overrides = _task_overrides()
    if method in MATL_METHODS:  # foreground=<choice> is an option of the run
        keys = ("foreground.", "refiner.", "refiner=") if method == "matl_refine" else ("foreground.",)
        return [o for o in overrides if o.lstrip("+~").startswith(keys)]
    prefix = f"baselines.{method}."
    return [o.replace(prefix, "baseline.", 1) for o in overrides if o.lstrip("+~").startswith(prefix)]


def foreground_choice(cfg: DictConfig) -> str:
    """The ``foreground`` group's choice of an unseen config (``grabcut``, ``learned``, ``none``), for predict: the
    command line's, else the group file whose ``_target_`` the node has (a config composed in Python)."""
    from matl.utils.errors import group_options
    from matl.utils.runs import hydra_choice

    choice = hydra_choice("foreground")
    if choice is not None:
        return choice
    node = cfg.get("foreground")
    target = None if node is None else node.get("_target_")
    if target is None:
        return "none"
    return next((name for name in group_options("foreground")
                 if OmegaConf.load(CONF_DIR / "foreground" / f"{name}.yaml").get("_target_") == target), "grabcut")


def score_command(predictions: Path, truth: Path, ckpt: Path, gallery_fill: float, query_fill: float,
                  out: Path) -> str:
    """The shell command that scores a method's predictions as the benchmark does (``python -m matl.score``)."""
    args = {"predictions": predictions, "truth": truth, "ckpt": ckpt, "gallery_fill": gallery_fill,
            "query_fill": query_fill, "out": out}
    return shlex.join(["python", "-m", "matl.score", *(_arg(key, value) for key, value in args.items())])


# ------------------------------------------------------------------------------------------ runs
def predict_defaults() -> DictConfig:
    """``conf/predict.yaml`` composed as ``python -m matl.predict`` composes it with no override."""
    import hydra
    from hydra.core.global_hydra import GlobalHydra

    if GlobalHydra.instance().is_initialized():  # inside a Hydra app (matl.unseen): its search path is conf/
        return hydra.compose(config_name="predict")
    with hydra.initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return hydra.compose(config_name="predict")


def shared_options(cfg: DictConfig, ckpt: Path, folder: Path, threshold: float | str | None, gallery_fill: float,
                   query_fill: float) -> dict[str, Any]:
    """predict's options common to every method of a condition written into ``folder`` (``gallery/``,
    ``queries/``), in the order the recorded commands list them; ``threshold`` None: the closed set."""
    return {"ckpt": ckpt, "gallery": folder / "gallery", "images": folder / "queries", "gallery_fill": gallery_fill,
            "query_fill": query_fill, "batch_size": cfg.batch_size, "device": cfg.device, "threshold": threshold,
            "open_set_quantile": cfg.get("open_set_quantile", option_default("open_set_quantile")),
            **{key: cfg.get(key, default) for key, default in OPEN_SET_KEYS.items()}}


@dataclass(frozen=True)
class MethodRun:
    """One method's predict run on a condition's files.

    Attributes:
        method: one of :data:`METHODS`.
        options: predict's top-level keys (``conf/predict.yaml``) and their values (None: null; a path: its
            text), in the order :attr:`command` lists them, ``out`` last. A key of ``groups`` names the group's
            choice (``foreground=grabcut``, ``baseline=sift``) for the command; the config takes the group's node.
        groups: predict's config groups as nodes of the benchmark's config, the user's overrides included:
            ``foreground`` (and ``refiner`` for matl_refine) for MATL, ``baseline`` (``baselines.<method>``) for
            a keypoint baseline.
        overrides: those overrides as the command line gave them, in predict's keys (:func:`method_overrides`).
    """

    method: str
    options: dict[str, Any]
    groups: dict[str, Any]
    overrides: tuple[str, ...] = field(default=())

    @classmethod
    def of(cls, method: str, cfg: DictConfig, shared: dict[str, Any], out: Path) -> MethodRun:
        """``method``'s run on the files of ``shared`` (:func:`shared_options`), predicting into ``out``; the
        benchmark's config ``cfg`` gives its groups and runtime. A keypoint baseline answers a closed set."""
        if method in MATL_METHODS:
            options = {**shared, "refine": method == "matl_refine", "foreground": foreground_choice(cfg),
                       "runtime": runtime_option(cfg)}
            groups = {"foreground": cfg.get("foreground")}
            if method == "matl_refine":
                groups["refiner"] = cfg.refiner
        else:
            options = {**{k: v for k, v in shared.items() if k != "threshold"}, "baseline": method, "threshold": None}
            groups = {"baseline": cfg.baselines[method]}
        return cls(method, {**options, "out": out}, groups, tuple(method_overrides(method)))

    @property
    def command(self) -> str:
        """The shell command that runs the same: ``python -m matl.predict <options> <overrides> out=<out>``."""
        args = [_arg(key, "null" if value is None else value) for key, value in self.options.items() if key != "out"]
        return shlex.join(["python", "-m", "matl.predict", *args, *self.overrides, _arg("out", self.options["out"])])

    def config(self, batch_size: int | None = None) -> DictConfig:
        """predict's config of the run: :func:`predict_defaults` with :attr:`options` and :attr:`groups` set (what
        :attr:`command` composes); ``batch_size`` replaces the option's (timing: 1)."""
        cfg = predict_defaults()
        with open_dict(cfg):
            for key, value in self.options.items():
                if key not in self.groups:
                    cfg[key] = str(value) if isinstance(value, Path) else value
            for key, node in self.groups.items():
                cfg[key] = None if node is None else OmegaConf.to_container(node, resolve=True)
            cfg.paths.output_dir = str(Path(self.options["out"]).parent)  # viz_dir's folder (viz=false here)
            if batch_size is not None:
                cfg.batch_size = int(batch_size)
        return cfg

    def run(self) -> dict[str, Any]:
        """Predict the files in this process (:func:`matl.inference.files.predict`); returns predict's summary.

        Raises:
            MatlError: predict's one-line error, naming the method.
        """
        from matl.inference.files import predict

        try:
            return predict(self.config(), baseline_name=None if self.method in MATL_METHODS else self.method)
        except MatlError as error:
            raise MatlError(f"{self.method}: {error}") from None

    def check(self) -> None:
        """Check the run before any work: predict's options (:func:`matl.utils.config.validate_config`) and its
        recognizer, built and dropped (the checkpoint, the open-set and verification options, a baseline's matcher
        and its optional package).

        Raises:
            MatlError: the first problem, in one line naming the method.
        """
        from matl.utils.config import validate_config

        try:
            config = self.config()
            validate_config(config)
            self.recognizer()
        except MatlError as error:
            raise MatlError(f"{self.method}: {error}") from None

    def recognizer(self) -> Any:
        """The method's recognizer as predict builds it, with a batch of one (not enrolled yet)."""
        config = self.config(batch_size=1)
        if self.method in MATL_METHODS:
            from matl.inference.files import recognizer_from_config

            return recognizer_from_config(config)
        from matl.inference.baseline_files import baseline_recognizer_from_config

        return baseline_recognizer_from_config(config, self.method)


# ------------------------------------------------------------------------------------------ timing
def time_methods(recognizers: dict[str, Any], files: list[Path], warmup: int, threads: int) -> dict[str, float]:
    """``query_ms`` of each enrolled recognizer on the same query files: the median of single-query calls
    (file already decoded; framing, recognition, pose and pose-in-files timed), after ``warmup`` untimed
    calls, with ``threads`` torch and OpenCV threads for every method. Every method is timed in this process,
    one after the other, on the same arrays."""
    from matl.data.image_files import read_rgba
    from matl.utils.timing import median_query_ms

    arrays = [rgb if alpha is None else np.concatenate([rgb, alpha[..., None]], -1)  # RGBA: alpha = mask
              for rgb, alpha in map(read_rgba, files)]
    shapes = {a.shape for a in arrays}
    if len(shapes) != 1:
        raise MatlError(f"timing needs query files of one size, got {sorted(shapes)}")
    queries = torch.from_numpy(np.stack(arrays))  # (Q, H, W, 3 or 4)
    # median_query_ms sets torch's and OpenCV's threads alike (matl.utils.timing.compute_threads)
    return {name: median_query_ms(lambda x, r=rec: r.predict_details([x[0].numpy()]), queries, warmup,
                                  threads=int(threads)) for name, rec in recognizers.items()}
