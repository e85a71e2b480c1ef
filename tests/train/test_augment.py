"""Augmentation maps events and ground-truth flow consistently and never mutates its input."""

from __future__ import annotations

import numpy as np
import pytest

from evseg.events import make_events
from evseg.train.augment import (
    NO_AUGMENTATION,
    AugmentConfig,
    FlowSlice,
    add_noise_events,
    augment_slice,
    flip_slice,
    rotate_slice,
    scale_slice,
    subsample_slice,
    time_scale_slice,
)


def _slice() -> FlowSlice:
    ev = make_events(x=[5, 6, 0, 10], y=[4, 4, 0, 8], t=[0, 100, 200, 300], p=[1, -1, 1, 1])
    nf = np.array([[1, 0], [0, 2], [np.nan, np.nan], [3, 4]], dtype=np.float32)
    of = np.array([[1, 1], [0, 2], [np.nan, np.nan], [3, 4]], dtype=np.float32)
    return FlowSlice(ev, (11, 9), nf, of)


def test_rotation_by_quarter_turn_is_exact():
    s = _slice()
    r = rotate_slice(s, np.pi / 2)
    # centre (5, 4); (x, y) -> (cx - (y - cy), cy + (x - cx)): y down, so clockwise on screen
    # (0, 0) -> (9, -1) is off the sensor and dropped; (10, 8) -> (1, 9) is off too (H = 9)
    assert r.events["x"].tolist() == [5, 5]
    assert r.events["y"].tolist() == [4, 5]
    np.testing.assert_allclose(r.normal_flow, [[0, 1], [-2, 0]], atol=1e-6)  # float rounding of cos(pi/2)
    np.testing.assert_allclose(r.optical_flow, [[-1, 1], [-2, 0]], atol=1e-6)


def test_full_turn_is_identity_and_input_untouched():
    s = _slice()
    before = s.events.copy(), s.normal_flow.copy()
    r = rotate_slice(s, 2 * np.pi)
    np.testing.assert_array_equal(r.events, s.events)
    np.testing.assert_allclose(r.normal_flow, s.normal_flow, atol=1e-5)  # float32 round trip
    np.testing.assert_array_equal(s.events, before[0])
    np.testing.assert_array_equal(s.normal_flow, before[1])


def test_flip_negates_components_and_is_an_involution():
    s = _slice()
    f = flip_slice(s, horizontal=True, vertical=False)
    assert f.events["x"].tolist() == [5, 4, 10, 0]
    assert f.events["y"].tolist() == s.events["y"].tolist()
    np.testing.assert_array_equal(f.normal_flow[0], [-1, 0])
    ff = flip_slice(f, horizontal=True, vertical=False)
    np.testing.assert_array_equal(ff.events, s.events)
    fv = flip_slice(s, horizontal=False, vertical=True)
    assert fv.events["y"].tolist() == [4, 4, 8, 0]
    np.testing.assert_array_equal(fv.normal_flow[3], [3, -4])


def test_scale_multiplies_positions_and_flow():
    s = _slice()
    r = scale_slice(s, 2.0)
    # (6, 4) -> (7, 4); (5, 4) stays; others leave the 11 x 9 sensor
    assert r.events["x"].tolist() == [5, 7]
    np.testing.assert_array_equal(r.normal_flow, [[2, 0], [0, 4]])


def test_time_scaling_divides_flow():
    s = _slice()
    r = time_scale_slice(s, 2.0)
    assert r.events["t"].tolist() == [0, 200, 400, 600]
    np.testing.assert_array_equal(r.optical_flow[3], [1.5, 2.0])


def test_subsample_and_noise():
    s = _slice()
    rng = np.random.default_rng(0)
    assert len(subsample_slice(s, 1.0, rng)) == 4
    big = FlowSlice(
        make_events(np.zeros(1000), np.zeros(1000), np.arange(1000), np.ones(1000)),
        (20, 10),
        np.ones((1000, 2), np.float32),
    )
    half = subsample_slice(big, 0.5, rng)
    assert 400 < len(half) < 600  # binomial(1000, 0.5): 6 standard deviations either side
    noisy = add_noise_events(big, rate_ev_px_s=500.0, rng=rng)  # 200 px * 1 ms * 500 -> ~100
    added = len(noisy) - len(big)
    assert 50 < added < 150
    assert np.all(np.diff(noisy.events["t"]) >= 0)
    assert np.isnan(noisy.normal_flow).any(axis=1).sum() == added
    assert noisy.optical_flow is None


def test_augment_slice_identity_and_random():
    s = _slice()
    same = augment_slice(s, NO_AUGMENTATION, np.random.default_rng(0))
    np.testing.assert_array_equal(same.events, s.events)
    a = augment_slice(s, AugmentConfig(), np.random.default_rng(3))
    b = augment_slice(s, AugmentConfig(), np.random.default_rng(3))
    np.testing.assert_array_equal(a.events, b.events)  # deterministic given the seed


def test_bad_factors_raise():
    with pytest.raises(ValueError):
        scale_slice(_slice(), 0.0)
    with pytest.raises(ValueError):
        time_scale_slice(_slice(), -1.0)


def test_right_angle_rotations_are_exact_grid_symmetries():
    from evseg.train.augment import draw_augmentation

    cfg = AugmentConfig(rotation_step_deg=90.0)
    angles = {round(np.degrees(draw_augmentation(cfg, np.random.default_rng(i)).angle_rad)) for i in range(64)}
    assert angles == {0, 90, 180, 270}
    # A square sensor: a quarter turn keeps every event (no rounding, nothing off the sensor).
    ev = make_events(x=[0, 3, 7, 2], y=[0, 5, 7, 6], t=[0, 1, 2, 3], p=[1, 1, -1, 1])
    s = FlowSlice(ev, (8, 8), np.ones((4, 2), np.float32))
    r = rotate_slice(s, np.pi / 2)
    assert len(r) == 4
    assert sorted(zip(r.events["x"].tolist(), r.events["y"].tolist())) == sorted([(7, 0), (2, 3), (0, 7), (1, 2)])


def test_labels_follow_their_events_through_every_transform():
    """The ground-truth motion label travels with its event (noise events get -1), so the
    training rows know which targets lie on moving objects."""
    s = _slice()
    s = FlowSlice(s.events, s.sensor_size, s.normal_flow, s.optical_flow, np.array([0, 1, -1, 2], np.int16))
    key = lambda f: {(int(e["t"]), int(lab)) for e, lab in zip(f.events, f.label)}  # noqa: E731
    for out in (rotate_slice(s, np.pi / 2), flip_slice(s, True, True), scale_slice(s, 1.0),
                subsample_slice(s, 1.0, np.random.default_rng(0)), s.take(np.array([3, 0]))):
        assert len(out.label) == len(out) and key(out) <= key(s)
    assert time_scale_slice(s, 2.0).label.tolist() == [0, 1, -1, 2]
    noisy = add_noise_events(s, rate_ev_px_s=5000.0, rng=np.random.default_rng(0))
    assert len(noisy) > len(s) and sorted(noisy.label.tolist()).count(-1) == len(noisy) - 3
    assert _slice().label is None and rotate_slice(_slice(), 0.0).label is None
