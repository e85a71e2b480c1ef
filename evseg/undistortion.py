"""Normal flow in undistorted pixel coordinates: positions and flows of the sensor grid mapped
through a camera calibration, by table lookup (the pipeline's step 2 with a calibration)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from evseg.calibration import Calibration


@dataclass(frozen=True)
class UndistortionTable:
    """Undistorted position and Jacobian of the undistortion for every pixel of the sensor.

    Built once per calibration so that per-window undistortion is a table lookup, not an
    OpenCV call per event. All arrays are (height, width) float64; ``j11 = d xu / d x``,
    ``j12 = d xu / d y``, ``j21 = d yu / d x``, ``j22 = d yu / d y`` (central differences).
    """

    xu: np.ndarray
    yu: np.ndarray
    j11: np.ndarray
    j12: np.ndarray
    j21: np.ndarray
    j22: np.ndarray

    @cached_property
    def nearest_pixel(self) -> tuple[np.ndarray, np.ndarray]:
        """``(on, flat)``: bool (height, width), whether each raw pixel's undistorted position
        rounds to a pixel of the grid, and the flat index of that pixel for those that do
        (computed once per table: :func:`mask_to_raw` runs per object and window)."""
        h, w = self.xu.shape
        xi, yi = np.rint(self.xu).astype(np.int64), np.rint(self.yu).astype(np.int64)
        on = (xi >= 0) & (xi < w) & (yi >= 0) & (yi < h)
        return on, yi[on] * w + xi[on]

    @classmethod
    def from_calibration(cls, calibration: Calibration) -> "UndistortionTable":
        xu, yu = (m.astype(np.float64) for m in calibration.undistortion_map())
        dxu_dy, dxu_dx = np.gradient(xu)
        dyu_dy, dyu_dx = np.gradient(yu)
        return cls(xu, yu, dxu_dx, dxu_dy, dyu_dx, dyu_dy)


def undistort_normal_flow(
    table: UndistortionTable, x: np.ndarray, y: np.ndarray, nx: np.ndarray, ny: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Map pixel positions (integer px) and their normal flows (px/s) to undistorted pixels.

    With J the local Jacobian of the undistortion and g the unit normal direction, the
    optical flow maps as u' = J u and the gradient direction as g' ~ J^-T g, so the normal
    flow's magnitude along g' is (u . g) / |J^-T g| = |n| / |J^-T g|: computable from n alone.

    Returns ``(xu, yu, nxu, nyu)``: float64 px and float32 px/s.
    """
    r = np.asarray(y, dtype=np.int64)
    c = np.asarray(x, dtype=np.int64)
    j11, j12, j21, j22 = table.j11[r, c], table.j12[r, c], table.j21[r, c], table.j22[r, c]
    det = j11 * j22 - j12 * j21
    mag = np.hypot(nx, ny)
    gx, gy = nx / np.maximum(mag, 1e-12), ny / np.maximum(mag, 1e-12)
    # J^-T g with J^-1 = [[j22, -j12], [-j21, j11]] / det
    hx = (j22 * gx - j21 * gy) / det
    hy = (-j12 * gx + j11 * gy) / det
    hn = np.maximum(np.hypot(hx, hy), 1e-12)
    scale = mag / hn
    return table.xu[r, c], table.yu[r, c], (scale * hx / hn).astype(np.float32), (scale * hy / hn).astype(np.float32)


def mask_to_raw(table: UndistortionTable, mask: np.ndarray) -> np.ndarray:
    """A (height, width) bool mask in undistorted pixels as a mask of the sensor's raw pixels:
    raw pixel (x, y) is set when its undistorted position (``table.xu``, ``table.yu``, rounded)
    falls on a set pixel. Undistorted positions off the grid are unset.

    >>> import numpy as np
    >>> ident = np.meshgrid(np.arange(4.0), np.arange(3.0))
    >>> table = UndistortionTable(ident[0] + 1, ident[1], *[np.ones((3, 4))] * 4)  # shifted by 1 px
    >>> m = np.zeros((3, 4), bool); m[1, 2] = True
    >>> np.argwhere(mask_to_raw(table, m)).tolist()  # raw (row 1, col 1) lands on (1, 2)
    [[1, 1]]
    """
    on, flat = table.nearest_pixel
    out = np.zeros(mask.shape, dtype=bool)
    out[on] = mask.ravel()[flat]
    return out


def raw_box(mask: np.ndarray) -> tuple[int, int, int, int] | None:
    """Inclusive (x0, y0, x1, y1) px box of a bool mask's set pixels; None if none is set."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if not len(rows):
        return None
    return int(cols[0]), int(rows[0]), int(cols[-1]), int(rows[-1])
