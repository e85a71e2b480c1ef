"""The `evseg info` and `evseg convert` subcommands."""

from __future__ import annotations

import numpy as np
import pytest

from evfiles import es_bytes, sample_events, text_lines, write_bag
from evseg.cli import main
from evseg.io import read_events


def test_info_prints_the_summary(tmp_path, capsys):
    ev = sample_events(100, seed=9)
    ev["p"][:25] = 1
    ev["p"][25:] = -1
    p = tmp_path / "e.es"
    p.write_bytes(es_bytes(ev, width=64, height=48))
    assert main(["info", str(p)]) == 0
    out = capsys.readouterr().out
    assert "format:       es" in out
    assert "sensor size:  64x48 px (from the file)" in out
    assert "events:       100" in out
    assert f"time range:   {ev['t'][0]:,} .. {ev['t'][-1]:,} us" in out
    assert "polarity:     25.0 % ON, 75.0 % OFF" in out
    rate = 100 / ((ev["t"][-1] - ev["t"][0]) * 1e-6) / 1e6
    assert f"event rate:   {rate:,.3f} Mev/s" in out


def test_info_inferred_and_given_sizes(tmp_path, capsys):
    p = tmp_path / "e.txt"
    p.write_text(text_lines(sample_events(10, width=8, height=6), size=None))
    assert main(["info", str(p)]) == 0
    assert "(inferred as max+1)" in capsys.readouterr().out
    assert main(["info", str(p), "--sensor-size", "100x90"]) == 0
    assert "100x90 px (given)" in capsys.readouterr().out


def test_info_names_the_topic_read_from_a_bag(tmp_path, capsys):
    # A user with a stereo ROS2 bag must see which camera's events (and calibration) info read.
    d = tmp_path / "stereo"
    write_bag(d, {"/left/events": [sample_events(20, seed=1)], "/right/events": [sample_events(12, seed=2)]},
              ros2="mcap", msgtype="event_camera_msgs/msg/EventPacket", encoding="mono",
              camera_info={"/right/camera_info": {"K": [60.0, 0, 32.0, 0, 61.0, 24.0, 0, 0, 1.0],
                                                  "D": [0.0] * 5, "distortion_model": "plumb_bob"}})
    assert main(["info", str(d), "--topic", "/right/events"]) == 0
    out = capsys.readouterr().out
    assert "format:       rosbag2\ntopic:        /right/events (event_camera_msgs/msg/EventPacket)\n" in out
    assert "events:       12\n" in out
    assert "calibration:  K, D in camera_info beside the topic" in out
    assert main(["info", str(d), "--topic", "/left/events"]) == 0
    out = capsys.readouterr().out
    assert "events:       20\n" in out and "calibration:  none" in out
    p = tmp_path / "e.es"
    p.write_bytes(es_bytes(sample_events(5, seed=3)))
    assert main(["info", str(p)]) == 0
    assert "topic:" not in capsys.readouterr().out


def test_user_errors_are_one_line_exit_2(tmp_path, capsys):
    p = tmp_path / "u.txt"
    p.write_text("0.2 1 1 1\n0.1 1 1 1\n")
    assert main(["info", str(p)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not sorted" in err[0] and "--sort" in err[0]
    assert main(["info", str(p), "--sort"]) == 0
    capsys.readouterr()
    assert main(["info", str(tmp_path / "missing.raw")]) == 2
    assert "file not found" in capsys.readouterr().err
    assert main(["info", str(p), "--sensor-size", "12"]) == 2


@pytest.mark.parametrize("suffix", [".npz", ".h5"])
def test_convert_round_trip(tmp_path, capsys, suffix):
    ev = sample_events(500, seed=10)
    src = tmp_path / "in.es"
    src.write_bytes(es_bytes(ev))
    out = tmp_path / f"out{suffix}"
    assert main(["convert", str(src), str(out)]) == 0
    assert "500 events" in capsys.readouterr().out
    back = read_events(out)
    np.testing.assert_array_equal(back.events, ev)
    assert back.sensor_size == (64, 48)
    assert sorted(x.name for x in tmp_path.iterdir()) == ["in.es", f"out{suffix}"]  # no temp left


def test_convert_sorts_on_request_and_keeps_inferred_size(tmp_path, capsys):
    src = tmp_path / "u.csv"
    src.write_text("t,x,y,p\n30,1,2,1\n10,5,3,0\n20,2,2,1\n")
    out = tmp_path / "o.bin"
    assert main(["convert", str(src), str(out)]) == 2
    assert "use --to npz|h5" in capsys.readouterr().err
    assert main(["convert", str(src), str(out), "--to", "h5"]) == 2
    assert not out.exists()  # the failed conversion left nothing behind
    assert main(["convert", str(src), str(out), "--to", "h5", "--sort"]) == 0
    back = read_events(out, format="h5")
    assert back.events["t"].tolist() == [10, 20, 30] and back.sensor_size == (6, 4)


def test_convert_real_recordings_losslessly(shared_data, tmp_path, capsys):
    for src in [shared_data / "prophesee_evt_samples" / "evt3_sample.raw",
                shared_data / "ecd_poster" / "poster_6dof.npz",
                shared_data / "dvxplorer_person_aedat4" / "sample.aedat4"]:
        a = read_events(src)
        for suffix in (".npz", ".h5"):
            out = tmp_path / (src.stem + suffix)
            assert main(["convert", str(src), str(out)]) == 0
            b = read_events(out)
            np.testing.assert_array_equal(b.events, a.events)
            assert (b.sensor_size, b.t_offset_us) == (a.sensor_size, a.t_offset_us)
            assert (b.calibration is None) == (a.calibration is None)
