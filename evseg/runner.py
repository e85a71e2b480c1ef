"""The `evseg segment` job: recording in, result.npz (+ video) out. The I/O edge of the pipeline.

Everything with side effects lives here (opening files, the progress bar, writing results and
videos); the pipeline itself (:mod:`evseg.pipeline`) only returns values.
"""

from __future__ import annotations

import contextlib
import itertools
import math
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from evseg.errors import CalibrationError, ConfigError


@dataclass(frozen=True)
class SegmentJob:
    """What `evseg segment` was asked to do (see its --help for each field)."""

    recording: Path
    out: Path
    format: str | None = None
    topic: str | None = None
    sensor_size: str | tuple[int, int] | None = None
    calib: Path | None = None
    calib_camera: str | None = None
    sort: bool = False
    time_unit: str | None = None
    config: str | None = None
    overrides: dict | None = None  # segmentation fields set on top of `config` (--set FIELD=VALUE)
    window_ms: float = 10.0
    stride_ms: float | None = None
    flow_context_ms: float = 20.0
    flow_file: Path | None = None
    flow_method: str = "learned"
    model: Path | None = None
    threads: int | None = None
    overlap: bool = True
    worker: str = "auto"
    min_track_windows: int = 1
    fast_edges: bool = True
    slow_edges: bool = False
    mirrors: int = 1
    tracked_mirrors: int = 1
    tracked_max_targets: int | None = None
    realtime: bool = False
    speed: float = 1.0
    max_lag_ms: float = 20.0
    masks: bool = False
    video: Path | None = None
    video_fps: float = 25.0
    frames: Path | None = None
    progress: bool = True


AUTO_PROCESS_MIN_US = 5_000_000
"""``worker="auto"``: recordings whose span is known to be shorter than this (us) overlap on a
thread. The worker process takes ~1.5 s to start and saves up to ~10 ms per 10 ms window (at
1 M events/s on 2 cores; less at lower rates): it pays off from a few seconds of recording on.
A recording of unknown span (a format read as a stream) gets the process."""


def build_pipeline_config(job: SegmentJob):
    """Pipeline settings from the job: window, flow method and the segmentation preset/file."""
    from evseg.pipeline import PipelineConfig
    from evseg.segmentation import SegmentationConfig, load_segmentation_config

    if not (math.isfinite(job.window_ms) and job.window_ms > 0):
        raise ConfigError(f"--window-ms must be a positive number, got {job.window_ms}")
    if job.stride_ms is not None and not (math.isfinite(job.stride_ms) and job.stride_ms > 0):
        raise ConfigError(f"--stride-ms must be a positive number, got {job.stride_ms}")
    if not (math.isfinite(job.flow_context_ms) and job.flow_context_ms >= 0):
        raise ConfigError(f"--flow-context-ms must be a number >= 0, got {job.flow_context_ms}")
    if job.threads is not None and job.threads < 1:
        raise ConfigError(f"--threads must be at least 1, got {job.threads}")
    _check_flow_options(job)
    from evseg.overlay import MAX_VIDEO_FPS

    if not (math.isfinite(job.video_fps) and 0 < job.video_fps <= MAX_VIDEO_FPS):
        raise ConfigError(f"--fps must be a positive number up to {MAX_VIDEO_FPS} (the mp4 time base), "
                          f"got {job.video_fps:g}")
    if job.min_track_windows < 1:
        raise ConfigError(f"--min-track-windows must be >= 1, got {job.min_track_windows}")
    if job.tracked_max_targets is not None and job.tracked_max_targets < 0:
        raise ConfigError(f"--tracked-max-targets must be >= 0, got {job.tracked_max_targets}")
    if job.flow_file is None and job.flow_method == "learned":
        from evseg.veckm_flow.encoding import MAX_SLICE_SPAN_US

        if (job.window_ms + job.flow_context_ms) * 1000 > MAX_SLICE_SPAN_US:
            raise ConfigError(
                f"--window-ms plus --flow-context-ms must be at most {MAX_SLICE_SPAN_US / 1000:.0f} ms "
                f"(the learned flow's longest slice), got {job.window_ms} + {job.flow_context_ms}")
    if job.realtime:
        if job.flow_file is not None:
            raise ConfigError("--realtime replays a recording as a live camera, which has no precomputed "
                              "flow: leave out --flow")
        if not job.speed > 0:
            raise ConfigError(f"--speed must be positive, got {job.speed}")
        if not job.max_lag_ms >= 0:
            raise ConfigError(f"--max-lag-ms must be >= 0, got {job.max_lag_ms}")
    seg = load_segmentation_config(job.config) if job.config else SegmentationConfig()
    if job.overrides:
        from evseg.segmentation.config import with_overrides

        seg = with_overrides(seg, job.overrides, "--set")
    return PipelineConfig(
        window_us=int(round(job.window_ms * 1000)),
        stride_us=None if job.stride_ms is None else int(round(job.stride_ms * 1000)),
        flow_context_us=int(round(job.flow_context_ms * 1000)),
        flow="precomputed" if job.flow_file is not None else job.flow_method,
        model_path=None if job.model is None else str(job.model),
        threads=job.threads,
        overlap=job.overlap,
        worker="process" if job.worker == "auto" else job.worker,  # auto: see run_segment_job
        min_track_windows=job.min_track_windows,
        fast_edges=job.fast_edges,
        slow_edges=job.slow_edges,
        mirrors=job.mirrors,
        tracked_mirrors=job.tracked_mirrors,
        tracked_max_targets=job.tracked_max_targets,
        segmentation=seg,
    )


def _check_flow_options(job: SegmentJob) -> None:
    """Options of the learned flow make no sense with another flow: refuse them rather than
    run without them and record them in the result's configuration as if they had acted."""
    learned_only = [("--model", job.model is not None), ("--mirrors", job.mirrors != 1),
                    ("--tracked-mirrors", job.tracked_mirrors != 1), ("--slow-edges", job.slow_edges),
                    ("--no-fast-edges", not job.fast_edges),
                    ("--tracked-max-targets", job.tracked_max_targets is not None)]
    given = [name for name, on in learned_only if on]
    estimator_only = [("--flow-context-ms", job.flow_context_ms != SegmentJob.flow_context_ms),
                      ("--threads", job.threads is not None)]
    if job.flow_file is not None:
        given += [name for name, on in estimator_only if on]
    if job.flow_file is not None and (given or job.flow_method != "learned"):
        other = given[0] if given else "--flow-method"
        raise ConfigError(f"--flow and {other} exclude each other: {other} is about the normal flow evseg "
                          "estimates, and --flow brings its own")
    if job.flow_method == "planefit" and given:
        raise ConfigError(f"--flow-method planefit and {given[0]} exclude each other: {given[0]} is about the "
                          "learned flow")
    if job.tracked_max_targets is not None and job.tracked_mirrors == 1:
        raise ConfigError("--tracked-max-targets bounds the targets of --tracked-mirrors: give --tracked-mirrors "
                          "2, 4 or 8 too")


def check_job_outputs(job: SegmentJob) -> None:
    """Refuse, before any work, outputs that cannot be written or would replace an input."""
    from evseg.io.output_paths import check_output_folder, check_output_path

    inputs = [("the recording", job.recording), ("the flow file (--flow)", job.flow_file),
              ("the calibration (--calib)", job.calib), ("the model (--model)", job.model),
              ("the configuration (--config)", Path(job.config) if job.config and Path(job.config).suffix else None)]
    check_output_path(job.out, "--out", (".npz",), inputs)
    if job.video is not None:
        check_output_path(job.video, "--video", (".mp4",), inputs)
    if job.frames is not None:
        check_output_folder(job.frames, "--frames")
    outputs = [(o, p) for o, p in (("--out", job.out), ("--video", job.video), ("--frames", job.frames))
               if p is not None]
    for i, (option, path) in enumerate(outputs):
        for other, other_path in outputs[i + 1:]:
            if Path(path).resolve() == Path(other_path).resolve():
                raise ConfigError(f"{option} and {other} are both {path}: give each output its own name")


def config_yaml(config) -> str:
    import yaml

    d = asdict(config)
    return yaml.safe_dump(d, sort_keys=False)


@contextlib.contextmanager
def _closing(writer, windows_done):
    """Close ``writer`` at the end; after an error (or Ctrl-C) keep a result flagged partial
    only when ``windows_done()``: a failure before the first window (e.g. a bad first chunk)
    writes nothing, so an existing result is not replaced by an empty one."""
    try:
        yield writer
    except BaseException:
        if windows_done():
            writer.close(partial=True)
        else:
            writer.abort()
        raise
    writer.close()


def _progress_bar_kwargs(span: tuple[int, int] | None) -> dict:
    """tqdm settings: progress in seconds of recording, out of its duration when the format
    tells it; the postfix (:func:`_advance`) gives the real-time factor and the windows done."""
    # tqdm's own rate would print "5.0s/s" (wall s per recording s) below 1x, hence no rate_fmt.
    kw = dict(desc="segment", unit="s", postfix="0 windows")
    if span is None or span[1] <= span[0]:
        return {**kw, "bar_format": "{desc}: {n:.2f} s of recording [{elapsed}{postfix}]"}
    return {**kw, "total": (span[1] - span[0]) / 1e6,
            "bar_format": "{desc}: {percentage:3.0f}%|{bar}| {n:.2f}/{total:.2f} s of recording "
                          "[{elapsed}<{remaining}{postfix}]"}


def _advance(bar, t_us: int, origin_us: int, n_windows: int) -> None:
    """Move the bar to recording time ``t_us`` (us; ``origin_us`` is its zero)."""
    bar.update(max((t_us - origin_us) / 1e6 - bar.n, 0.0))
    elapsed = bar.format_dict["elapsed"]
    rtf = f"{real_time_factor(bar.n / elapsed)}x real time, " if elapsed > 0 else ""
    bar.set_postfix_str(f"{rtf}{plural(n_windows, 'window')}", refresh=False)


def plural(n: int, word: str) -> str:
    """``n`` and ``word``, with an s unless ``n`` is 1.

    >>> plural(1, "window"), plural(3, "window")
    ('1 window', '3 windows')
    """
    return f"{n} {word}" if n == 1 else f"{n} {word}s"


def real_time_factor(value: float) -> str:
    """A real-time factor with two decimals, or three significant digits below 0.01 (a short
    recording's set-up time would otherwise read "0.00x").

    >>> real_time_factor(0.7), real_time_factor(0.0043)
    ('0.70', '0.0043')
    """
    return f"{value:.2f}" if value >= 0.01 or value == 0 else f"{value:.2g}"


def run_segment_job(job: SegmentJob) -> str:
    """Run the job; returns a one-paragraph summary for the terminal."""
    from tqdm import tqdm

    from evseg.calibration import load_calibration, needs_sensor_size
    from evseg.io import open_recording
    from evseg.io.recording import parse_sensor_size
    from evseg.overlay import VideoSink, label_overlay
    from evseg.flow_file import flow_file_settings, to_time_order
    from evseg.pipeline import MotionSegmentationPipeline, load_flow_file
    from evseg.results import ResultWriter

    cfg = build_pipeline_config(job)  # config errors surface before any work
    if job.calib_camera is not None and job.calib is None:
        raise ConfigError(f"--calib-camera {job.calib_camera} names a camera of a calibration file: give --calib too")
    check_job_outputs(job)
    sensor_size = parse_sensor_size(job.sensor_size) if isinstance(job.sensor_size, str) else job.sensor_size
    # ECD's one-line calib.txt holds no image size: it is read once the recording's is known.
    calibration = (load_calibration(job.calib, job.calib_camera)
                   if job.calib is not None and not needs_sensor_size(job.calib) else None)
    with open_recording(job.recording, format=job.format, topic=job.topic, sensor_size=sensor_size,
                        sort=job.sort, time_unit=job.time_unit) as rec:
        inferred = ""
        if calibration is not None:
            # A file without a sensor size takes the calibration's (its events are checked
            # against it), not max + 1 of its events, which would refuse the calibration.
            rec.assume_sensor_size(calibration.sensor_size, "calibration")
        if rec.sensor_size is None:
            # As `evseg flow`: the size of the pixel grid the events use (one extra pass).
            for _ in rec.chunks():
                pass
            if rec.sensor_size is None:
                raise ConfigError(f"{job.recording}: no events, and no --sensor-size given")
            inferred = (f"; sensor size {rec.sensor_size[0]}x{rec.sensor_size[1]} inferred from the events "
                        "(pass --sensor-size WxH if the sensor is larger)")
        if job.calib is not None and calibration is None:
            calibration = load_calibration(job.calib, job.calib_camera, sensor_size=rec.sensor_size)
        if calibration is None:
            rec.require_usable_calibration()
            calibration = rec.calibration
            if calibration is not None and tuple(calibration.sensor_size) != tuple(rec.sensor_size):
                raise CalibrationError(
                    f"{job.recording}: the calibration stored in the file is for {calibration.sensor_size[0]}x"
                    f"{calibration.sensor_size[1]}, the sensor is {rec.sensor_size[0]}x{rec.sensor_size[1]} "
                    f"({rec.sensor_size_source}); give the file's size, or a calibration for this one (--calib)")
        elif tuple(calibration.sensor_size) != tuple(rec.sensor_size):
            # K of another camera or resolution would undistort every event wrongly, silently.
            raise CalibrationError(
                f"{job.calib}: fields 'image_width', 'image_height' (Kalibr: 'resolution') = "
                f"{calibration.sensor_size[0]}x{calibration.sensor_size[1]} do not match the sensor "
                f"{rec.sensor_size[0]}x{rec.sensor_size[1]} of {job.recording}"
            )
        flow = (load_flow_file(job.flow_file, sensor_size=rec.sensor_size)
                if job.flow_file is not None else None)
        # evseg flow records the event count of its recording; another recording of the same
        # sensor and at least as many events would pass every check of the rows.
        flow_n_events = flow_file_settings(job.flow_file).get("n_events") if job.flow_file is not None else None
        span = rec.time_span_us()
        if job.worker == "auto" and span is not None and span[1] - span[0] < AUTO_PROCESS_MIN_US:
            cfg = replace(cfg, worker="thread")  # too short to earn the process's start-up back
        pipe = MotionSegmentationPipeline(cfg, sensor_size=rec.sensor_size, calibration=calibration)
        stride_us = cfg.stride_us or cfg.window_us
        n_windows = n_objects = 0
        t_wall = time.perf_counter()
        t_first = t_last = None  # recording time covered: first window start to last event (us)
        ids: set[int] = set()
        writer = ResultWriter(job.out, None, rec.sensor_size, config_yaml(cfg), with_masks=job.masks,
                              t_offset_us=rec.t_offset_us)
        origin = span[0] if span is not None else None  # bar zero: first event, else first window
        # The video closes after the result: a video that fails to finish costs no labels.
        with pipe, VideoSink(job.video, job.frames, fps=job.video_fps) as sink, _closing(writer, lambda: n_windows > 0), \
                tqdm(**_progress_bar_kwargs(span), disable=not job.progress) as bar:
            seen = [0]

            def counted(chunks):
                for c in chunks:
                    seen[0] += len(c)
                    yield c

            chunks = counted(rec.chunks())
            if job.sort:
                # The sorted copy is made when the first chunk is asked for; the labels go back
                # to file order at the end, and a flow file counts events in file order too.
                first = next(chunks, None)
                writer.set_input_order(rec.input_order)
                if flow is not None:
                    flow = to_time_order(flow, rec.input_order, source=str(job.flow_file))
                chunks = itertools.chain([] if first is None else [first], chunks)

            latencies: list[float] = []
            dropped = [0]
            if job.realtime:
                from evseg.live import replay, run_live

                pipe.warm_up()  # the first window must not pay the one-time set-up
                t_wall = time.perf_counter()
                bar.reset(total=bar.total)  # nor the bar's real-time factor
                live = run_live(pipe, replay(chunks, speed=job.speed),
                                max_lag_us=int(round(job.max_lag_ms * 1000)))
                results = _live_windows(live, latencies, dropped)
            else:
                results = pipe.run(chunks, precomputed_flow=flow, flow_source=str(job.flow_file))
            for res in write_window_labels(writer, results, stride_us):
                writer.add_window(res.t0_us, res.t1_us, res.boxes, res.masks if job.masks else None)
                if job.video is not None or job.frames is not None:
                    sink.add(label_overlay(res.events, res.labels, res.boxes, rec.sensor_size,
                                           title=f"{res.t0_us / 1e3:.1f} ms"))
                n_windows += 1
                t_first = res.t0_us if t_first is None else t_first
                if len(res.events):  # the last window's end may lie far beyond the recording
                    t_last = int(res.events["t"][-1])
                n_objects += len(res.boxes)
                ids.update(res.boxes)
                if origin is None:
                    origin = res.t0_us
                _advance(bar, res.t1_us if span is None else min(res.t1_us, span[1]), origin, n_windows)
            writer.add_unassigned(seen[0] - writer.n_written)  # events after the last window
    wall = time.perf_counter() - t_wall
    mismatch = ""
    if isinstance(flow_n_events, int) and flow_n_events != seen[0]:
        mismatch = (f"; WARNING: {job.flow_file} was computed for a recording of {flow_n_events} events, this one has "
                    f"{seen[0]} (flow of another recording?)")
    frames = ""
    if job.frames is not None:
        stale = (f", {plural(sink.stale_frames_removed, 'numbered frame')} of an earlier run removed"
                 if sink.stale_frames_removed else "")
        frames = f"; {plural(sink.n_frames, 'frame')} in {job.frames}{stale}"
    speed = ""
    if t_first is not None and t_last is not None and wall > 0:
        speed = f" in {wall:.1f} s ({real_time_factor((t_last - t_first) / 1e6 / wall)}x real time)"
    live = ""
    if job.realtime and latencies:
        pace = f"at {job.speed:g}x the sensor's pace" if math.isfinite(job.speed) else "as fast as it could be read"
        live = (f"; replayed {pace}: {n_windows} of {plural(n_windows + dropped[0], 'window')} "
                + (f"segmented, {dropped[0]} dropped to keep up (their events are labelled -1), labels "
                   if dropped[0] else "segmented, none dropped, labels ")
                + f"{np.median(latencies):.1f} ms after their window was complete (median; p90 "
                f"{np.percentile(latencies, 90):.1f} ms)")
    return (
        f"wrote {job.out}: {plural(writer.n_written, 'event')}, {plural(n_windows, 'window')}{speed}, "
        f"{plural(len(ids), 'distinct object')}, {n_objects / max(n_windows, 1):.2f} objects per window"
        + live + (f"; video {job.video}" if job.video else "") + frames + inferred + mismatch
    )


def write_window_labels(writer, results, stride_us: int):
    """Yield each window result of ``results`` (in window order, with ``index``,
    ``first_event``, ``events``, ``labels``, ``t0_us``) after appending to ``writer`` the labels
    it owns: its events up to the next window's start (``t0_us + stride_us``) that no earlier
    window labelled, after -1 for events no window covered. The rest of its events belong to
    the next window, unless that window never comes (dropped by a live run, or the end of
    the stream): then they keep this window's labels."""
    pending = None  # (window index, first event, labels) of the events the next window takes
    for res in results:
        if pending is not None:
            if res.index != pending[0] + 1:  # the next window was dropped
                writer.add_labels(pending[2][: max(res.first_event - pending[1], 0)])
            pending = None
        # Events before this window and not in any earlier one (gaps when stride > window).
        if res.first_event > writer.n_written:
            writer.add_unassigned(res.first_event - writer.n_written)
        own = int(np.searchsorted(res.events["t"], res.t0_us + stride_us, side="left"))
        skip = writer.n_written - res.first_event  # already labelled by an overlapping window
        if own > skip:
            writer.add_labels(res.labels[skip:own])
        at = max(own, skip)
        if len(res.labels) > at:
            pending = (res.index, res.first_event + at, res.labels[at:])
        yield res
    if pending is not None:
        writer.add_labels(pending[2])


def _live_windows(live, latencies: list[float], dropped: list[int]):
    """The windows of a live run (:func:`evseg.live.run_live`), noting each one's latency (ms)
    and the windows dropped before it."""
    for res in live:
        latencies.append(res.latency_ms)
        dropped[0] += res.dropped
        yield res.window
