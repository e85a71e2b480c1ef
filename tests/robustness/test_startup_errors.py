"""Bad model, calibration and configuration files: `evseg segment` fails at start-up.

Contract checked for each: exit status 2, one line on stderr naming the file and the field,
nothing written (no result file, no temporary file) and an existing result left byte for byte.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from evseg.cli import main

GOOD_K = "camera_matrix: {rows: 3, cols: 3, data: [100, 0, 64, 0, 100, 48, 0, 0, 1]}\n"
SIZE = "image_width: 128\nimage_height: 96\n"
KALIBR_TWO = "".join(
    f"cam{k}: {{camera_model: pinhole, intrinsics: [100, 100, 64, 48], distortion_model: equidistant, "
    f"distortion_coeffs: [0.01, 0, 0, 0], resolution: [128, 96]}}\n" for k in (0, 1))


def _segment_fails_cleanly(capsys, tmp_path: Path, recording: Path, extra: list[str], must_name: list[str]) -> str:
    """Run `evseg segment` twice (new output, existing output); return the error line."""
    out_dir = tmp_path / "out"
    out_dir.mkdir(exist_ok=True)
    fresh = out_dir / "fresh.npz"
    existing = out_dir / "existing.npz"
    existing.write_bytes(b"an earlier result")
    for out in (fresh, existing):
        capsys.readouterr()
        rc = main(["segment", str(recording), "--out", str(out), "--flow-method", "planefit", "--no-progress", *extra])
        err = capsys.readouterr().err
        assert rc == 2, err
        lines = err.strip().splitlines()
        assert len(lines) == 1, err
        for text in must_name:
            assert text in lines[0], (text, lines[0])
    assert not fresh.exists()
    assert existing.read_bytes() == b"an earlier result"
    assert sorted(p.name for p in out_dir.iterdir()) == ["existing.npz"]  # no temporary left over
    return lines[0]


# ------------------------------------------------------------------ model files
def _model(tmp_path: Path, kind: str, random_onnx: Path) -> Path:
    p = tmp_path / f"{kind}.onnx"
    if kind == "missing":
        return p
    if kind == "empty":
        p.write_bytes(b"")
    elif kind == "garbage":
        p.write_bytes(bytes(range(256)) * 8)
    elif kind == "truncated":
        p.write_bytes(random_onnx.read_bytes()[: random_onnx.stat().st_size // 2])
    elif kind == "not an evseg model":
        import onnx
        from onnx import TensorProto, helper

        x = helper.make_tensor_value_info("x", TensorProto.FLOAT, [None, 3])
        y = helper.make_tensor_value_info("y", TensorProto.FLOAT, [None, 3])
        graph = helper.make_graph([helper.make_node("Identity", ["x"], ["y"])], "g", [x], [y])
        onnx.save(helper.make_model(graph), p)
    else:
        raise AssertionError(kind)
    return p


@pytest.mark.parametrize("kind", ["missing", "empty", "garbage", "truncated", "not an evseg model"])
def test_bad_model_file(kind, tmp_path, capsys, sim_files, random_onnx):
    _, recording, _ = sim_files
    model = _model(tmp_path, kind, random_onnx)
    line = _segment_fails_cleanly(capsys, tmp_path, recording, ["--flow-method", "learned", "--model", str(model)],
                                  [str(model)])
    if kind == "not an evseg model":
        assert "evseg.format" in line  # the metadata field that is wrong


def test_good_model_runs(tmp_path, sim_files, random_onnx):
    """Control for the test above: the same command with an intact model succeeds."""
    _, recording, _ = sim_files
    out = tmp_path / "r.npz"
    assert main(["segment", str(recording), "--out", str(out), "--model", str(random_onnx), "--threads", "1",
                 "--no-progress"]) == 0
    assert out.is_file()


# ------------------------------------------------------------------ calibration files
CALIBRATIONS = {
    # name: (YAML text, field the message must name)
    "missing image_width": ("image_height: 96\n" + GOOD_K, "image_width"),
    "missing camera_matrix": (SIZE, "camera_matrix"),
    "K with 8 numbers": (SIZE + "camera_matrix: {data: [100, 0, 64, 0, 100, 48, 0, 0]}\n", "camera_matrix"),
    "K not numbers": (SIZE + "camera_matrix: {data: [100, 0, 64, 0, 100, 48, 0, 0, x]}\n", "camera_matrix"),
    "K without data": (SIZE + "camera_matrix: {rows: 3, cols: 3}\n", "camera_matrix"),
    "zero focal length": (SIZE + "camera_matrix: {data: [0, 0, 64, 0, 100, 48, 0, 0, 1]}\n", "K"),
    "3 distortion coefficients": (SIZE + GOOD_K + "distortion_coefficients: {data: [0.1, 0, 0]}\n",
                                  "distortion_coefficients"),
    "unknown distortion model": (SIZE + GOOD_K + "distortion_model: fov\n", "distortion_model"),
    "fisheye with 5 coefficients": (SIZE + GOOD_K + "distortion_model: equidistant\n"
                                    "distortion_coefficients: {data: [0.1, 0, 0, 0, 0]}\n", "distortion_coefficients"),
    "Kalibr camchain, two cameras": (KALIBR_TWO, "--calib-camera"),
    "Kalibr camchain, no resolution": ("cam0: {camera_model: pinhole, intrinsics: [100, 100, 64, 48]}\n",
                                       "cam0.resolution"),
    "not a mapping": ("- 1\n- 2\n", "mapping"),
    "other sensor size": ("image_width: 640\nimage_height: 480\n" + GOOD_K, "image_width"),
}


@pytest.mark.parametrize("name", sorted(CALIBRATIONS))
def test_bad_calibration(name, tmp_path, capsys, sim_files):
    _, recording, _ = sim_files
    text, field = CALIBRATIONS[name]
    calib = tmp_path / "calib.yaml"
    calib.write_text(text)
    _segment_fails_cleanly(capsys, tmp_path, recording, ["--calib", str(calib)], [str(calib), field])


def test_missing_calibration_file(tmp_path, capsys, sim_files):
    _, recording, _ = sim_files
    calib = tmp_path / "nowhere.yaml"
    _segment_fails_cleanly(capsys, tmp_path, recording, ["--calib", str(calib)], [str(calib), "not found"])


def test_kalibr_camchain_camera_runs(tmp_path, capsys, sim_files):
    """Control for the two-camera case above: naming the camera makes the same command run."""
    _, recording, _ = sim_files
    calib = tmp_path / "camchain.yaml"
    calib.write_text(KALIBR_TWO)
    out = tmp_path / "r.npz"
    assert main(["segment", str(recording), "--out", str(out), "--flow-method", "planefit", "--no-progress",
                 "--calib", str(calib), "--calib-camera", "cam1"]) == 0
    assert out.is_file()
    _segment_fails_cleanly(capsys, tmp_path, recording, ["--calib-camera", "cam1"], ["--calib-camera cam1", "--calib"])


# Found by these tests and fixed in evseg/calibration.py: non-integer sizes, NaN distortion,
# multi-line YAML parser messages.
CALIBRATION_BUGS = {
    "width not a number": (SIZE.replace("128", "abc") + GOOD_K, "image_width"),
    "width a list": (SIZE.replace("128", "[1, 2]") + GOOD_K, "image_width"),
    "NaN distortion": (SIZE + GOOD_K + "distortion_coefficients: {data: [0.1, .nan, 0, 0]}\n",
                       "distortion_coefficients"),
    "broken YAML": (SIZE + "camera_matrix: {data: [1, 2\n", "YAML"),
}


@pytest.mark.parametrize("name", sorted(CALIBRATION_BUGS))
def test_bad_calibration_known_bugs(name, tmp_path, capsys, sim_files):
    _, recording, _ = sim_files
    text, field = CALIBRATION_BUGS[name]
    calib = tmp_path / "calib.yaml"
    calib.write_text(text)
    _segment_fails_cleanly(capsys, tmp_path, recording, ["--calib", str(calib)], [str(calib), field])


# ------------------------------------------------------------------ segmentation configs
CONFIGS = {
    "unknown key": ("lambda_p: 2.0\nlamda_m: 3.0\n", "lamda_m"),
    "wrong type": ("lambda_p: two\n", "lambda_p"),
    "out of range": ("truncation: -1\n", "truncation"),
    "bad choice": ("robust_loss: l1\n", "robust_loss"),
    "null": ("cell_px: null\n", "cell_px"),
    "NaN": ("lambda_m: .nan\n", "lambda_m must be a finite number, got nan"),
    "infinite": ("lambda_p: .inf\n", "lambda_p must be a finite number, got inf"),
    "a list": ("- 1\n- 2\n", "mapping"),
}


@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_bad_segmentation_config(name, tmp_path, capsys, sim_files):
    _, recording, _ = sim_files
    text, field = CONFIGS[name]
    cfg = tmp_path / "seg.yaml"
    cfg.write_text(text)
    _segment_fails_cleanly(capsys, tmp_path, recording, ["--config", str(cfg)], [str(cfg), field])


def test_unknown_preset_and_missing_config_file(tmp_path, capsys, sim_files):
    _, recording, _ = sim_files
    _segment_fails_cleanly(capsys, tmp_path, recording, ["--config", "no_such_preset"], ["no_such_preset", "presets"])
    missing = tmp_path / "missing.yaml"
    _segment_fails_cleanly(capsys, tmp_path, recording, ["--config", str(missing)], [str(missing)])


def test_broken_yaml_segmentation_config_is_one_line(tmp_path, capsys, sim_files):
    _, recording, _ = sim_files
    cfg = tmp_path / "seg.yaml"
    cfg.write_text("lambda_p: [\n")
    _segment_fails_cleanly(capsys, tmp_path, recording, ["--config", str(cfg)], [str(cfg), "YAML"])


@pytest.mark.parametrize("extra, field", [(["--window-ms", "0"], "--window-ms"),
                                          (["--stride-ms", "-5"], "--stride-ms"),
                                          (["--sensor-size", "12xx"], "12xx"),
                                          (["--flow-context-ms", "-1"], "--flow-context-ms"),
                                          (["--flow-context-ms", "nan"], "--flow-context-ms")])
def test_bad_options(extra, field, tmp_path, capsys, sim_files):
    _, recording, _ = sim_files
    _segment_fails_cleanly(capsys, tmp_path, recording, extra, [field])


def test_learned_flow_context_beyond_the_encoders_longest_slice(tmp_path, capsys, sim_files):
    # The learned flow encodes at most 2^30 us (17.9 min) per slice: refused before any work.
    _, recording, _ = sim_files
    out = tmp_path / "r.npz"
    assert main(["segment", str(recording), "--out", str(out), "--flow-context-ms", "2e6", "--no-progress"]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "--window-ms plus --flow-context-ms must be at most 1073742 ms" in lines[0]
    assert not out.exists()


# ------------------------------------------------------------------ scene presets (evseg simulate)
SCENES = {
    "unknown top-level key": ("sensr: {width: 64, height: 48}\n", "sensr"),
    "unknown nested key": ("sensor: {width: 64, heigth: 48}\n", "heigth"),
    "broken YAML": ("sensor: {width: 64\n", "YAML"),
}


@pytest.mark.parametrize("name", sorted(SCENES))
def test_bad_scene_config(name, tmp_path, capsys):
    text, field = SCENES[name]
    cfg = tmp_path / "scene.yaml"
    cfg.write_text(text)
    out = tmp_path / "sim.npz"
    rc = main(["simulate", "--config", str(cfg), "--out", str(out), "--duration", "0.01", "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and str(cfg) in err[0] and field in err[0], err
    assert not out.exists()


def test_unknown_scene_preset(tmp_path, capsys):
    from evseg.errors import ConfigError
    from evseg.simulator import load_scene_preset

    with pytest.raises(ConfigError, match="unknown scene preset 'nope'"):
        load_scene_preset("nope")
    rc = main(["simulate", "--preset", "nope", "--out", str(tmp_path / "s.npz"), "--quiet"])
    assert rc == 2 and "nope" in capsys.readouterr().err


@pytest.mark.parametrize("option", ["--config", "--calib"])
def test_a_binary_file_given_as_yaml(option, tmp_path, capsys, sim_files):
    _, recording, _ = sim_files
    binary = tmp_path / "seg.mp4.yaml"
    binary.write_bytes(bytes(range(128, 256)) * 4)
    _segment_fails_cleanly(capsys, tmp_path, recording, [option, str(binary)], [str(binary), "not a text (YAML) file"])
