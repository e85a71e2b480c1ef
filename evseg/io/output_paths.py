"""Checks of output paths before any work: a long run must not end in an error about where
its result goes, and an output must never replace an input.

The CLI commands call :func:`check_output_path` for each file they will write (and
:func:`check_output_folder` for a folder of frames) before they read the first event.
"""

from __future__ import annotations

import os
import uuid
from collections.abc import Iterable
from pathlib import Path

from evseg.errors import ConfigError


def check_output_path(path: Path, option: str, suffixes: tuple[str, ...] = (),
                      inputs: Iterable[tuple[str, Path | None]] = ()) -> None:
    """Raise :class:`~evseg.errors.ConfigError` naming ``option`` and ``path`` when ``path``
    cannot take the output: its extension is not one of ``suffixes`` (case-insensitive; empty:
    any), it is a folder, it is one of ``inputs`` (pairs of a description and a path, e.g.
    ``("the recording", recording)``; the same file under another name counts), a part of its
    folder path is a file, or its folder cannot be written. Missing folders are fine (the
    writers create them); nothing is created here except a probe file, removed at once.

    >>> import tempfile
    >>> folder = Path(tempfile.mkdtemp())
    >>> check_output_path(folder / "result.npz", "--out", (".npz",))
    >>> check_output_path(folder / "result.txt", "--out", (".npz",))
    Traceback (most recent call last):
    ...
    evseg.errors.ConfigError: --out ...result.txt: the file must end in .npz (...)
    """
    path = Path(path)
    if suffixes and path.suffix.lower() not in suffixes:
        wanted = " or ".join(suffixes)
        raise ConfigError(f"{option} {path}: the file must end in {wanted} (it is written in that format)")
    if path.is_dir():
        raise ConfigError(f"{option} {path}: is a folder; give a file name inside it")
    for what, other in inputs:
        if other is not None and _same_file(path, Path(other)):
            raise ConfigError(f"{option} {path}: is {what}, which the run reads; choose another name")
    _check_writable_folder(path.parent, option, path)


def check_output_folder(folder: Path, option: str) -> None:
    """Raise :class:`~evseg.errors.ConfigError` when ``folder`` (created by the writer if
    missing) is a file, lies below a file, or cannot be written."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise ConfigError(f"{option} {folder}: is a file, not a folder")
    _check_writable_folder(folder, option, folder)


def _same_file(a: Path, b: Path) -> bool:
    if not a.exists() or not b.exists():
        return False
    try:
        return os.path.samefile(a, b)
    except OSError:
        return a.resolve() == b.resolve()


def _check_writable_folder(folder: Path, option: str, target: Path) -> None:
    """The nearest existing folder of ``folder`` must be a folder and accept a new file."""
    existing = folder if str(folder) else Path(".")
    while not existing.exists():
        parent = existing.parent
        if parent == existing:
            break
        existing = parent
    if not existing.is_dir():
        raise ConfigError(f"{option} {target}: {existing} is a file, not a folder")
    # os.access says yes to root everywhere, and some folders (/proc) refuse files anyway:
    # creating a file is the only test that answers for this machine and user.
    probe = existing / f".evseg-write-test-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    try:
        with open(probe, "xb"):
            pass
    except OSError as exc:
        reason = exc.strerror or type(exc).__name__
        raise ConfigError(f"{option} {target}: cannot write in {existing} ({reason})") from None
    try:
        probe.unlink()
    except OSError:
        pass
