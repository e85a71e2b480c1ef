"""The one in-memory form of event data used everywhere in evseg.

Events are a numpy structured array of dtype :data:`EVENT_DTYPE`:

========  =========  ===========================================================
field     dtype      meaning
========  =========  ===========================================================
``x``     uint16     pixel column, 0 = left
``y``     uint16     pixel row, 0 = **top**
``t``     int64      timestamp in microseconds (relative to ``t_offset_us``)
``p``     int8       polarity, **+1** (ON, brightness up) or **-1** (OFF)
========  =========  ===========================================================

Polarity is signed (+1/-1) rather than 0/1 so that it can be summed and multiplied
directly (event images, contrast sums); readers convert 0/1 and boolean ``on`` fields.

An :class:`EventStream` bundles the array with the sensor size, the time offset and an
optional camera calibration. Functions in evseg never mutate a caller's array; where they
need a changed copy they make one.

Example
-------
>>> import numpy as np
>>> from evseg.events import make_events, EventStream
>>> ev = make_events(x=[1, 2], y=[0, 0], t=[10, 20], p=[1, -1])
>>> stream = EventStream(ev, sensor_size=(4, 3))
>>> stream.duration_us
10
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Iterator

import numpy as np

from evseg.checks import is_whole
from evseg.errors import EventDataError

if TYPE_CHECKING:  # pragma: no cover
    from evseg.calibration import Calibration

EVENT_DTYPE = np.dtype([("x", "<u2"), ("y", "<u2"), ("t", "<i8"), ("p", "i1")])
"""dtype of every event array in evseg (see module docstring for units)."""




def make_events(x, y, t, p) -> np.ndarray:
    """Build an :data:`EVENT_DTYPE` array from four equal-length sequences.

    ``p`` may be +1/-1, 0/1 or boolean: values > 0 become +1, the others -1. ``x``, ``y``
    and ``t`` (microseconds) must be whole numbers that fit their fields (else
    :class:`~evseg.errors.EventDataError`): casting would truncate time in seconds to 0.

    >>> make_events([0], [1], [5], [0])["p"].tolist()
    [-1]
    """
    x, y, t, p = (np.asarray(a) for a in (x, y, t, p))
    for name, a in (("x", x), ("y", y), ("t", t), ("p", p)):
        if a.ndim != 1:
            raise EventDataError(f"make_events: field '{name}' must be a 1-D sequence of values, got shape {a.shape}")
        if len(a) and (not (np.issubdtype(a.dtype, np.number) or np.issubdtype(a.dtype, np.bool_))
                       or np.issubdtype(a.dtype, np.complexfloating)):
            raise EventDataError(f"make_events: field '{name}' must hold real numbers, got {a.dtype} "
                                 f"(first value {a[0]!r})")
    n = len(x)
    for name, a in (("y", y), ("t", t), ("p", p)):
        if len(a) != n:
            raise EventDataError(f"make_events: field '{name}' has {len(a)} values, 'x' has {n}")
    if n and np.issubdtype(p.dtype, np.floating) and not np.isfinite(p).all():
        i = int(np.flatnonzero(~np.isfinite(p))[0])
        raise EventDataError(f"make_events: field 'p' = {p[i].item()!r} at event {i} is not a polarity")
    # Storing into the integer fields would truncate or wrap silently: time in seconds would all
    # become 0, x = -1 would become 65535.
    for name, a, lo, hi in (("x", x, 0, 65535), ("y", y, 0, 65535), ("t", t, -(2**63), 2**63 - 1)) if n else ():
        if not (np.issubdtype(a.dtype, np.integer) or np.issubdtype(a.dtype, np.bool_)):
            whole = np.isfinite(a) & (a == np.round(a)) if np.issubdtype(a.dtype, np.number) else np.zeros(n, bool)
            if not whole.all():
                i = int(np.flatnonzero(~whole)[0])
                unit = " (integer microseconds; time in seconds: multiply by 1e6 and round)" if name == "t" else ""
                raise EventDataError(f"make_events: field '{name}' = {a[i].item()!r} at event {i} "
                                     f"is not a whole number{unit}")
        if a.min() < lo or a.max() > hi:
            i = int(np.flatnonzero((a < lo) | (a > hi))[0])
            raise EventDataError(f"make_events: field '{name}' = {a[i].item()!r} at event {i} is outside [{lo}, {hi}]")
    ev = np.empty(n, dtype=EVENT_DTYPE)
    ev["x"] = x
    ev["y"] = y
    ev["t"] = t
    ev["p"] = polarity_to_signed(p)
    return ev


def first_off_sensor(events: np.ndarray, sensor_size: tuple[int, int]) -> str | None:
    """``"event i at (x, y)"`` of the first event off a ``(width, height)`` sensor; None if all
    lie on it. Two max-reductions when every event is on the sensor (the common case).

    >>> first_off_sensor(make_events([1, 9], [2, 2], [0, 1], [1, 1]), (8, 4))
    'event 1 at (9, 2)'
    """
    w, h = sensor_size
    if len(events) == 0 or (int(events["x"].max()) < w and int(events["y"].max()) < h):
        return None
    i = int(np.flatnonzero((events["x"] >= w) | (events["y"] >= h))[0])
    return f"event {i} at ({int(events['x'][i])}, {int(events['y'][i])})"


def polarity_to_signed(p: np.ndarray) -> np.ndarray:
    """Map polarity in any common encoding (bool, 0/1, -1/+1) to int8 +1/-1."""
    p = np.asarray(p)
    if p.dtype == bool:
        return np.where(p, 1, -1).astype(np.int8)
    return np.where(p > 0, 1, -1).astype(np.int8)


def empty_events() -> np.ndarray:
    """A zero-length event array."""
    return np.empty(0, dtype=EVENT_DTYPE)


def checked_sensor_size(sensor_size) -> tuple[int, int]:
    """``(width, height)`` as two positive ints; a fractional, negative or malformed size is an
    :class:`EventDataError` (it would otherwise be truncated or fail deep inside numpy).

    >>> checked_sensor_size((346, 260.0))
    (346, 260)
    """
    try:
        w, h = sensor_size
        ok = all(not isinstance(v, (bool, np.bool_)) and float(v) == int(v) and int(v) > 0 for v in (w, h))
    except (TypeError, ValueError, OverflowError):
        ok = False
    if not ok:
        raise EventDataError(f"sensor_size must be (width, height) in whole pixels > 0, got {sensor_size!r}")
    return int(w), int(h)


def validate_events(
    events: np.ndarray,
    sensor_size: tuple[int, int] | None = None,
    source: str = "events",
    check_sorted: bool = True,
) -> None:
    """Raise :class:`EventDataError` if ``events`` breaks the event model.

    Checks the dtype, non-decreasing timestamps and (when ``sensor_size = (width, height)`` is
    given) that every coordinate lies on the sensor. The message names ``source``, the field
    and the index of the first bad event.
    """
    if not isinstance(events, np.ndarray) or events.dtype != EVENT_DTYPE:
        got = getattr(events, "dtype", type(events).__name__)
        raise EventDataError(f"{source}: expected an array of dtype {EVENT_DTYPE}, got {got}")
    if events.ndim != 1:
        raise EventDataError(f"{source}: expected a 1-D array of events, got shape {events.shape}")
    if len(events) == 0:
        return
    if check_sorted:
        bad = np.flatnonzero(np.diff(events["t"]) < 0)
        if len(bad):
            i = int(bad[0]) + 1
            raise EventDataError(
                f"{source}: field 't' is not sorted: event {i} has t={int(events['t'][i])} us "
                f"< t={int(events['t'][i - 1])} us of event {i - 1} "
                f"({len(bad)} decreasing steps in total; sort the events first)"
            )
    if sensor_size is not None:
        width, height = sensor_size
        for name, limit in (("x", width), ("y", height)):
            bad = np.flatnonzero(events[name] >= limit)
            if len(bad):
                i = int(bad[0])
                raise EventDataError(
                    f"{source}: field '{name}' = {int(events[name][i])} at event {i} is outside "
                    f"the sensor ({width}x{height}; {len(bad)} such events)"
                )


@dataclass(frozen=True)
class EventStream:
    """Events of one recording (or one chunk of it) with their sensor and time reference.

    Attributes:
        events: array of :data:`EVENT_DTYPE`, sorted by ``t``.
        sensor_size: ``(width, height)`` in pixels.
        t_offset_us: absolute time of ``t == 0`` in microseconds (e.g. a ROS epoch time),
            so that ``t`` itself stays small.
        calibration: optional camera intrinsics and distortion.
    """

    events: np.ndarray
    sensor_size: tuple[int, int]
    t_offset_us: int = 0
    calibration: "Calibration | None" = field(default=None, repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "sensor_size", checked_sensor_size(self.sensor_size))
        off = self.t_offset_us
        if not is_whole(off):
            raise EventDataError(f"EventStream.t_offset_us must be whole microseconds, got {off!r}")
        object.__setattr__(self, "t_offset_us", int(off))
        # Unsorted or off-sensor events would make durations, windows and labels silently
        # wrong later; one O(N) pass here names the first bad event instead.
        validate_events(self.events, self.sensor_size, source="EventStream.events")

    def __len__(self) -> int:
        return len(self.events)

    @property
    def width(self) -> int:
        return self.sensor_size[0]

    @property
    def height(self) -> int:
        return self.sensor_size[1]

    @property
    def duration_us(self) -> int:
        """Time from first to last event in microseconds (0 for fewer than 2 events)."""
        if len(self.events) < 2:
            return 0
        return int(self.events["t"][-1] - self.events["t"][0])

    @property
    def rate_ev_s(self) -> float:
        """Mean event rate in events per second (0 when undefined)."""
        d = self.duration_us
        return len(self.events) / (d * 1e-6) if d > 0 else 0.0

    def validate(self, source: str = "events") -> "EventStream":
        validate_events(self.events, self.sensor_size, source=source)
        return self

    def time_windows(self, window_us: int, stride_us: int | None = None) -> Iterator["EventStream"]:
        """Yield consecutive windows of fixed duration as views (no copy of the events)."""
        from evseg.windows import time_window_slices

        for sl in time_window_slices(self.events["t"], window_us, stride_us):
            yield self._view(self.events[sl])

    def with_events(self, events: np.ndarray) -> "EventStream":
        """Same sensor, offset and calibration, other events (checked as in the constructor)."""
        return EventStream(events, self.sensor_size, self.t_offset_us, self.calibration)

    def _view(self, events: np.ndarray) -> "EventStream":
        """:meth:`with_events` for a slice of this stream's own events: valid already."""
        out = object.__new__(EventStream)
        for name, value in (("events", events), ("sensor_size", self.sensor_size),
                            ("t_offset_us", self.t_offset_us), ("calibration", self.calibration)):
            object.__setattr__(out, name, value)
        return out
