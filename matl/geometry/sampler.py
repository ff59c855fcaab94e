"""Random homographies for positives, negatives and test queries (paper Sec. 5.1).

Decomposition (our decision; the paper only gives ranges). In pixel coordinates with the image
centre ``c`` moved to the origin::

    query_H_canon = C · T(t) · R(theta) · S(s) · Sh(k) · P(phi_x, phi_y) · C^-1

* ``T``: translation, each axis uniform in ``translation`` x image size (paper: +-25 px at 100 px).
* ``R``: in-plane rotation, uniform in ``rotation_deg`` (paper: +-180 deg), counter-clockwise on screen.
* ``S``: isotropic scale, uniform in ``scale`` (paper: [0.8, 1.2]).
* ``Sh``: horizontal shear ``[[1, k, 0], [0, 1, 0], [0, 0, 1]]``, uniform in ``shear`` (default off).
* ``P``: the paper's "remaining parameters" in [-0.5, 0.5], read as two *out-of-plane tilt angles in
  radians* (+-28.6 deg). The plane, rotated about its centre by ``Ry(phi_y) · Rx(phi_x)`` and seen
  by a pinhole camera of focal length ``D = focal x width`` at distance ``D`` (so the untilted plane
  images 1:1), induces exactly ``[[r11, r12, 0], [r21, r22, 0], [r31 / D, r32 / D, 1]]``. This
  reading keeps every sample a view a real camera could take of a planar face, is well
  conditioned over the whole range, and gives the two projective degrees of freedom that
  similarity plus shear lack.
* ``focal`` (default 3 image widths): the 100 px image is a *crop* around one product of a robot
  camera's frame, so its focal length in crop widths is the camera's focal length divided by the
  crop's share of the frame (e.g. ~0.8 frame widths / a 0.27-wide crop = 3). ``focal=1`` would be a
  camera whose whole field of view is the crop (53 deg across 100 px): at +-0.5 rad its perspective
  alone moves the image corners by 8.9 px (median) from the best affine fit (2.9 px at 3);
  docs/decisions.md.

``keep_inside`` rejection-samples (vectorised, ``max_tries`` candidates per item) so that the
object's footprint (corners of its mask's bounding box) stays in the frame; where no candidate
fits, the one that leaves the frame least is taken. All ranges are config values.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from matl.geometry.homography import Size, scale_to_unit, transfer_points


@dataclass
class HomographySampler:
    """Samples ``query_H_canon`` pixel homographies.

    Args:
        translation: range of the translation per axis, as a fraction of the image size.
        rotation_deg: range of the in-plane rotation in degrees.
        scale: range of the isotropic scale.
        tilt: range of each of the two out-of-plane tilt angles, radians.
        shear: range of the horizontal shear.
        focal: focal length of the virtual camera used for tilts, in image widths.
        keep_inside: rejection-sample so that the object footprint stays inside the frame.
        max_tries: candidates drawn per item when ``keep_inside``.
    """

    translation: tuple[float, float] = (-0.25, 0.25)
    rotation_deg: tuple[float, float] = (-180.0, 180.0)
    scale: tuple[float, float] = (0.8, 1.2)
    tilt: tuple[float, float] = (-0.5, 0.5)
    shear: tuple[float, float] = (0.0, 0.0)
    focal: float = 3.0
    keep_inside: bool = True
    max_tries: int = 16

    def __post_init__(self) -> None:
        for name in ("translation", "rotation_deg", "scale", "tilt", "shear"):
            low, high = (float(v) for v in getattr(self, name))
            if low > high:
                raise ValueError(f"homography.{name} must be [low, high] with low <= high, got [{low}, {high}]")
            setattr(self, name, (low, high))
        if self.scale[0] <= 0:
            raise ValueError(f"homography.scale must be positive, got {list(self.scale)}")
        if self.focal <= 0:
            raise ValueError(f"homography.focal must be > 0 (image widths), got {self.focal}")
        if self.max_tries < 1:
            raise ValueError(f"homography.max_tries must be >= 1, got {self.max_tries}")

    def compose(self, params: torch.Tensor, size: Size) -> torch.Tensor:
        """Build homographies from parameters ``(..., 7)`` = (tx_px, ty_px, deg, scale, shear, phi_x, phi_y)."""
        height, width = size
        tx, ty, deg, s, k, phx, phy = params.unbind(-1)
        depth = self.focal * width
        theta = torch.deg2rad(deg)
        c, sn = torch.cos(theta), torch.sin(theta)
        zero, one = torch.zeros_like(tx), torch.ones_like(tx)

        def mat(rows: list[list[torch.Tensor]]) -> torch.Tensor:
            return torch.stack([torch.stack(r, -1) for r in rows], -2)

        cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
        centre = mat([[one, zero, one * cx], [zero, one, one * cy], [zero, zero, one]])
        uncentre = mat([[one, zero, -one * cx], [zero, one, -one * cy], [zero, zero, one]])
        translate = mat([[one, zero, tx], [zero, one, ty], [zero, zero, one]])
        rotate = mat([[c, sn, zero], [-sn, c, zero], [zero, zero, one]])
        scale = mat([[s, zero, zero], [zero, s, zero], [zero, zero, one]])
        shear = mat([[one, k, zero], [zero, one, zero], [zero, zero, one]])
        cx_, sx_ = torch.cos(phx), torch.sin(phx)
        cy_, sy_ = torch.cos(phy), torch.sin(phy)
        # R = Ry(phi_y) @ Rx(phi_x); only columns 1-2 matter for points on the plane z = 0.
        r11, r12 = cy_, sy_ * sx_
        r21, r22 = zero, cx_
        r31, r32 = -sy_, cy_ * sx_
        tilt = mat([[r11, r12, zero], [r21, r22, zero], [r31 / depth, r32 / depth, one]])
        return scale_to_unit(centre @ translate @ rotate @ scale @ shear @ tilt @ uncentre)

    def sample_params(self, n: int, size: Size, generator: torch.Generator) -> torch.Tensor:
        """Draw ``(n, 7)`` parameters uniformly in the configured ranges (pixel translations)."""
        height, width = size
        ranges = torch.tensor([
            [self.translation[0] * width, self.translation[1] * width],
            [self.translation[0] * height, self.translation[1] * height],
            list(self.rotation_deg), list(self.scale), list(self.shear), list(self.tilt), list(self.tilt),
        ], dtype=torch.float64)
        u = torch.rand(n, 7, generator=generator, dtype=torch.float64)
        return ranges[:, 0] + u * (ranges[:, 1] - ranges[:, 0])

    def sample(self, n: int, size: Size, generator: torch.Generator,
               footprints: torch.Tensor | None = None) -> torch.Tensor:
        """Sample ``n`` homographies ``query_H_canon`` ``(n, 3, 3)`` (float64).

        Args:
            footprints: ``(n, 4, 2)`` pixel corners of each source object's bounding box; used
                with ``keep_inside`` to keep the object in the frame.
        """
        if not self.keep_inside or footprints is None:
            return self.compose(self.sample_params(n, size, generator), size)
        tries = self.max_tries
        params = self.sample_params(n * tries, size, generator).view(n, tries, 7)
        H = self.compose(params, size)  # (n, tries, 3, 3)
        corners = footprints.to(torch.float64)[:, None].expand(n, tries, 4, 2).reshape(-1, 4, 2)
        mapped = transfer_points(H.reshape(-1, 3, 3), corners).view(n, tries, 4, 2)
        height, width = size
        limits = torch.tensor([width - 1.0, height - 1.0], dtype=torch.float64)
        outside = (-mapped).clamp(min=0) + (mapped - limits).clamp(min=0)
        violation = torch.nan_to_num(outside.sum(dim=(-1, -2)), nan=float("inf"))
        # a corner behind the camera (w <= 0) is never acceptable
        w = (H.reshape(-1, 3, 3)[:, None, 2, :2] * corners).sum(-1) + 1.0
        violation = violation + (w <= 0).view(n, tries, 4).any(-1).double() * 1e9
        best = violation.argmin(dim=1)  # first zero-violation candidate, else the least bad
        return H[torch.arange(n), best]
