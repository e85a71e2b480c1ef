"""Affine motion of a layer over time, in closed form (the source of ground-truth flow).

A layer point with layer coordinates X (px, origin at the layer's anchor) appears in the image at

    x(t) = c(t) + s(t) R(theta(t)) X,        R(theta) = [[cos, -sin], [sin, cos]]

(x = column, y = row, row down). With rates v = dc/dt (px/s), omega = dtheta/dt (rad/s) and
z = d(log s)/dt (1/s), the image velocity (optical flow) of the layer at image point x is

    u(x, t) = v(t) + z(t) (x - c(t)) + omega(t) J (x - c(t)),     J = [[0, -1], [1, 0]],

the 4-parameter affine model of the paper (rho' = z, theta' = omega about c(t)). Each rate is
``mean + amp * sin(2 pi f t + phase)``, whose integral is exact, so poses and flows at any time
are analytic: no finite differences anywhere in the ground truth.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from evseg.simulator.scene import MotionConfig


def _rate(mean, amp, hz, phase, t_s):
    """mean + amp * sin(2 pi hz t + phase); broadcasts over t_s (s)."""
    return mean + amp * np.sin(2 * np.pi * hz * t_s + phase)


def _integral(mean, amp, hz, phase, t_s):
    """Integral from 0 to t_s of :func:`_rate` (exact; hz = 0 means a constant amp sin(phase))."""
    w = 2 * np.pi * np.asarray(hz, np.float64)
    safe = np.where(w == 0, 1.0, w)
    osc = np.where(w == 0, amp * np.sin(phase) * t_s, amp / safe * (np.cos(phase) - np.cos(w * t_s + phase)))
    return mean * t_s + osc


@dataclass(frozen=True)
class AffineTrajectory:
    """Closed-form pose and velocity of a layer (see module docstring).

    Attributes:
        c0: image position (px) of the layer anchor at t = 0, ``(x, y)``.
        v_mean, v_amp, v_hz, v_phase: translation rate per axis ``(x, y)``, px/s, Hz, rad.
        omega_mean, omega_amp, omega_hz, omega_phase: rotation rate (rad/s).
        zoom_mean, zoom_amp, zoom_hz, zoom_phase: zoom rate d(log s)/dt (1/s).
        theta0: rotation at t = 0 (rad); log_s0: log scale at t = 0.
    """

    c0: tuple[float, float] = (0.0, 0.0)
    v_mean: tuple[float, float] = (0.0, 0.0)
    v_amp: tuple[float, float] = (0.0, 0.0)
    v_hz: tuple[float, float] = (1.0, 1.0)
    v_phase: tuple[float, float] = (0.0, 0.0)
    omega_mean: float = 0.0
    omega_amp: float = 0.0
    omega_hz: float = 1.0
    omega_phase: float = 0.0
    zoom_mean: float = 0.0
    zoom_amp: float = 0.0
    zoom_hz: float = 1.0
    zoom_phase: float = 0.0
    theta0: float = 0.0
    log_s0: float = 0.0

    # -- pose ------------------------------------------------------------------------------
    def center(self, t_s) -> np.ndarray:
        """Anchor position c(t) in px, shape (..., 2) for t_s of shape (...)."""
        t = np.asarray(t_s, np.float64)[..., None]
        return np.asarray(self.c0) + _integral(
            np.asarray(self.v_mean), np.asarray(self.v_amp), np.asarray(self.v_hz), np.asarray(self.v_phase), t
        )

    def velocity(self, t_s) -> np.ndarray:
        """Anchor velocity dc/dt in px/s, shape (..., 2)."""
        t = np.asarray(t_s, np.float64)[..., None]
        return _rate(np.asarray(self.v_mean), np.asarray(self.v_amp), np.asarray(self.v_hz), np.asarray(self.v_phase), t)

    def theta(self, t_s) -> np.ndarray:
        return self.theta0 + _integral(self.omega_mean, self.omega_amp, self.omega_hz, self.omega_phase, np.asarray(t_s, np.float64))

    def omega(self, t_s) -> np.ndarray:
        return _rate(self.omega_mean, self.omega_amp, self.omega_hz, self.omega_phase, np.asarray(t_s, np.float64))

    def log_scale(self, t_s) -> np.ndarray:
        return self.log_s0 + _integral(self.zoom_mean, self.zoom_amp, self.zoom_hz, self.zoom_phase, np.asarray(t_s, np.float64))

    def zoom(self, t_s) -> np.ndarray:
        return _rate(self.zoom_mean, self.zoom_amp, self.zoom_hz, self.zoom_phase, np.asarray(t_s, np.float64))

    def linear(self, t_s: float) -> np.ndarray:
        """The 2x2 matrix s(t) R(theta(t)) at one time."""
        s = float(np.exp(self.log_scale(t_s)))
        th = float(self.theta(t_s))
        return s * np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])

    def layer_to_image(self, t_s: float, origin: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
        """2x3 forward affine matrix mapping a texture pixel P (whose layer coordinates are
        ``P + origin``) to image px at time t_s: ``x = c + sR (P + origin)``."""
        a = self.linear(t_s)
        c = self.center(t_s)
        return np.hstack([a, (c + a @ np.asarray(origin, np.float64))[:, None]])

    def image_to_layer(self, xy: np.ndarray, t_s: float) -> np.ndarray:
        """Layer coordinates X of image points ``xy`` (N, 2) at time t_s."""
        a = self.linear(t_s)
        return (np.asarray(xy, np.float64) - self.center(t_s)) @ np.linalg.inv(a).T

    # -- flow ------------------------------------------------------------------------------
    def flow(self, x, y, t_s) -> np.ndarray:
        """Optical flow u (px/s) of this layer at image points (x, y) (px) and times t_s (s);
        all three broadcast; returns float64 (..., 2) with u[..., 0] along x (columns)."""
        x, y, t = np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(y, np.float64), np.asarray(t_s, np.float64))
        c = self.center(t)
        v = self.velocity(t)
        z = self.zoom(t)
        w = self.omega(t)
        rx, ry = x - c[..., 0], y - c[..., 1]
        return np.stack([v[..., 0] + z * rx - w * ry, v[..., 1] + z * ry + w * rx], -1)

    def max_speed(self, corners_xy: np.ndarray, t_s: np.ndarray) -> float:
        """Largest |u| (px/s) over image points ``corners_xy`` (M, 2) and times t_s (T,).

        The flow is affine in x, so over a convex region its maximum is at a corner."""
        u = self.flow(corners_xy[None, :, 0], corners_xy[None, :, 1], np.asarray(t_s)[:, None])
        return float(np.max(np.hypot(u[..., 0], u[..., 1]))) if u.size else 0.0

    def with_translation_scaled(self, factor: float) -> "AffineTrajectory":
        """Same rotation and zoom, translation rates times ``factor`` (parallax of a nearer
        layer under camera translation)."""
        return replace(
            self,
            v_mean=tuple(factor * np.asarray(self.v_mean)),
            v_amp=tuple(factor * np.asarray(self.v_amp)),
        )

    def anchored(self, point_xy: tuple[float, float], t_s: float) -> "AffineTrajectory":
        """Same rates, anchor moved so that c(t_s) = point_xy."""
        shift = np.asarray(point_xy, np.float64) - self.center(t_s)
        return replace(self, c0=tuple(np.asarray(self.c0) + shift))


def sample_trajectory(cfg: MotionConfig, rng: np.random.Generator, c0=(0.0, 0.0), theta0: float = 0.0) -> AffineTrajectory:
    """Draw a smooth random trajectory from the ranges of ``cfg`` (px/s, deg/s, 1/s)."""
    u = lambda r: float(r[0]) if r[1] == r[0] else float(rng.uniform(*r))  # noqa: E731
    speed = u(cfg.speed_px_s)
    direction = np.deg2rad(u(cfg.direction_deg))
    wob = u(cfg.wobble)
    v_mean = speed * np.array([np.cos(direction), np.sin(direction)])
    v_amp = wob * speed * rng.uniform(-1, 1, 2)
    omega = np.deg2rad(u(cfg.rotation_deg_s)) * (1 if rng.random() < 0.5 else -1)
    zoom = u(cfg.zoom_per_s)
    hz = [u(cfg.wobble_hz) for _ in range(4)]
    ph = rng.uniform(0, 2 * np.pi, 4)
    return AffineTrajectory(
        c0=(float(c0[0]), float(c0[1])),
        v_mean=(float(v_mean[0]), float(v_mean[1])),
        v_amp=(float(v_amp[0]), float(v_amp[1])),
        v_hz=(hz[0], hz[1]),
        v_phase=(float(ph[0]), float(ph[1])),
        omega_mean=omega,
        omega_amp=float(wob * abs(omega) * rng.uniform(-1, 1)),
        omega_hz=hz[2],
        omega_phase=float(ph[2]),
        zoom_mean=zoom,
        zoom_amp=float(wob * abs(zoom) * rng.uniform(-1, 1)),
        zoom_hz=hz[3],
        zoom_phase=float(ph[3]),
        theta0=float(theta0),
    )
