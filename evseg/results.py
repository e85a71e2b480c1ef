"""Segmentation results on disk: the stable ``result.npz`` schema, written atomically.

Schema (all arrays; documented in the README):

==================  ==============  =====================================================
key                 dtype, shape    meaning
==================  ==============  =====================================================
``label``           int16 (N,)      one per input event in input order: -1 unassigned,
                                    0 background, k >= 1 object id (stable across windows)
``window_t0_us``    int64 (W,)      window start (us, time base of the recording)
``window_t1_us``    int64 (W,)      window end (exclusive)
``boxes``           int64 (B, 6)    rows ``(window index, object id, x0, y0, x1, y1)``,
                                    inclusive pixel bounds
``masks``           uint8 (B, P)    optional: per ``boxes`` row the object's dense mask,
                                    ``np.packbits`` of the (height, width) bool mask
``sensor_size``     int64 (2,)      (width, height)
``partial``         bool ()         True when the run stopped early (error, Ctrl-C): ``label``
                                    then holds the first ``n_events_processed`` events only
                                    (the later ones were not read; with ``--sort``: all events,
                                    -1 after the first ones in time order)
``n_events_processed`` int64 ()     events covered by processed windows
``config``          str ()          the effective configuration, as YAML
``t_offset_us``     int64 ()        absolute time (us) of t = 0 of the recording (ROS / DSEC
                                    epoch times), so ``window_t0_us + t_offset_us`` is absolute
==================  ==============  =====================================================

The writer streams ``label`` (and ``masks``) to temporary files as windows arrive and keeps
window times and boxes as packed int64 (48 bytes per box), so memory stays bounded however
long the recording; :meth:`ResultWriter.close` assembles the npz next to the target
and renames it into place, so a reader never sees a half-written file.
"""

from __future__ import annotations

import os
import tempfile
import zipfile
from array import array
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from evseg.errors import FormatError
from evseg.io._atomic import atomic_path
from evseg.io.numpy_files import require_npz

LABEL_DTYPE = np.dtype("<i2")
UNASSIGNED = -1


@dataclass
class SegmentationOutput:
    """A ``result.npz`` loaded back (see module docstring for the fields)."""

    label: np.ndarray
    window_t0_us: np.ndarray
    window_t1_us: np.ndarray
    boxes: np.ndarray
    sensor_size: tuple[int, int]
    partial: bool
    n_events_processed: int
    config: str
    masks: np.ndarray | None = None
    t_offset_us: int = 0

    def mask(self, row: int) -> np.ndarray:
        """Dense (height, width) bool mask of ``boxes[row]``."""
        if self.masks is None:
            raise FormatError("this result was written without masks (use --masks)")
        w, h = self.sensor_size
        return np.unpackbits(self.masks[row], count=w * h).astype(bool).reshape(h, w)


class ResultWriter:
    """Stream per-window labels and boxes into ``result.npz`` (atomic, bounded memory).

    Labels must arrive in input order: :meth:`add_labels` appends the labels of the next
    events. When ``n_events`` is known, events never covered by a window are written as -1 by
    :meth:`close`; when it is None (a stream of unknown length) ``label`` holds the events seen.
    """

    def __init__(self, path: str | Path, n_events: int | None, sensor_size: tuple[int, int], config_yaml: str = "",
                 with_masks: bool = False, t_offset_us: int = 0):
        self.path = Path(path)
        self.t_offset_us = int(t_offset_us)
        self.n_events = None if n_events is None else int(n_events)
        self.sensor_size = (int(sensor_size[0]), int(sensor_size[1]))
        self.config_yaml = config_yaml
        self.with_masks = with_masks
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd, name = tempfile.mkstemp(prefix=".labels-", suffix=".bin", dir=self.path.parent)
        self._label_file = os.fdopen(fd, "wb")
        self._label_path = Path(name)
        self._mask_file = self._mask_path = None
        if with_masks:  # a dense mask per object and window: on disk, not in memory
            fd, name = tempfile.mkstemp(prefix=".masks-", suffix=".bin", dir=self.path.parent)
            self._mask_file, self._mask_path = os.fdopen(fd, "wb"), Path(name)
        self.n_written = 0
        # Packed int64 rather than lists of Python ints (~25x smaller): a 10 min recording has
        # 60 000 windows and a few boxes each.
        self._t0 = array("q")
        self._t1 = array("q")
        self._boxes = array("q")  # 6 values per box
        self._n_masks = 0
        self._closed = False
        self._input_order: np.ndarray | None = None

    def set_input_order(self, order: np.ndarray | None) -> None:
        """Labels arrive in another order than the file's (a sorted copy of an unsorted file):
        ``order[i]`` is the file position of the i-th event labelled. :meth:`close` writes
        ``label`` in file order; events never labelled get -1."""
        self._input_order = None if order is None else np.asarray(order, dtype=np.int64)

    def add_labels(self, labels: np.ndarray) -> None:
        """Append labels for the next ``len(labels)`` events of the input."""
        labels = np.asarray(labels, dtype=LABEL_DTYPE)
        if self.n_events is not None and self.n_written + len(labels) > self.n_events:
            raise ValueError(f"more labels ({self.n_written + len(labels)}) than events ({self.n_events})")
        self._label_file.write(labels.tobytes())
        self.n_written += len(labels)

    def add_unassigned(self, n: int) -> None:
        """Append -1 for the next ``n`` events (events outside every window)."""
        fill = np.full(min(int(n), 1 << 20), UNASSIGNED, dtype=LABEL_DTYPE)
        while n > 0:
            k = min(n, len(fill))
            self.add_labels(fill[:k])
            n -= k

    def add_window(self, t0_us: int, t1_us: int, boxes: dict[int, tuple[int, int, int, int]],
                   masks: dict[int, np.ndarray] | None = None) -> None:
        """Record one window's time span and its objects' boxes (and masks)."""
        w = len(self._t0)
        self._t0.append(int(t0_us))
        self._t1.append(int(t1_us))
        for oid in sorted(boxes):
            if self.with_masks:
                if masks is None or oid not in masks:
                    raise ValueError(f"window {w}: no mask for object {oid}")
                shape = np.shape(masks[oid])
                if shape != (self.sensor_size[1], self.sensor_size[0]):
                    # Another size shifts every later mask in the file (or cuts it short).
                    raise ValueError(f"window {w}: the mask of object {oid} has shape {shape}, expected "
                                     f"(height, width) = ({self.sensor_size[1]}, {self.sensor_size[0]})")
                self._mask_file.write(np.packbits(np.asarray(masks[oid], dtype=bool).ravel()).tobytes())
                self._n_masks += 1
            self._boxes.extend((w, int(oid), *(int(v) for v in boxes[oid])))

    def close(self, partial: bool = False) -> Path:
        """Write the npz atomically; remaining events get -1. Returns the path."""
        if self._closed:
            return self.path
        self._closed = True
        n_done = self.n_written
        if self.n_events is not None:
            self.add_unassigned(self.n_events - self.n_written)
        if self._input_order is not None:
            self.add_unassigned(len(self._input_order) - self.n_written)
        n_total = self.n_written
        self._label_file.close()
        if self._input_order is not None:
            self._restore_input_order(n_total)
        if self._mask_file is not None:
            self._mask_file.close()
        try:
            with atomic_path(self.path) as tmp, \
                    zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf:
                _write_npy_from_file(zf, "label", self._label_path, LABEL_DTYPE, (n_total,))
                if self.with_masks:
                    w, h = self.sensor_size
                    _write_npy_from_file(zf, "masks", self._mask_path, np.dtype(np.uint8),
                                         (self._n_masks, (w * h + 7) // 8))
                arrays = {
                    "window_t0_us": np.frombuffer(self._t0, dtype=np.int64),
                    "window_t1_us": np.frombuffer(self._t1, dtype=np.int64),
                    "boxes": np.frombuffer(self._boxes, dtype=np.int64).reshape(-1, 6),
                    "sensor_size": np.asarray(self.sensor_size, dtype=np.int64),
                    "partial": np.asarray(bool(partial)),
                    "n_events_processed": np.asarray(n_done, dtype=np.int64),
                    "config": np.asarray(self.config_yaml),
                    "t_offset_us": np.asarray(self.t_offset_us, dtype=np.int64),
                }
                for key, arr in arrays.items():
                    with zf.open(f"{key}.npy", "w", force_zip64=True) as f:
                        np.lib.format.write_array(f, arr, allow_pickle=False)
        finally:
            self._drop_temporaries()
        return self.path

    def _restore_input_order(self, n_total: int) -> None:
        # Only with --sort, which holds the whole recording in memory anyway: the labels fit too.
        order = self._input_order
        if len(order) != n_total:
            raise ValueError(f"input order has {len(order)} events, {n_total} were labelled")
        labels = np.fromfile(self._label_path, dtype=LABEL_DTYPE, count=n_total)
        in_file_order = np.empty_like(labels)
        in_file_order[order] = labels
        in_file_order.tofile(self._label_path)

    def abort(self) -> None:
        """Drop temporary files without writing anything (nothing already on disk is touched)."""
        if not self._closed:
            self._closed = True
            self._label_file.close()
            if self._mask_file is not None:
                self._mask_file.close()
            self._drop_temporaries()

    def _drop_temporaries(self) -> None:
        self._label_path.unlink(missing_ok=True)
        if self._mask_path is not None:
            self._mask_path.unlink(missing_ok=True)

    def __enter__(self) -> "ResultWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        # An exception (including Ctrl-C) still leaves a readable result of the windows done.
        self.close(partial=exc_type is not None)


def _write_npy_from_file(zf: zipfile.ZipFile, key: str, src: Path, dtype: np.dtype, shape: tuple[int, ...]) -> None:
    """Copy a raw binary file into the zip as ``key.npy`` in chunks (bounded memory)."""
    header = {"descr": np.lib.format.dtype_to_descr(dtype), "fortran_order": False, "shape": shape}
    with zf.open(f"{key}.npy", "w", force_zip64=True) as f, open(src, "rb") as raw:
        np.lib.format.write_array_header_1_0(f, header)
        while True:
            block = raw.read(1 << 24)
            if not block:
                break
            f.write(block)


def load_result(path: str | Path) -> SegmentationOutput:
    """Read a ``result.npz`` written by :class:`ResultWriter`."""
    path = Path(path)
    require_npz(path, "segmentation result")
    try:
        with np.load(path, allow_pickle=False) as z:
            missing = {"label", "window_t0_us", "window_t1_us", "boxes", "sensor_size"} - set(z.files)
            if missing:
                raise FormatError(f"{path}: not an evseg result, missing keys {sorted(missing)}")
            label, boxes, size = z["label"], z["boxes"], z["sensor_size"]
            if label.ndim != 1 or not np.issubdtype(label.dtype, np.integer):
                raise FormatError(f"{path}: key 'label' must be 1-D integers, got {label.dtype} {label.shape}")
            if boxes.ndim != 2 or boxes.shape[1] != 6:
                raise FormatError(f"{path}: key 'boxes' must have rows (window, id, x0, y0, x1, y1), got shape "
                                  f"{boxes.shape}")
            if size.shape != (2,):
                raise FormatError(f"{path}: key 'sensor_size' must be [width, height], got {size.tolist()}")
            return SegmentationOutput(
                label=z["label"],
                window_t0_us=z["window_t0_us"],
                window_t1_us=z["window_t1_us"],
                boxes=z["boxes"],
                sensor_size=tuple(int(v) for v in z["sensor_size"]),
                partial=bool(z["partial"]) if "partial" in z.files else False,
                n_events_processed=int(z["n_events_processed"]) if "n_events_processed" in z.files else len(z["label"]),
                config=str(z["config"]) if "config" in z.files else "",
                masks=z["masks"] if "masks" in z.files else None,
                t_offset_us=int(z["t_offset_us"]) if "t_offset_us" in z.files else 0,
            )
    except (OSError, ValueError, zipfile.BadZipFile) as exc:
        raise FormatError(f"{path}: cannot read segmentation result ({exc})") from None
