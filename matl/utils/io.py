"""Writing result and cache files atomically: a crash mid-write never leaves a truncated file.

Every file the project writes for a reader to trust (``metrics.json``, ``eval.json``,
``per_query.csv``, the canonical and view caches, the gallery feature cache) goes through
:func:`atomic_write`: the bytes go to a temporary file in the target's own folder, are flushed to
disk, and the temporary file is renamed over the target (``os.replace`` is atomic within one
filesystem on POSIX and Windows). A failed write removes its temporary file and leaves the old
target untouched.

Every command checks the outputs a user named (``out=``, ``viz_dir=``) *before* its work starts
(:func:`check_output_file`, :func:`check_output_folder`): an existing file is replaced only with
``overwrite=true``, and a folder that is read-only, cannot be created or is a file is a one-line error
naming the fix, not an ``OSError`` after minutes of work.
"""

from __future__ import annotations

import contextlib
import csv
import errno
import json
import math
import os
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import IO, Any

from matl.utils.errors import MatlError


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


def _probe_writable(folder: Path, path: Path, key: str) -> None:
    """Create and remove a file in ``folder`` (permissions, read-only filesystems and root alike); a one-line
    :class:`MatlError` about ``key=path`` if that fails."""
    try:
        fd, probe = tempfile.mkstemp(prefix=".matl_write_probe.", dir=folder)
        os.close(fd)
        os.unlink(probe)
    except OSError as error:
        reason = "is read-only" if error.errno in (errno.EACCES, errno.EPERM, errno.EROFS) else (
            f"cannot be written ({error.strerror})")
        raise MatlError(f"{key}={path} cannot be written: the folder {folder} {reason}; choose another {key}=") \
            from None


def _check_can_create(path: Path, key: str) -> None:
    """``path`` (absent) could be created: its nearest existing ancestor is a folder we may write in."""
    ancestor = path.parent
    while not ancestor.exists() and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise MatlError(f"{key}={path} cannot be created: {ancestor} is a file, not a folder; choose another {key}=")
    _probe_writable(ancestor, path, key)


def check_output_file(path: str | Path, key: str = "out", overwrite: bool = False,
                      example: str = "predictions.jsonl") -> Path:
    """Check, before any work, that the file ``key=path`` can be written without losing anything.

    Raises a one-line :class:`MatlError` when ``path`` is a folder (``example``: the file name suggested in
    it), exists and ``overwrite`` is False, or lies in (or below) a folder that cannot be written or created.
    Creates nothing. Returns the path.
    """
    path = Path(str(path)).expanduser()
    if path.is_dir():
        raise MatlError(f"{key}={path} is a folder: name a file in it, e.g. {key}={path / example}")
    if path.exists() and not overwrite:
        raise MatlError(f"{key}={path} already exists: pass overwrite=true to replace it, or choose another {key}=")
    _check_can_create(path, key)
    return path


def check_output_folder(path: str | Path, names: Sequence[str], key: str = "out", overwrite: bool = False) -> Path:
    """Check, before any work, that the folder ``key=path`` can receive the files ``names`` without losing any.

    Raises a one-line :class:`MatlError` when ``path`` is a file, holds one of ``names`` (a glob pattern
    each) and ``overwrite`` is False, or cannot be written or created. Creates nothing. Returns the path.
    """
    path = Path(str(path)).expanduser()
    if path.exists() and not path.is_dir():
        raise MatlError(f"{key}={path} is a file, not a folder: choose a folder for the outputs")
    if path.is_dir() and not overwrite:
        held = sorted({p.name for pattern in names for p in path.glob(pattern)})
        if held:
            raise MatlError(f"{key}={path} already holds {', '.join(held)}: pass overwrite=true to replace "
                            f"{'it' if len(held) == 1 else 'them'}, or choose another {key}=")
    if path.is_dir():
        _probe_writable(path, path, key)
    else:
        _check_can_create(path, key)
    return path


def overwrite_option(cfg: Any) -> bool:
    """``overwrite=true|false`` of a command's config (absent: false); a one-line error otherwise."""
    value = cfg.get("overwrite", False)
    if not isinstance(value, bool):
        raise MatlError(f"overwrite={value} is invalid: use true (replace existing outputs) or false")
    return value


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
