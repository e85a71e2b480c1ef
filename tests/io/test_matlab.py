"""MATLAB .mat reader ([x, y, p, t_us] as in rpg_event_lifetime)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.io

from evfiles import sample_events
from evseg.errors import FormatError
from evseg.io import detect_format, read_events


def test_tiny_mat(tmp_path):
    ev = sample_events(25)
    m = np.stack([ev["x"], ev["y"], ev["p"], ev["t"]], axis=1).astype(np.int32)
    scipy.io.savemat(tmp_path / "e.mat", {"events": m})
    assert detect_format(tmp_path / "e.mat") == "mat"
    np.testing.assert_array_equal(read_events(tmp_path / "e.mat").events, ev)
    scipy.io.savemat(tmp_path / "d.mat", {"events": m.astype(np.float64)})  # double matrix: still us
    np.testing.assert_array_equal(read_events(tmp_path / "d.mat").events, ev)


def test_missing_variable(tmp_path):
    scipy.io.savemat(tmp_path / "v.mat", {"other": np.zeros((2, 4))})
    with pytest.raises(FormatError, match=r"no variable 'events' \(variables: \['other'\]\)"):
        read_events(tmp_path / "v.mat")


def test_real_dvs128_clips(shared_data):
    # Event counts and durations from the folder README.
    expected = {"stripes": 340_394, "garfield": 202_235, "flip": 175_136, "building": 115_839}
    for name, n in expected.items():
        s = read_events(shared_data / "dvs128_single_motion" / f"{name}.mat")
        assert len(s) == n and s.sensor_size == (128, 128), name
        assert int(s.events["t"][0]) >= 0


def test_double_times_in_seconds_are_refused_not_rounded(tmp_path):
    # Rounded, seconds become 0 or 1 us and the recording collapses to one window.
    ev = np.array([[1, 2, 1, 0.5], [3, 4, -1, 0.75]], dtype=np.float64)
    scipy.io.savemat(tmp_path / "s.mat", {"events": ev})
    with pytest.raises(FormatError, match=r"s.mat: mat: variable 'events' row 0: t = 0.5 has a fraction.*1e6"):
        read_events(tmp_path / "s.mat")
    ev[:, 3] = [500000, 750000]  # whole microseconds in a double matrix are fine
    scipy.io.savemat(tmp_path / "us.mat", {"events": ev})
    assert read_events(tmp_path / "us.mat").events["t"].tolist() == [500000, 750000]
