"""One window's preparation (segmentation/window.py): the node graph and per-node terms from
the window's flow alone, and round 0's sampled candidates."""

import numpy as np
import pytest

from evseg.errors import EventDataError
from evseg.segmentation import SegmentationConfig
from evseg.segmentation.synthetic import synthetic_scene
from evseg.segmentation.window import prepare_window, sample_candidates, support_weights


def test_prepared_window_holds_one_entry_per_node_and_leaves_the_inputs_alone():
    s = synthetic_scene(n_flows=1500, n_objects=2, seed=2)
    before = [a.copy() for a in (s.x, s.y, s.t, s.nx, s.ny)]
    pw = prepare_window(s.x, s.y, s.t, s.nx, s.ny, sensor_size=s.sensor_size)
    for a, b in zip((s.x, s.y, s.t, s.nx, s.ny), before):
        np.testing.assert_array_equal(a, b)
    m = len(pw.graph)
    assert 0 < m <= len(s.x)
    for name in ("xr", "yr", "conf", "fit_w", "vote_x", "vote_y", "voting", "suspect"):
        assert getattr(pw, name).shape == (m,), name
    assert pw.origin == ((s.sensor_size[0] - 1) / 2, (s.sensor_size[1] - 1) / 2)  # the sensor centre
    np.testing.assert_allclose(pw.xr, pw.graph.x - pw.origin[0])
    assert pw.edge_w.shape == (len(pw.graph.edges),) and pw.sigma > 0


def test_support_weights_are_relative_to_the_median_and_clipped():
    w = support_weights(np.array([1.0, 16.0, 16.0, 16.0, 4096.0]), 0.5)
    np.testing.assert_allclose(w, [0.25, 1.0, 1.0, 1.0, 4.0])  # sqrt(1/16) = 0.25, sqrt(256) -> 4
    np.testing.assert_array_equal(support_weights(np.array([3.0, 9.0]), 0.0), [1.0, 1.0])
    assert support_weights(None, 0.25).shape == (0,)


@pytest.mark.parametrize("event_xy, match", [
    ((np.zeros(3), np.zeros(2)), "x has 3 values, y has 2"),
    ((np.array([0.0, np.nan]), np.zeros(2)), "NaN or infinite"),
    ((np.zeros(2), ["a", "b"]), "numeric"),
    # events of another place or window: the support weights divided by a median of 0 (NaN costs)
    ((np.zeros(10), np.zeros(10)), r"event_xy: \d+ of the \d+ node cells hold none of its 10 positions"),
    ((np.zeros(0), np.zeros(0)), r"event_xy: \d+ of the \d+ node cells hold none of its 0 positions"),
])
def test_bad_event_positions_are_a_clear_error(event_xy, match):
    s = synthetic_scene(n_flows=300, n_objects=1, seed=1)
    with pytest.raises(EventDataError, match=match):
        prepare_window(s.x, s.y, s.t, s.nx, s.ny, sensor_size=s.sensor_size, event_xy=event_xy)


def test_n_sampled_normal_adds_candidates_from_the_normal_flows():
    """n_sampled_normal = k: round 0 gets up to k more sampled candidates, translations chosen
    among the nodes' normal flows away from the other candidates; 0 leaves sampling as it was."""
    s = synthetic_scene(n_flows=2000, n_objects=2, seed=5)
    plain = sample_candidates(prepare_window(s.x, s.y, s.t, s.nx, s.ny, sensor_size=s.sensor_size), 6)
    cfg = SegmentationConfig(n_sampled_normal=2)
    more = sample_candidates(prepare_window(s.x, s.y, s.t, s.nx, s.ny, config=cfg, sensor_size=s.sensor_size), 6)
    k = len(more.models) - len(plain.models)
    assert 1 <= k <= 2
    np.testing.assert_array_equal(more.models[: len(plain.models)], plain.models)
    assert more.data.shape == (plain.data.shape[0], len(more.models))


