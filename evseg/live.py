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
from typing import TYPE_CHECKING, Callable, Iterable, Iterator

import numpy as np

from evseg.checks import is_whole
from evseg.errors import ConfigError, EventDataError
from evseg.events import EVENT_DTYPE, first_off_sensor
from evseg.windows import Window, as_event_chunks

if TYPE_CHECKING:  # pragma: no cover
    from evseg.pipeline import MotionSegmentationPipeline, WindowResult

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

    window: "WindowResult"
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
    chunks = as_event_chunks(chunks, "replay")  # one array of events: a recording of one chunk
    if not (isinstance(speed, (int, float, np.integer, np.floating)) and speed > 0):
        raise ConfigError(f"replay speed must be a positive number, got {speed!r}")
    if int(packet_us) != packet_us or packet_us <= 0:
        raise ConfigError(f"replay packet_us must be a positive integer (us), got {packet_us!r}")
    packet_us = int(packet_us)
    t_first = None  # sensor time (us) of the first event
    t_newest = None
    wall_first = 0.0
    for chunk in chunks:
        _check_packet(chunk, t_newest, "replay")
        if len(chunk) == 0:
            continue
        t = chunk["t"]
        t_newest = int(t[-1])
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
    pipeline: "MotionSegmentationPipeline",
    source: Iterable[np.ndarray],
    max_lag_us: int | None = 20_000,
    clock: Callable[[], float] = time.perf_counter,
) -> Iterator[LiveResult]:
    """Segment a live source window by window, dropping windows when it falls behind.

    The source is read on its own thread (packets arrive while a window is segmented). When a
    window is picked, if the newest event that has arrived is more than ``max_lag_us`` past the
    window's end, the windows up to the newest complete one are dropped (their events get no
    labels) and that one is taken; the pipeline's object tracks are moved on over the gap
    (:meth:`~evseg.pipeline.MotionSegmentationPipeline.skip_windows`), so an object whose motion
    holds keeps its id.

    With the pipeline's ``overlap`` (its default), the next window is picked and its normal flow
    and graph are computed by the pipeline's worker (``worker``: thread or process) while the
    current one is segmented, as :meth:`~evseg.pipeline.MotionSegmentationPipeline.run` does:
    more windows per second when the pipeline cannot keep up; without it each window is picked
    once the one before has its labels, which gives the lowest latency when it can.

    Args:
        pipeline: a :class:`~evseg.pipeline.MotionSegmentationPipeline` (its learned or plane-fit
            flow; precomputed flow has no place in a live run).
        source: sorted event packets (:data:`~evseg.events.EVENT_DTYPE`), contiguous in time,
            e.g. :func:`replay` of a recording or a camera driver's packet iterator.
        max_lag_us: how far (us) behind the newest event a window may end and still be
            segmented; None never drops (every window is segmented, however late: the results
            are those of ``pipeline.run``, and a source faster than the pipeline leaves a
            growing backlog of events in memory). One difference by design: with gaps between
            windows (stride longer than the window) the gap's events that have arrived are
            context for the next window's flow, as after dropped windows; ``pipeline.run``
            never reads them.
        clock: wall clock (s) for ``latency_ms``.

    Yields:
        :class:`LiveResult` per segmented window, in time order; ``result.window.first_event``
        counts the source's events before the window, as ``pipeline.run`` does. When the source
        raises (a camera unplugged), the windows complete before are yielded first, then its
        error is raised. The reader thread pulls the source until the generator is closed: after
        leaving a loop over it early, call its ``close()`` (or drop it) to stop the source.
    """
    if max_lag_us is not None and not (is_whole(max_lag_us) and max_lag_us >= 0):
        raise ConfigError(f"max_lag_us must be a non-negative integer (us) or None, got {max_lag_us!r}")
    from evseg.pipeline import MotionSegmentationPipeline

    if not isinstance(pipeline, MotionSegmentationPipeline):
        raise ConfigError(f"run_live needs a MotionSegmentationPipeline, got {type(pipeline).__name__}")
    # One array (or stream) of events is a source of one packet, as pipeline.run takes it.
    source = as_event_chunks(source, "run_live")
    return pipeline._exclusive(_run_live(pipeline, source, max_lag_us, clock))


def _run_live(pipeline, source, max_lag_us, clock) -> Iterator[LiveResult]:
    cfg = pipeline.config
    if cfg.flow == "precomputed":
        raise ConfigError("a live run estimates its own normal flow: pipeline.flow must be learned or planefit, "
                          "not precomputed")
    pipeline.reset()  # a live run starts afresh, as pipeline.run does
    packets: queue.Queue = queue.Queue()
    stop = threading.Event()
    reader = threading.Thread(target=_read_into, args=(source, packets, clock, stop),
                              name="evseg-live-reader", daemon=True)
    reader.start()
    windows = _LiveWindows(packets, int(cfg.window_us), int(cfg.stride_us or cfg.window_us),
                           int(pipeline.kept_us), max_lag_us, pipeline.sensor_size)
    try:
        if pipeline.overlaps:
            yield from _overlapped(pipeline, windows, clock)
            return
        while (live := windows.take(block=True)) is not None:
            pipeline.skip_windows(live.dropped)
            yield _result(live, pipeline.process(live.window, context=live.context), clock)
    finally:
        stop.set()


@dataclass(frozen=True)
class _LiveWindow:
    """A window picked from a live source: its events, the events before it (the flow's
    context), the windows dropped before it, its lag (us) and when it was complete (s)."""

    window: Window
    context: np.ndarray | None
    dropped: int
    lag_us: int
    completed_s: float


_NOT_READY = object()


def _overlapped(pipeline, windows: "_LiveWindows", clock: Callable[[], float]) -> Iterator[LiveResult]:
    """Window t + 1 is picked, and its flow and graph computed by the pipeline's worker, while
    window t is segmented, when window t + 1 is complete by the time window t's flow and graph
    are (the pipeline is behind); otherwise window t is segmented at once, so that its labels
    never wait for window t + 1."""
    from concurrent.futures import wait

    pending = None  # (picked window, future of what the segmentation needs)
    try:
        while True:
            if pending is None:
                live = windows.take(block=True)
                if live is None:
                    return
                pending = (live, pipeline.submit_prepare(live.window, live.context))
            wait([pending[1]])
            try:
                live = windows.take(block=False)
            except BaseException:
                # The source failed: the window already prepared is still segmented and yielded.
                done, pending = pending, None
                yield _finish(pipeline, *done, clock)
                raise
            job = None
            if live is not None and live is not _NOT_READY:
                job = (live, pipeline.submit_prepare(live.window, live.context))
            done, pending = pending, job
            yield _finish(pipeline, *done, clock)
            if live is None:
                return
    finally:
        if pending is not None:
            pending[1].cancel()


def _finish(pipeline, live: _LiveWindow, future, clock: Callable[[], float]) -> LiveResult:
    pipeline.skip_windows(live.dropped)
    return _result(live, pipeline.finish_prepared(live.window, future), clock)


def _result(live: _LiveWindow, result, clock: Callable[[], float]) -> LiveResult:
    """The :class:`LiveResult` of a picked window segmented just now."""
    return LiveResult(result, live.dropped, live.lag_us, (clock() - live.completed_s) * 1e3)


class _LiveWindows:
    """The windows to segment from the packets a reader thread puts in ``packets``, each picked
    when :meth:`take` is called: the next window, or the newest complete one when the next ends
    more than ``max_lag_us`` before the newest event that has arrived."""

    def __init__(self, packets: "queue.Queue", window_us: int, stride_us: int, kept_us: int,
                 max_lag_us: int | None, sensor_size: tuple[int, int] | None = None) -> None:
        self.packets, self.window_us, self.stride_us = packets, window_us, stride_us
        self.sensor_size = sensor_size
        self.n_packets = 0
        self.kept_us, self.max_lag_us = kept_us, max_lag_us
        self.buf = np.empty(0, dtype=EVENT_DTYPE)
        self.buf_first = 0  # position in the source of buf[0]
        self.arrivals: list[tuple[int, float]] = []  # (last event time, arrival) of the packets in buf
        self.t0: int | None = None  # start of the next window
        self.index = 0
        self.ended = False
        self.error: BaseException | None = None  # what ended the source, when it failed
        self.t_newest: int | None = None  # time (us) of the newest event of any packet so far

    @property
    def final(self) -> bool:
        """The source ended normally: its last window may be incomplete. A source that failed
        gives only the windows that were complete before it failed, as ``pipeline.run`` does."""
        return self.ended and self.error is None

    def _ready(self) -> bool:
        return self.t0 is not None and len(self.buf) > 0 and (
            self.t0 + self.window_us <= int(self.buf["t"][-1]) or (self.final and self.t0 <= int(self.buf["t"][-1])))

    def _drain(self, block: bool) -> None:
        """Take every packet that has arrived; with ``block``, wait for one first."""
        new = [self.buf] if len(self.buf) else []
        while not self.ended:
            try:
                packet, arrived = self.packets.get(block=block)
            except queue.Empty:
                break
            block = False
            if packet is _END:
                self.ended = True
                break
            if isinstance(packet, BaseException):
                # Raised by take() once the windows complete before the failure are handed out.
                self.error, self.ended = packet, True
                break
            self.n_packets += 1
            if len(packet) == 0:
                continue
            _check_packet(packet, self.t_newest)
            off = None if self.sensor_size is None else first_off_sensor(packet, self.sensor_size)
            if off is not None:
                w, h = self.sensor_size
                raise EventDataError(f"live source: packet {self.n_packets - 1}: {off} (t={int(packet['t'][0])} us "
                                     f"at its start) is outside the {w}x{h} sensor the pipeline was made for")
            if self.t0 is None:
                self.t0 = int(packet["t"][0])
            new.append(packet)
            self.t_newest = int(packet["t"][-1])
            self.arrivals.append((self.t_newest, arrived))
        # One copy per drain, not per packet (a backlog of many packets would be quadratic).
        if len(new) > 1:
            self.buf = np.concatenate(new)
        elif new:
            self.buf = new[0]

    def take(self, block: bool):
        """The next window to segment (:class:`_LiveWindow`); None once the source has ended and
        every window holding its events was taken; without ``block``, :data:`_NOT_READY` when no
        window is complete yet (with ``block`` it waits for one)."""
        self._drain(block=False)
        while not self._ready():
            if self.ended:
                if self.error is not None:
                    raise self.error
                return None
            if not block:
                return _NOT_READY
            self._drain(block=True)
        w, stride = self.window_us, self.stride_us
        t_last = int(self.buf["t"][-1])
        newest = newest_window_start(self.t0, t_last, w, stride, final=self.final)
        dropped = 0
        if self.max_lag_us is not None and t_last - (self.t0 + w) > self.max_lag_us and newest > self.t0:
            dropped = (newest - self.t0) // stride
            self.t0, self.index = newest, self.index + dropped
        t0, buf = self.t0, self.buf
        c0, i0, i1 = np.searchsorted(buf["t"], [t0 - self.kept_us, t0, t0 + w], side="left")
        completed = next((a for t_end, a in self.arrivals if t_end >= t0 + w), self.arrivals[-1][1])
        live = _LiveWindow(Window(self.index, t0, t0 + w, buf[i0:i1], self.buf_first + int(i0)),
                           buf[c0:i0] if self.kept_us else None, int(dropped), int(max(t_last - (t0 + w), 0)),
                           completed)
        self.index += 1
        self.t0 += stride
        # Keep what later windows and their context can still need.
        cut = int(np.searchsorted(buf["t"], self.t0 - self.kept_us, side="left"))
        self.buf, self.buf_first = buf[cut:], self.buf_first + cut
        keep = [(t_end, a) for t_end, a in self.arrivals if t_end >= self.t0 - self.kept_us]
        self.arrivals = keep or self.arrivals[-1:]
        return live


def _check_packet(packet: np.ndarray, t_newest: int | None, where: str = "live source") -> None:
    """A live packet must be events, sorted, and not older than the newest event of the packets
    before it (``t_newest``, us): a window once segmented cannot take late events."""
    if getattr(packet, "dtype", None) != EVENT_DTYPE:
        got = f"dtype {packet.dtype}" if isinstance(packet, np.ndarray) else type(packet).__name__
        raise EventDataError(f"{where}: a packet must be an event array of dtype {EVENT_DTYPE} "
                             f"(evseg.events.make_events(x, y, t, p) makes one), got {got}")
    t = packet["t"]
    if len(t) > 1 and np.any(np.diff(t) < 0):
        at = int(np.flatnonzero(np.diff(t) < 0)[0])
        raise EventDataError(f"{where}: packet timestamps go back in time ({int(t[at])} -> "
                             f"{int(t[at + 1])} us): sort the events of each packet")
    if t_newest is not None and len(t) and int(t[0]) < t_newest:
        raise EventDataError(f"{where}: a packet starts at {int(t[0])} us, before the previous "
                             f"packet's last event at {t_newest} us: packets must come in time order")
