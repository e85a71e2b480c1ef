"""Time windows over event arrays: by fixed duration or fixed event count.

All slicing is index based (``np.searchsorted`` on the sorted timestamps), so a window of an
in-memory recording is a view, never a copy. :func:`stream_time_windows` does the same over a
chunked reader so that a recording larger than memory is processed window by window.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Iterator

import numpy as np

from evseg.checks import is_whole
from evseg.errors import EventDataError
from evseg.events import EVENT_DTYPE, validate_events


@dataclass(frozen=True)
class Window:
    """One time window: events with ``t0_us <= t < t1_us``.

    Attributes:
        index: running window number, from 0.
        t0_us, t1_us: window bounds in microseconds (same time base as the events).
        events: array of :data:`~evseg.events.EVENT_DTYPE` (a view where possible).
        first_event: position of ``events[0]`` in the whole recording, so that per-event
            results can be written back in input order.
    """

    index: int
    t0_us: int
    t1_us: int
    events: np.ndarray
    first_event: int


def as_event_chunks(source, where: str) -> Iterable[np.ndarray]:
    """A stream given as an :class:`~evseg.events.EventStream`, one event array or an iterable
    of event arrays, as an iterable of event arrays; errors name ``where``."""
    from evseg.events import EventStream

    if isinstance(source, EventStream):
        return [source.events]
    if isinstance(source, np.ndarray):
        if source.dtype == EVENT_DTYPE:
            return [source]
        raise EventDataError(
            f"{where}: an array of dtype {source.dtype} is not events; pass an "
            f"array of dtype {EVENT_DTYPE} (evseg.events.make_events(x, y, t, p) makes one), an "
            "EventStream, or an iterable of such arrays")
    if isinstance(source, (str, bytes)) or not hasattr(source, "__iter__"):
        raise EventDataError(
            f"{where}: expected an EventStream, an event array or an iterable "
            f"of event arrays, got {type(source).__name__} (a file: evseg.io.open_recording(path).chunks())")
    return source


def _check_positive(name: str, value: int) -> int:
    if int(value) != value or value <= 0:
        raise ValueError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


def time_window_bounds(
    t_first_us: int, t_last_us: int, window_us: int, stride_us: int | None = None
) -> np.ndarray:
    """Start times (us) of windows of ``window_us`` every ``stride_us`` covering the span.

    The first window starts at ``t_first_us``; the last one is the first that reaches past
    ``t_last_us``. ``stride_us`` defaults to ``window_us`` (back-to-back windows).

    >>> time_window_bounds(0, 25, 10).tolist()
    [0, 10, 20]
    """
    window_us = _check_positive("window_us", window_us)
    stride_us = _check_positive("stride_us", stride_us if stride_us is not None else window_us)
    n = max(1, int((t_last_us - t_first_us) // stride_us) + 1)
    return t_first_us + stride_us * np.arange(n, dtype=np.int64)


def time_window_slices(
    t_us: np.ndarray, window_us: int, stride_us: int | None = None
) -> list[slice]:
    """Slices of a sorted timestamp array into windows ``[t0, t0 + window_us)``.

    >>> t = np.array([0, 3, 9, 10, 25])
    >>> [(s.start, s.stop) for s in time_window_slices(t, 10)]
    [(0, 3), (3, 4), (4, 5)]
    """
    t_us = np.asarray(t_us)
    if len(t_us) == 0:
        return []
    if np.any(t_us[1:] < t_us[:-1]):
        # searchsorted on unsorted times returns slices that miss events without a word.
        i = int(np.flatnonzero(t_us[1:] < t_us[:-1])[0]) + 1
        raise EventDataError(f"time_window_slices: times not sorted: t = {int(t_us[i])} us at {i} after "
                             f"{int(t_us[i - 1])} us")
    starts = time_window_bounds(int(t_us[0]), int(t_us[-1]), window_us, stride_us)
    i0 = np.searchsorted(t_us, starts, side="left")
    i1 = np.searchsorted(t_us, starts + window_us, side="left")
    return [slice(int(a), int(b)) for a, b in zip(i0, i1)]


def count_window_slices(n_events: int, count: int, stride: int | None = None) -> list[slice]:
    """Slices of ``count`` consecutive events every ``stride`` events (last may be shorter).

    >>> [(s.start, s.stop) for s in count_window_slices(5, 2)]
    [(0, 2), (2, 4), (4, 5)]
    """
    count = _check_positive("count", count)
    stride = _check_positive("stride", stride if stride is not None else count)
    return [slice(i, min(i + count, n_events)) for i in range(0, n_events, stride)]


def stream_time_windows(
    chunks: Iterable[np.ndarray],
    window_us: int,
    stride_us: int | None = None,
    t_start_us: int | None = None,
) -> Iterator[Window]:
    """Cut a stream of sorted event chunks into fixed-duration windows.

    Memory stays bounded by one window plus one chunk: events older than the next window
    start are dropped as soon as no later window can contain them. Empty windows (gaps in the
    recording) are yielded too, with zero events, so window indices map to fixed times.

    Args:
        chunks: iterable of :data:`EVENT_DTYPE` arrays, sorted and contiguous in time.
        window_us: window duration in microseconds.
        stride_us: time between window starts (default ``window_us``); may be shorter
            (overlapping windows) or longer (gaps) than the window.
        t_start_us: start of the first window (default: time of the first event).
    """
    yield from ordered_time_windows(_in_order(chunks), window_us, stride_us, t_start_us)


def _in_order(chunks: Iterable[np.ndarray]) -> Iterator[np.ndarray]:
    """``chunks`` as they are, after checking each is sorted events and none starts before the
    one before it ended: windows are cut by searchsorted, so either would lose events silently."""
    t_prev = None
    for k, chunk in enumerate(chunks):
        if len(chunk) == 0:
            continue
        validate_events(chunk, None, source=f"stream_time_windows: chunk {k}")
        if t_prev is not None and int(chunk["t"][0]) < t_prev:
            raise EventDataError(f"stream_time_windows: chunk {k} starts at t = {int(chunk['t'][0])} us, before "
                                 f"the chunk before it ended (t = {t_prev} us)")
        t_prev = int(chunk["t"][-1])
        yield chunk


def ordered_time_windows(
    chunks: Iterable[np.ndarray],
    window_us: int,
    stride_us: int | None = None,
    t_start_us: int | None = None,
) -> Iterator[Window]:
    """:func:`stream_time_windows` of chunks their caller has checked already (sorted events,
    each starting where the one before ended; the pipeline's own checks name its chunks)."""
    window_us = _check_positive("window_us", window_us)
    stride_us = _check_positive("stride_us", stride_us if stride_us is not None else window_us)
    if t_start_us is not None and not is_whole(t_start_us):
        raise ValueError(f"t_start_us must be a whole number of microseconds, got {t_start_us!r}")
    buf = np.empty(0, dtype=EVENT_DTYPE)
    buf_first = 0  # index in the recording of buf[0]
    seen = 0  # events received so far
    t0 = None if t_start_us is None else int(t_start_us)
    index = 0
    for chunk in chunks:
        if len(chunk) == 0:
            continue
        if t0 is None:
            t0 = int(chunk["t"][0])
        elif index == 0 and seen == 0 and int(chunk["t"][0]) < t0:
            raise EventDataError(f"stream_time_windows: the first event (t = {int(chunk['t'][0])} us) lies before "
                                 f"t_start_us = {t0} us; its events would belong to no window")
        buf = np.concatenate([buf, chunk]) if len(buf) else chunk
        seen += len(chunk)
        t_last = int(buf["t"][-1])
        # A window is complete once an event at or after its end has arrived.
        while t0 + window_us <= t_last:
            yield _cut(buf, buf_first, index, t0, window_us)
            index += 1
            t0 += stride_us
            drop = int(np.searchsorted(buf["t"], t0, side="left"))
            buf, buf_first = buf[drop:], buf_first + drop
    if t0 is not None and len(buf):
        # Flush: windows that still hold events, including the partial last one.
        while t0 <= int(buf["t"][-1]):
            yield _cut(buf, buf_first, index, t0, window_us)
            index += 1
            t0 += stride_us


def _cut(buf: np.ndarray, buf_first: int, index: int, t0: int, window_us: int) -> Window:
    i0 = int(np.searchsorted(buf["t"], t0, side="left"))
    i1 = int(np.searchsorted(buf["t"], t0 + window_us, side="left"))
    return Window(index, t0, t0 + window_us, buf[i0:i1], buf_first + i0)


class EventHistory:
    """The events just before each window of a stream, kept for the windows that follow.

    The normal flow of an event at the start of a window depends on where its edge was a few
    milliseconds earlier, i.e. on events of the previous window: an estimator that only sees
    the window itself has one-sided neighbourhoods there and almost none on slow scenes.
    ``EventHistory`` keeps the last ``duration_us`` of the stream so that each window can be
    given that context (``before``), then learns the window (``add``). Memory: one context
    span of events. Works with overlapping windows (events are never duplicated) and with gaps
    between windows (stride > duration), where the events of the gaps, never read, are no
    context either.

    >>> import numpy as np
    >>> from evseg.events import make_events
    >>> ev = make_events(np.zeros(4), np.zeros(4), np.array([0, 5, 12, 18]), np.ones(4))
    >>> hist = EventHistory(10)
    >>> hist.add(Window(0, 0, 10, ev[:2], 0))
    >>> hist.before(Window(1, 10, 20, ev[2:], 2))["t"].tolist()
    [0, 5]
    """

    def __init__(self, duration_us: int) -> None:
        if int(duration_us) != duration_us or duration_us < 0:
            raise ValueError(f"context duration must be a non-negative integer (us), got {duration_us!r}")
        self.duration_us = int(duration_us)
        self._events = np.empty(0, dtype=EVENT_DTYPE)
        self._end_us: int | None = None  # every event before this time has been added

    def before(self, window: Window) -> np.ndarray:
        """Events with ``window.t0_us - duration_us <= t < window.t0_us`` (sorted by t)."""
        if self.duration_us == 0 or len(self._events) == 0:
            return self._events[:0]
        t = self._events["t"]
        a, b = np.searchsorted(t, [window.t0_us - self.duration_us, window.t0_us], side="left")
        return self._events[a:b]

    def add(self, window: Window) -> None:
        """Remember the events of ``window`` (those not already added) and forget what no
        later window can need (windows start at increasing times)."""
        ev = window.events
        if self._end_us is not None and len(ev):
            ev = ev[np.searchsorted(ev["t"], self._end_us, side="left"):]
        if self.duration_us == 0:
            self._end_us = window.t1_us
            return
        keep_from = window.t0_us - self.duration_us
        old = self._events[np.searchsorted(self._events["t"], keep_from, side="left"):]
        self._events = np.concatenate([old, ev]) if len(old) else np.array(ev, copy=True)
        self._end_us = window.t1_us if self._end_us is None else max(self._end_us, window.t1_us)
