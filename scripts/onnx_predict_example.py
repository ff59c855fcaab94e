"""Recognition and pose from ``python -m matl.export format=onnx``'s files with numpy, OpenCV and onnxruntime only.

    python -m matl.export ckpt=pretrained format=onnx out=exported
    python scripts/onnx_predict_example.py exported my_products/ crop1.png crop2.png

prints one JSON line per query: the nearest ``object`` / ``plane``, the anchor, the feature distance and
``H``, the pose in the files' own pixels (gallery image -> query image), as ``matl.predict`` gives it:
``cv2.warpPerspective(gallery_image, np.array(H), (w, h))`` lands on the query. The gallery folder is
``<gallery>/<object>/<plane>.png``; queries are crops whose background is black (or transparent: the alpha
is the mask). Everything ``export.json`` describes is here: the resize into the model frame, the anchors,
the search, the alignment stage (``align_net.onnx``) and the mapping back to the files' pixels. What the
library adds on top (GrabCut for crops with a background, verification and the open set, refinement)
is not; with ``foreground="none", verify_top_k=0, threshold=None`` ``matl.Recognizer`` answers the same
(``tests/scripts/test_onnx_predict_example.py`` checks the poses agree to < 0.1 px median). The lines are
``matl.score``'s predictions; ``--without-align`` leaves the alignment stage out (s()'s pose alone).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import cv2
import numpy as np
import onnxruntime as ort


def read_rgb(path: str | Path) -> np.ndarray:
    """An 8-bit image file as float32 RGB ``(h, w, 3)`` in [0, 1]; an alpha channel masks it (transparent -> 0)."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise SystemExit(f"error: {path}: not an image")
    if image.ndim == 2:
        image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    x = image.astype(np.float32) / 255.0
    rgb = x[..., 2::-1]  # BGR(A) -> RGB
    if x.shape[2] == 4:
        rgb = rgb * x[..., 3:4]
    return np.ascontiguousarray(rgb)


def resize_weights(size_in: int, size_out: int) -> np.ndarray:
    """``(size_out, size_in)`` weights of an antialiased bilinear resize (a triangle filter widened by the
    shrink factor, half-pixel centres, renormalised at the borders): export.json's ``to_model_frame``."""
    scale = size_in / size_out
    support = max(scale, 1.0)
    weights = np.zeros((size_out, size_in), np.float64)
    for i in range(size_out):
        centre = scale * (i + 0.5)
        lo, hi = max(int(centre - support + 0.5), 0), min(int(centre + support + 0.5), size_in)
        j = np.arange(lo, hi)
        w = np.maximum(0.0, 1.0 - np.abs((j - centre + 0.5) / support))
        weights[i, lo:hi] = w / w.sum()
    return weights


def fit_to_model(rgb: np.ndarray, size: int, fill: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """The ``(3, S, S)`` model-frame image and ``model_H_file`` (file pixel -> model pixel), as export.json says."""
    h, w = rgb.shape[:2]
    s = fill * size / max(h, w)
    new_w, new_h = min(size, max(1, round(w * s))), min(size, max(1, round(h * s)))
    left, top = (size - new_w) // 2, (size - new_h) // 2
    wy, wx = resize_weights(h, new_h), resize_weights(w, new_w)
    resized = np.einsum("yh,hwc,xw->cyx", wy, rgb.astype(np.float64), wx).clip(0.0, 1.0)
    out = np.zeros((3, size, size), np.float32)
    out[:, top:top + new_h, left:left + new_w] = resized
    sx, sy = new_w / w, new_h / h
    model_H_file = np.array([[sx, 0.0, 0.5 * sx - 0.5 + left], [0.0, sy, 0.5 * sy - 0.5 + top], [0.0, 0.0, 1.0]])
    return out, model_H_file


class OnnxRecognizer:
    """The gallery of a folder and the query path of ``matl.export format=onnx``'s files."""

    def __init__(self, export_dir: str | Path, gallery: str | Path, gallery_fill: float = 1.0,
                 query_fill: float = 1.0) -> None:
        export_dir = Path(export_dir)
        info = json.loads((export_dir / "export.json").read_text())
        self.size, self.query_fill = int(info["image_size"]), float(query_fill)
        self.anchor_H_canon = np.array(info["anchor_k_H_canon"], np.float64)  # (N, 3, 3)

        def session(name: str) -> ort.InferenceSession | None:
            path = export_dir / f"{name}.onnx"
            return ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]) if path.is_file() else None

        self.gallery_net, self.query_net, self.align_net = (session(n) for n in ("gallery_net", "query_net",
                                                                                  "align_net"))
        self.labels, self.gallery_files, self.gallery_H_file, anchors = [], [], [], []
        for path in sorted(Path(gallery).glob("*/*")):
            if path.suffix.lower() not in (".png", ".jpg", ".jpeg") or path.name.startswith("."):
                continue
            canon, model_H_file = fit_to_model(read_rgb(path), self.size, gallery_fill)
            canon = np.round(canon * 255.0) / 255.0  # the gallery is kept as 8-bit canonical images
            for H in self.anchor_H_canon:  # anchor k: the canonical image rotated by k * 360 / N degrees
                warped = cv2.warpPerspective(canon.transpose(1, 2, 0), H, (self.size, self.size),
                                             flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
                anchors.append(warped.transpose(2, 0, 1))
            self.labels.append((path.parent.name, path.stem))
            self.gallery_files.append(str(path))
            self.gallery_H_file.append(model_H_file)
        self.anchors = np.stack(anchors).astype(np.float32)                     # (P * N, 3, S, S), plane-major
        self.features = self.gallery_net.run(None, {"images": self.anchors})[0]  # (P * N, D)

    def predict(self, image: str | Path | np.ndarray) -> dict:
        """The nearest plane and its pose in the files' pixels for one query (a path or float RGB in [0, 1])."""
        rgb = read_rgb(image) if isinstance(image, (str, Path)) else image
        query, query_H_file = fit_to_model(rgb, self.size, self.query_fill)
        images = query[None]
        embedding, query_H_anchor, degenerate, warped = self.query_net.run(None, {"images": images})
        distances = np.linalg.norm(self.features - embedding, axis=1)
        g = int(np.argmin(distances))
        plane, anchor = divmod(g, len(self.anchor_H_canon))
        if self.align_net is not None:  # the alignment stage, against the anchor found
            query_H_anchor = self.align_net.run(None, {"images": images, "anchors": self.anchors[g:g + 1],
                                                       "stn_query_H_anchor": query_H_anchor, "warped": warped})[0]
        query_H_canon = query_H_anchor[0].astype(np.float64) @ self.anchor_H_canon[anchor]
        query_H_canon /= query_H_canon[2, 2]
        H = np.linalg.solve(query_H_file, query_H_canon @ self.gallery_H_file[plane])  # gallery file -> query file
        obj, name = self.labels[plane]
        return {"object": obj, "plane": name, "anchor": anchor, "distance": float(distances[g]),
                "degenerate": bool(degenerate[0]), "H": (H / H[2, 2]).tolist(),
                "gallery_image": self.gallery_files[plane]}


def main(argv: list[str]) -> None:
    without_align = "--without-align" in argv  # s()'s pose alone: what an export without align_net would answer
    argv = [a for a in argv if a != "--without-align"]
    if len(argv) < 3:
        raise SystemExit("usage: python scripts/onnx_predict_example.py [--without-align] <export dir> <gallery dir> "
                         "<image>...")
    recognizer = OnnxRecognizer(argv[0], argv[1])
    if without_align:
        recognizer.align_net = None
    for image in argv[2:]:
        print(json.dumps({"image": image, **recognizer.predict(image)}))


if __name__ == "__main__":
    main(sys.argv[1:])
