import re

import numpy as np
import pytest

from evseg.events import EVENT_DTYPE
from evseg.veckm_flow import PlaneFitNormalFlow, plane_fit_normal_flow, select_targets, time_surface
from evseg.veckm_flow.synthetic import edge_events, translating_edges


def _edge_slice(angle_deg: float, speed: float):
    x, y, t = edge_events((64, 48), (10.0, 10.0), np.radians(angle_deg), speed, 200.0, 60_000)
    order = np.argsort(t, kind="stable")
    ev = np.empty(len(x), EVENT_DTYPE)
    ev["x"], ev["y"], ev["t"], ev["p"] = x[order], y[order], t[order], 1
    return ev


@pytest.mark.parametrize("angle_deg,speed", [(0.0, 500.0), (30.0, 1500.0), (-120.0, 800.0), (90.0, 300.0)])
def test_plane_fit_recovers_known_normal_flow_of_a_translating_edge(angle_deg, speed):
    ev = _edge_slice(angle_deg, speed)
    # Targets away from the sensor border and from the slice's first/last 3 px of travel,
    # where the window sees a full plane.
    inner = (ev["x"] > 4) & (ev["x"] < 59) & (ev["y"] > 4) & (ev["y"] < 43)
    inner &= (ev["t"] > 3 / speed * 1e6) & (ev["t"] < 60_000 - 3 / speed * 1e6)
    targets = np.flatnonzero(inner)
    flow = PlaneFitNormalFlow()(ev, (64, 48), targets)
    ok = flow.valid
    assert ok.mean() > 0.95
    expect = speed * np.array([np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))])
    # Timestamps are floored to whole microseconds: over a 7 px window at <= 1500 px/s
    # (>= 667 us per px) that is < 0.2 % of the time differences, so 1 % on flow is safe.
    np.testing.assert_allclose(np.median(flow.nx[ok]), expect[0], atol=0.01 * speed)
    np.testing.assert_allclose(np.median(flow.ny[ok]), expect[1], atol=0.01 * speed)
    np.testing.assert_allclose(flow.nx[ok], expect[0], atol=0.03 * speed)
    assert np.all(flow.uncertainty[ok] < 0.01)  # rad: a clean plane fits almost exactly


def test_rejects_isolated_events_and_flags_them():
    ev = np.zeros(3, EVENT_DTYPE)
    ev["x"] = [5, 20, 40]
    ev["y"] = [5, 20, 10]
    ev["t"] = [0, 10, 20]
    flow = PlaneFitNormalFlow()(ev, (64, 48))
    assert not flow.valid.any()
    assert np.all(np.isinf(flow.uncertainty))
    np.testing.assert_array_equal(flow.index, [0, 1, 2])


def test_time_surface_keeps_latest_timestamp():
    ev = np.zeros(4, EVENT_DTYPE)
    ev["x"] = [1, 1, 2, 1]
    ev["y"] = [0, 0, 1, 0]
    ev["t"] = [5, 7, 8, 9]
    ts = time_surface(ev, (3, 2))
    np.testing.assert_array_equal(ts, [[-1, 9, -1], [-1, -1, 8]])


def test_baseline_on_many_edges_is_accurate_and_uncertainty_ranks_errors():
    scene = translating_edges(n_edges=30, seed=4)
    targets = select_targets(scene.events, scene.sensor_size, cell_px=2)
    flow = PlaneFitNormalFlow()(scene.events, scene.sensor_size, targets)
    ok = flow.valid
    gt = scene.nx[targets] + 1j * scene.ny[targets]
    ang = np.degrees(np.abs(np.angle((flow.nx + 1j * flow.ny) / gt)))[ok]
    assert np.median(ang) < 1.0  # clean planes; crossings of edges make the outliers
    unc = flow.uncertainty[ok]
    keep = unc <= np.quantile(unc, 0.8)
    assert np.mean(ang[keep]) < np.mean(ang)


def test_plane_fit_function_does_not_mutate_input():
    scene = translating_edges(n_edges=3, seed=1)
    before = scene.events.copy()
    plane_fit_normal_flow(scene.events, np.arange(0, len(scene.events), 5), scene.sensor_size)
    np.testing.assert_array_equal(scene.events, before)


def test_random_timestamps_are_rejected_by_the_scale_free_residual_rule(make_slice):
    # Uniformly random times on a dense 40x30 patch: no plane explains them. The residual as an
    # edge position error is many px, so (almost) all fits are rejected; without the rule none is.
    ev = make_slice(3000, (40, 30))
    assert PlaneFitNormalFlow()(ev, (40, 30)).valid.mean() < 0.02
    assert PlaneFitNormalFlow(max_rms_px=1e9)(ev, (40, 30)).valid.mean() == 1.0


@pytest.mark.parametrize("kwargs, message", [
    (dict(radius_px=0), "PlaneFitNormalFlow.radius_px must be an integer >= 1, got 0"),
    (dict(radius_px=-1), "PlaneFitNormalFlow.radius_px must be an integer >= 1, got -1"),
    (dict(radius_px=2.5), "PlaneFitNormalFlow.radius_px must be an integer >= 1, got 2.5"),
    (dict(min_points=2), "PlaneFitNormalFlow.min_points must be an integer >= 4, got 2"),
    (dict(max_dt_us=0), "PlaneFitNormalFlow.max_dt_us must be a positive integer"),
    (dict(max_rms_px=0.0), "PlaneFitNormalFlow.max_rms_px must be positive"),
])
def test_settings_that_would_give_no_flow_or_crash_are_refused(kwargs, message):
    from evseg.errors import ConfigError

    with pytest.raises(ConfigError, match=re.escape(message)):
        PlaneFitNormalFlow(**kwargs)


def test_time_surface_and_plane_fit_refuse_events_off_the_sensor():
    # Their compiled kernel writes per pixel without bounds checks: events off the sensor
    # (or a swapped width and height) corrupted the heap and killed the interpreter.
    from evseg.errors import EventDataError

    ev = _edge_slice(0.0, 500.0)  # on a 64x48 sensor
    with pytest.raises(EventDataError, match=r"time_surface events: field 'x' = \d+ at event \d+ is outside the sensor \(10x10"):
        time_surface(ev, (10, 10))
    with pytest.raises(EventDataError, match="outside the sensor"):
        plane_fit_normal_flow(ev, np.arange(10), (10, 10))
    with pytest.raises(EventDataError, match=r"targets: position 99999 is outside"):
        plane_fit_normal_flow(ev, np.array([99999]), (64, 48))
