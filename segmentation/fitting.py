"""Batched fitting of affine motion models to labelled normal flow (torch, all labels at once).

Two fitters, both over every label in one batch (no Python loop over labels):

* :func:`fit_linear` - paper Eq. 8-9. Each node gives a row
  [n_x x, n_x y, n_x, n_y x, n_y y, n_y] m = |n|^2; we divide the row and the right side by |n|
  (the normalised residual, see :mod:`.motion_model`), accumulate the weighted normal equations
  A^T W A (L, 6, 6) and A^T W b (L, 6) per label with ``index_add_``, and solve all L systems
  in one batched call. A small ridge keeps degenerate labels (fewer than 6 nodes, all flows
  parallel) solvable: the unobservable directions go to zero (rho = 1, theta = 0, t = 0 along
  them). rho and theta are read back with Eq. 9 (atan2 instead of arcsin, equal for
  |theta| < pi/2 and defined everywhere).
* :func:`fit_lm` - Levenberg-Marquardt on the 4 parameters (rho, theta, t_x, t_y) of every
  label at once, with IRLS weights for a robust loss. The residual is linear in
  q = (a, b, t_x, t_y) (a = rho cos - 1, b = rho sin), so the per-node Jacobian rows
  J_q = [n_hat . x, n_hat . (-y, x), n_hat_x, n_hat_y] are constant: we accumulate per label
  H_q = J_q^T W J_q (L, 4, 4) and g_q = J_q^T W r, and apply the chain rule
  T = dq/d(rho, theta, t) at the label level (H = T^T H_q T, g = T^T g_q), which makes an LM
  iteration a handful of tensor ops whatever the node count. Each label keeps its own damping
  and accepts a step only when its robust cost decreases.

All computations are float64 (the systems are tiny; float32 loses the rotation rate at
positions ~500 px from the origin). Inputs are numpy arrays and are never modified.
"""

from __future__ import annotations

import functools

import numpy as np
import torch

from evseg.segmentation._kernels import lm_setup, lm_steps

LOSSES = ("none", "huber", "cauchy", "truncated")

FIT_THREADS = 1
"""torch intra-op threads while fitting. The systems are tiny (a few thousand nodes, 4-6
parameters): with more threads every op pays a thread-pool wake-up, and on a loaded 2-core
machine torch's spinning workers made one window's fitting 70x slower (2 s instead of 28 ms)."""


def _fit_threads(fn):
    """Run ``fn`` with :data:`FIT_THREADS` torch threads in ``torch.inference_mode`` and
    restore the caller's thread setting."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        before = torch.get_num_threads()
        if before != FIT_THREADS:
            torch.set_num_threads(FIT_THREADS)
        try:
            # inference_mode: no autograd bookkeeping on the ~20 small tensor ops of an LM
            # iteration (same floats; the captured fits of the 1 M events/s benchmark stream took
            # 1.08 instead of 1.18 ms each).
            with torch.inference_mode():
                return fn(*args, **kwargs)
        finally:
            if before != FIT_THREADS:
                torch.set_num_threads(before)

    return wrapper


def _t(a) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float64))


def _valid(labels: np.ndarray, n_labels: int) -> np.ndarray:
    labels = np.asarray(labels, dtype=np.int64)
    return (labels >= 0) & (labels < n_labels)


@_fit_threads
def fit_linear(
    x: np.ndarray,
    y: np.ndarray,
    nx: np.ndarray,
    ny: np.ndarray,
    labels: np.ndarray,
    n_labels: int,
    weights: np.ndarray | None = None,
    ridge: float = 1e-9,
) -> np.ndarray:
    """Linear least-squares affine model per label (paper Eq. 8-9), batched.

    Args:
        x, y: (M,) node positions, px from the model origin. nx, ny: (M,) normal flow, px/s.
        labels: (M,) int label of each node; labels outside [0, n_labels) are ignored.
        weights: (M,) non-negative node weights, or None for ones.
        ridge: Tikhonov weight relative to the mean diagonal of each label's system.
    Returns:
        (n_labels, 4) float64 models (rho, theta, t_x, t_y); labels without nodes get the
        identity model (1, 0, 0, 0).
    """
    keep = _valid(labels, n_labels)
    lab = torch.from_numpy(np.asarray(labels, dtype=np.int64)[keep])
    xs, ys, nxs, nys = (np.asarray(a, dtype=np.float64)[keep] for a in (x, y, nx, ny))
    w = np.ones(len(xs)) if weights is None else np.asarray(weights, dtype=np.float64)[keep]
    # Scale coordinates so the 6 columns have comparable size (conditioning).
    s = max(1.0, float(np.sqrt(np.mean(xs * xs + ys * ys)))) if len(xs) else 1.0
    norm = np.hypot(nxs, nys)
    X, Y, NX, NY, N, W = (_t(a) for a in (xs / s, ys / s, nxs / norm, nys / norm, norm, w))
    A = torch.stack([NX * X, NX * Y, NX, NY * X, NY * Y, NY], dim=1)  # (M, 6)
    AW = A * W[:, None]
    AtA = torch.zeros(n_labels, 36, dtype=torch.float64).index_add_(
        0, lab, (AW[:, :, None] * A[:, None, :]).reshape(-1, 36)).reshape(n_labels, 6, 6)
    Atb = torch.zeros(n_labels, 6, dtype=torch.float64).index_add_(0, lab, AW * N[:, None])
    diag = torch.diagonal(AtA, dim1=1, dim2=2)
    reg = ridge * diag.mean(dim=1) + 1e-12
    m = torch.linalg.solve(AtA + reg[:, None, None] * torch.eye(6, dtype=torch.float64), Atb)
    m = m.numpy()
    m1, m2, m4, m5 = m[:, 0] / s, m[:, 1] / s, m[:, 3] / s, m[:, 4] / s
    # Eq. 9: project the general affine onto the similarity (rho R - I) part.
    c = (m1 + m5) / 2.0 + 1.0
    sn = (m4 - m2) / 2.0
    return np.column_stack([np.hypot(c, sn), np.arctan2(sn, c), m[:, 2], m[:, 5]])


def _robust(z: torch.Tensor, loss: str, trunc: float) -> tuple[torch.Tensor, torch.Tensor]:
    """IRLS weight and cost rho(z) of residuals z in units of the loss scale."""
    z2 = z * z
    if loss == "none":
        return torch.ones_like(z), z2
    if loss == "huber":
        a = z.abs()
        return torch.clamp(1.0 / a.clamp_min(1e-12), max=1.0), torch.where(a <= 1.0, z2, 2.0 * a - 1.0)
    if loss == "cauchy":
        return 1.0 / (1.0 + z2), torch.log1p(z2)
    if loss == "truncated":
        inl = z2 <= trunc * trunc
        return inl.to(z.dtype), torch.clamp(z2, max=trunc * trunc)
    raise ValueError(f"unknown robust loss {loss!r}; one of {LOSSES}")


def _q_of(p: np.ndarray) -> np.ndarray:
    """(L, 4) linear parameters q = (rho cos theta - 1, rho sin theta, t_x, t_y) of models p."""
    q = np.empty((len(p), 4))  # not column_stack: its checks cost more than the math here
    q[:, 0] = p[:, 0] * np.cos(p[:, 1]) - 1.0
    q[:, 1] = p[:, 0] * np.sin(p[:, 1])
    q[:, 2:] = p[:, 2:]
    return q


@_fit_threads
def fit_lm(
    x: np.ndarray,
    y: np.ndarray,
    nx: np.ndarray,
    ny: np.ndarray,
    labels: np.ndarray,
    models: np.ndarray,
    weights: np.ndarray | None = None,
    loss: str = "cauchy",
    loss_scale_px_s: float = 1.0,
    truncation: float = 3.0,
    iterations: int = 6,
    damping: float = 1e-3,
    step_tol: float = 1e-5,
    affine_prior_px: float = 0.0,
) -> np.ndarray:
    """Levenberg-Marquardt refinement of (rho, theta, t_x, t_y) for every label at once.

    Minimises per label sum_k w_k rho(r_k / loss_scale) with r the normalised residual (px/s)
    and rho the robust loss ('none' = squares; 'huber', 'cauchy'; 'truncated' = squares capped
    at ``truncation``^2), by IRLS-weighted LM steps.

    Args:
        x, y: (M,) px from the model origin. nx, ny: (M,) normal flow px/s.
        labels: (M,) int; entries outside [0, L) are ignored.
        models: (L, 4) start models (rho, theta, t_x, t_y).
        weights: (M,) node weights or None.
        iterations: maximum LM iterations; stops early when every step is below ``step_tol``
            (relative to the parameter size).
        affine_prior_px: r0 >= 0, px. Adds W_l r0^2 (a^2 + b^2) / loss_scale^2 to each label's
            cost (W_l its total node weight; a = rho cos - 1, b = rho sin): the divergence and
            rotation rates are charged as if every node had an extra residual |(a, b)| r0, the
            flow difference they make over r0 px. A label spread over far more than r0 px
            (the background) hardly notices; a small object, whose few noisy flows an affine
            model would otherwise "explain" with a wild zoom (rho = 8 on a 30 px ball), stays
            close to a translation. 0 = plain robust fit.
    Returns:
        (L, 4) float64 refined models; labels with no nodes keep their start model.
    """
    if loss not in LOSSES:
        raise ValueError(f"unknown robust loss {loss!r}; one of {LOSSES}")
    p = np.array(models, dtype=np.float64).reshape(-1, 4)
    n_labels = p.shape[0]
    labels = np.ascontiguousarray(labels, dtype=np.int64)
    f64 = lambda a: np.ascontiguousarray(a, dtype=np.float64)  # noqa: E731
    lengths = {name: len(np.asarray(a)) for name, a in (("x", x), ("y", y), ("nx", nx), ("ny", ny))}
    if weights is not None:
        lengths["weights"] = len(np.asarray(weights))
    if any(n != len(labels) for n in lengths.values()):  # the compiled pass does not check bounds
        raise ValueError(f"fit_lm: {len(labels)} labels but lengths {lengths}")
    # The per-node arrays of the labels in [0, L) in one compiled pass (the rows of
    # motion_model.residual_jacobian, their outer products and the label indicator; ~0.3 ms of
    # numpy and torch calls per fit).
    lab_np, jq, jj, norm, w0, indicator = lm_setup(
        labels, n_labels, f64(x), f64(y), f64(nx), f64(ny), np.ones(len(labels)) if weights is None else f64(weights))
    if len(lab_np) == 0:  # no label or no node with a label
        return p.copy()
    lab = torch.from_numpy(lab_np)
    Jq, JJ = torch.from_numpy(jq), torch.from_numpy(jj)  # (M, 4): r = Jq q - |n|, linear in q
    N, W0 = torch.from_numpy(norm), torch.from_numpy(w0)
    lab_col = lab[:, None]
    # Per-label sums as (L, M) @ (M, k) products with the label indicator instead of
    # index_add_: for the few labels and thousands of nodes of a window, fitting went from 9.3
    # to 8.7 ms per window on the 1 M ev/s benchmark stream (identical labels).
    onehot = torch.from_numpy(indicator)
    inv_scale = 1.0 / float(loss_scale_px_s)
    # Prior weight per label (IRLS units: squared px/s residuals), and in cost units.
    kappa = float(affine_prior_px) ** 2 * np.bincount(lab_np, weights=w0, minlength=n_labels)
    kappa_cost = kappa * inv_scale * inv_scale

    # Per-node work is torch (one matmul gives every node's residual under every label, two
    # indicator products the normal equations of all labels); the per-label 4x4 algebra is numpy, where
    # an op on a (L, 4, 4) array costs ~1 us instead of torch's ~7 us dispatch.
    def evaluate(pp: np.ndarray):
        r = (Jq @ _t(_q_of(pp)).T).gather(1, lab_col)[:, 0] - N
        wr, cost = _robust(r * inv_scale, loss, truncation)
        total = (onehot @ (W0 * cost)).numpy()
        if affine_prior_px > 0:
            q = _q_of(pp)
            total = total + kappa_cost * (q[:, 0] ** 2 + q[:, 1] ** 2)
        return r, wr, total

    r, wr, cost = evaluate(p)
    mu = np.full(n_labels, float(damping))
    for _ in range(iterations):
        w = W0 * wr
        # One accumulation for H_q (16 entries) and g_q (4) of every label.
        acc20 = torch.cat([(onehot * w) @ JJ, (onehot * (w * r)) @ Jq], dim=1).numpy()
        Hq, gq = acc20[:, :16].reshape(-1, 4, 4), acc20[:, 16:, None]
        if affine_prior_px > 0:
            q = _q_of(p)
            Hq[:, 0, 0] += kappa
            Hq[:, 1, 1] += kappa
            gq[:, 0, 0] += kappa * q[:, 0]
            gq[:, 1, 0] += kappa * q[:, 1]
        # The per-label 4x4 algebra in one compiled pass (~15 numpy calls before).
        step = lm_steps(p, np.ascontiguousarray(Hq), np.ascontiguousarray(gq[:, :, 0]), mu)
        trial = p + step
        r_t, wr_t, cost_t = evaluate(trial)
        acc = cost_t < cost
        p = np.where(acc[:, None], trial, p)
        if acc.all():  # the common cases need no per-node selection
            r, wr = r_t, wr_t
        elif acc.any():
            node_acc = torch.from_numpy(acc)[lab]
            r = torch.where(node_acc, r_t, r)
            wr = torch.where(node_acc, wr_t, wr)
        cost = np.where(acc, cost_t, cost)
        mu = np.clip(np.where(acc, mu * 0.3, mu * 10.0), 1e-9, 1e9)
        if float((np.abs(step) / (np.abs(p) + 1.0)).max()) < step_tol:
            break
    return p
