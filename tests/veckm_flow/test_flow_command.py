import json

import cv2
import numpy as np
import pytest

from evseg.cli import main
from evseg.veckm_flow import OnnxNormalFlow, select_targets
from evseg.veckm_flow.context import flow_with_context
from evseg.veckm_flow.synthetic import translating_edges
from evseg.windows import time_window_slices


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """A 50 ms synthetic recording in the project's npz schema, first event at t = 5 ms."""
    scene = translating_edges((80, 60), n_edges=6, duration_us=50_000, seed=9)
    ev = scene.events.copy()
    ev["t"] += 5_000
    path = tmp_path_factory.mktemp("rec") / "rec.npz"
    np.savez(path, events=ev, sensor_size=np.array([80, 60]))
    return path, ev


@pytest.mark.parametrize("context_ms", [0, 10])
def test_flow_writes_documented_schema_with_recording_indices(recording, random_onnx, tmp_path, capsys, context_ms):
    path, ev = recording
    model, _, cfg = random_onnx
    out = tmp_path / "flow.npz"
    args = ["--window-ms", "20", "--context-ms", str(context_ms), "--no-progress"]
    assert main(["flow", str(path), "--out", str(out), "--model", str(model), *args]) == 0
    z = np.load(out)
    assert {"index", "nx", "ny", "uncertainty", "sensor_size"} <= set(z.files)
    assert z["index"].dtype == np.int64 and z["nx"].dtype == np.float32 and z["uncertainty"].dtype == np.float32
    np.testing.assert_array_equal(z["sensor_size"], [80, 60])
    assert json.loads(str(z["config"]))["encoding"] == cfg.to_dict()
    assert json.loads(str(z["config"]))["context_us"] == context_ms * 1000
    # Recompute slice by slice with the API: same targets (as recording positions) and flows;
    # the events of the context_ms before a slice are neighbours (and only neighbours), and the
    # slow-edge look also sees as long again before them (slice + context) as history.
    est = OnnxNormalFlow(model)
    history_us = 20_000 + context_ms * 1000
    assert json.loads(str(z["config"]))["history_us"] == history_us
    idx, nx = [], []
    for sl in time_window_slices(ev["t"], 20_000):
        w = ev[sl]
        t0 = int(ev["t"][0]) + 20_000 * len(idx)
        t_ctx = t0 - context_ms * 1000
        context = ev[np.searchsorted(ev["t"], t_ctx) : sl.start]
        history = ev[np.searchsorted(ev["t"], t_ctx - history_us) : np.searchsorted(ev["t"], t_ctx)]
        assert context_ms or len(context) == 0
        f = flow_with_context(est, w, (80, 60), select_targets(w, (80, 60), cell_px=2), context, history=history)
        idx.append(f.index + sl.start)
        nx.append(f.nx)
    np.testing.assert_array_equal(z["index"], np.concatenate(idx))
    np.testing.assert_allclose(z["nx"], np.concatenate(nx), rtol=1e-6)
    assert "normal flows" in capsys.readouterr().out


def test_flow_mirrors_option_averages_the_mirror_looks(recording, random_onnx, tmp_path):
    """`evseg flow --mirrors 4` writes what `OnnxNormalFlow(mirrors=4)` computes, and records it."""
    path, ev = recording
    model, _, _ = random_onnx
    out = tmp_path / "flow.npz"
    args = ["--window-ms", "20", "--context-ms", "0", "--no-slow-edges", "--no-progress"]
    assert main(["flow", str(path), "--out", str(out), "--model", str(model), "--mirrors", "4", *args]) == 0
    z = np.load(out)
    assert json.loads(str(z["config"]))["mirrors"] == 4
    est = OnnxNormalFlow(model, slow_edges=None, mirrors=4)
    w = ev[time_window_slices(ev["t"], 20_000)[0]]
    f = est(w, (80, 60), select_targets(w, (80, 60), cell_px=2))
    np.testing.assert_allclose(z["nx"][: len(f)], f.nx, rtol=1e-6, atol=1e-6)
    one = tmp_path / "one.npz"
    assert main(["flow", str(path), "--out", str(one), "--model", str(model), *args]) == 0
    assert json.loads(str(np.load(one)["config"]))["mirrors"] == 1
    assert not np.allclose(np.load(one)["nx"], z["nx"])


def test_flow_baseline_all_targets_and_video(recording, tmp_path):
    path, ev = recording
    out, video = tmp_path / "b.npz", tmp_path / "b.mp4"
    rc = main(["flow", str(path), "--out", str(out), "--baseline", "--targets", "all", "--video", str(video), "--no-progress"])
    assert rc == 0
    z = np.load(out)
    np.testing.assert_array_equal(z["index"], np.arange(len(ev)))
    assert str(z["method"]) == "planefit"
    cap = cv2.VideoCapture(str(video))
    n_frames = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
    ok, frame = cap.read()
    cap.release()
    assert ok and n_frames == 5  # 50 ms in 10 ms slices (the default)
    assert frame.shape[0] >= 360  # small sensors are enlarged
    assert cv2.VideoCapture(str(video)).get(cv2.CAP_PROP_FPS) == pytest.approx(60.0)  # 100 slices/s, capped
    slow = tmp_path / "slow.mp4"
    assert main(["flow", str(path), "--out", str(tmp_path / "c.npz"), "--baseline", "--video", str(slow),
                 "--fps", "5", "--no-progress"]) == 0
    assert cv2.VideoCapture(str(slow)).get(cv2.CAP_PROP_FPS) == pytest.approx(5.0)


def test_flow_option_errors_are_user_errors(recording, tmp_path, capsys):
    path, _ = recording
    assert main(["flow", str(path), "--out", str(tmp_path / "x.npz"), "--baseline", "--model", "m.onnx"]) == 2
    assert main(["flow", str(path), "--out", str(tmp_path / "x.npz"), "--model", str(tmp_path / "none.onnx")]) == 2
    assert main(["flow", str(path), "--out", str(tmp_path / "x.npz"), "--context-ms", "-1"]) == 2
    assert "none.onnx" in capsys.readouterr().err
    assert not (tmp_path / "x.npz").exists()
    # A context beyond the encoder's longest slice (17.9 min) is refused before reading.
    assert main(["flow", str(path), "--out", str(tmp_path / "x.npz"), "--context-ms", "2e6"]) == 2
    assert "--context-ms must be at most" in capsys.readouterr().err


def test_flow_takes_the_option_names_of_segment(recording, tmp_path):
    # --flow-method planefit and --flow-context-ms are segment's names for --baseline and
    # --context-ms: either spelling gives the same file.
    path, _ = recording
    a, b = tmp_path / "a.npz", tmp_path / "b.npz"
    assert main(["flow", str(path), "--out", str(a), "--baseline", "--context-ms", "10", "--no-progress"]) == 0
    assert main(["flow", str(path), "--out", str(b), "--flow-method", "planefit", "--flow-context-ms", "10",
                 "--no-progress"]) == 0
    za, zb = np.load(a), np.load(b)
    assert str(zb["method"]) == "planefit"
    np.testing.assert_array_equal(za["nx"], zb["nx"])
    np.testing.assert_array_equal(za["index"], zb["index"])
    assert main(["flow", str(path), "--out", str(b), "--flow-method", "learned", "--baseline"]) == 2
