"""ROS1 bags with ``dvs_msgs/EventArray`` messages (EED, EVIMO, EMSGC data), without ROS.

The bag container is read by the ``rosbags`` library; the event messages themselves are
decoded with numpy straight from their ROS1 serialisation (a packed array of 13-byte events),
which is far faster than building one Python object per event.

Topic: the one connection whose type is ``dvs_msgs/msg/EventArray``; if there are several,
:class:`FormatError` lists them and ``topic=`` (``--topic``) picks one. Sensor size: the
``width``/``height`` of the first message. Times: ``t_offset_us`` is the absolute ROS time
(us) of the first event, and ``t`` counts from there. Calibration: the first
``sensor_msgs/CameraInfo`` message on ``camera_info`` beside the event topic (``/dvs/events``
-> ``/dvs/camera_info``, as the rpg_dvs_ros driver publishes it), unless its ``K`` is all zeros
(an uncalibrated camera); a ``--calib`` file overrides it.

``dvs_msgs`` is not built into ``rosbags``; :func:`dvs_typestore` registers it from its message
definitions (used to write bags, e.g. in the tests).
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterator

import numpy as np

from evseg.errors import FormatError
from evseg.events import EVENT_DTYPE
from evseg.io.recording import Chunk, batched_chunks

EVENT_ARRAY = "dvs_msgs/msg/EventArray"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"

DVS_MSG_DEFINITIONS = {
    "dvs_msgs/msg/Event": "uint16 x\nuint16 y\ntime ts\nbool polarity\n",
    EVENT_ARRAY: "std_msgs/Header header\nuint32 height\nuint32 width\ndvs_msgs/Event[] events\n",
}
"""Message definitions of dvs_msgs (rpg_dvs_ros), in ROS .msg syntax."""

_WIRE_EVENT = np.dtype(
    [("x", "<u2"), ("y", "<u2"), ("sec", "<u4"), ("nsec", "<u4"), ("polarity", "u1")]
)  # 13 bytes, packed, as ROS1 serialises dvs_msgs/Event


def dvs_typestore():
    """A ROS1 Noetic ``rosbags`` typestore with ``dvs_msgs`` registered."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    types = {}
    for name, text in DVS_MSG_DEFINITIONS.items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


def decode_event_array(raw: bytes | memoryview, where: str) -> tuple[np.ndarray, int, int]:
    """Decode one serialised EventArray.

    Returns ``(wire_events, width, height)`` with ``wire_events`` of the packed wire dtype.
    Raises :class:`FormatError` if the message is shorter than its own lengths say.
    """
    buf = memoryview(raw)
    try:
        frame_len = int.from_bytes(buf[12:16], "little")
        off = 16 + frame_len
        height = int.from_bytes(buf[off : off + 4], "little")
        width = int.from_bytes(buf[off + 4 : off + 8], "little")
        n = int.from_bytes(buf[off + 8 : off + 12], "little")
        off += 12
        if len(buf) < off or off + n * _WIRE_EVENT.itemsize > len(buf):
            raise ValueError
    except ValueError:
        raise FormatError(f"{where}: EventArray message is truncated or corrupt ({len(buf)} bytes)") from None
    return np.frombuffer(buf, dtype=_WIRE_EVENT, count=n, offset=off), width, height


class RosbagSource:
    format = "rosbag"

    def __init__(self, path: Path, format: str = "rosbag", topic: str | None = None) -> None:
        from rosbags.rosbag1 import Reader

        self.path = path
        self.calibration = None
        self._where = where = f"{path}: rosbag"
        self._reader = Reader(path)
        try:
            self._reader.open()
        except Exception as exc:  # rosbags raises ReaderError, but also struct/KeyError on garbage
            raise FormatError(f"{where}: not a readable ROS1 bag ({type(exc).__name__}: {exc})") from None
        try:
            self._pick_topic(topic)
            self._peek()
            self.calibration = self._camera_info()
        except Exception:
            self.close()
            raise

    def _pick_topic(self, topic: str | None) -> None:
        conns = self._reader.connections
        event_conns = [c for c in conns if c.msgtype == EVENT_ARRAY]
        if topic is not None:
            chosen = [c for c in conns if c.topic == topic]
            if not chosen:
                raise FormatError(
                    f"{self._where}: no topic '{topic}'; topics: "
                    + ", ".join(sorted(f"{c.topic} ({c.msgtype})" for c in conns))
                )
            if chosen[0].msgtype != EVENT_ARRAY:
                raise FormatError(f"{self._where}: topic '{topic}' has type {chosen[0].msgtype}, not {EVENT_ARRAY}")
        else:
            topics = sorted({c.topic for c in event_conns})
            if not topics:
                raise FormatError(
                    f"{self._where}: no {EVENT_ARRAY} topic; topics: "
                    + (", ".join(sorted(f"{c.topic} ({c.msgtype})" for c in conns)) or "none")
                )
            if len(topics) > 1:
                raise FormatError(
                    f"{self._where}: several {EVENT_ARRAY} topics ({', '.join(topics)}); choose one with --topic"
                )
            topic = topics[0]
            chosen = [c for c in event_conns if c.topic == topic]
        self.topic = topic
        self._conns = chosen

    def _camera_info(self):
        """The calibration published beside the event topic (module docstring), or None."""
        name = self.topic.rsplit("/", 1)[0] + "/camera_info"
        conns = [c for c in self._reader.connections if c.topic == name and c.msgtype == CAMERA_INFO]
        if not conns:
            return None
        from rosbags.typesys import Stores, get_typestore

        from evseg.calibration import calibration_from_camera_info
        from evseg.errors import CalibrationError

        where = f"{self._where}: topic '{name}'"
        try:
            raw = next((raw for _, _, raw in self._reader.messages(connections=conns)), None)
            if raw is None:
                return None
            msg = get_typestore(Stores.ROS1_NOETIC).deserialize_ros1(raw, CAMERA_INFO)
        except Exception as exc:
            raise FormatError(f"{where}: corrupt CameraInfo message ({type(exc).__name__}: {exc})") from None
        size = self.sensor_size or (int(msg.width), int(msg.height))
        if msg.width and msg.height and (int(msg.width), int(msg.height)) != tuple(size):
            raise FormatError(f"{where}: CameraInfo is for {msg.width}x{msg.height}, the events are "
                              f"{size[0]}x{size[1]}; pick the event topic of that camera (--topic)")
        try:
            return calibration_from_camera_info(msg.K, msg.D, msg.distortion_model, size, where)
        except CalibrationError as exc:
            raise FormatError(str(exc)) from None

    def _messages(self):
        try:
            for _, _, raw in self._reader.messages(connections=self._conns):
                yield raw
        except FormatError:
            raise
        except Exception as exc:
            raise FormatError(f"{self._where}: corrupt or truncated message data ({type(exc).__name__}: {exc})") from None

    def _peek(self) -> None:
        self.sensor_size = None
        self.t_offset_us = 0
        for raw in self._messages():
            wire, width, height = decode_event_array(raw, self._where)
            if width > 0 and height > 0 and self.sensor_size is None:
                self.sensor_size = (width, height)
            if len(wire):
                self.t_offset_us = int(wire["sec"][0]) * 1_000_000 + int(wire["nsec"][0]) // 1000
                break

    def chunks(self, chunk_events: int) -> Iterator[Chunk]:
        return batched_chunks(self._events(), chunk_events)

    def _events(self) -> Iterator[np.ndarray]:
        for raw in self._messages():
            wire, _, _ = decode_event_array(raw, self._where)
            ev = np.empty(len(wire), dtype=EVENT_DTYPE)
            ev["x"], ev["y"] = wire["x"], wire["y"]
            ev["t"] = wire["sec"].astype(np.int64) * 1_000_000 + wire["nsec"].astype(np.int64) // 1000 - self.t_offset_us
            ev["p"] = np.where(wire["polarity"] > 0, 1, -1)
            yield ev

    def close(self) -> None:
        try:
            self._reader.close()
        except Exception:  # a bag that failed to open has nothing to close
            pass


def open_source(path: Path, format: str = "rosbag", topic: str | None = None) -> RosbagSource:
    return RosbagSource(path, format, topic)
