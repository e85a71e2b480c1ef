"""DSEC sequences as training recordings (evseg.train.dsec), on synthetic files in DSEC's format."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from evseg.errors import ConfigError, FormatError
from evseg.events import EventStream, make_events
from evseg.io import write_h5
from evseg.train.data import load_flow_recording
from evseg.train.dsec import DSEC_SENSOR_SIZE, convert_dsec, main, read_flow_png

W, H = DSEC_SENSOR_SIZE
T_OFFSET = 50_000_000_000  # DSEC's absolute clock, us
SHIFT = (2.4, -1.3)  # the synthetic rectification: a shift, rounded per event


def _flow_png(path, flow_px: tuple[float, float], valid_rows: slice) -> None:
    """A DSEC flow map: (x, y, valid) channels as uint16, written the way OpenCV stores RGB."""
    rgb = np.zeros((H, W, 3), np.uint16)
    rgb[valid_rows, :, 0] = round(flow_px[0] * 128 + 2**15)
    rgb[valid_rows, :, 1] = round(flow_px[1] * 128 + 2**15)
    rgb[valid_rows, :, 2] = 1
    assert cv2.imwrite(str(path), rgb[..., ::-1])


@pytest.fixture()
def sequence(tmp_path):
    """Events every 5 ms over 350 ms and two flow intervals of 100 ms with a 100 ms gap."""
    import h5py

    ev_dir, flow_dir = tmp_path / "events" / "left", tmp_path / "flow"
    (flow_dir / "forward").mkdir(parents=True)
    ev_dir.mkdir(parents=True)
    rng = np.random.default_rng(0)
    n = 71
    t = np.arange(n, dtype=np.int64) * 5_000  # us after T_OFFSET
    x, y = rng.integers(0, W, n), rng.integers(0, H, n)
    x[1], y[1] = W - 1, 10  # at 5 ms, inside the first interval, rectified to x = 641: dropped
    write_h5(EventStream(make_events(x, y, t, np.where(rng.random(n) < 0.5, 1, -1)), DSEC_SENSOR_SIZE,
                         t_offset_us=T_OFFSET), ev_dir / "events.h5")
    gx, gy = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    with h5py.File(ev_dir / "rectify_map.h5", "w") as f:
        f["rectify_map"] = np.stack([gx + SHIFT[0], gy + SHIFT[1]], -1)
    starts = [T_OFFSET + 1_000, T_OFFSET + 201_000]
    (flow_dir / "forward_timestamps.txt").write_text(
        "# from_timestamp_us, to_timestamp_us\n" + "".join(f"{s}, {s + 100_000}\n" for s in starts))
    _flow_png(flow_dir / "forward" / "000002.png", (12.5, -3.25), slice(0, H // 2))  # top half valid
    _flow_png(flow_dir / "forward" / "000004.png", (-0.5, 4.0), slice(0, H))
    return ev_dir, flow_dir, (x, y, t)


def test_a_sequence_becomes_rectified_events_with_flow_in_px_per_s(sequence, tmp_path):
    ev_dir, flow_dir, (x, y, t) = sequence
    out = convert_dsec(ev_dir, flow_dir, tmp_path / "seq.npz")
    rec = load_flow_recording(out)
    # Kept: events inside [1, 101) ms or [201, 301) ms after the offset, rectified on the sensor.
    inside = ((t >= 1_000) & (t < 101_000)) | ((t >= 201_000) & (t < 301_000))
    xr, yr = np.rint(x + SHIFT[0]), np.rint(y + SHIFT[1])
    keep = inside & (xr >= 0) & (xr < W) & (yr >= 0) & (yr < H)
    assert not keep[1] and inside[1]
    assert rec.sensor_size == DSEC_SENSOR_SIZE
    np.testing.assert_array_equal(rec.events["t"], t[keep] - 1_000)  # time base: the first interval
    np.testing.assert_array_equal(rec.events["x"], xr[keep])
    np.testing.assert_array_equal(rec.events["y"], yr[keep])
    # 12.5 px over 100 ms = 125 px/s; -3.25 px -> -32.5 px/s; the second map -5 and 40 px/s.
    first = rec.events["t"] < 100_000
    top = rec.events["y"] < H // 2
    np.testing.assert_allclose(rec.optical_flow[first & top], np.tile([125.0, -32.5], ((first & top).sum(), 1)))
    assert np.isnan(rec.optical_flow[first & ~top]).all()  # invalid pixels: no ground truth
    np.testing.assert_allclose(rec.optical_flow[~first], np.tile([-5.0, 40.0], ((~first).sum(), 1)))
    with np.load(out) as z:  # the gap between the intervals has an all-NaN map
        assert z["flow_t_us"].tolist() == [0, 100_000, 200_000]
        assert np.isnan(z["flow_maps"][1]).all()


def test_max_maps_keeps_the_first_intervals(sequence, tmp_path):
    ev_dir, flow_dir, (_, _, t) = sequence
    rec = load_flow_recording(convert_dsec(ev_dir, flow_dir, tmp_path / "one.npz", max_maps=1))
    assert rec.events["t"].max() < 100_000 and len(rec.events) > 0


def test_flow_png_channels_and_scale(tmp_path):
    _flow_png(tmp_path / "f.png", (-1.0, 2.5), slice(0, 3))
    flow, valid = read_flow_png(tmp_path / "f.png")
    assert flow.shape == (H, W, 2) and valid[:3].all() and not valid[3:].any()
    np.testing.assert_allclose(flow[0, 0], [-1.0, 2.5])


def test_broken_sequences_are_refused_by_name(sequence, tmp_path):
    ev_dir, flow_dir, _ = sequence
    (flow_dir / "forward" / "000004.png").unlink()
    with pytest.raises(FormatError, match=r"1 flow maps in forward/ but 2 rows in forward_timestamps.txt"):
        convert_dsec(ev_dir, flow_dir, tmp_path / "x.npz")
    (flow_dir / "forward_timestamps.txt").write_text("5, 3\n")
    with pytest.raises(FormatError, match=r"row 1 ends before it starts"):
        convert_dsec(ev_dir, flow_dir, tmp_path / "x.npz")
    cv2.imwrite(str(tmp_path / "eight.png"), np.zeros((4, 4, 3), np.uint8))
    with pytest.raises(FormatError, match=r"3-channel 16-bit PNG, got dtype uint8"):
        read_flow_png(tmp_path / "eight.png")
    assert not (tmp_path / "x.npz").exists()


def test_command_line(sequence, tmp_path, capsys):
    ev_dir, flow_dir, _ = sequence
    assert main([str(ev_dir), str(flow_dir), "--out", str(tmp_path / "s.npz")]) == 0
    assert "flow maps" in capsys.readouterr().out
    assert main([str(tmp_path), str(flow_dir), "--out", str(tmp_path / "t.npz")]) == 2
    assert "rectify_map.h5" in capsys.readouterr().err


def test_the_output_may_not_replace_an_input_or_be_another_format(sequence, tmp_path, capsys):
    ev_dir, flow_dir, _ = sequence
    raw = (ev_dir / "events.h5").read_bytes()
    # DSEC's own events.h5 (the suffix alone refuses it), and any name but .npz.
    for out in (ev_dir / "events.h5", tmp_path / "out.h5", tmp_path / "noext"):
        assert main([str(ev_dir), str(flow_dir), "--out", str(out)]) == 2
        assert f"--out {out}: the file must end in .npz" in capsys.readouterr().err
    assert (ev_dir / "events.h5").read_bytes() == raw
    assert not (tmp_path / "out.h5").exists() and not (tmp_path / "noext").exists()
    # A sequence file with the .npz suffix (the same file under another name counts too).
    (flow_dir / "forward_timestamps.npz").symlink_to(flow_dir / "forward_timestamps.txt")
    before = (flow_dir / "forward_timestamps.txt").read_bytes()
    with pytest.raises(ConfigError, match=r"is the flow timestamps .* which the run reads"):
        convert_dsec(ev_dir, flow_dir, flow_dir / "forward_timestamps.npz")
    assert (flow_dir / "forward_timestamps.txt").read_bytes() == before
