"""Prophesee ``.dat`` recordings of CD events (the layout of Prophesee's Gen1 and 1 Mpx
automotive datasets and of Metavision's DAT export).

A ``.dat`` file is a text header of lines starting with ``%`` (``% Data file containing CD
events``, ``% Version 2``, ``% Width 640``, ``% Height 480``, ...), then two bytes, the event
type (0x00 Event2d or 0x0C EventCd: both are CD events) and the event size (8), then
little-endian 8-byte records: a uint32 timestamp in microseconds and a uint32 word with x in
bits 0-13, y in bits 14-27 and the polarity in bits 28-31 (1 ON -> +1, 0 OFF -> -1).

The 32-bit timestamps wrap after 71.6 min; a decrease of more than half the range is taken as
a wrap and times are unwrapped to int64. Timestamps are the camera's (``t_offset_us`` = 0).
The sensor size comes from ``Width``/``Height`` when the header has them. Other event types
(external triggers), other record sizes, format versions other than 2 and a truncated last
record raise :class:`~evseg.errors.FormatError` naming the byte offset.
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterator

import numpy as np

from evseg.errors import FormatError
from evseg.events import EVENT_DTYPE
from evseg.io.prophesee import header_of, read_blocks
from evseg.io.recording import Chunk

CD_EVENT_TYPES = {0x00: "Event2d", 0x0C: "EventCd"}
RECORD = np.dtype([("t", "<u4"), ("w", "<u4")])
_WRAP = 1 << 32


def is_dat_header(fields: dict[str, str]) -> bool:
    """Whether a ``%`` header (:func:`evseg.io.prophesee.read_header`) is a DAT file's: it says
    ``Data file containing ...`` (mandatory in the format)."""
    return fields.get("data", "").lower().startswith("file containing")


def decode_records(records: np.ndarray, wraps: int, last_t: int) -> tuple[np.ndarray, int, int]:
    """Events of a block of records, ``(events, wraps, last raw time)``; ``wraps`` and
    ``last_t`` carry the time unwrapping from one block to the next (start: 0, -1)."""
    t_raw = records["t"].astype(np.int64)
    prev = np.empty_like(t_raw)
    if len(t_raw):
        prev[0] = last_t if last_t >= 0 else t_raw[0]
        prev[1:] = t_raw[:-1]
    wrapped = (prev - t_raw) > (_WRAP // 2)
    n_wraps = wraps + np.cumsum(wrapped)
    ev = np.empty(len(records), dtype=EVENT_DTYPE)
    w = records["w"]
    ev["x"] = w & 0x3FFF
    ev["y"] = (w >> 14) & 0x3FFF
    ev["t"] = t_raw + n_wraps * _WRAP
    ev["p"] = np.where((w >> 28) & 0xF, 1, -1)
    if len(records):
        wraps, last_t = int(n_wraps[-1]), int(t_raw[-1])
    return ev, wraps, last_t


class DatSource:
    """Streaming reader of one Prophesee ``.dat`` file."""

    format = "dat"

    def __init__(self, path: Path) -> None:
        self.path = path
        self.calibration = None
        self.t_offset_us = 0
        self._where = where = f"{path}: dat"
        fields, offset = header_of(path, where)
        with open(path, "rb") as f:
            f.seek(offset)
            type_size = f.read(2)
        if not fields:
            raise FormatError(f"{where}: no '%' text header at byte offset 0 (not a Prophesee .dat file)")
        version = (fields.get("version") or "2").split()[0]
        if version != "2":
            raise FormatError(f"{where}: header field 'Version' is {version}; evseg reads DAT version 2")
        if len(type_size) < 2:
            raise FormatError(f"{where}: truncated: the event type and size bytes at byte offset {offset} are missing")
        ev_type, ev_size = type_size[0], type_size[1]
        if ev_type not in CD_EVENT_TYPES:
            raise FormatError(f"{where}: event type 0x{ev_type:02X} at byte offset {offset} is not a CD event "
                              f"(0x00 Event2d or 0x0C EventCd; 0x0E are external triggers)")
        if ev_size != RECORD.itemsize:
            raise FormatError(f"{where}: event size {ev_size} at byte offset {offset + 1}, expected 8")
        self._data_offset = offset + 2
        size = path.stat().st_size - self._data_offset
        if size % RECORD.itemsize:
            end = self._data_offset + size - size % RECORD.itemsize
            raise FormatError(f"{where}: truncated: {size % RECORD.itemsize} trailing byte(s) at byte offset "
                              f"{end} do not make a whole 8-byte event")
        width, height = fields.get("width", ""), fields.get("height", "")
        self.sensor_size = (int(width), int(height)) if width.isdigit() and height.isdigit() else None
        self.header = fields

    def chunks(self, chunk_events: int) -> Iterator[Chunk]:
        wraps, last_t = 0, -1
        for base, buf in read_blocks(self.path, self._data_offset, chunk_events * RECORD.itemsize):
            ev, wraps, last_t = decode_records(np.frombuffer(buf, dtype=RECORD), wraps, last_t)
            yield Chunk(ev, lambda i, base=base: f"byte offset {base + RECORD.itemsize * int(i)}")

    def close(self) -> None:
        pass


def open_source(path: Path, format: str = "dat") -> DatSource:
    return DatSource(path)
