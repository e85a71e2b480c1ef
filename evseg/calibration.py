"""Camera calibration: pinhole intrinsics K with radtan or equidistant (fisheye) distortion,
loaded from a ROS ``camera_info`` / EMSGC YAML, a Kalibr camchain YAML or an OpenCV
``FileStorage`` YAML.

ROS ``camera_info`` layout (as EMSGC uses it)::

    image_width: 240
    image_height: 180
    camera_matrix: {rows: 3, cols: 3, data: [fx, 0, cx, 0, fy, cy, 0, 0, 1]}
    distortion_model: radtan          # or plumb_bob / rational_polynomial / equidistant / none
    distortion_coefficients: {rows: 1, cols: 4, data: [k1, k2, p1, p2]}   # 5 with k3, 8 rational

Kalibr camchain layout (``kalibr_calibrate_cameras`` output; one block per camera)::

    cam0:
      camera_model: pinhole
      intrinsics: [fu, fv, pu, pv]
      distortion_model: equidistant   # or radtan / none
      distortion_coeffs: [k1, k2, k3, k4]
      resolution: [346, 260]

OpenCV ``FileStorage`` layout (``%YAML:1.0``, as OpenCV's calibration sample writes it): the
fields of ROS ``camera_info`` with the matrices as ``!!opencv-matrix``; read with
``cv2.FileStorage``.

One-line text layout (the RPG Event Camera Dataset's ``calib.txt``)::

    fx fy cx cy k1 k2 p1 p2 k3        # or fx fy cx cy k1 k2 p1 p2, or fx fy cx cy alone

radtan distortion (none with 4 numbers); separators are spaces, tabs or commas, ``#`` starts a
comment. It holds no image size, so the recording's sensor size goes with it
(``load_calibration(path, sensor_size=(w, h))``; the CLI passes the recording's).

Distortion models: ``radtan`` (Brown-Conrady: ``[k1, k2, p1, p2(, k3)]``, or the 8
coefficients ``[k1, k2, p1, p2, k3, k4, k5, k6]`` of ROS's ``rational_polynomial``), undistorted
with ``cv2.undistortPoints``; ``equidistant`` (Kannala-Brandt, OpenCV's fisheye model:
``[k1, k2, k3, k4]``), undistorted with ``cv2.fisheye.undistortPoints``. Everything in evseg also
works without a calibration: coordinates then stay raw pixels.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from evseg.errors import CalibrationError, yaml_problem

DISTORTION_MODELS = ("radtan", "equidistant")
"""The distortion models a :class:`Calibration` can hold."""

_MODEL_NAMES = {"radtan": "radtan", "plumb_bob": "radtan", "rational_polynomial": "radtan", "none": "radtan",
                "equidistant": "equidistant", "fisheye": "equidistant"}
"""Names files use (ROS, Kalibr, OpenCV) -> the model they mean."""

_N_COEFFS = {"radtan": (0, 4, 5, 8), "equidistant": (4,)}

# cv2.undistortPoints stops after 5 iterations by default, which leaves up to 0.05 px of error
# at the corners of a DAVIS240 with k1 = -0.37; 100 iterations to 1e-12 make it exact.
_CRITERIA = (3, 100, 1e-12)  # cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, max iterations, eps


@dataclass(frozen=True)
class Calibration:
    """Pinhole intrinsics with radtan or equidistant distortion.

    Attributes:
        K: 3x3 camera matrix (px).
        D: distortion coefficients: ``[k1, k2, p1, p2(, k3)]`` or 8 rational ones for
            ``radtan``, ``[k1, k2, k3, k4]`` for ``equidistant``; empty = no distortion.
        sensor_size: ``(width, height)`` in pixels.
        model: ``'radtan'`` (default) or ``'equidistant'`` (:data:`DISTORTION_MODELS`).

    Example:
        >>> cal = Calibration(np.array([[200.0, 0, 120], [0, 200, 90], [0, 0, 1]]), np.zeros(4), (240, 180))
        >>> [round(float(v[0]), 3) for v in cal.undistort(np.array([120.0]), np.array([90.0]))]
        [120.0, 90.0]
    """

    K: np.ndarray
    D: np.ndarray
    sensor_size: tuple[int, int]
    model: str = "radtan"

    def __post_init__(self) -> None:
        if isinstance(self.model, str) and self.model.lower() in _MODEL_NAMES and self.model not in DISTORTION_MODELS:
            # plumb_bob, fisheye, ...: the names ROS, Kalibr and OpenCV write for the two models.
            if self.model.lower() == "none" and np.any(np.asarray(self.D, dtype=np.float64) != 0):
                raise CalibrationError(f"distortion model 'none' but D = {np.ravel(self.D).tolist()} is not zero")
            object.__setattr__(self, "model", _MODEL_NAMES[self.model.lower()])
        K = np.asarray(self.K, dtype=np.float64)
        D = np.asarray(self.D, dtype=np.float64).ravel()
        if K.shape != (3, 3):
            raise CalibrationError(f"camera matrix K must be 3x3, got shape {K.shape}")
        if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise CalibrationError(f"camera matrix K needs finite positive fx, fy; got {K.tolist()}")
        if K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
            # A transposed (column-major) K or one with a zero last row undistorts every event
            # wrongly without any other sign.
            raise CalibrationError(
                f"camera matrix K must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] (row-major), got {K.tolist()}")
        w, h = (int(v) for v in self.sensor_size)
        if not (0 <= K[0, 2] <= w and 0 <= K[1, 2] <= h):
            raise CalibrationError(
                f"principal point (cx, cy) = ({K[0, 2]:g}, {K[1, 2]:g}) px lies outside the {w}x{h} sensor: "
                "K of another resolution?")
        if self.model not in DISTORTION_MODELS:
            raise CalibrationError(f"distortion model must be one of {', '.join(DISTORTION_MODELS)}, got {self.model!r}")
        if len(D) not in _N_COEFFS[self.model]:
            counts = " or ".join(str(n) for n in _N_COEFFS[self.model] if n)
            raise CalibrationError(f"{self.model} distortion needs {counts} coefficients, got {len(D)}")
        if not np.all(np.isfinite(D)):
            raise CalibrationError(f"distortion coefficients contain NaN or inf: {D.tolist()}")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "D", D)

    @property
    def focal_px(self) -> float:
        """Mean focal length in pixels."""
        return float(0.5 * (self.K[0, 0] + self.K[1, 1]))

    def undistort(self, x: np.ndarray, y: np.ndarray, normalized: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Undistort pixel coordinates.

        Args:
            x, y: distorted pixel coordinates (column, row), any shape.
            normalized: return normalised camera coordinates (unit focal length, origin at the
                principal point) instead of undistorted pixels.

        Returns:
            ``(xu, yu)`` float64 arrays of the input shape: px (the camera matrix K applied to
            the undistorted rays), or normalised when asked.
        """
        import cv2

        x = np.asarray(x, dtype=np.float64)
        shape = x.shape
        pts = np.stack([x.ravel(), np.asarray(y, dtype=np.float64).ravel()], axis=-1)
        if len(pts) == 0:
            return np.empty(shape), np.empty(shape)
        pts = pts.reshape(-1, 1, 2)
        if self.model == "equidistant":
            out = cv2.fisheye.undistortPoints(pts, self.K, self.D, None, None, None, _CRITERIA)
        elif hasattr(cv2, "undistortPointsIter"):
            # OpenCV 4.x: undistortPoints takes no stopping criteria (its 5 iterations are not
            # enough); the iterated variant does. OpenCV 5 merged the two.
            out = cv2.undistortPointsIter(pts, self.K, self.D, None, None, _CRITERIA)
        else:
            out = cv2.undistortPoints(pts, self.K, self.D, None, None, None, _CRITERIA)
        out = out.reshape(-1, 2)
        if not normalized:
            out = out @ self.K[:2, :2].T + self.K[:2, 2]
        return out[:, 0].reshape(shape), out[:, 1].reshape(shape)

    def undistortion_map(self, normalized: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Undistorted coordinates of every pixel: two ``(height, width)`` float32 arrays.

        Precomputing this once turns per-event undistortion into a table lookup.
        """
        w, h = self.sensor_size
        yy, xx = np.mgrid[0:h, 0:w]
        xu, yu = self.undistort(xx, yy, normalized=normalized)
        return xu.astype(np.float32), yu.astype(np.float32)


def _field(doc: dict, key: str, path: str, prefix: str = ""):
    if key not in doc:
        raise CalibrationError(f"{path}: missing field '{prefix}{key}'")
    return doc[key]


def _numbers(val, name: str, path: str) -> np.ndarray:
    data = val.get("data") if isinstance(val, dict) else val
    if data is None:
        raise CalibrationError(f"{path}: field '{name}' has no 'data' list")
    try:
        arr = np.asarray(data, dtype=np.float64).ravel()
    except (TypeError, ValueError) as exc:
        raise CalibrationError(f"{path}: field '{name}' is not a list of numbers: {exc}") from None
    if not np.all(np.isfinite(arr)):
        raise CalibrationError(f"{path}: field '{name}' contains NaN or inf: {arr.tolist()}")
    return arr


def _positive_int(val, name: str, path: str) -> int:
    if isinstance(val, bool) or not isinstance(val, (int, float)) or val != int(val) or val <= 0:
        raise CalibrationError(f"{path}: field '{name}' must be a positive integer (px), got {val!r}")
    return int(val)


def _model(doc: dict, key: str, path: str, prefix: str) -> str:
    name = str(doc.get(key, "radtan")).lower()
    if name not in _MODEL_NAMES:
        raise CalibrationError(
            f"{path}: field '{prefix}{key}' = '{name}' is not supported "
            f"(supported: {', '.join(_MODEL_NAMES)})")
    return _MODEL_NAMES[name]


def _coefficients(D: np.ndarray, model: str, name: str, path: str, declared: str) -> np.ndarray:
    if declared == "none":
        if np.any(D != 0):
            raise CalibrationError(f"{path}: distortion model 'none' but field '{name}' = {D.tolist()} is not zero")
        return np.zeros(4)
    if model == "radtan" and len(D) == 0:
        return np.zeros(4)  # ROS: an empty D means no distortion
    if len(D) not in _N_COEFFS[model]:
        counts = " or ".join(str(n) for n in _N_COEFFS[model] if n)
        raise CalibrationError(f"{path}: field '{name}' needs {counts} numbers for {model} distortion, got {D.size}")
    return D


_KALIBR_CAMERA = re.compile(r"cam\d+$")


def _kalibr_cameras(doc: dict) -> list[str]:
    """Names of the Kalibr camera blocks (``cam0``, ``cam1``, ...) of a camchain document."""
    return [k for k, v in doc.items() if isinstance(k, str) and _KALIBR_CAMERA.match(k)
            and isinstance(v, dict) and "intrinsics" in v]


def _load_kalibr(doc: dict, path: str, camera: str | None) -> Calibration:
    names = _kalibr_cameras(doc)
    if camera is None:
        if len(names) > 1:
            raise CalibrationError(
                f"{path}: Kalibr camchain with {len(names)} cameras ({', '.join(names)}); "
                "choose one (camera='cam1', or --calib-camera cam1)")
        camera = names[0]
    elif camera not in names:
        raise CalibrationError(f"{path}: no camera '{camera}' in this Kalibr camchain (it has {', '.join(names)})")
    cam, pre = doc[camera], f"{camera}."
    kind = str(cam.get("camera_model", "pinhole")).lower()
    if kind != "pinhole":
        raise CalibrationError(f"{path}: field '{pre}camera_model' = '{kind}' is not supported (only pinhole)")
    intr = _numbers(_field(cam, "intrinsics", path, pre), pre + "intrinsics", path)
    if intr.size != 4:
        raise CalibrationError(f"{path}: field '{pre}intrinsics' needs 4 numbers [fu, fv, pu, pv], got {intr.size}")
    res = _field(cam, "resolution", path, pre)
    if not isinstance(res, (list, tuple)) or len(res) != 2:
        raise CalibrationError(f"{path}: field '{pre}resolution' must be [width, height] (px), got {res!r}")
    width, height = (_positive_int(v, pre + "resolution", path) for v in res)
    model = _model(cam, "distortion_model", path, pre)
    D = (_numbers(cam["distortion_coeffs"], pre + "distortion_coeffs", path) if "distortion_coeffs" in cam
         else np.zeros(4))
    D = _coefficients(D, model, pre + "distortion_coeffs", path, str(cam.get("distortion_model", "")).lower())
    fu, fv, pu, pv = intr
    return _checked(np.array([[fu, 0.0, pu], [0.0, fv, pv], [0.0, 0.0, 1.0]]), D, (width, height), model, path)


def _load_camera_info(doc: dict, path: str) -> Calibration:
    width = _positive_int(_field(doc, "image_width", path), "image_width", path)
    height = _positive_int(_field(doc, "image_height", path), "image_height", path)
    K = _numbers(_field(doc, "camera_matrix", path), "camera_matrix.data", path)
    if K.size != 9:
        raise CalibrationError(f"{path}: field 'camera_matrix.data' needs 9 numbers (3x3), got {K.size}")
    model = _model(doc, "distortion_model", path, "")
    D = (_numbers(doc["distortion_coefficients"], "distortion_coefficients.data", path)
         if "distortion_coefficients" in doc else np.zeros(4))
    D = _coefficients(D, model, "distortion_coefficients.data", path, str(doc.get("distortion_model", "")).lower())
    return _checked(K.reshape(3, 3), D, (width, height), model, path)


def _checked(K, D, size, model, path) -> Calibration:
    try:
        return Calibration(K, D, size, model)
    except CalibrationError as exc:
        raise CalibrationError(f"{path}: {exc}") from None


def calibration_from_camera_info(K, D, distortion_model: str, sensor_size: tuple[int, int],
                                 where: str) -> Calibration | None:
    """A :class:`Calibration` from the fields of a ROS ``sensor_msgs/CameraInfo`` message (``K``:
    9 numbers, ``D``, ``distortion_model``), or None when ``K`` is all zeros: what camera
    drivers publish for a camera that was never calibrated. ``where`` prefixes errors."""
    K = _numbers(list(K), "K", where)
    if K.size != 9:
        raise CalibrationError(f"{where}: field 'K' needs 9 numbers (3x3), got {K.size}")
    if not np.any(K):
        return None
    doc = {"distortion_model": distortion_model or "radtan"}
    model = _model(doc, "distortion_model", where, "")
    D = _coefficients(_numbers(list(D), "D", where), model, "D", where, str(doc["distortion_model"]).lower())
    return _checked(K.reshape(3, 3), D, tuple(int(v) for v in sensor_size), model, where)


def _is_opencv_filestorage(path: str) -> bool:
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError:
        return False  # the YAML loader reports it
    # Older OpenCV writes "%YAML:1.0" (not YAML), newer "%YAML 1.2" with !!opencv-matrix tags.
    return head.lstrip().startswith(b"%YAML:") or b"!!opencv-matrix" in head


def _read_opencv_filestorage(path: str) -> dict:
    """The ROS camera_info fields of an OpenCV FileStorage YAML, as plain Python values."""
    import cv2

    try:
        fs = cv2.FileStorage(path, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_FORMAT_YAML)
    except cv2.error as exc:
        raise CalibrationError(f"{path}: not a readable OpenCV FileStorage YAML ({str(exc).strip()})") from None
    try:
        if not fs.isOpened():
            raise CalibrationError(f"{path}: not a readable OpenCV FileStorage YAML")
        doc: dict = {}
        for key in ("image_width", "image_height", "camera_matrix", "distortion_coefficients", "distortion_model"):
            node = fs.getNode(key)
            if node.empty() or node.isNone():
                continue
            if node.isMap():  # !!opencv-matrix
                mat = node.mat()
                if mat is None:
                    raise CalibrationError(f"{path}: field '{key}' is not a matrix")
                doc[key] = {"data": np.asarray(mat, dtype=np.float64).ravel().tolist()}
            elif node.isSeq():
                doc[key] = [node.at(i).real() for i in range(node.size())]
            elif node.isString():
                doc[key] = node.string()
            else:
                value = node.real()
                doc[key] = int(value) if key.startswith("image_") and value == int(value) else value
        return doc
    finally:
        fs.release()


_TEXT_COUNTS = {4: "fx fy cx cy", 8: "fx fy cx cy k1 k2 p1 p2", 9: "fx fy cx cy k1 k2 p1 p2 k3"}


def _text_calibration_numbers(path: str) -> list[str] | None:
    """The fields of a one-line text calibration (ECD's ``calib.txt``), or None when the file
    is not one (a YAML layout, unreadable, several lines, words that are not numbers)."""
    try:
        with open(path, "rb") as f:
            head = f.read(4097)
    except OSError:
        return None  # the YAML loader reports it
    if len(head) > 4096:
        return None
    try:
        text = head.decode("utf-8-sig")
    except UnicodeDecodeError:
        return None
    lines = [line.split("#", 1)[0].strip() for line in text.splitlines()]
    lines = [line for line in lines if line]
    if len(lines) != 1:
        return None
    fields = [f for f in re.split(r"[\s,]+", lines[0]) if f]
    try:
        [float(f) for f in fields]
    except ValueError:
        return None
    return fields


def needs_sensor_size(path: str | Path) -> bool:
    """True when the calibration file's layout holds no image size (the one-line text layout of
    ECD's ``calib.txt``): :func:`load_calibration` then needs ``sensor_size``."""
    return _text_calibration_numbers(str(path)) is not None


def _load_text(fields: list[str], path: str, sensor_size) -> Calibration:
    if len(fields) not in _TEXT_COUNTS:
        raise CalibrationError(
            f"{path}: a one-line text calibration holds {len(fields)} numbers; expected "
            + ", ".join(f"{n} ({names})" for n, names in _TEXT_COUNTS.items()))
    if sensor_size is None:
        raise CalibrationError(
            f"{path}: a one-line text calibration (fx fy cx cy k1 k2 p1 p2 k3, as ECD's calib.txt) holds no image "
            "size: give the sensor size too (load_calibration(path, sensor_size=(width, height)); on the command "
            "line --sensor-size WxH, unless the recording stores its size)")
    from evseg.events import checked_sensor_size

    from evseg.errors import EventDataError

    try:
        size = checked_sensor_size(sensor_size)
    except EventDataError as exc:
        raise CalibrationError(f"{path}: {exc}") from None
    fx, fy, cx, cy, *D = (float(f) for f in fields)
    if not all(np.isfinite(v) for v in (fx, fy, cx, cy, *D)):
        raise CalibrationError(f"{path}: the calibration line contains NaN or inf: {' '.join(fields)}")
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return _checked(K, np.asarray(D) if D else np.zeros(4), size, "radtan", path)


def load_calibration(path: str | Path, camera: str | None = None,
                     sensor_size: tuple[int, int] | None = None) -> Calibration:
    """Load a calibration file: ROS ``camera_info`` / EMSGC style YAML, a Kalibr camchain, an
    OpenCV ``FileStorage`` file of the camera_info fields, or ECD's one-line ``calib.txt``.

    Args:
        path: the file (layouts in the module docstring; the layout is recognised from its
            contents, not its name).
        camera: which camera block of a Kalibr camchain (``'cam0'``, ``'cam1'``, ...); needed
            only when the camchain holds several cameras.
        sensor_size: ``(width, height)`` in px, for a layout that holds no image size (the
            one-line text layout, :func:`needs_sensor_size`); the layouts that hold one ignore
            it (callers compare the two: :class:`~evseg.pipeline.MotionSegmentationPipeline`
            refuses a calibration of another size).

    Raises :class:`CalibrationError` naming the file and field when something is missing or
    has the wrong number of entries.

    Example (ECD's ``calib.txt`` of the DAVIS240C):
        >>> import tempfile, os
        >>> path = os.path.join(tempfile.mkdtemp(), "calib.txt")
        >>> _ = open(path, "w").write("199.092 198.829 132.192 110.713 -0.368 0.151 -0.0003 -0.0008 0\\n")
        >>> cal = load_calibration(path, sensor_size=(240, 180))
        >>> cal.K[0].tolist(), cal.D.size, cal.sensor_size
        ([199.092, 0.0, 132.192], 5, (240, 180))
    """
    import yaml

    path = str(path)
    fields = _text_calibration_numbers(path)
    if fields is not None:
        if camera is not None:
            raise CalibrationError(f"{path}: camera '{camera}' asked for, but the file is a single-camera "
                                   "one-line text calibration, not a Kalibr camchain")
        return _load_text(fields, path, sensor_size)
    if _is_opencv_filestorage(path):
        doc = _read_opencv_filestorage(path)
        if camera is not None:
            raise CalibrationError(f"{path}: camera '{camera}' asked for, but the file is a single-camera "
                                   "OpenCV FileStorage calibration, not a Kalibr camchain")
        return _load_camera_info(doc, path)
    try:
        with open(path) as f:
            doc = yaml.safe_load(f)
    except FileNotFoundError:
        raise CalibrationError(f"{path}: calibration file not found") from None
    except UnicodeDecodeError:
        raise CalibrationError(f"{path}: not a text (YAML) file") from None
    except OSError as exc:
        raise CalibrationError(f"{path}: cannot read calibration file ({exc.strerror or exc})") from None
    except yaml.YAMLError as exc:
        raise CalibrationError(f"{path}: {yaml_problem(exc)}") from None
    if not isinstance(doc, dict):
        raise CalibrationError(
            f"{path}: expected a mapping of calibration fields, got {type(doc).__name__}; the layouts read are ROS "
            "camera_info (image_width, image_height, camera_matrix, distortion_model, distortion_coefficients), "
            "a Kalibr camchain (cam0: intrinsics, resolution, ...), OpenCV FileStorage YAML and a one-line "
            "'fx fy cx cy k1 k2 p1 p2 k3' (ECD's calib.txt)")
    blocks = [k for k, v in doc.items() if isinstance(k, str) and _KALIBR_CAMERA.match(k) and isinstance(v, dict)]
    if blocks and not _kalibr_cameras(doc):
        raise CalibrationError(f"{path}: Kalibr camchain block '{blocks[0]}' has no field 'intrinsics' "
                               "([fu, fv, pu, pv])")
    if _kalibr_cameras(doc):
        return _load_kalibr(doc, path, camera)
    if camera is not None:
        raise CalibrationError(f"{path}: camera '{camera}' asked for, but the file is a single-camera "
                               "ROS camera_info calibration, not a Kalibr camchain")
    return _load_camera_info(doc, path)
