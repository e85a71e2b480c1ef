"""EVIMO2 v2 sequences as training recordings (evseg.train.evimo2), on synthetic folders in
EVIMO2's layout."""

from __future__ import annotations

import numpy as np
import pytest

from evseg.errors import ConfigError, FormatError
from evseg.train.data import load_flow_recording
from evseg.train.evimo2 import convert_evimo2, main

W, H = 64, 48
SPACING_S = 1 / 60  # EVIMO2's ground-truth frames
ROS_OFFSET_S = 1_600_000_000.25


def _folder(tmp_path, epoch: bool = False, with_info: bool = True):
    """Events every ms over 120 ms; flow maps at frames 0, 1, 2 and 5 (frames 3-4 lost), each a
    displacement over 10 ms; the right half of every map has no depth (NaN)."""
    folder = tmp_path / "seq"
    folder.mkdir()
    rng = np.random.default_rng(0)
    n = 120
    t_s = np.arange(n) * 1e-3 + 0.0005
    xy = np.stack([rng.integers(0, W, n), rng.integers(0, H, n)], -1).astype(np.uint16)
    np.save(folder / "dataset_events_xy.npy", xy)
    np.save(folder / "dataset_events_t.npy", t_s)
    np.save(folder / "dataset_events_p.npy", rng.integers(0, 2, n).astype(np.uint8))
    frames = [0, 1, 2, 5]
    maps = {}
    for f in frames:
        m = np.full((H, W, 2), np.nan, np.float32)
        m[:, : W // 2] = (0.5 * (f + 1), -0.25)  # px over 10 ms: (50 (f + 1), -25) px/s
        maps[f"flow_{f:010d}"] = m
    t0 = np.array(frames) * SPACING_S + (ROS_OFFSET_S if epoch else 0.0)
    np.savez(folder / "dataset_flow.npz", t=t0, t_end=t0 + 0.01, **maps)
    if with_info:
        meta = {"meta": {"ros_time_offset": ROS_OFFSET_S, "res_x": W, "res_y": H}}
        np.savez(folder / "dataset_info.npz", meta=np.array(meta, dtype=object))
    return folder, xy, t_s, frames


@pytest.mark.parametrize("epoch", [False, True])
def test_events_get_the_flow_of_their_frame_in_px_per_s(tmp_path, epoch):
    folder, xy, t_s, frames = _folder(tmp_path, epoch=epoch)
    rec = load_flow_recording(convert_evimo2(folder, tmp_path / "out.npz"))
    start = np.array(frames) * SPACING_S
    k = np.searchsorted(start, t_s, side="right") - 1
    inside = (k >= 0) & (t_s < start[np.maximum(k, 0)] + SPACING_S)  # frames 3-4 lost: no flow there
    assert 0 < inside.sum() < len(t_s)
    np.testing.assert_array_equal(rec.events["t"], np.rint(t_s[inside] * 1e6).astype(np.int64))
    np.testing.assert_array_equal(rec.events["x"], xy[inside, 0])
    assert rec.sensor_size == (W, H)
    left = rec.events["x"] < W // 2
    f = np.array(frames)[k[inside]]
    np.testing.assert_allclose(rec.optical_flow[left], np.stack([50.0 * (f[left] + 1), np.full(left.sum(), -25.0)], -1),
                               rtol=1e-5)
    assert np.isnan(rec.optical_flow[~left]).all()


def test_max_maps(tmp_path):
    folder, _, _, _ = _folder(tmp_path)
    rec = load_flow_recording(convert_evimo2(folder, tmp_path / "out.npz", max_maps=1))
    assert rec.events["t"].max() < SPACING_S * 1e6


def test_broken_folders_are_refused_by_name(tmp_path):
    folder, _, _, _ = _folder(tmp_path, epoch=True, with_info=False)
    with pytest.raises(FormatError, match=r"dataset_info.npz: the flow's times are epoch seconds"):
        convert_evimo2(folder, tmp_path / "out.npz")
    (folder / "dataset_flow.npz").unlink()
    with pytest.raises(FormatError, match=r"run EVIMO's tools/evimo_flow.py on the sequence first"):
        convert_evimo2(folder, tmp_path / "out.npz")
    np.save(folder / "dataset_events_p.npy", np.zeros(3, np.uint8))
    with pytest.raises(FormatError, match=r"must be \(N, 2\) with N"):
        convert_evimo2(folder, tmp_path / "out.npz")
    assert not (tmp_path / "out.npz").exists()


def test_command_line(tmp_path, capsys):
    folder, _, _, _ = _folder(tmp_path)
    assert main([str(folder), "--out", str(tmp_path / "s.npz")]) == 0
    assert "with ground-truth flow" in capsys.readouterr().out
    assert main([str(tmp_path), "--out", str(tmp_path / "t.npz")]) == 2
    assert "dataset_events_xy.npy" in capsys.readouterr().err


def test_the_output_may_not_replace_an_input_or_be_another_format(tmp_path, capsys):
    folder, _, _, _ = _folder(tmp_path)
    flow = (folder / "dataset_flow.npz").read_bytes()
    assert main([str(folder), "--out", str(folder / "dataset_flow.npz")]) == 2
    assert "is the sequence's dataset_flow.npz, which the run reads" in capsys.readouterr().err
    with pytest.raises(ConfigError, match=r"dataset_info.npz: is the sequence's dataset_info.npz"):
        convert_evimo2(folder, folder / "dataset_info.npz")
    assert (folder / "dataset_flow.npz").read_bytes() == flow
    for out in (tmp_path / "out.h5", tmp_path / "noext"):
        assert main([str(folder), "--out", str(out)]) == 2
        assert f"--out {out}: the file must end in .npz" in capsys.readouterr().err
        assert not out.exists()
