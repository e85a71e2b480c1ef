"""The reader interface: a :class:`Recording` streams validated event chunks from one file.

Every format module provides a *source*: an object with the metadata the file declares
(sensor size, time offset, calibration) and a generator of raw :class:`Chunk` s. A
:class:`Recording` wraps a source and checks each chunk against the event model before handing
it on, so a broken file fails with one message naming the file, the format and the position
(line, byte offset or event index), never with a numpy traceback from deep inside a decoder.

Checks applied to every chunk (across chunk boundaries too):

* timestamps must be non-negative and non-decreasing. Unsorted input is rejected unless the
  recording is opened with ``sort=True``, which loads the whole recording, sorts it stably by
  ``t`` and then streams the sorted copy (memory: the whole recording);
* coordinates must lie on the sensor when the file (or the caller) declares its size.

When neither the file nor the caller gives a sensor size, :meth:`Recording.read_all` infers it
as ``(max x + 1, max y + 1)`` and records that in :attr:`Recording.sensor_size_source`
(``"inferred"``), so callers can say so.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Iterable, Iterator, Protocol

import numpy as np

from evseg.errors import EventDataError, EvsegError, FormatError
from evseg.events import EVENT_DTYPE, EventStream, checked_sensor_size, empty_events

if TYPE_CHECKING:  # pragma: no cover
    from evseg.calibration import Calibration

DEFAULT_CHUNK_EVENTS = 1_000_000
"""Events per chunk yielded by the readers (about 16 MB of :data:`EVENT_DTYPE`)."""


@dataclass(frozen=True)
class Chunk:
    """Events decoded from one stretch of a file.

    Attributes:
        events: :data:`EVENT_DTYPE` array, ``t`` in microseconds relative to the source's
            ``t_offset_us``; not yet validated.
        locate: maps an index into ``events`` to a position in the file for error messages
            (e.g. ``"line 12"`` or ``"byte offset 4096"``); ``None`` means "event <index>".
    """

    events: np.ndarray
    locate: Callable[[int], str] | None = None


class Source(Protocol):
    """What a format module provides to :class:`Recording` (see module docstring)."""

    format: str
    sensor_size: tuple[int, int] | None
    t_offset_us: int
    calibration: "Calibration | None"

    def chunks(self, chunk_events: int) -> Iterator[Chunk]: ...

    def close(self) -> None: ...

    # Optional: ``time_span_us() -> (first t, last t) | None``, the times (us, chunk time) of the
    # file's first and last events when the format can read them without decoding the file
    # (arrays, HDF5). Used for progress bars only; sources that cannot tell leave it out.


class Recording:
    """A recording file opened for streaming; use as a context manager.

    Attributes:
        path: the file.
        format: registry name of the format (see :data:`evseg.io.FORMATS`).
        sensor_size: ``(width, height)`` in px from the caller, the file, or (after
            :meth:`read_all` or a full pass of :meth:`chunks`) inferred; ``None`` if unknown.
        sensor_size_source: ``"user"``, ``"file"``, ``"inferred"``, ``"calibration"`` (set by
            :meth:`assume_sensor_size`) or ``None``.
        t_offset_us: absolute time (us) of ``t == 0`` in the chunks.
        calibration: intrinsics stored in the file, if any.
        topic, message_type: for bags, the topic read and its message type
            (``'dvs_msgs/msg/EventArray'``, ...); ``None`` for other formats.
    """

    def __init__(
        self,
        path: Path,
        source: Source,
        sensor_size: tuple[int, int] | None = None,
        chunk_events: int = DEFAULT_CHUNK_EVENTS,
        sort: bool = False,
    ) -> None:
        if int(chunk_events) <= 0:
            raise ValueError(f"chunk_events must be positive, got {chunk_events}")
        self.path = Path(path)
        self.format = source.format
        self._source = source
        self._chunk_events = int(chunk_events)
        self._closed = False
        self._sort = bool(sort)
        if sensor_size is not None:
            self.sensor_size: tuple[int, int] | None = _check_sensor_size(sensor_size)
            self.sensor_size_source: str | None = "user"
        elif source.sensor_size is not None:
            self.sensor_size = _check_sensor_size(source.sensor_size)
            self.sensor_size_source = "file"
        else:
            self.sensor_size, self.sensor_size_source = None, None
        self.t_offset_us = int(source.t_offset_us)
        self.calibration = source.calibration
        self.calibration_problem: str | None = getattr(source, "calibration_problem", None)
        """Why a calibration the file carries is unusable (it is then None), e.g. a bag's
        CameraInfo of another size; :meth:`require_usable_calibration` raises it."""
        if (self.calibration is not None and source.sensor_size is None and sensor_size is not None
                and tuple(self.calibration.sensor_size) != self.sensor_size):
            # The file's K, D came without a size (the reader took max + 1 of the events): the
            # size the user gives is the one they belong to.
            from dataclasses import replace

            self.calibration = replace(self.calibration, sensor_size=self.sensor_size)
        self.topic: str | None = getattr(source, "topic", None)
        self.message_type: str | None = getattr(source, "msgtype", None)
        self.input_order: np.ndarray | None = None
        """With ``sort=True``, once :meth:`chunks` has started: for each event in the order
        :meth:`chunks` yields them, its position in the file (int64), so that per-event
        results can be put back in file order (``out[input_order] = results``). None when
        the file was already in time order (the positions are then the same)."""

    def __enter__(self) -> "Recording":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self._source.close()
        self._closed = True

    def _check_open(self) -> None:
        if self._closed:
            raise EvsegError(f"{self.path}: the recording was closed (its with-block has ended); open it again "
                             "to read it")

    def __repr__(self) -> str:
        return (
            f"Recording({str(self.path)!r}, format={self.format!r}, sensor_size={self.sensor_size}, "
            f"t_offset_us={self.t_offset_us})"
        )

    def require_usable_calibration(
            self, hint: str = "give a calibration of your own (--calib, calibration=...) to use instead") -> None:
        """Raise :class:`~evseg.errors.FormatError` when the file carries a calibration that
        cannot be used (:attr:`calibration_problem`): going on without it would silently skip
        the undistortion the file asks for."""
        if self.calibration_problem is not None:
            raise FormatError(f"{self.calibration_problem}; {hint}")

    def assume_sensor_size(self, sensor_size: tuple[int, int], source: str) -> None:
        """Give the sensor size of a file that declares none, before its events are read, e.g.
        from the calibration the user gave; ``source`` says where it came from in messages
        about events outside it. A size already known (the file's or the user's) is kept."""
        if self.sensor_size is None:
            self.sensor_size = _check_sensor_size(sensor_size)
            self.sensor_size_source = source

    def time_span_us(self) -> tuple[int, int] | None:
        """``(first, last)`` event time (us, chunk time) when the format can read its two ends
        without decoding the file (arrays, HDF5), else None. For progress bars: the ends are
        not validated (a broken file still fails in :meth:`chunks`), and with ``sort=True`` of
        an unsorted file they need not be the earliest and latest times."""
        self._check_open()
        span = getattr(self._source, "time_span_us", None)
        return span() if span is not None else None

    def _where(self, chunk: Chunk, i: int, global_index: int) -> str:
        pos = f"event {global_index}"
        if chunk.locate is not None:
            pos += f" ({chunk.locate(i)})"
        return pos

    def _raw_checked(self, check_sorted: bool) -> Iterator[np.ndarray]:
        """Validated chunks of the source, in file order."""
        label = f"{self.path}: {self.format}"
        seen = 0
        t_prev = None
        max_x = max_y = -1
        for chunk in self._source.chunks(self._chunk_events):
            ev = chunk.events
            if ev.dtype != EVENT_DTYPE:  # a bug in a format module, not a user error
                raise TypeError(f"{self.format} reader produced dtype {ev.dtype}")
            if len(ev) == 0:
                continue
            t = ev["t"]
            neg = np.flatnonzero(t < 0)
            if len(neg):
                i = int(neg[0])
                raise EventDataError(
                    f"{label}: negative timestamp t={int(t[i])} us at {self._where(chunk, i, seen + i)}"
                )
            if check_sorted:
                steps = np.diff(t)
                if t_prev is not None and t[0] < t_prev:
                    bad = 0
                else:
                    dec = np.flatnonzero(steps < 0)
                    bad = int(dec[0]) + 1 if len(dec) else -1
                if bad >= 0:
                    before = t_prev if bad == 0 else int(t[bad - 1])
                    raise EventDataError(
                        f"{label}: timestamps not sorted: t={int(t[bad])} us at "
                        f"{self._where(chunk, bad, seen + bad)} is earlier than the previous event's "
                        f"t={before} us (open with sort=True / pass --sort to sort the events)"
                    )
            if self.sensor_size is not None:
                for name, limit in zip("xy", self.sensor_size):
                    off = np.flatnonzero(ev[name] >= limit)
                    if len(off):
                        i = int(off[0])
                        raise EventDataError(
                            f"{label}: field '{name}' = {int(ev[name][i])} at "
                            f"{self._where(chunk, i, seen + i)} is outside the sensor "
                            f"{self.sensor_size[0]}x{self.sensor_size[1]} ({self.sensor_size_source})"
                        )
            else:
                max_x = max(max_x, int(ev["x"].max()))
                max_y = max(max_y, int(ev["y"].max()))
            t_prev = int(t[-1])
            seen += len(ev)
            yield ev
        if self.sensor_size is None and max_x >= 0:
            self.sensor_size = (max_x + 1, max_y + 1)
            self.sensor_size_source = "inferred"

    def chunks(self) -> Iterator[np.ndarray]:
        """Yield validated :data:`EVENT_DTYPE` chunks (t relative to :attr:`t_offset_us`).

        Memory is bounded by one chunk, except with ``sort=True`` (whole recording).
        Each call starts again from the beginning of the file.
        """
        self._check_open()
        if not self._sort:
            yield from self._raw_checked(check_sorted=True)
            return
        allev = _concat(list(self._raw_checked(check_sorted=False)))
        t = allev["t"]
        self.input_order = None
        if len(t) > 1 and bool(np.any(t[1:] < t[:-1])):
            order = np.argsort(t, kind="stable")
            allev = allev[order]
            self.input_order = order.astype(np.int64, copy=False)
        for i in range(0, len(allev), self._chunk_events):
            yield allev[i : i + self._chunk_events]

    def read_all(self) -> EventStream:
        """The whole recording in memory as an :class:`~evseg.events.EventStream`.

        Raises :class:`EventDataError` if the sensor size is unknown and there are no events
        to infer it from.
        """
        self.require_usable_calibration("open_recording(...) reads the events alone, with calibration None")
        events = _concat(list(self.chunks()))
        if self.sensor_size is None:
            raise EventDataError(
                f"{self.path}: {self.format}: the file declares no sensor size and has no events "
                "to infer it from; pass sensor_size=(width, height) / --sensor-size WxH"
            )
        cal = self.calibration
        if cal is not None and tuple(cal.sensor_size) != tuple(self.sensor_size):
            from dataclasses import replace

            cal = replace(cal, sensor_size=self.sensor_size)
        return EventStream(events, self.sensor_size, self.t_offset_us, cal)


def batched_chunks(packets: Iterable[np.ndarray], chunk_events: int) -> Iterator[Chunk]:
    """Join small event packets (one per message / file packet) into chunks of at least
    ``chunk_events`` events (the last may be smaller); empty packets are skipped."""
    parts: list[np.ndarray] = []
    count = 0
    try:
        for ev in packets:
            if len(ev) == 0:
                continue
            parts.append(ev)
            count += len(ev)
            if count >= chunk_events:
                yield Chunk(np.concatenate(parts))
                parts, count = [], 0
    except EvsegError:
        # A file cut or damaged further on: the events before the damage are still the user's
        # (a run keeps their labels in a result flagged partial), then the error is raised.
        if parts:
            yield Chunk(np.concatenate(parts))
        raise
    if parts:
        yield Chunk(np.concatenate(parts))


def _concat(chunks: list[np.ndarray]) -> np.ndarray:
    if not chunks:
        return empty_events()
    if len(chunks) == 1:
        # Chunks may be views of memory-mapped or cached arrays: own the result.
        return np.array(chunks[0], dtype=EVENT_DTYPE, copy=True)
    return np.concatenate(chunks)


def _check_sensor_size(size) -> tuple[int, int]:
    """:func:`~evseg.events.checked_sensor_size` within the 16-bit coordinates of events."""
    w, h = checked_sensor_size(size)
    if w > 65536 or h > 65536:
        raise EventDataError(f"sensor_size must be at most 65536 px per side (16-bit coordinates), got {size!r}")
    return (w, h)


def parse_sensor_size(text: str) -> tuple[int, int]:
    """Parse ``"WxH"`` (e.g. ``"346x260"``) into ``(width, height)``.

    >>> parse_sensor_size("346x260")
    (346, 260)
    """
    parts = text.lower().replace(",", "x").split("x")
    if len(parts) != 2 or not all(p.strip().isdigit() for p in parts):
        raise EventDataError(f"sensor size must look like WIDTHxHEIGHT (e.g. 346x260), got {text!r}")
    return _check_sensor_size((int(parts[0]), int(parts[1])))
