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


def test_a_failed_parity_check_leaves_the_model_at_out_as_it_was(tmp_path, capsys, monkeypatch):
    import evseg.export

    cfg = EncodingConfig(d=8, window_px=3)
    save_head_checkpoint(tmp_path / "h.pt", build_head(cfg, hidden=16), cfg)
    (tmp_path / "m.onnx").write_bytes(b"the model of yesterday")
    monkeypatch.setattr(evseg.export, "parity", lambda *a, **k: 1.0)
    assert main(["export", str(tmp_path / "h.pt"), "--out", str(tmp_path / "m.onnx")]) == 2
    assert "onnxruntime differs from torch by 1 (> --tolerance 0.0001); nothing written" in capsys.readouterr().err
    assert (tmp_path / "m.onnx").read_bytes() == b"the model of yesterday"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["h.pt", "m.onnx"]  # no temporary left


def test_the_output_may_not_be_the_checkpoint_or_another_format(tmp_path, capsys):
    cfg = EncodingConfig(d=8, window_px=3)
    save_head_checkpoint(tmp_path / "h.pt", build_head(cfg, hidden=16), cfg)
    before = (tmp_path / "h.pt").read_bytes()
    assert main(["export", str(tmp_path / "h.pt"), "--out", str(tmp_path / "h.pt")]) == 2
    assert "--out" in capsys.readouterr().err  # .pt is no .onnx: refused before the checkpoint is read
    assert main(["export", str(tmp_path / "h.pt"), "--out", str(tmp_path / "m.txt")]) == 2
    assert "the file must end in .onnx" in capsys.readouterr().err
    assert (tmp_path / "h.pt").read_bytes() == before
