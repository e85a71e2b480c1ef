import numpy as np

from evseg.cli import main
from evseg.veckm_flow import EncodingConfig, OnnxNormalFlow, build_head, save_head_checkpoint


def test_evseg_export_writes_a_loadable_model(tmp_path, capsys):
    cfg = EncodingConfig(d=8, window_px=3)
    save_head_checkpoint(tmp_path / "h.pt", build_head(cfg, hidden=16), cfg)
    rc = main(["export", str(tmp_path / "h.pt"), "--out", str(tmp_path / "m.onnx"), "--note", "unit test"])
    assert rc == 0
    out = capsys.readouterr().out
    assert "parity" in out and "max |torch - onnxruntime|" in out
    est = OnnxNormalFlow(tmp_path / "m.onnx")
    assert est.cfg == cfg and est.metadata["evseg.note"] == "unit test"


def test_evseg_export_bad_checkpoint_is_a_user_error(tmp_path, capsys):
    (tmp_path / "x.ckpt").write_text("nope")
    assert main(["export", str(tmp_path / "x.ckpt"), "--out", str(tmp_path / "m.onnx")]) == 2
    assert "x.ckpt" in capsys.readouterr().err
    assert not (tmp_path / "m.onnx").exists()
