"""Inference options shared by ``matl.eval``, ``matl.predict`` and ``matl.bench``: ``search=`` and ``refine=``.

* ``search=exact|faiss`` (config group ``conf/search/``): the gallery search backend of an embedding
  model's recognizer (:mod:`matl.models.search`).
* ``refine=true`` with the ``refiner`` node (``conf/refiner/``: ``fast`` by default, or ``photometric``):
  wrap the recognizer in :class:`matl.inference.refine.RefinedRecognizer`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from omegaconf import DictConfig, OmegaConf

from matl.models.prediction import Prediction
from matl.utils.errors import MatlError

__all__ = ["configure_recognizer", "search_name"]


def search_name(node: DictConfig | None) -> str:
    """``exact`` or ``faiss`` (the backend class's ``name``) for a ``search`` config node."""
    if node is None or "_target_" not in node:
        return "exact"
    target = str(node._target_)
    return "faiss" if target.endswith("FaissSearch") else "exact" if target.endswith("ExactSearch") else target


def configure_recognizer(recognizer: Callable[..., Prediction], cfg: DictConfig
                         ) -> tuple[Callable[..., Prediction], dict[str, Any]]:
    """Apply ``cfg.search`` and ``cfg.refine`` / ``cfg.refiner`` to a recognizer.

    Args:
        recognizer: MATL's ``TensorRecognizer`` (has ``use_search``), the STN classifier's or a baseline's.
        cfg: an eval / predict / bench config; missing keys mean the defaults (exact, no refinement).
    Returns:
        The recognizer to call, and what was applied (for ``eval.json`` and friends):
        ``{"search": name, "refine": bool, "refiner": options or None}``.
    Raises:
        MatlError: one line, for an option that does not apply to this recognizer or a bad value.
    """
    from matl.utils.instantiate import instantiate_node

    node = cfg.get("search")
    name = search_name(node)
    if name != "exact":
        if not hasattr(recognizer, "use_search"):
            raise MatlError(f"search={name} applies to embedding models (model=matl or model=tl) only; "
                            f"{type(recognizer).__name__} has no feature gallery")
        factory = instantiate_node(node, "search")
        try:
            recognizer.use_search(factory)
        except (ValueError, TypeError) as error:
            raise MatlError(f"search: {' '.join(str(error).split())}") from error
    elif node is not None and "_target_" in node and hasattr(recognizer, "use_search"):
        recognizer.use_search(instantiate_node(node, "search"))  # exact, with the config's chunk size

    refine = cfg.get("refine", False)
    if refine not in (True, False):
        raise MatlError(f"refine={refine} is invalid: use true or false")
    refiner_options = None
    if refine:
        if getattr(recognizer, "stn", True) is None:
            raise MatlError("refine=true needs a pose to refine: this model has no STN (model=tl estimates no pose)")
        if cfg.get("refiner") is None:
            raise MatlError("refine=true needs a refiner node (conf/refiner/; add refiner=fast)")
        from matl.inference.refine import RefinedRecognizer

        refiner = instantiate_node(cfg.refiner, "refiner")
        recognizer = RefinedRecognizer(recognizer, refiner)
        refiner_options = {k: v for k, v in OmegaConf.to_container(cfg.refiner, resolve=True).items()
                           if k != "_target_"}
    return recognizer, {"search": name, "refine": bool(refine), "refiner": refiner_options}
