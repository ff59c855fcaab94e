"""Every bad input matl is tested against, in one table (``CASES``), one human-readable id per case.

A case either must *fail cleanly* (``error=`` a substring of the expected message: for a command line,
exit status 2, exactly one ``error:`` line and no traceback; in-process, a one-line :class:`MatlError`)
or must *work* (``check=`` inspects the result: grey and RGBA images, a corrupt cache, ...).
docs/reliability.md states ``len(CASES)``; ``test_docs_state_the_count`` keeps it honest.

Config cases run ``python -m matl.<entry>`` in a subprocess: validation happens before any data or
model is built (and, for train, before torch and Lightning are imported), so each takes about a second.
"""

from __future__ import annotations

import json
import os
import re
import struct
import subprocess
import sys
import warnings
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import hydra
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf, open_dict
from PIL import Image

from matl.data.canonical import CanonicalSet, cache_path, load_canonical
from matl.data.image_files import fit_to_model, load_image_file
from matl.evaluation.evaluate import evaluate
from matl.inference.files import predict
from matl.training.fit import train
from matl.utils.config import SYNTHETIC_CATALOGS
from matl.utils.errors import MatlError, group_options
from tests.conftest import TINY, compose_config

REPO = Path(__file__).resolve().parents[1]


# ---------------------------------------------------------------------------------- context
class Ctx:
    """What a case needs: a fresh folder, the shared canonical cache, tiny fabricated checkpoints."""

    def __init__(self, tmp: Path, cache_dir: Path, shared: dict[str, Any]) -> None:
        self.tmp, self.cache_dir, self.shared = tmp, cache_dir, shared

    def checkpoint(self, size: int = 32, model: str = "matl", weights_only_file: bool = False) -> Path:
        """An untrained matl checkpoint at ``size`` px, made once per session (what matl.train writes,
        minus training)."""
        key = f"{model}{size}{'w' if weights_only_file else ''}"
        if key not in self.shared:
            folder = self.shared["root"] / key
            cfg = train_cfg(folder, self.cache_dir, [f"data.image_size={size}", f"model={model}"])
            module = hydra.utils.instantiate(cfg.model)
            module.run_config = OmegaConf.to_container(cfg, resolve=True)
            ckpt: dict[str, Any] = {"state_dict": module.state_dict(), "epoch": 0, "global_step": 0}
            if not weights_only_file:
                ckpt.update(loops={}, optimizer_states=[], lr_schedulers=[])
            module.on_save_checkpoint(ckpt)
            folder.mkdir(parents=True, exist_ok=True)
            torch.save(ckpt, folder / "model.ckpt")
            self.shared[key] = folder / "model.ckpt"
        return self.shared[key]

    def run32(self) -> Path:
        """A run folder as matl.train leaves it (.hydra/config.yaml), 32 px."""
        if "run32" not in self.shared:
            run = self.shared["root"] / "run32"
            (run / ".hydra").mkdir(parents=True, exist_ok=True)
            OmegaConf.save(train_cfg(run, self.cache_dir), run / ".hydra" / "config.yaml")
            self.shared["run32"] = run
        return self.shared["run32"]


def train_cfg(out: Path, cache_dir: Path, extra: list[str] | None = None):
    return compose_config("train", [*TINY, f"paths.cache_dir={cache_dir}", "logger=none", *(extra or [])], out)


def predict_cfg(ctx: Ctx, ckpt: Path, gallery: Path, images: Path, extra: list[str] | None = None):
    cfg = compose_config("predict", [f"ckpt={ckpt}", f"gallery={gallery}", f"images={images}",
                                     f"out={ctx.tmp / 'out.jsonl'}", "cache=false", *(extra or [])], ctx.tmp / "p")
    return cfg


# ------------------------------------------------------------------------------- file makers
def png(path: Path, array: np.ndarray, mode: str | None = None) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(array, mode=mode).save(path)
    return path


def colour(h: int = 40, w: int = 50, seed: int = 0) -> np.ndarray:
    return (np.random.default_rng(seed).random((h, w, 3)) * 255).astype(np.uint8)


def good_gallery(root: Path) -> Path:
    for k, name in enumerate(("red_box", "green_can")):
        png(root / name / "front.png", colour(48, 64, k))
    return root


def zero_size_png(path: Path) -> Path:
    """A syntactically valid PNG whose header says 0 x 0 pixels."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 0, 0, 8, 2, 0, 0, 0))
                     + chunk(b"IDAT", zlib.compress(b"")) + chunk(b"IEND", b""))
    return path


def truncated_png(path: Path) -> Path:
    full = png(path.with_name("full.png"), colour(60, 80))
    path.write_bytes(full.read_bytes()[: full.stat().st_size // 2])
    return path


def palette_png(path: Path) -> Path:
    image = Image.fromarray((np.arange(40 * 50).reshape(40, 50) % 4).astype(np.uint8), mode="P")
    image.putpalette([255, 0, 0, 0, 255, 0, 0, 0, 255, 255, 255, 255])
    image.save(path, transparency=3)  # palette entry 3 (white) is transparent
    return path


class Exploit:
    """Pickles to a call of os.system: what a malicious checkpoint would hold."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


# ---------------------------------------------------------------------------------- the cases
@dataclass(frozen=True)
class Case:
    run: Callable[[Ctx], Any]                # performs the action (returns a CompletedProcess for a CLI case)
    error: str | None = None                 # the one-line error must contain this; None: the input must work
    check: Callable[[Any, Ctx], None] | None = None


def run_cli(ctx: Ctx, module: str, args: list[str]) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(REPO)}
    return subprocess.run([sys.executable, "-m", module, *args, f"hydra.run.dir={ctx.tmp / 'h'}"],
                          cwd=ctx.tmp, env=env, capture_output=True, text=True, timeout=300)


def cli(what: str, module: str, args: list[str], error: str):
    return pytest.param(Case(lambda ctx: run_cli(ctx, module, args), error), id=what)


def train_cli(what: str, args: list[str], error: str):
    return cli(what, "matl.train", args, error)


def call(what: str, run: Callable[[Ctx], Any], error: str | None = None,
         check: Callable[[Any, Ctx], None] | None = None):
    return pytest.param(Case(run, error, check), id=what)


def image(what: str, make: Callable[[Path], Path], error: str | None = None,
          check: Callable[[np.ndarray, Ctx], None] | None = None):
    def run(ctx: Ctx) -> np.ndarray:
        loaded = load_image_file(make(ctx.tmp / "in.png"))
        fit_to_model(loaded, 32)  # what predict and the gallery do next
        return loaded
    return pytest.param(Case(run, error, check), id=what)


# checks of inputs that must work
def rgb_in_unit_range(x: np.ndarray) -> None:
    assert x.ndim == 3 and x.shape[2] == 3 and x.dtype == np.float32 and x.min() >= 0.0 and x.max() <= 1.0


def grey_check(x: np.ndarray, ctx: Ctx) -> None:
    rgb_in_unit_range(x)
    assert np.array_equal(x[..., 0], x[..., 1]) and np.array_equal(x[..., 1], x[..., 2]) and x.std() > 0


def alpha_check(x: np.ndarray, ctx: Ctx) -> None:  # left half transparent -> background 0, right half kept
    rgb_in_unit_range(x)
    assert x[:, :25].max() == 0.0 and x[:, 25:].min() > 0.4


def sixteen_bit_check(x: np.ndarray, ctx: Ctx) -> None:
    rgb_in_unit_range(x)
    assert 0.45 < x.mean() < 0.55 and x.min() == 0.0 and x.max() == 1.0  # a ramp, not saturated white


def alpha_image(mode: str) -> Callable[[Path], Path]:
    def make(path: Path) -> Path:
        h, w = 30, 50
        alpha = np.zeros((h, w), np.uint8)
        alpha[:, 25:] = 255
        grey = np.full((h, w), 200, np.uint8)
        if mode == "LA":
            return png(path, np.dstack([grey, alpha]), "LA")
        return png(path, np.dstack([colour(h, w) // 2 + 120, alpha]), "RGBA")
    return make


def palette_check(x: np.ndarray, ctx: Ctx) -> None:
    rgb_in_unit_range(x)
    assert x[0, 3].max() == 0.0 and x[0, 0].tolist() == [1.0, 0.0, 0.0]  # transparent entry -> 0, red kept


def cmyk_jpeg(path: Path) -> Path:
    path = path.with_suffix(".jpg")
    Image.fromarray(colour()).convert("CMYK").save(path)
    return path


def sixteen_bit(path: Path) -> Path:
    import cv2
    cv2.imwrite(str(path), np.linspace(0, 65535, 40 * 64).reshape(40, 64).astype(np.uint16))
    return path


def predict_folder_with_bad_file(ctx: Ctx) -> dict[str, Any]:
    gallery = good_gallery(ctx.tmp / "gallery")
    queries = ctx.tmp / "queries"
    png(queries / "a_grey.png", colour(30, 40)[..., 0], "L")
    alpha_image("RGBA")(queries / "b_rgba.png")
    (queries / "c_broken.png").write_text("this is not an image")
    png(queries / "d_colour.png", colour(30, 40, 3))
    return predict(predict_cfg(ctx, ctx.checkpoint(), gallery, queries))


def predicted_the_good_files(summary: dict[str, Any], ctx: Ctx) -> None:
    assert summary["predicted"] == 3 and summary["skipped"] == 1
    records = [json.loads(line) for line in (ctx.tmp / "out.jsonl").read_text().splitlines()]
    assert sorted(Path(r["image"]).name for r in records) == ["a_grey.png", "b_rgba.png", "d_colour.png"]
    assert all(r["H"] is not None and all(np.isfinite(np.asarray(r["H"])).flat) for r in records)


def gallery_case(make: Callable[[Path], Path]) -> Callable[[Ctx], Any]:
    def run(ctx: Ctx) -> Any:
        queries = png(ctx.tmp / "q" / "q.png", colour())
        return predict(predict_cfg(ctx, ctx.checkpoint(), make(ctx.tmp / "gallery"), queries))
    return run


def unreadable_gallery(root: Path) -> Path:
    (root / "obj").mkdir(parents=True)
    (root / "obj" / "front.png").write_text("not a png")
    zero_size_png(root / "obj" / "back.png")
    return root


def loose_files_gallery(root: Path) -> Path:
    png(root / "front.png", colour())  # not inside an object folder
    return root


def predict_with_checkpoint(make: Callable[[Ctx], Path], extra: list[str] | None = None) -> Callable[[Ctx], Any]:
    def run(ctx: Ctx) -> Any:
        gallery = good_gallery(ctx.tmp / "gallery")
        queries = png(ctx.tmp / "q" / "q.png", colour())
        return predict(predict_cfg(ctx, make(ctx), gallery, queries, extra))
    return run


def predict_images(make: Callable[[Path], Path]) -> Callable[[Ctx], Any]:
    def run(ctx: Ctx) -> Any:
        return predict(predict_cfg(ctx, ctx.checkpoint(), good_gallery(ctx.tmp / "gallery"), make(ctx.tmp / "images")))
    return run


def text_checkpoint(ctx: Ctx) -> Path:
    (ctx.tmp / "t.ckpt").write_text("not a checkpoint")
    return ctx.tmp / "t.ckpt"


def exploit_checkpoint(ctx: Ctx) -> Any:
    marker = ctx.tmp / "pwned"
    torch.save({"state_dict": {}, "payload": Exploit(marker)}, ctx.tmp / "evil.ckpt")
    try:
        return predict_with_checkpoint(lambda c: c.tmp / "evil.ckpt")(ctx)
    finally:
        assert not marker.exists(), "loading the checkpoint ran its code"


def config_exploit(target: str) -> Callable[[Ctx], Any]:
    """A checkpoint whose *config* (not its pickle) names a function for Hydra to call."""
    def run(ctx: Ctx) -> Any:
        marker = ctx.tmp / "pwned"
        model = {"_target_": target, "command": f"touch {marker}", "path": str(marker), "payload": {}}
        torch.save({"state_dict": {}, "matl_image_size": 32, "matl_num_anchors": 4,
                    "matl_config": {"model": model, "data": {"image_size": 32}}}, ctx.tmp / "evil.ckpt")
        try:
            return predict_with_checkpoint(lambda c: c.tmp / "evil.ckpt")(ctx)
        finally:
            assert not marker.exists(), "building the checkpoint's model ran its code"
    return run


def plain_lightning_checkpoint(ctx: Ctx) -> Path:
    torch.save({"state_dict": {"w": torch.zeros(2)}, "epoch": 0}, ctx.tmp / "plain.ckpt")
    return ctx.tmp / "plain.ckpt"


def truncated_checkpoint(ctx: Ctx) -> Path:
    data = ctx.checkpoint().read_bytes()
    (ctx.tmp / "cut.ckpt").write_bytes(data[: len(data) // 3])
    return ctx.tmp / "cut.ckpt"


def eval_with(ckpt: Callable[[Ctx], Path | str]) -> Callable[[Ctx], Any]:
    def run(ctx: Ctx) -> Any:
        cfg = compose_config("eval", [f"run={ctx.run32()}", f"ckpt={ckpt(ctx)}"], ctx.tmp / "e")
        return evaluate(cfg, show_progress=False)
    return run


def resume_with(ckpt: Callable[[Ctx], Path], extra: list[str] | None = None) -> Callable[[Ctx], Any]:
    def run(ctx: Ctx) -> Any:
        cfg = train_cfg(ctx.tmp / "t", ctx.cache_dir, extra)
        with open_dict(cfg):
            cfg.ckpt_path = str(ckpt(ctx))
        return train(cfg)
    return run


def untextured_mesh_render(ctx: Ctx) -> subprocess.CompletedProcess:
    pytest.importorskip("matl.data.meshes", reason="mesh datasets not installed")
    import trimesh

    (ctx.tmp / "meshes").mkdir()
    trimesh.creation.box().export(ctx.tmp / "meshes" / "plain_box.obj")
    return run_cli(ctx, "matl.render", ["data=meshes", f"data.source.root={ctx.tmp / 'meshes'}", "data.image_size=32"])


def not_a_mesh(ctx: Ctx) -> Any:
    meshes = pytest.importorskip("matl.data.meshes.io", reason="mesh datasets not installed")
    (ctx.tmp / "broken.obj").write_text("this is not\nv 1 2\nf 1 2 9\n")
    return meshes.load_mesh_parts(ctx.tmp / "broken.obj")


class TinySource:
    """A two-plane canonical source for the cache cases."""

    def cache_key(self) -> dict[str, Any]:
        return {"tiny": 1}

    def build(self, image_size: int) -> CanonicalSet:
        images = np.zeros((2, image_size, image_size, 3), np.uint8)
        images[:, 4:-4, 4:-4] = 200
        return CanonicalSet(images, images[..., 0] > 0, np.array([0, 1]), ["front", "front"], ["a", "b"],
                            ["planar", "planar"])


def corrupt_cache(ctx: Ctx) -> tuple[CanonicalSet, list[str]]:
    load_canonical(TinySource(), 16, ctx.tmp)
    cache_path(TinySource(), 16, ctx.tmp).write_bytes(b"PK\x03\x04 torn zip")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rebuilt = load_canonical(TinySource(), 16, ctx.tmp)
    return rebuilt, [str(w.message) for w in caught]


def rebuilt_with_warning(result: tuple[CanonicalSet, list[str]], ctx: Ctx) -> None:
    rebuilt, messages = result
    assert rebuilt.num_planes == 2 and any("unreadable" in m and "rebuilding" in m for m in messages)
    assert load_canonical(TinySource(), 16, ctx.tmp).num_planes == 2  # and the rebuilt file is good


# ------------------------------------------------------------------- outputs a user named (out=, viz_dir=)
EARLIER = '{"image": "earlier.png", "object": "tea"}\n' * 100  # a complete earlier result


def earlier_result(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(EARLIER)
    return path


def read_only_folder(ctx: Ctx) -> Path:
    """A folder nothing can be written in: a 0o555 folder, or (as root, who may write there anyway) a folder
    of a read-only filesystem."""
    folder = ctx.tmp / "read_only"
    folder.mkdir()
    folder.chmod(0o555)
    try:
        (folder / "probe").write_text("")
    except OSError:
        return folder
    (folder / "probe").unlink()
    folder.chmod(0o755)
    for candidate in (Path("/sys"), Path("/proc")):
        try:
            (candidate / "matl_probe").write_text("")
        except OSError:
            return candidate
    pytest.skip("no read-only folder on this machine (root may write anywhere here)")


def predict_cli_out(out: Callable[[Ctx], Path], extra: list[str] | Callable[[Ctx], list[str]] | None = None,
                    keeps: Callable[[Ctx], Path] | None = None) -> Callable[[Ctx], Any]:
    """``python -m matl.predict`` with a good gallery and query and ``out=`` (then ``keeps``' file must be intact)."""
    def run(ctx: Ctx) -> subprocess.CompletedProcess:
        gallery = good_gallery(ctx.tmp / "gallery")
        queries = png(ctx.tmp / "q" / "q.png", colour())
        more = extra(ctx) if callable(extra) else extra or []
        result = run_cli(ctx, "matl.predict", [f"ckpt={ctx.checkpoint()}", f"gallery={gallery}", f"images={queries}",
                                               f"out={out(ctx)}", "cache=false", *more])
        if keeps is not None:
            assert keeps(ctx).read_text() == EARLIER, "an earlier result was changed"
        return result
    return run


def below_a_file(ctx: Ctx) -> Path:
    (ctx.tmp / "notes.txt").write_text("a file, not a folder")
    return ctx.tmp / "notes.txt" / "sub" / "out.jsonl"


def rerun_with_overwrite(ctx: Ctx) -> list[str]:
    out = earlier_result(ctx.tmp / "out.jsonl")
    gallery, queries = good_gallery(ctx.tmp / "gallery"), png(ctx.tmp / "q" / "q.png", colour())
    predict(predict_cfg(ctx, ctx.checkpoint(), gallery, queries, ["overwrite=true", "threshold=null"]))
    return out.read_text().splitlines()


def replaced_by_one_answer(lines: list[str], ctx: Ctx) -> None:
    assert len(lines) == 1 and json.loads(lines[0])["image"].endswith("q.png")


def export_cli(out: Callable[[Ctx], Path], ckpt: Callable[[Ctx], Path | str] | None = None) -> Callable[[Ctx], Any]:
    def run(ctx: Ctx) -> subprocess.CompletedProcess:
        return run_cli(ctx, "matl.export", [f"ckpt={ckpt(ctx) if ckpt else ctx.checkpoint()}", f"out={out(ctx)}"])
    return run


def earlier_export(ctx: Ctx) -> Path:
    earlier_result(ctx.tmp / "exported" / "export.json")
    return ctx.tmp / "exported"


def score_cli(out: Callable[[Ctx], Path], ckpt: Callable[[Ctx], Path | str] | None = None) -> Callable[[Ctx], Any]:
    def run(ctx: Ctx) -> subprocess.CompletedProcess:
        (ctx.tmp / "truth.jsonl").write_text(json.dumps({"image": "q.png", "object": "tea"}) + "\n")
        (ctx.tmp / "pred.jsonl").write_text(json.dumps({"image": "q.png", "object": "tea"}) + "\n")
        return run_cli(ctx, "matl.score", [f"predictions={ctx.tmp / 'pred.jsonl'}", f"truth={ctx.tmp / 'truth.jsonl'}",
                                           f"ckpt={ckpt(ctx) if ckpt else ctx.checkpoint()}", f"out={out(ctx)}"])
    return run


def viz_pictures(ctx: Ctx) -> Path:
    png(ctx.tmp / "pictures" / "q.png", colour())
    return ctx.tmp / "pictures"


# ------------------------------------------------------------------------ checkpoints that are other files
def torchscript_file(ctx: Ctx) -> Path:
    torch.jit.save(torch.jit.script(torch.nn.Linear(2, 2)), str(ctx.tmp / "query_net.pt"))
    return ctx.tmp / "query_net.pt"


def gallery_file(ctx: Ctx) -> Path:
    torch.save({"format": 2, "model_id": "x", "planes": []}, ctx.tmp / "gallery.pt")
    return ctx.tmp / "gallery.pt"


def predict_shard(args: list[str]) -> Callable[[Ctx], Any]:
    """predict of one query file with ``args`` (``shard=``, ``shards=``)."""
    def run(ctx: Ctx) -> Any:
        queries = png(ctx.tmp / "q" / "q.png", colour())
        return predict(predict_cfg(ctx, ctx.checkpoint(), good_gallery(ctx.tmp / "gallery"), queries.parent, args))
    return run


def score_overlapping_shards(ctx: Ctx) -> subprocess.CompletedProcess:
    """matl.score of a folder whose two shard files both answer one query."""
    (ctx.tmp / "truth.jsonl").write_text(json.dumps({"image": "q.png", "object": "tea"}) + "\n")
    for k in range(2):
        (ctx.tmp / "shards" / str(k)).mkdir(parents=True)
        (ctx.tmp / "shards" / str(k) / "predictions.jsonl").write_text(json.dumps({"image": "q.png", "object": "tea"})
                                                                       + "\n")
    return run_cli(ctx, "matl.score", [f"predictions={ctx.tmp / 'shards'}", f"truth={ctx.tmp / 'truth.jsonl'}",
                                       f"ckpt={ctx.checkpoint()}", f"out={ctx.tmp / 'scored'}"])


def enrol_cli(args: list[str]) -> Callable[[Ctx], Any]:
    """``python -m matl.enrol`` on a good gallery with ``args``."""
    def run(ctx: Ctx) -> subprocess.CompletedProcess:
        gallery = good_gallery(ctx.tmp / "gallery")
        return run_cli(ctx, "matl.enrol", [f"ckpt={ctx.checkpoint()}", f"gallery={gallery}", *args])
    return run


def predict_cli_ckpt(ckpt: Callable[[Ctx], Path]) -> Callable[[Ctx], Any]:
    def run(ctx: Ctx) -> subprocess.CompletedProcess:
        gallery, queries = good_gallery(ctx.tmp / "gallery"), png(ctx.tmp / "q" / "q.png", colour())
        result = run_cli(ctx, "matl.predict", [f"ckpt={ckpt(ctx)}", f"gallery={gallery}", f"images={queries}",
                                               f"out={ctx.tmp / 'out.jsonl'}"])
        assert "weights_only` set to `False`" not in result.stdout + result.stderr  # torch's advice is not passed on
        return result
    return run


# ----------------------------------------------------------------------- images and names given to the API
def api_recognizer(ctx: Ctx) -> Any:
    from matl import Recognizer

    return Recognizer.from_checkpoint(ctx.checkpoint(), threshold=None).enrol(good_gallery(ctx.tmp / "gallery"),
                                                                            cache=False)


def api_predict(make: Callable[[], Any]) -> Callable[[Ctx], Any]:
    return lambda ctx: api_recognizer(ctx).predict(make())


def api_add(object: Any, plane: Any, make: Callable[[], Any] = lambda: colour(40, 50)) -> Callable[[Ctx], Any]:
    from matl import Recognizer

    def run(ctx: Ctx) -> Any:
        return Recognizer.from_checkpoint(ctx.checkpoint(), threshold=None).add(object, plane, make())
    return run


def with_nan(image: np.ndarray, count: int = 1) -> np.ndarray:
    image = image.astype(np.float32) / 255.0
    image.flat[:count] = np.nan
    return image


def grey_answered(match: Any, ctx: Ctx) -> None:
    assert match.nearest_object in ("red_box", "green_can") and np.isfinite(match.H).all()


def enrol_with_a_tiny_file(ctx: Ctx) -> Any:
    gallery = good_gallery(ctx.tmp / "gallery")
    png(gallery / "speck" / "front.png", colour(1, 1))
    return api_recognizer(ctx)


def tiny_file_skipped(recognizer: Any, ctx: Ctx) -> None:
    assert recognizer.objects == ["green_can", "red_box"]


CASES = [
    # --- config values (python -m matl.train ...): before any data, model, torch or Lightning
    train_cli("train N=0 (no anchors)", ["N=0"], "N=0 is invalid"),
    train_cli("train N=abc (not a number)", ["N=abc"], "N='abc' is invalid"),
    train_cli("train N=2.5 (not an integer)", ["N=2.5"], "N=2.5 is invalid"),
    train_cli("train N=true (a bool)", ["N=true"], "N=True is invalid"),
    train_cli("train lam=-1 (negative weight)", ["lam=-1"], "lam=-1 is invalid"),
    train_cli("train seed=-1", ["seed=-1"], "seed=-1 is invalid"),
    train_cli("train loss=nce loss.fn.tau=0", ["loss=nce", "loss.fn.tau=0"], "loss.fn.tau=0 is invalid"),
    train_cli("train loss.fn.margin=-0.1", ["loss.fn.margin=-0.1"], "loss.fn.margin=-0.1 is invalid"),
    train_cli("train loss.num_negatives=0", ["loss.num_negatives=0"], "loss.num_negatives=0 is invalid"),
    train_cli("train loss=nce with a batch too small for M=64", ["loss=nce", "data.batch_size=8"],
              "needs data.batch_size >= 22"),
    train_cli("train data.image_size=abc", ["data.image_size=abc"], "data.image_size='abc' is invalid"),
    train_cli("train data.image_size=8 (too small)", ["data.image_size=8"], "data.image_size=8 is invalid"),
    train_cli("train model.image_size=64 vs data 100", ["model.image_size=64"],
              "model.image_size=64 differs from data.image_size=100"),
    train_cli("train model.stn.regressor.image_size=48 vs data 100", ["model.stn.regressor.image_size=48"],
              "model.stn.regressor.image_size=48 differs from data.image_size=100"),
    train_cli("train model.num_anchors=3 with N=4", ["model.num_anchors=3"], "model.num_anchors=3 differs from N=4"),
    train_cli("train data.batch_size=0", ["data.batch_size=0"], "data.batch_size=0 is invalid"),
    train_cli("train data.train_triplets=8 fewer than a batch", ["data.train_triplets=8"],
              "data.train_triplets=8 < data.batch_size=32"),
    train_cli("train data.queries=photos", ["data.queries=photos"], "data.queries='photos' is invalid"),
    train_cli("train data.source.catalog=xyz", ["data.source.catalog=xyz"], "data.source.catalog='xyz' is invalid"),
    train_cli("train data=ycb without data.source.root", ["data=ycb"], "data.source.root is not set"),
    train_cli("train trainer.max_epochs=0", ["trainer.max_epochs=0"], "trainer.max_epochs=0 is invalid"),
    train_cli("train trainer.accelerator=quantum", ["trainer.accelerator=quantum"],
              "trainer.accelerator='quantum' is invalid"),
    train_cli("train test=maybe (not a bool)", ["test=maybe"], "test='maybe' is invalid"),
    train_cli("train optimized_metric=val/loss", ["optimized_metric=val/loss"],
              "optimized_metric='val/loss' is invalid"),
    train_cli("train ckpt_path=missing file", ["ckpt_path=/nonexistent/last.ckpt"], "no such checkpoint file"),
    train_cli("train init_from=missing file", ["init_from=/nonexistent/model.ckpt"],
              "no such checkpoint file (a model"),
    train_cli("train model.optimizer.lr=0", ["model.optimizer.lr=0"], "model.optimizer.lr=0 is invalid"),
    train_cli("train callbacks.model_checkpoint.last_every_n_train_steps=-5",
              ["callbacks.model_checkpoint.last_every_n_train_steps=-5"],
              "callbacks.model_checkpoint.last_every_n_train_steps=-5 is invalid"),
    # --- unknown names: Hydra's composition errors, one line with the valid options
    train_cli("train data=foo (unknown dataset)", ["data=foo"], "unknown option data=foo; valid: "),
    train_cli("train loss=hinge (unknown loss)", ["loss=hinge"], "unknown option loss=hinge; valid: "),
    train_cli("train model=resnet (unknown model)", ["model=resnet"],
              "unknown option model=resnet; valid: "),
    train_cli("train anchors=spiral (unknown anchors)", ["anchors=spiral"],
              "unknown option anchors=spiral; valid: "),
    train_cli("train trainer=tpu (unknown trainer)", ["trainer=tpu"],
              "unknown option trainer=tpu; valid: "),
    train_cli("train foo=1 (unknown key)", ["foo=1"], "unknown key 'foo'"),
    train_cli("train data.batchsize=8 (misspelt key)", ["data.batchsize=8"], "unknown key 'data.batchsize'"),
    train_cli("train N=[1 (unparsable override)", ["N=[1"], "cannot parse the override"),
    cli("render data=foo (unknown dataset)", "matl.render", ["data=foo"], "unknown option data=foo"),
    cli("render data.image_size=4", "matl.render", ["data.image_size=4"], "data.image_size=4 is invalid"),
    cli("predict gallery_fill=2", "matl.predict", ["gallery_fill=2"], "gallery_fill=2 is invalid"),
    cli("predict foreground.retry_insets=[0.7]", "matl.predict", ["foreground.retry_insets=[0.7]"],
        "foreground.retry_insets=[0.7] is invalid"),
    cli("unseen condition=foggy", "matl.unseen", ["ckpt=pretrained", "condition=foggy"],
        "condition=foggy is invalid: use one or a list of clean, photometric"),
    cli("unseen open_set_statistic=foo (a method's predict option: before any file is written)", "matl.unseen",
        ["ckpt=pretrained", "methods=[matl]", "open_set_statistic=foo"], "matl: open_set_statistic='foo' is invalid"),
    cli("unseen refine_check=loss (a method's predict option)", "matl.unseen",
        ["ckpt=pretrained", "methods=[matl_refine]", "refine_check=loss"], "refine_check='loss' is invalid"),
    cli("unseen keypoint_pose=often (a method's predict option)", "matl.unseen",
        ["ckpt=pretrained", "methods=[matl]", "keypoint_pose=often"], "keypoint_pose='often' is invalid"),
    cli("unseen catalog_sizes=[1,20] (a gallery of one product)", "matl.unseen",
        ["ckpt=pretrained", "condition=catalog", "catalog_sizes=[1,20]"],
        "catalog_sizes=[1, 20] is invalid: use a list of distinct gallery sizes, integers >= 2"),
    cli("unseen catalog_sizes=[20000] (larger than the catalogue makes)", "matl.unseen",
        ["ckpt=pretrained", "condition=catalog", "catalog_sizes=[20000]"],
        "galleries of at most 10000 products; drop 20000"),
    cli("unseen condition=[catalog,clean] (the catalogue runs alone)", "matl.unseen",
        ["ckpt=pretrained", "condition=[catalog,clean]"], "condition=catalog runs alone"),
    cli("eval data=foo (unknown dataset)", "matl.eval", ["data=foo"], "unknown option data=foo"),
    # --- image files (queries and gallery images go through the same loader)
    image("image: text file named .png", lambda p: (p.write_text("hello"), p)[1], "not an image"),
    image("image: zero-byte file", lambda p: (p.write_bytes(b""), p)[1], "empty file (0 bytes)"),
    image("image: PNG header of 0 x 0 pixels", zero_size_png, "not an image"),
    image("image: truncated PNG", truncated_png, "truncated"),
    image("image: missing file", lambda p: p, "no such file"),
    image("image: a folder named like an image", lambda p: (p.mkdir(), p)[1], "no such file"),
    image("image: grey PNG works (3 equal channels)", lambda p: png(p, colour()[..., 0], "L"), check=grey_check),
    image("image: grey+alpha PNG works (alpha as mask)", alpha_image("LA"), check=alpha_check),
    image("image: RGBA PNG works (alpha as mask)", alpha_image("RGBA"), check=alpha_check),
    image("image: 16-bit grey PNG works (not saturated)", sixteen_bit, check=sixteen_bit_check),
    image("image: palette PNG with a transparent colour works", palette_png, check=palette_check),
    image("image: CMYK JPEG works", cmyk_jpeg, check=lambda x, ctx: rgb_in_unit_range(x)),
    image("image: 1 x 1 pixel works", lambda p: png(p, colour(1, 1)), check=lambda x, ctx: rgb_in_unit_range(x)),
    image("image: 1 x 400 strip works", lambda p: png(p, colour(1, 400)), check=lambda x, ctx: rgb_in_unit_range(x)),
    # --- predict on folders and galleries
    call("predict: a non-image among grey, RGBA and colour queries is reported, the rest predicted",
         predict_folder_with_bad_file, check=predicted_the_good_files),
    call("predict: images folder missing", predict_images(lambda p: p), "no such file or folder"),
    call("predict: empty images folder", predict_images(lambda p: (p.mkdir(), p)[1]), "holds no files"),
    call("gallery: folder missing", gallery_case(lambda p: p), "no such folder"),
    call("gallery: empty folder", gallery_case(lambda p: (p.mkdir(), p)[1]), "holds no canonical images"),
    call("gallery: images not inside object folders", gallery_case(loose_files_gallery), "holds no canonical images"),
    call("gallery: only unreadable images", gallery_case(unreadable_gallery), "holds no usable image"),
    call("enrol: gallery= missing", lambda ctx: run_cli(ctx, "matl.enrol", []), "gallery=... is required"),
    call("enrol: shard=2 of shards=2", enrol_cli(["shard=2", "shards=2"]), "shard=2 is invalid"),
    call("enrol: shards=0", enrol_cli(["shards=0"]), "shards=0 is invalid"),
    call("enrol: shard= with save= (a shard fills the cache only)", enrol_cli(["shard=0", "shards=2", "save=g.pt"]),
         "shard= fills the gallery's cache only"),
    call("predict: shard=1 of shards=1", predict_shard(["shard=1", "shards=1"]), "shard=1 is invalid"),
    call("predict: a shard with no file (more shards than files)", predict_shard(["shard=1", "shards=2"]),
         "shard=1 of shards=2 holds no file"),
    call("score: a folder of shard files answering one image twice", score_overlapping_shards,
         "is answered in both"),
    # --- checkpoints
    call("checkpoint: missing file (predict)", predict_with_checkpoint(lambda c: c.tmp / "missing.ckpt"), "not found"),
    call("checkpoint: missing file (eval ckpt=)", eval_with(lambda c: c.tmp / "missing.ckpt"), "not found"),
    call("checkpoint: text file", predict_with_checkpoint(text_checkpoint), "cannot be read safely"),
    call("checkpoint: truncated file", predict_with_checkpoint(truncated_checkpoint), "cannot be read safely"),
    call("checkpoint: pickled code is refused, never run (weights_only=True)", exploit_checkpoint,
         "cannot be read safely"),
    call("checkpoint: its config names os.system for Hydra (refused, never run)", config_exploit("os.system"),
         "asks to build 'os.system'"),
    call("checkpoint: its config names a matl function that writes files (refused)",
         config_exploit("matl.utils.io.write_json"), "asks to build 'matl.utils.io.write_json'"),
    call("checkpoint: plain Lightning checkpoint without matl metadata",
         predict_with_checkpoint(plain_lightning_checkpoint), "not written by matl.train"),
    call("checkpoint: trained at 48 px, predict image_size=32",
         predict_with_checkpoint(lambda c: c.checkpoint(48), ["image_size=32"]), "was trained at 48 px"),
    call("checkpoint: trained at 48 px, eval on a 32 px run", eval_with(lambda c: c.checkpoint(48)),
         "was trained at 48 px with N=4, but the data is 32 px"),
    call("checkpoint: trained at 48 px, resumed by a 32 px train", resume_with(lambda c: c.checkpoint(48)),
         "was trained at 48 px with N=4"),
    call("checkpoint: weights-only file as train ckpt_path",
         resume_with(lambda c: c.checkpoint(weights_only_file=True)), "holds weights only"),
    call("checkpoint: model=tl checkpoint resumed as model=matl", resume_with(lambda c: c.checkpoint(model="tl")),
         "does not fit this model"),
    # --- meshes (matl.data.meshes) and the canonical-image cache
    call("mesh: without texture (render data=meshes)", untextured_mesh_render, "plain_box.obj: mesh has no texture"),
    call("mesh: a file that is not a mesh", not_a_mesh, "broken.obj"),
    call("cache: corrupt canonical-image cache is rebuilt with a warning", corrupt_cache, check=rebuilt_with_warning),
    # --- outputs a user named: checked before any work, an existing file replaced only with overwrite=true
    call("predict out= a file from an earlier run (no overwrite=true): kept whole",
         predict_cli_out(lambda c: earlier_result(c.tmp / "earlier.jsonl"), keeps=lambda c: c.tmp / "earlier.jsonl"),
         "already exists: pass overwrite=true to replace it"),
    call("predict out= a file from an earlier run, overwrite=true: replaced when complete", rerun_with_overwrite,
         check=replaced_by_one_answer),
    call("predict out= an existing folder", predict_cli_out(lambda c: c.tmp), "is a folder: name a file in it"),
    call("predict out= in a read-only folder", predict_cli_out(lambda c: read_only_folder(c) / "sub" / "out.jsonl"),
         "is read-only; choose another out="),
    call("predict out= below a file (folder cannot be created)", predict_cli_out(below_a_file),
         "cannot be created: "),
    call("predict viz_dir= holding pictures (no overwrite=true)",
         predict_cli_out(lambda c: c.tmp / "new.jsonl", lambda c: ["viz=true", f"viz_dir={viz_pictures(c)}"]),
         "already holds q.png: pass overwrite=true"),
    call("predict overwrite=maybe", predict_cli_out(lambda c: c.tmp / "new.jsonl", ["overwrite=maybe"]),
         "overwrite=maybe is invalid"),
    call("export out= holding an earlier export (no overwrite=true)", export_cli(earlier_export),
         "already holds export.json: pass overwrite=true"),
    call("export out= a file", export_cli(lambda c: earlier_result(c.tmp / "export.txt")), "is a file, not a folder"),
    call("score out= holding an earlier score.json (no overwrite=true)",
         score_cli(lambda c: earlier_result(c.tmp / "scored" / "score.json").parent),
         "already holds score.json: pass overwrite=true"),
    # --- checkpoints that are other files: one line, torch's weights_only=False advice never passed on
    call("checkpoint: text file (predict command line)", predict_cli_ckpt(text_checkpoint),
         "not a torch checkpoint file"),
    call("checkpoint: a TorchScript file (export's output) as ckpt=", predict_cli_ckpt(torchscript_file),
         "a TorchScript file"),
    call("checkpoint: a saved gallery as ckpt=", predict_cli_ckpt(gallery_file), "has no state_dict"),
    call("checkpoint: export ckpt= a text file", export_cli(lambda c: c.tmp / "e", text_checkpoint),
         "cannot be read safely"),
    call("checkpoint: score ckpt= a text file", score_cli(lambda c: c.tmp / "s", text_checkpoint),
         "cannot be read safely"),
    # --- images and names given to the Python API
    call("api: float image with 0-255 values", api_predict(lambda: colour().astype(np.float32)),
         "float pixels must be in [0, 1]"),
    call("api: float image with negative values", api_predict(lambda: colour().astype(np.float32) / 255.0 - 0.5),
         "float pixels must be in [0, 1]"),
    call("api: NaN pixels", api_predict(lambda: with_nan(colour())), "NaN or infinite"),
    call("api: infinite pixels", api_predict(lambda: np.full((30, 40, 3), np.inf, np.float32)), "NaN or infinite"),
    call("api: HxW grey uint8 array works (matched against the grey gallery)",
         api_predict(lambda: colour()[..., 0]), check=grey_answered),
    call("api: (1, H, W) grey float tensor works",
         api_predict(lambda: torch.from_numpy(colour()[..., 0] / 255.0)[None]), check=grey_answered),
    call("api: add('../x', ...)", api_add("../x", "front"), "object='../x' is not a name"),
    call("api: add('', ...)", api_add("", "front"), "object='' is not a name"),
    call("api: add(None, ...)", api_add(None, "front"), "object=None is not a name"),
    call("api: add('tea', 'a/b', ...)", api_add("tea", "a/b"), "plane='a/b' is not a name"),
    call("api: add() of a 1 x 1 image", api_add("tea", "front", lambda: colour(1, 1)), "at least 8 px a side"),
    call("api: add() of an all-NaN image", api_add("tea", "front", lambda: np.full((40, 50, 3), np.nan)),
         "NaN or infinite"),
    call("api: add() of an all-black image", api_add("tea", "front", lambda: np.zeros((40, 50, 3), np.uint8)),
         "is empty"),
    call("api: add() of None", api_add("tea", "front", lambda: None), "got None instead of an image"),
    call("gallery: a 1 x 1 file is reported and skipped, the rest enrolled", enrol_with_a_tiny_file,
         check=tiny_file_skipped),
]


@pytest.fixture(scope="module")
def shared(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    return {"root": tmp_path_factory.mktemp("bad_inputs_shared")}


@pytest.mark.parametrize("case", CASES)
def test_bad_input(case: Case, tmp_path: Path, cache_dir: Path, shared: dict[str, Any]) -> None:
    ctx = Ctx(tmp_path, cache_dir, shared)
    if case.error is None:  # must work
        result = case.run(ctx)
        if case.check is not None:
            case.check(result, ctx)
        return
    try:
        result = case.run(ctx)
    except MatlError as error:
        message = str(error)
        assert "\n" not in message and case.error in message, message
        return
    assert isinstance(result, subprocess.CompletedProcess), f"no error raised; expected {case.error!r}"
    output = result.stdout + result.stderr
    errors = [line for line in output.splitlines() if line.startswith("error: ")]
    assert result.returncode == 2, output[-3000:]
    assert "Traceback" not in output, output[-3000:]
    assert len(errors) == 1 and case.error in errors[0], output[-3000:]
    unknown = re.search(r"unknown option (\w+)=\w+; valid: (.*)$", errors[0])
    if unknown:  # the valid choices listed are exactly the group's files (minus _-prefixed bases)
        assert unknown.group(2).split(", ") == group_options(unknown.group(1)), errors[0]


def test_catalog_names_in_validation_match_the_catalog() -> None:
    from matl.data.catalog import CATALOGS

    assert sorted(SYNTHETIC_CATALOGS) == sorted(CATALOGS)


def test_docs_state_the_count() -> None:
    text = (REPO / "docs" / "reliability.md").read_text()
    found = re.search(r"(\d+) bad inputs are tested in `?tests/test_bad_inputs\.py", text)
    assert found is not None and int(found.group(1)) == len(CASES), (found and found.group(1), len(CASES))
