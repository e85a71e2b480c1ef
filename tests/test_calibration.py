import numpy as np
import pytest

from evseg.calibration import Calibration, load_calibration
from evseg.errors import CalibrationError

YAML = """image_width: 240
image_height: 180
camera_matrix:
  rows: 3
  cols: 3
  data: [199.092, 0, 132.192, 0, 198.829, 110.713, 0, 0, 1]
distortion_model: radtan
distortion_coefficients:
  rows: 1
  cols: 4
  data: [-0.3684, 0.1509, -2.96e-4, -7.59e-4]
"""


def test_load_and_undistort_roundtrip(tmp_path):
    p = tmp_path / "calib.yaml"
    p.write_text(YAML)
    cal = load_calibration(p)
    assert cal.sensor_size == (240, 180)
    # The principal point is a fixed point of radtan undistortion.
    xu, yu = cal.undistort(np.array([132.192]), np.array([110.713]))
    np.testing.assert_allclose([xu[0], yu[0]], [132.192, 110.713], atol=1e-6)
    xn, yn = cal.undistort(np.array([132.192 + 10]), np.array([110.713]), normalized=True)
    # Close to the centre distortion is tiny: 10 px / fx within 1 %.
    np.testing.assert_allclose(xn[0], 10 / 199.092, rtol=1e-2)
    assert yn[0] == pytest.approx(0, abs=1e-6)


def test_shared_emsgc_calibration(shared_data):
    cal = load_calibration(shared_data / "emsgc_reference/calib/EED/calib.yaml")
    assert cal.sensor_size == (240, 180)
    assert cal.K[0, 0] == 250


@pytest.mark.parametrize(
    "text, message",
    [
        (YAML.replace("image_width: 240\n", ""), "missing field 'image_width'"),
        (YAML.replace("data: [199.092, 0, 132.192, 0, 198.829, 110.713, 0, 0, 1]", "data: [1, 2, 3]"),
         r"'camera_matrix.data' needs 9 numbers"),
        (YAML.replace("radtan", "equidistant"), "'distortion_model' = 'equidistant' is not supported"),
        ("- just a list", "expected a mapping"),
    ],
)
def test_bad_calibration_names_file_and_field(tmp_path, text, message):
    p = tmp_path / "bad.yaml"
    p.write_text(text)
    with pytest.raises(CalibrationError, match=message) as info:
        load_calibration(p)
    assert "bad.yaml" in str(info.value)


def test_missing_calibration_file():
    with pytest.raises(CalibrationError, match="not found"):
        load_calibration("/nonexistent/calib.yaml")
