import json
import subprocess
import sys

import numpy as np
import pytest

from evseg.calibration import Calibration
from evseg.errors import ModelError
from evseg.veckm_flow import OnnxNormalFlow, encode_targets, head_output_to_flow, select_targets
from evseg.veckm_flow.synthetic import translating_edges


def test_inference_module_does_not_import_torch(tmp_path):
    code = (
        "import sys, evseg.veckm_flow.inference, evseg.veckm_flow; "
        "from evseg.veckm_flow import OnnxNormalFlow, PlaneFitNormalFlow, encode_targets; "
        "print('torch' in sys.modules)"
    )
    # cwd: from the repository root, ./evseg would shadow an installed (non-editable) evseg
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=tmp_path)
    assert out.stdout.strip() == "False"


def test_onnx_estimator_matches_torch_head_in_px_s(random_onnx):
    import torch

    path, head, cfg = random_onnx
    scene = translating_edges(n_edges=8, seed=2)
    targets = select_targets(scene.events, scene.sensor_size, cell_px=3)
    est = OnnxNormalFlow(path, threads=1, fast_edges=None)  # the head's own look: parity
    flow = est(scene.events, scene.sensor_size, targets)
    feats = encode_targets(scene.events, targets, scene.sensor_size, cfg)
    with torch.no_grad():
        nx, ny, u = head_output_to_flow(head(torch.from_numpy(feats)), cfg)
    np.testing.assert_array_equal(flow.index, targets)
    # float32 MLP in two runtimes: differences are a few ulps of outputs of size ~1 head unit
    # (1 head unit = flow_unit_px_s px/s), so 1e-5 relative to the unit is generous.
    tol = 1e-5 * cfg.flow_unit_px_s
    np.testing.assert_allclose(flow.nx, nx, atol=tol)
    np.testing.assert_allclose(flow.ny, ny, atol=tol)
    np.testing.assert_allclose(flow.uncertainty, u, rtol=1e-4)
    assert flow.nx.dtype == np.float32 and flow.index.dtype == np.int64
    assert set(est.last_timing_s) == {"encode", "network", "fast_edges", "slow_edges"}
    assert est.last_timing_s["fast_edges"] == 0.0 and est.last_timing_s["slow_edges"] == 0.0  # no history given


def test_metadata_rebuilds_encoder(random_onnx):
    path, _, cfg = random_onnx
    est = OnnxNormalFlow(path)
    assert est.cfg == cfg
    assert json.loads(est.metadata["evseg.encoding"]) == cfg.to_dict()
    assert est.matrix.shape == cfg.matrix_shape == (cfg.n_coords, cfg.d)


def test_default_targets_are_all_events_and_deterministic(random_onnx, make_slice):
    path, _, cfg = random_onnx
    ev = make_slice(2000, (40, 30))
    est = OnnxNormalFlow(path, threads=1)
    a = est(ev, (40, 30))
    b = est(ev, (40, 30))
    np.testing.assert_array_equal(a.index, np.arange(2000))
    np.testing.assert_array_equal(a.nx, b.nx)


def test_calibration_changes_flow_only_through_distortion(random_onnx, make_slice):
    path, _, _ = random_onnx
    ev = make_slice(3000, (40, 30), seed=4)
    est = OnnxNormalFlow(path, threads=1)
    K = np.array([[40.0, 0, 20], [0, 40.0, 15], [0, 0, 1]])
    plain = est(ev, (40, 30))
    # A distortion-free calibration is the identity map: same flow up to float32 rounding of
    # the undistortion map (positions ~1e-5 px -> phases ~1e-5 rad).
    same = est(ev, (40, 30), calibration=Calibration(K, np.zeros(4), (40, 30)))
    np.testing.assert_allclose(same.nx, plain.nx, rtol=1e-3, atol=1e-2)
    dist = est(ev, (40, 30), calibration=Calibration(K, np.array([-0.3, 0.1, 0, 0]), (40, 30)))
    assert not np.allclose(dist.nx, plain.nx, rtol=1e-2)


def test_missing_or_foreign_model_raises(tmp_path):
    with pytest.raises(ModelError, match="not found"):
        OnnxNormalFlow(tmp_path / "nope.onnx")
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"not an onnx file")
    with pytest.raises(ModelError, match="cannot load"):
        OnnxNormalFlow(bad)


def test_thread_count_changes_nothing_but_rounding(random_onnx, make_slice):
    path, _, _ = random_onnx
    ev = make_slice(3000, (60, 40), seed=8)
    one = OnnxNormalFlow(path, threads=1)(ev, (60, 40))
    two = OnnxNormalFlow(path, threads=2)(ev, (60, 40))
    # Threads own column blocks whose sliding sums start at different columns: float32
    # rounding differs (~1e-6 relative), nothing else.
    np.testing.assert_allclose(one.nx, two.nx, rtol=1e-3, atol=1e-2)
    np.testing.assert_allclose(one.uncertainty, two.uncertainty, rtol=1e-3)


def test_pyramid_model_exports_and_runs_like_its_torch_head(tmp_path):
    import torch

    from evseg.export import export_onnx
    from evseg.veckm_flow import EncodingConfig, build_head

    cfg = EncodingConfig(d=8, window_px=3, seed=2, polarity=True, pyramid_levels=2)
    head = build_head(cfg, seed=0, hidden=16)
    path = export_onnx(head, cfg, tmp_path / "pyramid.onnx")
    est = OnnxNormalFlow(path, threads=1)
    assert est.cfg == cfg and est.matrix.shape == (4, 16)
    assert est.session.get_inputs()[0].shape[1] == 34
    scene = translating_edges(n_edges=6, seed=1)
    targets = select_targets(scene.events, scene.sensor_size, cell_px=3)
    K = np.array([[200.0, 0, 173], [0, 200.0, 130], [0, 0, 1]])
    cal = Calibration(K, np.array([-0.2, 0.05, 0.0, 0.0]), scene.sensor_size)
    for calibration in (None, cal):
        flow = est(scene.events, scene.sensor_size, targets, calibration=calibration)
        feats = encode_targets(scene.events, targets, scene.sensor_size, cfg, calibration=calibration)
        with torch.no_grad():
            out = head(torch.from_numpy(feats)).numpy()
        np.testing.assert_allclose(est.predict(feats), out, atol=1e-5)
        if calibration is None:  # (with one, the flow is mapped back to the sensor grid)
            nx, ny, _ = head_output_to_flow(out, cfg)
            np.testing.assert_allclose(flow.nx, nx, atol=1e-5 * cfg.flow_unit_px_s)
            np.testing.assert_allclose(flow.ny, ny, atol=1e-5 * cfg.flow_unit_px_s)


def test_the_network_runs_in_chunks_with_the_same_output(random_onnx, monkeypatch):
    from evseg.veckm_flow import inference

    path, _, cfg = random_onnx
    est = OnnxNormalFlow(path, threads=1)
    feats = np.random.default_rng(0).standard_normal((1000, cfg.n_features)).astype(np.float32)
    whole = est.predict(feats)
    monkeypatch.setattr(inference, "PREDICT_ROWS", 300)  # 4 runs, the last of 100 rows
    np.testing.assert_array_equal(est.predict(feats), whole)


def test_a_targets_flow_does_not_depend_on_the_other_targets_asked_for():
    # With the fast-edge look, a slice whose gated targets lie early in it used to move the
    # stretched slice's start for every target: a target's flow depended on which others
    # were asked for (up to 400 px/s). The shipped model, fast edges on, no context.
    S = (346, 260)
    ev = translating_edges(S, 20, 30_000, seed=0).events  # 30 ms: the stretched look keeps the last 15
    tg = select_targets(ev, S)
    est = OnnxNormalFlow()
    whole = est(ev, S, tg)
    fast = np.hypot(whole.nx, whole.ny) > est.fast_edges.speed_from * est.cfg.flow_unit_px_s
    half = ev["t"][tg] < ev["t"][-1] - 15_000
    assert (fast & half).sum() > 100 and (fast & ~half).sum() > 100  # gated targets in both halves
    for part in (tg[-200:], tg[: len(tg) // 2], tg[len(tg) // 2:], tg[::7]):
        alone = est(ev, S, part)
        at = np.searchsorted(tg, part)
        np.testing.assert_array_equal(alone.nx, whole.nx[at])
        np.testing.assert_array_equal(alone.uncertainty, whole.uncertainty[at])
