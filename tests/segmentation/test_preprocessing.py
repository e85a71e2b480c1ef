"""Node selection (one flow per cell) and the Delaunay graph, including degenerate inputs."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evseg.segmentation.preprocessing import build_node_graph, delaunay_edges, select_nodes


def test_one_node_per_cell_latest_wins_without_uncertainty():
    x = np.array([0.5, 1.5, 2.0, 5.0, 5.5])
    y = np.array([0.5, 1.0, 2.5, 0.0, 0.2])
    t = np.array([10, 30, 20, 5, 5])
    n = np.full(5, 10.0)
    idx = select_nodes(x, y, t, n, n, None, cell_px=4.0)
    # cell (0,0) holds flows 0,1,2 -> latest t=30 is flow 1; cell (1,0) holds 3,4 (same t) -> larger index
    np.testing.assert_array_equal(idx, [1, 4])


def test_most_certain_flow_wins_then_latest():
    x = np.array([0.0, 1.0, 2.0])
    y = np.zeros(3)
    t = np.array([1, 2, 3])
    n = np.full(3, 10.0)
    idx = select_nodes(x, y, t, n, n, np.array([0.1, 0.05, 0.2]), cell_px=4.0)
    np.testing.assert_array_equal(idx, [1])


def test_invalid_slow_uncertain_and_old_flows_are_dropped():
    x = np.arange(6) * 10.0
    y = np.zeros(6)
    t = np.array([0, 100, 200, 300, 400, 500])
    nx = np.array([np.nan, 0.5, 10.0, 10.0, 10.0, 10.0])
    ny = np.zeros(6)
    unc = np.array([0.0, 0.0, 0.0, 0.5, 0.0, 0.0])
    idx = select_nodes(x, y, t, nx, ny, unc, cell_px=4.0, min_flow_px_s=1.0, max_uncertainty=0.3,
                       node_window_us=250)
    np.testing.assert_array_equal(idx, [4, 5])  # 0 NaN, 1 slow, 3 uncertain, 2 older than 250 us


def test_cell_zero_merges_exact_duplicates_only():
    x = np.array([1.0, 1.0, 1.25])
    y = np.array([2.0, 2.0, 2.0])
    idx = select_nodes(x, y, np.array([1, 2, 3]), np.ones(3) * 5, np.ones(3), None, cell_px=0.0)
    np.testing.assert_array_equal(idx, [1, 2])


def test_delaunay_degenerate_cases():
    assert delaunay_edges(np.array([]), np.array([])).shape == (0, 2)
    assert delaunay_edges(np.array([1.0]), np.array([1.0])).shape == (0, 2)
    np.testing.assert_array_equal(delaunay_edges(np.array([0.0, 1.0]), np.array([0.0, 1.0])), [[0, 1]])
    # collinear: a chain in order along the line
    e = delaunay_edges(np.array([0.0, 2.0, 1.0, 3.0]), np.array([0.0, 2.0, 1.0, 3.0]))
    np.testing.assert_array_equal(e, [[0, 2], [1, 2], [1, 3]])
    # a triangle
    np.testing.assert_array_equal(delaunay_edges(np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0])),
                                  [[0, 1], [0, 2], [1, 2]])


def test_square_with_centre():
    x = np.array([0.0, 2.0, 2.0, 0.0, 1.0])
    y = np.array([0.0, 0.0, 2.0, 2.0, 1.0])
    e = delaunay_edges(x, y)
    # 4 sides + 4 spokes to the centre
    assert len(e) == 8
    assert {tuple(r) for r in e} >= {(0, 4), (1, 4), (2, 4), (3, 4)}


@settings(max_examples=60, deadline=None)
@given(n=st.integers(0, 40), seed=st.integers(0, 1000), grid=st.booleans())
def test_graph_edges_are_unique_ordered_and_connected(n, seed, grid):
    rng = np.random.default_rng(seed)
    if grid:  # integer pixels with many duplicates and collinear runs
        x = rng.integers(0, 5, n).astype(float)
        y = rng.integers(0, 3, n).astype(float)
    else:
        x, y = rng.uniform(0, 50, n), rng.uniform(0, 50, n)
    g = build_node_graph(x, y, np.arange(n), np.full(n, 3.0), np.full(n, -4.0), cell_px=1.0)
    m = len(g)
    e = g.edges
    assert e.dtype == np.int64 and e.shape[1] == 2
    assert np.all(e[:, 0] < e[:, 1]) and np.all(e[:, 1] < max(m, 1))
    assert len(np.unique(e, axis=0)) == len(e)
    pos = np.column_stack([g.x, g.y])
    assert len(np.unique(pos, axis=0)) == m  # no duplicate node positions
    if m >= 2:  # a triangulation (or chain) of distinct points is connected
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components

        ncomp, _ = connected_components(coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(m, m)))
        assert ncomp == 1
    np.testing.assert_allclose(g.edge_length, np.hypot(*(pos[e[:, 0]] - pos[e[:, 1]]).T))


@settings(max_examples=40, deadline=None)
@given(n=st.integers(3, 300), seed=st.integers(0, 1000))
def test_delaunay_edges_are_the_sides_of_qhulls_triangles(n, seed):
    """The compiled edge extraction (each edge from one triangle) gives exactly the set of
    triangle sides, sorted, as deduplicating all sides would."""
    from scipy.spatial import Delaunay

    rng = np.random.default_rng(seed)
    x, y = rng.uniform(0, 100, n), rng.uniform(0, 100, n)
    e = delaunay_edges(x, y)
    h = (np.arange(n) * 0.6180339887498949) % 1.0  # the same tie-breaking offset
    tri = Delaunay(np.column_stack([x, y]) + np.column_stack([h - 0.5, (h * 7.3) % 1.0 - 0.5]) * 1e-3)
    s = tri.simplices
    sides = np.sort(np.concatenate([s[:, [0, 1]], s[:, [1, 2]], s[:, [0, 2]]]), axis=1)
    np.testing.assert_array_equal(e, np.unique(sides, axis=0))


def test_confirmed_rule_passes_over_a_stray_latest_flow():
    # One 4 px cell, flows in time order: three along (10, 0) px/s, the latest a stray one.
    x = np.array([0.5, 1.0, 1.5, 2.0])
    y = np.zeros(4)
    t = np.array([1, 2, 3, 4])
    nx = np.array([10.0, 10.0, 11.0, -80.0])
    ny = np.array([0.0, 0.0, 0.0, 50.0])
    assert select_nodes(x, y, t, nx, ny, None, cell_px=4.0, rule="preferred").tolist() == [3]
    # The stray flow is 90+ px/s from every other (tolerance 0.25 x 94 + 1 = 24.6 px/s); flow 2
    # (11 px/s) is 1 px/s from flows 0 and 1 (tolerance 3.75): the latest confirmed one.
    assert select_nodes(x, y, t, nx, ny, None, cell_px=4.0, rule="confirmed").tolist() == [2]
    # No flow confirmed: the preferred (latest) one.
    lone = np.array([10.0, 40.0, 90.0, -80.0])
    assert select_nodes(x, y, t, lone, ny, None, cell_px=4.0, rule="confirmed").tolist() == [3]
    # With an uncertainty per flow the most certain flow wins, stray or not: the estimator's
    # certainty decides before any vote.
    unc = np.array([0.3, 0.2, 0.1, 0.05])
    assert select_nodes(x, y, t, nx, ny, unc, cell_px=4.0, rule="confirmed").tolist() == [3]
    with pytest.raises(ValueError, match="rule"):
        select_nodes(x, y, t, nx, ny, None, cell_px=4.0, rule="median")


def test_confirmed_rule_keeps_few_outliers_as_nodes():
    """30 % of the flows replaced by random vectors (uniform in +-300 px/s): with 'preferred'
    about 30 % of the nodes are outliers. With 'confirmed' an outlier becomes a node only when
    another outlier of its cell happens to lie within its tolerance (~5 % of the square for
    |n| ~ 300 px/s) and it is later than every confirmed inlier, or when the cell has fewer
    than two inliers: a few % of the cells (8 flows each); the bound 8 % leaves room."""
    rng = np.random.default_rng(0)
    n = 8 * 40 * 40  # 8 flows in each 4 px cell of a 160 px square
    x = rng.uniform(0, 160, n)
    y = rng.uniform(0, 160, n)
    t = rng.integers(0, 10_000, n)
    nx = np.full(n, 100.0)
    ny = np.full(n, 20.0)
    bad = rng.random(n) < 0.3
    nx[bad] = rng.uniform(-300, 300, bad.sum())
    ny[bad] = rng.uniform(-300, 300, bad.sum())
    share = {rule: bad[select_nodes(x, y, t, nx, ny, None, 4.0, rule=rule)].mean()
             for rule in ("preferred", "confirmed")}
    assert 0.25 < share["preferred"] < 0.35
    assert share["confirmed"] < 0.08


def _occupied(x, y, cell):
    return len(set(zip(np.floor(x / cell).astype(int).tolist(), np.floor(y / cell).astype(int).tolist())))


def test_node_budget_grows_the_cell_to_the_smallest_sufficient_step():
    from evseg.segmentation.preprocessing import CELL_GROWTH, node_cell_px

    rng = np.random.default_rng(3)
    x, y = rng.uniform(0, 400, 20_000), rng.uniform(0, 300, 20_000)
    full = _occupied(x, y, 3.0)
    assert full > 10_000
    # no budget, a budget the window fits, cell 0: unchanged
    assert node_cell_px(x, y, 3.0, None) == 3.0
    assert node_cell_px(x, y, 3.0, full) == 3.0
    assert node_cell_px(x, y, 0.0, 10) == 0.0
    for budget in (8_000, 3_000, 500):
        c = node_cell_px(x, y, 3.0, budget)
        k = round(np.log(c / 3.0) / np.log(CELL_GROWTH))
        assert k >= 1 and c == pytest.approx(3.0 * CELL_GROWTH**k)
        assert _occupied(x, y, c) <= budget < _occupied(x, y, c / CELL_GROWTH)


def test_build_node_graph_keeps_the_budget_and_reports_its_cell():
    from evseg.segmentation.preprocessing import node_cell_px

    rng = np.random.default_rng(4)
    n = 30_000
    x, y = rng.uniform(0, 640, n), rng.uniform(0, 480, n)
    t, nx, ny = np.arange(n), rng.normal(50, 5, n), rng.normal(0, 5, n)
    free = build_node_graph(x, y, t, nx, ny, cell_px=3.0)
    assert free.cell_px == 3.0 and len(free) > 15_000
    g = build_node_graph(x, y, t, nx, ny, cell_px=3.0, max_nodes=5_000)
    assert len(g) <= 5_000 and g.cell_px == node_cell_px(x, y, 3.0, 5_000) > 3.0
    # the nodes are exactly those of the grown cell
    np.testing.assert_array_equal(g.index, select_nodes(x, y, t, nx, ny, None, g.cell_px))
    # a budget the window fits changes nothing
    same = build_node_graph(x, y, t, nx, ny, cell_px=3.0, max_nodes=len(free))
    np.testing.assert_array_equal(same.index, free.index)
    np.testing.assert_array_equal(same.edges, free.edges)


def test_cells_with_too_few_events_give_no_node():
    """min_cell_events: a cell's support counts all the window's events (event_xy); a lone
    event in its cell (sensor noise under a still camera) gives no node and no graph edge."""
    x = np.array([1.0, 10.0, 20.0])
    y = np.zeros(3)
    t = np.array([0, 1, 2])
    nx, ny = np.full(3, 50.0), np.zeros(3)
    ex = np.array([1.0, 1.5, 2.0, 10.0, 20.0, 20.5])  # cells 0 (3 events), 3 (1), 6 (2)
    ey = np.zeros(len(ex))
    g = build_node_graph(x, y, t, nx, ny, cell_px=3.0, event_xy=(ex, ey))
    assert g.index.tolist() == [0, 1, 2] and g.support.tolist() == [3.0, 1.0, 2.0]
    g = build_node_graph(x, y, t, nx, ny, cell_px=3.0, event_xy=(ex, ey), min_cell_events=2)
    assert g.index.tolist() == [0, 2] and g.support.tolist() == [3.0, 2.0]
    assert g.edges.tolist() == [[0, 1]]
