"""`evseg demo` end to end with ground-truth flow (the learned path is covered once a model ships)."""

from evseg.cli import main


def test_demo_oracle_writes_video_picture_and_scores(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--out-dir", str(out), "--flow-method", "oracle", "--duration", "0.05"]) == 0
    assert (out / "segmentation.mp4").stat().st_size > 10_000
    assert (out / "overlay.png").stat().st_size > 10_000
    text = capsys.readouterr().out
    # The default scene (evimo_like, seed 1234) has one object that the oracle path finds.
    line = [l for l in text.splitlines() if l.startswith("accuracy over 5 windows")][0]
    assert "detection rate 100.0 %" in line
