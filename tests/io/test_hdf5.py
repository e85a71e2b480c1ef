"""DSEC-style HDF5 reader and writer."""

from __future__ import annotations

import numpy as np
import pytest

h5py = pytest.importorskip("h5py", reason="the 'formats' extra (pip install -e \".[formats]\")")

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


def test_column_vector_datasets_and_a_one_element_offset(tmp_path):
    # MATLAB-style (N, 1) columns and t_offset stored as [42] are DSEC files all the same.
    ev = sample_events(50)
    with h5py.File(tmp_path / "col.h5", "w") as f:
        for k in "xyt":
            f.create_dataset(f"events/{k}", data=ev[k][:, None])
        f.create_dataset("events/p", data=(ev["p"] > 0).astype(np.uint8)[:, None])
        f.create_dataset("t_offset", data=np.array([42], np.int64))
    with open_recording(tmp_path / "col.h5", sensor_size=(64, 48)) as rec:
        assert rec.time_span_us() == (int(ev["t"][0]), int(ev["t"][-1]))
        s = rec.read_all()
    assert s.t_offset_us == 42
    np.testing.assert_array_equal(s.events, ev)


def test_other_layouts_are_named(tmp_path):
    with h5py.File(tmp_path / "m.h5", "w") as f:
        for k in "xytp":
            f.create_dataset(f"events/{k}", data=np.zeros((3, 2), np.int64))
    with pytest.raises(FormatError, match=r"dataset 'events/x' must be one column of N values, got shape \(3, 2\)"):
        read_events(tmp_path / "m.h5")
    with h5py.File(tmp_path / "v2e.h5", "w") as f:
        f.create_dataset("events", data=np.zeros((5, 4), np.uint32))
    with pytest.raises(FormatError, match=r"'events' is a dataset of shape \(5, 4\).*\.npy N x 4 \[t, x, y, p\]"):
        read_events(tmp_path / "v2e.h5")
    with h5py.File(tmp_path / "o.h5", "w") as f:
        for k in "xytp":
            f.create_dataset(f"events/{k}", data=np.zeros(3, np.int64))
        f.create_dataset("t_offset", data=np.array([1, 2], np.int64))
    with pytest.raises(FormatError, match=r"dataset 't_offset' is not an integer scalar"):
        read_events(tmp_path / "o.h5")
