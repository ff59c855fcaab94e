"""Which error of the foreground step's mask costs the open set: its false pixels (an occluder, a neighbour or the
floor taken for the product) or its misses (print left out).

For the RGB queries of a ``matl.unseen leave_out=...`` condition folder (``truth.jsonl``: the enrolled products'
queries, ``truth_left_out.jsonl``: the others', ``mask_file``: the true visible mask), the shipped default model
enrolled on the folder's gallery (``threshold=auto``) answers each query

* ``as given``: the RGB file, through the recognizer's own foreground step and its retries;
* ``step's mask``: RGBA with the foreground step's first mask as alpha;
* ``without false pixels``: RGBA with that mask and the truth (its pixels the truth does not hold removed);
* ``without misses``: RGBA with that mask or the truth (the true pixels it left out added);
* ``true mask``: RGBA with the truth;

and prints the share of enrolled queries answered with their product (known) and of left-out ones answered
unknown, with the step's mean mask precision and recall (:func:`matl.evaluation.masks.mask_precision_recall`):

    python -m matl.unseen ckpt=pretrained data=synthetic_ycb condition=occluded leave_out=0.5 'methods=[matl]' \
        queries=300 timing.queries=0 out=runs/val_open
    python scripts/mask_errors.py runs/val_open [--weights <visibility checkpoint>]
"""

from __future__ import annotations

import argparse
import json
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
from PIL import Image

from matl import Recognizer
from matl.evaluation.masks import mask_precision_recall
from matl.inference.foreground import LearnedForeground

Variant = Callable[[np.ndarray, np.ndarray], np.ndarray]
VARIANTS: dict[str, Variant | None] = {
    "as given": None,
    "step's mask": lambda truth, found: found,
    "without false pixels": lambda truth, found: truth & found,
    "without misses": lambda truth, found: truth | found,
    "true mask": lambda truth, found: truth,
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folder", type=Path, help="a matl.unseen leave_out=... condition folder")
    parser.add_argument("--weights", default=None, help="a visibility checkpoint (default: the shipped one)")
    args = parser.parse_args()
    folder = args.folder

    def rgb_queries(name: str) -> list[dict]:
        lines = (folder / name).read_text().splitlines()
        return [t for t in map(json.loads, filter(str.strip, lines)) if not t.get("rgba")]

    enrolled, left_out = rgb_queries("truth.jsonl"), rgb_queries("truth_left_out.jsonl")
    step = LearnedForeground(weights=args.weights)
    rec = Recognizer.pretrained(foreground=step)
    rec.enrol(folder / "gallery")
    crops = []
    for t in enrolled + left_out:
        rgb = np.asarray(Image.open(folder / t["image"]).convert("RGB"))
        truth = np.asarray(Image.open(folder / t["mask_file"]).convert("L")) > 127
        crops.append((t, rgb, truth, step(rgb.astype(np.float32) / 255.0) > 0.5))
    shares = np.array([mask_precision_recall(found, truth) for _, _, truth, found in crops[:len(enrolled)]])
    print(f"{folder}: {len(enrolled)} enrolled / {len(left_out)} left-out RGB queries; the step's first mask on the "
          f"enrolled ones: precision {shares[:, 0].mean():.3f}, recall {shares[:, 1].mean():.3f}")
    with tempfile.TemporaryDirectory() as tmp:
        for name, variant in VARIANTS.items():
            paths = []
            for i, (t, rgb, truth, found) in enumerate(crops):
                if variant is None:
                    paths.append(str(folder / t["image"]))
                    continue
                path = Path(tmp) / f"{i:05d}.png"
                alpha = variant(truth, found).astype(np.uint8) * 255
                Image.fromarray(np.dstack([rgb, alpha])).save(path)
                paths.append(str(path))
            answers = rec.predict(paths)
            known = sum(a.object == t["object"] for a, t in zip(answers, enrolled, strict=False))
            unknown = sum(a.object is None for a in answers[len(enrolled):])
            print(f"{name:>22}: enrolled answered right and known {known / max(len(enrolled), 1):.3f}, left-out "
                  f"answered unknown {unknown / max(len(left_out), 1):.3f}", flush=True)


if __name__ == "__main__":
    main()
