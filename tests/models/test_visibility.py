"""The visibility network (matl/models/visibility.py): shapes, its ONNX graph, losses, checkpoints."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from matl.models.visibility import (
    VISIBILITY_FORMAT,
    VisibilityModule,
    VisibilityNet,
    dice_loss,
    load_visibility_net,
    mask_iou,
    visibility_loss,
)
from matl.utils.errors import MatlError


def test_shapes_and_early_checks() -> None:
    net = VisibilityNet(size=32).eval()
    out = net(torch.rand(2, 3, 32, 32))
    assert out.shape == (2, 1, 32, 32) and out.dtype == torch.float32 and torch.isfinite(out).all()
    full = VisibilityNet(size=24, channels=(4, 6, 8), dilations=(2,), full_channels=4, global_context=False,
                         coordinates=False).eval()
    assert full(torch.rand(1, 3, 24, 24)).shape == (1, 1, 24, 24)
    for bad in (torch.rand(2, 3, 16, 16), torch.rand(2, 4, 32, 32), torch.rand(3, 32, 32), torch.rand(1, 3, 32, 16)):
        with pytest.raises(ValueError, match=r"must be \(B, 3, 32, 32\)"):
            net(bad)
    for kwargs in ({"size": 36}, {"size": 8}, {"channels": (8, 8)}, {"dilations": (0,)}):
        with pytest.raises(ValueError, match="visibility net"):
            VisibilityNet(**kwargs)


def test_the_coordinates_tell_where_the_centre_is() -> None:
    """A flat image gives every pixel the same input but its coordinates: the logits still vary over the crop."""
    net = VisibilityNet(size=32).eval()
    with torch.no_grad():
        logits = net(torch.full((1, 3, 32, 32), 0.5))
    assert float(logits.std()) > 0
    plain = VisibilityNet(size=32, coordinates=False, global_context=False).eval()
    with torch.no_grad():
        flat = plain(torch.full((1, 3, 32, 32), 0.5))[0, 0, 12:20, 12:20]  # away from the zero padding
    assert float(flat.std()) < 1e-5


def test_onnx_graph_matches_torch() -> None:
    ort = pytest.importorskip("onnxruntime")
    from matl.inference.export import onnx_bytes

    torch.manual_seed(0)
    net = VisibilityNet(size=32, full_channels=4)
    for module in net.modules():  # batch-norm statistics that are not the identity: folded in the graph
        if isinstance(module, torch.nn.BatchNorm2d):
            module.running_mean.uniform_(-0.5, 0.5)
            module.running_var.uniform_(0.5, 2.0)
    net.eval()
    images = torch.rand(3, 3, 32, 32, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        graph = onnx_bytes(net, images[:1], ("logits",))
        expected = net(images).numpy()
    session = ort.InferenceSession(graph, providers=["CPUExecutionProvider"])
    got = session.run(None, {"images": images.numpy()})[0]
    assert got.shape == (3, 1, 32, 32) and np.abs(got - expected).max() < 1e-4


def test_losses_and_iou() -> None:
    target = torch.zeros(2, 1, 8, 8)
    target[:, :, 2:6, 2:6] = 1.0
    right, wrong = (target * 2 - 1) * 20, (1 - target * 2) * 20
    assert float(dice_loss(right, target)) < 1e-3 and float(dice_loss(wrong, target)) > 0.9
    assert float(visibility_loss(right, target)) < float(visibility_loss(wrong, target))
    assert float(visibility_loss(right, target, dice_weight=0.0)) == pytest.approx(
        float(torch.nn.functional.binary_cross_entropy_with_logits(right, target)))
    # negative_weight by hand: one pixel of the product (logit 0: ln 2) and one of the background taken for it
    # (logit ln 3: p = 3/4, its cross-entropy ln 4), the background's counting 3 times
    logits, truth = torch.tensor([[[[0.0, math.log(3.0)]]]]), torch.tensor([[[[1.0, 0.0]]]])
    assert float(visibility_loss(logits, truth, 0.0, negative_weight=3.0)) == pytest.approx(
        (math.log(2.0) + 3.0 * math.log(4.0)) / 4.0)
    assert float(visibility_loss(logits, truth, 0.0, negative_weight=1.0)) == pytest.approx(
        (math.log(2.0) + math.log(4.0)) / 2.0)
    with pytest.raises(MatlError, match="negative_weight"):
        VisibilityModule({"size": 16, "channels": (8, 8, 8)}, negative_weight=0.0)
    # occluder_weight: only the pixel an occluder hides (covered, not visible) counts more; the floor does not
    logits3, truth3 = torch.tensor([[[[0.0, math.log(3.0), math.log(3.0)]]]]), torch.tensor([[[[1.0, 0.0, 0.0]]]])
    covered = torch.tensor([[[[1.0, 1.0, 0.0]]]])                       # the second pixel: product under an occluder
    assert float(visibility_loss(logits3, truth3, 0.0, occluder_weight=5.0, covered=covered)) == pytest.approx(
        (math.log(2.0) + 5.0 * math.log(4.0) + math.log(4.0)) / 7.0)
    assert float(visibility_loss(logits3, truth3, 0.0, occluder_weight=5.0)) == pytest.approx(  # nothing covered
        (math.log(2.0) + 2.0 * math.log(4.0)) / 3.0)
    with pytest.raises(MatlError, match="occluder_weight"):
        VisibilityModule({"size": 16, "channels": (8, 8, 8)}, occluder_weight=-1.0)
    half = target.clone()
    half[:, :, 2:4] = 0.0
    assert mask_iou(half > 0, target > 0).tolist() == [0.5, 0.5]
    assert mask_iou(torch.zeros(1, 4, 4, dtype=torch.bool), torch.zeros(1, 4, 4, dtype=torch.bool)).tolist() == [1.0]


def test_a_few_steps_fit_a_centred_square() -> None:
    torch.manual_seed(0)
    module = VisibilityModule({"size": 16, "channels": (8, 8, 8)}, lr=1e-2)
    images = torch.rand(8, 3, 16, 16)
    target = torch.zeros(8, 1, 16, 16)
    target[:, :, 4:12, 4:12] = 1.0
    images = images * 0.2 + target * 0.8
    optimiser = torch.optim.Adam(module.parameters(), lr=1e-2)
    first = None
    for _ in range(30):
        loss = visibility_loss(module.net(images), target)
        first = float(loss.detach()) if first is None else first
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    assert float(loss.detach()) < 0.5 * first


def test_published_checkpoints_load_and_bad_files_are_one_line(tmp_path: Path) -> None:
    net = VisibilityNet(size=32, channels=(4, 6, 8)).eval()
    path = tmp_path / "fg.ckpt"
    torch.save({"format": VISIBILITY_FORMAT, "state_dict": net.state_dict(), "matl_visibility": net.config}, path)
    loaded = load_visibility_net(path)
    x = torch.rand(1, 3, 32, 32)
    with torch.no_grad():
        assert torch.equal(loaded(x), net(x)) and not loaded.training
    assert load_visibility_net(path, size=48).size == 48  # the same weights at another working size
    with pytest.raises(MatlError, match="not found"):
        load_visibility_net(tmp_path / "missing.ckpt")
    torch.save({"state_dict": {}}, tmp_path / "other.ckpt")
    with pytest.raises(MatlError, match="not a visibility checkpoint"):
        load_visibility_net(tmp_path / "other.ckpt")
    (tmp_path / "text.ckpt").write_text("hello")
    with pytest.raises(MatlError, match="cannot be read safely"):
        load_visibility_net(tmp_path / "text.ckpt")
    torch.save({"format": VISIBILITY_FORMAT, "state_dict": net.state_dict(),
                "matl_visibility": {**net.config, "channels": [4, 6, 9]}}, tmp_path / "mismatch.ckpt")
    with pytest.raises(MatlError, match="does not fit"):
        load_visibility_net(tmp_path / "mismatch.ckpt")


def test_the_shipped_network_loads_safely_and_is_small() -> None:
    from matl.models.visibility import FOREGROUND_WEIGHTS

    if not FOREGROUND_WEIGHTS.is_file():
        pytest.skip("this install ships no visibility network")
    assert FOREGROUND_WEIGHTS.stat().st_size < 1_000_000
    slim = torch.load(FOREGROUND_WEIGHTS, weights_only=True)
    assert slim["format"] == VISIBILITY_FORMAT and set(slim) == {"format", "state_dict", "matl_visibility",
                                                                  "matl_metrics"}
    net = load_visibility_net()
    assert net.size == slim["matl_visibility"]["size"] and 0.0 < slim["matl_metrics"]["val_iou"] <= 1.0
    assert net(torch.rand(1, 3, net.size, net.size)).shape == (1, 1, net.size, net.size)
