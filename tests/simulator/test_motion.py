"""Closed-form affine trajectories: flow equals the time derivative of the pose."""

import numpy as np
import pytest

from evseg.simulator.motion import AffineTrajectory, sample_trajectory
from evseg.simulator.scene import MotionConfig

# numpy 2 renamed trapz to trapezoid; the project allows numpy >= 1.24.
_trapezoid = getattr(np, "trapezoid", None) or getattr(np, "trapz")

TRAJ = AffineTrajectory(
    c0=(10.0, -4.0), v_mean=(120.0, -40.0), v_amp=(30.0, 15.0), v_hz=(2.0, 0.7), v_phase=(0.3, 1.1),
    omega_mean=0.8, omega_amp=0.3, omega_hz=1.5, omega_phase=0.2,
    zoom_mean=-0.4, zoom_amp=0.2, zoom_hz=3.0, zoom_phase=2.0, theta0=0.5, log_s0=0.1,
)


@pytest.mark.parametrize("t", [0.0, 0.137, 0.9])
def test_flow_is_the_derivative_of_the_image_position_of_layer_points(t):
    layer_pts = np.array([[0.0, 0.0], [25.0, -13.0], [-40.0, 60.0]])
    h = 1e-6

    def image(ts):
        return TRAJ.center(ts) + layer_pts @ TRAJ.linear(ts).T

    numeric = (image(t + h) - image(t - h)) / (2 * h)
    x = image(t)
    analytic = TRAJ.flow(x[:, 0], x[:, 1], t)
    # central difference with h = 1 us: truncation ~h^2 |x'''| and rounding ~1e-16 |x| / h
    np.testing.assert_allclose(analytic, numeric, atol=1e-4)


def test_integrals_of_rates_match_numerical_quadrature():
    t = np.linspace(0, 0.8, 8001)
    v = TRAJ.velocity(t)
    dx = _trapezoid(v, t, axis=0)
    np.testing.assert_allclose(TRAJ.center(0.8) - TRAJ.center(0.0), dx, rtol=1e-6)
    np.testing.assert_allclose(TRAJ.theta(0.8) - TRAJ.theta(0.0), _trapezoid(TRAJ.omega(t), t), rtol=1e-6)


def test_zero_frequency_wobble_is_a_constant_offset():
    traj = AffineTrajectory(v_mean=(1.0, 0.0), v_amp=(2.0, 0.0), v_hz=(0.0, 0.0), v_phase=(np.pi / 2, 0.0))
    np.testing.assert_allclose(traj.velocity(0.5), [3.0, 0.0])
    np.testing.assert_allclose(traj.center(0.5), [1.5, 0.0])


def test_image_to_layer_inverts_layer_to_image():
    m = TRAJ.layer_to_image(0.3, origin=(-5.0, 2.0))
    p = np.array([[3.0, 4.0], [10.0, -2.0]])
    x = p @ m[:, :2].T + m[:, 2]
    np.testing.assert_allclose(TRAJ.image_to_layer(x, 0.3), p + (-5.0, 2.0), atol=1e-9)


def test_anchored_and_parallax():
    a = TRAJ.anchored((50.0, 60.0), 0.25)
    np.testing.assert_allclose(a.center(0.25), [50.0, 60.0])
    np.testing.assert_allclose(a.velocity(0.4), TRAJ.velocity(0.4))
    p = TRAJ.with_translation_scaled(2.0)
    np.testing.assert_allclose(p.velocity(0.4), 2 * TRAJ.velocity(0.4))
    assert p.omega(0.4) == TRAJ.omega(0.4)


def test_sampled_speed_respects_the_configured_range():
    cfg = MotionConfig(speed_px_s=(100.0, 200.0), wobble=(0.0, 0.0), direction_deg=(90.0, 90.0))
    rng = np.random.default_rng(0)
    for _ in range(20):
        tr = sample_trajectory(cfg, rng)
        v = tr.velocity(np.linspace(0, 1, 11))
        np.testing.assert_allclose(v[:, 0], 0.0, atol=1e-9)  # 90 deg = straight down (+y)
        assert np.all((v[:, 1] >= 100.0) & (v[:, 1] <= 200.0))
