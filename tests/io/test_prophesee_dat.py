"""Prophesee .dat reader: files written here one record at a time (struct), so the reader's
vectorised decoding is checked against an independent encoder of the documented layout."""

from __future__ import annotations

import numpy as np
import pytest

from evfiles import dat_bytes, sample_events
from evseg.errors import FormatError
from evseg.io import detect_format, read_events


def test_round_trip_with_the_header_geometry(tmp_path):
    ev = sample_events(300, seed=7)
    p = tmp_path / "rec_td.dat"
    p.write_bytes(dat_bytes(ev))
    assert detect_format(p) == "dat"
    s = read_events(p)
    assert s.sensor_size == (64, 48) and s.t_offset_us == 0
    for k in "xytp":
        np.testing.assert_array_equal(s.events[k], ev[k])


def test_coordinates_use_all_14_bits(tmp_path):
    ev = sample_events(20, seed=1, width=1280, height=720)
    ev["x"][0], ev["y"][0] = 1279, 719
    p = tmp_path / "big.dat"
    p.write_bytes(dat_bytes(ev, header="% Data file containing CD events\n% Version 2\n% Width 1280\n% Height 720\n"))
    s = read_events(p)
    assert s.sensor_size == (1280, 720) and (s.events["x"][0], s.events["y"][0]) == (1279, 719)


def test_32_bit_time_wraps_to_monotonic_time(tmp_path):
    ev = sample_events(40, seed=3, max_dt=1000)
    t = ev["t"] + (1 << 32) - int(ev["t"][20])  # event 20 is the first after the wrap
    p = tmp_path / "wrap.dat"
    p.write_bytes(dat_bytes(ev, t_raw=t))
    got = read_events(p).events["t"]
    np.testing.assert_array_equal(np.diff(got), np.diff(ev["t"]))


def test_event2d_type_and_a_header_without_its_first_line(tmp_path):
    ev = sample_events(10, seed=2)
    p = tmp_path / "no_data_line.dat"
    p.write_bytes(dat_bytes(ev, header="% Version 2\n% Width 64\n% Height 48\n", event_type=0x00))
    assert detect_format(p) == "dat"
    np.testing.assert_array_equal(read_events(p).events["x"], ev["x"])


@pytest.mark.parametrize("kind, message", [
    ("trigger events", r"event type 0x0E at byte offset \d+ is not a CD event"),
    ("16-byte events", r"event size 16 at byte offset \d+, expected 8"),
    ("version 1", r"header field 'Version' is 1; evseg reads DAT version 2"),
    ("cut record", r"truncated: 3 trailing byte\(s\) at byte offset \d+ do not make a whole 8-byte event"),
])
def test_what_it_cannot_read_is_named(tmp_path, kind, message):
    ev = sample_events(10, seed=4)
    data = {"trigger events": dat_bytes(ev, event_type=0x0E),
            "16-byte events": dat_bytes(ev, event_size=16),
            "version 1": dat_bytes(ev, header="% Data file containing CD events\n% Version 1\n"),
            "cut record": dat_bytes(ev)[:-5]}[kind]
    p = tmp_path / "bad.dat"
    p.write_bytes(data)
    with pytest.raises(FormatError, match=rf"bad.dat: dat: {message}"):
        read_events(p)


def test_a_text_file_named_dat_is_still_text(tmp_path):
    p = tmp_path / "events.dat"
    p.write_text("0.000001 1 2 1\n0.000002 3 4 0\n")
    assert detect_format(p) == "text"
    assert len(read_events(p)) == 2
