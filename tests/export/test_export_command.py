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


def test_bad_opset_and_tolerance_are_refused_before_the_checkpoint_is_read(tmp_path, capsys):
    (tmp_path / "x.ckpt").write_text("never read")
    out = tmp_path / "m.onnx"
    cases = [(["--opset", "99"], "--opset 99: the ONNX exporter writes opsets 9-20 (the shipped model uses 17)"),
             (["--opset", "5"], "--opset 5: the ONNX exporter writes opsets 9-20 (the shipped model uses 17)"),
             (["--tolerance", "-1"], "--tolerance -1.0: must be a number > 0"),
             (["--tolerance", "0"], "--tolerance 0.0: must be a number > 0"),
             (["--tolerance", "nan"], "--tolerance nan: must be a number > 0")]
    for option, message in cases:
        assert main(["export", str(tmp_path / "x.ckpt"), "--out", str(out), *option]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"evseg export: error: {message}"), err
    assert not out.exists()


def test_export_onnx_refuses_an_opset_it_cannot_write(tmp_path):
    import pytest

    from evseg.errors import ConfigError
    from evseg.export import export_onnx

    cfg = EncodingConfig(d=8, window_px=3)
    with pytest.raises(ConfigError, match=r"opset 21: the ONNX exporter writes opsets 9-20"):
        export_onnx(build_head(cfg, hidden=16), cfg, tmp_path / "m.onnx", opset=21)
    assert not list(tmp_path.iterdir())


def test_non_finite_weights_are_named_as_such(tmp_path, capsys):
    import torch

    cfg = EncodingConfig(d=8, window_px=3)
    head = build_head(cfg, hidden=16)
    with torch.no_grad():
        head.out.bias[1] = float("nan")
    save_head_checkpoint(tmp_path / "nan.pt", head, cfg)
    assert main(["export", str(tmp_path / "nan.pt"), "--out", str(tmp_path / "m.onnx")]) == 2
    assert capsys.readouterr().err.strip() == (
        f"evseg export: error: {tmp_path / 'nan.pt'}: non-finite weights in the checkpoint (NaN or infinity in "
        "out.bias); its training run diverged: export an earlier checkpoint")
    assert not (tmp_path / "m.onnx").exists()


def test_errors_of_the_check_name_out_not_the_temporary_file(tmp_path, capsys, monkeypatch):
    import evseg.export
    from evseg.errors import ModelError

    def unloadable(head, cfg, path, feats):
        raise ModelError(f"{path}: onnxruntime cannot load the model (NOT_IMPLEMENTED)")

    cfg = EncodingConfig(d=8, window_px=3)
    save_head_checkpoint(tmp_path / "h.pt", build_head(cfg, hidden=16), cfg)
    monkeypatch.setattr(evseg.export, "parity", unloadable)
    assert main(["export", str(tmp_path / "h.pt"), "--out", str(tmp_path / "m.onnx")]) == 2
    assert capsys.readouterr().err.strip() == (
        f"evseg export: error: {tmp_path / 'm.onnx'}: onnxruntime cannot load the model (NOT_IMPLEMENTED)")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["h.pt"]
