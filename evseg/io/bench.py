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


def write_synthetic(fmt: str, ev: np.ndarray, folder: Path, size: tuple[int, int]) -> Path:
    """Write ``ev`` in format ``fmt`` (text, npz, h5, evt2, evt3, es) under ``folder``."""
    from evseg.io import write_h5, write_npz, write_text

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
        for fmt in ("evt3", "evt2", "es", "h5", "npz", "text"):
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
                "file_MB": path.stat().st_size / 1e6,
                "read_s": med,
                "Mev_per_s": n / med / 1e6,
            })
    return rows
