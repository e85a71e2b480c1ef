"""ROS1 and ROS2 bag reader: bags written here with rosbags' own writers and serialisers (no ROS
installed), so the numpy decoders of evseg.io.ros_messages are checked against another
implementation of the wire formats."""

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
    with pytest.raises(FormatError, match=r"several event topics \(/left/events \(dvs_msgs/msg/EventArray\), /right/events \(dvs_msgs/msg/EventArray\)\); choose one with --topic"):
        read_events(p)
    assert len(read_events(p, topic="/right/events")) == 7
    with pytest.raises(FormatError, match=r"topic '/chatter' has type std_msgs/msg/String, not one of the event messages evseg reads \(dvs_msgs/msg/EventArray, prophesee_event_msgs/msg/EventArray, event_camera_msgs/msg/EventPacket\)"):
        read_events(p, topic="/chatter")
    with pytest.raises(FormatError, match=r"no topic '/nope'; topics: /chatter \(std_msgs/msg/String\)"):
        read_events(p, topic="/nope")


def test_bag_without_events(tmp_path):
    p = tmp_path / "none.bag"
    write_bag(p, {})
    with pytest.raises(FormatError, match=r"no event topic \(dvs_msgs/msg/EventArray, .*\); topics: /chatter \(std_msgs/msg/String\)"):
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
    # The events themselves stay readable, and say why the calibration is not used.
    with open_recording(p) as rec:
        assert rec.calibration is None and "CameraInfo is for 346x260" in rec.calibration_problem
        assert sum(len(c) for c in rec.chunks()) == len(ev)


def test_an_empty_d_means_no_distortion(tmp_path):
    # ROS drivers publish D = [] for an undistorted (or never-distorted) camera.
    ev = sample_events(30, seed=6)
    write_bag(p := tmp_path / "b.bag", {"/dvs/events": [ev]}, camera_info={
        "/dvs/camera_info": {"K": K_INFO, "D": [], "distortion_model": "plumb_bob"}})
    cal = read_events(p).calibration
    assert cal.model == "radtan" and not np.any(cal.D)


def test_a_calibration_of_ones_own_reads_a_bag_with_an_unusable_camera_info(tmp_path, capsys):
    from evseg.cli import main

    ev = sample_events(300, seed=6)
    write_bag(p := tmp_path / "b.bag", {"/dvs/events": [ev]}, camera_info={
        "/dvs/camera_info": {"K": K_INFO, "D": [], "distortion_model": "plumb_bob", "width": 346, "height": 260}})
    calib = tmp_path / "calib.yaml"
    calib.write_text("image_width: 64\nimage_height: 48\ncamera_matrix: {rows: 3, cols: 3, data: [60, 0, 32, 0, 60, 24, "
                     "0, 0, 1]}\ndistortion_model: plumb_bob\ndistortion_coefficients: {rows: 1, cols: 5, data: [0, 0, 0, 0, 0]}\n")
    out = tmp_path / "r.npz"
    assert main(["segment", str(p), "--out", str(out), "--flow-method", "planefit", "--no-progress"]) == 2
    assert "CameraInfo is for 346x260, the events are 64x48; give a calibration of your own (--calib" in \
        capsys.readouterr().err
    assert main(["segment", str(p), "--out", str(out), "--calib", str(calib), "--flow-method", "planefit",
                 "--no-progress"]) == 0
    assert len(np.load(out)["label"]) == len(ev)


def _same_events(stream, ev):
    np.testing.assert_array_equal(stream.events["t"], ev["t"] - ev["t"][0])
    for k in "xyp":
        np.testing.assert_array_equal(stream.events[k], ev[k])


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
@pytest.mark.parametrize("msgtype", ["dvs_msgs/msg/EventArray", "prophesee_event_msgs/msg/EventArray"])
def test_ros2_bag_round_trip_directory_and_storage_file(tmp_path, storage, msgtype):
    # 1, 2, 3 and 70 events per message: the CDR event array's first element has another stride
    # than the rest, so each length is a separate case of the decoder.
    ev = sample_events(76, seed=7)
    d = tmp_path / "bag2"
    write_bag(d, {"/dvs/events": [ev[:1], ev[1:3], ev[3:3], ev[3:6], ev[6:]]}, ros2=storage, msgtype=msgtype)
    assert detect_format(d) == "rosbag2"
    with open_recording(d, chunk_events=4) as rec:
        assert (rec.format, rec.sensor_size) == ("rosbag2", (64, 48))
        assert rec.t_offset_us == 1_519_939_282_250_708 + int(ev["t"][0])
        assert [len(c) for c in rec.chunks()] == [6, 70]
    _same_events(read_events(d), ev)
    (storage_file,) = [f for f in d.iterdir() if f.suffix in (".db3", ".mcap")]
    assert detect_format(storage_file) == "rosbag2"
    _same_events(read_events(storage_file), ev)


@pytest.mark.parametrize("ros2", [None, "sqlite3"])
@pytest.mark.parametrize("encoding", ["evt3", "mono"])
def test_event_camera_msgs_packets(tmp_path, ros2, encoding):
    # evt3: times are the sensor's clock (us); the stream is cut between packets, so each
    # packet continues the time and row state of the one before.
    ev = sample_events(90, seed=8, max_dt=3000)
    p = tmp_path / ("pk" if ros2 else "pk.bag")
    write_bag(p, {"/event_camera/events": [ev[:40], ev[40:41], ev[41:]]}, ros2=ros2,
              msgtype="event_camera_msgs/msg/EventPacket", encoding=encoding, width=64, height=48)
    with open_recording(p) as rec:
        assert rec.sensor_size == (64, 48)
        assert rec.t_offset_us == int(ev["t"][0])
    _same_events(read_events(p), ev)


def test_event_packets_with_an_encoding_evseg_does_not_read(tmp_path):
    write_bag(p := tmp_path / "lc.bag", {"/cam/events": [sample_events(5)]},
              msgtype="event_camera_msgs/msg/EventPacket", encoding="libcaer_cmp")
    with pytest.raises(FormatError, match=r"lc.bag: rosbag: topic '/cam/events': EventPacket encoding "
                                          r"'libcaer_cmp' is not read by evseg \(supported: evt3, mono\)"):
        read_events(p)


def test_ros2_camera_info_and_topic_choice(tmp_path):
    a, b = sample_events(20, seed=9), sample_events(12, seed=10)
    d = tmp_path / "stereo"
    write_bag(d, {"/left/events": [a], "/right/events": [b]}, ros2="mcap", camera_info={
        "/right/camera_info": {"K": K_INFO, "D": [0.01, -0.002, 0.0005, 0.0001, 0.0], "distortion_model": "plumb_bob"}})
    with pytest.raises(FormatError, match=r"several event topics"):
        read_events(d)
    s = read_events(d, topic="/right/events")
    assert len(s) == 12 and s.calibration.model == "radtan"
    np.testing.assert_array_equal(s.calibration.K.ravel(), K_INFO)
    assert read_events(d, topic="/left/events").calibration is None


def test_directories_that_are_not_ros2_bags(tmp_path):
    (d := tmp_path / "frames").mkdir()
    with pytest.raises(FormatError, match=r"frames: is a directory, not a recording file \(a ROS2 bag directory holds metadata.yaml\)"):
        read_events(d)
    with pytest.raises(FormatError, match=r"frames: rosbag2: not a readable ROS2 bag"):
        read_events(d, format="rosbag2")
    with pytest.raises(FormatError, match=r"is a directory, not a recording file \(only a ROS2 bag"):
        read_events(d, format="npz")
    (f := tmp_path / "x.mcap").write_bytes(b"not an mcap file at all")
    with pytest.raises(FormatError, match=r"x.mcap: not a valid rosbag2 file: bad magic bytes at offset 0 "
                                          r"\(expected b'SQLite format 3\\x00' or b'\\x89MCAP0\\r\\n'"):
        read_events(f)


def test_evseg_flow_reads_a_chosen_topic(tmp_path, capsys):
    from evseg.cli import main

    a, b = sample_events(300, seed=4), sample_events(200, seed=5)
    p = tmp_path / "two.bag"
    write_bag(p, {"/left/events": [a], "/right/events": [b]})
    out = tmp_path / "f.npz"
    assert main(["flow", str(p), "--baseline", "--out", str(out), "--no-progress"]) == 2
    assert "choose one with --topic" in capsys.readouterr().err
    assert main(["flow", str(p), "--baseline", "--topic", "/right/events", "--out", str(out), "--no-progress"]) == 0
    assert "for 200 events" in capsys.readouterr().out


def test_a_cut_ros1_bag_points_to_reindex(tmp_path):
    write_bag(p := tmp_path / "b.bag", {"/dvs/events": [sample_events(300)]})
    cut = tmp_path / "cut.bag"
    cut.write_bytes(p.read_bytes()[: p.stat().st_size // 2])
    with pytest.raises(FormatError, match=r"cut.bag: rosbag: not a readable ROS1 bag .*`rosbag reindex` rebuilds it"):
        read_events(cut)
