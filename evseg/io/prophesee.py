"""Prophesee ``.raw`` recordings in the EVT 2.0 and EVT 3.0 encodings.

A ``.raw`` file is a text header of lines starting with ``%`` (optionally closed by
``% end``) followed by little-endian binary words. The header names the encoding
(``% evt 3.0``, ``% format EVT3;height=720;width=1280``) and usually the geometry
(``% geometry 1280x720`` or ``width``/``height`` in the ``format`` line); older files only name
the camera plugin, from which the size is looked up in :data:`PLUGIN_GEOMETRY`.

Decoding is vectorised over blocks of words (no Python loop per word). The sensor's time
counters wrap (EVT2: 34-bit time, 28-bit TIME_HIGH; EVT3: 24-bit time, 12-bit TIME_HIGH); a
decrease of TIME_HIGH is taken as a wrap and timestamps are unwrapped to monotonic int64 us.
Timestamps are the camera's (``t_offset_us`` = 0). Polarity 1 (ON) -> +1, 0 (OFF) -> -1.
Unknown word types and a truncated last word raise :class:`FormatError` with the byte offset.

EVT 3.0 words (16 bits, type in the top 4 bits): 0x0 EVT_ADDR_Y (y, 11 bits), 0x2 EVT_ADDR_X
(x, 11 bits; polarity bit 11: one event), 0x3 VECT_BASE_X (x and polarity for vectors), 0x4
VECT_12 / 0x5 VECT_8 (validity masks: events at base_x + i, then base_x += 12 / 8), 0x6
TIME_LOW and 0x8 TIME_HIGH (12 bits each), 0xA EXT_TRIGGER, 0xE OTHERS, 0x7 / 0xF CONTINUED
(skipped). EVT 2.0 words (32 bits, type in bits 28-31): 0x0 CD_OFF / 0x1 CD_ON (t low 6 bits
in 22-27, x in 11-21, y in 0-10), 0x8 EVT_TIME_HIGH (28 bits), 0xA EXT_TRIGGER, 0xE OTHERS,
0xF CONTINUED (skipped).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np

from evseg.errors import FormatError
from evseg.events import EVENT_DTYPE
from evseg.io.recording import Chunk

PLUGIN_GEOMETRY = {
    "gen41": (1280, 720),
    "gen4": (1280, 720),
    "imx636": (1280, 720),
    "imx646": (1280, 720),
    "gen31": (640, 480),
    "gen3": (640, 480),
    "imx8": (320, 320),
    "genx320": (320, 320),
}
"""Sensor size by substring of the header's ``plugin_name`` (files without geometry)."""

_MAX_HEADER_BYTES = 1 << 20


def read_header(f) -> tuple[dict[str, str], int]:
    """Parse the ``%`` header from an open binary file positioned at 0.

    Returns ``(fields, data_offset)``: header keys (first word of each line, lower case) to
    the rest of the line, and the byte offset of the first binary word.
    """
    fields: dict[str, str] = {}
    offset = 0
    while True:
        peek = f.read(1)
        if peek != b"%":
            break
        line = b"%" + f.readline(_MAX_HEADER_BYTES)
        offset += len(line)
        if not line.endswith(b"\n") or offset > _MAX_HEADER_BYTES:
            raise FormatError(f"header line at byte offset {offset - len(line)} is not terminated")
        text = line[1:].decode("latin-1").strip()
        if text == "end":
            return fields, offset
        key, _, value = text.partition(" ")
        if key:
            fields.setdefault(key.lower(), value.strip())
    return fields, offset


def encoding_of(fields: dict[str, str]) -> str | None:
    """``"evt2"``, ``"evt3"``, another lower-case encoding name, or ``None`` if not stated."""
    if "evt" in fields:
        v = fields["evt"].strip()
        return {"2.0": "evt2", "3.0": "evt3"}.get(v, "evt" + v.replace(".", ""))
    if "format" in fields:
        name = fields["format"].split(";")[0].strip().lower()
        return {"evt2": "evt2", "evt3": "evt3", "evt21": "evt21"}.get(name, name)
    return None


def geometry_of(fields: dict[str, str]) -> tuple[int, int] | None:
    """Sensor ``(width, height)`` from ``geometry``, the ``format`` line or the plugin name."""
    if "geometry" in fields:
        m = re.match(r"\s*(\d+)\s*x\s*(\d+)", fields["geometry"])
        if m:
            return int(m.group(1)), int(m.group(2))
    if "format" in fields:
        opts = dict(
            kv.split("=", 1) for kv in fields["format"].split(";")[1:] if "=" in kv
        )
        if "width" in opts and "height" in opts and opts["width"].isdigit() and opts["height"].isdigit():
            return int(opts["width"]), int(opts["height"])
    if "width" in fields and "height" in fields and fields["width"].isdigit() and fields["height"].isdigit():
        return int(fields["width"]), int(fields["height"])
    plugin = fields.get("plugin_name", "").lower()
    for key, size in PLUGIN_GEOMETRY.items():
        if key in plugin:
            return size
    return None


def sniff_raw_format(head: bytes) -> str | None:
    """Encoding named in the header at the start of a file (see :func:`encoding_of`)."""
    import io

    try:
        fields, _ = read_header(io.BytesIO(head))
    except FormatError:
        return None
    enc = encoding_of(fields)
    return enc if enc is not None else "raw (no encoding in header)"


@dataclass
class _State:
    """Decoder state carried from one block of words to the next."""

    time_high: int = 0  # unwrapped TIME_HIGH count (wraps already added)
    last_raw_high: int = -1  # last raw TIME_HIGH value, to detect wraps
    time_low: int = 0
    y: int = 0
    base_x: int = 0
    vect_pol: int = 0
    extra: dict = field(default_factory=dict)


def _ffill(is_set: np.ndarray, values: np.ndarray, initial: int) -> np.ndarray:
    """Value of the last setter at or before each position (``initial`` before the first)."""
    idx = np.where(is_set, np.arange(len(is_set)), -1)
    np.maximum.accumulate(idx, out=idx)
    out = np.where(idx >= 0, values[np.maximum(idx, 0)], initial)
    return out.astype(np.int64)


def _unwrap_time_high(raw_high: np.ndarray, st: _State, period: int) -> np.ndarray:
    """Unwrapped TIME_HIGH counts for the TIME_HIGH words of a block (in order)."""
    if len(raw_high) == 0:
        return raw_high.astype(np.int64)
    prev = np.concatenate([[st.last_raw_high], raw_high[:-1]]).astype(np.int64)
    wraps = np.cumsum((raw_high.astype(np.int64) < prev) & (prev >= 0))
    base = st.time_high - (st.last_raw_high if st.last_raw_high >= 0 else 0)
    return base + raw_high.astype(np.int64) + period * wraps


def _bad_type(where: str, types: np.ndarray, known: tuple[int, ...], word_offset: int, word_bytes: int) -> None:
    bad = np.flatnonzero(~np.isin(types, known))
    if len(bad):
        i = int(bad[0])
        raise FormatError(
            f"{where}: unknown word type {int(types[i]):#x} at byte offset {word_offset + i * word_bytes} "
            f"({len(bad)} such words in this block; corrupt data or wrong encoding)"
        )


def decode_evt3(words: np.ndarray, st: _State, where: str, byte_offset: int) -> tuple[np.ndarray, np.ndarray]:
    """Decode a block of EVT 3.0 words, updating ``st``.

    Args:
        words: uint16 words.
        st: state from the previous block (mutated to the state after this block).
        where, byte_offset: file label and offset of ``words[0]`` for error messages.

    Returns:
        ``(events, word_index)``: :data:`EVENT_DTYPE` events (t in us) in stream order and,
        for each event, the index of the word it came from.
    """
    w = words.astype(np.int64)
    typ = w >> 12
    _bad_type(where, typ, (0x0, 0x2, 0x3, 0x4, 0x5, 0x6, 0x7, 0x8, 0xA, 0xE, 0xF), byte_offset, 2)
    payload = w & 0xFFF
    is_y, is_x, is_base = typ == 0x0, typ == 0x2, typ == 0x3
    is_v12, is_v8, is_tl, is_th = typ == 0x4, typ == 0x5, typ == 0x6, typ == 0x8

    th_idx = np.flatnonzero(is_th)
    th_unwrapped = np.zeros(len(w), dtype=np.int64)
    th_unwrapped[th_idx] = _unwrap_time_high(payload[th_idx], st, 1 << 12)
    time_high = _ffill(is_th, th_unwrapped, st.time_high)
    time_low = _ffill(is_tl, payload, st.time_low)
    t = (time_high << 12) | time_low
    y = _ffill(is_y, payload & 0x7FF, st.y)

    # Vector base: the last VECT_BASE_X plus 12 / 8 for every vector word since then.
    inc = np.where(is_v12, 12, 0) + np.where(is_v8, 8, 0)
    cum_excl = np.cumsum(inc) - inc
    base_val = _ffill(is_base, payload & 0x7FF, st.base_x)
    base_cum = _ffill(is_base, cum_excl, 0)
    base_x = base_val + cum_excl - base_cum
    vect_pol = _ffill(is_base, payload >> 11, st.vect_pol)

    rel = np.flatnonzero(is_x | is_v12 | is_v8)
    bits = np.arange(12)
    mask = np.where(is_x[rel], 1, np.where(is_v12[rel], payload[rel], payload[rel] & 0xFF))
    valid = ((mask[:, None] >> bits) & 1).astype(bool)
    x0 = np.where(is_x[rel], payload[rel] & 0x7FF, base_x[rel])
    pol = np.where(is_x[rel], payload[rel] >> 11, vect_pol[rel])
    r, b = np.nonzero(valid)
    word = rel[r]
    ev = np.empty(len(r), dtype=EVENT_DTYPE)
    x = x0[r] + b
    if len(x) and x.max() > 65535:  # only reachable with corrupt vector words
        i = int(np.argmax(x > 65535))
        raise FormatError(f"{where}: vector event x={int(x[i])} at byte offset {byte_offset + 2 * int(word[i])} is not a pixel")
    ev["x"] = x
    ev["y"] = y[word]
    ev["t"] = t[word]
    ev["p"] = np.where(pol[r] > 0, 1, -1)

    if len(w):
        st.time_high = int(time_high[-1])
        if len(th_idx):
            st.last_raw_high = int(payload[th_idx[-1]])
        st.time_low, st.y = int(time_low[-1]), int(y[-1])
        st.base_x = int(base_x[-1] + inc[-1])
        st.vect_pol = int(vect_pol[-1])
    return ev, word


def decode_evt2(words: np.ndarray, st: _State, where: str, byte_offset: int) -> tuple[np.ndarray, np.ndarray]:
    """Decode a block of EVT 2.0 uint32 words (see :func:`decode_evt3` for the contract)."""
    w = words.astype(np.int64)
    typ = w >> 28
    _bad_type(where, typ, (0x0, 0x1, 0x8, 0xA, 0xE, 0xF), byte_offset, 4)
    is_cd, is_th = typ <= 1, typ == 0x8
    th_idx = np.flatnonzero(is_th)
    th_unwrapped = np.zeros(len(w), dtype=np.int64)
    th_unwrapped[th_idx] = _unwrap_time_high(w[th_idx] & 0x0FFFFFFF, st, 1 << 28)
    time_high = _ffill(is_th, th_unwrapped, st.time_high)
    cd = np.flatnonzero(is_cd)
    ev = np.empty(len(cd), dtype=EVENT_DTYPE)
    wc = w[cd]
    ev["t"] = (time_high[cd] << 6) | ((wc >> 22) & 0x3F)
    ev["x"] = (wc >> 11) & 0x7FF
    ev["y"] = wc & 0x7FF
    ev["p"] = np.where(typ[cd] == 1, 1, -1)
    if len(w):
        st.time_high = int(time_high[-1])
        if len(th_idx):
            st.last_raw_high = int(w[th_idx[-1]] & 0x0FFFFFFF)
    return ev, cd


class RawSource:
    """Streaming decoder of one Prophesee ``.raw`` file."""

    def __init__(self, path: Path, format: str) -> None:
        self.path = path
        self.format = format
        self.calibration = None
        self.t_offset_us = 0
        self._where = where = f"{path}: {format}"
        with open(path, "rb") as f:
            try:
                fields, self._data_offset = read_header(f)
            except FormatError as exc:
                raise FormatError(f"{where}: {exc}") from None
        if not fields:
            raise FormatError(f"{where}: no '%' text header at byte offset 0 (not a Prophesee .raw file)")
        enc = encoding_of(fields)
        if enc is not None and enc != format:
            raise FormatError(f"{where}: the header says the encoding is {enc}, not {format}")
        self.sensor_size = geometry_of(fields)
        self.header = fields
        self._word_bytes = 4 if format == "evt2" else 2
        size = path.stat().st_size - self._data_offset
        if size % self._word_bytes:
            end = self._data_offset + size - size % self._word_bytes
            raise FormatError(
                f"{where}: truncated: {size % self._word_bytes} trailing byte(s) at byte offset {end} "
                f"do not make a whole {8 * self._word_bytes}-bit word"
            )

    def chunks(self, chunk_events: int) -> Iterator[Chunk]:
        decode = decode_evt2 if self.format == "evt2" else decode_evt3
        dtype = np.dtype("<u4") if self.format == "evt2" else np.dtype("<u2")
        st = _State()
        offset = self._data_offset
        with open(self.path, "rb") as f:
            f.seek(offset)
            while True:
                buf = f.read(chunk_events * self._word_bytes)
                if not buf:
                    return
                words = np.frombuffer(buf, dtype=dtype)
                ev, word = decode(words, st, self._where, offset)
                base = offset
                yield Chunk(ev, lambda i, word=word, base=base: f"byte offset {base + self._word_bytes * int(word[i])}")
                offset += len(buf)

    def close(self) -> None:
        pass


def open_source(path: Path, format: str) -> RawSource:
    return RawSource(path, format)
