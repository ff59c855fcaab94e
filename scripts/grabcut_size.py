"""GrabCut on large crops: segmented at the crop's own size or on a copy of ``max_side`` px, mask IoU and time.

A camera's crop of a product is often several hundred px; the benchmark's are 100. This enlarges the RGB crops of
``matl.unseen`` condition folders (bicubic, their true masks nearest) by each factor and scores
``foreground.max_side`` against segmenting at full size (:mod:`matl.evaluation.masks`, one thread):

    python -m matl.unseen ckpt=pretrained data=synthetic_ycb 'condition=[clutter,occluded]' queries=150 \
        'methods=[matl]' timing.queries=0 out=runs/val_masks
    python scripts/grabcut_size.py runs/val_masks/clutter runs/val_masks/occluded --factors 1 4 8 --limit 40
"""

from __future__ import annotations

import argparse
import json

import cv2
import numpy as np

from matl.evaluation.masks import compare_steps, condition_crops
from matl.inference.foreground import GrabCutForeground


def enlarged(crops: list[tuple[np.ndarray, np.ndarray]], factor: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """The RGB crops ``factor`` times larger (bicubic, clipped to [0, 1]) with their true masks (nearest)."""
    out = []
    for image, truth in crops:
        if image.shape[-1] != 3:
            continue
        h, w = image.shape[:2]
        big = np.clip(cv2.resize(image, (w * factor, h * factor), interpolation=cv2.INTER_CUBIC), 0.0, 1.0)
        mask = cv2.resize(truth.astype(np.uint8), (w * factor, h * factor), interpolation=cv2.INTER_NEAREST) > 0
        out.append((big.astype(np.float32), mask))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folders", nargs="+", help="matl.unseen condition folders with masks/ (clutter, occluded)")
    parser.add_argument("--factors", type=int, nargs="+", default=[1, 4, 8])
    parser.add_argument("--limit", type=int, default=40, help="crops per folder")
    parser.add_argument("--max-side", type=int, default=200)
    args = parser.parse_args()
    steps = {"full size": GrabCutForeground(max_side=None), f"max_side={args.max_side}":
             GrabCutForeground(max_side=args.max_side)}
    for folder in args.folders:
        crops = condition_crops(folder, args.limit)
        for factor in args.factors:
            result = compare_steps(enlarged(crops, factor), steps)
            print(json.dumps({"folder": folder, "factor": factor, **result}))


if __name__ == "__main__":
    main()
