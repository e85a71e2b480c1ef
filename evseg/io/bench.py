"""Reader throughput: decode synthetic recordings of known size in every writable format.

``benchmark(repeats, quick)`` writes one file per format (events at ~1 Mev/s over a 640x480
sensor, fixed seed) into a temporary folder, then times a full streaming pass
(``Recording.chunks``) and reports the median over ``repeats`` runs, with the file size.
The EVT2 / EVT3 / Event Stream files are produced by the vectorised encoders below, which the
tests check against the readers.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from evseg.events import EVENT_DTYPE, EventStream


def synthetic_events(n: int, width: int = 640, height: int = 480, rate_ev_s: float = 1e6,
                     seed: int = 0) -> np.ndarray:
    """``n`` sorted random events at about ``rate_ev_s`` (Poisson gaps, whole us)."""
    rng = np.random.default_rng(seed)
    ev = np.empty(n, dtype=EVENT_DTYPE)
    ev["t"] = np.cumsum(rng.exponential(1e6 / rate_ev_s, n)).astype(np.int64)
    ev["x"] = rng.integers(0, width, n)
    ev["y"] = rng.integers(0, height, n)
    ev["p"] = np.where(rng.random(n) < 0.5, 1, -1)
    return ev


def encode_evt2(ev: np.ndarray) -> np.ndarray:
    """EVT 2.0 uint32 words: a TIME_HIGH word wherever ``t >> 6`` changes, one CD word per event."""
    t = ev["t"].astype(np.int64)
    th = t >> 6
    new_th = np.concatenate([[True], th[1:] != th[:-1]])
    cd = ((ev["p"] > 0).astype(np.int64) << 28) | ((t & 0x3F) << 22) | (ev["x"].astype(np.int64) << 11) | ev["y"]
    words = np.stack([(0x8 << 28) | (th & 0x0FFFFFFF), cd], axis=1)
    keep = np.stack([new_th, np.ones(len(ev), bool)], axis=1)
    return words[keep].astype("<u4")


def encode_evt3(ev: np.ndarray) -> np.ndarray:
    """EVT 3.0 uint16 words: TIME_HIGH / TIME_LOW / ADDR_Y when they change, one ADDR_X per event."""
    t = ev["t"].astype(np.int64)
    th, tl, y = (t >> 12) & 0xFFF, t & 0xFFF, ev["y"].astype(np.int64)

    def changed(a: np.ndarray) -> np.ndarray:
        return np.concatenate([[True], a[1:] != a[:-1]])

    words = np.stack([0x8000 | th, 0x6000 | tl, y, 0x2000 | ((ev["p"] > 0).astype(np.int64) << 11) | ev["x"]], axis=1)
    keep = np.stack([changed(t >> 12), changed(t), changed(y), np.ones(len(ev), bool)], axis=1)
    return words[keep].astype("<u2")


def encode_es(ev: np.ndarray, width: int, height: int) -> bytes:
    """Event Stream 2.0 DVS bytes: ``dt // 127`` overflow bytes, then the 5-byte event."""
    t = ev["t"].astype(np.int64)
    dt = np.diff(t, prepend=0)
    n_ovf = dt // 127
    size = n_ovf + 5
    start = np.cumsum(size) - size
    out = np.full(int(size.sum()), 0xFF, dtype=np.uint8)
    pos = start + n_ovf
    out[pos] = ((dt % 127) << 1) | (ev["p"] > 0)
    x, y = ev["x"].astype(np.int64), ev["y"].astype(np.int64)
    out[pos + 1], out[pos + 2] = x & 0xFF, x >> 8
    out[pos + 3], out[pos + 4] = y & 0xFF, y >> 8
    header = b"Event Stream" + bytes([2, 0, 0, 1]) + int(width).to_bytes(2, "little") + int(height).to_bytes(2, "little")
    return header + out.tobytes()


def _header(cdr: bool) -> bytes:
    """A std_msgs/Header with stamp 0 and an empty frame_id, then the alignment to 4 bytes."""
    if cdr:  # encapsulation CDR_LE, sec, nanosec, frame_id "" (length 1: the NUL), 3 bytes padding
        return b"\x00\x01\x00\x00" + bytes(8) + (1).to_bytes(4, "little") + bytes(4)
    return bytes(12) + bytes(4)  # seq, sec, nsec, frame_id length 0


def encode_event_arrays(ev: np.ndarray, size: tuple[int, int], cdr: bool, per_message: int = 1000) -> list[bytes]:
    """Serialised ``dvs_msgs/EventArray`` messages of ``per_message`` events each (t = ROS
    time in us), ROS1 or CDR (the layouts of :mod:`evseg.io.ros_messages`)."""
    out = []
    for a in range(0, len(ev), per_message):
        part = ev[a:a + per_message]
        n = len(part)
        head = _header(cdr) + np.array([size[1], size[0], n], dtype="<u4").tobytes()
        if cdr:
            body = np.zeros(14 + 16 * (n - 1), dtype=np.uint8)
            rows = [(0, 14, (0, 2, 4, 8, 12))] + [(14, 16, (0, 2, 6, 10, 14))] * (n > 1)
            for start, stride, offsets in rows:
                sub = part[:1] if start == 0 else part[1:]
                view = body[start:].reshape(-1, stride) if start else body[:14].reshape(1, 14)
                for field, off, width, value in zip(("x", "y", "sec", "nsec", "p"), offsets, (2, 2, 4, 4, 1), (
                        sub["x"], sub["y"], sub["t"] // 1_000_000, (sub["t"] % 1_000_000) * 1000, sub["p"] > 0)):
                    view[:, off:off + width] = np.asarray(value).astype(f"<u{width}").view(np.uint8).reshape(-1, width)
            out.append(head + body.tobytes())
        else:
            wire = np.empty(n, dtype=[("x", "<u2"), ("y", "<u2"), ("sec", "<u4"), ("nsec", "<u4"), ("polarity", "u1")])
            wire["x"], wire["y"] = part["x"], part["y"]
            wire["sec"], wire["nsec"] = part["t"] // 1_000_000, (part["t"] % 1_000_000) * 1000
            wire["polarity"] = part["p"] > 0
            out.append(head + wire.tobytes())
    return out


def encode_evt3_packets(ev: np.ndarray, size: tuple[int, int], cdr: bool, words: int = 4096) -> list[bytes]:
    """Serialised ``event_camera_msgs/EventPacket`` messages, encoding ``evt3``: the EVT 3.0
    words of ``ev`` (:func:`encode_evt3`) cut every ``words`` words, as a camera driver sends them."""
    stream = encode_evt3(ev)
    out = []
    for a in range(0, len(stream), words):
        data = stream[a:a + words].tobytes()
        head = _header(cdr) + np.array([size[1], size[0]], dtype="<u4").tobytes()
        # CDR: seq (uint64) needs 8-alignment and starts at data offset 24, already aligned.
        head += np.array([a // words, 0], dtype="<u8").tobytes()
        enc = b"evt3\x00" if cdr else b"evt3"
        head += len(enc).to_bytes(4, "little") + enc + b"\x00"  # is_bigendian
        if cdr:
            head += bytes((-(len(head) - 4)) % 4)
        out.append(head + len(data).to_bytes(4, "little") + data)
    return out


def write_bag_file(path: Path, messages: list[bytes], msgtype: str, ros2: bool) -> Path:
    """A ROS1 bag (``path``) or ROS2 MCAP bag directory of ``messages`` on topic /dvs/events."""
    from evseg.io.ros_messages import event_typestore

    store = event_typestore(ros2)
    if ros2:
        from rosbags.rosbag2 import StoragePlugin, Writer

        writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    else:
        from rosbags.rosbag1 import Writer

        writer = Writer(path)
    with writer as w:
        conn = w.add_connection("/dvs/events", msgtype, typestore=store)
        for i, raw in enumerate(messages):
            w.write(conn, i * 1_000_000, raw)
    return path


BAG_FORMATS = ("rosbag", "rosbag2", "rosbag2_evt3")
"""The benchmark's bags: ROS1 and ROS2 (MCAP) dvs_msgs/EventArray, and ROS2 EVT 3.0 packets."""


def write_synthetic(fmt: str, ev: np.ndarray, folder: Path, size: tuple[int, int]) -> Path:
    """Write ``ev`` in format ``fmt`` (text, npz, h5, evt2, evt3, es or one of
    :data:`BAG_FORMATS`) under ``folder``."""
    from evseg.io import write_h5, write_npz, write_text
    from evseg.io.ros_messages import DVS_EVENT_ARRAY, EVENT_PACKET

    if fmt in ("rosbag", "rosbag2"):
        return write_bag_file(folder / ("events.bag" if fmt == "rosbag" else "events_ros2"),
                              encode_event_arrays(ev, size, cdr=fmt == "rosbag2"), DVS_EVENT_ARRAY, fmt == "rosbag2")
    if fmt == "rosbag2_evt3":
        return write_bag_file(folder / "evt3_ros2", encode_evt3_packets(ev, size, cdr=True), EVENT_PACKET, True)
    stream = EventStream(ev, size)
    if fmt == "text":
        return write_text(stream, folder / "events.txt")
    if fmt == "npz":
        return write_npz(stream, folder / "events.npz")
    if fmt == "h5":
        return write_h5(stream, folder / "events.h5")
    geometry = f"% geometry {size[0]}x{size[1]}\n% end\n"
    if fmt == "evt2":
        path = folder / "evt2.raw"
        path.write_bytes(b"% evt 2.0\n" + geometry.encode() + encode_evt2(ev).tobytes())
        return path
    if fmt == "evt3":
        path = folder / "evt3.raw"
        path.write_bytes(b"% evt 3.0\n" + geometry.encode() + encode_evt3(ev).tobytes())
        return path
    if fmt == "es":
        path = folder / "events.es"
        path.write_bytes(encode_es(ev, *size))
        return path
    raise ValueError(f"no synthetic writer for format {fmt!r}")


def _stream_once(path: Path) -> int:
    from evseg.io import open_recording

    with open_recording(path) as rec:
        return sum(len(c) for c in rec.chunks())


def benchmark(repeats: int, quick: bool) -> list[dict]:
    """Median time of a full streaming read per format (see module docstring)."""
    n = 200_000 if quick else 2_000_000
    size = (640, 480)
    ev = synthetic_events(n, *size)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for fmt in ("evt3", "evt2", "es", "h5", "npz", *BAG_FORMATS, "text"):
            path = write_synthetic(fmt, ev, Path(tmp), size)
            times = []
            for _ in range(repeats):
                t0 = time.perf_counter()
                got = _stream_once(path)
                times.append(time.perf_counter() - t0)
            assert got == n, f"{fmt}: read {got} of {n} events"
            med = float(np.median(times))
            rows.append({
                "format": fmt,
                "events": n,
                "file_MB": sum(f.stat().st_size for f in ([path] if path.is_file() else path.iterdir())) / 1e6,
                "read_s": med,
                "Mev_per_s": n / med / 1e6,
            })
    return rows
