"""numpy recordings (.npy, .npz) and the project's own .npz writer.

Layouts read:

* a structured array (alone in an ``.npy``, or under the key ``events`` of an ``.npz``) with
  fields ``x``, ``y``, a time field (``t``/``ts``/``timestamp``/``time``) and a polarity field
  (``p``/``pol``/``polarity``/``on``; bool, 0/1 or -1/+1), as the EED excerpt
  ``events_t_us_x_y_on.npy``;
* an N x 4 array ``[t, x, y, p]`` (alone in an ``.npy`` or under ``events``), as the ECD poster
  files of ``ecd_poster``;
* an ``.npz`` with column keys ``x``, ``y``, ``t`` (or an alias above) and ``p`` (or alias).

Time unit: integer time fields are microseconds, floating-point ones seconds
(``rint(t * 1e6)``), except that a ``_us`` / ``_s`` suffix on the time field's name
(``t_us``, ``timestamp_s``, ...) says the unit whatever the dtype. Other keys of an ``.npz`` are ignored except ``sensor_size`` (or
``width`` and ``height``), ``t_offset_us`` and the calibration ``K`` (3x3) and ``D`` (radtan;
absent: no distortion),
exposed as :attr:`Recording.calibration` (its sensor size is the declared one, else max + 1).

``.npy`` files are memory-mapped (streaming from disk); an ``.npz`` member is loaded whole
(zip members cannot be memory-mapped), then sliced into chunks.
"""

from __future__ import annotations

import shutil
import tempfile
import zipfile
from pathlib import Path
from typing import Callable, Iterable, Iterator

import numpy as np

from evseg.errors import FormatError
from evseg.events import EVENT_DTYPE, EventStream
from evseg.io._atomic import atomic_path
from evseg.io.recording import Chunk

US_PER_TIME_UNIT = {"s": 1e6, "ms": 1e3, "us": 1.0, "ns": 1e-3}
"""Microseconds per unit of the time units the readers take (``time_unit=``, ``--time-unit``)."""

_TIME_BASES = ("t", "ts", "timestamp", "time")
TIME_NAMES = _TIME_BASES + tuple(f"{b}_{u}" for b in _TIME_BASES for u in US_PER_TIME_UNIT)
"""Names of the time column, in order of preference; a unit suffix sets the unit (:func:`time_unit_of`)."""
POLARITY_NAMES = ("p", "pol", "polarity", "on")


def _pick(names: Iterable[str], wanted: tuple[str, ...]) -> str | None:
    names = list(names)
    for w in wanted:
        if w in names:
            return w
    return None


def _field_names(a: np.ndarray) -> list[str]:
    """Field names and titles of a structured array (EED's npy titles 'on' as 'p')."""
    names = list(a.dtype.names or ())
    titles = [v[2] for v in a.dtype.fields.values() if len(v) > 2 and isinstance(v[2], str)]
    return names + titles


def time_unit_of(name: str) -> str | None:
    """The unit of a time column named with a unit suffix (``_s``, ``_ms``, ``_us``, ``_ns``),
    else None (decided by dtype).

    >>> time_unit_of("timestamp_us"), time_unit_of("t_s"), time_unit_of("t_ns"), time_unit_of("t")
    ('us', 's', 'ns', None)
    """
    for unit in US_PER_TIME_UNIT:
        if name.endswith("_" + unit):
            return unit
    return None


LATEST_PLAUSIBLE_US = 4_102_444_800_000_000
"""2100-01-01 in microseconds since the Unix epoch. A time read beyond it (absolute or relative)
is in another unit than the one assumed: epoch nanoseconds read as microseconds, epoch
milliseconds read as seconds."""


def implausible_time_problem(t_us: np.ndarray, t: np.ndarray, unit: str, where: str,
                             first: Callable[[int], str]) -> str | None:
    """The message for the first time of ``t_us`` (us, converted from ``t`` read as ``unit``)
    beyond :data:`LATEST_PLAUSIBLE_US`, or None. ``first`` names its position (``event 12``)."""
    if not len(t_us):
        return None
    bad = np.flatnonzero(np.abs(t_us) > LATEST_PLAUSIBLE_US)
    if not len(bad):
        return None
    i = int(bad[0])
    others = "/".join(u for u in US_PER_TIME_UNIT if u != unit)
    return (f"{where}: field 't' = {t[i]} at {first(i)} read as {unit} is after the year 2100: the times are in "
            f"another unit; give it (--time-unit {others}, time_unit=..., or a unit suffix such as t_ns)")


def check_time_unit(time_unit: str | None, where: str) -> None:
    """Raise :class:`FormatError` unless ``time_unit`` is None or one of :data:`US_PER_TIME_UNIT`."""
    if time_unit is not None and time_unit not in US_PER_TIME_UNIT:
        raise FormatError(f"{where}: time_unit must be one of {', '.join(map(repr, US_PER_TIME_UNIT))}, "
                          f"got {time_unit!r}")


def columns_to_events(
    t: np.ndarray, x: np.ndarray, y: np.ndarray, p: np.ndarray, where: str, first_index: int = 0,
    time_unit: str | None = None,
) -> np.ndarray:
    """Convert decoded columns to :data:`EVENT_DTYPE`, checking values.

    ``t`` is in ``time_unit`` (a key of :data:`US_PER_TIME_UNIT`; converted to microseconds and
    rounded to whole ones); None: microseconds when integer, seconds when floating point. Raises
    :class:`FormatError` naming ``where`` and the event index of the first NaN/inf,
    non-integer or negative coordinate, or polarity outside {0, 1, -1, True, False}.
    """
    cols = {"t": np.asarray(t), "x": np.asarray(x), "y": np.asarray(y), "p": np.asarray(p)}
    for name, c in cols.items():
        if c.dtype.kind not in "biuf":
            raise FormatError(f"{where}: field '{name}' has non-numeric dtype {c.dtype}")
        if c.dtype.kind == "f":
            bad = np.flatnonzero(~np.isfinite(c))
            if len(bad):
                i = int(bad[0])
                raise FormatError(f"{where}: field '{name}' is {c[i]} (not finite) at event {first_index + i}")
    for name in "xy":
        c = cols[name]
        if c.dtype.kind in "if":
            out = (c < 0) | (c > 65535)
            if c.dtype.kind == "f":
                out |= c != np.floor(c)
            bad = np.flatnonzero(out)
            if len(bad):
                i = int(bad[0])
                raise FormatError(
                    f"{where}: field '{name}' = {c[i]} at event {first_index + i} is not a pixel "
                    "coordinate (an integer in 0..65535)"
                )
    p = cols["p"]
    if p.dtype.kind != "b":
        bad = np.flatnonzero((p != 0) & (p != 1) & (p != -1))
        if len(bad):
            i = int(bad[0])
            raise FormatError(f"{where}: field 'p' = {p[i]} at event {first_index + i} is not 0, 1 or -1")
    t = cols["t"]
    unit = time_unit if time_unit is not None else "s" if t.dtype.kind == "f" else "us"
    if t.dtype.kind == "u" and len(t) and int(t.max()) > 2**63 - 1:
        i = int(np.argmax(t))
        raise FormatError(f"{where}: field 't' = {t[i]} at event {first_index + i} is out of range")
    if t.dtype.kind in "iub" and unit == "us":
        t_us = t
    elif t.dtype.kind in "iub" and unit == "ns":
        t_us = (t.astype(np.int64) + 500) // 1000  # exact: float64 would round epoch nanoseconds
    else:
        t_us = t.astype(np.float64) * US_PER_TIME_UNIT[unit]
        bad = np.flatnonzero(np.abs(t_us) > 2**62)
        if len(bad):
            i = int(bad[0])
            raise FormatError(f"{where}: field 't' = {t[i]} at event {first_index + i} is out of range")
    if time_unit is None:  # a guess from the dtype: check it
        problem = implausible_time_problem(t_us, t, unit, where, lambda i: f"event {first_index + i}")
        if problem:
            raise FormatError(problem)
    ev = np.empty(len(t), dtype=EVENT_DTYPE)
    ev["t"] = np.rint(t_us) if t_us.dtype.kind == "f" else t_us
    ev["x"] = cols["x"]
    ev["y"] = cols["y"]
    ev["p"] = np.where(p > 0, 1, -1) if p.dtype.kind != "b" else np.where(p, 1, -1)
    return ev


class ArraySource:
    """Chunks of an in-memory or memory-mapped array in one of the layouts above."""

    def __init__(self, path: Path, format: str, get_columns, n: int, sensor_size=None,
                 t_offset_us: int = 0, calibration_KD=None, time_unit: str | None = None) -> None:
        self.path = path
        self.time_unit = time_unit  # the user's, else from the time column's name; None: by dtype
        self.format = format
        self.sensor_size = sensor_size
        self.t_offset_us = int(t_offset_us)
        self._get = get_columns  # (start, stop) -> (t, x, y, p)
        self._n = n
        self.calibration = None
        if calibration_KD is not None:
            self.calibration = self._calibration(*calibration_KD)

    def _calibration(self, K, D, model="radtan"):
        from evseg.calibration import Calibration
        from evseg.errors import CalibrationError

        size = self.sensor_size
        if size is None:
            _, x, y, _ = self._get(0, self._n)
            size = (int(np.max(x)) + 1, int(np.max(y)) + 1) if self._n else (1, 1)
        try:
            return Calibration(np.asarray(K), np.asarray(D), size, str(model))
        except CalibrationError as exc:
            raise FormatError(f"{self.path}: {self.format}: keys 'K'/'D'/'distortion_model': {exc}") from None

    def time_span_us(self) -> tuple[int, int] | None:
        """Times (us) of the first and last rows, O(1); None when empty or unreadable (the
        chunks then report the problem)."""
        if self._n == 0:
            return None
        try:
            ends = [columns_to_events(*self._get(i, i + 1), "", first_index=i, time_unit=self.time_unit)["t"][0]
                    for i in (0, self._n - 1)]
        except FormatError:
            return None
        return int(ends[0]), int(ends[1])

    def chunks(self, chunk_events: int) -> Iterator[Chunk]:
        where = f"{self.path}: {self.format}"
        for start in range(0, self._n, chunk_events):
            stop = min(self._n, start + chunk_events)
            t, x, y, p = self._get(start, stop)
            yield Chunk(columns_to_events(t, x, y, p, where, first_index=start, time_unit=self.time_unit))

    def close(self) -> None:
        self._get = None


def _structured_getter(a: np.ndarray, where: str):
    names = _field_names(a)
    tn, pn = _pick(names, TIME_NAMES), _pick(names, POLARITY_NAMES)
    missing = [k for k, v in (("x", "x" in names), ("y", "y" in names), ("t", tn), ("p", pn)) if not v]
    if missing:
        raise FormatError(
            f"{where}: structured array with fields {names} lacks {missing} "
            f"(time: {'/'.join(TIME_NAMES)}; polarity: {'/'.join(POLARITY_NAMES)})"
        )
    getter = lambda i, j: (a[tn][i:j], a["x"][i:j], a["y"][i:j], a[pn][i:j])  # noqa: E731
    getter.time_unit = time_unit_of(tn)
    return getter


def _nx4_getter(a: np.ndarray, where: str):
    if a.ndim != 2 or a.shape[1] != 4:
        raise FormatError(
            f"{where}: expected a structured array or an N x 4 [t, x, y, p] array, got shape "
            f"{a.shape} dtype {a.dtype}"
        )
    return lambda i, j: (a[i:j, 0], a[i:j, 1], a[i:j, 2], a[i:j, 3])


def _array_getter(a: np.ndarray, where: str):
    return _structured_getter(a, where) if a.dtype.names else _nx4_getter(a, where)


def _load_npy(path: Path, where: str) -> np.ndarray:
    try:
        return np.load(path, mmap_mode="r", allow_pickle=False)
    except ValueError as exc:
        msg = str(exc)
        if "allow_pickle" in msg or "Object arrays" in msg or "Python objects" in msg:
            raise FormatError(f"{where}: holds Python objects (pickles), which evseg does not load") from None
        raise FormatError(f"{where}: corrupt .npy header or truncated data ({msg})") from None
    except Exception as exc:  # np.load's header parser raises many types (TokenError, SyntaxError, ...)
        raise FormatError(f"{where}: corrupt or truncated .npy ({type(exc).__name__}: {exc})") from None


def _npz_member(z, key: str, where: str) -> np.ndarray:
    try:
        return z[key]
    except ValueError as exc:
        if "allow_pickle" in str(exc):
            raise FormatError(f"{where}: key '{key}' holds Python objects (pickles), not loaded") from None
        raise FormatError(f"{where}: key '{key}' is corrupt or truncated ({exc})") from None
    except Exception as exc:  # zip and npy parsers raise many types (BadZipFile, zlib.error, ...)
        raise FormatError(f"{where}: key '{key}' is corrupt or truncated ({type(exc).__name__}: {exc})") from None


def _open_npz(path: Path, where: str) -> ArraySource:
    try:
        z = np.load(path, allow_pickle=False)
    except Exception as exc:  # BadZipFile, ValueError, OSError, EOFError, ...
        raise FormatError(f"{where}: not a readable zip archive ({type(exc).__name__}: {exc})") from None
    with z:
        keys = list(z.keys())
        sensor_size = None
        if "sensor_size" in keys:
            s = _npz_member(z, "sensor_size", where).ravel()
            if len(s) != 2:
                raise FormatError(f"{where}: key 'sensor_size' must hold [width, height], got {s.tolist()}")
            sensor_size = (int(s[0]), int(s[1]))
        elif "width" in keys and "height" in keys:
            sensor_size = (int(_npz_member(z, "width", where)), int(_npz_member(z, "height", where)))
        t_offset = int(_npz_member(z, "t_offset_us", where)) if "t_offset_us" in keys else 0
        kd = None
        if "D" in keys and "K" not in keys:
            raise FormatError(f"{where}: key 'D' (distortion) without the camera matrix 'K'; store both, or neither")
        if "K" in keys:
            # K alone: a pinhole camera without distortion.
            kd = (_npz_member(z, "K", where), _npz_member(z, "D", where) if "D" in keys else np.zeros(0))
            if "distortion_model" in keys:  # absent in files written before it existed: radtan
                model = _npz_member(z, "distortion_model", where)
                if model.size != 1 or model.dtype.kind not in "US":
                    raise FormatError(f"{where}: key 'distortion_model' must hold one string, got {model!r}")
                kd += (str(model.item().decode() if model.dtype.kind == "S" else model.item()),)
        if "events" in keys:
            a = _npz_member(z, "events", where)
            get, n = _array_getter(a, f"{where}: key 'events'"), len(a)
        else:
            tn, pn = _pick(keys, TIME_NAMES), _pick(keys, POLARITY_NAMES)
            missing = [k for k, v in (("x", "x" in keys), ("y", "y" in keys), ("t", tn), ("p", pn)) if not v]
            if missing:
                raise FormatError(
                    f"{where}: no 'events' key and no column keys {missing} (keys present: {keys})"
                )
            cols = {k: _npz_member(z, k, where).ravel() for k in ("x", "y", tn, pn)}
            n = len(cols["x"])
            for k, c in cols.items():
                if len(c) != n:
                    raise FormatError(f"{where}: column '{k}' has {len(c)} values, 'x' has {n}")
            get = lambda i, j: (cols[tn][i:j], cols["x"][i:j], cols["y"][i:j], cols[pn][i:j])  # noqa: E731
            get.time_unit = time_unit_of(tn)
    return ArraySource(path, "npz", get, n, sensor_size, t_offset, kd, getattr(get, "time_unit", None))


def open_source(path: Path, format: str, time_unit: str | None = None) -> ArraySource:
    """Open an .npy / .npz recording; ``time_unit`` (a key of :data:`US_PER_TIME_UNIT`), when
    given, is the unit of the time column whatever its name or dtype says."""
    where = f"{path}: {format}"
    check_time_unit(time_unit, where)
    if format == "npz":
        source = _open_npz(path, where)
    else:
        a = _load_npy(path, where)
        get = _array_getter(a, where)
        source = ArraySource(path, "npy", get, len(a) if a.ndim else 0, time_unit=getattr(get, "time_unit", None))
    if time_unit is not None:
        source.time_unit = time_unit
    return source


def write_npz_chunks(
    chunks: Iterable[np.ndarray],
    path: str | Path,
    meta,
) -> Path:
    """Stream event chunks into an .npz (bounded memory), atomically.

    Args:
        chunks: :data:`EVENT_DTYPE` arrays in order.
        path: output file.
        meta: called after the last chunk, returns ``(sensor_size, t_offset_us, calibration)``
            (so a sensor size inferred during the pass can be written).

    Layout: ``events`` (structured :data:`EVENT_DTYPE`), ``sensor_size`` [w, h] int64,
    ``t_offset_us`` int64, and ``K``, ``D`` when there is a calibration.
    """
    path = Path(path)
    if path.suffix.lower() != ".npz":
        # The readers pick the format by extension: another one would write a file evseg refuses.
        raise FormatError(f"{path}: an .npz recording must be named *.npz")
    with atomic_path(path) as tmp, tempfile.TemporaryDirectory(dir=path.parent) as work:
        raw = Path(work) / "events.bin"
        n = 0
        with open(raw, "wb") as f:
            for c in chunks:
                c = np.ascontiguousarray(c, dtype=EVENT_DTYPE)
                f.write(c.tobytes())
                n += len(c)
        sensor_size, t_offset_us, calibration = meta()
        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf:
            with zf.open("events.npy", "w", force_zip64=True) as member:
                header = {"descr": np.lib.format.dtype_to_descr(EVENT_DTYPE), "fortran_order": False,
                          "shape": (n,)}
                np.lib.format.write_array_header_2_0(member, header)
                with open(raw, "rb") as f:
                    shutil.copyfileobj(f, member, 1 << 22)
            extra = {"sensor_size": np.asarray(sensor_size, dtype=np.int64),
                     "t_offset_us": np.asarray(t_offset_us, dtype=np.int64)}
            if calibration is not None:
                extra["K"], extra["D"] = calibration.K, calibration.D
                extra["distortion_model"] = np.asarray(calibration.model)
            for key, arr in extra.items():
                with zf.open(f"{key}.npy", "w") as member:
                    np.lib.format.write_array(member, arr, allow_pickle=False)
    return path


def write_npz(stream: EventStream, path: str | Path) -> Path:
    """Write ``stream`` to ``path`` (.npz, layout of :func:`write_npz_chunks`), atomically."""
    return write_npz_chunks(
        [stream.events], path, lambda: (stream.sensor_size, stream.t_offset_us, stream.calibration)
    )


NPZ_MAGIC = b"PK\x03\x04"
NPY_MAGIC = b"\x93NUMPY"


def require_npz(path: Path, what: str, hint: str = "", allow_npy: bool = False) -> None:
    """Raise :class:`~evseg.errors.FormatError` naming ``path`` when it cannot be read or is not
    an .npz archive (or, with ``allow_npy``, an .npy file, which the caller refuses in its own
    words), rather than numpy's "pickled data" message for an HDF5 file or a recording.
    ``what``: the kind of file expected ("segmentation result"); ``hint``: more about it."""
    from evseg.errors import FormatError

    try:
        with open(path, "rb") as f:
            head = f.read(len(NPY_MAGIC))
    except OSError as exc:
        raise FormatError(f"{path}: cannot read {what} ({exc.strerror or exc})") from None
    if not head.startswith(NPZ_MAGIC) and not (allow_npy and head.startswith(NPY_MAGIC)):
        raise FormatError(f"{path}: not an .npz archive (a {what} is one{hint}; the file starts with {head[:4]!r})")
