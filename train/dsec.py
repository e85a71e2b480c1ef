"""DSEC sequences as training recordings with ground-truth optical flow.

DSEC (Gehrig et al. 2021) ships, per sequence, the left event camera's raw events
(``events/left/events.h5``, 640x480, with ``rectify_map.h5``) and forward optical flow in the
rectified frame of that camera (``flow/forward/*.png`` with ``flow/forward_timestamps.txt``).
:func:`convert_dsec` turns one sequence into the ``.npz`` layout that
:func:`evseg.train.data.load_flow_recording` reads (``--data.real_recordings``):

- events are rectified (``rectify_map[y, x]``, rounded to the nearest pixel; events that land
  outside the sensor are dropped), and only those inside a flow interval are kept;
- each flow map (a displacement in px over its interval ``[from, to)``, stored as 16-bit PNG
  with ``(value - 2**15) / 128`` in the first two channels and a valid flag in the third)
  becomes px/s by dividing by the interval; invalid pixels are NaN, and a gap between two
  intervals gets an all-NaN map;
- times start at the first interval's ``from`` (microseconds).

Checked against DSEC's published format description and on synthetic files in that format
(``tests/train/test_dsec.py``), not on a downloaded sequence (none can be fetched here).

Example::

    python -m evseg.train.dsec train_events/zurich_city_09_a/events/left \\
        train_optical_flow/zurich_city_09_a/flow --out zurich_city_09_a.npz --max-maps 50
    evseg train --config configs/train/default.yaml --data.real_recordings "[zurich_city_09_a.npz]"
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from evseg.errors import EvsegError, FormatError

DSEC_SENSOR_SIZE = (640, 480)
"""(width, height) of DSEC's event cameras, px."""

FLOW_OFFSET = 2**15
FLOW_SCALE = 128.0
"""A DSEC flow PNG stores ``value = flow_px * 128 + 2**15`` (uint16)."""


def read_flow_png(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """One DSEC flow map: ``(flow, valid)``, flow (H, W, 2) float32 displacement in px (x =
    column, y = row down), valid (H, W) bool."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise FormatError(f"{path}: not a readable PNG image")
    if img.dtype != np.uint16 or img.ndim != 3 or img.shape[2] != 3:
        raise FormatError(f"{path}: a DSEC flow map is a 3-channel 16-bit PNG, got dtype {img.dtype}, shape {img.shape}")
    rgb = img[..., ::-1]  # OpenCV reads BGR; DSEC's channels are (x, y, valid)
    flow = (rgb[..., :2].astype(np.float32) - FLOW_OFFSET) / FLOW_SCALE
    return flow, rgb[..., 2] > 0


def read_flow_timestamps(path: str | Path) -> np.ndarray:
    """``forward_timestamps.txt``: (K, 2) int64 ``[from, to]`` in microseconds, one row per
    flow map (``#`` lines are comments)."""
    try:
        ts = np.loadtxt(path, delimiter=",", comments="#", dtype=np.int64, ndmin=2)
    except (OSError, ValueError) as exc:
        raise FormatError(f"{path}: cannot read flow timestamps ({exc})") from None
    if ts.shape[1:] != (2,) or len(ts) == 0:
        raise FormatError(f"{path}: expected rows 'from_timestamp_us, to_timestamp_us', got shape {ts.shape}")
    bad = np.flatnonzero(ts[:, 1] <= ts[:, 0])
    if len(bad):
        raise FormatError(f"{path}: row {bad[0] + 1} ends before it starts ({ts[bad[0], 0]}, {ts[bad[0], 1]})")
    if np.any(ts[1:, 0] < ts[:-1, 1]):
        k = int(np.flatnonzero(ts[1:, 0] < ts[:-1, 1])[0]) + 1
        raise FormatError(f"{path}: row {k + 1} starts before row {k} ends (intervals must be in time order)")
    return ts


def _read_rectify_map(path: Path) -> np.ndarray:
    import h5py

    try:
        with h5py.File(path, "r") as f:
            if "rectify_map" not in f:
                raise FormatError(f"{path}: no dataset 'rectify_map'")
            rmap = np.asarray(f["rectify_map"], dtype=np.float64)
    except OSError as exc:
        raise FormatError(f"{path}: cannot read ({exc})") from None
    w, h = DSEC_SENSOR_SIZE
    if rmap.shape != (h, w, 2):
        raise FormatError(f"{path}: 'rectify_map' has shape {rmap.shape}, expected ({h}, {w}, 2)")
    return rmap


def check_dsec_output(out: str | Path, events_dir: Path, flow_dir: Path, pngs: list[Path] = ()) -> None:
    """Refuse ``out`` before any work (:class:`~evseg.errors.ConfigError` naming ``--out``) when
    it is not a ``.npz`` file name (the converter writes npz content), or when it is one of the
    sequence's own files (``events.h5``, ``rectify_map.h5``, ``forward_timestamps.txt``, a flow
    PNG): the raw data would be replaced."""
    from evseg.io.output_paths import check_output_path

    inputs = [("DSEC's raw events (events_dir/events.h5)", events_dir / "events.h5"),
              ("the rectification map (events_dir/rectify_map.h5)", events_dir / "rectify_map.h5"),
              ("the flow timestamps (flow_dir/forward_timestamps.txt)", flow_dir / "forward_timestamps.txt"),
              *(("a flow map of flow_dir/forward", png) for png in pngs)]
    check_output_path(Path(out), "--out", (".npz",), inputs)


def convert_dsec(events_dir: str | Path, flow_dir: str | Path, out: str | Path, max_maps: int | None = None) -> Path:
    """Write one DSEC sequence as a training recording (module docstring) to ``out`` (.npz,
    atomically).

    Args:
        events_dir: the folder with ``events.h5`` and ``rectify_map.h5`` (DSEC's
            ``events/left``).
        flow_dir: the folder with ``forward/`` (PNG maps, sorted by name) and
            ``forward_timestamps.txt`` (DSEC's ``flow``).
        max_maps: use only the first this many flow intervals (each ~100 ms and 2.4 MB of
            flow in memory); None = all.
    Returns:
        ``out``.
    Raises:
        ConfigError: ``out`` does not end in ``.npz`` or is one of the sequence's files
            (checked before anything is read).
    """
    from evseg.events import EVENT_DTYPE
    from evseg.io import open_recording
    from evseg.io._atomic import atomic_savez

    events_dir, flow_dir = Path(events_dir), Path(flow_dir)
    pngs = sorted((flow_dir / "forward").glob("*.png"))
    check_dsec_output(out, events_dir, flow_dir, pngs)
    ts = read_flow_timestamps(flow_dir / "forward_timestamps.txt")
    if len(pngs) != len(ts):
        raise FormatError(f"{flow_dir}: {len(pngs)} flow maps in forward/ but {len(ts)} rows in forward_timestamps.txt")
    if max_maps is not None:
        if max_maps < 1:
            raise EvsegError(f"convert_dsec: max_maps must be at least 1, got {max_maps}")
        ts, pngs = ts[:max_maps], pngs[:max_maps]
    rmap = _read_rectify_map(events_dir / "rectify_map.h5")
    w, h = DSEC_SENSOR_SIZE
    t0 = int(ts[0, 0])

    kept = []
    with open_recording(events_dir / "events.h5", sensor_size=DSEC_SENSOR_SIZE) as rec:
        for chunk in rec.chunks():
            if len(chunk) == 0:
                continue
            t_abs = chunk["t"] + np.int64(rec.t_offset_us)
            past_last = t_abs[-1] >= ts[-1, 1]
            k = np.searchsorted(ts[:, 0], t_abs, side="right") - 1
            inside = (k >= 0) & (t_abs < ts[np.maximum(k, 0), 1])
            c, t_abs = chunk[inside], t_abs[inside]
            xy = rmap[c["y"], c["x"]]
            xr, yr = np.rint(xy[:, 0]), np.rint(xy[:, 1])
            on = (xr >= 0) & (xr < w) & (yr >= 0) & (yr < h)
            ev = np.empty(int(on.sum()), dtype=EVENT_DTYPE)
            ev["x"], ev["y"] = xr[on], yr[on]
            ev["t"], ev["p"] = t_abs[on] - t0, c["p"][on]
            kept.append(ev)
            if past_last:
                break
    events = np.concatenate(kept) if kept else np.empty(0, dtype=EVENT_DTYPE)

    # One array for all maps (filled in place: a list of maps and a stacked copy would need
    # twice the memory); a gap between two intervals gets an all-NaN map of its own.
    gap = np.r_[False, ts[1:, 0] > ts[:-1, 1]]
    flow_maps = np.full((len(ts) + int(gap.sum()), h, w, 2), np.nan, dtype=np.float32)
    starts = []
    for k, (png, (t_from, t_to)) in enumerate(zip(pngs, ts)):
        if gap[k]:  # no ground truth from the end of the interval before
            starts.append(int(ts[k - 1, 1]) - t0)
        flow, valid = read_flow_png(png)
        if flow.shape[:2] != (h, w):
            raise FormatError(f"{png}: flow map is {flow.shape[1]}x{flow.shape[0]}, expected {w}x{h}")
        flow_maps[len(starts)][valid] = flow[valid] / np.float32((t_to - t_from) * 1e-6)
        starts.append(int(t_from) - t0)
    atomic_savez(out, events=events, sensor_size=np.asarray(DSEC_SENSOR_SIZE, np.int64), flow_maps=flow_maps,
                 flow_t_us=np.asarray(starts, np.int64))
    return Path(out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m evseg.train.dsec",
        description="Convert a DSEC sequence (events/left + flow) into a training recording with "
                    "ground-truth optical flow (--data.real_recordings of evseg train).")
    parser.add_argument("events_dir", help="folder with events.h5 and rectify_map.h5 (DSEC events/left)")
    parser.add_argument("flow_dir", help="folder with forward/ and forward_timestamps.txt (DSEC flow)")
    parser.add_argument("--out", required=True, help="output .npz")
    parser.add_argument("--max-maps", type=int, default=None, help="only the first N flow intervals (default: all)")
    args = parser.parse_args(argv)
    try:
        path = convert_dsec(args.events_dir, args.flow_dir, args.out, args.max_maps)
    except EvsegError as exc:
        print(f"{parser.prog}: error: {exc}", file=sys.stderr)
        return 2
    with np.load(path) as z:
        print(f"wrote {path}: {len(z['events'])} rectified events, {len(z['flow_t_us'])} flow maps")
    return 0


if __name__ == "__main__":
    sys.exit(main())
