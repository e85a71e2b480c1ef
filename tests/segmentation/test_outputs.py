"""Label propagation: the bucket-grid nearest-node search against brute force."""

import numpy as np
import pytest

from evseg.segmentation.outputs import nearest_node_labels


def _brute_force(node_x, node_y, labels, x, y, limit):
    d2 = (x[:, None] - node_x[None, :]) ** 2 + (y[:, None] - node_y[None, :]) ** 2
    k = np.argmin(d2, axis=1)  # first minimum: ties to the lowest node index
    near = d2[np.arange(len(x)), k] <= limit * limit
    return np.where(near, labels[k], -1)


@pytest.mark.parametrize("seed", range(6))
def test_nearest_node_labels_equals_brute_force(seed):
    rng = np.random.default_rng(seed)
    m = int(rng.integers(1, 400))
    # Half the nodes on the pixel lattice (many exact ties), half anywhere.
    node_x = np.concatenate([rng.integers(0, 60, m // 2), rng.uniform(-5, 65, m - m // 2)]).astype(float)
    node_y = np.concatenate([rng.integers(0, 40, m // 2), rng.uniform(-5, 45, m - m // 2)]).astype(float)
    labels = np.arange(m)  # a distinct label per node: the chosen node itself is checked
    x = np.concatenate([rng.integers(-20, 80, 500), rng.uniform(-300, 300, 100)]).astype(float)
    y = np.concatenate([rng.integers(-20, 60, 500), rng.uniform(-300, 300, 100)]).astype(float)
    limit = float(rng.uniform(0.5, 25.0))
    got = nearest_node_labels(node_x, node_y, labels, x, y, limit)
    np.testing.assert_array_equal(got, _brute_force(node_x, node_y, labels, x, y, limit))


@pytest.mark.parametrize("limit", [np.inf, 1e300, 1e6])
def test_an_unlimited_search_radius_labels_every_point(limit):
    # max_propagation_px = inf is a valid setting (no limit); it used to size the search grid
    # with inf and label every event -1.
    rng = np.random.default_rng(3)
    node_x, node_y = rng.uniform(0, 60, 50), rng.uniform(0, 40, 50)
    labels = np.arange(50)
    x, y = rng.uniform(-100, 160, 300), rng.uniform(-100, 140, 300)
    got = nearest_node_labels(node_x, node_y, labels, x, y, limit)
    np.testing.assert_array_equal(got, _brute_force(node_x, node_y, labels, x, y, np.inf))
    assert (got >= 0).all()


def test_nearest_node_labels_empty_inputs():
    assert nearest_node_labels(np.array([]), np.array([]), np.array([], dtype=int),
                               np.array([1.0]), np.array([1.0]), 5.0).tolist() == [-1]
    assert nearest_node_labels(np.array([1.0]), np.array([1.0]), np.array([3]),
                               np.array([]), np.array([]), 5.0).shape == (0,)


def test_same_label_components_match_scipy_numbering():
    """The compiled union-find gives scipy's components and numbering (by first node), which
    the order of equal-sized objects depends on."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from evseg.segmentation._kernels import same_label_components

    rng = np.random.default_rng(1)
    for _ in range(200):
        m = int(rng.integers(1, 300))
        e = rng.integers(0, m, (int(rng.integers(0, 3 * m)), 2))
        e = np.ascontiguousarray(e[e[:, 0] != e[:, 1]].reshape(-1, 2).astype(np.int64))
        lab = rng.integers(-1, 4, m)
        keep = e[lab[e[:, 0]] == lab[e[:, 1]]]
        adj = coo_matrix((np.ones(len(keep)), (keep[:, 0], keep[:, 1])), shape=(m, m))
        np.testing.assert_array_equal(same_label_components(lab, e), connected_components(adj, directed=False)[1])


def test_isolated_nodes_stay_in_the_label_but_out_of_the_region():
    """isolated_out: a node tied to an object only by a long edge (noise far from it) keeps the
    object's label but not its region, so the box is the object's."""
    from evseg.segmentation.outputs import split_objects

    # object: a 3x3 block of nodes 3 px apart at x, y in [20, 26]; one far node at (90, 90)
    gx, gy = np.meshgrid([20.0, 23.0, 26.0], [20.0, 23.0, 26.0])
    x = np.concatenate([[0.0, 100.0, 0.0], gx.ravel(), [90.0]])
    y = np.concatenate([[0.0, 0.0, 100.0], gy.ravel(), [90.0]])
    labels = np.array([0, 0, 0] + [1] * 9 + [1])
    from evseg.segmentation.preprocessing import delaunay_edges

    edges = delaunay_edges(x, y)
    models = np.array([[1.0, 0, 0, 0], [1.0, 0, 50.0, 0]])
    for isolated_out, expected in ((False, set(range(3, 13))), (True, set(range(3, 12)))):
        new, _, regions = split_objects(labels, edges, models, 6, x, y, 12.0, 0, isolated_out=isolated_out)
        assert new[12] == 1 and set(regions[1].tolist()) == expected
