"""Exporting the query and gallery networks of a checkpoint as TorchScript or torch.export graphs.

The library side of ``python -m matl.export`` (the command and its options: :mod:`matl.export`).
"""

from __future__ import annotations

import json
import logging
import warnings
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig
from torch import nn

from matl.utils.errors import MatlError
from matl.utils.io import write_json

log = logging.getLogger(__name__)

FORMATS = ("torchscript", "export")


def __getattr__(name: str) -> Any:
    """``QueryNet``: :class:`matl.inference.recognizer.QueryGraph`, the ``s()`` + ``c()`` graph that
    ``Recognizer`` itself compiles for single queries, so the exported network and the in-process
    fast path are one piece of code. Imported on first use (matl.models loads kornia; a bad option
    of the CLI is reported before that)."""
    if name == "QueryNet":
        from matl.inference.recognizer import QueryGraph

        return QueryGraph
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _trace(module: nn.Module, example: torch.Tensor, fmt: str, path: Path) -> Any:
    """Export ``module`` in ``fmt`` to ``path``; returns the loaded exported module (callable)."""
    module.eval()
    if fmt == "torchscript":
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*torch.jit.trace.*deprecated")
            warnings.filterwarnings("ignore", message=".*Converting a tensor to a Python.*")
            traced = torch.jit.trace(module, example, check_trace=False)
        torch.jit.save(traced, str(path))
        return torch.jit.load(str(path))
    batch = torch.export.Dim("batch", min=1, max=4096)
    program = torch.export.export(module, (example,), dynamic_shapes=({0: batch},))
    with warnings.catch_warnings():  # torch's own archive code warns about CPU weights it handles fine
        warnings.filterwarnings("ignore", message=".*No complete tensor found")
        torch.export.save(program, str(path))
        return torch.export.load(str(path)).module()


def _max_diff(eager: Any, exported: Any) -> float:
    """Largest absolute difference between (tuples of) eager and exported outputs; inf on a shape mismatch."""
    eager = eager if isinstance(eager, tuple) else (eager,)
    exported = exported if isinstance(exported, tuple) else (exported,)
    worst = 0.0
    for a, b in zip(eager, exported, strict=True):
        if a.shape != b.shape:
            return float("inf")
        worst = max(worst, float((a.double() - b.double()).abs().max()) if a.numel() else 0.0)
    return worst


@torch.no_grad()
def export_inference(feature_net: nn.Module, stn: nn.Module | None, image_size: int, out_dir: str | Path,
                     fmt: str = "torchscript", tolerance: float = 1e-5, check_batches: tuple[int, ...] = (1, 3),
                     meta: dict[str, Any] | None = None, seed: int = 0) -> dict[str, Any]:
    """Export the gallery and query networks, check them against the eager ones, write ``export.json``.

    Args:
        feature_net: ``c()`` (eval mode is set here).
        stn: ``s()``, or None for a model without pose (the query net is then ``c()`` alone and returns
            only the embedding).
        image_size: ``S``.
        out_dir: destination folder (created).
        fmt: ``torchscript`` or ``export``.
        tolerance: largest accepted absolute difference between exported and eager outputs.
        check_batches: batch sizes checked (random images, and the same images brightened), so a
            batch size baked into the export would be caught.
        meta: extra fields for ``export.json`` (N, checkpoint, ...).
    Returns:
        ``export.json``'s content.
    Raises:
        MatlError: unknown format, or outputs differ by more than ``tolerance``.
    """
    if fmt not in FORMATS:
        raise MatlError(f"format={fmt} is invalid: use {' or '.join(FORMATS)}")
    from matl.inference.recognizer import QueryGraph

    out = Path(out_dir).expanduser()
    out.mkdir(parents=True, exist_ok=True)
    suffix = ".pt" if fmt == "torchscript" else ".pt2"
    feature_net = feature_net.eval().cpu()
    query_net: nn.Module = QueryGraph(stn.eval().cpu(), feature_net) if stn is not None else feature_net
    g = torch.Generator().manual_seed(seed)
    example = torch.rand(2, 3, image_size, image_size, generator=g)

    files = {"gallery_net": out / f"gallery_net{suffix}", "query_net": out / f"query_net{suffix}"}
    gallery_exported = _trace(feature_net, example, fmt, files["gallery_net"])
    query_exported = _trace(query_net, example, fmt, files["query_net"])

    def eager_query(x: torch.Tensor) -> tuple[torch.Tensor, ...] | torch.Tensor:
        if stn is None:
            return feature_net(x)
        result = stn(x)
        return feature_net(result.warped), result.query_H_anchor, result.degenerate, result.warped

    diffs = {"gallery_net": 0.0, "query_net": 0.0}
    for batch in check_batches:
        images = torch.rand(batch, 3, image_size, image_size, generator=g)
        for x in (images, (images * 1.5).clamp(0, 1)):
            diffs["gallery_net"] = max(diffs["gallery_net"], _max_diff(feature_net(x), gallery_exported(x)))
            diffs["query_net"] = max(diffs["query_net"], _max_diff(eager_query(x), query_exported(x)))
    for name, diff in diffs.items():
        if not diff <= tolerance:
            raise MatlError(f"exported {name} differs from the eager model by {diff:.3g} > tolerance {tolerance:g}")

    embedding_dim = int(feature_net(example[:1]).shape[1])
    info: dict[str, Any] = {
        "format": fmt, "files": {k: v.name for k, v in files.items()}, "image_size": int(image_size),
        "embedding_dim": embedding_dim, "torch": torch.__version__, "max_abs_diff": diffs,
        "tolerance": tolerance, "checked_batch_sizes": list(check_batches),
        "inputs": "float32 (B, 3, S, S) RGB in [0, 1], background 0 (foreground-segmented), S = image_size",
        "gallery_net": "(B, 3, S, S) -> embedding (B, D): c(anchor)",
        "query_net": ("(B, 3, S, S) -> embedding (B, D), query_H_anchor (B, 3, 3), degenerate (B,), warped (B, 3, S, S)"
                      if stn is not None else "(B, 3, S, S) -> embedding (B, D) (no STN: no pose)"),
        "recognition": "argmin over gallery anchors of the L2 distance between embeddings (paper Sec. 4.5)",
        "pose": "query_H_canon = query_H_anchor @ anchor_k_H_canon of the nearest anchor; pixel homographies, "
                "(0, 0) = centre of the top-left pixel, H[2, 2] = 1 (DESIGN §2)",
        **(meta or {}),
    }
    write_json(out / "export.json", info)
    return info


def export(cfg: DictConfig) -> dict[str, Any]:
    """``matl.export``'s work for a composed ``conf/export.yaml``."""
    if cfg.get("ckpt") in (None, ""):
        raise MatlError("ckpt=... is required: python -m matl.export ckpt=<path> out=<dir>")
    if not Path(str(cfg.ckpt)).expanduser().is_file():  # before the heavy imports: a typo costs a second
        raise MatlError(f"checkpoint {cfg.ckpt} not found")
    if str(cfg.format) not in FORMATS:
        raise MatlError(f"format={cfg.format} is invalid: use {' or '.join(FORMATS)}")
    from matl.inference.files import load_predictor
    model, size, num_anchors, sha = load_predictor(cfg.ckpt)
    stn = getattr(model, "stn", None)
    meta = {"N": num_anchors, "checkpoint": str(cfg.ckpt), "checkpoint_sha256": sha,
            "fixed_anchors": "anchor k = canonical image rotated by k * 360 / N degrees about the centre"}
    info = export_inference(model.feature_net, stn, size, cfg.out, str(cfg.format), float(cfg.tolerance), meta=meta)
    log.info("export: %s", json.dumps(info))
    return info
