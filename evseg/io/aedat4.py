"""iniVation AEDAT4 files, read with the ``aedat`` package (``aedat.Decoder``).

The decoder yields packets of one stream each; only packets of the (first) ``events`` stream
are kept, frames, IMU samples and triggers are skipped. Sensor size from the stream
description. Times are the camera's microseconds: ``t_offset_us`` is the time of the first
event and ``t`` counts from there. The ``on`` field (bool) becomes +1/-1.
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterator

import numpy as np

from evseg.errors import FormatError
from evseg.events import EVENT_DTYPE
from evseg.io.recording import Chunk, batched_chunks


def _reraise_interrupts(exc: BaseException) -> None:
    if isinstance(exc, (KeyboardInterrupt, SystemExit, GeneratorExit)):
        raise exc


class Aedat4Source:
    format = "aedat4"

    def __init__(self, path: Path, format: str = "aedat4") -> None:
        self.path = path
        self.calibration = None
        self._where = where = f"{path}: aedat4"
        streams = self._decoder().id_to_stream()
        ids = sorted(i for i, s in streams.items() if s.get("type") == "events")
        if not ids:
            kinds = sorted({s.get("type", "?") for s in streams.values()})
            raise FormatError(f"{where}: no event stream (streams: {', '.join(kinds) or 'none'})")
        self._stream_id = ids[0]
        s = streams[ids[0]]
        self.sensor_size = (int(s["width"]), int(s["height"])) if "width" in s and "height" in s else None
        self.t_offset_us = 0
        for ev in self._event_packets():
            if len(ev):
                self.t_offset_us = int(ev["t"][0])
                break

    def _decoder(self):
        import aedat

        try:
            return aedat.Decoder(str(self.path))
        except BaseException as exc:  # RuntimeError/OSError, or a Rust panic (a BaseException)
            _reraise_interrupts(exc)
            raise FormatError(f"{self._where}: not a readable AEDAT4 file ({exc})") from None

    def _event_packets(self) -> Iterator[np.ndarray]:
        it = iter(self._decoder())
        n_packets = n_events = 0
        t_last = None
        while True:
            try:
                packet = next(it)
            except StopIteration:
                return
            except BaseException as exc:  # see _decoder
                _reraise_interrupts(exc)
                # The decoder gives no byte offset; the packets and events read before say where.
                after = (f"after {n_packets} packets, {n_events} events (last t = {t_last} us, camera clock)"
                         if n_events else f"after {n_packets} packets, before any event")
                raise FormatError(f"{self._where}: corrupt or truncated packet {after} ({exc})") from None
            n_packets += 1
            if packet.get("stream_id") == self._stream_id and "events" in packet:
                ev = packet["events"]
                if len(ev):
                    n_events += len(ev)
                    t_last = int(ev["t"][-1])
                yield ev

    def chunks(self, chunk_events: int) -> Iterator[Chunk]:
        return batched_chunks(self._events(), chunk_events)

    def _events(self) -> Iterator[np.ndarray]:
        for raw in self._event_packets():
            if len(raw) == 0:
                continue
            t = raw["t"]
            if int(t.max()) > 2**63 - 1:
                raise FormatError(f"{self._where}: timestamp {int(t.max())} us out of range")
            ev = np.empty(len(raw), dtype=EVENT_DTYPE)
            ev["t"] = t.astype(np.int64) - self.t_offset_us
            ev["x"], ev["y"] = raw["x"], raw["y"]
            ev["p"] = np.where(raw["on"], 1, -1)
            yield ev

    def close(self) -> None:
        pass


def open_source(path: Path, format: str = "aedat4") -> Aedat4Source:
    return Aedat4Source(path, format)
