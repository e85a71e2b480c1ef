import numpy as np
import pytest

from evseg.metrics import (
    angular_error_deg,
    box_to_mask,
    convex_hull_mask,
    detection_outcome,
    detection_success,
    event_iou,
    flow_errors,
    mask_iou,
    mask_to_box,
    norm_error,
    score_window,
    sign_correct_rate,
    summarize,
    warp_sharpness,
)

SHAPE = (40, 40)


def test_box_mask_roundtrip_inclusive():
    m = box_to_mask((2, 3, 5, 7), SHAPE)
    assert m.sum() == 4 * 5  # inclusive: columns 2..5, rows 3..7
    assert mask_to_box(m) == (2, 3, 5, 7)
    assert mask_to_box(np.zeros(SHAPE, bool)) is None


def test_mask_iou_hand_computed():
    a = box_to_mask((0, 0, 9, 9), SHAPE)  # 100 px
    b = box_to_mask((5, 0, 14, 9), SHAPE)  # 100 px, overlap 50
    assert mask_iou(a, b) == pytest.approx(50 / 150)


def test_detection_criterion_both_conditions():
    g = box_to_mask((0, 0, 9, 9), SHAPE)  # 100 px
    # IoU = 81/100 > 0.5 and all of D inside G.
    assert detection_success(box_to_mask((0, 0, 8, 8), SHAPE), g)
    # D = 10x12 box overlapping G in 100 px, 20 px outside: IoU = 100/120 > .5, 100 > 20.
    assert detection_success(box_to_mask((0, 0, 9, 11), SHAPE), g)
    # IoU exactly 0.5 fails (strict): D of 200 px containing G.
    assert not detection_success(box_to_mask((0, 0, 19, 9), SHAPE), g)
    # Large overlap fraction but IoU < 0.5: D tiny inside G.
    assert not detection_success(box_to_mask((0, 0, 2, 2), SHAPE), g)


def test_score_window_matches_and_counts_false_objects():
    g1 = box_to_mask((0, 0, 9, 9), SHAPE)
    g2 = box_to_mask((20, 20, 29, 29), SHAPE)
    d_good = box_to_mask((20, 20, 28, 29), SHAPE)  # matches g2, IoU 0.9
    d_false = box_to_mask((0, 30, 5, 35), SHAPE)  # overlaps nothing
    s = score_window([d_false, d_good], [g1, g2])
    assert s.n_truth == 2 and s.n_detected == 2 and s.n_detected_ok == 1 and s.n_false == 1
    assert s.ious == pytest.approx((0.0, 0.9))
    summary = summarize([s, score_window([], [])])
    assert summary.detection_rate == pytest.approx(0.5)
    assert summary.mean_iou == pytest.approx(0.45)
    assert summary.count_correct_rate == pytest.approx(1.0)  # 2 == 2 and 0 == 0
    assert summary.false_object_rate == pytest.approx(0.5)


def test_misses_are_split_by_the_clause_of_the_criterion_they_fail():
    g1 = box_to_mask((0, 0, 9, 9), SHAPE)  # 100 px each
    g2 = box_to_mask((20, 0, 29, 9), SHAPE)
    g3 = box_to_mask((0, 20, 9, 29), SHAPE)
    g4 = box_to_mask((20, 20, 29, 29), SHAPE)
    detected = [
        box_to_mask((0, 0, 8, 9), SHAPE),  # g1: IoU 0.9 -> detected
        box_to_mask((20, 0, 23, 9), SHAPE),  # g2: 40 px, all inside: IoU 0.4 -> too small
        box_to_mask((0, 15, 19, 34), SHAPE),  # g3: 100 of 400 px inside -> spills out
    ]  # g4: nothing overlaps it -> not found
    s = score_window(detected, [g1, g2, g3, g4], truth_events=[500, 60, 80, 10])
    assert s.outcomes == ("detected", "too_small", "spills_out", "not_found")
    assert s.n_detected_ok == 1
    summary = summarize([s])
    assert summary.detection_rate == pytest.approx(0.25)
    assert (summary.missed_not_found, summary.missed_too_small, summary.missed_spills_out) == pytest.approx(
        (0.25, 0.25, 0.25))
    # g4 fired 10 events (< 50): sparse; the other three are dense, one detected.
    assert summary.sparse_share == pytest.approx(0.25)
    assert summary.detection_rate_dense == pytest.approx(1 / 3)


def test_detection_outcome_matches_detection_success():
    g = box_to_mask((5, 5, 14, 14), SHAPE)
    rng = np.random.default_rng(0)
    for _ in range(200):
        x0, y0 = rng.integers(0, 30, 2)
        w, h = rng.integers(1, 20, 2)
        d = box_to_mask((x0, y0, x0 + w, y0 + h), SHAPE)
        assert (detection_outcome(d, g) == "detected") == detection_success(d, g)
    assert detection_outcome(None, g) == "not_found"


def test_summary_without_event_counts_leaves_the_sparse_figures_unknown():
    g = box_to_mask((0, 0, 9, 9), SHAPE)
    summary = summarize([score_window([], [g])])
    assert summary.missed_not_found == 1.0
    assert np.isnan(summary.sparse_share) and np.isnan(summary.detection_rate_dense)
    with pytest.raises(ValueError, match="1 event counts for 2 truth objects"):
        score_window([], [g, g], truth_events=[5])


def test_convex_hull_mask_of_square_corners():
    m = convex_hull_mask(np.array([2, 8, 8, 2]), np.array([2, 2, 8, 8]), SHAPE)
    assert mask_to_box(m) == (2, 2, 8, 8) and m.sum() == 49


def test_event_iou_ignores_noise():
    truth = np.array([0, 1, 1, -1, 0])
    pred = np.array([0, 1, 0, 1, 2])
    # IMO events: pred {1, 4} (3 ignored), truth {1, 2} -> inter 1, union 3.
    assert event_iou(pred, truth) == pytest.approx(1 / 3)


def test_flow_metrics_hand_computed():
    assert angular_error_deg(np.array([[1.0, 1.0]]), np.array([[1.0, 0.0]]))[0] == pytest.approx(45)
    assert angular_error_deg(np.array([[-1.0, 0.0]]), np.array([[1.0, 0.0]]))[0] == pytest.approx(180)
    u = np.array([[2.0, 0.0]])
    # (1, 1) is on the circle of diameter u=(2,0): |p| = sqrt2, p.u/|p| = 2/sqrt2 = sqrt2.
    assert norm_error(np.array([[1.0, 1.0]]), u)[0] == pytest.approx(0, abs=1e-12)
    assert sign_correct_rate(np.array([[1.0, 5.0], [-1.0, 0.0]]), np.array([[1.0, 0.0], [1.0, 0.0]])) == 0.5
    e = flow_errors(np.array([[1.0, 0], [0, 1], [np.nan, 0]]), np.array([[2.0, 0], [1, 0], [1, 0]]))
    assert e.n == 2 and e.median_angular_error_deg == pytest.approx(45)
    assert e.median_relative_magnitude_error == pytest.approx(0.25)  # errors 0.5 and 0


def test_warp_sharpness_rewards_true_flow():
    # A vertical line of events moving right at 1000 px/s over 20 ms: 20 px of smear.
    rng = np.random.default_rng(0)
    n = 4000
    t = np.sort(rng.uniform(0, 20_000, n))
    x = 5 + 1000 * t * 1e-6
    y = rng.uniform(5, 35, n)
    true = np.tile([1000.0, 0.0], (n, 1))
    good = warp_sharpness(x, y, t, true, SHAPE)
    zero = warp_sharpness(x, y, t, np.zeros((n, 2)), SHAPE)
    wrong = warp_sharpness(x, y, t, -true, SHAPE)
    assert zero == pytest.approx(1.0)
    assert good > 5 and wrong < 1


def test_warp_sharpness_does_not_reward_small_flows_for_the_pixel_grid():
    # Events on whole pixels, moved by at most 0.3 px in random directions: too little to
    # sharpen or blur anything, so the ratio must stay near 1. Unsmoothed, the fractional
    # shifts alone spread each bilinear vote over four pixels and the ratio fell to 0.83,
    # which made any small flow (and zero flow most of all) look better than a right one.
    rng = np.random.default_rng(0)
    n = 4000
    t = np.sort(rng.uniform(0, 30_000, n))
    x, y = rng.integers(5, 55, n).astype(float), rng.integers(5, 35, n).astype(float)
    angle = rng.uniform(0, 2 * np.pi, n)
    flow = 20 * np.stack([np.cos(angle), np.sin(angle)], 1)  # px/s: <= 0.3 px over 15 ms
    assert warp_sharpness(x, y, t, flow, SHAPE) == pytest.approx(1.0, abs=0.03)
    assert warp_sharpness(x, y, t, flow, SHAPE, blur_px=0) < 0.9  # the bias the smoothing removes


def test_numeric_masks_count_their_nonzero_pixels_and_shapes_must_agree():
    # 1 and 2 are both "in": a bitwise and of them is empty (IoU 0, a miss).
    from evseg.errors import EventDataError
    from evseg.metrics import detection_success, mask_iou

    a, b = np.zeros((4, 4), np.int64), np.zeros((4, 4), np.uint8)
    a[:2, :2], b[:2, :2] = 1, 2
    assert mask_iou(a, b) == 1.0 and detection_success(a, b)
    assert mask_iou(a.astype(float), b) == 1.0
    with pytest.raises(EventDataError, match=r"masks of different shapes \(4, 4\) and \(4, 5\)"):
        mask_iou(a, np.zeros((4, 5), bool))


def test_flow_errors_refuse_flows_of_other_shapes():
    from evseg.errors import EventDataError
    from evseg.metrics import angular_error_deg, flow_errors

    pred = np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    with pytest.raises(EventDataError, match=r"one shape \(N, 2\).*\(2, 3\) and \(2, 3\)"):
        flow_errors(pred.T, pred.T)  # (2, N): would be read as 2 flows of N components
    with pytest.raises(EventDataError, match=r"\(3, 2\) and \(2,\)"):
        angular_error_deg(pred, np.array([1.0, 0.0]))
