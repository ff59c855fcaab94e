"""matl.export: exported gallery and query networks (TorchScript, torch.export, ONNX) agree with the eager model."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from torch import nn

from matl.inference.export import QueryNet, export, export_inference, svdvals_3x3
from matl.models.feature import FeatureNet
from matl.models.stn import HomographyRegressor, SpatialTransformer
from matl.utils.errors import MatlError
from tests.conftest import compose_config
from tests.speed_helpers import textured_planes, write_tiny_checkpoint

REPO = Path(__file__).resolve().parents[2]
S = 32


def tiny_networks(seed: int = 0) -> tuple[FeatureNet, SpatialTransformer]:
    torch.manual_seed(seed)
    stn = SpatialTransformer(HomographyRegressor(image_size=S), image_size=S, iterations=2)
    nn.init.normal_(stn.regressor.fc2.weight, std=0.02)  # not the identity it starts at
    nn.init.normal_(stn.regressor.fc2.bias, std=0.02)
    return FeatureNet().eval(), stn.eval()


def assert_matches_eager(gallery_net, query_net, feature_net, stn, images: torch.Tensor) -> torch.Tensor:
    """Exported networks' outputs equal the eager ``c()`` and ``s()`` within 1e-5; returns their ``query_H_anchor``."""
    with torch.no_grad():
        emb, H, degenerate, warped = query_net(images)
        ref = stn(images)
        assert torch.allclose(emb, feature_net(ref.warped), atol=1e-5)
        assert torch.allclose(H, ref.query_H_anchor, atol=1e-5)
        assert torch.allclose(warped, ref.warped, atol=1e-5)
        assert degenerate.dtype == torch.bool and torch.equal(degenerate, ref.degenerate)
        assert torch.allclose(gallery_net(images), feature_net(images), atol=1e-5)
    return H


def test_torchscript_export_matches_eager_for_any_batch_size(tmp_path: Path) -> None:
    feature_net, stn = tiny_networks()
    info = export_inference(feature_net, stn, S, tmp_path, "torchscript")
    assert info["max_abs_diff"]["gallery_net"] <= 1e-5 and info["max_abs_diff"]["query_net"] <= 1e-5
    gallery_net = torch.jit.load(str(tmp_path / "gallery_net.pt"))
    query_net = torch.jit.load(str(tmp_path / "query_net.pt"))
    H = assert_matches_eager(gallery_net, query_net, feature_net, stn, textured_planes(5, S, 1))  # batch 5: not
    assert not torch.allclose(H, torch.eye(3).expand_as(H), atol=1e-3)  # traced (2) nor checked; a real homography
    saved = json.loads((tmp_path / "export.json").read_text())
    assert saved["image_size"] == S and saved["embedding_dim"] == 128 and saved["format"] == "torchscript"


class ConstantRegressor(nn.Module):
    """Returns fixed normalised homographies (some degenerate)."""

    def __init__(self, H: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("H", H)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.H[: images.shape[0]]  # a size the ONNX trace keeps dynamic (len() would be a constant)


def test_query_net_guard_equals_the_stn_guard() -> None:
    bad = torch.stack([torch.full((3, 3), float("nan")), torch.zeros(3, 3), torch.eye(3) * 1.1])
    stn = SpatialTransformer(ConstantRegressor(bad), image_size=S).eval()  # type: ignore[arg-type]
    images = textured_planes(3, S, 2)
    with torch.no_grad():
        _, H, degenerate, warped = QueryNet(stn, FeatureNet()).eval()(images)
        ref = stn(images)
    assert degenerate.tolist() == ref.degenerate.tolist() == [True, True, False]
    assert torch.allclose(H, ref.query_H_anchor, atol=1e-5) and torch.allclose(warped, ref.warped, atol=1e-5)


@pytest.mark.slow  # torch.export traces symbolically: several seconds
def test_torch_export_format(tmp_path: Path) -> None:
    feature_net, stn = tiny_networks(1)
    info = export_inference(feature_net, stn, S, tmp_path, "export")
    assert (tmp_path / "query_net.pt2").is_file() and info["max_abs_diff"]["query_net"] <= 1e-5


def test_export_from_a_checkpoint_and_cli_errors(tmp_path: Path, cache_dir: Path) -> None:
    ckpt = write_tiny_checkpoint(tmp_path / "ckpt" / "tiny.ckpt", cache_dir)
    out = tmp_path / "exported"
    info = export(compose_config("export", [f"ckpt={ckpt}", f"out={out}"], tmp_path / "run"))
    assert info["N"] == 4 and info["image_size"] == S and info["checkpoint_sha256"]
    assert json.loads((out / "export.json").read_text())["max_abs_diff"] == info["max_abs_diff"]
    assert max(info["max_abs_diff"].values()) <= 1e-5 and "alignment_stage" not in info
    # the Hydra app: a missing checkpoint is one line, exit 2 (before any heavy import)
    bad = subprocess.run([sys.executable, "-m", "matl.export", f"ckpt={tmp_path / 'none.ckpt'}",
                          f"hydra.run.dir={tmp_path / 'run2'}"], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert bad.returncode == 2 and "not found" in bad.stderr and len(bad.stderr.strip().splitlines()) == 1


# ------------------------------------------------------------------------------------------- ONNX
def test_closed_form_singular_values_equal_svdvals() -> None:
    c, s = math.cos(0.3), math.sin(0.3)
    rotation = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    hand = torch.stack([rotation @ torch.diag(torch.tensor([3.0, 2.0, 0.5], dtype=torch.float64)) @ rotation.T,
                        torch.zeros(3, 3, dtype=torch.float64),                     # all zero
                        torch.outer(torch.tensor([1.0, 2.0, 2.0]), torch.tensor([0.0, 3.0, 4.0])).double(),  # rank 1
                        torch.eye(3, dtype=torch.float64) * 7])
    expected = torch.tensor([[3.0, 2.0, 0.5], [0.0, 0.0, 0.0], [15.0, 0.0, 0.0], [7.0, 7.0, 7.0]], dtype=torch.float64)
    assert torch.allclose(svdvals_3x3(hand), expected, rtol=1e-12, atol=1e-12)

    g = torch.Generator().manual_seed(0)
    H = torch.randn(4000, 3, 3, generator=g, dtype=torch.float64)
    H[:400, 2] = H[:400, 1] + H[:400, 2] * torch.logspace(-8, 0, 400, dtype=torch.float64)[:, None]  # ill-conditioned
    ref, got = torch.linalg.svdvals(H), svdvals_3x3(H)
    assert float(((got - ref).abs() / ref[:, :1]).max()) < 1e-12
    assert float(((got[:, 2] - ref[:, 2]).abs() / ref[:, 2]).max()) < 1e-6  # the smallest one relatively too
    for limit in (1e2, 1e4, 1e6):  # the guard's decision is the same
        assert torch.equal(got[:, 2] * limit <= got[:, 0], ref[:, 2] * limit <= ref[:, 0])
    assert svdvals_3x3(H.float()).dtype == torch.float32


def test_onnx_export_runs_in_onnxruntime_like_eager(tmp_path: Path) -> None:
    pytest.importorskip("onnxruntime", reason="format=onnx needs onnxruntime (a dependency of matl)")
    from matl.inference.export import OnnxNetwork

    feature_net, stn = tiny_networks(2)
    info = export_inference(feature_net, stn, S, tmp_path, "onnx", tolerance=1e-5)
    assert info["files"] == {"gallery_net": "gallery_net.onnx", "query_net": "query_net.onnx"}
    assert set(info["max_abs_diff_by_output"]["query_net"]) == {"embedding", "query_H_anchor", "degenerate", "warped"}
    assert max(info["max_abs_diff"].values()) <= 1e-5 and info["checked_batch_sizes"] == [1, 3]
    gallery_net, query_net = OnnxNetwork(tmp_path / "gallery_net.onnx"), OnnxNetwork(tmp_path / "query_net.onnx")
    assert query_net.output_names == ("embedding", "query_H_anchor", "degenerate", "warped")
    for batch in (1, 3):
        H = assert_matches_eager(gallery_net, query_net, feature_net, stn, textured_planes(batch, S, batch))
    assert not torch.allclose(H, torch.eye(3).expand_as(H), atol=1e-3)  # a real homography was compared


def test_onnx_query_net_guard_equals_the_stn_guard(tmp_path: Path) -> None:
    pytest.importorskip("onnxruntime", reason="format=onnx needs onnxruntime (a dependency of matl)")
    from matl.inference.export import OnnxNetwork

    bad = torch.stack([torch.full((3, 3), float("nan")), torch.zeros(3, 3), torch.diag(torch.tensor([1.0, 1.0, 1e-5])),
                       torch.eye(3) * 1.1])  # non-finite, zero, condition 1e5 > 1e4: identity; the last one kept
    stn = SpatialTransformer(ConstantRegressor(bad), image_size=S).eval()  # type: ignore[arg-type]
    export_inference(FeatureNet(), stn, S, tmp_path, "onnx", check_batches=(4,))
    images = textured_planes(4, S, 3)
    _, H, degenerate, _ = OnnxNetwork(tmp_path / "query_net.onnx")(images)
    assert degenerate.tolist() == stn(images).degenerate.tolist() == [True, True, True, False]
    assert torch.allclose(H[:3], torch.eye(3).expand(3, 3, 3), atol=1e-6)


def test_onnx_from_a_checkpoint_describes_the_files(tmp_path: Path, cache_dir: Path) -> None:
    pytest.importorskip("onnxruntime", reason="format=onnx needs onnxruntime (a dependency of matl)")
    ckpt = write_tiny_checkpoint(tmp_path / "ckpt" / "tiny.ckpt", cache_dir)
    out = tmp_path / "exported"
    info = export(compose_config("export", [f"ckpt={ckpt}", f"out={out}", "format=onnx"], tmp_path / "run"))
    saved = json.loads((out / "export.json").read_text())
    assert saved["format"] == "onnx" and saved["N"] == 4 and saved["tolerance"] == 5e-4
    assert max(info["max_abs_diff"].values()) <= 1e-5
    # anchor 1 of 4: a quarter turn about ((S - 1) / 2, (S - 1) / 2), counter-clockwise on screen (y down)
    anchors = torch.tensor(saved["anchor_k_H_canon"], dtype=torch.float64)
    assert anchors.shape == (4, 3, 3) and torch.equal(anchors[0], torch.eye(3, dtype=torch.float64))
    quarter = torch.tensor([[0.0, 1.0, 0.0], [-1.0, 0.0, S - 1.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    assert torch.allclose(anchors[1], quarter, atol=1e-12)
    for key in ("inputs", "to_model_frame", "model_H_file", "recognition", "pose", "pose_in_files", "runtime",
                "foreground_net"):
        assert saved[key], key
    assert "query_H_anchor @ anchor_k_H_canon" in saved["pose"] and "'images'" in saved["runtime"]
    # the shipped visibility network (foreground=learned) beside them: the same logits in onnxruntime
    from matl.inference.export import OnnxNetwork
    from matl.models.visibility import load_visibility_net

    assert saved["files"]["foreground_net"] == "foreground_net.onnx" and saved["foreground_weights"] == "shipped"
    net, exported = load_visibility_net(), OnnxNetwork(out / "foreground_net.onnx")
    crops = torch.rand(3, 3, net.size, net.size, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        assert (exported(crops) - net(crops)).abs().max() < 1e-4
    assert saved["max_abs_diff"]["foreground_net"] <= 1e-4 and "sigmoid(logits)" in saved["foreground_net"]
    without = export(compose_config("export", [f"ckpt={ckpt}", f"out={tmp_path / 'plain'}", "format=onnx",
                                               "foreground_net=null"], tmp_path / "run2"))
    assert "foreground_net" not in without["files"] and not (tmp_path / "plain" / "foreground_net.onnx").exists()


def test_onnx_without_onnxruntime_is_one_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "onnxruntime", None)  # import fails as if not installed
    feature_net, stn = tiny_networks()
    with pytest.raises(MatlError, match=r'onnxruntime is not installed\): pip install "onnx>=1\.15" "onnxruntime'):
        export_inference(feature_net, stn, S, tmp_path, "onnx")
    assert not list(tmp_path.iterdir())  # nothing written


def test_bench_onnx_entry_answers_like_the_eager_recognizer(tmp_path: Path, cache_dir: Path,
                                                            monkeypatch: pytest.MonkeyPatch) -> None:
    """``query_ms.matl_onnx`` of matl.bench (matl.evaluation.speed.measure_onnx) times a recognizer whose
    networks are the exported ONNX files; it finds the anchors eager finds."""
    pytest.importorskip("onnxruntime", reason="format=onnx needs onnxruntime (a dependency of matl)")
    from matl.evaluation.speed import measure_onnx
    from matl.inference.api import load_embedding_model
    from matl.inference.gallery import build_gallery

    model, size, N, _ = load_embedding_model(write_tiny_checkpoint(tmp_path / "ckpt" / "tiny.ckpt", cache_dir))
    canon = (textured_planes(3, size, 4) * 255).round().to(torch.uint8)
    gallery = build_gallery(canon, [0, 1, 2], ["a", "b", "c"], ["a", "b", "c"], N)
    queries = gallery.images[[0, 5, 10, 3]]  # anchors themselves: one clear nearest anchor each
    result = measure_onnx(model, gallery, queries, 1, [1], torch.device("cpu"))
    ms = result["query_ms"]["matl_onnx"]
    assert ms > 0 and result["matl_onnx_ms_by_threads"] == {"1": ms}
    assert result["matl_onnx_same_answers"] == 1.0 and result["matl_onnx_threads"] == 1
    assert max(result["matl_onnx_max_abs_diff"]["query_net"].values()) <= 1e-5

    monkeypatch.setitem(sys.modules, "onnxruntime", None)
    skipped = measure_onnx(model, gallery, queries, 1, [1], torch.device("cpu"))
    assert skipped["query_ms"] == {} and "pip install" in skipped["matl_onnx_skipped"]


# ------------------------------------------------------------------------------ the alignment stage
def tiny_stage(seed: int = 3):
    from matl.models.align import AlignmentStage

    torch.manual_seed(seed)
    stage = AlignmentStage(image_size=S, iterations=2, channels=(8, 8), hidden=16)
    nn.init.normal_(stage.regressor.fc2.weight, std=0.05)  # not the identity it starts at
    return stage.eval()


@pytest.mark.parametrize("fmt", ["torchscript", "onnx"])
def test_the_alignment_stage_is_exported_and_answers_like_eager(tmp_path: Path, fmt: str) -> None:
    if fmt == "onnx":
        pytest.importorskip("onnxruntime", reason="format=onnx needs onnxruntime (a dependency of matl)")
    from matl.inference.export import OnnxNetwork

    feature_net, stn = tiny_networks(4)
    stage = tiny_stage()
    info = export_inference(feature_net, stn, S, tmp_path, fmt, tolerance=1e-5, align=stage)
    suffix = ".onnx" if fmt == "onnx" else ".pt"
    assert info["files"]["align_net"] == f"align_net{suffix}" and info["max_abs_diff"]["align_net"] <= 1e-5
    assert "align_net" in info and "align_net's" in info["pose"]
    align_net = OnnxNetwork(tmp_path / "align_net.onnx") if fmt == "onnx" else torch.jit.load(
        str(tmp_path / "align_net.pt"))
    images, anchors = textured_planes(5, S, 7), textured_planes(5, S, 8)  # batch 5: neither traced nor checked
    with torch.no_grad():
        out = stn(images)
        eager = stage.infer(images, anchors, out.query_H_anchor, out.warped).query_H_anchor
        exported = align_net(images, anchors, out.query_H_anchor, out.warped)
    assert torch.allclose(exported, eager, atol=1e-5)
    assert not torch.allclose(eager, out.query_H_anchor, atol=1e-3)  # the stage moved the pose: a real comparison
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["export.json", *info["files"].values()])


def test_an_export_replaces_an_earlier_one_only_when_asked_and_a_failed_one_leaves_it(
        tmp_path: Path, cache_dir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import matl.inference.export as export_module

    ckpt = write_tiny_checkpoint(tmp_path / "ckpt" / "tiny.ckpt", cache_dir)
    out = tmp_path / "exported"
    export(compose_config("export", [f"ckpt={ckpt}", f"out={out}"], tmp_path / "run"))
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    with pytest.raises(MatlError, match=r"already holds export\.json, foreground_net\.pt, gallery_net\.pt, "
                                        r"query_net\.pt: pass overwrite=true to replace them"):
        export(compose_config("export", [f"ckpt={ckpt}", f"out={out}"], tmp_path / "run"))
    monkeypatch.setattr(export_module, "_max_diffs", lambda eager, exported, names: dict.fromkeys(names, 1.0))
    with pytest.raises(MatlError, match="differs from the eager model"):
        export(compose_config("export", [f"ckpt={ckpt}", f"out={out}", "overwrite=true"], tmp_path / "run"))
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before  # untouched, no temporary folder left
    monkeypatch.undo()
    info = export(compose_config("export", [f"ckpt={ckpt}", f"out={out}", "overwrite=true", "format=onnx"],
                                 tmp_path / "run"))
    assert info["format"] == "onnx" and (out / "query_net.onnx").is_file()
    assert not [p for p in out.iterdir() if p.name.startswith(".")]
