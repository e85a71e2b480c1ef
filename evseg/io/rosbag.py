"""ROS1 and ROS2 bags of event messages (EED, EVIMO, EMSGC data; ROS2 camera drivers), without ROS.

The bag container is read by the ``rosbags`` library: ROS1 ``.bag`` files (format
``rosbag``) and ROS2 bags (format ``rosbag2``): the directory ``ros2 bag record`` writes
(``metadata.yaml`` with its ``.db3`` or ``.mcap`` files), or one ``.db3`` / ``.mcap`` file of
it. The event messages themselves are decoded with numpy from their serialisation
(:mod:`evseg.io.ros_messages`: ``dvs_msgs/EventArray``, ``prophesee_event_msgs/EventArray``,
``event_camera_msgs/EventPacket`` with the ``evt3`` or ``mono`` encoding).

Topic: the one connection whose type carries events; if there are several,
:class:`FormatError` lists them and ``topic=`` (``--topic``) picks one. Sensor size: the
``width``/``height`` of the first message that gives them. Times: ``t_offset_us`` is the
absolute time (us) of the first event, and ``t`` counts from there: ROS time for
``EventArray`` and ``mono`` packets, the camera's own clock for ``evt3`` packets. Calibration:
the first ``sensor_msgs/CameraInfo`` message on ``camera_info`` beside the event topic
(``/dvs/events`` -> ``/dvs/camera_info``, as rpg_dvs_ros and the ROS2 drivers publish it),
unless its ``K`` is all zeros (an uncalibrated camera); a ``--calib`` file overrides it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from evseg.errors import FormatError
from evseg.io.recording import Chunk, batched_chunks
from evseg.io.ros_messages import (
    EVENT_ARRAY_TYPES,
    EVENT_PACKET,
    EVENT_TYPES,
    PacketDecoder,
    array_events,
    decode_event_array,
    parse_event_packet,
)

CAMERA_INFO = "sensor_msgs/msg/CameraInfo"


class RosbagSource:
    """Events of one topic of a ROS1 (``format='rosbag'``) or ROS2 (``'rosbag2'``) bag."""

    def __init__(self, path: Path, format: str = "rosbag", topic: str | None = None) -> None:
        self.path = path
        self.format = format
        self.calibration = None
        self.calibration_problem: str | None = None  # why the bag's CameraInfo is not used
        self._ros2 = format == "rosbag2"
        self._where = where = f"{path}: {format}"
        if self._ros2:
            from rosbags.rosbag2 import Reader
        else:
            from rosbags.rosbag1 import Reader
        kind = "ROS2 bag (a directory with metadata.yaml, or its .db3 / .mcap file)" if self._ros2 else "ROS1 bag"
        try:
            self._reader = Reader(path)
            self._reader.open()
        except Exception as exc:  # rosbags raises ReaderError, but also struct/KeyError on garbage
            hint = ("; a ROS1 bag cut short or never closed (a recording that was killed) loses its index: "
                    "`rosbag reindex` rebuilds it" if not self._ros2 and "index" in str(exc).lower() else "")
            raise FormatError(f"{where}: not a readable {kind} ({type(exc).__name__}: {exc}){hint}") from None
        try:
            self._pick_topic(topic)
            self._peek()
            try:
                self.calibration = self._camera_info()
            except FormatError as exc:
                # The events are fine; the calibration is refused only where it would be used,
                # so a --calib of the user's own still reads the bag.
                self.calibration_problem = str(exc)
        except Exception:
            self.close()
            raise

    def _pick_topic(self, topic: str | None) -> None:
        conns = self._reader.connections
        event_conns = [c for c in conns if c.msgtype in EVENT_TYPES]
        listing = ", ".join(sorted(f"{c.topic} ({c.msgtype})" for c in conns)) or "none"
        if topic is not None:
            chosen = [c for c in conns if c.topic == topic]
            if not chosen:
                raise FormatError(f"{self._where}: no topic '{topic}'; topics: {listing}")
            if chosen[0].msgtype not in EVENT_TYPES:
                raise FormatError(f"{self._where}: topic '{topic}' has type {chosen[0].msgtype}, not one of "
                                  f"the event messages evseg reads ({', '.join(EVENT_TYPES)})")
        else:
            topics = sorted({c.topic for c in event_conns})
            if not topics:
                raise FormatError(f"{self._where}: no event topic ({', '.join(EVENT_TYPES)}); topics: {listing}")
            if len(topics) > 1:
                raise FormatError(f"{self._where}: several event topics "
                                  f"({', '.join(f'{c.topic} ({c.msgtype})' for c in sorted(event_conns, key=lambda c: c.topic))}); "
                                  "choose one with --topic")
            topic = topics[0]
            chosen = [c for c in event_conns if c.topic == topic]
        types = {c.msgtype for c in chosen}
        if len(types) > 1:
            raise FormatError(f"{self._where}: topic '{topic}' is recorded with several types ({', '.join(sorted(types))})")
        self.topic = topic
        self.msgtype = types.pop()
        self._conns = chosen

    def _decoder(self) -> Callable[[bytes], tuple[np.ndarray, int, int]]:
        """A fresh per-pass decoder: raw message -> (events with absolute t in us, width, height)."""
        where, cdr = f"{self._where}: topic '{self.topic}'", self._ros2
        if self.msgtype in EVENT_ARRAY_TYPES:
            def decode(raw):
                wire, width, height = decode_event_array(raw, cdr, where)
                return array_events(wire), width, height
            return decode
        assert self.msgtype == EVENT_PACKET
        packets = PacketDecoder(where)

        def decode(raw):
            packet = parse_event_packet(raw, cdr, where)
            return packets.decode(packet), packet.width, packet.height
        return decode

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
            if self._ros2:
                msg = get_typestore(Stores.ROS2_HUMBLE).deserialize_cdr(raw, CAMERA_INFO)
                K, D = msg.k, msg.d
            else:
                msg = get_typestore(Stores.ROS1_NOETIC).deserialize_ros1(raw, CAMERA_INFO)
                K, D = msg.K, msg.D
        except Exception as exc:
            raise FormatError(f"{where}: corrupt CameraInfo message ({type(exc).__name__}: {exc})") from None
        size = self.sensor_size or (int(msg.width), int(msg.height))
        if msg.width and msg.height and (int(msg.width), int(msg.height)) != tuple(size):
            raise FormatError(f"{where}: CameraInfo is for {msg.width}x{msg.height}, the events are "
                              f"{size[0]}x{size[1]}")
        try:
            return calibration_from_camera_info(K, D, msg.distortion_model, size, where)
        except CalibrationError as exc:
            raise FormatError(str(exc)) from None

    def _messages(self) -> Iterator[tuple[np.ndarray, int, int]]:
        decode = self._decoder()
        try:
            for _, _, raw in self._reader.messages(connections=self._conns):
                yield decode(raw)
        except FormatError:
            raise
        except Exception as exc:
            raise FormatError(f"{self._where}: corrupt or truncated message data ({type(exc).__name__}: {exc})") from None

    def _peek(self) -> None:
        self.sensor_size = None
        self.t_offset_us = 0
        for ev, width, height in self._messages():
            if width > 0 and height > 0 and self.sensor_size is None:
                self.sensor_size = (width, height)
            if len(ev):
                self.t_offset_us = int(ev["t"][0])
                break

    def chunks(self, chunk_events: int) -> Iterator[Chunk]:
        return batched_chunks(self._events(), chunk_events)

    def _events(self) -> Iterator[np.ndarray]:
        for ev, _, _ in self._messages():
            ev["t"] -= self.t_offset_us
            yield ev

    def close(self) -> None:
        try:
            self._reader.close()
        except Exception:  # a bag that failed to open has nothing to close
            pass


def open_source(path: Path, format: str = "rosbag", topic: str | None = None) -> RosbagSource:
    return RosbagSource(path, format, topic)
