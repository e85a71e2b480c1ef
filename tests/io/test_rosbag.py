"""ROS1 bag reader: bags written here with rosbags' own writer (no ROS installed)."""

from __future__ import annotations

import numpy as np
import pytest

from evfiles import sample_events, write_bag
from evseg.errors import FormatError
from evseg.io import detect_format, open_recording, read_events


def test_round_trip_through_a_written_bag(tmp_path):
    ev = sample_events(120, seed=3)
    p = tmp_path / "e.bag"
    write_bag(p, {"/dvs/events": [ev[:50], ev[50:50], ev[50:]]})
    assert detect_format(p) == "rosbag"
    with open_recording(p, chunk_events=40) as rec:
        assert rec.sensor_size == (64, 48)
        assert rec.t_offset_us == 1_519_939_282_250_708 + int(ev["t"][0])
        chunks = list(rec.chunks())
    assert [len(c) for c in chunks] == [50, 70]  # whole messages, at least chunk_events each
    s = read_events(p)
    np.testing.assert_array_equal(s.events["t"], ev["t"] - ev["t"][0])
    for k in "xyp":
        np.testing.assert_array_equal(s.events[k], ev[k])


def test_several_event_topics_need_a_choice(tmp_path):
    a, b = sample_events(10, seed=4), sample_events(7, seed=5)
    p = tmp_path / "two.bag"
    write_bag(p, {"/left/events": [a], "/right/events": [b]})
    with pytest.raises(FormatError, match=r"several dvs_msgs/msg/EventArray topics \(/left/events, /right/events\); choose one with --topic"):
        read_events(p)
    assert len(read_events(p, topic="/right/events")) == 7
    with pytest.raises(FormatError, match=r"topic '/chatter' has type std_msgs/msg/String"):
        read_events(p, topic="/chatter")
    with pytest.raises(FormatError, match=r"no topic '/nope'; topics: /chatter \(std_msgs/msg/String\)"):
        read_events(p, topic="/nope")


def test_bag_without_events(tmp_path):
    p = tmp_path / "none.bag"
    write_bag(p, {})
    with pytest.raises(FormatError, match=r"no dvs_msgs/msg/EventArray topic; topics: /chatter"):
        read_events(p)


K_INFO = [60.0, 0.0, 32.0, 0.0, 61.0, 24.0, 0.0, 0.0, 1.0]


def test_camera_info_beside_the_event_topic_is_the_calibration(tmp_path):
    ev = sample_events(30, seed=6)
    write_bag(p := tmp_path / "b1.bag", {"/dvs/events": [ev]}, camera_info={
        "/dvs/camera_info": {"K": K_INFO, "D": [0.01, -0.002, 0.0005, 0.0001], "distortion_model": "equidistant"}})
    cal = read_events(p).calibration
    assert cal.model == "equidistant" and cal.sensor_size == (64, 48)
    np.testing.assert_array_equal(cal.K.ravel(), K_INFO)
    np.testing.assert_array_equal(cal.D, [0.01, -0.002, 0.0005, 0.0001])
    # Only the camera_info of the chosen event topic's namespace counts; a zero K = uncalibrated.
    write_bag(p := tmp_path / "b2.bag", {"/dvs/events": [ev]}, camera_info={
        "/other/camera_info": {"K": K_INFO, "D": [], "distortion_model": "plumb_bob"}})
    assert read_events(p).calibration is None
    write_bag(p := tmp_path / "b3.bag", {"/dvs/events": [ev]}, camera_info={
        "/dvs/camera_info": {"K": [0.0] * 9, "D": [], "distortion_model": ""}})
    assert read_events(p).calibration is None


def test_bad_camera_info_names_the_topic_and_field(tmp_path):
    ev = sample_events(30, seed=6)
    write_bag(p := tmp_path / "b4.bag", {"/dvs/events": [ev]}, camera_info={
        "/dvs/camera_info": {"K": K_INFO, "D": [0.1, 0.0, 0.0], "distortion_model": "plumb_bob"}})
    with pytest.raises(FormatError, match=r"topic '/dvs/camera_info': field 'D' needs 4 or 5 or 8 numbers"):
        read_events(p)
    write_bag(p := tmp_path / "b5.bag", {"/dvs/events": [ev]}, camera_info={
        "/dvs/camera_info": {"K": K_INFO, "D": [], "distortion_model": "plumb_bob", "width": 346, "height": 260}})
    with pytest.raises(FormatError, match=r"CameraInfo is for 346x260, the events are 64x48"):
        read_events(p)
