"""Event Stream v2 (``.es``) files of type DVS (neuromorphic-paris/event_stream spec).

Layout: ``"Event Stream"`` (12 bytes), version major/minor/patch (bytes 12-14, major 2),
stream type (byte 15; 1 = DVS, the only type read here), width and height (uint16 little
endian, bytes 16-19), then a byte stream. In the idle state a byte ``0xFF`` is an *overflow*
(adds 127 us to the next event's time difference) and ``0xFE`` a *reset* (ignored); any other
byte starts a 5-byte event: ``t_delta << 1 | is_increase``, x (uint16 LE), y (uint16 LE).

y is stored as the image row (0 = top), as in the EED excerpt of ``eed_what_is_background``
(checked against EMSGC's labels there), so it is used as is. Timestamps are the running sum of
the time differences from 0 (``t_offset_us`` = 0).

Decoding is vectorised: from each idle position the following events sit every 5 bytes until
the first overflow/reset byte on that 5-byte grid, found by binary search; only the runs of
overflow/reset bytes are stepped in Python, so the loop runs once per gap of 127 us or more.
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterator

import numpy as np

from evseg.errors import FormatError
from evseg.events import EVENT_DTYPE
from evseg.io.recording import Chunk

MAGIC = b"Event Stream"
_TYPES = {0: "generic", 1: "dvs", 2: "atis", 3: "asynchronous display", 4: "color"}
_HEADER_BYTES = 20


def _grid_events(b: np.ndarray) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Find event starts in a block of DVS bytes that begins in the idle state.

    Returns ``(starts, overflows, consumed, pending_overflows)``: byte positions of complete
    events, the number of overflow bytes just before each, the number of bytes consumed
    (everything before an incomplete trailing event) and overflow bytes seen after the last
    event.
    """
    n = len(b)
    special = b >= 0xFE
    sp = np.flatnonzero(special)
    by_phase = [sp[sp % 5 == r] for r in range(5)]
    non_special = np.flatnonzero(~special)
    ff_cum = np.concatenate([[0], np.cumsum(b == 0xFF)])
    seg_pos, seg_count, seg_ovf = [], [], []
    pos, pending = 0, 0
    while pos < n:
        grid = by_phase[pos % 5]
        k = np.searchsorted(grid, pos)
        brk = int(grid[k]) if k < len(grid) else n
        # Complete events on the grid before the break (an event needs 5 bytes).
        last_full = min(brk, n - 4)
        count = max(0, (last_full - pos + 4) // 5)
        if count:
            seg_pos.append(pos)
            seg_count.append(count)
            seg_ovf.append(pending)
            pending = 0
            pos += 5 * count
        if pos >= brk and brk < n:
            j = np.searchsorted(non_special, brk)
            end = int(non_special[j]) if j < len(non_special) else n
            pending += int(ff_cum[end] - ff_cum[brk])
            pos = end
        else:
            break  # an incomplete event at the end of the block
    counts = np.asarray(seg_count, dtype=np.int64)
    total = int(counts.sum()) if len(counts) else 0
    first = np.cumsum(counts) - counts
    starts = np.repeat(np.asarray(seg_pos, dtype=np.int64), counts) + 5 * (
        np.arange(total) - np.repeat(first, counts)
    )
    ovf = np.zeros(total, dtype=np.int64)
    if total:
        ovf[first[counts > 0]] = np.asarray(seg_ovf, dtype=np.int64)[counts > 0]
    return starts, ovf, min(pos, n), pending


class EventStreamSource:
    format = "es"

    def __init__(self, path: Path, format: str = "es") -> None:
        self.path = path
        self.calibration = None
        self.t_offset_us = 0
        self._where = where = f"{path}: es"
        with open(path, "rb") as f:
            head = f.read(_HEADER_BYTES)
        if not head.startswith(MAGIC):
            raise FormatError(f"{where}: bad magic bytes at offset 0 (expected {MAGIC!r}, got {head[:12]!r})")
        if len(head) < 16:
            raise FormatError(f"{where}: truncated header ({len(head)} bytes, need {_HEADER_BYTES})")
        major, minor, patch, typ = head[12], head[13], head[14], head[15]
        if major != 2:
            raise FormatError(f"{where}: Event Stream version {major}.{minor}.{patch} at byte offset 12 is not supported (only 2.x)")
        if typ != 1:
            raise FormatError(
                f"{where}: stream type {typ} ({_TYPES.get(typ, 'unknown')}) at byte offset 15 is not supported (only DVS)"
            )
        if len(head) < _HEADER_BYTES:
            raise FormatError(f"{where}: truncated header ({len(head)} bytes, need {_HEADER_BYTES})")
        w, h = int.from_bytes(head[16:18], "little"), int.from_bytes(head[18:20], "little")
        if w == 0 or h == 0:
            raise FormatError(f"{where}: sensor size {w}x{h} at byte offset 16 is not positive")
        self.sensor_size = (w, h)

    def chunks(self, chunk_events: int) -> Iterator[Chunk]:
        t_last = 0
        offset = _HEADER_BYTES  # file offset of carry[0]
        carry = b""
        pending = 0
        with open(self.path, "rb") as f:
            f.seek(_HEADER_BYTES)
            while True:
                data = f.read(5 * chunk_events)
                if not data:
                    break
                b = np.frombuffer(carry + data, dtype=np.uint8)
                starts, ovf, consumed, pend = _grid_events(b)
                if len(starts):
                    ovf[0] += pending
                    pending = 0
                pending += pend
                b0 = b[starts].astype(np.int64)
                dt = (b0 >> 1) + 127 * ovf
                ev = np.empty(len(starts), dtype=EVENT_DTYPE)
                ev["t"] = t_last + np.cumsum(dt)
                ev["x"] = b[starts + 1].astype(np.uint16) | (b[starts + 2].astype(np.uint16) << 8)
                ev["y"] = b[starts + 3].astype(np.uint16) | (b[starts + 4].astype(np.uint16) << 8)
                ev["p"] = np.where(b0 & 1, 1, -1)
                if len(ev):
                    t_last = int(ev["t"][-1])
                base = offset
                yield Chunk(ev, lambda i, s=starts, base=base: f"byte offset {base + int(s[i])}")
                carry = bytes(b[consumed:])
                offset += consumed
        if carry:
            raise FormatError(
                f"{self._where}: truncated: incomplete event ({len(carry)} of 5 bytes) at byte offset {offset}"
            )

    def close(self) -> None:
        pass


def open_source(path: Path, format: str = "es") -> EventStreamSource:
    return EventStreamSource(path, format)
