"""Per-event normal flow of a recording, slice by slice.

Reads the recording in time slices (``--window-ms``, constant memory), picks target events in
each slice (``--targets cell``: the latest event of each ``--cell-px`` cell; ``all``: every
event), estimates their normal flow with the learned model (default: the shipped ONNX model,
``--model`` for another; with the events of ``--context-ms`` before each slice as neighbours,
and for its slow-edge look as long again as slice plus context before that, so the flows
differ from the pipeline's unless ``--no-slow-edges``) or the plane-fit baseline
(``--baseline``), and writes ``--out`` (.npz, atomically) with one row per target event:

- ``index`` int64: position of the event in the input recording (0-based, file order)
- ``nx``, ``ny`` float32: normal flow in px/s of the sensor's pixel grid (x = column,
  y = row, row 0 at the top); NaN where the baseline rejected the fit
- ``uncertainty`` float32: larger = less certain (predicted angular error, radians; inf where
  rejected)

plus ``sensor_size`` (int64 [width, height]), ``window_us`` and ``method`` / ``config`` (JSON
of the estimator, model file and settings used, e.g. ``context_us``, ``history_us``,
``slow_edges``, ``mirrors``). ``--mirrors N`` averages the model's flow over N mirror images of
each slice (:mod:`evseg.veckm_flow.mirrors`). ``--video`` renders a normal-flow colour-wheel
video (one frame per slice, hue = direction, brightness = speed up to ``--max-px-s``).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

from evseg.overlay import MAX_VIDEO_FPS

HELP = "per-event normal flow (px/s) of a recording, learned (ONNX) or plane-fit baseline -> flow.npz"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("recording", type=Path, help="event recording (any supported format)")
    p.add_argument("--out", type=Path, required=True, help="output .npz (index, nx, ny, uncertainty)")
    p.add_argument("--model", type=Path, default=None, help="ONNX normal-flow model (default: the shipped one)")
    p.add_argument("--baseline", action="store_true", help="use the plane-fit baseline instead of the model")
    p.add_argument("--flow-method", choices=["learned", "planefit"], default=None,
                   help="the estimator, as evseg segment names it: planefit = --baseline (default: learned)")
    p.add_argument("--no-fast-edges", action="store_true",
                   help="skip the time-stretched second look at fast flows (README, Normal flow)")
    p.add_argument("--no-slow-edges", action="store_true",
                   help="skip the time-compressed second look at slow flows over a longer slice "
                        "(README, Normal flow; up to 2.4x less time on slow scenes)")
    p.add_argument("--mirrors", type=int, choices=[1, 2, 4, 8], default=1,
                   help="average the model's flow over this many mirror images of each slice "
                        "(README, Normal flow; 8: 9.9 instead of 11.5 deg median angular error "
                        "on held-out scenes, at ~5x the time)")
    p.add_argument("--calib", type=Path, default=None,
                   help="calibration YAML: ROS camera_info / EMSGC, or a Kalibr camchain (default: the file's own, if any)")
    p.add_argument("--calib-camera", default=None, metavar="NAME",
                   help="camera of a Kalibr camchain with several (cam0, cam1, ...)")
    p.add_argument("--window-ms", type=float, default=10.0, help="slice duration (ms): the targets of one slice")
    p.add_argument("--context-ms", "--flow-context-ms", dest="context_ms", type=float, default=20.0,
                   help="events of this span (ms) before a slice are neighbours of its targets too (0: the slice only)")
    p.add_argument("--targets", choices=["cell", "all"], default="cell", help="which events get a flow")
    p.add_argument("--cell-px", type=int, default=2, help="cell side (px) for --targets cell")
    p.add_argument("--threads", type=int, default=None, help="threads of the encoder and network (default: all cores)")
    p.add_argument("--video", type=Path, default=None, help="also write a colour-wheel flow video (.mp4)")
    p.add_argument("--max-px-s", type=float, default=None,
                   help="flow speed shown at full brightness in the video (default: 95th percentile)")
    p.add_argument("--fps", type=float, default=argparse.SUPPRESS,
                   help="frame rate of --video, one frame per slice (default: real time, at most 60)")
    p.add_argument("--format", default=None, help="override format detection")
    p.add_argument("--topic", default=None, help="ROS bag topic of the event messages (default: the only one)")
    p.add_argument("--sensor-size", default=None, help="WIDTHxHEIGHT when the file has none")
    p.add_argument("--time-unit", choices=["s", "ms", "us", "ns"], default=None,
                   help="text/csv, .npy and .npz only: unit of the time column (default: its name's suffix, e.g. t_ns; "
                        "else for text s if any of the first 1,000 times has a decimal point or exponent, else us; for "
                        "arrays s when floating point, us when integer)")
    p.add_argument("--sort", action="store_true",
                   help="sort events by time first (loads the whole recording; for files whose time goes "
                        "back); 'index' still counts events in file order")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")


def _estimator(args: argparse.Namespace):
    from evseg.veckm_flow import OnnxNormalFlow, PlaneFitNormalFlow

    if args.baseline:
        if args.model is not None or args.no_fast_edges or args.no_slow_edges or args.mirrors != 1:
            from evseg.errors import EvsegError

            other = ("--model" if args.model is not None
                     else "--no-fast-edges" if args.no_fast_edges
                     else "--no-slow-edges" if args.no_slow_edges else "--mirrors")
            raise EvsegError(f"--baseline and {other} exclude each other (both are about the learned flow)")
        est = PlaneFitNormalFlow()
        return est, {"method": "planefit", "planefit": {k: getattr(est, k) for k in est.__dataclass_fields__}}
    from dataclasses import asdict

    from evseg.veckm_flow.fast_edges import FastEdges
    from evseg.veckm_flow.slow_edges import SlowEdges

    est = OnnxNormalFlow(args.model, threads=args.threads, fast_edges=None if args.no_fast_edges else FastEdges(),
                         slow_edges=None if args.no_slow_edges else SlowEdges(), mirrors=args.mirrors)
    return est, {"method": "learned", "model": str(est.model_path), "encoding": est.cfg.to_dict(),
                 "mirrors": est.mirrors,
                 "fast_edges": None if est.fast_edges is None else asdict(est.fast_edges),
                 "slow_edges": None if est.slow_edges is None else asdict(est.slow_edges)}


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from evseg.calibration import load_calibration, needs_sensor_size
    from evseg.errors import EvsegError

    if args.flow_method == "learned" and args.baseline:
        raise EvsegError("--flow-method learned and --baseline contradict each other: give one")
    args.baseline = args.baseline or args.flow_method == "planefit"
    from evseg.io import open_recording, parse_sensor_size
    from evseg.flow_file import save_flow_file
    from evseg.veckm_flow import NormalFlow, select_targets
    from evseg.veckm_flow.context import flow_with_context, history_span_us, split_history
    from evseg.windows import EventHistory, ordered_time_windows

    if not (math.isfinite(args.window_ms) and args.window_ms > 0):
        raise EvsegError(f"--window-ms must be a positive number, got {args.window_ms}")
    if not (math.isfinite(args.context_ms) and args.context_ms >= 0):
        raise EvsegError(f"--context-ms must be a number >= 0, got {args.context_ms}")
    if args.threads is not None and args.threads < 1:
        raise EvsegError(f"--threads must be at least 1, got {args.threads}")
    if args.cell_px < 1:
        raise EvsegError(f"--cell-px must be at least 1, got {args.cell_px}")
    if args.calib_camera is not None and args.calib is None:
        raise EvsegError(f"--calib-camera {args.calib_camera} names a camera of a calibration file: give --calib too")
    window_us = max(1, int(round(args.window_ms * 1000)))
    if not args.baseline:
        from evseg.veckm_flow.encoding import MAX_SLICE_SPAN_US

        if window_us + args.context_ms * 1000 > MAX_SLICE_SPAN_US:
            raise EvsegError(
                f"--window-ms plus --context-ms must be at most {MAX_SLICE_SPAN_US / 1000:.0f} ms "
                f"(the learned flow's longest slice), got {args.window_ms} + {args.context_ms}")
    from evseg.io.output_paths import check_output_path

    inputs = [("the recording", args.recording), ("the calibration (--calib)", args.calib),
              ("the model (--model)", args.model)]
    check_output_path(args.out, "--out", (".npz",), inputs)
    if args.video is not None:
        check_output_path(args.video, "--video", (".mp4",), inputs)
    args.fps = getattr(args, "fps", None)  # SUPPRESS keeps "(default: None)" out of --help
    if args.fps is not None:
        if args.video is None:
            raise EvsegError("--fps sets the frame rate of --video: give --video too")
        if not (math.isfinite(args.fps) and 0 < args.fps <= MAX_VIDEO_FPS):
            raise EvsegError(f"--fps must be a positive number up to {MAX_VIDEO_FPS} (the mp4 time base), "
                             f"got {args.fps:g}")
    if args.max_px_s is not None:
        if args.video is None:
            raise EvsegError("--max-px-s sets the colour scale of --video: give --video too")
        if not (math.isfinite(args.max_px_s) and args.max_px_s > 0):
            raise EvsegError(f"--max-px-s must be a positive number (px/s), got {args.max_px_s:g}")
    est, info = _estimator(args)
    sensor = parse_sensor_size(args.sensor_size) if args.sensor_size else None
    t_start = time.perf_counter()
    parts: list[NormalFlow] = []
    frames: list[tuple[np.ndarray, NormalFlow]] = []
    with open_recording(args.recording, format=args.format, topic=args.topic, sensor_size=sensor,
                        sort=args.sort, time_unit=args.time_unit) as rec:
        # ECD's one-line calib.txt holds no image size: it is read once the recording's is known.
        user_calibration = (load_calibration(args.calib, args.calib_camera)
                            if args.calib is not None and not needs_sensor_size(args.calib) else None)
        if user_calibration is not None:
            rec.assume_sensor_size(user_calibration.sensor_size, "calibration")
        if rec.sensor_size is None:
            # Unknown sensor size: infer it from the whole file first (one extra pass).
            for _ in rec.chunks():
                pass
            if rec.sensor_size is None:
                raise EvsegError(f"{args.recording}: no events, and no --sensor-size given")
        sensor_size = rec.sensor_size
        if args.calib is not None and user_calibration is None:
            user_calibration = load_calibration(args.calib, args.calib_camera, sensor_size=sensor_size)
        if user_calibration is None:
            rec.require_usable_calibration()
        calibration = user_calibration if user_calibration is not None else rec.calibration
        if calibration is not None and tuple(calibration.sensor_size) != tuple(sensor_size):
            raise EvsegError(
                f"{args.calib or args.recording}: calibration is for {calibration.sensor_size[0]}x"
                f"{calibration.sensor_size[1]}, the recording is {sensor_size[0]}x{sensor_size[1]}"
            )
        windows = ordered_time_windows(rec.chunks(), window_us)  # the recording checks its order
        if not args.no_progress:
            from tqdm import tqdm

            span = rec.time_span_us()  # known without decoding for arrays and HDF5
            total = None if span is None else (span[1] - span[0]) // window_us + 1
            windows = tqdm(windows, desc="normal flow", unit="slice", total=total, file=sys.stderr)
        n_events = 0
        context_us = int(round(args.context_ms * 1000))
        # The slow-edge look sees further back than the context: keep that much more.
        history_us = history_span_us(est, window_us + context_us)
        history = EventHistory(context_us + history_us)
        for win in windows:
            ev = win.events
            n_events += len(ev)
            older, context = split_history(history.before(win), win.t0_us, context_us)
            history.add(win)
            if len(ev) == 0:
                continue
            if args.targets == "all":
                targets = np.arange(len(ev), dtype=np.int64)
            else:
                targets = select_targets(ev, sensor_size, cell_px=args.cell_px)
            flow = flow_with_context(est, ev, sensor_size, targets, context, calibration,
                                     history=older if history_us else None)
            parts.append(flow.shifted(win.first_event))
            if args.video is not None:
                frames.append((ev[flow.index], flow))
        input_order = rec.input_order  # set by a sorting read; None: file order is time order
    flow = NormalFlow.concatenate(parts)
    index = flow.index if input_order is None else input_order[flow.index]  # file positions
    elapsed = time.perf_counter() - t_start
    info.update(
        {"recording": str(args.recording), "n_events": n_events, "window_us": window_us,
         "context_us": context_us, "history_us": history_us, "targets": args.targets, "sorted": args.sort,
         "cell_px": args.cell_px if args.targets == "cell" else None,
         "calibration": str(args.calib) if args.calib else ("file" if calibration is not None else None)}
    )
    save_flow_file(args.out, index, flow.nx, flow.ny, flow.uncertainty, sensor_size=sensor_size,
                   window_us=window_us, method=info["method"], config=info)
    if args.video is not None:
        cell = args.cell_px if args.targets == "cell" else 1
        _write_video(args.video, frames, sensor_size, window_us, args.max_px_s, cell, args.fps)
    valid = float(np.mean(flow.valid)) if len(flow) else 0.0
    print(
        f"{args.out}: {len(flow)} normal flows ({valid:.1%} valid) for {n_events} events, "
        f"{info['method']}, {elapsed:.2f} s ({len(flow) / max(elapsed, 1e-9):,.0f} flows/s incl. reading)"
        + (f"; video {args.video}" if args.video is not None else "")
    )
    return 0


def _write_video(path: Path, frames, sensor_size, window_us: int, max_px_s: float | None, cell_px: int = 1,
                 fps: float | None = None) -> None:
    """One frame per slice: flow colours at the target pixels (filling each target's cell),
    colour-wheel legend, time."""
    import cv2
    import numpy as np

    from evseg.errors import EvsegError
    from evseg.io._atomic import atomic_path
    from evseg.visualize import color_wheel_legend, flow_events_to_image

    if max_px_s is None:  # the 95th percentile of the speeds, rounded for the legend
        speeds = np.concatenate([np.hypot(f.nx, f.ny)[f.valid] for _, f in frames]) if frames else np.zeros(0)
        max_px_s = max(round(float(np.percentile(speeds, 95)), 0), 1.0) if len(speeds) else 1.0
    w, h = sensor_size
    scale = max(1, int(np.ceil(360 / max(h, 1))))  # small sensors are enlarged for viewing
    legend = color_wheel_legend(size=min(96, max(48, h * scale // 3)), max_px_s=max_px_s)
    if fps is None:
        fps = float(min(60.0, max(1.0, 1e6 / window_us)))  # real time where players keep up
    size = (w * scale, h * scale)
    with atomic_path(path) as tmp:
        tmp_mp4 = tmp.with_name(tmp.name + ".mp4")  # OpenCV picks the container from the suffix
        writer = cv2.VideoWriter(str(tmp_mp4), cv2.VideoWriter_fourcc(*"mp4v"), fps, size)
        try:
            if not writer.isOpened():
                raise EvsegError(f"{path}: OpenCV cannot open an mp4 writer here")
            for i, (ev, flow) in enumerate(frames):
                xs, ys, fl = _fill_cells(ev["x"], ev["y"], np.stack([flow.nx, flow.ny], 1), cell_px, sensor_size)
                img = flow_events_to_image(xs, ys, fl, sensor_size, max_px_s)
                img = cv2.resize(img, size, interpolation=cv2.INTER_NEAREST)
                lh, lw = legend.shape[:2]
                img[-lh:, -lw:] = legend
                title = f"slice {i}  {i * window_us / 1e3:.0f} ms"
                for colour, thickness in (((255, 255, 255), 3), ((0, 0, 0), 1)):  # outlined: readable on any flow
                    cv2.putText(img, title, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, colour, thickness, cv2.LINE_AA)
                writer.write(np.ascontiguousarray(img[..., ::-1]))  # RGB -> BGR
        except BaseException:
            writer.release()
            tmp_mp4.unlink(missing_ok=True)  # atomic_path removes its own temporary name only
            raise
        writer.release()
        tmp_mp4.replace(tmp)


def _fill_cells(x, y, flow, cell_px: int, sensor_size):
    """Repeat each target's flow over the pixels of its ``cell_px`` cell (display only)."""
    import numpy as np

    if cell_px <= 1:
        return x, y, flow
    dy, dx = np.mgrid[0:cell_px, 0:cell_px]
    xs = (x.astype(np.int64) // cell_px * cell_px)[:, None] + dx.ravel()
    ys = (y.astype(np.int64) // cell_px * cell_px)[:, None] + dy.ravel()
    keep = (xs < sensor_size[0]) & (ys < sensor_size[1])
    return xs[keep], ys[keep], np.repeat(flow, cell_px * cell_px, axis=0)[keep.ravel()]
