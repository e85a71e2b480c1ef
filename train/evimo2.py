"""EVIMO2 (v2 layout) sequences as training recordings with ground-truth optical flow.

An EVIMO2 v2 sequence folder holds the events (``dataset_events_xy.npy`` (N, 2) px,
``dataset_events_t.npy`` seconds, ``dataset_events_p.npy`` 0/1) and, once EVIMO's
``evimo_flow.py`` has been run on it, ``dataset_flow.npz``: maps ``flow_<frame id>`` (H, W, 2),
each the displacement in px of every pixel from ``t[k]`` to ``t_end[k]`` (seconds; NaN where
EVIMO2 has no depth, e.g. the room's walls), in the same (distorted) pixel grid as the events.
:func:`convert_evimo2` turns such a folder into the ``.npz`` layout that
:func:`evseg.train.data.load_flow_recording` reads (``--data.real_recordings``), with one
optical flow per event:

- map k (in frame-id order, which is time order) applies to the events in ``[t[k], t[k] + s)``,
  ``s`` the median spacing of the maps: a gap in the maps (Vicon lost track) leaves its events
  without ground truth; the flow is the displacement over ``t_end[k] - t[k]``, in px/s;
- only events inside such an interval are kept; times are the sequence's, in microseconds;
- older versions of ``evimo_flow.py`` write ``t`` and ``t_end`` in epoch seconds (the events'
  times plus ``ros_time_offset``); that offset is then read from ``dataset_info.npz``, whose
  ``meta`` is a pickled dictionary (so that one file is loaded with ``allow_pickle``).

Dense maps at EVIMO2's 60 Hz would take 2.4 MB per frame, so the flow is stored per event.
Checked against EVIMO's published format description and ``evimo_flow.py`` and on synthetic
folders in that layout (``tests/train/test_evimo2.py``), not on a downloaded sequence.

Example::

    python -m evseg.train.evimo2 samsung_mono/imo/train/scene9_dyn_train_00_000000 --out scene9.npz
    evseg train --config configs/train/default.yaml --data.real_recordings "[scene9.npz]"
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from evseg.errors import EvsegError, FormatError

EPOCH_THRESHOLD_S = 1e8
"""Flow times beyond this (seconds, ~1973 as an epoch time) are taken as epoch times."""


def _load(folder: Path, name: str) -> np.ndarray:
    path = folder / name
    try:
        return np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise FormatError(f"{path}: cannot read ({exc})") from None


def _ros_time_offset(folder: Path) -> float:
    path = folder / "dataset_info.npz"
    try:
        with np.load(path, allow_pickle=True) as z:  # EVIMO2's meta is a pickled dict
            return float(z["meta"].item()["meta"]["ros_time_offset"])
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise FormatError(f"{path}: the flow's times are epoch seconds, and this file gives no "
                          f"meta['meta']['ros_time_offset'] to align them with the events ({exc!r})") from None


INPUT_FILES = ("dataset_events_xy.npy", "dataset_events_t.npy", "dataset_events_p.npy", "dataset_flow.npz",
               "dataset_info.npz")
"""The files of a sequence folder the converter reads."""


def check_evimo2_output(out: str | Path, folder: Path) -> None:
    """Refuse ``out`` before any work (:class:`~evseg.errors.ConfigError` naming ``--out``) when
    it is not a ``.npz`` file name, or when it is one of the sequence's own files
    (:data:`INPUT_FILES`, e.g. ``dataset_flow.npz``): EVIMO2's data would be replaced."""
    from evseg.io.output_paths import check_output_path

    inputs = [(f"the sequence's {name}", Path(folder) / name) for name in INPUT_FILES]
    check_output_path(Path(out), "--out", (".npz",), inputs)


def convert_evimo2(folder: str | Path, out: str | Path, max_maps: int | None = None) -> Path:
    """Write one EVIMO2 v2 sequence folder as a training recording (module docstring) to
    ``out`` (.npz, atomically). ``max_maps``: use only the first this many flow maps. Returns
    ``out``. An ``out`` that is not a ``.npz`` name or is one of the folder's files is a
    :class:`~evseg.errors.ConfigError` before anything is read."""
    from evseg.events import make_events, validate_events
    from evseg.io._atomic import atomic_savez

    folder = Path(folder)
    check_evimo2_output(out, folder)
    xy = _load(folder, "dataset_events_xy.npy")
    t_s = _load(folder, "dataset_events_t.npy")
    p = _load(folder, "dataset_events_p.npy")
    if xy.ndim != 2 or xy.shape[1] != 2 or len(t_s) != len(xy) or len(p) != len(xy):
        raise FormatError(f"{folder}: dataset_events_xy.npy must be (N, 2) with N = len(dataset_events_t.npy) = "
                          f"len(dataset_events_p.npy); got {xy.shape}, {len(t_s)}, {len(p)}")
    flow_path = folder / "dataset_flow.npz"
    try:
        flows = np.load(flow_path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise FormatError(f"{flow_path}: cannot read ({exc}); run EVIMO's tools/evimo_flow.py on the sequence first") from None
    with flows:
        keys = sorted(k for k in flows.files if k.startswith("flow_"))
        if not keys or "t" not in flows.files or "t_end" not in flows.files:
            raise FormatError(f"{flow_path}: needs maps 'flow_<frame id>' and arrays 't', 't_end'")
        t0, t1 = np.asarray(flows["t"], np.float64), np.asarray(flows["t_end"], np.float64)
        if len(t0) != len(keys) or len(t1) != len(keys):
            raise FormatError(f"{flow_path}: {len(keys)} flow maps but {len(t0)} 't' and {len(t1)} 't_end' values")
        if np.any(np.diff(t0) <= 0) or np.any(t1 <= t0):
            raise FormatError(f"{flow_path}: 't' must increase and every 't_end' follow its 't'")
        if max_maps is not None:
            if max_maps < 1:
                raise EvsegError(f"convert_evimo2: max_maps must be at least 1, got {max_maps}")
            keys, t0, t1 = keys[:max_maps], t0[:max_maps], t1[:max_maps]
        if np.median(t0) > EPOCH_THRESHOLD_S and (len(t_s) == 0 or t_s[-1] < EPOCH_THRESHOLD_S):
            offset = _ros_time_offset(folder)
            t0, t1 = t0 - offset, t1 - offset
        spacing = float(np.median(np.diff(t0))) if len(t0) > 1 else float(t1[0] - t0[0])
        t_us = np.rint(np.asarray(t_s, np.float64) * 1e6).astype(np.int64)
        start_us = np.rint(t0 * 1e6).astype(np.int64)
        end_us = start_us + int(round(spacing * 1e6))
        k = np.searchsorted(start_us, t_us, side="right") - 1
        inside = (k >= 0) & (t_us < end_us[np.maximum(k, 0)])
        idx = np.flatnonzero(inside)
        first = flows[keys[0]]
        if first.ndim != 3 or first.shape[2] != 2:
            raise FormatError(f"{flow_path}: '{keys[0]}' has shape {first.shape}, expected (H, W, 2)")
        h, w = first.shape[:2]
        x, y = xy[idx, 0].astype(np.int64), xy[idx, 1].astype(np.int64)
        if len(idx) and (x.min() < 0 or y.min() < 0 or x.max() >= w or y.max() >= h):
            raise FormatError(f"{folder}: events outside the {w}x{h} flow maps (x {x.min()}..{x.max()}, "
                              f"y {y.min()}..{y.max()})")
        flow = np.full((len(idx), 2), np.nan, dtype=np.float32)
        kk = k[idx]
        for j in np.unique(kk):
            m = flows[keys[j]]
            if m.shape != (h, w, 2):
                raise FormatError(f"{flow_path}: '{keys[j]}' has shape {m.shape}, expected ({h}, {w}, 2)")
            sel = kk == j
            flow[sel] = m[y[sel], x[sel]] / np.float32(t1[j] - t0[j])
    events = make_events(x, y, t_us[idx], np.asarray(p)[idx])
    validate_events(events, (w, h), source=str(folder))
    atomic_savez(out, events=events, sensor_size=np.asarray((w, h), np.int64), flow=flow)
    return Path(out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m evseg.train.evimo2",
        description="Convert an EVIMO2 v2 sequence folder (events and dataset_flow.npz from EVIMO's "
                    "evimo_flow.py) into a training recording with ground-truth optical flow "
                    "(--data.real_recordings of evseg train).")
    parser.add_argument("folder", help="the sequence folder (dataset_events_*.npy, dataset_flow.npz)")
    parser.add_argument("--out", required=True, help="output .npz")
    parser.add_argument("--max-maps", type=int, default=None, help="only the first N flow maps (default: all)")
    args = parser.parse_args(argv)
    try:
        path = convert_evimo2(args.folder, args.out, args.max_maps)
    except EvsegError as exc:
        print(f"{parser.prog}: error: {exc}", file=sys.stderr)
        return 2
    with np.load(path) as z:
        valid = float(np.isfinite(z["flow"][:, 0]).mean()) if len(z["flow"]) else 0.0
        print(f"wrote {path}: {len(z['events'])} events, {valid:.1%} with ground-truth flow")
    return 0


if __name__ == "__main__":
    sys.exit(main())
