"""Affine model, flow field and the normal-flow residual."""

import numpy as np

from evseg.segmentation.motion_model import (
    flow_field, linear_parameters, model_change_px_s, models_from_linear, normal_flow_of,
    normal_flow_residuals, raw_residuals,
)


def test_pure_rotation_and_translation_flow():
    # rho = 1, theta = 0 -> pure translation everywhere
    ux, uy = flow_field(np.array([[1.0, 0.0, 3.0, -2.0]]), np.array([0.0, 10.0]), np.array([5.0, -7.0]))
    np.testing.assert_allclose(ux[:, 0], [3.0, 3.0])
    np.testing.assert_allclose(uy[:, 0], [-2.0, -2.0])
    # rho R(theta) - I at (10, 0): ((cos - 1) * 10, sin * 10)
    ux, uy = flow_field(np.array([[1.0, 0.1, 0.0, 0.0]]), np.array([10.0]), np.array([0.0]))
    np.testing.assert_allclose([ux[0, 0], uy[0, 0]], [10 * (np.cos(0.1) - 1), 10 * np.sin(0.1)])


def test_linear_parameter_round_trip():
    m = np.array([[1.3, -0.4, 5.0, 6.0], [0.7, 2.0, -1.0, 0.0]])
    np.testing.assert_allclose(models_from_linear(linear_parameters(m)), m)


def test_residual_zero_for_true_model_and_normalised_form():
    rng = np.random.default_rng(0)
    models = np.array([[1.1, 0.2, 50.0, -20.0], [1.0, 0.0, -100.0, 0.0]])
    x, y = rng.uniform(-100, 100, 50), rng.uniform(-100, 100, 50)
    ang = rng.uniform(0, 2 * np.pi, 50)
    nx, ny = normal_flow_of(models, np.zeros(50, dtype=int), x, y, np.cos(ang), np.sin(ang))
    r = normal_flow_residuals(models, x, y, nx, ny)
    np.testing.assert_allclose(r[:, 0], 0.0, atol=1e-9)
    # normalised residual = raw residual / |n| (px/s)
    np.testing.assert_allclose(r, raw_residuals(models, x, y, nx, ny) / np.hypot(nx, ny)[:, None], atol=1e-9)
    # under the other model the residual is the flow difference along n_hat
    ux0, uy0 = flow_field(models[:1], x, y)
    ux1, uy1 = flow_field(models[1:], x, y)
    nh = np.column_stack([nx, ny]) / np.hypot(nx, ny)[:, None]
    np.testing.assert_allclose(r[:, 1], nh[:, 0] * (ux1 - ux0)[:, 0] + nh[:, 1] * (uy1 - uy0)[:, 0], atol=1e-9)


def test_model_change():
    a = np.array([[1.0, 0.0, 0.0, 0.0]])
    b = np.array([[1.0, 0.0, 3.0, 4.0]])
    np.testing.assert_allclose(model_change_px_s(a, b, 100.0), [5.0])
    c = np.array([[1.01, 0.0, 0.0, 0.0]])  # divergence rate 0.01 /s over 100 px = 1 px/s
    np.testing.assert_allclose(model_change_px_s(a, c, 100.0), [1.0])
