"""``gallery_scaling`` of ``matl.bench``: a query's latency per gallery size, exact search and (when installed) FAISS,
on random unit embeddings of the model's dimension plus the fixed ``c(s(q))`` cost of a real query (docs/speed.md)."""

from __future__ import annotations

import math
import time
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from matl.utils.errors import CONF_DIR, MatlError
from matl.utils.timing import median_query_ms, synced


def default_faiss_node() -> DictConfig:
    """``conf/search/faiss.yaml``, for the faiss timing when the run's search is exact."""
    path = CONF_DIR / "search" / "faiss.yaml"
    node = OmegaConf.load(path)
    assert isinstance(node, DictConfig)
    return node


def fixed_query_ms(model: Any, recognizer: Any, queries: torch.Tensor, warmup: int, device: torch.device,
                   threads: int | None = None) -> float:
    """Median milliseconds of ``c(s(query))`` for one query (the part of a query that does not
    depend on the gallery size), by the recognizer's own path (:meth:`TensorRecognizer.embed_queries`)."""
    embed_one = getattr(recognizer, "embed_queries", None)
    if embed_one is None:  # a recognizer without an embedding path (the STN classifier): its networks
        def embed_one(q: torch.Tensor) -> torch.Tensor:
            warped = model.stn(q).warped if getattr(model, "stn", None) is not None else q
            return model.feature_net(warped)
    return median_query_ms(synced(embed_one, device), queries, warmup, threads)


def measure_scaling(cfg: DictConfig, options: DictConfig, model: Any, fixed_ms: float,
                    device: torch.device, threads: int | None = None) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Search latency per gallery size, exact and (when installed) FAISS; see the module docstring."""
    from matl.inference.options import search_name
    from matl.models.search import ExactSearch, FaissSearch, require_faiss

    dim = int(getattr(model.feature_net, "embedding_dim", 0)) or int(
        model.feature_net(torch.zeros(1, 3, model.image_size, model.image_size, device=device)).shape[1])
    count, warmup = int(options.scaling_queries), int(options.scaling_warmup)
    use_faiss, faiss_note = bool(options.faiss), None
    if use_faiss:
        try:
            require_faiss()
        except MatlError as error:
            use_faiss, faiss_note = False, str(error)
    faiss_node = cfg.search if search_name(cfg.get("search")) == "faiss" else default_faiss_node()
    faiss_kwargs = {k: v for k, v in OmegaConf.to_container(faiss_node, resolve=True).items()
                    if not k.startswith("_")}
    g = torch.Generator().manual_seed(int(cfg.seed))
    rows = []
    for anchors in [int(a) for a in options.scaling_anchors]:
        gallery = torch.nn.functional.normalize(torch.randn(anchors, dim, generator=g), dim=1)
        truth = torch.randint(anchors, (warmup + count,), generator=g)
        # a query is its gallery entry moved by noise of norm ~0.3 (typical of a recognised query)
        noise = torch.randn(warmup + count, dim, generator=g) * (0.3 / math.sqrt(dim))
        queries = torch.nn.functional.normalize(gallery[truth] + noise, dim=1)
        gallery, queries = gallery.to(device), queries.to(device)
        exact = ExactSearch(gallery)
        search_ms = median_query_ms(synced(lambda q, e=exact: e.search(q), device), queries, warmup, threads)
        exact_index = exact.search(queries)[0]
        row: dict[str, Any] = {"anchors": anchors, "query_ms": fixed_ms + search_ms, "search_ms": search_ms}
        if use_faiss:
            start = time.perf_counter()
            index = FaissSearch(gallery, **faiss_kwargs)
            row["faiss_build_s"] = time.perf_counter() - start
            row["faiss_search_ms"] = median_query_ms(lambda q, i=index: i.search(q), queries, warmup, threads)
            row["faiss_query_ms"] = fixed_ms + row["faiss_search_ms"]
            row["faiss_recall_at_1"] = float((index.search(queries)[0] == exact_index).float().mean())
        rows.append(row)
    info = {
        "embedding_dim": dim, "queries": count, "warmup": warmup, "fixed_query_ms": fixed_ms, "threads": threads,
        "method": "query_ms = fixed_query_ms (STN + feature net of one real query, measured once) + search_ms "
                  "(median single-query search over random unit embeddings of the model's dimension; queries "
                  "are gallery entries plus noise of norm ~0.3)",
        "faiss": ({k: v for k, v in faiss_kwargs.items()} if use_faiss else None),
    }
    if faiss_note:
        info["faiss_note"] = faiss_note
    return rows, info

