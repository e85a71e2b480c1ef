"""Oracle evaluation: segment simulated scenes fed with their ground-truth normal flow.

For each scene (simulator preset x held-out seed >= 1000), the recording is cut into
consecutive windows of ``window_us``; each window's events with their ground-truth normal
flow go to :func:`segment_normal_flow` (with the previous window's result for motion
prediction) and the object masks are scored against the simulator's masks at the window's
mid-time with :mod:`evseg.metrics` (EED detection on boxes, mask IoU, object count).
Noise events carry no flow (NaN) and are dropped by the pre-processing like any flow-less
event. The outlier variant replaces a share of the flows (deterministic per scene) by random
vectors, uniform in the square of side twice the 90th percentile of |n|.

A ground-truth object counts in a window when it is visible AND produced at least
``MIN_OBJECT_EVENTS`` (:mod:`evseg.metrics`) events in the window: an object that slid in by
a few pixels (a dozen events) cannot be segmented from events by any method, and the
simulator's mask would still count it. Windows in which the truth has no such object still count for the object-count rate.

``detection_ceiling`` is the detection rate of a perfect labelling: the share of counted
objects for which the box of exactly the object's own events meets the detection criterion.
Boxes come from events, the truth from the silhouette, so a sparse object whose events cover
only part of it is missed by any labelling of the events.
"""

from __future__ import annotations

import numpy as np

from evseg.metrics import MIN_OBJECT_EVENTS
from evseg.segmentation.config import SegmentationConfig, load_segmentation_config
from evseg.segmentation.solver import segment_normal_flow

# simulator preset -> segmentation preset
PRESETS = {"eed_like": "eed_like", "evimo_like": "evimo_like", "driving_like": "outdoor_like"}


def add_outliers(nx: np.ndarray, ny: np.ndarray, fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Copies of (nx, ny) with ``fraction`` of the finite flows replaced by random vectors (px/s)."""
    nx, ny = np.array(nx, dtype=np.float64), np.array(ny, dtype=np.float64)
    finite = np.flatnonzero(np.isfinite(nx) & np.isfinite(ny))
    if fraction <= 0 or len(finite) == 0:
        return nx, ny
    rng = np.random.default_rng(seed)
    k = int(round(fraction * len(finite)))
    pick = rng.choice(finite, k, replace=False)
    s = float(np.percentile(np.hypot(nx[finite], ny[finite]), 90))
    nx[pick] = rng.uniform(-s, s, k)
    ny[pick] = rng.uniform(-s, s, k)
    return nx, ny


def own_events_detected(x: np.ndarray, y: np.ndarray, truth_box: tuple, shape: tuple[int, int]) -> bool:
    """Whether the box of an object's own events (px) meets the detection criterion against its
    truth box (inclusive px) on a sensor of ``shape`` (height, width).

    >>> own_events_detected(np.array([0, 9]), np.array([0, 9]), (0, 0, 9, 9), (20, 20))
    True
    >>> own_events_detected(np.array([0, 9]), np.array([0, 3]), (0, 0, 9, 9), (20, 20))
    False
    """
    from evseg.metrics import box_to_mask, detection_success

    box = (int(np.min(x)), int(np.min(y)), int(np.max(x)), int(np.max(y)))
    return bool(detection_success(box_to_mask(box, shape), box_to_mask(truth_box, shape)))


def evaluate_scene(
    preset: str,
    seed: int,
    duration_us: int,
    window_us: int = 10_000,
    outlier_fraction: float = 0.0,
    config: SegmentationConfig | None = None,
) -> dict:
    """Segment one simulated scene window by window; returns its metrics and timings."""
    from evseg.metrics import score_window, summarize
    from evseg.simulator import load_scene_preset, simulate

    rec = simulate(load_scene_preset(preset), seed=seed, duration_us=duration_us)
    cfg = config if config is not None else load_segmentation_config(PRESETS.get(preset, "evimo_like"))
    ev = rec.stream.events
    w, h = rec.stream.sensor_size
    nflow = rec.normal_flow.astype(np.float64)
    nx, ny = add_outliers(nflow[:, 0], nflow[:, 1], outlier_fraction, seed)
    scores, nodes, t_init, t_lf = [], [], [], []
    detectable = 0
    previous = None
    bounds = np.searchsorted(ev["t"], np.arange(0, duration_us + 1, window_us))
    for i in range(len(bounds) - 1):
        sl = slice(bounds[i], bounds[i + 1])
        t0, t1 = i * window_us, (i + 1) * window_us
        res = segment_normal_flow(ev["x"][sl].astype(np.float64), ev["y"][sl].astype(np.float64),
                                  ev["t"][sl], nx[sl], ny[sl], config=cfg, sensor_size=(w, h),
                                  previous=previous)
        previous = res
        truth = rec.window_truth(t0, t1)
        n_ev = np.bincount(np.maximum(rec.label[sl], 0).astype(np.int64),
                           minlength=max(truth.object_ids, default=0) + 1)
        visible = [k for k, oid in enumerate(truth.object_ids)
                   if oid in truth.boxes and n_ev[oid] >= MIN_OBJECT_EVENTS]
        truth_masks = [truth.masks[k] for k in visible]
        truth_boxes = [truth.boxes[truth.object_ids[k]] for k in visible]
        labels = rec.label[sl]
        for k, box in zip(visible, truth_boxes):
            own = labels == truth.object_ids[k]
            detectable += own_events_detected(ev["x"][sl][own], ev["y"][sl][own], box, (h, w))
        detected = [res.masks[k] for k in sorted(res.masks)]
        scores.append(score_window(detected, truth_masks, truth_boxes))
        nodes.append(len(res.node_index))
        t_init.append(res.timings["initialization"])
        t_lf.append(res.timings["labeling_fitting"])
    s = summarize(scores)
    return {
        "preset": preset,
        "seed": seed,
        "outliers": outlier_fraction,
        "windows": s.windows,
        "objects": sum(sc.n_truth for sc in scores),
        "nodes": float(np.median(nodes)),
        "detection_rate": s.detection_rate,
        "detection_ceiling": detectable / max(sum(sc.n_truth for sc in scores), 1),
        "mean_iou": s.mean_iou,
        "count_correct": s.count_correct_rate,
        "init_ms": float(np.median(t_init)),
        "label_fit_ms": float(np.median(t_lf)),
        "_scores": scores,
    }


def check_presets(presets, known: list[str], where: str) -> list[str]:
    """``presets`` (None = all ``known``) as a list in ``known``'s order; an unknown name is a
    :class:`~evseg.errors.ConfigError` naming ``where`` and the names it knows."""
    from evseg.errors import ConfigError

    if presets is None:
        return list(known)
    unknown = [p for p in presets if p not in known]
    if unknown or not presets:
        raise ConfigError(f"{where}: unknown or no simulator preset(s) {unknown or list(presets)}; known: {known}")
    return [p for p in known if p in presets]


def evaluate_oracle(quick: bool = False, seeds=None, overrides: dict | None = None, presets=None) -> list[dict]:
    """Oracle evaluation over held-out scenes: one row per scene, then pooled rows per preset
    and over all scenes (metrics over the pooled windows; timings are medians of the scenes'
    median per-window times).

    Full: 7 seeds (1000-1006) x 3 presets = 21 scenes of 100 ms (10 windows of 10 ms each),
    with clean flow and with 30 % outliers. Quick: 1 seed per preset, 50 ms, clean only.
    ``seeds``: other scene seeds (the README's validation figures use ``range(900, 921)``);
    ``overrides``: :class:`SegmentationConfig` fields set on every preset (e.g.
    ``{"contrast_min_weight": 1.0}``), to compare settings the way the README does;
    ``presets``: a subset of the simulator presets (default all three).
    """
    from evseg.metrics import summarize
    from evseg.segmentation.config import with_overrides

    with_overrides(SegmentationConfig(), overrides, "evaluate_oracle")  # bad keys fail before any work
    names = check_presets(presets, list(PRESETS), "evaluate_oracle")
    if seeds is None:
        seeds = [1000] if quick else list(range(1000, 1007))
    seeds = [int(s) for s in seeds]
    duration = 50_000 if quick else 100_000
    fractions = [0.0] if quick else [0.0, 0.3]
    rows = []
    for frac in fractions:
        block = []
        for preset in names:
            for seed in seeds:
                cfg = with_overrides(load_segmentation_config(PRESETS[preset]), overrides, "evaluate_oracle")
                block.append(evaluate_scene(preset, seed, duration, outlier_fraction=frac, config=cfg))
        rows += block
        groups = [(p, [r for r in block if r["preset"] == p]) for p in names] + [("ALL", block)]
        for name, members in groups:
            s = summarize([sc for r in members for sc in r["_scores"]])
            rows.append({
                "preset": f"{name} (pooled)", "seed": f"{len(members)} scenes", "outliers": frac,
                "windows": s.windows, "objects": sum(r["objects"] for r in members),
                "nodes": float(np.median([r["nodes"] for r in members])),
                "detection_rate": s.detection_rate,
                "detection_ceiling": (sum(r["detection_ceiling"] * r["objects"] for r in members)
                                      / max(sum(r["objects"] for r in members), 1)),
                "mean_iou": s.mean_iou, "count_correct": s.count_correct_rate,
                "init_ms": float(np.median([r["init_ms"] for r in members])),
                "label_fit_ms": float(np.median([r["label_fit_ms"] for r in members])),
            })
    for r in rows:
        r.pop("_scores", None)
    return rows
