"""How long a new process takes to answer its first query from a saved gallery (docs/speed.md).

    OMP_NUM_THREADS=1 python scripts/first_query_time.py --planes 20 --out runs/first_query

1. Writes ``--planes`` product images (textured art, 160 x 120) into ``<out>/gallery/<object>/front.png`` and a
   query of one of them (turned, shrunk, on a black background), enrols them with the shipped model
   (``Recognizer.pretrained()``, its defaults: open set ``threshold=auto``) and saves the gallery
   (``Recognizer.save``: canonical images, features and the open-set calibration).
2. In a new Python process for each case, times: the imports, the model (``Recognizer.pretrained()``), the saved
   gallery (``load``), the first query and a second one; ``calibration_kept=false`` drops the saved calibration
   after ``load`` (what every process did before the calibration was saved with the gallery).

Prints one JSON line per case and writes ``<out>/first_query.json``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]


def product_art(seed: int, height: int = 120, width: int = 160) -> np.ndarray:
    """A product's print: smooth colour patterns and a few bars of text-like stripes, uint8 RGB."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:height, 0:width].astype(np.float64)
    channels = []
    for _ in range(3):
        pattern = sum(np.sin(2 * np.pi * (rng.uniform(0.5, 3) * x / width + rng.uniform(0.5, 3) * y / height)
                             + rng.uniform(0, 2 * np.pi)) for _ in range(3))
        channels.append(0.5 + 0.15 * pattern)
    art = np.stack(channels, -1)
    for _ in range(4):  # stripes: the edges a product's text gives
        top, left = int(rng.integers(5, height - 20)), int(rng.integers(5, width - 60))
        art[top:top + 8, left:left + int(rng.integers(20, 55))] = rng.uniform(0, 1, 3)
    return (np.clip(art, 0, 1) * 255).round().astype(np.uint8)


def query_of(art: np.ndarray, degrees: float = 20.0, scale: float = 0.7) -> np.ndarray:
    """``art`` turned and shrunk about its centre onto a black frame of its own size."""
    h, w = art.shape[:2]
    c, s = scale * math.cos(math.radians(degrees)), scale * math.sin(math.radians(degrees))
    centre = np.array([[1, 0, -(w - 1) / 2], [0, 1, -(h - 1) / 2], [0, 0, 1]])
    H = np.linalg.inv(centre) @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ centre
    return cv2.warpPerspective(art, H, (w, h), flags=cv2.INTER_LINEAR)


def prepare(out: Path, planes: int) -> tuple[Path, Path]:
    from matl import Recognizer

    gallery = out / "gallery"
    for k in range(planes):
        (gallery / f"product_{k:02d}").mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(gallery / f"product_{k:02d}" / "front.png"), product_art(k)[..., ::-1])
    query = out / "query.png"
    cv2.imwrite(str(query), query_of(product_art(planes // 2))[..., ::-1])
    start = time.perf_counter()
    recognizer = Recognizer.pretrained().enrol(gallery, cache=False)
    recognizer.save(out / "gallery.pt")  # calibrates (threshold=auto) and keeps it
    print(f"enrolled and saved {planes} planes in {time.perf_counter() - start:.1f} s "
          f"({(out / 'gallery.pt').stat().st_size / 1e6:.2f} MB)", file=sys.stderr)
    return out / "gallery.pt", query


def measure(saved: str, query: str, calibration_kept: bool) -> dict[str, float | bool | str | None]:
    """Run in the new process: each step's seconds."""
    times: dict[str, float | bool | str | None] = {"calibration_kept": calibration_kept}
    start = time.perf_counter()
    from matl import Recognizer

    times["import_s"] = time.perf_counter() - start
    start = time.perf_counter()
    recognizer = Recognizer.pretrained()
    times["model_s"] = time.perf_counter() - start
    start = time.perf_counter()
    recognizer.load(saved)
    if not calibration_kept:
        recognizer._stored_calibration = None  # as if save() had not kept it
    times["load_s"] = time.perf_counter() - start
    image = cv2.imread(query)[..., ::-1].copy()
    start = time.perf_counter()
    match = recognizer.predict(image)
    times["first_query_s"] = time.perf_counter() - start
    start = time.perf_counter()
    recognizer.predict(image)
    times["second_query_s"] = time.perf_counter() - start
    times["load_and_first_query_s"] = float(times["load_s"]) + float(times["first_query_s"])
    times["answer"] = match.object
    return times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--planes", type=int, default=20)
    parser.add_argument("--out", type=Path, default=Path("runs/first_query"))
    parser.add_argument("--child", nargs=3, metavar=("SAVED", "QUERY", "KEPT"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(measure(args.child[0], args.child[1], args.child[2] == "true")))
        return
    args.out.mkdir(parents=True, exist_ok=True)
    saved, query = prepare(args.out, args.planes)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])])}
    results = []
    for kept in ("true", "false"):
        proc = subprocess.run([sys.executable, __file__, "--child", str(saved), str(query), kept], env=env,
                              capture_output=True, text=True, check=True)
        results.append(json.loads(proc.stdout.strip().splitlines()[-1]))
        print(json.dumps(results[-1]))
    (args.out / "first_query.json").write_text(json.dumps({"planes": args.planes, "cases": results}, indent=2) + "\n")


if __name__ == "__main__":
    main()
