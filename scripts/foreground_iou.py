"""Foreground steps side by side: mask IoU, precision and recall against the true visible mask, and milliseconds a
crop (one thread).

Scores ``foreground=grabcut`` (its defaults), ``foreground=learned`` (its defaults, with ``--weights``) and the learned
step with each ``--variant`` (``name:key=value,key=value``, e.g. ``alone:grabcut_iterations=0``) on the RGB crops of
``matl.unseen`` condition folders (an RGBA crop's alpha ignored: its RGB is masked by the step), through
:mod:`matl.evaluation.masks`:

    python -m matl.unseen ckpt=pretrained data=synthetic_ycb 'condition=[mask,clutter,occluded]' queries=150 \
        'methods=[matl]' timing.queries=0 out=runs/val_masks
    python scripts/foreground_iou.py runs/val_masks/clutter runs/val_masks/occluded:truth_rgb.jsonl \
        runs/val_masks/mask --variant alone:grabcut_iterations=0

A folder may name its truth file after a colon (``occluded:truth_rgb.jsonl``: its RGB files only).
"""

from __future__ import annotations

import argparse
import json

import yaml

from matl.evaluation.masks import compare_steps, condition_crops
from matl.inference.foreground import GrabCutForeground, LearnedForeground

#: the result keys printed per step
KEYS = ("iou", "iou_p10", "precision", "recall", "ms_per_crop")


def variant(text: str) -> tuple[str, dict]:
    """``name:key=value,...`` as ``(name, {key: value})`` (values read as YAML)."""
    name, _, settings = text.partition(":")
    pairs = (item.partition("=") for item in settings.split(",") if item)
    return name, {key: yaml.safe_load(value) for key, _, value in pairs}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folders", nargs="+", help="matl.unseen condition folders with masks/ [:truth file]")
    parser.add_argument("--weights", default=None, help="a visibility checkpoint (default: the shipped one)")
    parser.add_argument("--variant", action="append", default=[], help="name:key=value,... of LearnedForeground")
    parser.add_argument("--limit", type=int, default=150, help="crops per folder")
    args = parser.parse_args()
    steps = {"grabcut": GrabCutForeground(), "learned": LearnedForeground(weights=args.weights)}
    for text in args.variant:
        name, settings = variant(text)
        steps[name] = LearnedForeground(weights=args.weights, **settings)
    for spec in args.folders:
        folder, _, truth = spec.partition(":")
        crops = [(image[..., :3], mask) for image, mask in condition_crops(folder, args.limit, truth or "truth.jsonl")]
        result = compare_steps(crops, steps, use_alpha=False, keep=lambda k: k in KEYS)
        print(json.dumps({"folder": spec, "crops": len(crops), **result}))


if __name__ == "__main__":
    main()
