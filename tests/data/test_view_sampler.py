"""Random cameras around a plane: their homographies, tilt, framing, and agreement with real renders."""

from __future__ import annotations

import math

import numpy as np
import torch

from matl.data.catalog.rendering import ViewCamera, ViewRenderer, plane_half_width
from matl.data.catalog.shapes import PlaneView
from matl.data.view_sampler import ViewSampler, bounding_box_corners
from matl.geometry import warp_image
from tests.data.conftest import TinyCatalog

FRONT = PlaneView("front", np.array([0.0, -1.0, 0.0]), np.array([0.0, 0.0, 1.0]), (4.0, 6.0))


def test_frontal_view_has_identity_homography() -> None:
    half, offset, size = 5.0, 1.5, 64
    sampler = ViewSampler(tilt_deg=(0.0, 0.0), rotation_deg=(0.0, 0.0), scale=(1.0, 1.0), translation=(0.0, 0.0))
    cams, H = sampler.sample(FRONT, offset, half, np.zeros((8, 3)) + 0.1, size, 1, np.random.default_rng(0))
    assert isinstance(cams[0], ViewCamera)
    assert np.allclose(H[0], np.eye(3), atol=1e-9)
    # A rolled camera gives a pure rotation about the image centre; scale 1.2 enlarges by 1.2.
    rolled = ViewSampler(tilt_deg=(0.0, 0.0), rotation_deg=(90.0, 90.0), scale=(1.2, 1.2), translation=(0.0, 0.0))
    _, H = rolled.sample(FRONT, offset, half, np.zeros((8, 3)), size, 1, np.random.default_rng(0))
    A = H[0][:2, :2]
    assert np.allclose(A @ A.T, 1.44 * np.eye(2), atol=1e-9) and np.allclose(H[0][2, :2], 0, atol=1e-12)
    c = (size - 1) / 2
    assert np.allclose(H[0] @ [c, c, 1.0], [c, c, 1.0])


def test_tilted_view_is_projective_and_stays_inside() -> None:
    box = np.array([[x, y, z] for x in (-2, 2) for y in (-1, 1) for z in (-3, 3)], float)
    sampler = ViewSampler(tilt_deg=(30.0, 30.0))
    cams, H = sampler.sample(FRONT, 1.0, 5.0, box, 64, 8, np.random.default_rng(1))
    assert (np.abs(H[:, 2, :2]).sum(1) > 1e-4).all()  # a 30 deg tilt is not affine
    assert np.allclose(H[:, 2, 2], 1.0)
    # the tilt is exactly 30 deg: the optical axis (camera +z) makes that angle with the normal
    for cam in cams:
        assert math.isclose(float(cam.pose[:3, 2] @ FRONT.normal), math.cos(math.radians(30.0)), abs_tol=1e-9)


def test_rendered_view_matches_the_warped_canonical_on_a_box_face(tiny: TinyCatalog) -> None:
    """For a planar face the homography is exact: the canonical image warped by it lands on the render."""
    model = list(tiny.models())[1]  # the box
    size = 64
    sampler = ViewSampler(ambient=(0.72, 0.72), direct=(0.28, 0.28), light_cone_deg=0.0, tint=0.0)
    with ViewRenderer(size, 2) as renderer:
        canon, masks, offsets = renderer.canonical(model, tiny.fill)
        for p in (0, 4):  # front and top
            plane = model.planes[p]
            cams, H = sampler.sample(plane, float(offsets[p]), plane_half_width(plane, tiny.fill),
                                     bounding_box_corners(model), size, 4, np.random.default_rng(p))  # fmt: skip
            views, _ = renderer.render(model, cams)
            src = torch.from_numpy(canon[p]).permute(2, 0, 1)[None].float().div(255).repeat(4, 1, 1, 1)
            warped = warp_image(src, torch.from_numpy(H).float())
            inside = warp_image(torch.from_numpy(masks[p])[None, None].float().repeat(4, 1, 1, 1),
                                torch.from_numpy(H).float())[:, 0] > 0.999  # fmt: skip
            rendered = torch.from_numpy(views).permute(0, 3, 1, 2).float().div(255)
            err = (warped - rendered).abs().mean(1)[inside].mean()
            assert inside.sum() > 200 and err < 0.06, (plane.name, float(err))
            # a wrong pose would not match: shift the homography by 3 px
            shift = torch.tensor([[1.0, 0, 3], [0, 1, 0], [0, 0, 1]])
            wrong = warp_image(src, shift @ torch.from_numpy(H).float())
            assert (wrong - rendered).abs().mean(1)[inside].mean() > 1.5 * err


def test_bounding_box_corners(tiny: TinyCatalog) -> None:
    model = list(tiny.models())[1]
    corners = bounding_box_corners(model)
    vertices = np.concatenate([p.vertices for p in model.parts])
    assert corners.shape == (8, 3)
    assert np.allclose(corners.min(0), vertices.min(0)) and np.allclose(corners.max(0), vertices.max(0))
