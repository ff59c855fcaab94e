"""The alignment stage: identity start, shapes, the direction of the residual, training through it, loading."""

from __future__ import annotations

import math
from pathlib import Path

import hydra
import pytest
import torch
from kornia.geometry.transform import get_perspective_transform
from omegaconf import OmegaConf, open_dict

from matl.data.gallery import Gallery
from matl.geometry import (
    anchor_H_canon,
    normalised_to_pixel,
    pixel_to_normalised,
    scale_to_unit,
    transfer_points,
    warp_image,
)
from matl.losses import TripletLoss
from matl.models.align import SQUARE, AlignmentStage, square_to_quad
from matl.models.checkpoint import build_model
from matl.models.feature import FeatureNet
from matl.models.module import MATLModule
from matl.models.recognizer import TensorRecognizer
from matl.models.stn import HomographyRegressor, SpatialTransformer
from matl.utils.errors import MatlError
from tests.conftest import compose_config

S = 32
ADAM = "{_target_:torch.optim.Adam,_partial_:true,lr:0.001}"   # model.align.optimizer on the command line


def force_offsets(stage: AlignmentStage, offsets: torch.Tensor) -> None:
    """Make every step of ``stage`` predict the ``(4, 2)`` normalised corner ``offsets``, whatever the images."""
    reg = stage.regressor
    with torch.no_grad():
        reg.fc2.weight.zero_()
        reg.fc2.bias.copy_(torch.atanh(offsets.flatten() / reg.max_offset))


def textured_plane(seed: int = 0) -> torch.Tensor:
    """``(1, 3, S, S)`` a smooth textured product on a black background."""
    g = torch.Generator().manual_seed(seed)
    image = torch.zeros(1, 3, S, S)
    patch = torch.nn.functional.interpolate(torch.rand(1, 3, 4, 4, generator=g), size=(18, 14), mode="bilinear",
                                            align_corners=True)
    image[:, :, 7:25, 9:23] = patch
    return image


def shift(dx: float, dy: float) -> torch.Tensor:
    return torch.tensor([[[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]]])


def random_stn(seed: int = 0) -> SpatialTransformer:
    """An STN whose (otherwise zero) last layer gives a non-trivial pose."""
    torch.manual_seed(seed)
    stn = SpatialTransformer(HomographyRegressor(image_size=S), image_size=S, iterations=2)
    with torch.no_grad():
        stn.regressor.fc2.bias.copy_(torch.tensor([0.05, -0.03, 0.04, 0.02, -0.04, -0.05, 0.01, -0.02]))
    return stn.eval()


# ------------------------------------------------------------------------------------ the residual
def test_square_to_quad_is_exact_identity_at_zero_and_matches_kornia() -> None:
    assert torch.equal(square_to_quad(torch.zeros(3, 4, 2)), torch.eye(3).expand(3, 3, 3))
    g = torch.Generator().manual_seed(0)
    offsets = (torch.rand(6, 4, 2, generator=g, dtype=torch.float64) - 0.5) * 0.99   # within +-0.5: convex
    square = torch.tensor(SQUARE, dtype=torch.float64).expand(6, 4, 2)
    H = square_to_quad(offsets)
    assert torch.allclose(H, get_perspective_transform(square, square + offsets), atol=1e-12)
    assert torch.allclose(transfer_points(H, square), square + offsets, atol=1e-12)
    assert torch.all(H[:, 2, 2] == 1)


def test_zero_initialised_stage_is_exactly_the_identity() -> None:
    stage = AlignmentStage(S).eval()
    g = torch.Generator().manual_seed(1)
    queries, anchors = torch.rand(3, 3, S, S, generator=g), torch.rand(3, 3, S, S, generator=g)
    H = scale_to_unit(torch.eye(3) + 0.05 * torch.randn(3, 3, 3, generator=g))
    out = stage(queries, anchors, H)
    assert torch.equal(out.residual, torch.eye(3).expand(3, 3, 3))
    assert torch.equal(out.query_H_anchor, H) and not out.degenerate.any()
    assert out.warped.shape == queries.shape
    assert stage.infer(queries, anchors, H).warped is None


def test_zero_initialised_stage_leaves_the_recognizers_pose_unchanged() -> None:
    torch.manual_seed(0)
    N, P = 4, 3
    canon = torch.cat([textured_plane(i) for i in range(P)])
    rot = anchor_H_canon(N, (S, S), torch.float64)
    anchors = torch.stack([warp_image(canon, rot[k].expand(P, 3, 3)) for k in range(N)], 1)
    gallery = Gallery(anchors.reshape(P * N, 3, S, S), torch.arange(P).repeat_interleave(N),
                      torch.arange(P).repeat_interleave(N), torch.arange(N).repeat(P), rot.repeat(P, 1, 1),
                      [f"o{i}" for i in range(P)], [f"p{i}" for i in range(P)])
    feature, stn = FeatureNet().eval(), random_stn()
    queries = warp_image(anchors[:, 1], shift(1.5, -1.0).expand(P, 3, 3))
    for fast in (True, False):  # the compiled path (batches up to 8) and the forward path
        plain = TensorRecognizer(feature, stn, gallery, fast=fast)(queries)
        aligned = TensorRecognizer(feature, stn, gallery, fast=fast, align=AlignmentStage(S).eval())(queries)
        assert torch.equal(plain.gallery_index, aligned.gallery_index)
        assert torch.equal(plain.query_H_anchor, aligned.query_H_anchor)
        assert torch.equal(plain.query_H_canon, aligned.query_H_canon)
        assert torch.equal(plain.warped, aligned.warped)


def test_shapes_and_config_values_are_checked_early() -> None:
    stage = AlignmentStage(S)
    q, H = torch.rand(2, 3, S, S), torch.eye(3).expand(2, 3, 3)
    with pytest.raises(ValueError, match=r"anchors must be \(B, 3, 32, 32\), got \(2, 3, 16, 16\)"):
        stage(q, torch.rand(2, 3, 16, 16), H)
    with pytest.raises(ValueError, match=r"one anchor \(and warp\) per query, got 2 queries, 3 anchors"):
        stage(q, torch.rand(3, 3, S, S), H)
    with pytest.raises(ValueError, match=r"query_H_anchor must be \(2, 3, 3\)"):
        stage(q, q, torch.eye(3)[None])
    with pytest.raises(ValueError, match=r"warped must be"):
        stage(q, q, H, warped=torch.rand(2, 1, S, S))
    for kwargs, key in (({"iterations": 0}, "iterations"), ({"max_offset": 0.7}, "max_offset"),
                        ({"downsample": 0}, "downsample"), ({"channels": ()}, "channels"),
                        ({"max_condition": 1.0}, "max_condition"), ({"channels": (8,) * 6}, "pooling layers")):
        with pytest.raises(MatlError, match=key):
            AlignmentStage(S, **kwargs)
    with pytest.raises(MatlError, match=r"model\.align needs an STN"):
        MATLModule(FeatureNet(), None, TripletLoss(), image_size=S, align=AlignmentStage(S))
    with pytest.raises(MatlError, match=r"model\.align\.image_size=32 differs"):
        MATLModule(FeatureNet(), random_stn(), TripletLoss(), image_size=48, align=AlignmentStage(S))
    with pytest.raises(MatlError, match=r"model\.appearance_mask='fg' is invalid"):
        MATLModule(FeatureNet(), random_stn(), TripletLoss(), image_size=S, appearance_mask="fg")


def test_the_residual_composes_on_the_right_of_query_H_anchor() -> None:
    """``query_H_anchor <- query_H_anchor @ residual`` (normalised), residual = where the anchor's corners
    are found in the warp so far: a query that is the anchor moved by (+3, +2) px, with the STN at the
    identity, is aligned by the offsets (+3, +2) px and then its warp is the anchor."""
    anchor = textured_plane()
    query = warp_image(anchor, shift(3.0, 2.0))
    t = torch.tensor([3.0, 2.0]) * 2 / (S - 1)  # pixels -> normalised units
    stage = AlignmentStage(S, iterations=1).eval()
    force_offsets(stage, t.expand(4, 2))
    out = stage(query, anchor, torch.eye(3)[None])
    assert torch.allclose(out.query_H_anchor, shift(3.0, 2.0), atol=1e-5)
    inner = (slice(None), slice(None), slice(4, S - 4), slice(4, S - 4))
    assert torch.allclose(out.warped[inner], anchor[inner], atol=1e-5)
    # any start, any number of steps: start @ R @ R ... with R the forced residual
    g = torch.Generator().manual_seed(3)
    offsets = (torch.rand(4, 2, generator=g) - 0.5) * 0.2
    R = square_to_quad(offsets[None])
    start = scale_to_unit(torch.eye(3) + 0.03 * torch.randn(2, 3, 3, generator=g))
    start_norm = pixel_to_normalised(start, (S, S))
    for steps in (1, 3):
        stage = AlignmentStage(S, iterations=steps).eval()
        force_offsets(stage, offsets)
        out = stage(torch.rand(2, 3, S, S, generator=g), torch.rand(2, 3, S, S, generator=g), start)
        expected = start_norm @ torch.linalg.matrix_power(R, steps)
        assert torch.allclose(out.query_H_anchor_norm, expected, atol=1e-5)
        assert torch.allclose(out.query_H_anchor, normalised_to_pixel(expected, (S, S)), atol=1e-4)
        assert torch.allclose(out.residual, torch.linalg.matrix_power(R, steps).expand(2, 3, 3), atol=1e-5)


def test_recognizer_aligns_to_the_searched_anchor_and_keeps_recognition() -> None:
    torch.manual_seed(0)
    N, P = 4, 2
    canon = torch.cat([textured_plane(i) for i in range(P)])
    rot = anchor_H_canon(N, (S, S), torch.float64)
    anchors = torch.stack([warp_image(canon, rot[k].expand(P, 3, 3)) for k in range(N)], 1)
    gallery = Gallery(anchors.reshape(P * N, 3, S, S), torch.arange(P).repeat_interleave(N),
                      torch.arange(P).repeat_interleave(N), torch.arange(N).repeat(P), rot.repeat(P, 1, 1),
                      ["a", "b"], ["p", "p"])
    feature, stn = FeatureNet().eval(), random_stn()
    stage = AlignmentStage(S, iterations=2).eval()
    force_offsets(stage, torch.full((4, 2), 0.03))
    queries = warp_image(anchors[:, 2], shift(1.0, 0.5).expand(P, 3, 3))
    plain = TensorRecognizer(feature, stn, gallery)(queries)
    aligned = TensorRecognizer(feature, stn, gallery, align=stage)(queries)
    for name in ("gallery_index", "object_index", "anchor_index", "distance", "warped", "degenerate", "features"):
        assert torch.equal(getattr(plain, name), getattr(aligned, name)), name
    expected = stage.infer(queries, gallery.images[plain.gallery_index], plain.query_H_anchor, plain.warped)
    assert torch.equal(aligned.query_H_anchor, expected.query_H_anchor)
    pose = scale_to_unit(expected.query_H_anchor.double() @ gallery.anchor_H_canon[plain.gallery_index].double())
    assert torch.allclose(aligned.query_H_canon, pose, atol=1e-9)
    assert not torch.allclose(aligned.query_H_anchor, plain.query_H_anchor, atol=1e-3)


# ------------------------------------------------------------------------------------ training
def random_batch(B: int, N: int, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    anchors = torch.zeros(B, N, 3, S, S)
    anchors[..., 6:26, 8:24] = torch.rand(B, N, 3, 20, 16, generator=g)
    positive = warp_image(anchors[:, 0], shift(1.0, -2.0).expand(B, 3, 3))
    return {"anchors": anchors, "positive": positive, "negative": torch.rand(B, 3, S, S, generator=g),
            "object": torch.arange(B), "neg_object": torch.arange(B) + B}


def module(align: AlignmentStage | None, seed: int = 0, **kwargs) -> MATLModule:
    torch.manual_seed(seed)
    feature = FeatureNet()
    stn = SpatialTransformer(HomographyRegressor(image_size=S), image_size=S, iterations=2)
    with torch.no_grad():
        stn.regressor.fc2.bias.normal_(0.0, 0.02)
    return MATLModule(feature, stn, TripletLoss(), image_size=S, appearance_levels=2, appearance="symmetric",
                      align=align, **kwargs)


def _stage_with_a_nonzero_start() -> AlignmentStage:
    stage = AlignmentStage(S, iterations=2)
    force_offsets(stage, torch.full((4, 2), 0.02))
    return stage


def test_gradients_flow_into_the_stage_and_detach_input_keeps_the_stns_own() -> None:
    batch = random_batch(4, 4)
    plain = module(None)
    plain.training_step(batch, 0).backward()
    for detach in (True, False):
        stage = _stage_with_a_nonzero_start()
        stage.detach_input = detach
        model = module(stage)
        loss = model.training_step(batch, 0)
        assert math.isfinite(float(loss))
        loss.backward()
        grads = [p.grad for p in model.align.parameters()]
        assert all(g is not None for g in grads) and sum(float(g.abs().sum()) for g in grads) > 0
        stn_same = all(torch.allclose(a.grad, b.grad, atol=1e-7, rtol=1e-5)
                       for a, b in zip(model.stn.parameters(), plain.stn.parameters(), strict=True))
        assert stn_same == detach  # detached: the stage's loss does not reach s(); else it does


def test_stage_loss_is_the_appearance_of_the_final_homography() -> None:
    """The stage's term of the loss compares the anchor with the positive warped by the final homography:
    a stage forced onto the true pose of the positive has (almost) no forward term left."""
    batch = random_batch(2, 4)
    model = module(None)
    anchor = batch["anchors"][:, 0]
    true = shift(1.0, -2.0).expand(2, 3, 3)
    warped = warp_image(batch["positive"], torch.linalg.inv(true))
    good = model.pair_appearance(anchor, batch["positive"], warped, true, None)
    bad = model.pair_appearance(anchor, batch["positive"], batch["positive"], torch.eye(3).expand(2, 3, 3), None)
    assert float(good) < 0.2 * float(bad)


def test_masked_training_uses_the_batch_masks_or_the_fallback() -> None:
    batch = random_batch(3, 4)
    model = module(_stage_with_a_nonzero_start(), appearance_mask="foreground")
    fallback = model.anchor_masks(batch)
    assert fallback.shape == (3, 4, 1, S, S) and set(fallback.unique().tolist()) == {0.0, 1.0}
    assert torch.equal(fallback, (batch["anchors"].amax(dim=2, keepdim=True) > 0).float())
    loss_fallback = model.training_step(batch, 0)
    given = dict(batch, anchor_masks=fallback.clone())
    assert torch.equal(model.training_step(given, 0), loss_fallback)
    with pytest.raises(ValueError, match=r"anchor_masks'\] must be \(3, 4, 1, 32, 32\)"):
        model.training_step(dict(batch, anchor_masks=fallback[:, :, :, :16]), 0)
    unmasked = module(None).training_step(batch, 0)
    assert not torch.equal(loss_fallback, unmasked)


# ------------------------------------------------------------------------------------ configs and checkpoints
def test_a_training_step_composes_from_the_real_configs(tmp_path: Path) -> None:
    cfg = compose_config("train", ["model/align=corners", "model.appearance_mask=foreground", "scale=smoke"],
                         tmp_path)
    assert cfg.model.align._target_ == "matl.models.align.AlignmentStage" and cfg.model.align.iterations == 3
    model = hydra.utils.instantiate(cfg.model)
    assert isinstance(model.align, AlignmentStage) and model.appearance_mask == "foreground"
    assert cfg.data.image_size == S
    model.train()
    loss = model.training_step(random_batch(4, cfg.N), 0)
    loss.backward()
    assert math.isfinite(float(loss)) and float(model.align.regressor.fc2.weight.grad.abs().sum()) > 0
    # off by default and in the paper's rows
    for overrides in ([], ["experiment=table1_f"], ["experiment=table2_a"], ["scale=paper"], ["model=matl_fast"]):
        composed = compose_config("train", overrides, tmp_path)
        assert composed.model.align is None and composed.model.appearance_mask == "none", overrides


def _checkpoint(model: MATLModule, model_cfg: dict) -> dict:
    return {"state_dict": model.state_dict(), "matl_config": {"model": model_cfg, "data": {"image_size": S}},
            "matl_image_size": S, "matl_num_anchors": 4}


def test_old_checkpoints_without_the_stage_still_load(tmp_path: Path) -> None:
    cfg = compose_config("train", ["scale=smoke"], tmp_path)
    OmegaConf.resolve(cfg)
    old_cfg = OmegaConf.to_container(cfg.model)
    for key in ("align", "appearance_mask"):  # keys an older config never had
        del old_cfg[key]
    old = hydra.utils.instantiate(OmegaConf.create(old_cfg))
    loaded = build_model(old_cfg, _checkpoint(old, old_cfg), "old.ckpt")
    assert loaded.align is None and loaded.appearance_mask == "none"
    # and one with the stage round-trips, stage weights included
    new_cfg = compose_config("train", ["scale=smoke", "model/align=corners"], tmp_path)
    with open_dict(new_cfg):
        OmegaConf.resolve(new_cfg)
    new_model_cfg = OmegaConf.to_container(new_cfg.model)
    new = hydra.utils.instantiate(OmegaConf.create(new_model_cfg))
    force_offsets(new.align, torch.full((4, 2), 0.01))
    reloaded = build_model(new_model_cfg, _checkpoint(new, new_model_cfg), "new.ckpt")
    assert torch.equal(reloaded.align.regressor.fc2.bias, new.align.regressor.fc2.bias)
    with pytest.raises(MatlError, match="does not fit the model of its config"):
        build_model(old_cfg, _checkpoint(new, new_model_cfg), "mixed.ckpt")  # stage weights, no stage in config


@pytest.mark.slow
def test_tiny_run_with_the_stage_trains_evaluates_and_predicts(tiny_train_cfg) -> None:
    import numpy as np

    from matl import Recognizer as ApiRecognizer
    from matl.training.fit import train

    cfg = tiny_train_cfg(["model/align=corners", "model.appearance_mask=foreground"], run="align")
    metrics = train(cfg)
    assert math.isfinite(metrics["pose_err"]) and 0 <= metrics["rec_acc"] <= 1
    ckpt = Path(cfg.paths.output_dir) / "checkpoints" / "best.ckpt"
    state = torch.load(ckpt, weights_only=True)["state_dict"]
    assert any(k.startswith("align.") for k in state)
    rec = ApiRecognizer.from_checkpoint(ckpt, threshold=None)
    assert rec.model.align is not None
    image = np.zeros((40, 40, 3), np.uint8)
    image[8:30, 10:28] = np.random.default_rng(0).integers(0, 255, (22, 18, 3), dtype=np.uint8)
    rec.add("box", "front", image)
    match = rec.predict(image)
    assert match.object == "box" and match.H is not None and np.isfinite(match.H).all()


def test_the_stage_trains_at_its_own_multiple_of_the_learning_rate() -> None:
    import functools

    optimizer = functools.partial(torch.optim.SGD, lr=0.01, momentum=0.9)
    plain = module(None, optimizer=optimizer)
    groups = plain.configure_optimizers().param_groups
    assert len(groups) == 1 and groups[0]["lr"] == 0.01
    model = module(AlignmentStage(S, lr_scale=10.0), optimizer=optimizer)
    rest, stage = model.configure_optimizers().param_groups
    assert rest["lr"] == 0.01 and math.isclose(stage["lr"], 0.1)
    assert {id(p) for p in stage["params"]} == {id(p) for p in model.align.parameters()}
    assert len(rest["params"]) + len(stage["params"]) == len(list(model.parameters()))
    with pytest.raises(MatlError, match="lr_scale"):
        AlignmentStage(S, lr_scale=0.0)


def test_a_stage_with_its_own_optimiser_is_stepped_by_it_and_the_model_by_its_own(tmp_path: Path) -> None:
    import functools

    optimizer = functools.partial(torch.optim.SGD, lr=0.01, momentum=0.9)
    adam = functools.partial(torch.optim.Adam, lr=1e-3)
    scheduler = functools.partial(torch.optim.lr_scheduler.CosineAnnealingLR, T_max=4)
    model = module(AlignmentStage(S, optimizer=adam), optimizer=optimizer)
    model.scheduler_factory = scheduler
    assert model.automatic_optimization is False
    (main, stage), schedulers = model.configure_optimizers()
    assert isinstance(main, torch.optim.SGD) and isinstance(stage, torch.optim.Adam)
    assert {id(p) for g in stage.param_groups for p in g["params"]} == {id(p) for p in model.align.parameters()}
    n_main = sum(len(g["params"]) for g in main.param_groups)
    assert n_main + len(list(model.align.parameters())) == len(list(model.parameters()))
    assert [s["scheduler"].optimizer for s in schedulers] == [main, stage]
    # without one, a single optimiser as before; a non-callable optimiser is refused
    assert module(AlignmentStage(S), optimizer=optimizer).automatic_optimization is True
    with pytest.raises(MatlError, match="optimiser factory"):
        AlignmentStage(S, optimizer=3)
    # the config value composes to an Adam factory
    cfg = compose_config("train", ["scale=smoke", "model/align=corners", f"model.align.optimizer={ADAM}"], tmp_path)
    built = hydra.utils.instantiate(cfg.model)
    assert built.automatic_optimization is False and isinstance(built.align.optimizer_factory, functools.partial)


@pytest.mark.slow
def test_tiny_run_with_the_stages_own_optimiser_trains_both(tiny_train_cfg) -> None:
    cfg = tiny_train_cfg(["model/align=corners", f"model.align.optimizer={ADAM}"], run="align_adam")
    from matl.training.fit import train

    metrics = train(cfg)
    assert math.isfinite(metrics["pose_err"])
    state = torch.load(Path(cfg.paths.output_dir) / "checkpoints" / "last.ckpt", weights_only=False)
    sgd, adam = state["optimizer_states"]
    assert "momentum_buffer" in next(iter(sgd["state"].values()))
    assert "exp_avg" in next(iter(adam["state"].values()))
    assert all(s["last_epoch"] == cfg.trainer.max_epochs for s in state["lr_schedulers"])
