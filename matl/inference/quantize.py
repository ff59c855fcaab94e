"""Optional int8 query path (``quantize=int8`` in eval / predict / bench): the query networks in int8 (docs/speed.md).

Static post-training quantisation of the networks of one query, ``c(s(q))``, with torch's FX graph
mode (``torch.ao.quantization.quantize_fx``; torch 2.13 no longer ships PT2E's
``torch.ao.quantization.quantize_pt2e``, which moved to the separate ``torchao`` package):

* quantised (int8 weights per output channel, uint8 activations per tensor, calibrated): the
  convolutions (each fused with its ReLU), max pools and linear layers of the STN's homography
  regressor (both of its applications) and of the feature net ``c()``;
* kept in float32: the warps (``grid_sample``), the homography algebra (composition, degeneracy
  guard, pixel conversion), the global max pool and the L2 normalisation of the embedding, and the
  gallery search and pose (unchanged, :class:`matl.models.recognizer.TensorRecognizer`).

The result is one TorchScript graph (:class:`~matl.models.recognizer.QueryGraph` with the quantised
networks swapped in; traced, frozen, ``optimize_for_inference``), built once per recognizer by
:func:`quantize_recognizer` and used for every CPU float32 query batch. Activation ranges are
calibrated on training-distribution images (the datamodule's training positives, or gallery images
warped by random homographies: :func:`calibration_images`), never on test queries. The gallery's
embeddings are recomputed with the quantised ``c()`` so that queries and gallery share the same
rounding (``gallery="float"`` keeps the float ones).

The int8 path changes the outputs beyond float rounding (embeddings within a few 1e-2, poses within
about a pixel on the default model); its accuracy is measured by ``matl.eval quantize=int8``.
"""

from __future__ import annotations

import copy
import logging
import warnings
from collections.abc import Iterable
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from matl.models.feature import FeatureNet
from matl.models.recognizer import QueryGraph, weights_key
from matl.models.stn import HomographyRegressor, SpatialTransformer

__all__ = ["QUANTIZE_CHOICES", "QuantizedQueryPath", "apply_quantize_option", "calibration_images",
           "datamodule_calibration", "quantize_available", "quantize_option", "quantize_recognizer"]

log = logging.getLogger(__name__)

#: values of the ``quantize`` option
QUANTIZE_CHOICES = ("none", "int8")

#: quantised engine: oneDNN (VNNI int8 on recent x86 CPUs); activations use the full uint8 range
DEFAULT_ENGINE = "onednn"


def quantize_available(engine: str = DEFAULT_ENGINE) -> bool:
    """True when torch has the quantised ``engine`` and FX graph mode quantisation."""
    try:
        from torch.ao.quantization.quantize_fx import convert_fx, prepare_fx  # noqa: F401
    except ImportError:
        return False
    return engine in torch.backends.quantized.supported_engines


# ------------------------------------------------------------------------------ quantisable cores
class _RegressorCore(nn.Module):
    """The regressor's layers without its identity-add: ``(B, 3, S, S) -> (B, 8)`` deltas. The
    identities of a regressor without batch norm are dropped so that each convolution fuses with its ReLU."""

    def __init__(self, regressor: HomographyRegressor) -> None:
        super().__init__()
        self.features = nn.Sequential(*[m for m in regressor.features if not isinstance(m, nn.Identity)])
        self.fc1, self.fc2 = regressor.fc1, regressor.fc2

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        x = torch.flatten(self.features(images.contiguous(memory_format=torch.channels_last)), 1)
        return self.fc2(F.relu(self.fc1(x)))


class _FeatureCore(nn.Module):
    """``c()`` up to its last ReLU: ``(B, 3, S, S) -> (B, D, h, w)`` feature maps."""

    def __init__(self, feature_net: FeatureNet) -> None:
        super().__init__()
        self.conv1, self.pool, self.conv2 = feature_net.conv1, feature_net.pool, feature_net.conv2

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        x = images.contiguous(memory_format=torch.channels_last)
        return F.relu(self.conv2(self.pool(F.relu(self.conv1(x)))))


class _Regressor(nn.Module):
    """A (quantised) :class:`_RegressorCore` plus the identity in float: ``(B, 3, S, S) -> (B, 3, 3)``."""

    def __init__(self, core: nn.Module, input_norm: nn.Module) -> None:
        super().__init__()
        self.core, self.input_norm = core, input_norm   # the float network's input normalisation, in float
        self.register_buffer("eye", torch.eye(3).flatten(), persistent=False)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return (F.pad(self.core(self.input_norm(images)), (0, 1)) + self.eye).view(-1, 3, 3)


class _Feature(nn.Module):
    """A (quantised) :class:`_FeatureCore` plus the global max pool and normalisation in float."""

    def __init__(self, core: nn.Module, normalize: bool, input_norm: nn.Module) -> None:
        super().__init__()
        self.core, self.normalize, self.input_norm = core, bool(normalize), input_norm

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        x = torch.amax(self.core(self.input_norm(images)), dim=(-2, -1))
        return F.normalize(x, dim=-1) if self.normalize else x


def supports(feature_net: nn.Module, stn: nn.Module | None) -> str | None:
    """None when the networks can be quantised here, else the reason."""
    if not isinstance(stn, SpatialTransformer) or not isinstance(stn.regressor, HomographyRegressor):
        return "the int8 path needs the default spatial transformer (model=matl)"
    if not isinstance(feature_net, FeatureNet):
        return "the int8 path needs the default feature net"
    if not quantize_available():
        return f"this torch has no {DEFAULT_ENGINE} quantised engine or FX quantisation"
    tensors = (*stn.parameters(), *feature_net.parameters())
    if not all(t.device.type == "cpu" and t.dtype == torch.float32 for t in tensors):
        return "the int8 path runs on the CPU with float32 weights"
    return None


# ----------------------------------------------------------------------------------- calibration
def calibration_images(images: torch.Tensor, count: int = 256, seed: int = 0) -> torch.Tensor:
    """``count`` training-like images: random ``images`` (canonical or anchor images) warped by random
    homographies of the default :class:`~matl.geometry.HomographySampler` (the training positives' law)."""
    from matl.geometry import HomographySampler, warp_image

    g = torch.Generator().manual_seed(int(seed))
    pick = torch.randint(len(images), (int(count),), generator=g)
    size = (int(images.shape[-2]), int(images.shape[-1]))
    H = HomographySampler().sample(int(count), size, g)
    return warp_image(images[pick].float().cpu(), H.float())


def datamodule_calibration(datamodule: Any, count: int = 256) -> torch.Tensor:
    """The first ``count`` training positives of a set-up :class:`~matl.data.datamodule.TripletDataModule`
    (never its test queries); falls back to :func:`calibration_images` of its gallery."""
    train = getattr(datamodule, "train_set", None)
    params = getattr(train, "params", None)
    if params:
        batch = {k: v[:count] for k, v in params.items()}
        out = datamodule.materialize(batch)
        if "positive" in out:
            return out["positive"].float().cpu()
    return calibration_images(datamodule.gallery.images, count)


def _qconfig_mapping(core: nn.Module) -> Any:
    """The engine's default mapping, except that a max pool whose input has a channel count that is not
    a multiple of 32 stays in float (torch's uint8 channels-last max pool is vectorised for 32 channels
    at a time: on 16 it took 53 us against 31 us for dequantise + float pool + quantise)."""
    from torch.ao.quantization import get_default_qconfig_mapping

    mapping = get_default_qconfig_mapping(DEFAULT_ENGINE)
    channels = None
    for name, module in core.named_modules():
        if isinstance(module, nn.Conv2d):
            channels = module.out_channels
        elif isinstance(module, nn.MaxPool2d) and channels is not None and channels % 32:
            mapping = mapping.set_module_name(name, None)
    return mapping


# ------------------------------------------------------------------------------------ the path
class QuantizedQueryPath:
    """``c(s(query))`` with int8 convolutions and linears, as one frozen TorchScript graph.

    Returns :class:`~matl.models.recognizer.QueryGraph`'s outputs ``(embedding, query_H_anchor (pixel),
    degenerate, warped)`` for any CPU float32 batch. The graph holds quantised copies of the weights:
    the path is stale once the float networks change (``matches`` compares version counters).

    Args:
        feature_net: ``c()``.
        stn: ``s()``.
        image_size: ``S``.
        calibration: ``(C, 3, S, S)`` training-distribution images (never test queries).
        batch_size: calibration batch size.
    """

    def __init__(self, feature_net: FeatureNet, stn: SpatialTransformer, image_size: int,
                 calibration: torch.Tensor, batch_size: int = 64) -> None:
        reason = supports(feature_net, stn)
        if reason is not None:
            raise RuntimeError(reason)
        self.feature_net, self.stn, self.image_size = feature_net, stn, int(image_size)
        self._tensors = [*stn.parameters(), *feature_net.parameters()]
        self._key = weights_key(self._tensors)
        torch.backends.quantized.engine = DEFAULT_ENGINE
        with torch.inference_mode(False), torch.no_grad(), warnings.catch_warnings():
            warnings.filterwarnings("ignore", category=UserWarning)
            warnings.filterwarnings("ignore", category=DeprecationWarning)
            regressor, feature = self._quantize(calibration, batch_size)
            self.graph_module = QueryGraph(stn, feature_net, image_size, regressor=regressor, feature=feature).eval()
            self.feature_module = feature
            example = calibration[:1].float()
            self.graph = torch.jit.optimize_for_inference(torch.jit.freeze(
                torch.jit.trace(self.graph_module, example, check_trace=False)))
            self.feature = torch.jit.freeze(torch.jit.trace(feature, example, check_trace=False))
            for batch in (example, calibration[:3].float()):  # any batch size, same as the module
                for a, b in zip(self.graph_module(batch), self.graph(batch), strict=True):
                    if not torch.allclose(a.float(), b.float(), atol=1e-3, rtol=0):
                        raise RuntimeError("the traced int8 graph differs from its module")

    def matches(self) -> bool:
        """True while the float networks' weights are the ones quantised."""
        return weights_key(self._tensors) == self._key

    def _quantize(self, calibration: torch.Tensor, batch_size: int) -> tuple[nn.Module, nn.Module]:
        from torch.ao.quantization.quantize_fx import convert_fx, prepare_fx

        example = (calibration[:1].float(),)
        regressor_core = _RegressorCore(copy.deepcopy(self.stn.regressor)).eval()
        feature_core = _FeatureCore(copy.deepcopy(self.feature_net)).eval()
        observed_regressor = prepare_fx(regressor_core, _qconfig_mapping(regressor_core), example)
        observed_feature = prepare_fx(feature_core, _qconfig_mapping(feature_core), example)
        # the float query graph with observers: the regressor sees raw and warped queries, c() s(q), as at test time
        # (the observed modules keep the modes prepare_fx gave them)
        regressor_norm, feature_norm = self.stn.regressor.input_norm, self.feature_net.input_norm
        observer = QueryGraph(self.stn, self.feature_net, self.image_size,
                              regressor=_Regressor(observed_regressor, regressor_norm),
                              feature=_Feature(observed_feature, self.feature_net.normalize, feature_norm))
        for start in range(0, len(calibration), batch_size):
            observer(calibration[start:start + batch_size].float())
        return (_Regressor(convert_fx(observed_regressor), regressor_norm).eval(),
                _Feature(convert_fx(observed_feature), self.feature_net.normalize, feature_norm).eval())

    def __call__(self, queries: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        return self.graph(queries)

    @torch.no_grad()
    def embed(self, images: torch.Tensor, batch_size: int = 512) -> torch.Tensor:
        """The quantised ``c(images)`` (no STN), for the gallery: ``(G, 3, S, S) -> (G, D)``."""
        return torch.cat([self.feature(images[i:i + batch_size]) for i in range(0, len(images), batch_size)])


def quantize_recognizer(recognizer: Any, calibration: torch.Tensor | Iterable[torch.Tensor],
                        gallery: str = "int8") -> str | None:
    """Give a :class:`~matl.models.recognizer.TensorRecognizer` the int8 query path, in place.

    Args:
        recognizer: MATL's recognizer (``feature_net``, ``stn``, ``gallery``, ``gallery_features``).
        calibration: training-distribution images ``(C, 3, S, S)`` (or batches of them).
        gallery: ``int8``: re-embed the gallery with the quantised ``c()``; ``float``: keep its float embeddings.
    Returns:
        None when the int8 path is in place, else why not (the recognizer then stays float: the fallback).
    """
    if gallery not in ("int8", "float"):
        raise ValueError(f"gallery must be 'int8' or 'float', got {gallery!r}")
    images = calibration if isinstance(calibration, torch.Tensor) else torch.cat(list(calibration))
    reason = supports(recognizer.feature_net, getattr(recognizer, "stn", None))
    if reason is None:
        try:
            path = QuantizedQueryPath(recognizer.feature_net, recognizer.stn, recognizer.gallery.image_size, images)
            if gallery == "int8":
                recognizer.gallery_features = path.embed(recognizer.gallery.images.cpu())
            recognizer.quantized = path
            return None
        except Exception as error:  # quantised engine or TorchScript refused: the float path answers
            reason = f"{type(error).__name__}: {' '.join(str(error).split())[:300]}"
    log.warning("int8 query path unavailable, using float32: %s", reason)
    return reason


# ------------------------------------------------------------------------------ the config option
def quantize_option(cfg: Any) -> str:
    """The ``quantize`` value of an eval / predict / bench config (missing: ``none``), checked."""
    from matl.utils.errors import MatlError

    value = cfg.get("quantize", "none") if hasattr(cfg, "get") else "none"
    value = "none" if value in (None, False) else str(value)
    if value not in QUANTIZE_CHOICES:
        raise MatlError(f"quantize={value} is invalid: use none or int8")
    return value


def apply_quantize_option(recognizer: Any, cfg: Any, calibration: Any) -> dict[str, Any]:
    """``quantize=int8``: give ``recognizer`` the int8 query path (float32 stays the fallback).

    Args:
        recognizer: the recognizer about to be used (before ``configure_recognizer`` wraps it).
        cfg: the entry point's config.
        calibration: a callable returning calibration images (called only for ``int8``).
    Returns:
        ``{"quantize": "none" | "int8", "quantize_fallback": reason or None}`` for the run's record;
        ``quantize`` is ``none`` when the int8 path could not be built (the reason says why).
    Raises:
        MatlError: a bad value, or ``int8`` for a recognizer without networks to quantise (a keypoint baseline).
    """
    from matl.utils.errors import MatlError

    value = quantize_option(cfg)
    if value == "none":
        return {"quantize": "none", "quantize_fallback": None}
    if not hasattr(recognizer, "feature_net") or not hasattr(recognizer, "gallery_features"):
        raise MatlError(f"quantize={value} applies to MATL's recognizer (model=matl) only, not to "
                        f"{type(recognizer).__name__}")
    reason = quantize_recognizer(recognizer, calibration())
    return {"quantize": "none" if reason else value, "quantize_fallback": reason}
