"""AEDAT4 reader on the real recordings (aedat has no writer; broken copies are in test_fuzz)."""

from __future__ import annotations

import numpy as np

from evseg.io import detect_format, open_recording, read_events


def test_dvxplorer_sample(shared_data):
    p = shared_data / "dvxplorer_person_aedat4" / "sample.aedat4"
    assert detect_format(p) == "aedat4"
    s = read_events(p)
    # Figures from the folder README (decoded there with aedat 2.3.0).
    assert len(s) == 111_954 and s.sensor_size == (320, 240)
    assert s.events["t"][0] == 0 and abs(s.duration_us - 590_000) < 1_000  # README: 0.590 s
    import aedat

    raw = np.concatenate([pk["events"] for pk in aedat.Decoder(str(p)) if "events" in pk])
    np.testing.assert_array_equal(s.events["t"] + s.t_offset_us, raw["t"].astype(np.int64))
    np.testing.assert_array_equal(s.events["x"], raw["x"])
    np.testing.assert_array_equal(s.events["p"], np.where(raw["on"], 1, -1))


def test_davis_fixtures_skip_frames_and_imu(shared_data):
    folder = shared_data / "davis346_aedat4_fixtures"
    assert len(read_events(folder / "shiba24_sample.aedat4")) == 6_676
    with open_recording(folder / "aestream_davis.aedat4", chunk_events=10_000) as rec:
        assert rec.sensor_size == (346, 260)
        assert sum(len(c) for c in rec.chunks()) == 117_667


def test_a_cut_file_gives_its_events_before_the_cut_then_the_error(shared_data, tmp_path):
    import pytest

    from evseg.errors import FormatError

    data = (shared_data / "dvxplorer_person_aedat4" / "sample.aedat4").read_bytes()
    cut = tmp_path / "half.aedat4"
    cut.write_bytes(data[: len(data) // 2])
    got = []
    with open_recording(cut) as rec:  # one chunk of up to 1 M events would hold them all
        with pytest.raises(FormatError, match=r"half.aedat4: aedat4: corrupt or truncated packet after \d+ packets, "
                                              r"\d+ events \(last t = \d+ us"):
            for c in rec.chunks():
                got.append(c)
    n = sum(len(c) for c in got)
    assert 40_000 < n < 111_954  # about half of the 111,954 events
    whole = read_events(shared_data / "dvxplorer_person_aedat4" / "sample.aedat4").events
    np.testing.assert_array_equal(np.concatenate(got), whole[:n])
