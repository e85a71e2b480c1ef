"""DSEC-style HDF5 recordings: ``events/{x,y,t,p}``, ``t_offset``, ``ms_to_idx``.

Layout (as DSEC's ``events.h5``):

* ``events/x``, ``events/y`` (uint16), ``events/t`` (int64 us relative to ``t_offset``),
  ``events/p`` (uint8 0/1; also read: -1/+1 or bool);
* ``t_offset`` (int64 scalar, us): absolute time of ``t == 0`` (0 when absent);
* ``ms_to_idx`` (uint64): ``ms_to_idx[k]`` is the index of the first event with
  ``t >= 1000 k`` (written by evseg; not needed for reading);
* sensor size, when known, as root attributes ``width`` and ``height`` (DSEC files lack them:
  pass ``--sensor-size 640x480`` or let it be inferred).

Blosc-compressed files (DSEC) need ``hdf5plugin``, imported here. Reading slices the
datasets chunk by chunk, so memory stays bounded.
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterable, Iterator

import numpy as np

from evseg.errors import FormatError
from evseg.events import EventStream
from evseg.io._atomic import atomic_path
from evseg.io.numpy_files import columns_to_events
from evseg.io.recording import Chunk


def _h5():
    import h5py
    import hdf5plugin  # noqa: F401  (registers the Blosc filter DSEC files use)

    return h5py


class H5Source:
    format = "h5"

    def __init__(self, path: Path) -> None:
        h5py = _h5()
        self.path = path
        self._where = where = f"{path}: h5"
        self.calibration = None
        try:
            self._f = h5py.File(path, "r")
        except OSError as exc:
            raise FormatError(f"{where}: corrupt or truncated HDF5 file ({exc})") from None
        try:
            self._open(where)
        except FormatError:
            self.close()
            raise
        except Exception as exc:  # h5py maps damaged metadata to KeyError, OSError, RuntimeError...
            self.close()
            raise FormatError(f"{where}: corrupt HDF5 structure ({type(exc).__name__}: {exc})") from None

    def _open(self, where: str) -> None:
        f = self._f
        h5py = _h5()
        if "events" in f and isinstance(f["events"], h5py.Dataset):
            d = f["events"]
            raise FormatError(
                f"{where}: 'events' is a dataset of shape {d.shape} dtype {d.dtype}, not the DSEC group "
                "events/{x,y,t,p} this reader takes; save the columns as an .npy N x 4 [t, x, y, p] "
                "(integer t: us, float t: s), which evseg reads")
        try:
            g = f["events"]
            names = list(g.keys())
        except (KeyError, OSError, TypeError, AttributeError) as exc:
            raise FormatError(f"{where}: no readable group 'events' ({exc}; top-level keys: {list(f.keys())})") from None
        missing = [k for k in "xytp" if k not in names]
        if missing:
            raise FormatError(f"{where}: group 'events' lacks datasets {missing} (has {names})")
        self._ds = {k: g[k] for k in "xytp"}
        for k, d in self._ds.items():
            # Column vectors (N, 1), as MATLAB and some exporters write them, read as (N,).
            if not isinstance(d, h5py.Dataset) or not (len(d.shape) == 1 or (len(d.shape) == 2 and d.shape[1] == 1)):
                shape = getattr(d, "shape", "a group")
                raise FormatError(f"{where}: dataset 'events/{k}' must be one column of N values, got shape {shape}")
        n = {k: d.shape[0] if d.shape else -1 for k, d in self._ds.items()}
        if len(set(n.values())) != 1 or n["x"] < 0:
            raise FormatError(f"{where}: datasets events/x,y,t,p have different lengths {n}")
        self._n = n["x"]
        try:
            off = np.asarray(f["t_offset"][()]) if "t_offset" in f else np.zeros(1, np.int64)
            if off.size != 1 or off.dtype.kind not in "iuf" or (off.dtype.kind == "f" and off.item() != int(off.item())):
                raise ValueError(f"got {off.size} value(s) of dtype {off.dtype}: {off.ravel()[:3].tolist()}")
            self.t_offset_us = int(off.reshape(()))
        except (OSError, TypeError, ValueError) as exc:
            raise FormatError(f"{where}: dataset 't_offset' is not an integer scalar ({exc})") from None
        attrs = f.attrs
        self.sensor_size = None
        if "width" in attrs and "height" in attrs:
            self.sensor_size = (int(attrs["width"]), int(attrs["height"]))
        if "K" in f and "D" in f and self.sensor_size is not None:
            from evseg.calibration import Calibration
            from evseg.errors import CalibrationError

            try:
                model = attrs.get("distortion_model", "radtan")  # absent in older files: radtan
                model = model.decode() if isinstance(model, bytes) else str(model)
                self.calibration = Calibration(f["K"][()], f["D"][()], self.sensor_size, model)
            except (CalibrationError, OSError, ValueError) as exc:
                raise FormatError(f"{where}: datasets 'K'/'D' (attribute 'distortion_model'): {exc}") from None

    def time_span_us(self) -> tuple[int, int] | None:
        """Times (us) of the first and last events, read from the ends of ``events/t``; None
        when empty or unreadable (the chunks then report the problem)."""
        if self._n == 0:
            return None
        try:
            ends = [columns_to_events(*(self._read(k, i, i + 1) for k in "txyp"), "", i)["t"][0]
                    for i in (0, self._n - 1)]
        except (FormatError, OSError, ValueError, KeyError):
            return None
        return int(ends[0]), int(ends[1])

    def chunks(self, chunk_events: int) -> Iterator[Chunk]:
        for i in range(0, self._n, chunk_events):
            j = min(self._n, i + chunk_events)
            try:
                cols = {k: self._read(k, i, j) for k in self._ds}
            except Exception as exc:  # damaged chunks surface as OSError, ValueError, KeyError...
                raise FormatError(
                    f"{self._where}: cannot read events {i}..{j - 1} (corrupt data: {type(exc).__name__}: {exc})"
                ) from None
            yield Chunk(columns_to_events(cols["t"], cols["x"], cols["y"], cols["p"], self._where, i))

    def _read(self, key: str, i: int, j: int) -> np.ndarray:
        """Events i..j-1 of column ``key`` as a 1-D array."""
        d = self._ds[key]
        return d[i:j, 0] if d.ndim == 2 else d[i:j]

    def close(self) -> None:
        try:
            self._f.close()
        except Exception:  # closing a file h5py already found corrupt must not mask the error
            pass


def open_source(path: Path, format: str = "h5") -> H5Source:
    return H5Source(path)


def write_h5_chunks(chunks: Iterable[np.ndarray], path: str | Path, meta) -> Path:
    """Stream event chunks into a DSEC-style HDF5 file (bounded memory), atomically.

    ``meta`` is called after the last chunk and returns ``(sensor_size, t_offset_us,
    calibration)``; the calibration, when present, is stored as root datasets ``K`` and ``D``.
    Data are Blosc/zstd compressed (lossless), as in DSEC.
    """
    import hdf5plugin

    h5py = _h5()
    path = Path(path)
    comp = hdf5plugin.Blosc(cname="zstd", clevel=3, shuffle=hdf5plugin.Blosc.SHUFFLE)
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as f:
            g = f.create_group("events")
            dtypes = {"x": np.uint16, "y": np.uint16, "t": np.int64, "p": np.uint8}
            ds = {k: g.create_dataset(k, shape=(0,), maxshape=(None,), dtype=dt, chunks=(1 << 16,), **comp)
                  for k, dt in dtypes.items()}
            n = 0
            ms_idx: list[np.ndarray] = []
            next_ms = 0
            for c in chunks:
                if len(c) == 0:
                    continue
                for k in "xyt":
                    ds[k].resize((n + len(c),))
                    ds[k][n:] = c[k]
                ds["p"].resize((n + len(c),))
                ds["p"][n:] = (c["p"] > 0).astype(np.uint8)
                last_ms = int(c["t"][-1]) // 1000
                if last_ms >= next_ms:
                    ms = np.arange(next_ms, last_ms + 1, dtype=np.int64)
                    ms_idx.append(n + np.searchsorted(c["t"], ms * 1000, side="left"))
                    next_ms = last_ms + 1
                n += len(c)
            f.create_dataset("ms_to_idx", data=np.concatenate(ms_idx).astype(np.uint64) if ms_idx
                             else np.zeros(0, np.uint64))
            sensor_size, t_offset_us, calibration = meta()
            f.create_dataset("t_offset", data=np.int64(t_offset_us))
            if sensor_size is not None:
                f.attrs["width"], f.attrs["height"] = int(sensor_size[0]), int(sensor_size[1])
            if calibration is not None:
                f.create_dataset("K", data=calibration.K)
                f.create_dataset("D", data=calibration.D)
                f.attrs["distortion_model"] = calibration.model
    return path


def write_h5(stream: EventStream, path: str | Path) -> Path:
    """Write ``stream`` as DSEC-style HDF5 (see :func:`write_h5_chunks`), atomically."""
    return write_h5_chunks(
        [stream.events], path, lambda: (stream.sensor_size, stream.t_offset_us, stream.calibration)
    )
