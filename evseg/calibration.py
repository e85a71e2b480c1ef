"""Camera calibration: intrinsics K and radtan distortion, loaded from ROS/EMSGC YAML.

The YAML layout is the one of ROS ``camera_info`` files as used by EMSGC::

    image_width: 240
    image_height: 180
    camera_matrix: {rows: 3, cols: 3, data: [fx, 0, cx, 0, fy, cy, 0, 0, 1]}
    distortion_model: radtan          # also accepted: plumb_bob (the ROS name)
    distortion_coefficients: {rows: 1, cols: 4, data: [k1, k2, p1, p2]}   # or 5 with k3

Undistortion uses OpenCV (``cv2.undistortPoints``). Everything in evseg also works without a
calibration: coordinates then stay raw pixels.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from evseg.errors import CalibrationError, yaml_problem



@dataclass(frozen=True)
class Calibration:
    """Pinhole intrinsics with radtan distortion.

    Attributes:
        K: 3x3 camera matrix (px).
        D: distortion coefficients ``[k1, k2, p1, p2(, k3)]`` (radtan / plumb_bob).
        sensor_size: ``(width, height)`` in pixels.
    """

    K: np.ndarray
    D: np.ndarray
    sensor_size: tuple[int, int]

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=np.float64)
        D = np.asarray(self.D, dtype=np.float64).ravel()
        if K.shape != (3, 3):
            raise CalibrationError(f"camera matrix K must be 3x3, got shape {K.shape}")
        if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise CalibrationError(f"camera matrix K needs finite positive fx, fy; got {K.tolist()}")
        if len(D) not in (0, 4, 5, 8):
            raise CalibrationError(f"radtan distortion needs 4 or 5 coefficients, got {len(D)}")
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
            ``(xu, yu)`` float64 arrays of the input shape: px, or normalised when asked.
        """
        import cv2

        x = np.asarray(x, dtype=np.float64)
        shape = x.shape
        pts = np.stack([x.ravel(), np.asarray(y, dtype=np.float64).ravel()], axis=-1)
        if len(pts) == 0:
            return np.empty(shape), np.empty(shape)
        P = None if normalized else self.K
        out = cv2.undistortPoints(pts.reshape(-1, 1, 2), self.K, self.D, P=P).reshape(-1, 2)
        return out[:, 0].reshape(shape), out[:, 1].reshape(shape)

    def undistortion_map(self, normalized: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Undistorted coordinates of every pixel: two ``(height, width)`` float32 arrays.

        Precomputing this once turns per-event undistortion into a table lookup.
        """
        w, h = self.sensor_size
        yy, xx = np.mgrid[0:h, 0:w]
        xu, yu = self.undistort(xx, yy, normalized=normalized)
        return xu.astype(np.float32), yu.astype(np.float32)


def _field(doc: dict, key: str, path: str):
    if key not in doc:
        raise CalibrationError(f"{path}: missing field '{key}'")
    return doc[key]


def _matrix_data(doc: dict, key: str, path: str) -> np.ndarray:
    val = _field(doc, key, path)
    data = val.get("data") if isinstance(val, dict) else val
    if data is None:
        raise CalibrationError(f"{path}: field '{key}' has no 'data' list")
    try:
        arr = np.asarray(data, dtype=np.float64).ravel()
    except (TypeError, ValueError) as exc:
        raise CalibrationError(f"{path}: field '{key}.data' is not a list of numbers: {exc}") from None
    return arr


def _positive_int(doc: dict, key: str, path: str) -> int:
    val = _field(doc, key, path)
    if isinstance(val, bool) or not isinstance(val, (int, float)) or val != int(val) or val <= 0:
        raise CalibrationError(f"{path}: field '{key}' must be a positive integer (px), got {val!r}")
    return int(val)


def load_calibration(path: str | Path) -> Calibration:
    """Load a ROS ``camera_info`` / EMSGC style calibration YAML.

    Raises :class:`CalibrationError` naming the file and field when something is missing or
    has the wrong number of entries.
    """
    import yaml

    path = str(path)
    try:
        with open(path) as f:
            doc = yaml.safe_load(f)
    except FileNotFoundError:
        raise CalibrationError(f"{path}: calibration file not found") from None
    except yaml.YAMLError as exc:
        raise CalibrationError(f"{path}: {yaml_problem(exc)}") from None
    if not isinstance(doc, dict):
        raise CalibrationError(f"{path}: expected a mapping of calibration fields, got {type(doc).__name__}")
    width = _positive_int(doc, "image_width", path)
    height = _positive_int(doc, "image_height", path)
    K = _matrix_data(doc, "camera_matrix", path)
    if K.size != 9:
        raise CalibrationError(f"{path}: field 'camera_matrix.data' needs 9 numbers (3x3), got {K.size}")
    model = str(doc.get("distortion_model", "radtan")).lower()
    if model not in ("radtan", "plumb_bob", "none"):
        raise CalibrationError(
            f"{path}: field 'distortion_model' = '{model}' is not supported (use radtan/plumb_bob)"
        )
    D = _matrix_data(doc, "distortion_coefficients", path) if "distortion_coefficients" in doc else np.zeros(4)
    for name, arr in (("camera_matrix", K), ("distortion_coefficients", D)):
        if not np.all(np.isfinite(arr)):
            raise CalibrationError(f"{path}: field '{name}.data' contains NaN or inf: {arr.tolist()}")
    if D.size not in (4, 5, 8):
        raise CalibrationError(
            f"{path}: field 'distortion_coefficients.data' needs 4 or 5 numbers, got {D.size}"
        )
    try:
        return Calibration(K.reshape(3, 3), D, (width, height))
    except CalibrationError as exc:
        raise CalibrationError(f"{path}: {exc}") from None
