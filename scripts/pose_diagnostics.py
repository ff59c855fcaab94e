"""Where a pose error comes from (docs/decisions.md, "The virtual camera of the random homographies").

    python scripts/pose_diagnostics.py floor [--focal 1 1.5 2 2.5 3 4] [--samples 2000]
    python scripts/pose_diagnostics.py residuals <eval run>/per_query.csv

``floor``: for random homographies of the default ranges at each focal length, the image-corner
error of the best affine fit (least squares on the four mapped image corners): what an estimator
that models no perspective can at best reach.

``residuals``: for the correctly recognised queries of a ``per_query.csv`` (matl.eval), the
residual ``inv(true) @ estimated`` about the image centre split into rotation, translation, scale
and perspective, and the correlation of the estimated with the true perspective entries.
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np
import torch

from matl.geometry import HomographySampler, image_corners, transfer_points

SIZE = 100


def affine_floor(focal: float, samples: int, seed: int = 0) -> np.ndarray:
    """Mean corner distance ``(samples,)`` between each sampled homography and its best affine fit."""
    sampler = HomographySampler(focal=focal)
    footprint = torch.tensor([[20.0, 20.0], [80.0, 20.0], [80.0, 80.0], [20.0, 80.0]]).expand(samples, 4, 2)
    H = sampler.sample(samples, (SIZE, SIZE), torch.Generator().manual_seed(seed), footprint).double()
    corners = image_corners((SIZE, SIZE), torch.float64)                       # (4, 2)
    target = transfer_points(H, corners.expand(samples, 4, 2)).numpy()         # (B, 4, 2)
    design = np.concatenate([corners.numpy(), np.ones((4, 1))], axis=1)        # (4, 3): x, y, 1
    affine, *_ = np.linalg.lstsq(design, target.transpose(1, 0, 2).reshape(4, -1), rcond=None)
    fitted = (design @ affine).reshape(4, samples, 2).transpose(1, 0, 2)
    return np.linalg.norm(fitted - target, axis=-1).mean(-1)


def read_poses(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """True and estimated ``query_H_canon`` ``(B, 3, 3)`` of the correctly recognised queries."""
    with path.open() as f:
        rows = [r for r in csv.DictReader(f) if r["correct"] == "1"]
    if not rows:
        raise SystemExit(f"error: {path} has no correctly recognised query with a pose")
    keys = [f"{i}{j}" for i in range(3) for j in range(3)]
    true = np.array([[float(r[f"true_H_{k}"]) for k in keys] for r in rows]).reshape(-1, 3, 3)
    est = np.array([[float(r[f"est_H_{k}"]) for k in keys] for r in rows]).reshape(-1, 3, 3)
    return true, est


def centred(H: np.ndarray) -> np.ndarray:
    """Homographies in pixel coordinates about the image centre, scaled to ``H[2, 2] = 1``."""
    c = (SIZE - 1) / 2
    shift = np.array([[1.0, 0.0, c], [0.0, 1.0, c], [0.0, 0.0, 1.0]])
    out = np.linalg.inv(shift) @ H @ shift
    return out / out[:, 2:3, 2:3]


def residuals(path: Path) -> None:
    true, est = read_poses(path)
    residual = centred(np.linalg.inv(true) @ est)
    half = (SIZE - 1) / 2
    parts = {
        "rotation (deg)": np.abs(np.degrees(np.arctan2(residual[:, 1, 0] - residual[:, 0, 1],
                                                       residual[:, 0, 0] + residual[:, 1, 1]))),
        "translation (px)": np.hypot(residual[:, 0, 2], residual[:, 1, 2]),
        "|log scale|": np.abs(np.log(np.sqrt(np.abs(np.linalg.det(residual[:, :2, :2]))))),
        "perspective x half size": np.hypot(residual[:, 2, 0], residual[:, 2, 1]) * half,
    }
    print(f"{path}: {len(true)} correctly recognised queries; residual inv(true) @ estimated about the centre")
    for name, values in parts.items():
        print(f"  {name:24s} median {np.median(values):7.3f}   p25 {np.percentile(values, 25):7.3f}   "
              f"p75 {np.percentile(values, 75):7.3f}")
    t, e = centred(true), centred(est)
    for (i, j) in ((2, 0), (2, 1)):
        corr = np.corrcoef(t[:, i, j], e[:, i, j])[0, 1]
        print(f"  perspective entry h{i}{j}: true std {t[:, i, j].std() * half:.3f}, estimated std "
              f"{e[:, i, j].std() * half:.3f}, correlation {corr:.3f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    floor = sub.add_parser("floor", help="corner error of the best affine fit, per focal length")
    floor.add_argument("--focal", type=float, nargs="+", default=[1.0, 1.5, 2.0, 2.5, 3.0, 4.0])
    floor.add_argument("--samples", type=int, default=2000)
    res = sub.add_parser("residuals", help="split the pose errors of a per_query.csv")
    res.add_argument("per_query", type=Path)
    args = parser.parse_args()
    if args.command == "floor":
        for focal in args.focal:
            errors = affine_floor(focal, args.samples)
            print(f"focal {focal:g} image widths: best-affine corner error median {np.median(errors):.2f} px, "
                  f"within 5 px {np.mean(errors < 5):.2f}")
    else:
        if not args.per_query.is_file():
            raise SystemExit(f"error: {args.per_query} does not exist; pass the per_query.csv of a matl.eval run")
        residuals(args.per_query)


if __name__ == "__main__":
    main()
