"""Segmentation of the real recordings in the shared data folder (no ground truth).

``evseg eval pipeline-real`` runs the pipeline (shipped learned flow, 10 ms windows) over every
recording of :data:`REAL_SEGMENTATION` that is present under the shared data folder
(``EVSEG_SHARED_DATA`` or ``../shared/data``; missing ones are skipped) and reports, per
recording, how many windows have objects and how many objects. Two kinds of recordings say
something without ground truth:

* **One motion only** (``expect="none"``: a camera moving over a poster or a facade, a
  picture sliding past a static camera): every object reported is a false object, the real-data
  counterpart of the simulated ego-motion-only scenes.
* **EED *what is background*** (``expect="ball"``): a ball moving behind a net while the camera
  moves. The ball's position comes from a reference track: a straight line fitted to the
  centroids of the ball cluster in EMSGC's published labels for this sequence
  (``emsgc_reference/result_EED/what_is_background/seg_labels``, frames k at
  t = 69 ms + 10 ms k of the excerpt, the alignment estimated in that folder's README). A window
  finds the ball when one of its objects is ball-sized and its box, grown by
  :data:`BALL_MARGIN_PX`, contains the track point at the window's mid-time; every other
  object is counted as "other" (the net split off, or noise).

The other recordings (a person in front of a static camera, a spinning arm, sparks, a street
seen from a car) are reported for the counts only. Every recording is segmented in raw sensor
pixels (the ECD poster files carry a calibration; it is not applied), with the preset named in
:data:`REAL_SEGMENTATION` (default settings unless the scene calls for one). The figures are a
description, not a score: the alignment of EMSGC's frames is an estimate (+-3 ms) and EMSGC's
output is another method's result, not ground truth.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

BALL_MARGIN_PX = 8
"""Slack (px) around an object's box when testing the reference ball position: the track is a
straight-line fit (residuals up to ~4 px on EMSGC's centroids) and EMSGC's frames are aligned
to +-3 ms (~2 px at the ball's ~650 px/s)."""

BALL_MAX_SIDE_PX = 80
"""A ball object is at most this wide and high (px): the ball is ~25-35 px across, smeared by
~6 px over a 10 ms window; a box spanning the net is not "the ball"."""

EMSGC_FIRST_US = 69_000
EMSGC_STEP_US = 10_000
"""EMSGC frame k of *what is background* lies at 69 ms + 10 ms k of the excerpt (estimate from
``eed_what_is_background/README.txt``)."""


@dataclass(frozen=True)
class RealRecording:
    """A shared real recording and what a right answer looks like.

    Attributes:
        path: relative to the shared data folder.
        preset: segmentation preset (None = default settings).
        expect: ``"none"`` (one motion: every object is false), ``"ball"`` (EED, see the module
            docstring) or a short description (counts only).
        quick: part of the ``--quick`` run.
    """

    path: str
    preset: str | None
    expect: str
    quick: bool = True


REAL_SEGMENTATION = (
    RealRecording("eed_what_is_background/EED_what_is_background_events.es", "eed_like", "ball"),
    RealRecording("ecd_poster/poster_translation.npz", None, "none"),
    RealRecording("ecd_poster/poster_6dof.npz", None, "none", quick=False),
    RealRecording("dvs128_single_motion/stripes.mat", None, "none"),
    RealRecording("dvs128_single_motion/garfield.mat", None, "none", quick=False),
    RealRecording("dvs128_single_motion/building.mat", None, "none", quick=False),
    RealRecording("dvs128_single_motion/flip.mat", None, "none", quick=False),
    RealRecording("dvxplorer_person_aedat4/sample.aedat4", None, "a person, static camera"),
    RealRecording("prophesee_evt_samples/evt2_sample.raw", None, "a spinning arm, static camera", quick=False),
    RealRecording("prophesee_sparks/evt2.raw", None, "sparks, static camera", quick=False),
    RealRecording("dvxplorer_person_aedat4/sample.aedat4", "static_camera", "a person, static camera", quick=False),
    RealRecording("prophesee_evt_samples/evt2_sample.raw", "static_camera", "a spinning arm, static camera",
                  quick=False),
    RealRecording("prophesee_sparks/evt2.raw", "static_camera", "sparks, static camera", quick=False),
    RealRecording("prophesee_evt_samples/evt3_sample.raw", "outdoor_like", "a street from a moving car", quick=False),
)
"""The recordings ``evseg eval pipeline-real`` segments, in table order."""


def emsgc_ball_track(label_dir: str | Path) -> np.ndarray:
    """Straight-line track of the ball through EMSGC's per-frame labels.

    Args:
        label_dir: folder of EMSGC ``NNNN.txt`` files (rows ``x y label`` per pixel with events).
            In each frame the ball is the smallest cluster.
    Returns:
        ``(2, 2)`` float64 ``[[x0, vx], [y0, vy]]``: position at t = 0 of the excerpt (px) and
        velocity (px per us), least squares over the frames' cluster centroids, frame k at
        ``EMSGC_FIRST_US + EMSGC_STEP_US * k`` (us).

    Example:
        >>> import tempfile, pathlib
        >>> d = pathlib.Path(tempfile.mkdtemp())
        >>> for k in range(3):  # background cluster 0 everywhere, ball (label 1) moving left
        ...     rows = [(x, y, 0) for x in range(0, 60, 3) for y in range(0, 40, 3)]
        ...     rows += [(50 - 5 * k + dx, 20 + dy, 1) for dx in (-1, 0, 1) for dy in (-1, 0, 1)]
        ...     np.savetxt(d / f"{k:04d}.txt", rows, fmt="%d")
        >>> track = emsgc_ball_track(d)
        >>> [float(np.round(v * 1e6)) + 0.0 for v in track[:, 1]]  # velocity, px/s
        [-500.0, 0.0]
    """
    from evseg.errors import FormatError

    files = sorted(Path(label_dir).glob("[0-9][0-9][0-9][0-9].txt"))
    if len(files) < 2:
        raise FormatError(f"{label_dir}: needs at least 2 EMSGC label files NNNN.txt, found {len(files)}")
    t, cx, cy = [], [], []
    for f in files:
        try:
            rows = np.loadtxt(f, dtype=np.int64, ndmin=2)
        except ValueError as exc:
            raise FormatError(f"{f}: not rows of 'x y label' integers ({exc})") from None
        if rows.shape[1] != 3 or len(rows) == 0:
            raise FormatError(f"{f}: expected rows of 'x y label', got shape {rows.shape}")
        labels, counts = np.unique(rows[:, 2], return_counts=True)
        ball = rows[rows[:, 2] == labels[np.argmin(counts)]]
        t.append(EMSGC_FIRST_US + EMSGC_STEP_US * int(f.stem))
        cx.append(ball[:, 0].mean())
        cy.append(ball[:, 1].mean())
    A = np.column_stack([np.ones(len(t)), np.asarray(t, dtype=np.float64)])
    coef, *_ = np.linalg.lstsq(A, np.column_stack([cx, cy]), rcond=None)
    return coef.T


def ball_object(boxes: dict[int, tuple[int, int, int, int]], point: tuple[float, float],
                margin_px: float = BALL_MARGIN_PX, max_side_px: float = BALL_MAX_SIDE_PX) -> int | None:
    """Id of the object that is the ball at ``point`` (px), or None.

    An object qualifies when its box (inclusive px ``x0, y0, x1, y1``) is at most
    ``max_side_px`` wide and high and, grown by ``margin_px``, contains ``point``; of several,
    the smallest box.

    Example:
        >>> ball_object({1: (0, 0, 189, 179), 2: (90, 50, 110, 70)}, (112.0, 60.0))
        2
        >>> ball_object({1: (0, 0, 189, 179)}, (112.0, 60.0)) is None
        True
    """
    px, py = point
    best, best_area = None, np.inf
    for oid, (x0, y0, x1, y1) in boxes.items():
        if x1 - x0 + 1 > max_side_px or y1 - y0 + 1 > max_side_px:
            continue
        if x0 - margin_px <= px <= x1 + margin_px and y0 - margin_px <= py <= y1 + margin_px:
            area = (x1 - x0 + 1) * (y1 - y0 + 1)
            if area < best_area:
                best, best_area = int(oid), area
    return best


def segment_real_recording(
    path: Path, preset: str | None, max_windows: int | None = None, flow: str = "learned",
    slow_edges: bool = False, mirrors: int = 1, tracked_mirrors: int = 1, overrides: dict | None = None,
) -> tuple[list, list[float]]:
    """Run the pipeline (10 ms windows; ``flow``: 'learned' = the shipped model, or
    'planefit'; ``slow_edges``, ``mirrors``, ``tracked_mirrors``: :class:`~evseg.pipeline.PipelineConfig`'s;
    ``overrides``: segmentation fields set on top of ``preset``) over ``path``.

    Returns the window results (masks, events and raw segmentation dropped to save memory)
    and the wall time of each window (s, flow included). ``max_windows`` stops early."""
    from dataclasses import replace

    from evseg.io import read_events

    stream = read_events(path)
    results, times = [], []
    it = _pipeline(stream.sensor_size, preset, flow, slow_edges, mirrors, tracked_mirrors, overrides).run(stream)
    while max_windows is None or len(results) < max_windows:
        t0 = time.perf_counter()
        res = next(it, None)
        if res is None:
            break
        times.append(time.perf_counter() - t0)
        results.append(replace(res, masks={}, events=res.events[:0], segmentation=None))
    return results, times


def _pipeline(sensor_size: tuple[int, int], preset: str | None, flow: str = "learned", slow_edges: bool = False,
              mirrors: int = 1, tracked_mirrors: int = 1, overrides: dict | None = None):
    """The pipeline the evaluation and the pictures use: 10 ms windows, ``preset`` (None =
    default settings) with ``overrides`` set on it, ``flow`` estimator."""
    from evseg.pipeline import MotionSegmentationPipeline, PipelineConfig
    from evseg.segmentation import SegmentationConfig, load_segmentation_config
    from evseg.segmentation.config import with_overrides

    seg = with_overrides(load_segmentation_config(preset) if preset else SegmentationConfig(), overrides,
                         "evaluate_pipeline_real")
    return MotionSegmentationPipeline(PipelineConfig(flow=flow, segmentation=seg, slow_edges=slow_edges, mirrors=mirrors,
                                                     tracked_mirrors=tracked_mirrors), sensor_size=sensor_size)


def summarize_real(results: list, times: list[float], expect: str, track: np.ndarray | None) -> dict:
    """One table row from the window results of a recording (see the module docstring)."""
    n = len(results)
    counts = np.array([len(r.boxes) for r in results], dtype=np.int64)
    row = {
        "windows": n,
        "events/window": float(np.median([len(r.labels) for r in results])) if n else float("nan"),
        "windows with objects %": 100.0 * float(np.mean(counts > 0)) if n else float("nan"),
        "objects/window": float(counts.mean()) if n else float("nan"),
        "max objects": int(counts.max()) if n else 0,
        "ball windows": float("nan"),
        "other objects": float("nan"),
        "ms/window": float(np.median(times) * 1e3) if times else float("nan"),
    }
    if expect == "ball" and track is not None:
        found = other = 0
        for r in results:
            mid = (r.t0_us + r.t1_us) / 2.0
            point = (track[0, 0] + track[0, 1] * mid, track[1, 0] + track[1, 1] * mid)
            ball = ball_object(r.boxes, point)
            found += ball is not None
            other += len(r.boxes) - (ball is not None)
        row["ball windows"] = found
        row["other objects"] = other
    return row


def evaluate_pipeline_real(quick: bool = False, flow: str = "learned", slow_edges: bool = False,
                           mirrors: int = 1, tracked_mirrors: int = 1, overrides: dict | None = None) -> list[dict]:
    """``evseg eval pipeline-real``: one row per shared real recording (module docstring).

    Quick: the recordings marked ``quick``, at most 10 windows each. ``flow``: the normal-flow
    estimator, 'learned' (the command's) or 'planefit' (from Python, for comparison);
    ``slow_edges``: the learned flow's slow-edge look (``--slow-edges``); ``mirrors``: its
    mirror looks (``--mirrors``); ``tracked_mirrors``: its mirror looks in the tracked boxes
    (``--tracked-mirrors``); ``overrides``: :class:`~evseg.segmentation.SegmentationConfig`
    fields set on every row's preset (``--set``; the rows' preset column still names the preset).
    """
    from evseg.errors import EvsegError
    from evseg.segmentation import SegmentationConfig
    from evseg.segmentation.config import with_overrides
    from evseg.train.evaluate import missing_shared_data_message, shared_data_dir

    with_overrides(SegmentationConfig(), overrides, "evaluate_pipeline_real")  # bad keys fail before any work

    root = shared_data_dir()
    if not root.is_dir():
        raise EvsegError(missing_shared_data_message(root))
    labels = root / "emsgc_reference/result_EED/what_is_background/seg_labels"
    track = emsgc_ball_track(labels) if labels.is_dir() else None
    rows, one_motion = [], []
    for rec in REAL_SEGMENTATION:
        path = root / rec.path
        if not path.is_file() or (quick and not rec.quick):
            continue
        results, times = segment_real_recording(path, rec.preset, max_windows=10 if quick else None, flow=flow,
                                                slow_edges=slow_edges, mirrors=mirrors,
                                                tracked_mirrors=tracked_mirrors, overrides=overrides)
        rows.append({"recording": rec.path, "preset": rec.preset or "default",
                     "expected": _EXPECT.get(rec.expect, rec.expect),
                     **summarize_real(results, times, rec.expect, track)})
        if rec.expect == "none":
            one_motion.append(rows[-1])
    if one_motion:
        n = sum(r["windows"] for r in one_motion)
        rows.append({
            "recording": "**one-motion recordings (all windows)**", "preset": "default", "expected": _EXPECT["none"],
            "windows": n, "events/window": float("nan"),
            "windows with objects %": sum(r["windows"] * r["windows with objects %"] for r in one_motion) / max(n, 1),
            "objects/window": sum(r["windows"] * r["objects/window"] for r in one_motion) / max(n, 1),
            "max objects": max(r["max objects"] for r in one_motion),
            "ball windows": float("nan"), "other objects": float("nan"), "ms/window": float("nan"),
        })
    return rows


_EXPECT = {"none": "no object (one motion)", "ball": "the ball, nothing else"}


PICTURES = (
    ("eed_what_is_background/EED_what_is_background_events.es", "eed_real_learned.png", "eed_like"),
    ("dvxplorer_person_aedat4/sample.aedat4", "real_dvxplorer_person.png", None),
    ("dvxplorer_person_aedat4/sample.aedat4", "real_dvxplorer_person_static.png", "static_camera"),
    ("prophesee_sparks/evt2.raw", "real_prophesee_sparks.png", None),
    ("prophesee_evt_samples/evt2_sample.raw", "real_prophesee_spinner.png", None),
)
"""(recording, picture file, segmentation preset) of each strip :func:`save_real_strips` writes."""


def save_real_strips(out_dir: str | Path, panel_px: int = 400) -> list[Path]:
    """Write one strip of four windows per recording of :data:`PICTURES` that is present: the
    events of 4 evenly spaced 10 ms windows coloured by label (grey background, boxes with
    object ids; :func:`evseg.overlay.label_overlay`), each panel ``panel_px`` wide. Returns the
    paths written. The README's pictures come from ``save_real_strips('docs')``."""
    import cv2

    from evseg.io import read_events
    from evseg.overlay import label_overlay
    from evseg.train.evaluate import shared_data_dir
    from evseg.visualize import hstack_padded

    root = shared_data_dir()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for rel, name, preset in PICTURES:
        path = root / rel
        if not path.is_file():
            continue
        stream = read_events(path)
        results = list(_pipeline(stream.sensor_size, preset).run(stream))
        picks = np.unique(np.round(np.linspace(0, len(results) - 1, 6)[1:5]).astype(int))
        width = stream.sensor_size[0]
        panels = []
        for k in picks:
            r = results[k]
            img = label_overlay(r.events, r.labels, r.boxes, stream.sensor_size, scale=max(1, panel_px // width),
                                title=f"{r.t0_us / 1e3:.0f} ms")
            if img.shape[1] > panel_px:
                img = cv2.resize(img, (panel_px, round(img.shape[0] * panel_px / img.shape[1])),
                                 interpolation=cv2.INTER_AREA)
            panels.append(img)
        target = out_dir / name
        cv2.imwrite(str(target), hstack_padded(panels, gap=4))
        written.append(target)
    return written
