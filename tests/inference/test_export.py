"""matl.export: exported gallery and query networks agree with the eager model (tolerance 1e-5)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from torch import nn

from matl.inference.export import QueryNet, export, export_inference
from matl.models.feature import FeatureNet
from matl.models.stn import HomographyRegressor, SpatialTransformer
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


def test_torchscript_export_matches_eager_for_any_batch_size(tmp_path: Path) -> None:
    feature_net, stn = tiny_networks()
    info = export_inference(feature_net, stn, S, tmp_path, "torchscript")
    assert info["max_abs_diff"]["gallery_net"] <= 1e-5 and info["max_abs_diff"]["query_net"] <= 1e-5
    gallery_net = torch.jit.load(str(tmp_path / "gallery_net.pt"))
    query_net = torch.jit.load(str(tmp_path / "query_net.pt"))
    images = textured_planes(5, S, 1)  # another batch size than traced (2) and checked (1, 3)
    with torch.no_grad():
        emb, H, degenerate, warped = query_net(images)
        ref = stn(images)
        assert torch.allclose(emb, feature_net(ref.warped), atol=1e-5)
        assert torch.allclose(H, ref.query_H_anchor, atol=1e-5)
        assert torch.allclose(warped, ref.warped, atol=1e-5)
        assert torch.equal(degenerate, ref.degenerate)
        assert torch.allclose(gallery_net(images), feature_net(images), atol=1e-5)
    assert not torch.allclose(H, torch.eye(3).expand_as(H), atol=1e-3)  # a real homography was compared
    saved = json.loads((tmp_path / "export.json").read_text())
    assert saved["image_size"] == S and saved["embedding_dim"] == 128 and saved["format"] == "torchscript"


class ConstantRegressor(nn.Module):
    """Returns fixed normalised homographies (some degenerate)."""

    def __init__(self, H: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("H", H)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.H[: len(images)]


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
    assert max(info["max_abs_diff"].values()) <= 1e-5
    # the Hydra app: a missing checkpoint is one line, exit 2 (before any heavy import)
    bad = subprocess.run([sys.executable, "-m", "matl.export", f"ckpt={tmp_path / 'none.ckpt'}",
                          f"hydra.run.dir={tmp_path / 'run2'}"], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert bad.returncode == 2 and "not found" in bad.stderr and len(bad.stderr.strip().splitlines()) == 1
