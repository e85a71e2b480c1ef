"""Batched affine fitting: exact recovery from noise-free normal flow, degenerate labels."""

import numpy as np
import pytest

from evseg.segmentation.fitting import fit_linear, fit_lm
from evseg.segmentation.motion_model import normal_flow_of, normal_flow_residuals

TRUE = np.array([[1.2, 0.3, 120.0, -40.0], [0.8, -0.2, -300.0, 50.0], [1.0, 0.0, 10.0, 200.0]])


def make_flow(models, n_per=60, seed=0):
    rng = np.random.default_rng(seed)
    lab = np.repeat(np.arange(len(models)), n_per)
    x = rng.uniform(-170, 170, len(lab))
    y = rng.uniform(-130, 130, len(lab))
    ang = rng.uniform(0, 2 * np.pi, len(lab))
    nx, ny = normal_flow_of(models, lab, x, y, np.cos(ang), np.sin(ang))
    return x, y, nx, ny, lab


def test_linear_recovers_models_exactly():
    x, y, nx, ny, lab = make_flow(TRUE)
    got = fit_linear(x, y, nx, ny, lab, 3)
    # Noise-free data and a tiny ridge: agreement to ~1e-6 of the parameter scale.
    np.testing.assert_allclose(got, TRUE, rtol=1e-6, atol=1e-5)


@pytest.mark.parametrize("loss", ["none", "huber", "cauchy", "truncated"])
def test_lm_recovers_models_from_translation_start(loss):
    x, y, nx, ny, lab = make_flow(TRUE, seed=1)
    start = np.array([[1.0, 0.0, 100.0, 0.0], [1.0, 0.0, -250.0, 0.0], [1.0, 0.0, 0.0, 150.0]])
    got = fit_lm(x, y, nx, ny, lab, start, loss=loss, loss_scale_px_s=50.0, truncation=100.0,
                 iterations=30)
    # The residual is linear in (rho cos, rho sin, t): LM converges to the exact optimum.
    np.testing.assert_allclose(got, TRUE, rtol=1e-6, atol=1e-4)


def test_lm_robust_loss_ignores_outliers():
    x, y, nx, ny, lab = make_flow(TRUE[:1], n_per=200, seed=2)
    rng = np.random.default_rng(3)
    bad = rng.choice(200, 60, replace=False)
    nx, ny = nx.copy(), ny.copy()
    nx[bad] = rng.uniform(-400, 400, 60)
    ny[bad] = rng.uniform(-400, 400, 60)
    start = fit_linear(x, y, nx, ny, lab, 1)
    plain = fit_lm(x, y, nx, ny, lab, start, loss="none", iterations=20)
    robust = fit_lm(x, y, nx, ny, lab, start, loss="cauchy", loss_scale_px_s=5.0, iterations=40)
    err_plain = np.abs(plain[0, 2:] - TRUE[0, 2:]).max()
    err_robust = np.abs(robust[0, 2:] - TRUE[0, 2:]).max()
    # 30 % outliers: least squares is off by tens of px/s, Cauchy IRLS within 1 px/s.
    assert err_plain > 10.0
    assert err_robust < 1.0


def test_degenerate_labels_are_finite_and_harmless():
    x, y, nx, ny, lab = make_flow(TRUE[:1], n_per=50)
    # label 1: two nodes only; label 2: all gradients parallel (aperture problem); label 3: empty
    x2 = np.concatenate([x, [10.0, 20.0], np.linspace(-50, 50, 20)])
    y2 = np.concatenate([y, [5.0, -5.0], np.linspace(-30, 30, 20)])
    nx2 = np.concatenate([nx, [100.0, 90.0], np.full(20, 80.0)])
    ny2 = np.concatenate([ny, [0.0, 10.0], np.zeros(20)])
    lab2 = np.concatenate([lab, [1, 1], np.full(20, 2)])
    lin = fit_linear(x2, y2, nx2, ny2, lab2, 4)
    assert np.all(np.isfinite(lin))
    np.testing.assert_allclose(lin[0], TRUE[0], rtol=1e-6, atol=1e-5)  # unaffected by the others
    np.testing.assert_allclose(lin[3], [1.0, 0.0, 0.0, 0.0], atol=1e-12)  # empty: identity
    lm = fit_lm(x2, y2, nx2, ny2, lab2, np.tile([1.0, 0.0, 50.0, 0.0], (4, 1)), loss="none")
    assert np.all(np.isfinite(lm))
    np.testing.assert_allclose(lm[3], [1.0, 0.0, 50.0, 0.0])  # no nodes: start model kept
    # Parallel flows: the model is underdetermined but must still explain the data.
    rows = lab2 == 2
    for models in (lin, lm):
        r = normal_flow_residuals(models[2:3], x2[rows], y2[rows], nx2[rows], ny2[rows])
        np.testing.assert_allclose(r, 0.0, atol=1e-3)  # px/s; ridge bias is ~1e-9 relative


def test_inputs_not_modified():
    x, y, nx, ny, lab = make_flow(TRUE)
    copies = [a.copy() for a in (x, y, nx, ny, lab)]
    start = np.tile([1.0, 0.0, 0.0, 0.0], (3, 1))
    start_copy = start.copy()
    fit_lm(x, y, nx, ny, lab, start)
    fit_linear(x, y, nx, ny, lab, 3)
    for a, b in zip((x, y, nx, ny, lab), copies):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(start, start_copy)


def test_affine_prior_keeps_a_small_noisy_object_translational_and_spares_a_large_one():
    rng = np.random.default_rng(7)
    # A 30 px object 90 px from the origin translating at 345 px/s, flows with 15 % magnitude
    # noise (a learned estimate); and a 300 px wide background that zooms and turns.
    small = np.array([[1.0, 0.0, 345.0, -20.0]])
    x = rng.uniform(-105, -75, 30)
    y = rng.uniform(15, 45, 30)
    ang = rng.uniform(0, 2 * np.pi, 30)
    nx, ny = normal_flow_of(small, np.zeros(30, int), x, y, np.cos(ang), np.sin(ang))
    noise = rng.normal(1.0, 0.15, 30)
    nx, ny = nx * noise, ny * noise
    lab = np.zeros(30, int)
    free = fit_lm(x, y, nx, ny, lab, small, loss="none", iterations=20)
    prior = fit_lm(x, y, nx, ny, lab, small, loss="none", iterations=20, affine_prior_px=10.0)
    q_free = np.hypot(free[0, 0] * np.cos(free[0, 1]) - 1, free[0, 0] * np.sin(free[0, 1]))
    q_prior = np.hypot(prior[0, 0] * np.cos(prior[0, 1]) - 1, prior[0, 0] * np.sin(prior[0, 1]))
    # The noise buys a zoom/spin of 0.20 /s without the prior (60 px/s across the object's
    # 300 px lever arm to the origin); with r0 = 10 px it shrinks to 0.08 /s.
    assert q_free > 0.15
    assert q_prior < q_free / 2

    bx, by, bnx, bny, blab = make_flow(TRUE[:1], n_per=400, seed=8)
    plain = fit_lm(bx, by, bnx, bny, blab, np.array([[1.0, 0.0, 100.0, 0.0]]), loss="none", iterations=30)
    with_prior = fit_lm(bx, by, bnx, bny, blab, np.array([[1.0, 0.0, 100.0, 0.0]]), loss="none",
                        iterations=30, affine_prior_px=10.0)
    np.testing.assert_allclose(plain, TRUE[:1], rtol=1e-6, atol=1e-4)
    # Spread over +-170 px, the background keeps its rates within a few percent of the truth.
    np.testing.assert_allclose(with_prior[0, :2], TRUE[0, :2], rtol=0.05)


def test_lm_steps_solve_the_damped_normal_equations_in_model_parameters():
    # The compiled step against the formula in numpy: T = dq/dp, H = T^T Hq T, g = T^T gq,
    # (H + diag(mu H_ii + 1e-12 (mean H_ii + 1))) step = -g. Random well-conditioned systems:
    # the two solves agree to round-off (1e-9 relative).
    from evseg.segmentation._kernels import lm_steps

    rng = np.random.default_rng(0)
    n = 6
    p = np.column_stack([rng.uniform(0.5, 2.0, n), rng.uniform(-np.pi, np.pi, n), rng.normal(0, 50, (n, 2))])
    a = rng.normal(size=(n, 8, 4))
    hq = a.transpose(0, 2, 1) @ a
    gq = rng.normal(size=(n, 4))
    mu = rng.uniform(1e-4, 1.0, n)
    c, s = np.cos(p[:, 1]), np.sin(p[:, 1])
    t = np.zeros((n, 4, 4))
    t[:, 0, 0], t[:, 0, 1], t[:, 1, 0], t[:, 1, 1] = c, -p[:, 0] * s, s, p[:, 0] * c
    t[:, 2, 2] = t[:, 3, 3] = 1.0
    h = t.transpose(0, 2, 1) @ hq @ t
    g = (t.transpose(0, 2, 1) @ gq[:, :, None])[:, :, 0]
    d = np.diagonal(h, axis1=1, axis2=2)
    damp = mu[:, None] * d + 1e-12 * (d.mean(axis=1, keepdims=True) + 1.0)
    expected = -np.linalg.solve(h + damp[:, :, None] * np.eye(4), g[:, :, None])[:, :, 0]
    np.testing.assert_allclose(lm_steps(p, hq, gq, mu), expected, rtol=1e-9, atol=1e-12)
    # A label without nodes (Hq = 0, gq = 0) does not move.
    assert np.all(lm_steps(p[:1], np.zeros((1, 4, 4)), np.zeros((1, 4)), mu[:1]) == 0.0)


def test_fit_lm_rejects_arrays_of_different_lengths():
    x = np.zeros(5)
    with pytest.raises(ValueError, match="fit_lm: 5 labels but lengths .*'nx': 4"):
        fit_lm(x, x, np.ones(4), x, np.zeros(5, dtype=int), np.array([[1.0, 0.0, 0.0, 0.0]]))


def test_lm_setup_rows_are_residual_jacobian_rows():
    # The compiled set-up of fit_lm repeats motion_model.residual_jacobian's formula: the rows,
    # their outer products and |n| must stay bit-identical to it, for the kept labels in order.
    from evseg.segmentation._kernels import lm_setup
    from evseg.segmentation.motion_model import residual_jacobian

    rng = np.random.default_rng(3)
    m = 50
    x, y, nx, ny = rng.normal(0, 100, m), rng.normal(0, 80, m), rng.normal(0, 50, m), rng.normal(0, 50, m)
    labels = rng.integers(-1, 4, m)  # -1 and 3 are outside [0, 3): left out
    w = rng.uniform(0.1, 2, m)
    lab, jq, jj, norm, w0, onehot = lm_setup(labels, 3, x, y, nx, ny, w)
    keep = (labels >= 0) & (labels < 3)
    j_ref, n_ref = residual_jacobian(x[keep], y[keep], nx[keep], ny[keep])
    assert np.array_equal(lab, labels[keep]) and np.array_equal(w0, w[keep])
    assert np.array_equal(jq, j_ref) and np.array_equal(norm, n_ref)
    assert np.array_equal(jj, (j_ref[:, :, None] * j_ref[:, None, :]).reshape(-1, 16))
    assert np.array_equal(onehot, (lab[None, :] == np.arange(3)[:, None]).astype(float))
