"""The DVS pixel model: exact crossing times, refractory period, mismatch, noise rates."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evseg.simulator.camera import PixelArray, noise_events
from evseg.simulator.scene import SensorConfig


def _sensor(**kw) -> SensorConfig:
    base = dict(width=2, height=1, c_pos=0.2, c_neg=0.2, c_sigma=0.0, refractory_us=0.0,
                noise_rate_hz=0.0, random_initial_level=False)
    base.update(kw)
    return SensorConfig(**base)


def test_crossings_are_interpolated_linearly_in_log_intensity():
    # Pixel 0 rises by 1.0 in log intensity over 1000 us: 5 ON crossings at 200, 400, ... us.
    # Pixel 1 falls by 0.5: 2 OFF crossings at 400 and 800 us (the remaining 0.1 stays pending).
    px = PixelArray(_sensor(), np.zeros((1, 2), np.float32), np.random.default_rng(0))
    cr = px.step(np.zeros((1, 2), np.float32), np.array([[1.0, -0.5]], np.float32), 0.0, 1000.0)
    order = np.lexsort((cr.t_us, cr.pixel))
    np.testing.assert_array_equal(cr.pixel[order], [0, 0, 0, 0, 0, 1, 1])
    np.testing.assert_array_equal(cr.p[order], [1, 1, 1, 1, 1, -1, -1])
    # float32 log levels: times exact to well below a microsecond
    np.testing.assert_allclose(cr.t_us[order], [200, 400, 600, 800, 1000, 400, 800], atol=1e-3)
    np.testing.assert_allclose(px.ref, [1.0, -0.4], atol=1e-6)


def test_pending_change_fires_in_the_next_step():
    px = PixelArray(_sensor(width=1), np.zeros((1, 1), np.float32), np.random.default_rng(0))
    a = px.step(np.zeros((1, 1), np.float32), np.full((1, 1), 0.15, np.float32), 0.0, 100.0)
    assert len(a.pixel) == 0
    b = px.step(np.full((1, 1), 0.15, np.float32), np.full((1, 1), 0.25, np.float32), 100.0, 200.0)
    # level 0.2 is reached half-way through the second step
    np.testing.assert_allclose(b.t_us, [150.0], atol=1e-3)


def test_refractory_period_drops_crossings_and_loses_their_change():
    px = PixelArray(_sensor(width=1, refractory_us=300.0), np.zeros((1, 1), np.float32), np.random.default_rng(0))
    cr = px.step(np.zeros((1, 1), np.float32), np.ones((1, 1), np.float32), 0.0, 1000.0)
    # crossings at 200..1000 us; 400 and 800 fall within 300 us of the last emitted event
    np.testing.assert_allclose(np.sort(cr.t_us), [200, 600, 1000], atol=1e-3)
    np.testing.assert_allclose(px.ref, [1.0], atol=1e-6)


def test_threshold_mismatch_has_the_configured_spread():
    sensor = _sensor(width=200, height=100, c_sigma=0.03)
    px = PixelArray(sensor, np.zeros((100, 200), np.float32), np.random.default_rng(1))
    # 20000 draws: the sample std is within 3 % of sigma with overwhelming probability
    assert px.c_pos.std() == pytest.approx(0.03, rel=0.03)
    assert px.c_neg.mean() == pytest.approx(0.2, abs=0.002)


def test_random_initial_level_lies_within_the_threshold_band():
    sensor = _sensor(width=100, height=100, random_initial_level=True)
    log0 = np.random.default_rng(2).normal(size=(100, 100)).astype(np.float32)
    px = PixelArray(sensor, log0, np.random.default_rng(3))
    d = log0.ravel() - px.ref
    assert np.all(d > -0.2) and np.all(d < 0.2)  # strictly inside, as the step computes it
    assert d.std() == pytest.approx(0.4 / np.sqrt(12), rel=0.05)  # uniform on (-C_neg, C_pos)


def test_a_pixel_whose_intensity_does_not_change_never_fires():
    # 10^6 pixels with a random initial level: float32 rounding once put ~10 of them exactly
    # on a threshold, and they fired at t = 0 (a still camera's background showed them).
    sensor = _sensor(width=1000, height=1000, c_pos=0.25, c_neg=0.3, c_sigma=0.03, random_initial_level=True)
    # A large log intensity (coarse float32 spacing) makes the rounding likely.
    log0 = np.random.default_rng(5).uniform(100, 200, size=(1000, 1000)).astype(np.float32)
    px = PixelArray(sensor, log0, np.random.default_rng(6))
    with np.errstate(divide="raise", invalid="raise"):
        cr = px.step(log0, log0, 0.0, 1000.0)
    assert len(cr.pixel) == 0


def test_noise_and_hot_pixel_rates():
    sensor = _sensor(width=100, height=100, noise_rate_hz=2.0, hot_pixel_fraction=0.001, hot_pixel_rate_hz=500.0)
    cr = noise_events(sensor, 1_000_000, np.random.default_rng(4))
    hot_pix, counts = np.unique(cr.pixel, return_counts=True)
    hot = hot_pix[counts > 100]  # a BA pixel fires ~2 times in 1 s, a hot one ~500
    assert len(hot) == 10
    n_ba = len(cr.pixel) - counts[counts > 100].sum()
    expected = 2.0 * 100 * 100 * 1.0
    assert abs(n_ba - expected) < 5 * np.sqrt(expected)  # Poisson: 5 sigma
    for h in hot:  # a hot pixel keeps one polarity (plus its ~2 background-activity events)
        assert abs(cr.p[cr.pixel == h].mean()) > 0.95
    assert np.all((cr.t_us >= 0) & (cr.t_us < 1_000_000))



@settings(max_examples=60, deadline=None)
@given(
    levels=st.lists(st.floats(-3.0, 3.0, allow_nan=False), min_size=2, max_size=30),
    c_pos=st.floats(0.05, 0.5),
    c_neg=st.floats(0.05, 0.5),
)
def test_events_account_for_every_threshold_crossing(levels, c_pos, c_neg):
    # Whatever the log-intensity path, the reference stays within (-C_neg, C_pos) of the signal,
    # it moved by exactly (ON count) C_pos - (OFF count) C_neg, timestamps lie in their step and
    # are ordered per pixel.
    sensor = _sensor(width=1, c_pos=c_pos, c_neg=c_neg)
    path = np.asarray(levels, np.float32)
    px = PixelArray(sensor, path[:1].reshape(1, 1), np.random.default_rng(0))
    n_on = n_off = 0
    times = []
    for i in range(1, len(path)):
        cr = px.step(path[i - 1 : i].reshape(1, 1), path[i : i + 1].reshape(1, 1), 100.0 * (i - 1), 100.0 * i)
        assert np.all((cr.t_us >= 100.0 * (i - 1)) & (cr.t_us <= 100.0 * i))
        times.extend(np.sort(cr.t_us))
        n_on += int((cr.p > 0).sum())
        n_off += int((cr.p < 0).sum())
        d = float(path[i] - px.ref[0])
        assert -c_neg - 1e-5 < d < c_pos + 1e-5
    np.testing.assert_allclose(px.ref[0] - path[0], n_on * np.float32(c_pos) - n_off * np.float32(c_neg), atol=1e-4)
    assert np.all(np.diff(times) >= 0)
