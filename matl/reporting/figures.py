"""The paper's figures as PNG files, for ``matl.report``: Fig. 2, Fig. 4 and Fig. 5.

* **Fig. 2** (:func:`appearance_vs_rotation`, :func:`plot_fig2`; :func:`write_fig2` from a catalog):
  the appearance loss ``L^a`` (Eq. 1, the mean L1 of :func:`matl.losses.appearance_distance`)
  between a canonical image and the same image rotated in-plane about its centre by -180..180
  degrees. Computed directly from a catalog's canonical image, no training: the global minimum is
  at 0 and, for the box-like silhouettes of products, poor local minima sit at +-180 degrees (and
  +-90 for square ones), which is what traps a single-anchor STN (Sec. 3.2).
* **Fig. 4** (:func:`plot_fig4`): ``rec_acc`` and ``pose_err`` against the number of anchors N,
  mean +- std over seeds, one column per dataset (the paper's (a)-(f)).
* **Fig. 5** (:func:`fig5_panels`, :func:`plot_fig5`): test queries, the query warped by the
  single-anchor model's STN, the query warped by MATL's STN, and the anchor MATL chose.

Matplotlib runs with the Agg backend (files only, no display).
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from matl.geometry import centre_rotation, warp_image
from matl.losses import appearance_distance
from matl.utils.errors import MatlError
from matl.utils.io import write_csv


def _save(fig: Any, path: Path) -> None:
    """Lay out, write a PNG at 150 dpi (creating its folder) and free the figure."""
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=150)
    _pyplot().close(fig)


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")  # files only: works on headless machines and inside tests
    import matplotlib.pyplot as plt

    return plt


# ------------------------------------------------------------------------------------------ Fig. 2
def appearance_vs_rotation(image: torch.Tensor, angles_deg: torch.Tensor | Sequence[float],
                           levels: int = 1) -> torch.Tensor:
    """``L^a(I, R_theta I)`` for each angle: ``image`` ``(3, S, S)`` in [0, 1] -> ``(len(angles),)``.

    ``R_theta`` rotates about the image centre (the centre of docs/design.md, as the fixed anchors do);
    ``levels=1`` is the paper's loss, more levels the CPU default's pyramid.
    """
    if image.ndim != 3 or image.shape[0] != 3:
        raise ValueError(f"image must be (3, S, S), got {tuple(image.shape)}")
    angles = torch.as_tensor(angles_deg, dtype=torch.float64)
    size = tuple(image.shape[-2:])
    H = centre_rotation(angles, size)                          # (A, 3, 3) canonical -> rotated
    images = image.float().unsqueeze(0).expand(len(angles), -1, -1, -1)
    rotated = warp_image(images, H)
    return appearance_distance(images, rotated, levels).double()


def local_minima(angles: Sequence[float], values: Sequence[float]) -> list[tuple[float, float]]:
    """``(angle, value)`` of the strict interior local minima of a sampled curve, plus the ends
    (+-180 deg) when they are lower than their only neighbour (the curve is periodic, and its ends
    are the same rotation)."""
    a, v = np.asarray(angles, dtype=float), np.asarray(values, dtype=float)
    found = [(float(a[i]), float(v[i])) for i in range(1, len(v) - 1) if v[i] < v[i - 1] and v[i] <= v[i + 1]]
    if len(v) > 1 and v[0] < v[1]:
        found.insert(0, (float(a[0]), float(v[0])))
    if len(v) > 1 and v[-1] < v[-2]:
        found.append((float(a[-1]), float(v[-1])))
    return found


def plot_fig2(angles: Sequence[float], values: Sequence[float], path: Path, title: str,
              image: torch.Tensor | None = None) -> Path:
    """Fig. 2: the loss curve with its local minima marked, and the image itself as an inset."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 3.6))
    ax.plot(angles, values, color="tab:blue", lw=1.5)
    for angle, value in local_minima(angles, values):
        ax.plot([angle], [value], "o", color="tab:red" if abs(angle) > 1e-6 else "tab:green", ms=5)
        align = "left" if angle <= -179 else "right" if angle >= 179 else "center"  # keep end labels inside
        ax.annotate(f"{angle:+.0f}°", (angle, value), textcoords="offset points", xytext=(0, -13),
                    ha=align, fontsize=7)
    ax.set_xlabel("in-plane rotation (degrees)")
    ax.set_ylabel("appearance loss $L^a$ (mean L1)")
    ax.set_xlim(-180, 180)
    ax.set_xticks(range(-180, 181, 45))
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    if image is not None:
        inset = ax.inset_axes((0.40, 0.62, 0.2, 0.35))
        inset.imshow(image.permute(1, 2, 0).clamp(0, 1).cpu().numpy())
        inset.set_axis_off()
    _save(fig, path)
    return path


def write_fig2(path: Path, data: str, plane: str | None, image_size: int, cache_dir: str | None) -> tuple[Path, str]:
    """Fig. 2 from the ``data=<data>`` catalog's canonical image of ``plane`` (index or ``object/plane``;
    default: the first plane of the first planar object, the paper's "book"), its curve beside it as
    ``<path>.csv``; returns the PNG's path and the report's caption."""
    import hydra

    from matl.data.canonical import load_canonical
    from matl.utils.runs import compose_data_group

    source = hydra.utils.instantiate(compose_data_group(data).source)
    cache = cache_dir or os.environ.get("MATL_CACHE_DIR") or ".cache/matl"
    canonical = load_canonical(source, image_size, cache)
    index = pick_plane(canonical, plane)
    image = torch.from_numpy(canonical.images[index]).permute(2, 0, 1).float().div(255.0)
    angles = torch.arange(-180.0, 180.0 + 1e-9, 2.0, dtype=torch.float64)
    values = appearance_vs_rotation(image, angles)
    label = canonical.plane_label(index)
    plot_fig2(angles.tolist(), values.tolist(), path, f"{data}: {label} ({image_size} px)", image)
    write_csv(path.with_suffix(".csv"), [{"rotation_deg": f"{a:.1f}", "appearance_loss": f"{v:.6f}"}
                                         for a, v in zip(angles.tolist(), values.tolist(), strict=True)])
    minima = ", ".join(f"{a:+.0f}° ({v:.4f})" for a, v in local_minima(angles.tolist(), values.tolist()))
    return path, (f"`{label}` of `{data}` at {image_size} px, rotated about its centre; L^a = mean L1 "
                  f"(Eq. 1). Local minima: {minima}. Data: `fig2.csv`.")


def pick_plane(canonical: Any, plane: str | None) -> int:
    """A plane index from ``plane`` (an index, or ``object/plane``), default the first planar object's first plane."""
    if plane is None:
        for index in range(canonical.num_planes):
            if canonical.object_shapes[int(canonical.plane_object[index])] == "planar":
                return index
        return 0
    if plane.isdigit():
        if int(plane) >= canonical.num_planes:
            raise MatlError(f"--fig2-plane {plane}: the catalog has {canonical.num_planes} planes")
        return int(plane)
    labels = [canonical.plane_label(i) for i in range(canonical.num_planes)]
    if plane not in labels:
        raise MatlError(f"--fig2-plane {plane!r} is not a plane of the catalog (e.g. {labels[0]!r})")
    return labels.index(plane)


# ------------------------------------------------------------------------------------------ Fig. 4
@dataclass
class Point:
    """One Fig. 4 point: mean and sample std over seeds (std 0 with one seed)."""

    mean: float
    std: float
    n: int


def plot_fig4(series: Mapping[str, Mapping[int, Mapping[str, Point]]], path: Path,
              metrics: Sequence[tuple[str, str]] = (("rec_acc", "recognition accuracy"),
                                                     ("pose_err", "pose error (Frobenius)"))) -> Path:
    """Fig. 4: ``series[dataset][N][metric]`` -> one column per dataset, one row per metric."""
    plt = _pyplot()
    datasets = list(series)
    fig, axes = plt.subplots(len(metrics), max(1, len(datasets)), figsize=(3.2 * max(1, len(datasets)), 5.2),
                             squeeze=False)
    letters = "abcdefghijklmnopqrstuvwxyz"
    for col, dataset in enumerate(datasets):
        by_n = series[dataset]
        for row, (metric, label) in enumerate(metrics):
            ax = axes[row][col]
            ns = sorted(n for n in by_n if metric in by_n[n] and math.isfinite(by_n[n][metric].mean))
            if ns:
                ax.errorbar(ns, [by_n[n][metric].mean for n in ns], yerr=[by_n[n][metric].std for n in ns],
                            marker="o", capsize=3, color="tab:blue" if row == 0 else "tab:orange")
                ax.set_xticks(ns)
            ax.set_xlabel("number of anchors N")
            ax.set_ylabel(label)
            ax.set_title(f"({letters[2 * col + row]}) {dataset}", fontsize=9)
            ax.grid(alpha=0.3)
    _save(fig, path)
    return path


# ------------------------------------------------------------------------------------------ Fig. 5
@dataclass
class Fig5Panels:
    """Images ``(K, 3, S, S)`` of Fig. 5's four columns and what they show."""

    query: torch.Tensor
    single: torch.Tensor        # s(query) of the single-anchor model ([28], N=1)
    matl: torch.Tensor          # s(query) of MATL
    anchor: torch.Tensor        # the gallery anchor MATL chose
    labels: list[str]           # "<object>/<plane>, rotation +123°"


def _check_data_targets(node: Any, path: str) -> None:
    """A checkpoint's data config is instantiated: only matl's own classes may be named in it."""
    if isinstance(node, Mapping):
        target = node.get("_target_")
        if target is not None and not str(target).startswith("matl."):
            raise MatlError(f"checkpoint {path}: data config names {target!r}; only matl.* classes are instantiated")
        for value in node.values():
            _check_data_targets(value, path)
    elif isinstance(node, (list, tuple)):
        for value in node:
            _check_data_targets(value, path)


def rotation_deg(H: torch.Tensor) -> torch.Tensor:
    """In-plane rotation angle (degrees) of pixel homographies ``(..., 3, 3)``, from their linear part."""
    # centre_rotation(t) has [[c, s], [-s, c]] (counter-clockwise on screen, y down): atan2(2s, 2c) = t
    return torch.rad2deg(torch.atan2(H[..., 0, 1] - H[..., 1, 0], H[..., 0, 0] + H[..., 1, 1]))


@torch.no_grad()
def fig5_panels(single_ckpt: str | Path, matl_ckpt: str | Path, rows: int = 3, pool: int = 200) -> Fig5Panels:
    """Fig. 5's images from two ``matl.train`` checkpoints (the first single-anchor, the second MATL).

    The queries are the first ``pool`` test queries of MATL's run (its saved config: data, seed, N);
    ``rows`` of those MATL recognised correctly are shown, spread from the smallest to the largest
    in-plane rotation (the paper's third row has a large one).
    """
    import hydra
    from omegaconf import OmegaConf

    from matl.models.checkpoint import build_model, checkpoint_info, load_checkpoint

    ckpts = [load_checkpoint(single_ckpt), load_checkpoint(matl_ckpt)]
    sizes = [checkpoint_info(c, p)[0] for c, p in zip(ckpts, (single_ckpt, matl_ckpt), strict=True)]
    if sizes[0] != sizes[1]:
        raise MatlError(f"Fig. 5 needs two checkpoints of one image size, got {sizes[0]} and {sizes[1]} px")
    configs = []
    for ckpt, path in zip(ckpts, (single_ckpt, matl_ckpt), strict=True):
        if "matl_config" not in ckpt:
            raise MatlError(f"checkpoint {path} has no matl_config: not written by matl.train")
        configs.append(OmegaConf.create(ckpt["matl_config"]))
    _check_data_targets(OmegaConf.to_container(configs[1].data, resolve=False), str(matl_ckpt))
    datamodule = hydra.utils.instantiate(configs[1].data)
    datamodule.setup("test")
    models = [build_model(cfg.model, ckpt, path) for cfg, ckpt, path
              in zip(configs, ckpts, (single_ckpt, matl_ckpt), strict=True)]
    for model, path in zip(models, (single_ckpt, matl_ckpt), strict=True):
        if getattr(model, "stn", None) is None:
            raise MatlError(f"checkpoint {path} has no STN (model=tl?): Fig. 5 compares STN outputs")

    params = {k: v[:pool] for k, v in datamodule.test_set.params.items()}
    batch = datamodule.materialize(params)
    queries = batch["query"]
    recognizer = models[1].build_recognizer(datamodule.gallery)
    pred = recognizer(queries)
    single = models[0].stn(queries).warped
    correct = (pred.object_index == batch["object"]).nonzero().flatten()
    candidates = correct if len(correct) >= rows else torch.arange(len(queries))
    angles = rotation_deg(batch["query_H_canon"].double())
    order = candidates[angles[candidates].abs().argsort()]
    pick = order[torch.linspace(0, len(order) - 1, min(rows, len(order))).round().long()]
    gallery = datamodule.gallery
    labels = [f"{gallery.object_names[int(gallery.object_index[pred.gallery_index[i]])]}/"
              f"{gallery.plane_names[int(gallery.plane_index[pred.gallery_index[i]])]}, "
              f"rotation {float(angles[i]):+.0f}°" for i in pick.tolist()]
    return Fig5Panels(query=queries[pick], single=single[pick], matl=pred.warped[pick],
                      anchor=gallery.images[pred.gallery_index[pick]], labels=labels)


def plot_fig5(panels: Fig5Panels, path: Path, single_name: str = "[28] (N=1)", matl_name: str = "ours (MATL)") -> Path:
    """Fig. 5: one row per query; input, warped by [28], warped by ours, anchor."""
    plt = _pyplot()
    columns = [("input", panels.query), (f"s(input): {single_name}", panels.single),
               (f"s(input): {matl_name}", panels.matl), ("anchor (reference)", panels.anchor)]
    rows = len(panels.query)
    fig, axes = plt.subplots(rows, 4, figsize=(8.0, 2.1 * rows + 0.3), squeeze=False)
    for r in range(rows):
        for c, (title, images) in enumerate(columns):
            ax = axes[r][c]
            ax.imshow(images[r].permute(1, 2, 0).clamp(0, 1).cpu().numpy())
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(title, fontsize=8)
        axes[r][0].set_ylabel(panels.labels[r], fontsize=6)
    _save(fig, path)
    return path
