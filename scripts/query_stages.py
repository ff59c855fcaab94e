"""Where single queries' milliseconds go against a gallery folder, stage by stage (docs/catalog.md, docs/speed.md).

    python -m matl.unseen ckpt=pretrained condition=catalog 'catalog_sizes=[10000]' ... out=runs/catalog
    python scripts/query_stages.py runs/catalog/n10000 --queries 24

Enrols ``<folder>/gallery`` with the shipped default model, refined (``Recognizer.pretrained(refine=True)``; the
features' cache of an earlier enrolment is read, so a catalogue's gallery is ready in seconds), answers the enrolled
queries of ``<folder>/truth.jsonl`` one at a time (one thread, after ``--warmup`` untimed calls) with
``Recognizer.time_stages`` on, and prints one JSON line: the median and mean milliseconds of a call, the mean of each
stage and ``other`` (what ran between the stages), and the calls sorted by time with their stages. ``--threshold``
defaults to a closed set (no open-set calibration: the stages an answer runs are the same, the calibration of a
large gallery takes minutes); ``--flow-pose`` as the recognizer's ``flow_pose``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from matl import Recognizer
from matl.utils.timing import StageTimer


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folder", type=Path, help="a folder with gallery/ and truth.jsonl (e.g. a catalogue size's)")
    parser.add_argument("--queries", type=int, default=24, help="enrolled queries timed (the first ones)")
    parser.add_argument("--warmup", type=int, default=3, help="untimed calls first")
    parser.add_argument("--threshold", default=None, help="the open set's threshold (auto, a number); default none")
    parser.add_argument("--flow-pose", default="always", help="the recognizer's flow_pose (always, unverified, none)")
    args = parser.parse_args()
    for need in (args.folder / "gallery", args.folder / "truth.jsonl"):
        if not need.exists():
            raise SystemExit(f"query_stages: {need} not found: pass a folder with gallery/ and truth.jsonl "
                             "(a matl.unseen condition folder or a catalogue size's, e.g. <out>/n10000)")
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    threshold = None if args.threshold is None else (args.threshold if args.threshold == "auto"
                                                     else float(args.threshold))
    rec = Recognizer.pretrained(refine=True, threshold=threshold, flow_pose=args.flow_pose)
    start = time.perf_counter()
    rec.enrol(args.folder / "gallery")
    enrol_s = time.perf_counter() - start
    truth = [json.loads(line) for line in (args.folder / "truth.jsonl").read_text().splitlines() if line.strip()]
    files = [args.folder / t["image"] for t in truth if t.get("enrolled", True)][:args.queries]
    images = []
    for file in files:
        image = cv2.imread(str(file))
        if image is None:
            raise SystemExit(f"query_stages: {file} cannot be read as an image: is the folder complete?")
        images.append(cv2.cvtColor(image, cv2.COLOR_BGR2RGB))
    for image in images[:args.warmup]:
        rec.predict(image)
    timer = StageTimer()
    rec.time_stages(timer)
    calls = []
    for file, image in zip(files, images, strict=True):
        start = time.perf_counter()
        rec.predict(image)
        total = (time.perf_counter() - start) * 1000.0
        stages = timer.take()["ms"]
        calls.append({"file": file.name, "ms": round(total, 2),
                      "stages": {k: round(v, 2) for k, v in stages.items()},
                      "other": round(total - sum(stages.values()), 2)})
    rec.time_stages(None)
    totals = np.array([c["ms"] for c in calls])
    names = sorted({k for c in calls for k in c["stages"]})
    print(json.dumps({
        "folder": str(args.folder), "gallery_planes": len(rec.planes),
        "enrol_s": round(enrol_s, 1), "queries": len(calls),
        "median_ms": round(float(np.median(totals)), 2), "mean_ms": round(float(totals.mean()), 2),
        "stage_mean_ms": {k: round(float(np.mean([c["stages"].get(k, 0.0) for c in calls])), 2) for k in names},
        "other_mean_ms": round(float(np.mean([c["other"] for c in calls])), 2),
        "calls": sorted(calls, key=lambda c: c["ms"])}))


if __name__ == "__main__":
    main()
