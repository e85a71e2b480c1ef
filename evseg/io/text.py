"""Text recordings: ``t x y p`` per line (RPG / EMSGC ``events.txt``) and csv.

Layout:

* optional comment lines starting with ``#`` or ``%`` and blank lines (skipped everywhere);
* optional first line ``width height`` (two integers): the sensor size;
* optional csv header naming the columns (``t``/``ts``/``timestamp``/``time``, ``x``, ``y``,
  ``p``/``pol``/``polarity``/``on``; a ``_s``, ``_ms``, ``_us`` or ``_ns`` suffix on the time
  column sets its unit); without a header the columns are ``t x y p``;
* one event per line, separated by whitespace, commas or semicolons (decided by the first data
  line). Spreadsheet and pandas exports read as they are: a UTF-8 byte-order mark, quoted
  header names, a trailing separator, and columns the header leaves unnamed (pandas' index)
  or names otherwise (ignored), and a polarity written ``True`` / ``False`` (a boolean column).

Time unit: seconds when any of the first 1,000 time values has a decimal point or exponent,
microseconds otherwise (``time_unit=`` ``"s"``, ``"ms"``, ``"us"`` or ``"ns"``, or a header
suffix, overrides). A guess
of microseconds that a later line contradicts (a time with a fraction) is an error naming the
line, never a silent rounding. Seconds are converted with ``rint(t * 1e6)``, exact to the
microsecond for ``|t| < 2**31`` s (float64 keeps 0.25 us there). Polarity 0/-1 is OFF.

Reading is chunked: blocks of ``chunk_events`` lines parsed by numpy; error messages give the
line number.
"""

from __future__ import annotations

import io
import itertools
from pathlib import Path
from typing import Iterator

import numpy as np

from evseg.errors import FormatError
from evseg.events import EVENT_DTYPE, EventStream
from evseg.io._atomic import atomic_path
from evseg.io.numpy_files import (TIME_NAMES, US_PER_TIME_UNIT, check_time_unit, implausible_time_problem,
                                  time_unit_of)
from evseg.io.recording import Chunk

_ALIASES = {
    "t": TIME_NAMES,
    "x": ("x",),
    "y": ("y",),
    "p": ("p", "pol", "polarity", "on"),
}


_UNIT_SAMPLE_LINES = 1000
"""Data lines whose time column decides seconds vs microseconds when nothing else does."""


def _has_fraction_syntax(toks: list[bytes], column: int) -> bool:
    """Whether the time token is written with a decimal point or an exponent."""
    if column >= len(toks):
        return False
    tok = toks[column].strip().lower()
    return b"." in tok or b"e" in tok


_BOM = b"\xef\xbb\xbf"
"""UTF-8 byte-order mark, which spreadsheet programs put at the start of a csv."""


def _tokens(line: bytes) -> list[bytes]:
    """Fields of a line whatever its separator (for telling numbers from a header)."""
    return line.replace(b",", b" ").replace(b";", b" ").split()


def _split(line: bytes, delimiter: str | None) -> list[bytes]:
    return line.split(delimiter.encode()) if delimiter else line.split()


def _is_number(tok: bytes) -> bool:
    try:
        float(tok)
    except ValueError:
        return False
    return True


def _is_bool(tok: bytes) -> bool:
    """``True`` / ``False`` in any case: how pandas writes a boolean polarity column."""
    return tok.strip().lower() in (b"true", b"false")


def _polarity_value(tok: str | bytes) -> float:
    """A polarity token as a number: ``True`` / ``False`` (any case) as 1 / 0, else the number.
    (numpy 2's loadtxt hands converters str, numpy 1's bytes.)"""
    low = (tok.decode("ascii", "replace") if isinstance(tok, bytes) else tok).strip().lower()
    return 1.0 if low == "true" else 0.0 if low == "false" else float(tok)


class TextSource:
    """Streaming reader of one text/csv file (see module docstring)."""

    format = "text"

    def __init__(self, path: Path, format: str = "text", time_unit: str | None = None) -> None:
        check_time_unit(time_unit, f"{path}: text")
        self.path = path
        self.calibration = None
        self.t_offset_us = 0
        self.sensor_size: tuple[int, int] | None = None
        self._where = f"{path}: text"
        self._columns = [0, 1, 2, 3]  # positions of t, x, y, p
        self._ncols = 4
        self._delimiter: str | None = None
        self._strip_trailing: bytes | None = None  # a separator every line ends with (header "t,x,y,p,")
        self._unit = time_unit
        self._unit_guessed = False  # microseconds guessed from the first lines: checked on every line
        self._unit_inferred = False  # the unit was guessed (not given, no suffix): times beyond 2100 refused
        self._data_start = 0  # number of lines before the first data line
        self._scan_header()

    def _lines(self):
        """(line number from 1, raw line) of non-blank, non-comment lines."""
        with open(self.path, "rb") as f:
            for n, line in enumerate(f, start=1):
                if n == 1 and line.startswith(_BOM):
                    line = line[len(_BOM):]
                s = line.strip()
                if b"\r" in s:
                    raise FormatError(
                        f"{self._where}: line {n}: a carriage return (\\r) inside the line: the file ends its lines "
                        "with CR alone (classic Mac); convert them to \\n first, e.g. tr '\\r' '\\n' < in.txt > out.txt")
                if s and not s.startswith((b"#", b"%")):
                    if self._strip_trailing is not None and s.endswith(self._strip_trailing):
                        s = s[:-1].rstrip()
                    yield n, s

    def _scan_header(self) -> None:
        first = list(itertools.islice(self._lines(), 3))
        if not first:
            raise FormatError(f"{self._where}: no events (only blank or comment lines)")
        i = 0
        n, line = first[0]
        toks = _tokens(line)
        if len(toks) == 2 and all(t.isdigit() for t in toks):
            self.sensor_size = (int(toks[0]), int(toks[1]))
            if min(self.sensor_size) <= 0:
                raise FormatError(f"{self._where}: line {n}: sensor size must be positive, got {line!r}")
            self._data_start = n
            i = 1
        if i < len(first) and not all(_is_number(t) or _is_bool(t) for t in _tokens(first[i][1])):
            n, line = first[i]
            self._parse_column_names(n, line)
            self._data_start = n
            i += 1
            first = list(itertools.islice(self._lines(), 3))  # again, with a trailing separator stripped
        if i >= len(first):
            return  # a header and no events: an empty recording
        n, line = first[i]
        self._delimiter = "," if b"," in line else ";" if b";" in line else None
        toks = _split(line, self._delimiter)
        if len(toks) != self._ncols:
            raise FormatError(
                f"{self._where}: line {n}: expected {self._ncols} columns (t x y p), got {len(toks)}: "
                f"{line[:80]!r}"
            )
        if self._unit is None:
            # One line is not enough: a file written with %g starts "0 x y p" in seconds.
            sample = itertools.islice(itertools.dropwhile(lambda nl: nl[0] <= self._data_start, self._lines()),
                                      _UNIT_SAMPLE_LINES)
            seconds = any(_has_fraction_syntax(_split(ln, self._delimiter), self._columns[0]) for _, ln in sample)
            self._unit = "s" if seconds else "us"
            self._unit_guessed = not seconds
            self._unit_inferred = True

    def _parse_column_names(self, n: int, line: bytes) -> None:
        try:
            text = line.decode("ascii")
        except UnicodeDecodeError:
            raise FormatError(f"{self._where}: line {n}: not ASCII text") from None
        sep = "," if "," in text else ";" if ";" in text else None
        # Split on the separator itself, so that an unnamed column (pandas' index) still counts.
        names = [t.strip().strip("\"'").strip().lower() for t in (text.split(sep) if sep else text.split())]
        if sep is not None and len(names) > 1 and names[-1] == "":
            self._strip_trailing = sep.encode()  # "t,x,y,p," and "1,2,3,4,"
            names = names[:-1]
        known = {a for aliases in _ALIASES.values() for a in aliases}
        if sum(nm in known for nm in names) < 4:
            raise FormatError(
                f"{self._where}: line {n}: expected 't x y p' numbers or a csv header naming the "
                f"t, x, y, p columns, got {line[:80]!r}"
            )
        cols = []
        for key in "txyp":
            hits = [i for i, nm in enumerate(names) if nm in _ALIASES[key]]
            if len(hits) != 1:
                raise FormatError(
                    f"{self._where}: line {n}: header {names} must name exactly one '{key}' column "
                    f"(accepted: {', '.join(_ALIASES[key])})"
                )
            cols.append(hits[0])
        self._columns, self._ncols = cols, len(names)
        if self._unit is None:
            self._unit = time_unit_of(names[cols[0]])

    def chunks(self, chunk_events: int) -> Iterator[Chunk]:
        lines = self._lines()
        # Skip the header lines.
        lines = itertools.dropwhile(lambda nl: nl[0] <= self._data_start, lines)
        while True:
            block = list(itertools.islice(lines, chunk_events))
            if not block:
                return
            numbers = np.fromiter((n for n, _ in block), dtype=np.int64, count=len(block))
            yield Chunk(self._parse_block(block, numbers), lambda i, nums=numbers: f"line {nums[i]}")

    def _parse_block(self, block: list[tuple[int, bytes]], numbers: np.ndarray) -> np.ndarray:
        try:
            text = b"\n".join(line for _, line in block).decode("ascii")
        except UnicodeDecodeError:
            for n, line in block:
                try:
                    line.decode("ascii")
                except UnicodeDecodeError as exc:
                    raise FormatError(
                        f"{self._where}: line {n}: not ASCII text (byte {line[exc.start]:#04x})"
                    ) from None
            raise  # pragma: no cover - the loop above always finds the line
        try:
            a = np.loadtxt(io.StringIO(text), delimiter=self._delimiter, dtype=np.float64, ndmin=2,
                           converters={self._columns[3]: _polarity_value})  # as fast as without (numpy 2)
        except ValueError:
            self._raise_bad_line(block)
        if a.shape[1] != self._ncols:
            self._raise_bad_line(block)
        t, x, y, p = (a[:, c] for c in self._columns)
        for name, col in (("t", t), ("x", x), ("y", y), ("p", p)):
            bad = np.flatnonzero(~np.isfinite(col))
            if len(bad):
                i = int(bad[0])
                raise FormatError(f"{self._where}: line {numbers[i]}: field '{name}' is {col[i]} (not finite)")
        for name, col in (("x", x), ("y", y)):
            bad = np.flatnonzero((col != np.floor(col)) | (col < 0) | (col > 65535))
            if len(bad):
                i = int(bad[0])
                raise FormatError(
                    f"{self._where}: line {numbers[i]}: field '{name}' = {col[i]} is not a pixel "
                    "coordinate (an integer in 0..65535)"
                )
        bad = np.flatnonzero((p != 0) & (p != 1) & (p != -1))
        if len(bad):
            i = int(bad[0])
            raise FormatError(f"{self._where}: line {numbers[i]}: field 'p' = {p[i]} is not 0, 1 or -1")
        if self._unit_guessed:
            bad = np.flatnonzero(t != np.floor(t))
            if len(bad):
                i = int(bad[0])
                raise FormatError(
                    f"{self._where}: line {numbers[i]}: field 't' = {float(t[i])!r} has a fraction, but the first "
                    f"{_UNIT_SAMPLE_LINES} times are whole numbers, so the time unit was taken as microseconds; "
                    "pass --time-unit s (time_unit='s') if the times are seconds, --time-unit us to round them"
                )
        t_us = t * US_PER_TIME_UNIT[self._unit] if self._unit != "us" else t
        bad = np.flatnonzero(np.abs(t_us) > 2**62)
        if len(bad):
            i = int(bad[0])
            raise FormatError(f"{self._where}: line {numbers[i]}: field 't' = {t[i]} is out of range")
        if self._unit_inferred:
            problem = implausible_time_problem(t_us, t, self._unit, self._where, lambda i: f"line {numbers[i]}")
            if problem:
                raise FormatError(problem)
        ev = np.empty(len(a), dtype=EVENT_DTYPE)
        ev["t"] = np.rint(t_us).astype(np.int64)
        ev["x"] = x
        ev["y"] = y
        ev["p"] = np.where(p > 0, 1, -1)
        return ev

    def _raise_bad_line(self, block: list[tuple[int, bytes]]):
        for n, line in block:
            toks = _split(line, self._delimiter)
            if len(toks) != self._ncols:
                raise FormatError(
                    f"{self._where}: line {n}: expected {self._ncols} columns, got {len(toks)}: {line[:80]!r}"
                )
            for j, tok in enumerate(toks):
                if not (_is_number(tok) or (j == self._columns[3] and _is_bool(tok))):
                    raise FormatError(f"{self._where}: line {n}: {tok[:40]!r} is not a number")
        raise FormatError(f"{self._where}: lines {block[0][0]}-{block[-1][0]}: cannot parse as numbers")

    def close(self) -> None:
        pass


def open_source(path: Path, format: str = "text", time_unit: str | None = None) -> TextSource:
    return TextSource(path, format, time_unit)


def write_text(stream: EventStream, path: str | Path) -> Path:
    """Write ``width height`` then ``t x y p`` lines (t absolute seconds, 6 decimals; p 1/0).

    Atomic; :func:`evseg.io.read_events` gives back the same absolute times (its
    ``t_offset_us`` is 0), coordinates and polarities.
    """
    ev = stream.events
    t_abs = ev["t"].astype(np.int64) + int(stream.t_offset_us)
    cols = np.stack(
        [t_abs // 1_000_000, t_abs % 1_000_000, ev["x"], ev["y"], (ev["p"] > 0)], axis=1
    ).astype(np.int64)
    path = Path(path)
    with atomic_path(path) as tmp:
        with open(tmp, "w") as f:
            f.write(f"{stream.width} {stream.height}\n")
            np.savetxt(f, cols, fmt="%d.%06d %d %d %d")
    return path
