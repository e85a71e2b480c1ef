import numpy as np
import pytest

from evseg.errors import EventDataError
from evseg.events import EVENT_DTYPE, EventStream, make_events, validate_events


def test_make_events_converts_polarity_encodings():
    ev = make_events([0, 1, 2, 3], [0, 0, 0, 0], [0, 1, 2, 3], [0, 1, True, -1])
    assert ev.dtype == EVENT_DTYPE
    assert ev["p"].tolist() == [-1, 1, 1, -1]


def test_validate_names_field_and_index_of_unsorted_time():
    ev = make_events([0, 0, 0], [0, 0, 0], [5, 7, 6], [1, 1, 1])
    with pytest.raises(EventDataError, match=r"rec.npz: field 't' is not sorted: event 2"):
        validate_events(ev, source="rec.npz")


def test_validate_names_coordinate_outside_sensor():
    ev = make_events([0, 9], [0, 0], [0, 1], [1, 1])
    with pytest.raises(EventDataError, match=r"field 'x' = 9 at event 1 is outside the sensor \(8x4"):
        validate_events(ev, sensor_size=(8, 4))


def test_stream_windows_are_views_and_cover_all_events():
    t = np.arange(0, 100_000, 7)
    ev = make_events(np.zeros_like(t), np.zeros_like(t), t, np.ones_like(t))
    stream = EventStream(ev, sensor_size=(2, 2))
    wins = list(stream.time_windows(10_000))
    assert sum(len(w) for w in wins) == len(ev)
    assert all(np.shares_memory(w.events, ev) for w in wins if len(w))
    assert stream.duration_us == int(t[-1])


@pytest.mark.parametrize("field, values, message", [
    ("t", [0.000001, 0.000002], r"field 't' = 1e-06 at event 0 is not a whole number \(integer microseconds; "
                                r"time in seconds: multiply by 1e6 and round\)"),
    ("x", [3, -1], r"field 'x' = -1 at event 1 is outside \[0, 65535\]"),
    ("y", [2.5, 1], r"field 'y' = 2.5 at event 0 is not a whole number"),
])
def test_make_events_refuses_values_it_would_change(field, values, message):
    # Casting into the integer fields would truncate (seconds -> 0) or wrap (-1 -> 65535) silently.
    args = {"x": [1, 2], "y": [1, 1], "t": [10, 20], "p": [1, 0]}
    args[field] = values
    with pytest.raises(EventDataError, match=message):
        make_events(**args)
    whole = make_events(x=[1.0, 2.0], y=[1, 1], t=np.array([10.0, 20.0]), p=[True, False])
    assert whole["t"].tolist() == [10, 20] and whole["p"].tolist() == [1, -1]


@pytest.mark.parametrize("events, size, message", [
    (make_events([0, 1], [0, 0], [5, 3], [1, 1]), (8, 8), r"EventStream.events: field 't' is not sorted: event 1"),
    (make_events([0, 9], [0, 0], [0, 1], [1, 1]), (8, 8), r"field 'x' = 9 at event 1 is outside the sensor \(8x8"),
    (np.zeros((3, 4)), (8, 8), r"expected an array of dtype .* got float64"),
    ([(0, 0, 0, 1)], (8, 8), r"expected an array of dtype .* got list"),
    (make_events([0], [0], [0], [1]), (4.7, 4), r"sensor_size must be \(width, height\) in whole pixels > 0, got \(4.7, 4\)"),
    (make_events([0], [0], [0], [1]), (-4, 5), r"in whole pixels > 0, got \(-4, 5\)"),
    (make_events([0], [0], [0], [1]), (8,), r"in whole pixels > 0, got \(8,\)"),
])
def test_an_event_stream_refuses_what_would_make_its_windows_wrong(events, size, message):
    with pytest.raises(EventDataError, match=message):
        EventStream(events, size)


def test_the_pipeline_refuses_a_fractional_sensor_size():
    from evseg.pipeline import MotionSegmentationPipeline, PipelineConfig

    with pytest.raises(EventDataError, match=r"got \(346.9, 260\)"):
        MotionSegmentationPipeline(PipelineConfig(flow="planefit"), sensor_size=(346.9, 260))


@pytest.mark.parametrize("args, message", [
    ((1, 2, 3, 4), "field 'x' must be a 1-D sequence of values, got shape ()"),
    (([1, None], [1, 1], [0, 1], [1, 1]), "field 'x' must hold real numbers, got object"),
    (([1], [1], [0], ["on"]), "field 'p' must hold real numbers"),
    (([1], [1], [0], [float("nan")]), "field 'p' = nan at event 0 is not a polarity"),
])
def test_make_events_names_the_field_of_unusable_values(args, message):
    import re

    with pytest.raises(EventDataError, match=re.escape(message)):
        make_events(*args)


def test_an_event_stream_needs_one_dimension_and_a_whole_offset():
    ev = make_events([0, 1], [0, 0], [0, 1], [1, 1])
    with pytest.raises(EventDataError, match=r"expected a 1-D array of events, got shape \(1, 2\)"):
        EventStream(ev.reshape(1, 2), (8, 8))
    with pytest.raises(EventDataError, match="t_offset_us must be whole microseconds, got 1.7"):
        EventStream(ev, (8, 8), t_offset_us=1.7)
