"""Text / csv reader: layouts, time units, line-numbered errors, writer round trip."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evfiles import sample_events, text_lines
from evseg.errors import EventDataError, FormatError
from evseg.events import EventStream, make_events
from evseg.io import open_recording, read_events, write_text


def _write(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_rpg_layout_with_size_line(tmp_path):
    ev = sample_events(100)
    p = _write(tmp_path, "events.txt", text_lines(ev))
    s = read_events(p)
    assert s.sensor_size == (64, 48)
    np.testing.assert_array_equal(s.events, ev)
    chunks = list(open_recording(p, chunk_events=30).chunks())
    assert [len(c) for c in chunks] == [30, 30, 30, 10]
    np.testing.assert_array_equal(np.concatenate(chunks), ev)


def test_no_size_line_infers_max_plus_one(tmp_path):
    p = _write(tmp_path, "e.txt", "0.000001 3 4 1\n0.000002 9 2 0\n")
    with open_recording(p) as rec:
        assert rec.sensor_size is None
        s = rec.read_all()
        assert rec.sensor_size_source == "inferred"
    assert s.sensor_size == (10, 5)
    assert s.events["t"].tolist() == [1, 2] and s.events["p"].tolist() == [1, -1]


def test_csv_with_header_in_any_column_order_and_us_time(tmp_path):
    p = _write(tmp_path, "e.csv", "# exported\nx,y,p,t\n5,6,1,100\n\n7,8,0,250\n")
    s = read_events(p)
    assert s.events["t"].tolist() == [100, 250]  # integer time column -> microseconds
    assert s.events["x"].tolist() == [5, 7] and s.events["p"].tolist() == [1, -1]


def test_time_unit_from_header_suffix_and_override(tmp_path):
    p = _write(tmp_path, "e.csv", "timestamp_us,x,y,polarity\n1.0,1,1,1\n")
    assert read_events(p).events["t"].tolist() == [1]
    q = _write(tmp_path, "f.txt", "1 1 1 1\n2 1 1 0\n")
    assert read_events(q).events["t"].tolist() == [1, 2]
    assert read_events(q, time_unit="s").events["t"].tolist() == [1_000_000, 2_000_000]
    r = _write(tmp_path, "g.csv", "t_ns,x,y,p\n1000499,1,1,1\n2000500,1,1,0\n")
    assert read_events(r).events["t"].tolist() == [1000, 2000]  # rint: half to even
    assert read_events(q, time_unit="ms").events["t"].tolist() == [1000, 2000]
    assert read_events(q, time_unit="ns").events["t"].tolist() == [0, 0]


def test_ros_epoch_seconds_are_exact_to_the_microsecond(tmp_path):
    p = _write(tmp_path, "e.txt", "1519939282.250708 1 2 1\n1519939282.250709 1 2 0\n")
    assert read_events(p).events["t"].tolist() == [1519939282250708, 1519939282250709]


@pytest.mark.parametrize(
    "body, message",
    [
        ("0.1 1 2 1\n0.2 1 2\n", r"line 2: expected 4 columns, got 3"),
        ("0.1 1 2 1\n0.2 a 2 1\n", r"line 2: b'a' is not a number"),
        ("0.1 1 2 1\nnan 1 2 1\n", r"line 2: field 't' is nan \(not finite\)"),
        ("0.1 1 2 1\n0.2 inf 2 1\n", r"line 2: field 'x' is inf"),
        ("0.1 1.5 2 1\n", r"line 1: field 'x' = 1.5 is not a pixel coordinate"),
        ("0.1 -1 2 1\n", r"line 1: field 'x' = -1.0 is not a pixel coordinate"),
        ("0.1 1 2 3\n", r"line 1: field 'p' = 3.0 is not 0, 1 or -1"),
        ("0.1 1 2 1\n0.2 1 2 1 \xe9\n", r"line 2: "),
    ],
)
def test_bad_lines_are_named(tmp_path, body, message):
    p = tmp_path / "bad.txt"
    p.write_bytes(body.encode("latin-1"))
    with pytest.raises(FormatError, match=message) as exc:
        read_events(p)
    assert str(p) in str(exc.value)


def test_unsorted_rejected_with_line_then_sorted_on_request(tmp_path):
    p = _write(tmp_path, "u.txt", "64 48\n0.3 1 1 1\n0.1 2 2 0\n0.2 3 3 1\n")
    with pytest.raises(EventDataError, match=r"not sorted: t=100000 us at event 1 \(line 3\)"):
        read_events(p)
    s = read_events(p, sort=True)
    assert s.events["t"].tolist() == [100000, 200000, 300000]
    assert s.events["x"].tolist() == [2, 3, 1]


def test_negative_time_and_outside_sensor(tmp_path):
    p = _write(tmp_path, "n.txt", "0.1 1 1 1\n-0.2 1 1 1\n")
    with pytest.raises(EventDataError, match=r"negative timestamp t=-200000 us at event 1 \(line 2\)"):
        read_events(p)
    q = _write(tmp_path, "o.txt", "10 10\n0.1 1 1 1\n0.2 1 12 1\n")
    with pytest.raises(EventDataError, match=r"field 'y' = 12 at event 1 \(line 3\) is outside the sensor 10x10"):
        read_events(q)


def test_header_only_is_an_empty_recording(tmp_path):
    s = read_events(_write(tmp_path, "h.txt", "32 24\n"))
    assert len(s) == 0 and s.sensor_size == (32, 24)


def test_write_text_round_trip_keeps_absolute_time(tmp_path):
    ev = sample_events(40)
    stream = EventStream(ev, (64, 48), t_offset_us=1_519_939_282_000_000)
    back = read_events(write_text(stream, tmp_path / "o.txt"))
    assert back.t_offset_us == 0 and back.sensor_size == (64, 48)
    np.testing.assert_array_equal(back.events["t"], ev["t"] + stream.t_offset_us)
    for k in "xyp":
        np.testing.assert_array_equal(back.events[k], ev[k])


@st.composite
def streams(draw):
    n = draw(st.integers(0, 40))
    w = draw(st.integers(1, 2000))
    h = draw(st.integers(1, 2000))
    x = draw(st.lists(st.integers(0, w - 1), min_size=n, max_size=n))
    y = draw(st.lists(st.integers(0, h - 1), min_size=n, max_size=n))
    dt = draw(st.lists(st.integers(0, 10**7), min_size=n, max_size=n))
    t0 = draw(st.integers(0, 2**31 * 10**6 - 10**9))  # absolute times up to 2**31 s
    p = draw(st.lists(st.sampled_from([-1, 1]), min_size=n, max_size=n))
    return EventStream(make_events(x, y, np.cumsum(dt, dtype=np.int64), p), (w, h), t_offset_us=t0)


@settings(max_examples=150, deadline=None)
@given(stream=streams())
def test_text_and_npz_round_trip_property(tmp_path_factory, stream):
    from evseg.io import write_npz

    d = tmp_path_factory.mktemp("rt")
    back = read_events(write_npz(stream, d / "a.npz"))
    assert back.sensor_size == stream.sensor_size and back.t_offset_us == stream.t_offset_us
    np.testing.assert_array_equal(back.events, stream.events)
    back = read_events(write_text(stream, d / "a.txt"))
    assert back.sensor_size == stream.sensor_size
    np.testing.assert_array_equal(back.events["t"], stream.events["t"] + stream.t_offset_us)
    for k in "xyp":
        np.testing.assert_array_equal(back.events[k], stream.events[k])


def test_comment_and_blank_lines_inside_blocks(tmp_path):
    p = _write(tmp_path, "c.txt", "64 48\n0.1 1 1 1\n\n# note\n0.2 2 2 0\n0.3 3 3 1\n")
    chunks = list(open_recording(p, chunk_events=2).chunks())
    assert [c["t"].tolist() for c in chunks] == [[100000, 200000], [300000]]  # chunks count events
    q = _write(tmp_path, "d.txt", "64 48\n0.1 1 1 1\n\n0.2 2 2 0\n0.3 99 3 1\n")
    with pytest.raises(EventDataError, match=r"field 'x' = 99 at event 2 \(line 5\)"):
        read_events(q)


def test_seconds_written_with_g_format_are_seconds(tmp_path):
    # "%g" writes the first time (0 after subtracting the start) without a decimal point: the
    # unit must come from more than the first line, or every later time rounds to 0 us.
    p = _write(tmp_path, "g.txt", "0 1 1 1\n0.0499657 2 2 0\n0.1 3 3 1\n")
    assert read_events(p).events["t"].tolist() == [0, 49966, 100000]


def test_a_fraction_after_the_sampled_lines_is_an_error_not_a_rounding(tmp_path):
    from evseg.io import text

    lines = [f"{i} 1 1 1" for i in range(text._UNIT_SAMPLE_LINES)] + ["1000.5 1 1 0"]
    p = _write(tmp_path, "late.txt", "\n".join(lines) + "\n")
    with pytest.raises(FormatError, match=r"late.txt: text: line 1001: field 't' = 1000.5 has a fraction.*"
                                          r"--time-unit s"):
        read_events(p)
    # Said by the user, microseconds are rounded as asked.
    assert read_events(p, time_unit="us").events["t"][-1] == 1000  # rint(1000.5): round half to even


def test_percent_comment_lines_are_skipped(tmp_path):
    p = _write(tmp_path, "m.txt", "% exported by a MATLAB script\n0.1 1 1 1\n% more\n0.2 2 2 0\n")
    assert read_events(p).events["t"].tolist() == [100000, 200000]


def test_segment_and_flow_take_the_time_unit(tmp_path, capsys):
    from evseg.cli import main

    # Whole-number seconds: read as microseconds unless told (1 us apart: one window).
    lines = [f"{i} {i % 20} {i % 10} {i % 2}" for i in range(3)]
    p = _write(tmp_path, "sec.txt", "20 10\n" + "\n".join(lines) + "\n")
    for command in ("segment", "flow"):
        out = tmp_path / f"{command}.npz"
        argv = [command, str(p), "--out", str(out), "--time-unit", "s", "--no-progress"]
        if command == "segment":
            argv += ["--flow-method", "planefit"]
        else:
            argv += ["--baseline"]
        assert main(argv) == 0, capsys.readouterr().err
    r = np.load(tmp_path / "segment.npz")
    assert r["window_t0_us"][-1] == 2_000_000 and len(r["label"]) == 3  # the last event at 2 s


@pytest.mark.parametrize("name, text", [
    ("bom.csv", "\ufefft,x,y,p\n0.1,1,2,1\n0.2,3,4,0\n"),  # Excel's UTF-8 byte-order mark
    ("pandas.csv", ",t,x,y,p\n0,0.1,1,2,1\n1,0.2,3,4,0\n"),  # DataFrame.to_csv with its index
    ("trailing.csv", "t,x,y,p,\n0.1,1,2,1,\n0.2,3,4,0,\n"),
    ("quoted.csv", '"t","x","y","p"\n0.1,1,2,1\n0.2,3,4,0\n'),
    ("semicolon.csv", "t;x;y;p\n0.1;1;2;1\n0.2;3;4;0\n"),  # spreadsheets with a decimal comma locale
    ("extra.csv", "t,x,y,p,confidence\n0.1,1,2,1,0.5\n0.2,3,4,0,0.9\n"),
])
def test_spreadsheet_and_pandas_exports(tmp_path, name, text):
    p = tmp_path / name
    p.write_bytes(text.encode("utf-8"))
    ev = read_events(p).events
    assert ev["t"].tolist() == [100000, 200000] and ev["x"].tolist() == [1, 3]
    assert ev["y"].tolist() == [2, 4] and ev["p"].tolist() == [1, -1]


def test_times_beyond_2100_under_a_guessed_unit_ask_for_the_unit(tmp_path):
    p = _write(tmp_path, "ns.txt", "1700000000000000000 1 1 0\n1700000000001000000 2 1 1\n")
    with pytest.raises(FormatError, match=r"ns.txt: text: field 't' = 1.7e\+18 at line 1 read as us is after the "
                                          r"year 2100"):
        read_events(p)
    assert read_events(p, time_unit="ns").events["t"].tolist() == [1_700_000_000_000_000, 1_700_000_000_001_000]


def test_a_boolean_polarity_column_as_pandas_writes_it(tmp_path):
    # DataFrame.to_csv writes a bool column as True/False.
    p = _write(tmp_path, "b.csv", ",t,x,y,p\n0,0.1,1,2,True\n1,0.2,3,4,False\n2,0.3,5,6,true\n")
    s = read_events(p)
    assert s.events["p"].tolist() == [1, -1, 1] and s.events["x"].tolist() == [1, 3, 5]
    q = _write(tmp_path, "h.txt", "0.1 1 2 FALSE\n0.2 3 4 TRUE\n")  # no header either
    assert read_events(q).events["p"].tolist() == [-1, 1]
    # True elsewhere than the polarity column is still an error naming it.
    r = _write(tmp_path, "x.csv", "t,x,y,p\n0.1,1,2,1\n0.2,True,4,0\n")
    with pytest.raises(FormatError, match=r"x.csv: text: line 3: b'True' is not a number"):
        read_events(r)


def test_cr_only_line_endings_are_named(tmp_path):
    p = tmp_path / "mac.txt"
    p.write_bytes(b"0.1 1 2 1\r0.2 3 4 0\r")
    with pytest.raises(FormatError, match=r"mac.txt: text: line 1: a carriage return .* CR alone"):
        read_events(p)
    q = tmp_path / "win.txt"  # CRLF is fine
    q.write_bytes(b"0.1 1 2 1\r\n0.2 3 4 0\r\n")
    assert read_events(q).events["t"].tolist() == [100000, 200000]
