"""Writing result and cache files atomically: a crash mid-write never leaves a truncated file.

Every file the project writes for a reader to trust (``metrics.json``, ``eval.json``,
``per_query.csv``, the canonical and view caches, the gallery feature cache) goes through
:func:`atomic_write`: the bytes go to a temporary file in the target's own folder, are flushed to
disk, and the temporary file is renamed over the target (``os.replace`` is atomic within one
filesystem on POSIX and Windows). A failed write removes its temporary file and leaves the old
target untouched.
"""

from __future__ import annotations

import contextlib
import csv
import json
import math
import os
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import IO, Any


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_write(path: str | Path, mode: str = "w", newline: str | None = None) -> Iterator[IO[Any]]:
    """Open a temporary file beside ``path`` for writing; on a clean exit it replaces ``path``.

    ``mode`` is ``"w"`` (text) or ``"wb"`` (bytes). The file gets the permissions a plain ``open``
    would give it (``0o666`` less the umask: caches are meant to be shared), not ``mkstemp``'s 0600.
    """
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_write mode must be 'w' or 'wb', got {mode!r}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, mode, newline=newline) if mode == "w" else os.fdopen(fd, mode) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def json_safe(value: Any) -> Any:
    """``value`` with every non-finite float replaced by None (JSON has no NaN; ``null`` is explicit)."""
    if hasattr(value, "item") and getattr(value, "ndim", None) == 0:  # 0-d tensors / numpy scalars
        value = value.item()
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    return value


def write_json(path: str | Path, payload: dict[str, Any]) -> None:
    """Atomic JSON write (sorted keys, indent 2); NaN / inf are written as null."""
    text = json.dumps(json_safe(payload), indent=2, sort_keys=True, default=str, allow_nan=False)
    with atomic_write(path) as f:
        f.write(text + "\n")


def write_csv(path: str | Path, rows: Sequence[dict[str, Any]], columns: Sequence[str] | None = None) -> None:
    """Atomic CSV write with a header; ``columns`` defaults to the keys of the rows in first-seen order."""
    keys = list(columns) if columns is not None else list(dict.fromkeys(k for row in rows for k in row))
    with atomic_write(path, newline="") as f:
        writer = csv.DictWriter(f, fieldnames=keys)
        writer.writeheader()
        writer.writerows(rows)


def atomic_savez(path: str | Path, **arrays: Any) -> None:
    """``np.savez_compressed`` through :func:`atomic_write`."""
    import numpy as np

    with atomic_write(path, "wb") as f:
        np.savez_compressed(f, **arrays)
