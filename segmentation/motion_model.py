"""The 4-parameter affine motion model and the normal-flow constraint residual.

Model (paper Eq. 3-5): a label's flow field is

    u(x) = (rho R(theta) - I) x + t,     x measured in px from a fixed origin,

with u in px/s. We fit velocities, so the transform is "per second": the linear part
A = rho R(theta) - I = [[a, -b], [b, a]] has a = rho cos(theta) - 1, the divergence rate
(1/s; a > 0 = expansion, an object approaching), and b = rho sin(theta), the rotation rate
(rad/s for small rates); t = (t_x, t_y) is the flow at the origin in px/s. rho = 1, theta = 0
is a pure translation. A model is a row (rho, theta, t_x, t_y) of a (L, 4) float array.

Residual (normal-flow constraint, Eq. 2): n^T u(x) - |n|^2 = 0 for the true flow. We use the
|n|-normalised form

    r = n^T u(x) / |n| - |n|  =  n_hat . u(x) - |n|          (px/s),

the error of the model's flow along the gradient direction. The raw form weighs each node by
|n| (fast edges dominate and the residual's unit is px^2/s^2); the normalised one has the unit
of the flow, so one residual scale sigma in px/s fits slow and fast parts of a scene alike.
"""

from __future__ import annotations

import numpy as np


def linear_parameters(models: np.ndarray) -> np.ndarray:
    """(L, 4) (rho, theta, t_x, t_y) -> (L, 4) (a, b, t_x, t_y) with a = rho cos - 1, b = rho sin."""
    m = np.asarray(models, dtype=np.float64)
    rho, theta = m[:, 0], m[:, 1]
    return np.column_stack([rho * np.cos(theta) - 1.0, rho * np.sin(theta), m[:, 2], m[:, 3]])


def models_from_linear(q: np.ndarray) -> np.ndarray:
    """Inverse of :func:`linear_parameters`: (L, 4) (a, b, t_x, t_y) -> (rho, theta, t_x, t_y)."""
    q = np.asarray(q, dtype=np.float64)
    rho = np.hypot(q[:, 0] + 1.0, q[:, 1])
    theta = np.arctan2(q[:, 1], q[:, 0] + 1.0)
    return np.column_stack([rho, theta, q[:, 2], q[:, 3]])


def flow_field(models: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Flow of every model at every point.

    Args:
        models: (L, 4) (rho, theta, t_x, t_y). x, y: (N,) px relative to the model origin.
    Returns:
        (ux, uy), each (N, L), px/s.
    """
    q = linear_parameters(models)
    x = np.asarray(x, dtype=np.float64)[:, None]
    y = np.asarray(y, dtype=np.float64)[:, None]
    ux = q[:, 0] * x - q[:, 1] * y + q[:, 2]
    uy = q[:, 1] * x + q[:, 0] * y + q[:, 3]
    return ux, uy


def normal_flow_residuals(
    models: np.ndarray, x: np.ndarray, y: np.ndarray, nx: np.ndarray, ny: np.ndarray
) -> np.ndarray:
    """Normalised residual r = n_hat . u(x) - |n| of every node under every model.

    Args:
        models: (L, 4). x, y: (N,) px from the origin. nx, ny: (N,) normal flow px/s, |n| > 0.
    Returns:
        (N, L) residuals in px/s.
    """
    nx = np.asarray(nx, dtype=np.float64)
    ny = np.asarray(ny, dtype=np.float64)
    norm = np.hypot(nx, ny)
    ux, uy = flow_field(models, x, y)
    return (nx / norm)[:, None] * ux + (ny / norm)[:, None] * uy - norm[:, None]


def residual_jacobian(
    x: np.ndarray, y: np.ndarray, nx: np.ndarray, ny: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The normalised residual as a linear function of q = (a, b, t_x, t_y) (see
    :func:`linear_parameters`): r = J q - |n|.

    Args:
        x, y: (N,) px from the origin. nx, ny: (N,) normal flow px/s, |n| > 0.
    Returns:
        ``(J, norm)``: J (N, 4) rows [n_hat . (x, y), n_hat . (-y, x), n_hat_x, n_hat_y]
        (px, px, 1, 1) and |n| (N,) px/s.
    """
    x, y, nx, ny = (np.asarray(a, dtype=np.float64) for a in (x, y, nx, ny))
    norm = np.hypot(nx, ny)
    hx, hy = nx / norm, ny / norm
    return np.column_stack([hx * x + hy * y, hy * x - hx * y, hx, hy]), norm


def raw_residuals(
    models: np.ndarray, x: np.ndarray, y: np.ndarray, nx: np.ndarray, ny: np.ndarray
) -> np.ndarray:
    """Paper's raw form n^T u(x) - |n|^2, (N, L) in px^2/s^2 (kept for reference and tests)."""
    nx = np.asarray(nx, dtype=np.float64)
    ny = np.asarray(ny, dtype=np.float64)
    ux, uy = flow_field(models, x, y)
    return nx[:, None] * ux + ny[:, None] * uy - (nx * nx + ny * ny)[:, None]


def normal_flow_of(models: np.ndarray, label: np.ndarray, x: np.ndarray, y: np.ndarray,
                   gx: np.ndarray, gy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Normal flow that model ``models[label]`` induces at (x, y) for unit gradients (gx, gy).

    n = (u . g) g, (N,) each, px/s. Used to synthesise test data and by the initialization.
    """
    q = linear_parameters(models)[np.asarray(label)]
    ux = q[:, 0] * x - q[:, 1] * y + q[:, 2]
    uy = q[:, 1] * x + q[:, 0] * y + q[:, 3]
    s = ux * gx + uy * gy
    return s * gx, s * gy


def model_change_px_s(old: np.ndarray, new: np.ndarray, radius_px: float) -> np.ndarray:
    """Largest change of the flow field (px/s) within ``radius_px`` of the origin, per model.

    |delta t| + radius * |delta A|_2 bounds the change of u over the disc; (L,) from (L, 4) each.
    """
    dq = linear_parameters(new) - linear_parameters(old)
    return np.hypot(dq[:, 2], dq[:, 3]) + radius_px * np.hypot(dq[:, 0], dq[:, 1])
