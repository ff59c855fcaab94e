"""The rendered view pool: cached once, reused, keyed by everything that changes it; object subsets."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from matl.data.view_pool import load_view_pool, view_pool_path
from matl.data.view_sampler import ViewSampler
from tests.data.conftest import TinyCatalog

SIZE = 32


def test_view_pool_is_cached_and_reused(tiny: TinyCatalog, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    sampler = ViewSampler()
    pool = load_view_pool(tiny, SIZE, 3, sampler, 0, tmp_path)
    assert pool.images.shape == (18, 3, SIZE, SIZE, 3) and pool.query_H_canon.shape == (18, 3, 3, 3)
    assert pool.images.reshape(18 * 3, -1).max(1).min() > 0  # every view shows the object
    path, _ = view_pool_path(tiny, SIZE, 3, sampler, 0, tmp_path)
    assert path.exists() and not list(tmp_path.glob(".*.tmp"))

    def fail(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("should have loaded from the cache")

    monkeypatch.setattr("matl.data.view_pool.render_view_pool", fail)
    again = load_view_pool(tiny, SIZE, 3, sampler, 0, tmp_path)
    assert np.array_equal(again.images, pool.images) and np.array_equal(again.query_H_canon, pool.query_H_canon)
    assert view_pool_path(tiny, SIZE, 3, ViewSampler(tilt_deg=(0, 10)), 0, tmp_path)[0] != path
    assert view_pool_path(tiny, SIZE, 3, sampler, 1, tmp_path)[0] != path

    # the planes of objects 2 and 0, in that order, re-indexed 0 and 1
    sub = again.subset_objects([2, 0])
    assert sub.object_names == [pool.object_names[2], pool.object_names[0]]
    assert sub.plane_object.tolist() == [0] * 10 + [1] * 2
    assert np.array_equal(sub.images[10:], pool.images[:2])
