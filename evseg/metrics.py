"""Evaluation metrics: IMO detection, IoU, normal-flow errors, label-free flow sharpness.

Detection (EED, Mitrokhin et al. 2018), exactly as implemented here. For a ground-truth
object region G (its box, as a filled mask) and the estimated region D of the object matched
to it (its convex hull or box, as a filled mask), the detection succeeds when

    |D ∩ G| / |D ∪ G| > 0.5      and      |D ∩ G| > |D \\ G|,

i.e. the regions overlap with IoU above one half and more of the detection lies inside the
ground-truth box than outside it. The detection rate is the share of ground-truth objects
(over all windows) whose matched detection succeeds; a ground-truth object with no matched
detection counts as a miss. This is the reading of the paper's "B_D ∩ B_G > 0.5 and
B_D ∩ B_G > B_D ∩ not(B_G)" that public evaluation code uses (method.md section 5).

Matching: detections are assigned to ground-truth objects one to one by maximum total IoU
(Hungarian, :func:`scipy.optimize.linear_sum_assignment`); pairs with IoU 0 stay unmatched.

Normal-flow errors compare predicted normal flow ``p`` with ground truth ``g`` (both px/s,
shape (N, 2)); VecKM_flow's metrics compare ``p`` with the full optical flow ``u``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from evseg.errors import EventDataError

Box = tuple[int, int, int, int]
"""(x0, y0, x1, y1), inclusive pixel bounds, x = column, y = row."""


# --------------------------------------------------------------------------- regions


def box_to_mask(box: Box, shape: tuple[int, int]) -> np.ndarray:
    """Filled boolean mask of ``shape = (height, width)`` for an inclusive box (clipped)."""
    h, w = shape
    x0, y0, x1, y1 = (int(v) for v in box)
    m = np.zeros((h, w), dtype=bool)
    m[max(y0, 0) : min(y1, h - 1) + 1, max(x0, 0) : min(x1, w - 1) + 1] = True
    return m


def mask_to_box(mask: np.ndarray) -> Box | None:
    """Inclusive bounding box of a boolean mask, or None when the mask is empty."""
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return None
    return int(xs.min()), int(ys.min()), int(xs.max()), int(ys.max())


def convex_hull_mask(x: np.ndarray, y: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Filled convex hull of points (px) as a boolean ``(height, width)`` mask.

    Fewer than 3 distinct points give the mask of the points (and the segment between two).
    """
    import cv2

    m = np.zeros(shape, dtype=np.uint8)
    if len(x) == 0:
        return m.astype(bool)
    pts = np.stack([np.round(x), np.round(y)], axis=-1).astype(np.int32)
    hull = cv2.convexHull(pts.reshape(-1, 1, 2))
    cv2.fillConvexPoly(m, hull, 1)
    return m.astype(bool)


def _mask_pair(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two masks of one shape as bool (a numeric mask counts its non-zero pixels: 1 and 2 are
    both "in", where a bitwise and of them would be empty)."""
    a, b = np.asarray(a), np.asarray(b)
    if a.shape != b.shape:
        raise EventDataError(f"masks of different shapes {a.shape} and {b.shape}: (height, width) both")
    if a.dtype != bool:
        a = a != 0
    if b.dtype != bool:
        b = b != 0
    return a, b


def mask_iou(a: np.ndarray, b: np.ndarray) -> float:
    """|a ∩ b| / |a ∪ b| of two masks (bool, or numbers: non-zero = in); 1.0 when both are
    empty.

    >>> mask_iou(np.array([[1, 1, 0]]), np.array([[2, 0, 0]]))
    0.5
    """
    a, b = _mask_pair(a, b)
    union = np.count_nonzero(a | b)
    if union == 0:
        return 1.0
    return float(np.count_nonzero(a & b) / union)


def detection_success(detected: np.ndarray, truth: np.ndarray) -> bool:
    """EED detection criterion for one detected region and one ground-truth region (masks).

    True when IoU > 0.5 and |D ∩ G| > |D \\ G| (see module docstring).

    >>> g = box_to_mask((0, 0, 9, 9), (20, 20))
    >>> detection_success(box_to_mask((1, 1, 9, 9), (20, 20)), g)
    True
    >>> detection_success(box_to_mask((5, 5, 14, 14), (20, 20)), g)
    False
    """
    detected, truth = _mask_pair(detected, truth)
    inter = np.count_nonzero(detected & truth)
    outside = np.count_nonzero(detected & ~truth)
    return bool(mask_iou(detected, truth) > 0.5 and inter > outside)


# --------------------------------------------------------------------------- matching


def match_regions(detected: list[np.ndarray], truth: list[np.ndarray]) -> list[tuple[int, int, float]]:
    """One-to-one matching of detected and ground-truth masks by maximum total IoU.

    Returns ``(detected_index, truth_index, iou)`` for matched pairs with IoU > 0.
    """
    from scipy.optimize import linear_sum_assignment

    if not detected or not truth:
        return []
    iou = np.array([[mask_iou(d, g) for g in truth] for d in detected])
    rows, cols = linear_sum_assignment(-iou)
    return [(int(r), int(c), float(iou[r, c])) for r, c in zip(rows, cols) if iou[r, c] > 0]


@dataclass(frozen=True)
class WindowScore:
    """Segmentation scores of one window.

    Attributes:
        n_truth: ground-truth objects visible in the window.
        n_detected: objects the method reported.
        n_detected_ok: ground-truth objects detected by the EED criterion.
        ious: IoU of each ground-truth object's mask with its matched detection's mask
            (0 for a missed object), length ``n_truth``.
        n_false: detections matched to no ground-truth object (false objects).
        outcomes: one of :data:`OUTCOMES` per ground-truth object, in truth order: why a
            missed object was missed (see :func:`detection_outcome`).
        truth_events: events each ground-truth object fired in the window, in truth order
            (empty when the caller did not give them).
    """

    n_truth: int
    n_detected: int
    n_detected_ok: int
    ious: tuple[float, ...]
    n_false: int
    outcomes: tuple[str, ...] = ()
    truth_events: tuple[int, ...] = ()


OUTCOMES = ("detected", "not_found", "too_small", "spills_out")
"""How a ground-truth object fared in a window (:func:`detection_outcome`)."""


def detection_outcome(detected: np.ndarray | None, truth: np.ndarray) -> str:
    """Which clause of the detection criterion a ground-truth region meets or fails.

    ``detected``: the box mask of the detection matched to it (None when no detection
    overlaps it); ``truth``: its ground-truth box mask. Returns ``"detected"`` when
    :func:`detection_success` holds, else ``"not_found"`` (nothing matched), ``"spills_out"``
    (|D ∩ G| <= |D \\ G|: more of the detection lies outside the truth box than inside, e.g. the
    object merged with its surroundings or the box is displaced) or ``"too_small"`` (the
    detection lies mostly inside the truth box but covers too little of it: IoU <= 0.5).

    >>> g = box_to_mask((0, 0, 9, 9), (20, 20))
    >>> detection_outcome(box_to_mask((0, 0, 3, 9), (20, 20)), g)
    'too_small'
    >>> detection_outcome(box_to_mask((0, 0, 19, 19), (20, 20)), g)
    'spills_out'
    """
    if detected is None:
        return "not_found"
    if detection_success(detected, truth):
        return "detected"
    inter = np.count_nonzero(detected & truth)
    return "spills_out" if inter <= np.count_nonzero(detected & ~truth) else "too_small"


def score_window(
    detected_masks: list[np.ndarray],
    truth_masks: list[np.ndarray],
    truth_boxes: list[Box] | None = None,
    truth_events: list[int] | None = None,
) -> WindowScore:
    """Score one window: match detections to ground truth and apply both metrics.

    Args:
        detected_masks: one dense boolean (H, W) mask per detected IMO.
        truth_masks: one dense boolean (H, W) mask per visible ground-truth IMO.
        truth_boxes: the ground-truth boxes for the detection criterion (default: the boxes
            of ``truth_masks``). The detected region for the criterion is the box of the
            detected mask, matching the box annotation of EED.
        truth_events: optional events fired by each ground-truth object in the window (for
            :func:`summarize`'s detection rate over objects with enough events).
    """
    shape = truth_masks[0].shape if truth_masks else (detected_masks[0].shape if detected_masks else (1, 1))
    if truth_boxes is None:
        truth_boxes = [mask_to_box(m) or (0, 0, -1, -1) for m in truth_masks]
    if truth_events is not None and len(truth_events) != len(truth_masks):
        raise ValueError(f"score_window: {len(truth_events)} event counts for {len(truth_masks)} truth objects")
    pairs = match_regions(detected_masks, truth_masks)
    ious = [0.0] * len(truth_masks)
    outcomes = ["not_found"] * len(truth_masks)
    for d, g, iou in pairs:
        ious[g] = iou
        dbox = mask_to_box(detected_masks[d])
        if dbox is not None:
            outcomes[g] = detection_outcome(box_to_mask(dbox, shape), box_to_mask(truth_boxes[g], shape))
    return WindowScore(
        n_truth=len(truth_masks),
        n_detected=len(detected_masks),
        n_detected_ok=outcomes.count("detected"),
        ious=tuple(ious),
        n_false=len(detected_masks) - len(pairs),
        outcomes=tuple(outcomes),
        truth_events=tuple(int(n) for n in truth_events) if truth_events is not None else (),
    )


MIN_OBJECT_EVENTS = 50
"""A ground-truth object with fewer events in a window is 'sparse' there: no labelling of
events can box it reliably (``evseg eval seg`` does not count such objects at all)."""


@dataclass(frozen=True)
class SegmentationSummary:
    """Aggregate over windows: the figures reported in the README tables.

    The ``missed_*`` shares split the ground-truth objects that were not detected by
    :func:`detection_outcome` (they add up to 1 - ``detection_rate``). ``sparse_share`` and
    ``detection_rate_dense`` need the windows' ``truth_events`` (NaN without them): the share
    of ground-truth objects with fewer than :data:`MIN_OBJECT_EVENTS` events in their window,
    and the detection rate over the others.
    """

    windows: int
    detection_rate: float  # detected ground-truth objects / all ground-truth objects
    mean_iou: float  # mean over ground-truth objects (misses count as 0)
    count_correct_rate: float  # share of windows where the object count equals the truth
    false_object_rate: float  # share of windows with at least one false object
    missed_not_found: float = float("nan")
    missed_too_small: float = float("nan")
    missed_spills_out: float = float("nan")
    sparse_share: float = float("nan")
    detection_rate_dense: float = float("nan")


def summarize(scores: list[WindowScore]) -> SegmentationSummary:
    """Aggregate window scores; rates over empty sets are NaN (nothing to measure)."""
    n_truth = sum(s.n_truth for s in scores)
    ious = [v for s in scores for v in s.ious]
    nan = float("nan")
    outcomes = [o for s in scores for o in s.outcomes]
    known = bool(outcomes) and len(outcomes) == n_truth  # scores built without outcomes: NaN

    def share(kind: str) -> float:
        return outcomes.count(kind) / n_truth if known else nan

    sparse = dense_ok = n_dense = 0
    with_events = bool(scores) and all(len(s.truth_events) == s.n_truth for s in scores) and n_truth > 0
    if with_events:
        for s in scores:
            for n, o in zip(s.truth_events, s.outcomes):
                if n < MIN_OBJECT_EVENTS:
                    sparse += 1
                else:
                    n_dense += 1
                    dense_ok += o == "detected"
    return SegmentationSummary(
        windows=len(scores),
        detection_rate=sum(s.n_detected_ok for s in scores) / n_truth if n_truth else nan,
        mean_iou=float(np.mean(ious)) if ious else nan,
        count_correct_rate=float(np.mean([s.n_detected == s.n_truth for s in scores])) if scores else nan,
        false_object_rate=float(np.mean([s.n_false > 0 for s in scores])) if scores else nan,
        missed_not_found=share("not_found"),
        missed_too_small=share("too_small"),
        missed_spills_out=share("spills_out"),
        sparse_share=sparse / n_truth if with_events else nan,
        detection_rate_dense=dense_ok / n_dense if with_events and n_dense else nan,
    )


def event_iou(pred_labels: np.ndarray, truth_labels: np.ndarray) -> float:
    """Per-event IoU of the moving-object class: events labelled IMO (>= 1) vs truth IMO.

    Events with truth -1 (noise) are ignored. 1.0 when neither labels any IMO event.
    """
    keep = truth_labels >= 0
    p = pred_labels[keep] >= 1
    g = truth_labels[keep] >= 1
    union = np.count_nonzero(p | g)
    return np.count_nonzero(p & g) / union if union else 1.0


# --------------------------------------------------------------------------- normal flow


def _flow_pair(pred, truth) -> tuple[np.ndarray, np.ndarray]:
    """Two flow arrays of one shape (..., 2), float64: (2, N) or a (2,) broadcast against
    (N, 2) would be read as other flows without a word."""
    pred, truth = np.asarray(pred, np.float64), np.asarray(truth, np.float64)
    if pred.shape != truth.shape or pred.ndim == 0 or pred.shape[-1] != 2:
        raise EventDataError(f"flows must be two arrays of one shape (N, 2) (x, y per row), got {pred.shape} "
                             f"and {truth.shape}")
    return pred, truth


def angular_error_deg(pred: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Angle between predicted and true normal flow vectors, degrees in [0, 180].

    >>> angular_error_deg(np.array([[1.0, 0]]), np.array([[0.0, 2]])).round(6).tolist()
    [90.0]
    """
    pred, truth = _flow_pair(pred, truth)
    dot = np.sum(pred * truth, axis=-1)
    cross = pred[..., 0] * truth[..., 1] - pred[..., 1] * truth[..., 0]
    return np.degrees(np.abs(np.arctan2(cross, dot)))


def relative_magnitude_error(pred: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """| |p| - |g| | / |g| per flow (dimensionless)."""
    pred, truth = _flow_pair(pred, truth)
    gp = np.linalg.norm(pred, axis=-1)
    gt = np.linalg.norm(truth, axis=-1)
    return np.abs(gp - gt) / np.maximum(gt, 1e-12)


def sign_correct_rate(pred: np.ndarray, flow: np.ndarray) -> float:
    """Share of predictions pointing to the same half-plane as the (optical or normal) flow."""
    pred, flow = _flow_pair(pred, flow)
    return float(np.mean(np.sum(np.asarray(pred) * np.asarray(flow), axis=-1) > 0))


def norm_error(pred: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """VecKM_flow's norm error | |p| - (p . u) / |p| | (px/s) against optical flow u.

    Zero exactly when p is a valid normal flow of u (p lies on the circle of diameter u).
    """
    n = np.linalg.norm(pred, axis=-1)
    proj = np.sum(pred * flow, axis=-1) / np.maximum(n, 1e-12)
    return np.abs(n - proj)


@dataclass(frozen=True)
class FlowErrors:
    """Summary of normal-flow errors over a set of flows."""

    n: int
    median_angular_error_deg: float
    mean_angular_error_deg: float
    sign_correct_rate: float
    median_relative_magnitude_error: float


def flow_errors(pred: np.ndarray, truth: np.ndarray) -> FlowErrors:
    """Summarize errors of predicted vs true normal flow, (N, 2) each, px/s; NaN rows skipped."""
    pred, truth = _flow_pair(pred, truth)
    ok = np.all(np.isfinite(pred), axis=-1) & np.all(np.isfinite(truth), axis=-1)
    pred, truth = pred[ok], truth[ok]
    if len(pred) == 0:
        nan = float("nan")
        return FlowErrors(0, nan, nan, nan, nan)
    ae = angular_error_deg(pred, truth)
    return FlowErrors(
        n=len(pred),
        median_angular_error_deg=float(np.median(ae)),
        mean_angular_error_deg=float(np.mean(ae)),
        sign_correct_rate=sign_correct_rate(pred, truth),
        median_relative_magnitude_error=float(np.median(relative_magnitude_error(pred, truth))),
    )


# --------------------------------------------------------------------------- label-free


def event_image(x: np.ndarray, y: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Image of events: count per pixel with bilinear voting, float64 ``(height, width)``."""
    h, w = shape
    img = np.zeros((h + 1) * (w + 1))
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = x - x0, y - y0
    ok = (x0 >= 0) & (y0 >= 0) & (x0 < w) & (y0 < h)
    x0, y0, fx, fy = x0[ok].astype(np.int64), y0[ok].astype(np.int64), fx[ok], fy[ok]
    for dx, dy, wgt in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        np.add.at(img, (y0 + dy) * (w + 1) + (x0 + dx), wgt)
    return img.reshape(h + 1, w + 1)[:h, :w]


def warp_sharpness(
    x: np.ndarray,
    y: np.ndarray,
    t_us: np.ndarray,
    flow_px_s: np.ndarray,
    shape: tuple[int, int],
    t_ref_us: float | None = None,
    blur_px: float = 1.0,
) -> float:
    """Label-free flow quality: variance of the image of warped events over the unwarped one
    (Stoffregen et al.'s flow warp loss).

    Each event is moved along its flow to the reference time ``t_ref_us`` (default: the
    middle of the events' time span): x' = x - (t - t_ref) * flow. A flow that explains the
    motion stacks events of one edge onto one line, which raises the variance of the image
    of warped events (contrast maximisation). Values > 1 mean the flow sharpens the image;
    zero flow gives exactly 1. Normal flow moves events along the edge normal only, which is
    the direction that matters for sharpness.

    Both images are smoothed by a Gaussian of ``blur_px`` (px; 0: none). Without it the
    comparison is biased towards small flows: unwarped events sit on whole pixels and put
    their whole bilinear vote in one pixel, while any fractional shift spreads it over four,
    which lowers the variance by itself (on simulated scenes, 10 ms of events warped by their
    exact normal flow then scored below zero flow).

    Args:
        x, y: event coordinates (px); t_us: timestamps (us); flow_px_s: (N, 2) px/s; events
            whose flow is not finite are left out of both images.
        shape: (height, width) of the image.
        t_ref_us: reference time (us).
        blur_px: standard deviation of the Gaussian smoothing (px).

    Use every event of a span long enough for edges to move a few pixels (``evseg eval
    flow-real`` takes 30 ms), each with its own flow: a sparse subsample leaves little to
    stack, and a short span little to sharpen.
    """
    import cv2

    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    t = np.asarray(t_us, np.float64)
    flow = np.asarray(flow_px_s, np.float64)
    ok = np.all(np.isfinite(flow), axis=-1)
    x, y, t, flow = x[ok], y[ok], t[ok], flow[ok]
    if len(x) == 0:
        return float("nan")
    if t_ref_us is None:
        t_ref_us = 0.5 * (t.min() + t.max())
    dt = (t - t_ref_us) * 1e-6
    warped = event_image(x - dt * flow[:, 0], y - dt * flow[:, 1], shape)
    raw = event_image(x, y, shape)
    if blur_px > 0:
        warped = cv2.GaussianBlur(warped, (0, 0), blur_px)
        raw = cv2.GaussianBlur(raw, (0, 0), blur_px)
    v_raw = raw.var()
    return float(warped.var() / v_raw) if v_raw > 0 else float("nan")
