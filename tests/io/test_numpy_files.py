"""numpy readers (.npy / .npz layouts, field-name variants, calibration) and the npz writer."""

from __future__ import annotations

import numpy as np
import pytest

from evfiles import sample_events
from evseg.calibration import Calibration
from evseg.errors import FormatError
from evseg.events import EventStream
from evseg.io import open_recording, read_events, write_npz


def test_structured_npy_with_field_variants(tmp_path):
    ev = sample_events(30)
    a = np.empty(30, dtype=[("timestamp", "<u8"), ("x", "<u2"), ("y", "<u2"), ("pol", "u1")])
    a["timestamp"], a["x"], a["y"], a["pol"] = ev["t"], ev["x"], ev["y"], ev["p"] > 0
    np.save(tmp_path / "a.npy", a)
    np.testing.assert_array_equal(read_events(tmp_path / "a.npy").events, ev)


def test_nx4_float_seconds_layout(tmp_path):
    ev = sample_events(20)
    a = np.stack([ev["t"] / 1e6, ev["x"], ev["y"], (ev["p"] > 0)], axis=1)
    np.save(tmp_path / "b.npy", a)
    np.testing.assert_array_equal(read_events(tmp_path / "b.npy").events, ev)


def test_npz_column_keys_extra_keys_ignored(tmp_path):
    ev = sample_events(20)
    np.savez(tmp_path / "c.npz", x=ev["x"], y=ev["y"], ts=ev["t"], polarity=ev["p"],
             notes=np.arange(3), width=100, height=90)
    s = read_events(tmp_path / "c.npz")
    assert s.sensor_size == (100, 90)
    np.testing.assert_array_equal(s.events, ev)


def test_npz_nan_names_event_index(tmp_path):
    a = np.zeros((5, 4), dtype=np.float32)
    a[3, 2] = np.nan
    np.savez(tmp_path / "n.npz", events=a)
    with pytest.raises(FormatError, match=r"n.npz: npz: field 'y' is nan \(not finite\) at event 3"):
        read_events(tmp_path / "n.npz")


def test_pickled_objects_are_refused(tmp_path):
    np.save(tmp_path / "o.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(FormatError, match="pickles"):
        read_events(tmp_path / "o.npy")


def test_missing_fields_are_listed(tmp_path):
    np.save(tmp_path / "m.npy", np.zeros(3, dtype=[("x", "u2"), ("y", "u2"), ("t", "i8")]))
    with pytest.raises(FormatError, match=r"lacks \['p'\]"):
        read_events(tmp_path / "m.npy")


def test_write_npz_round_trip_with_calibration(tmp_path):
    K = np.array([[200.0, 0, 120], [0, 199, 90], [0, 0, 1]])
    cal = Calibration(K, np.array([-0.3, 0.1, 1e-4, -2e-4]), (240, 180))
    stream = EventStream(sample_events(1000, width=240, height=180), (240, 180), 123_456_789, cal)
    p = write_npz(stream, tmp_path / "out.npz")
    assert sorted(p.parent.iterdir()) == [p]  # the temporary file is gone
    back = read_events(p)
    np.testing.assert_array_equal(back.events, stream.events)
    assert back.sensor_size == (240, 180) and back.t_offset_us == 123_456_789
    np.testing.assert_array_equal(back.calibration.K, K)
    np.testing.assert_array_equal(back.calibration.D, cal.D)
    assert back.calibration.model == "radtan"


@pytest.mark.parametrize("suffix", [".npz", ".h5"])
def test_written_files_keep_the_distortion_model(tmp_path, suffix):
    """An equidistant calibration read back as radtan would undistort every event wrongly."""
    from evseg.io import write_h5

    K = np.array([[200.0, 0, 120], [0, 199, 90], [0, 0, 1]])
    cal = Calibration(K, np.array([-0.04, 0.012, -0.006, 0.001]), (240, 180), model="equidistant")
    stream = EventStream(sample_events(100, width=240, height=180), (240, 180), 0, cal)
    p = (write_npz if suffix == ".npz" else write_h5)(stream, tmp_path / f"out{suffix}")
    back = read_events(p).calibration
    assert back.model == "equidistant"
    np.testing.assert_array_equal(back.D, cal.D)


def test_failed_write_leaves_no_file(tmp_path):
    class Boom(Exception):
        pass

    def chunks():
        yield sample_events(5)
        raise Boom

    from evseg.io.numpy_files import write_npz_chunks

    with pytest.raises(Boom):
        write_npz_chunks(chunks(), tmp_path / "x.npz", lambda: ((64, 48), 0, None))
    assert list(tmp_path.iterdir()) == []


def test_real_ecd_poster_with_calibration(shared_data):
    s = read_events(shared_data / "ecd_poster" / "poster_translation.npz")
    assert len(s) == 100_000 and s.sensor_size == (240, 180)
    raw = np.load(shared_data / "ecd_poster" / "poster_translation.npz")
    np.testing.assert_array_equal(s.events["t"], np.rint(raw["events"][:, 0].astype(np.float64) * 1e6))
    np.testing.assert_allclose(s.calibration.K[0, 0], 199.092, atol=1e-3)  # README's fx, 3 decimals
    assert s.calibration.D.shape == (4,)


def test_real_eed_npy_titled_field(shared_data):
    s = read_events(shared_data / "eed_what_is_background" / "events_t_us_x_y_on.npy")
    assert len(s) == 271_264 and s.sensor_size == (190, 180)
    assert 0.49 < float((s.events["p"] > 0).mean()) < 0.51  # README: 49.8 % ON


def test_a_unit_suffix_on_the_time_name_decides_the_unit(tmp_path):
    # Float microseconds under 't_us' must not be read as seconds (x 1e6), nor integer
    # seconds under 't_s' as microseconds.
    x, y, p = np.array([1, 2]), np.array([3, 4]), np.array([1, 0])
    np.savez(tmp_path / "us.npz", t_us=np.array([500010.0, 500020.4]), x=x, y=y, p=p)
    assert read_events(tmp_path / "us.npz").events["t"].tolist() == [500010, 500020]
    np.savez(tmp_path / "s.npz", t_s=np.array([1, 2]), x=x, y=y, p=p)
    assert read_events(tmp_path / "s.npz").events["t"].tolist() == [1_000_000, 2_000_000]
    a = np.zeros(2, dtype=[("timestamp_us", "<f8"), ("x", "<u2"), ("y", "<u2"), ("polarity", "i1")])
    a["timestamp_us"] = [7.0, 9.0]
    np.save(tmp_path / "st.npy", a)
    with open_recording(tmp_path / "st.npy") as rec:
        assert rec.time_span_us() == (7, 9)
        assert rec.read_all().events["t"].tolist() == [7, 9]


def test_nanoseconds_and_milliseconds_by_suffix_or_time_unit(tmp_path):
    # Epoch nanoseconds (as ROS and many loggers write them) become microseconds exactly,
    # rounded half up; read as microseconds they would stretch the recording 1000x silently.
    x, y, p = np.array([1, 2, 3]), np.array([3, 4, 5]), np.array([1, 0, 1])
    t_ns = np.array([1_700_000_000_000_000_000, 1_700_000_000_001_000_499, 1_700_000_000_002_000_500])
    expected = [1_700_000_000_000_000, 1_700_000_000_001_000, 1_700_000_000_002_001]
    np.savez(tmp_path / "ns.npz", t_ns=t_ns, x=x, y=y, p=p)
    assert read_events(tmp_path / "ns.npz").events["t"].tolist() == expected
    np.savez(tmp_path / "plain.npz", t=t_ns, x=x, y=y, p=p)
    assert read_events(tmp_path / "plain.npz", time_unit="ns").events["t"].tolist() == expected
    with open_recording(tmp_path / "plain.npz", time_unit="ns") as rec:
        assert rec.time_span_us() == (expected[0], expected[-1])
    np.save(tmp_path / "ms.npy", np.stack([np.array([1.5, 2.25, 3.0]), x, y, p], 1))
    assert read_events(tmp_path / "ms.npy", time_unit="ms").events["t"].tolist() == [1500, 2250, 3000]
    with pytest.raises(FormatError, match=r"ms.npy: npy: time_unit must be one of 's', 'ms', 'us', 'ns', got 'min'"):
        read_events(tmp_path / "ms.npy", time_unit="min")


def test_a_stored_calibration_takes_the_size_the_user_gives(tmp_path):
    # K, D without a sensor size: the reader sizes them as max + 1 of the events, which is
    # smaller than the sensor; --sensor-size must size the calibration too, not be refused.
    ev = sample_events(200)
    K = np.array([[60.0, 0, 32], [0, 60, 24], [0, 0, 1]])
    np.savez(tmp_path / "kd.npz", events=np.stack([ev["t"] / 1e6, ev["x"], ev["y"], ev["p"]], 1), K=K, D=np.zeros(4))
    with open_recording(tmp_path / "kd.npz", sensor_size=(80, 60)) as rec:
        assert rec.calibration.sensor_size == (80, 60)


def test_segment_takes_the_calibrations_size_for_a_file_without_one(tmp_path, capsys):
    from evseg.cli import main

    ev = sample_events(300)  # events within 64x48; the camera is 80x60
    lines = "".join(f"{t / 1e6:.6f} {x} {y} {int(p > 0)}\n" for t, x, y, p in ev[["t", "x", "y", "p"]])
    (tmp_path / "e.txt").write_text(lines)
    (tmp_path / "c.yaml").write_text(
        "image_width: 80\nimage_height: 60\ncamera_matrix: {data: [60, 0, 40, 0, 60, 30, 0, 0, 1]}\n"
        "distortion_model: plumb_bob\ndistortion_coefficients: {data: [0, 0, 0, 0, 0]}\n")
    out = tmp_path / "r.npz"
    rc = main(["segment", str(tmp_path / "e.txt"), "--calib", str(tmp_path / "c.yaml"), "--out", str(out),
               "--flow-method", "planefit", "--no-progress"])
    assert rc == 0, capsys.readouterr().err
    assert np.load(out)["sensor_size"].tolist() == [80, 60]
    rc = main(["flow", str(tmp_path / "e.txt"), "--calib", str(tmp_path / "c.yaml"), "--out", str(tmp_path / "f.npz"),
               "--baseline", "--no-progress"])
    assert rc == 0, capsys.readouterr().err
    assert np.load(tmp_path / "f.npz")["sensor_size"].tolist() == [80, 60]


def test_a_camera_matrix_alone_is_a_calibration_and_d_alone_is_refused(tmp_path):
    ev = sample_events(50)
    K = np.array([[60.0, 0, 32], [0, 60, 24], [0, 0, 1]])
    cols = dict(t=ev["t"], x=ev["x"], y=ev["y"], p=ev["p"], sensor_size=np.array([64, 48]))
    np.savez(tmp_path / "k.npz", K=K, **cols)
    cal = read_events(tmp_path / "k.npz").calibration
    assert cal is not None and not np.any(cal.D)
    np.savez(tmp_path / "d.npz", D=np.zeros(4), **cols)
    with pytest.raises(FormatError, match=r"d.npz: npz: key 'D' \(distortion\) without the camera matrix 'K'"):
        read_events(tmp_path / "d.npz")


def test_write_npz_needs_the_npz_extension(tmp_path):
    with pytest.raises(FormatError, match=r"e.bin: an .npz recording must be named \*.npz"):
        write_npz(EventStream(sample_events(5), (64, 48)), tmp_path / "e.bin")
    assert not (tmp_path / "e.bin").exists()


def test_ecd_layout_events_txt_with_its_one_line_calib_txt(tmp_path, capsys):
    # ECD ships events.txt (t in s, x, y, p) and calib.txt (fx fy cx cy k1 k2 p1 p2 k3) without
    # an image size: the CLI reads the calibration at the size the user gives, and it must act
    # exactly as the same numbers in a camera_info YAML.
    from evseg.cli import main

    ev = sample_events(300)
    lines = "".join(f"{t / 1e6:.6f} {x} {y} {int(p > 0)}\n" for t, x, y, p in ev[["t", "x", "y", "p"]])
    (tmp_path / "events.txt").write_text(lines)
    (tmp_path / "calib.txt").write_text("60 61 40 30 -0.2 0.05 0.001 -0.002 0\n")
    (tmp_path / "c.yaml").write_text(
        "image_width: 80\nimage_height: 60\ncamera_matrix: {data: [60, 0, 40, 0, 61, 30, 0, 0, 1]}\n"
        "distortion_model: plumb_bob\ndistortion_coefficients: {data: [-0.2, 0.05, 0.001, -0.002, 0]}\n")
    flows = {}
    for calib in ("calib.txt", "c.yaml"):
        out = tmp_path / f"{calib}.npz"
        rc = main(["flow", str(tmp_path / "events.txt"), "--calib", str(tmp_path / calib), "--sensor-size", "80x60",
                   "--out", str(out), "--baseline", "--no-progress"])
        assert rc == 0, capsys.readouterr().err
        flows[calib] = np.load(out)
        rc = main(["segment", str(tmp_path / "events.txt"), "--calib", str(tmp_path / calib), "--sensor-size",
                   "80x60", "--out", str(tmp_path / f"seg_{calib}.npz"), "--flow-method", "planefit", "--no-progress"])
        assert rc == 0, capsys.readouterr().err
    for key in ("index", "nx", "ny"):
        np.testing.assert_array_equal(flows["calib.txt"][key], flows["c.yaml"][key])
    np.testing.assert_array_equal(np.load(tmp_path / "seg_calib.txt.npz")["label"],
                                  np.load(tmp_path / "seg_c.yaml.npz")["label"])
    # Without calibration the flows differ: the calibration was applied.
    rc = main(["flow", str(tmp_path / "events.txt"), "--sensor-size", "80x60", "--out", str(tmp_path / "raw.npz"),
               "--baseline", "--no-progress"])
    assert rc == 0
    assert not np.array_equal(np.load(tmp_path / "raw.npz")["nx"], flows["c.yaml"]["nx"])


def test_times_beyond_2100_under_a_guessed_unit_ask_for_the_unit(tmp_path):
    # Integer epoch nanoseconds under a plain 't' would read as microseconds 54,000 years
    # away; epoch milliseconds as floats would read as seconds. Both are refused with the fix.
    x, y, p = np.array([1, 2]), np.array([3, 4]), np.array([1, 0])
    np.savez(tmp_path / "ns.npz", t=np.array([1_700_000_000_000_000_000, 1_700_000_000_000_001_000]), x=x, y=y, p=p)
    with pytest.raises(FormatError, match=r"ns.npz: npz: field 't' = 1700000000000000000 at event 0 read as us is "
                                          r"after the year 2100: .* \(--time-unit s/ms/ns"):
        read_events(tmp_path / "ns.npz")
    np.savez(tmp_path / "ms.npz", t=np.array([1.7e12, 1.7e12 + 1]), x=x, y=y, p=p)
    with pytest.raises(FormatError, match=r"read as s is after the year 2100"):
        read_events(tmp_path / "ms.npz")
    assert read_events(tmp_path / "ms.npz", time_unit="ms").events["t"].tolist() == [1_700_000_000_000_000,
                                                                                      1_700_000_000_001_000]
    # Epoch microseconds and seconds of today are plausible.
    np.savez(tmp_path / "us.npz", t=np.array([1_700_000_000_000_000]), x=x[:1], y=y[:1], p=p[:1])
    assert read_events(tmp_path / "us.npz").events["t"].tolist() == [1_700_000_000_000_000]
