"""Images given to the recognizer: a query's mask becomes its visibility in the model frame."""

from __future__ import annotations

import numpy as np
import torch

from matl.inference.images import _query_visibility

SIZE = 48


def test_the_query_mask_travels_with_the_query_as_its_visibility() -> None:
    from matl.inference.foreground import GrabCutForeground, mask_query

    rng = np.random.default_rng(0)
    rgb = rng.uniform(0.2, 1.0, (30, 20, 3)).astype(np.float32)
    alpha = np.ones((30, 20), np.float32)
    alpha[:, 5:9] = 0.0
    alpha[:, 9] = 0.5  # a soft edge
    rgba = np.concatenate([rgb, alpha[..., None]], -1)
    plain = mask_query(None, rgb)
    assert _query_visibility([plain], SIZE, 1.0, torch.device("cpu")) is None  # no mask: ones everywhere
    seen = _query_visibility([mask_query(None, rgba), plain], SIZE, 1.0, torch.device("cpu"))
    framed = torch.from_numpy(alpha)[None]
    from matl.data.image_files import fit_to_model

    expected = fit_to_model(framed, SIZE, 1.0)[0][:1]
    assert seen.shape == (2, 1, SIZE, SIZE) and torch.allclose(seen[0], expected, atol=1e-6)  # the alpha read back
    ones = fit_to_model(torch.ones_like(framed), SIZE, 1.0)[0][:1]
    assert torch.equal(seen[1], ones)  # a query without a mask beside one with it: ones where the file is
    assert float(ones[:, :, :8].max()) == 0.0 and float(ones.max()) == 1.0  # the frame's padding holds no pixel
    # the foreground step's mask is the visibility of an RGB query
    step = GrabCutForeground(retry_insets=())
    crop = np.zeros((40, 40, 3), np.float32)
    crop[10:30, 12:28] = rgb[:20, :16]
    found = mask_query(step, crop)
    assert found[2] is not None
    assert torch.allclose(_query_visibility([found], SIZE, 1.0, torch.device("cpu"))[0],
                          fit_to_model(torch.from_numpy(found[2])[None], SIZE, 1.0)[0][:1])
