import numpy as np
import pytest

from evseg.events import make_events
from evseg.windows import EventHistory, count_window_slices, stream_time_windows, time_window_slices


def _events(t):
    t = np.asarray(t)
    return make_events(np.zeros_like(t), np.zeros_like(t), t, np.ones_like(t))


def test_time_window_slices_half_open_bounds():
    t = np.array([0, 3, 9, 10, 19, 20, 35])
    sl = time_window_slices(t, 10)
    assert [(s.start, s.stop) for s in sl] == [(0, 3), (3, 5), (5, 6), (6, 7)]


def test_overlapping_windows_with_stride():
    t = np.arange(0, 30)
    sl = time_window_slices(t, 10, stride_us=5)
    assert [(s.start, s.stop) for s in sl][:3] == [(0, 10), (5, 15), (10, 20)]


def test_count_windows():
    assert [(s.start, s.stop) for s in count_window_slices(7, 3)] == [(0, 3), (3, 6), (6, 7)]
    with pytest.raises(ValueError, match="count must be a positive integer"):
        count_window_slices(7, 0)


@pytest.mark.parametrize("chunk", [1, 3, 50, 1000])
def test_streamed_windows_equal_in_memory_windows(chunk):
    rng = np.random.default_rng(0)
    t = np.sort(rng.integers(0, 200_000, 500))
    ev = _events(t)
    chunks = [ev[i : i + chunk] for i in range(0, len(ev), chunk)]
    streamed = list(stream_time_windows(chunks, 10_000, 7_000))
    ref = time_window_slices(t, 10_000, 7_000)
    assert len(streamed) == len(ref)
    for w, s in zip(streamed, ref):
        assert w.first_event == s.start
        np.testing.assert_array_equal(w.events, ev[s])


def test_streamed_windows_keep_gaps_as_empty_windows():
    ev = _events([0, 1, 50_000])
    wins = list(stream_time_windows([ev], 10_000))
    assert [len(w.events) for w in wins] == [2, 0, 0, 0, 0, 1]
    assert [w.t0_us for w in wins] == [0, 10_000, 20_000, 30_000, 40_000, 50_000]


@pytest.mark.parametrize("stride", [10, 4, 25])
def test_event_history_gives_exactly_the_events_before_each_window(stride):
    """Back to back, overlapping and gapped windows: the context of a window is every event
    of the earlier windows with t0 - C <= t < t0, each once (events in gaps between windows
    are never read, so they are no context either)."""
    rng = np.random.default_rng(3)
    ev = _events(np.sort(rng.integers(0, 200, 300)))
    hist = EventHistory(15)
    for w in stream_time_windows([ev[:90], ev[90:]], 10, stride):
        ctx = hist.before(w)
        in_a_window = (ev["t"] - int(ev["t"][0])) % stride < 10
        expected = ev[(ev["t"] >= w.t0_us - 15) & (ev["t"] < w.t0_us) & in_a_window]
        np.testing.assert_array_equal(ctx, expected)
        hist.add(w)


def test_event_history_of_zero_keeps_nothing():
    ev = _events([0, 5, 12])
    hist = EventHistory(0)
    for w in stream_time_windows([ev], 10):
        assert len(hist.before(w)) == 0
        hist.add(w)
    with pytest.raises(ValueError, match="context duration"):
        EventHistory(-1)


def test_unsorted_or_overlapping_chunks_and_a_late_start_are_refused_not_lost():
    from evseg.errors import EventDataError

    ev = make_events(list(range(20)), [0] * 20, np.arange(0, 100, 5), [1] * 20)
    with pytest.raises(EventDataError, match=r"stream_time_windows: chunk 1 starts at t = 10 us, before the chunk"):
        list(stream_time_windows([ev[5:], ev[2:4]], 10))
    with pytest.raises(EventDataError, match=r"stream_time_windows: chunk 0: field 't' is not sorted"):
        list(stream_time_windows([ev[::-1]], 10))
    with pytest.raises(EventDataError, match=r"the first event \(t = 0 us\) lies before t_start_us = 20 us"):
        list(stream_time_windows([ev], 10, t_start_us=20))
    with pytest.raises(ValueError, match="t_start_us must be a whole number"):
        list(stream_time_windows([ev], 10, t_start_us=0.5))
    with pytest.raises(EventDataError, match="time_window_slices: times not sorted"):
        time_window_slices(np.array([0, 5, 3]), 10)
