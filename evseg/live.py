"""Live event sources: segment what a camera sends as it sends it, and keep up with it.

:meth:`MotionSegmentationPipeline.run <evseg.pipeline.MotionSegmentationPipeline.run>` segments
every window of a stream, however long each takes: right for a recording, wrong for a camera.
When a window takes longer to segment than the sensor takes to fill it (on 2 cores a 10 ms
window at 1 M events/s does), the backlog of a live source grows without bound and the labels
describe an ever older past. :func:`run_live` reads the source on a thread of its own, so events
arrive while a window is segmented, and when the windows waiting to be segmented reach further
back than ``max_lag_us`` behind the newest event it drops them and segments the newest complete
window instead: the labels stay at most one window's processing time plus ``max_lag_us`` old.
Each result says how many windows were dropped before it and how late it came.

:func:`replay` turns a recording into such a source: it hands out its events in packets at the
pace the sensor recorded them (or ``speed`` times that), which is how to try a live setting, and
how ``evseg segment --realtime`` and ``evseg bench live`` measure whether the pipeline keeps up.

Example::

    from evseg.io import read_events
    from evseg.live import replay, run_live
    from evseg.pipeline import MotionSegmentationPipeline, PipelineConfig

    stream = read_events("recording.aedat4")
    pipe = MotionSegmentationPipeline(PipelineConfig(), sensor_size=stream.sensor_size)
    for res in run_live(pipe, replay([stream.events]), max_lag_us=20_000):
        res.window.labels, res.window.boxes   # as from pipe.run
        res.dropped, res.latency_ms           # windows dropped before this one; how late it came

A camera driver's packet iterator (any iterable of sorted event arrays that blocks until the
next packet arrives) takes the place of ``replay(...)``.
"""

from __future__ import annotations

import queue
import threading
import time
from dataclasses import dataclass
from typing import Callable, Iterable, Iterator

import numpy as np

from evseg.errors import ConfigError, EventDataError
from evseg.events import EVENT_DTYPE
from evseg.windows import Window

DEFAULT_PACKET_US = 1_000
"""Span (us) of the packets :func:`replay` hands out: event cameras' drivers deliver events in
packets of about a millisecond (or a few thousand events)."""


@dataclass(frozen=True)
class LiveResult:
    """One segmented window of a live source.

    Attributes:
        window: the pipeline's :class:`~evseg.pipeline.WindowResult` (labels, boxes, masks).
        dropped: windows dropped just before this one to catch up with the source (their
            events get no labels; 0 while the pipeline keeps up).
        lag_us: sensor time (us) from this window's end to the newest event that had arrived
            when its segmentation started: how far behind the source the pipeline was.
        latency_ms: wall time (ms) from the arrival of the packet that completed this window
            (the first with an event at or after its end) to its result.
    """

    window: object
    dropped: int
    lag_us: int
    latency_ms: float


def replay(
    chunks: Iterable[np.ndarray],
    speed: float = 1.0,
    packet_us: int = DEFAULT_PACKET_US,
    clock: Callable[[], float] = time.perf_counter,
    sleep: Callable[[float], None] = time.sleep,
) -> Iterator[np.ndarray]:
    """Hand out a recording's events in packets at the pace they were recorded.

    Args:
        chunks: sorted event arrays (:data:`~evseg.events.EVENT_DTYPE`), e.g. a reader's
            ``chunks()`` or ``[stream.events]``.
        speed: 1.0 = the sensor's pace; 2.0 twice as fast; ``float('inf')`` as fast as possible.
        packet_us: span (us) of each packet; a packet is handed out once the sensor's clock
            has passed its end, as a driver delivers a packet once it is full.
        clock, sleep: wall clock (s) and how to wait (s); replaceable for tests.

    Yields:
        Consecutive slices of the events, each within one ``packet_us`` span.
    """
    if not speed > 0:
        raise ConfigError(f"replay speed must be positive, got {speed!r}")
    if int(packet_us) != packet_us or packet_us <= 0:
        raise ConfigError(f"replay packet_us must be a positive integer (us), got {packet_us!r}")
    packet_us = int(packet_us)
    t_first = None  # sensor time (us) of the first event
    wall_first = 0.0
    for chunk in chunks:
        if len(chunk) == 0:
            continue
        t = chunk["t"]
        if t_first is None:
            t_first, wall_first = int(t[0]), clock()
        bins = (t.astype(np.int64) - t_first) // packet_us
        cuts = np.flatnonzero(np.diff(bins)) + 1
        for a, b in zip(np.r_[0, cuts], np.r_[cuts, len(chunk)]):
            if np.isfinite(speed):
                due = wall_first + (int(bins[a]) + 1) * packet_us * 1e-6 / speed
                wait = due - clock()
                if wait > 0:
                    sleep(wait)
            yield chunk[a:b]


_END = object()


def _read_into(source: Iterable[np.ndarray], packets: "queue.Queue", clock: Callable[[], float],
               stop: threading.Event) -> None:
    """Reader thread: put ``(packet, arrival time)`` for each packet, then the end marker (or
    the error that ended the source)."""
    try:
        for packet in source:
            if stop.is_set():
                return
            packets.put((packet, clock()))
        packets.put((_END, clock()))
    except BaseException as exc:  # handed to the consuming thread, which raises it
        packets.put((exc, clock()))


def newest_window_start(t0_us: int, t_last_us: int, window_us: int, stride_us: int, final: bool) -> int:
    """Start (us) of the newest window that can be segmented once events up to ``t_last_us``
    have arrived: the newest complete one (its end at or before ``t_last_us``) or, at the end
    of the stream (``final``), the newest that holds an event; never before ``t0_us``.

    >>> newest_window_start(0, 95, 10, 10, final=False)   # [80, 90) is the newest complete one
    80
    >>> newest_window_start(0, 95, 10, 10, final=True)    # the last event is in [90, 100)
    90
    """
    reach = t_last_us if final else t_last_us - window_us
    return t0_us + max((reach - t0_us) // stride_us, 0) * stride_us


def run_live(
    pipeline,
    source: Iterable[np.ndarray],
    max_lag_us: int | None = 20_000,
    clock: Callable[[], float] = time.perf_counter,
) -> Iterator[LiveResult]:
    """Segment a live source window by window, dropping windows when it falls behind.

    The source is read on its own thread (packets arrive while a window is segmented). Before
    each window, if the newest event that has arrived is more than ``max_lag_us`` past the
    window's end, the windows up to the newest complete one are dropped (their events get no
    labels) and that one is segmented; the pipeline's object tracks are moved on over the gap
    (:meth:`~evseg.pipeline.MotionSegmentationPipeline.skip_windows`), so an object whose motion
    holds keeps its id. Windows are segmented one after the other (the pipeline's ``overlap``
    does not apply: a live window cannot be read before it has happened).

    Args:
        pipeline: a :class:`~evseg.pipeline.MotionSegmentationPipeline` (its learned or plane-fit
            flow; precomputed flow has no place in a live run).
        source: sorted event packets (:data:`~evseg.events.EVENT_DTYPE`), contiguous in time,
            e.g. :func:`replay` of a recording or a camera driver's packet iterator.
        max_lag_us: how far (us) behind the newest event a window may end and still be
            segmented; None never drops (every window is segmented, however late: the results
            are those of ``pipeline.run`` with ``overlap=False``).
        clock: wall clock (s) for ``latency_ms``.

    Yields:
        :class:`LiveResult` per segmented window, in time order; ``result.window.first_event``
        counts the source's events before the window, as ``pipeline.run`` does.
    """
    if max_lag_us is not None and (int(max_lag_us) != max_lag_us or max_lag_us < 0):
        raise ConfigError(f"max_lag_us must be a non-negative integer (us) or None, got {max_lag_us!r}")
    cfg = pipeline.config
    if cfg.flow == "precomputed":
        raise ConfigError("a live run estimates its own normal flow: pipeline.flow must be learned or planefit, "
                          "not precomputed")
    window_us = int(cfg.window_us)
    stride_us = int(cfg.stride_us or cfg.window_us)
    kept_us = int(pipeline.kept_us)

    packets: queue.Queue = queue.Queue()
    stop = threading.Event()
    reader = threading.Thread(target=_read_into, args=(source, packets, clock, stop),
                              name="evseg-live-reader", daemon=True)
    reader.start()

    buf = np.empty(0, dtype=EVENT_DTYPE)
    buf_first = 0  # position in the source of buf[0]
    arrivals: list[tuple[int, float]] = []  # (last event time, arrival) of the packets in buf
    t0: int | None = None
    index = 0
    ended = False
    try:
        while True:
            # Take every packet that has arrived; wait for one when no window is ready.
            block = not ended and (t0 is None or not len(buf) or t0 + window_us > int(buf["t"][-1]))
            new = [buf] if len(buf) else []
            while True:
                try:
                    packet, arrived = packets.get(block=block)
                except queue.Empty:
                    break
                block = False
                if packet is _END:
                    ended = True
                    break
                if isinstance(packet, BaseException):
                    raise packet
                if len(packet) == 0:
                    continue
                _check_packet(packet, new[-1] if new else buf)
                if t0 is None:
                    t0 = int(packet["t"][0])
                new.append(packet)
                arrivals.append((int(packet["t"][-1]), arrived))
            # One copy per drain, not per packet (a backlog of many packets would be quadratic).
            if len(new) > 1:
                buf = np.concatenate(new)
            elif new:
                buf = new[0]
            if t0 is None or not len(buf):
                if ended:
                    return
                continue
            t_last = int(buf["t"][-1])
            if not ended and t0 + window_us > t_last:
                continue  # the window is not complete yet
            if ended and t0 > t_last:
                return
            newest = newest_window_start(t0, t_last, window_us, stride_us, final=ended)
            lag = max(t_last - (t0 + window_us), 0)
            dropped = 0
            if max_lag_us is not None and lag > max_lag_us and newest > t0:
                dropped = (newest - t0) // stride_us
                pipeline.skip_windows(dropped)
                t0, index = newest, index + dropped
            t = buf["t"]
            c0, i0, i1 = np.searchsorted(t, [t0 - kept_us, t0, t0 + window_us], side="left")
            window = Window(index, t0, t0 + window_us, buf[i0:i1], buf_first + int(i0))
            completed = next((a for t_end, a in arrivals if t_end >= t0 + window_us), arrivals[-1][1])
            result = pipeline.process(window, context=buf[c0:i0] if kept_us else None)
            yield LiveResult(result, int(dropped), int(max(t_last - (t0 + window_us), 0)),
                             (clock() - completed) * 1e3)
            index += 1
            t0 += stride_us
            # Keep what later windows and their context can still need.
            drop = int(np.searchsorted(buf["t"], t0 - kept_us, side="left"))
            buf, buf_first = buf[drop:], buf_first + drop
            arrivals = [(t_end, a) for t_end, a in arrivals if t_end >= t0 - kept_us] or arrivals[-1:]
    finally:
        stop.set()


def _check_packet(packet: np.ndarray, buf: np.ndarray) -> None:
    """A live packet must be events, sorted, and not older than the one before it: a window
    once segmented cannot take late events."""
    if packet.dtype != EVENT_DTYPE:
        raise EventDataError(f"live source: a packet must be an event array of dtype {EVENT_DTYPE} "
                             f"(evseg.events.make_events(x, y, t, p) makes one), got dtype {packet.dtype}")
    t = packet["t"]
    if len(t) > 1 and np.any(np.diff(t) < 0):
        at = int(np.flatnonzero(np.diff(t) < 0)[0])
        raise EventDataError(f"live source: packet timestamps go back in time ({int(t[at])} -> "
                             f"{int(t[at + 1])} us): sort the events of each packet")
    if len(buf) and int(t[0]) < int(buf["t"][-1]):
        raise EventDataError(f"live source: a packet starts at {int(t[0])} us, before the previous "
                             f"packet's last event at {int(buf['t'][-1])} us: packets must come in time order")
