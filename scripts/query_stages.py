"""Where single queries' milliseconds go against a gallery folder, stage by stage (docs/catalog.md, docs/speed.md).

    python -m matl.unseen ckpt=pretrained condition=catalog 'catalog_sizes=[10000]' ... out=runs/catalog
    python scripts/query_stages.py runs/catalog/n10000 --queries 24

Enrols ``<folder>/gallery`` with the shipped default model, refined (``Recognizer.pretrained(refine=True)``; the
features' cache of an earlier enrolment is read, so a catalogue's gallery is ready in seconds), answers the enrolled
queries of ``<folder>/truth.jsonl`` one at a time (one thread, after ``--warmup`` untimed calls) with
``Recognizer.time_stages`` on, and prints one JSON line: the median and mean milliseconds of a call, the mean of each
stage and ``other`` (what ran between the stages), and the calls sorted by time with their stages. ``--threshold``
defaults to a closed set (no open-set calibration: the stages an answer runs are the same, the calibration of a
large gallery takes minutes); ``--flow-pose`` as the recognizer's ``flow_pose``; ``--option NAME=VALUE`` (repeated) sets
any other Recognizer option (the value read as YAML: ``--option lookalike_ratio=1.1 --option
lookalike_statistic=global``).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import yaml

from matl import Recognizer
from matl.utils.timing import StageTimer, stage_query_ms


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folder", type=Path, help="a folder with gallery/ and truth.jsonl (e.g. a catalogue size's)")
    parser.add_argument("--queries", type=int, default=24, help="enrolled queries timed (the first ones)")
    parser.add_argument("--warmup", type=int, default=3, help="untimed calls first")
    parser.add_argument("--threshold", default=None, help="the open set's threshold (auto, a number); default none")
    parser.add_argument("--flow-pose", default="always", help="the recognizer's flow_pose (always, unverified, none)")
    parser.add_argument("--option", action="append", default=[], metavar="NAME=VALUE",
                        help="another Recognizer option, the value as YAML (repeat for several)")
    args = parser.parse_args()
    options = {}
    for item in args.option:
        name, sep, value = item.partition("=")
        if not sep or not name:
            raise SystemExit(f"query_stages: --option {item!r} is not NAME=VALUE: e.g. --option lookalike_ratio=1.1")
        options[name] = yaml.safe_load(value)
    for need in (args.folder / "gallery", args.folder / "truth.jsonl"):
        if not need.exists():
            raise SystemExit(f"query_stages: {need} not found: pass a folder with gallery/ and truth.jsonl "
                             "(a matl.unseen condition folder or a catalogue size's, e.g. <out>/n10000)")
    threshold = None if args.threshold is None else (args.threshold if args.threshold == "auto"
                                                     else float(args.threshold))
    rec = Recognizer.pretrained(refine=True, threshold=threshold, flow_pose=args.flow_pose, **options)
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
    timer = StageTimer()
    rec.time_stages(timer)
    try:  # the first --warmup calls (the first files again) untimed, then every file once, one thread
        parts = stage_query_ms(rec.predict, images[:args.warmup] + images, timer, args.warmup, threads=1)
    finally:
        rec.time_stages(None)
    stages = dict(parts["stages_ms"])
    other = stages.pop("other")
    calls = [{"file": file.name, "ms": round(call["ms"], 2),
              "stages": {k: round(v, 2) for k, v in call["stages"].items()},
              "other": round(call["ms"] - sum(call["stages"].values()), 2)}
             for file, call in zip(files, parts["per_call"], strict=True)]
    print(json.dumps({
        "folder": str(args.folder), "gallery_planes": len(rec.planes), "options": options,
        "enrol_s": round(enrol_s, 1), "queries": len(calls),
        "median_ms": round(parts["call_ms_median"], 2), "mean_ms": round(parts["call_ms"], 2),
        "stage_mean_ms": {k: round(v, 2) for k, v in sorted(stages.items())},
        "other_mean_ms": round(other, 2),
        "calls": sorted(calls, key=lambda c: c["ms"])}))


if __name__ == "__main__":
    main()
