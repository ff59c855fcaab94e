"""Open-set calibration of a :class:`~matl.inference.api.Recognizer`, and the calibration kept across processes.

Warped copies of every enrolled plane (the training warps, seeded by the plane's name) are embedded (for the
``verify`` statistic also posed and verified as queries are, half of them partly occluded with
``verify_statistic=patches``); their statistic against the whole gallery is the *genuine* sample, against the
gallery without their own product the *impostor* sample. The threshold is a quantile of the genuine sample
(:func:`calibrate_open_set`). The samples are kept by ``save()`` and beside an enrolled folder, keyed by
:meth:`OpenSetCalibration.calibration_key`.
"""

from __future__ import annotations

import logging
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import torch

from matl.geometry import HomographySampler, warp_image
from matl.inference.enrolment import _Plane
from matl.utils.errors import MatlError

_log = logging.getLogger("matl.inference.api")  # the recognizer's logger, whichever module of it speaks

CALIBRATION_FORMAT = 1  # bump when the calibration's samples change meaning: cached ones then miss their key
CALIBRATION_PREFIX = ".matl_calibration_"

#: ``verify_occluded_copies``: the hidden share of the plane under a copy's bar, uniform in this range
CALIBRATION_HIDDEN = (0.1, 0.5)
#: planes whose copies are embedded, posed and verified at a time: the calibration's memory stays that of so many
#: copies however large the gallery (a warehouse catalogue's copies alone would take gigabytes)
CALIBRATION_PLANES = 256


def _occluded_copies(images: torch.Tensor, names: list[str], every: int, first: int = 0
                     ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The calibration's copies ``(P * W, 3, S, S)`` (plane-major, ``names`` one per plane) with a bar across one in
    ``every`` of each plane's (:data:`CALIBRATION_HIDDEN` of the plane hidden), drawn grey (a mask that kept the
    occluder) or set to 0 and out of the visibility (a mask that left it out) by turns; the copies' visibility
    ``(P * W, 1, S, S)`` and the rows changed. ``first``: the gallery position of the first of ``names`` (the turns
    run over the whole gallery, so a gallery taken in parts gets the copies it gets whole).

    A bar is a band across the whole frame at a random angle whose two edges are quantiles of the plane's pixels
    projected on its normal, so it hides the drawn share of the plane; its grey level is uniform in [0.15, 0.85]
    (drawn) or it is set to 0 (left out of the visibility). Seeded by each plane's name: the same copies each time.
    """
    per_plane = len(images) // max(len(names), 1)
    out, visibility = images.clone(), torch.ones_like(images[:, :1])
    S = images.shape[-1]
    ys, xs = torch.meshgrid(torch.arange(S, dtype=torch.float64), torch.arange(S, dtype=torch.float64), indexing="ij")
    rows = []
    for p, name in enumerate(names):
        g = torch.Generator().manual_seed(zlib.crc32(f"{name}/occluded".encode()))
        for j in range(per_plane):
            draws = torch.rand(4, generator=g, dtype=torch.float64)  # angle, hidden share, position, grey
            if j % every != every - 1:
                continue
            row = p * per_plane + j
            plane = images[row].amax(0) > 0
            if int(plane.sum()) < 16:
                continue
            angle = float(draws[0]) * torch.pi
            along = xs * np.cos(angle) + ys * np.sin(angle)
            low, high = CALIBRATION_HIDDEN
            share = low + (high - low) * float(draws[1])
            start = float(draws[2]) * (1.0 - share)
            edges = torch.quantile(along[plane], torch.tensor([start, start + share], dtype=torch.float64))
            bar = ((along >= edges[0]) & (along <= edges[1])).to(images.device)
            if (first + p + j // every) % 2 == 0:
                out[row][:, bar] = 0.15 + 0.7 * float(draws[3])
            else:
                out[row][:, bar] = 0.0
                visibility[row][:, bar] = 0.0
            rows.append(row)
    return out, visibility, torch.tensor(rows, dtype=torch.long)


def calibrate_open_set(genuine: torch.Tensor, impostor: torch.Tensor, quantile: float) -> float:
    """The open-set threshold: the ``quantile`` quantile of the genuine statistics.

    Args:
        genuine: ``(M,)`` statistics of warped gallery copies against the whole gallery.
        impostor: ``(M',)`` the same against the gallery without their own product (unused by the
            rule; kept so the trade-off can be reported beside it).
        quantile: in (0, 1].
    """
    if not 0.0 < quantile <= 1.0:
        raise MatlError(f"open_set_quantile={quantile} is invalid: use a fraction in (0, 1]")
    if len(genuine) == 0:
        return float("inf")
    return float(torch.quantile(genuine.double(), quantile))


class OpenSetCalibration:
    """The open-set side of :class:`~matl.inference.api.Recognizer`: calibration samples, threshold, score and the
    samples' cache; a mixin of it, using its model, gallery, verification and options."""

    def _calibration_images(self, planes: list[_Plane]) -> torch.Tensor:
        """``(len(planes) * W, 3, S, S)`` the calibration's warped copies of ``planes`` (the training warps,
        seeded by each plane's name: the same copies every time), plane-major, on the recognizer's device."""
        options = getattr(self.model, "homography_config", None) or {}
        sampler = HomographySampler(**{k: v for k, v in dict(options).items() if k != "_target_"})
        size = (self.image_size, self.image_size)
        H = torch.cat([sampler.sample(self.calibration_warps, size, torch.Generator().manual_seed(
            zlib.crc32(f"{plane.object}/{plane.name}".encode()))) for plane in planes]).float()
        canon = torch.stack([p.canon_u8 for p in planes]).float().div(255.0)
        return warp_image(canon.repeat_interleave(self.calibration_warps, 0), H).to(self.device)

    def _calibration_sampled(self) -> bool:
        """Whether the gallery has more planes than ``calibration_planes``: its calibration takes a sample of them."""
        return self.calibration_planes is not None and len(self._planes) > self.calibration_planes

    def _calibration_sample(self) -> list[int]:
        """The gallery positions of the planes whose copies the calibration takes, in gallery order: every plane, or
        with ``calibration_planes`` the so many whose names hash lowest (the same planes each time, whatever the
        enrolment order)."""
        count = len(self._planes)
        if not self._calibration_sampled():
            return list(range(count))
        keys = [zlib.crc32(f"{p.object}/{p.name}/calibration".encode()) for p in self._planes]
        return sorted(sorted(range(count), key=lambda i: (keys[i], i))[:self.calibration_planes])

    def _calibration_features(self, sample: list[int]) -> None:
        """Features of warped copies of every plane of ``sample`` (gallery positions) that has none yet (the
        training warps; once per plane)."""
        missing = [self._planes[i] for i in sample if self._planes[i].calibration is None]
        inner = self._gallery_recognizer() if missing else None
        for start in range(0, len(missing), CALIBRATION_PLANES):  # so many planes' copies in memory at a time
            planes = missing[start:start + CALIBRATION_PLANES]
            images = self._calibration_images(planes)
            features = torch.cat([inner.embed_queries(images[i:i + 256])[0] for i in range(0, len(images), 256)])
            for plane, chunk in zip(planes, features.float().cpu().split(self.calibration_warps), strict=True):
                plane.calibration = chunk

    def _statistic(self, nearest: torch.Tensor, second: torch.Tensor,
                   verified: torch.Tensor | None = None) -> torch.Tensor:
        if self.open_set_statistic == "distance":
            return nearest
        ratio = nearest / second.clamp_min(1e-12)
        if self.open_set_statistic in ("verify", "verify_or_ratio") and verified is not None:
            return torch.where(verified.cpu(), torch.zeros_like(ratio), ratio)
        return ratio

    def calibration(self) -> dict[str, torch.Tensor]:
        """Genuine and impostor samples of the open-set statistic (see the module docstring) of the copies of the
        planes of :meth:`_calibration_sample`, taken :data:`CALIBRATION_PLANES` planes at a time."""
        with self._lock:
            sample = self._calibration_sample()
            self._calibration_features(sample)
            owners = torch.tensor(self._plane_objects())
            parts = [self._calibration_part(sample[start:start + CALIBRATION_PLANES], start, owners)
                     for start in range(0, len(sample), CALIBRATION_PLANES)]
            return {name: torch.cat([part[name] for part in parts]) for name in ("genuine", "impostor")}

    def _calibration_part(self, positions: list[int], first: int, owners: torch.Tensor) -> dict[str, torch.Tensor]:
        """:meth:`calibration`'s samples of the copies of the planes at gallery ``positions``, the sample's planes
        ``first`` to ``first + len(positions)`` (the occluded copies take their turns over the sample: over the whole
        gallery when every plane is in it)."""
        planes = [self._planes[i] for i in positions]
        features = torch.cat([p.calibration for p in planes])
        own = owners[positions].repeat_interleave(self.calibration_warps)
        d, objects = self._object_distances(features)               # (M, O)
        # verify: the copies are posed and verified as queries are (against the whole gallery; the
        # impostors against the gallery without their product); verify_or_ratio: the ratio's samples
        images = (self._calibration_images(planes)
                  if self.open_set_statistic == "verify" and self._verifying() else None)
        visibility = None
        share = self.verify_occluded_copies
        if images is not None and self.verify_statistic == "patches" and share > 0:  # some copies partly hidden
            images, visibility, rows = _occluded_copies(images, [f"{p.object}/{p.name}" for p in planes],
                                                        max(1, round(1.0 / share)), first)
            inner = self._gallery_recognizer()
            features = features.clone()
            features[rows] = torch.cat([inner.embed_queries(images[rows[i:i + 256]])[0].float().cpu()
                                        for i in range(0, len(rows), 256)])
            d, objects = self._object_distances(features)
        ranked = d.sort(1).values
        genuine_ok = None if images is None else self._verified_copies(images, visibility)
        genuine = self._statistic(ranked[:, 0], ranked[:, 1] if len(objects) > 1 else ranked[:, 0], genuine_ok)
        impostor = torch.zeros(0, dtype=torch.float64)
        if len(objects) > 2:  # without its own product, a copy's nearest and second-nearest products
            impostor_ok = None if images is None else self._verified_copies(images, visibility, own.to(self.device))
            others = d.scatter(1, own[:, None], float("inf")).sort(1).values
            impostor = self._statistic(others[:, 0], others[:, 1], impostor_ok)
        return {"genuine": genuine, "impostor": impostor}

    @property
    def threshold(self) -> float | None:
        """The open-set threshold on the statistic in force (None: closed set)."""
        with self._lock:
            if self.threshold_option is None:
                return None
            if self.threshold_option != "auto":
                return float(self.threshold_option)
            return self._calibrate()[0]

    def _calibrate(self) -> tuple[float, torch.Tensor]:
        if self._calibrated is None:
            samples = self._calibration_samples()
            threshold = calibrate_open_set(samples["genuine"], samples["impostor"], self.open_set_quantile)
            self._calibrated = (threshold, samples["impostor"].sort().values)
        return self._calibrated

    # ------------------------------------------------------------------------- the calibration, kept
    def calibration_key(self) -> str:
        """What the open-set samples (:meth:`calibration`) depend on: the model, every plane's name and canonical
        image, and the options that change the statistic (the statistic, the warps, verification and the
        refiner that poses candidates, the query path). ``open_set_quantile`` is not in it: the threshold is
        taken from the kept samples for any quantile."""
        import hashlib
        import json

        digest = hashlib.sha256()
        for plane in self._planes:
            digest.update(f"{plane.object}\0{plane.name}\0".encode())
            digest.update(plane.canon_u8.contiguous().numpy().tobytes())
        refiner = None if self.refiner is None else {k: v for k, v in vars(self.refiner).items()
                                                     if not k.startswith("_")}
        options = {"format": CALIBRATION_FORMAT, "model": self.model_id, "image_size": self.image_size,
                   "num_anchors": self.num_anchors, "statistic": self.open_set_statistic,
                   "warps": self.calibration_warps, "homography": getattr(self.model, "homography_config", None),
                   "verify": ([self.verify_top_k, self.verify_shortlist, self.verify_max, self.verify_blur,
                               self.verify_refine, self.verify_statistic, self.verify_min_visible,
                               self.verify_occluded_copies]
                              # the second look changes only copies with an occluder across them
                              + ([self.verify_occluder_margin] if self.verify_occluded_copies > 0 else [])
                              if self._verifying() else None),
                   "refiner": refiner, "quantize": self.quantize, "runtime": self.runtime,
                   "search": self.options()["search"], "device": self.device.type, "variant": self._variant}
        if self._calibration_sampled():  # a sample of the planes' copies
            options["calibration_planes"] = self.calibration_planes
        return json.dumps(options, sort_keys=True, default=str) + "|planes:" + digest.hexdigest()

    def calibration_cache_file(self) -> Path | None:
        """Where the calibration of a gallery enrolled from a folder (``enrol(folder, cache=True)``, nothing added
        or removed since) is kept: ``<folder>/.matl_calibration_<model>_<options>.pt``, beside the features'
        cache; None for any other gallery."""
        import hashlib

        if self._calibration_folder is None:
            return None
        folder, ids = self._calibration_folder
        if [id(p) for p in self._planes] != ids:
            return None
        options = hashlib.sha256(self.calibration_key().rsplit("|planes:", 1)[0].encode()).hexdigest()
        return folder / f"{CALIBRATION_PREFIX}{self.model_id[:16]}_{options[:16]}.pt"  # one per model and options

    def _calibration_samples(self) -> dict[str, Any]:
        """``{"key", "genuine", "impostor"}`` of the current gallery and options: the kept samples when their key
        is this one (from :meth:`load` or the enrolled folder's cache), else :meth:`calibration`'s, kept (and
        written beside an enrolled folder)."""
        key = self.calibration_key()
        stored = self._stored_calibration
        if stored is None or stored.get("key") != key:
            stored = self._read_calibration_cache(key)
        if stored is None:
            samples = self.calibration()
            stored = {"key": key, "genuine": samples["genuine"], "impostor": samples["impostor"]}
            self._write_calibration_cache(stored)
        self._stored_calibration = stored
        return stored

    def _read_calibration_cache(self, key: str) -> dict[str, Any] | None:
        path = self.calibration_cache_file()
        if path is None or not path.is_file():
            return None
        try:
            payload = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as error:  # a corrupt cache is never fatal: it is rebuilt
            _log.warning("calibration cache %s is unreadable (%s); calibrating again", path,
                         " ".join(str(error).split()))
            return None
        if (not isinstance(payload, dict) or payload.get("key") != key
                or not all(isinstance(payload.get(k), torch.Tensor) for k in ("genuine", "impostor"))):
            return None
        _log.info("open-set calibration loaded from %s", path)
        return payload

    def _write_calibration_cache(self, samples: dict[str, Any]) -> None:
        from matl.utils.io import atomic_write

        path = self.calibration_cache_file()
        if path is None:
            return
        try:
            with atomic_write(path, "wb") as f:
                torch.save(samples, f)
        except OSError as error:  # a read-only gallery folder only costs a warning
            _log.warning("cannot write the calibration cache %s (%s); it will be recomputed next time", path, error)

    def _score(self, statistic: float) -> float:
        if self.threshold_option is None or not self._planes:
            return float("nan")
        impostor = self._calibrate()[1]
        if len(impostor) == 0:
            return float("nan")
        farther = len(impostor) - int(torch.searchsorted(impostor, torch.tensor([statistic], dtype=impostor.dtype)))
        return farther / len(impostor)
