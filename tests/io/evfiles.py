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


def write_bag(path, topics: dict[str, list[np.ndarray]], t0_ns: int = 1_519_939_282_250_708_000,
              extra_topic: bool = True, width: int = 64, height: int = 48,
              camera_info: dict[str, dict] | None = None) -> None:
    """One EventArray message per array, per topic; times = t0 + event t (us).
    ``camera_info``: topic -> sensor_msgs/CameraInfo fields (K, D, distortion_model, width,
    height), one message each."""
    from rosbags.rosbag1 import Writer

    from evseg.io.rosbag import EVENT_ARRAY, dvs_typestore

    store = dvs_typestore()
    Time = store.types["builtin_interfaces/msg/Time"]
    Header = store.types["std_msgs/msg/Header"]
    Event = store.types["dvs_msgs/msg/Event"]
    EventArray = store.types[EVENT_ARRAY]
    with Writer(path) as w:
        for topic, info in (camera_info or {}).items():
            CameraInfo, roi = store.types["sensor_msgs/msg/CameraInfo"], store.types["sensor_msgs/msg/RegionOfInterest"]
            msg = CameraInfo(Header(0, Time(t0_ns // 10**9, t0_ns % 10**9), "cam"), info.get("height", height),
                             info.get("width", width), info["distortion_model"], np.asarray(info["D"], dtype=np.float64),
                             np.asarray(info["K"], dtype=np.float64), np.eye(3).ravel(), np.zeros(12), 0, 0,
                             roi(0, 0, 0, 0, False))
            conn = w.add_connection(topic, "sensor_msgs/msg/CameraInfo", typestore=store)
            w.write(conn, t0_ns, store.serialize_ros1(msg, "sensor_msgs/msg/CameraInfo"))
        if extra_topic:
            conn = w.add_connection("/chatter", "std_msgs/msg/String", typestore=store)
            w.write(conn, t0_ns, store.serialize_ros1(store.types["std_msgs/msg/String"]("hi"), "std_msgs/msg/String"))
        for topic, msgs in topics.items():
            conn = w.add_connection(topic, EVENT_ARRAY, typestore=store)
            for seq, ev in enumerate(msgs):
                events = []
                for e in ev:
                    ns = t0_ns + int(e["t"]) * 1000
                    events.append(Event(int(e["x"]), int(e["y"]), Time(ns // 10**9, ns % 10**9), bool(e["p"] > 0)))
                stamp_ns = t0_ns + int(ev["t"][-1]) * 1000 if len(ev) else t0_ns
                msg = EventArray(Header(seq, Time(stamp_ns // 10**9, stamp_ns % 10**9), "cam"), height, width, events)
                w.write(conn, stamp_ns, store.serialize_ros1(msg, EVENT_ARRAY))
