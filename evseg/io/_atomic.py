"""Atomic file writing: write to a temporary file next to the target, then rename."""

from __future__ import annotations

import contextlib
import os
import uuid
from pathlib import Path
from typing import Iterator


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path in ``path``'s folder; on success rename it to ``path``.

    A crash or an exception leaves ``path`` untouched (either the old file or none) and
    removes the temporary file, so readers never see a half-written recording.
    """
    from evseg.errors import EvsegError

    path = Path(path)
    if path.is_dir():
        # Found only at the final rename otherwise, after all the work (IsADirectoryError).
        raise EvsegError(f"{path}: is a folder; give a file name to write")
    if path.parent.exists() and not path.parent.is_dir():
        raise EvsegError(f"{path}: {path.parent} is a file, not a folder")
    path.parent.mkdir(parents=True, exist_ok=True)
    # A fresh name the writer creates itself, so the file gets the usual permissions (umask)
    # rather than mkstemp's 0600.
    tmp_path = path.with_name(f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:12]}.tmp")
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def atomic_savez(path: str | Path, **arrays) -> None:
    """``np.savez`` to ``path`` through :func:`atomic_path` (an error leaves an existing file as
    it was)."""
    import numpy as np

    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:  # a file object: np.savez would append '.npz' to a bare path
            np.savez(f, **arrays)
