"""Where the pose of a partly hidden product goes wrong, and what the flow pose recovers (docs/decisions.md, "the flow
pose").

    python scripts/flow_pose_diagnostics.py <unseen out>/occluded [--ckpt pretrained] [--true-mask]
    python scripts/flow_pose_diagnostics.py <unseen out>/<condition> --above 0 0.03 0.05
    python scripts/flow_pose_diagnostics.py <unseen leave_out=0.5 out>/<condition> --verifies none 0.05 0.03

For the RGB queries of a ``matl.unseen`` condition folder (``truth.jsonl``, ``gallery/``, ``queries/``) whose answer
(``refine=true``, ``flow_pose=none``) has the right product and plane, in model px (corner error, 100 px frame):

* ``answer``: the answer's pose within 5 px;
* ``flow``: :class:`matl.inference.flow_pose.FlowPose` (default settings) from the answer's pose;
* ``refined from the truth``: the fast refinement started at the true pose (and 7.8 px off it), as the
  recognizer's verification refines a candidate, with the query's visibility;

each for every such answer and for those that do not verify. ``--true-mask``: the queries as RGBA with the truth's
visible mask (``mask_file``) instead of the foreground step's.

``--above``: instead, the recognizer with ``flow_pose=FlowPose(mode="always", above=a)`` for each ``a`` given, its
closed-set rec_acc and ``pose_acc_5px`` over the folder's RGB queries and its median milliseconds a query.

``--verifies``: on a folder of ``matl.unseen leave_out=...`` (``truth.jsonl`` the enrolled products' queries,
``truth_left_out.jsonl`` the others'), the open-set recognizer (``threshold=auto``, the gallery's own calibration)
with ``flow_pose=FlowPose(mode="always", verifies=v)`` for each ``v`` (``none``: None): the share of enrolled
queries answered with their product and of left-out ones answered unknown.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from matl import Recognizer
from matl.data.image_files import fit_to_model
from matl.evaluation.score import to_model_frame
from matl.geometry import corner_error_px
from matl.inference.flow_pose import FlowPose
from matl.inference.foreground import mask_query
from matl.inference.images import _query_visibility


def shifted(tx: float, ty: float) -> torch.Tensor:
    """A translation of the anchor frame by ``(tx, ty)`` px."""
    return torch.tensor([[1.0, 0.0, tx], [0.0, 1.0, ty], [0.0, 0.0, 1.0]], dtype=torch.float64)


def true_pose(folder: Path, truth: dict, path: Path, rec: Recognizer, sizes: dict) -> torch.Tensor:
    """The truth's model-frame ``query_H_canon`` of a query file."""
    return to_model_frame(np.array(truth["H"]), folder / truth["gallery_image"], path, rec.image_size,
                          rec.gallery_fill, rec.query_fill, sizes)


def sweep_above(folder: Path, ckpt: str, values: list[float]) -> None:
    """rec_acc, pose_acc_5px and the median ms of the recognizer with each ``above``, on the RGB queries."""
    truths = [json.loads(line) for line in (folder / "truth.jsonl").read_text().splitlines()]
    truths = [t for t in truths if not t.get("rgba")]
    for above in values:
        options = {"refine": True, "threshold": None, "flow_pose": FlowPose(mode="always", above=above)}
        rec = Recognizer.from_checkpoint(ckpt, **options).enrol(folder / "gallery", cache=False)
        right, within, times, sizes = 0, 0, [], {}
        for truth in truths:
            path = folder / truth["image"]
            start = time.perf_counter()
            match = rec.predict(str(path))
            times.append(1e3 * (time.perf_counter() - start))
            if match.nearest_object != truth["object"] or match.H is None:
                continue
            right += 1
            estimate = to_model_frame(match.H, Path(match.gallery_image), path, rec.image_size, rec.gallery_fill,
                                      rec.query_fill, sizes)
            error = corner_error_px(estimate[None], true_pose(folder, truth, path, rec, sizes)[None],
                                    (rec.image_size, rec.image_size))
            within += int(float(error[0]) <= 5.0)
        n = max(len(truths), 1)
        print(f"above={above}: rec_acc {right / n:.3f}, pose_acc_5px {within / n:.3f}, median "
              f"{np.median(times[1:] or times):.1f} ms a query ({len(truths)} RGB queries)")


def sweep_verifies(folder: Path, ckpt: str, values: list[str]) -> None:
    """Enrolled queries answered known and right, left-out ones answered unknown, for each ``verifies``."""
    enrolled = [json.loads(line) for line in (folder / "truth.jsonl").read_text().splitlines()]
    left_out = [json.loads(line) for line in (folder / "truth_left_out.jsonl").read_text().splitlines()]
    rec = Recognizer.from_checkpoint(ckpt)
    rec.enrol(folder / "gallery")
    for value in values:
        rec.flow_pose = FlowPose(mode="always", verifies=None if value == "none" else float(value))
        answers = rec.predict([str(folder / t["image"]) for t in enrolled + left_out])  # one call: batched
        known = sum(a.object == t["object"] for a, t in zip(answers[:len(enrolled)], enrolled, strict=True))
        unknown = sum(a.object is None for a in answers[len(enrolled):])
        print(f"verifies={value}: enrolled answered right and known {known / max(len(enrolled), 1):.3f}, left-out "
              f"answered unknown {unknown / max(len(left_out), 1):.3f} ({len(enrolled)} / {len(left_out)} queries)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folder", type=Path)
    parser.add_argument("--ckpt", default="pretrained", help="pretrained, pretrained_fast (the shipped models) or a "
                        "checkpoint")
    parser.add_argument("--true-mask", action="store_true")
    parser.add_argument("--above", type=float, nargs="+", help="sweep FlowPose.above instead")
    parser.add_argument("--verifies", nargs="+", help="sweep FlowPose.verifies (none or a distance) instead")
    args = parser.parse_args()
    if args.above:
        sweep_above(args.folder, args.ckpt, args.above)
        return
    if args.verifies:
        sweep_verifies(args.folder, args.ckpt, args.verifies)
        return
    options = {"refine": True, "threshold": None, "flow_pose": "none"}
    rec = Recognizer.from_checkpoint(args.ckpt, **options)
    rec.enrol(args.folder / "gallery", cache=False)
    _, gallery = rec._build()
    refiner, templates = rec._candidate_refiner()
    flow = FlowPose(mode="always")
    size, sizes, rows = rec.image_size, {}, []
    for line in (args.folder / "truth.jsonl").read_text().splitlines():
        truth = json.loads(line)
        if truth.get("rgba"):
            continue
        path = args.folder / truth["image"]
        image = np.asarray(Image.open(path).convert("RGB"), np.float32) / 255.0
        if args.true_mask:
            mask = np.asarray(Image.open(args.folder / truth["mask_file"]).convert("L"), np.float32) / 255.0
            image = np.dstack([image, mask])
        matches, pred, queries = rec.predict_details([image])
        match = matches[0]
        if match.nearest_object != truth["object"] or match.nearest_plane != truth["plane"]:
            continue
        prepared = [mask_query(rec.foreground, image)]
        visibility = _query_visibility(prepared, size, rec.query_fill, torch.device("cpu"))
        model_H_file = fit_to_model(prepared[0][0], size, rec.query_fill)[1].model_H_file
        upscale = float(torch.sqrt(model_H_file[0, 0] * model_H_file[1, 1]))
        g = int(pred.gallery_index[0])
        anchor_H_canon = gallery.anchor_H_canon[g].double()
        true_canon = true_pose(args.folder, truth, path, rec, sizes)
        true_anchor = true_canon @ torch.linalg.inv(anchor_H_canon)

        def error(query_H_anchor: torch.Tensor, true_canon: torch.Tensor = true_canon,
                  anchor_H_canon: torch.Tensor = anchor_H_canon) -> float:
            pose = query_H_anchor.double() @ anchor_H_canon
            return float(corner_error_px((pose / pose[2, 2])[None], true_canon[None], (size, size))[0])

        answer = pred.query_H_anchor[0].double()
        flowed = flow.pose(queries[0], gallery.images[g], answer, None if visibility is None else visibility[0])
        starts = torch.stack([true_anchor, true_anchor @ shifted(-6.0, 5.0)])
        refined = refiner(queries.expand(2, -1, -1, -1), torch.tensor([g, g]), starts, templates,
                          visibility=None if visibility is None else visibility.expand(2, -1, -1, -1),
                          upscale=torch.tensor([upscale, upscale])).query_H_anchor
        rows.append((not match.verification <= rec.verify_max, error(answer),
                     error(answer if flowed is None else flowed), error(refined[0]), error(refined[1])))
    table = np.array(rows, dtype=np.float64).reshape(-1, 5)
    for name, keep in (("right product and plane", np.ones(len(table), bool)), ("not verified", table[:, 0] > 0)):
        part = table[keep]
        within = [int((part[:, k] <= 5.0).sum()) for k in range(1, 5)]
        print(f"{name}: {len(part)}; within 5 px: answer {within[0]}, flow {within[1]}, refined from the truth "
              f"{within[2]}, refined from 7.8 px off it {within[3]}; median px "
              + ", ".join(f"{np.median(part[:, k]):.1f}" if len(part) else "nan" for k in range(1, 5)))
    if not math.isfinite(float(table[:, 1:].sum())):
        print("note: some poses were not finite")


if __name__ == "__main__":
    main()
