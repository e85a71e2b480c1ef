"""Readers and writers of event recordings.

Every reader streams: :func:`open_recording` returns a :class:`Recording` whose
:meth:`~Recording.chunks` yields :data:`~evseg.events.EVENT_DTYPE` arrays of about
``chunk_events`` events, validated (sorted, non-negative ``t``; coordinates on the sensor), so
that a recording larger than memory can be cut into windows with
:func:`evseg.windows.stream_time_windows`. :func:`read_events` loads a whole file.

Example
-------
>>> from evseg.io import open_recording, read_events            # doctest: +SKIP
>>> with open_recording("events.txt") as rec:                   # doctest: +SKIP
...     for chunk in rec.chunks():
...         ...
>>> stream = read_events("sample.aedat4")                        # doctest: +SKIP

Formats (``FORMATS``; the format is detected from magic bytes and the extension, ``format=``
overrides): text/csv, npy, npz, mat, h5 (DSEC layout), rosbag and rosbag2 (ROS1 and ROS2 bags
of dvs_msgs / prophesee_event_msgs EventArray or event_camera_msgs EventPacket), aedat4,
evt2, evt3 (Prophesee .raw), dat (Prophesee .dat, CD events), es (Event Stream v2 DVS). Writers: :func:`write_npz`,
:func:`write_h5` (and :func:`write_text`), all atomic and lossless through the readers.
"""

from __future__ import annotations

from pathlib import Path

from evseg.errors import EvsegError
from evseg.events import EventStream
from evseg.io.recording import DEFAULT_CHUNK_EVENTS, Recording, parse_sensor_size
from evseg.io.registry import FORMATS, detect_format, format_names

__all__ = [
    "FORMATS",
    "Recording",
    "detect_format",
    "format_names",
    "open_recording",
    "parse_sensor_size",
    "read_events",
    "write_h5",
    "write_npz",
    "write_text",
]


def open_recording(
    path: str | Path,
    format: str | None = None,
    topic: str | None = None,
    sensor_size: tuple[int, int] | None = None,
    chunk_events: int = DEFAULT_CHUNK_EVENTS,
    sort: bool = False,
    time_unit: str | None = None,
) -> Recording:
    """Open a recording for streaming.

    Args:
        path: the file (or a ROS2 bag's directory).
        format: registry name (see :data:`FORMATS`); ``None`` detects it.
        topic: ROS bag topic of the event messages (default: the only one; see
            :mod:`evseg.io.rosbag`).
        sensor_size: ``(width, height)`` in px; overrides the file's, or supplies it when the
            file has none (otherwise it is inferred as max + 1 by :meth:`Recording.read_all`).
        chunk_events: approximate events per yielded chunk, the bound on memory (bags and
            AEDAT4 cut at message/packet boundaries; EVT3 reads this many 16-bit words, which
            decode to fewer events except in dense vector bursts).
        sort: accept unsorted timestamps and sort them (loads the whole recording).
        time_unit: text/csv, .npy and .npz only: ``"s"``, ``"ms"``, ``"us"`` or ``"ns"`` for
            the time column, whatever its name or dtype says. Default: a unit suffix of the
            column's name (``t_ns``, ``timestamp_us``, ...), else for text seconds when any of
            the first 1,000 time values has a decimal point or exponent, else microseconds (and
            then a later time with a fraction is an error); for arrays seconds when floating
            point, microseconds when integer.
    """
    from evseg.io.registry import open_source

    path = Path(path)
    fmt = format if format is not None else detect_format(path)
    options = {}
    if topic is not None:
        if fmt not in ("rosbag", "rosbag2"):
            raise EvsegError(f"{path}: a topic only applies to ROS bags, this file is {fmt}")
        options["topic"] = topic
    if time_unit is not None:
        if fmt not in ("text", "npy", "npz"):
            raise EvsegError(f"{path}: a time unit only applies to text/csv, .npy and .npz files (the other "
                             f"formats define theirs), this file is {fmt}")
        options["time_unit"] = time_unit
    source = open_source(path, fmt, **options)
    try:
        return Recording(path, source, sensor_size=sensor_size, chunk_events=chunk_events, sort=sort)
    except Exception:
        source.close()
        raise


def read_events(
    path: str | Path,
    format: str | None = None,
    sensor_size: tuple[int, int] | None = None,
    **kw,
) -> EventStream:
    """Read a whole recording into an :class:`~evseg.events.EventStream`.

    ``sensor_size`` overrides the file's; when neither is known it is ``(max x + 1,
    max y + 1)``. Other keywords as for :func:`open_recording`.
    """
    with open_recording(path, format=format, sensor_size=sensor_size, **kw) as rec:
        return rec.read_all()


def write_npz(stream: EventStream, path: str | Path) -> Path:
    """Write ``stream`` to an .npz that :func:`read_events` reads back losslessly (atomic)."""
    from evseg.io.numpy_files import write_npz as _write

    return _write(stream, path)


def write_h5(stream: EventStream, path: str | Path) -> Path:
    """Write ``stream`` as DSEC-style HDF5 that :func:`read_events` reads back losslessly."""
    from evseg.io.hdf5 import write_h5 as _write

    return _write(stream, path)


def write_text(stream: EventStream, path: str | Path) -> Path:
    """Write ``stream`` as text ``t x y p`` (t seconds, 6 decimals: lossless to the us)."""
    from evseg.io.text import write_text as _write

    return _write(stream, path)
