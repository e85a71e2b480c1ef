"""Classical normal flow: local plane fit of the time surface (method.md section 2).

The time surface of a slice holds the latest timestamp of each pixel. Around each target event
a plane ``t = a dx + b dy + c`` is fitted by least squares to the surface pixels of the
``(2r+1)^2`` window whose timestamps lie within ``max_dt_us`` of the target's time, then refitted
once without the pixels far off the first plane (as in Benosman et al.'s local plane fits);
``g = (a, b)`` (s/px) is the surface gradient and the normal flow is ``n = g / |g|^2`` (px/s).
Rejected fits (too few pixels, residual too large, flat surface) get NaN flow and infinite
uncertainty. The uncertainty of an accepted fit is the standard error of the gradient's
direction (radians) from the least-squares covariance, the same unit the learned model uses.

The fit is done in raw pixel coordinates, so the flow is directly in px/s of the sensor grid;
a calibration is accepted for interface parity but not needed: the distortion is locally linear
over a 7x7 window, and the normal flow of the sensor grid is what is reported.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from evseg.checks import is_int, is_whole
from evseg.events import checked_sensor_size, validate_events
from evseg.veckm_flow.result import NormalFlow

if TYPE_CHECKING:  # pragma: no cover
    from evseg.calibration import Calibration


def time_surface(events: np.ndarray, sensor_size: tuple[int, int]) -> np.ndarray:
    """Latest timestamp (us) per pixel of a slice: int64 ``(H, W)``, -1 where no event."""
    # The compiled kernel writes per pixel without bounds checks: an event off the sensor
    # (or a swapped width and height) would corrupt memory rather than fail.
    w, h = checked_sensor_size(sensor_size)
    validate_events(events, (w, h), source="time_surface events", check_sorted=False)
    return _latest_times(events, w, h)


def _latest_times(events: np.ndarray, w: int, h: int) -> np.ndarray:
    """:func:`time_surface` of events already checked to lie on the ``w`` x ``h`` sensor."""
    from evseg.veckm_flow import _kernels

    pix = events["y"].astype(np.int64) * w + events["x"].astype(np.int64)
    last = _kernels.latest_per_cell(pix, w * h)
    ts = np.full(w * h, -1, np.int64)
    hit = last >= 0
    ts[hit] = events["t"][last[hit]]
    return ts.reshape(h, w)


def plane_fit_normal_flow(
    events: np.ndarray,
    targets: np.ndarray,
    sensor_size: tuple[int, int],
    radius_px: int = 3,
    min_points: int = 8,
    max_dt_us: int | None = None,
    max_rms_px: float = 2.0,
    min_grad_s_px: float = 1e-6,
    refit_rounds: int = 1,
    outlier_factor: float = 2.0,
    min_outlier_us: float = 200.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Plane-fit normal flow of the targets of one slice.

    Args:
        events: :data:`~evseg.events.EVENT_DTYPE` ``(N,)`` sorted by ``t`` (us).
        targets: int ``(T,)`` positions in ``events``; None: every event.
        sensor_size: ``(width, height)`` px.
        radius_px: window half-width ``r``, px.
        min_points: fewer valid surface pixels -> rejected.
        max_dt_us: surface pixels further than this from the target's time are ignored
            (None: all of the slice).
        max_rms_px: fits whose residual RMS, converted to an edge position error
            (``rms_s * |n|``, px), exceeds this are rejected: a scale-free rule, since slow
            edges have large time residuals for the same geometric misfit.
        min_grad_s_px: gradients below this (s/px, i.e. faster than 1e6 px/s) are rejected.
        refit_rounds: times the plane is refitted after dropping pixels whose residual exceeds
            ``max(outlier_factor * RMS, min_outlier_us)`` (robustness where edges cross).

    Returns:
        ``(nx, ny, uncertainty)`` float32 ``(T,)``: px/s, angular standard error (rad); NaN /
        inf where rejected.
    """
    from evseg.errors import ConfigError
    from evseg.veckm_flow.encoding import _validate_targets

    w, h = checked_sensor_size(sensor_size)
    validate_events(events, (w, h), source="plane-fit normal flow events")
    targets = _validate_targets(np.arange(len(events)) if targets is None else targets, len(events))
    if not is_whole(radius_px) or radius_px < 1:
        raise ConfigError(f"plane_fit_normal_flow: radius_px must be an integer >= 1, got {radius_px!r}")
    r = int(radius_px)
    ts = np.pad(_latest_times(events, w, h), r, constant_values=-1)
    tx = events["x"][targets].astype(np.int64)
    ty = events["y"][targets].astype(np.int64)
    tt = events["t"][targets].astype(np.int64)
    dy, dx = np.mgrid[-r : r + 1, -r : r + 1]
    dx = dx.ravel().astype(np.float64)
    dy = dy.ravel().astype(np.float64)
    # (T, K) surface values around each target (padded indices: +r).
    win = ts[(ty[:, None] + r + dy.astype(np.int64)), (tx[:, None] + r + dx.astype(np.int64))]
    valid = win >= 0
    if max_dt_us is not None:
        valid &= np.abs(win - tt[:, None]) <= max_dt_us
    tau = np.where(valid, (win - tt[:, None]) * 1e-6, 0.0)  # s, relative to the target
    X = np.stack([np.broadcast_to(dx, win.shape), np.broadcast_to(dy, win.shape), np.ones(win.shape)], -1)
    for round_ in range(refit_rounds + 1):
        coef, XtX, n, ok = _weighted_plane(X, tau, valid, min_points)
        resid = np.where(valid, tau - np.einsum("tki,ti->tk", X, coef), 0.0)
        sigma2 = (resid**2).sum(1) / np.maximum(n - 3, 1)  # s^2
        if round_ < refit_rounds:
            # Drop pixels off the plane (another edge, a stale pixel) and fit again; the floor
            # keeps timestamp jitter of a clean plane from being called an outlier.
            thr = np.maximum(outlier_factor * np.sqrt(sigma2), min_outlier_us * 1e-6)
            valid = valid & (np.abs(resid) <= thr[:, None])
    a, b = coef[:, 0], coef[:, 1]
    g2 = a * a + b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        ok &= np.sqrt(sigma2) / np.sqrt(g2) <= max_rms_px  # rms (s) * |n| (px/s)
    ok &= np.sqrt(g2) >= min_grad_s_px
    cov = np.linalg.inv(XtX) * sigma2[:, None, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        var_theta = (a * a * cov[:, 1, 1] + b * b * cov[:, 0, 0] - 2 * a * b * cov[:, 0, 1]) / (g2 * g2)
        nx = np.where(ok, a / g2, np.nan)
        ny = np.where(ok, b / g2, np.nan)
    unc = np.where(ok, np.sqrt(np.maximum(var_theta, 0.0)), np.inf)
    return nx.astype(np.float32), ny.astype(np.float32), unc.astype(np.float32)


def _weighted_plane(X: np.ndarray, tau: np.ndarray, valid: np.ndarray, min_points: int):
    """Least-squares plane per target over its valid pixels: ``(coef (T, 3), XtX (T, 3, 3),
    n (T,), ok (T,))``; targets with too few pixels or a singular system get ``ok = False``
    (and an identity system so that the batch solve stays well-posed)."""
    wv = valid.astype(np.float64)
    n = wv.sum(1)
    XtX = np.einsum("tk,tki,tkj->tij", wv, X, X)
    Xty = np.einsum("tk,tki,tk->ti", wv, X, tau)
    ok = n >= max(min_points, 4)
    XtX[~ok] = np.eye(3)
    ok &= np.abs(np.linalg.det(XtX)) > 1e-9
    XtX[~ok] = np.eye(3)
    coef = np.linalg.solve(XtX, Xty[..., None])[..., 0]
    return coef, XtX, n, ok


@dataclass(frozen=True)
class PlaneFitNormalFlow:
    """Plane-fit normal flow estimator with the interface of ``OnnxNormalFlow``.

    Attributes: see :func:`plane_fit_normal_flow`.
    """

    radius_px: int = 3
    min_points: int = 8
    max_dt_us: int | None = None
    max_rms_px: float = 2.0
    refit_rounds: int = 1

    def __post_init__(self) -> None:
        from evseg.errors import ConfigError

        # radius 0 fits no plane (every flow NaN, silently); a negative one indexes backwards.
        for name, least in (("radius_px", 1), ("min_points", 4), ("refit_rounds", 0)):
            value = getattr(self, name)
            if not is_int(value) or value < least:
                raise ConfigError(f"PlaneFitNormalFlow.{name} must be an integer >= {least}, got {value!r}")
        if self.max_dt_us is not None and not (is_int(self.max_dt_us) and self.max_dt_us > 0):
            raise ConfigError(f"PlaneFitNormalFlow.max_dt_us must be a positive integer (us) or None, "
                              f"got {self.max_dt_us!r}")
        if not self.max_rms_px > 0:
            raise ConfigError(f"PlaneFitNormalFlow.max_rms_px must be positive (px), got {self.max_rms_px!r}")

    def __call__(
        self,
        events: np.ndarray,
        sensor_size: tuple[int, int],
        targets: np.ndarray | None = None,
        calibration: "Calibration | None" = None,
    ) -> NormalFlow:
        """Normal flow of ``targets`` (default: every event) of the slice ``events``."""
        # plane_fit_normal_flow checks the events and the targets, once.
        nx, ny, unc = plane_fit_normal_flow(
            events, targets, sensor_size, self.radius_px, self.min_points, self.max_dt_us, self.max_rms_px,
            refit_rounds=self.refit_rounds,
        )
        index = np.arange(len(events), dtype=np.int64) if targets is None else np.asarray(targets, dtype=np.int64)
        return NormalFlow(index, nx, ny, unc)
