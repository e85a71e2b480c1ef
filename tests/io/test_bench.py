"""The io benchmark's vectorised encoders agree with the readers (no timing assertions)."""

from __future__ import annotations

import numpy as np
import pytest

from evseg.io import read_events
from evseg.io.bench import benchmark, synthetic_events, write_synthetic


@pytest.mark.parametrize("fmt", ["evt2", "evt3", "es", "text", "npz", "h5", "rosbag", "rosbag2", "rosbag2_evt3"])
def test_synthetic_files_read_back(tmp_path, fmt):
    ev = synthetic_events(5000, 640, 480, rate_ev_s=2e4)  # sparse: gaps over 127 us (.es overflows)
    ev["t"] += 2**24 - 100_000  # crosses the EVT3 24-bit wrap
    s = read_events(write_synthetic(fmt, ev, tmp_path, (640, 480)))
    assert s.sensor_size == (640, 480)
    # Bags count from their first event (t_offset_us); the other files from 0.
    np.testing.assert_array_equal(s.events["t"] + s.t_offset_us - (ev["t"][0] if fmt.startswith("rosbag") else 0), ev["t"] - (ev["t"][0] if fmt.startswith("rosbag") else 0))
    for k in "xyp":
        np.testing.assert_array_equal(s.events[k], ev[k])


def test_benchmark_rows_name_the_input_size():
    rows = benchmark(repeats=1, quick=True)
    assert [r["format"] for r in rows] == ["evt3", "evt2", "es", "h5", "npz", "rosbag", "rosbag2", "rosbag2_evt3", "text"]
    assert all(r["events"] == 200_000 and r["read_s"] > 0 for r in rows)
