import numpy as np
import pytest

from evseg.errors import EventDataError
from evseg.events import EVENT_DTYPE
from evseg.veckm_flow import select_targets


def _ev(xs, ys):
    ev = np.zeros(len(xs), EVENT_DTYPE)
    ev["x"], ev["y"], ev["t"] = xs, ys, np.arange(len(xs))
    return ev


def test_latest_event_per_cell():
    #             cell (0,0)  (0,0)  (1,0)  (0,0)  (1,1)
    ev = _ev([0, 1, 2, 1, 3], [0, 1, 0, 0, 3])
    np.testing.assert_array_equal(select_targets(ev, (4, 4), cell_px=2), [2, 3, 4])
    np.testing.assert_array_equal(select_targets(ev, (4, 4), cell_px=None), [0, 1, 2, 3, 4])
    np.testing.assert_array_equal(select_targets(ev, (4, 4), cell_px=4), [4])


def test_max_targets_is_deterministic_and_sorted(make_slice):
    ev = make_slice(5000, (50, 40))
    a = select_targets(ev, (50, 40), cell_px=1, max_targets=300, seed=2)
    b = select_targets(ev, (50, 40), cell_px=1, max_targets=300, seed=2)
    np.testing.assert_array_equal(a, b)
    assert len(a) == 300 and np.all(np.diff(a) > 0) and a.dtype == np.int64


def test_bad_cell_size_raises():
    with pytest.raises(EventDataError, match="cell_px"):
        select_targets(_ev([0], [0]), (4, 4), cell_px=0)


def test_a_swapped_sensor_size_is_refused_not_used():
    # (height, width) keeps the combined cell index in range for most events, so the cells
    # (and the targets) came out wrong without a word.
    ev = np.zeros(2, EVENT_DTYPE)
    ev["x"], ev["y"], ev["t"] = [300, 5], [5, 5], [0, 1]
    assert len(select_targets(ev, (346, 260))) == 2
    with pytest.raises(EventDataError, match=r"select_targets: event 0 at \(300, 5\) is outside the 260x346 sensor"):
        select_targets(ev, (260, 346))
    with pytest.raises(EventDataError, match="max_targets must be a non-negative integer"):
        select_targets(ev, (346, 260), max_targets=-1)
