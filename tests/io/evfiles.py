"""Tiny encoders used by the reader tests to write fixture files of known content.

They follow the format specifications independently of the decoders in evseg.io (plain
Python loops, one word per step), so a test that round-trips through them checks the decoder
against the specification rather than against itself.
"""

from __future__ import annotations

import struct

import numpy as np

from evseg.events import make_events


def sample_events(n: int = 50, seed: int = 0, width: int = 64, height: int = 48, t0: int = 0,
                  max_dt: int = 300) -> np.ndarray:
    """Deterministic sorted events with gaps up to ``max_dt`` us (some equal timestamps)."""
    rng = np.random.default_rng(seed)
    t = t0 + np.cumsum(rng.integers(0, max_dt, n))
    return make_events(rng.integers(0, width, n), rng.integers(0, height, n), t, rng.integers(0, 2, n))


def evt2_bytes(ev: np.ndarray, header: str = "% evt 2.0\n% geometry 64x48\n% end\n") -> bytes:
    words = []
    th = None
    for e in ev:
        t = int(e["t"])
        if t >> 6 != th:
            th = t >> 6
            words.append((0x8 << 28) | (th & 0x0FFFFFFF))
        p = 1 if e["p"] > 0 else 0
        words.append((p << 28) | ((t & 0x3F) << 22) | (int(e["x"]) << 11) | int(e["y"]))
    return header.encode() + struct.pack(f"<{len(words)}I", *words)


def dat_bytes(ev: np.ndarray, header: str = "% Data file containing CD events\n% Version 2\n% Width 64\n% Height 48\n",
              event_type: int = 0x0C, event_size: int = 8, t_raw=None) -> bytes:
    """Prophesee DAT (one struct per record, independent of the reader's vectorised decode);
    ``t_raw``: the 32-bit timestamps to write instead of ``ev['t']`` (e.g. wrapped)."""
    t = ev["t"] if t_raw is None else t_raw
    body = b"".join(struct.pack("<II", int(ti) & 0xFFFFFFFF,
                                int(e["x"]) | (int(e["y"]) << 14) | ((1 if e["p"] > 0 else 0) << 28))
                    for ti, e in zip(t, ev))
    return header.encode() + bytes([event_type, event_size]) + body


def evt3_bytes(ev: np.ndarray, header: str = "% evt 3.0\n% format EVT3;height=48;width=64\n% end\n") -> bytes:
    """EVT3 with one EVT_ADDR_X word per event (vectors are tested with hand-made words)."""
    words = []
    th = tl = y = None
    for e in ev:
        t = int(e["t"])
        if (t >> 12) & 0xFFF != th:
            th = (t >> 12) & 0xFFF
            words.append((0x8 << 12) | th)
        if t & 0xFFF != tl:
            tl = t & 0xFFF
            words.append((0x6 << 12) | tl)
        if int(e["y"]) != y:
            y = int(e["y"])
            words.append(y)
        p = 1 if e["p"] > 0 else 0
        words.append((0x2 << 12) | (p << 11) | int(e["x"]))
    return header.encode() + struct.pack(f"<{len(words)}H", *words)


def es_bytes(ev: np.ndarray, width: int = 64, height: int = 48, resets_every: int = 0) -> bytes:
    """Event Stream 2.0.0 DVS file; optional 0xFE reset bytes (in idle state) every k events."""
    out = bytearray(b"Event Stream" + bytes([2, 0, 0, 1]) + struct.pack("<HH", width, height))
    prev = 0
    for i, e in enumerate(ev):
        if resets_every and i % resets_every == 0:
            out += b"\xfe" * 5
        dt = int(e["t"]) - prev
        prev = int(e["t"])
        out += b"\xff" * (dt // 127)
        out += bytes([((dt % 127) << 1) | (1 if e["p"] > 0 else 0)])
        out += struct.pack("<HH", int(e["x"]), int(e["y"]))
    return bytes(out)


def text_lines(ev: np.ndarray, size=(64, 48)) -> str:
    lines = [f"{size[0]} {size[1]}"] if size else []
    lines += [f"{int(e['t']) / 1e6:.6f} {e['x']} {e['y']} {1 if e['p'] > 0 else 0}" for e in ev]
    return "\n".join(lines) + "\n"


def mono_bytes(ev: np.ndarray, time_base_ns: int) -> bytes:
    """event_camera_msgs 'mono' encoding: one little-endian uint64 per event (polarity bit 63,
    y bits 48-62, x bits 32-47, time since ``time_base_ns`` in ns in bits 0-31)."""
    words = []
    for e in ev:
        dt = int(e["t"]) * 1000 - time_base_ns
        assert 0 <= dt < 2**32
        words.append(((1 if e["p"] > 0 else 0) << 63) | (int(e["y"]) << 48) | (int(e["x"]) << 32) | dt)
    return struct.pack(f"<{len(words)}Q", *words)


def write_bag(path, topics: dict[str, list[np.ndarray]], t0_ns: int = 1_519_939_282_250_708_000,
              extra_topic: bool = True, width: int = 64, height: int = 48,
              camera_info: dict[str, dict] | None = None, ros2: str | None = None,
              msgtype: str = "dvs_msgs/msg/EventArray", encoding: str = "evt3") -> None:
    """One event message per array, per topic, serialised by ``rosbags`` (not by evseg).

    ``ros2``: None writes a ROS1 bag, ``"sqlite3"`` or ``"mcap"`` a ROS2 bag directory with that
    storage. ``msgtype``: an EventArray type (times = t0 + event t in us) or
    ``event_camera_msgs/msg/EventPacket`` with ``encoding`` 'evt3' (the events of all of a
    topic's arrays as one EVT 3.0 stream, event t = sensor time in us, cut into one packet per
    array at its first event's words) or 'mono' (time_base = the array's first event, in ns),
    or any other string (an empty packet of that encoding). ``camera_info``: topic ->
    sensor_msgs/CameraInfo fields (K, D, distortion_model, width, height), one message each.
    """
    from evseg.io.ros_messages import EVENT_PACKET, event_typestore

    store = event_typestore(ros2 is not None)
    Time = store.types["builtin_interfaces/msg/Time"]
    Header = store.types["std_msgs/msg/Header"]

    def header(seq, ns):
        stamp = Time(ns // 10**9, ns % 10**9)
        return Header(stamp, "cam") if ros2 else Header(seq, stamp, "cam")

    def serialize(msg, kind):
        return store.serialize_cdr(msg, kind) if ros2 else store.serialize_ros1(msg, kind)

    if ros2:
        from rosbags.rosbag2 import StoragePlugin, Writer

        writer = Writer(path, version=9, storage_plugin=StoragePlugin[ros2.upper()])
    else:
        from rosbags.rosbag1 import Writer

        writer = Writer(path)
    with writer as w:
        for topic, info in (camera_info or {}).items():
            CameraInfo, roi = store.types["sensor_msgs/msg/CameraInfo"], store.types["sensor_msgs/msg/RegionOfInterest"]
            msg = CameraInfo(header(0, t0_ns), info.get("height", height),
                             info.get("width", width), info["distortion_model"], np.asarray(info["D"], dtype=np.float64),
                             np.asarray(info["K"], dtype=np.float64), np.eye(3).ravel(), np.zeros(12), 0, 0,
                             roi(0, 0, 0, 0, False))
            conn = w.add_connection(topic, "sensor_msgs/msg/CameraInfo", typestore=store)
            w.write(conn, t0_ns, serialize(msg, "sensor_msgs/msg/CameraInfo"))
        if extra_topic:
            conn = w.add_connection("/chatter", "std_msgs/msg/String", typestore=store)
            w.write(conn, t0_ns, serialize(store.types["std_msgs/msg/String"]("hi"), "std_msgs/msg/String"))
        for topic, msgs in topics.items():
            conn = w.add_connection(topic, msgtype, typestore=store)
            if msgtype == EVENT_PACKET:
                Packet = store.types[EVENT_PACKET]
                if encoding == "evt3":
                    cuts = np.cumsum([0] + [len(ev) for ev in msgs])
                    stream = np.concatenate(msgs)
                    # One stream cut at each array's first words: a packet does not repeat the
                    # time and row its first events share with the packet before, so decoding
                    # needs the state carried over from it.
                    starts = [len(evt3_bytes(stream[:c], header="")) for c in cuts]
                    data = evt3_bytes(stream, header="")
                for seq, ev in enumerate(msgs):
                    stamp_ns = t0_ns + int(ev["t"][-1]) * 1000 if len(ev) else t0_ns
                    if encoding == "evt3":
                        raw, base = data[starts[seq]:starts[seq + 1]], 0
                    elif encoding == "mono":
                        base = int(ev["t"][0]) * 1000 if len(ev) else 0
                        raw = mono_bytes(ev, base)
                    else:
                        raw, base = b"", 0
                    msg = Packet(header(seq, stamp_ns), height, width, seq, base, encoding, False,
                                 np.frombuffer(raw, dtype=np.uint8))
                    w.write(conn, stamp_ns, serialize(msg, EVENT_PACKET))
                continue
            Event, EventArray = store.types[msgtype.replace("EventArray", "Event")], store.types[msgtype]
            for seq, ev in enumerate(msgs):
                events = []
                for e in ev:
                    ns = t0_ns + int(e["t"]) * 1000
                    events.append(Event(int(e["x"]), int(e["y"]), Time(ns // 10**9, ns % 10**9), bool(e["p"] > 0)))
                stamp_ns = t0_ns + int(ev["t"][-1]) * 1000 if len(ev) else t0_ns
                msg = EventArray(header(seq, stamp_ns), height, width, events)
                w.write(conn, stamp_ns, serialize(msg, msgtype))
