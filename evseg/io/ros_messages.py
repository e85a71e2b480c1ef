"""Event messages of ROS1 and ROS2 bags, decoded with numpy from their serialised bytes.

Building one Python object per event (what a generic ROS deserialiser does) is far too slow
for millions of events, so the three message types event cameras publish are decoded here
straight from the wire:

* ``dvs_msgs/msg/EventArray`` (rpg_dvs_ros and its ROS2 port; EED, EVIMO, EMSGC data) and
  ``prophesee_event_msgs/msg/EventArray`` (Prophesee's ROS wrapper), which share one layout:
  ``Header header, uint32 height, uint32 width, Event[] events`` with ``Event = uint16 x,
  uint16 y, time ts, bool polarity``.
* ``event_camera_msgs/msg/EventPacket`` (ros-event-camera: metavision_driver, libcaer_driver):
  ``Header header, uint32 height, uint32 width, uint64 seq, uint64 time_base, string encoding,
  bool is_bigendian, uint8[] events``, the events a packed byte stream. Encodings read:
  ``evt3`` (Prophesee EVT 3.0 as the camera sends it; decoded across packets with the
  ``.raw`` reader's decoder, times are the sensor clock in us) and ``mono`` (one little-endian
  64-bit word per event: polarity bit 63, y bits 48-62, x bits 32-47, dt bits 0-31 in ns, the
  event's time being ``time_base + dt`` ns). Other encodings are refused by name.

ROS1 serialises fields packed, little-endian. ROS2 (CDR, little-endian encapsulation) aligns
each primitive to its size relative to the data after the 4-byte encapsulation header, so an
``Event`` array has no fixed stride in bytes: the first event takes 14 bytes (13 + 1 padding),
each later one 16 (``x, y``, 2 bytes padding, ``sec, nanosec, polarity``, 1 byte padding),
because the array itself starts 4-aligned.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from evseg.errors import FormatError
from evseg.events import EVENT_DTYPE

DVS_EVENT_ARRAY = "dvs_msgs/msg/EventArray"
PROPHESEE_EVENT_ARRAY = "prophesee_event_msgs/msg/EventArray"
EVENT_PACKET = "event_camera_msgs/msg/EventPacket"
EVENT_ARRAY_TYPES = (DVS_EVENT_ARRAY, PROPHESEE_EVENT_ARRAY)
EVENT_TYPES = (DVS_EVENT_ARRAY, PROPHESEE_EVENT_ARRAY, EVENT_PACKET)
"""Message types that carry events, in the order a bag's topics are listed in errors."""
PACKET_ENCODINGS = ("evt3", "mono")

_EVENT_TEXT = "uint16 x\nuint16 y\n{time} ts\nbool polarity\n"
_ARRAY_TEXT = "{header} header\nuint32 height\nuint32 width\n{pkg}/Event[] events\n"
_PACKET_TEXT = ("{header} header\nuint32 height\nuint32 width\nuint64 seq\nuint64 time_base\n"
                "string encoding\nbool is_bigendian\nuint8[] events\n")


def message_definitions(ros2: bool) -> dict[str, str]:
    """The .msg definitions of the event messages (ROS1 or ROS2 syntax), to register them
    with a ``rosbags`` typestore (writing bags, e.g. in the tests)."""
    time, header = ("builtin_interfaces/Time", "std_msgs/Header") if ros2 else ("time", "std_msgs/Header")
    out = {}
    for pkg in ("dvs_msgs", "prophesee_event_msgs"):
        out[f"{pkg}/msg/Event"] = _EVENT_TEXT.format(time=time)
        out[f"{pkg}/msg/EventArray"] = _ARRAY_TEXT.format(header=header, pkg=pkg)
    out[EVENT_PACKET] = _PACKET_TEXT.format(header=header)
    return out


def event_typestore(ros2: bool):
    """A ``rosbags`` typestore (ROS1 Noetic or ROS2 Humble) with the event messages registered."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE if ros2 else Stores.ROS1_NOETIC)
    types = {}
    for name, text in message_definitions(ros2).items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


_ROS1_EVENT = np.dtype([("x", "<u2"), ("y", "<u2"), ("sec", "<u4"), ("nsec", "<u4"), ("polarity", "u1")])
"""13 bytes, packed: one Event as ROS1 serialises it."""
_CDR_FIRST = np.dtype({"names": ["x", "y", "sec", "nsec", "polarity"], "formats": ["<u2", "<u2", "<i4", "<u4", "u1"],
                       "offsets": [0, 2, 4, 8, 12], "itemsize": 14})
_CDR_LATER = np.dtype({"names": ["x", "y", "sec", "nsec", "polarity"], "formats": ["<u2", "<u2", "<i4", "<u4", "u1"],
                       "offsets": [0, 2, 6, 10, 14], "itemsize": 16})
"""The first and every later Event of a CDR array (module docstring)."""


class _Reader:
    """Cursor over one serialised message; any read past its end is a FormatError."""

    def __init__(self, raw, cdr: bool, where: str, kind: str) -> None:
        self.buf = memoryview(raw).cast("B")
        self.where, self.kind, self.cdr = where, kind, cdr
        self.base = 0
        if cdr:
            if len(self.buf) < 4:
                self.fail()
            if self.buf[1] != 1:  # CDR_LE = 0x0001, CDR_BE = 0x0000
                raise FormatError(f"{where}: {kind} message is big-endian CDR, which evseg does not read")
            self.base = 4
        self.pos = self.base

    def fail(self):
        raise FormatError(f"{self.where}: {self.kind} message is truncated or corrupt ({len(self.buf)} bytes)")

    def align(self, n: int) -> None:
        if self.cdr:
            self.pos += (-(self.pos - self.base)) % n

    def take(self, n: int) -> memoryview:
        if n < 0 or self.pos + n > len(self.buf):
            self.fail()
        out = self.buf[self.pos:self.pos + n]
        self.pos += n
        return out

    def uint(self, n: int) -> int:
        self.align(n)
        return int.from_bytes(self.take(n), "little")

    def string(self) -> str:
        raw = bytes(self.take(self.uint(4)))
        return raw.rstrip(b"\x00").decode("utf-8", errors="replace")  # CDR counts the NUL

    def header(self) -> None:
        if not self.cdr:
            self.uint(4)  # seq: ROS1 only
        self.uint(4), self.uint(4)  # stamp
        self.string()  # frame_id


def decode_event_array(raw, cdr: bool, where: str) -> tuple[np.ndarray, int, int]:
    """Decode one serialised ``EventArray`` (dvs_msgs or prophesee_event_msgs).

    Returns ``(events, width, height)``; ``events`` is a structured array with fields ``x``,
    ``y`` (px), ``sec``, ``nsec`` (the event's ROS time) and ``polarity`` (0/1). Raises
    :class:`FormatError` naming ``where`` if the message is shorter than its own lengths say.
    """
    r = _Reader(raw, cdr, where, "EventArray")
    r.header()
    height, width, n = r.uint(4), r.uint(4), r.uint(4)
    if not cdr:
        return np.frombuffer(r.take(n * _ROS1_EVENT.itemsize), dtype=_ROS1_EVENT), width, height
    if n == 0:
        return np.zeros(0, dtype=_ROS1_EVENT), width, height
    start = r.pos
    size = 13 if n == 1 else 14 + 16 * (n - 2) + 15
    r.take(size)  # bounds check
    out = np.empty(n, dtype=_ROS1_EVENT)
    body = np.zeros(14 + 16 * (n - 1), dtype=np.uint8)  # padded so both views fit
    body[:size] = np.frombuffer(r.buf[start:start + size], dtype=np.uint8)
    first = body[:14].view(_CDR_FIRST)
    later = body[14:].view(_CDR_LATER)
    for name in _ROS1_EVENT.names:
        out[name][:1] = first[name]
        out[name][1:] = later[name]
    return out, width, height


@dataclass(frozen=True)
class EventPacket:
    """The fields of one ``event_camera_msgs/EventPacket`` that decoding needs."""

    width: int
    height: int
    time_base: int
    """ns; the ``mono`` encoding's event times are ``time_base + dt``."""
    encoding: str
    is_bigendian: bool
    events: memoryview
    """The packed event bytes."""


def parse_event_packet(raw, cdr: bool, where: str) -> EventPacket:
    """The fields of one serialised ``EventPacket`` (:class:`FormatError` if truncated)."""
    r = _Reader(raw, cdr, where, "EventPacket")
    r.header()
    height, width = r.uint(4), r.uint(4)
    r.uint(8)  # seq
    time_base = r.uint(8)
    encoding = r.string()
    is_bigendian = bool(r.uint(1))
    data = r.take(r.uint(4))
    return EventPacket(width, height, time_base, encoding, is_bigendian, data)


class PacketDecoder:
    """Events of a topic's ``EventPacket`` messages, in order (module docstring).

    One decoder per pass over a topic: EVT 3.0 carries its time and address state from one
    packet to the next. ``decode`` returns :data:`EVENT_DTYPE` events with ``t`` in absolute
    us (``evt3``: the sensor clock; ``mono``: ``time_base + dt``).
    """

    def __init__(self, where: str) -> None:
        from evseg.io.prophesee import _State

        self.where = where
        self.encoding: str | None = None
        self._state = _State()
        self._byte = 0

    def decode(self, packet: EventPacket) -> np.ndarray:
        from evseg.io.prophesee import decode_evt3

        enc = packet.encoding.lower()
        if enc not in PACKET_ENCODINGS:
            raise FormatError(f"{self.where}: EventPacket encoding '{packet.encoding}' is not read by evseg "
                              f"(supported: {', '.join(PACKET_ENCODINGS)})")
        if self.encoding is not None and enc != self.encoding:
            raise FormatError(f"{self.where}: EventPacket encoding changes from '{self.encoding}' to '{enc}' "
                              "within the topic")
        if packet.is_bigendian:
            raise FormatError(f"{self.where}: EventPacket is_bigendian is true; evseg reads little-endian packets only")
        self.encoding = enc
        data, at = packet.events, self._byte
        self._byte += len(data)
        if enc == "evt3":
            if len(data) % 2:
                raise FormatError(f"{self.where}: EventPacket of {len(data)} bytes does not hold whole 16-bit "
                                  "EVT 3.0 words")
            ev, _ = decode_evt3(np.frombuffer(data, dtype="<u2"), self._state, self.where, at)
            return ev
        if len(data) % 8:
            raise FormatError(f"{self.where}: EventPacket of {len(data)} bytes does not hold whole 64-bit "
                              "'mono' events")
        words = np.frombuffer(data, dtype="<u8")
        ev = np.empty(len(words), dtype=EVENT_DTYPE)
        ev["t"] = (packet.time_base + (words & 0xFFFFFFFF)).astype(np.int64) // 1000
        ev["x"] = (words >> 32) & 0xFFFF
        ev["y"] = (words >> 48) & 0x7FFF
        ev["p"] = np.where(words >> 63, 1, -1)
        return ev


def array_events(wire: np.ndarray) -> np.ndarray:
    """:data:`EVENT_DTYPE` events (``t`` absolute us) of :func:`decode_event_array`'s output."""
    ev = np.empty(len(wire), dtype=EVENT_DTYPE)
    ev["x"], ev["y"] = wire["x"], wire["y"]
    ev["t"] = wire["sec"].astype(np.int64) * 1_000_000 + wire["nsec"].astype(np.int64) // 1000
    ev["p"] = np.where(wire["polarity"] > 0, 1, -1)
    return ev
