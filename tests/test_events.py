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


def test_openmp_waits_passively_unless_the_user_chose():
    """evseg sets OMP_WAIT_POLICY=PASSIVE on import (spinning OpenMP threads of the encoder
    slow the network that runs right after it), but never overrides the user's setting."""
    import os
    import subprocess
    import sys

    code = "import os, evseg; print(os.environ['OMP_WAIT_POLICY'])"
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "PASSIVE"
    env["OMP_WAIT_POLICY"] = "ACTIVE"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "ACTIVE"
