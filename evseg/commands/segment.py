"""Segment a recording into background and independently moving objects.

Reads the recording window by window (constant memory), estimates normal flow (the shipped
learned model by default, ``--flow-method planefit`` for the classical baseline, or ``--flow``
for precomputed per-event flow), segments each window and writes ``--out result.npz``
(schema in the README: ``label`` per input event, ``window_t0_us``, ``window_t1_us``,
``boxes``, optional ``masks``, the configuration used). The result is written atomically; an
error or Ctrl-C leaves the windows already processed in a result flagged ``partial``.
``--realtime`` replays the recording at the sensor's pace through :func:`evseg.live.run_live`,
which drops windows when the pipeline falls behind, as it would on a live camera.
"""

from __future__ import annotations

import argparse
from pathlib import Path

HELP = "segment a recording: per-event labels, boxes and masks (result.npz), optional video"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("recording", type=Path, help="event recording (any supported format)")
    p.add_argument("--out", type=Path, required=True, help="result file (.npz)")
    p.add_argument("--format", default=None, help="override format detection")
    p.add_argument("--topic", default=None, help="ROS bag topic of the event messages (default: the only one)")
    p.add_argument("--sensor-size", default=None, help="WIDTHxHEIGHT when the file has none")
    p.add_argument("--sort", action="store_true",
                   help="sort events by time first (loads the whole recording; for files whose time goes back)")
    p.add_argument("--time-unit", choices=["s", "ms", "us", "ns"], default=None,
                   help="text/csv, .npy and .npz only: unit of the time column (default: its name's suffix, e.g. t_ns; "
                        "else for text s if any of the first 1,000 times has a decimal point or exponent, else us; for "
                        "arrays s when floating point, us when integer)")
    p.add_argument("--calib", type=Path, default=None,
                   help="calibration YAML (ROS camera_info / EMSGC, or a Kalibr camchain)")
    p.add_argument("--calib-camera", default=None, metavar="NAME",
                   help="camera of a Kalibr camchain with several (cam0, cam1, ...)")
    p.add_argument("--config", default=None,
                   help="segmentation preset name or YAML file; or a result.npz (or the config it stores) whose "
                        "segmentation settings to reuse (window, flow and the other options come from this "
                        "command line)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="FIELD=VALUE",
                   help="a segmentation field on top of --config (or the defaults), repeatable: --config eed_like "
                        "--set max_nodes=12000 (fields: README, Segmentation, Parameters)")
    p.add_argument("--window-ms", type=float, default=10.0, help="window duration (ms)")
    p.add_argument("--stride-ms", type=float, default=None, help="time between windows (ms); default = window")
    p.add_argument("--flow-context-ms", type=float, default=20.0,
                   help="events of this span (ms) before a window are neighbours in its normal flow estimate")
    p.add_argument("--flow", type=Path, default=None,
                   help="precomputed normal flow (.npz with index, nx, ny [px/s], optional uncertainty)")
    p.add_argument("--flow-method", choices=["learned", "planefit"], default="learned",
                   help="normal-flow estimator when --flow is not given")
    p.add_argument("--model", type=Path, default=None, help="ONNX normal-flow model (default: shipped)")
    p.add_argument("--threads", type=int, default=None,
                   help="threads of the normal-flow estimator (default: 1 while it overlaps the segmentation, else all cores)")
    p.add_argument("--no-overlap", action="store_true",
                   help="estimate each window's normal flow in turn instead of during the previous window's segmentation")
    p.add_argument("--worker", choices=["auto", "process", "thread"], default="auto",
                   help="where the overlapped flow and preparation run: a child process "
                        "(beside the segmentation, ~1.5 s to start) or a thread of this one; "
                        "auto: the thread for recordings known to be shorter than 5 s")
    p.add_argument("--min-track-windows", type=int, default=1,
                   help="report an object once its track was found in this many windows "
                        "(2: fewer false objects, each object reported one window later)")
    p.add_argument("--no-fast-edges", action="store_true",
                   help="learned flow: skip the time-stretched second look at fast flows "
                        "(faster, but fast small objects come out too slow; README, Normal flow)")
    p.add_argument("--slow-edges", action="store_true",
                   help="learned flow: add the time-compressed second look at slow flows over twice "
                        "the time (a better direction for slow edges, 1.5-2.4x the flow's time on slow "
                        "scenes; off by default: more false objects on real one-motion recordings; "
                        "README, Normal flow)")
    p.add_argument("--mirrors", type=int, choices=[1, 2, 4, 8], default=1,
                   help="learned flow: average it over this many mirror images of each window (fewer "
                        "false objects, at this many times the flow's time: for offline runs; "
                        "README, Normal flow)")
    p.add_argument("--tracked-mirrors", type=int, choices=[1, 2, 4, 8], default=1,
                   help="learned flow: this many mirror looks only where the object tracks expect an object "
                        "(inside their predicted boxes): more objects found and fewer false ones, at a "
                        "fraction of --mirrors 8's time when the objects are small; on real recordings "
                        "without objects about as many false ones; README, Normal flow")
    p.add_argument("--tracked-max-targets", type=int, default=None, metavar="N",
                   help="with --tracked-mirrors: at most N targets per window get the extra looks (the "
                        "smallest boxes first), which bounds its time; default: all in the boxes")
    p.add_argument("--realtime", action="store_true",
                   help="replay the recording at the sensor's pace as a live camera would send it, and drop "
                        "windows when the pipeline falls behind (their events are labelled -1); reports "
                        "the windows dropped and the latency of the labels (evseg.live)")
    p.add_argument("--speed", type=float, default=argparse.SUPPRESS,
                   help="with --realtime: replay this many times faster than recorded (default 1)")
    p.add_argument("--max-lag-ms", type=float, default=argparse.SUPPRESS,
                   help="with --realtime: windows that end more than this (ms) before the newest event are "
                        "dropped to catch up (default 20)")
    p.add_argument("--masks", action="store_true", help="also store dense object masks in the result")
    p.add_argument("--video", type=Path, default=None, help="write an overlay video (.mp4)")
    p.add_argument("--fps", type=float, default=argparse.SUPPRESS,
                   help="frame rate of --video, one frame per window (default 25: 0.25x real time with 10 ms "
                        "strides)")
    p.add_argument("--frames", type=Path, default=None, help="write one overlay PNG per window here")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")


def run(args: argparse.Namespace) -> int:
    from evseg.commands.eval import parse_overrides
    from evseg.errors import ConfigError
    from evseg.runner import SegmentJob, run_segment_job

    for name in ("speed", "max_lag_ms", "fps"):  # SUPPRESS keeps "(default: None)" out of --help
        setattr(args, name, getattr(args, name, None))
    for option, value in (("--speed", args.speed), ("--max-lag-ms", args.max_lag_ms)):
        if value is not None and not args.realtime:
            raise ConfigError(f"{option} sets the replay of --realtime: give --realtime too")
    if args.fps is not None and args.video is None:
        raise ConfigError("--fps sets the frame rate of --video: give --video too")

    job = SegmentJob(
        recording=args.recording,
        out=args.out,
        format=args.format,
        topic=args.topic,
        sensor_size=args.sensor_size,
        calib=args.calib,
        calib_camera=args.calib_camera,
        sort=args.sort,
        time_unit=args.time_unit,
        config=args.config,
        overrides=parse_overrides(args.overrides),
        window_ms=args.window_ms,
        stride_ms=args.stride_ms,
        flow_context_ms=args.flow_context_ms,
        flow_file=args.flow,
        flow_method=args.flow_method,
        model=args.model,
        threads=args.threads,
        overlap=not args.no_overlap,
        worker=args.worker,
        min_track_windows=args.min_track_windows,
        fast_edges=not args.no_fast_edges,
        slow_edges=args.slow_edges,
        mirrors=args.mirrors,
        tracked_mirrors=args.tracked_mirrors,
        tracked_max_targets=args.tracked_max_targets,
        realtime=args.realtime,
        speed=1.0 if args.speed is None else args.speed,
        max_lag_ms=20.0 if args.max_lag_ms is None else args.max_lag_ms,
        masks=args.masks,
        video=args.video,
        video_fps=25.0 if args.fps is None else args.fps,
        frames=args.frames,
        progress=not args.no_progress,
    )
    summary = run_segment_job(job)
    print(summary)
    return 0
