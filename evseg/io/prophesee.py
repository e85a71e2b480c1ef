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
    if enc is None:
        from evseg.io.prophesee_dat import is_dat_header

        if is_dat_header(fields):
            return "dat"
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


def _last_setter(setters: np.ndarray, at: np.ndarray) -> np.ndarray:
    """For each word index in ``at``, the position in ``setters`` (sorted word indices of the
    words that set a state value) of the last setter at or before it; -1 if none."""
    return np.searchsorted(setters, at, side="right") - 1


def _state_at(setters: np.ndarray, values: np.ndarray, at: np.ndarray, initial: int) -> np.ndarray:
    """Value of a decoder state (set by the words ``setters`` to ``values``) at words ``at``;
    ``initial`` (the state carried from the previous block) before the first setter."""
    k = _last_setter(setters, at)
    if len(values) == 0:
        return np.full(len(at), initial, dtype=np.int64)
    return np.where(k >= 0, values[np.maximum(k, 0)], initial).astype(np.int64)


def _unwrap_time_high(raw_high: np.ndarray, st: _State, period: int) -> np.ndarray:
    """Unwrapped TIME_HIGH counts for the TIME_HIGH words of a block (in order)."""
    raw_high = raw_high.astype(np.int64)
    if len(raw_high) == 0:
        return raw_high
    prev = np.concatenate([[st.last_raw_high], raw_high[:-1]])
    wraps = np.cumsum((raw_high < prev) & (prev >= 0))
    base = st.time_high - (st.last_raw_high if st.last_raw_high >= 0 else 0)
    return base + raw_high + period * wraps


def _check_types(where: str, types: np.ndarray, known: tuple[int, ...], word_offset: int, word_bytes: int) -> None:
    table = np.zeros(16, dtype=bool)
    table[list(known)] = True
    bad = np.flatnonzero(~table[types])
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

    Each state (y, TIME_HIGH, TIME_LOW, vector base and polarity) is looked up only at the
    event words, as the value of the last word that set it (binary search over the setters).
    """
    typ = (words >> 12).astype(np.intp)
    _check_types(where, typ, (0x0, 0x2, 0x3, 0x4, 0x5, 0x6, 0x7, 0x8, 0xA, 0xE, 0xF), byte_offset, 2)
    payload = (words & 0xFFF).astype(np.int64)
    is_x, is_v12, is_v8 = typ == 0x2, typ == 0x4, typ == 0x5
    y_w, base_w = np.flatnonzero(typ == 0x0), np.flatnonzero(typ == 0x3)
    tl_w, th_w = np.flatnonzero(typ == 0x6), np.flatnonzero(typ == 0x8)
    rel = np.flatnonzero(is_x | is_v12 | is_v8)

    th_unwrapped = _unwrap_time_high(payload[th_w], st, 1 << 12)
    time_high = _state_at(th_w, th_unwrapped, rel, st.time_high)
    time_low = _state_at(tl_w, payload[tl_w], rel, st.time_low)
    t = (time_high << 12) | time_low
    y = _state_at(y_w, payload[y_w] & 0x7FF, rel, st.y)

    # Vector base: the last VECT_BASE_X plus 12 / 8 for every vector word since then.
    inc = np.where(is_v12[rel], 12, 0) + np.where(is_v8[rel], 8, 0)
    done = np.concatenate([[0], np.cumsum(inc)])  # done[j]: increments of event words before j
    base_val = _state_at(base_w, payload[base_w] & 0x7FF, rel, st.base_x)
    if len(base_w):
        k = _last_setter(base_w, rel)
        done_at_base = done[np.searchsorted(rel, base_w, side="right")]  # increments before each base word
        since = done[:-1] - np.where(k >= 0, done_at_base[np.maximum(k, 0)], 0)
    else:
        since = done[:-1]
    base_x = base_val + since
    vect_pol = _state_at(base_w, payload[base_w] >> 11, rel, st.vect_pol)

    p_rel = payload[rel]
    is_x_rel = is_x[rel]
    mask = np.where(is_x_rel, 1, np.where(is_v12[rel], p_rel, p_rel & 0xFF))
    valid = ((mask[:, None] >> np.arange(12)) & 1).astype(bool)
    x0 = np.where(is_x_rel, p_rel & 0x7FF, base_x)
    pol = np.where(is_x_rel, p_rel >> 11, vect_pol)
    r, b = np.nonzero(valid)
    x = x0[r] + b
    if len(x) and x.max() > 65535:  # only reachable with corrupt vector words
        i = int(np.argmax(x > 65535))
        raise FormatError(
            f"{where}: vector event x={int(x[i])} at byte offset {byte_offset + 2 * int(rel[r[i]])} is not a pixel"
        )
    ev = np.empty(len(r), dtype=EVENT_DTYPE)
    ev["x"] = x
    ev["y"] = y[r]
    ev["t"] = t[r]
    ev["p"] = np.where(pol[r] > 0, 1, -1)

    # State after the block.
    if len(th_w):
        st.time_high, st.last_raw_high = int(th_unwrapped[-1]), int(payload[th_w[-1]])
    if len(tl_w):
        st.time_low = int(payload[tl_w[-1]])
    if len(y_w):
        st.y = int(payload[y_w[-1]] & 0x7FF)
    if len(base_w):
        last = int(base_w[-1])
        st.base_x = int(payload[last] & 0x7FF)
        st.vect_pol = int(payload[last] >> 11)
        after = rel > last
    else:
        after = np.ones(len(rel), dtype=bool)
    st.base_x += int(inc[after].sum())
    return ev, rel[r]


def decode_evt2(words: np.ndarray, st: _State, where: str, byte_offset: int) -> tuple[np.ndarray, np.ndarray]:
    """Decode a block of EVT 2.0 uint32 words (see :func:`decode_evt3` for the contract)."""
    typ = (words >> 28).astype(np.intp)
    _check_types(where, typ, (0x0, 0x1, 0x8, 0xA, 0xE, 0xF), byte_offset, 4)
    th_w = np.flatnonzero(typ == 0x8)
    cd = np.flatnonzero(typ <= 1)
    th_unwrapped = _unwrap_time_high(words[th_w] & 0x0FFFFFFF, st, 1 << 28)
    time_high = _state_at(th_w, th_unwrapped, cd, st.time_high)
    wc = words[cd].astype(np.int64)
    ev = np.empty(len(cd), dtype=EVENT_DTYPE)
    ev["t"] = (time_high << 6) | ((wc >> 22) & 0x3F)
    ev["x"] = (wc >> 11) & 0x7FF
    ev["y"] = wc & 0x7FF
    ev["p"] = np.where(typ[cd] == 1, 1, -1)
    if len(th_w):
        st.time_high, st.last_raw_high = int(th_unwrapped[-1]), int(words[th_w[-1]] & 0x0FFFFFFF)
    return ev, cd


def header_of(path: Path, where: str) -> tuple[dict[str, str], int]:
    """:func:`read_header` of the file at ``path``; errors are prefixed with ``where``."""
    with open(path, "rb") as f:
        try:
            return read_header(f)
        except FormatError as exc:
            raise FormatError(f"{where}: {exc}") from None


def read_blocks(path: Path, offset: int, block_bytes: int) -> Iterator[tuple[int, bytes]]:
    """``(byte offset, bytes)`` of consecutive blocks of ``block_bytes`` from ``offset`` to the
    end of the file (the last block may be shorter)."""
    with open(path, "rb") as f:
        f.seek(offset)
        while buf := f.read(block_bytes):
            yield offset, buf
            offset += len(buf)


class RawSource:
    """Streaming decoder of one Prophesee ``.raw`` file."""

    def __init__(self, path: Path, format: str) -> None:
        self.path = path
        self.format = format
        self.calibration = None
        self.t_offset_us = 0
        self._where = where = f"{path}: {format}"
        fields, self._data_offset = header_of(path, where)
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
        for base, buf in read_blocks(self.path, self._data_offset, chunk_events * self._word_bytes):
            ev, word = decode(np.frombuffer(buf, dtype=dtype), st, self._where, base)
            yield Chunk(ev, lambda i, word=word, base=base: f"byte offset {base + self._word_bytes * int(word[i])}")

    def close(self) -> None:
        pass


def open_source(path: Path, format: str) -> RawSource:
    return RawSource(path, format)
