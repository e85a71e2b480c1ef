"""DSEC-style HDF5 reader and writer."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from evfiles import sample_events
from evseg.errors import FormatError
from evseg.events import EventStream
from evseg.io import open_recording, read_events, write_h5


def test_round_trip_and_ms_to_idx(tmp_path):
    ev = sample_events(3000, max_dt=20)  # ~30 ms
    stream = EventStream(ev, (64, 48), t_offset_us=1_600_000_000_000_000)
    p = write_h5(stream, tmp_path / "e.h5")
    back = read_events(p)
    np.testing.assert_array_equal(back.events, ev)
    assert back.sensor_size == (64, 48) and back.t_offset_us == stream.t_offset_us
    with h5py.File(p) as f:
        ms = f["ms_to_idx"][()]
        assert set(f["events"].keys()) == {"x", "y", "t", "p"}
        assert f["events/p"].dtype == np.uint8
    # ms_to_idx[k] is the first event with t >= 1000 k (DSEC's definition).
    expected = np.searchsorted(ev["t"], 1000 * np.arange(int(ev["t"][-1]) // 1000 + 1), side="left")
    np.testing.assert_array_equal(ms, expected)
    chunks = list(open_recording(p, chunk_events=1000).chunks())
    assert [len(c) for c in chunks] == [1000, 1000, 1000]


def test_dsec_file_without_size_attributes(tmp_path):
    ev = sample_events(50)
    with h5py.File(tmp_path / "dsec.h5", "w") as f:
        for k in "xyt":
            f.create_dataset(f"events/{k}", data=ev[k])
        f.create_dataset("events/p", data=(ev["p"] > 0).astype(np.uint8))
        f.create_dataset("t_offset", data=np.int64(42))
    s = read_events(tmp_path / "dsec.h5", sensor_size=(640, 480))
    assert s.sensor_size == (640, 480) and s.t_offset_us == 42
    np.testing.assert_array_equal(s.events, ev)


def test_missing_datasets_and_unequal_lengths(tmp_path):
    with h5py.File(tmp_path / "a.h5", "w") as f:
        f.create_dataset("events/x", data=np.zeros(3, np.uint16))
    with pytest.raises(FormatError, match=r"group 'events' lacks datasets \['y', 't', 'p'\]"):
        read_events(tmp_path / "a.h5")
    with h5py.File(tmp_path / "b.h5", "w") as f:
        for k, n in zip("xytp", (3, 3, 2, 3)):
            f.create_dataset(f"events/{k}", data=np.zeros(n, np.int64))
    with pytest.raises(FormatError, match="different lengths"):
        read_events(tmp_path / "b.h5")
    with h5py.File(tmp_path / "c.h5", "w") as f:
        f.create_dataset("data", data=np.zeros(3))
    with pytest.raises(FormatError, match=r"no readable group 'events'.*\['data'\]"):
        read_events(tmp_path / "c.h5")
