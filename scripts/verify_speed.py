"""Milliseconds of one pose verification call, the CPU path against the torch reference (docs/speed.md).

    python scripts/verify_speed.py --rounds 300

``matl.inference.verify.verification_distance`` (``statistic=patches``, a visibility, blur 1 px) on CPU tensors
blurs with OpenCV, erodes the anchor's plane with OpenCV and sums the patches in one numba pass; the torch
reference (what runs on a GPU tensor) pads and convolves, pools and erodes in torch. Both run here on the same
inputs, one thread, in alternating rounds (one call of each per round), at a batch of 1 and of 8: textured
100 px anchors with a plane of 60 px, queries warped from them by poses near the identity under a random
visibility. Prints one JSON line per batch size: the median milliseconds of each path and their ratio, and the
largest difference between their distances.
"""

from __future__ import annotations

import argparse
import functools
import json
import time
from contextlib import contextmanager

import cv2
import numpy as np
import torch

from matl.inference import verify

S = 100


def cases(batch: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """``batch`` queries ``(B, 3, S, S)``, poses ``(B, 3, 3)``, anchors ``(B, 3, S, S)`` and visibilities."""
    rng = np.random.default_rng(seed)
    anchors = np.zeros((batch, 3, S, S), np.float32)
    for i in range(batch):  # smooth texture on a centred plane, zero around it
        texture = cv2.resize(rng.random((12, 12, 3)).astype(np.float32), (60, 60), interpolation=cv2.INTER_CUBIC)
        anchors[i, :, 20:80, 20:80] = np.clip(texture, 0.05, 1.0).transpose(2, 0, 1)
    poses = np.repeat(np.eye(3)[None], batch, 0)
    poses[:, :2, 2] += rng.uniform(-1.5, 1.5, (batch, 2))
    poses[:, :2, :2] += rng.uniform(-0.02, 0.02, (batch, 2, 2))
    queries = np.stack([cv2.warpPerspective(a.transpose(1, 2, 0), p, (S, S)).transpose(2, 0, 1)
                        for a, p in zip(anchors, poses, strict=True)])
    visibility = np.ones((batch, 1, S, S), np.float32)
    visibility[:, :, :, int(rng.integers(50, 80)):] = 0.0  # an occluder over the right part
    return (torch.from_numpy(queries), torch.from_numpy(poses), torch.from_numpy(anchors),
            torch.from_numpy(visibility))


@contextmanager
def torch_reference():
    """``verify``'s torch reference path for the calls inside (blur, erosion and patch sums in torch)."""
    saved = verify.gaussian_blur, verify.anchor_foreground, verify._cell_sums
    verify.gaussian_blur, verify.anchor_foreground = verify._gaussian_blur_torch, verify._anchor_foreground_torch
    verify._cell_sums = lambda a, b, w, cells: saved[2](a, b, w, cells, torch_only=True)
    try:
        yield
    finally:
        verify.gaussian_blur, verify.anchor_foreground, verify._cell_sums = saved


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=300)
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 8])
    args = parser.parse_args()
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    for batch in args.batches:
        queries, poses, anchors, visibility = cases(batch)
        call = functools.partial(verify.verification_distance, queries, poses, anchors, 1.0, visibility=visibility,
                                 statistic="patches")

        fast = call()
        with torch_reference():
            reference = call()
        times: dict[str, list[float]] = {"cpu_path": [], "torch_reference": []}
        for _ in range(args.rounds):
            start = time.perf_counter()
            call()
            times["cpu_path"].append(time.perf_counter() - start)
            with torch_reference():
                start = time.perf_counter()
                call()
                times["torch_reference"].append(time.perf_counter() - start)
        ms = {k: round(1e3 * float(np.median(v)), 3) for k, v in times.items()}
        print(json.dumps({"batch": batch, "ms": ms, "ratio": round(ms["torch_reference"] / ms["cpu_path"], 2),
                          "max_difference": float((fast - reference).abs().max())}))


if __name__ == "__main__":
    main()
