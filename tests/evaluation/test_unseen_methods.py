"""The unseen benchmark's methods: each one's predict options, the config built from them, the recorded command.

The config a :class:`MethodRun` builds in Python is checked against the one ``python -m matl.predict`` composes
from the recorded command line (so the command re-runs what ran), and a run in this process writes the same
lines as predict's library function called on that composed config.
"""

from __future__ import annotations

import json
import shlex
import shutil
from pathlib import Path

import numpy as np
import pytest
from omegaconf import DictConfig, OmegaConf

import matl.evaluation.unseen_methods as unseen_methods
from matl.evaluation.condition_writers import Queries
from matl.evaluation.conditions import sample_poses
from matl.evaluation.unseen_methods import MethodRun, foreground_choice, method_overrides, score_command, shared_options
from matl.geometry import HomographySampler
from matl.inference.api import PRETRAINED
from matl.inference.files import predict
from matl.utils.errors import MatlError, group_options
from tests.conftest import compose_config
from tests.evaluation.test_condition_writers import _write, textured_set


def _cfg(tmp_path: Path, *overrides: str) -> DictConfig:
    return compose_config("unseen", ["ckpt=unused.ckpt", *overrides], tmp_path / "run")


def _shared(cfg: DictConfig, folder: Path, threshold: float | str | None = None) -> dict:
    return shared_options(cfg, Path("/models/m.ckpt"), folder, threshold, 1.0, 1.0)


def _composed(run: MethodRun, tmp_path: Path) -> DictConfig:
    """predict's config composed from the run's recorded command line, as ``python -m matl.predict`` composes it."""
    args = shlex.split(run.command)
    assert args[:3] == ["python", "-m", "matl.predict"]
    return compose_config("predict", args[3:], tmp_path / "predict")


def _plain(cfg: DictConfig) -> dict:
    """A config's content, without the run folder (``paths``, ``viz_dir``), which predict writes nothing to here."""
    content = OmegaConf.to_container(cfg, resolve=False)
    return {k: v for k, v in content.items() if k not in ("paths", "viz_dir")}


def test_method_commands_list_predicts_options(tmp_path: Path) -> None:
    cfg = _cfg(tmp_path)
    shared = _shared(cfg, Path("/bench/clean"))
    files = ("ckpt=/models/m.ckpt gallery=/bench/clean/gallery images=/bench/clean/queries gallery_fill=1.0 "
             "query_fill=1.0 batch_size=64 device=cpu")
    open_set = "open_set_quantile=0.94 open_set_statistic=verify calibration_planes=2000 verify_top_k=8 " \
               "verify_shortlist=64 verify_max=0.1 verify_blur=1.0 verify_refine=true verify_statistic=patches " \
               "verify_min_visible=0.3 verify_occluded_copies=0.0 verify_occluder_margin=5 " \
               "refine_check=judge keypoint_pose=unverified flow_pose=always pose_judge=both lookalike_ratio=1.1 " \
               "lookalike_statistic=difference uncover=0.7"
    refined = MethodRun.of("matl_refine", cfg, shared, Path("/bench/clean/p.jsonl"))
    assert refined.command == (f"python -m matl.predict {files} threshold=null {open_set} refine=true "
                               "foreground=learned runtime=onnxruntime out=/bench/clean/p.jsonl")
    plain = MethodRun.of("matl", _cfg(tmp_path, "foreground=none", "runtime=torch"), shared, Path("/o.jsonl"))
    assert plain.command.endswith(f"threshold=null {open_set} refine=false foreground=none runtime=torch out=/o.jsonl")
    for baseline in ("sift_ecc", "xfeat_lighterglue"):  # a closed set, whatever the benchmark's threshold
        run = MethodRun.of(baseline, cfg, _shared(cfg, Path("/bench/clean"), "auto"), Path("/o.jsonl"))
        assert run.command == (f"python -m matl.predict {files} {open_set} baseline={baseline} threshold=null "
                               "out=/o.jsonl")
        assert run.config().baseline == OmegaConf.to_container(cfg.baselines[baseline], resolve=True)
    quoted = MethodRun.of("matl", cfg, _shared(cfg, Path("/my bench")), Path("/my bench/p.jsonl"))
    assert {"gallery='/my bench/gallery'", "out='/my bench/p.jsonl'"} <= set(shlex.split(quoted.command))  # Hydra's
    assert score_command(Path("/b/p.jsonl"), Path("/b/truth.jsonl"), Path("/m.ckpt"), 1.0, 0.6, Path("/b/s")) == (
        "python -m matl.score predictions=/b/p.jsonl truth=/b/truth.jsonl ckpt=/m.ckpt gallery_fill=1.0 "
        "query_fill=0.6 out=/b/s")
    assert method_overrides("sift") == []  # called as a function: no command-line overrides
    assert foreground_choice(cfg) == "learned"  # the default, passed on to predict
    for name in group_options("foreground"):  # each option of the group, named back from its node
        assert foreground_choice(_cfg(tmp_path, f"foreground={name}")) == name


@pytest.mark.parametrize("given", [
    [],
    ["refiner=photometric", "refiner.levels=2", "baselines.sift.ratio=0.7", "foreground.passes=1", "queries=10",
     "verify_top_k=4", "leave_out=0.5", "batch_size=8"],
    ["foreground=none", "runtime=torch", "baselines.sift_ecc.ecc_iterations=20", "open_set_statistic=ratio"],
])
def test_the_config_built_here_is_what_the_recorded_command_composes(tmp_path: Path, monkeypatch,
                                                                     given: list[str]) -> None:
    """Every method's config, the user's overrides of its groups included, equals predict's config composed from
    the method's command line: the command re-runs what ran."""
    monkeypatch.setattr(unseen_methods, "_task_overrides", lambda: ["ckpt=c", *given])
    cfg = _cfg(tmp_path, *given)
    threshold = "auto" if "leave_out=0.5" in given else None
    for method in ("matl", "matl_refine", "sift", "sift_ecc"):
        folder = tmp_path / "a condition"  # a space: quoted for Hydra, then for the shell
        run = MethodRun.of(method, cfg, _shared(cfg, folder, threshold), folder / "p.jsonl")
        assert _plain(run.config()) == _plain(_composed(run, tmp_path)), method
    if given:
        refined = MethodRun.of("matl_refine", cfg, _shared(cfg, tmp_path), tmp_path / "p.jsonl")
        if "refiner=photometric" in given:  # the refiner's choice and keys reach matl_refine only
            assert refined.overrides == ("refiner=photometric", "refiner.levels=2", "foreground.passes=1")
            assert refined.config().refiner.levels == 2 and refined.config().refiner._target_.endswith(
                "PhotometricRefiner")
            assert method_overrides("matl") == ["foreground.passes=1"]
            assert method_overrides("sift") == ["baseline.ratio=0.7"]
            assert refined.config().verify_top_k == 4 and refined.config().batch_size == 8
            assert refined.config(batch_size=1).batch_size == 1
        else:
            assert refined.config().foreground == {"_target_": None} and refined.config().runtime == "torch"


def test_a_run_in_this_process_writes_what_predict_writes_from_the_command(tmp_path: Path) -> None:
    """MATL and SIFT+RANSAC on the same files: a run here and predict's library function on the config composed
    from the recorded command write the same lines; a user's mistake is one line naming the method."""
    cs = textured_set(size=64)
    q = Queries(cs, *sample_poses(cs, HomographySampler(rotation_deg=(-20.0, 20.0)), 3, 3), 3, None,
                list(range(cs.num_objects)), _cfg(tmp_path))
    _write(q, "clean", tmp_path)
    cfg = _cfg(tmp_path, "verify_top_k=2")
    shared = shared_options(cfg, PRETRAINED, tmp_path, None, 1.0, 1.0)
    for method in ("matl", "sift"):
        run = MethodRun.of(method, cfg, shared, tmp_path / f"predictions_{method}.jsonl")
        summary = run.run()
        assert summary["predicted"] == 3 and (method == "matl" or summary["baseline"] == "sift")
        again = _composed(run, tmp_path)
        again.out = str(tmp_path / f"again_{method}.jsonl")
        predict(again)
        lines = [json.loads(line) for line in (tmp_path / f"predictions_{method}.jsonl").read_text().splitlines()]
        assert lines == [json.loads(line) for line in Path(again.out).read_text().splitlines()]
        assert [r["image"] for r in lines] == [str(tmp_path / "queries" / f"q{i:04d}.png") for i in range(3)]
        assert all(np.isfinite(np.array(r["H"])).all() for r in lines if r["H"] is not None)
        recognizer = run.recognizer()
        assert recognizer.batch_size == 1
    empty = tmp_path / "empty"  # the same gallery, no query file
    shutil.copytree(tmp_path / "gallery", empty / "gallery")
    (empty / "queries").mkdir()
    run = MethodRun.of("matl", cfg, shared_options(cfg, PRETRAINED, empty, None, 1.0, 1.0), empty / "p.jsonl")
    with pytest.raises(MatlError, match=r"^matl: images=.*/empty/queries holds no files$"):
        run.run()
    assert not (empty / "p.jsonl").exists()


def test_keypoint_baseline_on_files_frames_like_predict(tmp_path: Path) -> None:
    """predict's baseline path: the enrolled files framed by enrol_gallery, the pose back in file pixels."""
    from matl.baselines.sift import SiftRansacMatcher
    from matl.inference.baseline_files import KeypointFileRecognizer
    from matl.inference.files import predict_files

    cs = textured_set()
    q = Queries(cs, *sample_poses(cs, HomographySampler(rotation_deg=(-20.0, 20.0)), 4, 3), 3, None,
                list(range(cs.num_objects)), _cfg(tmp_path))
    truth = _write(q, "clean", tmp_path)
    rec = KeypointFileRecognizer(SiftRansacMatcher(), "sift", 64, 2).enrol(tmp_path / "gallery")
    assert len(rec.gallery) == cs.num_planes * 2 and rec.threshold is None
    records: list[dict] = []
    files = [tmp_path / t["image"] for t in truth]
    done, bad = predict_files(rec, files, records.append, show_progress=False)
    assert done == 4 and bad == [] and [r["image"] for r in records] == [str(f) for f in files]
    right = 0
    for record, t in zip(records, truth, strict=True):
        assert record["distance"] is None and (record["object"] is None) == (record["H"] is None)
        if record["object"] == t["object"] and record["plane"] == t["plane"]:
            # the corners of the textured rectangle, in gallery file pixels (80 px)
            corners = np.array([[16, 20, 1], [63, 20, 1], [63, 55, 1], [16, 55, 1.0]]).T
            a, b = np.array(record["H"]) @ corners, np.array(t["H"]) @ corners
            assert np.abs(a[:2] / a[2] - b[:2] / b[2]).max() < 2.5
            right += 1
    assert right >= 3
