"""Recording: validation across chunks, sort option, sensor size sources, windows."""

from __future__ import annotations

import numpy as np
import pytest

from evfiles import sample_events
from evseg.errors import EventDataError
from evseg.events import EventStream
from evseg.io import open_recording, parse_sensor_size, read_events, write_npz
from evseg.windows import stream_time_windows


def _npz(tmp_path, ev, size=(64, 48)):
    # Written directly: an EventStream refuses the unsorted events these tests need on disk.
    p = tmp_path / "e.npz"
    np.savez(p, events=ev, sensor_size=np.asarray(size, dtype=np.int64))
    return p


def test_unsorted_across_a_chunk_boundary(tmp_path):
    ev = sample_events(10)
    ev["t"] = [0, 1, 2, 3, 4, 5, 6, 7, 8, 9]
    ev["t"][5] = 3  # decreasing step from event 4 (t=4) to event 5, which starts chunk 2
    p = _npz(tmp_path, ev)
    with open_recording(p, chunk_events=5) as rec:
        with pytest.raises(EventDataError, match=r"not sorted: t=3 us at event 5 is earlier than the previous event's t=4 us \(open with sort=True / pass --sort"):
            list(rec.chunks())


def test_sort_is_stable_and_explicit(tmp_path):
    ev = sample_events(6)
    ev["t"] = [5, 1, 5, 0, 1, 9]
    ev["x"] = [0, 1, 2, 3, 4, 5]
    s = read_events(_npz(tmp_path, ev), sort=True, chunk_events=4)
    assert s.events["t"].tolist() == [0, 1, 1, 5, 5, 9]
    assert s.events["x"].tolist() == [3, 1, 4, 0, 2, 5]  # equal times keep file order


def test_sensor_size_sources(tmp_path):
    p = _npz(tmp_path, sample_events(20, width=10, height=10), size=(64, 48))
    with open_recording(p) as rec:
        assert (rec.sensor_size, rec.sensor_size_source) == ((64, 48), "file")
    with open_recording(p, sensor_size=(12, 11)) as rec:
        assert (rec.sensor_size, rec.sensor_size_source) == ((12, 11), "user")
    with pytest.raises(EventDataError, match=r"field 'x' = \d+ at event \d+ is outside the sensor 5x5 \(user\)"):
        read_events(p, sensor_size=(5, 5))


def test_empty_recording_without_size_cannot_be_read_all(tmp_path):
    np.save(tmp_path / "z.npy", np.zeros((0, 4)))
    with pytest.raises(EventDataError, match=r"declares no sensor size and has no events"):
        read_events(tmp_path / "z.npy")
    assert read_events(tmp_path / "z.npy", sensor_size=(4, 3)).sensor_size == (4, 3)


def test_chunks_feed_stream_time_windows(tmp_path):
    ev = sample_events(2000, max_dt=50)
    p = _npz(tmp_path, ev)
    with open_recording(p, chunk_events=137) as rec:
        streamed = [(w.t0_us, w.first_event, len(w.events)) for w in stream_time_windows(rec.chunks(), 5000)]
    whole = EventStream(ev, (64, 48))
    expected = [len(w) for w in whole.time_windows(5000)]
    assert [n for _, _, n in streamed] == expected
    assert sum(expected) == len(ev)


def test_parse_sensor_size():
    assert parse_sensor_size("346x260") == (346, 260)
    assert parse_sensor_size("640X480") == (640, 480)
    for bad in ("346", "0x10", "ax3", "1x2x3"):
        with pytest.raises(EventDataError, match="sensor size|sensor_size"):
            parse_sensor_size(bad)


def test_reader_never_mutates_or_aliases_a_source_array(tmp_path):
    ev = sample_events(10)
    np.save(tmp_path / "s.npy", ev)
    s = read_events(tmp_path / "s.npy")
    s.events["x"][:] = 0  # the result is ours to change
    np.testing.assert_array_equal(np.load(tmp_path / "s.npy"), ev)


def test_time_span_from_the_file_ends(tmp_path):
    """Arrays and HDF5 tell their first and last event times up front (progress bars); the
    value is the chunks' own time base, whatever unit the file stores."""
    import scipy.io

    from evseg.io import write_h5, write_text

    ev = sample_events(40, t0=1_000)
    first, last = int(ev["t"][0]), int(ev["t"][-1])
    stream = EventStream(ev, (64, 48))
    np.savez(tmp_path / "sec.npz", t=ev["t"] / 1e6, x=ev["x"], y=ev["y"], p=ev["p"])  # float seconds
    np.save(tmp_path / "e.npy", ev)
    scipy.io.savemat(tmp_path / "e.mat", {"events": np.column_stack(
        [ev["x"], ev["y"], np.where(ev["p"] > 0, 1, -1), ev["t"]]).astype(np.int32)})
    paths = [write_npz(stream, tmp_path / "e.npz"), write_h5(stream, tmp_path / "e.h5"),
             tmp_path / "sec.npz", tmp_path / "e.npy", tmp_path / "e.mat"]
    for p in paths:
        with open_recording(p, sensor_size=(64, 48)) as rec:
            assert rec.time_span_us() == (first, last), p.name
            assert int(next(iter(rec.chunks()))["t"][0]) == first
    # formats that would have to decode the file to know do not tell
    with open_recording(write_text(stream, tmp_path / "e.txt"), sensor_size=(64, 48)) as rec:
        assert rec.time_span_us() is None
    with open_recording(_npz(tmp_path, ev[:0])) as rec:
        assert rec.time_span_us() is None


def test_batched_chunks_hand_over_the_events_before_a_damaged_packet():
    from evseg.errors import FormatError
    from evseg.io.recording import batched_chunks

    def packets():
        yield sample_events(5)
        yield sample_events(3)
        raise FormatError("f: damaged packet 2")

    chunks = batched_chunks(packets(), 100)
    assert len(next(chunks).events) == 8
    with pytest.raises(FormatError, match="damaged packet 2"):
        next(chunks)


def test_a_closed_recording_says_so(tmp_path):
    from evseg.errors import EvsegError

    p = _npz(tmp_path, sample_events(10))
    with open_recording(p) as rec:
        pass
    with pytest.raises(EvsegError, match="the recording was closed"):
        rec.read_all()
    with pytest.raises(EvsegError, match="the recording was closed"):
        list(rec.chunks())
