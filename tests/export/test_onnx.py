import json

import numpy as np
import pytest
import torch

from evseg.errors import ModelError
from evseg.events import EVENT_DTYPE
from evseg.export import OPSET, export_onnx, parity
from evseg.veckm_flow import EncodingConfig, build_head, encode_targets, load_head_checkpoint, save_head_checkpoint, select_targets
from evseg.veckm_flow.synthetic import translating_edges

# Parity tolerance (head units, outputs ~0.1-1): onnxruntime and torch both run float32 GEMMs
# with different summation orders; observed differences are ~1e-7, 1e-5 leaves room for other
# CPUs' kernels while still catching any wrong weight, layer or constant.
PARITY_ATOL = 1e-5


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    cfg = EncodingConfig(d=16, window_px=5, alpha=3.0, seed=11, polarity=True)
    head = build_head(cfg, seed=1, hidden=48, layers=2)
    path = tmp_path_factory.mktemp("exp") / "m.onnx"
    export_onnx(head, cfg, path, extra_metadata={"note": "test"})
    return path, head, cfg


def test_onnx_file_has_pinned_opset_dynamic_targets_and_metadata(exported):
    import onnx

    path, head, cfg = exported
    m = onnx.load(str(path))
    assert OPSET == 17
    assert [o.version for o in m.opset_import if o.domain in ("", "ai.onnx")] == [17]
    dims = m.graph.input[0].type.tensor_type.shape.dim
    assert dims[0].dim_param and dims[1].dim_value == cfg.n_features
    meta = {p.key: p.value for p in m.metadata_props}
    assert meta["evseg.format"] == "evseg-normal-flow/1" and meta["evseg.note"] == "test"
    assert np.array(json.loads(meta["evseg.matrix"])).shape == (4, 16)  # x, y, t, polarity


def test_parity_on_synthetic_events(exported):
    path, head, cfg = exported
    scene = translating_edges(n_edges=12, seed=7)
    targets = select_targets(scene.events, scene.sensor_size, cell_px=2)
    feats = encode_targets(scene.events, targets, scene.sensor_size, cfg)
    assert len(feats) > 1000
    assert parity(head, cfg, path, feats) < PARITY_ATOL


def _ecd_poster_slice(shared_data):
    z = np.load(shared_data / "ecd_poster" / "poster_translation.npz")
    a = z["events"][:40_000]  # float32 (N, 4): t [s], x, y, p (0/1)
    ev = np.empty(len(a), EVENT_DTYPE)
    t_us = np.round((a[:, 0].astype(np.float64) - float(a[0, 0])) * 1e6).astype(np.int64)
    ev["t"] = np.maximum.accumulate(t_us)  # float32 seconds: keep order despite rounding
    ev["x"], ev["y"] = a[:, 1].astype(np.uint16), a[:, 2].astype(np.uint16)
    ev["p"] = np.where(a[:, 3] > 0, 1, -1)
    return ev, (240, 180)


def test_parity_on_real_events(exported, shared_data):
    path, head, cfg = exported
    ev, sensor = _ecd_poster_slice(shared_data)
    targets = select_targets(ev, sensor, cell_px=2)
    feats = encode_targets(ev, targets, sensor, cfg)
    assert len(feats) > 1000
    assert parity(head, cfg, path, feats) < PARITY_ATOL


def test_lightning_style_checkpoint_roundtrip(tmp_path):
    cfg = EncodingConfig(d=8, window_px=3)
    head = build_head(cfg, seed=2, hidden=16, layers=1)
    ckpt = {
        "epoch": 3,
        "hyper_parameters": {"encoding": cfg.to_dict(), "head": {"hidden": 16, "layers": 1}, "lr": 1e-3},
        "state_dict": {f"head.{k}": v for k, v in head.state_dict().items()},
    }
    torch.save(ckpt, tmp_path / "run.ckpt")
    loaded, cfg2 = load_head_checkpoint(tmp_path / "run.ckpt")
    assert cfg2 == cfg
    x = torch.randn(5, cfg.n_features)
    torch.testing.assert_close(loaded(x), head(x), rtol=0, atol=0)
    save_head_checkpoint(tmp_path / "plain.pt", head, cfg)
    again, cfg3 = load_head_checkpoint(tmp_path / "plain.pt")
    assert cfg3 == cfg
    torch.testing.assert_close(again(x), head(x), rtol=0, atol=0)


def test_bad_checkpoints_name_the_problem(tmp_path):
    cfg = EncodingConfig(d=8)
    torch.save({"state_dict": {}, "hyper_parameters": {"encoding": cfg.to_dict()}}, tmp_path / "a.ckpt")
    with pytest.raises(ModelError, match="'head'"):
        load_head_checkpoint(tmp_path / "a.ckpt")
    torch.save({"encoding": cfg.to_dict(), "head": {"in_features": 99}, "state_dict": {}}, tmp_path / "b.ckpt")
    with pytest.raises(ModelError, match="in_features"):
        load_head_checkpoint(tmp_path / "b.ckpt")
    (tmp_path / "c.ckpt").write_text("garbage")
    with pytest.raises(ModelError, match="not a readable"):
        load_head_checkpoint(tmp_path / "c.ckpt")
    with pytest.raises(ModelError, match="not found"):
        load_head_checkpoint(tmp_path / "missing.ckpt")
