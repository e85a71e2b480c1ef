"""MATLAB v5 .mat recordings: variable ``events``, N x 4 ``[x, y, p, t_us]``.

This is the layout of the DVS128 clips of ``dvs128_single_motion`` (Mueggler et al.,
rpg_event_lifetime): int32 columns x, y, polarity (-1/+1) and t in microseconds. The file is
loaded whole by ``scipy.io.loadmat`` (v5 files are not streamable), then sliced into chunks.
MATLAB v7.3 files are HDF5 and are refused with a message saying so.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from evseg.errors import FormatError
from evseg.io.numpy_files import ArraySource


def open_source(path: Path, format: str = "mat") -> ArraySource:
    import scipy.io

    where = f"{path}: mat"
    with open(path, "rb") as f:
        head = f.read(128)
    if head.startswith(b"\x89HDF") or b"MATLAB 7.3" in head:
        raise FormatError(f"{where}: MATLAB v7.3 (HDF5) files are not supported; save with -v7 or as .npz")
    try:
        m = scipy.io.loadmat(str(path))
    except Exception as exc:  # scipy raises many types (ValueError, TypeError, OSError, ...)
        raise FormatError(f"{where}: corrupt or truncated MATLAB file ({type(exc).__name__}: {exc})") from None
    if "events" not in m:
        names = [k for k in m if not k.startswith("__")]
        raise FormatError(f"{where}: no variable 'events' (variables: {names})")
    a = np.asarray(m["events"])
    if a.ndim != 2 or a.shape[1] != 4 or a.dtype.kind not in "iuf":
        raise FormatError(
            f"{where}: variable 'events' must be an N x 4 numeric [x, y, p, t_us] array, got shape "
            f"{a.shape} dtype {a.dtype}"
        )
    # Integer-typed time stays microseconds; a double matrix holds whole microseconds too, so
    # round it to int64 here rather than let the shared converter read floats as seconds.
    t = a[:, 3]
    if a.dtype.kind == "f":
        bad = np.flatnonzero(~np.isfinite(a).all(axis=1))
        if len(bad):
            raise FormatError(f"{where}: variable 'events' has NaN/inf in row {int(bad[0])}")
        frac = np.flatnonzero(t != np.floor(t))
        if len(frac):
            i = int(frac[0])
            raise FormatError(
                f"{where}: variable 'events' row {i}: t = {float(t[i])!r} has a fraction, but column 4 holds "
                "whole microseconds; if the times are seconds, multiply them by 1e6 (or save an .npz, "
                "where float times are seconds)"
            )
        t = t.astype(np.int64)
    return ArraySource(path, "mat", lambda i, j: (t[i:j], a[i:j, 0], a[i:j, 1], a[i:j, 2]), len(a))
