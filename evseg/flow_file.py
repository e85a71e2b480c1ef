"""Per-event normal flow files: the layout ``evseg flow`` writes and ``evseg segment --flow``
reads, for users who bring the flow of their own estimator.

One row per target event (not every event needs a flow)::

    index        int64 (T,)   position of the event in the input recording (0-based, file order)
    nx, ny       float32 (T,) normal flow, px/s of the sensor's pixel grid (x = column, y = row
                              down); NaN where the estimator gave none
    uncertainty  float32 (T,) optional; larger = less certain (evseg's estimators: angular
                              error in radians)

plus optional metadata (``sensor_size``, ``window_us``, ``method``, ``config``) that the
segmentation does not need.

Example (a flow for events 0, 5 and 9 of a recording, then segmentation with it):

>>> import tempfile, pathlib
>>> path = pathlib.Path(tempfile.mkdtemp()) / "flow.npz"
>>> save_flow_file(path, index=[9, 0, 5], nx=[120.0, -3.5, 0.0], ny=[0.0, 40.0, 80.0])
>>> flow = load_flow_file(path)
>>> flow["index"].tolist(), flow["nx"].tolist()
([0, 5, 9], [-3.5, 0.0, 120.0])

``evseg segment recording.h5 --flow flow.npz --out result.npz`` then segments that flow, and
``MotionSegmentationPipeline.run(stream, precomputed_flow=load_flow_file(path))`` does so from
Python.
"""

from __future__ import annotations

import json
import zipfile
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from evseg.errors import EvsegError, FormatError

FLOW_KEYS = ("index", "nx", "ny")
"""Keys every flow file and every ``precomputed_flow`` mapping must have."""
OPTIONAL_FLOW_KEYS = ("uncertainty",)

_UNCERTAINTY_NAMES = ("unc", "uncert", "uncertainties", "sigma", "std", "confidence", "conf", "var", "variance")
"""Keys a user may have meant as ``uncertainty``: refused (the flow would silently count as exact)."""


def _misnamed_key(key: str) -> str | None:
    """The flow key ``key`` most likely means (a misspelling such as ``uncertainity``, or another
    name for the uncertainty), or None for a key that is simply extra (``t``, ``x``, metadata)."""
    import difflib

    if key in FLOW_KEYS + OPTIONAL_FLOW_KEYS:
        return None
    if key.lower() in _UNCERTAINTY_NAMES:
        return "uncertainty"
    close = difflib.get_close_matches(key.lower(), FLOW_KEYS + OPTIONAL_FLOW_KEYS, n=1, cutoff=0.75)
    return close[0] if close and close[0] != key else None


def check_flow(data: Mapping, n_events: int | None = None, source: str = "precomputed flow",
               error: type[EvsegError] = EvsegError) -> dict[str, np.ndarray]:
    """The flow arrays of ``data`` checked and sorted by ``index`` (a new dict; ``data`` is not
    modified, and its arrays are shared, not copied, where they are already in order and of
    these dtypes): ``index`` int64, ``nx``, ``ny`` (and ``uncertainty`` when given) float32.

    Raises ``error`` naming ``source``, the key and the value when a key is missing or
    misspelt (``uncertainity``, ``sigma``: a flow whose uncertainty is silently dropped counts
    as exact), an array is not 1-D numbers, the lengths differ, an index is negative, repeated
    or (with ``n_events``) past the recording's last event, or an uncertainty is negative.
    Other keys (``t``, ``x``, metadata) are ignored.
    """
    if not isinstance(data, Mapping):
        hint = (" (a file: load_flow_file(path) reads it)" if isinstance(data, (str, Path)) else "")
        raise error(f"{source}: expected a mapping of arrays index, nx, ny[, uncertainty], got "
                    f"{type(data).__name__}{hint}")
    for key in data:
        meant = _misnamed_key(str(key))
        if meant is not None and meant not in data:
            raise error(f"{source}: key '{key}' is not a flow key; did you mean '{meant}'? "
                        "(keys: index, nx, ny[, uncertainty: the expected angular error, rad])")
    for key in FLOW_KEYS:
        if key not in data or data[key] is None:
            raise error(f"{source}: no key '{key}' (expected index, nx, ny[, uncertainty])")
    arrays = {}
    for key in FLOW_KEYS + OPTIONAL_FLOW_KEYS:
        if key not in data or data[key] is None:
            continue
        a = np.asarray(data[key])
        if a.ndim != 1:
            raise error(f"{source}: key '{key}' must be 1-D (one row per target event), got shape {a.shape}")
        if not np.issubdtype(a.dtype, np.number) or np.issubdtype(a.dtype, np.complexfloating):
            raise error(f"{source}: key '{key}' must hold real numbers, got dtype {a.dtype}")
        arrays[key] = a
    n = len(arrays["index"])
    for key, a in arrays.items():
        if len(a) != n:
            raise error(f"{source}: key '{key}' has {len(a)} rows, 'index' has {n}")
    index = arrays["index"]
    if not np.issubdtype(index.dtype, np.integer):
        whole = np.isfinite(index) & (index == np.round(index)) & (np.abs(index) < 2.0**62)
        if not whole.all():
            raise error(f"{source}: key 'index' must hold event positions (integers), got {index[~whole][0]}")
    index = index.astype(np.int64, copy=False)
    if n and (index.min() < 0 or (n_events is not None and index.max() >= n_events)):
        bad = int(index.min()) if index.min() < 0 else int(index.max())
        within = f"the recording's {n_events} events" if n_events is not None else "the recording"
        raise error(f"{source}: key 'index' has value {bad} outside {within}")
    # Flow that is already in order (a file load_flow_file has read, handed on to
    # MotionSegmentationPipeline.run) is passed through without a sort or a copy.
    in_order = n < 2 or bool(np.all(index[1:] >= index[:-1]))
    order = slice(None) if in_order else np.argsort(index, kind="stable")
    out = {"index": index[order]}
    twice = np.flatnonzero(out["index"][1:] == out["index"][:-1])
    if len(twice):
        raise error(f"{source}: key 'index' holds event {int(out['index'][twice[0]])} more than once "
                    f"({len(twice)} repeated rows); one flow per event")
    for key in ("nx", "ny") + OPTIONAL_FLOW_KEYS:
        if key in arrays:
            out[key] = arrays[key][order].astype(np.float32, copy=False)
    unc = out.get("uncertainty")
    if unc is not None and len(unc) and bool(np.any(unc < 0)):
        raise error(f"{source}: key 'uncertainty' has value {float(unc[np.flatnonzero(unc < 0)[0]])} < 0 "
                    "(larger = less certain, 0 = certain)")
    if unc is not None and len(unc) and bool(np.isnan(unc).any()):
        # NaN compares false everywhere: every such flow would be dropped without a word.
        row = int(np.flatnonzero(np.isnan(unc))[0])
        raise error(f"{source}: key 'uncertainty' is NaN for event {int(out['index'][row])} (use inf for a flow "
                    "to ignore, as the plane fit does where it rejects a fit)")
    return out


def load_flow_file(path: str | Path, n_events: int | None = None,
                   sensor_size: tuple[int, int] | None = None) -> dict[str, np.ndarray]:
    """Read a flow file (``.npz``, the layout of this module), checked (:func:`check_flow`,
    errors are :class:`~evseg.errors.FormatError` naming the file) and sorted by ``index``.
    ``n_events``: the recording's event count, to check the indices against.
    ``sensor_size``: the recording's (width, height); a file that stores another one (a flow
    of another recording or camera) is refused. Files without the key are not checked."""
    from evseg.io.numpy_files import require_npz

    path = Path(path)
    require_npz(path, "flow file", ", with keys index, nx, ny[, uncertainty]", allow_npy=True)
    try:
        loaded = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise FormatError(f"{path}: cannot read flow file ({exc})") from None
    if not isinstance(loaded, np.lib.npyio.NpzFile):  # a .npy file: one bare array
        raise FormatError(f"{path}: a flow file is an .npz archive with keys index, nx, ny[, uncertainty]")
    try:
        with loaded as z:
            data = {k: z[k] for k in z.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:  # a member cut short
        raise FormatError(f"{path}: cannot read flow file ({exc})") from None
    if sensor_size is not None and "sensor_size" in data:
        stored = np.asarray(data["sensor_size"]).ravel()
        if stored.shape != (2,) or tuple(int(v) for v in stored) != tuple(int(v) for v in sensor_size):
            raise FormatError(
                f"{path}: key 'sensor_size' = {stored.tolist()} but the recording's sensor is "
                f"{int(sensor_size[0])}x{int(sensor_size[1])} (flow of another recording?)")
    return check_flow(data, n_events, source=str(path), error=FormatError)


def flow_file_settings(path: str | Path) -> dict:
    """The settings a flow file stores under ``config`` (what ``evseg flow`` ran: the
    recording, its event count ``n_events``, the estimator...), or ``{}`` when it stores none
    (files of other estimators need not)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            text = str(z["config"]) if "config" in z.files else ""
        settings = json.loads(text) if text else {}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, TypeError):
        return {}  # load_flow_file reports a broken file
    return settings if isinstance(settings, dict) else {}


def to_time_order(flow: dict[str, np.ndarray], input_order: np.ndarray | None,
                  source: str = "precomputed flow") -> dict[str, np.ndarray]:
    """A checked flow (:func:`check_flow`) whose ``index`` counts events in file order,
    re-indexed for the same events sorted by time: ``input_order[i]`` is the file position of
    the i-th event in time order (:attr:`evseg.io.Recording.input_order`; None: the file was
    in time order, and ``flow`` is returned as it is). Rows are sorted by the new index; an
    index past the recording raises :class:`~evseg.errors.FormatError` naming ``source``.

    >>> flow = check_flow({"index": [0, 2], "nx": [1.0, 2.0], "ny": [0.0, 0.0]})
    >>> moved = to_time_order(flow, np.array([2, 0, 1]))  # file event 2 comes first in time
    >>> moved["index"].tolist(), moved["nx"].tolist()
    ([0, 1], [2.0, 1.0])
    """
    if input_order is None:
        return flow
    position = np.empty(len(input_order), dtype=np.int64)
    position[input_order] = np.arange(len(input_order), dtype=np.int64)
    index = flow["index"]
    if len(index) and index[-1] >= len(input_order):
        raise FormatError(f"{source}: key 'index' has value {int(index[-1])} outside the "
                          f"recording's {len(input_order)} events (flow of another recording?)")
    moved = dict(flow)
    moved["index"] = position[index]
    return check_flow(moved)


def save_flow_file(
    path: str | Path,
    index,
    nx,
    ny,
    uncertainty=None,
    *,
    sensor_size: tuple[int, int] | None = None,
    window_us: int | None = None,
    method: str = "external",
    config: dict | None = None,
) -> None:
    """Write normal flow for target events to ``path`` (.npz, atomically: an error leaves an
    existing file as it was).

    Args:
        index: (T,) positions of the target events in the recording (any order; rows are
            written sorted by it).
        nx, ny: (T,) normal flow, px/s (x = column, y = row down).
        uncertainty: optional (T,), larger = less certain.
        sensor_size: (width, height) px, stored for reference. window_us: slice length, us.
        method: the estimator's name. config: JSON-serialisable settings, stored as text.

    Raises :class:`~evseg.errors.EvsegError` naming the key for arrays that do not fit the
    layout (see :func:`check_flow`).
    """
    from evseg.io._atomic import atomic_savez

    where = f"save_flow_file({path})"
    flow = check_flow({"index": index, "nx": nx, "ny": ny, "uncertainty": uncertainty}, source=where)
    try:
        text = json.dumps(config or {})
    except (TypeError, ValueError) as exc:
        raise EvsegError(f"{where}: config must be JSON-serialisable settings ({exc})") from None
    extra = {"method": np.str_(method), "config": np.str_(text)}
    if sensor_size is not None:
        from evseg.events import checked_sensor_size

        extra["sensor_size"] = np.asarray(checked_sensor_size(sensor_size), dtype=np.int64)
    if window_us is not None:
        from evseg.checks import is_int

        if not is_int(window_us) or window_us <= 0:
            raise EvsegError(f"{where}: window_us must be a positive integer (us), got {window_us!r}")
        extra["window_us"] = np.int64(window_us)
    atomic_savez(path, **flow, **extra)


@dataclass
class WindowFlow:
    """The rows of a flow that fall into one window: ``index`` into the window's events."""

    index: np.ndarray
    nx: np.ndarray
    ny: np.ndarray
    uncertainty: np.ndarray | None


def slice_flow(flow: Mapping[str, np.ndarray], first: int, n: int) -> WindowFlow:
    """Rows of a checked flow (:func:`check_flow`, sorted by index) that fall into events
    [first, first + n), re-indexed from ``first``."""
    index = flow["index"]
    a, b = np.searchsorted(index, [first, first + n])
    unc = flow.get("uncertainty")
    return WindowFlow(index[a:b] - first, flow["nx"][a:b], flow["ny"][a:b], None if unc is None else unc[a:b])
