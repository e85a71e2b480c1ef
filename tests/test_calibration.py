import numpy as np
import pytest

from evseg.calibration import Calibration, load_calibration, needs_sensor_size
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
        (YAML.replace("radtan", "fov"), "'distortion_model' = 'fov' is not supported"),
        (YAML.replace("radtan", "equidistant").replace("cols: 4\n  data: [", "cols: 5\n  data: [0.01, "),
         r"'distortion_coefficients.data' needs 4 numbers for equidistant distortion, got 5"),
        (YAML.replace("radtan", "none"), r"distortion model 'none' but field 'distortion_coefficients.data'"),
        # A column-major K (as numpy's .T or MATLAB's K(:) write it) puts cx, cy in the last row.
        (YAML.replace("data: [199.092, 0, 132.192, 0, 198.829, 110.713, 0, 0, 1]",
                      "data: [199.092, 0, 0, 0, 198.829, 0, 132.192, 110.713, 1]"),
         r"K must be \[\[fx, s, cx\], \[0, fy, cy\], \[0, 0, 1\]\] \(row-major\)"),
        (YAML.replace("data: [199.092, 0, 132.192, 0, 198.829, 110.713, 0, 0, 1]",
                      "data: [199.092, 0, 132.192, 0, 198.829, 110.713, 0, 0, 0]"), r"\(row-major\)"),
        (YAML.replace("data: [199.092, 0, 132.192, 0, 198.829, 110.713, 0, 0, 1]",
                      "data: [199.092, 0, 640, 0, 198.829, 110.713, 0, 0, 1]"),
         r"principal point \(cx, cy\) = \(640, 110.713\) px lies outside the 240x180 sensor"),
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


K_DAVIS240 = np.array([[199.092, 0, 132.192], [0, 198.829, 110.713], [0, 0, 1]])


def _rays_inside(K, distort, size):
    """Undistorted normalised rays of a grid, their distorted pixels, kept where they land on
    the sensor: (truth px (N, 2), distorted px (N, 2))."""
    xs, ys = np.meshgrid(np.linspace(-0.9, 0.9, 37), np.linspace(-0.7, 0.7, 29))
    rays = np.stack([xs.ravel(), ys.ravel()], axis=1)
    px = distort(rays)
    inside = (px[:, 0] >= 0) & (px[:, 0] <= size[0] - 1) & (px[:, 1] >= 0) & (px[:, 1] <= size[1] - 1)
    truth = rays @ K[:2, :2].T + K[:2, 2]
    return truth[inside], px[inside]


def test_radtan_undistortion_inverts_the_distortion_to_a_micro_pixel():
    """OpenCV's default 5 iterations leave up to 0.05 px of error at this DAVIS240's corners
    (k1 = -0.37); the calibration iterates to convergence. Tolerance 1e-6 px: what the
    iteration's 1e-12 stop reaches, with room for float round-off."""
    import cv2

    D = np.array([-0.3684, 0.1509, -2.96e-4, -7.59e-4])
    cal = Calibration(K_DAVIS240, D, (240, 180))

    def distort(rays):
        obj = np.column_stack([rays, np.ones(len(rays))])
        return cv2.projectPoints(obj, np.zeros(3), np.zeros(3), K_DAVIS240, D)[0].reshape(-1, 2)

    truth, px = _rays_inside(K_DAVIS240, distort, cal.sensor_size)
    assert len(px) > 500
    xu, yu = cal.undistort(px[:, 0], px[:, 1])
    np.testing.assert_allclose(np.column_stack([xu, yu]), truth, atol=1e-6)


def test_equidistant_undistortion_inverts_the_fisheye_distortion():
    """Kannala-Brandt coefficients of a wide-angle lens: undistortion inverts
    cv2.fisheye.distortPoints (tolerance 1e-6 px, as above), and reading the same numbers as
    radtan would place the corner pixels pixels away (the model is really used)."""
    import cv2

    D = np.array([-0.04, 0.012, -0.006, 0.001])
    cal = Calibration(K_DAVIS240, D, (240, 180), model="equidistant")

    def distort(rays):
        return cv2.fisheye.distortPoints(rays.reshape(-1, 1, 2), K_DAVIS240, D).reshape(-1, 2)

    truth, px = _rays_inside(K_DAVIS240, distort, cal.sensor_size)
    xu, yu = cal.undistort(px[:, 0], px[:, 1])
    np.testing.assert_allclose(np.column_stack([xu, yu]), truth, atol=1e-6)
    xr, yr = Calibration(K_DAVIS240, D, (240, 180)).undistort(px[:, 0], px[:, 1])
    assert np.max(np.hypot(xr - truth[:, 0], yr - truth[:, 1])) > 1.0
    xn, yn = cal.undistort(px[:, 0], px[:, 1], normalized=True)
    np.testing.assert_allclose(xn * K_DAVIS240[0, 0] + K_DAVIS240[0, 2], xu, atol=1e-9)


def test_calibration_rejects_a_wrong_model_or_coefficient_count():
    with pytest.raises(CalibrationError, match="one of radtan, equidistant, got 'kb8'"):
        Calibration(K_DAVIS240, np.zeros(4), (240, 180), model="kb8")
    with pytest.raises(CalibrationError, match="equidistant distortion needs 4 coefficients, got 5"):
        Calibration(K_DAVIS240, np.zeros(5), (240, 180), model="equidistant")


def test_ros_equidistant_and_rational_polynomial_files(tmp_path):
    p = tmp_path / "fisheye.yaml"
    p.write_text(YAML.replace("radtan", "equidistant"))
    cal = load_calibration(p)
    assert cal.model == "equidistant"
    np.testing.assert_array_equal(cal.D, [-0.3684, 0.1509, -2.96e-4, -7.59e-4])
    p.write_text(YAML.replace("radtan", "rational_polynomial").replace(
        "cols: 4\n  data: [", "cols: 8\n  data: [0.01, 0.0, 0.0, 0.0, "))
    cal = load_calibration(p)
    assert cal.model == "radtan" and len(cal.D) == 8
    with pytest.raises(CalibrationError, match="camera 'cam1' asked for, but the file is a single-camera"):
        load_calibration(p, camera="cam1")


KALIBR = """cam0:
  cam_overlaps: [1]
  camera_model: pinhole
  distortion_coeffs: [-0.04, 0.012, -0.006, 0.001]
  distortion_model: equidistant
  intrinsics: [320.5, 321.25, 172.0, 131.5]
  resolution: [346, 260]
  rostopic: /davis/left/events
cam1:
  T_cn_cnm1:
  - [1.0, 0.0, 0.0, -0.1]
  - [0.0, 1.0, 0.0, 0.0]
  - [0.0, 0.0, 1.0, 0.0]
  - [0.0, 0.0, 0.0, 1.0]
  camera_model: pinhole
  distortion_coeffs: [-0.3, 0.09, 0.0001, -0.0002]
  distortion_model: radtan
  intrinsics: [330.0, 331.0, 170.0, 130.0]
  resolution: [346, 260]
  rostopic: /davis/right/events
"""


def test_kalibr_camchain_picks_the_named_camera(tmp_path):
    p = tmp_path / "camchain.yaml"
    p.write_text(KALIBR)
    with pytest.raises(CalibrationError, match=r"2 cameras \(cam0, cam1\); choose one") as info:
        load_calibration(p)
    assert "--calib-camera" in str(info.value) and "camchain.yaml" in str(info.value)
    left = load_calibration(p, camera="cam0")
    assert left.model == "equidistant" and left.sensor_size == (346, 260)
    np.testing.assert_array_equal(left.K, [[320.5, 0, 172.0], [0, 321.25, 131.5], [0, 0, 1]])
    np.testing.assert_array_equal(left.D, [-0.04, 0.012, -0.006, 0.001])
    right = load_calibration(p, camera="cam1")
    assert right.model == "radtan" and right.K[0, 0] == 330.0
    with pytest.raises(CalibrationError, match="no camera 'cam2' in this Kalibr camchain"):
        load_calibration(p, camera="cam2")
    # A camchain of one camera needs no name.
    p.write_text(KALIBR.split("cam1:")[0])
    assert load_calibration(p).model == "equidistant"


@pytest.mark.parametrize(
    "edit, message",
    [
        (("camera_model: pinhole", "camera_model: omni"), r"'cam0.camera_model' = 'omni' is not supported"),
        (("resolution: [346, 260]", "resolution: 346"), r"'cam0.resolution' must be \[width, height\]"),
        (("intrinsics: [320.5, 321.25, 172.0, 131.5]", "intrinsics: [320.5, 172.0, 131.5]"),
         r"'cam0.intrinsics' needs 4 numbers"),
        (("distortion_model: equidistant", "distortion_model: fov"), r"'cam0.distortion_model' = 'fov'"),
        (("distortion_coeffs: [-0.04, 0.012, -0.006, 0.001]", "distortion_coeffs: [-0.04, 0.012]"),
         r"'cam0.distortion_coeffs' needs 4 numbers for equidistant"),
    ],
)
def test_bad_kalibr_camchain_names_file_and_field(tmp_path, edit, message):
    p = tmp_path / "bad.yaml"
    p.write_text(KALIBR.split("cam1:")[0].replace(*edit))
    with pytest.raises(CalibrationError, match=message) as info:
        load_calibration(p)
    assert "bad.yaml" in str(info.value)


def test_file_names_of_the_distortion_models_and_an_empty_d():
    cal = Calibration(K_DAVIS240, [0.1, 0.01, 0.0, 0.0], (240, 180), model="fisheye")
    assert cal.model == "equidistant"
    assert Calibration(K_DAVIS240, np.zeros(5), (240, 180), model="plumb_bob").model == "radtan"
    assert Calibration(K_DAVIS240, [], (240, 180), model="none").model == "radtan"
    with pytest.raises(CalibrationError, match="distortion model 'none' but D"):
        Calibration(K_DAVIS240, [0.1, 0, 0, 0], (240, 180), model="none")


def test_an_empty_distortion_list_means_none(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text(YAML.replace("cols: 4\n  data: [", "cols: 0\n  data: []  # ").replace("radtan", "plumb_bob"))
    assert not np.any(load_calibration(p).D)


@pytest.mark.parametrize("header", ["%YAML:1.0\n", "%YAML 1.2\n---\n"])
def test_opencv_filestorage_yaml(tmp_path, header):
    # What cv2.FileStorage writes (old and new headers) for OpenCV's calibration sample fields.
    p = tmp_path / "ocv.yaml"
    p.write_text(header + "image_width: 240\nimage_height: 180\ncamera_matrix: !!opencv-matrix\n   rows: 3\n"
                 "   cols: 3\n   dt: d\n   data: [ 199., 0., 120., 0., 199., 90., 0., 0., 1. ]\n"
                 "distortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n"
                 "   data: [ -0.3, 0.1, 0., 0., 0. ]\navg_reprojection_error: 0.2\n")
    cal = load_calibration(p)
    assert cal.sensor_size == (240, 180) and cal.model == "radtan"
    np.testing.assert_array_equal(cal.K, [[199, 0, 120], [0, 199, 90], [0, 0, 1]])
    np.testing.assert_array_equal(cal.D, [-0.3, 0.1, 0, 0, 0])


@pytest.mark.parametrize("text, message", [
    ("just some words\n", r"expected a mapping of calibration fields, got str; the layouts read"),
    ("cam0:\n  resolution: [240, 180]\n", r"Kalibr camchain block 'cam0' has no field 'intrinsics'"),
])
def test_other_layouts_say_which_layouts_are_read(tmp_path, text, message):
    p = tmp_path / "calib.txt"
    p.write_text(text)
    with pytest.raises(CalibrationError, match=message):
        load_calibration(p)


def test_ecd_one_line_text_calibration(tmp_path):
    # ECD's calib.txt of the DAVIS240C: fx fy cx cy k1 k2 p1 p2 k3, one line, no image size.
    p = tmp_path / "calib.txt"
    p.write_text("199.092 198.829 132.192 110.713 -0.368436311798 0.150947243557 -0.000296130534385 "
                 "-0.000759431726241 0.0\n")
    assert needs_sensor_size(p) and not needs_sensor_size(tmp_path / "missing.txt")
    cal = load_calibration(p, sensor_size=(240, 180))
    np.testing.assert_array_equal(cal.K, [[199.092, 0, 132.192], [0, 198.829, 110.713], [0, 0, 1]])
    np.testing.assert_array_equal(cal.D, [-0.368436311798, 0.150947243557, -0.000296130534385,
                                          -0.000759431726241, 0.0])
    assert cal.model == "radtan" and cal.sensor_size == (240, 180)
    # The same numbers as a ROS camera_info YAML undistort alike.
    yaml_cal = load_calibration(_write(tmp_path / "c.yaml", YAML))
    x, y = np.array([5.0, 230.0]), np.array([7.0, 170.0])
    np.testing.assert_allclose(cal.undistort(x, y), yaml_cal.undistort(x, y), atol=0.05)  # D differs in digits
    # Commas, a comment line and 4 numbers (no distortion) are read too.
    q = _write(tmp_path / "k.txt", "# fx fy cx cy\n200, 200, 120, 90\n")
    assert not np.any(load_calibration(q, sensor_size=(240, 180)).D)


@pytest.mark.parametrize("text, size, message", [
    ("199 199 120 90 -0.3 0.1 0 0 0\n", None, r"calib.txt: a one-line text calibration .* holds no image size: "
     r"give the sensor size too"),
    ("199 199 120 90 -0.3 0.1\n", (240, 180), r"holds 6 numbers; expected 4 \(fx fy cx cy\), 8 .*, 9"),
    ("199 199 300 90\n", (240, 180), r"calib.txt: principal point .* outside the 240x180 sensor"),
    ("199 199 120 90\n", (240.5, 180), r"calib.txt: sensor_size must be \(width, height\) in whole pixels"),
    ("199 nan 120 90\n", (240, 180), r"calib.txt: the calibration line contains NaN or inf"),
])
def test_bad_one_line_text_calibration_names_the_problem(tmp_path, text, size, message):
    with pytest.raises(CalibrationError, match=message):
        load_calibration(_write(tmp_path / "calib.txt", text), sensor_size=size)


def _write(path, text):
    path.write_text(text)
    return path
