"""The end-to-end streaming pipeline: raw events in, per-event labels, boxes and masks out.

Per window (default 10 ms, back to back):

1. normal flow on target events (learned ONNX model by default, plane-fit baseline, or
   precomputed per-event flow from a file),
2. optional undistortion of positions and normal flows (with a calibration),
3. segmentation of the normal flow (pre-processing, initialization with motion prediction
   from the previous window, alternating labeling and fitting),
4. persistent object ids (predicted boxes matched across windows),
5. labels for every event of the window: the label of its nearest graph node, -1 where no
   node is close enough.

As in the paper's system, whose pre-processing and segmentation are two independently running
modules, :meth:`MotionSegmentationPipeline.run` estimates the next window's normal flow and
prepares its node graph (:func:`evseg.segmentation.prepare_window`) on a second thread, or in
a second process, while the current window is segmented (``PipelineConfig.overlap`` and
``worker``): neither depends on the segmentation, so the results are identical and a stream
goes through faster on two cores.

Example::

    from evseg.pipeline import MotionSegmentationPipeline, PipelineConfig
    pipe = MotionSegmentationPipeline(PipelineConfig(window_us=10_000), sensor_size=(346, 260))
    for res in pipe.run(stream):          # an EventStream, e.g. from evseg.io.read_events
        print(res.index, res.boxes)       # {object id: (x0, y0, x1, y1)}
"""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Iterable, Iterator, Protocol

import numpy as np

from evseg.calibration import Calibration
from evseg.checks import is_whole
from evseg.errors import CalibrationError, ConfigError, EventDataError, EvsegError, FormatError
from evseg.events import EVENT_DTYPE, EventStream, checked_sensor_size, first_off_sensor
from evseg.flow_file import WindowFlow, check_flow, load_flow_file, slice_flow  # noqa: F401 (load_flow_file: public here too)
from evseg.tracking import ObjectTracker
from evseg.undistortion import UndistortionTable, undistort_normal_flow
from evseg.windows import EventHistory, Window, as_event_chunks, ordered_time_windows, stream_time_windows


class NormalFlowLike(Protocol):
    index: np.ndarray
    nx: np.ndarray
    ny: np.ndarray
    uncertainty: np.ndarray


FlowFn = Callable[[np.ndarray, tuple[int, int]], NormalFlowLike]

WORKERS = ("thread", "process")
"""Where :attr:`PipelineConfig.overlap` runs the next window's flow and preparation."""


@dataclass(frozen=True)
class PipelineConfig:
    """Settings of the streaming pipeline (segmentation settings live in ``segmentation``).

    Attributes:
        window_us: window duration in microseconds (paper: 10 ms on EVIMO).
        stride_us: time between window starts; None = ``window_us`` (back to back).
        flow: ``"learned"`` (ONNX model), ``"planefit"`` (classical baseline) or
            ``"precomputed"`` (flow given to :meth:`MotionSegmentationPipeline.run`).
        model_path: ONNX model for ``flow="learned"``; None = the model shipped with evseg.
        threads: onnxruntime threads (None = onnxruntime's default).
        target_cell_px: normal flow is computed for the latest event of each square cell of
            this side (px); None computes it for every event. The segmentation keeps one node
            per ``segmentation.cell_px`` cell, so cells smaller than that lose nothing.
        flow_context_us: the events of this span (us) before a window are neighbours of its
            events in the normal-flow estimate (learned and plane fit; see
            :mod:`evseg.veckm_flow.context`); they get no flow and no label themselves.
            0 = each window on its own.
        overlap: in :meth:`MotionSegmentationPipeline.run`, estimate the next window's normal
            flow and prepare its node graph on a second thread while this one is segmented
            (built-in estimators only; the estimator then uses ``threads`` or, when None, one
            thread, leaving the other core to the segmentation). Same results; on the 2-core
            development machine 42.5 -> 36.5 ms per window at 1 M events/s with
            ``worker="thread"``, 26.9 ms with ``worker="process"`` (``evseg bench pipeline``).
            The next window is read
            before this one is segmented: from a file that costs nothing, from a live source
            that the pipeline keeps up with it holds each result until the next window has
            arrived (one window, 10 ms, later). For live sources use :func:`evseg.live.run_live`,
            which overlaps only when the pipeline is behind and drops what it cannot reach.
            False: one window after the other.
        worker: where the overlapped share runs: ``"thread"`` (a thread of this process) or
            ``"process"`` (a child process, started at the first overlapped run and kept
            until :meth:`MotionSegmentationPipeline.close`). Python runs one thread's code at a
            time, so the thread and the segmentation take turns in their Python parts; the
            child process runs truly beside it and also fits round 0's sampled candidates
            (:func:`evseg.segmentation.window.with_sampled_candidates`; for the candidate count
            the current tracks make likely) for the segmentation.
            Same results either way. The process costs ~1.5 s to start and a second copy of
            the model and libraries in memory (~0.3 GB), so it pays off on recordings, not on
            a few windows; ``evseg bench pipeline`` uses it, and ``evseg segment`` unless the
            recording is known to be shorter than 5 s. The process is
            started with ``spawn``: in a script (not a notebook), run the pipeline under
            ``if __name__ == "__main__":``, as with any Python multiprocessing.
        min_track_windows: an object is reported (its events' labels, box and mask) only once
            its track has been found in this many windows, not necessarily consecutive (SORT's
            ``min_hits``); until then its events are labelled background (0) while the track
            still feeds motion prediction. 1 = every object at once. Most false objects live
            for a single window (about half of them on learned-flow validation scenes, against
            ~5 % of the true objects' detections), so 2 trades the first window of every object
            for fewer false ones.
        fast_edges: with ``flow="learned"``, a second, time-stretched look at the targets
            whose flow is fast (:mod:`evseg.veckm_flow.fast_edges`): the head underestimates
            edges that cross its window in a millisecond or two (a thrown ball). False: the
            head's first look alone.
        slow_edges: with ``flow="learned"``, a second, time-compressed look over twice the
            time (window plus context; the pipeline then keeps that much more of the stream)
            at the targets whose flow is slow (:mod:`evseg.veckm_flow.slow_edges`; ``evseg
            flow`` uses it by default): a better direction for slow edges, at 1.5-2.4x the
            flow's time on slow scenes (~3 ms more per window at 1 M events/s, where the flow
            runs beside the segmentation). Off by default here: on simulated validation scenes
            it found a few more objects with fewer false ones, but on the real one-motion
            recordings it put a false object in more windows (docs/normal_flow.md).
        mirrors: with ``flow="learned"``, the flow averaged over this many mirror images of
            each window (1, 2, 4 or 8; :mod:`evseg.veckm_flow.mirrors`): a more accurate flow at
            ``mirrors`` times the flow's time, for offline runs (docs/normal_flow.md, Mirror
            looks). 1: the window as it is.
        tracked_mirrors: with ``flow="learned"``, the mirror looks (1, 2, 4 or 8) for the
            targets where the object tracks expect an object: inside the boxes the tracks
            predict for the window, grown by ``tracked_margin_px``; the other targets get
            ``mirrors``. The flow is most worth its extra looks there: on the learned-flow
            validation scenes (seeds 900-909) 8 looks in the tracked boxes found 75.1 % of the
            objects against 72.9 % with one look everywhere and 76.5 % with 8 everywhere, and
            cut the windows with a false object from 15.2 to 14.1 % (ego-motion-only 9.7 ->
            8.0 %); held out (``evseg eval pipeline --tracked-mirrors 8``) 71.9 -> 73.0 % and
            20.3 -> 13.6 % (ego-motion-only 3.3 -> 2.1 %), but on the real one-motion
            recordings 12.6 -> 13.2 % of the windows with a false object, at 1.3-2.5x the time
            per window, so it is off by default. It costs far less than ``mirrors=8`` where
            the objects are small (docs/normal_flow.md). The boxes are the
            ones known when the window before is segmented (the tracks after window t - 2,
            moved on by two strides), so the flow of window t is still computed beside the
            segmentation of window t - 1 and the results do not depend on ``overlap`` or
            ``worker``. 1: off.
        tracked_margin_px: how far (px) around a predicted box ``tracked_mirrors`` applies
            (a track's box moves by its model's flow; the margin covers its error).
        tracked_max_targets: at most this many targets per window get ``tracked_mirrors``
            looks, the boxes taken smallest first, each whole or not at all: a bound on the
            extra time where the tracked objects are large. None: every target in the boxes.
        segmentation: a :class:`evseg.segmentation.SegmentationConfig` (None = defaults), a
            preset name (``"eed_like"``) or a mapping of its fields, so that
            ``PipelineConfig(**yaml.safe_load(load_result(path).config))`` rebuilds the
            configuration a result file stores.
    """

    window_us: int = 10_000
    stride_us: int | None = None
    flow: str = "learned"
    model_path: str | None = None
    threads: int | None = None
    target_cell_px: int | None = 2
    flow_context_us: int = 20_000
    overlap: bool = True
    worker: str = "thread"
    min_track_windows: int = 1
    fast_edges: bool = True
    slow_edges: bool = False
    mirrors: int = 1
    tracked_mirrors: int = 1
    tracked_margin_px: int = 8
    tracked_max_targets: int | None = None
    segmentation: object | None = None

    def __post_init__(self) -> None:
        if self.flow not in ("learned", "planefit", "precomputed"):
            raise ConfigError(f"pipeline.flow must be learned, planefit or precomputed, got {self.flow!r}")
        for name in ("window_us", "stride_us"):
            value = getattr(self, name)
            if value is None and name == "stride_us":
                continue
            if not is_whole(value) or value <= 0:
                raise ConfigError(f"pipeline.{name} must be a positive whole number of microseconds, got {value!r}")
            object.__setattr__(self, name, int(value))
        for name in ("threads", "target_cell_px"):
            value = getattr(self, name)
            if value is not None and (not is_whole(value) or value < 1):
                raise ConfigError(f"pipeline.{name} must be an integer >= 1 or null, got {value!r}")
        if not isinstance(self.overlap, (bool, np.bool_)):
            raise ConfigError(f"pipeline.overlap must be true or false, got {self.overlap!r}")
        if self.segmentation is not None:
            from evseg.segmentation.config import as_segmentation_config

            # A preset name or the mapping a result file's stored YAML holds: the same config.
            object.__setattr__(self, "segmentation",
                               as_segmentation_config(self.segmentation, source="pipeline.segmentation"))
        if self.worker not in WORKERS:
            raise ConfigError(
                f"pipeline.worker must be one of {', '.join(WORKERS)}, got {self.worker!r}")
        if not isinstance(self.min_track_windows, (int, np.integer)) or self.min_track_windows < 1:
            raise ConfigError(f"pipeline.min_track_windows must be an integer >= 1, got {self.min_track_windows!r}")
        if not isinstance(self.fast_edges, (bool, np.bool_)):
            raise ConfigError(f"pipeline.fast_edges must be true or false, got {self.fast_edges!r}")
        if not isinstance(self.slow_edges, (bool, np.bool_)):
            raise ConfigError(f"pipeline.slow_edges must be true or false, got {self.slow_edges!r}")
        from evseg.veckm_flow.mirrors import mirror_looks

        try:
            mirror_looks(self.mirrors)
        except ConfigError as exc:
            raise ConfigError(f"pipeline.{exc}") from None
        try:
            mirror_looks(self.tracked_mirrors)
        except ConfigError as exc:
            raise ConfigError(f"pipeline.tracked_{exc}") from None
        margin = self.tracked_margin_px
        if not isinstance(margin, (int, np.integer)) or isinstance(margin, bool) or margin < 0:
            raise ConfigError(f"pipeline.tracked_margin_px must be a non-negative integer (px), got {margin!r}")
        most = self.tracked_max_targets
        if most is not None and (not isinstance(most, (int, np.integer)) or isinstance(most, bool) or most < 0):
            raise ConfigError(f"pipeline.tracked_max_targets must be a non-negative integer or null, got {most!r}")
        ctx = self.flow_context_us
        if not (isinstance(ctx, (int, np.integer)) or (isinstance(ctx, float) and ctx.is_integer())) or ctx < 0:
            raise ConfigError(f"pipeline.flow_context_us must be a non-negative integer (us), got {ctx!r}")
        if self.flow == "learned":
            from evseg.veckm_flow.encoding import MAX_SLICE_SPAN_US

            if int(self.window_us) + int(ctx) > MAX_SLICE_SPAN_US:
                raise ConfigError(
                    f"pipeline.window_us + flow_context_us must be at most {MAX_SLICE_SPAN_US} us (the learned "
                    f"flow's longest slice), got {self.window_us} + {ctx}")


@dataclass
class WindowResult:
    """Everything the pipeline knows about one window.

    Attributes:
        index, t0_us, t1_us: window number and bounds (us).
        first_event: position of the window's first event in the input.
        events: the window's events (a view).
        labels: int16 per event of the window: -1 unassigned, 0 background, k object id.
        boxes: object id -> (x0, y0, x1, y1) inclusive px of the sensor's raw pixel grid, like
            the events (with a calibration, the segmentation's boxes and masks, which are in
            undistorted pixels, are mapped back through the undistortion table).
        masks: object id -> bool (height, width) dense mask, raw pixels likewise.
        flow_index, flow: positions (in ``events``) and (nx, ny) px/s of the target flows.
        segmentation: the raw :class:`evseg.segmentation` result (labels 1..K, models).
        timings_ms: stage -> milliseconds ('flow', 'preprocessing', ...; with ``overlap`` the
            flow, the pre-processing and the window-local share of 'initialization' ran on the
            worker thread or process while the previous window was segmented).
    """

    index: int
    t0_us: int
    t1_us: int
    first_event: int
    events: np.ndarray
    labels: np.ndarray
    boxes: dict[int, tuple[int, int, int, int]]
    masks: dict[int, np.ndarray]
    flow_index: np.ndarray
    flow: np.ndarray
    segmentation: object | None
    timings_ms: dict[str, float] = field(default_factory=dict)


class MotionSegmentationPipeline:
    """Segment an event stream window by window (see module docstring).

    Args:
        config: pipeline settings.
        sensor_size: (width, height) px.
        calibration: optional; positions and flows are undistorted before segmentation.
        flow_fn: override the normal-flow estimator: ``flow_fn(events, sensor_size)`` returning
            an object with ``index``, ``nx``, ``ny``, ``uncertainty`` (index into ``events``);
            it sees the window only (``flow_context_us`` applies to the built-in estimators).
    """

    def __init__(
        self,
        config: PipelineConfig = PipelineConfig(),
        sensor_size: tuple[int, int] | None = None,
        calibration: Calibration | None = None,
        flow_fn: FlowFn | None = None,
    ):
        from evseg.segmentation import SegmentationConfig

        if config is None:
            config = PipelineConfig()
        if not isinstance(config, PipelineConfig):
            raise ConfigError(f"MotionSegmentationPipeline: config must be a PipelineConfig, got {type(config).__name__}"
                              " (segmentation settings go in PipelineConfig(segmentation=...))")
        if isinstance(calibration, (str, Path)):
            from evseg.calibration import load_calibration

            calibration = load_calibration(calibration, sensor_size=sensor_size)
        elif calibration is not None and not isinstance(calibration, Calibration):
            raise ConfigError(f"MotionSegmentationPipeline: calibration must be a Calibration or a calibration file, "
                              f"got {type(calibration).__name__}")
        if sensor_size is None:
            raise ConfigError("the pipeline needs the sensor size (width, height)")
        self.config = config if config.segmentation is not None else replace(config, segmentation=SegmentationConfig())
        self.sensor_size = checked_sensor_size(sensor_size)  # a fractional size would be truncated
        if calibration is not None and tuple(int(v) for v in calibration.sensor_size) != self.sensor_size:
            # Intrinsics of another camera or resolution would undistort every event wrongly.
            raise CalibrationError(
                f"MotionSegmentationPipeline: the calibration is for {calibration.sensor_size[0]}x"
                f"{calibration.sensor_size[1]} px, the sensor is {self.sensor_size[0]}x{self.sensor_size[1]}")
        self.calibration = calibration
        self._undistortion = UndistortionTable.from_calibration(calibration) if calibration is not None else None
        self._estimator = None
        self._history_us = 0  # events kept before a window beyond flow_context_us (slow-edge look)
        self._tracked_estimator = None  # the learned flow with tracked_mirrors looks
        self._flow_split: dict[str, float] = {}  # the last flow's parts (s)
        if flow_fn is not None:
            self._flow_fn = lambda events, sensor_size, context, t0_us: flow_fn(events, sensor_size)
        else:
            self._flow_fn = self._make_flow_fn()
        # A caller's flow_fn may not expect to run on another thread: only built-in estimators overlap.
        self._overlap = bool(self.config.overlap) and flow_fn is None and self._flow_fn is not None
        self._worker_process = None  # the "process" worker's pool, started by the first run
        self._waited_s = 0.0  # how long the segmentation waits for the worker (running mean, s)
        self._worker_finalizer = None
        self._thread_pool = None  # the "thread" worker of submit_prepare (live runs), kept until close()
        self.reset()

    def close(self) -> None:
        """Stop the worker process of ``worker="process"`` (if one was started); the pipeline
        stays usable and starts a new one when it needs it. Also called by ``with`` and at exit."""
        if self._worker_finalizer is not None:
            self._worker_finalizer()
        self._worker_process = self._worker_finalizer = None
        if self._thread_pool is not None:
            self._thread_pool.shutdown(wait=True, cancel_futures=True)
            self._thread_pool = None

    def __enter__(self) -> "MotionSegmentationPipeline":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def reset(self) -> None:
        """Forget the previous window (motion prediction) and the object tracks. A run still
        being iterated (:meth:`run`, :func:`evseg.live.run_live`) is superseded: resuming it
        raises instead of mixing its windows with the new state."""
        self._run_token = object()
        self._previous = None
        self._tracker = ObjectTracker()
        # object id -> (last model, last per-window displacement px) of each live track
        self._track_motion: dict[int, tuple[np.ndarray, tuple[float, float]]] = {}
        # window index -> (B, 4) boxes where that window's flow gets tracked_mirrors looks
        self._tracked_boxes: dict[int, np.ndarray] = {}

    def warm_up(self) -> float:
        """Pay the one-time set-up now (compiling the encoder's loops, the ONNX session's first
        run, the fitter's first solve, starting the worker process of ``worker="process"``: the
        first window of a run takes ~0.5-1 s on 2 cores, ~2 s more with the process) by segmenting
        a few windows of synthetic moving edges, then forget them (:meth:`reset`).
        Call it before a live source starts, so that its first windows are not late. Returns
        the seconds it took. With ``flow="precomputed"`` only the segmentation is warmed."""
        from evseg.veckm_flow.synthetic import translating_edges

        tic = time.perf_counter()
        cfg = self.config
        span = 3 * int(cfg.window_us)
        scene = translating_edges(self.sensor_size, n_edges=40, duration_us=span, seed=0)
        for window in stream_time_windows([scene.events], cfg.window_us, cfg.stride_us):
            if self._flow_fn is None:
                own = slice(window.first_event, window.first_event + len(window.events))
                self.process(window, WindowFlow(np.arange(len(window.events)), scene.nx[own], scene.ny[own], None))
            elif self.overlaps:
                # also starts (worker="process") and warms the worker that live runs use
                self.finish_prepared(window, self.submit_prepare(window, None))
            else:
                self.process(window)
        self.reset()
        return time.perf_counter() - tic

    def skip_windows(self, n: int) -> None:
        """The next ``n`` windows will not be segmented (a live source the pipeline fell behind,
        :func:`evseg.live.run_live`): move each object track's box on by ``n`` more strides with
        its last displacement, so an object whose motion holds is matched to its track (and keeps
        its id) in the window after the gap. The skipped windows do not count as misses.
        Motion prediction from the previous window needs nothing: it uses the windows' times."""
        if not is_whole(n) or n < 0:
            raise ValueError(f"skip_windows: n must be a whole number of windows >= 0, got {n!r}")
        n = int(n)
        if n == 0:
            return
        self._tracker.predict({oid: (dx * n, dy * n) for oid, (_, (dx, dy)) in self._track_motion.items()},
                              self.sensor_size)
        # Boxes remembered for tracked_mirrors are keyed by window index and were moved for no gap.
        self._tracked_boxes = {}

    def _make_flow_fn(self) -> FlowFn | None:
        cfg = self.config
        if cfg.flow == "precomputed":
            return None
        from evseg.veckm_flow import select_targets
        from evseg.veckm_flow.context import flow_with_context, history_span_us, split_history

        tracked_est = None
        if cfg.flow == "planefit":
            from evseg.veckm_flow import PlaneFitNormalFlow

            est = PlaneFitNormalFlow()
        else:
            from evseg.veckm_flow import OnnxNormalFlow
            from evseg.veckm_flow.fast_edges import FastEdges
            from evseg.veckm_flow.slow_edges import SlowEdges

            # Overlapped, the flow has its own thread next to the segmentation's: one core each.
            threads = cfg.threads if cfg.threads is not None else (1 if cfg.overlap else None)
            est = OnnxNormalFlow(model_path=cfg.model_path, threads=threads,
                                 fast_edges=FastEdges() if cfg.fast_edges else None,
                                 # the presets' residual scales are tuned to the first look's uncertainty
                                 slow_edges=SlowEdges(uncertainty="first") if cfg.slow_edges else None,
                                 mirrors=int(cfg.mirrors))
            if int(cfg.tracked_mirrors) > int(cfg.mirrors):
                tracked_est = est.with_mirrors(int(cfg.tracked_mirrors))
        self._estimator = est
        self._tracked_estimator = tracked_est
        self._history_us = history_span_us(est, int(cfg.window_us) + int(cfg.flow_context_us))

        def flow_fn(events: np.ndarray, sensor_size: tuple[int, int], kept: np.ndarray | None, t0_us: int,
                    boxes: np.ndarray | None = None):
            """``kept``: the events before the window (context, and history when wanted);
            ``boxes``: (B, 4) boxes where ``tracked_mirrors`` applies (segmentation px)."""
            targets = select_targets(events, sensor_size, cell_px=cfg.target_cell_px)
            history = None
            if self._history_us and kept is not None:
                history, kept = split_history(kept, t0_us, int(cfg.flow_context_us))
            inside = None
            if tracked_est is not None and boxes is not None and len(boxes) and len(targets):
                inside = self._in_tracked_boxes(events, targets, boxes)
            # With a calibration the estimator encodes undistorted positions and returns flow on the
            # sensor grid, as `evseg flow` does; positions and flows are undistorted after (_prepare()).
            calibration = self.calibration
            if inside is None or not inside.any():
                flow = flow_with_context(est, events, sensor_size, targets, kept, calibration, history=history)
                self._flow_split = dict(getattr(est, "last_timing_s", None) or {})
                return flow
            # Each target's flow does not depend on the other targets: two calls give the
            # flows one call with each look count would.
            rest = flow_with_context(est, events, sensor_size, targets[~inside], kept, calibration, history=history)
            split = dict(est.last_timing_s)
            t_tracked = time.perf_counter()
            tracked = flow_with_context(tracked_est, events, sensor_size, targets[inside], kept, calibration,
                                        history=history)
            for part, seconds in tracked_est.last_timing_s.items():
                split[part] = split.get(part, 0.0) + seconds
            split["tracked"] = time.perf_counter() - t_tracked
            self._flow_split = split
            return _merge_flows(targets, inside, rest, tracked)

        return flow_fn

    def _in_tracked_boxes(self, events: np.ndarray, targets: np.ndarray, boxes: np.ndarray) -> np.ndarray:
        """bool per target: inside one of ``boxes`` (segmentation px: undistorted with a
        calibration) grown by ``tracked_margin_px``, at most ``tracked_max_targets`` of them:
        the boxes are taken smallest first, each whole or not at all."""
        x, y = events["x"][targets], events["y"][targets]
        if self._undistortion is not None:
            x, y = self._undistortion.xu[y, x], self._undistortion.yu[y, x]
        m = float(self.config.tracked_margin_px)
        b = np.asarray(boxes, dtype=np.float64)
        b = b[np.argsort((b[:, 2] - b[:, 0] + 1) * (b[:, 3] - b[:, 1] + 1), kind="stable")]
        budget = self.config.tracked_max_targets
        chosen = np.zeros(len(targets), dtype=bool)
        for x0, y0, x1, y1 in b:
            box = (x >= x0 - m) & (x <= x1 + m) & (y >= y0 - m) & (y <= y1 + m) & ~chosen
            if budget is None or int(chosen.sum()) + int(box.sum()) <= budget:
                chosen |= box
        return chosen

    # ------------------------------------------------------------------ one window
    def process(
        self, window: Window, flow: NormalFlowLike | None = None, context: np.ndarray | None = None
    ) -> WindowResult:
        """Segment one window. ``flow`` (indices into ``window.events``) overrides the estimator;
        ``context``: the events of the :attr:`kept_us` before the window (:meth:`run` supplies
        them; an :class:`~evseg.windows.EventHistory` of that span keeps them), neighbours for
        the normal flow only: its last ``flow_context_us`` for every look, the rest (with
        ``slow_edges``) for the slow-edge look."""
        if not isinstance(window, Window):
            raise ConfigError(f"process() takes a Window (evseg.windows.Window, as run() cuts them), got "
                              f"{type(window).__name__}; to segment events, use run()")
        if context is not None and (not isinstance(context, np.ndarray) or context.dtype != EVENT_DTYPE
                                    or context.ndim != 1):
            # Its order and pixels are checked by the flow estimator with the window's events
            # (an O(1) check here: run() calls this for every window).
            got = f"{context.dtype} {context.shape}" if isinstance(context, np.ndarray) else type(context).__name__
            raise EventDataError(f"process(): context must be a 1-D event array ({EVENT_DTYPE}), got {got}")
        timings: dict[str, float] = {}
        if flow is None:
            flow, timings = self._estimate_flow(window.events, context, window.t0_us,
                                                self._tracked_boxes.get(window.index))
        else:
            timings["flow"] = 0.0
        return self._segment(window, flow, timings)

    def _estimate_flow(self, events: np.ndarray, context: np.ndarray | None,
                       t0_us: int, boxes: np.ndarray | None = None) -> tuple[NormalFlowLike, dict[str, float]]:
        """Normal flow of a window's events with its timings (ms): 'flow' and the estimator's
        parts (e.g. 'flow_encode', 'flow_network'; 'flow_tracked': the share of the targets in
        the tracked ``boxes``). Safe to run on the overlap thread."""
        if self._flow_fn is None:
            raise EvsegError("pipeline.flow is 'precomputed' but no flow was given for this window")
        t_start = time.perf_counter()
        self._flow_split = {}
        # Boxes exist only with tracked_mirrors (built-in learned flow): other flow functions
        # keep their four arguments.
        more = {} if boxes is None else {"boxes": boxes}
        flow = self._flow_fn(events, self.sensor_size, context, t0_us, **more)
        timings: dict[str, float] = {}
        split = self._flow_split
        for part, seconds in split.items():  # e.g. encode / network of the learned flow
            timings[f"flow_{part}"] = seconds * 1e3
        timings["flow"] = (time.perf_counter() - t_start) * 1e3
        return flow, timings

    def _segment(self, window: Window, flow: NormalFlowLike, timings: dict[str, float]) -> WindowResult:
        """Everything after the normal flow (steps 2-5 of the module docstring)."""
        return self._finish(window, *self._prepare(window, flow, timings))

    def _estimate_and_prepare(self, window: Window, context: np.ndarray | None,
                              sample_counts: tuple[int, ...] = (), boxes: np.ndarray | None = None) -> tuple:
        """The overlap worker's share of a window: its normal flow (``boxes``: where
        ``tracked_mirrors`` applies), :meth:`_prepare` and round 0's sampled candidates for each
        of ``sample_counts``."""
        flow, timings = self._estimate_flow(window.events, context, window.t0_us, boxes)
        prepared, *rest = self._prepare(window, flow, timings)
        if sample_counts:
            from evseg.segmentation.window import with_sampled_candidates

            prepared = with_sampled_candidates(prepared, sample_counts)
        return (prepared, *rest)

    def _worker_sample_counts(self) -> tuple[int, ...]:
        """Round 0's candidate counts the worker process should sample and fit for the next
        window: none when the segmentation had to wait for the worker last time (the worker is
        the slower of the two on average, e.g. the flow of a large sensor), else the count the
        current tracks make likely (fewer when objects are tracked: they give predicted
        candidates). A count not prepared costs the segmentation one sampling, never a
        different result."""
        if self._waited_s > 2e-3:
            return ()
        seg = self.config.segmentation
        return (seg.n_sampled_with_prediction if self._tracker.tracks else seg.n_sampled,)

    def _prepare(self, window: Window, flow: NormalFlowLike, timings: dict[str, float]) -> tuple:
        """Flow positions (undistorted), the window's event positions and the segmentation's
        window-local part (:func:`evseg.segmentation.prepare_window`: nodes, graph, per-node
        terms), none of which needs the previous window. Safe to run on the overlap thread."""
        from evseg.segmentation import prepare_window
        from evseg.segmentation.outputs import nearest_node_index

        ev = window.events
        idx, nx, ny, unc = _window_flow_arrays(flow, len(ev), window.index)
        ok = np.isfinite(nx) & np.isfinite(ny) & ((nx != 0) | (ny != 0))
        idx, nx, ny = idx[ok], nx[ok], ny[ok]
        unc = unc[ok] if unc is not None else None
        fx = ev["x"][idx]
        fy = ev["y"][idx]
        ft = ev["t"][idx]
        t0 = time.perf_counter()
        if self._undistortion is not None:
            fx, fy, nx, ny = undistort_normal_flow(self._undistortion, fx, fy, nx, ny)
            ex, ey = self._undistortion.xu[ev["y"], ev["x"]], self._undistortion.yu[ev["y"], ev["x"]]
        else:
            fx, fy = fx.astype(np.float64), fy.astype(np.float64)
            ex, ey = ev["x"].astype(np.float64), ev["y"].astype(np.float64)
        timings["undistort"] = (time.perf_counter() - t0) * 1e3

        # All the window's events give each node its support (flow covers only the targets).
        prepared = prepare_window(fx, fy, ft, nx, ny, uncertainty=unc, config=self.config.segmentation,
                                  sensor_size=self.sensor_size, event_xy=(ex, ey))
        # Each event's nearest node depends on the node positions only (label propagation).
        t0 = time.perf_counter()
        nearest = nearest_node_index(prepared.graph.x, prepared.graph.y, ex, ey, prepared.max_propagation_px)
        timings["propagation"] = (time.perf_counter() - t0) * 1e3
        return prepared, idx, nx, ny, nearest, timings

    def _finish(self, window: Window, prepared, idx: np.ndarray, nx: np.ndarray, ny: np.ndarray,
                nearest: np.ndarray, timings: dict[str, float]) -> WindowResult:
        """Segmentation with motion prediction from the previous window, object ids, labels of
        every event (needs the previous window's result: runs in window order)."""
        from evseg.segmentation import segment_prepared
        from evseg.segmentation.outputs import labels_of_nearest

        ev = window.events
        seg = segment_prepared(prepared, previous=self._previous, tracked_objects=self._tracked_objects())
        for k, v in getattr(seg, "timings", {}).items():
            timings[k] = v
        self._previous = seg

        t0 = time.perf_counter()
        mapping = self._tracker.update({int(k): tuple(v) for k, v in seg.boxes.items()})
        seg_labels = labels_of_nearest(seg.node_labels, nearest)  # -1 beyond max_propagation_px
        # Per-window labels 1..K -> persistent object ids (0 and -1 unchanged); objects of
        # tracks not yet confirmed (min_track_windows) -> background.
        shown = {label: oid for label, oid in mapping.items()
                 if self._tracker.hits.get(oid, 0) >= self.config.min_track_windows}
        lut = np.arange(-1, seg.n_objects + 1, dtype=np.int64)
        for label in mapping:
            lut[label + 1] = shown.get(label, 0)
        labels = lut[seg_labels + 1].astype(np.int16)
        boxes = {shown[int(k)]: tuple(int(c) for c in v) for k, v in seg.boxes.items() if int(k) in shown}
        masks = {shown[int(k)]: v for k, v in (getattr(seg, "masks", None) or {}).items() if int(k) in shown}
        if self._undistortion is not None:
            # Segmentation (and the tracks) work in undistorted pixels; boxes and masks are
            # reported in the sensor's raw pixels, like the events their labels belong to.
            boxes, masks = self._to_raw_pixels(boxes, masks, ev, labels)
        else:
            # The reported box is the extent of the reported mask (what the evaluations score),
            # not the region's box of node positions rounded outwards, which can be 1 px larger.
            from evseg.undistortion import raw_box

            boxes = {oid: (raw_box(masks[oid]) or box) if oid in masks else box for oid, box in boxes.items()}
        timings["propagation"] += (time.perf_counter() - t0) * 1e3
        self._predict_tracks(seg, mapping)
        if self._tracked_estimator is not None:
            self._remember_tracked_boxes(window.index)
        return WindowResult(
            index=window.index, t0_us=window.t0_us, t1_us=window.t1_us, first_event=window.first_event,
            events=ev, labels=labels, boxes=boxes, masks=masks, flow_index=idx,
            flow=np.stack([nx, ny], axis=-1), segmentation=seg, timings_ms=timings,
        )

    def _to_raw_pixels(self, boxes: dict, masks: dict, events: np.ndarray, labels: np.ndarray) -> tuple[dict, dict]:
        """Boxes and masks of a calibrated run (undistorted px) in raw sensor pixels: each mask
        looked up through the undistortion table, each box that mask's extent (or, for an
        object whose mask covers no raw pixel, the extent of its labelled events)."""
        from evseg.undistortion import mask_to_raw, raw_box

        raw_masks = {oid: mask_to_raw(self._undistortion, m) for oid, m in masks.items()}
        raw_boxes = {}
        for oid in boxes:
            box = raw_box(raw_masks[oid]) if oid in raw_masks else None
            if box is None:
                own = labels == oid
                if not own.any():
                    continue
                x, y = events["x"][own], events["y"][own]
                box = (int(x.min()), int(y.min()), int(x.max()), int(y.max()))
            raw_boxes[oid] = box
        return raw_boxes, {oid: m for oid, m in raw_masks.items() if oid in raw_boxes}

    def _tracked_objects(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Boxes (moved to this window) and last models of the live tracks, for motion
        prediction; None before any object was seen."""
        ids = [oid for oid in sorted(self._tracker.tracks) if oid in self._track_motion]
        if not ids:
            return None
        boxes = np.array([self._tracker.tracks[oid] for oid in ids], dtype=np.float64)
        return boxes, np.array([self._track_motion[oid][0] for oid in ids])

    def _remember_tracked_boxes(self, index: int) -> None:
        """After window ``index``: the boxes of the live tracks moved on by one more stride
        (the tracker holds them for window ``index + 1``), for window ``index + 2``'s flow,
        which the overlapped run starts before window ``index + 1`` is segmented."""
        self._tracked_boxes = {k: v for k, v in self._tracked_boxes.items() if k > index}
        boxes = []
        for oid in sorted(self._tracker.tracks):
            dx, dy = self._track_motion[oid][1] if oid in self._track_motion else (0.0, 0.0)
            x0, y0, x1, y1 = self._tracker.tracks[oid]
            boxes.append((x0 + dx, y0 + dy, x1 + dx, y1 + dy))
        self._tracked_boxes[index + 2] = np.array(boxes, dtype=np.float64).reshape(-1, 4)

    def _predict_tracks(self, seg, mapping: dict[int, int]) -> None:
        """Move each tracked box by its model's flow at the box centre over one stride; a
        track missed in this window moves on with its last displacement."""
        from evseg.segmentation.motion_model import flow_field

        dt_s = (self.config.stride_us or self.config.window_us) * 1e-6
        ox, oy = seg.origin_px
        for label, oid in mapping.items():
            x0, y0, x1, y1 = seg.boxes[label]
            cx, cy = np.array([(x0 + x1) / 2.0 - ox]), np.array([(y0 + y1) / 2.0 - oy])
            u, v = flow_field(np.asarray(seg.models[label : label + 1]), cx, cy)
            self._track_motion[oid] = (np.array(seg.models[label], dtype=np.float64),
                                       (float(u[0, 0]) * dt_s, float(v[0, 0]) * dt_s))
        self._track_motion = {k: v for k, v in self._track_motion.items() if k in self._tracker.tracks}
        self._tracker.predict({oid: motion[1] for oid, motion in self._track_motion.items()}, self.sensor_size)

    # ------------------------------------------------------------------ streams
    def run(
        self,
        source: EventStream | np.ndarray | Iterable[np.ndarray],
        precomputed_flow: dict[str, np.ndarray] | None = None,
        *,
        flow_source: str = "precomputed_flow",
    ) -> Iterator[WindowResult]:
        """Segment a whole stream: an EventStream, one event array (:data:`~evseg.events.EVENT_DTYPE`)
        or an iterable of event chunks, each sorted by time and each starting no earlier than
        the one before ended (else :class:`~evseg.errors.EventDataError` naming the chunk).
        Each call starts afresh (:meth:`reset`): object ids from 1, no tracks carried over.

        ``precomputed_flow``: the arrays of an ``evseg flow`` file (``index`` into the whole
        input, ``nx``, ``ny`` px/s, optional ``uncertainty``), sorted by ``index``; an index
        past the last event raises :class:`~evseg.errors.FormatError` naming ``flow_source``
        once the stream has ended.
        """
        return self._exclusive(self._run(source, precomputed_flow, flow_source))

    def _exclusive(self, run: Iterator[WindowResult]) -> Iterator[WindowResult]:
        """``run``'s results while it owns the pipeline's state: once another run (or
        :meth:`reset`) has started afresh, resuming this one raises :class:`ConfigError`
        rather than yielding labels from the other run's tracks."""
        token = None
        try:
            while True:
                if token is not None and self._run_token is not token:
                    raise ConfigError(
                        "this run of the pipeline was superseded: a later run(), run_live() or reset() on the same "
                        "pipeline started afresh; iterate one run at a time, or use one pipeline per stream")
                try:
                    result = next(run)
                except StopIteration:
                    return
                if token is None:
                    token = self._run_token  # the run's reset() has happened by its first window
                yield result
        finally:
            run.close()

    def _run(self, source, precomputed_flow, flow_source: str) -> Iterator[WindowResult]:
        if precomputed_flow is not None:
            precomputed_flow = check_flow(precomputed_flow, source=f"MotionSegmentationPipeline.run: {flow_source}")
        # Each run starts afresh (no tracks or motion prediction from an earlier run, object ids
        # from 1): the same stream gives the same labels however often it is run.
        self.reset()
        seen = [0]
        chunks = _checked_chunks(as_event_chunks(source, "MotionSegmentationPipeline.run"), seen, self.sensor_size)
        cfg = self.config
        needs_context = precomputed_flow is None and cfg.flow != "precomputed"
        history = EventHistory(self.kept_us if needs_context else 0)
        windows = ordered_time_windows(chunks, cfg.window_us, cfg.stride_us)  # _checked_chunks checked them
        if self._overlap and precomputed_flow is None:
            yield from self._run_overlapped(windows, history)
            return
        for window in windows:
            flow = None
            if precomputed_flow is not None:
                flow = slice_flow(precomputed_flow, window.first_event, len(window.events))
            result = self.process(window, flow, context=history.before(window))
            history.add(window)
            yield result
        index = None if precomputed_flow is None else precomputed_flow["index"]
        if index is not None and len(index) and index[-1] >= seen[0]:
            raise FormatError(f"{flow_source}: key 'index' refers to event {int(index[-1])} but the stream "
                              f"has {seen[0]} events (flow of another recording?)")

    def _run_overlapped(self, windows: Iterator[Window], history: EventHistory) -> Iterator[WindowResult]:
        """:meth:`run` with the flow of window t + 1 estimated by the worker (thread or process)
        while window t is segmented. Results, and the order in which errors surface, are those of the
        sequential loop: a window whose successor cannot be read is still yielded first."""
        from concurrent.futures import ThreadPoolExecutor

        if self.config.worker == "process":
            pool = self._process_pool()
            # The worker keeps its own copy of the recent events (the flow's context): each
            # window's events cross to it once. Window t + 1 is submitted before window t is
            # segmented: the tracks guess its candidate count.
            run_id = next(_RUN_IDS)
            history = EventHistory(0)  # the worker holds the context: no copies kept here
            self._waited_s = 0.0
            submit = lambda window, context: pool.submit(  # noqa: E731
                _prepare_in_worker, window, run_id, self._worker_sample_counts(),
                self._tracked_boxes.get(window.index))
        else:
            pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="evseg-flow")
            submit = lambda window, context: pool.submit(  # noqa: E731
                self._estimate_and_prepare, window, context, (), self._tracked_boxes.get(window.index))
        pending = job = None  # (window, future of what _finish needs)
        try:
            while True:
                try:
                    window = next(windows, None)
                except BaseException:
                    if pending is not None:  # the window read before the failure still counts
                        yield self._finish(pending[0], *self._prepared(pending[1]))
                        pending = None
                    raise
                job = None
                if window is not None:
                    job = (window, submit(window, history.before(window)))
                    history.add(window)
                if pending is not None:
                    # Window 0 waits for its flow whatever the speeds: not counted.
                    ready = self._prepared(pending[1], count_wait=pending[0].index > 0)
                    yield self._finish(pending[0], *ready)
                if job is None:
                    return
                pending = job
        finally:
            # An abandoned or failed run: drop queued work; a flow in progress ends on its own
            # (the worker process stays for the next run, its result is never read).
            for left in (pending, job):
                if left is not None:
                    left[1].cancel()
            if self.config.worker != "process":
                pool.shutdown(wait=False, cancel_futures=True)

    @property
    def overlaps(self) -> bool:
        """Whether a worker computes the next window's flow and graph while one is segmented
        (``config.overlap`` with a built-in estimator)."""
        return self._overlap

    def submit_prepare(self, window: Window, context: np.ndarray | None):
        """Start the worker's share of ``window`` (``config.worker``): its normal flow, with
        ``context`` (the events of the :attr:`kept_us` before it) as neighbours, and its graph.
        Returns a future for :meth:`finish_prepared`. For callers that pick the windows
        themselves (:func:`evseg.live.run_live`); :meth:`run` does this on its own."""
        boxes = self._tracked_boxes.get(window.index)
        if self.config.worker == "process":
            return self._process_pool().submit(_prepare_with_context_in_worker, window, context,
                                               self._worker_sample_counts(), boxes)
        if self._thread_pool is None:
            from concurrent.futures import ThreadPoolExecutor

            self._thread_pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="evseg-flow")
        return self._thread_pool.submit(self._estimate_and_prepare, window, context, (), boxes)

    def finish_prepared(self, window: Window, future) -> WindowResult:
        """Segment ``window`` once its worker share (:meth:`submit_prepare`) is done: motion
        prediction, labels, object ids. Windows must be finished in time order."""
        return self._finish(window, *self._prepared(future, count_wait=self._previous is not None))

    @property
    def kept_us(self) -> int:
        """How long (us) before each window the events are needed (``process``'s ``context``):
        the flow's context and, with the slow-edge look, its history (50 ms with the defaults
        and ``slow_edges=True``, else 20 ms)."""
        return int(self.config.flow_context_us) + self._history_us

    def _prepared(self, future, count_wait: bool = False) -> tuple:
        """The overlapped share of a window, from its worker; a worker process that died is
        reported as such (and a new one starts with the next run)."""
        from concurrent.futures.process import BrokenProcessPool

        tic = time.perf_counter()
        try:
            return future.result()
        except BrokenProcessPool as exc:
            self.close()
            raise EvsegError(f"the pipeline's worker process stopped unexpectedly ({exc}); "
                             "run again, or use pipeline.worker: thread") from None
        finally:
            if count_wait:
                self._waited_s = 0.7 * self._waited_s + 0.3 * (time.perf_counter() - tic)

    def _process_pool(self):
        """The worker process (``worker="process"``), started on first use: a pipeline of its
        own (same config, sensor, calibration) that estimates the flow and prepares windows."""
        if self._worker_process is None:
            import multiprocessing
            import weakref
            from concurrent.futures import ProcessPoolExecutor

            # spawn, not fork: this process may already run onnxruntime's and torch's threads.
            pool = ProcessPoolExecutor(
                max_workers=1, mp_context=multiprocessing.get_context("spawn"), initializer=_start_worker,
                initargs=(self.config, self.sensor_size, self.calibration))
            self._worker_process = pool
            self._worker_finalizer = weakref.finalize(self, pool.shutdown, wait=True,
                                                      cancel_futures=True)
        return self._worker_process


_WORKER_PIPELINE: MotionSegmentationPipeline | None = None  # in the worker process only
_WORKER_HISTORY: tuple[int, EventHistory] | None = None  # (run id, recent events) in the worker
_RUN_IDS = itertools.count()


def _start_worker(config: PipelineConfig, sensor_size: tuple[int, int],
                  calibration: Calibration | None) -> None:
    """Initializer of the worker process: its own pipeline; Ctrl-C is the parent's to handle
    (the terminal sends it to both processes; the parent stops the worker)."""
    import signal

    global _WORKER_PIPELINE
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _WORKER_PIPELINE = MotionSegmentationPipeline(config, sensor_size=sensor_size,
                                                  calibration=calibration)


def _prepare_in_worker(window: Window, run_id: int, sample_counts: tuple[int, ...],
                       boxes: np.ndarray | None = None) -> tuple:
    """One window's overlapped share in the worker process (see ``PipelineConfig.worker``).
    The windows of a run arrive in order; the worker keeps the events before each one (the
    flow's context) itself, as :meth:`MotionSegmentationPipeline.run` does."""
    global _WORKER_HISTORY
    if _WORKER_HISTORY is None or _WORKER_HISTORY[0] != run_id:
        _WORKER_HISTORY = (run_id, EventHistory(_WORKER_PIPELINE.kept_us))
    history = _WORKER_HISTORY[1]
    context = history.before(window)
    history.add(window)
    return _WORKER_PIPELINE._estimate_and_prepare(window, context, sample_counts, boxes)


def _prepare_with_context_in_worker(window: Window, context: np.ndarray | None, sample_counts: tuple[int, ...],
                                    boxes: np.ndarray | None = None) -> tuple:
    """:func:`_prepare_in_worker` for a caller that picks the windows (a live run, which may
    drop some): the flow's context comes with the window instead of from the worker's history."""
    return _WORKER_PIPELINE._estimate_and_prepare(window, context, sample_counts, boxes)


def _window_flow_arrays(flow, n_events: int, window_index: int):
    """``(index, nx, ny, uncertainty or None)`` of one window's flow (a :class:`NormalFlow`, or
    any object or mapping with those fields), checked against the window's ``n_events``: a
    flow from a ``flow_fn`` or given to :meth:`MotionSegmentationPipeline.process` must index
    the window's own events (-1 would silently be its last event)."""
    where = f"window {window_index}: the flow"
    get = (lambda k: flow.get(k)) if isinstance(flow, dict) else (lambda k: getattr(flow, k, None))
    idx, nx, ny, unc = (get(k) for k in ("index", "nx", "ny", "uncertainty"))
    if idx is None or nx is None or ny is None:
        raise EventDataError(f"{where} must have index, nx, ny (a NormalFlow or a mapping of them), got "
                             f"{type(flow).__name__}")
    idx = np.asarray(idx)
    if idx.ndim != 1 or not (np.issubdtype(idx.dtype, np.integer) or len(idx) == 0):
        raise EventDataError(f"{where}: 'index' must be 1-D integer positions, got {idx.dtype} {idx.shape}")
    idx = idx.astype(np.int64, copy=False)
    arrays = [np.asarray(a, dtype=np.float32) for a in (nx, ny)]
    if unc is not None:
        arrays.append(np.asarray(unc, dtype=np.float32))
    for name, a in zip(("nx", "ny", "uncertainty"), arrays):
        if a.shape != idx.shape:
            raise EventDataError(f"{where}: '{name}' has shape {a.shape}, 'index' {idx.shape}")
    if len(idx) and (idx.min() < 0 or idx.max() >= n_events):
        bad = int(idx.min()) if idx.min() < 0 else int(idx.max())
        raise EventDataError(f"{where}: 'index' {bad} is not one of the window's {n_events} events")
    return idx, arrays[0], arrays[1], arrays[2] if unc is not None else None


def _merge_flows(targets: np.ndarray, inside: np.ndarray, rest, tracked):
    """One NormalFlow over ``targets`` (in their order) from the flows of ``targets[~inside]``
    and ``targets[inside]``."""
    from evseg.veckm_flow.result import NormalFlow

    nx = np.empty(len(targets), dtype=np.float32)
    ny = np.empty(len(targets), dtype=np.float32)
    unc = np.empty(len(targets), dtype=np.float32)
    for part, where in ((rest, ~inside), (tracked, inside)):
        nx[where], ny[where], unc[where] = part.nx, part.ny, part.uncertainty
    return NormalFlow(targets, nx, ny, unc)


def _checked_chunks(chunks: Iterable[np.ndarray], seen: list[int],
                    sensor_size: tuple[int, int]) -> Iterator[np.ndarray]:
    """``chunks`` as they are, after checking that each is events on the sensor, sorted by
    time, and that none starts before the previous one ended (a chunk out of order would be
    dropped unseen by the windowing); counts the events in ``seen[0]``."""
    last_t = None
    for i, chunk in enumerate(chunks):
        if not isinstance(chunk, np.ndarray) or chunk.dtype != EVENT_DTYPE:
            got = f"dtype {chunk.dtype}" if isinstance(chunk, np.ndarray) else type(chunk).__name__
            raise EventDataError(f"MotionSegmentationPipeline.run: chunk {i} must be an event array of dtype "
                                 f"{EVENT_DTYPE} (evseg.events.make_events(x, y, t, p) makes one), got {got}")
        if len(chunk) == 0:
            continue
        t = chunk["t"]
        if len(t) > 1 and bool(np.any(t[1:] < t[:-1])):
            at = int(np.flatnonzero(t[1:] < t[:-1])[0])
            raise EventDataError(f"MotionSegmentationPipeline.run: chunk {i}: field 't' goes back in time at "
                                 f"event {at + 1} ({int(t[at])} -> {int(t[at + 1])} us); sort the events first")
        if last_t is not None and int(t[0]) < last_t:
            raise EventDataError(f"MotionSegmentationPipeline.run: chunk {i} starts at t={int(t[0])} us, before "
                                 f"the previous chunk's last event at t={last_t} us; chunks must follow each "
                                 "other in time")
        off = first_off_sensor(chunk, sensor_size)
        if off is not None:
            raise EventDataError(f"MotionSegmentationPipeline.run: chunk {i}: {off} is outside the "
                                 f"{sensor_size[0]}x{sensor_size[1]} sensor the pipeline was made for")
        last_t = int(t[-1])
        seen[0] += len(chunk)
        yield chunk

