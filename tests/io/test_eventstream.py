"""Event Stream v2 DVS decoding: overflow/reset bytes, chunking, the real EED file."""

from __future__ import annotations

import numpy as np
import pytest

from evfiles import es_bytes, sample_events
from evseg.errors import EventDataError, FormatError
from evseg.io import detect_format, read_events


def test_tiny_round_trip_with_overflows_and_resets(tmp_path):
    ev = sample_events(300, seed=2, max_dt=600)  # gaps up to 600 us -> up to 4 overflow bytes
    ev["x"][::7] = 0xFF  # coordinate bytes equal to the overflow/reset codes must not confuse it
    ev["y"][::5] = 0xFE
    p = tmp_path / "a.es"
    p.write_bytes(es_bytes(ev, width=256, height=256, resets_every=17))
    assert detect_format(p) == "es"
    for chunk in (1_000_000, 1, 3, 64):
        s = read_events(p, chunk_events=chunk)
        assert s.sensor_size == (256, 256)
        np.testing.assert_array_equal(s.events, ev)


def test_long_gap_of_many_overflow_bytes(tmp_path):
    ev = sample_events(4)
    ev["t"] = [0, 10, 10 + 10_000_000, 10 + 10_000_001]  # a 10 s gap = 78,740 overflow bytes
    p = tmp_path / "gap.es"
    p.write_bytes(es_bytes(ev))
    np.testing.assert_array_equal(read_events(p, chunk_events=1000).events["t"], ev["t"])


def test_truncated_event_is_reported(tmp_path):
    data = es_bytes(sample_events(10))
    p = tmp_path / "t.es"
    p.write_bytes(data[:-2])
    with pytest.raises(FormatError, match=r"truncated: incomplete event \(3 of 5 bytes\) at byte offset"):
        read_events(p)


def test_other_stream_types_and_versions_are_refused(tmp_path):
    p = tmp_path / "atis.es"
    p.write_bytes(b"Event Stream" + bytes([2, 0, 0, 2]) + bytes(4))
    with pytest.raises(FormatError, match=r"stream type 2 \(atis\) at byte offset 15"):
        read_events(p)
    p.write_bytes(b"Event Stream" + bytes([1, 0, 0, 1]) + bytes(4))
    with pytest.raises(FormatError, match="version 1.0.0"):
        read_events(p)


def test_coordinates_outside_declared_sensor(tmp_path):
    ev = sample_events(10)
    ev["x"][6] = 100
    p = tmp_path / "o.es"
    p.write_bytes(es_bytes(ev, width=64, height=48))
    with pytest.raises(EventDataError, match=r"field 'x' = 100 at event 6 \(byte offset \d+\) is outside the sensor 64x48"):
        read_events(p)


def test_real_eed_file_matches_reference_npy(shared_data):
    folder = shared_data / "eed_what_is_background"
    s = read_events(folder / "EED_what_is_background_events.es")
    ref = np.load(folder / "events_t_us_x_y_on.npy")
    assert s.sensor_size == (190, 180) and len(s) == 271_264
    np.testing.assert_array_equal(s.events["t"], ref["t"].astype(np.int64))
    np.testing.assert_array_equal(s.events["x"], ref["x"])
    np.testing.assert_array_equal(s.events["y"], ref["y"])  # stored y is the image row already
    np.testing.assert_array_equal(s.events["p"], np.where(ref["on"], 1, -1))
