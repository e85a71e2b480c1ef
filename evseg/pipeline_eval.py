"""End-to-end evaluation of the pipeline on simulated recordings with ground truth.

Each window's detected object masks are scored against the simulator's masks and boxes at
the window's mid-time (:meth:`SimulatedRecording.window_truth`; objects not visible then do
not count) with :func:`evseg.metrics.score_window`: EED detection rate on boxes, mask IoU,
object count, false objects. Ego-motion-only scenes have no object: every reported object
there is a false object.

Seeds >= 1000 only: the normal-flow network never saw them in training.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from evseg.metrics import MIN_OBJECT_EVENTS, WindowScore, angular_error_deg, score_window, summarize

# simulator preset -> segmentation preset
SEGMENTATION_PRESET = {
    "eed_like": "eed_like",
    "eed_lowlight": "eed_like",
    "evimo_like": "evimo_like",
    "driving_like": "outdoor_like",
    "ego_only": "evimo_like",
}


SEGMENTATION_PRESET_ORDER = ("eed_like", "evimo_like", "driving_like", "ego_only")
"""The simulator presets of ``evseg eval pipeline``, in table order."""


@dataclass
class RecordingEvaluation:
    """Scores of one simulated recording, window by window."""

    scores: list[WindowScore]
    results: list  # WindowResult per window (kept only when asked)
    flow_median_ae_deg: float  # median angular error of the flows used vs GT normal flow
    ms_per_window: float  # median wall time per window, flow included


def oracle_flow(rec) -> dict[str, np.ndarray]:
    """The simulator's ground-truth normal flow in the ``evseg flow`` file layout."""
    ok = np.flatnonzero(np.isfinite(rec.normal_flow[:, 0]))
    return {"index": ok, "nx": rec.normal_flow[ok, 0], "ny": rec.normal_flow[ok, 1]}


def evaluate_recording(rec, config, keep_results: bool = False) -> RecordingEvaluation:
    """Run the pipeline over a simulated recording and score every window.

    ``config.flow == "precomputed"`` feeds the ground-truth normal flow (oracle).
    """
    from evseg.pipeline import MotionSegmentationPipeline

    pipe = MotionSegmentationPipeline(config, sensor_size=rec.stream.sensor_size)
    flow = oracle_flow(rec) if config.flow == "precomputed" else None
    scores, results, aes, times = [], [], [], []
    it = pipe.run(rec.stream, precomputed_flow=flow)
    while True:
        t0 = time.perf_counter()
        res = next(it, None)
        if res is None:
            break
        times.append(time.perf_counter() - t0)
        scores.append(score_result(rec, res))
        aes.append(flow_angular_errors(rec, res))
        if keep_results:
            results.append(res)
    errors = np.concatenate(aes) if aes else np.empty(0)
    ae = float(np.median(errors)) if len(errors) else float("nan")
    return RecordingEvaluation(scores, results, ae, float(np.median(times) * 1e3) if times else float("nan"))


def score_result(rec, res) -> WindowScore:
    """Score one window's result (:class:`~evseg.pipeline.WindowResult`) against the simulated
    recording's objects visible at the window's mid-time."""
    truth = rec.window_truth(res.t0_us, res.t1_us)
    visible = [k for k, oid in enumerate(truth.object_ids) if oid in truth.boxes]
    detected = [res.masks[k] for k in sorted(res.masks)]
    own = rec.label[res.first_event : res.first_event + len(res.events)]
    n_events = np.bincount(np.maximum(own, 0).astype(np.int64), minlength=max(truth.object_ids, default=0) + 1)
    return score_window(detected, [truth.masks[k] for k in visible],
                        [truth.boxes[truth.object_ids[k]] for k in visible],
                        truth_events=[int(n_events[truth.object_ids[k]]) for k in visible])


def flow_angular_errors(rec, res) -> np.ndarray:
    """Angular error (deg) of a window's flows against the ground-truth normal flow, where the
    recording has one."""
    gt = rec.normal_flow[res.first_event + res.flow_index]
    ok = np.isfinite(gt[:, 0])
    return angular_error_deg(res.flow[ok], gt[ok]) if ok.any() else np.empty(0)


def evaluate_pipeline(quick: bool = False, flow: str = "learned", seeds=None, overrides: dict | None = None,
                      presets=None, **pipeline_options) -> list[dict]:
    """The simulated benchmark suite: one row per scene, then one mean row per preset and overall.

    Full: 8 seeds x (eed_like, evimo_like, driving_like) + 8 ego-motion-only scenes, 300 ms
    each, 10 ms windows. Quick: 2 seeds per preset, 100 ms. ``seeds``: other scene seeds (the
    README's learned-flow validation figures use ``range(900, 910)``; the network was trained on
    seeds < 144). ``overrides``: :class:`~evseg.segmentation.SegmentationConfig` fields set on
    every preset (e.g. ``{"max_object_extent": 0.35}``), as ``evaluate_oracle`` takes them.
    ``presets``: a subset of the simulator presets (default all four, in their order).
    ``pipeline_options``: further :class:`~evseg.pipeline.PipelineConfig` fields (e.g.
    ``min_track_windows=2``).
    """
    from evseg.pipeline import PipelineConfig
    from evseg.segmentation import SegmentationConfig, load_segmentation_config
    from evseg.segmentation.config import with_overrides
    from evseg.simulator import load_scene_preset, simulate

    with_overrides(SegmentationConfig(), overrides, "evaluate_pipeline")  # bad keys fail before any work

    from evseg.segmentation.evaluate import check_presets

    presets = check_presets(presets, list(SEGMENTATION_PRESET_ORDER), "evaluate_pipeline")
    if seeds is None:
        seeds = range(1000, 1002) if quick else range(1000, 1008)
    duration_us = 100_000 if quick else 300_000
    rows, per_preset = [], {}
    for preset in presets:
        for seed in seeds:
            rec = simulate(load_scene_preset(preset), seed=seed, duration_us=duration_us)
            seg = with_overrides(load_segmentation_config(SEGMENTATION_PRESET[preset]), overrides, "evaluate_pipeline")
            cfg = PipelineConfig(flow=flow, segmentation=seg, **pipeline_options)
            ev = evaluate_recording(rec, cfg)
            s = summarize(ev.scores)
            per_preset.setdefault(preset, []).extend(ev.scores)
            rows.append(summary_row(f"{preset} #{seed}", s, ev.flow_median_ae_deg, ev.ms_per_window))
    for preset, scores in per_preset.items():
        rows.append(summary_row(f"**{preset} (all)**", summarize(scores), float("nan"), float("nan")))
    imo = [s for p, sc in per_preset.items() if p != "ego_only" for s in sc]
    rows.append(summary_row("**scenes with objects**", summarize(imo), float("nan"), float("nan")))
    return rows


def evaluate_pipeline_and_oracle(quick: bool = False, model_path: str | None = None,
                                 slow_edges: bool = False, mirrors: int = 1, tracked_mirrors: int = 1,
                                 seeds=None, overrides: dict | None = None, presets=None) -> list[dict]:
    """``evseg eval pipeline``: :func:`evaluate_pipeline` with the learned flow (``model_path``,
    default the shipped model; every scene's row and the pooled rows), then the pooled rows of
    the same scenes run through the same pipeline with the simulator's ground-truth normal flow
    (``flow="precomputed"``), which tell what the flow's errors cost from what the segmentation
    misses by itself. ``slow_edges``, ``mirrors``, ``tracked_mirrors``:
    :class:`~evseg.pipeline.PipelineConfig`'s, for the learned flow; ``seeds``, ``overrides``,
    ``presets``: :func:`evaluate_pipeline`'s, for both runs (``evseg eval pipeline --seeds --set
    --presets``)."""
    rows = evaluate_pipeline(quick, seeds=seeds, overrides=overrides, presets=presets,
                             model_path=None if model_path is None else str(model_path), slow_edges=slow_edges,
                             mirrors=mirrors, tracked_mirrors=tracked_mirrors)
    for r in evaluate_pipeline(quick, flow="precomputed", seeds=seeds, overrides=overrides, presets=presets):
        if r["scene"].startswith("**"):
            rows.append({**r, "scene": r["scene"][:-2] + ", ground-truth flow**"})
    return rows


def summary_row(name: str, s, ae: float, ms: float) -> dict:
    """One row of the ``evseg eval pipeline`` table: a :class:`~evseg.metrics.SegmentationSummary`
    in percent, with the flows' median angular error (deg) and the median ms per window."""
    return {
        "scene": name,
        "windows": s.windows,
        "detection rate %": 100 * s.detection_rate,
        "mean IoU": s.mean_iou,
        "count correct %": 100 * s.count_correct_rate,
        "windows with false objects %": 100 * s.false_object_rate,
        "missed: not found %": 100 * s.missed_not_found,
        "missed: box too small %": 100 * s.missed_too_small,
        "missed: box spills out %": 100 * s.missed_spills_out,
        f"objects under {MIN_OBJECT_EVENTS} events %": 100 * s.sparse_share,
        f"detection rate, >= {MIN_OBJECT_EVENTS} events %": 100 * s.detection_rate_dense,
        "flow median AE deg": ae,
        "ms/window": ms,
    }


def evaluate_static_camera(quick: bool = False, slow_edges: bool = False, mirrors: int = 1,
                           tracked_mirrors: int = 1, seeds=None, overrides: dict | None = None) -> list[dict]:
    """Simulated scenes from a camera that does not move (scene preset ``static_camera``):
    pooled scores with the default settings, which take the largest motion for the background,
    and with the ``static_camera`` segmentation preset, which keeps zero motion as the
    background; each with the simulator's ground-truth normal flow and with the shipped
    learned flow (``slow_edges``: with the slow-edge look; ``mirrors``: its mirror looks;
    ``tracked_mirrors``: its mirror looks in the tracked boxes). Full: 8 seeds (1000-1007) of 300 ms;
    quick: 2 seeds of 100 ms. ``seeds``: other scene seeds (validation: 900-999);
    ``overrides``: :class:`~evseg.segmentation.SegmentationConfig` fields set on both settings
    (``evseg eval static --seeds --set``)."""
    from evseg.pipeline import PipelineConfig
    from evseg.segmentation import SegmentationConfig, load_segmentation_config
    from evseg.segmentation.config import with_overrides
    from evseg.simulator import load_scene_preset, simulate

    settings = {name: with_overrides(cfg, overrides, "evaluate_static_camera")  # bad keys fail first
                for name, cfg in (("default", SegmentationConfig()),
                                  ("static_camera", load_segmentation_config("static_camera")))}
    if seeds is None:
        seeds = range(1000, 1002) if quick else range(1000, 1008)
    duration_us = 100_000 if quick else 300_000
    scores: dict[tuple[str, str], list] = {}
    for seed in seeds:
        rec = simulate(load_scene_preset("static_camera"), seed=seed, duration_us=duration_us)
        for flow in ("precomputed", "learned"):
            for name, seg in settings.items():
                ev = evaluate_recording(rec, PipelineConfig(flow=flow, segmentation=seg, slow_edges=slow_edges,
                                                            mirrors=mirrors, tracked_mirrors=tracked_mirrors))
                scores.setdefault((flow, name), []).extend(ev.scores)
    rows = []
    for (flow, name), sc in scores.items():
        row = summary_row(f"{'ground-truth' if flow == 'precomputed' else 'learned'} flow, {name} settings",
                   summarize(sc), float("nan"), float("nan"))
        rows.append({k: v for k, v in row.items() if k not in ("flow median AE deg", "ms/window")})
    return rows
