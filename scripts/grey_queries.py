"""Grey crops of colour products: matched against the colour gallery, or against its grey twins (docs/decisions.md).

    OMP_NUM_THREADS=1 python scripts/grey_queries.py --out runs/grey_queries

Eight of scikit-image's bundled photos are the products (160 x 120 gallery images), three crops of each are the
queries (turned by up to 30 degrees, shrunk to 0.6-0.8, a little perspective, on black), as colour and as grey
(OpenCV's RGB -> grey). The shipped model (``Recognizer.pretrained()``, its defaults) answers: the colour crops
against the colour gallery; the grey crops as ``Recognizer.predict`` answers them (against the grey twins of the
planes); and the grey crops against the colour gallery itself (what a grey crop met before). Prints the recognised
and the known (not answered unknown) counts of each.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import cv2
import numpy as np

PRODUCTS = ("astronaut", "coffee", "chelsea", "rocket", "immunohistochemistry", "hubble_deep_field", "retina", "cat")


def main() -> None:
    from skimage import data

    from matl import Recognizer

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("runs/grey_queries"))
    args = parser.parse_args()
    gallery, queries = args.out / "gallery", args.out / "queries"
    rng = np.random.default_rng(1)
    for name in PRODUCTS:
        image = cv2.resize(getattr(data, name)()[..., :3], (160, 120), interpolation=cv2.INTER_AREA)
        (gallery / name).mkdir(parents=True, exist_ok=True)
        queries.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(gallery / name / "front.png"), image[..., ::-1])
        for j in range(3):
            angle, scale = math.radians(rng.uniform(-30, 30)), rng.uniform(0.6, 0.8)
            centre = np.array([[1, 0, -79.5], [0, 1, -59.5], [0, 0, 1]])
            turn = np.array([[scale * math.cos(angle), -scale * math.sin(angle), 0],
                             [scale * math.sin(angle), scale * math.cos(angle), 0], [*rng.uniform(-5e-4, 5e-4, 2), 1]])
            H = np.array([[1, 0, 75], [0, 1, 65], [0, 0, 1]]) @ turn @ centre
            cv2.imwrite(str(queries / f"{name}_{j}.png"), cv2.warpPerspective(image[..., ::-1], H, (150, 130)))
    recognizer = Recognizer.pretrained().enrol(gallery, cache=False)
    counts = {case: {"recognised": 0, "known": 0} for case in ("colour", "grey", "grey_vs_colour_gallery")}
    files = sorted(queries.iterdir())
    for path in files:
        truth = path.stem.rsplit("_", 1)[0]
        bgr = cv2.imread(str(path))
        grey = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
        answers = {"colour": recognizer.predict(bgr[..., ::-1].copy()), "grey": recognizer.predict(grey),
                   "grey_vs_colour_gallery": recognizer._predict_arrays(  # without the grey twins
                       [np.repeat(grey[..., None], 3, -1).astype(np.float32) / 255.0])[0][0]}
        for case, match in answers.items():
            counts[case]["recognised"] += match.object == truth
            counts[case]["known"] += match.known
    print(json.dumps({"queries": len(files), **counts}))


if __name__ == "__main__":
    main()
