"""The segmentation energy: exact values by hand and by its definition, and clear errors."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evseg.segmentation.energy import energy, label_cost_energy, potts_energy


def test_energy_by_hand():
    # Node 0 takes label 0 (data 0), node 1 label 1 (data 1); their edge is cut (0.5); both
    # labels are in use (10 + 4).
    data = np.array([[0.0, 2.0], [3.0, 1.0]])
    assert energy(np.array([0, 1]), data, np.array([[0, 1]]), np.array([0.5]), np.array([10.0, 4.0])) == 15.5
    # One label for both: data 0 + 3, no cut, one label cost.
    assert energy(np.array([0, 0]), data, np.array([[0, 1]]), np.array([0.5]), np.array([10.0, 4.0])) == 13.0


@pytest.mark.parametrize("seed", range(5))
def test_energy_is_data_plus_potts_plus_label_costs(seed):
    rng = np.random.default_rng(seed)
    m, n_labels, n_edges = 200, 6, 500
    data = rng.uniform(0, 9, (m, n_labels))
    labels = rng.integers(0, n_labels - 1, m)  # the last label unused
    edges = rng.integers(0, m, (n_edges, 2))
    w = rng.uniform(0, 2, n_edges)
    h = rng.uniform(0, 80, n_labels)
    expected = data[np.arange(m), labels].sum() + potts_energy(labels, edges, w) + label_cost_energy(labels, h)
    # Summation order differs from numpy's pairwise sums: equal to round-off.
    assert energy(labels, data, edges, w, h) == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize("bad, message", [
    (dict(labels=np.array([0, 2])), "labels must lie in \\[0, 2\\)"),
    (dict(labels=np.array([-1, 0])), "got labels in \\[-1, 0\\]"),
    (dict(edges=np.array([[0, 5]])), "edge ends in \\[0, 5\\]"),
    (dict(edge_w=np.array([0.5, 1.0])), "1 edges, 2 edge weights"),
    (dict(label_costs=np.array([1.0])), "data \\(2, 2\\)"),
    (dict(data=np.array([[0.0, np.nan], [3.0, 1.0]]), labels=np.array([1, 1])), "NaN in the data costs"),
])
def test_energy_rejects_inconsistent_input(bad, message):
    args = dict(labels=np.array([0, 1]), data=np.array([[0.0, 2.0], [3.0, 1.0]]), edges=np.array([[0, 1]]),
                edge_w=np.array([0.5]), label_costs=np.array([10.0, 4.0]))
    args.update(bad)
    with pytest.raises(ValueError, match=message):
        energy(**args)


def test_contrast_weights():
    from evseg.segmentation.energy import contrast_weights

    tau2 = 9.0
    # Nodes 0, 1 fit label 0; node 2 fits label 1; node 3 fits nothing (an outlier: tau^2 under both).
    data = np.array([[0.0, tau2], [0.5, tau2], [tau2, 0.0], [tau2, tau2]])
    edges = np.array([[0, 1], [1, 2], [2, 3], [0, 3]])
    w = contrast_weights(data, edges, min_weight=0.5)
    assert w[0] == 1.0  # one surface: c = 0.5 - 0.5 = 0 below the onset
    assert w[1] == 0.5  # an outline: c = 9 - 0.5, exp(-(8.5 - 2) / 3) = 0.11 -> the floor
    assert w[2] == 1.0 and w[3] == 1.0  # the outlier has no contrast with anything
    # c = 4 (two sigma^2 past the onset): exp(-2 / 3)
    mid = contrast_weights(np.array([[0.0, 4.0], [4.0, 0.0]]), np.array([[0, 1]]), min_weight=0.1)
    assert mid[0] == pytest.approx(np.exp(-2.0 / 3.0))
    np.testing.assert_array_equal(contrast_weights(data, edges, 0.5, strength=0.0), np.ones(4))
    assert contrast_weights(data, edges, 0.5, strength=0.5)[1] == 0.75


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 100_000), sigma=st.floats(0.5, 50.0), tau=st.floats(1.0, 5.0))
def test_data_costs_with_angular_uncertainty_match_their_formula(seed, sigma, tau):
    """The compiled cost (data_costs with node_scale, node_angle and confidence) equals the
    documented formula evaluated in numpy: c_k * min(r^2 / s^2 + log(s^2 / s0^2), tau^2) with
    s0 = sigma * node_scale_k, s^2 = s0^2 + (a_k * n_hat_perp . u_l(x_k))^2; nodes with a_k = 0
    get exactly c_k * min((r / s0)^2, tau^2)."""
    from evseg.segmentation.energy import data_costs
    from evseg.segmentation.motion_model import flow_field

    rng = np.random.default_rng(seed)
    m, n_labels = 30, 4
    x, y = rng.uniform(-150, 150, m), rng.uniform(-100, 100, m)
    nx, ny = rng.normal(0, 80, m), rng.normal(0, 80, m)
    models = np.column_stack([rng.uniform(0.8, 1.2, n_labels), rng.uniform(-0.3, 0.3, n_labels),
                              rng.normal(0, 100, n_labels), rng.normal(0, 100, n_labels)])
    scale = rng.uniform(1, 3, m)
    angle = np.where(rng.random(m) < 0.3, 0.0, rng.uniform(0, 0.6, m))
    conf = rng.uniform(0.2, 1, m)
    got = data_costs(models, x, y, nx, ny, sigma, tau, conf, scale, angle)

    norm = np.hypot(nx, ny)[:, None]
    hx, hy = nx[:, None] / norm, ny[:, None] / norm
    ux, uy = flow_field(models, x, y)  # (M, L) px/s
    r = hx * ux + hy * uy - norm
    s0 = sigma * scale[:, None]
    s2 = s0**2 + (angle[:, None] * (hx * uy - hy * ux)) ** 2
    want = conf[:, None] * np.minimum(r**2 / s2 + np.log(s2 / s0**2), tau**2)
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)
    plain = angle == 0
    exact = conf[plain, None] * np.minimum((r[plain] / s0[plain]) ** 2, tau**2)
    np.testing.assert_allclose(got[plain], exact, rtol=1e-12)
